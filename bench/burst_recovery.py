"""The soak's bursts of bad frames, offline: how long the body solve takes to come back.

``bench/soak.py`` finds, over 10 minutes of a live daemon, the bursts after which the
pose is not back within 0.25 s of the intact solve (issue 28 item 3, issue 30 item 6).
This replays the same source without the daemon, in seconds: the real Plug-in Gait walk
(``../shared/datasets/btkdata``) played forward then backward at 240 Hz
(``soak.walk_row``), with the soak's background occlusions (``soak.occlusion_mask``,
10 % of each marker's samples in runs of 20-250 ms), and every ``--every-s`` a burst of
1-50 bad frames of each kind in turn (``soak.BURSTS``: every seen marker on their mean,
all zeros, left and right labels swapped, every marker at 1e30, which the live decoder
occludes: NaN here). The take is solved twice by one solver kind (``--method``), with
and without the bursts; per burst, the recovery is the time from its last bad frame to
the first frame after it whose every bone is within ``soak.RECOVERED_DEG`` and root
within ``soak.RECOVERED_M`` of the solve without the bursts, that is neither held nor
unseen (the soak's own measure), and a burst is late past ``soak.MAX_RECOVERY_S``.

The same take is solved a third time with nothing hidden and no burst. Where the hides
leave a rotation that only a hidden marker saw, the solve without the bursts holds it
where it was when that marker hid (``fit_track.hold_priors``): its answer there depends
on the path, and the solve after a burst holds it where the burst left it. So a second
recovery is measured as well: the first frame after which every bone is within
``soak.RECOVERED_DEG`` of the solve without the bursts *or* no more than that further
from the solve with nothing hidden than the solve without the bursts is (the root
likewise), neither held nor unseen: the burst left nothing worse than the hides
already had. A burst late on this one is late whichever solve is right.

Prints per kind: bursts, late (both measures), median and max recovery; then each late
burst with the bone furthest off in the 0.25 s after it.
"""

from __future__ import annotations

import argparse
import math
import os
import random
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import soak

from retargetd.daemon.body.calibration import calibrate
from retargetd.daemon.body.method import make_body_solver
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.synth.damage import bone_deviation_deg
from retargetd.daemon.validate.limits import JOINT_LIMITS_DEG
from retargetd.daemon.validate.model import SEGMENT_KIND
from retargetd.replay.takes import load_take

REPO = Path(__file__).resolve().parents[1]
STATIC = "btkdata/PiG_Calibration-FlatFoot-Full.c3d"
WALK = "btkdata/PiG_Motion-FlatFoot-Full.c3d"


def _swap(labels: list[str]) -> np.ndarray:
    """The left/right label swap: each L* marker's column takes its R* twin's."""
    out = np.arange(len(labels))
    for i, name in enumerate(labels):
        if name[:1] in ("L", "R"):
            twin = ("R" if name[0] == "L" else "L") + name[1:]
            if twin in labels:
                out[i] = labels.index(twin)
    return out


def _bad(kind: str, row: np.ndarray, swap: np.ndarray) -> np.ndarray:
    """One bad frame of ``kind`` in place of ``row`` (soak.Source._bad_row; 1e30 and
    zeros as the live decoder passes them to the solver: not seen)."""
    if kind in ("zeros", "far"):
        return np.full_like(row, np.nan)
    if kind == "swapped":
        return row[swap]
    bad = row.copy()
    seen = np.isfinite(row).all(axis=1)
    if seen.any():
        bad[seen] = row[seen].mean(axis=0)
    return bad


