"""``retargetd calibrate STATIC --rig RIG --out performer.json [--frames a:b]``.

The performer holds the base pose over the selected frames (0-based, half-open rows of
the take as loaded; default: the whole take). The result is a calibrated skeleton
(point offsets, bone lengths, rest orientations, measurements used with their source,
rig identity) loaded by ``retargetd solve --calibration`` and by the daemon.
"""

from __future__ import annotations

import argparse
import logging
import sys
from typing import Any

from retargetd.daemon.cli import UsageError

logger = logging.getLogger(__name__)


def add_rig_arguments(parser: argparse.ArgumentParser) -> None:
    """``--rig`` and ``--measure`` (shared by calibrate and solve)."""
    parser.add_argument(
        "--rig", required=True, metavar="RIG", help="shipped rig name or a rig file"
    )
    parser.add_argument(
        "--measure",
        action="append",
        default=[],
        metavar="NAME=MM",
        help="override a subject measurement in mm (repeatable)",
    )


def parse_measures(items: list[str]) -> dict[str, float]:
    """``["LKneeWidth=105", ...]`` -> {name: mm}. Raises UsageError naming the item."""
    out: dict[str, float] = {}
    for item in items:
        name, sep, value = item.partition("=")
        try:
            if not sep or not name:
                raise ValueError
            out[name.strip()] = float(value)
        except ValueError:
            raise UsageError(f"--measure: expected NAME=MM; got {item!r}") from None
    return out


def add_parser(subparsers: Any) -> None:
    """Register ``calibrate``."""
    parser = subparsers.add_parser(
        "calibrate",
        help="calibrate a rig on a base pose (static trial or frames of a take)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("static", metavar="STATIC", help="take holding the base pose")
    add_rig_arguments(parser)
    parser.add_argument("--out", required=True, metavar="FILE.json")
    parser.add_argument(
        "--frames", metavar="a:b", help="base-pose rows (0-based, half-open)"
    )
    from retargetd.daemon.cmd_take import add_take_arguments

    add_take_arguments(parser)
    parser.set_defaults(run=run)


def calibrate_from_take(
    take: Any, rig: Any, frames: slice, overrides: dict[str, float]
) -> Any:
    """Calibrate ``rig`` on ``take.positions[frames]``; errors become UsageError."""
    from retargetd.daemon.calibration import CalibrationError, calibrate

    try:
        return calibrate(
            rig,
            take.positions[frames],
            take.labels,
            take_measurements=take.measurements,
            overrides=overrides,
            base_pose={
                "take": str(take.path),
                "subject": take.subject,
                "frames": f"{frames.start}:{frames.stop}",
                "rate_hz": take.rate_hz,
            },
        )
    except CalibrationError as exc:
        raise UsageError(str(exc)) from None


def load_rig_or_fail(name: str) -> Any:
    """Load a rig; a bad rig is a UsageError (one line, exit 2)."""
    from retargetd.daemon.rig import RigError, load_rig

    try:
        return load_rig(name)
    except RigError as exc:
        raise UsageError(str(exc)) from None


def run(args: argparse.Namespace) -> int:
    """Run ``calibrate``."""
    from retargetd.daemon.framesel import parse_frames
    from retargetd.replay.takes import load_take

    rig = load_rig_or_fail(args.rig)
    overrides = parse_measures(args.measure)
    take = load_take(
        args.static, subject=args.subject, units=args.take_units, up_axis=args.take_up
    )
    frames = parse_frames(args.frames, take.n_frames, option="--frames")
    cal = calibrate_from_take(take, rig, frames, overrides)
    cal.save(args.out)
    out = sys.stdout.write
    out(f"wrote {args.out}: rig {rig.name}, base pose {take.path} rows ")
    out(f"{frames.start}:{frames.stop} ({frames.stop - frames.start} frames)\n")
    unseen = [
        m for m, s in zip(cal.marker_names, cal.markers_seen, strict=False) if s == 0.0
    ]
    if unseen:
        out(f"markers never seen in the base pose: {' '.join(unseen)}\n")
    defaults = [k for k, v in cal.measurements.items() if v.source == "default"]
    if cal.measurements:
        used = ", ".join(
            f"{k}={v.value_mm:g} ({v.source})" for k, v in cal.measurements.items()
        )
        out(f"measurements (mm): {used}\n")
    if defaults:
        out(
            "measurements missing from the take, rig defaults used: "
            f"{' '.join(defaults)}\n"
        )
    out("bone lengths (mm): ")
    out(
        ", ".join(
            f"{n} {1000 * length:.0f}"
            for n, length in zip(cal.bone_names, cal.bone_lengths, strict=False)
        )
        + "\n"
    )
    return 0


def add_solve_arguments(parser: argparse.ArgumentParser) -> None:
    """TAKE, ``--rig``/``--measure``, ``--calibration FILE | --calibrate-frames a:b``
    and the take options: what every command that solves a take accepts."""
    from retargetd.daemon.cmd_take import add_take_arguments

    parser.add_argument("take", metavar="TAKE", help="a .c3d, .trc or .mcap take")
    add_rig_arguments(parser)
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument("--calibration", metavar="FILE.json", help="calibrated skeleton")
    group.add_argument(
        "--calibrate-frames",
        metavar="a:b",
        help="calibrate on these rows of the take itself (0-based, half-open)",
    )
    add_take_arguments(parser)


def solver_for_take(args: argparse.Namespace) -> tuple[Any, Any, Any, Any]:
    """Load the rig and the take, load or make the calibration, build the solver.

    Returns:
        ``(rig, take, calibration, solver)``.

    Raises:
        UsageError: a bad rig, calibration or frame selection (one line, exit 2).
    """
    from retargetd.daemon.calibration import (
        CalibrationError,
        load_calibration,
    )
    from retargetd.daemon.framesel import parse_frames
    from retargetd.daemon.solve_body import BodySolver
    from retargetd.replay.takes import load_take

    rig = load_rig_or_fail(args.rig)
    take = load_take(
        args.take, subject=args.subject, units=args.take_units, up_axis=args.take_up
    )
    try:
        if args.calibration is not None:
            cal = load_calibration(args.calibration)
        else:
            frames = parse_frames(
                args.calibrate_frames, take.n_frames, option="--calibrate-frames"
            )
            cal = calibrate_from_take(take, rig, frames, parse_measures(args.measure))
        solver = BodySolver(rig, cal, take.labels)
    except CalibrationError as exc:
        raise UsageError(str(exc)) from None
    return rig, take, cal, solver
