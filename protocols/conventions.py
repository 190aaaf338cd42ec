"""Frames, units and the one conversion from a capture system's frame to the world.

The internal world is right-handed, +Z up, metres (MuJoCo's world). A take or stream
declares its own units and up axis and is converted once, at the input::

    p_world = world_from_capture @ (p_capture * unit_to_metres)

``world_from_capture`` is a pure rotation: the lab's horizontal axes are kept as the
capture system had them (no recentring, no heading change). For a +Y-up capture it is
+90 degrees about X (capture +Y -> world +Z, capture +Z -> world -Y). See the
"Conventions" table in README.md.
"""

from __future__ import annotations

import numpy as np

from retargetd.protocols.frames import F64Array

MM_TO_M = 1e-3
CM_TO_M = 1e-2
DM_TO_M = 1e-1
IN_TO_M = 0.0254

#: Length units a take or stream may declare, to metres.
UNIT_TO_METRES: dict[str, float] = {
    "m": 1.0,
    "dm": DM_TO_M,
    "cm": CM_TO_M,
    "mm": MM_TO_M,
    "in": IN_TO_M,
}

#: Up axes a take or stream may declare.
UP_AXES = ("+X", "-X", "+Y", "-Y", "+Z", "-Z")

_UP_VECTORS = {
    "+X": (1.0, 0.0, 0.0),
    "-X": (-1.0, 0.0, 0.0),
    "+Y": (0.0, 1.0, 0.0),
    "-Y": (0.0, -1.0, 0.0),
    "+Z": (0.0, 0.0, 1.0),
    "-Z": (0.0, 0.0, -1.0),
}

# Each is the smallest rotation taking the declared up axis onto world +Z, written as
# an exact signed permutation (rows = world axes, columns = capture axes).
_WORLD_FROM_CAPTURE = {
    "+Z": ((1, 0, 0), (0, 1, 0), (0, 0, 1)),
    # +90 deg about X: capture +Y -> world +Z, capture +Z -> world -Y.
    "+Y": ((1, 0, 0), (0, 0, -1), (0, 1, 0)),
    # -90 deg about Y: capture +X -> world +Z, capture +Z -> world -X.
    "+X": ((0, 0, -1), (0, 1, 0), (1, 0, 0)),
    # 180 deg about X.
    "-Z": ((1, 0, 0), (0, -1, 0), (0, 0, -1)),
    # -90 deg about X: capture -Y -> world +Z.
    "-Y": ((1, 0, 0), (0, 0, 1), (0, -1, 0)),
    # +90 deg about Y: capture -X -> world +Z.
    "-X": ((0, 0, 1), (0, 1, 0), (-1, 0, 0)),
}


def normalize_up_axis(up: str) -> str:
    """Return the canonical spelling (``"+Y"``) of an up axis like ``"y"``, ``"-z"``.

    Raises:
        ValueError: naming the value unless it is X, Y or Z with an optional sign.
    """
    text = up.strip().upper()
    if text in ("X", "Y", "Z"):
        text = "+" + text
    if text not in _WORLD_FROM_CAPTURE:
        raise ValueError(f"up axis must be one of {', '.join(UP_AXES)}; got {up!r}")
    return text


def normalize_units(units: str) -> str:
    """Return the canonical unit name (``"mm"``) for a declared length unit.

    Raises:
        ValueError: naming the value when the unit is unknown.
    """
    text = units.strip().lower()
    aliases = {
        "millimeters": "mm",
        "millimetres": "mm",
        "meters": "m",
        "metres": "m",
        "centimeters": "cm",
        "centimetres": "cm",
        "inches": "in",
    }
    text = aliases.get(text, text)
    if text not in UNIT_TO_METRES:
        raise ValueError(
            f"length units must be one of {', '.join(UNIT_TO_METRES)}; got {units!r}"
        )
    return text


def world_from_capture_mat(up_axis: str) -> F64Array:
    """Rotation taking capture-frame vectors to the internal world (+Z up).

    Args:
        up_axis: the capture system's up axis, e.g. ``"+Y"`` (case and sign optional).

    Returns:
        (3, 3) float64 rotation matrix, det +1, a signed permutation.
    """
    mat = np.array(_WORLD_FROM_CAPTURE[normalize_up_axis(up_axis)], dtype=np.float64)
    mat.flags.writeable = False
    return mat


def world_from_capture_pos(
    pos_capture: F64Array, up_axis: str, units: str, out: F64Array | None = None
) -> F64Array:
    """Convert positions from a capture frame and unit to world metres.

    Args:
        pos_capture: (..., 3) float, the capture system's unit and frame; NaN allowed.
        up_axis: the capture system's up axis (``"+Z"``, ``"+Y"`` ...).
        units: the capture system's length unit (``"mm"``, ``"m"`` ...).
        out: optional (..., 3) float64 destination.

    Returns:
        (..., 3) float64, metres, internal world frame (``out`` when given).
    """
    scale = UNIT_TO_METRES[normalize_units(units)]
    mat = world_from_capture_mat(up_axis) * scale
    result = np.matmul(np.asarray(pos_capture, dtype=np.float64), mat.T, out=out)
    return result


def up_vector(up_axis: str) -> F64Array:
    """Unit vector of the declared up axis in capture coordinates, (3,) float64."""
    return np.array(_UP_VECTORS[normalize_up_axis(up_axis)], dtype=np.float64)
