"""Feet planted on the target (issue 34 item 2, ``daemon/post/plant.py``): a stance
foot held where it landed while the body moves over it, the leg out of reach
straightened toward its hold and flagged (never bent backwards), a zero correction
leaving the pose as solved, the release blended out with the knee never popping, no
allocation per frame; ``solve --plant-feet`` (the synthetic gaits' evidence:
``test_feet_evidence.py``)."""

from __future__ import annotations

import math
import tracemalloc
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from retargetd.daemon import rotations as rot
from retargetd.daemon.post.foot_roll import ball_roll
from retargetd.daemon.post.plant import PLANT, FootPlant, foot_points, roll_radius
from retargetd.daemon.retarget.retarget import default_humanoid, joint_positions_world
from retargetd.protocols.pose_stream import FRAME_PLANT_UNREACHED

RATE_HZ = 120.0
ALPHA = math.radians(15.0)  # hip flexion; the knee flexed 2 * ALPHA
LEG_M = 0.90  # the default humanoid's hip joints above its floor


def _crouch(target: Any, root_y: float, root_z: float) -> SimpleNamespace:
    """Both legs with the hips flexed ALPHA and the knees 2 ALPHA (the ankle under
    the hip, the foot flat), the root at (0, root_y, root_z): G, L, root, hips."""
    n = len(target.bone_names)
    g = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    x_axis = np.array([1.0, 0.0, 0.0])
    for side in ("Left", "Right"):
        ul, ll, ft = (target.index(side + b) for b in ("UpperLeg", "LowerLeg", "Foot"))
        g[ul] = rot.quat_from_axis_angle(x_axis, ALPHA)  # knee forward
        g[ll] = rot.quat_from_axis_angle(x_axis, -ALPHA)  # shank back
        for b in ("Foot", "Toes"):
            g[target.index(side + b)] = [1.0, 0.0, 0.0, 0.0]
        del ft
    parents = target.parents
    rfb = np.array(g)
    for i in range(1, n):
        rfb[i] = rot.quat_mul(rot.quat_conj(g[parents[i]]), g[i])
    root = np.array([0.0, root_y, root_z])
    return SimpleNamespace(
        world_from_bone_quat=g,
        rest_from_bone_quat=rfb,
        root_pos=root,
        hips_pos=root + target.rest_offsets[0],
    )


def _on_floor_z() -> float:
    """The root height that puts the crouched feet flat on the floor."""
    return 0.82 * (math.cos(ALPHA) - 1.0)


#: The left foot's heel raised 20 deg about the lateral axis (heel-off).
HEEL_UP = rot.quat_from_axis_angle(np.array([1.0, 0.0, 0.0]), math.radians(-20.0))


def _heel_lift(target: Any) -> float:
    """How far the root rises so that the foot pitched by HEEL_UP keeps its ball on
    the floor."""
    _, ball = foot_points(target)
    return float(ball[0, 2] - rot.quat_rotate(HEEL_UP, ball[0])[2])


def _pitch_left_foot(target: Any, pose: SimpleNamespace) -> None:
    """Pitch ``pose``'s left foot and toes by HEEL_UP in the world, its local
    rotation following."""
    lf, lt = target.index("LeftFoot"), target.index("LeftToes")
    g = pose.world_from_bone_quat
    g[lf] = rot.quat_mul(HEEL_UP, g[lf])
    g[lt] = rot.quat_mul(HEEL_UP, g[lt])
    pose.rest_from_bone_quat[lf] = rot.quat_mul(
        rot.quat_conj(g[target.parents[lf]]), g[lf]
    )


def _stance(left: bool, right: bool) -> np.ndarray:
    st = np.zeros((2, 4))
    st[0, 3], st[1, 3] = float(left), float(right)
    return st


def _run(
    stage: FootPlant, target: Any, frames: list[tuple[float, float, bool]]
) -> tuple[list[np.ndarray], list[int], list[np.ndarray]]:
    """Each frame (root y, root z, left in contact): the planted joints (N, 3), the
    flags, and the unplanted joints."""
    joints, flags, free = [], [], []
    for t, (y, z, left) in enumerate(frames):
        pose = _crouch(target, y, z)
        free.append(joint_positions_world(target, pose))
        flags.append(
            stage.apply(
                pose.world_from_bone_quat,
                pose.rest_from_bone_quat,
                pose.root_pos,
                pose.hips_pos,
                _stance(left, False),
                t / RATE_HZ,
            )
        )
        joints.append(joint_positions_world(target, pose))
    return joints, flags, free


