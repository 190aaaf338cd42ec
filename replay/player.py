"""The replay player: sends a take or a recording over OSC or ZeroMQ, paced.

Two sources:

- :class:`TakeSource` (C3D, TRC, or a recording decoded to a take): one frame per
  row, in world metres (units ``m``, up ``+Z``: the daemon input's default config),
  frame number = take row (+ one window length per loop pass, so numbers keep
  increasing), source timestamp = frame number / rate. Compact OSC and ZeroMQ
  announce labels (set id 1) before the first frame and then every second.
- :class:`RecordingSource` (MCAP): the recorded packets of one input, bytes
  unchanged, at their recorded receive times. On loop passes after the first, the
  frame number inside each frame is moved on by the window's length (the only
  change made to the bytes).

Pacing (:func:`play`) keeps an absolute schedule: packet k is due at
``start + t_k / speed`` (``t_k`` the take time of the packet), so errors never
accumulate. ``time.sleep`` covers all but the last ``SPIN_S`` (200 us), then a
spin on ``perf_counter`` hits the mark. ``speed = 0`` sends unpaced. Lateness
(send time - due time) of every frame is kept, and the report gives its median,
p99 and max.
"""

from __future__ import annotations

import math
import socket
import struct
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from retargetd.protocols import osc_in, zmq_wire
from retargetd.protocols.marker_input import LabelSet
from retargetd.replay import recording as rf
from retargetd.replay.take import Take

#: The last stretch before a due time is spun, not slept (sleep overshoots ~50-100 us).
SPIN_S = 200e-6
#: Longest single sleep, so a stop request is seen promptly.
MAX_SLEEP_S = 0.05
#: Label announcements at least this often (wall clock).
LABELS_EVERY_S = 1.0
LABEL_SET_ID = 1


@dataclass(frozen=True, slots=True)
class Endpoint:
    """A parsed ``osc://HOST:PORT``, ``zmq://HOST:PORT`` or ``zmq+sub://HOST:PORT``."""

    scheme: str
    host: str
    port: int

    @property
    def tcp(self) -> str:
        """The ZeroMQ address, ``tcp://HOST:PORT``."""
        return f"tcp://{self.host}:{self.port}"

    def __str__(self) -> str:
        return f"{self.scheme}://{self.host}:{self.port}"


def parse_endpoint(
    url: str, schemes: tuple[str, ...] = ("osc", "zmq"), *, allow_port_0: bool = False
) -> Endpoint:
    """Parse ``SCHEME://HOST:PORT``.

    Raises:
        ValueError: one line naming what is wrong and what is expected.
    """
    expected = " or ".join(f"{s}://HOST:PORT" for s in schemes)
    scheme, sep, rest = url.partition("://")
    host, colon, port_text = rest.rpartition(":")
    if not sep or scheme not in schemes or not colon or not host:
        raise ValueError(f"expected {expected}; got {url!r}")
    try:
        port = int(port_text)
    except ValueError:
        raise ValueError(
            f"port must be an integer; got {port_text!r} in {url!r}"
        ) from None
    low = 0 if allow_port_0 else 1
    if not low <= port <= 65535:
        raise ValueError(f"port must be in {low}..65535; got {port} in {url!r}")
    return Endpoint(scheme, host.strip("[]"), port)


