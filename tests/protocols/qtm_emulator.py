"""A QTM real-time server (TCP, 127.0.0.1) that serves a real take to ``qtm-rt``.

Written from Qualisys' "QTM Real-time Server Protocol Documentation", protocol
version 1.25 (little-endian port), independently of ``retargetd.protocols.qtm``:

- every packet: int32 size (header included), int32 type (0 error, 1 command, 2 XML,
  3 data, 6 event); strings are NUL-terminated;
- on accept the server sends the command string ``QTM RT Interface connected``;
- ``version 1.25`` -> ``Version set to 1.25``; ``qtmversion`` -> a version string;
  ``getparameters general 3d`` -> the parameters XML (``QTM_Parameters_Ver_1.25``,
  ``General/Frequency``, ``The_3D/AxisUpwards``, ``The_3D/Label/Name``);
  ``getstate`` -> an event packet with the current state;
  ``streamframes allframes 3dres`` -> data packets at the take's rate;
  ``streamframes stop`` -> no reply; anything else -> an error packet;
- data packet: int64 timestamp (microseconds), int32 frame number, int32 component
  count; 3D-with-residuals component: int32 size, int32 type 9, uint32 marker count,
  uint16 2D drop rate, uint16 out-of-sync rate, then x, y, z, residual float32 per
  marker (millimetres); a marker not seen is NaN with residual -1.

Faults (``Scenario``): a truncated and a garbled data packet (valid framing, bad
content), a label change (marker 0 renamed, then event 11 "camera settings changed";
the client re-reads the parameters), a restart (connection and listening socket
closed for ``restart_pause_s``, then frame numbers from the start), no measurement
(``getstate`` answers "connection closed", ``streamframes`` an error) and an abrupt
vanish.
"""

from __future__ import annotations

import contextlib
import socket
import struct
import threading
import time
from dataclasses import dataclass, field

import numpy as np

PACKET_ERROR = 0
PACKET_COMMAND = 1
PACKET_XML = 2
PACKET_DATA = 3
PACKET_EVENT = 6
EVENT_CONNECTED = 1
EVENT_CONNECTION_CLOSED = 2
EVENT_CAMERA_SETTINGS_CHANGED = 11
COMPONENT_3D_RES = 9


def rt_packet(kind: int, body: bytes) -> bytes:
    return struct.pack("<ii", 8 + len(body), kind) + body


def rt_string(kind: int, text: str) -> bytes:
    return rt_packet(kind, text.encode() + b"\0")


def parameters_xml(labels: list[str], rate_hz: float, up: str = "+Z") -> str:
    names = "".join(
        f"<Label><Name>{name}</Name><RGBColor>16711680</RGBColor></Label>"
        for name in labels
    )
    return (
        "<QTM_Parameters_Ver_1.25><General>"
        f"<Frequency>{rate_hz:g}</Frequency><Capture_Time>10</Capture_Time>"
        "</General><The_3D>"
        f"<AxisUpwards>{up}</AxisUpwards>"
        "<CalibrationTime>2026-01-01 00:00:00</CalibrationTime>"
        f"<Labels>{len(labels)}</Labels>{names}"
        "</The_3D></QTM_Parameters_Ver_1.25>"
    )


def data_packet(frame: int, timestamp_us: int, markers_mm: np.ndarray) -> bytes:
    """A data packet with one 3D-with-residuals component; NaN rows not seen."""
    n = markers_mm.shape[0]
    body = b""
    for xyz in markers_mm:
        residual = -1.0 if np.isnan(xyz).any() else 0.8
        x, y, z = (float(v) for v in xyz)
        body += struct.pack("<4f", x, y, z, residual)
    component = struct.pack("<iiIHH", 16 + len(body), COMPONENT_3D_RES, n, 0, 0)
    head = struct.pack("<qii", timestamp_us, frame, 1)
    return rt_packet(PACKET_DATA, head + component + body)


