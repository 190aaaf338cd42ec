"""Post-stage benchmark: the One Euro filter's lag and jitter on a real take with
added noise, and the per-call cost of every per-frame post stage.

Run from the repository root::

    python bench/bench_post.py [--calls N] [--noise-deg D] [--noise-mm M]

Take: the Plug-in Gait walk (``../shared/datasets/btkdata``, 100 Hz), calibrated on
its static and solved with ``BodySolver.solve_take``; its whole ``parent_from_bone``
rotations (``clip_from_solve``) are the clean signal. Gaussian noise is added: a
random rotation vector of ``--noise-deg`` per axis on every bone and frame, and
``--noise-mm`` per axis on the root (seeded).

Lag and jitter: for each filter setting the filtered take is compared with the clean
one delayed by tau (slerp at fractional frames, tau = 0 .. 150 ms in 1 ms steps); the
lag is the tau of least RMS rotation error over bones and frames (after a 0.5 s
warm-up), the jitter the RMS error left at that lag. The unfiltered noisy take is
the baseline row.

Cost: ``time.perf_counter_ns`` around each ``apply`` after a warm-up, one frame at a
time as the loop calls them (``live: SolvePost.apply`` is the live loop's stage:
the pipeline on a body-solve pose in place, with its copies and forward kinematics;
then each stage as the daemon itself times it); median and p99 in microseconds, and
the ratio of medians to ``PoseBuffer.copy_from`` (the least any stage does: copy one
pose), measured in the same run. Speed is printed, never asserted (STYLE.md section 10).
"""

from __future__ import annotations

import argparse
import gc
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.calibration import Calibration, calibrate
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.body.solve import BodySolver
from retargetd.daemon.post.export_gltf import clip_from_solve
from retargetd.daemon.post.hermite import HermiteSpine
from retargetd.daemon.post.interp import Clip, RateResampler, resample
from retargetd.daemon.post.one_euro import OneEuroFilter
from retargetd.daemon.post.pipeline import build_pipeline
from retargetd.daemon.post.pivot import ShiftingPivot, SpinePivot
from retargetd.daemon.post.plant import FootPlant, performer_leg_m
from retargetd.daemon.post.pose import PoseBuffer
from retargetd.daemon.post.reduce import reduce_clip
from retargetd.daemon.post.solve_post import SolvePost
from retargetd.daemon.post.stance import StanceDetector
from retargetd.daemon.post.twist import TwistDistribution, arm_chains
from retargetd.daemon.retarget.retarget import Retargeter
from retargetd.daemon.retarget.skeleton import default_humanoid
from retargetd.replay.takes import load_take

DATASETS = Path(__file__).resolve().parent.parent.parent / "shared" / "datasets"
STATIC = DATASETS / "btkdata/PiG_Calibration-FlatFoot-Full.c3d"
WALK = DATASETS / "btkdata/PiG_Motion-FlatFoot-Full.c3d"
#: (min_cutoff_hz, beta_rot, beta_pos) rows: the paper's start (1 Hz, beta 0), then
#: raising beta as its tuning procedure says, and a higher floor.
SETTINGS = ((1.0, 0.0, 0.0), (1.0, 0.5, 5.0), (1.0, 2.0, 20.0), (3.0, 1.0, 10.0))


def _solve() -> tuple[Clip, list[int], tuple[str, ...], Calibration, Any]:
    rig = load_rig("plug-in-gait")
    static = load_take(STATIC)
    cal = calibrate(
        rig, static.positions, static.labels, take_measurements=static.measurements
    )
    take = load_take(WALK)
    solver = BodySolver(rig, cal, take.labels)
    res = solver.solve_take(take.positions)
    return (
        clip_from_solve(res, cal, take.rate_hz),
        list(cal.bone_parents),
        cal.bone_names,
        cal,
        (solver, res),
    )


def _delayed(
    q: np.ndarray, p: np.ndarray, shift_frames: float
) -> tuple[np.ndarray, np.ndarray]:
    """The clean take delayed: frame t -> the clean pose at t - shift (clamped)."""
    t = np.clip(np.arange(len(q)) - shift_frames, 0.0, len(q) - 1.0)
    i = np.minimum(np.floor(t).astype(int), len(q) - 2)
    u = t - i
    return rot.slerp(q[i], q[i + 1], u[:, None]), p[i] + (p[i + 1] - p[i]) * u[:, None]


