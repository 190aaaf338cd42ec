"""Slerp at work (5.86-5.87): resampling, gap filling, blending, loops, live resampling.

Oracles: scipy's ``Slerp`` between the same keys, and the synthetic performer's truth
at the target rate with the linear-interpolation error bound.
"""

from __future__ import annotations

import tracemalloc
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from retargetd.daemon import rotations as rot
from retargetd.daemon.post.interp import (
    Clip,
    RateResampler,
    blend,
    fill_gaps,
    fill_gaps_linear,
    find_loop,
    loop,
    resample,
)
from retargetd.daemon.post.pose import PoseBuffer
from retargetd.daemon.synth import performer as pf

MOTIONS = ("walk", "arm_raise", "forearm_twist", "spine", "head_turn")
Synth = Callable[[tuple[str, ...], float, float], pf.SynthTake]


def _norm_err(q: np.ndarray) -> float:
    return float(np.max(np.abs(np.linalg.norm(q, axis=-1) - 1.0)))


def _steps(q: np.ndarray) -> np.ndarray:
    """(T-1, B) rotation angle from each frame to the next, radians."""
    return rot.quat_angle(rot.quat_mul(rot.quat_conj(q[:-1]), q[1:]))


def _angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return rot.quat_angle(rot.quat_mul(rot.quat_conj(a), b))


@pytest.mark.parametrize("rate_hz", [60.0, 120.0])
def test_resample_matches_scipy_and_the_truth(
    synth_take: Synth, rate_hz: float
) -> None:
    src = synth_take(MOTIONS, 100.0, 3.0)
    times, q, p = resample(
        src.times_s, src.parent_from_segment_quat, src.joint_pos_world[:, 0], rate_hz
    )
    assert _norm_err(q) < 1e-12
    truth = synth_take(MOTIONS, rate_hz, 3.0)
    n = len(times)
    np.testing.assert_allclose(times, truth.times_s[:n], atol=1e-12)
    for b in range(q.shape[1]):
        keys = Rotation.from_quat(src.parent_from_segment_quat[:, b], scalar_first=True)
        expected = Slerp(src.times_s, keys)(times).as_quat(scalar_first=True)
        assert np.all(np.abs(np.abs(np.sum(q[:, b] * expected, -1)) - 1) < 1e-12)
    # Against the truth: slerp between keys h apart is linear interpolation of
    # r(t) = log(q_i^-1 q(t)), wrong by <= h^2/8 max|r''| in the tangent space, and
    # exp is distance non-increasing on the (positively curved) rotation group, so
    # the angle error obeys the same bound. max|r''| from a 1 kHz truth.
    fine = synth_take(MOTIONS, 1000.0, 3.0)
    fq = fine.parent_from_segment_quat
    h = 0.01
    acc = np.zeros(fq.shape[1])
    for i in range(len(src.times_s) - 1):
        seg = fq[10 * i : 10 * i + 11]
        r = rot.rotvec_from_quat(rot.quat_mul(rot.quat_conj(seg[:1]), seg))
        second = np.linalg.norm(r[2:] - 2 * r[1:-1] + r[:-2], axis=-1) / 1e-3**2
        acc = np.maximum(acc, second.max(axis=0))
    err = _angle(q, truth.parent_from_segment_quat[:n])
    bound = h**2 / 8 * acc
    worst_deg, bound_deg = np.degrees(err.max()), np.degrees(bound.max())
    print(f"\n{rate_hz} Hz: worst {worst_deg:.4f} deg, bound {bound_deg:.4f}")
    assert np.all(err <= bound * 1.01 + 1e-12)  # 1 %: max|r''| sampled at 1 kHz
    root_truth = truth.joint_pos_world[:n, 0]
    assert np.max(np.abs(p - root_truth)) < 1e-3  # 1 mm: well under marker noise


