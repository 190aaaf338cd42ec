"""``retargetd solve TAKE (--rig RIG (--calibration FILE | --calibrate-frames a:b)
[--face FACE.npz] | --face FACE.npz --face-only)
--out OUT.npz|OUT.bvh|OUT.csv|OUT.glb|OUT.mcap [--fill-gaps N] [--pipeline FILE.toml]
[--bvh-order ZXY] [--bvh-root-order ORDER] [--euler-order ORDER] [--degrees] [--json]
[--quiet] [--frames a:b]``: solve every frame of a take, or the rows ``--frames``
selects. The ``--out`` suffix chooses the format.

``--frames a:b``: solve only rows a..b-1 of the take (0-based, half-open; e.g. past
a run of empty leading frames). ``--calibrate-frames`` still counts rows of the
whole take, so a take can calibrate on rows outside the ones it solves. The NPZ
keeps the take's frame numbering: its ``first_frame`` is the take's number of row a
(the take's own ``first_frame`` + a), so NPZ row i is source frame ``first_frame +
i``; BVH, CSV, glTF and MCAP count frames and time from the first solved row.

``--json`` prints the summary as one JSON object (keys in README "Machine-readable
output"); ``--quiet`` prints nothing on success. On a terminal a progress bar runs on
stderr (never into a pipe or a file, none with ``--quiet``).

``--fill-gaps N``: a bone held (too little data) for at most N frames, with solved
frames on both sides, is slerped across the gap instead of holding and then jumping
(``retargetd.daemon.post.interp.fill_gaps``); done before the pipeline.

``--pipeline FILE.toml``: the file's ``[[pipeline]]`` post stages (``twist``,
``one_euro``; README "Post stages") run over every solved frame, in the order listed,
before anything is written (every format below then holds the processed motion). A
``[target]`` table with ``spine = "pivot"`` (the shifting pivot on Spine, Chest,
UpperChest; a daemon config's works too) also maps the processed solve onto the
target skeleton as the live loop does before VMC, that stage included: ``.npz``
only, as
``target_bone_names``, ``target_world_from_bone_quat``, ``target_rest_from_bone_quat``
(T, N, 4) w x y z (what VMC sends, world axes), ``target_root_pos`` and
``target_spine``.

``.bvh``: the calibrated skeleton and the solved motion as BVH, centimetres, Y up,
every joint's rotation channels in ``--bvh-order`` (default Z X Y), the root's in
``--bvh-root-order`` when given. BVH can express only the 6 Tait-Bryan channel orders
XYZ, XZY, YXZ, YZX, ZXY, ZYX (one channel per axis, composed in the listed order);
the 6 proper Euler orders (XYX ...) repeat an axis and are only in the CSV. See
``retargetd.daemon.retarget.bvh``.

``.csv``: one row per frame, spreadsheet-friendly: ``frame, time_s, root_x_m,
root_y_m, root_z_m`` then three Euler angles per bone (``<bone>_1Z_deg`` ...) of the
true parent-relative rotation in ``--euler-order`` (any of the 12: upper case
intrinsic, ``ZXY`` = R_Z R_X R_Y about the moving axes; lower case extrinsic, about
the fixed parent axes in that order; default ZXY), radians unless ``--degrees``,
unwrapped over time. See ``retargetd.daemon.retarget.euler_csv``.

``.glb``: glTF 2.0 binary, every frame as a key: the calibrated skeleton as a skin
(one joint per bone, named by the rig's humanoid map where it has one, else the rig's
name, kept in each node's ``extras``; inverse bind matrices at the calibration pose),
one animation on the joints (rotations LINEAR, i.e. slerp, root translation LINEAR);
importers build an armature from the skin. ``--glb-mesh capsules`` adds a capsule per
bone bound to it, so the take shows as a figure. See
``retargetd.daemon.post.export_gltf``.

``--face FACE.npz``: also the face, solved as the daemon solves it, in every format but
BVH (``face_*`` arrays, CSV columns, a glTF morph-target mesh, ``/face/weights`` in the
MCAP); ``--face-only``: the face alone, no rig and no calibration
(``retargetd.daemon.cli.face_io``; README "Face output"). ``--face-config``: the face
config whose ``head_weights`` the daemon uses.

``.mcap``: Foxglove channels alone (``/foxglove/scene`` skeleton and markers,
``/foxglove/tf`` bone frames, ``/foxglove/health``), Foxglove's published schemas
written with its SDK: Foxglove's 3D panel shows the take with no layout work. See
``retargetd.replay.foxglove`` and ``protocols/PROTOCOLS.md``.

The NPZ (``numpy.load(..., allow_pickle=False)``) holds, in rig order:
``joint_names`` (J,), ``joint_centres`` (T, J, 3) metres world; ``bone_names`` (B,),
``bone_parents`` (B,) int (-1 root), ``bone_humanoid`` (B,) ("" when unmapped),
``world_from_bone_quat`` (T, B, 4) w x y z, ``parent_from_bone_quat`` (T, B, 4) w x y z
(relative to the parent bone: ``world_from_parent * parent_from_bone =
world_from_bone``), ``rest_from_bone_quat`` (T, B, 4) w x y z (relative to the
calibration pose), ``root_pos`` (T, 3) metres, ``bone_lengths`` (B,)
metres as calibrated, ``bone_quality`` (T, B) float32, ``bone_flags`` (T, B) uint8,
``rate_hz``, ``world_from_capture`` (3, 3), ``first_frame``, ``rig_name``. See README
"Solve output".
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from typing import Any

import numpy as np

from retargetd.daemon.errors import UsageError

logger = logging.getLogger(__name__)


def add_parser(subparsers: Any) -> None:
    """Register ``solve``."""
    from retargetd.daemon.cli.args import (
        add_force_argument,
        add_frames_argument,
        add_output_arguments,
        add_solve_arguments,
    )
    from retargetd.daemon.cli.face_io import add_face_arguments
    from retargetd.daemon.cli.post_io import (
        add_glb_mesh_argument,
        add_pipeline_argument,
        add_plant_feet_argument,
    )
    from retargetd.daemon.cli.prop_io import add_solve_prop_arguments

    parser = subparsers.add_parser(
        "solve",
        help="solve every frame of a take to the rig's skeleton (NPZ, BVH, CSV, glTF, "
        "Foxglove MCAP)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_solve_arguments(parser, body_optional=True)
    add_face_arguments(parser)
    add_frames_argument(parser)
    parser.add_argument(
        "--out", required=True, metavar="OUT.npz|OUT.bvh|OUT.csv|OUT.glb|OUT.mcap",
        help="the solved take; the suffix picks the format",
    )  # fmt: skip
    add_output_arguments(parser, json=True)
    add_pipeline_argument(parser)
    add_plant_feet_argument(parser)
    add_glb_mesh_argument(parser)
    add_solve_prop_arguments(parser)  # --prop FILE.json (cli/prop_io.py)
    parser.add_argument(
        "--fill-gaps",
        type=int,
        metavar="N",
        help="slerp each bone across runs of at most N held frames (solved frames "
        "on both sides) instead of holding it",
    )
    add_force_argument(parser)
    parser.add_argument(
        "--bvh-order",
        metavar="ORDER",
        help="BVH: rotation channel order of every joint, as the channels are "
        "listed (case-insensitive; default ZXY); BVH can express only the 6 "
        "Tait-Bryan orders XYZ, XZY, YXZ, YZX, ZXY, ZYX",
    )
    parser.add_argument(
        "--bvh-root-order",
        metavar="ORDER",
        help="BVH: rotation channel order of the root (default: --bvh-order)",
    )
    parser.add_argument(
        "--euler-order",
        metavar="ORDER",
        help="CSV: Euler sequence, any of the 12 (XYZ ... ZXZ; upper case intrinsic, "
        "lower case extrinsic; default ZXY)",
    )
    parser.add_argument(
        "--degrees", action="store_true", help="CSV: angles in degrees (else radians)"
    )
    parser.set_defaults(run=run)


def segment_stability(
    rig: Any, joint_names: tuple[str, ...], joints: np.ndarray
) -> list[tuple[str, float, float]]:
    """(bone, mean length m, coefficient of variation %) for every bone whose origin
    and aim are both named joint centres."""
    point_to_joint = {p: j for j, p in rig.joints.items()}
    index = {j: i for i, j in enumerate(joint_names)}
    out = []
    for bone in rig.bones:
        a = point_to_joint.get(bone.origin)
        b = point_to_joint.get(bone.aim)
        if a is None or b is None:
            continue
        d = np.linalg.norm(joints[:, index[b]] - joints[:, index[a]], axis=-1)
        d = d[np.isfinite(d)]
        if d.size < 2:
            continue
        out.append(
            (f"{bone.name} ({a}-{b})", float(d.mean()), float(100 * d.std() / d.mean()))
        )
    return out


#: Our joint-centre names -> the vendor reference points that hold the same centre
#: (Plug-in Gait: femur proximal = hip, femur origin = knee, tibia origin = ankle,
#: humerus proximal = shoulder, humerus origin = elbow, radius origin = wrist).
REFERENCE_CENTRES = {
    f"{s}{j}": (f"{s}{j}", f"{s}{pig}")
    for s in "LR"
    for j, pig in (("HJC", "FEP"), ("KJC", "FEO"), ("AJC", "TIO"), ("SJC", "HUP"),
                   ("EJC", "HUO"), ("WJC", "RAO"))
}  # fmt: skip


def reference_distances(
    take: Any, joint_names: tuple[str, ...], joints: np.ndarray
) -> list[tuple[str, str, float, float]]:
    """(joint, reference, median mm, p95 mm) against the take's vendor joint centres."""
    refs = take.references
    out = []
    for j, name in enumerate(joint_names):
        for ref in REFERENCE_CENTRES.get(name, ()):
            if ref in refs.labels and refs.kinds[refs.index(ref)] != "angle":
                d = 1000 * np.linalg.norm(joints[:, j] - refs.get(ref), axis=-1)
                d = d[np.isfinite(d)]
                if d.size:
                    out.append(
                        (name, ref, float(np.median(d)), float(np.percentile(d, 95)))
                    )
                break
    return out


