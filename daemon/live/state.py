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
from retargetd.daemon.body.solve_fit import FitSolver
from retargetd.daemon.live.config import DaemonConfig
from retargetd.daemon.live.face import FaceStage, LiveFace
from retargetd.daemon.live.ratelog import RateLimitedLog, RateLimiter
from retargetd.daemon.live.recording import LiveRecording
from retargetd.daemon.live.stats import LoopStats
from retargetd.daemon.live.surface import CurveGuard
from retargetd.daemon.post.solve_post import SolvePost
from retargetd.protocols import pose_stream
from retargetd.protocols.marker_input import MarkerStream
from retargetd.protocols.vmc_out import VmcEncoder


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
    post: SolvePost | None = None  # the [[pipeline]] stages (None: none configured)


class DaemonState:
    """Attribute declarations of the daemon (set in ``Daemon.__init__``/``open``)."""

    config: DaemonConfig
    config_path: Any  # str | Path | None: the config file (reload re-reads it)
    out: Callable[[str], None]
    stats: LoopStats
    rig: Rig
    calibration: Calibration | None
    target: Any
    endpoints: dict[str, str]
    recording: LiveRecording
    face: LiveFace | None
    validator: Any
    console: Any  # live.console_feed.ConsoleFeed when [console] is on
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
    _zbuf_header: bytearray
    _zbuf_payload: bytearray
    _zbuf_extra: bytearray
    _zview_header: memoryview
    _zview_payload: memoryview
    _allow: frozenset[str]
    _calib_target: int
    _calib_frames: list[np.ndarray]
    _calib_labels: tuple[str, ...]
    _calib_requested_by: str
    _calib_times: list[tuple[float, int, int]]  # (source time s, frame id, t_ns)
    _calib_last_ns: int  # the request or the last collected frame (timeout)
    _calib_message: str  # how the last calibration ended ("" = none yet)
    _calibrate_limit: RateLimiter
    _reload_limit: RateLimiter
    _log: RateLimitedLog
    _show_counters: dict[str, int]  # show-control messages refused, by reason
    _show_token_prefix: str  # "/TOKEN" when show_control.token is set, else ""
    _guards: list[CurveGuard]
    _frame_flags: int
    _wake_ns: int
    _catch_up_ns: int
    _window: tuple[int, int, int]
    _osc_form: int
    _validation_bits: int
    _validation_bones: np.ndarray | None
    _validation_enc: pose_stream.ValidationEncoder | None
    _validation_results: list[Any]  # reused by LiveValidator.drain_results
    _vmc_state: VmcEncoder  # the /VMC/Ext/OK state datagram (not calibrated yet)
    _next_vmc_state_ns: int
    _last_frame_ns: int
    _log_after_ns: dict[str, int]
    _capture: Any  # sources.CaptureInput when [input] source is set

    # The parts call each other through the daemon; each is implemented by one mixin
    # (or Daemon itself), declared here so every part type-checks on its own.
    def _accept(self, stream: MarkerStream, code: int, t_ns: int, every: bool) -> int:
        raise NotImplementedError  # inputs

    def _send_pub(self, parts: list[Any], t_ns: int) -> None:  # send
        raise NotImplementedError

    def _send_vmc_state(self, now_ns: int) -> None:  # send
        raise NotImplementedError

    def _start_validator(self) -> None:  # Daemon
        raise NotImplementedError

    def _solve_and_send(self, stream: MarkerStream, received_ns: int) -> None:  # send
        raise NotImplementedError

    def _pipeline(self, stream: MarkerStream) -> Pipeline | None:  # send
        raise NotImplementedError

    def _drain_show_control(self) -> None:  # control
        raise NotImplementedError

    def _serve_control(self) -> None:  # control
        raise NotImplementedError

    def _collect_calibration_frame(self, stream: MarkerStream) -> None:  # calibrate
        raise NotImplementedError

    def _collect_face_frame(self, stream: MarkerStream) -> None:  # calibrate
        raise NotImplementedError

    def request_calibration(self, count: int | None = None, by: str = "") -> str:
        raise NotImplementedError  # calibrate

    def request_face_capture(
        self, name: str, count: int | None = None, by: str = ""
    ) -> str:
        raise NotImplementedError  # calibrate

    def _record_control(self, req: dict[str, Any]) -> str:  # control
        raise NotImplementedError

    def reload(self) -> str:  # calibrate
        raise NotImplementedError

    def status(self) -> dict[str, Any]:  # status
        raise NotImplementedError

    def stats_line(self) -> str:  # status
        raise NotImplementedError

    def _drain_capture(self, events: list[tuple[Any, int]], every: bool) -> int:
        raise NotImplementedError  # implemented by sources.CaptureMixin

    def _capture_status(self) -> dict[str, Any] | None:
        raise NotImplementedError  # implemented by sources.CaptureMixin
