"""Shared by the offline post commands (``solve``, ``reduce``, ``blend``, ``loop``):
the ``--pipeline FILE.toml`` option and applying its ``[[pipeline]]`` stages to a
solved take, frame by frame, with the same stage objects the live path builds
(:func:`retargetd.daemon.post.pipeline.build_pipeline`); and writing a clip (true
parent-relative rotations and the root) as ``.glb``, ``.bvh`` or ``.npz``.

Not a command module: commands import it, it imports no command. Heavy modules are
imported inside the functions (the CLI's lazy-import rule).
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from retargetd.daemon.errors import UsageError

#: Output suffixes a clip can be written as (``blend``, ``loop``).
CLIP_SUFFIXES = ("glb", "bvh", "npz")


def add_pipeline_argument(parser: argparse.ArgumentParser) -> None:
    """``--pipeline FILE.toml`` (``[[pipeline]]`` tables, README "Post stages")."""
    parser.add_argument(
        "--pipeline",
        metavar="FILE.toml",
        help="apply the file's [[pipeline]] post stages (twist, one_euro) to every "
        "solved frame, in the order listed, before writing",
    )


def add_plant_feet_argument(
    parser: argparse.ArgumentParser, help_text: str | None = None
) -> None:
    """``--plant-feet`` (``[target] feet = "plant"`` offline; README "Feet that
    plant"); ``help_text`` replaces the help of the commands that solve a take."""
    parser.add_argument(
        "--plant-feet",
        action="store_true",
        help=help_text
        or "map the motion onto the target skeleton (--pipeline's [target], else "
        "the default humanoid) with the stance feet planted, as the live "
        '[target] feet = "plant" does: the root scaled by the leg-length ratio, '
        "each stance foot held where it landed by two-bone leg IK; written as the "
        ".npz's target_* arrays (.npz only)",
    )


def plant_target_config(target_config: Any, out: str, out_format: str) -> Any:
    """``--plant-feet``: the ``[target]`` config (the given one, else the defaults:
    the humanoid) with ``feet = "plant"``.

    Raises:
        UsageError: an output other than ``.npz``.
    """
    from retargetd.daemon.live.config_schema import TargetConfig

    if out_format != "npz":
        raise UsageError(
            "--plant-feet: the planted motion is on the target skeleton, written as "
            f"the .npz's target_* arrays (.npz only); got --out {out}"
        )
    base = TargetConfig() if target_config is None else target_config
    return dataclasses.replace(base, feet="plant")


def clip_plant_config(args: argparse.Namespace, out_format: str) -> Any:
    """``blend`` / ``loop`` ``--plant-feet``: the ``[target]`` config to plant on
    (``--pipeline``'s ``[target]``, else the defaults: the humanoid), checked before
    any solve; None without ``--plant-feet``.

    Raises:
        UsageError: an output other than ``.npz``, or a bad ``[target]``.
    """
    if not getattr(args, "plant_feet", False):
        return None
    target_cfg = None
    if getattr(args, "pipeline", None) is not None:
        target_cfg = load_target_section(args.pipeline)
    return plant_target_config(target_cfg, args.out, out_format)


def plant_clip(
    clip: Any, rig: Any, calibration: Any, target_config: Any
) -> dict[str, np.ndarray]:
    """``--plant-feet`` on a clip (``blend``'s or ``loop``'s output): the clip's
    motion mapped onto the target with its stance feet planted, as
    :func:`retarget_solve` maps a solve, the stance detected on the clip itself (the
    motion that is written: a fade or a seam is walked on like any frame).

    Returns:
        The ``target_*`` NPZ arrays (:func:`retarget_solve`).
    """
    from types import SimpleNamespace

    from retargetd.daemon.retarget.bvh import world_from_parent_chain

    n_frames, n_bones = clip.parent_from_bone_quat.shape[:2]
    motion = SimpleNamespace(
        world_from_bone_quat=world_from_parent_chain(
            calibration.bone_parents, clip.parent_from_bone_quat
        ),
        root_pos=np.asarray(clip.root_pos, dtype=np.float64),
        bone_flags=np.zeros((n_frames, n_bones), dtype=np.uint8),
    )
    return retarget_solve(motion, rig, calibration, target_config, rate_hz=clip.rate_hz)


def add_glb_mesh_argument(parser: argparse.ArgumentParser) -> None:
    """``--glb-mesh none|capsules`` (glTF output: the skin alone, or a capsule per
    bone on it; :mod:`retargetd.replay.gltf_mesh`)."""
    parser.add_argument(
        "--glb-mesh",
        choices=("none", "capsules"),
        help="glTF: 'none' writes the skeleton as a skin alone (importers build an "
        "armature from it); 'capsules' adds a capsule per bone bound to it, so the "
        "take shows as a figure (default none)",
    )


def glb_mesh_of(args: argparse.Namespace, suffix: str) -> str:
    """``--glb-mesh``'s value (``"none"`` when not given).

    Raises:
        UsageError: given for an output other than ``.glb``.
    """
    mesh = getattr(args, "glb_mesh", None)
    if mesh is not None and suffix != "glb":
        raise UsageError(f"--glb-mesh applies to .glb output; --out is {args.out!r}")
    return mesh or "none"


def humanoid_names(rig: Any) -> list[str]:
    """(B,) each rig bone's standard humanoid name, ``""`` when unmapped (the NPZ's
    ``bone_humanoid``; glTF node names)."""
    return [b.humanoid or "" for b in rig.bones]


def _read_toml(path: str | Path) -> dict[str, Any]:
    from retargetd.daemon.files import FileFormatError, loads_toml, read_text

    try:
        return loads_toml(read_text(path, "pipeline file"))
    except FileFormatError as exc:
        raise UsageError(f"--pipeline {path}: {exc}") from None


def load_target_section(path: str | Path) -> Any:
    """The file's ``[target]`` table as a ``TargetConfig`` (None when it has none).

    Raises:
        UsageError: unreadable TOML or a bad key or value (named).
    """
    from retargetd.daemon.live.config import ConfigError, parse_target

    table = _read_toml(path).get("target")
    if table is None:
        return None
    try:
        return parse_target(table, f"--pipeline {path}")
    except ConfigError as exc:
        raise UsageError(str(exc)) from None


def load_pipeline_entries(path: str | Path) -> list[dict[str, Any]]:
    """The ``[[pipeline]]`` tables of a TOML file (a daemon config works too); none
    when the file has only a ``[target]`` table (its ``spine``).

    Raises:
        UsageError: unreadable TOML, or no ``pipeline`` array of tables.
    """
    data = _read_toml(path)
    if "pipeline" not in data and "target" in data:
        return []
    entries = data.get("pipeline")
    if not isinstance(entries, list) or not all(isinstance(e, dict) for e in entries):
        raise UsageError(
            f'--pipeline {path}: expected [[pipeline]] tables (kind = "twist" | '
            '"one_euro", ...)'
        )
    return entries


def apply_pipeline_to_solve(
    path: str | Path, solve: Any, calibration: Any, rate_hz: float
) -> tuple[Any, tuple[str, ...]]:
    """Run a pipeline file's stages over every frame of a solve.

    Each frame goes through :meth:`Pipeline.apply` on one :class:`PoseBuffer` (the
    live path's objects; ``t_s = frame / rate_hz``). The solve's
    ``parent_from_bone_quat`` (the true parent-relative rotation) is what the stages
    read and write; ``world_from_bone_quat`` (forward kinematics, sign-continuous)
    and ``rest_from_bone_quat`` (``conj(rest_parent_from_bone) * parent_from_bone``,
    w >= 0) are recomputed from it; ``root_pos`` is the filtered root.

    Args:
        path: the TOML file with ``[[pipeline]]`` tables.
        solve: the :class:`~retargetd.daemon.body.solve.BodySolve`.
        calibration: the calibration it was solved with (rest rotations).
        rate_hz: the take's frame rate.

    Returns:
        ``(solve, kinds)``: a new solve and the stage kinds applied, in order.

    Raises:
        UsageError: a bad file, kind, key or value (naming the entry).
    """
    from retargetd.daemon import rotations as rot
    from retargetd.daemon.post.pipeline import build_pipeline
    from retargetd.daemon.post.pose import PoseBuffer
    from retargetd.daemon.retarget.bvh import world_from_parent_chain

    entries = load_pipeline_entries(path)
    try:
        pipe = build_pipeline(
            entries,
            bone_names=solve.bone_names,
            bone_parents=solve.bone_parents,
            rest_parent_from_bone_quat=np.asarray(
                calibration.rest_parent_from_bone_quat, dtype=np.float64
            ),
        )
    except ValueError as exc:
        raise UsageError(f"--pipeline {path}: {exc}") from None
    q_in = np.asarray(solve.parent_from_bone_quat, dtype=np.float64)
    p_in = np.asarray(solve.root_pos, dtype=np.float64)
    q_out = np.empty_like(q_in)
    p_out = np.empty_like(p_in)
    pose = PoseBuffer.new(q_in.shape[1])
    for t in range(len(q_in)):
        pose.t_s = t / rate_hz
        np.copyto(pose.parent_from_bone_quat, q_in[t])
        np.copyto(pose.root_pos, p_in[t])
        pipe.apply(pose, pose)
        q_out[t] = pose.parent_from_bone_quat
        p_out[t] = pose.root_pos
    wfb = sign_continuous(world_from_parent_chain(solve.bone_parents, q_out))
    rest = np.asarray(calibration.rest_parent_from_bone_quat, dtype=np.float64)
    rfb = rot.quat_mul(rot.quat_conj(rest), q_out)
    rfb *= np.where(rfb[..., :1] < 0.0, -1.0, 1.0)
    new = dataclasses.replace(
        solve,
        parent_from_bone_quat=q_out,
        world_from_bone_quat=wfb,
        rest_from_bone_quat=rfb,
        root_pos=p_out,
    )
    return new, pipe.kinds


def retarget_solve(
    solve: Any,
    rig: Any,
    calibration: Any,
    target_config: Any,
    *,
    rate_hz: float = 0.0,
    stance_solve: Any = None,
) -> dict[str, np.ndarray]:
    """A solve mapped onto the ``[target]`` skeleton frame by frame, as the live loop
    maps it before VMC: :class:`~retargetd.daemon.retarget.retarget.Retargeter` (the
    same ``compensate_base_pose``), then, with ``spine = "pivot"``, the same
    :class:`~retargetd.daemon.post.pivot.SpinePivot`
    (:func:`retargetd.daemon.post.pivot.spine_stage`), then, with ``feet = "plant"``,
    the same :class:`~retargetd.daemon.post.plant.FootPlant`
    (:func:`retargetd.daemon.live.send.plant_stage`) fed by the stance detector run
    on ``stance_solve`` (the solve before any post stage, as live), each contact's
    support the level it settled on over the whole contact
    (:func:`~retargetd.daemon.post.stance.take_stance_states`; off the floor the
    target's own sole's, :meth:`~retargetd.daemon.post.plant.FootPlant.hold_settled`;
    live, the level so far).

    Args:
        solve: the (processed) :class:`~retargetd.daemon.body.solve.BodySolve`.
        rig: its rig.
        calibration: its calibration.
        target_config: a ``TargetConfig`` (:func:`load_target_section`).
        rate_hz: the take's frame rate (needed with ``feet = "plant"``).
        stance_solve: the solve stance is detected on (default ``solve``).

    Returns:
        NPZ arrays: ``target_bone_names`` (N,), ``target_world_from_bone_quat`` and
        ``target_rest_from_bone_quat`` (T, N, 4) w x y z (the latter what VMC sends,
        world axes), ``target_root_pos`` (T, 3) metres world, ``target_spine``,
        ``target_feet``; with ``feet = "plant"`` also ``target_plant_flags`` (T,)
        uint32 (``FRAME_PLANT_UNREACHED`` where a foot could not reach its hold) and
        ``target_leg_ratio`` (the target's leg length over the performer's).

    Raises:
        UsageError: a target the spine pivot or the plant does not fit, or a bad BVH
            target.
    """
    from types import SimpleNamespace

    from retargetd.daemon.post.pivot import spine_stage
    from retargetd.daemon.post.plant import plant_stage
    from retargetd.daemon.post.stance import StanceDetector, take_stance_states
    from retargetd.daemon.retarget.retarget import (
        Retargeter,
        TargetSkeleton,
        default_humanoid,
    )

    t = target_config
    try:
        target = (
            default_humanoid()
            if t.skeleton == "humanoid"
            else TargetSkeleton.from_bvh(Path(t.skeleton), units=t.bvh_units,
                                         up=t.bvh_up)
        )  # fmt: skip
        spine = spine_stage(t, target, rig)
    except ValueError as exc:
        raise UsageError(f"[target]: {exc} (rig {rig.name})") from None
    rt = Retargeter(
        rig, calibration, target, compensate_base_pose=t.compensate_base_pose
    )
    stance = StanceDetector(rig, calibration)
    try:
        plant = plant_stage(t.feet, rt, stance)
    except ValueError as exc:
        raise UsageError(f"[target] feet = 'plant': {exc}") from None
    if plant is not None and not rate_hz > 0.0:
        raise UsageError("feet = 'plant': the take's frame rate is needed")
    src = solve if stance_solve is None else stance_solve
    if plant is not None:  # the whole take known: each support settled per contact
        states = take_stance_states(
            rig, calibration, np.ascontiguousarray(src.root_pos, dtype=np.float64),
            np.ascontiguousarray(src.world_from_bone_quat, dtype=np.float64), rate_hz,
        )  # fmt: skip
    out = rt.new_pose()
    n_frames, n = len(solve.world_from_bone_quat), len(target.bone_names)
    wfb, rfb = np.empty((n_frames, n, 4)), np.empty((n_frames, n, 4))
    root, hips = np.empty((n_frames, 3)), np.empty((n_frames, 3))
    for k in range(n_frames):
        frame = SimpleNamespace(
            world_from_bone_quat=np.ascontiguousarray(solve.world_from_bone_quat[k]),
            root_pos=np.ascontiguousarray(solve.root_pos[k]),
            bone_flags=np.ascontiguousarray(solve.bone_flags[k]),
        )
        rt.apply(frame, out)  # type: ignore[arg-type]
        if spine is not None:
            spine.apply(out.world_from_bone_quat, out.rest_from_bone_quat)
        wfb[k], rfb[k] = out.world_from_bone_quat, out.rest_from_bone_quat
        root[k], hips[k] = out.root_pos, out.hips_pos
    plant_flags = np.zeros(n_frames, dtype=np.uint32)
    if plant is not None:  # each level off the floor settled per contact, then held
        plant_flags = plant.plant_take(wfb, rfb, root, hips, states, rate_hz)
    arrays = {
        "target_bone_names": np.asarray(target.bone_names, dtype=str),
        "target_world_from_bone_quat": wfb,
        "target_rest_from_bone_quat": rfb,
        "target_root_pos": root,
        "target_spine": np.asarray(t.spine),
        "target_feet": np.asarray(t.feet),
    }
    if plant is not None:
        arrays["target_plant_flags"] = plant_flags
        arrays["target_leg_ratio"] = np.asarray(plant.leg_ratio, dtype=np.float64)
    return arrays


def fill_held_gaps(solve: Any, calibration: Any, max_frames: int) -> tuple[Any, int]:
    """Fill each bone's short runs of held frames by slerp (DESIGN "Slerp at work").

    A bone the solve held (``FLAG_HELD``: too little data) keeps its last good
    rotation and jumps when data returns; a run of at most ``max_frames`` held frames
    with a solved frame on each side is replaced by the slerp of the true
    parent-relative rotation between those two frames
    (:func:`~retargetd.daemon.post.interp.fill_gaps`), the root's position by a line
    when the root bone was held. ``world_from_bone_quat`` (forward kinematics,
    sign-continuous) and ``rest_from_bone_quat`` are recomputed; flags and joint
    centres are kept. Longer runs, and runs at either end of the take, stay held.

    Returns:
        ``(solve, filled)``: the new solve and the bone-frames filled.

    Raises:
        UsageError: ``max_frames`` < 1.
    """
    from retargetd.daemon import rotations as rot
    from retargetd.daemon.body.solve import FLAG_HELD
    from retargetd.daemon.post.interp import fill_gaps, fill_gaps_linear
    from retargetd.daemon.retarget.bvh import world_from_parent_chain

    if max_frames < 1:
        raise UsageError(f"--fill-gaps: expected >= 1 frames; got {max_frames}")
    valid = (np.asarray(solve.bone_flags) & FLAG_HELD) == 0
    q, filled = fill_gaps(
        np.asarray(solve.parent_from_bone_quat, np.float64), valid, max_frames
    )
    root = int(list(solve.bone_parents).index(-1))
    pos, _ = fill_gaps_linear(
        np.asarray(solve.root_pos, np.float64), valid[:, root], max_frames
    )
    wfb = sign_continuous(world_from_parent_chain(solve.bone_parents, q))
    rest = np.asarray(calibration.rest_parent_from_bone_quat, dtype=np.float64)
    rfb = rot.quat_mul(rot.quat_conj(rest), q)
    rfb *= np.where(rfb[..., :1] < 0.0, -1.0, 1.0)
    new = dataclasses.replace(
        solve,
        parent_from_bone_quat=q,
        world_from_bone_quat=wfb,
        rest_from_bone_quat=rfb,
        root_pos=pos,
    )
    return new, int(np.count_nonzero(filled))


def sign_continuous(q: Any) -> Any:
    """(T, B, 4) quaternions with each frame's sign in the hemisphere of the last."""
    out = np.array(q, dtype=np.float64)
    for t in range(1, len(out)):
        flip = np.sum(out[t] * out[t - 1], axis=-1) < 0.0
        out[t, flip] *= -1.0
    return out


def suffix_of(path: str, allowed: tuple[str, ...], *, option: str = "--out") -> str:
    """The lower-case suffix of ``path`` if allowed, else a UsageError listing them."""
    suffix = path.lower().rsplit(".", 1)[-1] if "." in Path(path).name else ""
    if suffix not in allowed:
        dotted = [f".{s}" for s in allowed]
        listed = (
            dotted[0]
            if len(dotted) == 1
            else ", ".join(dotted[:-1]) + f" or {dotted[-1]}"
        )
        raise UsageError(f"{option}: expected a {listed} file; got {path!r}")
    return suffix


def write_clip(
    path: str,
    clip: Any,
    calibration: Any,
    *,
    bvh_order: str | None = None,
    travel_m: Any = None,
    humanoid: Any = None,
    glb_mesh: str = "none",
    extra: dict[str, Any] | None = None,
) -> None:
    """Write a clip as ``.glb`` (every frame), ``.bvh`` or ``.npz``.

    NPZ (``numpy.load(..., allow_pickle=False)``): ``bone_names`` (B,),
    ``bone_parents`` (B,) int64, ``parent_from_bone_quat`` (T, B, 4) w x y z (true
    parent-relative), ``world_from_bone_quat`` (T, B, 4) w x y z, ``root_pos`` (T, 3)
    metres world, ``rate_hz``, and for a loop ``travel_m`` (3,) metres (the root's
    travel per cycle).

    Args:
        path: the output file; its suffix picks the format.
        clip: a :class:`~retargetd.daemon.post.interp.Clip` of the calibration's bones.
        calibration: the calibrated skeleton.
        bvh_order: BVH channel order (default ZXY).
        travel_m: optional (3,) float64 metres, stored in the NPZ.
        humanoid: (B,) humanoid name per bone or ``""`` (:func:`humanoid_names`):
            glTF node names.
        glb_mesh: glTF: ``"none"`` or ``"capsules"`` (``--glb-mesh``).
        extra: more NPZ arrays (``--plant-feet``'s ``target_*``: :func:`plant_clip`).

    Raises:
        UsageError: a bad suffix, or a calibration that cannot be exported.
    """
    from retargetd.daemon.body.calibration import CalibrationError
    from retargetd.daemon.post.export_gltf import write_clip_glb
    from retargetd.daemon.retarget.bvh import (
        DEFAULT_ROTATION_ORDER,
        world_from_parent_chain,
        write_clip_bvh,
    )

    suffix = suffix_of(path, CLIP_SUFFIXES)
    try:
        if suffix == "glb":
            write_clip_glb(path, clip, calibration, humanoid=humanoid, mesh=glb_mesh)
        elif suffix == "bvh":
            write_clip_bvh(
                path, calibration, clip.parent_from_bone_quat, clip.root_pos,
                clip.rate_hz, rotation_order=bvh_order or DEFAULT_ROTATION_ORDER,
            )  # fmt: skip
        else:
            arrays: dict[str, Any] = {
                "bone_names": np.asarray(calibration.bone_names, dtype=str),
                "bone_parents": np.asarray(calibration.bone_parents, dtype=np.int64),
                "parent_from_bone_quat": clip.parent_from_bone_quat,
                "world_from_bone_quat": world_from_parent_chain(
                    calibration.bone_parents, clip.parent_from_bone_quat
                ),
                "root_pos": clip.root_pos,
                "rate_hz": np.float64(clip.rate_hz),
            }
            if travel_m is not None:
                arrays["travel_m"] = np.asarray(travel_m, dtype=np.float64)
            arrays.update(extra or {})
            np.savez(path, **arrays)
    except CalibrationError as exc:
        raise UsageError(str(exc)) from None


def check_bvh_order(option: str, value: str) -> str:
    """The canonical BVH channel order, or a UsageError that says which BVH can hold.

    BVH lists one rotation channel per axis (``Zrotation Xrotation Yrotation``,
    composed ``R = R_Z R_X R_Y`` in the listed order), so it can express only the 6
    Tait-Bryan orders, read as channel orders (intrinsic); the 6 proper Euler orders
    repeat an axis and need three channels about two axes, which BVH has not.
    """
    from retargetd.replay.bvh import ROTATION_ORDERS, normalize_rotation_order

    try:
        return normalize_rotation_order(value)
    except ValueError:
        raise UsageError(
            f"{option}: BVH can express only the 6 Tait-Bryan channel orders "
            f"{', '.join(ROTATION_ORDERS)} (one channel per axis, composed in the "
            f"listed order); got {value!r}. Proper Euler orders (XYX, ZXZ, ...) repeat "
            "an axis: use --out take.csv --euler-order ORDER for those"
        ) from None


def solved_take(args: argparse.Namespace) -> tuple[Any, Any, Any, Any]:
    """Solve ``args.take`` (:func:`retargetd.daemon.cli.args.solver_for_take`) and
    apply ``--pipeline`` when given.

    Returns:
        ``(rig, take, calibration, solve)``.

    Raises:
        UsageError: bad input (one line, exit 2).
    """
    from retargetd.daemon.cli.args import solve_take_progress, solver_for_take

    rig, take, cal, solver = solver_for_take(args)
    quiet = getattr(args, "quiet", False)
    res = solve_take_progress(
        solver, take.positions, quiet=quiet, causal=getattr(args, "causal", False)
    )
    if getattr(args, "pipeline", None) is not None:
        res, _ = apply_pipeline_to_solve(args.pipeline, res, cal, take.rate_hz)
    return rig, take, cal, res


def solve_other_take(
    args: argparse.Namespace, path: str, rig: Any, calibration: Any
) -> tuple[Any, Any]:
    """Solve a second take with the first one's rig and calibration (``blend``'s B).

    Returns:
        ``(take, solve)``.
    """
    from retargetd.daemon.body.calibration import CalibrationError
    from retargetd.daemon.cli.args import solver_of_method, take_overrides
    from retargetd.replay.takes import load_take

    take = load_take(path, **take_overrides(args))
    try:  # the method the first take was solved with
        solver = solver_of_method(args, rig, calibration, take.labels, take.rate_hz)
    except CalibrationError as exc:
        raise UsageError(f"{path}: {exc}") from None
    from retargetd.daemon.cli.args import solve_take_progress

    res = solve_take_progress(
        solver,
        take.positions,
        quiet=getattr(args, "quiet", False),
        causal=getattr(args, "causal", False),
    )
    if getattr(args, "pipeline", None) is not None:
        res, _ = apply_pipeline_to_solve(args.pipeline, res, calibration, take.rate_hz)
    return take, res


def clip_of(solve: Any, calibration: Any, rate_hz: float, what: str) -> Any:
    """The solve as a :class:`~retargetd.daemon.post.interp.Clip`.

    Raises:
        UsageError: non-finite rotations or root (naming ``what``).
    """
    from retargetd.daemon.post.export_gltf import clip_from_solve

    clip = clip_from_solve(solve, calibration, rate_hz)
    if not (
        np.isfinite(clip.parent_from_bone_quat).all()
        and np.isfinite(clip.root_pos).all()
    ):
        raise UsageError(f"{what}: the solve has non-finite rotations or root")
    return clip


def pose_steps_deg(quat: Any) -> Any:
    """(T-1,) float64 degrees: RMS rotation between consecutive poses (root
    excluded, :func:`retargetd.daemon.post.interp.pose_distance`)."""
    from retargetd.daemon.post.interp import pose_distance

    return np.degrees(pose_distance(quat[:-1], quat[1:]))
