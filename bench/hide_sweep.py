"""Every marker hidden in turn, against the solve with nothing hidden (issue 28 item 6).

Per marker: the largest joint-centre distance (mm) and bone rotation (deg) from the
intact solve over the hidden window, and the new steps over 5 deg between frames that
the intact solve does not have (``synth.damage.damage_metrics``); a case is past when
a joint is over 20 mm, a bone over 10 deg or any new step. ``--take synthetic``: the
synthetic performer as ``bench/fit_truth.py`` makes it (10 s at 120 Hz, the default
motions, calibrated on its first second), hidden from ``--at-s``; ``--take walk``: the
btkdata Plug-in Gait walk (100 Hz), hidden from each row of ``--rows``. Prints one
line per case and the count past, with the load. For the hold and the virtual markers
(``body.fit_track``); ``python bench/hide_sweep.py --rig plug-in-gait --seconds 1``.
``--two-sided``: judge the offline solve (``body.fit_gaps``: forward and backward,
each hidden span filled from both sides; the intact solve too) instead of the causal
one, as ``retargetd solve`` gives it (``--causal`` there for the live daemon's).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import fit_truth as ft
from burst_recovery import add_datasets_option

from retargetd.daemon.body import fit_gaps
from retargetd.daemon.body.calibration import calibrate
from retargetd.daemon.body.method import make_body_solver
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.synth.damage import damage, damage_metrics
from retargetd.daemon.validate.limits import JOINT_LIMITS_DEG
from retargetd.daemon.validate.model import SEGMENT_KIND
from retargetd.replay.takes import load_take

REPO = Path(__file__).resolve().parents[1]
STATIC = "btkdata/PiG_Calibration-FlatFoot-Full.c3d"
WALK = "btkdata/PiG_Motion-FlatFoot-Full.c3d"
#: item 6's limits
JOINT_MM, BONE_DEG, STEP_DEG = 20.0, 10.0, 5.0


def _line(start: int, name: str, mt: Any) -> tuple[str, bool]:
    past = mt.max_joint_mm > JOINT_MM or mt.max_bone_deg > BONE_DEG or mt.new_steps > 0
    return (
        f"{start:5d} {name:10s} joint {mt.max_joint_mm:7.1f} ({mt.max_joint}) bone "
        f"{mt.max_bone_deg:6.1f} ({mt.max_bone}) steps {mt.new_steps:3d}"
        f"{' PAST' if past else ''}",
        past,
    )


def _solve(fit: Any, positions: np.ndarray, two_sided: bool) -> Any:
    """The take from a fresh state: causal, or filled from both sides."""
    fit.reset()
    if two_sided:
        return fit_gaps.solve_two_sided(fit, positions)
    return fit.solve_take(positions)


def synthetic(
    rig: str, seconds: float, at_s: float, only: set[str], two_sided: bool = False
) -> list[bool]:
    """The synthetic performer, each marker hidden ``seconds`` from ``at_s``."""
    s = ft.Settings(
        seconds=10.0, rate_hz=120.0, noise_mm=0.0, seed=0, calibrate_frames=120,
        recovery_tol_deg=2.0, recovery_tol_mm=10.0, unobserved="",
        damage_at_s=at_s,
    )  # fmt: skip
    take = ft._take(rig, "default", s)
    truth_rig, _ = ft._calibrated(rig, "default", s)
    fit = ft._solver(rig, "default", "fit", s)
    intact = _solve(fit, take.markers_world, two_sided)
    start = round(at_s * s.rate_hz)
    window = slice(start, start + round(seconds * s.rate_hz))
    out = []
    for m, name in enumerate(take.labels):
        if only and name not in only:
            continue
        pos = damage(take.markers_world, take.labels, "hide", window, marker=m)
        hidden = _solve(fit, pos, two_sided)
        mt = damage_metrics(intact, hidden, window, s.rate_hz, step_deg=STEP_DEG,
                            truth=take, rig=truth_rig)  # fmt: skip
        text, past = _line(start, name, mt)
        print(text, flush=True)
        out.append(past)
    return out


def walk(
    datasets: Path,
    seconds: float,
    rows: list[int],
    only: set[str],
    two_sided: bool = False,
) -> list[bool]:
    """The btkdata Plug-in Gait walk, each marker hidden ``seconds`` from each row."""
    static, take = load_take(datasets / STATIC), load_take(datasets / WALK)
    rig = load_rig("plug-in-gait")
    cal = calibrate(rig, static.positions, static.labels,
                    take_measurements=static.measurements)  # fmt: skip
    fit = make_body_solver(
        "fit", rig, cal, take.labels, joint_limits=JOINT_LIMITS_DEG,
        segment_kind=SEGMENT_KIND, rate_hz=take.rate_hz,
    )  # fmt: skip
    intact = _solve(fit, take.positions, two_sided)
    n = round(seconds * take.rate_hz)
    out = []
    for start in rows:
        window = slice(start, start + n)
        for m, name in enumerate(take.labels):
            if (only and name not in only) or not np.isfinite(
                take.positions[window, m]
            ).any():
                continue
            hidden = _solve(
                fit,
                damage(take.positions, take.labels, "hide", window, marker=m),
                two_sided,
            )
            mt = damage_metrics(intact, hidden, window, take.rate_hz,
                                step_deg=STEP_DEG)  # fmt: skip
            text, past = _line(start, name, mt)
            print(text, flush=True)
            out.append(past)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--take", choices=("synthetic", "walk"), default="synthetic")
    ap.add_argument("--rig", default="plug-in-gait", help="synthetic: the rig worn")
    ap.add_argument("--seconds", type=float, default=1.0, help="hidden this long")
    ap.add_argument("--at-s", type=float, default=4.0, help="synthetic: hidden from")
    ap.add_argument("--rows", default="30,150", help="walk: hidden from these rows")
    ap.add_argument("--markers", default="", help="only these (comma-separated)")
    ap.add_argument(
        "--two-sided",
        action="store_true",
        help="the offline solve filled from both sides (body.fit_gaps), not the "
        "causal one",
    )
    add_datasets_option(ap)
    args = ap.parse_args(argv)
    if args.seconds <= 0.0:
        print("error: --seconds must be positive", file=sys.stderr)
        return 2
    only = {m for m in args.markers.split(",") if m}
    if args.take == "walk":
        if not (args.datasets / WALK).is_file():
            print(f"error: {args.datasets / WALK} not found (../shared/datasets)",
                  file=sys.stderr)  # fmt: skip
            return 2
        try:
            rows = [int(r) for r in args.rows.split(",") if r]
        except ValueError:
            print(f"error: --rows {args.rows!r}: comma-separated row numbers",
                  file=sys.stderr)  # fmt: skip
            return 2
        past = walk(args.datasets, args.seconds, rows, only, args.two_sided)
    else:
        past = synthetic(args.rig, args.seconds, args.at_s, only, args.two_sided)
    print(f"past {sum(past)} of {len(past)}; load {os.getloadavg()[0]:.2f} (1 min)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
