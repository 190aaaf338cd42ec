"""A rig file's ``[fit]`` table: what the rigid-skeleton fit may be told per marker
and per bone (reference: ``daemon/body/rigs/RIGS.md``, "``[fit]``").

```toml
[fit.markers.LKNE]
segment = "lfemur"   # the bone the marker rides (default: from the bones using it)
weight = 1.0         # residual weight (0 = ignored by the fit)
[fit.bones.ltibia]
dof = "hinge"        # "ball" (default), "hinge", "hinge_twist", "swing" or "fixed"
axis = "x"           # hinge axis: "x", "y", "z" or [x, y, z]
axis_in = "bone"     # the axes it is in: the bone's (default) or its "parent"'s
axis_from_bend_deg = 0  # bent at least this much in the calibration pose: the axis
                        # there perpendicular to the bone and its parent instead
axis_markers = ["LIKNEE", "LEKNEE"]  # the axis is the line through these two markers
                        # of the parent bone at the calibration pose (signed like axis)
twist_to = "LUS"     # hinge_twist: the twist turns about the line from the bone's
                        # origin to this marker or point at the calibration pose
                        # (default: the bone's own +Y); swing: the twist it forbids
stiffness_mm = 0     # pull towards the calibration pose, mm of residual per radian
stiffness_free_plane = ["LHEE", "LTOE"]  # the pull spares the rotation about the
                        # normal of the plane through the joint and these two
                        # markers of the bone (default: it pulls every rotation)
```

``body.rig`` parses the table with :func:`parse_fit_table` into the rig's
:class:`FitOptions` (``Rig.fit``); ``body.fit_model`` builds the fit from it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from retargetd.daemon import rotations as rot
from retargetd.protocols.frames import F64Array

#: The keys of each table, in the order errors list them.
FIT_KEYS = ("markers", "bones")
MARKER_KEYS = ("segment", "weight")
BONE_KEYS = (
    "dof",
    "axis",
    "axis_in",
    "axis_from_bend_deg",
    "axis_markers",
    "twist_to",
    "stiffness_mm",
    "stiffness_free_plane",
)
#: ``stiffness_mm`` at most a hinge's stiffness (FitParams.kappa_hinge: 1 m/rad);
#: ``body.rig_model.RIG_RANGES`` lists the same range.
STIFFNESS_MAX_MM = 1000.0
STIFFNESS_WHY = "0 = none; at most a hinge's stiffness, past which the joint is frozen"
#: A marker's ``weight`` is a ratio of variances, the default marker's over this one's:
#: at most (10 mm / 1 mm)^2, a marker at the optical noise floor (< 1 mm, Merriaux et
#: al., Sensors 17(7):1591, 2017) against the low end of skin artefact on a limb
#: (10-30 mm, Leardini et al., Gait Posture 21(2):212-225, 2005). OpenSim's IK setups
#: use 10 (subject01_Setup_IK.xml); ``body.rig_model.RIG_RANGES`` lists the range.
WEIGHT_MAX = 100.0
WEIGHT_WHY = "0 = ignored; at most a noise-floor marker's against a skin-artefact one's"
#: A hinge's ``axis = [x, y, z]`` is a direction: each component of a unit vector lies
#: in [-1, 1] (the parser normalizes what rounding leaves).
AXIS_WHY = "a direction's components, as of a unit vector (normalized on reading)"
#: ``axis_from_bend_deg``: a bend short of straight, at most a right angle.
BEND_WHY = "0 = never; a joint's bend, at most a right angle"
DOFS = ("ball", "hinge", "hinge_twist", "swing", "fixed")
#: The joints with an axis (``axis``, ``axis_in``).
HINGES = ("hinge", "hinge_twist")
AXES_IN = ("bone", "parent")

_AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}


@dataclass(frozen=True, slots=True, kw_only=True)
class MarkerFitOptions:
    """Per-marker rig keys: the bone it rides (None: default) and its weight."""

    segment: str | None = None
    weight: float = 1.0


@dataclass(frozen=True, slots=True, kw_only=True)
class BoneFitOptions:
    """Per-bone rig keys: ``dof`` and the hinge axis (bone axes).

    ``dof``: "ball" (three rotations), "hinge" (one, about ``axis``), "hinge_twist"
    (two: a hinge about ``axis``, then the bone's own twist about its long axis +Y: an
    elbow with its forearm's pronation), "swing" (two: a ball joint without rotation
    about the bone's own long axis, +Y, or ``twist_to``'s line) or "fixed" (none:
    the bone keeps its calibration pose relative to its parent, a link of one rigid
    segment).
    ``axis_in``: the axes ``axis`` is given in, the bone's rest axes ("bone") or its
    parent's ("parent": an elbow's flexion axis is the upper arm's epicondyle axis,
    the upper arm's +X when its up reference is the lateral epicondyle).
    ``axis_from_bend_deg``: where the calibration pose bends the joint at least this
    much (the angle between the bone's +Y and its parent's), the hinge turns about
    the axis perpendicular to both there, signed like ``axis`` (0: never): a hinge's
    axis is the one its bend is about.
    ``axis_markers``: two markers riding the parent bone (a knee's femoral
    epicondyles, an elbow's humeral ones): the hinge turns about the line through
    them where the calibration placed them, signed like ``axis`` (empty: ``axis``).
    The line is the anatomical axis itself; a bone frame's axis is that line made
    perpendicular to a bone whose other end is an estimate (a hip or shoulder
    centre), so it carries the estimate's error into every flexion.
    ``twist_to``: a "hinge_twist" or a "swing" only: the twist turns (a swing: the
    rotation it forbids is the one) about the line from the bone's origin to this
    marker or derived point where the calibration placed it, not about the bone's
    own +Y (empty: +Y). A wrist flexes and deviates about axes perpendicular to the
    hand's long axis, the third metacarpal's, which lies along the forearm's at
    neutral (Wu et al. 2005, below): a hand bone that aims at a marker off that line
    (Plug-in Gait's FIN, over the second metacarpal, 20 deg off it) names a point on
    the forearm's axis carried past the wrist centre. A forearm pronates about the
    line from the radial head to the ulnar head (Hollister et al., Clin Orthop Relat Res
    298:272-276, 1994), which the ISB takes as the line from the elbow centre to the
    ulnar styloid (Wu et al., J Biomech 38(5):981-992, 2005); a forearm bone that
    aims at the wrist centre names its ulnar styloid (a marker on it, or a point the
    rig derives for it) here.
    ``stiffness_mm``: a pull of the joint towards its calibration pose, in mm of
    marker residual per radian (0: none), like OpenSim IK's coordinate tasks.
    ``stiffness_free_plane``: two markers riding the bone: the pull spares the
    rotation about the normal of the plane through the joint and the two markers
    where the calibration placed them (the one both markers see at their full
    lever: a foot's plantarflexion, with its heel and toe markers), and acts on the
    rotations about the axes in that plane (the foot's roll about its heel-toe line,
    which those markers cannot see, and its turn about the vertical, which only the
    toe marker sees) (empty: it pulls every rotation).
    """

    dof: str = "ball"
    axis: tuple[float, float, float] = (1.0, 0.0, 0.0)
    axis_in: str = "bone"
    axis_from_bend_deg: float = 0.0
    axis_markers: tuple[str, ...] = ()
    twist_to: str = ""
    stiffness_mm: float = 0.0
    stiffness_free_plane: tuple[str, ...] = ()


@dataclass(frozen=True, slots=True, kw_only=True)
class FitOptions:
    """The rig's ``[fit]`` table, parsed (empty: every default)."""

    markers: dict[str, MarkerFitOptions] = field(default_factory=dict)
    bones: dict[str, BoneFitOptions] = field(default_factory=dict)


def hinge_axes_in_bone(
    bones: Mapping[str, BoneFitOptions],
    bone_names: Sequence[str],
    rest_parent_from_bone_quat: F64Array,
) -> dict[str, F64Array]:
    """bone -> its hinge's unit ``axis`` in the bone's rest axes, for the hinges of
    ``bones`` (an ``axis_in = "parent"`` axis turned by the calibration's rest
    rotation: pfb = R_axis(t) rest_pfb = rest_pfb R_h(t))."""
    out = {}
    y = np.array([0.0, 1.0, 0.0])
    for name, bopt in bones.items():
        if bopt.dof in HINGES:
            q = rest_parent_from_bone_quat[bone_names.index(name)]
            axis = np.asarray(bopt.axis, dtype=np.float64)
            if bopt.axis_in == "parent":
                axis = rot.quat_rotate(rot.quat_conj(q), axis)
            if bopt.axis_from_bend_deg > 0.0:
                # in the bone's axes: its parent's +Y, then the bend's normal
                bend = np.cross(rot.quat_rotate(rot.quat_conj(q), y), y)
                sin = float(np.linalg.norm(bend))
                if sin >= math.sin(math.radians(bopt.axis_from_bend_deg)):
                    axis = bend if bend @ axis >= 0.0 else -bend
            out[name] = axis / np.linalg.norm(axis)
    return out


def _is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def parse_fit_table(
    table: Any,
    *,
    markers: Collection[str],
    bones: Collection[str],
    roots: Collection[str],
    fail: Callable[[str, str], Exception],
    points: Collection[str] = (),
) -> FitOptions:
    """Validate a rig's ``[fit]`` table against the rig's names.

    Args:
        table: the TOML value of ``fit``.
        markers, bones: the rig's marker and bone names; ``roots`` its root bones.
        points: its derived points' names (``twist_to`` may name one).
        fail: ``fail(key, message)`` -> the exception to raise (the rig parser's:
            one line naming the file and ``fit.KEY``).

    Raises:
        whatever ``fail`` returns, for the first bad key.
    """
    if not isinstance(table, dict):
        raise fail("fit", f"expected a table, got {type(table).__name__}")
    for key in table:
        if key not in FIT_KEYS:
            raise fail(
                f"fit.{key}", f"unknown key (expected one of: {', '.join(FIT_KEYS)})"
            )
    markers_t = table.get("markers", {})
    bones_t = table.get("bones", {})
    for key, value in (("markers", markers_t), ("bones", bones_t)):
        if not isinstance(value, dict):
            raise fail(f"fit.{key}", f"expected tables [fit.{key}.NAME]")
    out_m: dict[str, MarkerFitOptions] = {}
    for name, spec in markers_t.items():
        key = f"fit.markers.{name}"
        if name not in markers:
            raise fail(key, "unknown marker")
        if not isinstance(spec, dict):
            raise fail(key, "expected a table")
        for k in spec:
            if k not in MARKER_KEYS:
                raise fail(
                    f"{key}.{k}",
                    f"unknown key (expected one of: {', '.join(MARKER_KEYS)})",
                )
        seg = spec.get("segment")
        if seg is not None and seg not in bones:
            raise fail(f"{key}.segment", f"unknown bone {seg!r}")
        weight = spec.get("weight", 1.0)
        if not _is_number(weight):
            raise fail(f"{key}.weight", f"expected a number: {weight!r}")
        if not 0.0 <= weight <= WEIGHT_MAX:  # (NaN too)
            raise fail(
                f"{key}.weight",
                f"{weight!r} is out of range: allowed [0, {WEIGHT_MAX:g}] "
                f"({WEIGHT_WHY})",
            )
        out_m[name] = MarkerFitOptions(segment=seg, weight=float(weight))
    out_b: dict[str, BoneFitOptions] = {}
    for name, spec in bones_t.items():
        key = f"fit.bones.{name}"
        if name not in bones:
            raise fail(key, "unknown bone")
        if not isinstance(spec, dict):
            raise fail(key, "expected a table")
        for k in spec:
            if k not in BONE_KEYS:
                raise fail(
                    f"{key}.{k}",
                    f"unknown key (expected one of: {', '.join(BONE_KEYS)})",
                )
        dof = spec.get("dof", "ball")
        if dof not in DOFS:
            raise fail(
                f"{key}.dof",
                f"expected 'ball', 'hinge', 'hinge_twist', 'swing' or 'fixed': {dof!r}",
            )
        for k in ("axis", "axis_in"):
            if k in spec and dof not in HINGES:
                raise fail(f"{key}.{k}", "only a hinge has an axis")
        axis_in = spec.get("axis_in", "bone")
        if axis_in not in AXES_IN:
            raise fail(f"{key}.axis_in", f"expected 'bone' or 'parent': {axis_in!r}")
        axis_v = spec.get("axis", "x")
        if isinstance(axis_v, str) and axis_v in _AXES:
            axis = _AXES[axis_v]
        elif (
            isinstance(axis_v, list)
            and len(axis_v) == 3
            and all(_is_number(v) for v in axis_v)
        ):
            for i, v in enumerate(axis_v):
                if not -1.0 <= v <= 1.0:  # (NaN too)
                    raise fail(
                        f"{key}.axis[{i}]",
                        f"{v!r} is out of range: allowed [-1, 1] ({AXIS_WHY})",
                    )
            n = math.hypot(*axis_v)
            if n == 0.0:
                raise fail(f"{key}.axis", f"a zero vector is no direction: {axis_v!r}")
            axis = (axis_v[0] / n, axis_v[1] / n, axis_v[2] / n)
        else:
            raise fail(f"{key}.axis", f"expected x, y, z or [x, y, z]: {axis_v!r}")
        if name in roots and dof != "ball":
            raise fail(f"{key}.dof", "a root bone is free (ball)")
        stiff = spec.get("stiffness_mm", 0.0)
        if not _is_number(stiff):
            raise fail(f"{key}.stiffness_mm", f"expected a number: {stiff!r}")
        if not 0.0 <= stiff <= STIFFNESS_MAX_MM:  # (NaN too)
            raise fail(
                f"{key}.stiffness_mm",
                f"{stiff!r} is out of range: allowed [0, {STIFFNESS_MAX_MM:g}] mm/rad "
                f"({STIFFNESS_WHY})",
            )
        if name in roots and stiff:
            raise fail(f"{key}.stiffness_mm", "a root bone is free (no stiffness)")
        about = spec.get("stiffness_free_plane", [])
        if (
            not isinstance(about, list)
            or len(about) not in (0, 2)
            or not all(isinstance(m, str) and m in markers for m in about)
            or (about and about[0] == about[1])
        ):
            raise fail(
                f"{key}.stiffness_free_plane",
                f"expected two of the rig's markers: {about!r}",
            )
        if about and not stiff:
            raise fail(
                f"{key}.stiffness_free_plane", "needs a stiffness_mm to act with"
            )
        from_bend = spec.get("axis_from_bend_deg", 0.0)
        if "axis_from_bend_deg" in spec and dof not in HINGES:
            raise fail(f"{key}.axis_from_bend_deg", "only a hinge has an axis")
        if not _is_number(from_bend):
            raise fail(f"{key}.axis_from_bend_deg", f"expected a number: {from_bend!r}")
        if not 0.0 <= from_bend <= 90.0:  # (NaN too)
            raise fail(
                f"{key}.axis_from_bend_deg",
                f"{from_bend!r} is out of range: allowed [0, 90] deg ({BEND_WHY})",
            )
        pair = spec.get("axis_markers", [])
        if "axis_markers" in spec and dof not in HINGES:
            raise fail(f"{key}.axis_markers", "only a hinge has an axis")
        if (
            not isinstance(pair, list)
            or len(pair) not in (0, 2)
            or not all(isinstance(m, str) for m in pair)
        ):
            raise fail(f"{key}.axis_markers", f"expected two marker names: {pair!r}")
        for m in pair:
            if m not in markers:
                raise fail(f"{key}.axis_markers", f"unknown marker {m!r}")
        if len(pair) == 2 and pair[0] == pair[1]:
            raise fail(f"{key}.axis_markers", f"two different markers: {pair!r}")
        if pair and from_bend:
            raise fail(
                f"{key}.axis_markers",
                "give axis_markers or axis_from_bend_deg, not both",
            )
        twist_to = spec.get("twist_to", "")
        if "twist_to" in spec and dof not in ("hinge_twist", "swing"):
            raise fail(
                f"{key}.twist_to", "only a hinge_twist or a swing has a twist axis"
            )
        if not isinstance(twist_to, str) or (
            twist_to and twist_to not in markers and twist_to not in points
        ):
            raise fail(f"{key}.twist_to", f"expected a marker or point: {twist_to!r}")
        out_b[name] = BoneFitOptions(
            dof=dof, axis=axis, axis_in=axis_in, stiffness_mm=float(stiff),
            axis_from_bend_deg=float(from_bend), axis_markers=tuple(pair),
            twist_to=twist_to, stiffness_free_plane=tuple(about),
        )  # fmt: skip
    return FitOptions(markers=out_m, bones=out_b)


def free_plane_axis(a: F64Array, b: F64Array) -> F64Array | None:
    """The unit normal of the plane through a joint (the origin) and two markers at
    ``a`` and ``b`` in its bone's axes: the rotation a ``stiffness_free_plane`` pull
    spares; None where the three lie on one line."""
    normal = np.cross(np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64))
    n = float(np.linalg.norm(normal))
    return normal / n if math.isfinite(n) and n > 0.0 else None


def stiffness_matrix(stiffness_mm: float, normal: F64Array | None) -> F64Array:
    """A joint's pull towards its calibration pose (m^2 / rad^2, in the chart of its
    bone's rest axes: ``fit_model.FitModel.prior_mat``): ``stiffness_mm`` squared in
    metres on every rotation, or on every rotation but the one about ``normal`` (the
    normal of the plane through the joint and the bone's ``stiffness_free_plane``
    markers, in its rest axes) where one is given and the calibration placed the
    joint and the markers off one line."""
    k2 = (1e-3 * stiffness_mm) ** 2
    n = float(np.linalg.norm(normal)) if normal is not None else 0.0
    if not (math.isfinite(n) and n > 0.0):
        return k2 * np.eye(3)
    u = np.asarray(normal, dtype=np.float64) / n
    return k2 * (np.eye(3) - np.outer(u, u))
