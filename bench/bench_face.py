"""Face solve benchmark: stabilize + weights, one frame at a time, and a scipy baseline.

Run from the repository root::

    python bench/bench_face.py [--calls C] [--baseline-calls B] [--occluded P]
                               [--model ict|makehuman] [--all-shapes]

The synthetic face (``--model``: ICT-FaceKit, default, or MakeHuman + TalkingHead ARKit;
``retargetd.daemon.synth.face``): 40 facial markers, 4 head markers, ARKit 52 shapes,
0.5 mm noise) rides on the head motion of the Plug-in Gait walk
(``../shared/datasets``), replayed end to end to fill ``--calls``. For each case (every
marker seen; ``--occluded`` percent of facial markers hidden at random per frame, so the
restricted normal matrix is rebuilt on most frames) it prints ``FaceSolver.solve_frame``
latency (``time.perf_counter_ns`` around each call after a warm-up): median, p99, max in
microseconds, the Cholesky solves per frame, and the same-run baseline: numpy Kabsch
(SVD) + ``scipy.optimize.lsq_linear`` (method ``bvls``) on the same problem per frame
(the weights in [0, 1] and the head pose's correction, unbounded, with its prior from
the head markers), with the ratio of medians. The solver solves what the daemon
solves: the shapes the layout can observe (``observability``: 38 of ICT's 52 with
these markers; the others are sent as 0), and holds a shape while one of its key
markers is hidden; ``--all-shapes`` solves all 52 (before issue 32). Speed is printed,
never asserted (STYLE.md section 10).
"""

from __future__ import annotations

import argparse
import gc
import math
import sys
import time
from pathlib import Path

import numpy as np
from scipy.optimize import lsq_linear

from retargetd.daemon.face import solve as sf
from retargetd.daemon.face.observability import pose_jacobian
from retargetd.daemon.synth import face as fs

DATASETS = Path(__file__).resolve().parent.parent.parent / "shared" / "datasets"


def _stats(ns: np.ndarray) -> tuple[float, float, float]:
    us = ns / 1e3
    return float(np.median(us)), float(np.percentile(us, 99)), float(us.max())


def _baseline_frame(
    solver: sf.FaceSolver, markers: np.ndarray, valid: np.ndarray
) -> np.ndarray:
    tr = solver.training
    h = len(tr.head_names)
    head = markers[:h][valid[:h]]
    layout = tr.head_layout[valid[:h]]
    ch, cl = head.mean(axis=0), layout.mean(axis=0)
    u, _, vt = np.linalg.svd((layout - cl).T @ (head - ch))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    rot = vt.T @ np.diag([1.0, 1.0, d]) @ u.T  # world_from_head
    seen = valid[h:]
    face = (markers[h:][seen] - ch + rot @ cl) @ rot
    rows = np.repeat(seen, 3)
    dvec = (face - tr.neutral[seen]).reshape(-1)
    basis = tr.basis[rows][:, solver.solved]
    k = basis.shape[1]
    # The same problem: the head pose's correction (6, unbounded) with the weights,
    # its prior from the head markers seen (face.solve's module docstring).
    jac = pose_jacobian(tr.neutral).reshape(-1, 6)[rows]
    jh = pose_jacobian(tr.head_layout[valid[:h]]).reshape(-1, 6)
    a = np.block(
        [
            [basis, jac],
            [math.sqrt(solver.lambda_) * np.eye(k), np.zeros((k, 6))],
            [np.zeros((len(jh), k)), jh],
        ]
    )
    rhs = np.concatenate([dvec, np.zeros(k + len(jh))])
    lo = np.r_[np.zeros(k), np.full(6, -np.inf)]
    hi = np.r_[np.ones(k), np.full(6, np.inf)]
    return lsq_linear(a, rhs, bounds=(lo, hi), method="bvls").x[:k]


def main(argv: list[str] | None = None) -> int:
    """Print the figures; return 0 (2 when the datasets are absent)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--calls", type=int, default=20000)
    ap.add_argument("--baseline-calls", type=int, default=500)
    ap.add_argument("--occluded", type=float, default=10.0, help="percent")
    ap.add_argument("--model", choices=sorted(fs.MODELS), default="ict")
    ap.add_argument(
        "--all-shapes", action="store_true", help="solve all shapes, unobservable too"
    )
    args = ap.parse_args(argv)
    if not (DATASETS / fs.MODEL_DIRS[args.model]).is_dir():
        sys.stderr.write(f"bench_face: datasets not found at {DATASETS}\n")
        return 2
    rng = np.random.default_rng(0)
    take = fs.synth_face_take(DATASETS, rng, model=args.model)
    tr = take.training
    n, m = take.markers_world.shape[:2]
    solved = None if args.all_shapes else sf.observability(tr).observable
    n_solved = tr.k if solved is None else int(solved.sum())
    print(
        f"face ({args.model}): {len(tr.marker_names)} facial + "
        f"{len(tr.head_names)} head markers x "
        f"{tr.k} shapes ({n_solved} solved); {n} frames of the PiG walk's head "
        "motion, looped"
    )
    cases = {"all seen": np.ones((n, m), dtype=bool)}
    occ = np.ones((n, m), dtype=bool)
    occ[:, len(tr.head_names) :] = rng.uniform(size=(n, m - len(tr.head_names))) >= (
        args.occluded / 100.0
    )
    cases[f"{args.occluded:g}% facial occluded"] = occ
    print(
        f"{'case':<24}{'median us':>10}{'p99 us':>9}{'max us':>9}{'solves':>8}"
        f"{'scipy med':>11}{'scipy p99':>11}{'ratio':>8}"
    )
    for name, valid in cases.items():
        markers = np.ascontiguousarray(
            np.where(valid[..., None], take.markers_world, np.nan)
        )
        solver = sf.FaceSolver(tr, solved=solved)
        out = solver.new_output()
        for t in range(min(n, 200)):  # warm-up: compilation and caches
            solver.solve_frame(markers[t], valid[t], out)
        ns = np.empty(args.calls, dtype=np.int64)
        solves = np.empty(args.calls, dtype=np.int64)
        gc.disable()
        try:
            for c in range(args.calls):
                t = c % n
                t0 = time.perf_counter_ns()
                solver.solve_frame(markers[t], valid[t], out)
                ns[c] = time.perf_counter_ns() - t0
                solves[c] = out.status[1]
        finally:
            gc.enable()
        base = np.empty(args.baseline_calls, dtype=np.int64)
        for c in range(args.baseline_calls):
            t = c % n
            t0 = time.perf_counter_ns()
            _baseline_frame(solver, markers[t], valid[t])
            base[c] = time.perf_counter_ns() - t0
        med, p99, mx = _stats(ns)
        bmed, bp99, _ = _stats(base)
        print(
            f"{name:<24}{med:>10.1f}{p99:>9.1f}{mx:>9.0f}{np.mean(solves):>8.2f}"
            f"{bmed:>11.1f}{bp99:>11.1f}{bmed / med:>7.1f}x"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
