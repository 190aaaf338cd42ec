"""Minimal OSC 1.0/1.1 primitives: the byte layout we read and write ourselves.

An OSC packet is a message or a bundle. Every item is padded with NUL bytes to a
multiple of 4, and all numbers are big-endian:

- string ``s``: UTF-8 bytes, then 1-4 NUL bytes (at least one) up to a multiple of 4;
- type tag string: a string starting with ``,`` (``",hdiib"``);
- ``i`` int32, ``h`` int64, ``f`` float32, ``d`` float64 (IEEE 754);
- blob ``b``: int32 byte count, the bytes, NUL padding to a multiple of 4;
- ``T`` ``F`` ``N`` ``I``: no argument bytes;
- bundle: ``#bundle\\0`` (8 bytes), an 8-byte NTP time tag (1 = "immediately"), then
  elements, each an int32 size (a multiple of 4) followed by a message or a bundle.

:func:`build_message` and :func:`build_bundle` serve tests and control messages; the hot
paths use prebuilt templates and fixed offsets instead (see ``osc_in``, ``vmc_out``).
"""

from __future__ import annotations

import struct
from collections.abc import Iterator, Sequence

from retargetd.protocols.errors import DecodeError

BUNDLE_TAG = b"#bundle\0"
#: The NTP time tag meaning "immediately" (OSC 1.0): seconds 0, fraction 1.
TIMETAG_IMMEDIATELY = 1
#: ``#bundle\\0`` + the "immediately" time tag: the first 16 bytes of our bundles.
BUNDLE_HEADER = BUNDLE_TAG + struct.pack(">Q", TIMETAG_IMMEDIATELY)
BUNDLE_HEADER_SIZE = 16
#: Each bundle element is preceded by its int32 size.
ELEMENT_SIZE_PREFIX = 4
#: Bundles nested deeper than this are refused (``bad_bundle``).
MAX_BUNDLE_DEPTH = 4

_ARG_SIZES = {"i": 4, "h": 8, "f": 4, "d": 8}
_ARG_FORMATS = {"i": ">i", "h": ">q", "f": ">f", "d": ">d"}
_NO_DATA_TAGS = frozenset("TFNI")
OscArg = int | float | str | bytes | bool | None
_NO_DATA_VALUES: dict[str, OscArg] = {"T": True, "F": False, "N": None, "I": None}


def padded_size(n: int) -> int:
    """Size of ``n`` bytes padded with NUL to the next multiple of 4 (0 stays 0)."""
    return (n + 3) & ~3


def osc_string(text: str | bytes) -> bytes:
    """Encode an OSC string: UTF-8, at least one NUL, padded to a multiple of 4.

    Raises:
        ValueError: if ``text`` contains a NUL byte.
    """
    raw = text.encode() if isinstance(text, str) else bytes(text)
    if b"\0" in raw:
        raise ValueError(f"OSC strings cannot contain NUL; got {text!r}")
    return raw + b"\0" * (padded_size(len(raw) + 1) - len(raw))


def osc_blob(data: bytes) -> bytes:
    """Encode an OSC blob: int32 size, the bytes, NUL padding to a multiple of 4."""
    data = bytes(data)
    return (
        struct.pack(">i", len(data))
        + data
        + b"\0" * (padded_size(len(data)) - len(data))
    )


def osc_string_size(text: str | bytes) -> int:
    """Encoded size in bytes of an OSC string (see :func:`osc_string`)."""
    raw = text.encode() if isinstance(text, str) else text
    return padded_size(len(raw) + 1)


def build_message(address: str, typetags: str, args: Sequence[OscArg]) -> bytes:
    """Build one OSC message (tests and control messages; not for the hot path).

    Args:
        address: OSC address, starting with ``/``.
        typetags: type tags with or without the leading comma (``"hdiib"``); ``i h f d
            s b`` take one argument each, ``T F N I`` none.
        args: the arguments, one per data-carrying tag.

    Returns:
        The encoded message.

    Raises:
        ValueError: unknown tag, wrong argument count, or a value out of range.
    """
    tags = typetags.removeprefix(",")
    data_tags = [t for t in tags if t not in _NO_DATA_TAGS]
    if len(data_tags) != len(args):
        raise ValueError(
            f"type tags {typetags!r} take {len(data_tags)} arguments; got {len(args)}"
        )
    parts = [osc_string(address), osc_string("," + tags)]
    values = iter(args)
    for tag in tags:
        if tag in _NO_DATA_TAGS:
            continue
        value = next(values)
        if tag in _ARG_FORMATS:
            try:
                parts.append(struct.pack(_ARG_FORMATS[tag], value))
            except struct.error as exc:
                raise ValueError(
                    f"argument {value!r} does not fit tag {tag!r}"
                ) from exc
        elif tag == "s":
            if not isinstance(value, str | bytes):
                raise ValueError(f"tag 's' takes a str; got {value!r}")
            parts.append(osc_string(value))
        elif tag == "b":
            if not isinstance(value, bytes | bytearray | memoryview):
                raise ValueError(f"tag 'b' takes bytes; got {type(value).__name__}")
            parts.append(osc_blob(bytes(value)))
        else:
            raise ValueError(f"unsupported OSC type tag {tag!r} in {typetags!r}")
    return b"".join(parts)


