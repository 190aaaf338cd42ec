"""One wake-up of the loop: drain every readable marker input (OSC and ZeroMQ), decoding
straight into preallocated buffers; malformed packets counted by reason and dropped;
accepted frames solved at once while the wake-up is within ``solve_budget_ms``, past it
the latest frame wins (the rest counted ``stale``).
"""

from __future__ import annotations

import logging
import time
from typing import Any

import zmq

from retargetd.daemon.live.recording import (
    FORM_ZMQ,
)
from retargetd.daemon.live.state import DaemonState
from retargetd.protocols import osc_auth, osc_in, pose_stream, zmq_wire
from retargetd.protocols.errors import DecodeError
from retargetd.protocols.marker_input import (
    ACCEPTED,
    AUTH_FAILED,
    AUTH_REPLAYED,
    IMPLAUSIBLE_JUMP,
    REASON_INDEX,
    RESTART,
    LabelSet,
    MarkerStream,
)

logger = logging.getLogger(__name__)

#: One log line per kind of input trouble and input at most this often (10 s): the
#: counters carry the exact numbers, the log only says that it happens.
LOG_INTERVAL_NS = 10_000_000_000


class InputsMixin(DaemonState):
    """Draining the marker inputs in one wake-up: decode into preallocated buffers,
    count what is dropped, solve while within the budget, latest wins past it.
    """

    def _service(self, events: list[tuple[Any, int]]) -> None:
        every = self.config.loop.process_every_frame
        self._wake_ns = time.monotonic_ns()
        # Which sockets are readable: a scan of the poll result (no dict per wake-up).
        osc = zin = zmon = show = ctl = False
        osc_fd, show_fd = self._osc_fd, self._show_fd
        for sock, _flags in events:
            if sock is self._zin:
                zin = True
            elif sock is self._ctl:
                ctl = True
            elif sock is self._zmon:
                zmon = True
            elif sock == osc_fd:
                osc = True
            elif sock == show_fd:
                show = True
            else:  # a watched socket's monitor (watch.py): never on the hot path
                self._watch.drain(sock, self._wake_ns)
        newest: MarkerStream | None = None
        newest_ns = 0
        if osc:
            got = self._drain_osc(every)
            if got:
                newest, newest_ns = self.osc_stream, got
        if zin:
            got = self._drain_zmq(every)
            if got and newest is not None and not every:
                if self._multi:  # several performers: each input's own latest
                    self._solve(newest, newest_ns)
                    newest, newest_ns = None, 0
                else:
                    # Both inputs delivered in one wake-up: only the newer one is
                    # solved, so the other's newest frame is stale too (counted,
                    # never silent).
                    self.stats.stale += 1
                    self._flag_frames(pose_stream.FRAME_INPUT_DROPPED)
            if got and got >= newest_ns:
                newest, newest_ns = self.zmq_stream, got
        if self._capture is not None:
            got = self._drain_capture(events, every)
            if got and newest is not None and not every:
                if self._multi:  # as above
                    self._solve(newest, newest_ns)
                    newest, newest_ns = None, 0
                else:
                    self.stats.stale += 1  # two inputs in one wake-up, as above
                    self._flag_frames(pose_stream.FRAME_INPUT_DROPPED)
            if got and got >= newest_ns:
                newest, newest_ns = self._capture.inp.stream, got
        if newest is not None and not every:
            self._solve(newest, newest_ns)
        stalls = self._stalls
        stalls.lap("markers")  # the drain and the solves
        if zmon:
            self._drain_zmq_monitor()
        if show:
            self._drain_show_control()
            stalls.lap("show_control")
        if ctl:
            self._serve_control()  # its lap names the command

    def _accept(self, stream: MarkerStream, code: int, t_ns: int, every: bool) -> int:
        """Book-keeping for one decoded packet; returns its receive time when it was
        accepted and left for later (latest wins), else 0."""
        if code != ACCEPTED and code != RESTART:
            if code == IMPLAUSIBLE_JUMP:
                name = (
                    "osc"
                    if stream is self.osc_stream
                    else "zmq"
                    if stream is self.zmq_stream
                    else "capture"
                )
                self._log_limited(
                    f"{name}.implausible_jump",
                    t_ns,
                    "%s input: frame number jumped implausibly past %d (faster than "
                    "max_rate_hz); dropped (implausible_jump)",
                    name,
                    stream.sequencer.last_frame,
                )
            return 0
        self.stats.frames_in += 1
        self._last_frame_ns = t_ns
        self._prewarm.observe(t_ns)
        stream.current.frame.t_ns = t_ns
        if code == RESTART:
            self.stats.restarts += 1
            self._flag_frames(pose_stream.FRAME_RESTARTED)
            self._restart_pipelines(stream)
        self._collect(stream)  # live calibrations and face captures
        self.props.on_frame(stream, t_ns)  # [[prop]]: every accepted frame
        # Solve at once while this wake-up is within the budget (frames that merely
        # arrived together are all solved); past it the loop is behind, and the
        # latest frame wins: this one waits and is dropped if a newer one comes.
        if every or time.monotonic_ns() - self._wake_ns < self._catch_up_ns:
            if self._multi:
                self._solve(stream, t_ns)  # every performer on this input
            else:
                self._solve_and_send(stream, t_ns)  # (what _solve does for one)
            return 0
        return t_ns

    def _drain_osc(self, every: bool) -> int:
        assert self._osc is not None
        sock, buf, stream = self._osc, self._buf, self.osc_stream
        simple = self._osc_simple
        limit = self._osc_limit
        allow = self._allow
        more = self._osc_more
        auth, view = self._osc_auth, self._view
        newest = 0  # receive time of the newest accepted frame not yet solved
        # The poll said a datagram waits; after it, a zero-timeout poll of this socket
        # says whether another does: the receive that ends a drain in EAGAIN raises
        # (an exception object), and recvfrom_into builds the sender's address tuple;
        # both cost more than the poll (one datagram paced at 240 Hz, median: 69 us
        # with both, 34 with neither; bench/bench_socket_calls.py). The address is
        # read only for an allow list.
        k = 0
        while k == 0 or more.poll(0):
            k += 1
            try:
                # One byte more than the limit: a larger datagram shows as n > limit
                # (the kernel truncates it), refused before any decoding.
                if allow:
                    n, addr = sock.recvfrom_into(buf, limit + 1)
                    if addr[0] not in allow:
                        self.stats.rejected_sources += 1
                        continue
                else:
                    n = sock.recv_into(buf, limit + 1)
            except (BlockingIOError, InterruptedError):
                break
            if n > limit:
                stream.counters.add_reason("too_large")
                continue
            t_ns = time.monotonic_ns()
            if auth is not None:  # before any OSC in it is parsed
                m = auth.check(view, n)
                if m < 0:
                    self._refuse_unsigned(stream, m, t_ns)
                    continue
                if auth.new_session:  # the sender restarted: so does its sequence
                    stream.sequencer.restart_next()
                n = m  # the datagram without its trailer (recorded, decoded)
            rec = self.recording.packets
            if rec is not None:
                rec.record_packet("osc", self._osc_form, t_ns, self._view[:n])
            if simple:
                code = stream.feed(
                    osc_in.decode_simple_bundle, self._view[:n], t_ns=t_ns
                )
            elif n >= 12 and buf.startswith(b"/rtd/labels\0"):  # no per-packet copy
                try:
                    label_set = osc_in.decode_labels(self._view[:n])
                except DecodeError as exc:
                    stream.counters.add_reason(exc.reason)
                    continue
                self._take_labels("osc", stream, label_set, t_ns)
                continue
            else:  # checks and store in one compiled call, from the buffer itself
                code = stream.feed(osc_in.decode_compact_into, self._wire, n, t_ns=t_ns)
            got = self._accept(stream, code, t_ns, every)
            if got:
                if newest:  # a newer frame supersedes the unsolved one: stale
                    self.stats.stale += 1
                    self._flag_frames(pose_stream.FRAME_INPUT_DROPPED)
                newest = got
        return newest

    def _refuse_unsigned(self, stream: MarkerStream, code: int, t_ns: int) -> None:
        """Count a datagram the HMAC check refused (``osc_auth``); one log line per
        kind every ``LOG_INTERVAL_NS``."""
        if code == osc_auth.REPLAYED:
            stream.counters.add(AUTH_REPLAYED)
            auth = self._osc_auth
            assert auth is not None
            self._log_limited(
                "osc.auth_replayed", t_ns,
                "osc input: a signed datagram not newer than the last accepted "
                "(session %d, counter %d) refused (auth_replayed)",
                auth.session, auth.counter,
            )  # fmt: skip
            return
        stream.counters.add(AUTH_FAILED)
        what = (
            "unsigned (no RTDS trailer)"
            if code == osc_auth.UNSIGNED
            else "its tag is not the key's (another key, or altered bytes)"
        )
        self._log_limited(
            f"osc.auth_failed.{code}", t_ns,
            "osc input: a datagram refused, %s (auth_failed)", what,
        )  # fmt: skip

    def _drain_zmq(self, every: bool) -> int:
        assert self._zin is not None
        sock, stream = self._zin, self.zmq_stream
        limit = self.config.input.zmq.max_message_bytes
        # Parts are received into preallocated buffers (``recv_into`` returns the
        # part's full size, so a larger one shows as n > the buffer): no Frame objects,
        # no bytes per message. Parts past the second go to a scratch buffer.
        hbuf, pbuf, scratch = self._zbuf_header, self._zbuf_payload, self._zbuf_extra
        hview, pview = self._zview_header, self._zview_payload
        newest = 0  # receive time of the newest accepted frame not yet solved
        # Drained while ZMQ_EVENTS says a message waits: the empty socket's zmq.Again
        # is a Python exception object per wake-up (its enum and strerror: ~10 µs
        # under cProfile), the option read is one C call.
        while int(sock.get(zmq.EVENTS)) & zmq.POLLIN:
            try:
                n0 = sock.recv_into(hbuf, flags=zmq.NOBLOCK)
            except zmq.Again:
                break
            n_parts, n1 = 1, 0
            while sock.get(zmq.RCVMORE):  # the rest of a message is already here
                if n_parts == 1:
                    n1 = sock.recv_into(pbuf)
                else:
                    sock.recv_into(scratch)
                n_parts += 1
            t_ns = time.monotonic_ns()
            if n0 > len(hbuf) or n1 > limit:  # before decoding
                stream.counters.add_reason("too_large")
                continue
            header, payload = hview[:n0], pview[:n1]
            rec = self.recording.packets
            if rec is not None:
                if n_parts == 1:
                    rec.record_packet("zmq", FORM_ZMQ, t_ns, header)
                else:  # (parts past the second are not kept: malformed anyway)
                    rec.record_packet("zmq", FORM_ZMQ, t_ns, header, payload)
            if n_parts != 2:
                stream.counters.add_reason("bad_length")
                continue
            if n0 >= 4 and hbuf.startswith(zmq_wire.LABELS_MAGIC):
                try:
                    label_set = zmq_wire.decode_zmq_labels(
                        header, payload, stream.max_markers
                    )
                except DecodeError as exc:
                    stream.counters.add_reason(exc.reason)
                    continue
                self._take_labels("zmq", stream, label_set, t_ns)
                continue
            code = stream.feed(
                zmq_wire.decode_zmq_into, self._zwire_header, n0, self._zwire_payload,
                n1, t_ns=t_ns,
            )  # fmt: skip
            got = self._accept(stream, code, t_ns, every)
            if got:
                if newest:  # a newer frame supersedes the unsolved one: stale
                    self.stats.stale += 1
                    self._flag_frames(pose_stream.FRAME_INPUT_DROPPED)
                newest = got
        return newest

    def _drain_zmq_monitor(self) -> None:
        """Count the ZeroMQ input's disconnect events (a part over MAXMSGSIZE makes
        libzmq drop the peer before buffering it; a sender closing does too)."""
        assert self._zmon is not None
        while True:
            try:
                self._zmon.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                return
            self.stats.zmq_disconnects += 1
            self._log_limited(
                "zmq.disconnect",
                time.monotonic_ns(),
                "zmq input: a peer was disconnected (a message part over "
                "input.zmq.max_message_bytes = %d, or the peer closed)",
                self.config.input.zmq.max_message_bytes,
            )

    def _take_labels(
        self, name: str, stream: MarkerStream, label_set: LabelSet, t_ns: int
    ) -> None:
        """Hand an announcement to the stream; log a label conflict or refusal (one
        line per input and kind every ``LOG_INTERVAL_NS``; the counters say how many).
        """
        self.stats.labels_in += 1
        before = stream.counters.counts.copy()  # announcements are rare: not hot
        stream.set_labels(label_set, t_ns)
        self._prepare_views(stream, label_set)  # performers' columns, built now
        after = stream.counters
        if after["conflicting_labels"] > before[_CONFLICTING]:
            self._log_limited(
                f"{name}.label_conflict",
                t_ns,
                "%s input: label set %d announced with other names while its frames "
                "stream (conflicting_labels); the names in use stay until the old "
                "names are announced again, a new id is, or the new names persist "
                "for 1 s",
                name,
                label_set.id,
            )
        if after["too_many_markers"] > before[_TOO_MANY]:
            self._log_limited(
                f"{name}.too_many_markers",
                t_ns,
                "%s input: label set %d of %d markers refused (max_markers %d)",
                name,
                label_set.id,
                len(label_set.labels),
                stream.max_markers,
            )

    def _log_limited(self, key: str, t_ns: int, msg: str, *args: Any) -> None:
        """``logger.warning`` at most once per ``LOG_INTERVAL_NS`` for ``key``."""
        if t_ns < self._log_after_ns.get(key, 0):
            return
        self._log_after_ns[key] = t_ns + LOG_INTERVAL_NS
        logger.warning(msg, *args)


_CONFLICTING = REASON_INDEX["conflicting_labels"]
_TOO_MANY = REASON_INDEX["too_many_markers"]
