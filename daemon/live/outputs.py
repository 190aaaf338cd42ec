"""The outputs of the loop, one part: the ZeroMQ pose stream (a PUB socket, and the
recording's copy of every message) and each performer's VMC destination (a UDP
socket). Every send is non-blocking: a message the socket cannot take now is dropped
and counted (``send_drops``, ``vmc_errors``), never queued.
"""

from __future__ import annotations

import socket
from collections.abc import Callable, Iterable
from typing import Any

import zmq

from retargetd.daemon.live.recording import LiveRecording
from retargetd.daemon.live.stats import LoopStats
from retargetd.daemon.live.surface import endpoint_is_local, who_reaches
from retargetd.protocols.vmc_out import VmcEncoder

_NOBLOCK_MORE = zmq.NOBLOCK | zmq.SNDMORE

#: How often the VMC state is sent while nothing is streamed (0.5 s).
VMC_STATE_INTERVAL_NS = 500_000_000


class VmcOut:
    """One performer's VMC destination: its socket, connected when the route is
    there (a connected UDP socket sends without parsing an address or looking up the
    route per call; a receiver absent on this machine then shows as refused sends,
    counted in ``vmc_errors``).

    Args:
        addr: (host, port) of the receiver.
        max_datagram: the largest datagram sent to it, bytes.
        stats: the loop's counters (``vmc_errors``); None: the datagrams refused
            are not counted (the loop gives its counters before it opens it).
    """

    def __init__(
        self, addr: tuple[str, int], max_datagram: int, stats: LoopStats | None
    ) -> None:
        self.addr = addr
        self.max_datagram = max_datagram
        self.stats = stats
        self.sock: socket.socket | None = None  # None: [output.vmc] off (or closed)
        self.connected = False
        self.next_state_ns = 0  # the next "waiting / calibrating" state datagram
        self.state = VmcEncoder(())  # the state datagram (no bones needed)

    @property
    def on(self) -> bool:
        """Whether its socket is open ([output.vmc] on and not closed)."""
        return self.sock is not None

    def open(self, allow_broadcast: bool, out: Callable[[str], None]) -> None:
        """Open the socket and connect it; without a route to the host yet (a network
        not up) it stays unconnected and sends with ``sendto``, as the route may
        come later."""
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setblocking(False)
        if allow_broadcast:  # without it the kernel refuses broadcast sends
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
        self.sock, self.connected = sock, False
        try:
            sock.connect(self.addr)
        except OSError as exc:
            out(
                f"vmc out: no route to {self.addr[0]} yet ({exc.strerror}): "
                "sending unconnected"
            )
        else:
            self.connected = True

    def send(self, datagrams: Iterable[Any]) -> None:
        """Send datagrams to the receiver, never blocking: a refused one (receiver
        absent, buffer full, no route) is counted."""
        sock, addr = self.sock, self.addr
        if sock is None:
            return
        for dgram in datagrams:
            try:
                if self.connected:
                    sock.send(dgram)
                else:
                    sock.sendto(dgram, addr)
            except OSError:
                if self.stats is not None:
                    self.stats.vmc_errors += 1

    def close(self) -> None:
        """Close the socket (idempotent)."""
        if self.sock is not None:
            self.sock.close()
            self.sock = None


class Outputs:
    """The pose stream and the performers' VMC destinations.

    Args:
        stats: the loop's counters (``send_drops``).
        recording: the live recording: every pose-stream message is also handed to
            it while it records poses.
        vmc: each performer's VMC destination, in performer order.
    """

    def __init__(
        self, stats: LoopStats, recording: LiveRecording, vmc: list[VmcOut]
    ) -> None:
        self.stats = stats
        self.recording = recording
        self.vmc = vmc
        self.vmc_on = False  # [output.vmc] on: every destination has its socket
        self.pub: zmq.Socket[bytes] | None = None

    def open_pub(
        self,
        sock: zmq.Socket[bytes],
        endpoint: str,
        sndhwm: int,
        curve: str,
        announce: Callable[[str, str], None],
    ) -> None:
        """Bind the pose stream's PUB socket (made by the loop: plain or CURVE) and
        say who can reach it."""
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.SNDHWM, sndhwm)
        sock.bind(endpoint)
        self.pub = sock
        value = sock.getsockopt(zmq.LAST_ENDPOINT)
        ep = value.decode() if isinstance(value, bytes) else str(value)
        who = who_reaches(endpoint_is_local(endpoint), ep)
        announce("zmq poses", f"{ep} (pub; poses to {who}{curve})")

    def open_vmc(self, allow_broadcast: bool, out: Callable[[str], None]) -> None:
        """Open every performer's VMC socket."""
        self.vmc_on = True
        for v in self.vmc:
            v.open(allow_broadcast, out)

    @property
    def publishing(self) -> bool:
        """Whether pose-stream messages go anywhere (a subscriber socket or a
        recording of poses)."""
        return self.pub is not None or self.recording.poses is not None

    def send_pub(self, parts: list[Any], t_ns: int) -> None:
        """One pose-stream message (its parts): recorded when poses are, then
        published without blocking (a PUB at its high-water mark drops it whole)."""
        rec = self.recording.poses
        if rec is not None:
            rec.record_pose(t_ns, *parts)
        pub = self.pub
        if pub is None:
            return
        # Part by part, each copied into its message: for parts this small a copy is
        # cheaper than send_multipart's zero-copy Frames (pose send at 240 Hz 45 -> ~20
        # µs median, bench/profile_loop.py). libzmq queues the parts and delivers the
        # message whole; a PUB at its high-water mark drops it whole (Again is
        # raised, if ever, by the first part only, before anything is queued).
        last = len(parts) - 1
        try:
            for i in range(last):
                pub.send(parts[i], _NOBLOCK_MORE)
            pub.send(parts[last], zmq.NOBLOCK)
        except zmq.Again:
            self.stats.send_drops += 1

    def send_unrecorded(self, message: Any) -> None:
        """A one-part message on the pose stream only (the face's per-shape states,
        right after their pose; not recorded)."""
        if self.pub is None:
            return
        try:
            self.pub.send(message, zmq.NOBLOCK)
        except zmq.Again:
            self.stats.send_drops += 1

    def close(self) -> None:
        """Close the VMC sockets (the PUB socket is closed with the loop's)."""
        for v in self.vmc:
            v.close()
        self.vmc_on = False