def build_bundle(
    elements: Sequence[bytes], timetag: int = TIMETAG_IMMEDIATELY
) -> bytes:
    """Build an OSC bundle of already encoded messages or bundles.

    Args:
        elements: encoded messages/bundles, each a multiple of 4 bytes long.
        timetag: 64-bit NTP time tag; 1 means "immediately" (what we always send).
    """
    parts = [BUNDLE_TAG, struct.pack(">Q", timetag)]
    for element in elements:
        if len(element) % 4:
            raise ValueError(
                f"bundle elements are multiples of 4 bytes; got {len(element)}"
            )
        parts.append(struct.pack(">i", len(element)))
        parts.append(bytes(element))
    return b"".join(parts)


def read_string(buf: bytes, offset: int) -> tuple[str, int]:
    """Read an OSC string at ``offset``.

    Args:
        buf: the packet (``bytes``: ``find`` is used to locate the NUL).
        offset: where the string starts, a multiple of 4.

    Returns:
        The decoded text and the offset just past its padding.

    Raises:
        DecodeError: ``bad_string`` when unterminated, overrunning or not UTF-8.
    """
    end = buf.find(b"\0", offset)
    if end < 0:
        raise DecodeError("bad_string", f"unterminated string at offset {offset}")
    nxt = padded_size(end + 1)
    if nxt > len(buf):
        raise DecodeError(
            "bad_string", f"string padding overruns the packet at {offset}"
        )
    try:
        text = buf[offset:end].decode()
    except UnicodeDecodeError as exc:
        raise DecodeError("bad_string", f"not UTF-8 at offset {offset}") from exc
    return text, nxt


def parse_message(buf: bytes) -> tuple[str, str, list[OscArg]]:
    """Parse any OSC message we understand into Python values (not hot).

    Args:
        buf: one OSC message.

    Returns:
        ``(address, typetags, args)``; ``typetags`` includes the leading comma.

    Raises:
        DecodeError: ``bad_length``, ``bad_address``, ``bad_typetags``,
            ``bad_string`` or ``bad_blob_size``.
    """
    buf = bytes(buf)
    if len(buf) < 8 or len(buf) % 4:
        raise DecodeError("bad_length", f"{len(buf)} bytes is not an OSC message")
    if buf[0:1] != b"/":
        raise DecodeError("bad_address", "address does not start with '/'")
    address, offset = read_string(buf, 0)
    if buf[offset : offset + 1] != b",":
        raise DecodeError("bad_typetags", "type tag string missing")
    typetags, offset = read_string(buf, offset)
    args: list[OscArg] = []
    for tag in typetags[1:]:
        if tag in _ARG_SIZES:
            size = _ARG_SIZES[tag]
            if offset + size > len(buf):
                raise DecodeError("bad_length", f"argument {tag!r} overruns the packet")
            args.append(struct.unpack_from(_ARG_FORMATS[tag], buf, offset)[0])
            offset += size
        elif tag == "s":
            text, offset = read_string(buf, offset)
            args.append(text)
        elif tag == "b":
            if offset + 4 > len(buf):
                raise DecodeError("bad_length", "blob size overruns the packet")
            (size,) = struct.unpack_from(">i", buf, offset)
            end = offset + 4 + size
            if size < 0 or padded_size(end) > len(buf):
                raise DecodeError("bad_blob_size", f"blob of {size} bytes overruns")
            args.append(buf[offset + 4 : end])
            offset = padded_size(end)
        elif tag in _NO_DATA_TAGS:
            args.append(_NO_DATA_VALUES[tag])
        else:
            raise DecodeError("bad_typetags", f"unsupported type tag {tag!r}")
    if offset != len(buf):
        raise DecodeError("bad_length", f"{len(buf) - offset} trailing bytes")
    return address, typetags, args


def iter_bundle_elements(buf: bytes | bytearray | memoryview) -> Iterator[memoryview]:
    """Yield the elements (messages or nested bundles) of one OSC bundle.

    The time tag is not interpreted: bundles are handled on arrival, never scheduled.

    Args:
        buf: one OSC bundle.

    Yields:
        A memoryview of each element's bytes, in order.

    Raises:
        DecodeError: ``bad_length`` (shorter than a bundle header), ``not_bundle``
            (no ``#bundle`` tag) or ``bad_bundle`` (an element size that is negative,
            not a multiple of 4, or overruns the packet).
    """
    view = memoryview(buf).cast("B")
    size = len(view)
    if size < BUNDLE_HEADER_SIZE:
        raise DecodeError("bad_length", f"{size} bytes is shorter than a bundle header")
    if view[0:8] != BUNDLE_TAG:
        raise DecodeError("not_bundle", "packet does not start with '#bundle'")
    offset = BUNDLE_HEADER_SIZE
    while offset < size:
        if offset + ELEMENT_SIZE_PREFIX > size:
            raise DecodeError("bad_bundle", f"element size at {offset} overruns")
        (n,) = struct.unpack_from(">i", view, offset)
        offset += ELEMENT_SIZE_PREFIX
        if n < 0 or n % 4 or offset + n > size:
            raise DecodeError("bad_bundle", f"bad element size {n} at {offset - 4}")
        yield view[offset : offset + n]
        offset += n
