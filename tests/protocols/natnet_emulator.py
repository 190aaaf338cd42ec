"""A NatNet server (Motive stand-in) on 127.0.0.1 that serves a real take.

Written from NaturalPoint's published description of the bitstream: the NatNet SDK
4.x samples ``PacketClient.cpp`` / ``NatNetClient.py`` (SDK 4.1-4.3; NatNet 3.0-4.1
layouts), independently of ``retargetd.protocols.natnet`` (the encoders below pack
field by field with ``struct``; the decoder under test slices by offset with NumPy).

- Command port (UDP): ``NAT_CONNECT`` -> ``NAT_SERVERINFO`` (``sSender_Server``:
  name[256], app version[4], NatNet version[4], uint64 clock, uint16 data port,
  uint8 multicast, uint8[4] group); ``NAT_REQUEST_MODELDEF`` -> ``NAT_MODELDEF`` (one
  marker set named after the skeleton, one skeleton description with its id);
  ``NAT_KEEPALIVE`` ignored; anything else -> ``NAT_UNRECOGNIZED_REQUEST``.
- Data: ``NAT_FRAMEOFDATA`` at the take's rate, unicast to the address that connected.
  Positions in metres, Y up (Motive's default), marker-set markers in model order;
  an occluded marker is sent at (0, 0, 0) in the marker set with the labelled marker's
  occluded flag (0x01) set, as Motive does for a skeleton marker it cannot see.

Faults (``Scenario``): a duplicate and a swapped pair of frames, a truncated and a
garbled datagram, a label change (a marker renamed, the "tracked models changed"
suffix flag set until the client asks for the model definitions again), a restart
(1.2 s of silence, then frame numbers from the start), and ``vanish`` / ``flood``.
"""

from __future__ import annotations

import socket
import struct
import threading
import time
from dataclasses import dataclass, field

import numpy as np

NAT_CONNECT = 0
NAT_SERVERINFO = 1
NAT_REQUEST_MODELDEF = 4
NAT_MODELDEF = 5
NAT_FRAMEOFDATA = 7
NAT_KEEPALIVE = 10
NAT_UNRECOGNIZED_REQUEST = 100

SKELETON_NAME = "Performer"
SKELETON_ID = 1

# world (+Z up) -> Motive (+Y up): the inverse of conventions' +Y matrix.
MOTIVE_FROM_WORLD = np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], dtype=np.float64)


def packet(msg_id: int, payload: bytes) -> bytes:
    """uint16 message id, uint16 payload size, payload."""
    return struct.pack("<HH", msg_id, len(payload)) + payload


def cstr(text: str) -> bytes:
    return text.encode() + b"\0"


def server_info(version: tuple[int, int], data_port: int) -> bytes:
    """``NAT_SERVERINFO`` for Motive 3.1.0.0 streaming NatNet ``version``."""
    name = b"Motive".ljust(256, b"\0")
    payload = name + bytes([3, 1, 0, 0]) + bytes([version[0], version[1], 0, 0])
    payload += struct.pack("<QHB4s", 1_000_000_000, data_port, 0, bytes(4))
    return packet(NAT_SERVERINFO, payload)


def rigid_body_description(version: tuple[int, int], name: str, rb_id: int) -> bytes:
    """A rigid body with two markers: name, id, parent -1, offset, (4.2 on: a
    quaternion), marker count, offsets, active labels, (4.0 on: marker names)."""
    out = cstr(name) + struct.pack("<ii3f", rb_id, -1, 0.0, 0.0, 0.0)
    if version >= (4, 2):
        out += struct.pack("<4f", 0.0, 0.0, 0.0, 1.0)
    out += struct.pack("<i", 2) + struct.pack("<6f", 0.0, 0.0, 0.1, 0.0, 0.1, 0.0)
    out += struct.pack("<ii", 0, 0)
    if version >= (4, 0):
        out += cstr(f"{name}_1") + cstr(f"{name}_2")
    return out