class Sender:
    """Sends packets to an endpoint: UDP datagrams (``osc``) or a ZeroMQ PUSH that
    connects to the daemon's bound PULL (``zmq``). Never blocks on ZeroMQ: a full
    queue drops the message and counts it.

    Args:
        endpoint: where to send.
        linger_ms: how long closing waits for queued ZeroMQ messages (a player
            finishing a take wants its tail delivered; bounded).
        sign: OSC only: called on each datagram, returns the bytes to send
            (``osc_auth.DatagramSigner.sign``: signed datagrams, PROTOCOLS.md 13).
    """

    def __init__(
        self,
        endpoint: Endpoint,
        linger_ms: int = 2000,
        sign: Callable[[Any], bytes] | None = None,
    ) -> None:
        if sign is not None and endpoint.scheme != "osc":
            raise ValueError("only OSC datagrams are signed (ZeroMQ has CURVE)")
        self.endpoint = endpoint
        self._sign = sign
        self.dropped = 0
        self._udp: socket.socket | None = None
        self._push: Any = None
        self._ctx: Any = None
        if endpoint.scheme == "osc":
            self._udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self._addr = (endpoint.host, endpoint.port)
        else:
            import zmq

            self._ctx = zmq.Context()
            self._push = self._ctx.socket(zmq.PUSH)
            self._push.setsockopt(zmq.LINGER, linger_ms)
            self._push.setsockopt(zmq.SNDHWM, 100_000)
            self._push.connect(endpoint.tcp)
            self._again = zmq.Again
            self._noblock = zmq.NOBLOCK

    @property
    def transport(self) -> str:
        """``"osc"`` or ``"zmq"``."""
        return self.endpoint.scheme

    def send(self, parts: tuple[bytes, ...] | list[bytes]) -> None:
        """Send one packet (one datagram, or the parts of one ZeroMQ message)."""
        if self._udp is not None:
            data = parts[0] if self._sign is None else self._sign(parts[0])
            try:
                self._udp.sendto(data, self._addr)
            except OSError:  # e.g. ECONNREFUSED from an earlier ICMP: count, go on
                self.dropped += 1
            return
        try:
            self._push.send_multipart(parts, self._noblock)
        except self._again:
            self.dropped += 1

    def close(self) -> None:
        """Close the socket (ZeroMQ waits at most ``linger_ms`` for queued messages)."""
        if self._udp is not None:
            self._udp.close()
        if self._push is not None:
            self._push.close()
            self._ctx.term()


@dataclass(slots=True)
class PlayReport:
    """What :func:`play` did. Lateness in seconds (send time - due time)."""

    frames: int = 0
    label_packets: int = 0
    other_packets: int = 0
    passes: int = 0
    wall_s: float = 0.0
    speed: float = 1.0
    dropped: int = 0
    lateness_s: list[float] = field(default_factory=list)

    def jitter_us(self) -> dict[str, float]:
        """Median, p99 and max lateness of the frames, microseconds (paced only)."""
        if not self.lateness_s:
            return {"median": math.nan, "p99": math.nan, "max": math.nan}
        arr = np.asarray(self.lateness_s) * 1e6
        return {
            "median": float(np.median(arr)),
            "p99": float(np.percentile(arr, 99)),
            "max": float(arr.max()),
        }


# A source yields, per pass, (take time s from the window start, parts, kind).
_Item = tuple[float, tuple[bytes, ...], int]


