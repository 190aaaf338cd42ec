"""Live validator benchmark: per-frame check cost, submit cost, and what the validator
thread costs the loop thread (the GIL).

Run from the repository root::

    python bench/bench_validate_live.py [--calls N] [--gil-seconds S] [--rate HZ]

Needs ``../shared/datasets/btkdata``: the PiG walk (plug-in-gait rig calibrated on
``PiG_Calibration``, 100 Hz, 315 frames, 19 bones) and the MOTEK ballet (cmu41 rig
calibrated on ``MOTEK_T``, 30 Hz, 100 frames).

1. **check**: ``LiveValidator.check_frame`` one frame at a time, the frames in order
   (the validator thread's code on this thread: qpos write, ``mj_kinematics``,
   ``mj_collision``, the compiled checks, the result object). Baselines in the same run:
   the offline per-frame MuJoCo step ``validate.FrameChecker.check`` (which does less:
   no fit, limits, speed or support), and the offline ``validate_take`` (no ghost force,
   vectorised over the take) as wall time / frames, best of 3.
2. **submit**: the copy into the ring (thread not started, slot released by hand after
   each call) and a dropped submit (ring full).
3. **thread**: every frame submitted at ``--rate`` with the thread running: its own
   per-frame cost (``cost_us``) and submit → result latency.
4. **GIL**: a loop-like main thread at ``--rate``: sleep to the tick (the GIL is free
   while it sleeps, as in the daemon's poll), then the send-like work of the daemon's
   loop (``BodySolver.solve_frame`` + ``Retargeter.apply`` + ``PoseEncoder.encode`` of
   the PiG walk, then ``results()`` and ``submit()``). Timed: ``late`` = tick → work
   start (wake-up + taking the GIL back) and ``work`` (solve → encode). Cases: the
   validator ``off``; ``on`` (one frame per tick, as in the daemon); ``saturated`` (the
   ring refilled every tick so the validator thread never idles: the worst case); for
   switch intervals 5 ms (Python's default), 1, 0.5 and 0.1 ms; all twelve cases run
   in interleaved 0.25 s blocks in a shuffled order, so machine noise hits them alike.
   ``+p99`` = the case's p99 of late + work minus the ``off`` one at the same
   interval: the delay the validator inflicts on a send.

Figures, 2026-11-22, this 2-core shared machine (load 0.2-0.8), default options
(p99s move from run to run; quote a quiet run):

- check, PiG walk: median 19.8 µs, p99 33.4 µs; MOTEK ballet: 19.0 / 31.4 µs (target
  p99 <= 100 µs). Baselines: FrameChecker.check 32.3 / 59.9 µs (ratio of medians
  1.6: the offline step alone, doing less, is slower); validate_take 64.5 µs/frame
  amortised (3.3x the check median).
- submit: median 2.5 µs, p99 2.9 µs; dropped: 0.5 / 0.5 µs.
- thread at 1000 Hz: in-thread cost p50 30 µs, p99 53 µs; submit -> result median
  44 µs, p99 78 µs; 0 dropped.
- GIL (``--gil-seconds 5``), +p99 against ``off``: ``on`` -27, -15, +1, -21 µs at 5,
  1, 0.5, 0.1 ms (noise), ``saturated`` +66, +113, +66, +81 µs; work median 18 µs
  off, 22.5 on, 27 saturated. The switch interval makes no difference: see
  ``daemon/validate/live.py``.

Speed is printed, never asserted (STYLE.md section 10).
"""

from __future__ import annotations

import argparse
import gc
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from retargetd.daemon.body.calibration import calibrate
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.body.solve import BodySolve, BodySolver
from retargetd.daemon.retarget import retarget as tg
from retargetd.daemon.validate import live as vl
from retargetd.daemon.validate.checks import FrameChecker, fit_pairs, validate_take
from retargetd.protocols import pose_stream
from retargetd.replay.takes import load_take