def run(args: argparse.Namespace) -> int:
    """Run ``solve``."""
    from retargetd.daemon.body.solve import FLAG_HELD
    from retargetd.daemon.cli import face_io
    from retargetd.daemon.cli.args import (
        refuse_existing,
        solve_take_progress,
        solver_for_take,
    )

    out_format = _out_format(args)
    face = face_io.check_face_arguments(args, out_format)
    if args.fill_gaps is not None and args.fill_gaps < 1:
        raise UsageError(f"--fill-gaps: expected >= 1 frames; got {args.fill_gaps}")
    refuse_existing(args.out, force=args.force)
    if face is not None and args.face_only:
        return _run_face_only(args, face, out_format)
    target_cfg = None
    if args.pipeline is not None:  # checked before the solve
        from retargetd.daemon.cli.post_io import load_target_section

        target_cfg = load_target_section(args.pipeline)
        if (
            target_cfg is not None
            and target_cfg.spine != "pivot"
            and not args.plant_feet
        ):
            target_cfg = None  # a daemon config's [target]: nothing to emit offline
        if target_cfg is not None and out_format != "npz":
            raise UsageError(
                f"--pipeline {args.pipeline}: a [target] table maps the solve onto "
                'the target skeleton (spine = "pivot" ...), written in .npz only '
                f"(target_* arrays); got --out {args.out}"
            )
    if args.plant_feet:
        from retargetd.daemon.cli.post_io import plant_target_config

        target_cfg = plant_target_config(target_cfg, args.out, out_format)
    rig, take, cal, solver = solver_for_take(args)
    from retargetd.daemon.cli.prop_io import solve_props_for_take

    prop_arrays, prop_lines = solve_props_for_take(args)  # --prop: props beside
    started = time.perf_counter()
    res = solve_take_progress(
        solver, take.positions, quiet=args.quiet, causal=args.causal
    )
    solve_s = time.perf_counter() - started
    ft = None if face is None else face_io.solve_face_of_take(face, take)
    # Stance from the solve, before any post stage: the live daemon's detector on the
    # same frames (post/stance.py), so the NPZ's contacts are the stream's.
    from retargetd.daemon.post.stance import foot_contact

    contact = foot_contact(
        rig, cal, res.root_pos, res.world_from_bone_quat, take.rate_hz
    )
    raw = res  # stance is detected on the solve before any post stage, as live
    kinds: tuple[str, ...] = ()
    n_filled = None
    if args.fill_gaps is not None:
        from retargetd.daemon.cli.post_io import fill_held_gaps

        res, n_filled = fill_held_gaps(res, cal, args.fill_gaps)
    target_arrays: dict[str, Any] = {}
    if args.pipeline is not None:
        from retargetd.daemon.cli.post_io import apply_pipeline_to_solve

        res, kinds = apply_pipeline_to_solve(args.pipeline, res, cal, take.rate_hz)
    if target_cfg is not None:
        from retargetd.daemon.cli.post_io import retarget_solve

        target_arrays = retarget_solve(
            res, rig, cal, target_cfg, rate_hz=take.rate_hz, stance_solve=raw
        )
    if out_format == "bvh":
        _write_bvh(args, cal, res, take.rate_hz)
    elif out_format == "csv":
        from retargetd.daemon.retarget.euler_csv import write_euler_csv

        write_euler_csv(
            args.out, res.bone_names, res.parent_from_bone_quat, res.root_pos,
            take.rate_hz, order=args.euler_order or "ZXY", degrees=args.degrees,
        )  # fmt: skip
        if ft is not None:
            face_io.write_face_csv(args.out, ft, take.rate_hz, append=True)
    elif out_format == "glb":
        morph = None if ft is None else face_io.morph_face(face, ft, take.rate_hz)
        _write_glb(args, rig, cal, res, take.rate_hz, morph)
    else:
        arrays = dict(
            joint_names=np.asarray(res.joint_names, dtype=str),
            joint_centres=res.joint_centres,
            bone_names=np.asarray(res.bone_names, dtype=str),
            bone_parents=np.asarray(res.bone_parents, dtype=np.int64),
            bone_humanoid=np.asarray([b.humanoid or "" for b in rig.bones], dtype=str),
            world_from_bone_quat=res.world_from_bone_quat,
            parent_from_bone_quat=res.parent_from_bone_quat,
            rest_from_bone_quat=res.rest_from_bone_quat,
            root_pos=res.root_pos,
            bone_lengths=res.bone_lengths,
            bone_quality=res.bone_quality,
            bone_flags=res.bone_flags,
            foot_contact=contact,
            rate_hz=np.float64(take.rate_hz),
            world_from_capture=np.asarray(take.world_from_capture, dtype=np.float64),
            first_frame=np.int64(take.first_frame),
            rig_name=np.asarray(rig.name),
            method=np.asarray(args.method),
            **_fit_arrays(res),
            **target_arrays,
            **({} if ft is None else face_io.face_arrays(ft)),
            **prop_arrays,
        )
        if out_format == "mcap":
            from retargetd.daemon.console.export import write_solve_foxglove
            from retargetd.daemon.progress import Progress
            from retargetd.daemon.version import package_version

            with Progress(
                take.n_frames, "write mcap", unit="frames", enabled=not args.quiet
            ) as bar:
                write_solve_foxglove(
                    args.out, arrays, rig, markers=take.positions,
                    marker_valid=take.valid, library=f"retargetd {package_version()}",
                    progress=bar.update, face=None if ft is None else arrays,
                )  # fmt: skip
        else:
            np.savez(args.out, **arrays)
    if args.json:
        _print_json_summary(args, rig, take, solver, res, solve_s, kinds, ft)
        return 0
    if args.quiet:
        return 0
    out = sys.stdout.write
    n = take.n_frames
    cols = solver.marker_cols
    present = cols[cols >= 0]
    occluded = int((~take.valid[:, present]).sum())
    total = n * len(cols)
    rows = f" (rows {args.solve_rows} of the take)" if args.solve_rows else ""
    out(f"wrote {args.out}: {n} frames{rows} at {take.rate_hz:g} Hz, rig {rig.name}, ")
    out(f"{len(res.bone_names)} bones, {len(res.joint_names)} joint centres\n")
    fps = n / solve_s if solve_s > 0 else float("inf")
    out(f"solved in {solve_s:.2f} s: {fps:.0f} frames/s\n")
    rms = getattr(res, "marker_rms", None)
    if rms is not None and len(rms):
        finite = rms[np.isfinite(rms)] * 1e3
        med, p95 = (
            (np.median(finite), np.percentile(finite, 95))
            if len(finite)
            else (float("nan"), float("nan"))
        )
        out(
            f"fit: marker residual RMS median {med:.1f} mm, p95 {p95:.1f} mm; "
            f"outliers rejected {res.outliers_rejected} marker samples; reseeded "
            f"{int(np.count_nonzero(res.reseeded))} frames; unexplained (held) "
            f"{int(np.count_nonzero(res.unexplained))}; performer unseen "
            f"{int(np.count_nonzero(res.unseen))}\n"
        )
    filled = getattr(res, "filled", None)
    if filled is not None:
        out(
            f"hidden spans filled from both sides: {int(filled.any(axis=1).sum())} "
            f"frames, {int(filled.sum())} bone-frames (--causal: none)\n"
        )
    missing = n * int((cols < 0).sum())
    out(
        f"occluded rig-marker samples: {occluded + missing} of {total} "
        f"({100.0 * (occluded + missing) / max(total, 1):.1f} %)"
    )
    if solver.missing_markers:
        out(f"; not in the take: {' '.join(solver.missing_markers)}")
    out("\n")
    if n_filled is not None:
        out(f"gaps filled (<= {args.fill_gaps} held frames): {n_filled} bone-frames\n")
    if kinds:
        out(f"pipeline {args.pipeline}: {' -> '.join(kinds)}\n")
    for line in prop_lines:
        out(line)
    held = (res.bone_flags & FLAG_HELD) != 0
    flagged = [
        f"{name} {100.0 * held[:, b].mean():.1f} %"
        for b, name in enumerate(res.bone_names)
        if held[:, b].any()
    ]
    out(args.calibration_match.summary() + "\n")
    out("bones held (frames): " + (", ".join(flagged) if flagged else "none") + "\n")
    stab = segment_stability(rig, res.joint_names, res.joint_centres)
    if stab:
        out("joint-centre segment stability (mean length, CV):\n")
        for name, mean, cv in stab:
            out(f"  {name}: {1000 * mean:.1f} mm, {cv:.2f} %\n")
    compared = reference_distances(take, res.joint_names, res.joint_centres)
    if compared:
        out("joint centres against the take's own reference points (median, p95):\n")
        for name, ref, med, p95 in compared:
            out(f"  {name} vs {ref}: {med:.1f} mm, {p95:.1f} mm\n")
    if ft is not None:
        for line in face_io.face_summary(ft):
            out(line + "\n")
    return 0