def _knee_deg(target: Any, joints: np.ndarray, side: str = "Left") -> float:
    ul, ll, ft = (target.index(side + b) for b in ("UpperLeg", "LowerLeg", "Foot"))
    a, b = joints[ll] - joints[ul], joints[ft] - joints[ll]
    c = a @ b / np.linalg.norm(a) / np.linalg.norm(b)
    return math.degrees(math.acos(min(1.0, c)))


def test_the_stance_foot_stays_where_it_landed_as_the_body_moves_over_it() -> None:
    """The hips travel 8 cm forward over 0.25 s with the left foot in contact: its
    ankle stays put (< 1e-9 m) where the rotations alone carry it 8 cm; its knee
    stays bent forward (the knee ahead of the hip-ankle line); the swing foot (no
    contact) goes with the body untouched."""
    target = default_humanoid()
    stage = FootPlant(target, 1.0, LEG_M)
    z = _on_floor_z()
    frames = [(0.08 * min(t / 30.0, 1.0), z, True) for t in range(40)]
    joints, flags, free = _run(stage, target, frames)
    lf, rf = target.index("LeftFoot"), target.index("RightFoot")
    held = np.array([j[lf] for j in joints])
    moved = np.array([j[lf] for j in free])
    assert np.abs(held - held[0]).max() < 1e-9
    assert moved[-1, 1] - moved[0, 1] == pytest.approx(0.08, abs=1e-9)
    np.testing.assert_allclose([j[rf] for j in joints], [j[rf] for j in free],
                               atol=1e-12)  # fmt: skip
    knee = target.index("LeftLowerLeg")
    hip = target.index("LeftUpperLeg")
    for j in joints:  # the knee in front of the hip-ankle line (forward is +y)
        line = j[lf] - j[hip]
        off = (j[knee] - j[hip]) - line * ((j[knee] - j[hip]) @ line) / (line @ line)
        assert off[1] > 0.01
    assert not any(flags)


class _WritableArrays:
    """A target as a BVH's legs are (``cli/retarget_plant.py``): its rest arrays
    writable, where a ``TargetSkeleton``'s are read-only."""

    def __init__(self, target: Any) -> None:
        self._target = target

    def __getattr__(self, name: str) -> Any:
        value = getattr(self._target, name)
        if name in ("rest_world_from_bone_quat", "rest_offsets"):
            return np.array(value)
        return value


def test_a_target_with_writable_arrays_plants_alike_on_one_compiled_kernel() -> None:
    """Whether the target's rest arrays are read-only or not, the plant passes them
    on read-only: numba types the two apart and compiled its kernel twice (the
    post stages' largest) in one run."""
    from retargetd.daemon.post.plant import _plant_step

    target = default_humanoid()
    assert not target.rest_offsets.flags.writeable
    writable = _WritableArrays(target)
    assert writable.rest_offsets.flags.writeable
    z = _on_floor_z()
    frames = [(0.08 * min(t / 30.0, 1.0), z, True) for t in range(40)]
    a, _, _ = _run(FootPlant(target, 1.0, LEG_M), target, frames)
    b, _, _ = _run(FootPlant(writable, 1.0, LEG_M), target, frames)
    np.testing.assert_array_equal(np.array(a), np.array(b))
    assert _plant_step.signatures
    assert not any(sig[6].mutable or sig[7].mutable for sig in _plant_step.signatures)


