"""``retargetd solve --out take.mcap``: a solve as Foxglove channels.

Joins the solve's arrays (the NPZ keys of ``retargetd solve``) and the rig's bone
layout (:class:`~retargetd.daemon.console.snapshot.SkeletonProgram`) to
:func:`retargetd.replay.foxglove.write_solve_mcap` (``replay`` may not import the
daemon, so the bone ends are placed here).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from retargetd.daemon.console.snapshot import SkeletonProgram, bone_endpoints
from retargetd.replay.foxglove import solve_health, write_solve_mcap


def solve_bone_ends(arrays: Mapping[str, Any], rig: Any) -> np.ndarray:
    """(T, B, 2, 3) metres world: both ends of every bone of a solve.

    Args:
        arrays: the solve's arrays by NPZ key (``joint_names``, ``joint_centres``,
            ``world_from_bone_quat``, ``root_pos``, ``bone_lengths``).
        rig: the rig it was solved with (``retargetd.daemon.body.rig.Rig``).
    """
    program = SkeletonProgram.from_rig(rig, [str(n) for n in arrays["joint_names"]])
    return bone_endpoints(
        program,
        np.asarray(arrays["joint_centres"], np.float64),
        np.asarray(arrays["world_from_bone_quat"], np.float64),
        np.asarray(arrays["root_pos"], np.float64),
        np.asarray(arrays["bone_lengths"], np.float64),
    )


def write_solve_foxglove(
    path: str | os.PathLike[str],
    arrays: Mapping[str, Any],
    rig: Any,
    *,
    markers: np.ndarray | None = None,
    marker_valid: np.ndarray | None = None,
    library: str = "retargetd",
    progress: Callable[[int], None] | None = None,
    face: Mapping[str, Any] | None = None,
) -> int:
    """Write a solve as an MCAP of Foxglove channels (with ``face``: the ``face_*``
    arrays of ``retargetd solve --face``, on ``/face/weights``).

    Args:
        path: the ``.mcap`` to write.
        arrays: the solve's arrays by NPZ key (as ``retargetd solve`` saves them).
        rig: the rig it was solved with.
        markers: (T, M, 3) metres world, the take's markers (shown as spheres).
        marker_valid: (T, M) bool.
        library: the MCAP header's library string (``"retargetd 0.1.0"``).
        progress: called with 1 after each frame written.

    Returns:
        Frames written.
    """
    flags = np.asarray(arrays["bone_flags"], np.uint8)
    rms = arrays.get("marker_rms")
    return write_solve_mcap(
        path,
        bone_names=[str(n) for n in arrays["bone_names"]],
        bone_parents=[int(p) for p in arrays["bone_parents"]],
        bone_ends=solve_bone_ends(arrays, rig),
        world_from_bone_quat=np.asarray(arrays["world_from_bone_quat"], np.float64),
        rate_hz=float(arrays["rate_hz"]),
        bone_flags=flags,
        markers=markers,
        marker_valid=marker_valid,
        library=library,
        progress=progress,
        health=solve_health(
            float(arrays["rate_hz"]), flags, marker_valid,
            None if rms is None else np.asarray(rms, np.float64),
        ),
        face=face,
    )  # fmt: skip
