"""A rig file's ``[fit]`` table: what the rigid-skeleton fit may be told per marker
and per bone (reference: ``daemon/body/rigs/RIGS.md``, "``[fit]``").

```toml
[fit.markers.LKNE]
segment = "lfemur"   # the bone the marker rides (default: from the bones using it)
weight = 1.0         # residual weight (0 = ignored by the fit)
[fit.bones.ltibia]
dof = "hinge"        # "ball" (default), "hinge" or "swing"
axis = "x"           # hinge axis in the bone's axes: "x", "y", "z" or [x, y, z]
```

``body.rig`` parses the table with :func:`parse_fit_table` into the rig's
:class:`FitOptions` (``Rig.fit``); ``body.fit_model`` builds the fit from it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Collection
from dataclasses import dataclass, field
from typing import Any

#: The keys of each table, in the order errors list them.
FIT_KEYS = ("markers", "bones")
MARKER_KEYS = ("segment", "weight")
BONE_KEYS = ("dof", "axis")
DOFS = ("ball", "hinge", "swing")

_AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}


@dataclass(frozen=True, slots=True, kw_only=True)
class MarkerFitOptions:
    """Per-marker rig keys: the bone it rides (None: default) and its weight."""

    segment: str | None = None
    weight: float = 1.0


@dataclass(frozen=True, slots=True, kw_only=True)
class BoneFitOptions:
    """Per-bone rig keys: ``dof`` and the hinge axis (bone axes).

    ``dof``: "ball" (three rotations), "hinge" (one, about ``axis``) or "swing" (two:
    a ball joint without rotation about the bone's own long axis, +Y).
    """

    dof: str = "ball"
    axis: tuple[float, float, float] = (1.0, 0.0, 0.0)


@dataclass(frozen=True, slots=True, kw_only=True)
class FitOptions:
    """The rig's ``[fit]`` table, parsed (empty: every default)."""

    markers: dict[str, MarkerFitOptions] = field(default_factory=dict)
    bones: dict[str, BoneFitOptions] = field(default_factory=dict)


def _is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def parse_fit_table(
    table: Any,
    *,
    markers: Collection[str],
    bones: Collection[str],
    roots: Collection[str],
    fail: Callable[[str, str], Exception],
) -> FitOptions:
    """Validate a rig's ``[fit]`` table against the rig's names.

    Args:
        table: the TOML value of ``fit``.
        markers, bones: the rig's marker and bone names; ``roots`` its root bones.
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
        if not _is_number(weight) or not math.isfinite(weight) or weight < 0.0:
            raise fail(f"{key}.weight", f"expected a number >= 0: {weight!r}")
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
            raise fail(f"{key}.dof", f"expected 'ball', 'hinge' or 'swing': {dof!r}")
        if "axis" in spec and dof != "hinge":
            raise fail(f"{key}.axis", "only a hinge has an axis")
        axis_v = spec.get("axis", "x")
        if isinstance(axis_v, str) and axis_v in _AXES:
            axis = _AXES[axis_v]
        elif (
            isinstance(axis_v, list)
            and len(axis_v) == 3
            and all(_is_number(v) and math.isfinite(v) for v in axis_v)
            and math.hypot(*axis_v) > 0.0
        ):
            n = math.hypot(*axis_v)
            axis = (axis_v[0] / n, axis_v[1] / n, axis_v[2] / n)
        else:
            raise fail(f"{key}.axis", f"expected x, y, z or [x, y, z]: {axis_v!r}")
        if name in roots and dof != "ball":
            raise fail(f"{key}.dof", "a root bone is free (ball)")
        out_b[name] = BoneFitOptions(dof=dof, axis=axis)
    return FitOptions(markers=out_m, bones=out_b)