def test_a_zero_correction_leaves_the_pose_as_solved() -> None:
    """Standing still with both feet flat on the floor and in contact: every
    rotation, the root and the hips come out as they went in (the IK of a goal where
    the ankle already is changes nothing)."""
    target = default_humanoid()
    stage = FootPlant(target, 1.0, LEG_M)
    for t in range(10):
        pose = _crouch(target, 0.0, _on_floor_z())
        before = {k: np.array(v) for k, v in vars(pose).items()}
        bits = stage.apply(
            pose.world_from_bone_quat, pose.rest_from_bone_quat, pose.root_pos,
            pose.hips_pos, _stance(True, True), t / RATE_HZ,
        )  # fmt: skip
        assert bits == 0
        for k, v in before.items():
            np.testing.assert_allclose(getattr(pose, k), v, atol=1e-12, err_msg=k)


def test_out_of_reach_the_leg_straightens_toward_its_hold_and_is_flagged() -> None:
    """The hips rise 20 cm while the left foot is held: the goal is past the
    straight leg, so the frame is flagged ``plant_unreached``, the knee reaches 0
    (straight: never negative, never bent backwards) at most ``knee_step_deg`` a
    frame, and the leg points at the hold."""
    target = default_humanoid()
    stage = FootPlant(target, 1.0, LEG_M)
    z0 = _on_floor_z()
    frames = [(0.0, z0 + 0.2 * min(t / 10.0, 1.0), True) for t in range(40)]
    joints, flags, _ = _run(stage, target, frames)
    hold = joints[0][target.index("LeftFoot")]
    knees = [_knee_deg(target, j) for j in joints]
    assert flags[-1] == FRAME_PLANT_UNREACHED and FRAME_PLANT_UNREACHED in flags
    assert min(knees) >= 0.0 and knees[-1] < 1e-6
    assert np.abs(np.diff(knees)).max() <= PLANT["knee_step_deg"] + 1e-9
    j = joints[-1]
    hip, ankle = j[target.index("LeftUpperLeg")], j[target.index("LeftFoot")]
    aim = (ankle - hip) / np.linalg.norm(ankle - hip)
    want = (hold - hip) / np.linalg.norm(hold - hip)
    assert np.degrees(np.arccos(min(1.0, aim @ want))) < 0.01


def test_a_knee_lagging_its_flexion_rolls_the_foot_about_its_mtp_joint() -> None:
    """The left foot stands on its ball, heel up 20 deg (past heel-off), when the
    hips drop 4 cm in a frame: the knee needs more flexion than ``knee_step_deg``
    allows in a frame, so for some frames the leg is longer than the hip-goal
    distance. The foot rolls about its MTP joint (the Toes joint) instead of the leg
    pushing it into the floor: the joint stays where it is held (1e-9 m), its rest
    height above the floor, the ball never below the floor, the heel comes down but
    never below the ball."""
    target = default_humanoid()
    stage = FootPlant(target, 1.0, LEG_M)
    z = _on_floor_z()
    lf, lt = target.index("LeftFoot"), target.index("LeftToes")
    heel, ball = foot_points(target)
    z += _heel_lift(target)  # the pitched foot's ball on the floor
    rest = np.asarray(target.rest_world_from_bone_quat)
    balls, heels, knees, mtps = [], [], [], []
    for t in range(40):
        pose = _crouch(target, 0.0, z - (0.04 if t >= 20 else 0.0))
        _pitch_left_foot(target, pose)
        g = pose.world_from_bone_quat
        stage.apply(
            g, pose.rest_from_bone_quat, pose.root_pos, pose.hips_pos,
            _stance(True, False), t / RATE_HZ,
        )  # fmt: skip
        j = joint_positions_world(target, pose)
        e = rot.quat_mul(g[lf], rot.quat_conj(rest[lf]))
        balls.append(j[lf] + rot.quat_rotate(e, ball[0]))
        heels.append(j[lf] + rot.quat_rotate(e, heel[0]))
        mtps.append(j[lt])
        knees.append(_knee_deg(target, j))
    b, h, m = np.array(balls), np.array(heels), np.array(mtps)
    lagged = np.diff(knees)[19:] >= PLANT["knee_step_deg"] - 1e-9
    assert lagged.sum() >= 2  # the knee was rate limited for some frames
    assert h[0, 2] - b[0, 2] > 0.03  # on the ball: heel-off
    assert b[:, 2].min() >= -1e-9
    assert np.abs(m[12:] - m[12]).max() < 1e-9
    assert m[12, 2] == pytest.approx(roll_radius(target)[0], abs=1e-9)
    assert roll_radius(target)[0] > 0.01  # the joint, not the ball, held
    assert np.abs(b[20:, 1] - b[19, 1]).max() > 1e-4  # the ball rolls with the foot
    assert (h[:, 2] - b[:, 2]).min() >= -1e-9
    assert h[20:, 2].min() < h[19, 2] - 1e-3  # the heel came down


