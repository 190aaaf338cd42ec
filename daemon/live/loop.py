"""The live loop: one thread owns the sockets and the solve.

A ``zmq.Poller`` waits on every input at once (plain UDP sockets and ZeroMQ sockets
alike). Each wake-up drains every readable socket, decoding marker packets straight
into preallocated buffers (``retargetd.protocols``); malformed packets are counted by
reason and dropped. Accepted frames are solved as they are decoded while the wake-up is
within ``solve_budget_ms`` (frames that merely arrived together are all solved); past
that the loop is behind and the latest frame wins: the older ones are counted as
``stale`` and dropped. ``process_every_frame`` solves every accepted frame in order
whatever the time (offline replay). A solved frame is retargeted onto the engine
skeleton, encoded as VMC datagrams and a ZeroMQ pose message, and sent without ever
blocking (a slow subscriber loses messages, counted). Solve + send has a budget
(``solve_budget_ms``): a frame over it is sent late, flagged and counted, never queued.

Control requests (``retargetd ctl``: status, calibrate, reload, record) arrive on a
local ZeroMQ REP socket; show-control arrives as OSC on VMC's performer port
(``/VMC/Ext/Set/Calib/Ready``, ``/VMC/Ext/Set/Calib/Exec``, ``/rtd/calibrate``,
``/rtd/reload``). A live calibration averages the next N accepted frames while the
stream goes on with the old calibration, then swaps the new one in atomically (the
loop thread is the only one that reads it) and saves it.

``record`` starts and stops a recording inside the daemon (``live_recording.py``):
the loop hands packets, poses and control events to a writer thread with
``put_nowait`` only, and never writes to the disk itself.

With ``[face]`` on, the same frame is also solved for the face (``live_face.py``:
stabilized markers and blendshape weights) before the send: the weights go out as
VMC blendshapes under the target's names and in the pose stream with the stabilized
markers. ``face-capture`` captures training poses live.

With ``[validate]`` on, every sent pose is handed to the live validator
(``validate_live.py``) with a non-blocking submit after the send; its results come
back on later frames: their bits are ORed into the next pose and each is published
as an ``RTDV`` message (``protocols/PROTOCOLS.md``).
"""

from __future__ import annotations

import contextlib
import gc
import logging
import select
import socket
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import zmq

from retargetd.daemon.body.match import warm_up as warm_up_match
from retargetd.daemon.body.solve_fit import warm_up as warm_up_fit
from retargetd.daemon.live.calibrate import CalibrationMixin
from retargetd.daemon.live.config import ConfigError, DaemonConfig, check_pipeline
from retargetd.daemon.live.console_feed import ConsoleFeed
from retargetd.daemon.live.console_feed import dispatch as dispatch_console
from retargetd.daemon.live.control import (
    CONTROL_RCVHWM,
    CONTROL_TRANSPORT_MAX_BYTES,
    ControlMixin,
)
from retargetd.daemon.live.emit import warm_up as warm_up_emit
from retargetd.daemon.live.face import warm_up as warm_up_face
from retargetd.daemon.live.inputs import InputsMixin
from retargetd.daemon.live.performer import build_performers
from retargetd.daemon.live.performers import PerformersMixin
from retargetd.daemon.live.prewarm import Prewarm
from retargetd.daemon.live.props import LiveProps, vmc_destinations
from retargetd.daemon.live.ratelog import RateLimitedLog, RateLimiter, print_line
from retargetd.daemon.live.recording import FORM_OSC, LiveRecording
from retargetd.daemon.live.send import SendMixin, spine_stage
from retargetd.daemon.live.sources import CaptureMixin
from retargetd.daemon.live.stalls import LoopStalls
from retargetd.daemon.live.stats import LoopStats
from retargetd.daemon.live.status import StatusMixin
from retargetd.daemon.live.surface import (
    CurveGuard,
    KeyFileError,
    curve_client,
    endpoint_is_local,
    is_loopback_host,
    osc_verifier,
    unauthenticated_warning,
    who_reaches,
)
from retargetd.daemon.live.watch import SocketWatch
from retargetd.daemon.post.interp import RateResampler
from retargetd.daemon.post.pose import PoseBuffer
from retargetd.daemon.progress import Progress
from retargetd.daemon.target.retarget import TargetSkeleton, default_humanoid, warm_up
from retargetd.daemon.validate.live import LiveValidator
from retargetd.protocols import kernels as protocol_kernels
from retargetd.protocols.marker_input import LabelSet, MarkerStream
from retargetd.protocols.vmc_out import VmcEncoder

