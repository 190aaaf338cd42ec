"""What the daemon's bound ZeroMQ sockets refuse below the messages: CURVE handshakes
that fail, by reason, and connections that cannot be accepted for lack of file
descriptors, each episode logged once. Read from each socket's monitor (libzmq's
event stream) on the loop thread.

CURVE failures (a socket with ``secret_key``), by libzmq's event:

- ``plain_client``: ``HANDSHAKE_FAILED_PROTOCOL`` with ``ZMTP_MECHANISM_MISMATCH``
  (a peer without CURVE; the greeting names another mechanism);
- ``wrong_server_key``: ``HANDSHAKE_FAILED_PROTOCOL`` with ``ZMTP_CRYPTOGRAPHIC``
  (the client's HELLO does not open with this server's key);
- ``unlisted_key``: ``HANDSHAKE_FAILED_AUTH`` (the ZAP authenticator refused the
  client's key, status 400);
- ``other``: any other handshake failure (a malformed command, a timeout, a peer that
  hung up in the greeting: ``HANDSHAKE_FAILED_NO_DETAIL``, EPIPE ...).

A plain ZeroMQ client is ``plain_client`` only when its mechanism reached the daemon:
each side of a ZMTP greeting checks the other's mechanism, and libzmq sends a client's
version and mechanism only once its socket is writable again, so a client that reads
the daemon's whole greeting first sees the mismatch and hangs up without them: the
daemon read a connection closed in the greeting, ``other``. Which side wins is a race
(measured on loopback with a bare CURVE REP server: 56 of 100 plain REQs connecting
20 at once, 6 of 60 one at a time, were the daemon's ``other``).

libzmq 4.3's monitor names the socket's own endpoint in these events, never the
peer's, so the peer is read from the accepted connection's descriptor
(``getpeername``) when the loop sees the ``ACCEPTED`` event, if it is still open
then: a handshake that fails on loopback can close it first (``peer unknown``).

Descriptor exhaustion: libzmq's listener reports ``ACCEPT_FAILED`` with ``EMFILE`` or
``ENFILE`` and retries at once (a busy loop in its I/O thread, ~180,000 failures a
second measured), so the count of failures says nothing: an episode is counted, its
first failure logs one line, and the first check without a failure ends it with a line
giving its length and the failures seen (the monitor's queue holds ~2,000 events
and drops the rest: a lower bound). During an episode the socket's monitor is taken
off the loop's poller (it would wake the loop without end) and :data:`DRAIN_MAX`
events are read every :data:`EPISODE_CHECK_NS` instead, so the end is seen once the
queue has drained (within a second). UDP inputs cannot meet it: a datagram needs no
descriptor.
"""

from __future__ import annotations

import errno
import os
import socket
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import zmq
from zmq.utils.monitor import parse_monitor_message

from retargetd.daemon.live.ratelog import RateLimitedLog

#: Reasons a CURVE handshake fails (status ``curve_refused``).
CURVE_REASONS = ("plain_client", "unlisted_key", "wrong_server_key", "other")
#: Events a watched socket's monitor delivers (with CURVE: the handshake failures).
_BASE_EVENTS = zmq.EVENT_ACCEPTED | zmq.EVENT_ACCEPT_FAILED | zmq.EVENT_DISCONNECTED
_CURVE_EVENTS = (
    zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL
    | zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL
    | zmq.EVENT_HANDSHAKE_FAILED_AUTH
)
_EXHAUSTED = (errno.EMFILE, errno.ENFILE)
#: During an episode a paused monitor is read this often (0.1 s).
EPISODE_CHECK_NS = 100_000_000
#: Monitor events read per wake-up at most: a burst never holds the loop long (the
#: monitor's queue itself holds about 2,000).
DRAIN_MAX = 256
#: Accepted connections whose peer is remembered (one a handshake failure names).
_PEERS_MAX = 256


