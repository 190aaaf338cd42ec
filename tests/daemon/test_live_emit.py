"""The live loop's one compiled call per frame (``live/emit.py``) writes exactly what
the separate steps it replaced wrote: ``StanceDetector.update`` (the foot contact),
``Retargeter.apply``, ``engine_unity``'s two conversions, ``VmcEncoder.encode`` and
``PoseEncoder.encode``, byte for byte, on the real Plug-in Gait walk solved both
ways."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from retargetd.daemon.body.calibration import load_calibration
from retargetd.daemon.body.method import make_body_solver
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.live.emit import (
    DO_POSE,
    DO_RETARGET,
    DO_STANCE,
    DO_VMC,
    EmitPlan,
    emit_frame,
)
from retargetd.daemon.post.stance import StanceDetector
from retargetd.daemon.retarget.retarget import Retargeter, default_humanoid
from retargetd.protocols import engine_unity, pose_stream
from retargetd.protocols.vmc_out import VmcEncoder
from retargetd.replay.takes import load_take

PIG_WALK = "btkdata/PiG_Motion-FlatFoot-Full.c3d"
N_BLEND = 5


def _parts(enc: pose_stream.PoseEncoder) -> bytes:
    return b"".join(bytes(p) for p in enc.parts[:2])


@pytest.mark.timeout(300)
@pytest.mark.parametrize("method", ["construction", "fit"])
@pytest.mark.parametrize("spine", [False, True])
def test_emit_frame_equals_the_separate_steps_byte_for_byte(
    method: str, spine: bool, pig_calibration: Path, datasets: Path
) -> None:
    rig = load_rig("plug-in-gait")
    cal = load_calibration(pig_calibration)
    take = load_take(datasets / PIG_WALK)
    solver = make_body_solver(method, rig, cal, take.labels)
    target = default_humanoid()
    rt = Retargeter(rig, cal, target)
    names = tuple(target.bone_names)
    n, b = len(names), len(rig.bones)
    blends = tuple(f"B{i}" for i in range(N_BLEND))
    vmc_old, vmc_new = VmcEncoder(names, blends), VmcEncoder(names, blends)
    pose_old = pose_stream.PoseEncoder(b, 3, names_id=7, performer=2)
    pose_new = pose_stream.PoseEncoder(b, 3, names_id=7, performer=2)
    tp_old = rt.new_pose()
    bone_pos = np.zeros((n, 3))
    engine_unity.unity_pos_from_world(np.asarray(tp_old.rest_offsets), bone_pos)
    plan = EmitPlan(rt, vmc_new, pose_new, bone_pos)
    tp_new = plan.target_pose
    bq, rp, root_quat = np.zeros((n, 4)), np.zeros(3), np.array([0.0, 0, 0, 1])
    pose = solver.new_pose()
    blend, weights = np.zeros(N_BLEND), np.zeros(3)  # bound: written in place
    # The contact inside the call unless the loop pivots (then it runs before).
    st_old, st_new = StanceDetector(rig, cal), StanceDetector(rig, cal)
    assert st_new.known  # the walk's rig maps both feet
    folded = None if spine else st_new
    plan.bind(pose, blend, weights, folded)
    assert plan.stance is folded
    # The loop calls the compiled function itself (EmitPlan.call), past numba's
    # dispatcher: found for these types (warm: compiled by the calls below at the
    # latest), and every other frame goes through it, byte for byte the same.
    emit_frame(
        DO_RETARGET, *plan.args, np.zeros(0, np.uint8), 0.0, 0, 0.0, 0, 0, 0, 0.0
    )  # fmt: skip
    plan.bind(pose, blend, weights, folded)
    assert plan.call is not emit_frame
    contacts: set[int] = set()
    rng = np.random.default_rng(11)
    frames = np.asarray(take.positions, dtype=np.float64)
    checked = 0
    for i in range(len(frames)):
        solver.solve_frame(frames[i], pose)
        blend[:] = rng.uniform(size=N_BLEND)
        weights[:] = rng.uniform(size=3)
        or_flags = (
            rng.integers(0, 16, b).astype(np.uint8) << 4
            if i % 3
            else np.zeros(0, np.uint8)
        )
        flags = int(rng.integers(0, 1 << 16))
        t_s = 0.004 * i
        source_t = np.nan if i % 5 == 0 else i / 100.0
        stamps = (i, source_t, 10_000 + i, 20_000 + i)
        dt = 0.0 if i == 0 else 1.0 / take.rate_hz
        # The steps the loop made before.
        contact_old = 0
        if not spine:
            contact_old = st_old.update(pose.root_pos, pose.world_from_bone_quat, dt)
        rt.apply(pose, tp_old)
        engine_unity.unity_quat_xyzw_from_world(tp_old.rest_from_bone_quat, bq)
        engine_unity.unity_pos_from_world(tp_old.root_pos, rp)
        want_vmc = b"".join(
            bytes(d) for d in vmc_old.encode(rp, root_quat, bone_pos, bq, blend, t_s)
        )
        sent_flags = pose.bone_flags
        if len(or_flags) == b:
            sent_flags = pose.bone_flags | or_flags
        pose_old.encode(
            *stamps, flags | contact_old, pose.root_pos, pose.world_from_bone_quat,
            pose.parent_from_bone_quat, pose.rest_from_bone_quat, weights, sent_flags,
        )  # fmt: skip
        # The one call.
        what = DO_VMC | DO_POSE | (0 if spine else DO_STANCE)
        if spine:  # the loop retargets itself (and pivots) first, then packs
            rt.apply(pose, tp_new)
        else:
            what |= DO_RETARGET
        word = (flags & ~pose_stream.PERFORMER_MASK) | pose_new.performer_bits
        call = plan.call if i % 2 else emit_frame
        contact = call(what, *plan.args, or_flags, t_s, *stamps, word, dt)
        assert contact == contact_old, f"contact, frame {i}"
        contacts.add(contact)
        np.testing.assert_array_equal(st_new.state, st_old.state if not spine else 0)
        np.testing.assert_array_equal(st_new.clock, st_old.clock)
        got_vmc = b"".join(bytes(d) for d in vmc_new.datagrams)
        assert got_vmc == want_vmc, f"VMC, frame {i}"
        assert _parts(pose_new) == _parts(pose_old), f"pose message, frame {i}"
        for field in ("world_from_bone_quat", "rest_from_bone_quat", "root_pos",
                      "hips_pos", "flags"):  # fmt: skip
            np.testing.assert_array_equal(
                getattr(tp_new, field), getattr(tp_old, field), err_msg=field
            )
        checked += 1
    assert checked == len(frames) > 300
    if not spine:  # the walk's feet were seen in and out of contact
        assert len(contacts) >= 3, contacts


def test_stamp_flags_rewrites_only_the_flags_word() -> None:
    enc = pose_stream.PoseEncoder(2, 0, performer=3)
    q = np.tile([1.0, 0.0, 0.0, 0.0], (2, 1))
    parts = enc.encode(5, 0.5, 1, 2, 0x11, np.zeros(3), q, q, q, np.zeros(0),
                       np.zeros(2, np.uint8))  # fmt: skip
    before = bytes(parts[0])
    word = 0x11 | enc.performer_bits
    pose_stream.stamp_flags(parts[0], word | pose_stream.FRAME_LATE)
    msg = pose_stream.decode_pose([bytes(p) for p in parts])
    assert msg.flags == 0x11 | pose_stream.FRAME_LATE and msg.performer == 3
    after = bytes(parts[0])
    off = pose_stream.FLAGS_OFFSET
    assert after[:off] == before[:off] and after[off + 4 :] == before[off + 4 :]
