"""The fit's model: a calibrated rig as a rigid kinematic chain with markers on it.

:func:`build_fit_model` turns a :class:`~retargetd.daemon.rig.Rig`, its
:class:`~retargetd.daemon.calibration.Calibration` and the base-pose frames into a
:class:`FitModel`, the flat arrays ``kernel_fit`` walks:

- **chain**: every bone is a rigid segment with the calibrated bone frame (+Y along the
  bone, as the construction defines it); a bone's origin sits at its calibrated rest
  offset in its parent's frame (``conj(rest_world_from_parent) (o_b - o_parent)``, the
  joint), so bone lengths and joint positions are constant; a root bone has a free
  position and rotation; every other joint is a ball joint (3 rotations) unless the rig
  says ``dof = "hinge"``;
- **markers**: every rig marker rides one bone at a local position, the mean over the
  base-pose frames of ``conj(world_from_bone(f)) (m(f) - o_bone(f))`` with the
  construction's bone frames of each frame;
- **joint centres**: each ``[joints]`` point rides a bone the same way (a bone's origin
  exactly, by construction);
- **limits**: the validator's swing/twist table per bone, for the fit's soft penalty:
  passed in by the caller (``validate.limits.JOINT_LIMITS_DEG`` and
  ``validate.model.SEGMENT_KIND``; ``body`` may not import ``validate``), none when
  not given.

Which bone a marker rides (unless the rig's ``[fit.markers.NAME] segment`` says): the
bones whose ``aim`` or ``up`` need the marker, and the parent of each bone whose
``origin`` needs it (a joint centre is built from markers of the proximal segment);
of those, the ones that use it most directly (the marker itself as the point, then as
an input of the point, ...: menache's LSHOULDER is the scapula's up, while the
shoulder bone's aim is only a point on a line from it); among those, the bone whose
base-pose line (origin to aim) is nearest to the marker,
the proximal one when two are within :data:`PROXIMAL_TIE_M` (a marker on a joint's
condyle or malleolus rides the proximal bone). The markers of a ``[segments]`` group
all ride the most proximal bone lying inside the group (origin and aim both built from
its markers: Plug-in Gait's thorax markers ride the chest, not the spine whose aim they
build), when there is one. A marker no bone uses rides the bone of the other markers
of its group, else the nearest bone.

Rig keys (a ``[fit]`` table, see ``daemon/body/rigs/RIGS.md``), parsed with the rig
(``Rig.fit``, ``body.rig_fit``) and used by default:

```toml
[fit.markers.LKNE]
segment = "lfemur"   # the bone the marker rides
weight = 1.0         # residual weight (0 = ignored by the fit)
[fit.bones.ltibia]
dof = "hinge"        # "ball" (default) or "hinge"
axis = "x"           # hinge axis in the bone's axes: "x", "y", "z" or [x, y, z]
```
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.calibration import (
    Calibration,
    CalibrationError,
    bone_world_quats,
    check_calibration_fits,
    compute_points,
    match_markers,
)
from retargetd.daemon.body.fit_observe import (
    BoneObservation,
    Chain,
    hidden_information,
    marker_hinges,
    observe,
)
from retargetd.daemon.body.neutral import neutral_from_rest, performer_left
from retargetd.daemon.body.rig import Rig, RigError, load_rig
from retargetd.daemon.body.rig_fit import (
    BoneFitOptions,
    FitOptions,
    MarkerFitOptions,
    free_plane_axis,
    hinge_axes_in_bone,
    parse_fit_table,
    stiffness_matrix,
)

__all__ = [
    "BoneFitOptions",
    "FitModel",
    "FitOptions",
    "MarkerFitOptions",
    "build_fit_model",
    "load_fit_rig",
    "parse_fit_options",
]
from retargetd.protocols.frames import F64Array, IntArray

logger = logging.getLogger(__name__)

#: Two candidate bones whose base-pose lines are this close to a marker count as a tie,
#: broken towards the proximal bone: half the smallest joint width a rig puts a marker
#: pair across (knee / ankle / wrist widths 50-110 mm, Plug-in Gait's measurements
#: table; a marker on one condyle is ~half that from either bone's line).
PROXIMAL_TIE_M = 0.025

#: ``axis_markers`` closer than this are no joint's two sides (the narrowest joint a
#: rig puts a marker pair across is ~50 mm wide, Plug-in Gait's measurements table:
#: half that is already a marker pair on one side): the rig's axis is kept.
AXIS_MARKERS_MIN_M = 0.025

#: A "hinge_twist" axis must be at least 30 deg off the bone's own axis (|cos| <= this):
#: nearer, the cone the hinge sweeps the bone's axis on narrows to the axis itself and
#: the hinge is mostly the twist (an elbow's flexion axis is ~90 deg off the forearm's).
HINGE_TWIST_MAX_COS = math.cos(math.radians(30.0))

#: A fixed joint's pull towards its calibration pose, m^2 / rad^2: a hinge's off-axis
#: stiffness (``FitParams.kappa_hinge``, 1 m of residual per radian), far above any
#: marker's pull, so the joint does not turn.
FIXED_STIFFNESS = 1.0

#: The fit's joint limits sit this far inside the validator's table: the penalty is
#: soft (``FitParams.kappa_limit``), so markers that ask for more push a joint a
#: little past where it begins; the table is where a pose fails, and the fit stays
#: inside it.
LIMIT_MARGIN_RAD = math.radians(1.0)

#: Limit table columns (radians; NaN = no such limit): twist lo, twist hi,
#: sagittal lo, sagittal hi, frontal |max|, cone max; then (4) the bone's
#: ``neutral_from_rest`` (w x y z, ``body.neutral``): the limits apply to it times
#: the calibration-relative rotation.
LIM_TWIST_LO, LIM_TWIST_HI, LIM_SAG_LO, LIM_SAG_HI, LIM_FRONTAL, LIM_CONE = range(6)
LIM_REF = 6
N_LIM = 10


@dataclass(frozen=True, slots=True, kw_only=True)
class FitModel:
    """The flat model ``kernel_fit`` runs (all arrays read-only, float64 / int64).

    Attributes:
        bone_names: (B,) rig order, parents first.
        bone_parent: (B,) parent index, -1 for a root.
        bone_root: (B,) ordinal of the root each bone hangs from (0 .. R-1).
        off_parent: (B, 3) metres, the bone's origin in its parent's bone frame
            (roots: zeros).
        rest_pfb: (B, 4) calibrated parent_from_bone (root: world_from_bone), w x y z.
        root_rest_pos: (R, 3) metres, world, each root's calibrated origin.
        marker_names: (Mr,) rig markers; ``marker_bone`` (Mr,) the bone each rides
            (-1: never seen in the base pose, unused); ``marker_local`` (Mr, 3) metres
            in that bone's frame; ``marker_weight`` (Mr,) residual weights.
        joint_names: (J,); ``joint_bone`` (J,), ``joint_local`` (J, 3) metres.
        hinge_axis: (B, 3) unit hinge axis in the bone's rest axes, zeros = ball.
        twist_axis: (B, 3) unit twist axis of a "hinge_twist" or a "swing" in the
            bone's rest axes (``twist_to``: to that marker; else, and for every other
            bone, +Y).
        twist_lock: (B,) 1.0 for a swing joint (no rotation about its twist axis
            relative to its calibration pose), 2.0 for a hinge with the bone's twist
            ("hinge_twist": the bone's axis stays on the cone the hinge sweeps it
            on), else 0.0.
        prior_mat: (B, 3, 3) m^2 / rad^2, each joint's pull towards its calibration
            pose, ``1/2 c^T P c`` with ``c`` the joint's rotation relative to it in
            swing-twist coordinates of the bone's rest axes (swing x, twist about +Y,
            swing z; ``fit_terms.prior_chart``): the rig's ``stiffness_mm`` (squared,
            in metres, times I), a fixed joint's :data:`FIXED_STIFFNESS`, and the
            automatic prior on each rotation the markers do not observe
            (``fit_observe``).
        hide_axes, hide_lam, hide_lost: (2 Mr B, 9), (2 Mr B, 3), (2 Mr B, 3): row
            ``k * B + b``, bone b's rotations with marker k hidden (three
            directions in its rest axes), their marginal information and what k gave
            along each, m^2 / rad^2, at the calibration pose; from row ``Mr * B`` on
            the same with every nearly straight hinge at a right angle
            (``fit_observe.hidden_information``: the hold prior).
        hide_hinge: (Mr,) the hinge whose bend picks a hidden marker's table, -1
            none (``fit_observe.marker_hinges``).
        joint_dof: (B,) each joint's model ("root", "ball", "hinge", ...).
        observation: (B,) what the markers determine of each bone
            (``fit_observe.observe``).
        limits: (B, N_LIM) radians (``LIM_*`` columns, NaN = none), then each
            bone's ``neutral_from_rest`` (``LIM_REF``); ``limit_left`` and
            ``limit_forward`` (B, 3): the performer's left and forward in each bone's
            axes at anatomical neutral (the validator's sagittal and frontal axes).
        penalty_cos: (B,) cos(theta_min / 2), theta_min the smallest limit of the
            bone: a joint rotated from neutral by less than that (|w| of
            ``neutral_from_rest * q`` above it) is inside all its
            limits, since swing and twist angles never exceed the rotation's angle
            (-1 for a bone without limits: never checked; 2 for a hinge or a swing
            joint: always).
        anc_ptr, anc_idx: CSR, per bone its ancestors-or-self, self first.
        n_dof: 3 B + 3 R unknowns: bone b's rotation at ``3 (B - 1 - b)``, root r's
            translation at ``3 B + 3 r`` (children before parents: the elimination
            order of the chain's Cholesky, which then has no fill-in).
        node_ptr, node_idx: CSR over the Cholesky's 3 x 3 nodes (bone b's rotation
            is node B - 1 - b, root r's translation node B + r), each node's
            ancestors in ascending order: the only blocks its column reaches.
    """

    bone_names: tuple[str, ...]
    bone_parent: IntArray
    bone_root: IntArray
    off_parent: F64Array
    rest_pfb: F64Array
    root_rest_pos: F64Array
    marker_names: tuple[str, ...]
    marker_bone: IntArray
    marker_local: F64Array
    marker_weight: F64Array
    joint_names: tuple[str, ...]
    joint_bone: IntArray
    joint_local: F64Array
    hinge_axis: F64Array
    twist_axis: F64Array
    twist_lock: F64Array
    prior_mat: F64Array
    hide_axes: F64Array
    hide_lam: F64Array
    hide_lost: F64Array
    hide_hinge: IntArray
    limits: F64Array
    limit_left: F64Array
    limit_forward: F64Array
    anc_ptr: IntArray
    anc_idx: IntArray
    penalty_cos: F64Array
    n_dof: int
    node_ptr: IntArray
    node_idx: IntArray
    joint_dof: tuple[str, ...] = ()
    observation: tuple[BoneObservation, ...] = ()

    @property
    def n_roots(self) -> int:
        """Number of root bones R."""
        return int(self.root_rest_pos.shape[0])


# --- the rig's [fit] table --------------------------------------------------------


def load_fit_rig(name_or_path: str | Path) -> tuple[Rig, FitOptions]:
    """Load a rig and its ``[fit]`` keys (``Rig.fit``; kept for callers that want
    the pair).

    Raises:
        RigError: one line naming the file, the key and the bad value.
    """
    rig = load_rig(name_or_path)
    return rig, rig.fit


def parse_fit_options(rig: Rig, table: Any, *, source: str) -> FitOptions:
    """Validate a ``[fit]`` table against ``rig`` (as the rig parser does).

    Raises:
        RigError: naming ``source`` and the key.
    """
    return parse_fit_table(
        table,
        markers=rig.markers,
        points=[p.name for p in rig.points],
        bones=rig.bone_names,
        roots=[b.name for b in rig.bones if b.parent is None],
        fail=lambda key, message: RigError(f"{source}: {key}: {message}"),
    )


# --- building the model -----------------------------------------------------------


def _readonly(arr: np.ndarray) -> np.ndarray:
    arr = np.ascontiguousarray(arr)
    arr.flags.writeable = False
    return arr


def _local_mean(pos: F64Array, origin: F64Array, wfb: F64Array) -> tuple[F64Array, int]:
    """Mean over frames of conj(wfb) (pos - origin), finite frames only.

    Args:
        pos, origin: (F, 3) metres, world; wfb: (F, 4).

    Returns:
        (3,) metres in the bone frame (NaN when no frame is usable), frames used.
    """
    mats = rot.mat_from_quat(wfb)  # (F, 3, 3); NaN rows stay NaN
    local = np.einsum("fji,fj->fi", mats, pos - origin)
    ok = np.isfinite(local).all(axis=-1)
    if not ok.any():
        return np.full(3, np.nan), 0
    return local[ok].mean(axis=0), int(ok.sum())


def _twist_axis(
    name: str, marker: str, rig: Rig, pts: Mapping[str, F64Array], wfb: F64Array
) -> F64Array:
    """``twist_to``'s axis: the unit line from bone ``name``'s origin to ``marker``
    over the base-pose frames, in the bone's axes (one line, exit 2, when the marker
    is never seen there or sits on the origin)."""
    origin = rig.bones[rig.bone_names.index(name)].origin
    loc, used = _local_mean(pts[marker], pts[origin], wfb)
    n = float(np.linalg.norm(loc)) if used else 0.0
    if not n > AXIS_MARKERS_MIN_M:
        raise CalibrationError(
            f"fit.bones.{name}.twist_to: {marker} is not seen in the base pose or "
            f"lies within {AXIS_MARKERS_MIN_M * 1e3:.0f} mm of the bone's origin"
        )
    return np.asarray(loc / n, dtype=np.float64)


def _segment_distance(p: F64Array, a: F64Array, b: F64Array) -> float:
    """Distance from point p to the segment a-b (metres)."""
    ab = b - a
    denom = float(ab @ ab)
    u = 0.0 if denom <= 0.0 else float(np.clip((p - a) @ ab / denom, 0.0, 1.0))
    return float(np.linalg.norm(p - (a + u * ab)))


def default_marker_bones(
    rig: Rig, marker_mean: F64Array, bone_origin: F64Array, bone_aim: F64Array
) -> tuple[int, ...]:
    """The bone each rig marker rides by default (see module docstring).

    Args:
        rig: the rig.
        marker_mean: (Mr, 3) metres, world, base-pose mean of each marker (NaN: never
            seen).
        bone_origin, bone_aim: (B, 3) metres, world, base-pose bone ends.

    Returns:
        (Mr,) bone index per marker (-1 when the marker was never seen).
    """
    parents = rig.bone_parent_indices()
    depth = [0] * len(parents)
    for b, p in enumerate(parents):
        depth[b] = 0 if p < 0 else depth[p] + 1
    # candidate bone -> how directly the marker enters it (0: the point itself)
    cand: dict[str, dict[int, int]] = {m: {} for m in rig.markers}
    by_name = {p.name: p for p in rig.points}

    def levels(point: str) -> dict[str, int]:
        found: dict[str, int] = {}
        frontier, level = [point], 0
        while frontier:
            nxt: list[str] = []
            for item in frontier:
                if item in rig.markers:
                    found.setdefault(item, level)
                elif item in by_name:
                    nxt.extend(by_name[item].frame_inputs)
            frontier, level = nxt, level + 1
        return found

    def add(b: int, point: str) -> None:
        for m, level in levels(point).items():
            cand[m][b] = min(cand[m].get(b, level), level)

    for b, bone in enumerate(rig.bones):
        for name in (bone.aim, *bone.up):
            add(b, name)
        add(b if parents[b] < 0 else parents[b], bone.origin)
    dist = {
        (m, b): _segment_distance(marker_mean[i], bone_origin[b], bone_aim[b])
        for i, m in enumerate(rig.markers)
        for b in range(len(parents))
        if np.isfinite(marker_mean[i]).all()
    }
    out: dict[str, int] = {}
    for i, m in enumerate(rig.markers):
        if not np.isfinite(marker_mean[i]).all():
            out[m] = -1
        elif cand[m]:
            direct = min(cand[m].values())
            first = [b for b, level in cand[m].items() if level == direct]
            best = min(first, key=lambda b: dist[(m, b)])
            near = [
                b for b in first if dist[(m, b)] <= dist[(m, best)] + PROXIMAL_TIE_M
            ]
            out[m] = min(near, key=lambda b: (depth[b], b))
    for names in rig.segments.values():
        # A rigid group rides, whole, the most proximal bone lying inside it (origin
        # and aim both built from its markers), when there is one.
        group = set(names)
        inside = [
            b
            for b, bone in enumerate(rig.bones)
            if group & set(rig.markers_of(bone.origin))
            and group & set(rig.markers_of(bone.aim))
        ]
        if inside:
            host = min(inside, key=lambda b: (depth[b], b))
            for m in names:
                if out.get(m, 0) >= 0:
                    out[m] = host
            continue
        voted = [out[m] for m in names if m in out and out[m] >= 0]
        for m in names:
            if m not in out and voted:
                out[m] = max(set(voted), key=voted.count)
    for m in rig.markers:
        if m not in out:
            out[m] = min(range(len(parents)), key=lambda b: dist[(m, b)])
    return tuple(out[m] for m in rig.markers)


class JointLimitLike(Protocol):
    """A row of the validator's limit table (``validate.limits.JointLimit``), deg."""

    @property
    def twist(self) -> tuple[float, float]: ...
    @property
    def sagittal(self) -> tuple[float, float] | None: ...
    @property
    def frontal(self) -> float | None: ...
    @property
    def cone(self) -> float | None: ...


def _limit_rows(
    rig: Rig,
    calibration: Calibration,
    joint_limits: Mapping[str, JointLimitLike],
    segment_kind: Mapping[str, str],
) -> tuple[F64Array, F64Array, F64Array]:
    """The validator's limits per bone in radians, and its sagittal / frontal axes."""
    n_bones = len(rig.bones)
    limits = np.full((n_bones, N_LIM), np.nan)
    limits[:, LIM_REF : LIM_REF + 4] = neutral_from_rest(rig, calibration, segment_kind)
    left_b = np.zeros((n_bones, 3))
    fwd_b = np.zeros((n_bones, 3))
    # The same performer's left as validate_model.skeleton_from_calibration.
    left = performer_left(rig, calibration)
    forward = np.cross(left, np.array([0.0, 0.0, 1.0]))
    rest_wfb = np.asarray(calibration.rest_world_from_bone_quat, dtype=np.float64)
    for b, bone in enumerate(rig.bones):
        lim = joint_limits.get(segment_kind.get(bone.humanoid or "", "link"))
        if lim is None or bone.parent is None:
            continue
        # the performer's axes in the bone's axes at anatomical neutral
        bone_from_world = rot.quat_mul(
            limits[b, LIM_REF : LIM_REF + 4], rot.quat_conj(rest_wfb[b])
        )
        left_b[b] = rot.quat_rotate(bone_from_world, left)
        fwd_b[b] = rot.quat_rotate(bone_from_world, forward)
        if lim.twist[0] > -180.0 or lim.twist[1] < 180.0:
            limits[b, LIM_TWIST_LO] = math.radians(lim.twist[0]) + LIMIT_MARGIN_RAD
            limits[b, LIM_TWIST_HI] = math.radians(lim.twist[1]) - LIMIT_MARGIN_RAD
        if lim.sagittal is not None:
            limits[b, LIM_SAG_LO] = math.radians(lim.sagittal[0]) + LIMIT_MARGIN_RAD
            limits[b, LIM_SAG_HI] = math.radians(lim.sagittal[1]) - LIMIT_MARGIN_RAD
        if lim.frontal is not None:
            limits[b, LIM_FRONTAL] = math.radians(lim.frontal) - LIMIT_MARGIN_RAD
        if lim.cone is not None:
            limits[b, LIM_CONE] = math.radians(lim.cone) - LIMIT_MARGIN_RAD
    return limits, left_b, fwd_b


def _marker_axis(
    name: str,
    pair: tuple[str, ...],
    rig: Rig,
    parent: int,
    bones_of: Sequence[int],
    local: F64Array,
    rest_pfb: F64Array,
    nominal: F64Array,
) -> F64Array:
    """A hinge's axis from ``[fit.bones.NAME] axis_markers``: the line from the first
    marker to the second where the calibration placed them on the parent bone,
    turned into the bone's rest axes and signed like ``nominal`` (the rig's
    ``axis``, the same axes). A marker the base pose never saw leaves ``nominal``
    (a warning); a marker riding another bone is the rig's error (one line)."""
    i, k = (rig.marker_names.index(m) for m in pair)
    for m, c in ((pair[0], i), (pair[1], k)):
        if bones_of[c] != parent:
            raise CalibrationError(
                f"fit.bones.{name}.axis_markers: marker {m} rides "
                f"{rig.bone_names[bones_of[c]]}, not the parent bone "
                f"{rig.bone_names[parent]}"
            )
    line = local[k] - local[i]
    norm = float(np.linalg.norm(line))
    if not math.isfinite(norm) or norm < AXIS_MARKERS_MIN_M:
        logger.warning(
            "fit: %s's axis markers %s and %s are %.1f mm apart in the base pose: "
            "the rig's axis is kept", name, pair[0], pair[1], 1e3 * norm,
        )  # fmt: skip
        return nominal
    axis = rot.quat_rotate(rot.quat_conj(rest_pfb), line / norm)
    return axis if axis @ nominal >= 0.0 else -axis


def build_fit_model(
    rig: Rig,
    calibration: Calibration,
    base_positions: F64Array,
    base_labels: tuple[str, ...] | list[str] | None,
    options: FitOptions | None = None,
    *,
    joint_limits: Mapping[str, JointLimitLike] | None = None,
    segment_kind: Mapping[str, str] | None = None,
    layout_positions: F64Array | None = None,
) -> FitModel:
    """Build the fit's rigid model (see module docstring).

    Args:
        rig: the rig.
        calibration: its calibrated skeleton (with rest bone origins).
        base_positions: (F, M, 3) float64, metres, world: the base-pose frames the
            calibration was made from (NaN rows = occluded).
        base_labels: (M,) their labels (matched as a take's: aliases, prefixes);
            None: the columns are already the rig's markers in rig order (M = Mr,
            e.g. ``calibration.base_marker_pos[None]``), used as they are: a rig
            marker's name need not be one of its labels.
        options: ``[fit]`` keys (default: the rig's own, ``rig.fit``).
        joint_limits: the validator's table, segment kind -> limits
            (``validate.limits.JOINT_LIMITS_DEG``); None: no limit penalty.
        segment_kind: humanoid bone -> segment kind (``validate.model.SEGMENT_KIND``).
        layout_positions: (Mr, 3) metres, world, base pose, rig order: where each
            marker sits on its bone when that is not where the base pose saw it
            (a refined layout, ``Calibration.layout_marker_pos``); a marker's place
            on its bone is taken from its finite row, in the bone frames the base
            pose's markers build. None: the base pose's places.

    Returns:
        The model.

    Raises:
        ValueError: a calibration without rest bone origins, the wrong rig, or
            rig-order positions (``base_labels`` None) without one column per rig
            marker.
    """
    check_calibration_fits(rig, calibration)
    if calibration.rest_bone_origin_pos is None:
        raise ValueError("calibration has no rest bone origins: recalibrate")
    options = options if options is not None else rig.fit
    base_positions = np.asarray(base_positions, dtype=np.float64)
    n_rig = len(rig.markers)
    if base_labels is None and base_positions.shape[1:] != (n_rig, 3):
        raise ValueError(
            f"base_positions in rig order must be (F, {n_rig}, 3) for rig "
            f"{rig.name}; got {base_positions.shape}"
        )
    # Rig order already: never re-match the rig's names as if they were labels.
    cols = np.asarray(
        np.arange(n_rig) if base_labels is None else match_markers(rig, base_labels)
    )
    n_frames = base_positions.shape[0]
    marker_pos = np.full((n_frames, len(cols), 3), np.nan)
    have = cols >= 0
    marker_pos[:, have] = base_positions[:, cols[have]]
    pts = compute_points(rig, marker_pos, calibration.point_offsets)
    wfb = bone_world_quats(rig, pts)  # (F, B, 4)
    n_bones = len(rig.bones)
    parents = np.asarray(rig.bone_parent_indices(), dtype=np.int64)
    rest_wfb = np.asarray(calibration.rest_world_from_bone_quat, dtype=np.float64)
    origins = np.asarray(calibration.rest_bone_origin_pos, dtype=np.float64)
    lengths = np.asarray(calibration.bone_lengths, dtype=np.float64)
    aims = origins + rot.quat_rotate(
        rest_wfb, np.stack([np.zeros(n_bones), lengths, np.zeros(n_bones)], -1)
    )
    # The chain.
    roots = [b for b in range(n_bones) if parents[b] < 0]
    bone_root = np.zeros(n_bones, dtype=np.int64)
    off_parent = np.zeros((n_bones, 3))
    for b in range(n_bones):
        p = parents[b]
        if p < 0:
            bone_root[b] = roots.index(b)
        else:
            bone_root[b] = bone_root[p]
            off_parent[b] = rot.quat_rotate(
                rot.quat_conj(rest_wfb[p]), origins[b] - origins[p]
            )
    # Markers on bones.
    ok_frames = np.asarray(np.isfinite(marker_pos).all(axis=-1), dtype=bool)
    with np.errstate(invalid="ignore"):
        seen_any = np.asarray(ok_frames.any(axis=0), dtype=bool)
        marker_mean = np.where(
            seen_any[:, None],
            np.nansum(np.where(ok_frames[..., None], marker_pos, 0.0), axis=0)
            / np.maximum(ok_frames.sum(axis=0), 1)[:, None],
            np.nan,
        )
    bones_of = list(default_marker_bones(rig, marker_mean, origins, aims))
    weight = np.ones(len(rig.markers))
    for i, m in enumerate(rig.markers):
        opt = options.markers.get(m)
        if opt is not None:
            weight[i] = opt.weight
            if opt.segment is not None and bones_of[i] >= 0:
                bones_of[i] = rig.bone_names.index(opt.segment)
    local = np.zeros((len(rig.markers), 3))
    for i, m in enumerate(rig.markers):
        b = bones_of[i]
        if b < 0:
            logger.warning("fit: marker %s never seen in the base pose: unused", m)
            weight[i] = 0.0
            bones_of[i] = 0
            continue
        bone = rig.bones[b]
        place = marker_pos[:, i]
        if layout_positions is not None and np.isfinite(layout_positions[i]).all():
            # one row per base frame: the bone frames are the base frames'
            place = np.broadcast_to(layout_positions[i], place.shape)
        loc, used = _local_mean(place, pts[bone.origin], wfb[:, b])
        if used == 0:
            loc = rot.quat_rotate(
                rot.quat_conj(rest_wfb[b]), marker_mean[i] - origins[b]
            )
        local[i] = loc
    # Joint centres on bones.
    joint_bone = np.zeros(len(rig.joints), dtype=np.int64)
    joint_local = np.zeros((len(rig.joints), 3))
    origin_of = {bone.origin: b for b, bone in reversed(list(enumerate(rig.bones)))}
    aim_of = {bone.aim: b for b, bone in reversed(list(enumerate(rig.bones)))}
    for j, point in enumerate(rig.joints.values()):
        if point in origin_of:
            joint_bone[j] = origin_of[point]
        elif point in aim_of:
            b = aim_of[point]
            joint_bone[j] = b
            joint_local[j] = (0.0, lengths[b], 0.0)
        elif point in rig.markers:
            i = rig.marker_names.index(point)
            joint_bone[j], joint_local[j] = bones_of[i], local[i]
        else:
            users = [
                b for b, bone in enumerate(rig.bones) if point in (bone.aim, *bone.up)
            ]
            b = users[0] if users else 0
            loc, used = _local_mean(pts[point], pts[rig.bones[b].origin], wfb[:, b])
            joint_bone[j], joint_local[j] = b, (loc if used else np.zeros(3))
    # Joint models, the rig's own priors, and the automatic priors on what the
    # markers do not observe (fit_observe).
    hinge = np.zeros((n_bones, 3))
    twist_axis = np.tile(np.array([0.0, 1.0, 0.0]), (n_bones, 1))
    twist_lock = np.zeros(n_bones)
    explicit = np.zeros((n_bones, 3, 3))
    dof = ["root" if parents[b] < 0 else "ball" for b in range(n_bones)]
    rest_pfb = np.asarray(calibration.rest_parent_from_bone_quat, dtype=np.float64)
    axes = hinge_axes_in_bone(options.bones, rig.bone_names, rest_pfb)
    functional_axes = calibration.functional_axes
    for name, bopt in options.bones.items():
        b = rig.bone_names.index(name)
        dof[b] = bopt.dof
        normal = None
        if bopt.stiffness_free_plane:
            i, k = (rig.marker_names.index(m) for m in bopt.stiffness_free_plane)
            if weight[i] > 0.0 and weight[k] > 0.0:  # (one never seen: every rotation)
                if bones_of[i] != b or bones_of[k] != b:
                    raise CalibrationError(
                        f"fit.bones.{name}.stiffness_free_plane: "
                        f"{bopt.stiffness_free_plane} must both ride {name}"
                    )
                normal = free_plane_axis(local[i], local[k])  # (None: collinear)
        explicit[b] = stiffness_matrix(bopt.stiffness_mm, normal)
        if name in axes:  # calibrate --rom's functional axis first, the rig's else
            hinge[b] = functional_axes.get(name, axes[name])
            if bopt.axis_markers and name not in functional_axes:
                hinge[b] = _marker_axis(
                    name, bopt.axis_markers, rig, parents[b], bones_of, local,
                    rest_pfb[b], axes[name],
                )  # fmt: skip
            if bopt.dof == "hinge_twist":
                if bopt.twist_to:
                    twist_axis[b] = _twist_axis(
                        name, bopt.twist_to, rig, pts, wfb[:, b]
                    )
                if abs(hinge[b] @ twist_axis[b]) > HINGE_TWIST_MAX_COS:  # exit 2
                    raise CalibrationError(
                        f"fit.bones.{name}: the hinge axis is within "
                        f"{math.degrees(math.acos(HINGE_TWIST_MAX_COS)):.0f} deg of "
                        "the twist axis, so a hinge about it is its twist"
                    )
                twist_lock[b] = 2.0
        elif bopt.dof == "swing":
            if bopt.twist_to:  # the twist it forbids: about that line, not +Y
                twist_axis[b] = _twist_axis(name, bopt.twist_to, rig, pts, wfb[:, b])
            twist_lock[b] = 1.0
        elif bopt.dof == "fixed":
            explicit[b] = FIXED_STIFFNESS * np.eye(3)
    root_rest_pos = origins[roots]
    chain = Chain(
        parent=parents, root_of=bone_root, off_parent=off_parent, rest_pfb=rest_pfb,
        root_rest_pos=root_rest_pos, marker_bone=np.asarray(bones_of, dtype=np.int64),
        marker_local=local, marker_weight=weight, dof=dof, hinge_axis=hinge,
        twist_axis=twist_axis,
    )  # fmt: skip
    observation = observe(chain, bone_names=rig.bone_names, explicit_prior=explicit)
    prior_mat = explicit + np.stack([o.prior for o in observation])
    hide_axes, hide_lam, hide_lost = hidden_information(chain, prior=prior_mat)
    limits, left_b, fwd_b = _limit_rows(
        rig, calibration, joint_limits or {}, segment_kind or {}
    )
    penalty_cos = np.full(n_bones, -1.0)
    for b in range(n_bones):
        bounds = np.abs(limits[b, :LIM_REF][np.isfinite(limits[b, :LIM_REF])])
        if bounds.size:
            penalty_cos[b] = math.cos(0.5 * float(bounds.min()))
        if hinge[b].any() or twist_lock[b]:
            penalty_cos[b] = 2.0
    # Ancestors (self first) and the Cholesky structure.
    anc_ptr = [0]
    anc_idx: list[int] = []
    for b in range(n_bones):
        k = b
        while k >= 0:
            anc_idx.append(k)
            k = int(parents[k])
        anc_ptr.append(len(anc_idx))
    n_dof = 3 * n_bones + 3 * len(roots)
    # Cholesky nodes (3 unknowns each) in elimination order: bone b is node
    # B - 1 - b, root r's translation node B + r; a node's ancestors come later.
    node_ptr = [0]
    node_idx: list[int] = []
    for node in range(n_bones + len(roots)):
        if node < n_bones:
            b = n_bones - 1 - node
            k = int(parents[b])
            while k >= 0:
                node_idx.append(n_bones - 1 - k)
                k = int(parents[k])
            node_idx.append(n_bones + int(bone_root[b]))
        node_ptr.append(len(node_idx))
    return FitModel(
        bone_names=rig.bone_names,
        bone_parent=_readonly(parents),
        bone_root=_readonly(bone_root),
        off_parent=_readonly(off_parent),
        rest_pfb=_readonly(rest_pfb),
        root_rest_pos=_readonly(root_rest_pos),
        marker_names=rig.marker_names,
        marker_bone=_readonly(np.asarray(bones_of, dtype=np.int64)),
        marker_local=_readonly(local),
        marker_weight=_readonly(weight),
        joint_names=tuple(rig.joints),
        joint_bone=_readonly(joint_bone),
        joint_local=_readonly(joint_local),
        hinge_axis=_readonly(hinge),
        twist_axis=_readonly(twist_axis),
        twist_lock=_readonly(twist_lock),
        prior_mat=_readonly(prior_mat),
        hide_axes=_readonly(hide_axes),
        hide_lam=_readonly(hide_lam),
        hide_lost=_readonly(hide_lost),
        hide_hinge=_readonly(marker_hinges(chain)),
        joint_dof=tuple(dof),
        observation=observation,
        limits=_readonly(limits),
        limit_left=_readonly(left_b),
        limit_forward=_readonly(fwd_b),
        penalty_cos=_readonly(penalty_cos),
        anc_ptr=_readonly(np.asarray(anc_ptr, dtype=np.int64)),
        anc_idx=_readonly(np.asarray(anc_idx, dtype=np.int64)),
        n_dof=n_dof,
        node_ptr=_readonly(np.asarray(node_ptr, dtype=np.int64)),
        node_idx=_readonly(np.asarray(node_idx, dtype=np.int64)),
    )