def _reason(event: int, value: int) -> str:
    if event == zmq.EVENT_HANDSHAKE_FAILED_AUTH:
        return "unlisted_key"
    if event == zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL:
        if value == zmq.PROTOCOL_ERROR_ZMTP_MECHANISM_MISMATCH:
            return "plain_client"
        if value == zmq.PROTOCOL_ERROR_ZMTP_CRYPTOGRAPHIC:
            return "wrong_server_key"
    return "other"


def _peer_of(fd: int, port: int) -> str | None:
    """``host:port`` of the peer on descriptor ``fd`` (an accepted connection of the
    listener on ``port``), or None when it is closed or is something else now."""
    try:
        dup = os.dup(fd)
    except OSError:
        return None
    try:
        with socket.socket(fileno=dup) as sock:
            if sock.type != socket.SOCK_STREAM or sock.getsockname()[1] != port:
                return None  # the number was reused by another descriptor
            host, peer_port = sock.getpeername()[:2]
            return f"{host}:{peer_port}"
    except OSError:
        return None


@dataclass(slots=True)
class _Watched:
    name: str
    monitor: Any  # the PAIR socket the monitor's events arrive on
    port: int  # the listener's port (tcp), -1 for ipc/inproc
    curve: bool
    refused: dict[str, int] = field(default_factory=dict)
    peers: dict[int, str | None] = field(default_factory=dict)  # fd -> peer
    failed: str = ""  # a handshake failure waiting for its DISCONNECTED (the fd)
    paused: bool = False  # off the poller (an episode)


