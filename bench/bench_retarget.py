"""Retarget benchmark: ``Retargeter.apply`` one frame at a time, and its numpy oracle.

Run from the repository root::

    python bench/bench_retarget.py [--calls N] [--seconds S]

The ``menache`` rig on the synthetic performer (240 Hz, calibrated on its T-pose hold)
is solved once with ``BodySolver.solve_take``; the timed loop then retargets those
solved frames onto the default humanoid, cycling through them, as the live loop calls
it: the same ``TargetPose`` buffers every call, ``time.perf_counter_ns`` around each
call, after a warm-up. Printed: median, p99 and max in microseconds (max is one call
and mostly shows the machine).

Baseline, in the same run on the same frames: the plain numpy implementation the
compiled kernel replaced (``tests/helpers/retarget_oracle.py``, ~41 numpy calls,
preallocated
scratch), after checking that both give the same quaternions; and the ratio of
medians. Speed is printed, never asserted (STYLE.md section 10).
"""

from __future__ import annotations

import argparse
import gc
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from retargetd.daemon.body.calibration import calibrate
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.body.solve import BodyPose, BodySolver
from retargetd.daemon.retarget import retarget as tg
from retargetd.daemon.synth import performer as pf


def _time(fn: Callable[[int], object], calls: int, n_frames: int) -> np.ndarray:
    for i in range(min(200, calls)):  # warm-up: compile/cache load, caches
        fn(i % n_frames)
    ns = np.zeros(calls, dtype=np.int64)
    clock = time.perf_counter_ns
    gc.disable()
    try:
        for i in range(calls):
            f = i % n_frames
            t0 = clock()
            fn(f)
            ns[i] = clock() - t0
    finally:
        gc.enable()
    return ns / 1000.0


def _row(what: str, us: np.ndarray) -> str:
    return (
        f"{what:<34} {np.median(us):>9.2f} {np.percentile(us, 99):>9.2f} "
        f"{us.max():>9.1f}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--calls", type=int, default=10_000)
    ap.add_argument("--seconds", type=float, default=8.0, help="synthetic take")
    args = ap.parse_args()

    rate_hz = 240.0
    take = pf.synthesize(seconds=args.seconds, rate_hz=rate_hz, markerset="menache")
    rig = load_rig("menache")
    cal = calibrate(rig, take.markers_world[take.base_pose_frames], take.labels)
    solve = BodySolver(rig, cal, take.labels).solve_take(take.markers_world)
    n = take.n_frames
    poses = [
        BodyPose(
            joint_centres=solve.joint_centres[t],
            world_from_bone_quat=solve.world_from_bone_quat[t],
            parent_from_bone_quat=solve.parent_from_bone_quat[t],
            rest_from_bone_quat=solve.rest_from_bone_quat[t],
            root_pos=solve.root_pos[t],
            bone_quality=solve.bone_quality[t],
            bone_flags=solve.bone_flags[t],
        )
        for t in range(n)
    ]
    rt = tg.Retargeter(rig, cal)
    out = rt.new_pose()
    print(
        f"menache rig, synthetic performer, {rate_hz:g} Hz, {n} solved frames; "
        f"default humanoid ({len(rt.bone_names)} bones, {len(rt.filled)} filled); "
        f"{args.calls} calls"
    )
    print(f"{'':<34} {'median µs':>9} {'p99 µs':>9} {'max µs':>9}")
    us = _time(lambda f: rt.apply(poses[f], out), args.calls, n)
    print(_row("Retargeter.apply", us))

    # The numpy oracle lives beside the tests (tests/helpers/retarget_oracle.py).
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "helpers"))
    import retarget_oracle as oracle

    ref = oracle._reference_apply
    scratch = oracle._ReferenceScratch(rt)
    ref_out = rt.new_pose()
    worst = 0.0
    for f in range(n):
        rt.apply(poses[f], out)
        ref(rt, poses[f], ref_out, scratch)
        for name in ("world_from_bone_quat", "rest_from_bone_quat", "root_pos"):
            d = np.abs(getattr(out, name) - getattr(ref_out, name)).max()
            worst = max(worst, float(d))
        assert (out.flags == ref_out.flags).all()
    print(f"  (compiled vs numpy: largest difference {worst:.1e} over {n} frames)")
    us_ref = _time(lambda f: ref(rt, poses[f], ref_out, scratch), args.calls, n)
    print(_row("numpy baseline (_reference_apply)", us_ref))
    print(f"ratio of medians numpy / compiled: {np.median(us_ref) / np.median(us):.1f}")


if __name__ == "__main__":
    main()
