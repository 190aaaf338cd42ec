"""A solved take as a spreadsheet-friendly CSV: one row per frame, Euler channels.

``retargetd solve TAKE ... --out take.csv --euler-order ORDER [--degrees]``. The
chapter's users fit curves to joint angles in spreadsheets; any of the 12 rotation
orders (:func:`retargetd.daemon.rotations.euler_from_quat`, scipy's convention) can be
asked for:

- upper case (``"ZXY"``): intrinsic, the rotations about the bone's own moving axes,
  ``R = R_Z(a1) R_X(a2) R_Y(a3)``, the same as BVH channels listed in that order;
- lower case (``"zxy"``): extrinsic, about the fixed parent axes applied in that
  order, ``R = R_Y(a3) R_X(a2) R_Z(a1)`` (so ``"zxy"`` equals intrinsic ``"YXZ"``
  with the angles reversed);
- Tait-Bryan (each axis once: ``XYZ`` ...) or proper Euler (first axis repeated:
  ``ZXZ``, ``XYX`` ...). The middle angle is in [-90°, 90°] (Tait-Bryan) or
  [0°, 180°] (proper); at gimbal lock the last angle is 0. Proper Euler orders are
  singular at no rotation at all (middle angle 0: only the sum of the outer two is
  defined), so near the rest pose their first and third channels can jump; for
  curve fitting pick a Tait-Bryan order whose middle axis the joint does not turn
  90° about (e.g. ``ZXY`` for most joints with +Y along the bone).

Columns::

    frame, time_s, root_x_m, root_y_m, root_z_m,
    <bone>_1<A>_<unit>, <bone>_2<B>_<unit>, <bone>_3<C>_<unit>   (per bone, rig order)

``<A><B><C>`` are the order's letters in upper case (``lhand_1Z_deg``,
``lhand_2X_deg``, ``lhand_3Y_deg``), the digit the angle's place in the sequence;
``<unit>`` is ``deg`` or ``rad``. The angles are of each bone's true parent-relative
rotation ``parent_from_bone`` (``world_from_parent * parent_from_bone =
world_from_bone``; the root's parent is the world), in the bone axes of the rig
(RIGS.md "Bone axes": +Y origin -> aim), unwrapped over time (a channel crossing
±180° continues past it instead of jumping by 360°, which is what curve fitting
wants). Root position: metres, the internal world (Z up).
"""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from retargetd.daemon.rotations import euler_from_quat
from retargetd.protocols.frames import F64Array


def euler_columns(bone_names: Sequence[str], order: str, *, degrees: bool) -> list[str]:
    """The CSV header (module docstring).

    Args:
        bone_names: (B,) bones, rig order.
        order: one of the 12 sequences (e.g. ``"ZXY"``, ``"zxz"``).
        degrees: degree columns (else radians).

    Returns:
        ``5 + 3 B`` column names.
    """
    unit = "deg" if degrees else "rad"
    cols = ["frame", "time_s", "root_x_m", "root_y_m", "root_z_m"]
    for name in bone_names:
        cols += [f"{name}_{k + 1}{a.upper()}_{unit}" for k, a in enumerate(order)]
    return cols


def euler_table(
    parent_from_bone_quat: F64Array, order: str, *, degrees: bool
) -> F64Array:
    """Per-bone Euler angles, unwrapped over time.

    Args:
        parent_from_bone_quat: (T, B, 4) float64 (w, x, y, z).
        order: one of the 12 sequences.
        degrees: return degrees (else radians).

    Returns:
        (T, B, 3) float64 angles in the order's sequence.

    Raises:
        ValueError: a bad order.
    """
    angles = euler_from_quat(np.asarray(parent_from_bone_quat), order)
    angles = np.unwrap(angles, period=2.0 * math.pi, axis=0)
    return np.degrees(angles) if degrees else angles


def write_euler_csv(
    path: str | Path,
    bone_names: Sequence[str],
    parent_from_bone_quat: F64Array,
    root_pos: F64Array,
    rate_hz: float,
    *,
    order: str,
    degrees: bool,
) -> None:
    """Write the CSV of the module docstring.

    Args:
        path: the ``.csv`` file (overwritten).
        bone_names: (B,) bones, rig order.
        parent_from_bone_quat: (T, B, 4) float64 (w, x, y, z).
        root_pos: (T, 3) float64, metres, world.
        rate_hz: frame rate (> 0); ``time_s = frame / rate_hz``.
        order: one of the 12 sequences.
        degrees: degree columns (else radians).

    Raises:
        ValueError: a bad order, rate or shapes.
    """
    q = np.asarray(parent_from_bone_quat, dtype=np.float64)
    pos = np.asarray(root_pos, dtype=np.float64)
    if q.ndim != 3 or q.shape[1:] != (len(bone_names), 4) or pos.shape != (len(q), 3):
        raise ValueError(
            f"need parent_from_bone_quat (T, {len(bone_names)}, 4) and root_pos "
            f"(T, 3); got {q.shape} and {pos.shape}"
        )
    if not (math.isfinite(rate_hz) and rate_hz > 0.0):
        raise ValueError(f"rate_hz must be > 0; got {rate_hz}")
    angles = euler_table(q, order, degrees=degrees).reshape(len(q), -1)
    frames = np.arange(len(q))
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(euler_columns(bone_names, order, degrees=degrees))
        for t in range(len(q)):
            w.writerow(
                [int(frames[t]), f"{t / rate_hz:.9g}"]
                + [f"{v:.9g}" for v in pos[t]]
                + [f"{v:.9g}" for v in angles[t]]
            )