DATASETS = Path(__file__).resolve().parent.parent.parent / "shared" / "datasets"
SWITCH_INTERVALS_MS = (5.0, 1.0, 0.5, 0.1)
CASES = ("off", "on", "saturated")
BLOCK_S = 0.25  # GIL cases run in interleaved blocks: machine noise hits all alike


def _stats(us: np.ndarray) -> tuple[float, float, float]:
    return float(np.median(us)), float(np.percentile(us, 99)), float(us.max())


def _row(what: str, us: np.ndarray, extra: str = "") -> str:
    med, p99, mx = _stats(us)
    return f"{what:<44} {med:>9.1f} {p99:>9.1f} {mx:>9.1f}  {extra}"


def _time_calls(
    fn: Callable[[int], object], calls: int, warmup: int = 200
) -> np.ndarray:
    for i in range(warmup):
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
    return ns / 1e3


class Take:
    """A real take solved, with its validator."""

    def __init__(self, name: str, rig_name: str, cal_file: str, take_file: str) -> None:
        self.name = name
        self.rig = load_rig(rig_name)
        static = load_take(DATASETS / "btkdata" / cal_file)
        self.cal = calibrate(
            self.rig,
            static.positions,
            static.labels,
            take_measurements=static.measurements,
        )
        take = load_take(DATASETS / "btkdata" / take_file)
        self.rate_hz = float(take.rate_hz)
        self.labels = take.labels
        self.positions = take.positions
        self.solver = BodySolver(self.rig, self.cal, take.labels)
        self.solve: BodySolve = self.solver.solve_take(take.positions)
        self.n = self.solve.root_pos.shape[0]
        self.v = vl.LiveValidator(self.rig, self.cal, rate_hz=self.rate_hz)

    def frame(self, t: int) -> tuple[Any, ...]:
        s = self.solve
        return (
            s.root_pos[t],
            s.world_from_bone_quat[t],
            s.rest_from_bone_quat[t],
            s.joint_centres[t],
        )


def bench_check(take: Take, calls: int) -> np.ndarray:
    v, n = take.v, take.n
    frames = [take.frame(t) for t in range(n)]
    rate = take.rate_hz

    def call(i: int) -> None:
        t = i % n
        v.check_frame(i, int(i * 1e9 / rate), *frames[t])

    return _time_calls(call, calls)


def bench_baselines(take: Take, calls: int) -> tuple[np.ndarray, float]:
    vm, s = take.v.vm, take.solve
    checker = FrameChecker(vm)
    root = vm.skeleton.bone_parents.index(-1)

    def step(i: int) -> None:
        t = i % take.n
        checker.check(s.root_pos[t], s.world_from_bone_quat[t, root],
                      s.rest_from_bone_quat[t])  # fmt: skip

    us = _time_calls(step, calls)
    fit = fit_pairs(take.rig, s.joint_names)
    best = np.inf
    for _ in range(3):
        t0 = time.perf_counter()
        validate_take(vm, s, take.rate_hz, fit=fit, dynamics=False)
        best = min(best, time.perf_counter() - t0)
    return us, 1e6 * best / take.n


def bench_submit(take: Take, calls: int) -> tuple[np.ndarray, np.ndarray]:
    v = vl.LiveValidator(take.rig, take.cal, rate_hz=take.rate_hz, queue_size=16)
    frames = [take.frame(t) for t in range(take.n)]

    def submit(i: int) -> None:
        v.submit(i, i, *frames[i % take.n])
        v._tail = v._head  # release the slot by hand (no thread): the copy alone

    us = _time_calls(submit, calls)
    for i in range(v.queue_size):
        v.submit(i, i, *frames[0])
    dropped = _time_calls(lambda i: v.submit(i, i, *frames[0]), calls)
    v.close()
    return us, dropped


