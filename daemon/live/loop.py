"""The live loop: one thread owns the sockets and the solve. :class:`Daemon` composes
the parts (inputs, performers, outputs, control, health; ``daemon/live/__init__.py``
says who owns what) and :meth:`Daemon._service` is a frame's path, top-down.

A ``zmq.Poller`` waits on every input at once (plain UDP sockets and ZeroMQ sockets
alike). Each wake-up drains every readable socket, decoding marker packets straight
into preallocated buffers (``retargetd.protocols``); malformed packets are counted by
reason and dropped. Accepted frames are solved as they are decoded; frames that waited
behind a solve are caught up for one frame period of the source (``catchup.py``); past
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

``record`` starts and stops a recording inside the daemon (``recording.py``):
the loop hands packets, poses and control events to a writer thread with
``put_nowait`` only, and never writes to the disk itself.

With ``[face]`` on, the same frame is also solved for the face (``face.py``:
stabilized markers and blendshape weights) before the send: the weights go out as
VMC blendshapes under the target's names and in the pose stream with the stabilized
markers. ``face-capture`` captures training poses live.

With ``[validate]`` on, every sent pose is handed to the live validator
(``validate/live.py``) with a non-blocking submit after the send; its results come
back on later frames: their bits are ORed into the next pose and each is published
as an ``RTDV`` message (``protocols/PROTOCOLS.md``).
"""

from __future__ import annotations

import contextlib
import gc
import logging
import socket
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import zmq

from retargetd.daemon.body.match import warm_up as warm_up_match
from retargetd.daemon.body.solve_fit import warm_up as warm_up_fit
from retargetd.daemon.live.catchup import CatchUp
from retargetd.daemon.live.config import ConfigError, DaemonConfig, check_pipeline
from retargetd.daemon.live.console_feed import ConsoleFeed
from retargetd.daemon.live.console_feed import dispatch as dispatch_console
from retargetd.daemon.live.control import Control
from retargetd.daemon.live.emit import warm_up as warm_up_emit
from retargetd.daemon.live.face import warm_up as warm_up_face
from retargetd.daemon.live.inputs import (
    LOG_INTERVAL_NS,
    READY_EVENTS,
    READY_MONITOR,
    READY_OSC,
    READY_ZMQ,
    Inputs,
)
from retargetd.daemon.live.outputs import Outputs, VmcOut
from retargetd.daemon.live.performer import build_performers
from retargetd.daemon.live.performers import Performers
from retargetd.daemon.live.pipeline import may_fuse
from retargetd.daemon.live.prewarm import Prewarm
from retargetd.daemon.live.props import LiveProps, vmc_destinations
from retargetd.daemon.live.ratelog import (
    OncePer,
    RateLimitedLog,
    print_line,
)
from retargetd.daemon.live.recording import LiveRecording
from retargetd.daemon.live.shared import Shared
from retargetd.daemon.live.solve_emit import warm_up as warm_up_solve_emit
from retargetd.daemon.live.sources import CaptureSource
from retargetd.daemon.live.spin import Spin
from retargetd.daemon.live.stalls import LoopStalls
from retargetd.daemon.live.stats import LoopStats
from retargetd.daemon.live.status import Health
from retargetd.daemon.live.surface import (
    CurveGuard,
    is_loopback_host,
)
from retargetd.daemon.live.watch import SocketWatch
from retargetd.daemon.post.interp import RateResampler
from retargetd.daemon.post.pivot import spine_stage
from retargetd.daemon.post.pose import PoseBuffer
from retargetd.daemon.progress import Progress
from retargetd.daemon.retarget.retarget import (
    TargetSkeleton,
    default_humanoid,
    warm_up,
)
from retargetd.protocols import kernels as protocol_kernels
from retargetd.protocols import pose_stream
from retargetd.protocols.marker_input import ACCEPTED, RESTART, LabelSet, MarkerStream

logger = logging.getLogger(__name__)


