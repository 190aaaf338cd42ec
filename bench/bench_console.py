"""Console benchmark: what publishing to the console costs a loop-like thread.

Run from the repository root::

    python bench/bench_console.py [--seconds S] [--rate HZ] [--no-browser]

A loop-like thread runs ``BodySolver.solve_frame`` (rig ``menache`` on the synthetic
performer) at ``--rate`` Hz and, every frame the slot says is due (30 Hz), fills the
slot's back buffer and commits it. Three cases, each ``--seconds`` long, in one run:

``baseline``
    solve only, no console (the reference).
``publish``
    solve + publish, no console thread reading.
``console+browser``
    solve + publish with the console running and a headless Chromium showing the page
    (skipped with ``--no-browser`` or when Chromium is absent).

For each it prints the per-frame wall time of solve (+ publish) in microseconds
(median, p99; ``time.perf_counter_ns`` around the frame's work), the publish call
alone (median, p99), commits skipped, and the ratio of the frame medians and p99s to
the baseline's. Speed is printed, never asserted (STYLE.md section 10).
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from typing import Any

import numpy as np

from retargetd.daemon.body.calibration import calibrate
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.body.solve import BodySolver
from retargetd.daemon.console import (
    ConsoleLayout,
    SkeletonProgram,
    SnapshotSlot,
)
from retargetd.daemon.synth.performer import synthesize


def _browser(url: str) -> Any:
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = shutil.which("chromium") or "/usr/bin/chromium"
    for flag in (
        "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
        "--no-first-run", "--disable-background-networking",
        "--disable-component-update", "--disable-sync", "--enable-unsafe-swiftshader",
        f"--user-data-dir={tempfile.mkdtemp(prefix='retargetd-bench-')}",
    ):  # fmt: skip
        opts.add_argument(flag)
    drv = shutil.which("chromedriver") or "/usr/bin/chromedriver"
    d = webdriver.Chrome(options=opts, service=Service(drv))
    d.get(url)
    return d


def _run_case(
    solver: BodySolver,
    markers: np.ndarray,
    slot: SnapshotSlot | None,
    seconds: float,
    rate_hz: float,
) -> tuple[np.ndarray, np.ndarray]:
    pose = solver.new_pose()
    frame_ns: list[int] = []
    pub_ns: list[int] = []
    period = 1.0 / rate_hz
    n = markers.shape[0]
    t_next = time.perf_counter()
    t_end = t_next + seconds
    i = 0
    while True:
        now = time.perf_counter()
        if now >= t_end:
            break
        if now < t_next:
            time.sleep(t_next - now)
        t_next += period
        t0 = time.perf_counter_ns()
        solver.solve_frame(markers[i % n], pose)
        if slot is not None and slot.due():
            p0 = time.perf_counter_ns()
            s = slot.begin()
            s.frame = i
            s.t_s = i / rate_hz
            np.copyto(s.marker_pos, markers[i % n])
            np.isfinite(markers[i % n, :, 0], out=s.marker_valid)
            np.copyto(s.joint_pos, pose.joint_centres)
            np.copyto(s.world_from_bone_quat, pose.world_from_bone_quat)
            np.copyto(s.root_pos, pose.root_pos)
            np.copyto(s.bone_flags, pose.bone_flags)
            s.input_rate_hz = rate_hz
            slot.commit()
            pub_ns.append(time.perf_counter_ns() - p0)
        frame_ns.append(time.perf_counter_ns() - t0)
        i += 1
    return np.asarray(frame_ns[50:]), np.asarray(pub_ns[5:])


def _back_to_back(slot: SnapshotSlot, markers: np.ndarray, pose: Any) -> np.ndarray:
    """Publish alone, 20,000 calls back to back (warm caches): ns per call."""
    out = np.empty(20_000, np.int64)
    for i in range(out.size):
        t0 = time.perf_counter_ns()
        s = slot.begin()
        s.frame = i
        np.copyto(s.marker_pos, markers[i % markers.shape[0]])
        np.isfinite(markers[i % markers.shape[0], :, 0], out=s.marker_valid)
        np.copyto(s.joint_pos, pose.joint_centres)
        np.copyto(s.world_from_bone_quat, pose.world_from_bone_quat)
        np.copyto(s.root_pos, pose.root_pos)
        np.copyto(s.bone_flags, pose.bone_flags)
        slot.commit()
        out[i] = time.perf_counter_ns() - t0
    return out[100:]


def main() -> int:
    """Run the benchmark."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--rate", type=float, default=240.0)
    ap.add_argument("--no-browser", action="store_true")
    args = ap.parse_args()

    take = synthesize(seconds=4.0, rate_hz=args.rate, dropout=0.05, seed=1)
    rig = load_rig("menache")
    cal = calibrate(rig, take.markers_world[: int(args.rate)], take.labels)
    solver = BodySolver(rig, cal, take.labels)
    res = solver.solve_take(take.markers_world[:10])  # compile
    layout = ConsoleLayout(
        marker_names=take.labels,
        joint_names=res.joint_names,
        bone_names=res.bone_names,
        bone_parents=np.asarray(res.bone_parents, np.int64),
        skeleton=SkeletonProgram.from_rig(rig, res.joint_names),
        bone_lengths=np.asarray(res.bone_lengths),
    )
    print(f"load: {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f} (1, 5 min)")
    print(f"{args.rate:g} Hz loop, {args.seconds:g} s per case, menache, synthetic")
    cases: list[tuple[str, np.ndarray, np.ndarray, int]] = []
    f, p = _run_case(solver, take.markers_world, None, args.seconds, args.rate)
    cases.append(("baseline", f, p, 0))
    slot = SnapshotSlot(layout)
    f, p = _run_case(solver, take.markers_world, slot, args.seconds, args.rate)
    cases.append(("publish", f, p, slot.skipped))
    have_browser = shutil.which("chromium") or os.path.exists("/usr/bin/chromium")
    if not args.no_browser and have_browser:
        from retargetd.daemon.console.app import Console

        slot = SnapshotSlot(layout)
        console = Console(slot, None, port=0)
        console.start()
        driver = _browser(console.url)
        try:
            time.sleep(3.0)  # page loaded, scene drawing
            f, p = _run_case(solver, take.markers_world, slot, args.seconds, args.rate)
            cases.append(("console+browser", f, p, slot.skipped))
            print(f"console drew {console.frames_drawn} snapshots")
        finally:
            driver.quit()
            console.stop()
    else:
        print("console+browser: skipped (--no-browser or no chromium)")
    pose = solver.new_pose()
    solver.solve_frame(take.markers_world[0], pose)
    bb = _back_to_back(SnapshotSlot(layout), take.markers_world, pose) / 1e3
    print(
        f"publish back to back (warm): median {np.median(bb):.1f} us, "
        f"p99 {np.percentile(bb, 99):.1f} us"
    )
    base_med = float(np.median(cases[0][1])) / 1e3
    base_p99 = float(np.percentile(cases[0][1], 99)) / 1e3
    print(
        f"{'case':<16} {'frame med us':>12} {'frame p99 us':>12} "
        f"{'publish med':>11} {'publish p99':>11} {'skipped':>7} "
        f"{'x med':>6} {'x p99':>6}"
    )
    for name, fr, pu, skipped in cases:
        med, p99 = float(np.median(fr)) / 1e3, float(np.percentile(fr, 99)) / 1e3
        pm = float(np.median(pu)) / 1e3 if len(pu) else float("nan")
        pp = float(np.percentile(pu, 99)) / 1e3 if len(pu) else float("nan")
        print(
            f"{name:<16} {med:12.1f} {p99:12.1f} {pm:11.1f} {pp:11.1f} "
            f"{skipped:7d} {med / base_med:6.2f} {p99 / base_p99:6.2f}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
