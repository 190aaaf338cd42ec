"""``retargetd retarget IN.bvh --target TARGET.bvh --out OUT.bvh|OUT.glb
[--map FILE.toml] [--root-scale X] [--spread [equal|pivot|hermite]]
[--pivot-limit-deg 15] [--units cm] [--source-units U] [--plant-feet]``: map a BVH
take onto another skeleton (rotational data in, the chapter's first section).

Joints are matched by ``--map`` first (a ``[joints]`` table, ``"source joint" =
"target joint"``), then by equal names (ignoring a ``prefix:``), then through the
humanoid bone maps (Mixamo/MotionBuilder and CMU BVH names, the shipped rigs' bone
names). The rest-pose offsets are compensated (``R'_j = conj(C_parent) R_j C_j``,
the chapter's "negative of the offset"), so every mapped bone points in the world
where its source bone points whatever the two rest poses; each joint's rotation order
is read from the source's channels and written in the target's. The root's position
is scaled by the ratio of the rest root heights (``--root-scale`` overrides). Both
files are taken to share axes (+Y up, as BVH usually is). Target joints that map to
nothing keep their rest; with ``--spread`` those on a plain chain between two mapped
joints (a target with more spine bones) share the rotation between them equally, or
with ``--spread pivot`` by the chapter's shifting pivot (rx and rz doubled, at most
``--pivot-limit-deg`` a joint, the rest carried up the chain, ry shared equally; the
chain's lower mapped end takes the last share). ``--spread hermite`` places the
whole spine, from the joint mapped to Hips to the one mapped to Neck (else Head),
along the chapter's Hermite curve (5.60-5.61) through the source's spine joints: K
target joints at equal arc length, each bone aimed along the curve, the twist shared
equally (other chains spread equally). See ``retargetd.daemon.retarget.bvh_retarget``,
``retargetd.daemon.post.pivot`` and ``retargetd.daemon.post.hermite``.

``.glb``: the target's joints as a glTF skin (named as in the target BVH; inverse
bind matrices at its rest pose; ``--units``: the BVH length unit, default cm, for
glTF's metres), every frame as a LINEAR key on the joints; ``--glb-mesh capsules``
adds a capsule per joint-to-child segment.

``--plant-feet``: the stance feet held where they landed on the target (README "Feet
that plant"). The source's stance comes from its foot and toe joints (the stance
detector of ``solve``, its thresholds unchanged, the source's rest pose taken as
standing on the floor and the floor as the lowest its heels come over the take); the
root's height and travel are scaled by the target's leg length over the source's (the
UpperLeg joints' height over the lowest foot point at rest); each stance foot is held
by two-bone IK on the target's UpperLeg, LowerLeg and Foot joints (those the joint map
drives from the source's legs, else named so), blended in and out. Both files' lengths
in ``--units`` (``--source-units`` for the source's when it differs): the thresholds
are metric. BVH and glTF hold no per-frame flags, so a line ``planted feet: ...``
gives the leg ratio, the floor, the contact frames and the frames flagged
``plant_unreached`` (a foot its leg could not reach; their runs, 0-based, half-open). A
file without identifiable legs is refused (exit 2); ``--root-scale`` is refused with
it (the plant sets the root's scale).
"""

from __future__ import annotations

import argparse
import math
import sys
from typing import Any

from retargetd.daemon.errors import UsageError

#: Metres per BVH length unit accepted by ``--units``.
M_PER_UNIT = {"mm": 0.001, "cm": 0.01, "m": 1.0, "in": 0.0254}


