"""``retargetd retarget ... --plant-feet``: a BVH take retargeted onto a BVH target
with its stance feet planted (issue 34 item 2), by the stage ``solve --plant-feet``
runs (``post/plant.py`` :class:`FootPlant`, :meth:`FootPlant.plant_take`), fed by the
stance detector on the source's joints (``post/stance.py``
:func:`take_stance_states`, each contact's support settled over the contact), the
source's rig, calibration and floor and the target's legs made from the two
hierarchies (``retarget/bvh_legs.py``).

The root: the plant scales the root's height and travel by the leg ratio ``k``
(the target's leg length over the source's, both the UpperLeg joints' height over
the lowest foot point at rest): the target's root joint at ``k (p - (0, 0, h_s)) +
(0, 0, h_t)``, ``p`` the source's root joint over its floor, ``h`` each root's rest
height above its feet. Written over a floor at ``k`` times the source's (the
source's world scaled by ``k`` about its origin, as the retarget's own root scale
scales it).

Not a command module (``cli/retarget.py`` imports it).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from retargetd.daemon import rotations as rot
from retargetd.daemon.errors import UsageError
from retargetd.daemon.post.plant import FootPlant
from retargetd.daemon.post.plant_target import (
    LEG_MIN_M,
    performer_leg_m,
    target_leg_m,
)
from retargetd.daemon.post.stance import CONTACT_COLUMN, take_stance_states
from retargetd.daemon.retarget.bvh_legs import (
    SOURCE_LEGS,
    TARGET_LEGS,
    PlantTarget,
    missing_legs,
    source_humanoid,
    source_motion,
    source_rig,
    take_floor,
    target_humanoid,
)
from retargetd.daemon.retarget.bvh_retarget import BvhRetarget, motion_lines
from retargetd.replay.bvh import BvhSkeleton


@dataclass(frozen=True, slots=True, kw_only=True)
class PlantedRetarget:
    """The planted take and what the plant found.

    Attributes:
        result: the retarget with the target's legs and root planted
            (``root_scale`` the leg ratio).
        leg_ratio: the target's leg length over the source's.
        source_leg_m, target_leg_m: the leg lengths, metres.
        floor_m: the source's floor, metres along its +Y (``bvh_legs.take_floor``).
        contact: (T, 2) bool, left and right foot in contact (the detector's).
        flags: (T,) uint32, ``FRAME_PLANT_UNREACHED`` where a foot could not reach
            its hold.
    """

    result: BvhRetarget
    leg_ratio: float
    source_leg_m: float
    target_leg_m: float
    floor_m: float
    contact: np.ndarray
    flags: np.ndarray


def check_legs(
    source: BvhSkeleton, target: BvhSkeleton, mapping: tuple[int, ...]
) -> tuple[list[str | None], list[str | None]]:
    """Each file's humanoid names, once both have the legs the plant needs.

    Raises:
        UsageError: one line naming the file and the leg joints it lacks.
    """
    src = source_humanoid(source)
    tgt = target_humanoid(source, target, mapping)
    for what, sk, names, wanted in (
        ("source", source, src, SOURCE_LEGS),
        ("target", target, tgt, TARGET_LEGS),
    ):
        gone = missing_legs(names, wanted)
        if gone:
            raise UsageError(
                f"--plant-feet: the {what} {sk.source} has no joint named (or mapped) "
                f"as {', '.join(gone)}: the stance feet need identifiable legs"
            )
    return src, tgt


def plant_retarget(
    source: BvhSkeleton,
    target: BvhSkeleton,
    result: BvhRetarget,
    *,
    source_m_per_unit: float,
    target_m_per_unit: float,
) -> PlantedRetarget:
    """Plant the stance feet of a retarget (module docstring).

    Args:
        source: the take, read with motion.
        target: the hierarchy it was mapped onto.
        result: :func:`~retargetd.daemon.retarget.bvh_retarget.retarget_bvh`'s.
        source_m_per_unit, target_m_per_unit: metres per each file's unit.

    Returns:
        The planted take and the plant's figures.

    Raises:
        UsageError: a file without identifiable legs, or legs the plant cannot use.
    """
    src_h, tgt_h = check_legs(source, target, result.mapping)
    rig, cal = source_rig(source, src_h, source_m_per_unit)
    wfb_s, joints_s = source_motion(source, cal, source_m_per_unit)
    floor = take_floor(rig, cal, wfb_s, joints_s)
    root_s = np.ascontiguousarray(joints_s[:, 0] - np.array([0.0, 0.0, floor]))
    rate_hz = 1.0 / result.frame_time_s
    states = take_stance_states(rig, cal, root_s, wfb_s, rate_hz)
    legs = PlantTarget.from_bvh(target, tgt_h, target_m_per_unit)
    units = "each file's length unit: --units, --source-units"
    try:
        leg_t = target_leg_m(legs)
        if not leg_t > LEG_MIN_M:  # the plant's own bound on the performer's
            raise ValueError(
                f"target leg length must be > {LEG_MIN_M} m; got {leg_t:.3f} m"
            )
        plant = FootPlant(legs, 1.0, performer_leg_m(rig, cal))
    except ValueError as exc:
        raise UsageError(f"--plant-feet: {exc} ({units})") from None
    wfb, rfb = legs.pose_world(result.parent_from_joint_quat)
    h_s = float(cal.root_rest_pos[2])  # the source root's rest height over its feet
    root = np.ascontiguousarray(root_s - np.array([0.0, 0.0, h_s]))
    hips = root + legs.rest_offsets[0]
    flags = plant.plant_take(wfb, rfb, root, hips, states, rate_hz)
    k = float(plant.leg_ratio)
    # p_file = A^T p_world, A the file's axes in the world (rows: p_world @ A)
    a = rot.mat_from_quat(legs.rest_world_from_bone_quat[0])
    root_file = (hips + np.array([0.0, 0.0, k * floor])) @ a / target_m_per_unit
    local = legs.file_rotations(rfb)
    planted = dataclasses.replace(
        result,
        frames=motion_lines(result.skeleton, local, root_file),
        parent_from_joint_quat=local,
        root_pos=root_file,
        root_scale=k,
    )
    return PlantedRetarget(
        result=planted,
        leg_ratio=k,
        source_leg_m=performer_leg_m(rig, cal),
        target_leg_m=leg_t,
        floor_m=floor,
        contact=states[:, :, CONTACT_COLUMN] != 0.0,
        flags=flags,
    )


def summary_line(planted: PlantedRetarget) -> str:
    """The ``--plant-feet`` line ``retarget`` prints: the leg ratio, the floor, the
    contact frames per foot, and the frames flagged ``plant_unreached`` (BVH and
    glTF carry no per-frame flags) with their runs, 0-based, half-open."""
    flags = planted.flags != 0
    d = np.diff(np.concatenate([[0], flags.astype(np.int8), [0]]))
    runs = [f"{a}:{b}" for a, b in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1),
                                       strict=True)]  # fmt: skip
    shown = " ".join(runs[:20]) + (
        f" (+{len(runs) - 20} more)" if len(runs) > 20 else ""
    )
    contact = planted.contact.sum(axis=0)
    return (
        f"planted feet: leg ratio {planted.leg_ratio:.4g} (target "
        f"{planted.target_leg_m:.3f} m, source {planted.source_leg_m:.3f} m), source "
        f"floor {planted.floor_m:+.4f} m, contact frames left {contact[0]} right "
        f"{contact[1]}, plant_unreached {int(flags.sum())} frames"
        + (f": {shown}" if runs else "")
    )
