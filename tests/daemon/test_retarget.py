"""Retargeting onto the target humanoid: hand-worked poses, synthetic performer, BVH.

Hand-built performer: a rig whose bones are the default humanoid's own bones (UpperChest
and Toes left unmapped), calibrated facing world +Y like the target, so the heading
``H`` is identity and the numbers can be worked by hand.

Unity by hand (Unity_from_world M: (x, y, z) -> (x, z, y), det M = -1, so a rotation
``q = (w, v)`` becomes ``(w, -M v)``, stored x y z w):

- hips yawed +90° about world +Z (the performer turns to its left): ``q = (c, 0, 0, s)``
  with ``c = s = √½``; ``-M v = -(0, s, 0)``: Unity ``(0, -s, 0, c)``, -90° about
  Unity +Y. Left-handed Unity turns +Z to +X for a positive Y rotation (a right turn
  seen from above), so a left turn is negative. ✓
- left elbow flexed 90° in the T-pose (palms down, the hinge axis vertical): the
  forearm swings from the left (world -X) to the front (world +Y): the rotation taking
  -X to +Y about +Z is -90°, ``q = (c, 0, 0, -s)``; ``-M v = (0, s, 0)``: Unity
  ``(0, s, 0, c)``, +90° about Unity +Y, which takes Unity -X (the avatar's left) to
  Unity +Z (its front). ✓
"""

from __future__ import annotations

import dataclasses
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
import retarget_oracle

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.calibration import Calibration, calibrate
from retargetd.daemon.body.kernel import FLAG_HELD
from retargetd.daemon.body.rig import HUMANOID_BONES, Bone, Rig, load_rig
from retargetd.daemon.body.solve import BodyPose, BodySolver
from retargetd.daemon.retarget import retarget as tg
from retargetd.daemon.retarget.kernel import FLAG_FILLED, FLAG_SOURCE_HELD
from retargetd.daemon.synth import performer as pf
from retargetd.protocols import engine_unity
from retargetd.protocols.conventions import world_from_capture_mat
from retargetd.protocols.humanoid import HUMANOID_PARENTS
from retargetd.replay.bvh import read_bvh_hierarchy

DATA = Path(__file__).resolve().parent.parent / "data"
BVH = DATA / "target-apose-mixamo.bvh"
C = S = np.sqrt(0.5)
Y = np.array([0.0, 1.0, 0.0])
UNMAPPED = ("UpperChest", "LeftToes", "RightToes")
ROOT_REST = np.array([0.3, -0.2, 0.97])


def _quat_z(deg: float) -> np.ndarray:
    return rot.quat_from_axis_angle(np.array([0.0, 0.0, 1.0]), np.radians(deg))


def _angle_deg(q: np.ndarray) -> np.ndarray:
    return np.degrees(rot.quat_angle(q))


def _frame_with_y(d: np.ndarray) -> np.ndarray:
    """A world_from_bone quaternion whose +Y is ``d`` (the minimal swing from +Y)."""
    return tg._swing(Y, np.asarray(d, dtype=np.float64))


def _hand_rig() -> Rig:
    names = [h for h in HUMANOID_BONES if h not in UNMAPPED]
    bones = []
    for h in names:
        p = HUMANOID_PARENTS[h]
        while p in UNMAPPED:
            p = HUMANOID_PARENTS[p]
        up = ("RHIP", "LHIP") if h == "Hips" else ("X",)
        bones.append(
            Bone(
                name=h.lower(),
                parent=p and p.lower(),
                origin="O",
                aim="A",
                up=up,
                humanoid=h,
            )
        )
    return Rig(
        name="hand", source="", description="", lateral=("RHIP", "LHIP"),
        measurements={}, markers={}, segments={}, points=(), bones=tuple(bones),
        joints={}, humanoid={h: h.lower() for h in names},
    )  # fmt: skip


def _hand_calibration(rig: Rig, arm_down_deg: float = 0.0) -> Calibration:
    """The performer in the default humanoid's T-pose facing +Y (arms lowered by
    ``arm_down_deg`` at the shoulder joint: upper arm, forearm and hand)."""
    target = tg.default_humanoid()
    rest = []
    for bone in rig.bones:
        h = bone.humanoid
        assert h is not None
        if h == "Hips":  # +Y up, +X to the left (world -X), +Z forward (world +Y)
            mat = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]]).T
            rest.append(rot.quat_from_mat(mat))
            continue
        d = target.aim_offsets[target.index(h)]
        if arm_down_deg and h.endswith(("UpperArm", "LowerArm", "Hand")):
            sx = -1.0 if h.startswith("Left") else 1.0
            a = np.radians(arm_down_deg)
            d = np.array([sx * np.cos(a), 0.0, -np.sin(a)])
        rest.append(_frame_with_y(d))
    b = len(rig.bones)
    rest_w = np.asarray(rest)
    return Calibration(
        rig_name=rig.name, rig_source="", rig_sha256="", marker_names=(),
        markers_seen=(), point_names=(), point_offsets=np.zeros((0, 3)),
        segment_layouts={}, bone_names=rig.bone_names,
        bone_parents=rig.bone_parent_indices(), bone_lengths=np.ones(b),
        rest_world_from_bone_quat=rest_w, rest_parent_from_bone_quat=rest_w.copy(),
        root_rest_pos=ROOT_REST.copy(),
    )  # fmt: skip