def _run_face_only(args: argparse.Namespace, face: Any, out_format: str) -> int:
    """``solve --face FACE.npz --face-only``: the face alone (no rig, no
    calibration)."""
    from retargetd.daemon.cli import face_io
    from retargetd.daemon.cli.args import parse_frames, print_json, take_overrides
    from retargetd.replay.takes import load_take

    take = load_take(args.take, **take_overrides(args))
    args.solve_rows = None
    if args.solve_frames is not None:
        rows = parse_frames(args.solve_frames, take.n_frames, option="--frames")
        take = take.select_rows(rows)
        args.solve_rows = f"{rows.start}:{rows.stop}"
    started = time.perf_counter()
    ft = face_io.solve_face_of_take(face, take)
    solve_s = time.perf_counter() - started
    face_io.write_face_only(args, face, take, ft, out_format)
    n = take.n_frames
    if args.json:
        print_json(
            {
                "command": "solve",
                "take": str(take.path),
                "out": args.out,
                "format": out_format,
                "face_only": True,
                "frames": n,
                "frames_selected": args.solve_rows,
                "first_frame": int(take.first_frame),
                "rate_hz": float(take.rate_hz),
                "solve_s": solve_s,
                "face": face_io.face_json(ft),
            }
        )
        return 0
    if args.quiet:
        return 0
    rows_txt = f" (rows {args.solve_rows} of the take)" if args.solve_rows else ""
    sys.stdout.write(
        f"wrote {args.out}: {n} frames{rows_txt} at {take.rate_hz:g} Hz, the face "
        f"alone ({len(ft.marker_names)} facial markers)\n"
    )
    for line in face_io.face_summary(ft):
        sys.stdout.write(line + "\n")
    return 0