def _lag_jitter(
    clean: Clip, q: np.ndarray, p: np.ndarray, warm: int
) -> tuple[float, float, float, float]:
    """(rotation lag ms, rotation RMS deg, root lag ms, root RMS mm), each channel
    kind at its own best lag."""
    rot_best, pos_best = (np.inf, 0.0), (np.inf, 0.0)
    dt_ms = 1000.0 / clean.rate_hz
    for tau_ms in np.arange(0.0, 151.0, 1.0):
        dq, dp = _delayed(clean.parent_from_bone_quat, clean.root_pos, tau_ms / dt_ms)
        ang = rot.quat_angle(rot.quat_mul(rot.quat_conj(dq[warm:]), q[warm:]))
        rms = float(np.sqrt(np.mean(ang**2)))
        pos = float(np.sqrt(np.mean(np.sum((dp[warm:] - p[warm:]) ** 2, -1))))
        rot_best = min(rot_best, (rms, tau_ms))
        pos_best = min(pos_best, (pos, tau_ms))
    return rot_best[1], float(np.degrees(rot_best[0])), pos_best[1], 1e3 * pos_best[0]


def _filter(clip: Clip, q: np.ndarray, p: np.ndarray, f: OneEuroFilter) -> tuple:
    pose, out = PoseBuffer.new(q.shape[1]), PoseBuffer.new(q.shape[1])
    qs, ps = np.empty_like(q), np.empty_like(p)
    for t in range(len(q)):
        pose.t_s = t / clip.rate_hz
        pose.parent_from_bone_quat[:] = q[t]
        pose.root_pos[:] = p[t]
        f.apply(pose, out)
        qs[t], ps[t] = out.parent_from_bone_quat, out.root_pos
    return qs, ps


