"""A frame packet's feed, the body solve and the emit in one compiled call
(``solve_emit.feed_solve_emit_*``, the live loop's ``one_call.FastFrame``)
against the two calls the loop makes otherwise: ``MarkerStream.feed_packed`` (the
decode, the sequencer, the counter), the frame's interval
(``interval.frame_interval_s``) and the solve and emit (as ``test_solve_emit.py``
checks them, the solve and the emit as separate steps with the one call's stamp).
Both methods, OSC's packed form and ZeroMQ's, on the real Plug-in Gait walk with
mutated frames and packets duplicated, sent backwards, jumping ahead (a restart
after three), after a gap, corrupted, and of an unknown label set: every packet's
outcome, the stream (current frame, counters, sequencer), the counters the call
returns, the pose, the solver's and the contact detector's state, the VMC
datagram and the pose message agree after each."""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from numba import typeof

from retargetd.daemon.body.calibration import load_calibration
from retargetd.daemon.body.method import make_body_solver
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.live.emit import DO_POSE, DO_VMC, NO_FLAGS, EmitPlan
from retargetd.daemon.live.interval import frame_interval_s
from retargetd.daemon.live.solve_emit import (
    AVAILABLE,
    SolveEmit,
    interval_s,
    monotonic_ns,
    warm_fast_call,
)
from retargetd.daemon.post.stance import StanceDetector
from retargetd.daemon.retarget.retarget import Retargeter, default_humanoid
from retargetd.protocols import engine_unity, kernels, osc_in, pose_stream, zmq_wire
from retargetd.protocols import marker_input as mi
from retargetd.protocols.frames import MarkerFrame
from retargetd.protocols.vmc_out import VmcEncoder
from retargetd.replay.takes import load_take

pytestmark = pytest.mark.skipif(
    not AVAILABLE, reason="the compiled clock is not time.monotonic_ns()'s here"
)

PIG_WALK = "btkdata/PiG_Motion-FlatFoot-Full.c3d"
T0_NS = 123_456_789
SET_ID = 7
#: ``[validate] rate_hz`` (the interval from frame numbers without a source clock).
RATE_HZ = 240.0
POSE_FIELDS = (
    "joint_centres", "world_from_bone_quat", "parent_from_bone_quat",
    "rest_from_bone_quat", "root_pos", "bone_quality", "bone_flags",
)  # fmt: skip


def _side(method: str, rig: Any, cal: Any, labels: tuple[str, ...]) -> dict[str, Any]:
    """One path's stream, solver, pose, encoders, detector, bound plan and fused
    call."""
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
    assert plan.stance is stance
    stream = mi.MarkerStream(mi.LabelSet(SET_ID, labels))
    return {
        "solver": solver, "pose": pose, "vmc": vmc, "enc": enc, "plan": plan,
        "stance": stance, "fused": SolveEmit(solver, pose, plan), "stream": stream,
        "head": np.frombuffer(bytearray(65536), dtype=np.uint8),
        "payload": np.frombuffer(bytearray(65536), dtype=np.uint8),
    }  # fmt: skip


def _packets(frames: np.ndarray, rng: np.random.Generator) -> list[tuple[int, int]]:
    """(row of the take, frame number) per packet: the walk in order with a
    duplicate, a frame sent again late (backwards), a jump far ahead three packets
    long (adopted as a restart), another that does not last (dropped), and after
    the jump numbers that go on from it."""
    out: list[tuple[int, int]] = []
    offset = 0
    for i in range(len(frames)):
        if i == 120:  # far ahead from here on: dropped twice, then a restart
            offset = 1_000_000
        out.append((i, i + offset))
        if i % 41 == 40:  # the same packet again: a duplicate
            out.append((i, i + offset))
        if i % 53 == 52:  # an older packet late: backwards
            out.append((i - 3, i - 3 + offset))
        if i == 200:  # one packet far ahead (a corrupted number): dropped
            out.append((i, i + offset + 5_000_000))
    assert len({fid for _, fid in out}) < len(out)
    late = out[300:306]
    rng.shuffle(late)  # a few out of order
    out[300:306] = late
    return out


