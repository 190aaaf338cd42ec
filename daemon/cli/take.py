"""``retargetd take``: inspect take files (C3D, TRC).

``retargetd take info TAKE [--subject NAME] [--take-units U] [--take-up AXIS]
[--take-rate HZ] [--json]`` loads the take exactly as the daemon would and prints
what was found: format, the reader that read it and what it had to repair,
manufacturer, subjects, markers, rate and length, gaps, the units, up axis and rate
with where each came from, the rotation applied, vendor references and measurements
(with their units where the name says them).
``--json`` prints the same as one JSON object. ``take`` holds nested actions so that
more (``take convert`` ...) can join ``info``.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from typing import Any

import numpy as np

from retargetd.daemon.cli.args import add_take_arguments, take_overrides
from retargetd.protocols.frames import BoolArray
from retargetd.replay.take import Take

logger = logging.getLogger(__name__)

#: How many of the gappiest markers ``take info`` lists.
WORST_MARKERS = 5


def add_parser(subparsers: Any) -> None:
    """Register ``take`` and its actions on the top-level subparsers."""
    parser = subparsers.add_parser(
        "take", help="inspect take files (C3D, TRC, MCAP)", description=__doc__
    )
    parser.set_defaults(run=run)
    actions = parser.add_subparsers(dest="take_action", metavar="ACTION", required=True)
    info = actions.add_parser(
        "info", help="show what a take holds and how it will be converted"
    )
    info.add_argument("take", metavar="TAKE", help="a .c3d, .trc or .mcap file")
    add_take_arguments(info)
    info.add_argument("--json", action="store_true", help="print one JSON object")
    info.set_defaults(take_run=_run_info)


#: Units of Vicon Plug-in Gait ``PROCESSING`` values, by name without the L/R side.
#: Lengths are millimetres and Bodymass kilograms as Nexus writes them; the angles
#: are radians (PiG_Motion-FlatFoot-Full.c3d: HeadOffset = 0.354, i.e. 20 deg, and
#: LStaticPlantFlex = 0.116, i.e. 6.6 deg; as degrees they would be implausibly
#: small offsets).
PROCESSING_UNITS = {
    "Bodymass": "kg",
    "Height": "mm",
    "InterAsisDistance": "mm",
    "LegLength": "mm",
    "AsisTrocanterDistance": "mm",
    "KneeWidth": "mm",
    "AnkleWidth": "mm",
    "SoleDelta": "mm",
    "ShoulderOffset": "mm",
    "ElbowWidth": "mm",
    "WristWidth": "mm",
    "HandThickness": "mm",
    "PelvisLength": "mm",
    "PelvisOffset": "mm",
    "TibialTorsion": "rad",
    "ThighRotation": "rad",
    "ShankRotation": "rad",
    "StaticPlantFlex": "rad",
    "StaticRotOff": "rad",
    "AnkleAbAdd": "rad",
    "HeadOffset": "rad",
}


def measurement_unit(name: str) -> str:
    """Unit of a ``PROCESSING`` value by its name (Plug-in Gait), or "" if unknown."""
    for key in (name, name[1:] if name[:1] in "LR" else name):
        for prefix in ("Left", "Right"):
            key = key.removeprefix(prefix)
        if key in PROCESSING_UNITS:
            return PROCESSING_UNITS[key]
    return ""


def run(args: argparse.Namespace) -> int:
    """Run the selected ``take`` action; returns the exit code."""
    return int(args.take_run(args))


def longest_gaps(valid: BoolArray) -> np.ndarray:
    """Longest run of occluded frames per marker.

    Args:
        valid: (T, M) bool, True where the marker was seen.

    Returns:
        (M,) int64, frames.
    """
    n_frames, n_markers = valid.shape
    out = np.zeros(n_markers, dtype=np.int64)
    # Pad with seen frames, then gap runs lie between a seen->occluded edge and the
    # next occluded->seen edge.
    padded = np.ones((n_frames + 2, n_markers), dtype=np.int8)
    padded[1:-1] = valid
    edges = np.diff(padded, axis=0)
    for m in range(n_markers):
        starts = np.flatnonzero(edges[:, m] == -1)
        ends = np.flatnonzero(edges[:, m] == 1)
        if starts.size:
            out[m] = int((ends - starts).max())
    return out


def take_summary(take: Take) -> dict[str, Any]:
    """Everything ``take info`` reports, as a JSON-ready dict."""
    gap_per_marker = (
        1.0 - take.valid.mean(axis=0) if take.n_frames else np.zeros(take.n_markers)
    )
    longest = longest_gaps(take.valid)
    order = np.argsort(-gap_per_marker, kind="stable")
    worst = [
        {
            "label": take.labels[i],
            "gap_fraction": float(gap_per_marker[i]),
            "longest_gap_frames": int(longest[i]),
        }
        for i in order[:WORST_MARKERS]
        if gap_per_marker[i] > 0
    ]
    by_kind: dict[str, list[str]] = {}
    for label, kind in zip(take.references.labels, take.references.kinds, strict=True):
        by_kind.setdefault(kind, []).append(label)
    return {
        "file": take.path,
        "format": take.format,
        "reader": take.reader,
        "repairs": list(take.repairs),
        "manufacturer": take.manufacturer,
        "subjects": list(take.subjects),
        "subject": take.subject,
        "markers": {"count": take.n_markers, "labels": list(take.labels)},
        "unassigned_labels": list(take.unassigned_labels),
        "rate_hz": take.rate_hz,
        "rate_source": take.rate_source,
        "frames": take.n_frames,
        "duration_s": take.duration_s,
        "first_frame": take.first_frame,
        "gaps": {
            "fraction": take.gap_fraction,
            "markers_with_gaps": int((gap_per_marker > 0).sum()),
            "longest_gap_frames": int(longest.max()) if longest.size else 0,
            "worst": worst,
        },
        "units": take.units,
        "units_source": take.units_source,
        "up_axis": take.up_axis,
        "up_source": take.up_source,
        "world_from_capture": take.world_from_capture.tolist(),
        "references": {
            "count": len(take.references.labels),
            "by_kind": by_kind,
        },
        "measurements": dict(take.measurements),
        "measurement_units": {
            name: measurement_unit(name) for name in take.measurements
        },
    }


def _format_text(info: dict[str, Any]) -> str:
    gaps = info["gaps"]
    subjects = ", ".join(
        f"{s} (selected)" if s == info["subject"] else s for s in info["subjects"]
    )
    mat = "  ".join(
        "[" + " ".join(f"{v:+.0f}" for v in row) + "]"
        for row in info["world_from_capture"]
    )
    lines = [
        f"file:          {info['file']}",
        f"format:        {info['format']}",
        f"reader:        {info['reader'] or '(not recorded)'}",
        f"repairs:       {len(info['repairs']) or '(none)'}",
        *(f"  {repair}" for repair in info["repairs"]),
        f"manufacturer:  {info['manufacturer'] or '(not recorded)'}",
        f"subjects:      {subjects or '(none)'}",
        f"markers:       {info['markers']['count']}: "
        + " ".join(info["markers"]["labels"]),
    ]
    if info["unassigned_labels"]:
        lines.append(
            "unassigned:    " + " ".join(info["unassigned_labels"]) + " (left out)"
        )
    lines += [
        f"rate:          {info['rate_hz']:g} Hz"
        + (f" ({info['rate_source']})" if info["rate_source"] else ""),
        f"frames:        {info['frames']} (first frame {info['first_frame']})",
        f"duration:      {info['duration_s']:.3f} s",
        f"gaps:          {100 * gaps['fraction']:.2f} % of samples; "
        f"{gaps['markers_with_gaps']} markers with gaps; "
        f"longest gap {gaps['longest_gap_frames']} frames",
    ]
    for w in gaps["worst"]:
        lines.append(
            f"               {w['label']}: {100 * w['gap_fraction']:.1f} %, "
            f"longest {w['longest_gap_frames']} frames"
        )
    lines += [
        f"units:         {info['units']} ({info['units_source']})",
        f"up axis:       {info['up_axis']} ({info['up_source']})",
        f"world_from_capture: {mat}",
        f"references:    {info['references']['count']}",
    ]
    for kind, labels in info["references"]["by_kind"].items():
        lines.append(f"  {kind} ({len(labels)}): " + " ".join(labels))
    measurements = info["measurements"]
    lines.append(f"measurements:  {len(measurements) or '(none)'}")
    units = info["measurement_units"]
    lines += [
        f"  {name} = {value:g} {units.get(name) or '(unit not known)'}"
        for name, value in measurements.items()
    ]
    return "\n".join(lines) + "\n"


def _run_info(args: argparse.Namespace) -> int:
    # Heavy imports (ezc3d) only when the command runs.
    from retargetd.replay.takes import load_take

    take = load_take(args.take, **take_overrides(args))
    info = take_summary(take)
    if args.json:
        sys.stdout.write(json.dumps(info) + "\n")
    else:
        sys.stdout.write(_format_text(info))
    return 0
