"""The state every part of the live loop shares: the attributes of
:class:`~retargetd.daemon.live.loop.Daemon`, declared once for the mixins that
implement its parts (inputs, send, calibrate, status, control), and the per-stream
:class:`Pipeline`. The loop thread is the only one that touches any of it.

The attributes of one performer (rig, calibration, face, pipelines, live
calibration, VMC destination...) are :class:`OfPerformer` descriptors: they read
and write the *current* performer (``_perf``, a
:class:`~retargetd.daemon.live.performer.Performer`), which is the first one except
while the loop works for another (``performers.py`` switches it around a solve, a
calibration frame or a control command and back). With one performer every part
reads exactly what it read before there were several."""

from __future__ import annotations

import math
import socket
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Generic, TypeVar, overload

import numpy as np
import zmq

from retargetd.daemon.body.calibration import Calibration
from retargetd.daemon.body.rig import Rig
from retargetd.daemon.body.solve import BodySolver
from retargetd.daemon.body.solve_fit import FitSolver
from retargetd.daemon.live.config import DaemonConfig
from retargetd.daemon.live.emit import EmitPlan
from retargetd.daemon.live.face import FaceStage, LiveFace
from retargetd.daemon.live.performer import FrameSource, Performer
from retargetd.daemon.live.prewarm import Prewarm
from retargetd.daemon.live.props import LiveProps
from retargetd.daemon.live.ratelog import RateLimitedLog, RateLimiter
from retargetd.daemon.live.rebuild import Rebuild
from retargetd.daemon.live.recording import LiveRecording
from retargetd.daemon.live.stalls import LoopStalls
from retargetd.daemon.live.stats import LoopStats
from retargetd.daemon.live.surface import CurveGuard
from retargetd.daemon.live.watch import SocketWatch
from retargetd.daemon.post.pivot import SpinePivot
from retargetd.daemon.post.plant import FootPlant
from retargetd.daemon.post.solve_post import SolvePost
from retargetd.daemon.post.stance import StanceDetector
from retargetd.protocols import pose_stream
from retargetd.protocols.marker_input import MarkerStream
from retargetd.protocols.osc_auth import DatagramVerifier
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
    # frame time, SendMixin._frame_dt_s)
    last_times: tuple[float, int, int] = (math.nan, -1, 0)
    # the (rig, calibration) it was built for: another one is rebuilt (rebuild.py)
    built_for: tuple[Any, Any] = (None, None)
    rebuild: Rebuild | None = None  # its successor's body solver, being built


T = TypeVar("T")


class OfPerformer(Generic[T]):
    """An attribute of the current performer: ``daemon.rig`` is
    ``daemon._perf.rig`` (a leading ``_`` dropped: ``_pipelines`` is
    ``pipelines``)."""

    __slots__ = ("_attr",)

    def __init__(self) -> None:
        self._attr = ""

    def __set_name__(self, owner: type, name: str) -> None:
        self._attr = name.lstrip("_")

    @overload
    def __get__(self, obj: None, owner: type | None = None) -> OfPerformer[T]: ...

    @overload
    def __get__(self, obj: object, owner: type | None = None) -> T: ...

    def __get__(self, obj: object, owner: type | None = None) -> Any:
        if obj is None:
            return self
        return getattr(obj._perf, self._attr)  # type: ignore[attr-defined]

    def __set__(self, obj: object, value: T) -> None:
        setattr(obj._perf, self._attr, value)  # type: ignore[attr-defined]