def add_parser(subparsers: Any) -> None:
    """Register ``retarget``."""
    parser = subparsers.add_parser(
        "retarget",
        help="map a BVH take onto another BVH skeleton (BVH or glTF out)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("source", metavar="IN.bvh", help="the BVH take")
    parser.add_argument(
        "--target", required=True, metavar="TARGET.bvh", help="the skeleton to drive"
    )
    parser.add_argument(
        "--out", required=True, metavar="OUT.bvh|OUT.glb",
        help="the retargeted take; the suffix picks the format",
    )  # fmt: skip
    from retargetd.daemon.cli.post_io import add_glb_mesh_argument

    add_glb_mesh_argument(parser)
    parser.add_argument(
        "--map", metavar="FILE.toml", help='[joints] "source joint" = "target joint"'
    )
    parser.add_argument(
        "--root-scale",
        type=float,
        metavar="X",
        help="factor on the root position (default: rest root height ratio)",
    )
    parser.add_argument(
        "--spread",
        nargs="?",
        const="equal",
        choices=("equal", "pivot", "hermite"),
        help="unmapped joints on a chain between two mapped ones (extra spine "
        "bones) share the rotation between them: equally (--spread, --spread "
        "equal) or by the shifting pivot (--spread pivot); or the whole spine "
        "along a Hermite curve through the source's (--spread hermite); default: "
        "they keep rest",
    )
    parser.add_argument(
        "--pivot-limit-deg",
        type=float,
        default=15.0,
        metavar="DEG",
        help="--spread pivot: the most rotation a joint takes about x and z "
        "(default 15, the chapter's)",
    )
    parser.add_argument(
        "--units",
        default="cm",
        choices=sorted(M_PER_UNIT),
        help="the BVH length unit (the target's; the source's too unless "
        "--source-units), for .glb metres and --plant-feet (default cm)",
    )
    parser.add_argument(
        "--source-units",
        choices=sorted(M_PER_UNIT),
        help="--plant-feet: the source BVH's length unit when it is not --units'",
    )
    from retargetd.daemon.cli.post_io import add_plant_feet_argument

    add_plant_feet_argument(
        parser,
        "hold the stance feet where they landed on the target: stance detected on "
        "the source's foot and toe joints, the root's height and travel scaled by "
        "the target's leg length over the source's, two-bone IK on the target's "
        "legs; prints the frames flagged plant_unreached (a foot that could not "
        "reach its hold)",
    )
    parser.set_defaults(run=run)


def _load_map(path: str) -> dict[str, str]:
    from retargetd.daemon.files import FileFormatError, loads_toml, read_text

    try:
        data = loads_toml(read_text(path, "name map"))
    except FileFormatError as exc:
        raise UsageError(f"--map {path}: {exc}") from None
    joints = data.get("joints")
    if not isinstance(joints, dict) or not all(
        isinstance(v, str) for v in joints.values()
    ):
        raise UsageError(
            f'--map {path}: expected a [joints] table of "source" = "target" names'
        )
    return dict(joints)


def run(args: argparse.Namespace) -> int:
    """Run ``retarget``."""
    from retargetd.daemon.cli.post_io import glb_mesh_of, suffix_of
    from retargetd.daemon.retarget.bvh_retarget import (
        SpineCurve,
        retarget_bvh,
        spread_chains,
        write_retarget_glb,
    )
    from retargetd.replay.bvh import read_bvh_hierarchy, write_bvh

    suffix = suffix_of(args.out, ("bvh", "glb"))
    glb_mesh = glb_mesh_of(args, suffix)
    name_map = _load_map(args.map) if args.map is not None else None
    if args.root_scale is not None and not args.root_scale > 0.0:
        raise UsageError(f"--root-scale: expected > 0; got {args.root_scale}")
    limit = args.pivot_limit_deg
    if not (math.isfinite(limit) and 0.0 < limit <= 180.0):
        raise UsageError(f"--pivot-limit-deg: expected (0, 180]; got {limit}")
    if args.source_units is not None and not args.plant_feet:
        raise UsageError("--source-units applies to --plant-feet")
    if args.plant_feet and args.root_scale is not None:
        raise UsageError(
            "--root-scale and --plant-feet: the plant scales the root by the leg "
            "length ratio"
        )
    distribute = None
    if args.spread == "pivot":
        from retargetd.daemon.post.pivot import pivot_chains

        def distribute(glob: Any, chains: Any) -> None:
            pivot_chains(glob, chains, limit)

    spine_curve: SpineCurve | None = None
    if args.spread == "hermite":
        from retargetd.daemon.post.hermite import hermite_chain

        spine_curve = hermite_chain
    try:
        source = read_bvh_hierarchy(args.source, read_motion=True)
        target = read_bvh_hierarchy(args.target)
        result = retarget_bvh(
            source,
            target,
            name_map=name_map,
            root_scale=args.root_scale,
            spread=args.spread is not None,
            distribute=distribute,
            spine_curve=spine_curve,
        )
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    planted = None
    if args.plant_feet:
        from retargetd.daemon.cli.retarget_plant import plant_retarget

        planted = plant_retarget(
            source, target, result,
            source_m_per_unit=M_PER_UNIT[args.source_units or args.units],
            target_m_per_unit=M_PER_UNIT[args.units],
        )  # fmt: skip
        result = planted.result
    if suffix == "bvh":
        write_bvh(args.out, result.skeleton, result.frames, result.frame_time_s)
    else:
        write_retarget_glb(args.out, result, M_PER_UNIT[args.units], mesh=glb_mesh)
    w = sys.stdout.write
    mapped = [
        f"{target.joint_names[j]}<-{source.joint_names[s]}"
        for j, s in enumerate(result.mapping)
        if s >= 0
    ]
    unmapped = [
        n for n, s in zip(target.joint_names, result.mapping, strict=True) if s < 0
    ]
    w(
        f"wrote {args.out}: {len(result.frames)} frames, {len(mapped)} of "
        f"{len(target.joint_names)} target joints driven, root scale "
        f"{result.root_scale:.4g}\n"
    )
    w("mapped: " + " ".join(mapped) + "\n")
    w("unmapped (keep their rest): " + (" ".join(unmapped) or "none") + "\n")
    if planted is not None:
        from retargetd.daemon.cli.retarget_plant import summary_line

        w(summary_line(planted) + "\n")
    if result.spine:
        inner = " ".join(target.joint_names[j] for j in result.spine[1:-1])
        w(f"on the Hermite spine curve: {inner}\n")
    if args.spread:
        chains = spread_chains(target.parents, list(result.mapping))
        chains = {u: c for u, c in chains.items() if u not in result.spine}
        spread = [target.joint_names[u] for u in sorted(chains)]
        how = (
            f" (shifting pivot, {limit:g} deg a joint)"
            if args.spread == "pivot"
            else ""
        )
        w(f"of those, sharing a chain's rotation{how}: " + (" ".join(spread) or "none"))
        w("\n")
    return 0
