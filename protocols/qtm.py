"""Qualisys QTM as a marker source, through the vendor's SDK ``qtm-rt``.

The SDK is asyncio; the live loop is a ``zmq.Poller`` loop that must never block. So
:class:`QtmSource` runs the ``qtm-rt`` client on a thread of its own (connect, read the
3D labels from QTM's parameters, stream 3D frames with residuals, follow events,
reconnect with backoff) and hands every packet it gets to the loop *as QTM sent it*
(the RT packet: 8-byte header and body) through one end of a Unix datagram
socketpair. The loop polls the other end (:meth:`QtmSource.fileno`), reads packets
with :meth:`QtmSource.read`, and decodes them on its own thread:
:func:`decode_qtm_3d` for data packets, :func:`parse_qtm_parameters` for the
parameters XML. The thread never touches a :class:`MarkerPacket`.

Layout source: Qualisys "QTM Real-time Server Protocol Documentation", protocol
version 1.25 (the version ``qtm-rt`` 3.x asks for), little-endian (port 22223):

- packet header: int32 size (header included), int32 type (0 error, 1 command,
  2 XML, 3 data, 4 no more data, 6 event);
- data packet body: int64 timestamp (microseconds), int32 frame number, int32
  component count, then per component an int32 size (its 8-byte header included),
  int32 type and the data;
- 3D component (type 1; type 9 with residuals): uint32 marker count, uint16 2D drop
  rate, uint16 out-of-sync rate, then per marker float32 x, y, z in millimetres (type
  9: and a float32 residual); markers in the order of the parameters' labels; a marker
  not seen in a frame has NaN coordinates;
- parameters: ``getparameters general 3d`` answers with XML whose ``The_3D`` element
  holds ``AxisUpwards`` (``+Z`` by default) and one ``Label/Name`` per marker.

Units and axes: QTM streams millimetres in its own lab frame, whose up axis the
parameters report; :func:`parse_qtm_parameters` returns it and the stream is built for
it, so positions are converted once, at the input.

Loop integration (the loop thread never waits for the client thread)::

    host, port = parse_qtm_url("qtm://HOST[:PORT]")
    source = QtmSource(host, port, out=out); source.start()   # returns at once
    inp = QtmInput(source, out)
    poller.register(source.fileno(), zmq.POLLIN)
    # when readable: while (pkt := source.read()) is not None:
    #     record pkt (form qtm, kind from packet_info(pkt)); code = inp.feed(pkt, t)
    #     code ACCEPTED / RESTART -> inp.stream.current.frame (inp.stream may be
    #     replaced when QTM's up axis changes); -1 -> parameters / event / reply
    # close: source.close()   (bounded join)

Replay: ``QtmInput(None).feed(pkt, t_ns)`` for every recorded packet.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import socket
import struct
import threading
import xml.etree.ElementTree as ET
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from retargetd.protocols.errors import DecodeError
from retargetd.protocols.frames import F64Array
from retargetd.protocols.marker_input import LabelSet, MarkerPacket

logger = logging.getLogger(__name__)

DEFAULT_PORT = 22223  # QTM's little-endian RT port
PROTOCOL_VERSION = "1.25"

PACKET_ERROR = 0
PACKET_COMMAND = 1
PACKET_XML = 2
PACKET_DATA = 3
PACKET_NO_MORE_DATA = 4
PACKET_EVENT = 6

COMPONENT_3D = 1
COMPONENT_3D_RES = 9

_HEADER = struct.Struct("<ii")
_DATA = struct.Struct("<qii")  # timestamp us, frame number, component count
_COMPONENT = struct.Struct("<ii")
_3D = struct.Struct("<IHH")
_LE_F32 = np.dtype("<f4")
_DATA_OFFSET = _HEADER.size + _DATA.size  # 24: first component

#: Largest datagram handed over the socketpair; a QTM data packet with 3D and
#: residuals is 16 bytes a marker, so this holds 4000 markers.
MAX_PACKET = 65536

Buffer = bytes | bytearray | memoryview


@dataclass(frozen=True, slots=True)
class QtmParameters:
    """What the parameters XML tells us.

    Attributes:
        labels: the 3D labels, in frame order.
        up_axis: QTM's up axis (``"+Z"`` ...), from ``The_3D/AxisUpwards``.
        frequency_hz: the capture rate (``General/Frequency``; NaN when absent).
    """

    labels: tuple[str, ...]
    up_axis: str
    frequency_hz: float


def parse_qtm_parameters(xml: str | bytes) -> QtmParameters:
    """Parse QTM's parameters XML (not hot).

    Raises:
        DecodeError: ``bad_string`` (not XML) or ``no_3d`` (no ``The_3D`` element).
    """
    try:
        root = ET.fromstring(xml.rstrip(b"\0") if isinstance(xml, bytes) else xml)
    except ET.ParseError as exc:
        raise DecodeError("bad_string", f"parameters are not XML: {exc}") from exc
    the_3d = root.find("The_3D")
    if the_3d is None:
        raise DecodeError("no_3d", "parameters hold no The_3D element")
    labels = tuple(
        (label.findtext("Name") or "").strip() for label in the_3d.findall("Label")
    )
    up = (the_3d.findtext("AxisUpwards") or "+Z").strip()
    freq_text = root.findtext("General/Frequency")
    try:
        freq = float(freq_text) if freq_text else math.nan
    except ValueError:
        freq = math.nan
    return QtmParameters(labels, up, freq)


class Qtm3dDecoder:
    """Decodes QTM data packets; keeps the residuals of the last one.

    Args:
        n_markers: the label-set size (for the residual buffer).

    Attributes:
        residuals_mm: (n,) float64, millimetres, QTM's residual per marker in the last
            decoded frame (NaN when the packet carries plain 3D or the marker was not
            seen).
        drop_rate / out_of_sync_rate: QTM's 2D drop and out-of-sync rates of that
            frame (per mille of cameras, as sent).
    """

    def __init__(self, n_markers: int) -> None:
        self.residuals_mm: F64Array = np.full(n_markers, np.nan)
        self.drop_rate = 0
        self.out_of_sync_rate = 0

    def __call__(self, buf: Buffer, out: MarkerPacket) -> MarkerPacket:
        return self.decode_qtm_3d(buf, out)

    def decode_qtm_3d(self, buf: Buffer, out: MarkerPacket) -> MarkerPacket:
        """Decode one QTM RT data packet (header included) into ``out``.

        Args:
            buf: the RT packet as QTM sent it (from :meth:`QtmSource.read`).
            out: packet allocated for the parameters' labels, with QTM's up axis and
                millimetres.

        Returns:
            ``out``: ``frame.frame_id`` (QTM's frame number), ``frame.source_time_s``
            (QTM's timestamp), ``frame.markers_world`` (n, 3) float64 metres world,
            NaN rows = not seen, ``frame.valid``.

        Raises:
            DecodeError: ``bad_length``, ``bad_address`` (not a data packet),
                ``bad_count``, ``no_3d`` (no 3D component: QTM streams no 3D),
                ``count_mismatch`` (another marker count than the labels: parameters
                changed), ``bad_frame_number`` or ``non_finite``.
        """
        size = len(buf)
        if size < _DATA_OFFSET:
            raise DecodeError("bad_length", f"{size} bytes < {_DATA_OFFSET}")
        packet_size, packet_type = _HEADER.unpack_from(buf, 0)
        if packet_type != PACKET_DATA:
            raise DecodeError("bad_address", f"packet type {packet_type}, not data")
        if packet_size != size:
            raise DecodeError("bad_length", f"header says {packet_size}, got {size}")
        timestamp_us, frame_id, n_components = _DATA.unpack_from(buf, _HEADER.size)
        if not 0 <= n_components <= 32:  # the RT protocol defines < 32 kinds
            raise DecodeError("bad_count", f"{n_components} components")
        off = _DATA_OFFSET
        for _ in range(n_components):
            if off + 8 > size:
                raise DecodeError("bad_length", "component header cut short")
            c_size, c_type = _COMPONENT.unpack_from(buf, off)
            if c_size < 8 or off + c_size > size:
                raise DecodeError("bad_length", f"component of {c_size} bytes")
            if c_type in (COMPONENT_3D, COMPONENT_3D_RES):
                return self._store(
                    buf, off, c_size, c_type, frame_id, timestamp_us, out
                )
            off += c_size
        raise DecodeError("no_3d", "data packet without a 3D component")

    def _store(
        self,
        buf: Buffer,
        off: int,
        c_size: int,
        c_type: int,
        frame_id: int,
        timestamp_us: int,
        out: MarkerPacket,
    ) -> MarkerPacket:
        if c_size < 16:
            raise DecodeError("bad_length", "3D component header cut short")
        count, drop, sync = _3D.unpack_from(buf, off + 8)
        stride = 4 if c_type == COMPONENT_3D_RES else 3
        if c_size != 16 + 4 * stride * count:
            raise DecodeError("bad_length", f"3D component of {c_size} for {count}")
        n = len(out.label_set.labels)
        if count != n:
            raise DecodeError("count_mismatch", f"{count} markers for {n} labels")
        if frame_id < 0:
            raise DecodeError("bad_frame_number", f"frame number {frame_id}")
        values = np.frombuffer(buf, _LE_F32, stride * count, off + 16).reshape(
            count, stride
        )
        out.store(values[:, :3])  # raises non_finite before writing anything
        residuals = self.residuals_mm
        if stride == 4 and residuals.shape[0] == count:
            np.copyto(residuals, values[:, 3])
            np.copyto(residuals, np.nan, where=out._occluded)  # store()'s mask
        else:
            residuals.fill(np.nan)
        frame = out.frame
        frame.frame_id = frame_id
        frame.source_time_s = timestamp_us * 1e-6
        out.label_set_id = out.label_set.id
        out.unknown_labels = 0
        self.drop_rate = drop
        self.out_of_sync_rate = sync
        return out


def decode_qtm_3d(buf: Buffer, out: MarkerPacket) -> MarkerPacket:
    """Decode one QTM RT data packet into ``out`` (residuals not kept; see
    :class:`Qtm3dDecoder`, whose method this is)."""
    return _PLAIN.decode_qtm_3d(buf, out)


_PLAIN = Qtm3dDecoder(0)


def packet_type(buf: Buffer) -> int:
    """The RT packet type of a packet from :meth:`QtmSource.read` (-1 if too short)."""
    if len(buf) < _HEADER.size:
        return -1
    return int(_HEADER.unpack_from(buf, 0)[1])


def packet_info(buf: Buffer) -> tuple[int, int, float]:
    """(kind, frame number, source time s) of an RT packet, for the recording
    envelope: kind 1 data (QTM's frame number and timestamp), 2 parameters XML,
    0 anything else (-1, NaN)."""
    kind = packet_type(buf)
    if kind == PACKET_DATA and len(buf) >= _DATA_OFFSET:
        timestamp_us, frame_id, _ = _DATA.unpack_from(buf, _HEADER.size)
        return 1, int(frame_id), timestamp_us * 1e-6
    if kind == PACKET_XML:
        return 2, -1, math.nan
    return 0, -1, math.nan


def parse_qtm_url(url: str) -> tuple[str, int]:
    """``qtm://HOST[:PORT]`` -> (host, port); the port defaults to 22223.

    Raises:
        ValueError: naming the URL when it is not of that form.
    """
    from urllib.parse import urlsplit

    parts = urlsplit(url)
    try:
        port = parts.port or DEFAULT_PORT
    except ValueError as exc:
        raise ValueError(f"bad port in {url!r}: {exc}") from None
    if parts.scheme != "qtm" or not parts.hostname or parts.path or parts.query:
        raise ValueError(f"expected qtm://HOST[:PORT]; got {url!r}")
    return parts.hostname, port


def encode_packet(packet_type: int, body: bytes) -> bytes:
    """An RT packet: header + body (used to hand packets to the loop unchanged)."""
    return _HEADER.pack(_HEADER.size + len(body), packet_type) + body


#: Reconnect backoff: first retry after 0.5 s, doubling to 5 s. QTM restarts in
#: seconds; 5 s caps how long a returned QTM waits for us.
BACKOFF_FIRST_S = 0.5
BACKOFF_MAX_S = 5.0
#: qtm-rt's command timeout (its own default is 5 s).
COMMAND_TIMEOUT_S = 3.0

# QTM events (RT protocol "Event packet"), by number as qtm-rt's QRTEvent.
_EV_CONNECTED = 1
_EV_CONNECTION_CLOSED = 2
_EV_CAPTURE_STARTED = 3
_EV_CAPTURE_STOPPED = 4
_EV_RT_FROM_FILE_STARTED = 8
_EV_RT_FROM_FILE_STOPPED = 9
_EV_CAMERA_SETTINGS_CHANGED = 11
_EV_SHUTTING_DOWN = 12
#: Events after which QTM's parameters (labels) may differ: re-read, re-stream.
_RESTREAM = {
    _EV_CONNECTED,
    _EV_CAPTURE_STARTED,
    _EV_RT_FROM_FILE_STARTED,
    _EV_CAMERA_SETTINGS_CHANGED,
}
_IDLE = {_EV_CONNECTION_CLOSED, _EV_RT_FROM_FILE_STOPPED, _EV_SHUTTING_DOWN}


class QtmSource:
    """The ``qtm-rt`` client on its own thread, packets handed over a socketpair.

    Args:
        host: QTM's address.
        port: QTM's little-endian RT port (22223).
        components: what to stream: ``"3dres"`` (3D with residuals) or ``"3d"``.
        out: where status lines go (thread-safe: called from the client thread).

    Attributes:
        counts: ``connects``, ``disconnects``, ``connect_failures``, ``param_reads``,
            ``events``, ``handover_drops`` (loop too slow: socketpair full),
            ``oversize`` (packets larger than :data:`MAX_PACKET`), ``no_measurement``,
            ``bad_version`` (QTM refused the RT protocol version).
        state: ``"connecting"``, ``"streaming"``, ``"idle"`` (connected, no
            measurement) or ``"stopped"``.
    """

    def __init__(
        self,
        host: str,
        port: int = DEFAULT_PORT,
        *,
        components: str = "3dres",
        out: Callable[[str], None] | None = None,
    ) -> None:
        self.host, self.port = host, port
        self.components = components
        self._say = out or logger.info
        self._rsock, self._wsock = socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM)
        self._wsock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 1 << 20)
        self._rsock.setblocking(False)
        self._wsock.setblocking(False)
        self._buf = bytearray(MAX_PACKET)
        self._view = memoryview(self._buf)
        self.counts: dict[str, int] = dict.fromkeys(
            (
                "connects",
                "disconnects",
                "connect_failures",
                "param_reads",
                "events",
                "handover_drops",
                "oversize",
                "no_measurement",
                "bad_version",
            ),
            0,
        )
        self.state = "stopped"
        self._thread: threading.Thread | None = None
        self._aloop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._wake: asyncio.Event | None = None
        self._stopping = threading.Event()  # close() before the asyncio loop runs

    # ---- loop side ---------------------------------------------------------------

    def fileno(self) -> int:
        """The fd the loop polls (``zmq.POLLIN``)."""
        return self._rsock.fileno()

    def read(self) -> memoryview | None:
        """One RT packet as QTM sent it (a view the next call reuses), or None when
        nothing is waiting. Never blocks."""
        try:
            n = self._rsock.recv_into(self._buf)
        except (BlockingIOError, InterruptedError):
            return None
        return self._view[:n]

    # ---- lifecycle ---------------------------------------------------------------

    def start(self) -> None:
        """Start the client thread (returns at once)."""
        if self._thread is not None:
            return
        self.state = "connecting"
        self._thread = threading.Thread(target=self._run, name="qtm-rt", daemon=True)
        self._thread.start()

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop the thread (bounded wait) and close the socketpair (idempotent)."""
        self._stopping.set()
        aloop, stop = self._aloop, self._stop
        if aloop is not None and stop is not None:
            with contextlib.suppress(RuntimeError):
                aloop.call_soon_threadsafe(stop.set)
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None
        for sock in (self._rsock, self._wsock):
            sock.close()
        self.state = "stopped"

    # ---- client thread -----------------------------------------------------------

    def _forward(self, packet: bytes) -> None:
        if len(packet) > MAX_PACKET:
            self.counts["oversize"] += 1
            return
        try:
            self._wsock.send(packet)
        except (BlockingIOError, InterruptedError):
            self.counts["handover_drops"] += 1  # the loop is behind: newest lost
        except OSError:
            pass  # closed during shutdown

    def _run(self) -> None:
        asyncio.run(self._main())

    async def _main(self) -> None:
        self._aloop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        self._wake = asyncio.Event()
        if self._stopping.is_set():
            self._stop.set()
        backoff = BACKOFF_FIRST_S
        while not self._stop.is_set():
            streamed = await self._session()
            if self._stop.is_set():
                break
            if streamed:
                backoff = BACKOFF_FIRST_S
            self.state = "connecting"
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(self._stop.wait(), backoff)
            backoff = min(backoff * 2, BACKOFF_MAX_S)
        self.state = "stopped"

    def _on_event(self, event: Any) -> None:
        self.counts["events"] += 1
        self._last_event = int(event.value)
        assert self._wake is not None
        self._wake.set()

    def _on_disconnect(self, exc: Exception | None) -> None:
        self._connected = False
        assert self._wake is not None
        self._wake.set()

    def _on_packet(self, packet: Any) -> None:
        self._forward(encode_packet(PACKET_DATA, bytes(packet.data)))

    async def _session(self) -> bool:
        """One connection: returns True when it streamed frames."""
        import qtm_rt
        from qtm_rt.protocol import QRTCommandException

        assert self._stop is not None and self._wake is not None
        streamed = False
        conn = await self._connect(qtm_rt, QRTCommandException)
        if conn is None:
            return False
        self._connected = True
        self.counts["connects"] += 1
        self._say(f"qtm: connected to {self.host}:{self.port} (RT {PROTOCOL_VERSION})")
        try:
            while self._connected and not self._stop.is_set():
                self._wake.clear()
                self._last_event = 0
                xml = await conn.get_parameters(["general", "3d"])
                self.counts["param_reads"] += 1
                self._forward(encode_packet(PACKET_XML, bytes(xml) + b"\0"))
                try:
                    params = parse_qtm_parameters(bytes(xml))
                except DecodeError:
                    params = None
                if params is None or not params.labels:
                    self._say(
                        "qtm: QTM streams no 3D labels: switch on 3D tracking and "
                        "label the markers (AIM) in the measurement"
                    )
                try:
                    await conn.stream_frames(
                        components=[self.components], on_packet=self._on_packet
                    )
                    self.state = "streaming"
                    streamed = True
                    self._say(
                        f"qtm: streaming {len(params.labels) if params else 0} "
                        f"labelled markers"
                        + (
                            f" at {params.frequency_hz:g} Hz, up {params.up_axis}"
                            if params
                            else ""
                        )
                    )
                except (TimeoutError, QRTCommandException) as exc:
                    self._idle(f"({exc})")
                # Wait for an event that may change the parameters, a disconnect or
                # the stop request.
                while self._connected and not self._stop.is_set():
                    wake = asyncio.ensure_future(self._wake.wait())
                    stop = asyncio.ensure_future(self._stop.wait())
                    await asyncio.wait(
                        {wake, stop}, return_when=asyncio.FIRST_COMPLETED
                    )
                    for fut in (wake, stop):
                        fut.cancel()
                    self._wake.clear()
                    ev = self._last_event
                    if ev in _IDLE:
                        self._idle("")
                        with contextlib.suppress(Exception):
                            await conn.stream_frames_stop()
                    if ev in _RESTREAM:
                        with contextlib.suppress(Exception):
                            await conn.stream_frames_stop()
                        break
        except (TimeoutError, QRTCommandException, OSError) as exc:
            self._say(f"qtm: {self.host}:{self.port}: {exc}; reconnecting")
        finally:
            if conn.has_transport():
                conn.disconnect()
            self.counts["disconnects"] += 1
            if not self._stop.is_set():
                self._say(f"qtm: disconnected from {self.host}:{self.port}")
        return streamed

    async def _connect(self, qtm_rt: Any, command_error: type[Exception]) -> Any:
        """``qtm_rt.connect`` spelled out with the SDK's own classes, so that a
        refused protocol version is told apart from an unreachable QTM."""
        from qtm_rt.protocol import QTMProtocol

        loop = asyncio.get_running_loop()
        where = f"{self.host}:{self.port}"
        self.counts["connect_failures"] += 1  # until it succeeds
        first = self.counts["connect_failures"] == 1
        try:
            _, protocol = await asyncio.wait_for(
                loop.create_connection(
                    lambda: QTMProtocol(
                        loop=loop,
                        on_event=self._on_event,
                        on_disconnect=self._on_disconnect,
                    ),
                    self.host,
                    self.port,
                ),
                COMMAND_TIMEOUT_S,
            )
        except (OSError, TimeoutError) as exc:
            if first or self.state != "connecting":
                self._say(f"qtm: cannot connect to {where} ({exc}); retrying")
            return None
        try:
            await asyncio.wait_for(
                protocol.set_version(PROTOCOL_VERSION), COMMAND_TIMEOUT_S
            )
        except (command_error, TimeoutError) as exc:
            self.counts["bad_version"] += 1
            if self.counts["bad_version"] == 1:
                self._say(
                    f"qtm: {where} refused RT protocol version {PROTOCOL_VERSION} "
                    f"({exc}); QTM 2.x or later speaks it; retrying"
                )
            if protocol.transport is not None:
                protocol.transport.close()
            return None
        self.counts["connect_failures"] -= 1
        return qtm_rt.QRTConnection(protocol, timeout=COMMAND_TIMEOUT_S)

    def _idle(self, detail: str) -> None:
        self.state = "idle"
        self.counts["no_measurement"] += 1
        self._say(
            "qtm: QTM runs no measurement: start one (or RT from file); "
            "holding the last pose" + (f" {detail}" if detail else "")
        )


class QtmInput:
    """A QTM marker input for the live loop: the source's packets into a stream.

    Runs on the loop thread (live), or alone on recorded packets (replay: no
    source). Data packets are decoded with :class:`Qtm3dDecoder`;
    the parameters XML sets the labels (a new label-set id whenever they change) and
    QTM's up axis (a changed up axis rebuilds :attr:`stream`; the loop re-reads it);
    other packets (events, command replies) are counted.

    Args:
        source: the started :class:`QtmSource` (None when replaying a recording).
        out: where status lines go.

    Attributes:
        stream: the :class:`MarkerStream` (None until the first parameters arrive).
        params: the last parameters read.
        decoder: the data-packet decoder (residuals of the last frame).
        other_packets: packets that were neither data nor parameters.
    """

    def __init__(
        self, source: QtmSource | None, out: Callable[[str], None] | None = None
    ) -> None:
        from retargetd.protocols.marker_input import MarkerStream

        self.source = source
        self._say = out or logger.info
        self.stream: Any = None
        self._stream_cls = MarkerStream
        self.params: QtmParameters | None = None
        self.decoder = Qtm3dDecoder(0)
        self.other_packets = 0
        self._next_id = 1
        self._early = 0  # data packets before any parameters

    def feed(self, packet: Buffer, t_ns: int) -> int:
        """Handle one packet from :meth:`QtmSource.read`.

        Returns:
            The ``MarkerStream.feed`` reason index for a data packet (``ACCEPTED`` /
            ``RESTART`` = use ``stream.current``), -1 for any other packet.
        """
        kind = packet_type(packet)
        if kind == PACKET_DATA:
            if self.stream is None:
                self._early += 1
                return -1
            return int(self.stream.feed(self.decoder.decode_qtm_3d, packet, t_ns=t_ns))
        if kind == PACKET_XML:
            try:
                params = parse_qtm_parameters(bytes(packet[_HEADER.size :]))
            except DecodeError as exc:
                if self.stream is not None:
                    self.stream.counters.add_reason(exc.reason)
                self._say(f"qtm: unreadable parameters: {exc}")
                return -1
            self._adopt(params)
            return -1
        self.other_packets += 1
        return -1

    def _adopt(self, params: QtmParameters) -> None:
        old = self.params
        self.params = params
        try:
            labels = LabelSet(self._next_id, params.labels)
        except DecodeError as exc:
            self._say(f"qtm: labels refused: {exc}")
            return
        if self.stream is None or old is None or old.up_axis != params.up_axis:
            self.stream = self._stream_cls(None, params.up_axis, "mm")
        if self.stream.label_set is not None and (
            self.stream.label_set.labels == params.labels
        ):
            return
        self._next_id += 1
        self.stream.set_labels(labels)
        self.decoder = Qtm3dDecoder(len(labels.labels))
        if old is not None and old.labels != params.labels:
            self._say(f"qtm: labels changed: {len(params.labels)} markers")