def _time(fn: Callable[[int], object], calls: int) -> np.ndarray:
    for i in range(200):
        fn(i)
    ns = np.zeros(calls, dtype=np.int64)
    clock = time.perf_counter_ns
    gc.disable()
    try:
        for i in range(calls):
            t0 = clock()
            fn(i)
            ns[i] = clock() - t0
    finally:
        gc.enable()
    return ns / 1000.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--calls", type=int, default=5000)
    ap.add_argument("--noise-deg", type=float, default=1.0)
    ap.add_argument("--noise-mm", type=float, default=2.0)
    args = ap.parse_args()
    print(f"load average {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f}")
    clip, parents, names, cal, (solver, res) = _solve()
    q, p = clip.parent_from_bone_quat, clip.root_pos
    n, b = q.shape[:2]
    rng = np.random.default_rng(0)
    noisy_q = rot.quat_mul(
        q, rot.quat_from_rotvec(rng.normal(0, np.radians(args.noise_deg), (n, b, 3)))
    )
    noisy_p = p + rng.normal(0, 1e-3 * args.noise_mm, (n, 3))
    warm = int(0.5 * clip.rate_hz)
    print(
        f"\nPiG walk: {n} frames at {clip.rate_hz:g} Hz, {b} bones; noise "
        f"{args.noise_deg} deg/axis, {args.noise_mm} mm/axis"
    )
    head = "One Euro (min_cutoff Hz, beta rot, beta pos)"
    cols = f"{'rot lag ms':>10} {'RMS deg':>8} {'root lag ms':>11} {'RMS mm':>7}"
    print(f"{head:<46} {cols}")

    def row(label: str, fq: np.ndarray, fp: np.ndarray) -> None:
        lag, jit, plag, pos = _lag_jitter(clip, fq, fp, warm)
        print(f"{label:<46} {lag:>10.0f} {jit:>8.3f} {plag:>11.0f} {pos:>7.2f}")

    row("unfiltered (noisy input)", noisy_q, noisy_p)
    for fmin, br, bp in SETTINGS:
        f = OneEuroFilter(b, min_cutoff_hz=fmin, beta_rot=br, beta_pos=bp)
        row(f"({fmin:g}, {br:g}, {bp:g})", *_filter(clip, noisy_q, noisy_p, f))

    # Per-stage cost, one frame at a time.
    pose, out = PoseBuffer.new(b), PoseBuffer.new(b)
    frames = np.ascontiguousarray(q)

    def load(i: int) -> PoseBuffer:
        pose.parent_from_bone_quat[:] = frames[i % n]
        pose.root_pos[:] = p[i % n]
        pose.t_s = i / clip.rate_hz
        return pose

    twist = TwistDistribution(
        parents,
        arm_chains(names),
        rest_parent_from_bone_quat=cal.rest_parent_from_bone_quat,
    )
    pivot = ShiftingPivot()
    pivot_out = np.empty((3, 4))
    spine = HermiteSpine(4, 5)
    # Spine, chest, neck and head origins of the calibration: 4 solved spine points.
    spine_pts = np.ascontiguousarray(np.asarray(cal.rest_bone_origin_pos)[[1, 2, 3, 4]])
    spine_out = np.empty((5, 3))
    euro = OneEuroFilter(b, beta_rot=0.5, beta_pos=5.0)
    res60 = RateResampler(b, 60.0)
    res120 = RateResampler(b, 120.0)  # above the input's rate: 1-2 ticks a frame
    pipe = build_pipeline(
        [{"kind": "twist"}, {"kind": "one_euro", "beta_rot": 0.5, "beta_pos": 5.0}],
        bone_names=names,
        bone_parents=parents,
        rest_parent_from_bone_quat=cal.rest_parent_from_bone_quat,
    )

    # The live loop's stage (daemon/live/send.py): the same pipeline on the body
    # solve's pose in place, with the copies in and out and the forward kinematics.
    body = solver.new_pose()
    live_post = SolvePost(
        build_pipeline(
            [
                {"kind": "twist"},
                {"kind": "one_euro", "beta_rot": 2.0, "beta_pos": 20.0},
            ],
            bone_names=names,
            bone_parents=parents,
            rest_parent_from_bone_quat=cal.rest_parent_from_bone_quat,
        ),
        parents,
        cal.rest_parent_from_bone_quat,
    )
    body_q = np.ascontiguousarray(res.parent_from_bone_quat)
    body_p = np.ascontiguousarray(res.root_pos)

    def load_body(i: int) -> Any:
        body.parent_from_bone_quat[:] = body_q[i % n]
        body.root_pos[:] = body_p[i % n]
        return body

    def live_step(i: int) -> None:
        # A take's wrap-around is a clock step back: keep the clock going instead.
        live_post.apply(load_body(i), i / clip.rate_hz)

    def resample_step(i: int) -> None:
        res60.push(load(i))
        while res60.pending():
            res60.pop(out)

    # [target] spine = "pivot" (live/send.py): on each frame mapped onto the humanoid.
    humanoid = default_humanoid()
    retargeter = Retargeter(solver.rig, cal, humanoid)
    tpose = retargeter.new_pose()
    spine_pivot = SpinePivot(
        humanoid.bone_names, humanoid.parents, humanoid.rest_world_from_bone_quat,
        set(solver.rig.humanoid), humanoid.left_world,
    )  # fmt: skip
    body_w = np.ascontiguousarray(res.world_from_bone_quat)
    body_f = np.ascontiguousarray(res.bone_flags)
    mapped_w = np.empty((n, len(humanoid.bone_names), 4))
    mapped_r = np.empty_like(mapped_w)
    for i in range(n):
        body.world_from_bone_quat[:] = body_w[i]
        body.root_pos[:] = body_p[i]
        body.bone_flags[:] = body_f[i]
        retargeter.apply(body, tpose)
        mapped_w[i], mapped_r[i] = tpose.world_from_bone_quat, tpose.rest_from_bone_quat
    spine_g, spine_r = np.empty_like(mapped_w[0]), np.empty_like(mapped_r[0])

    def spine_step(i: int) -> None:
        np.copyto(spine_g, mapped_w[i % n])
        np.copyto(spine_r, mapped_r[i % n])
        spine_pivot.apply(spine_g, spine_r)

    # [target] feet = "plant" (live/send.py): on each mapped frame, the stance
    # detector's state of that frame (replayed: the detector's own cost is not in
    # this row), both feet; the PiG walk's contact holds a foot most frames.
    plant = FootPlant(humanoid, retargeter.root_scale, performer_leg_m(solver.rig, cal))
    detector = StanceDetector(solver.rig, cal)
    stance_states = np.empty((n, *detector.state.shape))
    mapped_root = np.empty((n, 3))
    for i in range(n):
        detector.update(body_p[i], body_w[i], 1.0 / clip.rate_hz if i else 0.0)
        stance_states[i] = detector.state
        body.world_from_bone_quat[:] = body_w[i]
        body.root_pos[:] = body_p[i]
        retargeter.apply(body, tpose)
        mapped_root[i] = tpose.root_pos
    plant_g, plant_r = np.empty_like(mapped_w[0]), np.empty_like(mapped_r[0])
    plant_root, plant_hips, plant_st = (
        np.empty(3),
        np.empty(3),
        np.empty(detector.state.shape),
    )

    def plant_step(i: int) -> None:
        k = i % n
        np.copyto(plant_g, mapped_w[k])
        np.copyto(plant_r, mapped_r[k])
        np.copyto(plant_root, mapped_root[k])
        np.copyto(plant_st, stance_states[k])
        plant.apply(
            plant_g, plant_r, plant_root, plant_hips, plant_st, i / clip.rate_hz
        )

    def upsample_step(i: int) -> None:
        now = i * 10_000_000  # 100 Hz arrivals; every queued tick sent by the next
        res120.push(load(i), now)
        while res120.due(now + 9_999_999):
            res120.pop(out)

    rows = [
        ("baseline: PoseBuffer.copy_from", lambda i: out.copy_from(load(i))),
        ("TwistDistribution.apply (2 arms)", lambda i: twist.apply(load(i), out)),
        (
            "ShiftingPivot.apply (3 joints)",
            lambda i: pivot.apply(load(i).parent_from_bone_quat[2], pivot_out),
        ),
        (
            "HermiteSpine.apply (4 pts, 5 joints)",
            lambda i: (load(i), spine.apply(spine_pts, spine_out)),
        ),
        ("SpinePivot.apply (humanoid, 3 joints)", spine_step),
        ("FootPlant.apply (humanoid, 2 feet)", plant_step),
        ("RateResampler push+pop (100->60 Hz)", resample_step),
        ("RateResampler push+pop (100->120 Hz)", upsample_step),
        ("OneEuroFilter.apply (19 bones)", lambda i: euro.apply(load(i), out)),
        ("Pipeline.apply (twist, one_euro)", lambda i: pipe.apply(load(i), out)),
        ("live: SolvePost.apply (twist, one_euro)", live_step),
    ]
    load_only = np.median(_time(load, args.calls))
    print(
        f"\nper call, {args.calls} calls each (the timed lambdas include loading the "
        f"frame into a PoseBuffer: {load_only:.2f} us median, not subtracted)"
    )
    print(f"{'stage':<40} {'median us':>10} {'p99 us':>9} {'x baseline':>11}")
    base = None
    for what, fn in rows:
        us = _time(fn, args.calls)
        med = float(np.median(us))
        base = base or med
        print(
            f"{what:<40} {med:>10.2f} {np.percentile(us, 99):>9.2f} {med / base:>11.2f}"
        )

    t0 = time.perf_counter()
    red = reduce_clip(clip)
    t1 = time.perf_counter()
    resample(np.arange(n) / clip.rate_hz, q, p, 60.0)
    t2 = time.perf_counter()
    kept = sum(len(c.frames) for c in red.rotations)
    print(
        f"\noffline: reduce_clip (0.5 deg, 1 mm) {1e3 * (t1 - t0):.1f} ms, keeps "
        f"{kept} of {n * b} rotation keys; resample to 60 Hz {1e3 * (t2 - t1):.1f} ms"
    )
    stage_us = {k: [] for k in live_post.stage_names}
    for i in range(args.calls):
        live_step(i)
        for k, v in zip(live_post.stage_names, live_post.stage_ns, strict=True):
            stage_us[k].append(v / 1000.0)
    print(
        "live stages as the daemon times them (Pipeline.stage_ns, perf_counter_ns "
        "around each stage; status latency_us post.<kind>): "
        + ", ".join(
            f"{k} {np.median(v):.2f} / {np.percentile(v, 99):.2f} us"
            for k, v in stage_us.items()
        )
    )
    print(f"load average {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f}")


if __name__ == "__main__":
    main()