def test_a_leg_the_knee_leaves_short_lifts_its_foot_where_it_stands() -> None:
    """The left foot stands flat while the hips go 6 cm forward, then rise 1.5 cm in
    a frame: the held foot is still in reach, but the knee needs more extension than
    ``knee_step_deg`` allows in a frame, so for some frames the leg is too short.
    The ankle lags its goal straight up, over it (horizontally where it is held,
    1e-9 m), never below it, rather than along the hip-goal line toward the hips
    (which slid it 0.72 mm here)."""
    target = default_humanoid()
    stage = FootPlant(target, 1.0, LEG_M)
    z = _on_floor_z()
    frames = [(0.06 * min(t / 20.0, 1.0), z + (0.015 if t >= 25 else 0.0), True)
              for t in range(45)]  # fmt: skip
    joints, flags, _ = _run(stage, target, frames)
    lf = target.index("LeftFoot")
    ankle = np.array([j[lf] for j in joints])
    knees = [_knee_deg(target, j) for j in joints]
    lagged = np.abs(np.diff(knees)[24:]) >= PLANT["knee_step_deg"] - 1e-9
    assert lagged.sum() >= 2  # the knee was rate limited for some frames
    assert not any(flags)  # in reach
    assert np.abs(ankle[:, :2] - ankle[0, :2]).max() < 1e-9
    assert ankle[:, 2].min() >= ankle[0, 2] - 1e-9
    assert ankle[25:, 2].max() > ankle[0, 2] + 1e-3  # it lifted while the knee lagged


def test_heel_off_anchors_the_ball_where_it_stood() -> None:
    """The left foot stands flat (held on its heel) while the hips go forward, then in
    one frame its heel rises 20 deg (heel-off) as the hips go on: the hold passes to
    the ball, anchored where the ball (the MTP joint, the Toes joint) stood the frame
    before, so the switch does not move it (1e-9 m) though the solve's foot moves
    (before: anchored where the solve's motion of that frame took it, 25 mm here)."""
    target = default_humanoid()
    stage = FootPlant(target, 1.0, LEG_M)
    z0 = _on_floor_z()
    lt = target.index("LeftToes")
    lift = _heel_lift(target)
    mtps, free = [], []
    for t in range(30):
        up = t >= 20
        pose = _crouch(target, 0.003 * t, z0 + (lift if up else 0.0))
        if up:
            _pitch_left_foot(target, pose)
        g = pose.world_from_bone_quat
        free.append(joint_positions_world(target, pose)[lt])
        stage.apply(
            g, pose.rest_from_bone_quat, pose.root_pos, pose.hips_pos,
            _stance(True, False), t / RATE_HZ,
        )  # fmt: skip
        mtps.append(joint_positions_world(target, pose)[lt])
    m, f = np.array(mtps), np.array(free)
    assert np.linalg.norm(f[20, :2] - f[19, :2]) > 0.005  # the solve's joint moved
    assert np.abs(m[:, :2] - m[0, :2]).max() < 1e-9