def model_defs(
    version: tuple[int, int], labels: list[str], *, rigid_body: bool = False
) -> bytes:
    """``NAT_MODELDEF``: a marker set and a skeleton (no bones), sized from 4.1;
    ``rigid_body`` puts a rigid-body description (id 7) between them."""
    sized = version >= (4, 1)
    marker_set = cstr(SKELETON_NAME) + struct.pack("<i", len(labels))
    marker_set += b"".join(cstr(f"{SKELETON_NAME}_{name}") for name in labels)
    skeleton = cstr(SKELETON_NAME) + struct.pack("<ii", SKELETON_ID, 0)
    items = [(0, marker_set), (2, skeleton)]
    if rigid_body:
        items.insert(1, (1, rigid_body_description(version, "Wand", 7)))
    out = struct.pack("<i", len(items))
    for kind, body in items:
        out += struct.pack("<i", kind)
        if sized:
            out += struct.pack("<i", len(body))
        out += body
    return packet(NAT_MODELDEF, out)


def _list(count: int, items: bytes, sized: bool) -> bytes:
    head = struct.pack("<i", count)
    if sized:
        head += struct.pack("<i", len(items))
    return head + items


def frame_of_data(
    version: tuple[int, int],
    frame: int,
    positions_motive_m: np.ndarray,
    timestamp_s: float,
    *,
    timecode: int = 0,
    models_changed: bool = False,
    residual_m: float = 2.0**-10,
) -> bytes:
    """``NAT_FRAMEOFDATA`` with one marker set, one rigid body and the labelled
    markers; NaN rows of ``positions_motive_m`` (n, 3) are sent occluded."""
    sized = version >= (4, 1)
    n = positions_motive_m.shape[0]
    seen = ~np.isnan(positions_motive_m).any(axis=1)
    pos = np.where(seen[:, None], positions_motive_m, 0.0)
    out = struct.pack("<i", frame)
    ms = cstr(SKELETON_NAME) + struct.pack("<i", n)
    ms += b"".join(struct.pack("<fff", *p) for p in pos)
    out += _list(1, ms, sized)
    out += _list(0, b"", sized)  # legacy other markers
    rb = struct.pack("<i3f4ffh", 7, 0.5, 1.0, 0.25, 0.0, 0.0, 0.0, 1.0, 0.125, 1)
    out += _list(1, rb, sized)  # one rigid body, to be skipped
    out += _list(0, b"", sized)  # skeletons
    if sized:
        out += _list(0, b"", sized)  # assets
    lm = b""
    for k in range(n):
        marker_id = (SKELETON_ID << 16) | (k + 1)
        params = 0x04 if seen[k] else 0x01  # model solved / occluded
        lm += struct.pack("<i3ffhf", marker_id, *pos[k], 2.0**-6, params, residual_m)
    out += _list(n, lm, sized)
    out += _list(0, b"", sized)  # force plates
    out += _list(0, b"", sized)  # devices
    stamp = int(timestamp_s * 1e9)
    out += struct.pack("<IId", timecode, 0, timestamp_s)
    out += struct.pack("<QQQ", stamp, stamp + 1000, stamp + 2000)
    if sized:
        out += struct.pack("<II", int(timestamp_s), 0)  # precision timestamp
    out += struct.pack("<h", 0x02 if models_changed else 0)
    return packet(NAT_FRAMEOFDATA, out)


def timecode_of(frame_index: int, rate_hz: float) -> int:
    """SMPTE timecode packed as the SDK decodes it (hh, mm, ss, ff in the bytes
    from high to low)."""
    fps = max(1, round(rate_hz))
    total_s, ff = divmod(frame_index, fps)
    hh, rem = divmod(total_s, 3600)
    mm, ss = divmod(rem, 60)
    return (hh << 24) | (mm << 16) | (ss << 8) | (ff % 256)


@dataclass
class Scenario:
    """What the server does while it plays the take once.

    Attributes:
        faults: insert the duplicate, swapped, truncated and garbled datagrams.
        label_change_at: frame index at which a marker is renamed (-1: never).
        restart_at: frame index after which it pauses 1.2 s and starts over from
            frame 0 (-1: never).
        vanish_at: frame index at which it stops answering anything (-1: never).
        flood: send every frame at once, unpaced.
        version: the NatNet version it streams.
    """

    faults: bool = True
    label_change_at: int = -1
    restart_at: int = -1
    vanish_at: int = -1
    flood: bool = False
    version: tuple[int, int] = (4, 1)
    sent: dict[str, int] = field(default_factory=dict)