class TakeSource:
    """Rows of a :class:`Take` encoded for a transport and form.

    Args:
        take: the take (world metres).
        transport: ``"osc"`` or ``"zmq"``.
        form: ``"compact"`` or ``"simple"`` (OSC only; ZeroMQ has one form).
        rows: the window of rows to send (0-based, half-open).
        pass_motion: ``(mat (3, 3), pos (3,))``, a rigid motion ``A(x) = mat x +
            pos`` (metres, world): pass ``k`` is sent moved by ``A^{-k}`` (a looped
            take that walks on, ``replay --loop --blend-frames``); None = every pass
            as recorded.
    """

    def __init__(
        self,
        take: Take,
        transport: str,
        form: str,
        rows: slice,
        pass_motion: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> None:
        if form not in ("compact", "simple"):
            raise ValueError(f"form must be compact or simple; got {form!r}")
        self.take = take
        self.transport = transport
        self.form = form
        self.rows = range(*rows.indices(take.n_frames))
        self.period_s = 1.0 / take.rate_hz
        self.duration_s = len(self.rows) * self.period_s
        self._positions = np.asarray(take.positions, dtype=np.float32)
        self._motion = pass_motion
        labels = LabelSet(LABEL_SET_ID, tuple(take.labels))
        self.labels: tuple[bytes, ...] | None = None
        if transport == "zmq":
            self.labels = tuple(zmq_wire.encode_zmq_labels(labels))
        elif form == "compact":
            self.labels = (osc_in.encode_labels(labels),)

    def iter_pass(self, k: int) -> Iterator[_Item]:
        """Pass ``k`` (0-based) of the window: frames due at ``i / rate``."""
        offset = k * len(self.rows)
        rate = self.take.rate_hz
        labels = self.take.labels
        positions = self._positions
        if self._motion is not None and k:
            mat, shift = _inverse_power(*self._motion, k)
            window = np.asarray(positions[self.rows.start : self.rows.stop], np.float64)
            moved = np.empty_like(positions)
            moved[self.rows.start : self.rows.stop] = window @ mat.T + shift
            positions = moved
        for i, row in enumerate(self.rows):
            frame = row + offset
            pos = positions[row]
            if self.transport == "zmq":
                parts = tuple(zmq_wire.encode_zmq_frame(frame, frame / rate, 1, pos))
            elif self.form == "compact":
                parts = (osc_in.encode_compact_frame(frame, frame / rate, 1, pos),)
            else:
                parts = (osc_in.encode_simple_bundle(labels, pos, frame),)
            yield i * self.period_s, parts, rf.KIND_FRAME


def _inverse_power(
    mat: np.ndarray, pos: np.ndarray, k: int
) -> tuple[np.ndarray, np.ndarray]:
    """``A^{-k}`` of ``A(x) = mat x + pos`` as ``(mat', pos')``."""
    inv_mat = np.asarray(mat, np.float64).T
    inv_pos = -inv_mat @ np.asarray(pos, np.float64)
    out_mat, out_pos = np.eye(3), np.zeros(3)
    for _ in range(k):  # x -> A^{-1}(A^{-(j)} x)
        out_mat, out_pos = inv_mat @ out_mat, inv_mat @ out_pos + inv_pos
    return out_mat, out_pos


class RecordingSource:
    """The recorded packets of one input of an MCAP recording, bytes unchanged.

    Args:
        packets: the input's packets in recorded order (``Recording.packets()``).
        rows: window of *frame* packets (0-based, half-open); the last label
            announcement before the window is sent first.
    """

    def __init__(self, packets: list[rf.Packet], rows: slice) -> None:
        frame_at = [i for i, p in enumerate(packets) if p.kind == rf.KIND_FRAME]
        window = range(*rows.indices(len(frame_at)))
        if not window:
            raise ValueError("the frame window selects no recorded frames")
        first, last = frame_at[window.start], frame_at[window.stop - 1]
        chosen = packets[first : last + 1]
        before = [p for p in packets[:first] if p.kind == rf.KIND_LABELS]
        t0 = chosen[0].t_ns
        if before:
            chosen.insert(0, rf.Packet(**{**_fields(before[-1]), "t_ns": t0}))
        self.packets = chosen
        self.transport = "zmq" if chosen[-1].form == rf.FORM_ZMQ else "osc"
        self.form = rf.FORM_NAMES[chosen[-1].form]
        self.labels = None  # the recorded announcements are part of the packets
        frames = [p for p in chosen if p.kind == rf.KIND_FRAME]
        steps = np.diff([p.t_ns for p in frames]) * 1e-9
        self.period_s = float(np.median(steps)) if steps.size else 0.0
        self.duration_s = (chosen[-1].t_ns - t0) * 1e-9 + self.period_s
        numbers = [p.source_frame for p in frames if p.source_frame >= 0]
        self.frame_span = (max(numbers) - min(numbers) + 1) if numbers else 0

    def iter_pass(self, k: int) -> Iterator[_Item]:
        """Pass ``k``: the packets at their recorded times (frame numbers moved on by
        ``k`` window lengths after the first pass)."""
        t0 = self.packets[0].t_ns
        shift = k * self.frame_span
        for p in self.packets:
            parts = p.parts
            if shift and p.kind == rf.KIND_FRAME and p.source_frame >= 0:
                parts = shift_frame_number(p, p.source_frame + shift)
            yield (p.t_ns - t0) * 1e-9, parts, p.kind


def _fields(p: rf.Packet) -> dict[str, Any]:
    return {name: getattr(p, name) for name in rf.Packet.__slots__}


def shift_frame_number(packet: rf.Packet, frame: int) -> tuple[bytes, ...]:
    """The packet's parts with its frame number replaced by ``frame``."""
    parts = [bytearray(p) for p in packet.parts]
    if packet.form == rf.FORM_OSC_COMPACT:
        struct.pack_into(">q", parts[0], 20, frame)
    elif packet.form == rf.FORM_ZMQ:
        struct.pack_into("<q", parts[0], 8, frame)
    elif packet.form == rf.FORM_OSC_SIMPLE:
        buf = parts[0]
        at = buf.find(b"/rtd/frame_number\0\0\0")
        if at >= 0 and buf[at + 20 : at + 22] == b",h":
            struct.pack_into(">q", buf, at + 24, frame)
        elif at >= 0 and buf[at + 20 : at + 22] == b",i":
            struct.pack_into(">i", buf, at + 24, frame & 0x7FFFFFFF)
    return tuple(bytes(p) for p in parts)


def _wait_until(due: float, should_stop: Callable[[], bool]) -> None:
    while True:
        left = due - time.perf_counter()
        if left <= SPIN_S or should_stop():
            break
        time.sleep(min(left - SPIN_S, MAX_SLEEP_S))
    while time.perf_counter() < due:
        pass


def play(
    source: TakeSource | RecordingSource,
    sender: Sender,
    *,
    speed: float = 1.0,
    loop: bool = False,
    should_stop: Callable[[], bool] = lambda: False,
    max_seconds: float | None = None,
) -> PlayReport:
    """Send ``source`` through ``sender``, paced by ``speed`` (0 = unpaced).

    Args:
        source: what to send.
        sender: where to send it.
        speed: 1 = recorded speed, 2 = twice as fast, 0 = as fast as possible.
        loop: start over at the end (until ``should_stop`` or ``max_seconds``).
        should_stop: polled between packets (a SIGINT handler's flag).
        max_seconds: stop after this long (wall clock).

    Returns:
        Counts, wall time and the lateness of every paced frame.
    """
    if not (speed >= 0 and math.isfinite(speed)):
        raise ValueError(f"speed must be >= 0; got {speed}")
    report = PlayReport(speed=speed)
    start = time.perf_counter()
    deadline = math.inf if max_seconds is None else start + max_seconds
    last_labels = -math.inf
    k = 0
    stopped = False
    while not stopped:
        base = k * source.duration_s
        for t_s, parts, kind in source.iter_pass(k):
            if should_stop() or time.perf_counter() >= deadline:
                stopped = True
                break
            due = start + (base + t_s) / speed if speed > 0 else 0.0
            if speed > 0:
                _wait_until(due, should_stop)
            now = time.perf_counter()
            if source.labels is not None and now - last_labels >= LABELS_EVERY_S:
                sender.send(source.labels)
                report.label_packets += 1
                last_labels = now
                now = time.perf_counter()
            sender.send(parts)
            if kind == rf.KIND_FRAME:
                report.frames += 1
                if speed > 0:
                    report.lateness_s.append(now - due)
            elif kind == rf.KIND_LABELS:
                report.label_packets += 1
            else:
                report.other_packets += 1
        else:
            report.passes += 1
        k += 1
        if not loop:
            break
    report.wall_s = time.perf_counter() - start
    report.dropped = sender.dropped
    return report
