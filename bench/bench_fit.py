"""Rigid-skeleton fit benchmark: one-frame latency, iterations, batch throughput and
two baselines measured in the same run.

Run from the repository root::

    python bench/bench_fit.py [--frames N] [--calls C] [--scipy-frames S]

For each case it prints

- ``FitSolver.solve_frame`` latency, one frame at a time as the live loop calls it
  (``--warmup`` frames first, then ``--calls`` timed calls, ``time.perf_counter_ns``
  around each): median, p99 and max in microseconds, and LM iterations per frame
  (median, p99, max) and reseeds; and the same calls' CPU time
  (``time.thread_time_ns`` around each, outside the wall clock's reads: the time
  the calling thread ran, not the time it waited for a core, which on a shared
  machine sets the wall clock's p99);
- batch throughput, ``FitSolver.solve_take`` over the stream (one core, best of
  ``--repeat``);
- baseline 1, the construction kernel (``BodySolver.solve_frame``) on the same frames:
  median, p99 and the ratio of medians;
- baseline 2, ``scipy.optimize.least_squares`` (method ``"lm"``, finite-difference
  Jacobian) on the same residuals (weighted marker residuals and the pull to the last
  frame, numpy forward kinematics), warm-started from the fit's previous frame, on
  ``--scipy-frames`` frames: median, p99 and the ratio of medians.

Cases: ``menache`` on the synthetic performer at 240 Hz (calibrated on its T-pose
hold); ``dense-75``, the issue's larger rig: the tests' exact rig
(``tests/data/synth-exact-rig.toml``, 21 bones) worn with 3 more markers (75) and
hinge knees (``[fit.bones] dof = "hinge"``), on the same performer with 0.5 mm noise:
62 degrees of freedom counted the biomechanical way (6 for the root, 3 per ball joint,
1 per hinge; the kernel solves 3 per bone, 66 unknowns), more than the 34 of the
issue's figure (biorbd's 34-DoF, 75-marker model, the Kalman filter's published time
in ``../shared/reference/peers.md``), so an upper bound for it (the performer's 21
segments leave no 34-DoF chain that fits it without a model error); ``plug-in-gait``
on the real walk
``PiG_Motion-FlatFoot-Full.c3d`` calibrated on ``PiG_Calibration-FlatFoot-Full.c3d``
(``../shared/datasets/btkdata``), played forward then backward to fill ``--frames``
(no jump at the seam); ``bioptim-wholebody``, the shipped rig for biorbd's
whole-body model (75 markers) on its gait take ``../shared/datasets/peers/
bioptim_gait_wholebody.c3d``, calibrated on its first 10 rows, forward and back.
Without the datasets those cases are skipped (said in the output). The
machine's load average is printed beside the figures. Speed is printed, never
asserted.
"""

from __future__ import annotations

import argparse
import gc
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from retargetd.daemon.body import fit_terms as ft
from retargetd.daemon.body.calibration import calibrate
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.body.solve import BodySolver
from retargetd.daemon.body.solve_fit import FitSolver
from retargetd.daemon.synth import performer as pf
from retargetd.daemon.validate.limits import JOINT_LIMITS_DEG
from retargetd.daemon.validate.model import SEGMENT_KIND

DATASETS = Path(__file__).resolve().parent.parent.parent / "shared" / "datasets"
TESTS_DATA = Path(__file__).resolve().parent.parent / "tests" / "data"
#: The dense case's three extra markers: segment, offset (mm, the segment's frame as
#: in tests/data/synth-exact-markers.toml), and the rig segment group they join.
DENSE_EXTRA = (
    ("LTHF", "l_thigh", (60, 40, -150)),
    ("RTHF", "r_thigh", (60, -40, -150)),
    ("STRN", "thorax", (110, 0, 120)),
)
PIG_MOTION = DATASETS / "btkdata" / "PiG_Motion-FlatFoot-Full.c3d"
PIG_CALIBRATION = DATASETS / "btkdata" / "PiG_Calibration-FlatFoot-Full.c3d"
BIOPTIM_TAKE = DATASETS / "peers" / "bioptim_gait_wholebody.c3d"


@dataclass(slots=True)
class Case:
    """A fit solver and the stream of frames it runs on."""

    name: str
    solver: FitSolver
    construction: BodySolver
    frames: np.ndarray  # (T, M, 3) float64, metres, world
    data: str


