"""The pipeline of one performer on one stream (or view): everything that depends on
(rig, calibration, label set), built off the hot path when one of them changes
(:func:`new_pipeline`) and reused for every frame (``send.BodyPath``).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from retargetd.daemon.body.solve import BodySolver
from retargetd.daemon.body.solve_fit import FitSolver
from retargetd.daemon.live.emit import EmitPlan
from retargetd.daemon.live.face import FaceStage
from retargetd.daemon.live.performer import Performer
from retargetd.daemon.live.rebuild import Rebuild, body_solver
from retargetd.daemon.live.shared import Shared
from retargetd.daemon.post.pipeline import build_pipeline
from retargetd.daemon.post.pivot import SpinePivot, spine_stage
from retargetd.daemon.post.plant import FootPlant, plant_stage
from retargetd.daemon.post.solve_post import SolvePost
from retargetd.daemon.post.stance import StanceDetector
from retargetd.daemon.retarget.retarget import Retargeter
from retargetd.protocols import engine_unity, pose_stream
from retargetd.protocols.vmc_out import VmcEncoder

logger = logging.getLogger(__name__)


@dataclass(slots=True)
class Pipeline:
    """Everything that depends on (rig, calibration, label set); rebuilt off the hot
    path when one of them changes."""

    solver: BodySolver | FitSolver
    retargeter: Any
    pose: Any
    target_pose: Any
    vmc: VmcEncoder
    bone_pos_unity: np.ndarray
    bone_quat_xyzw: np.ndarray
    root_pos_unity: np.ndarray
    root_quat_xyzw: np.ndarray
    blend: np.ndarray
    pose_enc: pose_stream.PoseEncoder
    names_parts: list[bytes]
    weights: np.ndarray
    bone_flags: np.ndarray  # sent bone flags: the solve's | the latest validation's
    face: FaceStage | None = None
    # the face's shape-state message (RTDF, after each pose with a face)
    shape_enc: pose_stream.ShapeStateEncoder | None = None
    post: SolvePost | None = None  # the [[pipeline]] stages (None: none configured)
    tick_source_clock: bool = True  # resampled ticks' times are the source's clock
    spine: SpinePivot | None = None  # [target] spine = "pivot", after the retarget
    emit: EmitPlan | None = None  # the one compiled call per frame (live/emit.py)
    stance: StanceDetector | None = None  # foot contact (post/stance.py)
    stance_bits: int = 0  # its FRAME_CONTACT_* bits for the latest solved frame
    plant: FootPlant | None = None  # [target] feet = "plant", after the retarget
    # the last solved frame's source time, frame number and receive time (the fit's
    # frame time, BodyPath._frame_dt_s)
    last_times: tuple[float, int, int] = (math.nan, -1, 0)
    # the (rig, calibration) it was built for: another one is rebuilt (rebuild.py)
    built_for: tuple[Any, Any] = (None, None)
    rebuild: Rebuild | None = None  # its successor's body solver, being built


def new_pipeline(
    perf: Performer,
    sh: Shared,
    labels: tuple[str, ...],
    *,
    with_face: bool = True,
    solver: Any = None,
) -> Pipeline:
    """A new pipeline of ``perf`` for a stream of ``labels`` (with the face stage
    unless ``with_face`` is False); its names id is the next of ``sh``. ``solver``:
    its body solver, built already (off the loop: rebuild.py), else built here."""
    config, rig, calibration, target = (
        sh.config,
        perf.rig,
        perf.calibration,
        sh.target,
    )
    assert calibration is not None
    if solver is None:
        solver = body_solver(config.solve.method, rig, calibration, labels,
                             config.validate.rate_hz)  # fmt: skip
    if solver.missing_markers:
        logger.warning(
            "rig %s markers not in the stream (occluded): %s",
            rig.name,
            " ".join(solver.missing_markers),
        )
    retargeter = Retargeter(
        rig, calibration, target,
        compensate_base_pose=config.target.compensate_base_pose,
    )  # fmt: skip
    target_pose = retargeter.new_pose()
    names = tuple(target.bone_names)
    n = len(names)
    bone_pos_unity = np.zeros((n, 3))
    engine_unity.unity_pos_from_world(
        np.asarray(target_pose.rest_offsets, dtype=np.float64), bone_pos_unity
    )
    names_id = sh.next_names_id()
    n_bones = len(rig.bones)
    face = None
    if with_face and perf.face is not None:
        face = perf.face.stage(labels)
    weight_names = face.weight_names if face is not None else ()
    face_markers = face.marker_names if face is not None else ()
    names_msg = pose_stream.PoseNames(
        rig=rig.name,
        bone_names=rig.bone_names,
        bone_parents=rig.bone_parent_indices(),
        weight_names=weight_names,
        names_id=names_id,
        face_markers=face_markers,
        performer=perf.name,
        performer_id=perf.index,
        bone_humanoid=tuple(b.humanoid or "" for b in rig.bones),
        unobserved=face.unobserved if face is not None else (),
    )
    vmc = VmcEncoder(
        names,
        face.output_names if face is not None else (),
        max_datagram=perf.vmc.max_datagram,
    )
    pose_enc = pose_stream.PoseEncoder(
        n_bones,
        len(weight_names),
        names_id=names_id,
        n_face_markers=len(face_markers) if face is not None else None,
        performer=perf.index,
    )
    emit = EmitPlan(retargeter, vmc, pose_enc, bone_pos_unity)
    stance = StanceDetector(rig, calibration)
    pose = solver.new_pose()
    blend = face.blend if face is not None else np.zeros(0)
    weights = face.weights if face is not None else np.zeros(0)
    emit.bind(pose, blend, weights)
    return Pipeline(
        built_for=(rig, calibration),
        solver=solver,
        retargeter=retargeter,
        pose=pose,
        target_pose=emit.target_pose,
        vmc=vmc,
        bone_pos_unity=bone_pos_unity,
        bone_quat_xyzw=np.zeros((n, 4)),
        root_pos_unity=np.zeros(3),
        root_quat_xyzw=np.array([0.0, 0.0, 0.0, 1.0]),
        blend=blend,
        pose_enc=pose_enc,
        names_parts=pose_stream.encode_pose_names(names_msg),
        weights=weights,
        bone_flags=np.zeros(n_bones, dtype=np.uint8),
        face=face,
        shape_enc=(
            pose_stream.ShapeStateEncoder(len(weight_names), names_id)
            if face is not None
            else None
        ),
        post=_post_stages(perf, sh),
        spine=spine_stage(config.target, target, rig),
        plant=plant_stage(config.target.feet, retargeter, stance),
        emit=emit,
        stance=stance,
    )


def _post_stages(perf: Performer, sh: Shared) -> SolvePost | None:
    """The ``[[pipeline]]`` stages for ``perf``'s rig and calibration (fresh
    state)."""
    config, rig, calibration = sh.config, perf.rig, perf.calibration
    rate = config.loop.output_rate_hz
    if not config.pipeline and not rate > 0.0:
        return None
    assert calibration is not None
    parents = rig.bone_parent_indices()
    rest = np.asarray(calibration.rest_parent_from_bone_quat, np.float64)
    stages = build_pipeline(
        config.pipeline,
        bone_names=rig.bone_names,
        bone_parents=parents,
        rest_parent_from_bone_quat=rest,
    )
    post = SolvePost(stages, parents, rest, output_rate_hz=rate)
    sh.stats.set_post_stages(post.stage_names)
    return post


def warm_up_pipeline(perf: Performer, sh: Shared) -> None:
    """Run every stage of a throwaway pipeline of ``perf`` once (its calibration
    needed), so that no streamed frame pays for a first call: the solve, the
    retarget, and the ``[[pipeline]]`` stages and spine pivot that compile on their
    first finite pose."""
    calibration = perf.calibration
    if calibration is None:
        return
    # A stream naming every marker as the rig's labels do (its names need not
    # be labels: such a warm-up would call every marker missing).
    labels = tuple(aliases[0] for aliases in perf.rig.markers.values())
    pipe = new_pipeline(perf, sh, labels, with_face=False)
    nan_frame = np.full((len(labels), 3), np.nan)
    pose = pipe.solver.solve_frame(nan_frame, pipe.pose)
    pipe.retargeter.apply(pose, pipe.target_pose)
    # The [[pipeline]] stages and the spine pivot compile on their first finite
    # pose (a twist and a One Euro stage: 4.1 s into the stream on a cold cache,
    # measured): run them here on the rest pose, two frames apart (the filters'
    # second-frame path), so no streamed frame pays for it.
    if pipe.post is not None or pipe.spine is not None:
        pose.parent_from_bone_quat[:] = calibration.rest_parent_from_bone_quat
        pose.root_pos[:] = 0.0
        now_ns = time.monotonic_ns()
        for k in range(2):
            if pipe.post is not None:
                t_ns = now_ns + k * 10_000_000
                pipe.post.apply(pose, k * 0.01, t_ns, k)
                pipe.post.pop_due(pose, t_ns)
        if pipe.spine is not None:
            tp = pipe.target_pose
            pipe.retargeter.apply(pose, tp)
            pipe.spine.apply(tp.world_from_bone_quat, tp.rest_from_bone_quat)
    pipe.solver.reset()
    sh.names_id -= 1  # this pipeline is thrown away; keep the ids dense
