"""``retargetd blend A B --rig RIG (--calibration FILE | --calibrate-frames a:b)
--at a:b --frames N --out OUT.glb|OUT.bvh|OUT.npz [--no-align-root]
[--pipeline FILE.toml] [--bvh-order ORDER] [--plant-feet]``: cross-fade take A into
take B.

Both takes are solved with the same rig and calibration (``--calibrate-frames``
calibrates on rows of A). ``--at a:b`` names the fade's first frame in each take
(0-based rows as loaded): the result is A's frames before ``a``, then N frames that
slerp from ``A[a + k]`` to ``B[b + k]`` with weights ``(k + 1) / (N + 1)``, then B's
frames from ``b + N`` on (:func:`retargetd.daemon.post.interp.blend`). Pick frames
alike in pose and timing (the chapter's advice). Unless ``--no-align-root``, B is
first turned about world +Z and moved on the floor so its root at ``b`` has A's
heading and horizontal position at ``a``.

Output by suffix: ``.glb`` (every frame; glTF 2.0 binary), ``.bvh`` (the calibrated
skeleton, ``--bvh-order`` channels), ``.npz`` (``bone_names``, ``bone_parents``,
``parent_from_bone_quat``, ``world_from_bone_quat``, ``root_pos``, ``rate_hz``).
Prints the largest pose change across the fade beside the takes' own
frame-to-frame motion.

``--plant-feet`` (``.npz`` only): the blended motion also mapped onto the target
skeleton (``--pipeline``'s ``[target]``, else the default humanoid) with its stance
feet planted, as ``solve --plant-feet`` (README "Feet that plant"): the ``target_*``
arrays beside the clip's, the stance detected on the blended motion.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

import numpy as np

from retargetd.daemon.errors import UsageError


def add_parser(subparsers: Any) -> None:
    """Register ``blend``."""
    from retargetd.daemon.cli.args import add_solve_arguments
    from retargetd.daemon.cli.post_io import (
        add_glb_mesh_argument,
        add_pipeline_argument,
        add_plant_feet_argument,
    )

    parser = subparsers.add_parser(
        "blend",
        help="cross-fade one take into another over N frames (glTF, BVH or NPZ)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_solve_arguments(parser)
    parser.add_argument("take_b", metavar="B", help="the take faded into")
    parser.add_argument(
        "--at", required=True, metavar="a:b", help="fade start: frame a of A, b of B"
    )
    parser.add_argument(
        "--frames", required=True, type=int, metavar="N", help="fade length, frames"
    )
    parser.add_argument(
        "--no-align-root",
        action="store_true",
        help="keep B's root where it is (default: turn and move it onto A's)",
    )
    add_pipeline_argument(parser)
    parser.add_argument("--bvh-order", metavar="ORDER", help="BVH: channel order")
    parser.add_argument(
        "--out", required=True, metavar="OUT.glb|OUT.bvh|OUT.npz",
        help="the blended take; the suffix picks the format",
    )  # fmt: skip
    add_glb_mesh_argument(parser)
    add_plant_feet_argument(parser)
    parser.set_defaults(run=run)


def _parse_at(text: str) -> tuple[int, int]:
    a, sep, b = text.partition(":")
    try:
        if not sep:
            raise ValueError
        return int(a), int(b)
    except ValueError:
        raise UsageError(
            f"--at: expected a:b (two frame numbers); got {text!r}"
        ) from None


def run(args: argparse.Namespace) -> int:
    """Run ``blend``."""
    from retargetd.daemon.cli.post_io import (
        CLIP_SUFFIXES,
        check_bvh_order,
        clip_of,
        clip_plant_config,
        glb_mesh_of,
        humanoid_names,
        plant_clip,
        pose_steps_deg,
        solve_other_take,
        solved_take,
        suffix_of,
        write_clip,
    )
    from retargetd.daemon.post.interp import blend

    suffix = suffix_of(args.out, CLIP_SUFFIXES)
    glb_mesh = glb_mesh_of(args, suffix)
    if args.bvh_order is not None:
        if suffix != "bvh":
            raise UsageError(
                f"--bvh-order applies to .bvh output; --out is {args.out!r}"
            )
        check_bvh_order("--bvh-order", args.bvh_order)
    at_a, at_b = _parse_at(args.at)
    if args.frames < 1:
        raise UsageError(f"--frames: expected >= 1; got {args.frames}")
    plant_cfg = clip_plant_config(args, suffix)
    rig, take_a, cal, res_a = solved_take(args)
    take_b, res_b = solve_other_take(args, args.take_b, rig, cal)
    if take_a.rate_hz != take_b.rate_hz:
        raise UsageError(
            f"A is {take_a.rate_hz:g} Hz, B {take_b.rate_hz:g} Hz: blend needs one rate"
        )
    a = clip_of(res_a, cal, take_a.rate_hz, args.take)
    b = clip_of(res_b, cal, take_b.rate_hz, args.take_b)
    try:
        out_clip = blend(
            a, b, at_a, at_b, args.frames, align_root=not args.no_align_root
        )
    except ValueError as exc:
        raise UsageError(f"--at/--frames: {exc}") from None
    planted = None if plant_cfg is None else plant_clip(out_clip, rig, cal, plant_cfg)
    write_clip(
        args.out, out_clip, cal, bvh_order=args.bvh_order,
        humanoid=humanoid_names(rig), glb_mesh=glb_mesh, extra=planted,
    )  # fmt: skip
    steps = pose_steps_deg(out_clip.parent_from_bone_quat)
    fade = steps[max(at_a - 1, 0) : at_a + args.frames]
    own = max(
        float(pose_steps_deg(a.parent_from_bone_quat).max()),
        float(pose_steps_deg(b.parent_from_bone_quat).max()),
    )
    w = sys.stdout.write
    w(
        f"wrote {args.out}: {out_clip.n_frames} frames at {a.rate_hz:g} Hz "
        f"(A 0..{at_a - 1}, fade {args.frames} frames, B {at_b + args.frames}..)\n"
    )
    w(
        f"largest pose change across the fade: {float(np.max(fade)):.3f} deg per "
        f"frame (the takes' own: up to {own:.3f} deg per frame)\n"
    )
    return 0
