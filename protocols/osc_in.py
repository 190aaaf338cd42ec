"""OSC marker input: the compact frame, label announcements and the simple bundle.

Byte layouts are specified in ``protocols/PROTOCOLS.md`` (sections 1-3); in short:

- compact frame ``/rtd/frame ,hdiib``: frame number int64, source time float64 s,
  label-set id int32, marker count int32, blob of count x 3 big-endian float32
  (x y z per marker, sender's units and axes, NaN = occluded). Fixed 48-byte header,
  so it is decoded by offset with ``np.frombuffer``, never through python-osc.
- labels ``/rtd/labels ,ii s...``: label-set id, count, then one string per marker.
- simple bundle: ``#bundle`` holding ``/rtd/marker ,sfff`` (name x y z) per marker and
  optionally ``/rtd/frame_number ,i`` or ``,h``.

Decoders raise only :class:`DecodeError`. Checks run size -> address -> type tags ->
structure (counts, blob size) -> label set -> values; the label-set checks come before
the per-value scan because the scratch buffers are sized by the label set. Nothing is
written into ``out`` unless the whole packet is good. The encoders at the end serve
senders (the replay player) and tests.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any, cast

import numpy as np

from retargetd.protocols import kernels
from retargetd.protocols.errors import DecodeError
from retargetd.protocols.marker_input import KERNEL_REASONS, LabelSet, MarkerPacket
from retargetd.protocols.osc_wire import (
    BUNDLE_HEADER_SIZE,
    BUNDLE_TAG,
    ELEMENT_SIZE_PREFIX,
    MAX_BUNDLE_DEPTH,
    build_bundle,
    build_message,
    iter_bundle_elements,
    osc_string,
    parse_message,
    read_string,
)

COMPACT_ADDRESS = "/rtd/frame"
COMPACT_TYPETAGS = ",hdiib"
LABELS_ADDRESS = "/rtd/labels"
MARKER_ADDRESS = "/rtd/marker"
FRAME_NUMBER_ADDRESS = "/rtd/frame_number"

_COMPACT_ADDR = osc_string(COMPACT_ADDRESS)  # 12 bytes
_COMPACT_TAGS = osc_string(COMPACT_TYPETAGS)  # 8 bytes
_COMPACT_FIELDS = struct.Struct(">qdiii")  # frame, time, label set, count, blob size
#: Byte offsets in a compact frame.
COMPACT_FIELDS_OFFSET = len(_COMPACT_ADDR) + len(_COMPACT_TAGS)  # 20
COMPACT_HEADER_SIZE = COMPACT_FIELDS_OFFSET + _COMPACT_FIELDS.size  # 48
_BE_F32 = np.dtype(">f4")
_TIME_BE = struct.Struct(">d")
_TIME_OFFSET = COMPACT_FIELDS_OFFSET + 8

_MARKER_TAGS = osc_string(",sfff")
_MARKER_XYZ = struct.Struct(">fff")
_FRAME_NUMBER_FORMATS = {b",i\0\0": ">i", b",h\0\0": ">q"}


def decode_compact_frame(
    buf: bytes | bytearray | memoryview, out: MarkerPacket
) -> MarkerPacket:
    """Decode a ``/rtd/frame ,hdiib`` datagram into ``out`` (the hot path).

    Args:
        buf: one UDP datagram.
        out: packet allocated for the current label set; positions are converted with
            its ``world_from_capture_scaled_mat``.

    Returns:
        ``out``, with ``frame.frame_id``, ``frame.source_time_s``,
        ``frame.markers_world`` (n, 3) float64 metres world (NaN rows = occluded),
        ``frame.valid`` and ``label_set_id`` set; ``frame.t_ns`` is left to the caller.

    Raises:
        DecodeError: ``bad_length``, ``bad_address``, ``bad_typetags``, ``bad_count``,
            ``bad_blob_size``, ``unknown_label_set``, ``count_mismatch``,
            ``bad_frame_number`` (negative) or ``non_finite`` (±inf anywhere).
    """
    size = len(buf)
    if size < COMPACT_HEADER_SIZE:
        raise DecodeError("bad_length", f"{size} bytes < {COMPACT_HEADER_SIZE}")
    if buf[0:12] != _COMPACT_ADDR:
        raise DecodeError("bad_address", f"expected {COMPACT_ADDRESS}")
    if buf[12:20] != _COMPACT_TAGS:
        raise DecodeError("bad_typetags", f"expected {COMPACT_TYPETAGS}")
    frame_id, time_s, label_set_id, count, blob_size = _COMPACT_FIELDS.unpack_from(
        buf, COMPACT_FIELDS_OFFSET
    )
    if count < 0:
        raise DecodeError("bad_count", f"marker count {count}")
    if blob_size != 12 * count:
        raise DecodeError(
            "bad_blob_size", f"blob {blob_size} bytes for {count} markers"
        )
    if size != COMPACT_HEADER_SIZE + blob_size:
        raise DecodeError("bad_length", f"{size} bytes for a {blob_size}-byte blob")
    if label_set_id != out.label_set.id:
        raise DecodeError("unknown_label_set", f"label set {label_set_id}")
    if count != len(out.label_set.labels):
        raise DecodeError(
            "count_mismatch", f"{count} markers for label set {label_set_id}"
        )
    if frame_id < 0:
        raise DecodeError("bad_frame_number", f"frame number {frame_id}")
    raw = np.frombuffer(buf, _BE_F32, 3 * count, COMPACT_HEADER_SIZE).reshape(count, 3)
    if math.isinf(time_s):
        raise DecodeError("non_finite", "infinite source time")
    out.store(raw)  # raises non_finite before writing anything
    frame = out.frame
    frame.frame_id = frame_id
    frame.source_time_s = time_s
    out.label_set_id = label_set_id
    out.unknown_labels = 0
    return out


def decode_compact_into(wire: np.ndarray, n: int, out: MarkerPacket) -> MarkerPacket:
    """:func:`decode_compact_frame` of the datagram in ``wire[:n]``, its checks and
    the markers' store in one compiled call (``kernels.decode_frame``; the live
    loop's form: ``wire`` is a uint8 array over its receive buffer).

    Same result, same checks in the same order; a refused packet raises the
    :class:`DecodeError` :func:`decode_compact_frame` raises for it (its checks run
    again, in Python, to say why: refusals are not the hot path)."""
    frame_id = out.decode_packed(kernels.FORM_OSC_COMPACT, wire, n, wire, 0)
    if frame_id < 0:
        decode_compact_frame(wire.data[:n], out)  # raises the reason
        raise DecodeError(KERNEL_REASONS[frame_id], "refused by the compiled checks")
    frame = out.frame
    frame.frame_id = frame_id
    (frame.source_time_s,) = _TIME_BE.unpack_from(wire.data, _TIME_OFFSET)
    out.label_set_id = out.label_set.id
    out.unknown_labels = 0
    return out


def decode_labels(buf: bytes | bytearray | memoryview) -> LabelSet:
    """Decode a ``/rtd/labels ,ii s...`` datagram (not hot: Python objects are fine).

    Raises:
        DecodeError: the reasons of :func:`~retargetd.protocols.osc_wire.parse_message`,
            ``bad_address``, ``bad_typetags``, ``bad_count`` (count differs from the
            number of strings) or ``bad_label`` (empty or repeated name).
    """
    address, typetags, args = parse_message(bytes(buf))
    if address != LABELS_ADDRESS:
        raise DecodeError("bad_address", f"expected {LABELS_ADDRESS}; got {address!r}")
    if not typetags.startswith(",ii") or typetags[3:].strip("s"):
        raise DecodeError(
            "bad_typetags", f"expected ,ii followed by s; got {typetags!r}"
        )
    label_set_id, count, *labels = args
    if count != len(labels):
        raise DecodeError("bad_count", f"count {count!r} with {len(labels)} labels")
    # The type tags checked above make these an int and strings.
    return LabelSet(cast(int, label_set_id), tuple(str(name) for name in labels))


def _walk(buf: bytes, start: int, end: int, depth: int) -> Iterator[tuple[int, int]]:
    """(start, end) offsets in ``buf`` of a bundle's messages, nested bundles
    flattened (timetags ignored)."""
    if depth > MAX_BUNDLE_DEPTH:
        raise DecodeError(
            "bad_bundle", f"bundles nested deeper than {MAX_BUNDLE_DEPTH}"
        )
    offset = start + BUNDLE_HEADER_SIZE
    for element in iter_bundle_elements(memoryview(buf)[start:end]):
        n = len(element)
        a = offset + ELEMENT_SIZE_PREFIX
        offset = a + n
        if buf[a : a + 8] == BUNDLE_TAG:
            yield from _walk(buf, a, a + n, depth + 1)
        else:
            yield a, a + n


@dataclass(slots=True, eq=False)
class SimpleLayout:
    """The layout of the last simple bundle a packet decoded, so that the next bundle
    of the same layout (a sender sends the same names in the same order every frame)
    is read straight from its value slots, with no Python object per marker.

    Attributes:
        length: the datagram's size, bytes.
        template: (length / 4,) big-endian uint32 words of that datagram.
        mask: (length / 4,) uint32: 0 at the value slots, all ones elsewhere (a
            bundle matches when every other word equals the template's).
        diff: (length / 4,) uint32 scratch.
        slot_words: (K * 3,) intp word index of each known marker's x, y, z.
        flat_rows: (K * 3,) intp index into the staged (n, 3) rows, flattened.
        values: (K * 3,) big-endian float32 scratch.
        frame_word: word index of the frame number, -1 when there is none.
        frame_wide: the frame number is ``,h`` (int64, two words).
        unknown: /rtd/marker messages with names not in the label set.
        hits: bundles read through this layout (not parsed).
    """

    length: int
    template: np.ndarray
    mask: np.ndarray
    diff: np.ndarray
    slot_words: np.ndarray
    flat_rows: np.ndarray
    values: np.ndarray
    frame_word: int
    frame_wide: bool
    unknown: int
    hits: int = 0


def _fast_simple(buf: Any, out: MarkerPacket, lay: SimpleLayout) -> bool:
    """Decode ``buf`` with the cached layout; False when it is not that layout."""
    if len(buf) != lay.length:
        return False
    words = np.frombuffer(buf, dtype=">u4")
    np.bitwise_xor(words, lay.template, out=lay.diff)
    np.bitwise_and(lay.diff, lay.mask, out=lay.diff)
    if lay.diff.any():
        return False
    np.take(words.view(">f4"), lay.slot_words, out=lay.values)
    if np.isinf(lay.values).any():
        raise DecodeError("non_finite", "infinite coordinate in a simple bundle")
    staged = out._staged
    staged.fill(np.nan)
    # A signalling NaN (any NaN bit pattern is a hidden marker on the wire) raises
    # numpy's "invalid" flag when widened to float64; the value is still NaN.
    with np.errstate(invalid="ignore"):
        np.put(staged, lay.flat_rows, lay.values)
    frame_id = -1
    if lay.frame_word >= 0:
        hi = int(words[lay.frame_word])
        if lay.frame_wide:
            frame_id = (hi << 32) | int(words[lay.frame_word + 1])
            if frame_id >= 1 << 63:
                frame_id -= 1 << 64
        else:
            frame_id = hi - (1 << 32) if hi >= 1 << 31 else hi
        if frame_id < 0:
            raise DecodeError("bad_frame_number", f"frame number {frame_id}")
    out.store(staged)
    frame = out.frame
    frame.frame_id = frame_id
    frame.source_time_s = math.nan
    out.label_set_id = out.label_set.id
    out.unknown_labels = lay.unknown
    lay.hits += 1
    return True


def decode_simple_bundle(
    buf: bytes | bytearray | memoryview, out: MarkerPacket
) -> MarkerPacket:
    """Decode a bundle of ``/rtd/marker ,sfff`` messages into ``out``.

    Markers are matched by name against ``out.label_set`` (the configured labels).
    Configured markers missing from the bundle are occluded. Names not in the label
    set are ignored and counted in ``out.unknown_labels``; the rest of the frame is
    kept. Messages with other addresses are ignored (as OSC receivers do). The time
    tag is ignored: the bundle is used on arrival.

    Args:
        buf: one UDP datagram holding an OSC bundle.
        out: packet allocated for the configured label set.

    Returns:
        ``out``; ``frame.frame_id`` is the ``/rtd/frame_number`` value or -1 when the
        bundle has none; ``frame.source_time_s`` is NaN.

    Raises:
        DecodeError: ``not_bundle`` (a bare message), ``bad_length``, ``bad_bundle``
            (bad element sizes, nesting, two frame numbers), ``bad_string``,
            ``bad_typetags``, ``bad_frame_number``, ``non_finite``,
            ``duplicate_marker`` (a name twice) or ``no_markers`` (no /rtd/marker).
    """
    lay = out._simple
    if lay is not None and _fast_simple(buf, out, lay):
        return out
    data = bytes(buf)
    if data[0:1] == b"/":
        raise DecodeError("not_bundle", "a bare message, not a bundle")
    staged = out._staged
    seen = out._seen
    staged.fill(np.nan)
    seen.fill(False)
    index = out.label_index
    frame_id = -1
    frame_at, frame_wide = -1, False
    n_markers = 0
    unknown = 0
    slots: list[int] = []
    rows: list[int] = []
    ignored: list[int] = []
    for a, b in _walk(data, 0, len(data), 1):
        msg = data[a:b]
        address, offset = read_string(msg, 0)
        if address == MARKER_ADDRESS:
            if msg[offset : offset + 8] != _MARKER_TAGS:
                raise DecodeError("bad_typetags", "/rtd/marker takes ,sfff")
            name, offset = read_string(msg, offset + 8)
            if offset + 12 != len(msg):
                raise DecodeError("bad_length", "/rtd/marker has the wrong size")
            xyz = _MARKER_XYZ.unpack_from(msg, offset)
            if math.isinf(xyz[0]) or math.isinf(xyz[1]) or math.isinf(xyz[2]):
                raise DecodeError("non_finite", f"infinite coordinate for {name!r}")
            n_markers += 1
            row = index.get(name)
            if row is None:
                unknown += 1
                ignored.append((a + offset) // 4)  # its values vary: masked too
                continue
            if seen[row]:
                raise DecodeError("duplicate_marker", f"{name!r} twice in one bundle")
            seen[row] = True
            staged[row] = xyz
            slots.append((a + offset) // 4)
            rows.append(row)
        elif address == FRAME_NUMBER_ADDRESS:
            fmt = _FRAME_NUMBER_FORMATS.get(msg[offset : offset + 4])
            if fmt is None:
                raise DecodeError("bad_typetags", "/rtd/frame_number takes ,i or ,h")
            offset += 4
            if offset + struct.calcsize(fmt) != len(msg):
                raise DecodeError("bad_length", "/rtd/frame_number has the wrong size")
            if frame_id >= 0:
                raise DecodeError("bad_bundle", "two /rtd/frame_number messages")
            (frame_id,) = struct.unpack_from(fmt, msg, offset)
            if frame_id < 0:
                raise DecodeError("bad_frame_number", f"frame number {frame_id}")
            frame_at, frame_wide = (a + offset) // 4, fmt == ">q"
    if n_markers == 0:
        raise DecodeError("no_markers", "bundle holds no /rtd/marker message")
    out.store(staged)
    frame = out.frame
    frame.frame_id = frame_id
    frame.source_time_s = math.nan
    out.label_set_id = out.label_set.id
    out.unknown_labels = unknown
    out._simple = _layout_of(data, slots, rows, ignored, frame_at, frame_wide, unknown)
    return out


def _layout_of(
    data: bytes,
    slots: list[int],
    rows: list[int],
    ignored: list[int],
    frame_at: int,
    frame_wide: bool,
    unknown: int,
) -> SimpleLayout | None:
    """The layout cache of a decoded bundle (None when its size is not whole words):
    built once per new layout, not per frame."""
    if len(data) % 4:
        return None
    template = np.frombuffer(data, dtype=">u4").copy()
    mask = np.full(len(template), 0xFFFFFFFF, dtype=">u4")
    words = np.array([w + k for w in slots for k in range(3)], dtype=np.intp)
    mask[words] = 0
    for w in ignored:  # markers with names not in the label set
        mask[w : w + 3] = 0
    if frame_at >= 0:
        mask[frame_at : frame_at + (2 if frame_wide else 1)] = 0
    return SimpleLayout(
        length=len(data),
        template=template,
        mask=mask,
        diff=np.zeros(len(template), dtype=">u4"),
        slot_words=words,
        flat_rows=np.array([3 * r + k for r in rows for k in range(3)], np.intp),
        values=np.zeros(len(words), dtype=">f4"),
        frame_word=frame_at,
        frame_wide=frame_wide,
        unknown=unknown,
    )


def encode_compact_frame(
    frame_id: int, source_time_s: float, label_set_id: int, positions: np.ndarray
) -> bytes:
    """Encode a compact frame (senders and tests; not the receive path).

    Args:
        frame_id: frame number, int64 >= 0.
        source_time_s: the sender's timestamp in seconds, NaN when unknown.
        label_set_id: int32 id of the announced label set.
        positions: (n, 3) float, sender's units and axes; NaN rows = occluded.
    """
    pos = np.asarray(positions, dtype=_BE_F32)
    if pos.ndim != 2 or pos.shape[1] != 3:
        raise ValueError(f"positions must be (n, 3); got shape {pos.shape}")
    n = pos.shape[0]
    fields = _COMPACT_FIELDS.pack(frame_id, source_time_s, label_set_id, n, 12 * n)
    return _COMPACT_ADDR + _COMPACT_TAGS + fields + pos.tobytes()


def encode_labels(label_set: LabelSet) -> bytes:
    """Encode a ``/rtd/labels`` announcement for ``label_set``."""
    n = len(label_set.labels)
    return build_message(
        LABELS_ADDRESS, ",ii" + "s" * n, [label_set.id, n, *label_set.labels]
    )


def encode_simple_bundle(
    labels: Sequence[str], positions: np.ndarray, frame_id: int | None = None
) -> bytes:
    """Encode a simple bundle: one ``/rtd/marker`` per label, optional frame number.

    Args:
        labels: marker names, one per row of ``positions``.
        positions: (n, 3) float, sender's units and axes; NaN = occluded.
        frame_id: sent as ``/rtd/frame_number ,h`` when given.
    """
    pos = np.asarray(positions, dtype=np.float64)
    elements = [
        build_message(MARKER_ADDRESS, ",sfff", [name, *map(float, xyz)])
        for name, xyz in zip(labels, pos, strict=True)
    ]
    if frame_id is not None:
        elements.insert(0, build_message(FRAME_NUMBER_ADDRESS, ",h", [frame_id]))
    return build_bundle(elements)