def _mutated(frames: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The walk with markers hidden for a while, frames with none, a marker thrown
    far, every marker jumped (as ``test_solve_emit.py``)."""
    out = frames.copy()
    n, m = out.shape[:2]
    for start in range(20, n - 10, 37):
        cols = rng.choice(m, size=int(rng.integers(1, 6)), replace=False)
        out[start : start + 6, cols] = np.nan
    out[50:53] = np.nan
    for i in range(90, n, 71):
        out[i, int(rng.integers(m))] += (0.4, -0.3, 0.2)
    out[140:143] += (0.6, 0.0, 0.0)
    return out


def _state(s: dict[str, Any]) -> tuple[Any, ...]:
    stream = s["stream"]
    f = stream.current.frame
    return (
        f.frame_id, np.float64(f.source_time_s).tobytes(), f.t_ns,
        f.markers_world.tobytes(), f.valid.tobytes(), stream.current.label_set_id,
        stream.counters.counts.tobytes(), stream.sequencer.q.tobytes(),
        int(stream.implausible[0]),
    )  # fmt: skip


def _solved_state(s: dict[str, Any]) -> list[bytes]:
    out = [np.asarray(getattr(s["pose"], k)).tobytes() for k in POSE_FIELDS]
    for a in s["solver"].packed_buffers(s["pose"]):
        for b in a if isinstance(a, tuple) else (a,):
            if isinstance(b, np.ndarray):
                out.append(b.tobytes())
    out += [s["stance"].state.tobytes(), s["stance"].clock.tobytes()]
    out.append(b"".join(bytes(d) for d in s["vmc"].datagrams))
    out.append(b"".join(bytes(p) for p in s["enc"].parts[:2]))
    return out


def _two_steps(
    s: dict[str, Any], what: int, word: int, dt: float, solved_ns: int
) -> tuple[int, int, int, int]:
    """The solve, then the emit with the flags between them (``BodyPath._emit``):
    (held, occluded, fit flags, contact)."""
    pose, frame = s["pose"], s["stream"].current.frame
    s["solver"].solve_frame(frame.markers_world, pose, dt)
    if pose.frame_flags & pose_stream.FRAME_UNSEEN:
        return pose.n_held, pose.n_occluded, pose.frame_flags, 0
    word |= pose.frame_flags | (pose_stream.FRAME_HELD if pose.n_held else 0)
    contact = s["plan"].call(
        what, *s["plan"].args, NO_FLAGS, (solved_ns - T0_NS) * 1e-9, frame.frame_id,
        frame.source_time_s, frame.t_ns, solved_ns, word, dt,
    )  # fmt: skip
    return pose.n_held, pose.n_occluded, pose.frame_flags, contact


def _feed_python(
    s: dict[str, Any], form: int, n_head: int, n_payload: int, t: int
) -> int:
    """A packet the compiled checks refused: the Python decoder says why."""
    st, head, payload = s["stream"], s["head"], s["payload"]
    if form == kernels.FORM_OSC_COMPACT:
        return st.feed(osc_in.decode_compact_into, head, n_head, t_ns=t)
    return st.feed(zmq_wire.decode_zmq_into, head, n_head, payload, n_payload, t_ns=t)


@pytest.mark.timeout(900)
@pytest.mark.parametrize("form", ["osc", "zmq"])
@pytest.mark.parametrize("method", ["construction", "fit"])
def test_one_call_equals_the_feed_then_the_frame(
    method: str, form: str, pig_calibration: Path, datasets: Path
) -> None:
    rig = load_rig("plug-in-gait")
    cal = load_calibration(pig_calibration)
    take = load_take(datasets / PIG_WALK)
    labels = tuple(take.labels)
    old, new = _side(method, rig, cal, labels), _side(method, rig, cal, labels)
    kind = kernels.FORM_OSC_COMPACT if form == "osc" else kernels.FORM_ZMQ
    stream = new["stream"]
    fused = new["fused"]
    packets = stream.packets()  # the two the decode alternates between (FastFrame)
    tails = tuple(
        (*stream.fused_tail(kind, new["head"], new["payload"], p), *fused.args,
         T0_NS, RATE_HZ)
        for p in packets
    )  # fmt: skip
    rng = np.random.default_rng(35)
    frames = _mutated(np.asarray(take.positions, dtype=np.float64), rng)
    last_old: tuple[float, int, int] = (math.nan, -1, 0)
    last_new: tuple[float, int, int] = (math.nan, -1, 0)
    t_ns = 10_000_000
    step_ns = int(1e9 / take.rate_hz)
    outcomes: set[int] = set()
    bits_seen: set[int] = set()
    contacts: set[int] = set()
    n_solved = 0
    for k, (row, fid) in enumerate(_packets(frames, rng)):
        t_ns += step_ns if k != 400 else 1_500_000_000  # one gap past 1 s
        source_t = math.nan if k % 7 == 0 else fid / take.rate_hz
        set_id = SET_ID if k % 97 != 96 else SET_ID + 1  # an unknown label set
        pos = frames[row]
        if kind == kernels.FORM_OSC_COMPACT:
            head, payload = osc_in.encode_compact_frame(fid, source_t, set_id, pos), b""
        else:
            head, payload = zmq_wire.encode_zmq_frame(fid, source_t, set_id, pos)
        if k % 89 == 88:  # a byte changed: refused somewhere, or not
            m = bytearray(head)
            m[int(rng.integers(0, len(m)))] ^= 0x5A
            head = bytes(m)
        for s in (old, new):
            s["head"][: len(head)] = np.frombuffer(head, np.uint8)
            s["payload"][: len(payload)] = np.frombuffer(payload, np.uint8)
        nh, npl = len(head), len(payload)
        what = fused.what | (DO_VMC if k % 11 else 0) | (DO_POSE if k % 13 else 0)
        word = (int(rng.integers(0, 1 << 16)) & ~pose_stream.PERFORMER_MASK) | (
            new["enc"].performer_bits
        )
        # The two calls' side: the packet's feed first.
        code_old = old["stream"].feed_packed(kind, old["head"], nh, old["payload"],
                                             npl, t_ns)  # fmt: skip
        if code_old < 0:
            code_old = _feed_python(old, kind, nh, npl, t_ns)
        # The one call (the spare's arguments, as FastFrame.run picks them).
        spare = stream.spare_packet()
        assert spare is packets[0] or spare is packets[1]
        tail = tails[0] if spare is packets[0] else tails[1]
        t_before = monotonic_ns()
        got = fused.fast_kernel(nh, npl, t_ns, what, word, *last_new, *tail)
        t_after = time.monotonic_ns()
        code = stream.take(got[0], got[1], got[2], t_ns)
        if code < 0:
            code = _feed_python(new, kind, nh, npl, t_ns)
        assert code == code_old, f"packet {k}"
        assert _state(new) == _state(old), f"stream, packet {k}"
        outcomes.add(code)
        if code == mi.ACCEPTED:  # solved in the one call
            dt, last_old = frame_interval_s(
                last_old, old["stream"].current.frame, t_ns, RATE_HZ
            )
            last_new = (got[2], got[1], t_ns)  # (FastFrame.run)
            bits = [np.float64(x[0]).tobytes() for x in (last_new, last_old)]
            assert bits[0] == bits[1]
            assert last_new[1:] == last_old[1:]
            n_held, n_occ, fit_bits, contact, solved_ns, t_start = got[3:]
            ref = _two_steps(old, what, word, dt, solved_ns)
            assert (n_held, n_occ, fit_bits, contact) == ref, f"counters, packet {k}"
            bits_seen.add(fit_bits)
            if fit_bits & pose_stream.FRAME_UNSEEN:
                assert (contact, solved_ns) == (0, 0)
            else:
                assert t_before <= t_start <= solved_ns <= t_after
                contacts.add(contact)
            n_solved += 1
        elif code == mi.RESTART:  # the loop solves a restart with the two calls
            solved_ns = monotonic_ns()
            for s in (old, new):
                s["solver"].reset()
                s["vmc"].reset_continuity()
            dt, last_old = frame_interval_s(
                last_old, old["stream"].current.frame, t_ns, RATE_HZ
            )
            dt_new, last_new = frame_interval_s(
                last_new, new["stream"].current.frame, t_ns, RATE_HZ
            )
            assert dt_new == dt
            _two_steps(old, what, word, dt, solved_ns)
            _two_steps(new, what, word, dt, solved_ns)
        assert _solved_state(new) == _solved_state(old), f"solved state, packet {k}"
    # The packets met what they were built to meet.
    wanted = {mi.ACCEPTED, mi.RESTART, mi.DUPLICATE, mi.BACKWARDS,
              mi.IMPLAUSIBLE_JUMP, mi.UNKNOWN_LABEL_SET}  # fmt: skip
    assert wanted <= outcomes, outcomes
    assert n_solved > 300 and len(contacts) >= 3, (n_solved, contacts)
    if method == "fit":
        assert any(b & pose_stream.FRAME_UNSEEN for b in bits_seen), bits_seen


@pytest.mark.parametrize(
    ("last", "t", "fid", "received_ns"),
    [
        ((math.nan, -1, 0), 1.0, 5, 100),  # the first frame
        ((0.5, 4, 90), 0.75, 5, 100),  # the source's clock
        ((math.nan, 4, 90), math.nan, 7, 100),  # frame numbers
        ((0.5, 4, 90), 0.5, 7, 100),  # the clock not ahead: frame numbers
        ((math.nan, 9, 90), math.nan, 7, 4_000_123),  # neither: the receive clock
        ((math.nan, 9, 9_000), math.nan, 7, 100),  # a receive clock back: 0
    ],
)
def test_interval_is_frame_interval_s(
    last: tuple[float, int, int], t: float, fid: int, received_ns: int
) -> None:
    frame = MarkerFrame.empty(0)
    frame.source_time_s, frame.frame_id = t, fid
    want, _ = frame_interval_s(last, frame, received_ns, RATE_HZ)
    got = interval_s(*last, t, fid, received_ns, RATE_HZ)
    assert np.float64(got).tobytes() == np.float64(want).tobytes()


@pytest.mark.parametrize("form", ["osc", "zmq"])
@pytest.mark.parametrize("method", ["construction", "fit"])
def test_warm_up_compiles_the_types_the_loop_passes(
    method: str, form: str, exact_calibration: Path
) -> None:
    """The daemon's start compiles (or loads) the one call
    (``solve_emit.warm_up``): the loop's arguments must have the same types, else
    its first frame compiles."""
    from live_harness import EXACT_RIG, _take

    rig = load_rig(EXACT_RIG)
    side = _side(method, rig, load_calibration(exact_calibration), _take().labels)
    kind = kernels.FORM_OSC_COMPACT if form == "osc" else kernels.FORM_ZMQ
    st, fused = side["stream"], side["fused"]
    real = (
        48, 0, 10_000, fused.what, 0, math.nan, -1, 0,
        *st.fused_tail(kind, side["head"], side["payload"], st.packets()[1]),
        *fused.args, T0_NS, RATE_HZ,
    )  # fmt: skip
    kernel, warm = warm_fast_call(method == "fit")
    assert kernel is fused.fast_kernel
    assert len(warm) == len(real)
    for k, (a, b) in enumerate(zip(warm, real, strict=True)):
        assert typeof(a) == typeof(b), f"argument {k}: {typeof(a)} != {typeof(b)}"
