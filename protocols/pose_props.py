"""The pose stream's prop message (topic ``RTDR``): one rigid prop's pose per frame.

One part, little-endian, sent on the pose stream's PUB beside the performers' data
messages (PROTOCOLS.md section 6, "Prop message"); a client subscribed to ``b"RTD"``
receives it, one subscribed to ``b"RTDR"`` only these.

| offset | size | type | field |
|---|---|---|---|
| 0 | 4 | bytes | magic ``RTDR`` |
| 4 | 2 | uint16 | version = 1 |
| 6 | 1 | uint8 | prop id: its index among the daemon's ``[[prop]]`` tables |
| 7 | 1 | uint8 | kind: 0 rigid, 1 camera |
| 8 | 8 | int64 | frame number (the source's) |
| 16 | 8 | float64 | source timestamp, seconds (NaN = unknown) |
| 24 | 8 | int64 | received_ns (``time.monotonic_ns()`` at the frame's arrival) |
| 32 | 8 | int64 | sent_ns (just before the send) |
| 40 | 4 | uint32 | flags: bit 0 held, 1 partial, 2 swap, 3 never |
| 44 | 1 | uint8 | markers used by the fit |
| 45 | 1 | uint8 | markers of the prop seen |
| 46 | 1 | uint8 | N, the name's length in bytes |
| 47 | 1 | uint8 | reserved, 0 |
| 48 | 16 | float32 x 4 | world_from_prop, w x y z, internal world (+Z up) |
| 64 | 12 | float32 x 3 | the prop's origin, metres, internal world |
| 76 | 4 | float32 | field of view, degrees (vertical; 0 for a rigid prop) |
| 80 | 4 | float32 | residual RMS of the used markers, metres (NaN when held) |
| 84 | N, NUL-padded to a multiple of 4 | UTF-8 | the prop's name |
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

import numpy as np

from retargetd.protocols.errors import DecodeError
from retargetd.protocols.frames import F64Array

PROP_MAGIC = b"RTDR"
PROP_VERSION = 1
PROP_HEADER = struct.Struct("<4sHBBqdqqIBBBB4f3fff")
KIND_RIGID = 0
KIND_CAMERA = 1
PROP_HELD = 1 << 0
PROP_PARTIAL = 1 << 1
PROP_SWAP = 1 << 2
PROP_NEVER = 1 << 3
#: Flag name -> bit (the kernel's ``daemon/props/kernel.FLAG_*``).
PROP_FLAG_BITS = {"held": 0, "partial": 1, "swap": 2, "never": 3}
_SENT_OFFSET = 32
_MAX_NAME = 64


def prop_size(name: bytes) -> int:
    """Bytes in a prop message for a name of this many UTF-8 bytes."""
    return PROP_HEADER.size + ((len(name) + 3) & ~3)


class PropEncoder:
    """One prop's messages, written into one reused buffer.

    Args:
        prop_id: its index among the ``[[prop]]`` tables (0-255).
        name: its name (at most 64 UTF-8 bytes).
        kind: KIND_RIGID or KIND_CAMERA.
    """

    def __init__(self, prop_id: int, name: str, kind: int) -> None:
        raw = name.encode()
        if not (0 <= prop_id <= 255 and 0 < len(raw) <= _MAX_NAME):
            raise ValueError(f"prop id 0-255 and a name of 1-64 bytes; got {prop_id}")
        self.prop_id, self.kind, self._name = prop_id, kind, raw
        self._buf = bytearray(prop_size(raw))
        self._buf[PROP_HEADER.size : PROP_HEADER.size + len(raw)] = raw
        self.part = memoryview(self._buf)

    def encode(
        self, frame_id: int, source_time_s: float, received_ns: int, flags: int,
        used: int, seen: int, quat_wxyz: F64Array, pos_world: F64Array,
        fov_deg: float, rms_m: float,
    ) -> memoryview:  # fmt: skip
        """Write one frame's message (sent_ns 0: :func:`stamp_sent` before sending)."""
        PROP_HEADER.pack_into(
            self._buf, 0, PROP_MAGIC, PROP_VERSION, self.prop_id, self.kind,
            frame_id, source_time_s, received_ns, 0, flags, used, seen,
            len(self._name), 0, quat_wxyz[0], quat_wxyz[1], quat_wxyz[2],
            quat_wxyz[3], pos_world[0], pos_world[1], pos_world[2], fov_deg, rms_m,
        )  # fmt: skip
        return self.part


def stamp_sent(part: memoryview | bytearray, sent_ns: int) -> None:
    """Write sent_ns into an encoded message, just before the send."""
    struct.pack_into("<q", part, _SENT_OFFSET, sent_ns)


@dataclass(slots=True, eq=False)
class PropMessage:
    """A decoded prop message (fields as in the module docstring)."""

    prop_id: int
    kind: int
    name: str
    frame_id: int
    source_time_s: float
    received_ns: int
    sent_ns: int
    flags: int
    used: int
    seen: int
    world_from_prop_quat: F64Array
    pos_world: F64Array
    fov_deg: float
    rms_m: float


def decode_prop(part: bytes | bytearray | memoryview) -> PropMessage:
    """Decode a prop message.

    Raises:
        DecodeError: ``bad_length``, ``bad_magic``, ``bad_version``, ``bad_name``,
            ``non_finite`` (a pose that is not finite), ``bad_quaternion``.
    """
    if len(part) < PROP_HEADER.size:
        raise DecodeError("bad_length", f"prop message of {len(part)} bytes, < 84")
    f = PROP_HEADER.unpack_from(part)
    if f[0] != PROP_MAGIC:
        raise DecodeError("bad_magic", f"expected {PROP_MAGIC!r}; got {f[0]!r}")
    if f[1] != PROP_VERSION:
        raise DecodeError("bad_version", f"version {f[1]}, expected {PROP_VERSION}")
    n = f[11]
    if len(part) != PROP_HEADER.size + ((n + 3) & ~3):
        raise DecodeError("bad_length", f"prop message of {len(part)} bytes for {n}")
    raw = bytes(part[PROP_HEADER.size : PROP_HEADER.size + n])
    try:
        name = raw.decode()
    except UnicodeDecodeError:
        raise DecodeError("bad_name", "prop name is not UTF-8") from None
    quat = np.array(f[13:17], dtype=np.float64)
    pos = np.array(f[17:20], dtype=np.float64)
    if not (np.all(np.isfinite(quat)) and np.all(np.isfinite(pos))):
        raise DecodeError("non_finite", "prop pose is not finite")
    if abs(math.sqrt(float(quat @ quat)) - 1.0) > 1e-3:
        raise DecodeError("bad_quaternion", "prop rotation is not a unit quaternion")
    return PropMessage(
        prop_id=f[2], kind=f[3], name=name, frame_id=f[4], source_time_s=f[5],
        received_ns=f[6], sent_ns=f[7], flags=f[8], used=f[9], seen=f[10],
        world_from_prop_quat=quat, pos_world=pos, fov_deg=f[20], rms_m=f[21],
    )  # fmt: skip
