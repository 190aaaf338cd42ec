"""A solved take as glTF 2.0 binary: every frame, or the keys of a reduction.

The calibrated skeleton is a glTF **skin** (:mod:`retargetd.replay.gltf`): one joint
node per bone (as :mod:`retargetd.daemon.retarget.bvh`: the calibration pose is the rest
pose and the bind pose, bone lengths fixed), under a scene root node ``world`` that
turns our +Z-up world into glTF's +Y up (:data:`GLTF_FROM_WORLD_QUAT`, the same axes
as the BVH export: world +Z -> +Y, world -Y -> +Z):

    rest translation_j = conj(rest_world_from_bone_p) (o_j - o_p)     metres
    rest rotation_j    = rest_parent_from_bone_j   (root: rest_world_from_root)
    inverse bind_j     = (gltf_from_world ⊗ rest_world_from_bone_j, o_j)^-1
    rotation_j(t)      = solve.parent_from_bone_j(t)
    translation_root(t) = root_pos(t)   (world, metres)

``solve.parent_from_bone_quat`` is the whole parent-relative rotation
(``rest_parent_from_bone ⊗ solve.rest_from_bone``), which is what a glTF node
rotation is: ``parent_from_node``.

Names: a bone the rig maps onto the standard humanoid is named by it (``Hips``,
``LeftUpperArm``; the NPZ's ``bone_humanoid``), any other by the rig's name; every
joint node's ``extras`` keeps ``{"rig_bone": NAME}`` (and ``"humanoid"`` when mapped).

Mesh (``mesh="capsules"``, CLI ``--glb-mesh capsules``): one capsule per bone
(:func:`retargetd.replay.gltf_mesh.bone_capsule`: radius 0.15 of the length, at
least 1 cm) along the bone's +Y from its origin to ``bone_length``, every vertex
weighted 1 to its bone. Without it (the default) the file holds the skin alone,
which is enough for an armature (Blender 3.4 builds one from the skin's joints).

Blender's importer (default options) turns the file back into our world, metres:
the ``world`` node becomes the armature object and each bone a bone of it, posed at
``world_from_bone(t)`` relative to its rest ``rest_world_from_bone`` (the importer's
bone-direction heuristic changes each bone's rest axes by a constant rotation, which
cancels in that relative pose); ``tests/daemon/post/test_gltf_blender.py`` checks this.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.calibration import Calibration, CalibrationError
from retargetd.daemon.body.solve import BodySolve
from retargetd.daemon.post.interp import Clip
from retargetd.daemon.post.reduce import KeyChannel, ReducedClip
from retargetd.protocols.frames import F64Array
from retargetd.replay.gltf import GltfChannel, MorphFace, write_glb
from retargetd.replay.gltf_mesh import Capsule, bone_capsule, check_mesh

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


def node_names(
    bone_names: Sequence[str], humanoid: Sequence[str] | None
) -> tuple[list[str], list[dict[str, Any]]]:
    """Each bone's node name and ``extras`` (module docstring).

    Args:
        bone_names: (B,) the rig's bone names.
        humanoid: (B,) each bone's standard humanoid name, ``""`` when unmapped (the
            NPZ's ``bone_humanoid``); None: the rig's names throughout.

    Returns:
        ``(names, extras)``. When a humanoid name would repeat another node's name
        (an unmapped bone called like a mapped one), every node keeps its rig name.

    Raises:
        ValueError: ``humanoid`` of another length.
    """
    extras: list[dict[str, Any]] = [{"rig_bone": str(b)} for b in bone_names]
    if humanoid is None:
        return [str(b) for b in bone_names], extras
    if len(humanoid) != len(bone_names):
        raise ValueError(
            f"need {len(bone_names)} humanoid names (one per bone); got {len(humanoid)}"
        )
    names = [str(h) if h else str(b) for b, h in zip(bone_names, humanoid, strict=True)]
    for e, h in zip(extras, humanoid, strict=True):
        if h:
            e["humanoid"] = str(h)
    if len(set(names)) != len(names):
        names = [str(b) for b in bone_names]
    return names, extras


def bone_capsules(calibration: Calibration) -> list[Capsule]:
    """One capsule per bone, along its +Y from its origin to its length (metres, the
    bone's frame; :func:`~retargetd.replay.gltf_mesh.bone_capsule`)."""
    lengths = np.asarray(calibration.bone_lengths, dtype=np.float64)
    return [
        bone_capsule(b, np.array([0.0, length, 0.0]))
        for b, length in enumerate(lengths)
    ]


def write_reduced_glb(
    path: str | Path,
    reduced: ReducedClip,
    calibration: Calibration,
    *,
    humanoid: Sequence[str] | None = None,
    mesh: str = "none",
    face: MorphFace | None = None,
) -> None:
    """Write a reduced take (:func:`retargetd.daemon.post.reduce.reduce_clip` of a
    :func:`clip_from_solve` clip): one channel per bone and the root's translation,
    on the skin (module docstring).

    Args:
        path: destination ``.glb``.
        reduced: the keys.
        calibration: the skeleton.
        humanoid: (B,) each bone's humanoid name or ``""`` (:func:`node_names`).
        mesh: ``"none"`` (the skin alone) or ``"capsules"``.
        face: the face as morph targets (``retargetd solve --face``), or None.

    Raises:
        CalibrationError: no bone rest origins in the calibration.
        ValueError: the keys do not fit the skeleton; an unknown mesh.
    """
    check_mesh(mesh)
    names, extras = node_names(calibration.bone_names, humanoid)
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
        node_extras=extras,
        capsules=bone_capsules(calibration) if mesh == "capsules" else (),
        face=face,
    )


def write_clip_glb(
    path: str | Path,
    clip: Clip,
    calibration: Calibration,
    *,
    humanoid: Sequence[str] | None = None,
    mesh: str = "none",
    face: MorphFace | None = None,
) -> None:
    """Write every frame of a clip (no reduction), on the skin (module docstring).

    Args:
        path: destination ``.glb``.
        clip: from :func:`clip_from_solve` (finite).
        calibration: the skeleton.
        humanoid: (B,) each bone's humanoid name or ``""`` (:func:`node_names`).
        mesh: ``"none"`` (the skin alone) or ``"capsules"``.
        face: the face as morph targets (``retargetd solve --face``), or None.

    Raises:
        CalibrationError: no bone rest origins in the calibration.
        ValueError: an unknown mesh.
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
    write_reduced_glb(
        path, reduced, calibration, humanoid=humanoid, mesh=mesh, face=face
    )
