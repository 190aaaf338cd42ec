"""Body solve benchmark: one-frame latency, batch throughput, and a numpy baseline.

Run from the repository root::

    python bench/bench_solve.py [--frames N] [--repeat R] [--calls C]

For each rig it prints

- ``solve_frame`` latency, one frame at a time as the live loop calls it (warm-up
  first, then ``--calls`` timed calls, ``time.perf_counter_ns`` around each call):
  median, p99 and max in microseconds;
- batch throughput, ``solve_take`` over ``--frames`` frames, best of ``--repeat``;
- the baseline, measured in the same run: the same rig solved per frame in plain numpy
  (``calibration.compute_points`` + ``solve_body.bone_world_quats`` + quaternion
  products for the parent-relative rotations) and, slower still, with a scipy
  ``Rotation`` per bone; its median / p99 and the ratio of medians, which is what
  justifies compiling the kernel with numba;
- the ratio to biorbd's extended Kalman filter, 7.11 ms per frame: a published figure
  from ``../shared/reference/peers.md`` (another model and data), not measured here.

Rigs: ``menache`` on the synthetic performer at 240 Hz (calibrated on its T-pose
hold); ``plug-in-gait`` on the real walk ``PiG_Motion-FlatFoot-Full.c3d`` calibrated on
``PiG_Calibration-FlatFoot-Full.c3d`` (``../shared/datasets/btkdata``), repeated end to
end to fill ``--frames``. Without the datasets, plug-in-gait runs on the synthetic
performer wearing the plug-in-gait marker set (said in the output). Speed is printed,
never asserted (STYLE.md section 10).
"""

from __future__ import annotations

import argparse
import gc
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.calibration import (
    Calibration,
    calibrate,
    compute_points,
    match_markers,
)
from retargetd.daemon.body.rig import LinePoint, Rig, load_rig, shipped_rigs
from retargetd.daemon.body.solve import FLAG_PARTIAL, BodySolver, bone_world_quats
from retargetd.daemon.synth import performer as pf

DATASETS = Path(__file__).resolve().parent.parent.parent / "shared" / "datasets"
PIG_MOTION = DATASETS / "btkdata" / "PiG_Motion-FlatFoot-Full.c3d"
PIG_CALIBRATION = DATASETS / "btkdata" / "PiG_Calibration-FlatFoot-Full.c3d"
#: biorbd 1.12.4 KalmanReconsMarkers.reconstructFrame, median per frame (peers.md).
BIORBD_KALMAN_MEDIAN_US = 7110.0
BIORBD_KALMAN_P99_US = 7870.0


@dataclass(slots=True)
class Case:
    """One rig on one stream of frames."""

    rig: Rig
    calibration: Calibration
    labels: tuple[str, ...]
    frames: np.ndarray  # (T, M, 3) float64, metres, world
    data: str


def _menache(n_frames: int) -> Case:
    rate_hz = 240.0
    take = pf.synthesize(seconds=n_frames / rate_hz, rate_hz=rate_hz)
    rig = load_rig("menache")
    cal = calibrate(rig, take.markers_world[take.base_pose_frames], take.labels)
    data = f"synthetic performer, 240 Hz, {take.n_frames} frames"
    return Case(rig, cal, take.labels, np.ascontiguousarray(take.markers_world), data)