def test_the_ball_roll_only_brings_the_heel_down() -> None:
    """``ball_roll`` (the foot on its ball, 1 cm heel up, the hip 0.4 m ahead and 0.7
    m above the ball): where the leg's reach is met by raising the heel 1 cm more
    (0.05 rad) or by swinging the foot 173 deg round (the other root, the heel past
    20 cm on the way), it does not roll (before: the first, a flip of the kind the
    tennis serve showed, then the second); where it is met by lowering the heel to
    half its height, it turns the foot that way."""
    left, ef = np.array([0.0, 1.0, 0.0]), np.array([1.0, 0.0, 0.0, 0.0])
    ankle = np.array([-0.13, 0.0, 0.08])  # less the ball
    heel = np.array([-0.2, 0.0, 0.02])
    hip = np.array([0.4, 0.0, 0.7])

    def turned(t: float, v: np.ndarray) -> np.ndarray:  # about +y (left)
        c, s_ = math.cos(t), math.sin(t)
        return np.array([v[0] * c + v[2] * s_, v[1], -v[0] * s_ + v[2] * c])

    for t, rolls in ((0.05, False), (-0.05, True)):
        r2 = float(np.sum((turned(t, ankle) - hip) ** 2))
        q = ball_roll(ef, left, *ankle, *(-hip), r2, *heel)
        if not rolls:
            assert q == (1.0, 0.0, 0.0, 0.0)
            continue
        got = 2.0 * math.atan2(q[2], q[0])
        assert got == pytest.approx(t, abs=1e-9)
        assert 0.0 <= turned(got, heel)[2] < heel[2]


def test_a_forefoot_coming_down_faster_than_the_knee_is_stopped_by_the_floor() -> None:
    """The left foot stands flat on its heel when, in a frame, it plantarflexes 4 deg
    (the forefoot slapping down, as the tennis serve's): its lowest point is then the
    ball, 9 mm below the floor (less than ``pivot_switch_m`` below the heel: the foot
    is still on its heel, no roll about the ball), and lifting it needs more knee
    flexion than ``knee_step_deg`` allows in a frame. The leg lags, its ankle low;
    the foot is turned toes up about the ankle so the ball stays on the floor (never
    below it, the heel neither; 4 mm below without the turn) until the knee has
    caught up, when the foot has its solved rotation again."""
    target = default_humanoid()
    stage = FootPlant(target, 1.0, LEG_M)
    z = _on_floor_z()
    lf, lt = target.index("LeftFoot"), target.index("LeftToes")
    down = rot.quat_from_axis_angle(np.array([1.0, 0.0, 0.0]), math.radians(-4.0))
    heel, ball = foot_points(target)
    rest = np.asarray(target.rest_world_from_bone_quat)
    balls, heels, knees, turned = [], [], [], []
    for t in range(40):
        pose = _crouch(target, 0.0, z)
        g = pose.world_from_bone_quat
        if t >= 20:
            g[lf] = rot.quat_mul(down, g[lf])
            g[lt] = rot.quat_mul(down, g[lt])
            pose.rest_from_bone_quat[lf] = rot.quat_mul(
                rot.quat_conj(g[target.parents[lf]]), g[lf]
            )
        solved = np.array(g[lf])
        stage.apply(
            g, pose.rest_from_bone_quat, pose.root_pos, pose.hips_pos,
            _stance(True, False), t / RATE_HZ,
        )  # fmt: skip
        j = joint_positions_world(target, pose)
        e = rot.quat_mul(g[lf], rot.quat_conj(rest[lf]))
        balls.append(j[lf] + rot.quat_rotate(e, ball[0]))
        heels.append(j[lf] + rot.quat_rotate(e, heel[0]))
        knees.append(_knee_deg(target, j))
        turned.append(abs(float(np.dot(solved, g[lf]))))
    b, h = np.array(balls), np.array(heels)
    lagged = np.diff(knees)[19:] >= PLANT["knee_step_deg"] - 1e-9
    assert lagged.any()  # the knee was rate limited
    assert b[:, 2].min() >= -1e-9 and h[:, 2].min() >= -1e-9
    assert min(turned[20:]) < 1.0 - 1e-6  # the foot was turned while the knee lagged
    assert turned[-1] == pytest.approx(1.0, abs=1e-12)  # and has its own rotation
    assert b[-1, 2] == pytest.approx(0.0, abs=1e-9)
    assert h[-1, 2] > 0.005  # heel up 9 mm: the foot as solved