def test_fill_gaps(synth_take: Synth, rng: np.random.Generator) -> None:
    src = synth_take(MOTIONS, 100.0, 3.0)
    q = src.parent_from_segment_quat
    valid = np.ones(q.shape[:2], dtype=bool)
    gaps = []
    for b in range(q.shape[1]):
        start = int(rng.integers(5, 200))
        length = int(rng.integers(1, 12))
        valid[start : start + length, b] = False
        gaps.append((b, start, length))
    valid[:3, 0] = False  # at the start: never filled
    holes = np.where(valid[..., None], q, np.nan)
    out, filled = fill_gaps(holes, valid, max_frames=8)
    for b, start, length in gaps:
        if length > 8:
            assert not filled[start : start + length, b].any()
            assert np.isnan(out[start : start + length, b]).all()
            continue
        assert filled[start : start + length, b].all()
        a, z = start - 1, start + length
        keys = Rotation.from_quat(q[[a, z], b], scalar_first=True)
        exp = Slerp([a, z], keys)(np.arange(start, z)).as_quat(scalar_first=True)
        assert np.all(np.abs(np.abs(np.sum(out[start:z, b] * exp, -1)) - 1) < 1e-12)
    assert np.isnan(out[:3, 0]).all() and not filled[:3, 0].any()
    assert filled.sum() == (~valid).sum() - 3 - sum(n for _, _, n in gaps if n > 8)
    assert _norm_err(out[filled]) < 1e-12
    # Positions: linear.
    pos = src.joint_pos_world[:, 0]
    pv = np.ones(len(pos), dtype=bool)
    pv[50:55] = False
    pout, pfilled = fill_gaps_linear(np.where(pv[:, None], pos, np.nan), pv, 5)
    np.testing.assert_allclose(
        pout[52], pos[49] + (pos[55] - pos[49]) * 3 / 6, atol=1e-15
    )
    assert pfilled.sum() == 5


def _seam_ok(
    out: np.ndarray, own_takes: tuple[np.ndarray, ...], mismatch: np.ndarray, n: int
) -> float:
    """Largest excess of a step of ``out`` over its bound, per bone (<= 0 passes).

    Frame k of a fade is slerp(a_k, b_k, u_k); by the triangle inequality its step is
    at most the larger of the two takes' own steps plus |u_{k+1} - u_k| = 1 / (N + 1)
    of the pose mismatch d(a, b) at the join. With frames alike in pose (the
    chapter's condition) the mismatch term vanishes and the bound is the takes' own
    frame-to-frame motion.
    """
    own = np.max(np.stack([_steps(t).max(axis=0) for t in own_takes]), axis=0)
    bound = own + mismatch / (n + 1)
    return float(np.max(_steps(out).max(axis=0) - bound))


def test_blend_two_takes(synth_take: Synth) -> None:
    src = synth_take(("walk", "arm_raise", "head_turn"), 100.0, 6.0)
    qa = src.parent_from_segment_quat
    pa = src.joint_pos_world[:, 0]
    a = Clip(parent_from_bone_quat=qa, root_pos=pa, rate_hz=100.0)
    # B: the same motion 37 frames later, turned 40° and moved 2 m away.
    turn = rot.quat_from_axis_angle([0.0, 0.0, 1.0], np.radians(40.0))
    qb = qa[37:].copy()
    qb[:, 0] = rot.quat_mul(turn, qb[:, 0])
    pb = rot.quat_rotate(turn, pa[37:]) + np.array([1.0, -2.0, 0.0])
    b = Clip(parent_from_bone_quat=qb, root_pos=pb, rate_hz=100.0)
    at_a, n = 250, 30
    at_b = at_a - 37 + 2  # two frames off: the poses are alike, not equal
    out = blend(a, b, at_a, at_b, n)
    assert out.n_frames == at_a + b.n_frames - at_b
    assert _norm_err(out.parent_from_bone_quat) < 1e-12
    np.testing.assert_array_equal(out.parent_from_bone_quat[:at_a], qa[:at_a])
    mismatch = _angle(qa[at_a : at_a + n], qb[at_b : at_b + n]).max(axis=0)
    assert _seam_ok(out.parent_from_bone_quat, (qa, qb), mismatch, n) <= 1e-12
    own_root = max(np.linalg.norm(np.diff(pa, axis=0), axis=-1).max(), 1e-9)
    assert np.linalg.norm(np.diff(out.root_pos, axis=0), axis=-1).max() <= own_root
    # Without aligning, the 40° turn and the 2 m jump are spread over the fade.
    raw = blend(a, b, at_a, at_b, n, align_root=False)
    assert _steps(raw.parent_from_bone_quat)[:, 0].max() > _steps(qa)[:, 0].max()


def _cyclic_clip(n_extra: int) -> Clip:
    """1 Hz motion of 6 bones at 100 Hz, walking 1.2 m/s along x."""
    t = np.arange(100 + n_extra) / 100.0
    rng = np.random.default_rng(4)
    amp = rng.uniform(0.1, 0.8, size=(6, 3))
    phase = rng.uniform(0, 2 * np.pi, size=(6, 3))
    rv = amp * np.sin(2 * np.pi * t[:, None, None] + phase)
    root = np.stack(
        [1.2 * t, 0.02 * np.sin(2 * np.pi * t), 0.9 + 0.02 * np.cos(4 * np.pi * t)], -1
    )
    return Clip(
        parent_from_bone_quat=rot.quat_from_rotvec(rv), root_pos=root, rate_hz=100.0
    )


