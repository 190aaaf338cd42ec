"""OptiTrack Motive as a live marker source: the NatNet client's sockets (unicast or
multicast), its command exchange with the server, the ``natnet://`` URL, and the loop's
input. The bitstream itself (packets, model definitions, frames of data) is decoded by
``protocols/natnet.py``.

Loop integration (one thread, never blocks)::

    opts = parse_natnet_url("natnet://HOST")           # or from the config
    client = opts.client(out)                           # binds non-blocking sockets
    inp = NatNetInput(client, opts.up_axis)
    for sock in client.fds(): poller.register(sock, zmq.POLLIN)
    # every wake-up / poll timeout: client.tick()
    # for each readable sock: while (pkt := client.read(sock)) is not None:
    #     record pkt (form natnet, kind from packet_info(pkt)); code = inp.feed(pkt, t)
    #     code ACCEPTED / RESTART -> inp.stream.current.frame; -1 -> control message
    # close: client.close()

Replay: ``NatNetInput(None, up_axis).feed(pkt, t_ns)`` for every recorded datagram.
"""

from __future__ import annotations

import contextlib
import logging
import math
import socket
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from retargetd.protocols.errors import DecodeError
from retargetd.protocols.marker_input import MarkerPacket
from retargetd.protocols.natnet import (
    COUNT_MISMATCH,
    DEFAULT_COMMAND_PORT,
    DEFAULT_DATA_PORT,
    DEFAULT_MULTICAST_GROUP,
    NAT_FRAMEOFDATA,
    NAT_KEEPALIVE,
    NAT_REQUEST_MODELDEF,
    NAT_SERVERINFO,
    REQUESTED_VERSION,
    Buffer,
    NatNetSession,
    Version,
    encode_connect,
    encode_request,
)

logger = logging.getLogger(__name__)


#: Wait this long for a command reply before asking again (Motive answers within a
#: frame; the SDK sample's command socket times out at 2 s, we re-ask sooner).
COMMAND_RETRY_S = 1.0
#: Unicast keep-alive period: the SDK's NatNetClient.py sends one per second.
KEEPALIVE_S = 1.0
#: No packet for this long: the server is gone (2 s, the SDK sample's timeout).
SERVER_TIMEOUT_S = 2.0


