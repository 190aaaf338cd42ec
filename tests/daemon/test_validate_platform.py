"""Stepping down from a platform is supported; hanging in the air with moving feet is
not.

The synthetic performer's skeleton (the shared clean take's model) is posed by hand:
the upper body in its calibration T-pose, the legs by a sagittal two-link inverse
kinematics that puts each ankle where its foot must be (feet pitching about their toes,
toes flat on the ground). Timeline (s): 0-1 standing still on a 35 cm platform; 1-2 the
right foot steps 30 cm forward and down to the floor, landing toes first, while the
left heel rises on the platform; 2-3 the left foot follows; 3-4 standing on the floor.
Support is inferred from the feet alone (``validate_dynamics.infer_contacts``): on the
platform from stillness, on the floor from height, so the whole take is supported and
its ghost force stays low. The same body hanging 30 cm up with its legs swinging (feet
never still, never near the floor) is floating and leaves ~1 body weight unexplained.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.calibration import calibrate
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.body.solve import BodySolve, BodySolver
from retargetd.daemon.validate import dynamics as vd
from retargetd.daemon.validate.checks import (
    THRESHOLDS,
    fit_pairs,
    pose_skeleton,
    validate_take,
)
from retargetd.daemon.validate.model import (
    Skeleton,
    build_model,
    skeleton_from_calibration,
)
from retargetd.replay.takes import load_take

RATE_HZ = 120.0
PLATFORM_M = 0.35
STEP_M = 0.30  # forward, per step
pytestmark = pytest.mark.usefixtures("mujoco_cwd")

Keys = list[tuple[float, Any]]


def _ease(t: np.ndarray, keys: Keys) -> np.ndarray:
    """Values through (time, value) keys, quintic smoothstep between keys."""
    values = [np.asarray(v, dtype=np.float64) for _, v in keys]
    out = np.empty((t.size, *values[0].shape))
    out[:] = values[0]
    for (t0, _), (t1, _), v0, v1 in zip(
        keys, keys[1:], values, values[1:], strict=False
    ):
        u = np.clip((t[t >= t0] - t0) / (t1 - t0), 0.0, 1.0)
        s = u * u * u * (u * (6.0 * u - 15.0) + 10.0)
        out[t >= t0] = v0 + (v1 - v0) * s.reshape(-1, *([1] * v0.ndim))
    return out


def _leg_ik(
    hip: np.ndarray, ankle: np.ndarray, thigh_m: float, shank_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Thigh and shank pitch from straight down (forward +, rad), knee bending back.

    hip, ankle: (T, 2) forward and up, metres.
    """
    dx, dz = ankle[:, 0] - hip[:, 0], ankle[:, 1] - hip[:, 1]
    d = np.hypot(dx, dz)
    assert (d <= thigh_m + shank_m + 1e-6).all(), "ankle out of reach"
    cos_hip = (thigh_m**2 + d**2 - shank_m**2) / (2.0 * thigh_m * d)
    cos_knee = (thigh_m**2 + shank_m**2 - d**2) / (2.0 * thigh_m * shank_m)
    thigh = np.arctan2(dx, -dz) + np.arccos(np.clip(cos_hip, -1.0, 1.0))
    return thigh, thigh - (np.pi - np.arccos(np.clip(cos_knee, -1.0, 1.0)))


def _pose(
    clean: Any, root_pos: np.ndarray, legs: Mapping[str, tuple[Any, ...]]
) -> BodySolve:
    """A solve of the clean take's skeleton: T-pose upper body, legs pitched about the
    performer's left by (thigh, shank, foot) angles (foot + = toes down; toes flat)."""
    skel: Skeleton = clean.skel
    n = root_pos.shape[0]
    rest = skel.rest_world_from_bone_quat
    wfb = np.tile(rest, (n, 1, 1))
    for side, (thigh, shank, foot) in legs.items():
        for bone, angle in (("thigh", -thigh), ("shank", -shank), ("foot", foot)):
            b = skel.bone_names.index(f"{side}_{bone}")
            turn = rot.quat_from_axis_angle(skel.left_world, angle)
            wfb[:, b] = rot.quat_mul(turn, rest[b])
    pfb = np.empty_like(wfb)
    for b, p in enumerate(skel.bone_parents):
        if p < 0:
            pfb[:, b] = rot.quat_mul(rot.quat_conj(rest[b]), wfb[:, b])
        else:
            rest_pfb = rot.quat_mul(rot.quat_conj(rest[p]), rest[b])
            pfb[:, b] = rot.quat_mul(
                rot.quat_conj(rest_pfb),
                rot.quat_mul(rot.quat_conj(wfb[:, p]), wfb[:, b]),
            )
    origins, aims = pose_skeleton(skel, root_pos, wfb)
    points = np.concatenate([origins, aims], axis=1)
    frame0 = np.zeros(n, dtype=np.int64)
    s = clean.solve
    joints = s.joint_centres[frame0]
    joints[:, clean.fit[0]] = points[:, clean.fit[1]]
    return dataclasses.replace(
        s, root_pos=root_pos, world_from_bone_quat=wfb, rest_from_bone_quat=pfb,
        joint_centres=joints, bone_quality=s.bone_quality[frame0],
        bone_flags=s.bone_flags[frame0],
    )  # fmt: skip


