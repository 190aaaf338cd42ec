"""``retargetd export-c3d TAKE --out FILE.c3d [--frames a:b] [--units mm|m] [--up AXIS]
[--out-subject NAME] [--with-references]``: write a take's markers to C3D.

Any take ``load_take`` reads (C3D, TRC) is loaded as usual (``--subject``,
``--take-units``, ``--take-up``) and its markers written with
:func:`retargetd.replay.c3d.write_c3d`: in ``--units`` (default mm) and a capture
frame with ``--up`` up (default +Z, the internal world's axes), occluded samples as
residual -1, the rate, the first frame number (shifted by ``--frames``) and the
subject measurements (``PROCESSING``) kept. Labels carry the take's subject as a
``Name:`` prefix (with a ``SUBJECTS`` group) unless ``--out-subject`` names another
one, or ``--out-subject ""`` writes them unprefixed.

Vendor references (Plug-in Gait joint centres, angles, forces ...) are not exported:
only markers are. ``--with-references`` adds the position references (joint centres,
segment and model points) as plain points after the markers; angles, forces, moments
and powers are never written.
"""

from __future__ import annotations

import argparse
import logging
import sys
from typing import Any

import numpy as np

from retargetd.daemon.cli.args import add_force_argument, take_overrides
from retargetd.daemon.errors import UsageError

logger = logging.getLogger(__name__)


def add_parser(subparsers: Any) -> None:
    """Register ``export-c3d``."""
    from retargetd.daemon.cli.args import add_take_arguments

    parser = subparsers.add_parser(
        "export-c3d",
        help="write a take's markers (C3D, TRC ...) to a C3D file",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("take", metavar="TAKE", help="a .c3d or .trc take")
    parser.add_argument(
        "--out", required=True, metavar="FILE.c3d", help="the C3D file to write"
    )
    add_force_argument(parser)
    parser.add_argument(
        "--frames", metavar="a:b", help="rows to write (0-based, half-open; all)"
    )
    parser.add_argument(
        "--units", default="mm", choices=("mm", "m"), help="file length unit (mm)"
    )
    parser.add_argument(
        "--up", default="+Z", metavar="AXIS", help="file up axis: +Z, +Y or +X (+Z)"
    )
    parser.add_argument(
        "--out-subject",
        metavar="NAME",
        help='label prefix to write (default: the take\'s subject; "" for none)',
    )
    parser.add_argument(
        "--with-references",
        action="store_true",
        help="also write the take's position references as points",
    )
    add_take_arguments(parser)
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Run ``export-c3d``."""
    from retargetd.daemon.cli.args import parse_frames, refuse_existing
    from retargetd.replay.c3d import write_c3d
    from retargetd.replay.take import POSITION_KINDS
    from retargetd.replay.takes import load_take

    if not args.out.lower().endswith(".c3d"):
        raise UsageError(f"--out: expected a .c3d file; got {args.out!r}")
    refuse_existing(args.out, force=args.force)
    take = load_take(args.take, **take_overrides(args))
    rows = parse_frames(args.frames, take.n_frames, option="--frames")
    labels = list(take.labels)
    positions = take.positions[rows]
    refs = take.references
    kept = [
        i
        for i, kind in enumerate(refs.kinds)
        if args.with_references and kind in POSITION_KINDS
    ]
    clash = sorted(set(labels) & {refs.labels[i] for i in kept})
    if clash:
        raise UsageError(
            f"--with-references: references named like markers: {', '.join(clash)}"
        )
    if kept:
        labels += [refs.labels[i] for i in kept]
        positions = np.concatenate([positions, refs.values[rows][:, kept]], axis=1)
    subject = take.subject if args.out_subject is None else args.out_subject
    try:
        write_c3d(
            args.out, labels, positions, take.rate_hz,
            units=args.units, up_axis=args.up,
            first_frame=take.first_frame + rows.start,
            measurements=take.measurements, subject=subject or None,
        )  # fmt: skip
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    out = sys.stdout.write
    n_markers = take.n_markers
    out(
        f"wrote {args.out}: {positions.shape[0]} frames at {take.rate_hz:g} Hz, "
        f"{n_markers} markers"
        + (f" + {len(kept)} reference points" if kept else "")
        + f", {args.units}, up {args.up}"
        + (f", subject {subject}" if subject else "")
        + "\n"
    )
    skipped = len(refs.labels) - len(kept)
    if skipped:
        why = (
            "angles, forces ... are never written"
            if args.with_references
            else "add --with-references for the position ones"
        )
        out(f"not exported: {skipped} vendor references ({why})\n")
    return 0