def _pose(cal: Calibration) -> BodyPose:
    """The calibration pose as a BodyPose (edit ``world_from_bone_quat`` to move)."""
    b = len(cal.bone_names)
    return BodyPose(
        joint_centres=np.zeros((0, 3)),
        world_from_bone_quat=cal.rest_world_from_bone_quat.copy(),
        parent_from_bone_quat=cal.rest_parent_from_bone_quat.copy(),
        rest_from_bone_quat=np.tile([1.0, 0.0, 0.0, 0.0], (b, 1)),
        root_pos=cal.root_rest_pos.copy(),
        bone_quality=np.ones(b, dtype=np.float32),
        bone_flags=np.zeros(b, dtype=np.uint8),
    )


@pytest.fixture
def hand() -> tuple[Rig, Calibration, tg.Retargeter]:
    rig = _hand_rig()
    cal = _hand_calibration(rig)
    return rig, cal, tg.Retargeter(rig, cal)


def _rotate_bones(pose: BodyPose, rig: Rig, q: np.ndarray, bones: list[str]) -> None:
    for name in bones:
        i = rig.bone_names.index(name)
        pose.world_from_bone_quat[i] = rot.quat_mul(q, pose.world_from_bone_quat[i])


def _unity(q_wxyz: np.ndarray) -> np.ndarray:
    out = np.zeros(4)
    return engine_unity.unity_quat_xyzw_from_world(q_wxyz, out)


def _same_rotation(q: np.ndarray, ref: np.ndarray, atol: float = 1e-12) -> None:
    q, ref = np.asarray(q), np.asarray(ref)
    sign = np.where(np.sum(q * ref, axis=-1, keepdims=True) < 0.0, -1.0, 1.0)
    np.testing.assert_allclose(q * sign, ref, atol=atol)


# -- default humanoid ---------------------------------------------------------------


def test_default_humanoid_shape() -> None:
    t = tg.default_humanoid()
    assert t.bone_names == HUMANOID_BONES and len(t.bone_names) == 22
    for h, p in zip(t.bone_names, t.parents, strict=True):
        assert (
            (HUMANOID_PARENTS[h] is None)
            if p < 0
            else (t.bone_names[p] == HUMANOID_PARENTS[h])
        )
    np.testing.assert_array_equal(t.forward_world, [0, 1, 0])
    np.testing.assert_array_equal(t.left_world, [-1, 0, 0])
    np.testing.assert_array_equal(t.rest_world_from_bone_quat[:, 0], 1.0)
    # Unity: forward world +Y -> Unity +Z, left world -X -> Unity -X.
    u = np.zeros(3)
    engine_unity.unity_pos_from_world(t.forward_world, u)
    np.testing.assert_array_equal(u, [0, 0, 1])
    # Real offsets, never zeros; a 1.70 m adult.
    assert (np.linalg.norm(t.rest_offsets, axis=1) > 0.05).all()
    assert t.hips_height == pytest.approx(0.95)
    pos = np.zeros((22, 3))
    for i, p in enumerate(t.parents):
        pos[i] = t.rest_offsets[i] + (pos[p] if p >= 0 else 0.0)
    head_top = pos[t.index("Head")] + t.aim_offsets[t.index("Head")]
    assert head_top[2] == pytest.approx(1.70)
    assert pos[t.index("LeftUpperArm"), 0] < 0 < pos[t.index("RightUpperArm"), 0]
    assert not t.rest_offsets.flags.writeable


# -- hand-worked poses ----------------------------------------------------------------


def test_calibration_pose_is_identity(hand: tuple) -> None:
    _, cal, rt = hand
    assert rt.heading_deg == pytest.approx(0.0, abs=1e-12)
    assert _angle_deg(rt.compensation_quat).max() < 1e-6
    out = rt.apply(_pose(cal), rt.new_pose())
    _same_rotation(
        out.rest_from_bone_quat, np.tile([1.0, 0, 0, 0], (22, 1)), atol=1e-12
    )
    _same_rotation(
        out.world_from_bone_quat, np.tile([1.0, 0, 0, 0], (22, 1)), atol=1e-12
    )
    np.testing.assert_allclose(out.root_pos, 0.0, atol=1e-15)
    np.testing.assert_allclose(out.hips_pos, [0, 0, 0.95], atol=1e-15)