def test_loop_of_a_cyclic_take() -> None:
    n = 12
    clip = _cyclic_clip(n + 3)  # the cycle is 100 frames; 3 frames too many
    end = find_loop(clip, n, 60)
    assert end == 100
    cut = Clip(parent_from_bone_quat=clip.parent_from_bone_quat[: end + n],
               root_pos=clip.root_pos[: end + n], rate_hz=100.0)  # fmt: skip
    looped, travel = loop(cut, n)
    assert looped.n_frames == end
    np.testing.assert_allclose(travel, [1.2, 0.0, 0.0], atol=1e-12)
    q = looped.parent_from_bone_quat
    assert _norm_err(q) < 1e-12
    twice = np.concatenate([q, q[:5]])  # played round: the wrap is a step too
    cq = cut.parent_from_bone_quat
    mismatch = _angle(cq[-n:], cq[:n]).max(axis=0)
    assert mismatch.max() < _steps(cq).max()  # 3 frames off: a small mismatch
    assert _seam_ok(twice, (cq,), mismatch, n) <= 1e-12
    wrapped = np.concatenate([looped.root_pos, looped.root_pos[:1] + travel])
    own = np.linalg.norm(np.diff(clip.root_pos, axis=0), axis=-1).max()
    assert np.linalg.norm(np.diff(wrapped, axis=0), axis=-1).max() <= own + 1e-12


def test_loop_of_the_real_walk(pig_walk: Any) -> None:
    res = pig_walk.solve
    q = res.parent_from_bone_quat
    ok = np.all(np.isfinite(q), axis=(1, 2))
    first_bad = int(np.argmin(ok)) if not ok.all() else len(q)
    clip = Clip(parent_from_bone_quat=q[:first_bad], root_pos=res.root_pos[:first_bad],
                rate_hz=pig_walk.rate_hz)  # fmt: skip
    n = 10  # 0.1 s
    # One gait cycle is about 1 s at a normal walking cadence (~110 steps/min,
    # Perry & Burnfield, "Gait Analysis", 2010): search from 0.8 s.
    end = find_loop(clip, n, int(0.8 * clip.rate_hz))
    cut = Clip(parent_from_bone_quat=clip.parent_from_bone_quat[: end + n],
               root_pos=clip.root_pos[: end + n], rate_hz=clip.rate_hz)  # fmt: skip
    looped, travel = loop(cut, n)
    print(f"\nPiG walk loop: {end} frames, travel {travel}")
    lq = looped.parent_from_bone_quat
    assert _norm_err(lq) < 1e-12
    cq = cut.parent_from_bone_quat
    mismatch = _angle(cq[-n:], cq[:n]).max(axis=0)
    own = _steps(clip.parent_from_bone_quat).max(axis=0)
    seam = _steps(np.concatenate([lq[-n:], lq[: n + 1]])).max(axis=0)
    print("seam / own max step per bone:", np.round(seam / own, 2))
    print("mismatch / own max step:", np.round(mismatch / own, 2))
    assert _seam_ok(np.concatenate([lq, lq[: n + 1]]), (cq,), mismatch, n) <= 1e-12


def test_live_resampler_matches_offline(synth_take: Synth) -> None:
    src = synth_take(MOTIONS, 100.0, 2.0)
    q, p = src.parent_from_segment_quat, src.joint_pos_world[:, 0]
    times, eq, ep = resample(src.times_s, q, p, 60.0)
    r = RateResampler(q.shape[1], 60.0)
    pose, out = PoseBuffer.new(q.shape[1]), PoseBuffer.new(q.shape[1])
    got_q, got_p, got_t = [], [], []
    for t in range(len(q)):
        pose.t_s = float(src.times_s[t])
        pose.parent_from_bone_quat[:] = q[t]
        pose.root_pos[:] = p[t]
        r.push(pose)
        while r.pending():
            assert r.pop(out) is out
            got_t.append(out.t_s)
            got_q.append(out.parent_from_bone_quat.copy())
            got_p.append(out.root_pos.copy())
    np.testing.assert_allclose(got_t, times, atol=1e-9)
    assert np.all(np.abs(np.abs(np.sum(np.array(got_q) * eq, -1)) - 1) < 1e-12)
    np.testing.assert_allclose(np.array(got_p), ep, atol=1e-12)
    # Allocation-free in steady state.
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        start, _ = tracemalloc.get_traced_memory()
        for _ in range(1000):
            pose.t_s += 0.01
            r.push(pose)
            while r.pending():
                r.pop(out)
        end, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert end - start < 1024
    assert peak - start < 3072, peak - start  # numba's argument boxing


