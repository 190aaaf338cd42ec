"""The body solve and the emit in one compiled call (``live/solve_emit.py``) against
the two calls the loop made before (``solver.solve_frame``, then ``EmitPlan.call``
with the flags ``BodyPath._emit`` built in between): the same VMC datagram and pose
message byte for byte, the same counters (bones held, markers occluded, the fit's
frame flags, the foot contact), the same pose and the same solver and detector
state, on the real Plug-in Gait walk with mutated frames (hidden markers, a frame
with none, markers thrown away, a jump), both body methods."""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from live_harness import EXACT_RIG, _take
from numba import typeof

from retargetd.daemon.body.calibration import load_calibration
from retargetd.daemon.body.method import make_body_solver
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.live.config import DaemonConfig
from retargetd.daemon.live.emit import (
    DO_POSE,
    DO_RETARGET,
    DO_STANCE,
    DO_VMC,
    NO_FLAGS,
    EmitPlan,
)
from retargetd.daemon.live.pipeline import may_fuse
from retargetd.daemon.live.solve_emit import (
    AVAILABLE,
    SolveEmit,
    monotonic_ns,
    warm_call,
)
from retargetd.daemon.post.stance import StanceDetector
from retargetd.daemon.retarget.retarget import Retargeter, default_humanoid
from retargetd.protocols import engine_unity, pose_stream
from retargetd.protocols.vmc_out import VmcEncoder
from retargetd.replay.takes import load_take

pytestmark = pytest.mark.skipif(
    not AVAILABLE, reason="the compiled clock is not time.monotonic_ns()'s here"
)

PIG_WALK = "btkdata/PiG_Motion-FlatFoot-Full.c3d"
T0_NS = 123_456_789
POSE_FIELDS = (
    "joint_centres", "world_from_bone_quat", "parent_from_bone_quat",
    "rest_from_bone_quat", "root_pos", "bone_quality", "bone_flags",
)  # fmt: skip


def _side(method: str, rig: Any, cal: Any, labels: tuple[str, ...]) -> dict[str, Any]:
    """One path's solver, pose, encoders, detector and bound emit plan."""
    solver = make_body_solver(method, rig, cal, labels)
    target = default_humanoid()
    rt = Retargeter(rig, cal, target)
    names = tuple(target.bone_names)
    vmc = VmcEncoder(names, ())
    enc = pose_stream.PoseEncoder(len(rig.bones), 0, names_id=3, performer=1)
    bone_pos = np.zeros((len(names), 3))
    engine_unity.unity_pos_from_world(np.asarray(rt.new_pose().rest_offsets), bone_pos)
    plan = EmitPlan(rt, vmc, enc, bone_pos)
    pose = solver.new_pose()
    stance = StanceDetector(rig, cal)
    plan.bind(pose, np.zeros(0), np.zeros(0), stance)
    assert plan.stance is stance  # the contact inside the call, as live
    return {"solver": solver, "pose": pose, "vmc": vmc, "enc": enc, "plan": plan,
            "stance": stance}  # fmt: skip