def _plug_in_gait(n_frames: int) -> Case | None:
    if "plug-in-gait" not in shipped_rigs():
        print(
            "plug-in-gait: no rig daemon/body/rigs/plug-in-gait.toml yet: skipped",
            file=sys.stderr,
        )
        return None
    rig = load_rig("plug-in-gait")
    if PIG_MOTION.is_file() and PIG_CALIBRATION.is_file():
        from retargetd.replay.takes import load_take

        base = load_take(PIG_CALIBRATION)
        walk = load_take(PIG_MOTION)
        cal = calibrate(
            rig, base.positions, base.labels, take_measurements=base.measurements
        )
        reps = -(-n_frames // walk.n_frames)
        frames = np.concatenate([walk.positions] * reps)[:n_frames]
        data = (
            f"real walk {PIG_MOTION.name}, {walk.rate_hz:g} Hz, {walk.n_frames} "
            f"frames repeated to {len(frames)}"
        )
        return Case(rig, cal, walk.labels, np.ascontiguousarray(frames), data)
    print(
        f"plug-in-gait: datasets not found at {DATASETS}: using the synthetic "
        "performer wearing the plug-in-gait marker set instead",
        file=sys.stderr,
    )
    take = pf.synthesize(
        seconds=n_frames / 240.0, rate_hz=240.0, markerset="plug-in-gait"
    )
    cal = calibrate(rig, take.markers_world[take.base_pose_frames], take.labels)
    data = f"synthetic performer in plug-in-gait markers, 240 Hz, {take.n_frames} fr"
    return Case(rig, cal, take.labels, np.ascontiguousarray(take.markers_world), data)


def _rig_columns(case: Case) -> np.ndarray:
    """(Mr,) stream column of each rig marker, -1 when the stream lacks it."""
    return np.asarray(match_markers(case.rig, case.labels), dtype=np.int64)


def _baseline_numpy(case: Case) -> Callable[[np.ndarray], np.ndarray]:
    """The same rig solved per frame in plain numpy (no occlusion handling)."""
    rig, cal = case.rig, case.calibration
    cols = _rig_columns(case)
    parents = np.array(rig.bone_parent_indices())
    has_parent = parents >= 0
    conj_rest = rot.quat_conj(cal.rest_parent_from_bone_quat)
    joint_points = tuple(rig.joints.values())

    def solve(markers: np.ndarray) -> np.ndarray:
        marker_pos = np.where(cols[:, None] >= 0, markers[cols], np.nan)[None]
        pts = compute_points(rig, marker_pos, cal.point_offsets)
        wfb = bone_world_quats(rig, pts)[0]
        rel = wfb.copy()
        rel[has_parent] = rot.quat_mul(
            rot.quat_conj(wfb[parents[has_parent]]), wfb[has_parent]
        )
        pfb = rot.quat_mul(conj_rest, rel)
        np.stack([pts[p][0] for p in joint_points])
        return np.concatenate([wfb, pfb])

    return solve


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    # Row-wise cross product without np.cross's per-call overhead (~23 us, peers.md).
    return a[:, [1, 2, 0]] * b[:, [2, 0, 1]] - a[:, [2, 0, 1]] * b[:, [1, 2, 0]]


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.sqrt(np.einsum("ij,ij->i", v, v))[:, None]


def _baseline_vectorized(case: Case) -> Callable[[np.ndarray], np.ndarray]:
    """The same rig in numpy as the issue first proposed: derived points vectorized
    per dependency level, bones all at once, one preallocated point buffer."""
    rig, cal = case.rig, case.calibration
    names = [*rig.marker_names, *rig.point_names]
    index = {n: i for i, n in enumerate(names)}
    n_markers = len(rig.marker_names)
    cols = _rig_columns(case)
    seen_cols = np.flatnonzero(cols >= 0)
    depth = dict.fromkeys(rig.marker_names, 0)
    for p in rig.points:
        depth[p.name] = 1 + max(depth[n] for n in p.inputs)
    levels = []
    for d in range(1, max(depth.values(), default=0) + 1):
        line = [(k, p) for k, p in enumerate(rig.points) if depth[p.name] == d
                and isinstance(p, LinePoint)]  # fmt: skip
        rigid = [(k, p) for k, p in enumerate(rig.points) if depth[p.name] == d
                 and not isinstance(p, LinePoint)]  # fmt: skip
        levels.append(
            (
                np.array([n_markers + k for k, _ in line], dtype=np.int64),
                np.array([index[p.a] for _, p in line], dtype=np.int64),
                np.array([index[p.b] for _, p in line], dtype=np.int64),
                np.array([p.u for _, p in line])[:, None],
                np.array([n_markers + k for k, _ in rigid], dtype=np.int64),
                np.array(
                    [[index[n] for n in p.frame] for _, p in rigid], dtype=np.int64
                ).reshape(-1, 3),
                cal.point_offsets[[k for k, _ in rigid]].reshape(-1, 3),
            )
        )
    bo = np.array([index[b.origin] for b in rig.bones])
    ba = np.array([index[b.aim] for b in rig.bones])
    up_from = np.array(
        [index[b.up[0] if len(b.up) == 2 else b.origin] for b in rig.bones]
    )
    up_to = np.array([index[b.up[-1]] for b in rig.bones])
    parents = np.array(rig.bone_parent_indices())
    has_parent = parents >= 0
    conj_rest = rot.quat_conj(cal.rest_parent_from_bone_quat)
    joint_idx = np.array([index[p] for p in rig.joints.values()])
    pts = np.full((len(names), 3), np.nan)

    def solve(markers: np.ndarray) -> np.ndarray:
        pts[seen_cols] = markers[cols[seen_cols]]
        for ld, la, lb, lu, rd, rabc, roff in levels:
            if len(ld):
                a = pts[la]
                pts[ld] = a + lu * (pts[lb] - a)
            if len(rd):
                a = pts[rabc[:, 0]]
                x = _unit(pts[rabc[:, 1]] - a)
                z = _unit(_cross(x, pts[rabc[:, 2]] - a))
                y = _cross(z, x)
                pts[rd] = a + x * roff[:, :1] + y * roff[:, 1:2] + z * roff[:, 2:]
        o = pts[bo]
        y = _unit(pts[ba] - o)
        up = pts[up_to] - pts[up_from]
        x = _unit(up - np.einsum("ij,ij->i", up, y)[:, None] * y)
        wfb = rot.quat_from_mat(np.stack([x, y, _cross(x, y)], axis=-1))
        rel = wfb.copy()
        rel[has_parent] = rot.quat_mul(
            rot.quat_conj(wfb[parents[has_parent]]), wfb[has_parent]
        )
        pts[joint_idx]
        return np.concatenate([wfb, rot.quat_mul(conj_rest, rel)])

    return solve


def _baseline_scipy(case: Case) -> Callable[[np.ndarray], np.ndarray]:
    """As :func:`_baseline_numpy`, but a Python loop over bones with scipy
    ``Rotation`` objects (the peers.md "loop per joint" baseline)."""
    rig, cal = case.rig, case.calibration
    cols = _rig_columns(case)
    parents = rig.bone_parent_indices()
    rest = [
        Rotation.from_quat(q, scalar_first=True) for q in cal.rest_parent_from_bone_quat
    ]

    def solve(markers: np.ndarray) -> np.ndarray:
        marker_pos = np.where(cols[:, None] >= 0, markers[cols], np.nan)[None]
        pts = compute_points(rig, marker_pos, cal.point_offsets)
        world: list[Rotation] = []
        out = np.empty((2 * len(rig.bones), 4))
        for b, bone in enumerate(rig.bones):
            y = pts[bone.aim][0] - pts[bone.origin][0]
            y = y / np.linalg.norm(y)
            up = (
                pts[bone.up[1]][0] - pts[bone.up[0]][0]
                if len(bone.up) == 2
                else pts[bone.up[0]][0] - pts[bone.origin][0]
            )
            x = up - (up @ y) * y
            x = x / np.linalg.norm(x)
            r = Rotation.from_matrix(np.column_stack([x, y, np.cross(x, y)]))
            world.append(r)
            rel = r if parents[b] < 0 else world[parents[b]].inv() * r
            out[b] = r.as_quat(scalar_first=True)
            out[len(rig.bones) + b] = (rest[b].inv() * rel).as_quat(scalar_first=True)
        return out

    return solve


def _time_calls(fn: Callable[[int], object], n_calls: int, n_frames: int) -> np.ndarray:
    """Per-call wall time (ns) of ``fn(frame_index)`` over ``n_calls`` calls."""
    for i in range(min(200, n_calls)):  # warm-up
        fn(i % n_frames)
    gc.collect()
    times = np.empty(n_calls, dtype=np.int64)
    clock = time.perf_counter_ns
    for i in range(n_calls):
        t0 = clock()
        fn(i % n_frames)
        times[i] = clock() - t0
    return times


def _agree(
    case: Case, solver: BodySolver, baseline: Callable[[np.ndarray], np.ndarray]
) -> float:
    """Largest difference between kernel and baseline quaternions (up to sign), on
    frames with every rig marker seen and no roll held."""
    out = solver.new_pose()
    worst = 0.0
    for t in np.linspace(0, len(case.frames) - 1, 50).astype(int):
        frame = case.frames[t]
        if not np.isfinite(frame[solver.marker_cols[solver.marker_cols >= 0]]).all():
            continue  # the baselines do not handle occlusion
        solver.reset()
        solver.solve_frame(frame, out)
        if (out.bone_flags & FLAG_PARTIAL).any():
            # an up reference near its bone's axis: the kernel keeps that bone's
            # roll from its parent (RIGS.md up_min_mm), the baselines do not
            continue
        got = np.concatenate([out.world_from_bone_quat, out.rest_from_bone_quat])
        want = baseline(frame)
        sign = np.where(np.sum(got * want, axis=-1, keepdims=True) < 0, -1.0, 1.0)
        worst = max(worst, float(np.abs(got - sign * want).max()))
    return worst


#: (label, baseline factory, share of --baseline-calls)
BASELINES = (
    ("numpy, vectorized per level", _baseline_vectorized, 1.0),
    ("numpy, loop per point/bone", _baseline_numpy, 0.25),
    ("scipy Rotation per bone", _baseline_scipy, 0.25),
)


@dataclass(slots=True)
class Row:
    """One solver's per-frame figures (µs) on one rig."""

    solver: str
    calls: int
    median: float
    p99: float
    max: float


def _row(solver: str, times_us: np.ndarray) -> Row:
    return Row(
        solver,
        len(times_us),
        float(np.median(times_us)),
        float(np.percentile(times_us, 99)),
        float(times_us.max()),
    )


def run_case(
    name: str, case: Case, args: argparse.Namespace
) -> tuple[list[Row], float]:
    """Time one rig: per-frame rows (kernel first, then baselines) and batch fps."""
    solver = BodySolver(case.rig, case.calibration, case.labels)
    out = solver.new_pose()
    frames = case.frames
    n = len(frames)
    rig = case.rig
    print(
        f"\n{name}: {case.data}; rig {len(rig.marker_names)} markers, "
        f"{len(rig.points)} derived points, {len(rig.bones)} bones"
    )

    solver.reset()

    def one_frame(i: int) -> None:
        solver.solve_frame(frames[i], out)

    one = _time_calls(one_frame, args.calls, n)
    rows = [_row("kernel solve_frame (numba)", one / 1e3)]
    best = np.inf
    for _ in range(args.repeat):
        solver.reset()
        t0 = time.perf_counter()
        solver.solve_take(frames)
        best = min(best, time.perf_counter() - t0)

    # The baselines have no occlusion handling: they run on the frames where every
    # rig marker the stream has is seen.
    present = solver.marker_cols[solver.marker_cols >= 0]
    complete = np.flatnonzero(np.isfinite(frames[:, present]).all(axis=(1, 2)))
    print(f"  baselines run on the {len(complete)} frames with every rig marker seen")
    for label, make, share in BASELINES:
        base = make(case)
        print(f"  {label}: agrees with the kernel to "
              f"{_agree(case, solver, base):.1e} (quaternion components)")  # fmt: skip
        calls = max(round(args.baseline_calls * share), 20)

        def call(i: int, base: Callable[[np.ndarray], np.ndarray] = base) -> None:
            base(frames[complete[i]])

        times = _time_calls(call, calls, len(complete))
        rows.append(_row(label, times / 1e3))
    return rows, n / best


def print_table(
    results: dict[str, tuple[list[Row], float]], args: argparse.Namespace
) -> None:
    """The summary table: per-frame latency per solver, ratios to the kernel."""
    print(
        f"\nper frame, one frame at a time (warm-up, then timed calls; "
        f"time.perf_counter_ns per call); batch = solve_take over {args.frames} "
        f"frames, best of {args.repeat}"
    )
    head = (
        f"{'rig':<13} {'solver':<30} {'calls':>6} {'median µs':>10} {'p99 µs':>9} "
        f"{'max µs':>9} {'median / kernel':>15}"
    )
    print(head)
    print("-" * len(head))
    for name, (rows, _) in results.items():
        kernel = rows[0].median
        for r in rows:
            print(
                f"{name:<13} {r.solver:<30} {r.calls:>6} {r.median:10.1f} "
                f"{r.p99:9.1f} {r.max:9.1f} {r.median / kernel:15.1f}"
            )
        print(
            f"{name:<13} {'biorbd Kalman filter*':<30} {'':>6} "
            f"{BIORBD_KALMAN_MEDIAN_US:10.1f} {BIORBD_KALMAN_P99_US:9.1f} {'':>9} "
            f"{BIORBD_KALMAN_MEDIAN_US / kernel:15.1f}"
        )
    print(
        "* biorbd 1.12.4 KalmanReconsMarkers.reconstructFrame: published figure from "
        "peers.md (34-DoF model, 75 markers), not measured here"
    )
    print()
    for name, (_, fps) in results.items():
        print(f"batch {name:<13} {fps:12,.0f} frames/s (solve_take)")


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; returns the exit code."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=20_000, help="batch frames")
    parser.add_argument("--repeat", type=int, default=5, help="batch repeats (best)")
    parser.add_argument(
        "--calls", type=int, default=20_000, help="timed one-frame calls"
    )
    parser.add_argument(
        "--baseline-calls", type=int, default=1000, help="timed baseline calls"
    )
    args = parser.parse_args(argv)
    if args.frames < 1 or args.repeat < 1 or args.calls < 1 or args.baseline_calls < 1:
        parser.error("--frames, --repeat, --calls and --baseline-calls must be >= 1")
    results: dict[str, tuple[list[Row], float]] = {}
    cases = {
        "menache": _menache(args.frames),
        "plug-in-gait": _plug_in_gait(args.frames),
    }
    for name, case in cases.items():
        if case is not None:
            results[name] = run_case(name, case, args)
    print_table(results, args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
