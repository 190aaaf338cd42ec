"""The marker inputs of the loop (OSC over UDP and ZeroMQ), one part: their sockets,
receive buffers and :class:`MarkerStream` each (the frame buffer a packet is decoded
and sequenced into). A drain reads every waiting packet, decodes it straight into the
preallocated buffers, counts what it refuses by reason and hands each accepted frame
to the loop (``accept``, which solves it at once until the frames that waited behind
a solve have been caught up for a frame period: ``catchup.py``); it returns the
receive time of the newest accepted frame left unsolved (latest wins: an older one
left unsolved is ``stale``).
"""

from __future__ import annotations

import logging
import select
import socket
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import zmq

from retargetd.daemon.live.catchup import CatchUp
from retargetd.daemon.live.config import ConfigError, DaemonConfig
from retargetd.daemon.live.kernel_drops import udp_kernel_drops
from retargetd.daemon.live.one_call import FAST_NOT_TAKEN, FAST_SOLVED
from retargetd.daemon.live.ratelog import OncePer
from retargetd.daemon.live.recording import FORM_OSC, FORM_ZMQ, LiveRecording
from retargetd.daemon.live.stats import LoopStats
from retargetd.daemon.live.surface import (
    KeyFileError,
    curve_client,
    endpoint_is_local,
    is_loopback_host,
    osc_verifier,
    unauthenticated_warning,
    who_reaches,
)
from retargetd.protocols import kernels as protocol_kernels
from retargetd.protocols import osc_auth, osc_in, zmq_wire
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

_UDP_MAX = 65536

#: :meth:`Inputs.ready` bits: which of the inputs' sockets the poll found readable.
READY_OSC, READY_ZMQ, READY_MONITOR = 1, 2, 4
#: How many poll events the ``READY_*`` bits stand for (index: the bits).
READY_EVENTS = tuple(bin(bits).count("1") for bits in range(8))

#: ``accept(stream, code, t_ns, every) -> int``: the loop's hand-off of a decoded
#: frame (the receive time when it is left unsolved for later, else 0).
Accept = Callable[[MarkerStream, int, int, bool], int]


