"""Does touching the fit shortly before a frame arrives make the frame's solve cheaper?

Run from the repository root::

    python bench/bench_prewarm.py [--frames N] [--rate-hz 240] [--lead-us 500,1500]

On this shared VM a call 4 ms after the last one finds the code and data it touches
cold (README "The hot path, per frame"): the fit on the real Plug-in Gait walk takes
~45 us back to back and 2-3x that at 240 Hz. A stream at a steady rate says when the
next frame comes, so a loop could run the fit once on the last frame, on a scratch
solver of the same rig and calibration, ``lead`` us before it, and solve the real frame
warm. This measures that in process, the same frames, paced by sleeping as the loop
waits in its poll: the solve of each frame (``FitSolver.solve_frame``) with no touch
(the baseline, measured in the same run, alternated) and with a touch ``lead`` us
before, median and p99, and the ratio to the baseline. The touch's own cost is CPU the
loop spends between frames (printed). Nothing is asserted (STYLE.md section 10).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

DATASETS = Path(__file__).resolve().parent.parent.parent / "shared" / "datasets"
PIG_MOTION = DATASETS / "btkdata" / "PiG_Motion-FlatFoot-Full.c3d"
PIG_CALIBRATION = DATASETS / "btkdata" / "PiG_Calibration-FlatFoot-Full.c3d"


def _solvers(n: int) -> tuple[list[tuple[object, object]], np.ndarray]:
    """``n`` fit solvers of plug-in-gait calibrated on the static, and the walk."""
    from retargetd.daemon.body.calibration import calibrate
    from retargetd.daemon.body.method import make_body_solver
    from retargetd.daemon.body.rig import load_rig
    from retargetd.daemon.validate.limits import JOINT_LIMITS_DEG
    from retargetd.daemon.validate.model import SEGMENT_KIND
    from retargetd.replay.takes import load_take

    rig = load_rig("plug-in-gait")
    static, walk = load_take(PIG_CALIBRATION), load_take(PIG_MOTION)
    cal = calibrate(
        rig, static.positions, static.labels, take_measurements=static.measurements
    )
    out = []
    for _ in range(n):
        s = make_body_solver(
            "fit", rig, cal, walk.labels,
            joint_limits=JOINT_LIMITS_DEG, segment_kind=SEGMENT_KIND,
            rate_hz=walk.rate_hz,
        )  # fmt: skip
        out.append((s, s.new_pose()))
    return out, walk.positions


def _paced(
    solver: object, pose: object, scratch: object, scratch_pose: object,
    frames: np.ndarray, n: int, rate_hz: float, lead_s: float,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Solve ``n`` frames at ``rate_hz``; a touch ``lead_s`` before each (0: none).
    Returns the solve and the touch times, us."""
    period = 1.0 / rate_hz
    solve_us, touch_us = np.zeros(n), np.zeros(n)
    clock = time.perf_counter
    t_next = clock() + period
    for k in range(n):
        if lead_s > 0.0:
            while clock() < t_next - lead_s:
                time.sleep(0.0002)
            t0 = time.perf_counter_ns()
            scratch.solve_frame(frames[(k - 1) % len(frames)], scratch_pose)  # type: ignore[attr-defined]
            touch_us[k] = (time.perf_counter_ns() - t0) / 1e3
        while clock() < t_next:
            time.sleep(0.00005)
        t0 = time.perf_counter_ns()
        solver.solve_frame(frames[k % len(frames)], pose)  # type: ignore[attr-defined]
        solve_us[k] = (time.perf_counter_ns() - t0) / 1e3
        t_next += period
    return solve_us, touch_us


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; returns the exit code."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=2000, help="timed frames a case")
    parser.add_argument("--rate-hz", type=float, default=240.0)
    parser.add_argument("--lead-us", default="500,1500", help="touch leads, us")
    parser.add_argument("--rounds", type=int, default=2, help="alternations")
    args = parser.parse_args(argv)
    leads = [float(x) for x in args.lead_us.split(",") if x]
    period_us = 1e6 / args.rate_hz
    if args.frames < 100 or not 1.0 <= args.rate_hz <= 2000.0:
        parser.error("--frames >= 100, --rate-hz in [1, 2000]")
    if any(not 0.0 < x < period_us for x in leads) or args.rounds < 1:
        parser.error(f"--lead-us in (0, {period_us:.0f}), --rounds >= 1")
    if not (PIG_MOTION.is_file() and PIG_CALIBRATION.is_file()):
        print(f"datasets not found at {DATASETS / 'btkdata'}", file=sys.stderr)
        return 1
    pairs, walk = _solvers(2)
    (solver, pose), (scratch, scratch_pose) = pairs
    for f in walk[:100]:  # compile / load and warm both
        solver.solve_frame(f, pose)  # type: ignore[attr-defined]
        scratch.solve_frame(f, scratch_pose)  # type: ignore[attr-defined]
    print(
        f"fit, plug-in-gait, {PIG_MOTION.name}; {args.frames} frames a case at "
        f"{args.rate_hz:g} Hz, {args.rounds} rounds alternated; "
        f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}"
    )
    print(f"{'case':<22} {'solve p50':>9} {'p99':>7} {'ratio p50':>9} {'p99':>6} "
          f"{'touch p50':>9}")  # fmt: skip
    for r in range(args.rounds):
        base, _ = _paced(solver, pose, scratch, scratch_pose, walk, args.frames,
                         args.rate_hz, 0.0)  # fmt: skip
        b50, b99 = np.percentile(base, [50, 99])
        print(f"{f'no touch (round {r + 1})':<22} {b50:9.1f} {b99:7.1f}")
        for lead in leads:
            s, t = _paced(solver, pose, scratch, scratch_pose, walk, args.frames,
                          args.rate_hz, lead * 1e-6)  # fmt: skip
            s50, s99 = np.percentile(s, [50, 99])
            print(
                f"{f'touch {lead:g} us before':<22} {s50:9.1f} {s99:7.1f} "
                f"{s50 / b50:9.2f} {s99 / b99:6.2f} {np.median(t):9.1f}"
            )
    print(f"load average at the end: {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