@dataclass
class Scenario:
    """What the server plays (frame indices into the take; -1 = never).

    Attributes:
        faults: send a truncated and a garbled packet (after frames 30 and 31).
        label_change_at: rename marker 0 and send event 11 before this frame.
        restart_at: after this frame, close everything for ``restart_pause_s``, then
            serve the take from its start again.
        vanish_at: after this frame, close everything for good.
        no_measurement: QTM has no measurement open.
        refuse_version: answer ``version`` with an error (a QTM too old for 1.25).
        measurement_after_s: with ``no_measurement``, open one this long after the
            client connected (event 1, "connected": a new measurement).
        reload_at: before this frame the measurement is closed (event 2) and, 0.3 s
            later, opened again (event 1), as when QTM reloads a measurement.
        bad_component_at: after this frame, a data packet whose one component has
            type 99 (none in the protocol): ``qtm-rt``'s own parser raises on it.
    """

    faults: bool = True
    label_change_at: int = -1
    restart_at: int = -1
    restart_pause_s: float = 1.2
    vanish_at: int = -1
    no_measurement: bool = False
    refuse_version: bool = False
    measurement_after_s: float = -1.0
    reload_at: int = -1
    bad_component_at: int = -1
    sent: dict[str, int] = field(default_factory=dict)