def _menache(n_frames: int) -> Case:
    rate_hz = 240.0
    take = pf.synthesize(seconds=n_frames / rate_hz, rate_hz=rate_hz)
    rig = load_rig("menache")
    base = take.markers_world[take.base_pose_frames]
    cal = calibrate(rig, base, take.labels)
    return Case(
        "menache",
        FitSolver(
            rig,
            cal,
            take.labels,
            joint_limits=JOINT_LIMITS_DEG,
            segment_kind=SEGMENT_KIND,
            base_positions=base,
            rate_hz=take.rate_hz,
        ),
        BodySolver(rig, cal, take.labels),
        np.ascontiguousarray(take.markers_world),
        f"synthetic performer, 240 Hz, {take.n_frames} frames",
    )


def _dense(n_frames: int, folder: Path) -> Case:
    """The exact rig with 75 markers and hinge knees (module docstring)."""
    markers = (TESTS_DATA / "synth-exact-markers.toml").read_text()
    rig_text = (TESTS_DATA / "synth-exact-rig.toml").read_text()
    for name, seg, off in DENSE_EXTRA:
        markers += (
            f'\n[markers.{name}]\nsegment = "{seg}"\noffset_mm = {list(off)}\n'
            f'description = "bench_fit: extra {seg} marker"\n'
        )
        rig_text = rig_text.replace("[markers]\n", f'[markers]\n{name} = "{name}"\n', 1)
        group = f"[segments.{seg}]\nmarkers = ["
        rig_text = rig_text.replace(group, f'{group}"{name}", ', 1)
    rig_text += '\n[fit.bones.l_shank]\ndof = "hinge"\n'
    rig_text += '[fit.bones.r_shank]\ndof = "hinge"\n'
    (folder / "dense-markers.toml").write_text(markers)
    (folder / "dense-rig.toml").write_text(rig_text)
    rate_hz = 240.0
    take = pf.synthesize(
        seconds=n_frames / rate_hz, rate_hz=rate_hz,
        markerset=folder / "dense-markers.toml", noise_mm=0.5,
    )  # fmt: skip
    rig = load_rig(folder / "dense-rig.toml")
    base = take.markers_world[take.base_pose_frames]
    cal = calibrate(rig, base, take.labels)
    solver = FitSolver(
        rig, cal, take.labels, joint_limits=JOINT_LIMITS_DEG,
        segment_kind=SEGMENT_KIND, base_positions=base, rate_hz=rate_hz,
    )  # fmt: skip
    n_hinge = sum(b.dof == "hinge" for b in rig.fit.bones.values())
    n_ball = len(rig.bones) - 1 - n_hinge
    return Case(
        "dense-75",
        solver,
        BodySolver(rig, cal, take.labels),
        np.ascontiguousarray(take.markers_world),
        f"synthetic performer with the exact rig + 3 markers, 0.5 mm noise, 240 Hz, "
        f"{take.n_frames} frames; {len(rig.bones)} bones, {6 + 3 * n_ball + n_hinge} "
        f"DoF ({n_hinge} hinges)",
    )