def _mutated(frames: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The walk with what a live stream brings: markers hidden for a while, frames
    with none, a marker thrown far, every marker jumped."""
    out = frames.copy()
    n, m = out.shape[:2]
    for start in range(20, n - 10, 37):  # a few markers hidden for 6 frames
        cols = rng.choice(m, size=int(rng.integers(1, 6)), replace=False)
        out[start : start + 6, cols] = np.nan
    out[50:53] = np.nan  # nothing seen (the fit: unseen, not emitted)
    for i in range(90, n, 71):  # one marker 0.4 m off
        out[i, int(rng.integers(m))] += (0.4, -0.3, 0.2)
    out[140:143] += (0.6, 0.0, 0.0)  # everything jumps (the fit: reseeded)
    return out


def _packed(side: dict[str, Any]) -> list[np.ndarray]:
    arrays: list[np.ndarray] = []
    for a in side["solver"].packed_buffers(side["pose"]):
        if isinstance(a, tuple):
            arrays.extend(a)
        elif isinstance(a, np.ndarray):
            arrays.append(a)
    return arrays


@pytest.mark.timeout(600)
@pytest.mark.parametrize("method", ["construction", "fit"])
def test_solve_emit_equals_solve_then_emit(
    method: str, pig_calibration: Path, datasets: Path
) -> None:
    rig = load_rig("plug-in-gait")
    cal = load_calibration(pig_calibration)
    take = load_take(datasets / PIG_WALK)
    labels = tuple(take.labels)
    old, new = _side(method, rig, cal, labels), _side(method, rig, cal, labels)
    fused = SolveEmit(new["solver"], new["pose"], new["plan"])
    assert fused.what == DO_RETARGET | DO_STANCE
    rng = np.random.default_rng(35)
    frames = _mutated(np.asarray(take.positions, dtype=np.float64), rng)
    pose_old, pose_new = old["pose"], new["pose"]
    seen_bits: set[int] = set()
    contacts: set[int] = set()
    held = occluded = emitted = 0
    for i in range(len(frames)):
        markers = np.ascontiguousarray(frames[i])
        dt = 0.0 if i == 0 or i % 29 == 0 else 1.0 / take.rate_hz
        source_t = math.nan if i % 7 == 0 else i / take.rate_hz
        before = (int(rng.integers(0, 1 << 16)) & ~pose_stream.PERFORMER_MASK) | (
            new["enc"].performer_bits
        )  # (the loop's frame and match flags, the performer's id)
        what = fused.what | (DO_VMC if i % 11 else 0) | (DO_POSE if i % 13 else 0)
        # The one call (its compiled function past the dispatcher, every other
        # frame through the dispatcher).
        call = fused.call if i % 2 else fused.kernel
        t_before = monotonic_ns()
        n_held, n_occ, fit_bits, contact, solved_ns = call(
            what, markers, *fused.args, T0_NS, i, source_t, 10_000 + i, before, dt
        )
        t_after = time.monotonic_ns()
        # The two calls and the flags between them, as BodyPath did.
        old["solver"].solve_frame(markers, pose_old, dt)
        assert (n_held, n_occ, fit_bits) == (
            pose_old.n_held, pose_old.n_occluded, pose_old.frame_flags,
        ), f"counters, frame {i}"  # fmt: skip
        seen_bits.add(fit_bits)
        if fit_bits & pose_stream.FRAME_UNSEEN:  # not emitted: nothing stamped
            assert (contact, solved_ns) == (0, 0)
        else:
            assert t_before <= solved_ns <= t_after, "solved_ns is monotonic_ns's"
            word = before | pose_old.frame_flags
            word |= pose_stream.FRAME_HELD if pose_old.n_held else 0
            contact_old = old["plan"].call(
                what, *old["plan"].args, NO_FLAGS, (solved_ns - T0_NS) * 1e-9, i,
                source_t, 10_000 + i, solved_ns, word, dt,
            )  # fmt: skip
            assert contact == contact_old, f"contact, frame {i}"
            contacts.add(contact)
            emitted += 1
        held += n_held > 0
        occluded += n_occ > 0
        for name in POSE_FIELDS:
            np.testing.assert_array_equal(
                getattr(pose_new, name), getattr(pose_old, name), err_msg=name
            )
        for a, b in zip(_packed(new), _packed(old), strict=True):  # solver state
            np.testing.assert_array_equal(a, b, err_msg=f"solver state, frame {i}")
        np.testing.assert_array_equal(new["stance"].state, old["stance"].state)
        np.testing.assert_array_equal(new["stance"].clock, old["stance"].clock)
        got_vmc = b"".join(bytes(d) for d in new["vmc"].datagrams)
        want_vmc = b"".join(bytes(d) for d in old["vmc"].datagrams)
        assert got_vmc == want_vmc, f"VMC, frame {i}"
        got = b"".join(bytes(p) for p in new["enc"].parts[:2])
        want = b"".join(bytes(p) for p in old["enc"].parts[:2])
        assert got == want, f"pose message, frame {i}"
    # The mutations reached the paths they were meant for.
    assert held > 10 and occluded > 10 and emitted > 300
    assert len(contacts) >= 3, contacts
    if method == "fit":
        assert any(b & pose_stream.FRAME_UNSEEN for b in seen_bits), seen_bits
        assert any(b & pose_stream.FRAME_RESEEDED for b in seen_bits), seen_bits
    else:
        assert seen_bits == {0}


@pytest.mark.parametrize("method", ["construction", "fit"])
def test_warm_up_compiles_the_types_a_pipeline_passes(
    method: str, exact_calibration: Path
) -> None:
    """The daemon's start compiles (or loads) the fused kernel on the warm-up rig
    (``solve_emit.warm_up``): a pipeline's call must have the same argument types,
    else its first frame compiles (the reverted h35s tree's slow starts)."""
    rig = load_rig(EXACT_RIG)
    side = _side(method, rig, load_calibration(exact_calibration), _take().labels)
    fused = SolveEmit(side["solver"], side["pose"], side["plan"])
    markers = np.zeros((side["solver"].n_stream, 3))
    real = (fused.what, markers, *fused.args, T0_NS, 1, 0.5, 10_000, 0, 0.01)
    kernel, warm = warm_call(method == "fit")
    assert kernel is fused.kernel
    assert len(warm) == len(real)
    for k, (a, b) in enumerate(zip(warm, real, strict=True)):
        assert typeof(a) == typeof(b), f"argument {k}: {typeof(a)} != {typeof(b)}"


@pytest.mark.parametrize(
    ("extra", "fused"),
    [
        ({}, True),
        ({"pipeline": [{"kind": "one_euro"}]}, True),  # a reload may remove it
        ({"loop": {"output_rate_hz": 60.0}}, False),
        ({"target": {"spine": "pivot"}}, False),
        ({"target": {"feet": "plant"}}, False),
    ],
)
def test_the_start_warms_the_fused_call_only_where_it_can_run(
    extra: dict[str, Any], fused: bool
) -> None:
    config = DaemonConfig.from_dict(
        {"performer": {"rig": str(EXACT_RIG)}, **extra}, source="test"
    )
    assert may_fuse(config) is fused
