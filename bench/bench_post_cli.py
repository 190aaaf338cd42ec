"""Offline post-command benchmark: what ``solve --pipeline``, ``--out take.csv``,
``--out take.glb``, ``reduce``, ``blend``, ``loop`` and ``retarget`` (also with
``--plant-feet``) cost on a real
take, beside solving it.

Run from the repository root::

    python bench/bench_post_cli.py [--repeats N]

Take: the Plug-in Gait walk (``../shared/datasets/btkdata``, 100 Hz), calibrated on
its static. Each step runs ``--repeats`` times on the whole take after one warm-up
(compilation); ``time.perf_counter`` around each run. Printed per step: median and
p99 of the run's wall time in milliseconds, the per-frame median in microseconds, and
the ratio of medians to ``BodySolver.solve_take`` on the same take (the baseline,
measured in the same run). Files go to a temporary directory. Speed is printed, never
asserted (STYLE.md section 10).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from retargetd.daemon.body.calibration import calibrate
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.body.solve import BodySolver
from retargetd.daemon.cli.post_io import apply_pipeline_to_solve, write_clip
from retargetd.daemon.cli.retarget_plant import plant_retarget
from retargetd.daemon.post.export_gltf import (
    clip_from_solve,
    write_clip_glb,
    write_reduced_glb,
)
from retargetd.daemon.post.interp import blend, find_loop, loop
from retargetd.daemon.post.reduce import reduce_clip
from retargetd.daemon.retarget.bvh import write_solve_bvh
from retargetd.daemon.retarget.bvh_retarget import retarget_bvh
from retargetd.daemon.retarget.euler_csv import write_euler_csv
from retargetd.replay.bvh import read_bvh_hierarchy
from retargetd.replay.takes import load_take

DATASETS = Path(__file__).resolve().parent.parent.parent / "shared" / "datasets"
STATIC = DATASETS / "btkdata/PiG_Calibration-FlatFoot-Full.c3d"
WALK = DATASETS / "btkdata/PiG_Motion-FlatFoot-Full.c3d"
PIPELINE = (
    '[[pipeline]]\nkind = "twist"\n'
    '[[pipeline]]\nkind = "one_euro"\nmin_cutoff_hz = 1.0\nbeta_rot = 2.0\n'
)


def _time(fn: Callable[[], object], repeats: int) -> np.ndarray:
    fn()  # warm-up (compilation, caches)
    out = np.empty(repeats)
    for k in range(repeats):
        t0 = time.perf_counter()
        fn()
        out[k] = time.perf_counter() - t0
    return out


def main() -> None:
    """Run the benchmark and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    rig = load_rig("plug-in-gait")
    static = load_take(STATIC)
    cal = calibrate(
        rig, static.positions, static.labels, take_measurements=static.measurements
    )
    take = load_take(WALK)
    rate = float(take.rate_hz)
    solver = BodySolver(rig, cal, take.labels)
    res = solver.solve_take(take.positions)
    clip = clip_from_solve(res, cal, rate)
    n = clip.n_frames
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        (d / "pipe.toml").write_text(PIPELINE)
        write_solve_bvh(d / "src.bvh", cal, res, rate)
        src_bvh = read_bvh_hierarchy(d / "src.bvh", read_motion=True)
        half = n // 2
        end = find_loop(clip, 10, n // 3)
        cut = type(clip)(
            parent_from_bone_quat=clip.parent_from_bone_quat[: end + 10],
            root_pos=clip.root_pos[: end + 10],
            rate_hz=rate,
        )
        steps: list[tuple[str, Callable[[], object]]] = [
            ("solve_take (baseline)", lambda: solver.solve_take(take.positions)),
            ("--pipeline twist+one_euro", lambda: apply_pipeline_to_solve(
                d / "pipe.toml", res, cal, rate)),
            ("--out take.csv (ZXY, deg)", lambda: write_euler_csv(
                d / "t.csv", res.bone_names, res.parent_from_bone_quat, res.root_pos,
                rate, order="ZXY", degrees=True)),
            ("--out take.glb (every frame)", lambda: write_clip_glb(
                d / "t.glb", clip, cal)),
            ("reduce 0.5 deg, 1 mm + .glb", lambda: write_reduced_glb(
                d / "r.glb", reduce_clip(clip), cal)),
            ("blend (20 frames) + .npz", lambda: write_clip(
                str(d / "b.npz"), blend(clip, clip, half - 20, 10, 20), cal)),
            ("loop (10-frame fade) + .npz", lambda: write_clip(
                str(d / "l.npz"), loop(cut, 10)[0], cal)),
            ("retarget BVH -> BVH (same skel.)", lambda: retarget_bvh(
                src_bvh, src_bvh)),
            ("retarget --plant-feet (same skel.)", lambda: plant_retarget(
                src_bvh, src_bvh, retarget_bvh(src_bvh, src_bvh),
                source_m_per_unit=0.01, target_m_per_unit=0.01)),
        ]  # fmt: skip
        rows = [(name, _time(fn, args.repeats)) for name, fn in steps]
    base = float(np.median(rows[0][1]))
    load = os.getloadavg()[0]
    print(
        f"Plug-in Gait walk: {n} frames at {rate:g} Hz, {len(res.bone_names)} bones; "
        f"{args.repeats} runs each; load average {load:.1f} on {os.cpu_count()} cores"
    )
    print(f"{'step':<34} {'median ms':>10} {'p99 ms':>9} {'us/frame':>9} {'ratio':>7}")
    for name, t in rows:
        med = float(np.median(t))
        print(
            f"{name:<34} {1e3 * med:>10.2f} {1e3 * np.percentile(t, 99):>9.2f} "
            f"{1e6 * med / n:>9.1f} {med / base:>7.2f}"
        )


if __name__ == "__main__":
    main()