class Daemon:
    """The live daemon (one performer, or several: ``[[performer]]``). ``open()``,
    then ``run(should_exit)``.

    It composes parts, each owning its state (``daemon/live/__init__.py`` tells who
    owns what): ``inputs`` and ``capture`` (the marker sources), ``performers``
    (each performer's frame path and live calibration), ``outputs`` (the pose
    stream, the VMC destinations), ``recording``, ``props``, ``control`` (``ctl``
    and show control) and ``health`` (status and the stats line). A frame's path is
    :meth:`_service`.

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
        self.out = out or print_line
        self.stats = LoopStats()
        # Each performer's rig, calibration, face, VMC destination (performer.py).
        performers = build_performers(config)
        for perf in performers:  # each performer's rig, after any --rig
            check_pipeline(config.pipeline, perf.rig)
        self._every = config.loop.process_every_frame  # offline replay: no drops
        self._left: MarkerStream | None = None  # the wake-up's frame left unsolved
        self._left_ns = 0  # its receive time
        self.target = _load_target(config)
        for perf in performers:  # [target] spine = "pivot": target and rig fit
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
        self._t0_ns = time.monotonic_ns()
        self._warn = OncePer(LOG_INTERVAL_NS)  # the inputs' warning lines, by key
        rc = config.record
        self.recording = LiveRecording(
            rc.folder, rc.max_total_mb, rc.min_free_mb, rc.min_interval_s
        )
        budget_ns = int(config.loop.solve_budget_ms * 1e6)  # solve + send
        self._prewarm = Prewarm(config.loop.prewarm_ms)
        # A wake-up catches up the frames that waited behind a solve for one frame
        # period of the source (catchup.py); until its cadence is known, for the
        # budget of their solves: a frame of N performers is N solves.
        self._catch_up = CatchUp(self._prewarm, budget_ns * len(performers))
        # The marker inputs (OSC, ZeroMQ): sockets, buffers and a stream each.
        self.inputs = Inputs(
            config, self.stats, self.recording, self._warn,
            self._accept, self._on_labels, self._stale, self._catch_up,
        )  # fmt: skip
        # The pose stream and each performer's VMC destination.
        vmc = [VmcOut(p.vmc_addr, p.vmc_max_datagram, self.stats) for p in performers]
        self.outputs = Outputs(self.stats, self.recording, vmc)
        spin_us = config.loop.spin_us  # [loop] spin_us: None = off (the default)
        self._spin = Spin(spin_us, self._prewarm) if spin_us > 0.0 else None
        self.shared = Shared(
            config, self.target, self.stats, self.outputs, self.recording,
            self._prewarm, self.out, self.status, self._t0_ns, budget_ns,
        )  # fmt: skip
        # The performers: each its frame path and live calibration.
        self.performers = Performers(
            performers, self.shared, self.inputs.kind_of, self.inputs.streams,
            config_path,
        )  # fmt: skip
        self._log = RateLimitedLog(self.out, config.loop.log_interval_s)
        # CURVE handshake failures and descriptor exhaustion on the bound ZeroMQ
        # sockets (their monitors: watch.py)
        self._watch = SocketWatch(self._poller, self._log, self.out)
        self._stalls = LoopStalls(self._log)  # phases over 50 ms (stalls.py)
        #: open() tells how to calibrate a performer without a calibration (False:
        #: the caller calibrates itself and says so, as ``retargetd demo`` does)
        self.hint_uncalibrated = True
        self._guards: list[CurveGuard] = []
        self._wake_ns = 0  # when the current wake-up began
        self.last_stats_line = ""
        self.endpoints: dict[str, str] = {}
        # [[prop]]: rigid props and cameras, one part called per accepted frame
        self.props = LiveProps(config.props, vmc_destinations(config),
                               self.outputs.send_pub, self.out)  # fmt: skip
        # A frame's packet, solve and emit in one compiled call (one_call.FastFrame):
        # one performer, no props (each would run between the feed and the solve)
        self.shared.fast_ok = not self.performers.several and not self.props.props
        # A capture system ([input] source: QTM, NatNet): an input of its own.
        self.capture = CaptureSource(
            self.shared, self.performers, self._poller, self.endpoints, self._warn,
            self._accept, self._stale,
        )  # fmt: skip
        # ctl requests and show control: each command a call on a part.
        self.control = Control(
            self.shared, self.performers, self.props, self.inputs, self.endpoints,
            self._log, self._stalls, self._status_and_line,
        )  # fmt: skip
        # The status document and the stats line, read from the parts' counters.
        self.health = Health(
            self.stats, self.performers, self.inputs, self.recording, self.props,
            self._watch, self._stalls, self._prewarm, self._spin, self.endpoints,
            self._t0_ns,
            self.capture.status, self.control.status,
        )  # fmt: skip
        # The console shows the first performer (its buttons act for that one);
        # its t counts from the daemon's start, as the pose stream's t does.
        first = self.performers.first
        if config.console.enabled:
            first.console = ConsoleFeed(
                config.console, self.out, t0_ns=self._t0_ns,
                face_capture=first.face is not None,
            )  # fmt: skip
            first.console.props = self.props  # it draws the props too

    @property
    def config(self) -> DaemonConfig:
        """The running configuration (``reload`` replaces its ``[[pipeline]]``)."""
        return self.shared.config

    @property
    def console(self) -> ConsoleFeed | None:
        """The browser console's feed ([console] on; it shows the first performer)."""
        console: ConsoleFeed | None = self.performers.first.console
        return console

    @property
    def rig(self) -> Any:
        """The first performer's rig."""
        return self.performers.first.rig

    @property
    def calibration(self) -> Any:
        """The first performer's calibration (None before one)."""
        return self.performers.first.calibration

    @property
    def validator(self) -> Any:
        """The first performer's live validator ([validate] on, once calibrated)."""
        return self.performers.first.path.validator

    @property
    def face(self) -> Any:
        """The first performer's live face (None: no face)."""
        return self.performers.first.face

    def request_calibration(
        self, count: object = None, by: str = "", rom_s: object = None
    ) -> str:
        """A live calibration of the first performer (the console's button)."""
        msg: str = self.performers.first.calib.request(count, by, rom_s)
        return msg

    def request_face_capture(
        self, name: str, count: int | None = None, by: str = ""
    ) -> str:
        """A face capture of the first performer (the console's button)."""
        msg: str = self.performers.first.calib.request_face(name, count, by)
        return msg

    def reload(self) -> str:
        """Reload every performer's rig and calibration files and the config
        file's ``[[pipeline]]``, waiting for the worker that reads them
        (``Performers.reload``: for tests and callers off the loop; ``ctl``, show
        control and the console go through ``Control.reload_later``, which never
        waits). ValueError: rate limited."""
        return self.performers.reload()

    def status(self) -> dict[str, Any]:
        """The status document (``retargetd ctl status --json``)."""
        return self.health.document()

    def stats_line(self) -> str:
        """The periodic one-line health summary."""
        return self.health.line()

    def _status_and_line(self) -> tuple[dict[str, Any], str]:
        """``ctl status``: the document and the line."""
        return self.status(), self.stats_line()

    def control_reply(self, parts: list[bytes]) -> dict[str, Any]:
        """The reply to one control request (``control.Control.control_reply``)."""
        return self.control.control_reply(parts)

    def _record_control(self, req: dict[str, Any]) -> str:
        """``record start`` / ``stop`` (the console's buttons)."""
        return self.control.record(req)

    # ---- lifecycle -------------------------------------------------------------------

    def open(self) -> None:
        """Bind every endpoint; prints one line each saying who can reach it."""
        c = self.config
        self.inputs.open(self._udp_bind, self._server_socket, self._own,
                         self._announce, self.out)  # fmt: skip
        self.capture.open()
        if c.output.pose.enabled:
            pose = c.output.pose
            pub = self._server_socket(zmq.PUB, pose.secret_key, pose.client_keys)
            curve = (
                f", CURVE encrypted to {len(pose.client_keys)} client key(s)"
                if pose.secret_key
                else ", plain"
            )
            self.outputs.open_pub(
                pub, pose.endpoint, pose.sndhwm, curve, self._announce
            )
            self._sockets.append(pub)
            self._watch.watch("zmq poses", pub, bool(pose.secret_key))
        self.control.open(self._udp_bind, self._server_socket, self._own,
                          self._watch, self._announce)  # fmt: skip
        if c.output.vmc.enabled:
            vmc = c.output.vmc
            self.outputs.open_vmc(vmc.allow_broadcast, self.out)
            kind = "broadcast allowed" if vmc.allow_broadcast else "unicast"
            for perf in self.performers.all:  # one avatar per destination, one socket
                host, port = perf.vmc_addr
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
        self.performers.start_validators()
        self.performers.start_solve_threads()  # [loop] solve_threads
        self.performers.prepare_streams()  # configured labels: pipelines built now
        # Everything built so far lives as long as the daemon: keep it out of the
        # garbage collector's full passes (one took ~50 ms here, holding the GIL).
        gc.collect()
        gc.freeze()
        if self.hint_uncalibrated:
            self.performers.hint_uncalibrated()

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
            fuse = may_fuse(self.config)  # the solve and the emit in one call
            if fuse and not fit:
                warm_up_solve_emit(fit=False)
            bar.update()
            if fit:
                self.out(
                    "loading the fit kernel (a first start compiles for about a minute)"
                )
                bar.set_description("kernels: fit")
                warm_up_fit()
                if fuse:
                    warm_up_solve_emit(fit=True)
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
        self.performers.first.path.warm_up()  # its stages, on a throwaway pipeline

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

    def _own(self, sock: Any) -> None:
        """Poll ``sock`` and close it with the daemon's other sockets."""
        self._poller.register(sock, zmq.POLLIN)
        self._sockets.append(sock)

    def _udp_bind(self, host: str, port: int) -> socket.socket:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        sock.bind((host, port))
        sock.setblocking(False)
        self._poller.register(sock, zmq.POLLIN)
        self._sockets.append(sock)
        return sock

    def close(self) -> None:
        """Stop an active recording (its file is finished, bounded wait) and close
        every socket (idempotent)."""
        self.recording.close()
        self._stalls.close()
        self.props.close()
        self.capture.close()
        if self.console is not None:
            self.console.stop()
        self.performers.close()  # their live validators
        self._watch.close()  # the monitors before their sockets
        for sock in self._sockets:
            with contextlib.suppress(KeyError):
                self._poller.unregister(sock)
            sock.close()
        self._sockets.clear()
        self.outputs.close()  # the VMC sockets
        for guard in self._guards:
            guard.close()
        self._guards.clear()
        if not self._shared_ctx and not self._ctx.closed:
            self._ctx.destroy(linger=0)  # its sockets are closed above

    @property
    def osc_stream(self) -> MarkerStream:
        """The OSC input's stream (its current frame, counters, label set)."""
        return self.inputs.osc_stream

    @property
    def zmq_stream(self) -> MarkerStream:
        """The ZeroMQ input's stream."""
        return self.inputs.zmq_stream

    # ---- a frame's path ----------------------------------------------------------

    def _service(self, events: list[tuple[Any, int]]) -> None:
        """One wake-up, top-down: each readable input receives its packets (decoded
        into its stream, refusals counted) and hands every accepted frame to
        :meth:`_accept`, which solves and sends it at once until the frames that
        waited have been caught up for a frame period; the newest frame left over is
        solved last (latest wins: :meth:`_leave`); then the control sockets are
        served."""
        every = self._every
        self._wake_ns = time.monotonic_ns()
        self._catch_up.wake()
        inputs = self.inputs
        ready = inputs.ready(events)  # which inputs are readable: no allocation
        if ready & READY_OSC:
            got = inputs.drain_osc(every)  # 0: every frame solved already
            if got:
                self._leave(inputs.osc_stream, got)
        if ready & READY_ZMQ:
            got = inputs.drain_zmq(every)
            if got:
                self._leave(inputs.zmq_stream, got)
        if self.capture.on:
            got = self.capture.drain(events, every)
            if got:
                self._leave(self.capture.stream, got)
        if self._left is not None:  # every performer on its input
            self.performers.solve(self._left, self._left_ns)
            self._left, self._left_ns = None, 0
        self._stalls.lap("markers")  # the drains and the solves
        if ready & READY_MONITOR:
            inputs.drain_monitor()
        if len(events) > READY_EVENTS[ready]:  # more than the inputs' sockets
            self.control.serve(events)  # ctl requests, show control (timed inside)
            self._watch.drain_ready(events, self._wake_ns)  # watched monitors

    def _accept(self, stream: MarkerStream, code: int, t_ns: int, every: bool) -> int:
        """An input's decoded frame (``code``: the stream's verdict): counted, handed
        to live calibrations and the props, then solved and sent by every performer
        on its input at once, unless the frames that waited behind this wake-up's
        solves have been caught up for a frame period already (``catchup.py``).
        Then the loop is behind and the latest frame wins: returns its receive
        time, left for later, else 0."""
        if code != ACCEPTED and code != RESTART:
            self.inputs.refused(stream, code, t_ns)
            return 0
        self.stats.frames_in += 1
        self.shared.last_frame_ns = t_ns
        self._prewarm.observe(t_ns)  # (the spin reads the same cadence)
        stream.current.frame.t_ns = t_ns
        performers = self.performers
        if code == RESTART:
            self.stats.restarts += 1
            performers.flag(pose_stream.FRAME_RESTARTED)
            performers.restart(stream)
        performers.collect(stream)  # live calibrations and face captures
        self.props.on_frame(stream, t_ns)  # [[prop]]: every accepted frame
        if not every and self._catch_up.behind(time.monotonic_ns()):
            return t_ns  # past the catch-up window: the latest wins
        performers.solve(stream, t_ns)  # every performer on this input
        self._catch_up.solved()
        return 0

    def _leave(self, stream: MarkerStream, got_ns: int) -> None:
        """An input's newest accepted frame left unsolved (``got_ns``, 0: none). With
        one ``[performer]`` only the newest of the inputs' frames is solved, the
        other counted stale; with ``[[performer]]`` tables each input's is."""
        if not got_ns:
            return
        if self._left is not None:
            # [[performer]] tables: an input may carry other performers' markers,
            # or none of one's; one [performer] reads every input.
            if self.performers.several:
                self.performers.solve(self._left, self._left_ns)
                self._left, self._left_ns = None, 0
            else:
                self._stale()
        if got_ns >= self._left_ns:
            self._left, self._left_ns = stream, got_ns

    def _stale(self) -> None:
        """An accepted frame superseded before it was solved: counted, and every
        performer's next pose flagged."""
        self.stats.stale += 1
        self.performers.flag(pose_stream.FRAME_INPUT_DROPPED)

    def _on_labels(self, stream: MarkerStream, label_set: LabelSet) -> None:
        """An input took a label set: the performers build their columns now."""
        self.shared.bump()  # (the armed one-call paths: their packets' label set)
        self.performers.prepare(stream, label_set)

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
        performers = self.performers
        prewarm = self._prewarm
        clock = prewarm.clock
        while not should_exit():
            wait = timeout
            tick_ns = performers.next_tick_ns()  # output_rate_hz: a tick queued
            if tick_ns >= 0:  # wake for it (rounded up to the poll's 1 ms)
                left_ms = -(-(tick_ns - time.monotonic_ns()) // 1_000_000)
                wait = max(0, min(timeout, left_ms))
            stalls.mark()
            now = clock()  # (the cadence's clock: time.monotonic_ns)
            wait = prewarm.wait_ms(now, wait)
            spin, allow = self._spin, 0
            if spin is not None:  # [loop] spin_us: wake for the window, spin in it
                wait, allow = spin.wait_ms(now, wait), spin.allow_ns
            events = self._poller.poll(wait)  # [(socket or fd, flags)]
            if not events and spin is not None:
                events = spin.spin(self._poller.poll)
            stalls.lap("poll", wait * 1_000_000 + allow)  # past its timeout
            if events:
                self._service(events)  # its phases timed inside
            elif prewarm.due(clock()):
                prewarm.touch()  # the fit, warm for the frame that comes next
            if self.capture.on:
                self.capture.tick()  # requests, lost check, held pose: never blocks
            now = stalls.lap("prewarm_capture")
            if self.console is not None:
                cmd = self.console.commands.poll()  # nothing allocated when empty
                if cmd is not None:
                    dispatch_console(self, cmd)
                    stalls.lap("console")
            performers.tick_calibrations(now)  # a pending one's timeout
            stalls.lap("calibration")
            self.control.tick()  # a reload's files read: swapped in, answered
            performers.tick_sends(now)  # VMC state before a calibration, ticks due
            self._log.flush(now)
            self._watch.tick(now)  # descriptor exhaustion: its end, once
            stopped = self.recording.check_limits(now)  # [record] limits, once a s
            stalls.lap("ticks")
            if stopped:
                self.out(stopped)
            if now >= next_stats:
                self.last_stats_line = self.health.line()
                self.health.roll(now)
                self.out(self.last_stats_line)
                next_stats = now + int(c.stats_interval_s * 1e9)
                stalls.lap("stats_line")


def _load_target(config: DaemonConfig) -> Any:
    t = config.target
    if t.skeleton == "humanoid":
        return default_humanoid()
    return TargetSkeleton.from_bvh(Path(t.skeleton), units=t.bvh_units, up=t.bvh_up)