def test_hips_yaw_plus_90(hand: tuple) -> None:
    rig, cal, rt = hand
    pose = _pose(cal)
    _rotate_bones(pose, rig, _quat_z(90.0), list(rig.bone_names))  # all rigid
    out = rt.apply(pose, rt.new_pose())
    _same_rotation(out.rest_from_bone_quat[0], [C, 0.0, 0.0, S])
    _same_rotation(out.rest_from_bone_quat[1:], np.tile([1.0, 0, 0, 0], (21, 1)))
    # Hand-worked Unity quaternion (module docstring): -90° about Unity +Y.
    np.testing.assert_allclose(_unity(out.rest_from_bone_quat[0]), [0.0, -S, 0.0, C])
    # The avatar's left arm now points to world -Y (its front was +Y, turned left).
    pos = tg.joint_positions_world(rt.target, out)
    t = rt.target
    arm = pos[t.index("LeftLowerArm")] - pos[t.index("LeftUpperArm")]
    np.testing.assert_allclose(arm / np.linalg.norm(arm), [0, -1, 0], atol=1e-12)


def test_left_elbow_flexed_90(hand: tuple) -> None:
    rig, cal, rt = hand
    pose = _pose(cal)
    _rotate_bones(pose, rig, _quat_z(-90.0), ["leftlowerarm", "lefthand"])
    out = rt.apply(pose, rt.new_pose())
    t = rt.target
    i = t.index("LeftLowerArm")
    _same_rotation(out.rest_from_bone_quat[i], [C, 0.0, 0.0, -S])
    np.testing.assert_allclose(_unity(out.rest_from_bone_quat[i]), [0.0, S, 0.0, C])
    others = [k for k in range(22) if k != i]
    _same_rotation(out.rest_from_bone_quat[others], np.tile([1.0, 0, 0, 0], (21, 1)))
    pos = tg.joint_positions_world(t, out)
    fore = pos[t.index("LeftHand")] - pos[i]
    np.testing.assert_allclose(fore / np.linalg.norm(fore), [0, 1, 0], atol=1e-12)


def test_a_pose_calibration() -> None:
    rig = _hand_rig()
    cal = _hand_calibration(rig, arm_down_deg=60.0)
    rt = tg.Retargeter(rig, cal)
    t = rt.target
    out = rt.apply(_pose(cal), rt.new_pose())
    # Calibration pose: the avatar shows the performer's arms, 60° down.
    pos = tg.joint_positions_world(t, out)
    for side, sx in (("Left", -1.0), ("Right", 1.0)):
        want = np.array([sx * np.cos(np.radians(60)), 0.0, -np.sin(np.radians(60))])
        for a, b in (("UpperArm", "LowerArm"), ("LowerArm", "Hand")):
            d = pos[t.index(side + b)] - pos[t.index(side + a)]
            np.testing.assert_allclose(d / np.linalg.norm(d), want, atol=1e-12)
        # Hand straight on the forearm: its aim follows too.
        i = t.index(side + "Hand")
        aim = rot.quat_rotate(out.world_from_bone_quat[i], t.aim_offsets[i])
        np.testing.assert_allclose(aim / np.linalg.norm(aim), want, atol=1e-12)
        assert _angle_deg(out.rest_from_bone_quat[t.index(side + "UpperArm")]) == (
            pytest.approx(60.0)
        )
        for b in ("LowerArm", "Hand", "Shoulder"):
            assert _angle_deg(out.rest_from_bone_quat[t.index(side + b)]) < 1e-6
    # The performer raises the arms to a T-pose: the avatar is in its T-pose.
    pose = _pose(cal)
    for side, sx in (("left", 1.0), ("right", -1.0)):
        up = rot.quat_from_axis_angle(Y, np.radians(sx * 60.0))
        _rotate_bones(pose, rig, up, [f"{side}{b}" for b in ("upperarm", "lowerarm",
                                                               "hand")])  # fmt: skip
    out = rt.apply(pose, out)
    assert _angle_deg(out.rest_from_bone_quat).max() < 1e-6
    # Without compensation the calibration pose shows the target's rest (T-pose).
    plain = tg.Retargeter(rig, cal, compensate_base_pose=False)
    out = plain.apply(_pose(cal), plain.new_pose())
    assert _angle_deg(out.rest_from_bone_quat).max() < 1e-6


