"""``retargetd loop TAKE --rig RIG (--calibration FILE | --calibrate-frames a:b)
--frames N [--range a:b] [--find-cycle-s S] --out OUT.glb|OUT.bvh|OUT.npz
[--pipeline FILE.toml] [--bvh-order ORDER] [--plant-feet]``: a seamless loop of a
cyclic take.

The take is solved; ``--range a:b`` (0-based rows, half-open) keeps the cyclic part
(leave out a calibration hold, say). With ``--find-cycle-s S`` the cycle's end is
searched (:func:`retargetd.daemon.post.interp.find_loop`: the end, at least S seconds
in, whose following N frames best match the first N) and the range is cut there plus
N frames. Then the last N frames are cross-faded into the first N
(:func:`retargetd.daemon.post.interp.loop`): the loop has N fewer frames than its
input, its last frame runs into its first. The tail's root is moved on the floor by
the cycle's travel, so the fade does not slide; printed, and stored in the NPZ as
``travel_m`` (an engine playing the loop with root motion adds ``-travel`` each time
round).

Output by suffix: ``.glb`` (glTF 2.0 binary, every frame), ``.bvh``, ``.npz`` (as
``retargetd blend``). Prints the pose change at the seam (last frame -> first) beside
the take's own frame-to-frame motion.

``--plant-feet`` (``.npz`` only): the loop also mapped onto the target skeleton
(``--pipeline``'s ``[target]``, else the default humanoid) with its stance feet
planted, as ``solve --plant-feet``: the ``target_*`` arrays beside the clip's (one
pass over the loop's frames: the plant does not wrap round the seam).
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from retargetd.daemon.errors import UsageError


def add_parser(subparsers: Any) -> None:
    """Register ``loop``."""
    from retargetd.daemon.cli.args import add_solve_arguments
    from retargetd.daemon.cli.post_io import (
        add_glb_mesh_argument,
        add_pipeline_argument,
        add_plant_feet_argument,
    )

    parser = subparsers.add_parser(
        "loop",
        help="make a seamless loop of a cyclic take (glTF, BVH or NPZ)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_solve_arguments(parser)
    parser.add_argument(
        "--frames", required=True, type=int, metavar="N", help="fade length, frames"
    )
    parser.add_argument(
        "--range", metavar="a:b", help="rows of the take to loop (0-based, half-open)"
    )
    parser.add_argument(
        "--find-cycle-s",
        type=float,
        metavar="S",
        help="search the cycle's end, at least S seconds into the range",
    )
    add_pipeline_argument(parser)
    parser.add_argument("--bvh-order", metavar="ORDER", help="BVH: channel order")
    parser.add_argument(
        "--out", required=True, metavar="OUT.glb|OUT.bvh|OUT.npz",
        help="the loop; the suffix picks the format",
    )  # fmt: skip
    add_glb_mesh_argument(parser)
    add_plant_feet_argument(parser)
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Run ``loop``."""
    import numpy as np

    from retargetd.daemon.cli.args import parse_frames
    from retargetd.daemon.cli.post_io import (
        CLIP_SUFFIXES,
        check_bvh_order,
        clip_of,
        clip_plant_config,
        glb_mesh_of,
        humanoid_names,
        plant_clip,
        pose_steps_deg,
        solved_take,
        suffix_of,
        write_clip,
    )
    from retargetd.daemon.post.interp import Clip, find_loop, loop, pose_distance

    suffix = suffix_of(args.out, CLIP_SUFFIXES)
    glb_mesh = glb_mesh_of(args, suffix)
    if args.bvh_order is not None:
        if suffix != "bvh":
            raise UsageError(
                f"--bvh-order applies to .bvh output; --out is {args.out!r}"
            )
        check_bvh_order("--bvh-order", args.bvh_order)
    if args.frames < 1:
        raise UsageError(f"--frames: expected >= 1; got {args.frames}")
    plant_cfg = clip_plant_config(args, suffix)
    rig, take, cal, res = solved_take(args)
    full = clip_of(res, cal, take.rate_hz, args.take)
    sel = parse_frames(args.range, full.n_frames, option="--range")
    clip = Clip(
        parent_from_bone_quat=full.parent_from_bone_quat[sel],
        root_pos=full.root_pos[sel],
        rate_hz=full.rate_hz,
    )
    if args.find_cycle_s is not None:
        try:
            end = find_loop(clip, args.frames, round(args.find_cycle_s * clip.rate_hz))
        except ValueError as exc:
            raise UsageError(f"--find-cycle-s: {exc}") from None
        clip = Clip(
            parent_from_bone_quat=clip.parent_from_bone_quat[: end + args.frames],
            root_pos=clip.root_pos[: end + args.frames],
            rate_hz=clip.rate_hz,
        )
    try:
        looped, travel = loop(clip, args.frames)
    except ValueError as exc:
        raise UsageError(f"--frames: {exc}") from None
    planted = None if plant_cfg is None else plant_clip(looped, rig, cal, plant_cfg)
    write_clip(
        args.out, looped, cal, bvh_order=args.bvh_order, travel_m=travel,
        humanoid=humanoid_names(rig), glb_mesh=glb_mesh, extra=planted,
    )  # fmt: skip
    q = looped.parent_from_bone_quat
    seam = float(np.degrees(pose_distance(q[-1], q[0])))
    own = pose_steps_deg(clip.parent_from_bone_quat)
    unit = float(np.abs(np.linalg.norm(q, axis=-1) - 1.0).max())
    w = sys.stdout.write
    w(
        f"wrote {args.out}: a loop of {looped.n_frames} frames at {clip.rate_hz:g} Hz "
        f"(rows {sel.start}..{sel.start + clip.n_frames - 1} of the take, fade "
        f"{args.frames} frames)\n"
    )
    w(
        f"seam (last frame -> first): {seam:.3f} deg; the take's own frame-to-frame "
        f"motion: median {float(np.median(own)):.3f}, max {float(own.max()):.3f} deg\n"
    )
    w(
        f"root travel per cycle: {travel[0]:.4f} {travel[1]:.4f} {travel[2]:.4f} m "
        f"(x y z); largest |quat| - 1: {unit:.1e}\n"
    )
    return 0
