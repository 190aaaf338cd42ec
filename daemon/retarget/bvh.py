"""A solved take as BVH: the calibrated skeleton's hierarchy and the solve's motion.

``retargetd solve TAKE ... --out take.bvh`` writes through
:func:`retargetd.replay.bvh.write_bvh`. The file frame is Y up, centimetres:

    p_bvh = BVH_CM_PER_M * BVH_FROM_WORLD @ p_world,
    BVH_FROM_WORLD = world_from_capture_mat("+Y").T      (world +Z -> BVH +Y,
                                                          world -Y -> BVH +Z)

i.e. a +Y-up capture frame, the same convention a +Y-up take is read in with (README
"Conventions"). Blender's BVH importer, with its defaults (forward -Z, up Y), maps
this frame back onto our world exactly.

Hierarchy: one BVH joint per rig bone, named as the bone, at the bone's origin. The
rest pose of a BVH file has every joint at identity, its axes parallel to the file's;
our calibration pose is taken as that rest pose:

    OFFSET_j  = cm * M (o_j - o_parent(j))          o = calibrated bone origins, world
    OFFSET_root = 0                                  (the root's position channels
                                                      hold its absolute position)
    End Site  = cm * M (rest_world_from_bone_j * (0, L_j, 0))     leaf bones: the aim

Motion: with D_j(t) = world_from_bone_j(t) * conj(rest_world_from_bone_j), the bone's
rotation away from its calibration pose in world axes, and G_j = M D_j M^T (the same
rotation in file axes; M is a proper rotation, so as a quaternion G = (w, M v)),

    R_root(t) = G_root(t),   R_j(t) = conj(G_parent(t)) * G_j(t)   (parent-relative)
    position channels of the root = cm * M * root_pos(t)

written as Euler angles in degrees of the chosen order (``"ZXY"``: the channels
``Zrotation Xrotation Yrotation``, R = R_Z R_X R_Y), unwrapped over time. BVH forward
kinematics (global = product of channel rotations down the chain; position = parent
position + parent global * OFFSET) then gives back G_j(t) for every joint and the
posed skeleton of :func:`posed_bone_origins`: the calibrated (rigid) skeleton posed by
the solved rotations. That is what a BVH can hold: bone lengths are fixed, so the
joints sit where the calibrated skeleton puts them, not at the marker-derived joint
centres of that frame (they differ by the segments' length variation).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from retargetd.daemon.body.calibration import Calibration, CalibrationError
from retargetd.daemon.body.solve import BodySolve
from retargetd.daemon.rotations import euler_from_quat, quat_conj, quat_mul, quat_rotate
from retargetd.protocols.conventions import world_from_capture_mat
from retargetd.protocols.frames import F64Array
from retargetd.replay.bvh import (
    BvhSkeleton,
    bvh_motion,
    bvh_skeleton,
    normalize_rotation_order,
    write_bvh,
)

logger = logging.getLogger(__name__)

#: Rotation from the internal world (Z up) to the BVH file's axes (Y up).
BVH_FROM_WORLD = np.ascontiguousarray(world_from_capture_mat("+Y").T)
BVH_FROM_WORLD.flags.writeable = False
#: Length unit of the file.
BVH_CM_PER_M = 100.0
#: Default rotation order of every joint's channels.
DEFAULT_ROTATION_ORDER = "ZXY"


def _rest_origins(calibration: Calibration) -> F64Array:
    origins = calibration.rest_bone_origin_pos
    if origins is None:
        raise CalibrationError(
            f"calibration for rig {calibration.rig_name!r} has no bone rest origins "
            "(written by an older retargetd): recalibrate to export BVH"
        )
    return np.asarray(origins, dtype=np.float64)


def _check_one_root(calibration: Calibration) -> None:
    roots = [n for n, p in zip(calibration.bone_names, calibration.bone_parents,
                               strict=True) if p < 0]  # fmt: skip
    if len(roots) != 1 or calibration.bone_parents[0] != -1:
        raise CalibrationError(
            f"BVH holds one root bone, listed first; rig {calibration.rig_name!r} "
            f"has roots {roots}"
        )


def bvh_skeleton_from_calibration(
    calibration: Calibration,
    *,
    rotation_order: str = DEFAULT_ROTATION_ORDER,
    root_rotation_order: str | None = None,
) -> BvhSkeleton:
    """The BVH hierarchy of a calibrated skeleton (see the module docstring).

    Args:
        calibration: the calibrated skeleton (with bone rest origins).
        rotation_order: every joint's rotation channels, one of
            :data:`retargetd.replay.bvh.ROTATION_ORDERS`.
        root_rotation_order: the root's, when it should differ.

    Returns:
        The skeleton: offsets and End Sites in centimetres, file axes (Y up).

    Raises:
        CalibrationError: no rest origins, or not exactly one root bone.
        ValueError: a bad rotation order.
    """
    _check_one_root(calibration)
    origins = _rest_origins(calibration)
    parents = np.asarray(calibration.bone_parents, dtype=np.int64)
    rel = origins - np.where(parents[:, None] >= 0, origins[parents], origins)
    offsets = BVH_CM_PER_M * rel @ BVH_FROM_WORLD.T
    n = len(calibration.bone_names)
    aim = np.zeros((n, 3))
    aim[:, 1] = calibration.bone_lengths
    tips = quat_rotate(calibration.rest_world_from_bone_quat, aim)
    is_leaf = ~np.isin(np.arange(n), parents)
    end_sites = np.where(
        is_leaf[:, None], BVH_CM_PER_M * tips @ BVH_FROM_WORLD.T, np.nan
    )
    order = normalize_rotation_order(rotation_order)
    root_order = normalize_rotation_order(root_rotation_order or order)
    return bvh_skeleton(
        joint_names=calibration.bone_names,
        parents=calibration.bone_parents,
        offsets=offsets,
        rotation_orders=[root_order] + [order] * (n - 1),
        end_sites=end_sites,
    )


def _bvh_from_world_quat(q: F64Array) -> F64Array:
    out = np.array(q, dtype=np.float64)
    out[..., 1:] = q[..., 1:] @ BVH_FROM_WORLD.T
    return out


def bvh_frames_from_solve(
    calibration: Calibration, solve: BodySolve, skeleton: BvhSkeleton
) -> F64Array:
    """The motion lines of a solved take (see the module docstring).

    Args:
        calibration: the calibration the take was solved with.
        solve: the solved take (``world_from_bone_quat`` (T, B, 4) w x y z,
            ``root_pos`` (T, 3) metres, world).
        skeleton: from :func:`bvh_skeleton_from_calibration` (its rotation orders).

    Returns:
        (T, n_channels) float64: centimetres and degrees.
    """
    return bvh_frames_from_world(
        calibration, solve.world_from_bone_quat, solve.root_pos, skeleton
    )


def bvh_frames_from_world(
    calibration: Calibration,
    world_from_bone_quat: F64Array,
    root_pos: F64Array,
    skeleton: BvhSkeleton,
) -> F64Array:
    """The motion lines of bone rotations in the world (see the module docstring).

    Args:
        calibration: the calibrated skeleton.
        world_from_bone_quat: (T, B, 4) float64 (w, x, y, z).
        root_pos: (T, 3) float64, metres, world.
        skeleton: from :func:`bvh_skeleton_from_calibration` (its rotation orders).

    Returns:
        (T, n_channels) float64: centimetres and degrees.
    """
    wfb = np.asarray(world_from_bone_quat, dtype=np.float64)
    parents = np.asarray(calibration.bone_parents, dtype=np.int64)
    moved = quat_mul(wfb, quat_conj(calibration.rest_world_from_bone_quat))  # D
    moved_bvh = _bvh_from_world_quat(moved)  # G = M D M^T
    rel = quat_mul(quat_conj(moved_bvh[:, np.maximum(parents, 0)]), moved_bvh)
    rel[:, parents < 0] = moved_bvh[:, parents < 0]
    angles = np.zeros((*rel.shape[:-1], 3))
    for order in set(skeleton.rotation_orders):
        cols = [j for j, o in enumerate(skeleton.rotation_orders) if o == order]
        angles[:, cols] = euler_from_quat(rel[:, cols], order)
    angles_deg = np.unwrap(np.degrees(angles), period=360.0, axis=0)
    positions = np.full_like(angles_deg, np.nan)
    positions[:, 0] = BVH_CM_PER_M * np.asarray(root_pos) @ BVH_FROM_WORLD.T
    return bvh_motion(skeleton, angles_deg, positions)


def world_from_parent_chain(
    parents: tuple[int, ...] | list[int], parent_from_bone_quat: F64Array
) -> F64Array:
    """Forward kinematics of rotations: ``world_from_bone`` down the chain.

    Args:
        parents: (B,) parent index per bone, -1 for a root; parents before children.
        parent_from_bone_quat: (T, B, 4) float64 (w, x, y, z); a root's is
            ``world_from_root``.

    Returns:
        (T, B, 4) float64 (w, x, y, z) ``world_from_bone``.
    """
    q = np.asarray(parent_from_bone_quat, dtype=np.float64)
    out = np.empty_like(q)
    for b, p in enumerate(parents):
        out[:, b] = q[:, b] if p < 0 else quat_mul(out[:, p], q[:, b])
    return out


def posed_bone_origins(
    calibration: Calibration, world_from_bone_quat: F64Array, root_pos: F64Array
) -> F64Array:
    """The calibrated skeleton posed by solved rotations: what the BVH file holds.

    ``o_j(t) = o_parent(t) + D_parent(t) (o_j - o_parent)`` from the calibrated origins,
    with ``o_root(t) = root_pos(t)`` and ``D`` as in the module docstring.

    Args:
        calibration: the calibrated skeleton (with bone rest origins).
        world_from_bone_quat: (T, B, 4) float64, w x y z.
        root_pos: (T, 3) float64, metres, world.

    Returns:
        (T, B, 3) float64, metres, world: each bone's origin.
    """
    origins = _rest_origins(calibration)
    moved = quat_mul(
        np.asarray(world_from_bone_quat, dtype=np.float64),
        quat_conj(calibration.rest_world_from_bone_quat),
    )
    out = np.zeros((*moved.shape[:-1], 3))
    for j, p in enumerate(calibration.bone_parents):  # parents come first
        if p < 0:
            out[:, j] = root_pos
        else:
            out[:, j] = out[:, p] + quat_rotate(moved[:, p], origins[j] - origins[p])
    return out


def write_solve_bvh(
    path: str | Path,
    calibration: Calibration,
    solve: BodySolve,
    rate_hz: float,
    *,
    rotation_order: str = DEFAULT_ROTATION_ORDER,
    root_rotation_order: str | None = None,
) -> BvhSkeleton:
    """Write a solved take as BVH (centimetres, Y up).

    Args:
        path: the ``.bvh`` file.
        calibration: the calibration the take was solved with.
        solve: the solved take.
        rate_hz: the take's frame rate.
        rotation_order: every joint's channel order (default ``"ZXY"``).
        root_rotation_order: the root's, when it should differ.

    Returns:
        The hierarchy written.

    Raises:
        CalibrationError: no rest origins, or not exactly one root bone.
        ValueError: a bad rotation order or rate.
    """
    if not (np.isfinite(rate_hz) and rate_hz > 0):
        raise ValueError(f"rate_hz must be > 0; got {rate_hz}")
    skeleton = bvh_skeleton_from_calibration(
        calibration,
        rotation_order=rotation_order,
        root_rotation_order=root_rotation_order,
    )
    frames = bvh_frames_from_solve(calibration, solve, skeleton)
    write_bvh(path, skeleton, frames, 1.0 / rate_hz)
    return skeleton


def write_clip_bvh(
    path: str | Path,
    calibration: Calibration,
    parent_from_bone_quat: F64Array,
    root_pos: F64Array,
    rate_hz: float,
    *,
    rotation_order: str = DEFAULT_ROTATION_ORDER,
    root_rotation_order: str | None = None,
) -> BvhSkeleton:
    """Write a clip (true parent-relative rotations, e.g. a blend or a loop) as BVH.

    Args:
        path: the ``.bvh`` file.
        calibration: the calibrated skeleton the clip's bones are.
        parent_from_bone_quat: (T, B, 4) float64 (w, x, y, z).
        root_pos: (T, 3) float64, metres, world.
        rate_hz: frame rate.
        rotation_order: every joint's channel order (default ``"ZXY"``).
        root_rotation_order: the root's, when it should differ.

    Returns:
        The hierarchy written.

    Raises:
        CalibrationError: no rest origins, or not exactly one root bone.
        ValueError: a bad rotation order or rate.
    """
    if not (np.isfinite(rate_hz) and rate_hz > 0):
        raise ValueError(f"rate_hz must be > 0; got {rate_hz}")
    skeleton = bvh_skeleton_from_calibration(
        calibration,
        rotation_order=rotation_order,
        root_rotation_order=root_rotation_order,
    )
    wfb = world_from_parent_chain(calibration.bone_parents, parent_from_bone_quat)
    frames = bvh_frames_from_world(calibration, wfb, root_pos, skeleton)
    write_bvh(path, skeleton, frames, 1.0 / rate_hz)
    return skeleton