def bench_thread(take: Take, rate_hz: float, seconds: float) -> str:
    v = vl.LiveValidator(take.rig, take.cal, rate_hz=take.rate_hz, queue_size=16)
    v.start()
    frames = [take.frame(t) for t in range(take.n)]
    sent_ns: dict[int, int] = {}
    lat: list[int] = []
    period = 1.0 / rate_hz
    n_ticks = int(seconds * rate_hz)
    next_t = time.perf_counter()
    try:
        for i in range(n_ticks):
            next_t += period
            _sleep_until(next_t)
            for r in v.results():
                lat.append(r.validated_ns - sent_ns.pop(r.frame_id))
            now = time.monotonic_ns()
            if v.submit(i, now, *frames[i % take.n]):
                sent_ns[i] = now
        time.sleep(0.05)
        for r in v.results():
            lat.append(r.validated_ns - sent_ns.pop(r.frame_id))
    finally:
        v.close()
    p50, p99 = v.cost_us()
    lat_us = np.asarray(lat) / 1e3
    return (
        f"thread at {rate_hz:g} Hz: validated {v.validated}, dropped {v.dropped}; "
        f"in-thread cost p50 {p50:.1f} p99 {p99:.1f} µs; submit -> result "
        f"median {np.median(lat_us):.1f} p99 {np.percentile(lat_us, 99):.1f} µs"
    )


def _sleep_until(t: float) -> None:
    left = t - time.perf_counter()
    if left > 0:
        time.sleep(left)


