"""``retargetd calibrate STATIC --rig RIG --out performer.json [--frames a:b]
[--rom TAKE [--rom-frames a:b]] [--refine-layout TAKE [--refine-frames a:b]]``;
``retargetd calibrate STATIC --prop NAME [--config FILE | --markers A,B,C | --prefix
P] [--kind rigid|camera] [--pivot-mm X,Y,Z] --out NAME.json [--frames a:b]``.

``--prop NAME`` calibrates a prop instead (``cli/prop_io.py``): the layout of its
markers in its own frame (README "Props and a virtual camera").

The performer holds the base pose over the selected frames (0-based, half-open rows of
the take as loaded; default: the whole take). The result is a calibrated skeleton
(point offsets, bone lengths, rest orientations, measurements used with their source,
rig identity) loaded by ``retargetd solve --calibration`` and by the daemon.

``--rom TAKE`` places the rig's functional joints (its ``[functional]`` table: hip
centres, knee axes) from a range of motion (``--rom-frames``, default the whole take;
it may be the take itself): each is recorded with its residual and predicted error, and
one the motion does not determine keeps the base pose's estimate, said in one line.
``--refine-layout TAKE`` then re-places each marker on its bone from that take's
frames (``--refine-frames``, default the whole take): a wand re-seated or a marker
re-stuck since the static sits where the take says, the joint model is kept
(``body.refine``); the file records per marker how far it moved.
The summary also gives the calibration pose's own hip, knee and ankle angles from
anatomical neutral (``body.neutral``): the joint ranges the fit and ``validate`` use
are taken from neutral, not from the calibration pose.
``--json`` prints the summary as one JSON object (README "Machine-readable output").
"""

from __future__ import annotations

import argparse
import logging
import sys
from typing import Any

from retargetd.daemon.cli.args import (
    add_rig_arguments,
    calibrate_from_take,
    load_rig_or_fail,
    parse_measures,
    take_overrides,
)
from retargetd.daemon.cli.prop_io import add_prop_arguments, calibrate_prop_command
from retargetd.daemon.errors import UsageError

logger = logging.getLogger(__name__)