class SocketWatch:
    """Monitors of the daemon's bound ZeroMQ sockets: CURVE handshake failures counted
    by reason and logged (rate-limited, with the peer), descriptor exhaustion logged
    once per episode.

    Args:
        poller: the loop's poller (monitors are registered on it).
        log: the daemon's rate-limited log (handshake failures).
        out: where episode lines go (the daemon's ``out``).
    """

    def __init__(
        self, poller: zmq.Poller, log: RateLimitedLog, out: Callable[[str], None]
    ) -> None:
        self._poller = poller
        self._log = log
        self._out = out
        self._watched: list[_Watched] = []
        self._by_monitor: dict[Any, _Watched] = {}
        self.fd_episodes = 0  # episodes of descriptor exhaustion begun
        self.fd_accept_failures = 0  # failed accepts seen (libzmq retries at once)
        self._episode_ns = 0  # when the current one began (0: none)
        self._episode_failures = 0
        self._next_check_ns = 0

    def watch(self, name: str, sock: Any, curve: bool) -> Any:
        """Monitor ``sock`` (bound; ``name`` as status and the log call it); returns
        the monitor socket, registered on the poller."""
        events = _BASE_EVENTS | (_CURVE_EVENTS if curve else 0)
        monitor = sock.get_monitor_socket(events)
        monitor.setsockopt(zmq.LINGER, 0)
        endpoint = sock.getsockopt(zmq.LAST_ENDPOINT)
        endpoint = endpoint.decode() if isinstance(endpoint, bytes) else str(endpoint)
        port = -1
        if endpoint.startswith("tcp://"):
            port = int(endpoint.rsplit(":", 1)[1])
        watched = _Watched(name, monitor, port, curve)
        watched.refused = dict.fromkeys(CURVE_REASONS, 0) if curve else {}
        self._watched.append(watched)
        self._by_monitor[monitor] = watched
        self._poller.register(monitor, zmq.POLLIN)
        return monitor

    @property
    def exhausted(self) -> bool:
        """An episode of descriptor exhaustion is going on."""
        return self._episode_ns != 0

    def drain(self, sock: Any, now_ns: int) -> None:
        """Read the events waiting on ``sock`` (from a poll result; nothing unless it
        is one of the monitors), at most :data:`DRAIN_MAX`."""
        w = self._by_monitor.get(sock)
        if w is not None:
            self._drain(w, now_ns, DRAIN_MAX)

    def drain_ready(self, events: list[tuple[Any, int]], now_ns: int) -> None:
        """:meth:`drain` every socket of a poll result (the monitors among them)."""
        for sock, _flags in events:
            w = self._by_monitor.get(sock)
            if w is not None:
                self._drain(w, now_ns, DRAIN_MAX)

    def tick(self, now_ns: int) -> None:
        """During an episode, every :data:`EPISODE_CHECK_NS`: read the paused monitors;
        none failing any more ends the episode (call it every loop pass)."""
        if not self._episode_ns or now_ns < self._next_check_ns:
            return
        self._next_check_ns = now_ns + EPISODE_CHECK_NS
        before = self.fd_accept_failures
        for w in self._watched:
            if w.paused:  # bounded: libzmq refills the queue as fast as it is read
                self._drain(w, now_ns, DRAIN_MAX)
        if self.fd_accept_failures == before:
            seconds = (now_ns - self._episode_ns) * 1e-9
            self._out(
                f"file descriptors available again after {seconds:.1f} s: "
                f"{self._episode_failures} failed accepts seen in the episode"
            )
            self._episode_ns = 0
            for w in self._watched:
                if w.paused:
                    w.paused = False
                    self._poller.register(w.monitor, zmq.POLLIN)

    def _drain(self, w: _Watched, now_ns: int, limit: int) -> None:
        for _ in range(limit):
            try:
                msg = w.monitor.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                return
            event = parse_monitor_message(msg)
            kind, value = int(event["event"]), int(event["value"])
            if kind == zmq.EVENT_ACCEPT_FAILED:
                if value in _EXHAUSTED:
                    self._exhausted(w, value, now_ns)
            elif kind == zmq.EVENT_ACCEPTED:
                if w.curve and w.port >= 0:
                    if len(w.peers) >= _PEERS_MAX:
                        w.peers.pop(next(iter(w.peers)))
                    w.peers[value] = _peer_of(value, w.port)
            elif kind == zmq.EVENT_DISCONNECTED:
                peer = w.peers.pop(value, None)
                if w.failed:
                    self._log_refused(w, w.failed, peer, now_ns)
                    w.failed = ""
            else:  # a handshake failure, counted; its DISCONNECTED (the fd) is next
                if w.failed:  # two failures in a row: the first without its peer
                    self._log_refused(w, w.failed, None, now_ns)
                w.failed = _reason(kind, value)
                w.refused[w.failed] += 1

    def _log_refused(
        self, w: _Watched, reason: str, peer: str | None, now_ns: int
    ) -> None:
        who = peer or "peer unknown"
        self._log.line(
            f"{w.name} curve {reason}",
            f"{w.name}: CURVE handshake refused ({reason}) from {who}",
            now_ns,
        )

    def _exhausted(self, w: _Watched, code: int, now_ns: int) -> None:
        self.fd_accept_failures += 1
        if not self._episode_ns:
            self._episode_ns = now_ns
            self._episode_failures = 0
            self._next_check_ns = now_ns + EPISODE_CHECK_NS
            self.fd_episodes += 1
            self._out(
                f"{w.name}: cannot accept a connection: {os.strerror(code)} "
                f"({errno.errorcode.get(code, code)}); no new connection is taken "
                "until descriptors are freed (one line per episode)"
            )
        self._episode_failures += 1
        if not w.paused:
            w.paused = True
            self._poller.unregister(w.monitor)

    def status(self) -> dict[str, dict[str, int]]:
        """Refused CURVE handshakes by socket name and reason (CURVE sockets)."""
        return {w.name: dict(w.refused) for w in self._watched if w.curve}

    def close(self) -> None:
        """Close the monitor sockets (before their sockets)."""
        for w in self._watched:
            if not w.paused:
                self._poller.unregister(w.monitor)
            w.monitor.close()
        self._watched.clear()
        self._by_monitor.clear()
