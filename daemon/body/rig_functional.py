"""A rig's ``[functional]`` table: the joints a range of motion places
(``retargetd calibrate --rom``; RIGS.md "Functional joints").

- ``[functional.points.NAME]`` ``markers = [...]``: the derived rigid point NAME is a
  centre of rotation: from the range of motion, the point of NAME's own frame that
  these markers (on the segment that turns about it) keep their distances to
  (``body.functional.sphere_centre``) replaces the base pose's offset.
- ``[functional.axes.BONE]`` ``frame = [A, B, C]``, ``markers = [...]``, optional
  ``centre = "POINT"``: BONE's joint is a hinge: the axis these markers circle about in
  the frame of the three points (on the parent segment) becomes the fit's hinge axis
  for BONE (``body.functional.hinge_axis``); with ``centre``, that rigid point is
  moved onto the axis (its nearest point), so a knee centre sits on the axis the
  knee turns about.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

#: Keys of one ``[functional.points.NAME]`` and ``[functional.axes.BONE]`` table.
POINT_KEYS = ("markers",)
AXIS_KEYS = ("frame", "markers", "centre")


@dataclass(frozen=True, slots=True)
class FunctionalCentre:
    """A rigid point the range of motion places (module docstring)."""

    point: str
    markers: tuple[str, ...]


@dataclass(frozen=True, slots=True)
class FunctionalAxis:
    """A hinge axis the range of motion gives (module docstring)."""

    bone: str
    frame: tuple[str, str, str]
    markers: tuple[str, ...]
    centre: str | None = None


@dataclass(frozen=True, slots=True)
class FunctionalTable:
    """The ``[functional]`` table; empty for a rig without one."""

    points: tuple[FunctionalCentre, ...] = ()
    axes: tuple[FunctionalAxis, ...] = field(default=())

    def __bool__(self) -> bool:
        return bool(self.points or self.axes)


def parse_functional_table(
    doc: Any,
    markers: Mapping[str, Any],
    points: Sequence[Any],
    bones: Sequence[Any],
    fail: Callable[[str, str], Exception],
) -> FunctionalTable:
    """Parse and check ``[functional]``.

    Args:
        doc: the table (a dict).
        markers: the rig's markers.
        points: the rig's derived points (a rigid one has ``frame``).
        bones: the rig's bones (``name``).
        fail: ``fail(key, message)`` -> the rig error to raise.
    """
    rigid_points = {p.name: p.frame for p in points if hasattr(p, "frame")}
    bone_names = {b.name for b in bones}
    if not isinstance(doc, dict):
        raise fail("functional", "expected a table")
    for key in doc:
        if key not in ("points", "axes"):
            raise fail(f"functional.{key}", "unknown key (expected points, axes)")
    known = set(markers) | {p.name for p in points}

    def names(key: str, value: Any, n: int | None = None) -> tuple[str, ...]:
        if (
            not isinstance(value, list)
            or not value
            or not all(isinstance(v, str) for v in value)
        ):
            raise fail(key, "expected a list of names")
        if n is not None and len(value) != n:
            raise fail(key, f"expected {n} names")
        return tuple(value)

    def check_markers(key: str, items: tuple[str, ...]) -> None:
        for m in items:
            if m not in markers:
                raise fail(key, f"{m!r} is not a marker of the rig")

    centres = []
    for name, spec in _table(doc.get("points", {}), "functional.points", fail).items():
        key = f"functional.points.{name}"
        _keys(spec, key, POINT_KEYS, fail)
        if name not in rigid_points:
            raise fail(key, f"{name!r} is not a rigid point of the rig")
        ms = names(f"{key}.markers", spec.get("markers"))
        check_markers(f"{key}.markers", ms)
        centres.append(FunctionalCentre(name, ms))
    axes = []
    for bone, spec in _table(doc.get("axes", {}), "functional.axes", fail).items():
        key = f"functional.axes.{bone}"
        _keys(spec, key, AXIS_KEYS, fail)
        if bone not in bone_names:
            raise fail(key, f"{bone!r} is not a bone of the rig")
        frame = names(f"{key}.frame", spec.get("frame"), 3)
        for p in frame:
            if p not in known:
                raise fail(f"{key}.frame", f"{p!r} is not a marker or point")
        ms = names(f"{key}.markers", spec.get("markers"))
        check_markers(f"{key}.markers", ms)
        centre = spec.get("centre")
        if centre is not None and centre not in rigid_points:
            raise fail(f"{key}.centre", f"{centre!r} is not a rigid point of the rig")
        axes.append(FunctionalAxis(bone, (frame[0], frame[1], frame[2]), ms, centre))
    return FunctionalTable(tuple(centres), tuple(axes))


def _table(v: Any, key: str, fail: Callable[[str, str], Exception]) -> dict[str, Any]:
    if not isinstance(v, dict) or not all(isinstance(s, dict) for s in v.values()):
        raise fail(key, "expected tables")
    return v


def _keys(
    spec: dict[str, Any],
    key: str,
    allowed: tuple[str, ...],
    fail: Callable[[str, str], Exception],
) -> None:
    for k in spec:
        if k not in allowed:
            raise fail(
                f"{key}.{k}", f"unknown key (expected one of: {', '.join(allowed)})"
            )