def _out_format(args: argparse.Namespace) -> str:
    """``"npz"``, ``"bvh"``, ``"csv"``, ``"glb"`` or ``"mcap"`` from the ``--out``
    suffix; checks the format's options."""
    from retargetd.daemon.cli.post_io import check_bvh_order, glb_mesh_of, suffix_of
    from retargetd.daemon.rotations import euler_from_quat

    suffix = suffix_of(args.out, ("npz", "bvh", "csv", "glb", "mcap"))
    glb_mesh_of(args, suffix)  # --glb-mesh is for .glb alone
    for option, value in (
        ("--bvh-order", args.bvh_order),
        ("--bvh-root-order", args.bvh_root_order),
    ):
        if value is None:
            continue
        if suffix != "bvh":
            raise UsageError(f"{option} applies to .bvh output; --out is {args.out!r}")
        check_bvh_order(option, value)
    for option, given in (
        ("--euler-order", args.euler_order is not None),
        ("--degrees", args.degrees),
    ):
        if given and suffix != "csv":
            raise UsageError(f"{option} applies to .csv output; --out is {args.out!r}")
    if args.euler_order is not None:
        try:
            euler_from_quat(np.array([1.0, 0.0, 0.0, 0.0]), args.euler_order)
        except ValueError as exc:
            raise UsageError(f"--euler-order: {exc}") from None
    return suffix