def run(
    datasets: Path,
    *,
    bursts: int,
    seed: int,
    method: str,
    every_s: float,
    rate_hz: float,
    dropout: float,
    lengths: tuple[int, ...] = (),
) -> dict[str, Any]:
    """Solve the walk with and without the bursts; per burst its kind, length,
    recovery (s; inf: not back before the next burst) and the bone furthest off in
    the ``MAX_RECOVERY_S`` after it. ``lengths``: the bursts' lengths in turn
    (frames) instead of the soak's random 1-50."""
    static, walk = load_take(datasets / STATIC), load_take(datasets / WALK)
    rig = load_rig("plug-in-gait")
    cal = calibrate(rig, static.positions, static.labels,
                    take_measurements=static.measurements)  # fmt: skip
    every = round(every_s * rate_hz)
    n_frames = every * (bursts + 1)
    pos = walk.positions
    rows = np.fromiter(
        (soak.walk_row(k, pos.shape[0]) for k in range(n_frames)), dtype=np.int64
    )
    rng = np.random.default_rng(seed)
    clean = pos[rows].copy()
    clean[soak.occlusion_mask(rng, n_frames, pos.shape[1], dropout)] = np.nan
    damaged = clean.copy()
    swap = _swap(list(walk.labels))
    pick = random.Random(seed)
    spans = []
    for i in range(bursts):
        t0 = every * (i + 1) - every // 2
        n = lengths[i % len(lengths)] if lengths else pick.randint(1, 50)
        kind = soak.BURSTS[i % len(soak.BURSTS)]
        for f in range(t0, t0 + n):
            damaged[f] = _bad(kind, clean[f], swap)
        spans.append((kind, n, t0, t0 + n))

    def solve(markers: np.ndarray) -> Any:
        solver = make_body_solver(
            method, rig, cal, walk.labels,
            joint_limits=JOINT_LIMITS_DEG, segment_kind=SEGMENT_KIND, rate_hz=rate_hz,
        )  # fmt: skip
        return solver.solve_take(markers)

    t_start = time.perf_counter()
    intact, hit = solve(clean), solve(damaged)
    solve_s = time.perf_counter() - t_start
    seen_all = solve(pos[rows])

    def apart(a: Any, b: Any) -> tuple[np.ndarray, np.ndarray]:
        deg = bone_deviation_deg(
            np.asarray(a.world_from_bone_quat), np.asarray(b.world_from_bone_quat)
        )
        return deg, np.linalg.norm(np.asarray(a.root_pos) - np.asarray(b.root_pos),
                                   axis=1)  # fmt: skip

    deg, root = apart(hit, intact)
    deg_all, root_all = apart(hit, seen_all)
    deg_hides, root_hides = apart(intact, seen_all)
    held = np.zeros(n_frames, dtype=bool)
    for name in ("unexplained", "unseen"):
        flags = getattr(hit, name, None)
        if flags is not None:
            held |= np.asarray(flags, dtype=bool)
    back = (np.nanmax(deg, axis=1) <= soak.RECOVERED_DEG) & (
        root <= soak.RECOVERED_M
    ) & ~held  # fmt: skip
    worse_deg = np.nanmax(np.minimum(deg, deg_all - deg_hides), axis=1)
    worse_m = np.minimum(root, root_all - root_hides)
    no_worse = (worse_deg <= soak.RECOVERED_DEG) & (worse_m <= soak.RECOVERED_M) & ~held
    window = round(soak.MAX_RECOVERY_S * rate_hz)
    out = []
    for i, (kind, n, _t0, t1) in enumerate(spans):
        stop = spans[i + 1][2] if i + 1 < len(spans) else n_frames
        rec = []
        for ok in (back, no_worse):
            after = np.flatnonzero(ok[t1:stop])
            rec.append((after[0] + 1) / rate_hz if after.size else math.inf)
        seg = deg[t1 : min(t1 + window, stop)]
        b = int(np.nanargmax(np.nanmax(seg, axis=0)))
        out.append({"kind": kind, "frames": n, "recovery_s": rec[0],
                    "no_worse_s": rec[1], "bone": hit.bone_names[b],
                    "bone_deg": float(np.nanmax(seg[:, b])),
                    "bone_deg_all": float(np.nanmax(deg_all[t1 : t1 + len(seg), b])),
                    "bone_deg_hides": float(
                        np.nanmax(deg_hides[t1 : t1 + len(seg), b]))})  # fmt: skip
    return {"bursts": out, "frames": n_frames, "solve_s": solve_s}


def report(result: dict[str, Any]) -> list[str]:
    """The summary lines: per kind, then each late burst."""
    limit = soak.MAX_RECOVERY_S
    rows = result["bursts"]
    lines = [
        "| kind | bursts | late | median s | max s | left worse than the hides |",
        "|---|---|---|---|---|---|",
    ]
    for kind in soak.BURSTS:
        mine = [b for b in rows if b["kind"] == kind]
        if not mine:
            continue
        rec = [b["recovery_s"] for b in mine]
        late = sum(r > limit for r in rec)
        worse = sum(b["no_worse_s"] > limit for b in mine)
        lines.append(f"| {kind} | {len(rec)} | {late} | {np.median(rec):.3f} | "
                     f"{max(rec):.3f} | {worse} |")  # fmt: skip
    late = [b for b in rows if b["recovery_s"] > limit]
    worse = [b for b in rows if b["no_worse_s"] > limit]
    lines.append(f"late (over {limit:g} s): {len(late)} of {len(rows)}; left worse "
                 f"than the hides past {limit:g} s: {len(worse)}")  # fmt: skip
    lines += [
        f"  {b['kind']} {b['frames']} frames: {b['recovery_s']:.3f} s "
        f"(no worse after {b['no_worse_s']:.3f} s), {b['bone']} {b['bone_deg']:.1f} "
        f"deg off (from the solve with nothing hidden {b['bone_deg_all']:.1f}, the "
        f"solve without the bursts {b['bone_deg_hides']:.1f})"
        for b in late
    ]
    return lines


def add_datasets_option(ap: argparse.ArgumentParser) -> None:
    """``--datasets``: the shared datasets folder (``$RETARGETD_SHARED/datasets``, else
    ``../shared/datasets`` beside the repository)."""
    ap.add_argument(
        "--datasets", type=Path,
        default=Path(os.environ.get("RETARGETD_SHARED", REPO.parent / "shared"))
        / "datasets",
    )  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bursts", type=int, default=40)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--method", choices=("fit", "construction"), default="fit")
    ap.add_argument("--every-s", type=float, default=2.5)
    ap.add_argument("--rate-hz", type=float, default=soak.RATE_HZ)
    ap.add_argument("--dropout", type=float, default=0.10)
    add_datasets_option(ap)
    args = ap.parse_args(argv)
    if args.bursts < 1:
        print("error: --bursts must be at least 1", file=sys.stderr)
        return 2
    if not (args.datasets / WALK).is_file():
        print(f"error: {args.datasets / WALK} not found (../shared/datasets)",
              file=sys.stderr)  # fmt: skip
        return 2
    result = run(
        args.datasets, bursts=args.bursts, seed=args.seed, method=args.method,
        every_s=args.every_s, rate_hz=args.rate_hz, dropout=args.dropout,
    )  # fmt: skip
    print(
        f"{args.method}: {result['frames']} frames at {args.rate_hz:g} Hz, "
        f"{args.bursts} bursts, seed {args.seed}; both solves "
        f"{result['solve_s']:.1f} s; "
        f"load {os.getloadavg()[0]:.2f} (1 min)"
    )
    print("\n".join(report(result)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
