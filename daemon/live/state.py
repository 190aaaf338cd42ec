"""What the three parts of :class:`~retargetd.daemon.live.loop.Daemon` still written as
mixins (the capture input ``sources.CaptureMixin``, ``status.StatusMixin`` and
``control.ControlMixin``) read of the daemon: its composed parts and a few values of
its own, declared once so each type-checks on its own. The performers, inputs and
outputs are parts with their own state (``performers.py``, ``inputs.py``,
``outputs.py``); nothing here is per performer any more.
"""

from __future__ import annotations

import socket
from collections.abc import Callable
from typing import Any

import zmq

from retargetd.daemon.live.config import DaemonConfig
from retargetd.daemon.live.inputs import Inputs
from retargetd.daemon.live.outputs import Outputs
from retargetd.daemon.live.performers import Performers
from retargetd.daemon.live.prewarm import Prewarm
from retargetd.daemon.live.props import LiveProps
from retargetd.daemon.live.ratelog import OncePer, RateLimitedLog
from retargetd.daemon.live.recording import LiveRecording
from retargetd.daemon.live.stats import LoopStats
from retargetd.daemon.live.watch import SocketWatch
from retargetd.protocols.marker_input import MarkerStream


class DaemonState:
    """Attribute declarations of the daemon (set in ``Daemon.__init__``/``open``)."""

    out: Callable[[str], None]
    stats: LoopStats
    inputs: Inputs  # the marker inputs (inputs.py)
    outputs: Outputs  # the pose stream and VMC destinations (outputs.py)
    performers: Performers  # every performer's path and calibration
    recording: LiveRecording
    props: LiveProps  # [[prop]] (live/props.py)
    endpoints: dict[str, str]
    _multi: bool  # [[performer]] tables: status per performer
    _poller: zmq.Poller
    _show: socket.socket | None
    _show_buf: bytearray  # a show-control datagram
    _ctl: zmq.Socket[bytes] | None
    _t0_ns: int
    _allow: frozenset[str]
    _log: RateLimitedLog
    _warn: OncePer  # once-per-interval warning lines, by key
    _show_counters: dict[str, int]  # show-control messages refused, by reason
    _show_token_prefix: str  # "/TOKEN" when show_control.token is set, else ""
    _watch: SocketWatch  # the bound ZeroMQ sockets' monitors (CURVE, descriptors)
    _window: tuple[int, int, int]
    _prewarm: Prewarm  # [loop] prewarm_ms: the fit touched before a steady frame
    _capture: Any  # sources.CaptureInput when [input] source is set

    # Declared here, defined by Daemon itself or by one of the mixins.
    @property
    def config(self) -> DaemonConfig:  # Daemon
        raise NotImplementedError

    @property
    def rig(self) -> Any:  # Daemon: the first performer's
        raise NotImplementedError

    @property
    def face(self) -> Any:  # Daemon: the first performer's
        raise NotImplementedError

    @property
    def validator(self) -> Any:  # Daemon: the first performer's
        raise NotImplementedError

    def _accept(self, stream: MarkerStream, code: int, t_ns: int, every: bool) -> int:
        raise NotImplementedError  # Daemon

    def _stale(self) -> None:  # Daemon
        raise NotImplementedError

    def reload(self) -> str:  # Daemon
        raise NotImplementedError

    def status(self) -> dict[str, Any]:  # status
        raise NotImplementedError

    def stats_line(self) -> str:  # status
        raise NotImplementedError

    def _capture_status(self) -> dict[str, Any] | None:
        raise NotImplementedError  # sources.CaptureMixin