def _axes(skel: Skeleton) -> tuple[np.ndarray, np.ndarray]:
    up = np.array([0.0, 0.0, 1.0])
    return np.cross(skel.left_world, up), up


def _step_down(clean: Any) -> tuple[np.ndarray, BodySolve]:
    skel: Skeleton = clean.skel
    names = skel.bone_names
    fwd, up = _axes(skel)
    t = np.arange(int(4.0 * RATE_HZ)) / RATE_HZ
    root0 = skel.rest_origin_world[names.index("pelvis")]
    r0 = root0 @ up  # standing root height; the hips are level with it
    a0 = skel.rest_origin_world[names.index("l_foot")] @ up  # standing ankle height
    foot_m = skel.bone_lengths[names.index("l_foot")]
    toe = rot.quat_rotate(
        skel.rest_world_from_bone_quat[names.index("l_foot")], [0.0, foot_m, 0.0]
    )
    tx, tz = toe @ fwd, toe @ up  # ankle -> toe base, in the calibration pose
    h, s = PLATFORM_M, STEP_M
    root = _ease(t, [
        (0.0, [0.0, r0 + h]), (1.0, [0.0, r0 + h]), (2.0, [0.5 * s, r0]),
        (2.5, [0.8 * s, r0 - 0.02]), (3.0, [s, r0]),
    ])  # fmt: skip

    def foot(toe_keys: Keys, pitch_keys: Keys, lift: tuple[float, float]) -> Any:
        tip = _ease(t, toe_keys)
        pitch = np.radians(_ease(t, pitch_keys))
        c, si = np.cos(pitch), np.sin(pitch)
        u = np.clip((t - lift[0]) / (lift[1] - lift[0]), 0.0, 1.0)
        ankle = np.stack(
            [
                tip[:, 0] - (tx * c + tz * si),
                tip[:, 1] - (tz * c - tx * si) + 0.05 * np.sin(np.pi * u),
            ],
            axis=-1,
        )
        return ankle, pitch

    up_high, down_low = [tx, a0 + tz + h], [tx + s, a0 + tz]
    right = foot(
        [(0.0, up_high), (1.0, up_high), (2.0, down_low)],
        [(0.0, 0.0), (1.0, 0.0), (2.0, 25.0), (2.4, 0.0)],
        (1.0, 2.0),
    )
    left = foot(
        [(0.0, up_high), (2.0, up_high), (3.0, down_low)],
        [(0.0, 0.0), (1.1, 0.0), (2.0, 40.0), (2.35, 40.0), (3.0, 0.0)],
        (2.0, 3.0),
    )
    thigh_m = skel.bone_lengths[names.index("l_thigh")]
    shank_m = skel.bone_lengths[names.index("l_shank")]
    legs = {}
    for side, (ankle, pitch) in (("l", left), ("r", right)):
        legs[side] = (*_leg_ik(root, ankle, thigh_m, shank_m), pitch)
    root_pos = root0 + root[:, :1] * fwd + (root[:, 1:] - r0) * up
    return t, _pose(clean, root_pos, legs)


def test_stepping_down_from_a_platform_is_supported(clean_synth: Any) -> None:
    t, solve = _step_down(clean_synth)
    vm = clean_synth.vm
    rep = validate_take(vm, solve, RATE_HZ, fit=clean_synth.fit)
    print(
        "\nstep down: "
        + ", ".join(
            f"{n} max {np.nanmax(c.values):.3g}"
            for n, c in rep.checks.items()
            if n in ("floating", "ghost_force", "limits", "floor_penetration")
        )
    )
    assert rep.passed, {n: c.summary() for n, c in rep.checks.items() if c.n_flagged}
    assert rep.checks["floating"].values.max() == 0.0
    assert np.nanmax(rep.checks["ghost_force"].values) < THRESHOLDS["ghost_force_bw"]

    origins, aims = pose_skeleton(
        vm.skeleton, solve.root_pos, solve.world_from_bone_quat
    )
    pts, bones, _ = vd.foot_points(vm.skeleton, origins, aims)
    height = pts[..., 2] - vm.floor_z
    # Direct evidence (what the floating check counts): the floor or a still foot.
    contacts = vd.infer_contacts(pts, vm.floor_z, RATE_HZ, surfaces=False)
    assert contacts.any(axis=1).all()
    # On the platform, every foot point stands 35 cm up: supported by stillness alone.
    on_platform = t < 1.0
    assert (height[on_platform] > PLATFORM_M - 0.01).all()
    assert contacts[on_platform].all()
    # While the right foot steps down, the still left foot up there carries the body.
    names = vm.skeleton.bone_names
    left = np.isin(bones, [names.index("l_foot"), names.index("l_toes")])
    stepping = (t > 1.2) & (t < 1.8)
    assert not contacts[stepping][:, ~left].all(axis=1).any()  # right foot moving
    assert contacts[stepping][:, left].any(axis=1).all()
    assert (height[stepping][:, left] > PLATFORM_M - 0.01).all()
    # Standing on the floor at the end.
    assert (height[t > 3.2] < 0.1).all() and contacts[t > 3.2].all()
    # The ghost force's contacts add the platform around where the feet stood: the
    # right foot is on it while it lifts off, not while it is between the levels.
    around = vd.infer_contacts(pts, vm.floor_z, RATE_HZ)
    assert (around >= contacts).all()
    right = ~left
    lifting = (t > 1.0) & (t < 1.1)
    assert around[lifting][:, right].all()
    top = PLATFORM_M + vm.floor_z
    # Below the platform's band, and over 10 cm above the spots the feet will stand on
    # on the floor (the ankle capsule's bottom stands 5 cm up): in the air.
    between = (pts[..., 2] < top - 0.05) & (height > 0.2) & right
    assert between[(t > 1.0) & (t < 2.0)].any()
    assert not around[between].any()


