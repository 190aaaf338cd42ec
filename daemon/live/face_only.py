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
A face capture (``ctl face-capture``) works as with a body. ``ctl calibrate`` is
refused for it (nothing to calibrate).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np
import zmq

from retargetd.daemon.live.face import FaceStage
from retargetd.daemon.live.performer import FrameSource
from retargetd.daemon.live.state import DaemonState
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


class FaceOnlyMixin(DaemonState):
    """Solving and sending the face of a performer without a body."""

    def _face_only_stage(self, stream: FrameSource) -> FaceOnlyStage | None:
        perf = self._perf
        labels = stream.current.label_set.labels
        key = id(stream)
        stage = perf.face_stages.get(key)
        if stage is not None and stage.labels == labels:
            return stage
        face = perf.face.stage(labels) if perf.face is not None else None
        if face is None:  # no training set yet
            perf.face_stages.pop(key, None)
            return None
        self._names_id = (self._names_id + 1) % 65536
        perf.last_names_ns = 0
        names = pose_stream.PoseNames(
            rig="", bone_names=(), bone_parents=(), weight_names=face.weight_names,
            names_id=self._names_id, face_markers=face.marker_names,
            performer=perf.name, performer_id=perf.index, unobserved=face.unobserved,
        )  # fmt: skip
        stage = FaceOnlyStage(
            face=face,
            labels=labels,
            pose_enc=pose_stream.PoseEncoder(
                0,
                len(face.weight_names),
                names_id=self._names_id,
                n_face_markers=len(face.marker_names),
                performer=perf.index,
            ),
            names_parts=pose_stream.encode_pose_names(names),
            shape_enc=pose_stream.ShapeStateEncoder(
                len(face.weight_names), self._names_id
            ),
            vmc=BlendEncoder(face.output_names, perf.vmc_max_datagram),
            no_quat=np.zeros((0, 4)),
            no_flags=np.zeros(0, np.uint8),
        )
        perf.face_stages[key] = stage
        self.stats.pipeline_builds += 1
        return stage

    def _solve_and_send_face(self, stream: FrameSource, received_ns: int) -> None:
        """The face-only performer's frame: solve, then the pose stream and VMC."""
        t_start = time.monotonic_ns()
        stage = self._face_only_stage(stream)
        stats = self.stats
        if stage is None:
            stats.unsolved += 1
            return
        perf = self._perf
        frame = stream.current.frame
        fo = stage.face.solve(frame.markers_world, frame.valid)
        stats.face_solved += 1
        if fo.status[0] & pose_stream.FACE_HEAD_LOST:
            stats.face_head_lost += 1
        solved_ns = time.monotonic_ns()
        stats.frames_solved += 1
        flags = perf.frame_flags
        perf.frame_flags = 0
        sock = perf.vmc_sock
        if sock is not None:
            dgrams = stage.vmc.encode(
                stage.face.blend, (solved_ns - self._t0_ns) * 1e-9
            )
            if perf.vmc_connected:
                for dgram in dgrams:
                    try:
                        sock.send(dgram)
                    except OSError:
                        stats.vmc_errors += 1
            else:
                self._send_vmc_datagrams(dgrams)
        if self._pub is not None or self.recording.poses is not None:
            if solved_ns - perf.last_names_ns >= 1_000_000_000:
                self._send_pub(stage.names_parts, solved_ns)
                perf.last_names_ns = solved_ns
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
            self._send_pub(parts, sent_ns)
            if self._pub is not None:
                try:  # per-shape states, right after their pose (not recorded)
                    self._pub.send(
                        stage.shape_enc.encode(frame.frame_id, fo.shape_state),
                        zmq.NOBLOCK,
                    )
                except zmq.Again:
                    stats.send_drops += 1
        sent_ns = time.monotonic_ns()
        stats.frames_out += 1
        if sent_ns - t_start > self._budget_ns:
            stats.overruns += 1
        stats.record(
            solved_ns - received_ns, solved_ns - t_start, sent_ns - solved_ns,
            sent_ns - received_ns,
        )  # fmt: skip