def test_the_release_blends_out_and_the_knee_never_pops() -> None:
    """Held while the hips travel 6 cm, then released: the ankle rejoins the
    unplanted path within ``blend_out_s`` (to 1e-9 m after it), the correction
    shrinking every frame; the knee's change per frame stays within 3 deg through
    the onset and the release."""
    target = default_humanoid()
    stage = FootPlant(target, 1.0, LEG_M)
    z = _on_floor_z()
    hold_n = 30
    frames = [(0.06 * min(t / hold_n, 1.0), z, t < hold_n) for t in range(70)]
    joints, _, free = _run(stage, target, frames)
    lf = target.index("LeftFoot")
    gap = np.linalg.norm(np.array(joints)[:, lf] - np.array(free)[:, lf], axis=-1)
    n_out = math.ceil(PLANT["blend_out_s"] * RATE_HZ)
    assert gap[hold_n - 1] > 0.05  # held 6 cm behind
    assert np.all(np.diff(gap[hold_n : hold_n + n_out]) < 0.0)
    assert gap[hold_n + n_out + 1 :].max() < 1e-9
    knees = np.array([_knee_deg(target, j) for j in joints])
    assert np.abs(np.diff(knees)).max() <= 3.0


def test_a_frame_allocates_nothing() -> None:
    """In steady state ``apply`` allocates no memory. (Measured: the first ~2,000
    calls with distinct frame times grow Python's traced memory by ~200 B each, then
    nothing more, bounded; with a constant time nothing from the start. The warm-up
    runs past that.)"""
    target = default_humanoid()
    stage = FootPlant(target, 1.0, LEG_M)
    pose = _crouch(target, 0.0, _on_floor_z())
    st = _stance(True, False)
    args = (pose.world_from_bone_quat, pose.rest_from_bone_quat, pose.root_pos,
            pose.hips_pos, st)  # fmt: skip
    for t in range(3000):
        stage.apply(*args, t / RATE_HZ)
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        start, _ = tracemalloc.get_traced_memory()
        for t in range(3000, 4000):
            pose.root_pos[1] = 0.0001 * (t - 3000)
            stage.apply(*args, t / RATE_HZ)
        end, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert end - start < 1024
    assert peak - start < 3072, peak - start  # numba's argument boxing


def test_foot_points_are_on_the_floor_at_rest() -> None:
    """The heel and ball sit on the floor (z = 0) at rest, the ball ahead."""
    target = default_humanoid()
    heel, ball = foot_points(target)
    fy = target.forward_world
    for s, side in enumerate(("Left", "Right")):
        rest = SimpleNamespace(
            world_from_bone_quat=np.tile([1.0, 0, 0, 0], (len(target.bone_names), 1)),
            hips_pos=target.rest_offsets[0],
        )
        ankle = joint_positions_world(target, rest)[target.index(side + "Foot")]
        assert ankle[2] + heel[s, 2] == pytest.approx(0.0)
        assert ankle[2] + ball[s, 2] == pytest.approx(0.0)
        assert ball[s] @ fy > 0.1


def test_solve_plant_feet_writes_the_planted_target(tmp_path: Any) -> None:
    """``retargetd solve --plant-feet``: the NPZ holds the target arrays with the feet
    planted (``target_feet`` "plant", ``target_plant_flags``, ``target_leg_ratio``);
    any other output is refused in one line, exit 2."""
    import subprocess
    import sys

    cli = [sys.executable, "-m", "retargetd.daemon"]
    take = tmp_path / "walk.c3d"
    synth = [*cli, "synth", "--seconds", "3", "--rate", "60", "--motions", "walk"]
    subprocess.run([*synth, "--out", str(take)], check=True, capture_output=True)
    solve = [*cli, "solve", str(take), "--rig", "menache", "--calibrate-frames",
             "0:30", "--quiet"]  # fmt: skip
    bad = subprocess.run([*solve, "--out", str(tmp_path / "w.bvh"), "--plant-feet"],
                         capture_output=True, text=True)  # fmt: skip
    assert bad.returncode == 2 and "--plant-feet" in bad.stderr
    assert len(bad.stderr.strip().splitlines()) == 1
    out = tmp_path / "w.npz"
    subprocess.run([*solve, "--out", str(out), "--plant-feet"], check=True,
                   capture_output=True)  # fmt: skip
    d = np.load(out)
    assert str(d["target_feet"]) == "plant"
    n = len(d["root_pos"])
    assert d["target_plant_flags"].shape == (n,)
    assert d["target_world_from_bone_quat"].shape[0] == n
    assert 0.5 < float(d["target_leg_ratio"]) < 2.0