class DaemonState:
    """Attribute declarations of the daemon (set in ``Daemon.__init__``/``open``)."""

    config: DaemonConfig
    config_path: Any  # str | Path | None: the config file (reload re-reads it)
    out: Callable[[str], None]
    stats: LoopStats
    performers: list[Performer]  # one, or one per [[performer]] table
    _perf: Performer  # the current performer (see the module docstring)
    _multi: bool  # [[performer]] tables: views, per-performer status
    # Of the current performer:
    rig: OfPerformer[Rig] = OfPerformer()
    calibration: OfPerformer[Calibration | None] = OfPerformer()
    face: OfPerformer[LiveFace | None] = OfPerformer()
    validator: OfPerformer[Any] = OfPerformer()
    # live.console_feed.ConsoleFeed when [console] is on (the first performer's)
    console: OfPerformer[Any] = OfPerformer()
    _pipelines: OfPerformer[dict[int, Pipeline]] = OfPerformer()
    _labels_of: OfPerformer[dict[int, tuple[str, ...]]] = OfPerformer()
    _last_names_ns: OfPerformer[int] = OfPerformer()
    _frame_flags: OfPerformer[int] = OfPerformer()  # set for all: _flag_frames
    _vmc_addr: OfPerformer[tuple[str, int]] = OfPerformer()
    _vmc_sock: OfPerformer[socket.socket | None] = OfPerformer()
    _vmc_connected: OfPerformer[bool] = OfPerformer()
    _next_vmc_state_ns: OfPerformer[int] = OfPerformer()
    _calib_target: OfPerformer[int] = OfPerformer()  # frames still wanted
    _calib_frames: OfPerformer[list[np.ndarray]] = OfPerformer()
    _calib_labels: OfPerformer[tuple[str, ...]] = OfPerformer()
    _calib_requested_by: OfPerformer[str] = OfPerformer()
    # (source time s, frame id, t_ns)
    _calib_times: OfPerformer[list[tuple[float, int, int]]] = OfPerformer()
    # the request or the last collected frame (timeout)
    _calib_last_ns: OfPerformer[int] = OfPerformer()
    # how the last calibration ended ("" = none yet)
    _calib_message: OfPerformer[str] = OfPerformer()
    _calib_id: OfPerformer[int] = OfPerformer()  # requests so far
    _calib_state: OfPerformer[str] = OfPerformer()  # "", pending, calibrated ...
    _calib_stream: OfPerformer[Any] = OfPerformer()  # the frames' stream or view
    _calib_rom_s: OfPerformer[float] = OfPerformer()  # range of motion wanted, s
    _calib_base: OfPerformer[Any] = OfPerformer()  # the still base pose, during it
    _calib_rom_frames: OfPerformer[list[np.ndarray]] = OfPerformer()
    _calib_rom_times: OfPerformer[list[tuple[float, int, int]]] = OfPerformer()
    _calibrate_limit: OfPerformer[RateLimiter] = OfPerformer()
    _validation_bits: OfPerformer[int] = OfPerformer()
    _validation_bones: OfPerformer[np.ndarray | None] = OfPerformer()
    _validation_values: OfPerformer[np.ndarray] = OfPerformer()
    _validation_enc: OfPerformer[pose_stream.ValidationEncoder | None] = OfPerformer()
    # reused by LiveValidator.drain_results
    _validation_results: OfPerformer[list[Any]] = OfPerformer()
    target: Any
    endpoints: dict[str, str]
    recording: LiveRecording
    props: LiveProps  # [[prop]] (live/props.py)
    last_stats_line: str
    osc_stream: MarkerStream
    zmq_stream: MarkerStream
    _ctx: Any
    _poller: zmq.Poller
    _sockets: list[Any]
    _osc: socket.socket | None
    _osc_more: Any  # select.poll of _osc: another datagram waiting?
    _show: socket.socket | None
    _vmc: bool  # [output.vmc] on: each performer has its socket (vmc_sock)
    _zin: zmq.Socket[bytes] | None
    _zmon: zmq.Socket[bytes] | None
    _pub: zmq.Socket[bytes] | None
    _ctl: zmq.Socket[bytes] | None
    _names_id: int
    _t0_ns: int
    _buf: bytearray
    _zbuf_header: bytearray
    _zbuf_payload: bytearray
    _zbuf_extra: bytearray
    _zview_header: memoryview
    _zview_payload: memoryview
    _view: memoryview  # of _buf
    _wire: np.ndarray  # _buf as uint8 (the compiled decode's input)
    _zwire_header: np.ndarray  # _zbuf_header as uint8
    _zwire_payload: np.ndarray  # _zbuf_payload as uint8
    _osc_simple: bool  # input.osc.form == "simple"
    _osc_limit: int  # input.osc.max_message_bytes
    _osc_fd: int  # the OSC input's and show control's fds (-2: closed)
    _show_fd: int
    _allow: frozenset[str]
    _osc_auth: DatagramVerifier | None  # [input.osc] key_file: signed datagrams only
    _reload_limit: RateLimiter
    _log: RateLimitedLog
    _show_counters: dict[str, int]  # show-control messages refused, by reason
    _show_token_prefix: str  # "/TOKEN" when show_control.token is set, else ""
    _guards: list[CurveGuard]
    _watch: SocketWatch  # the bound ZeroMQ sockets' monitors (CURVE, descriptors)
    _stalls: LoopStalls  # phases of a loop iteration over 50 ms (stalls.py)
    _wake_ns: int
    _budget_ns: int  # loop.solve_budget_ms: solve + send of one frame
    _catch_up_ns: int
    _window: tuple[int, int, int]
    _osc_form: int
    _vmc_state: VmcEncoder  # the /VMC/Ext/OK state datagram (not calibrated yet)
    _last_frame_ns: int
    _prewarm: Prewarm  # [loop] prewarm_ms: the fit touched before a steady frame
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

    def _send_vmc_datagrams(self, datagrams: Any) -> None:  # send
        raise NotImplementedError

    def _start_validator(self) -> None:  # Daemon
        raise NotImplementedError

    def _solve_and_send(self, stream: FrameSource, received_ns: int) -> None:  # send
        raise NotImplementedError

    def _pipeline(self, stream: FrameSource) -> Pipeline | None:  # send
        raise NotImplementedError

    def _drain_show_control(self) -> None:  # control
        raise NotImplementedError

    def _serve_control(self) -> None:  # control
        raise NotImplementedError

    def _collect_calibration_frame(self, stream: FrameSource) -> None:  # calibrate
        raise NotImplementedError

    def _collect_face_frame(self, stream: FrameSource) -> None:  # calibrate
        raise NotImplementedError

    def request_calibration(
        self, count: object = None, by: str = "", rom_s: object = None
    ) -> str:
        raise NotImplementedError  # calibrate

    def request_face_capture(
        self, name: str, count: int | None = None, by: str = ""
    ) -> str:
        raise NotImplementedError  # calibrate

    def _record_control(self, req: dict[str, Any]) -> str:  # control
        raise NotImplementedError

    def _control(self, req: dict[str, Any]) -> dict[str, Any]:  # control
        raise NotImplementedError

    def _occluded_and_held(self) -> tuple[list[str], list[str]]:  # status
        raise NotImplementedError

    def _calibration_tick(self, now_ns: int) -> None:  # calibrate
        raise NotImplementedError

    # performers.PerformersMixin
    def _solve(self, stream: MarkerStream, t_ns: int) -> None:
        raise NotImplementedError

    def _collect(self, stream: MarkerStream) -> None:
        raise NotImplementedError

    def _restart_pipelines(self, stream: MarkerStream) -> None:
        raise NotImplementedError

    def _flag_frames(self, bits: int) -> None:
        raise NotImplementedError

    def _prepare_views(self, stream: MarkerStream, label_set: Any) -> None:
        raise NotImplementedError

    def _own_streams(self) -> list[FrameSource]:
        raise NotImplementedError

    def _each_performer(self, fn: Callable[[int], None], now_ns: int) -> None:
        raise NotImplementedError

    def performer_named(self, name: object) -> Performer:
        raise NotImplementedError

    def _control_for(self, req: dict[str, Any]) -> dict[str, Any]:
        raise NotImplementedError

    def calibrate_performer(self, name: object, count: object, by: str) -> str:
        raise NotImplementedError

    def performers_status(self) -> list[dict[str, Any]]:
        raise NotImplementedError

    def performers_line(self, docs: list[dict[str, Any]]) -> str:
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