def bench_gil(take: Take, rate_hz: float, seconds: float) -> None:
    rt = tg.Retargeter(take.rig, take.cal)
    pose = take.solver.new_pose()
    tp = rt.new_pose()
    enc = pose_stream.PoseEncoder(len(take.solve.bone_names), 0)
    weights = np.zeros(0, dtype=np.float32)
    markers = [np.ascontiguousarray(take.positions[t]) for t in range(take.n)]
    period_ns = round(1e9 / rate_hz)
    block = max(1, round(BLOCK_S * rate_hz))
    rounds = max(1, round(seconds / BLOCK_S))
    print(
        f"\nGIL: loop-like main thread at {rate_hz:g} Hz, {rounds * block} ticks per "
        f"case in {rounds} interleaved blocks of {BLOCK_S:g} s (PiG walk: solve_frame "
        f"+ Retargeter.apply + PoseEncoder.encode, then results() + submit()); µs"
    )
    print(
        f"{'switch':>7} {'case':<10} {'late p50':>9} {'late p99':>9} {'work p50':>9} "
        f"{'work p99':>9} {'sum p99':>9} {'+p99':>7} {'validated':>9} {'dropped':>8}"
    )
    validators = {
        "on": vl.LiveValidator(take.rig, take.cal, rate_hz=take.rate_hz),
        "saturated": vl.LiveValidator(
            take.rig, take.cal, rate_hz=take.rate_hz, queue_size=64
        ),
    }
    keys = [(ms, case) for ms in SWITCH_INTERVALS_MS for case in CASES]
    late: dict[tuple[float, str], list[np.ndarray]] = {k: [] for k in keys}
    work: dict[tuple[float, str], list[np.ndarray]] = {k: [] for k in keys}
    counts = {k: [0, 0] for k in keys}
    order = np.random.default_rng(0)
    default_interval = sys.getswitchinterval()
    clock = time.perf_counter_ns
    tick = 0
    try:
        for v in validators.values():
            v.start()
        for _ in range(rounds):
            for idx in order.permutation(len(keys)):
                interval_ms, case = keys[idx]
                v = validators.get(case)
                sys.setswitchinterval(interval_ms * 1e-3)
                before = (v.validated, v.dropped) if v is not None else (0, 0)
                lt = np.zeros(block, dtype=np.int64)
                wk = np.zeros(block, dtype=np.int64)
                time.sleep(0.02)  # the previous block's backlog drains
                gc.disable()
                try:
                    next_ns = clock() + 2_000_000
                    for i in range(block):
                        next_ns += period_ns
                        _sleep_until(next_ns * 1e-9)
                        t0 = clock()
                        solved = take.solver.solve_frame(markers[tick % take.n], pose)
                        rt.apply(solved, tp)
                        enc.encode(
                            tick, float("nan"), t0, t0, 0, solved.root_pos,
                            solved.world_from_bone_quat,
                            solved.rest_from_bone_quat, weights, solved.bone_flags,
                        )  # fmt: skip
                        t1 = clock()
                        lt[i] = t0 - next_ns
                        wk[i] = t1 - t0
                        tick += 1
                        if v is None:
                            continue
                        v.results()
                        k = 1 if case == "on" else v.queue_size - v.pending
                        for _ in range(k):
                            v.submit(tick, t0, solved.root_pos,
                                     solved.world_from_bone_quat,
                                     solved.rest_from_bone_quat,
                                     solved.joint_centres)  # fmt: skip
                finally:
                    gc.enable()
                late[keys[idx]].append(lt)
                work[keys[idx]].append(wk)
                if v is not None:
                    counts[keys[idx]][0] += v.validated - before[0]
                    counts[keys[idx]][1] += v.dropped - before[1]
    finally:
        sys.setswitchinterval(default_interval)
        for v in validators.values():
            v.close()
    for interval_ms in SWITCH_INTERVALS_MS:
        off_p99 = 0.0
        for case in CASES:
            key = (interval_ms, case)
            late_us = np.concatenate(late[key]) / 1e3
            work_us = np.concatenate(work[key]) / 1e3
            total = float(np.percentile(late_us + work_us, 99))
            if case == "off":
                off_p99 = total
            print(
                f"{interval_ms:>5g}ms {case:<10} {np.median(late_us):>9.1f} "
                f"{np.percentile(late_us, 99):>9.1f} {np.median(work_us):>9.1f} "
                f"{np.percentile(work_us, 99):>9.1f} {total:>9.1f} "
                f"{total - off_p99:>+7.0f} {counts[key][0]:>9} {counts[key][1]:>8}"
            )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--calls", type=int, default=5000)
    ap.add_argument("--gil-seconds", type=float, default=2.0, help="per GIL case")
    ap.add_argument("--rate", type=float, default=1000.0, help="loop-like rate, Hz")
    ap.add_argument("--no-ballet", action="store_true")
    args = ap.parse_args()
    if not DATASETS.is_dir():
        sys.exit(f"datasets not found at {DATASETS}")
    load = os.getloadavg()[0]
    print(f"load average {load:.2f}; {args.calls} calls per row")
    takes = [Take("PiG walk", "plug-in-gait", "PiG_Calibration-FlatFoot-Full.c3d",
                  "PiG_Motion-FlatFoot-Full.c3d")]  # fmt: skip
    if not args.no_ballet:
        takes.append(
            Take("MOTEK ballet", "cmu41", "MOTEK_T.trc", "MOTEK_ballet_reduced.trc")
        )
    print(f"{'':<44} {'median µs':>9} {'p99 µs':>9} {'max µs':>9}")
    for take in takes:
        head = f"{take.name} ({take.n} frames, {take.v.n_bones} bones)"
        check = bench_check(take, args.calls)
        print(_row(f"{head}: check_frame", check))
        step, per_frame = bench_baselines(take, args.calls)
        ratio = np.median(step) / np.median(check)
        print(_row("  baseline: FrameChecker.check (offline)", step,
                   f"ratio of medians {ratio:.2f}"))  # fmt: skip
        print(
            f"  baseline: validate_take (offline, no ghost force): "
            f"{per_frame:.1f} µs/frame amortised (best of 3); "
            f"ratio to check median {per_frame / np.median(check):.2f}"
        )
    pig = takes[0]
    sub, dropped = bench_submit(pig, args.calls)
    print(_row("submit (copy into the ring)", sub))
    print(_row("submit, ring full (dropped)", dropped))
    print(bench_thread(pig, args.rate, args.gil_seconds))
    bench_gil(pig, args.rate, args.gil_seconds)
    print(f"load average at the end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