def _write_glb(
    args: argparse.Namespace,
    rig: Any,
    cal: Any,
    res: Any,
    rate_hz: float,
    face: Any = None,
) -> None:
    from retargetd.daemon.body.calibration import CalibrationError
    from retargetd.daemon.cli.post_io import glb_mesh_of, humanoid_names
    from retargetd.daemon.post.export_gltf import clip_from_solve, write_clip_glb

    try:
        write_clip_glb(
            args.out, clip_from_solve(res, cal, rate_hz), cal,
            humanoid=humanoid_names(rig), mesh=glb_mesh_of(args, "glb"), face=face,
        )  # fmt: skip
    except CalibrationError as exc:
        raise UsageError(str(exc)) from None


def _write_bvh(args: argparse.Namespace, cal: Any, res: Any, rate_hz: float) -> None:
    from retargetd.daemon.body.calibration import CalibrationError
    from retargetd.daemon.retarget.bvh import DEFAULT_ROTATION_ORDER, write_solve_bvh

    try:
        write_solve_bvh(
            args.out, cal, res, rate_hz,
            rotation_order=args.bvh_order or DEFAULT_ROTATION_ORDER,
            root_rotation_order=args.bvh_root_order,
        )  # fmt: skip
    except CalibrationError as exc:
        raise UsageError(str(exc)) from None


