"""Prop solve benchmark: one prop, one frame at a time, and a numpy Kabsch baseline.

Run from the repository root::

    python bench/bench_props.py [--calls C]

Three props (a camera rig of 5 markers, a sword of 4, the pyomeca box's 8-marker
layout) each ride a random rigid motion with 0.5 mm noise. For each prop and case
(every marker seen; one marker hidden; two labels swapped, so the consensus search
runs) it prints ``PropSolver.solve`` latency (``time.perf_counter_ns`` around each
call after a warm-up): median, p99 and max in microseconds, and the same-run
baseline: an unweighted numpy Kabsch (SVD, the textbook fit, no gate and no swap
check) on the same frames, with the ratio of medians. Speed is printed, never
asserted (STYLE.md section 10).
"""

from __future__ import annotations

import argparse
import gc
import time

import numpy as np
from scipy.spatial.transform import Rotation

from retargetd.daemon.props.layout import calibrate_prop
from retargetd.daemon.props.solve import PropSolver

#: Layouts, metres: a camera rig (~30 cm), a sword (blade markers and a guard's),
#: a box like pyomeca's (pairs 35 mm apart on a 0.5 m frame).
PROPS = {
    "camera5": [
        [0.0, 0.0, 0.0], [0.16, 0.02, 0.0], [-0.12, 0.05, 0.03],
        [0.02, 0.21, 0.06], [0.05, -0.04, 0.14],
    ],
    "sword4": [[0.0, 0.0, 0.0], [0.0, 0.0, 0.35], [0.0, 0.0, 0.8], [0.09, 0.0, 0.05]],
    "box8": [
        [0.0, 0.0, 0.0], [0.035, 0.0, 0.0], [0.39, 0.01, 0.0], [0.425, 0.03, 0.0],
        [0.07, 0.2, 0.07], [0.35, 0.2, 0.07], [0.30, 0.25, 0.40],
        [0.05, 0.3, 0.35],
    ],
}  # fmt: skip


def _stats(ns: np.ndarray) -> tuple[float, float, float]:
    us = ns / 1e3
    return float(np.median(us)), float(np.percentile(us, 99)), float(us.max())


def _kabsch(lp: np.ndarray, pts: np.ndarray, valid: np.ndarray) -> np.ndarray:
    a, b = lp[valid], pts[valid]
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    return vt.T @ np.diag([1.0, 1.0, d]) @ u.T


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", type=int, default=20_000)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    print(f"calls per case: {args.calls} (after {args.calls // 10} warm-up)")
    print(
        f"{'prop':8} {'case':8} {'median_us':>9} {'p99_us':>8} {'max_us':>8} "
        f"{'kabsch_med':>10} {'kabsch_p99':>10} {'ratio':>6}"
    )
    for name, rows in PROPS.items():
        shape = np.array(rows)
        k = len(shape)
        labels = [f"{name}:{i}" for i in range(k)]
        layout = calibrate_prop(
            np.repeat(shape[None], 3, 0), labels, name=name, rate_hz=100.0
        )
        lp = np.array(layout.layout_prop_m)
        n = 1000
        rots = Rotation.random(n, random_state=1)
        pos = rng.normal(0.0, 1.0, (n, 3))
        pts = np.stack([rots[i].apply(lp) + pos[i] for i in range(n)])
        pts += rng.normal(0.0, 0.0005, pts.shape)
        for case in ("all", "hidden1", "swap2"):
            frames = np.ascontiguousarray(pts.copy())
            valid = np.ones((n, k), dtype=np.bool_)
            if case == "hidden1":
                valid[:, 1] = False
                frames[:, 1] = np.nan
            elif case == "swap2":
                frames[:, [0, 2]] = frames[:, [2, 0]]
            solver = PropSolver(layout)
            solver.bind(labels)
            for f in range(args.calls // 10):
                solver.solve(frames[f % n], valid[f % n])
            times = np.empty(args.calls, dtype=np.int64)
            gc.disable()
            for c in range(args.calls):
                f = c % n
                t0 = time.perf_counter_ns()
                solver.solve(frames[f], valid[f])
                times[c] = time.perf_counter_ns() - t0
            base = np.empty(min(args.calls, 5000), dtype=np.int64)
            ok = valid.copy()
            for c in range(base.size):
                f = c % n
                t0 = time.perf_counter_ns()
                _kabsch(lp, frames[f], ok[f])
                base[c] = time.perf_counter_ns() - t0
            gc.enable()
            med, p99, mx = _stats(times)
            bmed, bp99, _ = _stats(base)
            print(
                f"{name:8} {case:8} {med:9.2f} {p99:8.2f} {mx:8.1f} "
                f"{bmed:10.2f} {bp99:10.2f} {bmed / med:6.2f}"
            )


if __name__ == "__main__":
    main()