def test_unmapped_bones_filled_and_flagged(hand: tuple) -> None:
    rig, cal, rt = hand
    t = rt.target
    assert rt.filled == UNMAPPED
    pose = _pose(cal)
    # Twist the trunk: Chest (and above) 40° about +Z, Neck (and above) 80°.
    upper = ["neck", "head", "leftshoulder", "leftupperarm", "leftlowerarm",
             "lefthand", "rightshoulder", "rightupperarm", "rightlowerarm",
             "righthand"]  # fmt: skip
    _rotate_bones(pose, rig, _quat_z(40.0), ["chest"])
    _rotate_bones(pose, rig, _quat_z(80.0), upper)
    pose.bone_flags[rig.bone_names.index("leftfoot")] = FLAG_HELD
    out = rt.apply(pose, rt.new_pose())
    uc = t.index("UpperChest")
    # Between Chest (40°) and Neck (80°) at u = 1/2: 60° in the world, 20° + 20°.
    _same_rotation(out.world_from_bone_quat[uc], _quat_z(60.0))
    _same_rotation(out.rest_from_bone_quat[uc], _quat_z(20.0))
    _same_rotation(out.rest_from_bone_quat[t.index("Neck")], _quat_z(20.0))
    _same_rotation(out.rest_from_bone_quat[t.index("LeftShoulder")], _quat_z(20.0))
    for toes in ("LeftToes", "RightToes"):  # no mapped descendant: rigid on the foot
        assert _angle_deg(out.rest_from_bone_quat[t.index(toes)]) < 1e-6
    want = np.zeros(22, dtype=np.uint8)
    want[[t.index(h) for h in UNMAPPED]] = FLAG_FILLED
    want[t.index("LeftFoot")] = FLAG_SOURCE_HELD
    np.testing.assert_array_equal(out.flags, want)


def test_interpolation_parameter_by_chain_position() -> None:
    """Two filled bones in a row (Chest, UpperChest): u = 1/3 and 2/3."""
    rig = _hand_rig()
    rig = dataclasses.replace(
        rig, humanoid={k: v for k, v in rig.humanoid.items() if k != "Chest"}
    )
    cal = _hand_calibration(rig)
    rt = tg.Retargeter(rig, cal)
    pose = _pose(cal)
    above = [b for b in rig.bone_names if b not in ("hips", "spine", "chest") and not
             b.endswith(("upperleg", "lowerleg", "foot"))]  # fmt: skip
    _rotate_bones(pose, rig, _quat_z(90.0), above)
    out = rt.apply(pose, rt.new_pose())
    t = rt.target
    _same_rotation(out.world_from_bone_quat[t.index("Chest")], _quat_z(30.0))
    _same_rotation(out.world_from_bone_quat[t.index("UpperChest")], _quat_z(60.0))


def test_root_scaled_by_hip_heights(hand: tuple) -> None:
    _, cal, rt = hand
    pose = _pose(cal)
    step = np.array([0.5, -0.2, -0.1])
    pose.root_pos[:] = ROOT_REST + step
    out = rt.apply(pose, rt.new_pose())
    assert rt.root_scale == pytest.approx(0.95 / 0.97)
    np.testing.assert_allclose(out.root_pos, step * 0.95 / 0.97, atol=1e-15)
    np.testing.assert_allclose(
        out.hips_pos, out.root_pos + np.array([0, 0, 0.95]), atol=1e-15
    )
    np.testing.assert_array_equal(out.rest_offsets, rt.target.rest_offsets)


def test_heading_follows_the_performer(hand: tuple) -> None:
    """A performer facing world +X at calibration: the avatar turns to face +X."""
    rig, cal, _ = hand
    q = _quat_z(-90.0)
    turned = dataclasses.replace(
        cal,
        rest_world_from_bone_quat=rot.quat_mul(q, cal.rest_world_from_bone_quat),
    )
    rt = tg.Retargeter(rig, turned)
    assert rt.heading_deg == pytest.approx(-90.0)
    np.testing.assert_allclose(rt.performer_forward_world, [1, 0, 0], atol=1e-12)
    out = rt.apply(_pose(turned), rt.new_pose())
    _same_rotation(out.rest_from_bone_quat[0], q)
    _same_rotation(out.rest_from_bone_quat[1:], np.tile([1.0, 0, 0, 0], (21, 1)))


def test_apply_returns_out_and_does_not_allocate(hand: tuple) -> None:
    rig, cal, rt = hand
    pose = _pose(cal)
    _rotate_bones(pose, rig, _quat_z(30.0), ["chest"])
    out = rt.new_pose()
    assert rt.apply(pose, out) is out
    assert out.rest_from_bone_quat.dtype == np.float64 and out.flags.dtype == np.uint8
    for _ in range(10):
        rt.apply(pose, out)
    tracemalloc.start()
    try:
        start, _ = tracemalloc.get_traced_memory()
        for _ in range(1000):
            rt.apply(pose, out)
        end, _ = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert end - start < 1024, f"{end - start} bytes kept over 1000 apply calls"


