"""``retargetd reduce TAKE --rig RIG (--calibration FILE | --calibrate-frames a:b)
[--tolerance-deg 0.5] [--tolerance-mm 1] [--pipeline FILE.toml] --out take.glb``:
keyframe reduction, not downsampling (the chapter's last section).

The take is solved (and run through ``--pipeline`` when given); then per channel (each
bone's true parent-relative rotation, the root's position) the keys inside smooth
stretches are dropped between boundary keys while the curve played back between the
kept keys (slerp for rotations, a straight line for the root: glTF's LINEAR) stays
within the tolerance of every frame, and the kept keys are refitted by least squares
when that still holds (:mod:`retargetd.daemon.post.reduce`). The frame rate stays.

Written as glTF 2.0 binary: the calibrated skeleton as a skin (joint nodes named by
the humanoid map where the rig has one, inverse bind matrices at the calibration
pose; ``--glb-mesh capsules`` adds a capsule per bone), one animation on the joints
holding only the kept keys, rotation channels and the root's translation, LINEAR.
Prints the keys kept per channel and the worst error.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from retargetd.daemon.errors import UsageError


def add_parser(subparsers: Any) -> None:
    """Register ``reduce``."""
    from retargetd.daemon.cli.args import add_solve_arguments
    from retargetd.daemon.cli.post_io import (
        add_glb_mesh_argument,
        add_pipeline_argument,
    )
    from retargetd.daemon.post.reduce import (
        DEFAULT_TOLERANCE_DEG,
        DEFAULT_TOLERANCE_MM,
    )

    parser = subparsers.add_parser(
        "reduce",
        help="solve a take and keep only the keys needed within a tolerance (glTF)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_solve_arguments(parser)
    parser.add_argument(
        "--tolerance-deg",
        type=float,
        default=DEFAULT_TOLERANCE_DEG,
        metavar="DEG",
        help=f"largest rotation error of any frame (default {DEFAULT_TOLERANCE_DEG})",
    )
    parser.add_argument(
        "--tolerance-mm",
        type=float,
        default=DEFAULT_TOLERANCE_MM,
        metavar="MM",
        help=f"largest root position error (default {DEFAULT_TOLERANCE_MM})",
    )
    add_pipeline_argument(parser)
    parser.add_argument(
        "--out", required=True, metavar="OUT.glb", help="the reduced take (glTF binary)"
    )
    add_glb_mesh_argument(parser)
    from retargetd.daemon.cli.args import add_output_arguments

    add_output_arguments(parser, json=False)
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Run ``reduce``."""
    from retargetd.daemon.body.calibration import CalibrationError
    from retargetd.daemon.cli.post_io import (
        clip_of,
        glb_mesh_of,
        humanoid_names,
        solved_take,
        suffix_of,
    )
    from retargetd.daemon.post.export_gltf import write_reduced_glb
    from retargetd.daemon.post.reduce import describe, reduce_clip
    from retargetd.daemon.progress import Progress

    glb_mesh = glb_mesh_of(args, suffix_of(args.out, ("glb",)))
    for option, value in (
        ("--tolerance-deg", args.tolerance_deg),
        ("--tolerance-mm", args.tolerance_mm),
    ):
        if not value > 0.0 or value == float("inf"):
            raise UsageError(f"{option}: expected a positive number; got {value!r}")
    rig, take, cal, res = solved_take(args)
    clip = clip_of(res, cal, take.rate_hz, args.take)
    if clip.n_frames < 2:
        raise UsageError(f"{args.take}: needs at least 2 frames to reduce")
    with Progress(2, "reduce: fit keys", unit="steps", enabled=not args.quiet) as bar:
        reduced = reduce_clip(
            clip, tolerance_deg=args.tolerance_deg, tolerance_mm=args.tolerance_mm
        )
        bar.update()
        bar.set_description("reduce: write")
        try:
            write_reduced_glb(
                args.out, reduced, cal, humanoid=humanoid_names(rig), mesh=glb_mesh
            )
        except CalibrationError as exc:
            raise UsageError(str(exc)) from None
        bar.update()
    if args.quiet:
        return 0
    out = sys.stdout.write
    out(
        f"wrote {args.out}: {clip.n_frames} frames at {take.rate_hz:g} Hz, rig "
        f"{rig.name}, tolerance {args.tolerance_deg:g} deg, {args.tolerance_mm:g} mm\n"
    )
    out(describe(reduced, res.bone_names) + "\n")
    return 0
