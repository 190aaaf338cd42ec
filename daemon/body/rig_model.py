"""The rig's data model: what a parsed rig file holds (markers, measurements, derived
points, bones, joints, fit options), the numeric ranges every key is checked against
and the defaults they cite. Parsing lives in :mod:`retargetd.daemon.body.rig`
(``load_rig``, ``parse_rig``); the file format is ``daemon/body/rigs/RIGS.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from retargetd.daemon.body.rig_fit import (
    AXIS_WHY,
    BEND_WHY,
    STIFFNESS_MAX_MM,
    STIFFNESS_WHY,
    WEIGHT_MAX,
    WEIGHT_WHY,
    FitOptions,
)
from retargetd.daemon.body.rig_functional import FunctionalTable
from retargetd.protocols.humanoid import HUMANOID_BONES as _HUMANOID_BONES

#: The standard humanoid bones (parents first), re-exported for rig files.
HUMANOID_BONES = _HUMANOID_BONES

RULE_AXES = ("height", "width", "depth")


#: The keys of ``[rig]`` (RIGS.md documents each; a test keeps them equal).
RIG_KEYS = ("name", "description", "lateral", "up_min_mm")

#: Default ``[rig] up_min_mm``: a bone whose up reference is seen nearer its axis than
#: this (the up point's distance from the origin->aim line; for ``up = [FROM, TO]``
#: the part of FROM->TO across it) keeps its new axis and takes its roll from the
#: previous frame (``body.kernel``, step 4), flagged ``partial``. Marker noise sigma
#: across a lever d turns the bone by atan(sigma / d); at sigma = 1 mm, the top of
#: what optical systems track to (Merriaux et al., "A study of Vicon system
#: positioning performance", Sensors 17(7):1591, 2017: < 1 mm), d = 11 mm turns it
#: 5.2 deg, the roll change between frames the issue's evidence allows (issue 14).
#: 11 mm is also under the 14 mm diameter of the markers Plug-in Gait assumes
#: (``MarkerDiameter``): the up marker sits within its own size of the axis. It is well
#: under the 30 mm ``calibrate`` asks of a base-pose lever (``body.sanity``), so a
#: rig that passes that check holds a roll only when the lever collapses mid-take.
UP_MIN_MM = 11.0

#: The greatest distance between two points of one body, mm. Stature is at most 2.3 m
#: in the range the calibration's sanity check accepts (NCD-RisC 2016; ``body.sanity``)
#: and the arm span is about the stature (Drillis & Contini, in Winter 2009); 2500 mm
#: leaves a margin. No measurement of a body and no offset between two of its points
#: exceeds it; a larger value is a unit slip (m for mm is 1000x, cm 10x) or a typo.
BODY_EXTENT_MAX_MM = 2500.0


@dataclass(frozen=True, slots=True)
class NumberRange:
    """The values a numeric rig key allows: ``low..high``, ``low`` excluded when
    ``low_open``; never NaN or infinite. ``why`` says where the bounds come from."""

    low: float
    high: float
    why: str
    low_open: bool = False
    unit: str = ""

    def __contains__(self, value: float) -> bool:
        if not math.isfinite(value) or value > self.high:
            return False
        return value > self.low if self.low_open else value >= self.low

    def __str__(self) -> str:
        text = f"{'(' if self.low_open else '['}{self.low:g}, {self.high:g}]"
        return f"{text} {self.unit}" if self.unit else text


#: Every numeric key of the rig format and its range, by key path (``*``: a name of
#: the rig author's).
RIG_RANGES: dict[str, NumberRange] = {
    # 0 turns the roll hold off; above 100 mm, more than a limb's radius (a thigh's
    # girth is ~0.5-0.6 m, a radius under 100 mm: Gordon et al., ANSUR II 2014), a
    # limb bone's up marker would never count as off its axis.
    "rig.up_min_mm": NumberRange(
        0.0, 100.0, "0 = off; at most a limb's radius", unit="mm"
    ),
    # A measurement is a length of the body (a width, a depth, a marker diameter, an
    # offset): positive (Vicon writes 0 for "not measured", so 0 is no default) and
    # within the body's extent.
    "measurements.*.default": NumberRange(
        0.0,
        BODY_EXTENT_MAX_MM,
        "a length of the body: positive, within a body's extent",
        low_open=True,
        unit="mm",
    ),
    # The chapter's line point (eq. 5.13-5.17) interpolates for 0 <= u <= 1 and
    # extrapolates outside; up to one segment length beyond either end covers the
    # reflection of an end through the other (u = 2, Plug-in Gait's TRXO). Farther, the
    # point leaves the body part A-B spans and the markers' noise grows with |u|
    # (sigma * sqrt((1 - u)^2 + u^2)).
    "points.*.u": NumberRange(
        -1.0, 2.0, "at most one segment length beyond either end of the line"
    ),
    # The least bend a rigid point's frame needs in the base pose (the angle B-A-C
    # short of straight): a bend, not a reflex angle.
    "points.*.bend_min_deg": NumberRange(
        0.0, 90.0, "a joint's bend short of straight, at most a right angle", unit="deg"
    ),
    # An offset between two points of one body, per axis of the three-point frame.
    "points.*.offset_mm": NumberRange(
        -BODY_EXTENT_MAX_MM,
        BODY_EXTENT_MAX_MM,
        "an offset within one body",
        unit="mm",
    ),
    # The fit's pull of a joint towards its calibration pose (checked in body.rig_fit,
    # which words the error the same way).
    "fit.bones.*.stiffness_mm": NumberRange(
        0.0, STIFFNESS_MAX_MM, STIFFNESS_WHY, unit="mm/rad"
    ),
    # A marker's residual weight, a ratio of variances (checked in body.rig_fit, whose
    # WEIGHT_MAX cites its bound).
    "fit.markers.*.weight": NumberRange(0.0, WEIGHT_MAX, WEIGHT_WHY),
    # The least calibration-pose bend that gives a hinge its axis (body.rig_fit).
    "fit.bones.*.axis_from_bend_deg": NumberRange(0.0, 90.0, BEND_WHY, unit="deg"),
    # A hinge's axis as [x, y, z] (checked in body.rig_fit).
    "fit.bones.*.axis": NumberRange(-1.0, 1.0, AXIS_WHY),
}


class RigError(ValueError):
    """A rig file that cannot be used; the message is one line naming file and key."""


@dataclass(frozen=True, slots=True)
class LinearExpr:
    """``constant + sum(coef * name)``: a linear expression in named quantities."""

    constant: float
    terms: tuple[tuple[str, float], ...]
    text: str

    @property
    def names(self) -> tuple[str, ...]:
        """The names the expression uses."""
        return tuple(name for name, _ in self.terms)

    def evaluate(self, values: dict[str, float]) -> float:
        """Value with ``values[name]`` substituted for each name."""
        return self.constant + sum(coef * values[name] for name, coef in self.terms)


@dataclass(frozen=True, slots=True, kw_only=True)
class Measurement:
    """A named subject measurement (mm), its default and what it is."""

    name: str
    default_mm: float
    description: str = ""


@dataclass(frozen=True, slots=True, kw_only=True)
class LinePoint:
    """A point on the line ``a -> b`` at parameter ``u`` (0 at a, 1 at b)."""

    name: str
    a: str
    b: str
    u: float

    @property
    def inputs(self) -> tuple[str, ...]:
        """Points this one is built from."""
        return (self.a, self.b)

    @property
    def frame_inputs(self) -> tuple[str, ...]:
        """Points needed in every frame (the same as ``inputs`` for a line)."""
        return (self.a, self.b)


@dataclass(frozen=True, slots=True, kw_only=True)
class RigidPoint:
    """A point held rigidly in the frame of three points (see module docstring).

    Exactly one of ``rule`` (per-axis base-pose rule, affine combinations of points)
    and ``offset_mm`` (explicit offset in the three-point frame) is set.
    """

    name: str
    frame: tuple[str, str, str]
    rule: dict[str, LinearExpr] | None = None
    offset_mm: tuple[LinearExpr, LinearExpr, LinearExpr] | None = None
    #: The frame's least bend in the base pose, degrees (180 - the angle at A between
    #: B and C); 0 = none. Under it, calibrating warns (``body.sanity.check_bends``).
    bend_min_deg: float = 0.0

    @property
    def inputs(self) -> tuple[str, ...]:
        """Points this one is built from (the frame, and the rule's points)."""
        extra: list[str] = []
        if self.rule is not None:
            for expr in self.rule.values():
                extra.extend(expr.names)
        return tuple(dict.fromkeys((*self.frame, *extra)))

    @property
    def frame_inputs(self) -> tuple[str, ...]:
        """Points needed in every frame: the three of the frame (a rule's points are
        used only in the base pose)."""
        return self.frame


DerivedPoint = LinePoint | RigidPoint


@dataclass(frozen=True, slots=True, kw_only=True)
class Bone:
    """A bone: +Y from ``origin`` to ``aim``; +X towards ``up`` (a point or a direction
    between two points); ``parent`` is another bone or None for a root."""

    name: str
    parent: str | None
    origin: str
    aim: str
    up: tuple[str, ...]
    humanoid: str | None = None

    @property
    def inputs(self) -> tuple[str, ...]:
        """Points that define the bone."""
        return tuple(dict.fromkeys((self.origin, self.aim, *self.up)))


@dataclass(frozen=True, slots=True, kw_only=True)
class Rig:
    """A parsed, validated rig. Points and bones are in dependency order."""

    name: str
    source: str
    description: str
    lateral: tuple[str, str]
    measurements: dict[str, Measurement]
    markers: dict[str, tuple[str, ...]]
    segments: dict[str, tuple[str, ...]]
    points: tuple[DerivedPoint, ...]
    bones: tuple[Bone, ...]
    joints: dict[str, str]
    humanoid: dict[str, str] = field(default_factory=dict)
    #: ``[rig] up_min_mm`` (see :data:`UP_MIN_MM`).
    up_min_mm: float = UP_MIN_MM
    #: The ``[fit]`` table (``body.rig_fit``).
    fit: FitOptions = field(default_factory=FitOptions)
    #: The ``[functional]`` table (``body.rig_functional``).
    functional: FunctionalTable = field(default_factory=FunctionalTable)

    @property
    def marker_names(self) -> tuple[str, ...]:
        """Rig marker names, in file order."""
        return tuple(self.markers)

    @property
    def point_names(self) -> tuple[str, ...]:
        """Derived point names, in dependency order."""
        return tuple(p.name for p in self.points)

    @property
    def bone_names(self) -> tuple[str, ...]:
        """Bone names, parents before children."""
        return tuple(b.name for b in self.bones)

    def bone_parent_indices(self) -> tuple[int, ...]:
        """Parent index per bone (-1 for a root)."""
        index = {b.name: i for i, b in enumerate(self.bones)}
        return tuple(-1 if b.parent is None else index[b.parent] for b in self.bones)

    def markers_of(self, name: str, *, base_pose: bool = False) -> tuple[str, ...]:
        """Rig markers a point (or marker) depends on, transitively, in rig order.

        Args:
            name: a marker or derived point.
            base_pose: include the markers that ``rule`` points use only when they are
                calibrated (default: only what every frame's solve needs).
        """
        by_name = {p.name: p for p in self.points}
        seen: set[str] = set()
        stack = [name]
        found: set[str] = set()
        while stack:
            item = stack.pop()
            if item in seen:
                continue
            seen.add(item)
            if item in self.markers:
                found.add(item)
            elif item in by_name:
                point = by_name[item]
                stack.extend(point.inputs if base_pose else point.frame_inputs)
        return tuple(m for m in self.markers if m in found)