def test_a_foot_on_a_step_stands_on_its_own_sole_not_the_detectors_level() -> None:
    """Off the floor (a support other than 0: a step), the left foot is held at the
    level its own sole came down to, raised as the solve's foot rises (0.1 mm a
    frame) and not lowered when it dips (2 mm): live, frame by frame; offline
    (``hold_settled``) the whole contact at the level it reached. The detector's
    level, 36 mm higher here (its foot points read high on a pitched foot), is not
    where the foot is put (``post/plant_level.py``)."""
    target = default_humanoid()
    step = 0.17
    z0 = _on_floor_z() + step
    zs = [z0] * 10 + [z0 + 1e-4 * i for i in range(1, 11)]
    zs += [zs[-1] - 2e-3] * 5
    lf = target.index("LeftFoot")

    def run(stage: FootPlant, states: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        held, free = [], []
        for t, z in enumerate(zs):
            pose = _crouch(target, 0.0, z)
            free.append(joint_positions_world(target, pose)[lf, 2])
            g, r = pose.world_from_bone_quat, pose.rest_from_bone_quat
            stage.apply(g, r, pose.root_pos, pose.hips_pos, states[t], t / RATE_HZ)
            held.append(joint_positions_world(target, pose)[lf, 2])
        return np.array(held), np.array(free)

    live = FootPlant(target, 1.0, LEG_M)
    states = np.zeros((len(zs), 2, 4))
    states[:, 0, 3] = 1.0
    states[:, 0, 2] = (step + 0.036) / live.leg_ratio
    held, free = run(live, states)
    top = free[:20].max()
    np.testing.assert_allclose(held[:20], free[:20], atol=1e-9)  # came down, rose
    np.testing.assert_allclose(held[20:], top, atol=1e-9)  # not lowered by the dip
    assert free[20:].max() < top - 1.9e-3
    offline = FootPlant(target, 1.0, LEG_M)
    poses = [_crouch(target, 0.0, z) for z in zs]
    settled = offline.hold_settled(
        np.array([p.world_from_bone_quat for p in poses]),
        np.array([p.rest_from_bone_quat for p in poses]),
        np.array([p.root_pos for p in poses]),
        np.array([p.hips_pos for p in poses]),
        states,
        RATE_HZ,
    )
    held, _ = run(offline, settled)
    np.testing.assert_allclose(held, top, atol=1e-9)  # the level it reached, all along


def test_the_plant_warns_of_hip_centres_no_range_of_motion_placed(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """``feet = "plant"`` on a calibration whose hip centres are the rig's regression
    (Plug-in Gait's, no ``calibrate --rom``) says so once, naming them: on a stair a
    stance foot stands as low as the solve lands it (docs/feet.md, "The stairs' sink
    is the calibration's hip"); on hips placed from the performer's range of
    motion, nothing."""
    import logging

    from retargetd.daemon.body.calibration import calibrate
    from retargetd.daemon.body.rig import load_rig
    from retargetd.daemon.post.plant import plant_stage
    from retargetd.daemon.post.stance import StanceDetector
    from retargetd.daemon.retarget.retarget import Retargeter
    from retargetd.daemon.synth import performer as pf

    rig = load_rig("plug-in-gait")
    rom = pf.synthesize(seconds=25.0, rate_hz=60.0, markerset="plug-in-gait",
                        motions=("rom",), seed=0)  # fmt: skip
    base = rom.markers_world[:30]
    motion = (rom.markers_world, rom.labels, {"take": "synth rom"})
    lines = {}
    for placed in (False, True):
        cal = calibrate(rig, base, rom.labels, rom=motion if placed else None)
        caplog.clear()
        with caplog.at_level(
            logging.WARNING, logger="retargetd.daemon.post.plant_target"
        ):
            stage = plant_stage(
                "plant", Retargeter(rig, cal, default_humanoid()),
                StanceDetector(rig, cal),
            )  # fmt: skip
        assert stage is not None
        lines[placed] = [r.getMessage() for r in caplog.records]
    (line,) = lines[False]
    assert "LHJC RHJC" in line and "--rom" in line
    assert lines[True] == []