def _fit_arrays(res: Any) -> dict[str, Any]:
    """The fit's per-frame residuals for the NPZ (none for the construction)."""
    if not hasattr(res, "marker_rms"):
        return {}
    return {
        "marker_names": np.asarray(res.marker_names, dtype=str),
        "marker_rms": res.marker_rms,
        "marker_residual": res.marker_residual,
        "marker_rejected": res.marker_rejected,
        "fit_iterations": res.iterations,
        "fit_reseeded": res.reseeded,
        "fit_unexplained": res.unexplained,
        "fit_unseen": res.unseen,
        "fit_residual_level": res.residual_level,
        "frame_flags": res.frame_flags,
        **({"fit_filled": res.filled} if hasattr(res, "filled") else {}),
    }


def _print_json_summary(
    args: argparse.Namespace,
    rig: Any,
    take: Any,
    solver: Any,
    res: Any,
    solve_s: float,
    kinds: tuple[str, ...],
    ft: Any = None,
) -> None:
    """The summary as one JSON object (README "Machine-readable output")."""
    from retargetd.daemon.body.solve import FLAG_HELD
    from retargetd.daemon.cli.args import print_json
    from retargetd.daemon.cli.face_io import face_json

    n = take.n_frames
    cols = solver.marker_cols
    present = cols[cols >= 0]
    occluded = int((~take.valid[:, present]).sum()) + n * int((cols < 0).sum())
    held = (res.bone_flags & FLAG_HELD) != 0
    fit = None
    rms = getattr(res, "marker_rms", None)
    if rms is not None:
        finite = rms[np.isfinite(rms)] * 1e3
        fit = {
            "rms_median_mm": float(np.median(finite)) if len(finite) else None,
            "rms_p95_mm": float(np.percentile(finite, 95)) if len(finite) else None,
            "outliers_rejected": int(res.outliers_rejected),
            "reseeded_frames": int(np.count_nonzero(res.reseeded)),
            "unexplained_frames": int(np.count_nonzero(res.unexplained)),
            "unseen_frames": int(np.count_nonzero(res.unseen)),
        }
    print_json(
        {
            "command": "solve",
            "take": str(take.path),
            "out": args.out,
            "format": _out_format(args),
            "rig": rig.name,
            "method": args.method,
            "frames": n,
            "frames_selected": args.solve_rows,
            "first_frame": int(take.first_frame),
            "rate_hz": float(take.rate_hz),
            "bones": len(res.bone_names),
            "joint_centres": len(res.joint_names),
            "solve_s": solve_s,
            "frames_per_s": n / solve_s if solve_s > 0 else None,
            "rig_marker_samples": n * len(cols),
            "occluded_samples": occluded,
            "missing_markers": list(solver.missing_markers),
            "pipeline": list(kinds),
            "bones_held_fraction": {
                name: float(held[:, b].mean())
                for b, name in enumerate(res.bone_names)
                if held[:, b].any()
            },
            "fit": fit,
            "calibration_match": args.calibration_match.to_json(),
            "calibration_matches": args.calibration_match.matches,
            "layout_refined": (
                None
                if args.layout_refined is None
                else args.layout_refined.calibration.layout_refined
            ),
            "segment_stability": [
                {"bone": b, "mean_m": m, "cv_pct": cv}
                for b, m, cv in segment_stability(
                    rig, res.joint_names, res.joint_centres
                )
            ],
            "reference_distances": [
                {"joint": j, "reference": r, "median_mm": med, "p95_mm": p95}
                for j, r, med, p95 in reference_distances(
                    take, res.joint_names, res.joint_centres
                )
            ],
            "face": None if ft is None else face_json(ft),
        }
    )