class NatNetClient:
    """Command-port client and data socket for one Motive server; never blocks.

    All sockets are non-blocking UDP. The loop polls :meth:`fds`, reads every
    datagram with :meth:`read` and hands it to :meth:`NatNetInput.feed` (frames and
    control messages alike, so a recording holds both). :meth:`tick` (every wake-up
    or poll timeout) sends the connect and model-definition requests until answered,
    the unicast keep-alive, and notices a silent server.

    Unicast: requests go from the command socket to Motive's command port, and Motive
    answers and streams to that socket's address (the SDK's NatNetClient.py reads
    frames on its command socket too). Multicast: frames arrive on a data socket bound
    to ``data_port`` and joined to ``group``.

    Args:
        host: Motive's address.
        command_port / data_port: Motive's ports (1510 / 1511 by default).
        multicast: receive data from ``group`` (Motive's "Multicast" transmission).
        group: the multicast group.
        local: the local interface address for the binds and the group join.
        sets: the marker sets to read (all but ``all`` when None).
        subjects: label every marker ``<set>:<name>``.
        version: bitstream version asked for in ``NAT_CONNECT``.
        out: where status lines go.

    Attributes:
        session: what the server told us (decoder, label set, counts).
        timeouts: how often the server fell silent for :data:`SERVER_TIMEOUT_S`.
    """

    def __init__(
        self,
        host: str,
        command_port: int = DEFAULT_COMMAND_PORT,
        data_port: int = DEFAULT_DATA_PORT,
        *,
        multicast: bool = False,
        group: str = DEFAULT_MULTICAST_GROUP,
        local: str = "0.0.0.0",
        sets: Sequence[str] | None = None,
        subjects: bool = False,
        version: Version = REQUESTED_VERSION,
        out: Callable[[str], None] | None = None,
    ) -> None:
        self.server = (host, command_port)
        self.requested = version
        self._say = out or logger.info
        self.session = NatNetSession(sets, version, self._say, host, subjects)
        self.timeouts = 0
        self.cmd = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.cmd.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        self.cmd.bind((local, 0))
        self.cmd.setblocking(False)
        self.data: socket.socket | None = None
        if multicast:
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
            sock.bind(("", data_port))
            mreq = socket.inet_aton(group) + socket.inet_aton(local)
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, mreq)
            sock.setblocking(False)
            self.data = sock
        self._buf = bytearray(65536)
        self._view = memoryview(self._buf)
        self._last_rx = 0.0
        self._last_connect = -math.inf
        self._last_modeldef = -math.inf
        self._last_keepalive = -math.inf
        self._silent = False

    def fds(self) -> list[socket.socket]:
        """The sockets to poll (register them with ``zmq.POLLIN``)."""
        return [self.cmd] + ([self.data] if self.data is not None else [])

    def close(self) -> None:
        """Close the sockets (idempotent)."""
        for sock in self.fds():
            with contextlib.suppress(OSError):
                sock.close()

    def _send(self, packet: bytes) -> None:
        # UDP: a lost or refused request is sent again by tick().
        with contextlib.suppress(
            BlockingIOError, InterruptedError, ConnectionRefusedError
        ):
            self.cmd.sendto(packet, self.server)

    def tick(self, now_s: float | None = None) -> None:
        """Send what is due (connect, model definitions, keep-alive); never blocks."""
        now = time.monotonic() if now_s is None else now_s
        session = self.session
        if session.info is None and now - self._last_connect >= COMMAND_RETRY_S:
            self._last_connect = now
            self._send(encode_connect(self.requested))
        elif (
            session.info is not None
            and session.decoder is None
            and now - self._last_modeldef >= COMMAND_RETRY_S
        ):
            self.request_models(now)
        if self.data is None and now - self._last_keepalive >= KEEPALIVE_S:
            self._last_keepalive = now
            self._send(encode_request(NAT_KEEPALIVE))
        if (
            self._last_rx
            and not self._silent
            and now - self._last_rx >= SERVER_TIMEOUT_S
        ):
            self._silent = True
            self.timeouts += 1
            self._say(
                f"natnet: no packet from {self.server[0]} for {SERVER_TIMEOUT_S:g} s; "
                "holding the last pose, reconnecting"
            )
            session.info = None  # connect again (Motive restarted?)

    def request_models(self, now_s: float | None = None) -> None:
        """Ask for the model definitions (after a change or a ``count_mismatch``)."""
        self._last_modeldef = time.monotonic() if now_s is None else now_s
        self._send(encode_request(NAT_REQUEST_MODELDEF))

    def read(self, sock: socket.socket) -> memoryview | None:
        """One datagram from ``sock`` (a view into a buffer the next call reuses),
        or None when the socket is drained. Never blocks."""
        while True:
            try:
                n = sock.recv_into(self._buf)
            except (BlockingIOError, InterruptedError):
                return None
            except ConnectionRefusedError:
                continue  # ICMP from a closed port: server not (yet) there
            self._last_rx = time.monotonic()
            if self._silent:
                self._silent = False
                self._say(f"natnet: {self.server[0]} is back")
            return self._view[:n]


@dataclass(frozen=True, slots=True)
class NatNetOptions:
    """Where and how to reach Motive: what ``natnet://`` names.

    Attributes:
        host: Motive's address.
        command_port / data_port: 1510 / 1511 by default.
        multicast / group / local: transmission type, group, local interface.
        up_axis: Motive's streaming up axis (``+Y`` default).
        sets: the marker sets to read (None: all but ``all``).
        subjects: label every marker ``<set>:<name>`` (``subjects=1``).
    """

    host: str
    command_port: int = DEFAULT_COMMAND_PORT
    data_port: int = DEFAULT_DATA_PORT
    multicast: bool = False
    group: str = DEFAULT_MULTICAST_GROUP
    local: str = "0.0.0.0"
    up_axis: str = "+Y"
    sets: tuple[str, ...] | None = None
    subjects: bool = False

    def client(self, out: Callable[[str], None] | None = None) -> NatNetClient:
        """A client for these options."""
        return NatNetClient(
            self.host,
            self.command_port,
            self.data_port,
            multicast=self.multicast,
            group=self.group,
            local=self.local,
            sets=self.sets,
            subjects=self.subjects,
            out=out,
        )


