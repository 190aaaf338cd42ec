"""The pipeline of one performer on one stream (or view): everything that depends on
(rig, calibration, face training set, label set), built off the loop when one of them
changes (:func:`start_build` on a worker thread, ``rebuild.py``) and reused for every
frame (``send.BodyPath``).

A build reads only its :class:`PipelineSpec`, taken in the loop when it was asked
for (the performer's rig, calibration and training set, the config, the target, the
labels and the names id then); the loop's side of a new pipeline (the post stages'
names in the latency stats) is :func:`adopt`, at the swap.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from retargetd.daemon.body.solve import BodySolver
from retargetd.daemon.body.solve_fit import FitSolver
from retargetd.daemon.live import rebuild
from retargetd.daemon.live.emit import EmitPlan
from retargetd.daemon.live.face import FaceStage
from retargetd.daemon.live.performer import Performer
from retargetd.daemon.live.rebuild import Build
from retargetd.daemon.live.shared import Shared
from retargetd.daemon.live.solve_emit import AVAILABLE as SOLVE_EMIT_AVAILABLE
from retargetd.daemon.live.solve_emit import SolveEmit
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
    # the body solve and the emit in one call, when nothing runs between them
    # (live/solve_emit.py; None: the solve's call, then the emit's)
    solve_emit: SolveEmit | None = None
    stance: StanceDetector | None = None  # foot contact (post/stance.py)
    stance_bits: int = 0  # its FRAME_CONTACT_* bits for the latest solved frame
    plant: FootPlant | None = None  # [target] feet = "plant", after the retarget
    # the last solved frame's source time, frame number and receive time (the fit's
    # frame time, BodyPath._frame_dt_s)
    last_times: tuple[float, int, int] = (math.nan, -1, 0)
    # the (rig, calibration, face training set) it was built for: another one is
    # rebuilt off the loop (rebuild.py)
    built_for: tuple[Any, ...] = (None, None, None)
    # the stream columns it reads (the body solver's and the face's, -1: absent):
    # a new label set keeping their markers is solved by it until its own is built
    cols: tuple[int, ...] = field(default=())


@dataclass(frozen=True, slots=True, kw_only=True)
class PipelineSpec:
    """What one pipeline is built from, taken in the loop (:meth:`of`): a build on
    the worker reads nothing else."""

    name: str  # the performer's
    index: int
    max_datagram: int  # its VMC destination's
    face: Any  # its LiveFace (its config, never its changing state) or None
    training: Any  # the face training set then (None: no face solve)
    rig: Any
    calibration: Any
    labels: tuple[str, ...]
    config: Any  # DaemonConfig
    target: Any
    names_id: int

    @classmethod
    def of(
        cls, perf: Performer, sh: Shared, labels: tuple[str, ...], with_face: bool
    ) -> PipelineSpec:
        """``perf``'s pipeline for ``labels`` as things are now (the next names id
        taken: a build never used leaves its id unused)."""
        face = perf.face if with_face else None
        return cls(
            name=perf.name, index=perf.index, max_datagram=perf.vmc.max_datagram,
            face=face, training=face.training if face is not None else None,
            rig=perf.rig, calibration=perf.calibration, labels=labels,
            config=sh.config, target=sh.target, names_id=sh.next_names_id(),
        )  # fmt: skip

    @property
    def want(self) -> tuple[Any, ...]:
        """What it is built for, compared by identity (``Build.wants``)."""
        return (self.rig, self.calibration, self.training, self.labels)


def start_build(perf: Performer, sh: Shared, labels: tuple[str, ...]) -> Build:
    """``perf``'s pipeline for ``labels`` (with its face) built on a worker thread
    from now (``rebuild.Build``; its ``want``: :attr:`PipelineSpec.want`)."""
    spec = PipelineSpec.of(perf, sh, labels, True)
    return Build(spec.want, make_pipeline, spec)


def adopt(pipe: Pipeline, sh: Shared) -> Pipeline:
    """The loop's side of a new pipeline: its post stages named in the stats."""
    if pipe.post is not None:
        sh.stats.set_post_stages(pipe.post.stage_names)
    return pipe


def new_pipeline(
    perf: Performer,
    sh: Shared,
    labels: tuple[str, ...],
    *,
    with_face: bool = True,
    solver: Any = None,
) -> Pipeline:
    """A new pipeline of ``perf`` for a stream of ``labels`` (with the face stage
    unless ``with_face`` is False), built now in the calling thread (the warm-up,
    tests); its names id is the next of ``sh``. ``solver``: its body solver, built
    already, else built here."""
    spec = PipelineSpec.of(perf, sh, labels, with_face)
    return adopt(make_pipeline(spec, solver), sh)