logger = logging.getLogger(__name__)

_UDP_MAX = 65536


class Daemon(
    InputsMixin,
    CaptureMixin,
    SendMixin,
    CalibrationMixin,
    StatusMixin,
    ControlMixin,
    PerformersMixin,
):
    """The live daemon (one performer, or several: ``[[performer]]``). ``open()``,
    then ``run(should_exit)``.

    Args:
        config: validated configuration.
        out: where the "listening on" and stats lines go (``print`` by default).
        config_path: the file ``config`` was read from: ``reload`` re-reads its
            ``[[pipeline]]`` stages (None: the stages stay as given).

    Raises:
        ConfigError: ``[[pipeline]]`` stages the rig cannot carry.
    """

    def __init__(
        self,
        config: DaemonConfig,
        out: Callable[[str], None] | None = None,
        config_path: str | Path | None = None,
    ) -> None:
        self.config = config
        self.config_path = config_path  # re-read by reload for [[pipeline]]
        self.out = out or print_line
        self.stats = LoopStats()
        # Each performer's rig, calibration, face, VMC destination... (performer.py);
        # the attributes of one (self.rig, self.calibration ...) are the current's.
        self.performers = build_performers(config)
        for perf in self.performers:  # each performer's rig, after any --rig
            check_pipeline(config.pipeline, perf.rig)
        self._perf = self.performers[0]
        self._multi = bool(config.performers)
        self.target = _load_target(config)
        for perf in self.performers:  # [target] spine = "pivot": target and rig fit
            try:
                spine = spine_stage(config.target, self.target, perf.rig)
                if spine is not None:  # load (or compile) its kernel now, not live
                    rest = np.array(self.target.rest_world_from_bone_quat)
                    spine.apply(rest.copy(), rest)
            except ValueError as exc:
                msg = f"target.spine: {exc} (rig {perf.rig.name})"
                raise ConfigError(msg) from None
        # Its own ZeroMQ context (its own I/O thread), shut at close: the daemon's
        # sockets never share an I/O thread or a socket budget with the host's. An
        # inproc:// endpoint reaches only sockets of the same context, so with one
        # the daemon takes the process's shared context (zmq.Context.instance()).
        endpoints = (config.input.zmq.endpoint, config.output.pose.endpoint,
                     config.control.endpoint)  # fmt: skip
        self._shared_ctx = any(ep.startswith("inproc://") for ep in endpoints)
        self._ctx: Any = zmq.Context.instance() if self._shared_ctx else zmq.Context()
        self._poller = zmq.Poller()
        self._sockets: list[Any] = []
        self._osc: socket.socket | None = None
        self._show: socket.socket | None = None
        self._vmc = False  # [output.vmc] on (each performer's vmc_sock, open())
        self._zin: zmq.Socket[bytes] | None = None
        self._zmon: zmq.Socket[bytes] | None = None  # the input's disconnect events
        self._pub: zmq.Socket[bytes] | None = None
        self._ctl: zmq.Socket[bytes] | None = None
        self._capture: Any = None  # a capture system ([input] source), sources.py
        osc_cfg, zmq_cfg = config.input.osc, config.input.zmq
        simple_labels = (
            LabelSet(0, osc_cfg.labels) if osc_cfg.form == "simple" else None
        )
        self.osc_stream = MarkerStream(
            simple_labels,
            osc_cfg.up,
            osc_cfg.units,
            max_rate_hz=osc_cfg.max_rate_hz,
            max_markers=osc_cfg.max_markers,
            zero_is_occluded=osc_cfg.zero_is_occluded,
            max_coordinate_m=osc_cfg.max_coordinate_m,
        )
        self.zmq_stream = MarkerStream(
            None,
            zmq_cfg.up,
            zmq_cfg.units,
            max_rate_hz=zmq_cfg.max_rate_hz,
            max_markers=zmq_cfg.max_markers,
            zero_is_occluded=zmq_cfg.zero_is_occluded,
            max_coordinate_m=zmq_cfg.max_coordinate_m,
        )
        self._log_after_ns: dict[str, int] = {}  # rate-limited log lines, by key
        self._names_id = 0
        self._t0_ns = time.monotonic_ns()
        self._buf = bytearray(_UDP_MAX)
        # ZeroMQ input parts, received in place: header (a frame's or a label set's
        # is 32 / 16 bytes; 64 leaves room to see a wrong one), payload (the limit).
        self._zbuf_header = bytearray(64)
        self._zbuf_payload = bytearray(config.input.zmq.max_message_bytes)
        self._zbuf_extra = bytearray(64)
        self._zview_header = memoryview(self._zbuf_header)
        self._zview_payload = memoryview(self._zbuf_payload)
        # The same buffers as uint8 arrays: the compiled decode reads them in place.
        self._view = memoryview(self._buf)
        self._wire = np.frombuffer(self._buf, dtype=np.uint8)
        self._zwire_header = np.frombuffer(self._zbuf_header, dtype=np.uint8)
        self._zwire_payload = np.frombuffer(self._zbuf_payload, dtype=np.uint8)
        self._osc_simple = osc_cfg.form == "simple"
        self._osc_fd = self._show_fd = -2  # the poll result's fds (set by open)
        self._osc_more: Any = None  # select.poll of the OSC socket (set by open)
        self._osc_limit = osc_cfg.max_message_bytes
        self._allow = frozenset(osc_cfg.allow)
        try:  # [input.osc] key_file: signed datagrams only (PROTOCOLS.md 13)
            self._osc_auth = osc_verifier(osc_cfg.key_file)
        except KeyFileError as exc:  # changed since the config was checked
            raise ConfigError(f"input.osc.key_file: {exc}") from None
        self._reload_limit = RateLimiter(config.control.min_interval_s)
        self._log = RateLimitedLog(self.out, config.loop.log_interval_s)
        self._show_counters: dict[str, int] = {}
        # CURVE handshake failures and descriptor exhaustion on the bound ZeroMQ
        # sockets (their monitors: watch.py)
        self._watch = SocketWatch(self._poller, self._log, self.out)
        self._stalls = LoopStalls(self._log)  # phases over 50 ms (stalls.py)
        #: open() tells how to calibrate a performer without a calibration (False:
        #: the caller calibrates itself and says so, as ``retargetd demo`` does)
        self.hint_uncalibrated = True
        token = config.show_control.token
        self._show_token_prefix = f"/{token}" if token else ""
        self._guards: list[CurveGuard] = []
        self._wake_ns = 0  # when the current wake-up began
        # A wake-up solves the frames that arrived together while within the budget
        # of their solves: a frame of N performers is N solves, each with the budget.
        self._budget_ns = int(config.loop.solve_budget_ms * 1e6)  # solve + send
        self._catch_up_ns = self._budget_ns * len(self.performers)
        # (t_ns, frames_in, frames_out) at the last stats line: fps over that window.
        self._window = (self._t0_ns, 0, 0)
        self.last_stats_line = ""
        self.endpoints: dict[str, str] = {}
        rc = config.record
        self.recording = LiveRecording(
            rc.folder, rc.max_total_mb, rc.min_free_mb, rc.min_interval_s
        )
        # [[prop]]: rigid props and cameras, one part called per accepted frame
        self.props = LiveProps(config.props, vmc_destinations(config), self._send_pub,
                               self.out)  # fmt: skip
        self._osc_form = FORM_OSC[osc_cfg.form]
        self._vmc_state = VmcEncoder(())  # the state datagram (no bones needed)
        self._last_frame_ns = 0
        self._prewarm = Prewarm(config.loop.prewarm_ms)
        # The console shows the first performer (its buttons act for that one);
        # its t counts from the daemon's start, as the pose stream's t does.
        self.console = (
            ConsoleFeed(
                config.console,
                self.out,
                t0_ns=self._t0_ns,
                face_capture=self.performers[0].face is not None,
            )
            if config.console.enabled
            else None
        )
        if self.console is not None:  # it draws the props too
            self.console.props = self.props

    # ---- lifecycle -------------------------------------------------------------------

    def open(self) -> None:
        """Bind every endpoint; prints one line each saying who can reach it."""
        c = self.config
        if c.input.osc.enabled:
            osc = c.input.osc
            self._osc = self._udp_bind(osc.host, osc.port)
            self._osc_fd = self._osc.fileno()
            self._osc_more = select.poll()  # "another datagram waits?" (inputs.py)
            self._osc_more.register(self._osc_fd, select.POLLIN)
            allow = f", sources {', '.join(osc.allow)} only" if osc.allow else ""
            local = is_loopback_host(osc.host)
            who = who_reaches(local, osc.host)
            signed = ", signed only (HMAC-SHA256)" if osc.key_file else ""
            self._announce(
                "osc markers",
                f"udp://{self._addr(self._osc)} ({osc.form}; frames from {who}"
                f"{allow}{signed})",
            )
            if not local and not osc.key_file:
                self.out(unauthenticated_warning("osc", osc.host, "key_file"))
        if c.show_control.enabled:
            show = c.show_control
            self._show = self._udp_bind(show.host, show.port)
            self._show_fd = self._show.fileno()
            can = [w for w, on in (("calibrate", show.calibrate),
                                   ("reload", show.reload)) if on]  # fmt: skip
            who = who_reaches(is_loopback_host(show.host), show.host)
            token = ", token required" if show.token else ""
            self._announce(
                "show control",
                f"udp://{self._addr(self._show)} (OSC; "
                f"{' and '.join(can) or 'nothing but status'} from {who}{token})",
            )
        if c.input.zmq.enabled:
            zin = c.input.zmq
            local = endpoint_is_local(zin.endpoint)
            pull = zin.mode == "pull"
            # CURVE as the control socket's: a bound PULL is the server letting in
            # the listed clients; a SUB is a client of the publisher's key.
            self._zin = self._server_socket(
                zmq.PULL if pull else zmq.SUB,
                zin.secret_key if pull else "",
                zin.client_keys,
            )
            if not pull and zin.secret_key:
                curve_client(self._zin, zin.secret_key, zin.server_key)
            self._zin.setsockopt(zmq.LINGER, 0)
            # Bounded queue: 1,000 messages of parts of at most max_message_bytes;
            # libzmq drops the connection of a peer sending a larger part, before
            # buffering it (inproc bypasses this: the drain checks sizes too).
            self._zin.setsockopt(zmq.RCVHWM, 1000)
            self._zin.setsockopt(zmq.MAXMSGSIZE, zin.max_message_bytes)
            if pull:
                self._zin.bind(zin.endpoint)
                who = f"frames from {who_reaches(local, zin.endpoint)}"
            else:
                self._zin.setsockopt(zmq.SUBSCRIBE, b"RTD")
                self._zin.connect(zin.endpoint)
                who = f"frames from the publisher at {zin.endpoint}"
            self._poller.register(self._zin, zmq.POLLIN)
            self._sockets.append(self._zin)
            self._zmon = self._zin.get_monitor_socket(zmq.EVENT_DISCONNECTED)
            self._zmon.setsockopt(zmq.LINGER, 0)
            self._poller.register(self._zmon, zmq.POLLIN)
            self._sockets.append(self._zmon)
            ep = _last_endpoint(self._zin) or zin.endpoint
            curve = ", CURVE" if zin.secret_key else ""
            if pull and zin.secret_key:
                curve += f": {len(zin.client_keys)} client key(s)"
            self._announce("zmq markers", f"{ep} ({zin.mode}; {who}{curve})")
            if not local and not zin.secret_key:
                keys = "client_keys" if pull else "server_key"
                self.out(unauthenticated_warning("zmq", zin.endpoint, keys))
        self._open_capture()
        if c.output.pose.enabled:
            pose = c.output.pose
            self._pub = self._server_socket(zmq.PUB, pose.secret_key, pose.client_keys)
            self._pub.setsockopt(zmq.LINGER, 0)
            self._pub.setsockopt(zmq.SNDHWM, pose.sndhwm)
            self._pub.bind(pose.endpoint)
            self._sockets.append(self._pub)
            self._watch.watch("zmq poses", self._pub, bool(pose.secret_key))
            ep = _last_endpoint(self._pub)
            who = who_reaches(endpoint_is_local(pose.endpoint), ep)
            curve = (
                f", CURVE encrypted to {len(pose.client_keys)} client key(s)"
                if pose.secret_key
                else ", plain"
            )
            self._announce("zmq poses", f"{ep} (pub; poses to {who}{curve})")
        ctl = c.control
        self._ctl = self._server_socket(zmq.REP, ctl.secret_key, ctl.client_keys)
        self._ctl.setsockopt(zmq.LINGER, 0)
        self._ctl.setsockopt(zmq.MAXMSGSIZE, CONTROL_TRANSPORT_MAX_BYTES)
        self._ctl.setsockopt(zmq.RCVHWM, CONTROL_RCVHWM)
        self._ctl.bind(ctl.endpoint)
        self._poller.register(self._ctl, zmq.POLLIN)
        self._sockets.append(self._ctl)
        self._watch.watch("control", self._ctl, bool(ctl.secret_key))
        ep = _last_endpoint(self._ctl)
        who = who_reaches(endpoint_is_local(ctl.endpoint), ep)
        curve = (
            f", CURVE: {len(ctl.client_keys)} client key(s)" if ctl.secret_key else ""
        )
        self._announce(
            "control", f"{ep} (retargetd ctl --endpoint {ep}; from {who}{curve})"
        )
        if c.output.vmc.enabled:
            vmc = c.output.vmc
            self._vmc = True
            kind = "broadcast allowed" if vmc.allow_broadcast else "unicast"
            for perf in self.performers:  # one avatar per destination, one socket
                host, port = perf.vmc_addr
                self._open_vmc(perf, vmc.allow_broadcast)
                self._announce(
                    f"vmc out {perf.name}" if perf.name else "vmc out",
                    f"udp://{host}:{port} (plain OSC, {kind}, datagrams up to "
                    f"{perf.vmc_max_datagram} bytes; readable by "
                    f"{'this machine' if is_loopback_host(host) else host} "
                    "and the network path to it)",
                )
        if self.console is not None:
            url = self.console.start(self.rig)
            self._announce("console", f"{url} (browser; buttons act like ctl)")
        self._warm_up()
        for perf in self.performers:
            with self._acting_for(perf):
                self._start_validator()
        # Everything built so far lives as long as the daemon: keep it out of the
        # garbage collector's full passes (one took ~50 ms here, holding the GIL).
        gc.collect()
        gc.freeze()
        if self.hint_uncalibrated:
            self._hint_uncalibrated()

    def _warm_up(self) -> None:
        """Load the compiled kernel and run every stage once before the first frame
        arrives, so no streamed frame pays for it (numba's cache load is ~0.3 s; a
        first start compiles, seconds to a minute: a progress bar on a terminal)."""
        fit = self.config.solve.method == "fit"
        steps = 1 + fit + (self.face is not None)
        with Progress(steps, "kernels: body", unit="kernels") as bar:
            warm_up()
            protocol_kernels.warm_up()
            warm_up_emit()
            warm_up_match()  # the calibration check fits the first second's frames
            bar.update()
            if fit:
                self.out(
                    "loading the fit kernel (a first start compiles for about a minute)"
                )
                bar.set_description("kernels: fit")
                warm_up_fit()
                bar.update()
            if self.face is not None:
                bar.set_description("kernels: face")
                warm_up_face()
                bar.update()
        if self.config.loop.output_rate_hz > 0.0:  # the resampler's queue kernel
            res, probe = RateResampler(1, 100.0), PoseBuffer.new(1)
            for t_s in (0.0, 0.02):  # a tick on a pose and one between two
                probe.t_s = t_s
                res.push(probe)
        if self.calibration is None:
            return
        # A stream naming every marker as the rig's labels do (its names need not
        # be labels: such a warm-up would call every marker missing).
        labels = tuple(aliases[0] for aliases in self.rig.markers.values())
        pipe = self._build_pipeline(labels, with_face=False)
        nan_frame = np.full((len(labels), 3), np.nan)
        pose = pipe.solver.solve_frame(nan_frame, pipe.pose)
        pipe.retargeter.apply(pose, pipe.target_pose)
        # The [[pipeline]] stages and the spine pivot compile on their first finite
        # pose (a twist and a One Euro stage: 4.1 s into the stream on a cold cache,
        # measured): run them here on the rest pose, two frames apart (the filters'
        # second-frame path), so no streamed frame pays for it.
        if pipe.post is not None or pipe.spine is not None:
            pose.parent_from_bone_quat[:] = self.calibration.rest_parent_from_bone_quat
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
        self._names_id -= 1  # this pipeline is thrown away; keep the ids dense

    def _start_validator(self) -> None:
        """(Re)start the live validator on the current calibration ([validate] on).

        Builds the MuJoCo model (cached by skeleton hash) and warms the kernels
        (tens of ms; seconds on a cold numba cache): at start-up, and after a live
        calibration or a reload, never per frame."""
        v = self.config.validate
        old, self.validator = self.validator, None
        if old is not None:
            old.close()
        self._validation_bits = 0
        self._validation_bones = None
        self._validation_values.fill(np.nan)
        if not v.enabled or self.calibration is None:
            return

        validator = LiveValidator(
            self.rig,
            self.calibration,
            body_mass_kg=v.body_mass_kg or None,
            rate_hz=v.rate_hz,
            queue_size=v.queue,
        )
        validator.start()
        self._validation_results = [None] * validator.results_capacity
        self.validator = validator
        self.out(
            f"live validator on: MuJoCo model {validator.vm.digest[:12]}, "
            f"queue {v.queue}, frame numbers at {v.rate_hz:g} Hz"
        )

    def _open_vmc(self, perf: Any, allow_broadcast: bool) -> None:
        """``perf``'s VMC socket, connected to its destination: a connected UDP
        socket sends without parsing an address or looking up the route per call
        (a receiver absent on this machine then shows as refused sends, counted in
        ``vmc_errors``). Without a route to the host yet (a network not up), it
        stays unconnected and sends with ``sendto``, as the route may come later."""
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setblocking(False)
        if allow_broadcast:  # without it the kernel refuses broadcast sends
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
        perf.vmc_sock, perf.vmc_connected = sock, False
        try:
            sock.connect(perf.vmc_addr)
        except OSError as exc:
            self.out(
                f"vmc out: no route to {perf.vmc_addr[0]} yet ({exc.strerror}): "
                "sending unconnected"
            )
        else:
            perf.vmc_connected = True

    def _server_socket(
        self, kind: int, secret_key: str, client_keys: tuple[str, ...]
    ) -> Any:
        """A plain socket of the shared context, or, with a secret key, a CURVE
        server in a guarded context letting in only ``client_keys``."""
        if not secret_key:
            return self._ctx.socket(kind)
        guard = CurveGuard(f"{len(self._guards)}")
        self._guards.append(guard)
        return guard.server_socket(kind, secret_key, client_keys)

    def _announce(self, what: str, where: str) -> None:
        self.endpoints[what] = where
        self.out(f"listening on {where}: {what}" if not what.startswith("vmc out")
                 else f"sending to {where}: {what}")  # fmt: skip

    def _udp_bind(self, host: str, port: int) -> socket.socket:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        sock.bind((host, port))
        sock.setblocking(False)
        self._poller.register(sock, zmq.POLLIN)
        self._sockets.append(sock)
        return sock

    @staticmethod
    def _addr(sock: socket.socket) -> str:
        host, port = sock.getsockname()[:2]
        return f"{host}:{port}"

    def close(self) -> None:
        """Stop an active recording (its file is finished, bounded wait) and close
        every socket (idempotent)."""
        self.recording.close()
        self._stalls.close()
        self.props.close()
        self._close_capture()
        if self.console is not None:
            self.console.stop()
        for perf in self.performers:
            if perf.validator is not None:
                perf.validator.close()
                perf.validator = None
        self._watch.close()  # the monitors before their sockets
        for sock in self._sockets:
            with contextlib.suppress(KeyError):
                self._poller.unregister(sock)
            sock.close()
        self._sockets.clear()
        for perf in self.performers:
            if perf.vmc_sock is not None:
                perf.vmc_sock.close()
                perf.vmc_sock = None
        self._vmc = False
        for guard in self._guards:
            guard.close()
        self._guards.clear()
        if not self._shared_ctx and not self._ctx.closed:
            self._ctx.destroy(linger=0)  # its sockets are closed above

    def run(self, should_exit: Callable[[], bool]) -> None:
        """Serve until ``should_exit()`` is true (checked every poll timeout).

        The poll waits at most ``poll_timeout_ms``, less when a resampled output
        tick (``output_rate_hz``) is queued: it wakes at the tick's send time
        (rounded up to the next millisecond), and the tick goes out from here.
        """
        c = self.config.loop
        timeout = c.poll_timeout_ms
        next_stats = time.monotonic_ns() + int(c.stats_interval_s * 1e9)
        stalls = self._stalls.watch_gc()  # and the collector's passes
        while not should_exit():
            wait = timeout
            tick_ns = self.next_tick_ns()  # output_rate_hz: a resampled tick queued
            if tick_ns >= 0:  # wake for it (rounded up to the poll's 1 ms)
                left_ms = -(-(tick_ns - time.monotonic_ns()) // 1_000_000)
                wait = max(0, min(timeout, left_ms))
            wait = self._prewarm.wait_ms(stalls.mark(), wait)
            events = self._poller.poll(wait)  # [(socket or fd, flags)]
            stalls.lap("poll", wait * 1_000_000)  # past its timeout
            if events:
                self._service(events)  # its phases timed inside (inputs.py)
            elif self._prewarm.due(time.monotonic_ns()):
                self._prewarm.touch()  # the fit, warm for the frame that comes next
            if self._capture is not None:
                self._tick_capture()  # requests, lost check, held pose: never blocks
            now = stalls.lap("prewarm_capture")
            if self.console is not None:
                cmd = self.console.commands.poll()  # nothing allocated when empty
                if cmd is not None:
                    dispatch_console(self, cmd)
                    stalls.lap("console")
            self._each_performer(self._calibration_tick, now)
            stalls.lap("calibration")
            self._each_performer(self._send_vmc_state, now)
            self._each_performer(self._send_due_ticks, time.monotonic_ns())
            self._log.flush(now)
            self._watch.tick(now)  # descriptor exhaustion: its end, once
            stopped = self.recording.check_limits(now)  # [record] limits, once a s
            stalls.lap("ticks")
            if stopped:
                self.out(stopped)
            if now >= next_stats:
                self.last_stats_line = self.stats_line()
                self._window = (now, self.stats.frames_in, self.stats.frames_out)
                self.out(self.last_stats_line)
                next_stats = now + int(c.stats_interval_s * 1e9)
                stalls.lap("stats_line")


def _last_endpoint(sock: Any) -> str:
    """The endpoint a socket bound (with the real port of a ``*`` wildcard)."""
    value = sock.getsockopt(zmq.LAST_ENDPOINT)
    return value.decode() if isinstance(value, bytes) else str(value)


def _load_target(config: DaemonConfig) -> Any:
    t = config.target
    if t.skeleton == "humanoid":
        return default_humanoid()
    return TargetSkeleton.from_bvh(Path(t.skeleton), units=t.bvh_units, up=t.bvh_up)