class QtmEmulator:
    """The server: ``start()``, ``port``, ``close()``.

    Args:
        positions_world_m: (T, M, 3) float64 take positions (metres, world +Z up).
        labels: marker names.
        rate_hz: take rate.
        first_frame: frame number of row 0.
        scenario: faults to play.
    """

    def __init__(
        self,
        positions_world_m: np.ndarray,
        labels: list[str],
        rate_hz: float,
        first_frame: int,
        scenario: Scenario,
    ) -> None:
        self.markers_mm = positions_world_m * 1000.0  # QTM: mm, +Z up = world
        self.labels = list(labels)
        self.rate_hz = rate_hz
        self.first_frame = first_frame
        self.sc = scenario
        self.sent = scenario.sent
        for key in ("frames", "truncated", "garbled", "connections", "label_change"):
            self.sent.setdefault(key, 0)
        self.listener = self._listen(0)
        self.port = self.listener.getsockname()[1]
        self._stop = threading.Event()
        self.done = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._next = 0  # next frame index to serve
        self._restarted = False
        self.commands: list[str] = []

    @staticmethod
    def _listen(port: int) -> socket.socket:
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(("127.0.0.1", port))
        sock.listen(1)
        sock.settimeout(0.05)
        return sock

    def start(self) -> None:
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        with contextlib.suppress(OSError):
            self.listener.close()

    # ---- serving -------------------------------------------------------------------

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self.listener.accept()
            except (TimeoutError, OSError):
                continue
            self.sent["connections"] += 1
            outcome = self._serve(conn)
            with contextlib.suppress(OSError):
                conn.close()
            if outcome in ("restart", "vanish"):
                self.listener.close()
                if outcome == "vanish":
                    self.done.set()
                    return
                time.sleep(self.sc.restart_pause_s)
                self.listener = self._listen(self.port)
            if outcome == "done":
                self.done.set()

    def _read_command(self, conn: socket.socket, buf: bytearray) -> str | None:
        """One client command if a whole packet is buffered (non-blocking read)."""
        try:
            chunk = conn.recv(65536)
            if not chunk:
                raise ConnectionError("client closed")
            buf += chunk
        except (BlockingIOError, TimeoutError):
            pass
        if len(buf) < 8:
            return None
        size, _kind = struct.unpack_from("<ii", buf)
        if len(buf) < size:
            return None
        text = bytes(buf[8:size]).rstrip(b"\0").decode()
        del buf[:size]
        return text

    def _answer(self, conn: socket.socket, cmd: str) -> str:
        """Reply to ``cmd``; returns "stream", "stop" or ""."""
        self.commands.append(cmd)
        word = cmd.split(" ", 1)[0].lower()
        if word == "version" and self.sc.refuse_version:
            conn.sendall(rt_string(PACKET_ERROR, "Version NOT supported"))
        elif word == "version":
            conn.sendall(rt_string(PACKET_COMMAND, f"Version set to {cmd.split()[1]}"))
        elif word == "qtmversion":
            conn.sendall(rt_string(PACKET_COMMAND, "QTM Version is 2024.1 (emulated)"))
        elif word == "getparameters":
            xml = parameters_xml(self.labels, self.rate_hz)
            conn.sendall(rt_string(PACKET_XML, xml))
        elif word == "getstate":
            state = (
                EVENT_CONNECTION_CLOSED if self.sc.no_measurement else EVENT_CONNECTED
            )
            conn.sendall(rt_packet(PACKET_EVENT, bytes([state])))
        elif cmd.lower() == "streamframes stop":
            return "stop"
        elif word == "streamframes":
            if self.sc.no_measurement:
                conn.sendall(rt_string(PACKET_ERROR, "No measurement"))
                return ""
            return "stream"
        else:
            conn.sendall(rt_string(PACKET_ERROR, "Parse error"))
        return ""

    def _serve(self, conn: socket.socket) -> str:
        conn.setblocking(False)
        conn.sendall(rt_string(PACKET_COMMAND, "QTM RT Interface connected"))
        buf = bytearray()
        streaming = False
        period = 1.0 / self.rate_hz
        t_next = time.monotonic()
        t_connect = t_next
        n = self.markers_mm.shape[0]
        try:
            while not self._stop.is_set():
                if (
                    self.sc.no_measurement
                    and self.sc.measurement_after_s >= 0
                    and time.monotonic() - t_connect >= self.sc.measurement_after_s
                ):
                    self.sc.no_measurement = False
                    conn.sendall(rt_packet(PACKET_EVENT, bytes([EVENT_CONNECTED])))
                cmd = self._read_command(conn, buf)
                while cmd is not None:
                    what = self._answer(conn, cmd)
                    if what == "stream":
                        streaming, t_next = True, time.monotonic()
                    elif what == "stop":
                        streaming = False
                    cmd = self._read_command(conn, buf)
                if not streaming or self._next >= n:
                    if self._next >= n:
                        return "done"
                    time.sleep(0.002)
                    continue
                now = time.monotonic()
                if now < t_next:
                    time.sleep(min(t_next - now, 0.002))
                    continue
                t_next += period
                i = self._next
                if i == self.sc.reload_at:
                    self.sc.reload_at = -1
                    streaming = False
                    conn.sendall(
                        rt_packet(PACKET_EVENT, bytes([EVENT_CONNECTION_CLOSED]))
                    )
                    time.sleep(0.3)
                    conn.sendall(rt_packet(PACKET_EVENT, bytes([EVENT_CONNECTED])))
                    self.sent["reloads"] = self.sent.get("reloads", 0) + 1
                    continue
                if i == self.sc.label_change_at and self.labels[0] != "renamed":
                    self.labels[0] = "renamed"
                    self.sent["label_change"] += 1
                    streaming = False  # QTM pauses; the client re-reads parameters
                    conn.sendall(
                        rt_packet(PACKET_EVENT, bytes([EVENT_CAMERA_SETTINGS_CHANGED]))
                    )
                    continue
                data = data_packet(
                    self.first_frame + i,
                    round(i * 1e6 / self.rate_hz),
                    self.markers_mm[i],
                )
                conn.sendall(data)
                self.sent["frames"] += 1
                self._next += 1
                if self.sc.faults and i == 30:
                    self._send_truncated(conn, data)
                if self.sc.faults and i == 31:
                    self._send_garbled(conn, data)
                if i == self.sc.bad_component_at:
                    body = struct.pack("<qii", 0, 0, 1) + struct.pack("<ii", 8, 99)
                    conn.sendall(rt_packet(PACKET_DATA, body))
                    self.sent["bad_component"] = 1
                if i == self.sc.vanish_at:
                    return "vanish"
                if i == self.sc.restart_at and not self._restarted:
                    self._restarted = True
                    self._next = 0
                    self.sc.faults = False
                    return "restart"
        except (ConnectionError, OSError):
            return "lost"
        return "stopped"

    def _send_truncated(self, conn: socket.socket, data: bytes) -> None:
        """Marker bytes cut off; the framing (packet size) still matches."""
        cut = data[: len(data) // 2]
        conn.sendall(struct.pack("<ii", len(cut), PACKET_DATA) + cut[8:])
        self.sent["truncated"] += 1

    def _send_garbled(self, conn: socket.socket, data: bytes) -> None:
        """Component headers kept, the marker count and marker bytes garbage."""
        garbled = bytearray(data)
        rng = np.random.default_rng(31)
        garbled[32:36] = struct.pack("<I", 0x7FFF0000 + int(rng.integers(1000)))
        garbled[40:] = rng.bytes(len(garbled) - 40)
        conn.sendall(bytes(garbled))
        self.sent["garbled"] += 1