def _bioptim(n_frames: int) -> Case | None:
    """The shipped ``bioptim-wholebody`` rig (75 markers) on the bioptim gait take,
    calibrated on its first 10 rows with Harrington's pelvis width and depth measured
    there (as ``bench/peers.py`` does: the take has no static)."""
    if not BIOPTIM_TAKE.exists():
        return None
    from retargetd.replay.takes import load_take

    take = load_take(BIOPTIM_TAKE)
    rig = load_rig("bioptim-wholebody")
    base = take.positions[:10]
    col = {n: i for i, n in enumerate(take.labels)}
    right, left = base[:, col["RASIS"]], base[:, col["LASIS"]]
    back = 0.5 * (base[:, col["RPSIS"]] + base[:, col["LPSIS"]])
    meas = {
        "PelvisWidth": float(
            1000 * np.nanmedian(np.linalg.norm(left - right, axis=-1))
        ),
        "PelvisDepth": float(
            1000 * np.nanmedian(np.linalg.norm(0.5 * (left + right) - back, axis=-1))
        ),
    }
    cal = calibrate(rig, base, take.labels, overrides=meas)
    loop = np.concatenate([take.positions, take.positions[::-1]])
    reps = -(-n_frames // loop.shape[0])
    frames = np.ascontiguousarray(np.concatenate([loop] * reps)[:n_frames])
    return Case(
        "bioptim-wholebody",
        FitSolver(
            rig, cal, take.labels, joint_limits=JOINT_LIMITS_DEG,
            segment_kind=SEGMENT_KIND, base_positions=base, rate_hz=take.rate_hz,
        ),
        BodySolver(rig, cal, take.labels),
        frames,
        f"real gait {BIOPTIM_TAKE.name} (biorbd's 34-DoF, 75-marker problem), "
        f"forward and back, {frames.shape[0]} frames; {len(rig.bones)} bones",
    )  # fmt: skip


def _pig(n_frames: int) -> Case | None:
    if not (PIG_MOTION.exists() and PIG_CALIBRATION.exists()):
        return None
    from retargetd.replay.takes import load_take

    static = load_take(PIG_CALIBRATION)
    walk = load_take(PIG_MOTION)
    rig = load_rig("plug-in-gait")
    cal = calibrate(
        rig, static.positions, static.labels, take_measurements=static.measurements
    )
    loop = np.concatenate([walk.positions, walk.positions[::-1]])
    reps = -(-n_frames // loop.shape[0])
    frames = np.ascontiguousarray(np.concatenate([loop] * reps)[:n_frames])
    return Case(
        "plug-in-gait",
        FitSolver(
            rig,
            cal,
            walk.labels,
            joint_limits=JOINT_LIMITS_DEG,
            segment_kind=SEGMENT_KIND,
            base_positions=static.positions,
            base_labels=static.labels,
            rate_hz=walk.rate_hz,
        ),
        BodySolver(rig, cal, walk.labels),
        frames,
        f"real walk {PIG_MOTION.name}, forward and back, {frames.shape[0]} frames",
    )


def _pct(x_ns: np.ndarray) -> tuple[float, float, float]:
    us = x_ns / 1000.0
    return float(np.median(us)), float(np.percentile(us, 99)), float(us.max())


def _time_frames(
    solve: object, pose: object, frames: np.ndarray, warmup: int, calls: int
) -> np.ndarray:
    times = np.zeros(calls, dtype=np.int64)
    n = frames.shape[0]
    for f in range(warmup):
        solve(frames[f % n], pose)  # type: ignore[operator]
    gc.disable()
    try:
        for k in range(calls):
            frame = frames[(warmup + k) % n]
            t0 = time.perf_counter_ns()
            solve(frame, pose)  # type: ignore[operator]
            times[k] = time.perf_counter_ns() - t0
    finally:
        gc.enable()
    return times


class ScipyFit:
    """The fit's residuals in numpy, for ``scipy.optimize.least_squares``."""

    def __init__(self, solver: FitSolver) -> None:
        m = solver.model
        self.m = m
        self.cols = solver.marker_cols
        # the continuity weights the kernel uses at the solver's rate (one frame:
        # fit_terms.continuity_weights), about the warm start as the kernel's are
        # about its prediction
        p, dt = solver.params, 1.0 / solver.rate_hz
        self.lam = (p.noise_m / (0.5 * p.alpha_max * dt * dt)) ** 2
        self.lam_t = (p.noise_m / (0.5 * p.acc_max * dt * dt)) ** 2
        self.sw = np.sqrt(m.marker_weight)
        self.off = np.array(m.off_parent)  # (scipy wants writeable buffers)

    def fk(self, q: np.ndarray, t: np.ndarray) -> np.ndarray:
        m = self.m
        n_b = q.shape[0]
        rot_w: list[Rotation] = []
        origin = np.zeros((n_b, 3))
        for b in range(n_b):
            p = m.bone_parent[b]
            r = Rotation.from_quat(q[b], scalar_first=True)
            if p < 0:
                rot_w.append(r)
                origin[b] = t[m.bone_root[b]]
            else:
                rot_w.append(rot_w[p] * r)
                origin[b] = origin[p] + rot_w[p].apply(self.off[b])
        mats = np.stack([r.as_matrix() for r in rot_w])
        return origin[m.marker_bone] + np.einsum(
            "mij,mj->mi", mats[m.marker_bone], m.marker_local
        )

    def solve(self, frame: np.ndarray, q0: np.ndarray, t0: np.ndarray) -> None:
        n_b, n_r = q0.shape[0], t0.shape[0]
        meas = np.full((len(self.cols), 3), np.nan)
        have = self.cols >= 0
        meas[have] = frame[self.cols[have]]
        vis = np.isfinite(meas).all(axis=1) & (self.sw > 0)
        base = Rotation.from_quat(q0, scalar_first=True)

        def state(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            q = (base * Rotation.from_rotvec(x[: 3 * n_b].reshape(n_b, 3))).as_quat(
                scalar_first=True
            )
            return q, t0 + x[3 * n_b :].reshape(n_r, 3)

        def residuals(x: np.ndarray) -> np.ndarray:
            q, t = state(x)
            r = (self.fk(q, t) - meas)[vis] * self.sw[vis, None]
            return np.concatenate(
                [
                    r.ravel(),
                    np.sqrt(self.lam) * x[: 3 * n_b],
                    np.sqrt(self.lam_t) * x[3 * n_b :],
                ]
            )

        least_squares(residuals, np.zeros(3 * n_b + 3 * n_r), method="lm")


def _load() -> str:
    a, b, c = os.getloadavg()
    return f"load average {a:.2f} {b:.2f} {c:.2f} ({os.cpu_count()} cpus)"


def run(case: Case, args: argparse.Namespace) -> None:
    n_m = len(case.solver.marker_names)
    n_dof = case.solver.model.n_dof
    print(f"\n== {case.name}: {case.data}; {n_m} rig markers, {n_dof} unknowns")
    fit = case.solver
    fit.reset()
    pose = fit.new_pose()
    iters = np.zeros(args.calls)
    solves = np.zeros(args.calls)
    reseeds = 0

    fit.reset()
    n = case.frames.shape[0]
    for f in range(args.warmup):
        fit.solve_frame(case.frames[f % n], pose)
    gc.disable()
    times = np.zeros(args.calls, dtype=np.int64)
    cpu = np.zeros(args.calls, dtype=np.int64)
    try:
        for k in range(args.calls):
            frame = case.frames[(args.warmup + k) % n]
            c0 = time.thread_time_ns()
            t0 = time.perf_counter_ns()
            fit.solve_frame(frame, pose)
            t1 = time.perf_counter_ns()
            cpu[k] = time.thread_time_ns() - c0
            times[k] = t1 - t0
            iters[k] = pose.stats[ft.S_ITER]
            solves[k] = pose.stats[ft.S_SOLVES]
            reseeds += int(pose.stats[ft.S_RESEEDED])
    finally:
        gc.enable()
    med, p99, worst = _pct(times)
    print(
        f"  fit, one frame ({args.calls} calls after {args.warmup} warm-up): "
        f"median {med:.1f} us, p99 {p99:.1f} us, max {worst:.1f} us   [{_load()}]"
    )
    cmed_, cp99_, cmax_ = _pct(cpu)
    print(
        f"    CPU time of the same calls: median {cmed_:.1f} us, p99 {cp99_:.1f} us, "
        f"max {cmax_:.1f} us"
    )
    print(
        f"    iterations per frame: median {np.median(iters):.0f}, p99 "
        f"{np.percentile(iters, 99):.0f}, max {iters.max():.0f}; linear solves "
        f"median {np.median(solves):.0f}, p99 {np.percentile(solves, 99):.0f}; "
        f"reseeds {reseeds}"
    )
    best = float("inf")
    for _ in range(args.repeat):
        fit.reset()
        start = time.perf_counter()
        fit.solve_take(case.frames)
        best = min(best, time.perf_counter() - start)
    print(f"  fit, batch: {case.frames.shape[0] / best:,.0f} frames/s "
          f"({1e6 * best / case.frames.shape[0]:.1f} us/frame, best of {args.repeat})"
          f"   [{_load()}]")  # fmt: skip
    con = case.construction
    con.reset()
    cpose = con.new_pose()
    ctimes = _time_frames(con.solve_frame, cpose, case.frames, args.warmup, args.calls)
    cmed, cp99, _ = _pct(ctimes)
    print(f"  baseline construction kernel, one frame: median {cmed:.1f} us, p99 "
          f"{cp99:.1f} us; fit / construction median {med / cmed:.1f}x")  # fmt: skip
    sp = ScipyFit(fit)
    fit.reset()
    for f in range(args.warmup):
        fit.solve_frame(case.frames[f % n], pose)
    stimes = np.zeros(args.scipy_frames, dtype=np.int64)
    for k in range(args.scipy_frames):
        frame = case.frames[(args.warmup + k) % n]
        q0, t0a = fit._q.copy(), fit._t.copy()
        t0 = time.perf_counter_ns()
        sp.solve(frame, q0, t0a)
        stimes[k] = time.perf_counter_ns() - t0
        fit.solve_frame(frame, pose)
    smed, sp99, _ = _pct(stimes)
    print(f"  baseline scipy least_squares (lm, same residuals), one frame "
          f"({args.scipy_frames} frames): median {smed:.0f} us, p99 {sp99:.0f} us; "
          f"scipy / fit median {smed / med:.0f}x")  # fmt: skip


def main() -> None:
    """Run the benchmark (see module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=4800)
    ap.add_argument("--calls", type=int, default=3000)
    ap.add_argument("--warmup", type=int, default=300)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--scipy-frames", type=int, default=5)
    args = ap.parse_args()
    print(f"bench_fit  [{_load()}]")
    run(_menache(args.frames), args)
    with tempfile.TemporaryDirectory() as folder:
        run(_dense(args.frames, Path(folder)), args)
    bioptim = _bioptim(args.frames)
    if bioptim is None:
        print(f"\n== bioptim-wholebody: skipped, {BIOPTIM_TAKE} not found")
    else:
        run(bioptim, args)
    pig = _pig(args.frames)
    if pig is None:
        print(f"\n== plug-in-gait: skipped, {PIG_MOTION} not found")
    else:
        run(pig, args)


if __name__ == "__main__":
    main()
