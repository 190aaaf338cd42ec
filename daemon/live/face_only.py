"""A performer with a face and no body (``body = false``): the face solved and sent on
its own, with no rig calibration (a head-mounted or seated facial capture).

Per frame of its markers: the face stage (``face.FaceStage``, the same solver as
``retargetd solve --face``), then

- the pose stream: a data message with 0 bones, the solved weights and the face part
  (stabilized markers, face flags, ``world_from_head`` from the head markers); the
  header's root position is the head's (``head_pos_world``); then its ``RTDF``
  shape states. The names message has no bones (``rig`` "").
- VMC: the blendshapes alone (``vmc_out.BlendEncoder``: no Root/Pos, no Bone/Pos).

No training set yet: the frame is counted unsolved, as a body before its calibration.
A face capture (``ctl face-capture``) works as with a body. A stream's stage (its
solver bound to the labels, its encoders) is built off the loop (``rebuild.py``) for
each label set and training set: while one is built, the old stage solves if it reads
the same markers (a new training set, or a label set that keeps them); else the frame
is counted unsolved. ``ctl calibrate`` is
refused for it (nothing to calibrate).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from retargetd.daemon.live.face import FaceStage
from retargetd.daemon.live.performer import FrameSource, Performer
from retargetd.daemon.live.rebuild import Build, build_failed, reads_same, same_want
from retargetd.daemon.live.shared import Shared
from retargetd.protocols import pose_stream
from retargetd.protocols.vmc_out import BlendEncoder

logger = logging.getLogger(__name__)


@dataclass(slots=True, eq=False)
class FaceOnlyStage:
    """The per-stream encoders of a face-only performer (built off the hot path)."""

    face: FaceStage
    labels: tuple[str, ...]
    pose_enc: pose_stream.PoseEncoder
    names_parts: list[bytes]
    shape_enc: pose_stream.ShapeStateEncoder
    vmc: BlendEncoder
    no_quat: np.ndarray  # (0, 4)
    no_flags: np.ndarray  # (0,) uint8
    training: Any = None  # the training set it was built for
    cols: tuple[int, ...] = ()  # the stream columns it reads (-1: absent)


def build_stage(
    face: Any, labels: tuple[str, ...], training: Any, names_id: int, name: str,
    index: int, max_datagram: int,
) -> FaceOnlyStage:  # fmt: skip
    """A face-only stage for ``labels`` and ``training``, reading only its arguments
    (any thread may call it: a build off the loop, ``rebuild.py``).

    Args:
        face: the performer's ``LiveFace`` (its config: ``stage`` reads no state).
        labels: (M,) the stream's labels.
        training: the training set to solve with.
        names_id: its names message's id (taken in the loop).
        name, index: the performer's name and pose-stream id.
        max_datagram: its VMC destination's largest datagram, bytes.
    """
    stage = face.stage(labels, training)
    names = pose_stream.PoseNames(
        rig="", bone_names=(), bone_parents=(), weight_names=stage.weight_names,
        names_id=names_id, face_markers=stage.marker_names,
        performer=name, performer_id=index, unobserved=stage.unobserved,
    )  # fmt: skip
    return FaceOnlyStage(
        face=stage,
        labels=labels,
        pose_enc=pose_stream.PoseEncoder(
            0,
            len(stage.weight_names),
            names_id=names_id,
            n_face_markers=len(stage.marker_names),
            performer=index,
        ),
        names_parts=pose_stream.encode_pose_names(names),
        shape_enc=pose_stream.ShapeStateEncoder(len(stage.weight_names), names_id),
        vmc=BlendEncoder(stage.output_names, max_datagram),
        no_quat=np.zeros((0, 4)),
        no_flags=np.zeros(0, np.uint8),
        training=training,
        cols=tuple(stage.solver.columns()),
    )


class FacePath:
    """The frame path of a performer without a body: the face solved and sent.
    The same calls as :class:`~retargetd.daemon.live.send.BodyPath`; those about a
    body (pipelines, validation, the VMC calibration state) do nothing.

    Args:
        perf: the performer (its face, VMC destination).
        shared: the loop's side (config, counters, outputs, clocks).
    """

    validator: Any = None  # no body: nothing to validate

    def __init__(self, perf: Performer, shared: Shared) -> None:
        self.perf = perf
        self.shared = shared
        self.stages: dict[int, FaceOnlyStage] = {}  # id(stream or view) -> stage
        self.builds: dict[int, Build] = {}  # its next stage, built off the loop
        # id(stream or view) -> what its last build was for, when it raised
        # (as pipelines.Pipelines.failed)
        self.failed: dict[int, tuple[Any, ...]] = {}
        self.pipelines: dict[int, Any] = {}  # none: no body
        self.last_names_ns = 0
        self.frame_flags = 0

    def flag(self, bits: int) -> None:
        """Frame flags for the next pose (restarted, input dropped)."""
        self.frame_flags |= bits

    def announce_names(self) -> None:
        """The next pose is preceded by its names message."""
        self.last_names_ns = 0

    def match_status(self) -> dict[str, Any] | None:
        """No body: no calibration to match."""
        return None

    def resend_held(self, key: int, now_ns: int) -> tuple[bool, bool]:
        """Nothing held is sent again for a face alone."""
        return False, False

    def warm_up(self) -> None:
        """Nothing to warm (the face kernels warm up with the loop's)."""

    def restart(self, key: int) -> None:
        """The source of ``key`` restarted: its face solve starts over."""
        stage = self.stages.get(key)
        if stage is not None:
            stage.face.solver.reset()

    def rebuild(self, labels: tuple[str, ...], sources: list[FrameSource]) -> None:
        """The face's training set changed: the stages of the ``sources`` carrying
        ``labels`` are built with it off the loop from now, the old ones solving
        meanwhile (the others' when their next frame comes)."""
        for s in sources:
            if s.current.label_set.labels == labels:
                self.prepare(id(s), labels)

    def renew(self, labels: tuple[str, ...], sources: list[FrameSource]) -> None:
        """Nothing to renew (no body pipelines)."""

    def send_due_ticks(self, now_ns: int) -> None:
        """No resampled body ticks."""

    def next_tick_ns(self) -> int:
        """No resampled body ticks: -1."""
        return -1

    def send_vmc_state(self, now_ns: int, calibrating: bool) -> None:
        """No calibration state to tell (no body)."""

    def validation_status(self) -> dict[str, Any] | None:
        """No body, no validator: None."""
        return None

    def start_validator(self, wait: bool = False) -> None:
        """No body to validate."""

    def tick_validator(self) -> None:
        """No validator to swap in."""

    def validator_building(self) -> bool:
        """No validator: False."""
        return False

    def close(self) -> None:
        """Nothing to stop."""

    def occluded_and_held(self) -> tuple[list[str], list[str]]:
        """No body: no rig markers or bones to report."""
        return [], []

    def _stage(self, stream: FrameSource) -> FaceOnlyStage | None:
        """``stream``'s stage for its labels and the face's training set now; while
        that is built off the loop, the old one when it reads the same markers; else
        None (no training set, or nothing built that can solve the frame yet)."""
        face = self.perf.face
        training = face.training if face is not None else None
        labels = stream.current.label_set.labels
        key = id(stream)
        stage = self.stages.get(key)
        if stage is not None and stage.labels == labels and stage.training is training:
            return stage
        if training is None:  # no training set yet
            self.stages.pop(key, None)
            return None
        failed = self.failed.get(key)
        if failed is not None:
            if same_want(failed, (training, labels)):
                return None  # its build raised: counted unsolved_failed
            del self.failed[key]
        job = self._job(key, labels)
        if self.shared.config.loop.process_every_frame:  # offline replay: every
            if job is None:  # frame solved (as pipelines.Pipelines)
                self.builds[key].wait()
                job = self._job(key, labels)
            if job is not None:
                job.wait()
        if job is not None and job.done():
            del self.builds[key]
            try:
                stage = self.stages[key] = job.take()
            except Exception as exc:  # counted and said; the loop goes on
                self.failed[key] = job.want
                sh = self.shared
                build_failed(
                    self.perf.name, sh.stats, sh.out, "face stage", len(labels), exc
                )
                return None
            self.shared.stats.pipeline_builds += 1
            self.last_names_ns = 0  # its names go out with this frame
            return stage
        if stage is not None and reads_same(stage.labels, labels, stage.cols):
            return stage  # the old stage, until the new one is built
        return None

    def _job(self, key: int, labels: tuple[str, ...]) -> Build | None:
        """The build of ``key``'s stage for ``labels`` and the training set now:
        the one under way, else one started now; None while one for anything else
        still runs (one at a time per stream, as ``pipelines.Pipelines``)."""
        perf = self.perf
        face = perf.face
        assert face is not None and face.training is not None
        want = (face.training, labels)
        job = self.builds.get(key)
        if job is not None and not job.wants(want) and not job.done():
            return None
        if job is None or not job.wants(want):
            names_id = self.shared.next_names_id()
            job = self.builds[key] = Build(
                want, build_stage, face, labels, face.training, names_id, perf.name,
                perf.index, perf.vmc.max_datagram,
            )  # fmt: skip
        return job

    def prepare(self, key: int, labels: tuple[str, ...]) -> None:
        """A stream (or view) ``key`` took a label set: its stage's build starts
        now (off the loop) when there is a training set."""
        face = self.perf.face
        if face is None or face.training is None or not labels:
            return
        failed = self.failed.get(key)
        if failed is not None and same_want(failed, (face.training, labels)):
            return  # (the same as the one that raised: not again)
        stage = self.stages.get(key)
        if (
            stage is None
            or stage.labels != labels
            or stage.training is not face.training
        ):
            self._job(key, labels)

    def ready(self, key: int, labels: tuple[str, ...]) -> bool:
        """Whether a frame of ``labels`` on ``key`` would now be solved by its own
        stage (no training set: nothing to build). Reads only (tests)."""
        face = self.perf.face
        if face is None or face.training is None:
            return True
        stage = self.stages.get(key)
        if (
            stage is not None
            and stage.labels == labels
            and stage.training is face.training
        ):
            return True
        job = self.builds.get(key)
        return job is not None and job.wants((face.training, labels)) and job.done()

    def done_building(self, timeout_s: float) -> bool:
        """Wait until every build under way has ended (tests); False on timeout."""
        deadline = time.monotonic() + timeout_s
        return all(
            job.wait(max(0.0, deadline - time.monotonic()))
            for job in list(self.builds.values())
        )

    def begin(self, stream: FrameSource, received_ns: int) -> bool:
        """As ``BodyPath.begin``: the face's frame is done in :meth:`finish`."""
        return True

    def solve_begun(self) -> None:
        """No body to solve (the face is solved in :meth:`finish`, on the loop)."""

    def finish(self, stream: FrameSource, received_ns: int, turn_ns: int = 0) -> None:
        """The whole frame (:meth:`process`, its clock started there), in its turn
        among the performers."""
        self.process(stream, received_ns)

    def process(self, stream: FrameSource, received_ns: int) -> None:
        """The face-only performer's frame: solve, then the pose stream and VMC."""
        t_start = time.monotonic_ns()
        stage = self._stage(stream)
        sh = self.shared
        stats, outputs = sh.stats, sh.outputs
        if stage is None:
            stats.unsolved += 1
            if id(stream) in self.failed:  # its stage's build raised
                stats.unsolved_failed += 1
                self.frame_flags |= pose_stream.FRAME_INPUT_DROPPED
            elif self.builds:  # its stage being built (rebuild.py)
                stats.unsolved_building += 1
                self.frame_flags |= pose_stream.FRAME_INPUT_DROPPED
            return
        vmc = self.perf.vmc
        frame = stream.current.frame
        fo = stage.face.solve(frame.markers_world, frame.valid)
        stats.face_solved += 1
        if fo.status[0] & pose_stream.FACE_HEAD_LOST:
            stats.face_head_lost += 1
        solved_ns = time.monotonic_ns()
        stats.frames_solved += 1
        flags = self.frame_flags
        self.frame_flags = 0
        if vmc.on:
            vmc.send(stage.vmc.encode(stage.face.blend, (solved_ns - sh.t0_ns) * 1e-9))
        if outputs.publishing:
            if solved_ns - self.last_names_ns >= 1_000_000_000:
                outputs.send_pub(stage.names_parts, solved_ns)
                self.last_names_ns = solved_ns
            enc = stage.pose_enc
            parts = enc.encode(
                frame.frame_id, frame.source_time_s, received_ns, solved_ns, flags,
                fo.world_from_head_pos, stage.no_quat, stage.no_quat, stage.no_quat,
                fo.weights, stage.no_flags,
            )  # fmt: skip
            enc.encode_face(
                fo.flags, fo.world_from_head_quat, fo.world_from_head_pos,
                fo.markers_head,
            )  # fmt: skip
            sent_ns = time.monotonic_ns()
            pose_stream.stamp_sent(parts[0], sent_ns)
            outputs.send_pub(parts, sent_ns)
            # per-shape states, right after their pose (not recorded)
            outputs.send_unrecorded(
                stage.shape_enc.encode(frame.frame_id, fo.shape_state)
            )
        sent_ns = time.monotonic_ns()
        stats.frames_out += 1
        if sent_ns - t_start > sh.budget_ns:
            stats.overruns += 1
        stats.record(
            solved_ns - received_ns, solved_ns - t_start, sent_ns - solved_ns,
            sent_ns - received_ns,
        )  # fmt: skip
