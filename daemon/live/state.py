"""The state every part of the live loop shares: the attributes of
:class:`~retargetd.daemon.live.loop.Daemon`, declared once for the mixins that
implement its parts (inputs, send, calibrate, status, control), and the per-stream
:class:`Pipeline`. The loop thread is the only one that touches any of it."""

from __future__ import annotations

import socket
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import zmq

from retargetd.daemon.body.calibration import Calibration
from retargetd.daemon.body.rig import Rig
from retargetd.daemon.body.solve import BodySolver
from retargetd.daemon.live.config import DaemonConfig
from retargetd.daemon.live.face import FaceStage, LiveFace
from retargetd.daemon.live.recording import LiveRecording
from retargetd.daemon.live.stats import LoopStats
from retargetd.protocols import pose_stream
from retargetd.protocols.marker_input import MarkerStream
from retargetd.protocols.vmc_out import VmcEncoder


@dataclass(slots=True)
class Pipeline:
    """Everything that depends on (rig, calibration, label set); rebuilt off the hot
    path when one of them changes."""

    solver: BodySolver
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


class DaemonState:
    """Attribute declarations of the daemon (set in ``Daemon.__init__``/``open``)."""

    config: DaemonConfig
    out: Callable[[str], None]
    stats: LoopStats
    rig: Rig
    calibration: Calibration | None
    target: Any
    endpoints: dict[str, str]
    recording: LiveRecording
    face: LiveFace | None
    validator: Any
    last_stats_line: str
    osc_stream: MarkerStream
    zmq_stream: MarkerStream
    _ctx: Any
    _poller: zmq.Poller
    _sockets: list[Any]
    _osc: socket.socket | None
    _show: socket.socket | None
    _vmc: socket.socket | None
    _vmc_addr: tuple[str, int]
    _zin: zmq.Socket[bytes] | None
    _zmon: zmq.Socket[bytes] | None
    _pub: zmq.Socket[bytes] | None
    _ctl: zmq.Socket[bytes] | None
    _pipelines: dict[int, Pipeline]
    _labels_of: dict[int, tuple[str, ...]]
    _names_id: int
    _last_names_ns: int
    _t0_ns: int
    _buf: bytearray
    _allow: frozenset[str]
    _calib_target: int
    _calib_frames: list[np.ndarray]
    _calib_labels: tuple[str, ...]
    _calib_requested_by: str
    _frame_flags: int
    _wake_ns: int
    _catch_up_ns: int
    _window: tuple[int, int, int]
    _osc_form: int
    _validation_bits: int
    _validation_bones: np.ndarray | None
    _validation_enc: pose_stream.ValidationEncoder | None
    _log_after_ns: dict[str, int]
    _capture: Any  # sources.CaptureInput when [input] source is set

    def _start_validator(self) -> None:  # implemented by Daemon
        raise NotImplementedError

    def _drain_capture(self, events: dict[Any, int], every: bool) -> int:
        raise NotImplementedError  # implemented by sources.CaptureMixin

    def _capture_status(self) -> dict[str, Any] | None:
        raise NotImplementedError  # implemented by sources.CaptureMixin