class NatNetEmulator:
    """The server: ``start()``, then ``command_port``; ``close()`` when done.

    Args:
        positions_world_m: (T, M, 3) float64, the take (metres, world, NaN occluded).
        labels: the take's marker names.
        rate_hz: the take's rate.
        first_frame: the take's first frame number.
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
        self.positions = positions_world_m @ MOTIVE_FROM_WORLD.T
        self.labels = list(labels)
        self.rate_hz = rate_hz
        self.first_frame = first_frame
        self.sc = scenario
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.01)
        self.command_port = self.sock.getsockname()[1]
        self.client: tuple[str, int] | None = None
        self.modeldef_requests = 0
        self._models_changed = False
        self._stop = threading.Event()
        self.done = threading.Event()
        self.vanished = False
        self._thread = threading.Thread(target=self._run, daemon=True)
        self.sent: dict[str, int] = scenario.sent
        for key in ("frames", "duplicate", "swapped", "truncated", "garbled"):
            self.sent.setdefault(key, 0)

    def start(self) -> None:
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        self.sock.close()

    def _serve_commands(self) -> None:
        while True:
            try:
                data, addr = self.sock.recvfrom(65536)
            except (TimeoutError, BlockingIOError):
                return
            if self.vanished or len(data) < 4:
                continue
            msg_id = struct.unpack_from("<H", data)[0]
            if msg_id == NAT_CONNECT:
                self.client = addr
                reply = server_info(self.sc.version, self.command_port)
            elif msg_id == NAT_REQUEST_MODELDEF:
                self.modeldef_requests += 1
                self._models_changed = False
                reply = model_defs(self.sc.version, self.labels)
            elif msg_id == NAT_KEEPALIVE:
                continue
            else:
                reply = packet(NAT_UNRECOGNIZED_REQUEST, b"")
            self.sock.sendto(reply, addr)

    def _send(self, data: bytes) -> None:
        if self.client is not None and not self.vanished:
            self.sock.sendto(data, self.client)

    def _frame(self, i: int) -> bytes:
        return frame_of_data(
            self.sc.version,
            self.first_frame + i,
            self.positions[i],
            i / self.rate_hz,
            timecode=timecode_of(i, self.rate_hz),
            models_changed=self._models_changed,
        )

    def _run(self) -> None:
        period = 1.0 / self.rate_hz
        # Wait for a client and its model-definition request.
        while not self._stop.is_set() and self.modeldef_requests == 0:
            self._serve_commands()
        order = list(range(self.positions.shape[0]))
        if self.sc.flood:  # no 10 ms wait for commands between frames
            self.sock.settimeout(0.0)
        if self.sc.faults and len(order) > 40:
            order[20], order[21] = order[21], order[20]  # swapped pair
        start = time.monotonic()
        k = 0
        restarted = False
        while k < len(order) and not self._stop.is_set():
            i = order[k]
            self._serve_commands()
            if i == self.sc.vanish_at:
                self.vanished = True
            if i == self.sc.label_change_at and self.labels[0] != "renamed":
                self.labels[0] = "renamed"
                self._models_changed = True
            data = self._frame(i)
            self._send(data)
            self.sent["frames"] += 1
            if self.sc.faults and k == 10:
                self._send(data)  # duplicate
                self.sent["duplicate"] += 1
            if self.sc.faults and k == 30:
                self._send(data[: len(data) // 2])  # truncated
                self.sent["truncated"] += 1
            if self.sc.faults and k == 31:
                garbled = bytearray(np.random.default_rng(k).bytes(len(data)))
                garbled[0:4] = data[0:4]  # a frame header, garbage after it
                self._send(bytes(garbled))
                self.sent["garbled"] += 1
            if self.sc.faults and order[20] != 20 and k in (20, 21):
                self.sent["swapped"] += 1
            k += 1
            if i == self.sc.restart_at and not restarted:
                restarted = True
                time.sleep(1.2)
                k = 0
                order = list(range(self.positions.shape[0]))
                self.sc.faults = False
                start = time.monotonic()
            if not self.sc.flood:
                delay = start + k * period - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
        # Keep answering commands until closed.
        self.sock.settimeout(0.01)
        self.done.set()
        while not self._stop.is_set():
            self._serve_commands()
