"""A solved take as glTF 2.0 binary: every frame, or the keys of a reduction.

Nodes are the calibrated skeleton's bones (as :mod:`retargetd.daemon.target.bvh`: the
calibration pose is the rest pose, bone lengths fixed), under a scene root node that
turns our +Z-up world into glTF's +Y up (:data:`GLTF_FROM_WORLD_QUAT`, the same axes
as the BVH export: world +Z -> +Y, world -Y -> +Z):

    rest translation_j = conj(rest_world_from_bone_p) (o_j - o_p)     metres
    rest rotation_j    = rest_parent_from_bone_j   (root: rest_world_from_root)
    rotation_j(t)      = solve.parent_from_bone_j(t)
    translation_root(t) = root_pos(t)   (world, metres)

``solve.parent_from_bone_quat`` is the whole parent-relative rotation
(``rest_parent_from_bone ⊗ solve.rest_from_bone``), which is what a glTF node
rotation is: ``parent_from_node``.

Blender's importer (default options) turns the file back into our world, metres:
each bone becomes an empty at the bone's origin, its axes ``world_from_bone ⊗
gltf_from_world`` (the importer re-labels every node's own axes Y-up to Z-up as
well); ``tests/daemon/post/test_gltf_blender.py`` checks this.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.calibration import Calibration, CalibrationError
from retargetd.daemon.body.solve import BodySolve
from retargetd.daemon.post.interp import Clip
from retargetd.daemon.post.reduce import KeyChannel, ReducedClip
from retargetd.protocols.frames import F64Array
from retargetd.replay.gltf import GltfChannel, write_glb

#: glTF (+Y up) from our world (+Z up): -90° about x, (w, x, y, z).
GLTF_FROM_WORLD_QUAT = np.array([math.sqrt(0.5), -math.sqrt(0.5), 0.0, 0.0])
GLTF_FROM_WORLD_QUAT.flags.writeable = False


def clip_from_solve(solve: BodySolve, calibration: Calibration, rate_hz: float) -> Clip:
    """The solve's whole ``parent_from_bone`` rotations and root as a :class:`Clip`.

    Args:
        solve: the solved take (finite where it is to be exported).
        calibration: the calibration it was solved with.
        rate_hz: the take's frame rate.

    Returns:
        The clip: ``solve.parent_from_bone_quat`` (T, B, 4) and the root.
    """
    del calibration  # the solve's parent_from_bone already holds the rest pose
    return Clip(
        parent_from_bone_quat=np.array(solve.parent_from_bone_quat, dtype=np.float64),
        root_pos=np.asarray(solve.root_pos, dtype=np.float64),
        rate_hz=float(rate_hz),
    )


def _skeleton(calibration: Calibration) -> tuple[F64Array, F64Array]:
    origins = calibration.rest_bone_origin_pos
    if origins is None:
        raise CalibrationError(
            f"calibration for rig {calibration.rig_name!r} has no bone rest origins "
            "(written by an older retargetd): recalibrate to export glTF"
        )
    o = np.asarray(origins, dtype=np.float64)
    parents = np.asarray(calibration.bone_parents, dtype=np.int64)
    wfb = np.asarray(calibration.rest_world_from_bone_quat, dtype=np.float64)
    p = np.maximum(parents, 0)
    trans = rot.quat_rotate(rot.quat_conj(wfb[p]), o - o[p])
    trans[parents < 0] = o[parents < 0]
    quat = np.array(calibration.rest_parent_from_bone_quat, dtype=np.float64)
    quat[parents < 0] = wfb[parents < 0]
    return trans, quat


def write_reduced_glb(
    path: str | Path, reduced: ReducedClip, calibration: Calibration
) -> None:
    """Write a reduced take (:func:`retargetd.daemon.post.reduce.reduce_clip` of a
    :func:`clip_from_solve` clip): one channel per bone and the root's translation.

    Args:
        path: destination ``.glb``.
        reduced: the keys.
        calibration: the skeleton.

    Raises:
        CalibrationError: no bone rest origins in the calibration.
        ValueError: the keys do not fit the skeleton.
    """
    names = calibration.bone_names
    if len(reduced.rotations) != len(names):
        raise ValueError(
            f"reduced take has {len(reduced.rotations)} rotation channels, the "
            f"skeleton {len(names)} bones"
        )
    trans, quat = _skeleton(calibration)
    dt = 1.0 / reduced.rate_hz
    channels = [
        GltfChannel(
            node=b,
            path="rotation",
            times_s=np.asarray(ch.frames * dt, dtype=np.float64),
            values=ch.values,
        )
        for b, ch in enumerate(reduced.rotations)
    ]
    root = int(np.flatnonzero(np.asarray(calibration.bone_parents) < 0)[0])
    channels.append(
        GltfChannel(
            node=root,
            path="translation",
            times_s=np.asarray(reduced.root.frames * dt, dtype=np.float64),
            values=reduced.root.values,
        )
    )
    write_glb(
        path,
        names=names,
        parents=calibration.bone_parents,
        rest_translation=trans,
        rest_rotation_quat=quat,
        channels=channels,
        scene_root_quat=GLTF_FROM_WORLD_QUAT,
    )


def write_clip_glb(path: str | Path, clip: Clip, calibration: Calibration) -> None:
    """Write every frame of a clip (no reduction).

    Args:
        path: destination ``.glb``.
        clip: from :func:`clip_from_solve` (finite).
        calibration: the skeleton.

    Raises:
        CalibrationError: no bone rest origins in the calibration.
    """
    frames = np.arange(clip.n_frames)

    def keys(values: F64Array) -> KeyChannel:
        return KeyChannel(frames=frames, values=values, max_error=0.0, refitted=False)

    q = clip.parent_from_bone_quat
    reduced = ReducedClip(
        rotations=tuple(keys(q[:, b]) for b in range(q.shape[1])),
        root=keys(clip.root_pos),
        n_frames=clip.n_frames,
        rate_hz=clip.rate_hz,
    )
    write_reduced_glb(path, reduced, calibration)
