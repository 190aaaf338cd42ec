"""ZeroMQ marker input: two-part messages, a frame or a label announcement.

Byte layouts are in ``protocols/PROTOCOLS.md`` (section 4). All little-endian:

- frame: part 1 = 32-byte header ``<4sHHqdII``: magic ``RTDM``, version 1, flags
  (reserved, senders write 0, receivers ignore), frame number int64, source time
  float64 s (NaN = unknown), label-set id uint32, marker count uint32; part 2 =
  count x 3 float32 (x y z, sender's units and axes, NaN = occluded).
- labels: part 1 = 16-byte header ``<4sHHII``: magic ``RTDL``, version 1, reserved,
  label-set id, count; part 2 = the labels in UTF-8 joined by ``\\n``.

The magic doubles as the subscription topic: a SUB socket subscribes to ``b"RTD"``
(both kinds) and dispatches on ``header[:4]``. Same checks and reasons as ``osc_in``;
nothing is written into ``out`` unless the whole message is good.
"""

from __future__ import annotations

import math
import struct

import numpy as np

from retargetd.protocols import kernels
from retargetd.protocols.errors import DecodeError
from retargetd.protocols.marker_input import (
    KERNEL_REASONS,
    MAX_MARKERS,
    LabelSet,
    MarkerPacket,
)

FRAME_MAGIC = b"RTDM"
LABELS_MAGIC = b"RTDL"
VERSION = 1
FRAME_HEADER = struct.Struct("<4sHHqdII")  # 32 bytes
LABELS_HEADER = struct.Struct("<4sHHII")  # 16 bytes
_LE_F32 = np.dtype("<f4")
_TIME_LE = struct.Struct("<d")

Buffer = bytes | bytearray | memoryview


def decode_zmq_frame(
    header: Buffer, payload: Buffer, out: MarkerPacket
) -> MarkerPacket:
    """Decode a ZeroMQ marker frame (header part, payload part) into ``out``.

    Args:
        header: the 32-byte first part.
        payload: the second part, count x 3 little-endian float32.
        out: packet allocated for the current label set.

    Returns:
        ``out``, filled as by ``osc_in.decode_compact_frame``.

    Raises:
        DecodeError: ``bad_length``, ``bad_magic``, ``bad_version``,
            ``unknown_label_set``, ``count_mismatch``, ``bad_frame_number`` or
            ``non_finite``.
    """
    if len(header) != FRAME_HEADER.size:
        raise DecodeError("bad_length", f"header of {len(header)} bytes, expected 32")
    magic, version, _flags, frame_id, time_s, label_set_id, count = (
        FRAME_HEADER.unpack_from(header)
    )
    if magic != FRAME_MAGIC:
        raise DecodeError("bad_magic", f"expected {FRAME_MAGIC!r}; got {magic!r}")
    if version != VERSION:
        raise DecodeError("bad_version", f"version {version}, expected {VERSION}")
    if len(payload) != 12 * count:
        raise DecodeError("bad_length", f"payload {len(payload)} bytes for {count}")
    if label_set_id != out.label_set.id:
        raise DecodeError("unknown_label_set", f"label set {label_set_id}")
    if count != len(out.label_set.labels):
        raise DecodeError(
            "count_mismatch", f"{count} markers for label set {label_set_id}"
        )
    if frame_id < 0:
        raise DecodeError("bad_frame_number", f"frame number {frame_id}")
    raw = np.frombuffer(payload, _LE_F32, 3 * count).reshape(count, 3)
    if math.isinf(time_s):
        raise DecodeError("non_finite", "infinite source time")
    out.store(raw)  # raises non_finite before writing anything
    frame = out.frame
    frame.frame_id = frame_id
    frame.source_time_s = time_s
    out.label_set_id = label_set_id
    out.unknown_labels = 0
    return out


def decode_zmq_into(
    header: np.ndarray, n_header: int, payload: np.ndarray, n_payload: int,
    out: MarkerPacket,
) -> MarkerPacket:  # fmt: skip
    """:func:`decode_zmq_frame` of the parts in ``header[:n_header]`` and
    ``payload[:n_payload]`` (uint8 arrays over the receive buffers), its checks and
    the markers' store in one compiled call (``kernels.decode_frame``).

    Same result, same checks in the same order; a refused message raises the
    :class:`DecodeError` :func:`decode_zmq_frame` raises for it (its checks run
    again, in Python, to say why)."""
    frame_id = out.decode_packed(kernels.FORM_ZMQ, header, n_header, payload, n_payload)
    if frame_id < 0:
        decode_zmq_frame(
            header.data[:n_header], payload.data[:n_payload], out
        )  # raises the reason
        raise DecodeError(KERNEL_REASONS[frame_id], "refused by the compiled checks")
    frame = out.frame
    frame.frame_id = frame_id
    (frame.source_time_s,) = _TIME_LE.unpack_from(header.data, 16)
    out.label_set_id = out.label_set.id
    out.unknown_labels = 0
    return out


def decode_zmq_labels(
    header: Buffer, payload: Buffer, max_markers: int = MAX_MARKERS
) -> LabelSet:
    """Decode a ZeroMQ label announcement (not hot).

    The count in the header is checked against ``max_markers`` before the payload is
    touched, so an oversized announcement costs no decoding.

    Raises:
        DecodeError: ``bad_length``, ``bad_magic``, ``bad_version``,
            ``too_many_markers``, ``bad_string`` (not UTF-8), ``bad_count`` or
            ``bad_label``.
    """
    if len(header) != LABELS_HEADER.size:
        raise DecodeError("bad_length", f"header of {len(header)} bytes, expected 16")
    magic, version, _reserved, label_set_id, count = LABELS_HEADER.unpack_from(header)
    if magic != LABELS_MAGIC:
        raise DecodeError("bad_magic", f"expected {LABELS_MAGIC!r}; got {magic!r}")
    if version != VERSION:
        raise DecodeError("bad_version", f"version {version}, expected {VERSION}")
    if count > max_markers:
        raise DecodeError("too_many_markers", f"{count} labels > {max_markers}")
    try:
        text = bytes(payload).decode()
    except UnicodeDecodeError as exc:
        raise DecodeError("bad_string", "labels are not UTF-8") from exc
    labels = tuple(text.split("\n")) if text else ()
    if len(labels) != count:
        raise DecodeError("bad_count", f"count {count} with {len(labels)} labels")
    return LabelSet(label_set_id, labels)


def encode_zmq_frame(
    frame_id: int, source_time_s: float, label_set_id: int, positions: np.ndarray
) -> list[bytes]:
    """Encode a marker frame as ``[header, payload]`` (senders and tests).

    Args:
        frame_id: frame number, int64 >= 0.
        source_time_s: the sender's timestamp in seconds, NaN when unknown.
        label_set_id: uint32 id of the announced label set.
        positions: (n, 3) float, sender's units and axes; NaN rows = occluded.
    """
    pos = np.asarray(positions, dtype=_LE_F32)
    if pos.ndim != 2 or pos.shape[1] != 3:
        raise ValueError(f"positions must be (n, 3); got shape {pos.shape}")
    header = FRAME_HEADER.pack(
        FRAME_MAGIC, VERSION, 0, frame_id, source_time_s, label_set_id, pos.shape[0]
    )
    return [header, pos.tobytes()]


def encode_zmq_labels(label_set: LabelSet) -> list[bytes]:
    """Encode a label announcement as ``[header, payload]``."""
    header = LABELS_HEADER.pack(
        LABELS_MAGIC, VERSION, 0, label_set.id, len(label_set.labels)
    )
    return [header, "\n".join(label_set.labels).encode()]