def add_parser(subparsers: Any) -> None:
    """Register ``calibrate``."""
    parser = subparsers.add_parser(
        "calibrate",
        help="calibrate a rig on a base pose (static trial or frames of a take)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("static", metavar="STATIC", help="take holding the base pose")
    add_rig_arguments(
        parser,
        required=False,
        rig_help="shipped rig name or a rig file (required unless --prop)",
    )
    add_prop_arguments(parser)
    parser.add_argument(
        "--out", required=True, metavar="FILE.json", help="the calibration to write"
    )
    parser.add_argument(
        "--frames", metavar="a:b", help="base-pose rows (0-based, half-open)"
    )
    parser.add_argument(
        "--rom",
        metavar="TAKE",
        help="a range-of-motion take for the rig's functional joints (hip centres, "
        "knee axes; RIGS.md 'Functional joints')",
    )
    parser.add_argument(
        "--rom-frames", metavar="a:b", help="range-of-motion rows (0-based, half-open)"
    )
    parser.add_argument(
        "--refine-layout",
        metavar="TAKE",
        help="re-place each marker on its bone from this take's frames (markers "
        "re-seated since the static; the joint model kept)",
    )
    parser.add_argument(
        "--refine-frames",
        metavar="a:b",
        help="--refine-layout's rows (0-based, half-open)",
    )
    from retargetd.daemon.cli.args import add_take_arguments

    add_take_arguments(parser)
    parser.add_argument(
        "--json",
        action="store_true",
        help="print the summary as one JSON object (README: stable keys)",
    )
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Run ``calibrate``."""
    from retargetd.daemon.cli.args import parse_frames
    from retargetd.replay.takes import load_take

    if args.prop is not None:
        return calibrate_prop_command(args)
    if args.rig is None:
        raise UsageError("--rig is required (or --prop NAME for a prop)")
    rig = load_rig_or_fail(args.rig)
    overrides = parse_measures(args.measure)
    take = load_take(args.static, **take_overrides(args))
    frames = parse_frames(args.frames, take.n_frames, option="--frames")
    rom = None
    if args.rom_frames is not None and args.rom is None:
        raise UsageError("--rom-frames needs --rom TAKE")
    if args.rom is not None:
        if not rig.functional:
            raise UsageError(
                f"rig {rig.name} has no functional joints ([functional] in RIGS.md): "
                "--rom has nothing to place"
            )
        rom_take = load_take(args.rom, **take_overrides(args))
        rows = parse_frames(args.rom_frames, rom_take.n_frames, option="--rom-frames")
        rom = (
            rom_take.positions[rows],
            rom_take.labels,
            {"take": str(rom_take.path), "frames": f"{rows.start}:{rows.stop}"},
        )
    if args.refine_frames is not None and args.refine_layout is None:
        raise UsageError("--refine-frames needs --refine-layout TAKE")
    cal = calibrate_from_take(
        take, rig, frames, overrides, allow_moving=args.allow_moving_base_pose, rom=rom
    )
    if args.refine_layout is not None:
        from retargetd.daemon.cli.args import refine_from_take

        refine_take = load_take(args.refine_layout, **take_overrides(args))
        rows = parse_frames(
            args.refine_frames, refine_take.n_frames, option="--refine-frames"
        )
        cal = refine_from_take(rig, cal, refine_take, rows).calibration
    cal.save(args.out)
    if args.json:
        _print_json(args, rig, take, frames, cal)
        return 0
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
    for name, j in cal.functional.get("joints", {}).items():
        out(f"functional {name}: {_functional_line(j)}\n")
    from_neutral = _pose_from_neutral(rig, cal)
    if from_neutral:
        out(
            "calibration pose from anatomical neutral (sagittal / frontal deg; the "
            "joint ranges are taken from neutral): "
            + ", ".join(
                f"{b} {s:+.1f} / {f:+.1f}" for b, (s, f) in from_neutral.items()
            )
            + "\n"
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


def _functional_line(j: dict[str, Any]) -> str:
    """One functional joint's estimate, its quality and whether it is used."""
    used = "used" if j["used"] else "not used (the motion does not determine it)"
    if j["kind"] == "centre":
        return (
            f"centre {j['moved_mm']:.1f} mm from the base pose's, residual "
            f"{j['rms_mm']:.1f} mm, predicted error {_or_dash(j['se_mm'])} mm, "
            f"{j['frames']} frames: {used}"
        )
    rig = j.get("angle_from_rig_deg")
    turned = f"{rig:.1f} deg from the rig's, " if rig is not None else ""
    return (
        f"axis {turned}turned {j['arc_deg']:.0f} deg, residual {j['rms_mm']:.1f} mm, "
        f"predicted error {_or_dash(j['se_deg'])} deg, {j['frames']} frames: {used}"
    )


def _pose_from_neutral(rig: Any, cal: Any) -> dict[str, tuple[float, float]]:
    """Each bone's calibration pose from anatomical neutral (``body.neutral``), in
    the validator's sagittal / frontal split."""
    from retargetd.daemon.body.neutral import pose_from_neutral_deg
    from retargetd.daemon.validate.model import SEGMENT_KIND

    return pose_from_neutral_deg(rig, cal, SEGMENT_KIND)


def _or_dash(x: float | None) -> str:
    return "-" if x is None else f"{x:.2f}"


def _print_json(
    args: argparse.Namespace, rig: Any, take: Any, frames: slice, cal: Any
) -> None:
    from retargetd.daemon.cli.args import print_json

    print_json(
        {
            "command": "calibrate",
            "out": args.out,
            "rig": rig.name,
            "take": str(take.path),
            "frames": [frames.start, frames.stop],
            "markers_unseen": [
                m
                for m, s in zip(cal.marker_names, cal.markers_seen, strict=False)
                if s == 0.0
            ],
            "measurements_mm": {
                k: {"value": v.value_mm, "source": v.source}
                for k, v in cal.measurements.items()
            },
            "bone_lengths_m": {
                n: float(length)
                for n, length in zip(cal.bone_names, cal.bone_lengths, strict=False)
            },
            "functional": cal.functional.get("joints", {}),
            "layout_refined": cal.layout_refined or None,
            "pose_from_neutral_deg": {
                b: {"sagittal": sag, "frontal": fro}
                for b, (sag, fro) in _pose_from_neutral(rig, cal).items()
            },
        }
    )