def test_live_resampler_above_the_input_rate(synth_take: Synth) -> None:
    """A 60 Hz capture sent at 120 Hz: every tick (one between each pair of input
    frames) equals the offline ``resample`` at 120 Hz, unit quaternions; the first
    tick an input completes is due on its arrival, the next one output period later
    (before the next input: the timer sends it); each tick shows the source 8.33 ms
    late (one input period less one output period), measured from the send times.
    Ticks still queued when the next input arrives are due at once."""
    src = synth_take(MOTIONS, 60.0, 2.0)
    q, p = src.parent_from_segment_quat, src.joint_pos_world[:, 0]
    times, eq, ep = resample(src.times_s, q, p, 120.0)
    assert len(times) == 2 * len(q) - 1
    r = RateResampler(q.shape[1], 120.0)
    pose, out = PoseBuffer.new(q.shape[1]), PoseBuffer.new(q.shape[1])
    in_ns = 1_000_000_000 // 60
    got_q, got_p, got_t, sent_ns, tags, arrival = [], [], [], [], [], []
    for k in range(len(q)):
        pose.t_s = float(src.times_s[k])
        pose.parent_from_bone_quat[:] = q[k]
        pose.root_pos[:] = p[k]
        now = 10**9 + k * in_ns  # arrival: the capture's own clock, no jitter
        r.push(pose, now, tag=k)
        assert r.completed == (1 if k == 0 else 2)
        # Walk the loop's clock in 1 ms steps until the next input arrives.
        for step_ns in range(0, in_ns, 1_000_000):
            while r.due(now + step_ns):
                r.pop(out)
                sent_ns.append(now + step_ns)
                tags.append(r.popped_tag)
                arrival.append(r.popped_arrival_ns)
                got_t.append(out.t_s)
                got_q.append(out.parent_from_bone_quat.copy())
                got_p.append(out.root_pos.copy())
        assert not r.pending(), "every tick went out before the next input"
    np.testing.assert_allclose(got_t, times, atol=1e-9)
    got = np.array(got_q)
    assert _norm_err(got) < 1e-12
    assert np.all(np.abs(np.abs(np.sum(got * eq, -1)) - 1) < 1e-12)
    np.testing.assert_allclose(np.array(got_p), ep, atol=1e-12)
    # Latency behind the source: (send - arrival of the completing input) + (its
    # time - the tick's), for every tick after the first frame.
    lag_ms = (np.array(sent_ns[1:]) - np.array(arrival[1:])) * 1e-6 + (
        np.array(tags[1:]) / 60.0 - np.array(got_t[1:])
    ) * 1e3
    print(f"\n60 -> 120 Hz: added latency {np.median(lag_ms):.2f} ms median, "
          f"{lag_ms.min():.2f}..{lag_ms.max():.2f} ms (1 ms loop steps)")  # fmt: skip
    assert np.all(lag_ms >= 1000 / 60 - 1000 / 120 - 1e-6)
    assert np.all(lag_ms < 1000 / 60 - 1000 / 120 + 1.0)  # + the 1 ms step
    # Between inputs: the second tick of each input goes out before the next one.
    between = np.array(sent_ns[1:]) - np.array(arrival[1:])
    assert np.sum(between > 0) == len(q) - 1

    # Overdue: a loop that never ran its timer leaves a tick queued; the next input
    # makes it due at once (then its own first tick).
    r.reset()
    for k, now in ((0, 0), (1, in_ns), (2, 2 * in_ns)):
        pose.t_s = k / 60.0
        r.push(pose, now)
        while r.due(now):
            r.pop(out)
    assert r.pending() and not r.due(2 * in_ns)
    assert r.due(2 * in_ns + 1_000_000_000 // 120)


def test_live_resampler_queue_is_bounded() -> None:
    """Far above the input's rate the queue holds QUEUE_TICKS ticks; the oldest are
    dropped (counted), the latest kept."""
    from retargetd.daemon.post.interp import QUEUE_TICKS

    r = RateResampler(2, 1000.0)
    pose, out = PoseBuffer.new(2), PoseBuffer.new(2)
    r.push(pose, 0)
    r.pop(out)
    pose.t_s = 0.1  # 100 ticks in one input period
    r.push(pose, 100_000_000)
    assert r.completed == 100 and r.dropped == 100 - QUEUE_TICKS
    n = 0
    while r.pending():
        r.pop(out)
        n += 1
    assert n == QUEUE_TICKS and abs(out.t_s - 0.1) < 1e-12
