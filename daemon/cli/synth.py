"""``retargetd synth``: write a take of the synthetic performer (C3D or TRC).

``retargetd synth --seconds S --rate HZ --out FILE [--markers NAME|PATH]
[--motions walk,arm_raise,...] [--noise-mm X] [--dropout F] [--seed N]
[--base-pose-s X] [--height-m X] [--truth TRUTH.npz] [--units mm|m]``

The format follows the suffix of ``--out``: ``.c3d`` is written +Z up (the C3D lab
convention), ``.trc`` +Y up (what TRC readers assume). ``--truth`` also writes the
ground truth (joint centres and rotations, each foot's contact and support per frame)
as an NPZ readable with ``allow_pickle=False``
(:func:`retargetd.daemon.synth.performer.load_truth`). A short
summary goes to stdout.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np

from retargetd.daemon.errors import UsageError

#: Accepted frame rates, Hz.
MIN_RATE_HZ = 1.0
MAX_RATE_HZ = 10000.0
#: Longest take, seconds (memory: ~50 MB per minute at 1 kHz for 40 markers).
MAX_SECONDS = 3600.0
#: Joints whose range of motion the summary lists.
SUMMARY_JOINTS = (
    *("abdomen", "thorax", "neck", "head", "l_upper_arm", "r_upper_arm"),
    *(
        "l_forearm",
        "r_forearm",
        "l_hand",
        "r_hand",
        "l_thigh",
        "r_thigh",
        "l_shank",
        "r_shank",
    ),
    *("l_foot", "r_foot"),
)
_UP_AXIS = {".c3d": "+Z", ".trc": "+Y"}


def add_parser(subparsers: Any) -> None:
    """Register ``synth`` on the top-level subparsers."""
    from retargetd.daemon.synth.performer import (
        ALL_MOTIONS,
        DEFAULT_MOTIONS,
        DEFAULT_ORIGIN,
    )

    parser = subparsers.add_parser(
        "synth",
        help="write a take of the synthetic performer (C3D/TRC) and its truth",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--seconds", type=float, required=True, metavar="S", help="duration, seconds"
    )
    parser.add_argument(
        "--rate",
        type=float,
        required=True,
        metavar="HZ",
        help=f"frame rate, Hz ({MIN_RATE_HZ:g}-{MAX_RATE_HZ:g})",
    )
    parser.add_argument(
        "--out", required=True, metavar="FILE", help="output take, .c3d or .trc"
    )
    parser.add_argument(
        "--markers",
        default="menache",
        metavar="NAME|PATH",
        help="shipped marker set (menache, plug-in-gait) or a .toml "
        "file (default: menache)",
    )
    parser.add_argument(
        "--motions",
        default=",".join(DEFAULT_MOTIONS),
        metavar="LIST",
        help=f"comma-separated, from {','.join(ALL_MOTIONS)} "
        "(default: the everyday ones, "
        f"{','.join(DEFAULT_MOTIONS)}; 'none' for a static T-pose)",
    )
    parser.add_argument(
        "--noise-mm",
        type=float,
        default=0.0,
        metavar="X",
        help="Gaussian noise std per coordinate, mm (default 0)",
    )
    parser.add_argument(
        "--dropout",
        type=float,
        default=0.0,
        metavar="F",
        help="fraction of samples occluded, in runs, [0, 1) (default 0)",
    )
    parser.add_argument(
        "--seed", type=int, default=0, metavar="N", help="random seed (default 0)"
    )
    parser.add_argument(
        "--base-pose-s",
        type=float,
        default=1.0,
        metavar="X",
        help="static T-pose hold at the start, seconds (default 1)",
    )
    parser.add_argument(
        "--height-m",
        type=float,
        default=1.75,
        metavar="X",
        help="performer height, metres (default 1.75)",
    )
    parser.add_argument(
        "--truth", metavar="TRUTH.npz", help="also write the ground truth as NPZ"
    )
    parser.add_argument(
        "--units",
        choices=("mm", "m"),
        default="mm",
        help="length unit of the file (default mm)",
    )
    parser.add_argument(
        "--props",
        metavar="LIST",
        default="",
        help="also carry props (comma-separated: camera, sword; synth/props.py): "
        "their markers (camera1..5, sword1..4) in the take, their truth in "
        "TRUTH.props.npz with --truth",
    )
    parser.set_defaults(run=run, origin=DEFAULT_ORIGIN)


def _validate(args: argparse.Namespace) -> tuple[str, tuple[str, ...]]:
    """Check arguments; returns the output suffix and the motion list."""
    from retargetd.daemon.synth.performer import ALL_MOTIONS

    if not (np.isfinite(args.seconds) and 0.0 < args.seconds <= MAX_SECONDS):
        raise UsageError(
            f"--seconds must be in (0, {MAX_SECONDS:g}]; got {args.seconds:g}"
        )
    if not (np.isfinite(args.rate) and MIN_RATE_HZ <= args.rate <= MAX_RATE_HZ):
        raise UsageError(
            f"--rate must be in [{MIN_RATE_HZ:g}, {MAX_RATE_HZ:g}] Hz; "
            f"got {args.rate:g}"
        )
    if not (np.isfinite(args.dropout) and 0.0 <= args.dropout < 1.0):
        raise UsageError(f"--dropout must be in [0, 1); got {args.dropout:g}")
    if not (np.isfinite(args.noise_mm) and args.noise_mm >= 0.0):
        raise UsageError(f"--noise-mm must be >= 0; got {args.noise_mm:g}")
    if not (np.isfinite(args.base_pose_s) and args.base_pose_s >= 0.0):
        raise UsageError(f"--base-pose-s must be >= 0; got {args.base_pose_s:g}")
    if not (np.isfinite(args.height_m) and 0.5 <= args.height_m <= 2.5):
        raise UsageError(f"--height-m must be in [0.5, 2.5]; got {args.height_m:g}")
    suffix = Path(args.out).suffix.lower()
    if suffix not in _UP_AXIS:
        raise UsageError(f"--out must end in .c3d or .trc; got {args.out!r}")
    text = args.motions.strip()
    motions = (
        ()
        if text.lower() in ("", "none")
        else tuple(m.strip() for m in text.split(",") if m.strip())
    )
    unknown = [m for m in motions if m not in ALL_MOTIONS]
    if unknown:
        raise UsageError(
            f"--motions: unknown {', '.join(unknown)}; "
            f"choose from {','.join(ALL_MOTIONS)}"
        )
    return suffix, tuple(dict.fromkeys(motions))


def run(args: argparse.Namespace) -> int:
    """Synthesize, write the take (and truth), print the summary; returns 0."""
    from retargetd.daemon.synth.performer import synthesize
    from retargetd.replay.c3d import write_c3d
    from retargetd.replay.trc import write_trc

    suffix, motions = _validate(args)
    try:
        take = synthesize(
            seconds=args.seconds,
            rate_hz=args.rate,
            markerset=args.markers,
            motions=motions,
            noise_mm=args.noise_mm,
            dropout=args.dropout,
            seed=args.seed,
            base_pose_s=args.base_pose_s,
            height_m=args.height_m,
            origin=args.origin,
        )
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    labels, markers = list(take.labels), take.markers_world
    props = _props(args, take)  # --props: carried by the performer's hands
    for p in props:
        # unprefixed labels (camera1 ...): a C3D whose labels carry "Name:" prefixes
        # reads the unprefixed ones as no subject's, and the performer's are those
        labels += [label.replace(":", "") for label in p.labels]
        markers = np.concatenate([markers, p.markers_world], axis=1)
    writer = write_c3d if suffix == ".c3d" else write_trc
    writer(
        args.out,
        labels,
        markers,
        take.rate_hz,
        units=args.units,
        up_axis=_UP_AXIS[suffix],
    )
    if args.truth:
        take.save_truth(args.truth)
        if props:
            truth = Path(args.truth)
            arrays: dict[str, Any] = {}
            for p in props:
                arrays[f"{p.name}_world_from_prop_quat"] = p.world_from_prop_quat
                arrays[f"{p.name}_pos_world"] = p.prop_pos_world
                arrays[f"{p.name}_layout_prop_m"] = p.layout_prop_m
            np.savez(truth.with_name(truth.stem + ".props.npz"), **arrays)
    sys.stdout.write(summary(take, args.out, args.truth, _UP_AXIS[suffix], args.units))
    return 0


def _props(args: argparse.Namespace, take: Any) -> tuple[Any, ...]:
    """``--props``: the synthetic props of the take (UsageError on a bad name)."""
    names = tuple(n.strip() for n in args.props.split(",") if n.strip())
    if not names:
        return ()
    from retargetd.daemon.synth.props import synth_props

    try:
        return synth_props(
            take, names, noise_mm=args.noise_mm, seed=args.seed,
            base_pose_s=args.base_pose_s,
        )  # fmt: skip
    except ValueError as exc:
        raise UsageError(f"--props: {exc}") from None


def summary(take: Any, out: str, truth: str | None, up_axis: str, units: str) -> str:
    """Human summary of a synthesized take (a few lines, ends with a newline).

    Args:
        take: the :class:`~retargetd.daemon.synth.performer.SynthTake`.
        out: the take file written.
        truth: the truth NPZ written, or None.
        up_axis: the file's up axis.
        units: the file's length unit.

    Returns:
        The text.
    """
    from retargetd.daemon import rotations as rot

    hold = take.base_pose_frames
    pelvis_xy = take.joint_pos_world[:, 0, :2]
    path_m = float(np.linalg.norm(np.diff(pelvis_xy, axis=0), axis=1).sum())
    lines = [
        f"wrote {out} ({up_axis} up, {units})"
        + (f" and truth {truth}" if truth else ""),
        f"frames {take.n_frames} at {take.rate_hz:g} Hz "
        f"= {take.n_frames / take.rate_hz:g} s",
        f"markers {len(take.labels)} ({take.markerset}), segments "
        f"{len(take.segment_names)}, height {take.height_m:g} m",
        f"motions {','.join(take.motions) or 'none'}; noise {take.noise_mm:g} mm; "
        f"seed {take.seed}",
        f"occluded {100.0 * take.occluded_fraction:.2f} % of samples "
        f"(requested {100.0 * take.dropout:g} %)",
        f"base pose frames {hold.start}:{hold.stop} (static T-pose)",
        f"pelvis path {path_m:.2f} m",
        "range of motion from the T-pose, deg (max angle):",
    ]
    cells = []
    for name in SUMMARY_JOINTS:
        q = take.parent_from_segment_quat[:, take.segment_names.index(name)]
        cells.append(f"{name} {np.rad2deg(rot.quat_angle(q).max()):.0f}")
    for i in range(0, len(cells), 5):
        lines.append("  " + ", ".join(cells[i : i + 5]))
    return "\n".join(lines) + "\n"