def test_hanging_30cm_with_moving_feet_floats(clean_synth: Any) -> None:
    skel: Skeleton = clean_synth.skel
    _, up = _axes(skel)
    t = np.arange(int(3.0 * RATE_HZ)) / RATE_HZ
    root0 = skel.rest_origin_world[skel.bone_names.index("pelvis")]
    root_pos = np.tile(root0 + 0.3 * up, (t.size, 1))
    legs = {}
    for side, phase in (("l", 0.0), ("r", np.pi)):
        # Walking in the air at 1 Hz: straight legs swinging +-25 deg.
        swing = np.radians(25.0) * np.sin(2.0 * np.pi * t + phase)
        legs[side] = (swing, swing, np.zeros(t.size))
    solve = _pose(clean_synth, root_pos, legs)
    rep = validate_take(clean_synth.vm, solve, RATE_HZ, fit=clean_synth.fit)
    assert {"floating", "ghost_force"} <= set(rep.failed())
    assert rep.checks["floating"].values.max() > 1.0  # s, unsupported throughout
    ghost = rep.checks["ghost_force"].values
    assert 0.7 < np.nanmedian(ghost) < 1.3  # the body weight, unexplained
    # Everything else about the pose is fine.
    assert set(rep.failed()) == {"floating", "ghost_force"}


RISER_CASES = {
    "pig-walk": ("plug-in-gait", "btkdata/PiG_Motion-FlatFoot-Full.c3d",
                 "btkdata/PiG_Calibration-FlatFoot-Full.c3d", slice(None)),
    "motek-ballet": ("cmu41", "btkdata/MOTEK_ballet_reduced.trc",
                     "btkdata/MOTEK_T.trc", slice(None)),
    "tennis-serve": ("cmu41", "kineticstoolkit/kinematics_tennis_serve.c3d",
                     "kineticstoolkit/kinematics_tennis_serve.c3d", slice(0, 50)),
}  # fmt: skip


@pytest.mark.parametrize("name", list(RISER_CASES))
def test_real_take_on_a_riser_is_supported(datasets: Path, name: str) -> None:
    """Each real take raised 35 cm (walking, dancing, serving on a stage riser): no
    floating, and the ghost force the same as on the floor (heel strikes, landings and
    pivots on the riser are contacts, as near the floor)."""
    rig_name, take_path, static_path, frames = RISER_CASES[name]
    rig = load_rig(rig_name)
    static = load_take(datasets / static_path)
    cal = calibrate(
        rig, static.positions[frames], static.labels,
        take_measurements=static.measurements,
    )  # fmt: skip
    take = load_take(datasets / take_path)
    solve = BodySolver(rig, cal, take.labels).solve_take(take.positions)
    vm = build_model(skeleton_from_calibration(rig, cal))
    fit = fit_pairs(rig, solve.joint_names)
    ghost = {}
    for lift in (0.0, PLATFORM_M):
        up = np.array([0.0, 0.0, lift])
        raised = dataclasses.replace(
            solve, root_pos=solve.root_pos + up, joint_centres=solve.joint_centres + up
        )
        rep = validate_take(vm, raised, take.rate_hz, fit=fit)
        assert rep.passed, (lift, rep.failed())
        assert rep.checks["floating"].values.max() < 0.5  # s
        ghost[lift] = rep.checks["ghost_force"].values
    print(f"\n{name}: ghost force max floor {np.nanmax(ghost[0.0]):.3f}, "
          f"riser {np.nanmax(ghost[PLATFORM_M]):.3f} BW")  # fmt: skip
    np.testing.assert_allclose(ghost[PLATFORM_M], ghost[0.0], atol=0.02)