def make_pipeline(spec: PipelineSpec, solver: Any = None) -> Pipeline:
    """The pipeline ``spec`` describes, reading nothing else (any thread may call
    it: the worker's job). ``solver``: its body solver, built already."""
    config, rig, calibration, target = (
        spec.config, spec.rig, spec.calibration, spec.target
    )  # fmt: skip
    labels = spec.labels
    assert calibration is not None
    if solver is None:  # (through the module: tests hold the worker's builds)
        solver = rebuild.body_solver(config.solve.method, rig, calibration, labels,
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
    names_id = spec.names_id
    n_bones = len(rig.bones)
    face = None
    if spec.face is not None and spec.training is not None:
        face = spec.face.stage(labels, spec.training)
    weight_names = face.weight_names if face is not None else ()
    face_markers = face.marker_names if face is not None else ()
    names_msg = pose_stream.PoseNames(
        rig=rig.name,
        bone_names=rig.bone_names,
        bone_parents=rig.bone_parent_indices(),
        weight_names=weight_names,
        names_id=names_id,
        face_markers=face_markers,
        performer=spec.name,
        performer_id=spec.index,
        bone_humanoid=tuple(b.humanoid or "" for b in rig.bones),
        unobserved=face.unobserved if face is not None else (),
    )
    vmc = VmcEncoder(
        names,
        face.output_names if face is not None else (),
        max_datagram=spec.max_datagram,
    )
    pose_enc = pose_stream.PoseEncoder(
        n_bones,
        len(weight_names),
        names_id=names_id,
        n_face_markers=len(face_markers) if face is not None else None,
        performer=spec.index,
    )
    emit = EmitPlan(retargeter, vmc, pose_enc, bone_pos_unity)
    stance = StanceDetector(rig, calibration)
    pose = solver.new_pose()
    blend = face.blend if face is not None else np.zeros(0)
    weights = face.weights if face is not None else np.zeros(0)
    post = _post_stages(spec)
    spine = spine_stage(config.target, target, rig)
    plant = plant_stage(config.target.feet, retargeter, stance)
    # Nothing between the solve and the emit: the emit call finds the contact too.
    alone = post is None and spine is None and plant is None
    emit.bind(pose, blend, weights, stance if alone else None)
    # No face either, and the contact (if any) inside the emit: the solve joins
    # the emit's call (the loop uses it while no live validator runs).
    fused = None
    if SOLVE_EMIT_AVAILABLE and alone and face is None and emit.stance is not None:
        fused = SolveEmit(solver, pose, emit)
    cols = [int(c) for c in solver.marker_cols]
    if face is not None:
        cols += face.solver.columns()
    return Pipeline(
        built_for=(rig, calibration, spec.training),
        cols=tuple(cols),
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
        post=post,
        spine=spine,
        plant=plant,
        emit=emit,
        solve_emit=fused,
        stance=stance,
    )


def _post_stages(spec: PipelineSpec) -> SolvePost | None:
    """The ``[[pipeline]]`` stages for ``spec``'s rig and calibration (fresh
    state; their names go into the stats at :func:`adopt`)."""
    config, rig, calibration = spec.config, spec.rig, spec.calibration
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
    return SolvePost(stages, parents, rest, output_rate_hz=rate)


def may_fuse(config: Any) -> bool:
    """Whether a pipeline of the daemon's ``config`` (``DaemonConfig``) can run its
    solve and emit in one call (:func:`new_pipeline`'s ``fused``): not with an
    output rate, the spine pivot or the foot plant, which last the daemon's life.
    The ``[[pipeline]]`` stages (a reload), a face (the stream's labels) and the
    live validator (while it builds, or after its build failed) come and go, so
    they do not rule it out. The daemon's start warms the fused kernel only then
    (its cache load ~0.3-0.5 s, its compile 15-30 s on this VM)."""
    return (
        SOLVE_EMIT_AVAILABLE
        and not config.loop.output_rate_hz > 0.0
        and config.target.spine != "pivot"
        and config.target.feet != "plant"
    )


def warm_up_pipeline(perf: Performer, sh: Shared) -> None:
    """Run every stage of a throwaway pipeline of ``perf`` once (its calibration
    needed), so that no streamed frame pays for a first call: the solve, the
    retarget, the stance detector, and the ``[[pipeline]]`` stages, spine pivot and
    foot plant that compile on their first finite pose."""
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
    # The stance detector, the [[pipeline]] stages, the spine pivot and the foot
    # plant compile on their first solved (finite) pose: the stance detector on the
    # soak's first solved frame, 2.3 s of the loop (1.1 s of it on a CPU, at load
    # 4.9; issue 35), a twist and a One Euro stage 4.1 s into the stream (measured,
    # cold caches). Run them here on the rest pose, two frames apart (the filters'
    # and the detector's second-frame path), so no streamed frame pays for it.
    pose.parent_from_bone_quat[:] = calibration.rest_parent_from_bone_quat
    pose.root_pos[:] = 0.0
    now_ns = time.monotonic_ns()
    tp = pipe.target_pose
    for k in range(2):
        if pipe.stance is not None:  # (live: send.py, before the post stages)
            pipe.stance_bits = pipe.stance.update(
                pose.root_pos, pose.world_from_bone_quat, k * 0.01
            )
        if pipe.post is not None:
            t_ns = now_ns + k * 10_000_000
            pipe.post.apply(pose, k * 0.01, t_ns, k)
            pipe.post.pop_due(pose, t_ns)
        pipe.retargeter.apply(pose, tp)
        if pipe.spine is not None:
            pipe.spine.apply(tp.world_from_bone_quat, tp.rest_from_bone_quat)
        if pipe.plant is not None:
            pipe.plant.apply_pose(tp)
    fused = pipe.solve_emit
    if fused is not None:  # the solve and the emit in one call: its own kernel
        fused.call(
            fused.what, nan_frame, *fused.args, sh.t0_ns, 0, math.nan, now_ns, 0, 0.0
        )
    pipe.solver.reset()
    sh.names_id -= 1  # this pipeline is thrown away; keep the ids dense