def _nrt_stats() -> tuple[int, int]:
    nrt = pytest.importorskip("numba.core.runtime._nrt_python")
    if not hasattr(nrt, "memsys_enable_stats"):
        pytest.skip("numba has no NRT statistics switch")
    nrt.memsys_enable_stats()
    return int(nrt.memsys_get_stats_alloc()), int(nrt.memsys_get_stats_free())


def test_kernel_allocates_nothing_on_numba_heap(hand: tuple) -> None:
    # numba's own heap (not visible to tracemalloc): a call boxes each array argument
    # (one MemInfo per array, freed on return); the kernel itself allocates nothing.
    rig, cal, rt = hand
    pose = _pose(cal)
    _rotate_bones(pose, rig, _quat_z(30.0), ["chest"])
    out = rt.new_pose()
    rt.apply(pose, out)

    def allocs(calls: int) -> tuple[int, int]:
        a0, f0 = _nrt_stats()
        for _ in range(calls):
            rt.apply(pose, out)
        a1, f1 = _nrt_stats()
        return a1 - a0, f1 - f0

    one, _ = allocs(1)
    many, freed = allocs(100)
    n_array_args = 13  # kernel_target.retarget_one
    assert one <= n_array_args
    assert many == 100 * one and freed == many


def _random_quats(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _oracle_cases() -> list[tuple[str, Rig, Calibration, tg.Retargeter]]:
    rig = _hand_rig()
    cal = _hand_calibration(rig)
    apose = _hand_calibration(rig, arm_down_deg=60.0)
    sparse = dataclasses.replace(
        rig,
        humanoid={
            k: v
            for k, v in rig.humanoid.items()
            if k not in ("Chest", "Neck", "LeftLowerArm", "LeftHand", "RightFoot")
        },
    )
    turned = dataclasses.replace(
        cal, rest_world_from_bone_quat=rot.quat_mul(
            _quat_z(-37.0), cal.rest_world_from_bone_quat
        ),
    )  # fmt: skip
    bvh = tg.TargetSkeleton.from_bvh(BVH)
    return [
        ("hand", rig, cal, tg.Retargeter(rig, cal)),
        ("hand a-pose", rig, apose, tg.Retargeter(rig, apose)),
        ("hand plain", rig, apose, tg.Retargeter(rig, apose,
                                                 compensate_base_pose=False)),
        ("hand turned", rig, turned, tg.Retargeter(rig, turned)),
        ("sparse", sparse, cal, tg.Retargeter(sparse, cal)),
        ("bvh target", rig, apose, tg.Retargeter(rig, apose, bvh)),
    ]  # fmt: skip


def _assert_matches_oracle(
    rt: tg.Retargeter, pose: BodyPose, scratch: object, what: str
) -> None:
    got, want = rt.new_pose(), rt.new_pose()
    assert rt.apply(pose, got) is got
    retarget_oracle._reference_apply(rt, pose, want, scratch)
    for name in ("world_from_bone_quat", "rest_from_bone_quat", "root_pos",
                 "hips_pos"):  # fmt: skip
        np.testing.assert_allclose(
            getattr(got, name), getattr(want, name), rtol=0, atol=1e-12,
            err_msg=f"{what}: {name}",
        )  # fmt: skip
    np.testing.assert_array_equal(got.flags, want.flags, err_msg=what)


def test_compiled_apply_equals_numpy_oracle() -> None:
    """Random poses, held sources, filled bones (slerped and copied), BVH target."""
    rng = np.random.default_rng(7)
    for what, rig, cal, rt in _oracle_cases():
        assert rt.filled, what
        scratch = retarget_oracle._ReferenceScratch(rt)
        b = len(rig.bones)
        for trial in range(200):
            pose = _pose(cal)
            pose.world_from_bone_quat[:] = _random_quats(rng, b)
            pose.root_pos[:] = rng.normal(size=3)
            pose.bone_flags[:] = rng.integers(0, 16, size=b, dtype=np.uint8)
            _assert_matches_oracle(rt, pose, scratch, f"{what} #{trial}")
        # Slerp edge cases: ends equal, antipodal (same rotation), tiny angles on
        # both sides of the linear fallback, and nearly opposite rotations.
        for deg in (0.0, 1e-8, 4e-5, 6e-5, 1e-3, 30.0, 179.0, 180.0, 181.0, 359.9):
            pose = _pose(cal)
            for bone in rig.bone_names:
                if bone not in ("hips", "spine", "chest"):
                    _rotate_bones(pose, rig, _quat_z(deg), [bone])
            _assert_matches_oracle(rt, pose, scratch, f"{what} {deg} deg")
            pose.world_from_bone_quat[:] *= -1.0
            pose.bone_flags[:] = FLAG_HELD
            _assert_matches_oracle(rt, pose, scratch, f"{what} {deg} deg, negated")


def test_compiled_apply_equals_numpy_oracle_on_menache(synth: pf.SynthTake) -> None:
    rig = load_rig("menache")
    cal = calibrate(rig, synth.markers_world[synth.base_pose_frames], synth.labels)
    rt = tg.Retargeter(rig, cal)
    assert rt.filled
    scratch = retarget_oracle._ReferenceScratch(rt)
    solver = BodySolver(rig, cal, synth.labels)
    bp = solver.new_pose()
    frames = np.array(synth.markers_world)
    frames[60:, 0] = np.nan  # SACRUM lost after the T-pose: bones held
    held = 0
    for f in range(frames.shape[0]):
        solver.solve_frame(frames[f], bp)
        held += bool((bp.bone_flags & FLAG_HELD).any())
        _assert_matches_oracle(rt, bp, scratch, f"menache frame {f}")
    assert held > 0


def test_warm_up_loads_the_retarget_kernel(hand: tuple) -> None:
    from retargetd.daemon.retarget import kernel as kernel_target
    from retargetd.daemon.retarget.retarget import warm_up

    warm_up()
    signatures = list(kernel_target.retarget_one.signatures)
    assert signatures
    rig, cal, rt = hand
    rt.apply(_pose(cal), rt.new_pose())
    bvh = tg.Retargeter(rig, cal, tg.TargetSkeleton.from_bvh(BVH))
    bvh.apply(_pose(cal), bvh.new_pose())
    assert kernel_target.retarget_one.signatures == signatures  # nothing new compiled


# -- the synthetic performer ----------------------------------------------------------


@pytest.fixture(scope="module")
def synth() -> pf.SynthTake:
    return pf.synthesize(seconds=3.0, rate_hz=60.0)  # 1 s T-pose, then all motions


def test_exact_rig_tracks_the_truth() -> None:
    """The exact rig: avatar world deltas (heading removed) equal the performer's."""
    take = pf.synthesize(
        seconds=3.0, rate_hz=60.0, markerset=DATA / "synth-exact-markers.toml"
    )
    rig = load_rig(DATA / "synth-exact-rig.toml")
    cal = calibrate(rig, take.markers_world[take.base_pose_frames], take.labels)
    rt = tg.Retargeter(rig, cal)
    # The performer faces +X (its left +Y): H = -90° about +Z.
    assert rt.heading_deg == pytest.approx(-90.0, abs=1e-6)
    comp = _angle_deg(rt.compensation_quat)
    print("\nexact rig, T-pose calibration, compensation (deg):",
          dict(zip(rt.bone_names, comp.round(3), strict=True)))  # fmt: skip
    assert comp.max() < 0.01
    solver = BodySolver(rig, cal, take.labels)
    bp, out = solver.new_pose(), rt.new_pose()
    seg = [take.segment_names.index(b) for b in rt.source_bones if b]
    mapped = [i for i, b in enumerate(rt.source_bones) if b]
    h_conj = rot.quat_conj(rt.heading_quat)
    worst = 0.0
    frames = np.array(take.markers_world)  # writable, as the live loop's
    for f in range(frames.shape[0]):
        rt.apply(solver.solve_frame(frames[f], bp), out)
        if f == 0:
            _same_rotation(out.rest_from_bone_quat[0], rt.heading_quat, atol=1e-9)
            assert _angle_deg(out.rest_from_bone_quat[1:]).max() < 1e-6
        delta = rot.quat_mul(out.world_from_bone_quat[mapped], h_conj)
        err = _angle_deg(
            rot.quat_mul(rot.quat_conj(take.world_from_segment_quat[f, seg]), delta)
        )
        worst = max(worst, float(err.max()))
    print(f"exact rig: worst avatar-vs-truth world delta {worst:.2e} deg")
    assert worst < 1e-5


@pytest.mark.parametrize("name", ["menache", "plug-in-gait"])
def test_shipped_rigs_on_the_synthetic_performer(name: str) -> None:
    take = pf.synthesize(seconds=3.0, rate_hz=60.0, markerset=name)
    rig = load_rig(name)
    cal = calibrate(rig, take.markers_world[take.base_pose_frames], take.labels)
    left = tg.performer_left_from_calibration(rig, cal)
    np.testing.assert_allclose(left, [0, 1, 0], atol=1e-6)
    rt = tg.Retargeter(rig, cal)
    comp = dict(zip(rt.bone_names, _angle_deg(rt.compensation_quat), strict=True))
    print(f"\n{name}: T-pose compensation (deg): "
          + ", ".join(f"{k} {v:.1f}" for k, v in comp.items() if v > 0.05))  # fmt: skip
    # Long bones: the rig's joint centres in an exact T-pose (rig accuracy, not pose),
    # but for the static's own elbow bend (Plug-in Gait's: its marker set's
    # [base_pose]), which the compensation carries to the forearm and the hand.
    bend = pf.load_markerset(name).elbow_flexion_deg
    forearm = {"LeftLowerArm", "RightLowerArm", "LeftHand", "RightHand"}
    off = {k: abs(v - (bend if k in forearm else 0.0)) for k, v in comp.items()}
    assert max(off.values()) < 17.0
    solver = BodySolver(rig, cal, take.labels)
    bp, out = solver.new_pose(), rt.new_pose()
    rt.apply(solver.solve_frame(np.array(take.markers_world[0]), bp), out)
    _same_rotation(out.rest_from_bone_quat[0], rt.heading_quat, atol=1e-6)
    # Feet fallback agrees with the pelvis axis.
    pelvis = rig.humanoid["Hips"]
    no_lat = dataclasses.replace(
        rig,
        bones=tuple(
            dataclasses.replace(b, up=(b.aim,)) if b.name == pelvis else b
            for b in rig.bones
        ),
    )
    feet = tg.performer_left_from_calibration(no_lat, cal)
    assert np.degrees(np.arccos(np.clip(feet @ left, -1, 1))) < 3.0


def test_cmu41_heading_on_motek_t(datasets: Path) -> None:
    from retargetd.replay.takes import load_take

    rig = load_rig("cmu41")
    take = load_take(datasets / "btkdata" / "MOTEK_T.trc")
    cal = calibrate(rig, take.positions, take.labels)
    left = tg.performer_left_from_calibration(rig, cal)
    no_lat = dataclasses.replace(
        rig,
        bones=tuple(
            dataclasses.replace(b, up=(b.aim,)) if b.name == "hips" else b
            for b in rig.bones
        ),
    )
    feet = tg.performer_left_from_calibration(no_lat, cal)
    angle = float(np.degrees(np.arccos(np.clip(feet @ left, -1, 1))))
    rt = tg.Retargeter(rig, cal)
    print(f"\ncmu41 MOTEK_T: left {left.round(3)}, heading {rt.heading_deg:.1f} deg, "
          f"feet fallback {angle:.1f} deg away; upper-arm compensation "
          f"{_angle_deg(rt.compensation_quat[rt.target.index('LeftUpperArm')]):.1f} "
          "deg")  # fmt: skip
    assert abs(left[2]) < 1e-12 and angle < 20.0


def test_reversed_lateral_pair_flips_left(hand: tuple) -> None:
    rig, cal, _ = hand
    flipped = dataclasses.replace(rig, lateral=("LHIP", "RHIP"))
    np.testing.assert_allclose(
        tg.performer_left_from_calibration(rig, cal), [-1, 0, 0], atol=1e-12
    )
    np.testing.assert_allclose(
        tg.performer_left_from_calibration(flipped, cal), [1, 0, 0], atol=1e-12
    )


def test_retargeter_input_errors(hand: tuple) -> None:
    rig, cal, _ = hand
    with pytest.raises(ValueError, match="Hips"):
        tg.Retargeter(
            dataclasses.replace(
                rig, humanoid={k: v for k, v in rig.humanoid.items() if k != "Hips"}
            ),
            cal,
        )
    with pytest.raises(ValueError, match="unknown bones"):
        tg.Retargeter(rig, cal, compensate_base_pose=["Tail"])
    with pytest.raises(ValueError, match="hips height"):
        tg.Retargeter(rig, cal, performer_hips_height=0.0)


# -- BVH target -----------------------------------------------------------------------


def test_bvh_target_skeleton() -> None:
    t = tg.TargetSkeleton.from_bvh(BVH)
    assert t.bone_names == HUMANOID_BONES  # mixamorig: stripped, Spine1/2 mapped
    assert t.source_joints[t.index("Chest")] == "mixamorig:Spine1"
    # Y-up cm -> world metres: file (x, y, z) -> world (x, -z, y) / 100.
    np.testing.assert_allclose(
        t.rest_offsets[t.index("LeftUpperLeg")], [0.09, 0.0, -0.06], atol=1e-12
    )
    np.testing.assert_allclose(t.rest_offsets[0], [0, 0, 0.98])
    assert t.hips_height == pytest.approx(0.98)
    # Mixamo faces file +Z with its left at file +X: world forward -Y, left +X.
    np.testing.assert_allclose(t.forward_world, [0, -1, 0], atol=1e-12)
    # Head aims at HeadTop_End (unmapped joint), a leaf at its End Site.
    np.testing.assert_allclose(t.aim_offsets[t.index("Head")], [0, 0, 0.18])
    np.testing.assert_allclose(
        t.aim_offsets[t.index("LeftToes")], [0, -0.06, -0.02], atol=1e-12
    )
    a = rot.quat_from_mat(world_from_capture_mat("+Y"))
    _same_rotation(t.rest_world_from_bone_quat, np.tile(a, (22, 1)))


def test_bvh_name_map_skips_joints() -> None:
    names = {k: v for k, v in tg.DEFAULT_BVH_NAME_MAP.items()
             if k not in ("Spine1", "Spine2")}  # fmt: skip
    t = tg.TargetSkeleton.from_bvh(BVH, name_map=names)
    assert "Chest" not in t.bone_names and "UpperChest" not in t.bone_names
    neck = t.index("Neck")
    assert t.bone_names[t.parents[neck]] == "Spine"
    # Spine1 + Spine2 + Neck offsets: file (0, 38, 1) cm.
    np.testing.assert_allclose(t.rest_offsets[neck], [0, -0.01, 0.38], atol=1e-12)
    with pytest.raises(ValueError, match="two joints map"):
        tg.TargetSkeleton.from_bvh(BVH, name_map={"Hips": "Hips", "Spine": "Hips"})
    with pytest.raises(ValueError, match="unknown"):
        tg.TargetSkeleton.from_bvh(BVH, name_map={"Hips": "Hips", "Spine": "Tail"})
    with pytest.raises(ValueError, match="no joint maps to Hips"):
        tg.TargetSkeleton.from_bvh(BVH, name_map={"Spine": "Spine"})


def _bvh_fk(
    channels_quat: np.ndarray, offsets_cm: np.ndarray, parents: tuple
) -> np.ndarray:
    """File-frame forward kinematics: x_j = x_p + R_p o_j, R_j = R_p Q_j (cm, Y up)."""
    n = len(parents)
    world_q = np.zeros((n, 4))
    pos = np.zeros((n, 3))
    for j, p in enumerate(parents):
        if p < 0:
            world_q[j] = channels_quat[j]
            continue
        pos[j] = pos[p] + rot.quat_rotate(world_q[p], offsets_cm[j])
        world_q[j] = rot.quat_mul(world_q[p], channels_quat[j])
    return pos


def test_bvh_target_retarget_relative_to_its_rest(hand: tuple) -> None:
    """A-pose BVH target, T-pose performer: the avatar shows the T-pose, and the BVH
    channel rotations, run through the file's own FK, put every joint there."""
    rig, cal, _ = hand
    t = tg.TargetSkeleton.from_bvh(BVH)
    rt = tg.Retargeter(rig, cal, t)
    assert rt.heading_deg == pytest.approx(180.0)  # target faces -Y, performer +Y
    pose = _pose(cal)
    _rotate_bones(pose, rig, _quat_z(-90.0), ["leftlowerarm", "lefthand"])  # elbow
    out = rt.apply(pose, rt.new_pose())
    # Locals relative to the BVH's A-pose rest: the upper arm is raised 45°.
    up_l = t.index("LeftUpperArm")
    assert _angle_deg(out.rest_from_bone_quat[up_l]) == pytest.approx(45.0)
    assert _angle_deg(out.rest_from_bone_quat[t.index("LeftLowerArm")]) == (
        pytest.approx(90.0)
    )
    pos = tg.joint_positions_world(t, out)
    d = pos[t.index("LeftLowerArm")] - pos[up_l]
    np.testing.assert_allclose(d / np.linalg.norm(d), [-1, 0, 0], atol=1e-12)
    d = pos[t.index("LeftHand")] - pos[t.index("LeftLowerArm")]
    np.testing.assert_allclose(d / np.linalg.norm(d), [0, 1, 0], atol=1e-12)
    # The BVH's own FK (file axes, cm) with the channel rotations gives the same joints.
    chan = tg.bone_axes_from_world_axes(t, out.rest_from_bone_quat)
    sk = read_bvh_hierarchy(BVH)
    rows = [sk.joint_names.index(j) for j in t.source_joints]
    q_file = np.tile([1.0, 0, 0, 0], (len(sk.joint_names), 1))
    q_file[rows] = chan
    a = world_from_capture_mat("+Y")
    file_pos = _bvh_fk(q_file, sk.offsets, sk.parents)[rows] @ a.T / 100.0
    np.testing.assert_allclose(file_pos - file_pos[0], pos - pos[0], atol=1e-12)