def parse_natnet_url(url: str) -> NatNetOptions:
    """``natnet://HOST[:COMMAND_PORT][?data_port=N&multicast=1&group=G&local=A
    &up=+Z&sets=A,B&subjects=1]`` -> options.

    Raises:
        ValueError: naming the part that is wrong.
    """
    from urllib.parse import parse_qs, urlsplit

    from retargetd.protocols.conventions import normalize_up_axis

    parts = urlsplit(url)
    if parts.scheme != "natnet" or not parts.hostname:
        raise ValueError(f"expected natnet://HOST[:PORT][?...]; got {url!r}")
    query = {k: v[-1] for k, v in parse_qs(parts.query, strict_parsing=False).items()}
    known = {"data_port", "multicast", "group", "local", "up", "sets", "subjects"}
    if set(query) - known:
        raise ValueError(f"unknown natnet:// option(s) {sorted(set(query) - known)}")
    try:
        port = parts.port or DEFAULT_COMMAND_PORT
        data_port = int(query.get("data_port", DEFAULT_DATA_PORT))
    except ValueError as exc:
        raise ValueError(f"bad port in {url!r}: {exc}") from None
    multicast = query.get("multicast", "0").lower() in ("1", "true", "yes", "on")
    subjects = query.get("subjects", "0").lower() in ("1", "true", "yes", "on")
    sets = tuple(query["sets"].split(",")) if query.get("sets") else None
    return NatNetOptions(
        parts.hostname,
        port,
        data_port,
        multicast,
        query.get("group", DEFAULT_MULTICAST_GROUP),
        query.get("local", "0.0.0.0"),
        normalize_up_axis(query.get("up", "+Y")),
        sets,
        subjects,
    )


class NatNetInput:
    """A Motive marker input: any NatNet datagram in, frames into a stream.

    Live: built on a :class:`NatNetClient`; replay: on ``None`` (a socket-free
    session, fed the recorded datagrams in order).

    Args:
        client: the client, or None for replay.
        up_axis: Motive's streaming "Up Axis" (``"+Y"`` by default; the stream does
            not announce it).
        restart_gap_ns: see :class:`~retargetd.protocols.marker_input.FrameSequencer`.
        sets / subjects / out: for the replay session (the client has its own).

    Attributes:
        stream: the :class:`MarkerStream` (``stream.current.frame`` is the last
            accepted frame; counters by reason).
        session: the client's session (or the replay one).
    """

    def __init__(
        self,
        client: NatNetClient | None,
        up_axis: str = "+Y",
        restart_gap_ns: int | None = None,
        *,
        sets: Sequence[str] | None = None,
        subjects: bool = False,
        out: Callable[[str], None] | None = None,
    ) -> None:
        from retargetd.protocols.marker_input import RESTART_GAP_NS, MarkerStream

        self.client = client
        self.session = (
            client.session
            if client is not None
            else NatNetSession(sets, out=out, where="recording", subjects=subjects)
        )
        self.stream = MarkerStream(
            None,
            up_axis,
            "m",
            RESTART_GAP_NS if restart_gap_ns is None else restart_gap_ns,
        )
        self._last_models_request = -math.inf

    def feed(self, packet: Buffer, t_ns: int) -> int:
        """Handle one datagram.

        Returns:
            For a frame, the ``MarkerStream.feed`` reason index (``ACCEPTED`` /
            ``RESTART`` = use ``stream.current``); -1 for a control message.
        """
        if not (len(packet) >= 2 and packet[0] == NAT_FRAMEOFDATA and packet[1] == 0):
            msg_id = self.session.handle(packet)
            if msg_id == NAT_SERVERINFO and self.client is not None:
                self.client.request_models()
            return -1
        decoder = self.session.decoder
        stream = self.stream
        if decoder is None:
            return stream.feed(_no_labels, packet, t_ns=t_ns)  # unknown_label_set
        if decoder.label_set is not stream.label_set:
            stream.set_labels(decoder.label_set)
        code = stream.feed(decoder.decode_natnet_frame, packet, t_ns=t_ns)
        asked = decoder.models_changed or code == COUNT_MISMATCH
        now = time.monotonic()
        if (
            asked
            and self.client is not None
            and now - self._last_models_request >= COMMAND_RETRY_S
        ):
            self._last_models_request = now
            self.client.request_models()
        return code


def _no_labels(buf: Buffer, out: MarkerPacket) -> MarkerPacket:
    raise DecodeError("unknown_label_set", "no model definitions yet")