class Inputs:
    """The OSC and ZeroMQ marker inputs: sockets, buffers, streams, drains.

    Args:
        config: the daemon's configuration (``[input.osc]``, ``[input.zmq]``).
        stats: the loop's counters (frames refused by source, stale, disconnects).
        recording: the live recording (raw packets, when one records them).
        warn: the loop's once-per-interval gate for warning lines.
        accept: the loop's hand-off of an accepted frame (see :data:`Accept`).
        on_labels: told of every label set an input takes (the performers build
            their columns for it then, off the hot path).
        stale: called when an accepted frame is superseded before it was solved.
        catch_up: the wake-up's catch-up state: a stream's armed one-call path
            (``stream.fast``, ``one_call.FastFrame``) takes the wake-up's first solve.

    Raises:
        ConfigError: ``[input.osc] key_file`` unreadable since the config was read.
    """

    def __init__(
        self,
        config: DaemonConfig,
        stats: LoopStats,
        recording: LiveRecording,
        warn: OncePer,
        accept: Accept,
        on_labels: Callable[[MarkerStream, LabelSet], None],
        stale: Callable[[], None],
        catch_up: CatchUp,
    ) -> None:
        self.config = config
        self.stats = stats
        self.recording = recording
        self._warn = warn
        self._accept = accept
        self._on_labels = on_labels
        self._stale = stale
        self._catch_up = catch_up
        osc_cfg, zmq_cfg = config.input.osc, config.input.zmq
        simple_labels = (
            LabelSet(0, osc_cfg.labels) if osc_cfg.form == "simple" else None
        )
        self.osc_stream = _stream(simple_labels, osc_cfg)
        self.zmq_stream = _stream(None, zmq_cfg)
        self.osc: socket.socket | None = None
        self.zin: zmq.Socket[bytes] | None = None
        self._zmon: zmq.Socket[bytes] | None = None  # the input's disconnect events
        self._buf = bytearray(_UDP_MAX)
        # ZeroMQ input parts, received in place: header (a frame's or a label set's
        # is 32 / 16 bytes; 64 leaves room to see a wrong one), payload (the limit).
        self._zbuf_header = bytearray(64)
        self._zbuf_payload = bytearray(zmq_cfg.max_message_bytes)
        self._zbuf_extra = bytearray(64)
        self._zview_header = memoryview(self._zbuf_header)
        self._zview_payload = memoryview(self._zbuf_payload)
        # The same buffers as uint8 arrays: the compiled decode reads them in place.
        self._view = memoryview(self._buf)
        self._wire = np.frombuffer(self._buf, dtype=np.uint8)
        self._zwire_header = np.frombuffer(self._zbuf_header, dtype=np.uint8)
        self._zwire_payload = np.frombuffer(self._zbuf_payload, dtype=np.uint8)
        self._osc_simple = osc_cfg.form == "simple"
        self._osc_fd = -2  # the poll result's fd (set by open)
        self._osc_more: Any = None  # select.poll of the OSC socket (set by open)
        self._osc_limit = osc_cfg.max_message_bytes
        self.allow = frozenset(osc_cfg.allow)
        self.osc_form = FORM_OSC[osc_cfg.form]
        # What a stream's one-call path feeds from (one_call.FastFrame): its form and
        # the receive buffers (the simple OSC form decodes in Python: none).
        if not self._osc_simple:
            self.osc_stream.wire = (_OSC_COMPACT, self._wire, self._wire)
        self.zmq_stream.wire = (_ZMQ_FRAME, self._zwire_header, self._zwire_payload)
        try:  # [input.osc] key_file: signed datagrams only (PROTOCOLS.md 13)
            self._osc_auth = osc_verifier(osc_cfg.key_file)
        except KeyFileError as exc:  # changed since the config was checked
            raise ConfigError(f"input.osc.key_file: {exc}") from None

    # ---- lifecycle -------------------------------------------------------------------

    def open(
        self,
        udp_bind: Callable[[str, int], socket.socket],
        server_socket: Callable[[int, str, tuple[str, ...]], Any],
        own: Callable[[Any], None],
        announce: Callable[[str, str], None],
        out: Callable[[str], None],
    ) -> None:
        """Bind (or connect) the enabled inputs.

        Args:
            udp_bind: the loop's UDP bind (registered with its poller).
            server_socket: the loop's ZeroMQ socket factory (CURVE when keyed).
            own: registers a ZeroMQ socket with the loop's poller and closes it
                with the others.
            announce: says an endpoint ("listening on ...").
            out: where warnings go.
        """
        c = self.config
        if c.input.osc.enabled:
            osc = c.input.osc
            self.osc = udp_bind(osc.host, osc.port)
            self._osc_fd = self.osc.fileno()
            self._osc_more = select.poll()  # "another datagram waits?" (drain_osc)
            self._osc_more.register(self._osc_fd, select.POLLIN)
            allow = f", sources {', '.join(osc.allow)} only" if osc.allow else ""
            local = is_loopback_host(osc.host)
            who = who_reaches(local, osc.host)
            signed = ", signed only (HMAC-SHA256)" if osc.key_file else ""
            host, port = self.osc.getsockname()[:2]
            announce(
                "osc markers",
                f"udp://{host}:{port} ({osc.form}; frames from {who}{allow}{signed})",
            )
            if not local and not osc.key_file:
                out(unauthenticated_warning("osc", osc.host, "key_file"))
        if not c.input.zmq.enabled:
            return
        zin = c.input.zmq
        local = endpoint_is_local(zin.endpoint)
        pull = zin.mode == "pull"
        # CURVE as the control socket's: a bound PULL is the server letting in
        # the listed clients; a SUB is a client of the publisher's key.
        sock = server_socket(
            zmq.PULL if pull else zmq.SUB,
            zin.secret_key if pull else "",
            zin.client_keys,
        )
        self.zin = sock
        if not pull and zin.secret_key:
            curve_client(sock, zin.secret_key, zin.server_key)
        sock.setsockopt(zmq.LINGER, 0)
        # Bounded queue: 1,000 messages of parts of at most max_message_bytes;
        # libzmq drops the connection of a peer sending a larger part, before
        # buffering it (inproc bypasses this: the drain checks sizes too).
        sock.setsockopt(zmq.RCVHWM, 1000)
        sock.setsockopt(zmq.MAXMSGSIZE, zin.max_message_bytes)
        if pull:
            sock.bind(zin.endpoint)
            who = f"frames from {who_reaches(local, zin.endpoint)}"
        else:
            sock.setsockopt(zmq.SUBSCRIBE, b"RTD")
            sock.connect(zin.endpoint)
            who = f"frames from the publisher at {zin.endpoint}"
        own(sock)
        self._zmon = sock.get_monitor_socket(zmq.EVENT_DISCONNECTED)
        self._zmon.setsockopt(zmq.LINGER, 0)
        own(self._zmon)
        ep = last_endpoint(sock) or zin.endpoint
        curve = ", CURVE" if zin.secret_key else ""
        if pull and zin.secret_key:
            curve += f": {len(zin.client_keys)} client key(s)"
        announce("zmq markers", f"{ep} ({zin.mode}; {who}{curve})")
        if not local and not zin.secret_key:
            keys = "client_keys" if pull else "server_key"
            out(unauthenticated_warning("zmq", zin.endpoint, keys))

    # ---- one wake-up -----------------------------------------------------------------

    def ready(self, events: list[tuple[Any, int]]) -> int:
        """Which inputs the poll found readable (``READY_*`` bits): a scan of the
        poll result, no allocation."""
        bits = 0
        zin, zmon, osc_fd = self.zin, self._zmon, self._osc_fd
        for sock, _flags in events:
            if sock is zin:
                bits |= READY_ZMQ
            elif sock is zmon:
                bits |= READY_MONITOR
            elif sock == osc_fd:
                bits |= READY_OSC
        return bits

    def refused(self, stream: MarkerStream, code: int, t_ns: int) -> None:
        """A decoded frame the stream refused (counted by the stream): a frame number
        jumping implausibly is said, once per interval and input."""
        if code != IMPLAUSIBLE_JUMP:
            return
        name = self.kind_of(stream)
        self._log_limited(
            f"{name}.implausible_jump",
            t_ns,
            "%s input: frame number jumped implausibly past %d (faster than "
            "max_rate_hz); dropped (implausible_jump)",
            name,
            stream.sequencer.last_frame,
        )

    def drain_osc(self, every: bool) -> int:
        """Read every waiting OSC datagram; the receive time of the newest accepted
        frame left unsolved, else 0."""
        assert self.osc is not None
        sock, buf, stream = self.osc, self._buf, self.osc_stream
        simple = self._osc_simple
        limit = self._osc_limit
        allow = self.allow
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
                rec.record_packet("osc", self.osc_form, t_ns, self._view[:n])
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
            else:  # decode, sequencing and counter in one compiled call, in place
                code = FAST_NOT_TAKEN
                fast = stream.fast  # with the frame's solve and emit in it, armed:
                if (  # the wake-up's first solve (catchup.py)
                    fast is not None
                    and fast.epoch == fast.shared.epoch
                    and not self._catch_up.solved_any
                ):
                    code = fast.run(stream, n, 0, t_ns)
                    if code == FAST_SOLVED:  # sent: what _accept does after it
                        self._catch_up.solved_any = True
                        continue
                if code == FAST_NOT_TAKEN:
                    code = stream.feed_packed(_OSC_COMPACT, self._wire, n, self._wire,
                                              0, t_ns)  # fmt: skip
                if code < 0:  # refused by the compiled checks: the decoder says why
                    code = stream.feed(osc_in.decode_compact_into, self._wire, n,
                                       t_ns=t_ns)  # fmt: skip
            if code != ACCEPTED and code != RESTART:
                self.refused(stream, code, t_ns)
                continue
            got = self._accept(stream, code, t_ns, every)
            if got:
                if newest:  # a newer frame supersedes the unsolved one: stale
                    self._stale()
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

    def drain_zmq(self, every: bool) -> int:
        """Read every waiting ZeroMQ message; as :meth:`drain_osc`."""
        assert self.zin is not None
        sock, stream = self.zin, self.zmq_stream
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
            code = FAST_NOT_TAKEN
            fast = stream.fast  # the frame's solve and emit in the call (drain_osc)
            if (
                fast is not None
                and fast.epoch == fast.shared.epoch
                and not self._catch_up.solved_any
            ):
                code = fast.run(stream, n0, n1, t_ns)
                if code == FAST_SOLVED:
                    self._catch_up.solved_any = True
                    continue
            if code == FAST_NOT_TAKEN:
                code = stream.feed_packed(
                    _ZMQ_FRAME, self._zwire_header, n0, self._zwire_payload, n1, t_ns
                )  # decode, sequencing and counter in one compiled call, in place
            if code < 0:  # refused by the compiled checks: the decoder says why
                code = stream.feed(
                    zmq_wire.decode_zmq_into, self._zwire_header, n0,
                    self._zwire_payload, n1, t_ns=t_ns,
                )  # fmt: skip
            if code != ACCEPTED and code != RESTART:
                self.refused(stream, code, t_ns)
                continue
            got = self._accept(stream, code, t_ns, every)
            if got:
                if newest:  # a newer frame supersedes the unsolved one: stale
                    self._stale()
                newest = got
        return newest

    def drain_monitor(self) -> None:
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
        self._on_labels(stream, label_set)  # performers' columns, built now
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
        if self._warn.due(key, t_ns):
            logger.warning(msg, *args)

    # ---- what the other parts read --------------------------------------------------

    def kind_of(self, stream: object) -> str:
        """The input a stream belongs to: "osc", "zmq" or "source" (the capture
        system's)."""
        if stream is self.osc_stream:
            return "osc"
        return "zmq" if stream is self.zmq_stream else "source"

    def streams(self) -> tuple[MarkerStream, MarkerStream]:
        """The OSC and ZeroMQ inputs' streams (whether on or off)."""
        return self.osc_stream, self.zmq_stream

    def label_announcements(self) -> list[tuple[str, int, tuple[bytes, ...]]]:
        """The label sets in use, as their inputs' packets: a recording started
        mid-stream opens with them."""
        out: list[tuple[str, int, tuple[bytes, ...]]] = []
        if self.osc is not None and self.config.input.osc.form == "compact":
            ls = self.osc_stream.label_set
            if ls is not None:
                out.append(("osc", self.osc_form, (osc_in.encode_labels(ls),)))
        if self.zin is not None and self.zmq_stream.label_set is not None:
            parts = tuple(zmq_wire.encode_zmq_labels(self.zmq_stream.label_set))
            out.append(("zmq", FORM_ZMQ, parts))
        return out

    def status(self) -> dict[str, Any]:
        """The inputs' part of the status document."""
        osc, zin = self.osc_stream, self.zmq_stream
        return {
            "implausible_markers": int(osc.implausible[0] + zin.implausible[0]),
            "drops": {"osc": osc.counters.as_dict(), "zmq": zin.counters.as_dict()},
            "labels_taken": {"osc": osc.labels_taken, "zmq": zin.labels_taken},
            "kernel_drops_osc": udp_kernel_drops(self.osc),
        }


def last_endpoint(sock: Any) -> str:
    """The endpoint a socket bound (with the real port of a ``*`` wildcard)."""
    value = sock.getsockopt(zmq.LAST_ENDPOINT)
    return value.decode() if isinstance(value, bytes) else str(value)


_CONFLICTING = REASON_INDEX["conflicting_labels"]
#: ``MarkerStream.feed_packed`` forms.
_OSC_COMPACT = protocol_kernels.FORM_OSC_COMPACT
_ZMQ_FRAME = protocol_kernels.FORM_ZMQ
_TOO_MANY = REASON_INDEX["too_many_markers"]


def _stream(labels: LabelSet | None, cfg: Any) -> MarkerStream:
    """An input's marker stream, as its ``[input.osc]`` / ``[input.zmq]`` table sets
    it (``labels``: the simple OSC form's fixed set, else None until announced)."""
    return MarkerStream(
        labels,
        cfg.up,
        cfg.units,
        max_rate_hz=cfg.max_rate_hz,
        max_markers=cfg.max_markers,
        zero_is_occluded=cfg.zero_is_occluded,
        max_coordinate_m=cfg.max_coordinate_m,
    )
