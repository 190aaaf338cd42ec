"""C3D layout check: what a file declares, checked against its size before any reader.

:func:`inspect_c3d` walks the 512-byte header and the parameter section in pure
Python, reading at most the header, the parameter section and nothing of the data,
and never allocating from a size the file declares before comparing that size with
the bytes the file holds. It returns a :class:`C3DLayout`, or raises a one-line
:class:`~retargetd.replay.take.TakeError` when the file holds no data we could load
(empty, shorter than a header, no 3D points, no complete frame).

The walk follows ezc3d's rules (offsets to the next entry as unsigned 16-bit words,
description lengths as *signed* bytes, the section ending at a zero name length,
whatever the parameter block count says) so that it can say, before ezc3d runs,
whether ezc3d would read the file as written (``ezc3d_problems`` empty) or would
fail, read nothing, or allocate from a nonsense size. Examples from the c3d.org
samples (``../shared/formats``): ``BKINtechnologies.c3d`` gives
``EXPERIMENT:SESSION`` a 163-character description; ezc3d reads that length as -93
and asks for a ~4 GB string (12.6 GB and 46 s before it failed); the PhaseSpace
sample has an empty parameter section, where ezc3d reads 0 points and a 0 Hz rate
although the header declares 40 points at 30 Hz; the SGI sample is MIPS, which
ezc3d refuses.

Where an entry's next-entry offset disagrees with its own sizes, the walk reads the
section as BTK does (``btkC3DFileIO.cpp``; read, not copied), with one difference:

- **A description longer than the bytes left** before the entry the offset points at
  (a 211-character description in a vendor's file): BTK reads that many bytes, then
  seeks back to the offset's target. We read the description as the bytes left and go
  on at the target.
- **An offset pointing inside its own entry, backwards, or past the parameter
  section** (into the data section or past the file; ``POINT:LABELS`` in two vendors'
  files): BTK seeks to the target whatever it is, which inside an entry reads the
  entry's own bytes as the next entry; it stops reading parameters at a target in the
  data section. We go on from the entry's end when an entry (or the end marker)
  starts there; else, past the section, we stop as BTK does (the parameters after it
  are not read), and inside or backwards the file fails in one line.

Each repair is a note (``take info`` lists it) and a few bytes in ``patches`` that the
fallback reader overlays on the file, so the ``c3d`` package walks the same section;
ezc3d, which is strict about offsets, is not used for such a file.

Header words (16-bit, 1-based, C3D standard, https://www.c3d.org/): 1 parameter
block and key 0x50; 2 points; 3 analog samples per frame (all channels); 4 first
frame; 5 last frame; 7-8 scale (float, < 0 means float data); 9 data start block;
10 analog samples per channel per frame; 11-12 frame rate (float).
"""

from __future__ import annotations

import math
import os
import re
import struct
from dataclasses import dataclass, field

import numpy as np

from retargetd.replay.take import TakeError

#: C3D blocks are 512 bytes (C3D standard).
BLOCK_BYTES = 512
#: Parameter-section processor byte -> name (C3D standard: 84 Intel, 85 DEC, 86 MIPS).
PROCESSORS = {84: "Intel", 85: "DEC", 86: "MIPS"}
#: Zero bytes skipped before the header, as ezc3d does for some Vicon files (bound:
#: one block; a longer run is not a C3D header).
MAX_LEADING_ZEROS = BLOCK_BYTES
#: The parameter section is at most 255 blocks: its block count is one byte.
MAX_PARAMETER_BLOCKS = 255
#: Parameter element types: -1 char, 1 byte, 2 int16, 4 float (C3D standard).
PARAM_TYPES = (-1, 1, 2, 4)
_KEY = 0x50


@dataclass(frozen=True, slots=True)
class RawParam:
    """One parameter as stored: element type, dimensions and raw bytes."""

    type_code: int
    dims: tuple[int, ...]
    data: bytes


@dataclass(frozen=True, slots=True, kw_only=True)
class C3DLayout:
    """What a C3D file declares, checked against its size.

    Attributes:
        path: the file.
        size_bytes: its size.
        processor: ``"Intel"``, ``"DEC"`` or ``"MIPS"``.
        n_points: 3D points per frame (``POINT:USED``, else the header).
        frame_bytes: bytes of one frame (points and analog samples).
        data_offset: byte offset of the first frame.
        frames_declared: the largest frame count the file declares anywhere (header,
            ``POINT:FRAMES``, ``TRIAL:ACTUAL_*_FIELD``).
        frames_present: complete frames the file holds after ``data_offset``.
        header_rate_hz: the header's frame rate, Hz (0 when absent).
        first_frame: the header's first frame, 0-based (as ezc3d reports it).
        is_float: True for float data (scale < 0), False for 16-bit integers.
        params: ``(GROUP, NAME)`` -> raw parameter, for those whose declared size fits.
        ezc3d_problems: why ezc3d cannot be trusted with this file (empty: it can).
        notes: other departures from the standard, reported as repairs when a
            reader works around them.
        patches: ``(file offset, bytes)`` to overlay on the file so that a reader
            walking its parameter section sees the repaired section (a description
            length cut to the bytes left, a next-entry offset pointing at the
            entry's end or 0); empty for a standard section.
    """

    path: str
    size_bytes: int
    processor: str
    n_points: int
    frame_bytes: int
    data_offset: int
    frames_declared: int
    frames_present: int
    header_rate_hz: float
    first_frame: int
    is_float: bool
    params: dict[tuple[str, str], RawParam] = field(default_factory=dict)
    ezc3d_problems: tuple[str, ...] = ()
    notes: tuple[str, ...] = ()
    patches: tuple[tuple[int, bytes], ...] = ()

    def has(self, group: str, name: str) -> bool:
        """True when the file stores ``GROUP:NAME`` (readers may add defaults)."""
        return (group, name) in self.params


def _dec_float(raw: bytes) -> float:
    """A DEC (VAX F) float, 4 bytes as stored, to a Python float.

    VAX F is IEEE-like with the 16-bit halves swapped, exponent bias 128 and the
    binary point one place further left: swapping the halves and dividing the IEEE
    reading by 4 gives the value (a zero exponent is zero).
    """
    swapped = raw[2:4] + raw[0:2]
    if (swapped[3] & 0x7F) == 0 and (swapped[2] & 0x80) == 0:
        return 0.0
    return float(struct.unpack("<f", swapped)[0]) / 4.0


class _Decoder:
    """Integers and floats in one processor's byte order and float format."""

    def __init__(self, processor: int) -> None:
        self.big_endian = processor == 86
        self.dec = processor == 85
        self._i16 = struct.Struct(">h" if self.big_endian else "<h")
        self._u16 = struct.Struct(">H" if self.big_endian else "<H")

    def i16(self, raw: bytes, at: int = 0) -> int:
        return int(self._i16.unpack_from(raw, at)[0])

    def u16(self, raw: bytes, at: int = 0) -> int:
        return int(self._u16.unpack_from(raw, at)[0])

    def pack_u16(self, value: int) -> bytes:
        return self._u16.pack(value)

    def f32(self, raw: bytes, at: int = 0) -> float:
        chunk = raw[at : at + 4]
        if self.dec:
            return _dec_float(chunk)
        return float(struct.unpack(">f" if self.big_endian else "<f", chunk)[0])


def _no_data(path: str, why: str) -> TakeError:
    return TakeError(f"take {path}: {why}: the file holds no data to load")


def _param_number(dec: _Decoder, param: RawParam | None) -> float | None:
    """First value of a numeric parameter, or None when absent, empty or a string."""
    if param is None or param.type_code == -1:
        return None
    size = abs(param.type_code)
    if len(param.data) < size:
        return None
    if param.type_code == 4:
        return dec.f32(param.data)
    if param.type_code == 2:
        return float(dec.i16(param.data))
    return float(struct.unpack("b", param.data[:1])[0])


#: C3D names are letters, digits and underscores (C3D standard); used only to tell
#: whether an offset that disagrees with an entry's size lands on an entry.
_ENTRY_NAME = re.compile(rb"[A-Za-z0-9_]+")


def _entry_at(section: bytes, at: int, limit: int) -> bool:
    """True when an entry or the section's end marker plausibly starts at ``at``.

    A zero name length ends the section; otherwise a name of C3D characters, a
    non-zero group id and an offset word must fit before ``limit``.
    """
    if not 0 <= at < limit:
        return False
    n_name = struct.unpack_from("b", section, at)[0]
    if n_name == 0:
        return True
    if at + 4 + abs(n_name) > limit or section[at + 1] == 0:
        return False
    return _ENTRY_NAME.fullmatch(section[at + 2 : at + 2 + abs(n_name)]) is not None


@dataclass(frozen=True, slots=True, kw_only=True)
class _Entry:
    """Where one entry's parts lie, section-relative bytes."""

    name: str  # GROUP or GROUP:NAME
    start: int  # the name length byte
    offset_at: int  # the next-entry offset word
    target: int  # where the offset says the next entry starts (0: last entry)
    desc_at: int  # the description length byte
    n_desc: int  # the description length, as an unsigned byte
    end: int  # desc_at + 1 + n_desc: where the entry's own sizes say it ends


@dataclass(slots=True)
class _Repairs:
    """What the walk worked around: messages and byte patches (section-relative)."""

    notes: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)
    patches: list[tuple[int, bytes]] = field(default_factory=list)
    #: False once a "not standard" problem is recorded (one such message is enough).
    standard: bool = True


def _next_entry(
    section: bytes, entry: _Entry, limit: int, dec: _Decoder, fix: _Repairs
) -> int | None:
    """Where the entry after ``entry`` starts, repairing a bad offset as BTK would.

    BTK (``btkC3DFileIO.cpp``) seeks to the offset's target whatever the entry's own
    sizes say: a description longer than the bytes left is read and the stream
    seeked back; an offset pointing into the data section stops the walk. We do the
    same where the target is an entry, and otherwise, where BTK would read an
    entry's own bytes as the next entry, go on from the entry's end when an entry
    starts there. Each repair is noted and patched in the bytes the fallback reads,
    so that the ``c3d`` package walks the section the same way.

    Returns:
        The next entry's position, or None to stop the walk here.
    """
    target, end = entry.target, entry.end
    if target == end:
        return target
    fits = entry.desc_at < target < limit
    if fits and target < end and _entry_at(section, target, limit):
        left = target - entry.desc_at - 1
        fix.notes.append(
            f"{entry.name} description length {entry.n_desc} overstates the {left} "
            f"bytes left before the next entry; read as {left}"
        )
        fix.problems.append(f"{entry.name} description overstates its length")
        fix.patches.append((entry.desc_at, bytes([left])))
        return target
    if fits and target > end:
        # A gap: ezc3d (strict) refuses it; BTK and the c3d package follow the offset.
        if fix.standard:
            fix.problems.append(
                f"parameter section not standard: entry {entry.name!r} ends at byte "
                f"{end}, its offset says {target}"
            )
            fix.standard = False
        return target
    if target <= entry.start:
        where = f"backwards (to section byte {target})"
    elif target < limit:
        where = f"inside the entry (section byte {target}; it ends at {end})"
    else:
        where = (
            f"past the parameter section (section byte {target}; it ends at {limit})"
        )
    fix.problems.append(f"{entry.name} next-entry offset points {where.split(' (')[0]}")
    if end < limit and _entry_at(section, end, limit):
        fix.notes.append(
            f"{entry.name} next-entry offset points {where}; read on from the "
            f"entry's end (byte {end})"
        )
        fix.patches.append((entry.offset_at, dec.pack_u16(end - entry.offset_at)))
        return end
    if target >= limit:
        # BTK: "The next parameter is pointing in the Data section. Parameters'
        # extraction is stopped."
        fix.notes.append(
            f"{entry.name} next-entry offset points {where} and no entry starts at "
            f"its end: the parameters after it are not read"
        )
        fix.patches.append((entry.offset_at, dec.pack_u16(0)))
        return None
    raise ValueError(
        f"{entry.name} next-entry offset points {where} and no entry starts at its "
        f"end (byte {end})"
    )


def _walk_parameters(
    section: bytes, dec: _Decoder, n_blocks: int, limit: int
) -> tuple[dict[tuple[str, str], RawParam], list[str], _Repairs]:
    """Walk the parameter section as ezc3d does, bounded by the bytes present.

    Args:
        section: the parameter section bytes present in the file (from its first
            byte, at most :data:`MAX_PARAMETER_BLOCKS` blocks).
        dec: the processor's decoder.
        n_blocks: the block count the section declares.
        limit: where the data section starts (section-relative, at most
            ``len(section)``): no entry lies at or past it.

    Returns:
        ``(params, ezc3d_problems, repairs)``; ``repairs.notes`` holds every
        departure from the standard, ``repairs.patches`` the bytes to change so that
        a reader walking the file sees the repaired section.

    Raises:
        ValueError: an entry's offset points inside it or backwards and no entry
            starts at its end: nothing safe to read on from (one line).
    """
    params: dict[tuple[str, str], RawParam] = {}
    fix = _Repairs()
    problems = fix.problems
    notes = fix.notes
    group_names: dict[int, str] = {}
    pending: list[tuple[int, str, RawParam]] = []
    declared_end = n_blocks * BLOCK_BYTES
    pos = 4
    end = len(section)
    while True:
        if pos + 2 > end:
            problems.append(
                "parameter section has no end marker before the end of the file"
            )
            break
        start = pos
        n_name = struct.unpack_from("b", section, pos)[0]
        if n_name == 0:
            break
        gid = struct.unpack_from("b", section, pos + 1)[0]
        pos += 2
        name = section[pos : pos + abs(n_name)].decode("latin-1").strip()
        pos += abs(n_name)
        if pos + 2 > end:
            problems.append("parameter section cut inside an entry")
            break
        offset_at = pos
        offset = dec.u16(section, pos)
        pos += 2
        target = pos + offset - 2 if offset else 0
        if gid == 0:
            problems.append(f"entry {name!r} has group id 0")
            break
        if gid < 0:
            if pos + 1 > end:
                problems.append("parameter section cut inside a group entry")
                break
            group_names[-gid] = name
        else:
            name = f"{group_names.get(gid, f'group {gid}')}:{name}"
            if pos + 2 > end:
                problems.append("parameter section cut inside a parameter entry")
                break
            type_code = struct.unpack_from("b", section, pos)[0]
            n_dims = section[pos + 1]
            pos += 2
            dims = tuple(section[pos : pos + n_dims])
            pos += n_dims
            count = math.prod(dims) if dims else (0 if type_code == -1 else 1)
            size = abs(type_code) * count
            if type_code not in PARAM_TYPES:
                problems.append(f"parameter {name} has element type {type_code}")
                size = 0
            room = min(target if target else end, end)
            # An offset short of values that fit, followed by an entry, is the
            # offset's fault (repaired below), not the values'.
            own_end = pos + size
            offset_at_fault = (
                bool(offset)
                and own_end < min(limit, end)
                and _entry_at(section, own_end + 1 + section[own_end], min(limit, end))
            )
            if pos + size > room and not offset_at_fault:
                problems.append(
                    f"parameter {name} declares {size} bytes of values but its "
                    f"entry holds {max(0, room - pos)}"
                )
                notes.append(f"parameter {name} skipped: declares more bytes than held")
                fix.standard = False
                if (
                    offset
                    and start < target < pos + size
                    and not _entry_at(section, target, min(limit, end))
                ):
                    # BTK would read the values' bytes as the next entry.
                    raise ValueError(
                        f"{name} next-entry offset points inside the entry (section "
                        f"byte {target}) and no entry starts at its end"
                    )
                if offset:
                    if target <= start:
                        problems.append(f"entry {name!r} points backwards")
                        break
                    pos = target  # one message for this entry is enough
                    continue
            else:
                pending.append(
                    (
                        gid,
                        name.rpartition(":")[2],
                        RawParam(type_code, dims, section[pos : pos + size]),
                    )
                )
            pos += size
        n_desc = section[pos] if pos < end else 0
        if n_desc > 127:
            kind = "group" if gid < 0 else "parameter"
            problems.append(
                f"{kind} {name} has a {n_desc}-character description "
                "(ezc3d reads the length as negative and allocates ~4 GB)"
            )
        entry = _Entry(
            name=name,
            start=start,
            offset_at=offset_at,
            target=target,
            desc_at=pos,
            n_desc=n_desc,
            end=pos + 1 + n_desc,
        )
        pos = entry.end
        if not offset:
            break  # the last entry
        following = _next_entry(section, entry, min(limit, end), dec, fix)
        if following is None:
            break
        pos = following
    if not pending:
        notes.append("parameter section holds no parameters")
    elif pos > declared_end:
        notes.append(f"parameter section runs past its declared {n_blocks} blocks")
    for gid, name, param in pending:
        group = group_names.get(gid)
        if group is None:
            notes.append(f"parameter {name} belongs to no group (id {gid})")
            continue
        params.setdefault((group, name), param)
    return params, problems, fix


def _rotation_problems(
    dec: _Decoder,
    params: dict[tuple[str, str], RawParam],
    n_frames: int,
    header_rate_hz: float,
    size: int,
) -> list[str]:
    """ezc3d also reads a ``ROTATION`` data section: check its declared size.

    ezc3d reads ``USED`` x ``RATIO`` rotations per frame, each at least a 4 x 4 float
    matrix, from block ``DATA_START``; the c3d package ignores the section.
    """
    if not any(group == "ROTATION" for group, _ in params):
        return []
    used = _param_number(dec, params.get(("ROTATION", "USED")))
    start = _param_number(dec, params.get(("ROTATION", "DATA_START")))
    ratio = _param_number(dec, params.get(("ROTATION", "RATIO")))
    if ratio is None:
        rate = _param_number(dec, params.get(("ROTATION", "RATE")))
        if rate is not None and header_rate_hz > 0:
            ratio = rate / header_rate_hz
    if used is None or start is None or ratio is None:
        return ["ROTATION group without USED, DATA_START and RATIO or RATE"]
    if not (math.isfinite(ratio) and ratio >= 0 and start >= 1):
        return [f"ROTATION:RATIO {ratio} or DATA_START {start} out of range"]
    need = int(used) * int(ratio) * n_frames * 16 * 4
    held = size - (int(start) - 1) * BLOCK_BYTES
    if need > held:
        return [
            f"ROTATION data declares {need} bytes but the file holds {max(held, 0)}"
        ]
    return []


def inspect_c3d(path: str | os.PathLike[str]) -> C3DLayout:
    """Read and check what a C3D file declares, without reading its data.

    Args:
        path: the ``.c3d`` file.

    Returns:
        The layout; ``ezc3d_problems`` lists why ezc3d must not read it.

    Raises:
        TakeError: the file is unreadable, not a C3D file, or holds no data (empty,
            shorter than a header, no 3D points, no complete frame); one line.
    """
    name = str(path)
    leading_notes: list[str] = []
    try:
        size = os.stat(name).st_size
        with open(name, "rb") as fh:
            if size == 0:
                raise _no_data(name, "empty file (0 bytes)")
            # Some Vicon files start with zero bytes; ezc3d skips them and reads the
            # header and parameters after them (the data start stays absolute).
            lead = fh.read(MAX_LEADING_ZEROS + 1)
            zeros = len(lead) - len(lead.lstrip(b"\x00"))
            if zeros == len(lead):
                raise _no_data(name, f"the first {zeros} bytes are all zero")
            if zeros:
                leading_notes.append(f"{zeros} zero bytes before the header, skipped")
            fh.seek(zeros)
            head = fh.read(BLOCK_BYTES)
            if len(head) < BLOCK_BYTES:
                raise _no_data(name, f"{size} bytes, shorter than a C3D header (512)")
            if head[1] != _KEY:
                raise TakeError(
                    f"take {name}: not a C3D file (byte 2 is {head[1]:#04x}, not 0x50)"
                )
            param_block = head[0]
            section_at = (param_block - 1) * BLOCK_BYTES + zeros
            if section_at + 4 > size:
                raise _no_data(
                    name, f"parameter block {param_block} lies beyond the file"
                )
            fh.seek(section_at)
            # The walk may run past the declared block count (ezc3d ignores it), so
            # read the most a section can hold, bounded by the file.
            section = fh.read(MAX_PARAMETER_BLOCKS * BLOCK_BYTES)
    except OSError as exc:
        raise TakeError(f"take {name}: cannot read ({exc.strerror or exc})") from None
    n_blocks = section[2]
    proc_byte = section[3]
    if proc_byte not in PROCESSORS:
        raise TakeError(
            f"take {name}: not a readable C3D file (processor type {proc_byte}; "
            "the standard knows 84 Intel, 85 DEC, 86 MIPS)"
        )
    dec = _Decoder(proc_byte)
    problems: list[str] = []
    if proc_byte == 86:
        problems.append("MIPS (SGI) processor type, which ezc3d does not read")
    data_start = dec.u16(head, 16)
    # No entry lies in the data section (BTK stops the walk at an offset into it).
    data_at = (data_start - 1) * BLOCK_BYTES - section_at
    limit = data_at if 4 < data_at < len(section) else len(section)
    try:
        params, walk_problems, fix = _walk_parameters(section, dec, n_blocks, limit)
    except ValueError as exc:
        raise TakeError(f"take {name}: not a readable C3D file ({exc})") from None
    problems += walk_problems
    notes = fix.notes
    patches = tuple((section_at + at, raw) for at, raw in fix.patches)
    if zeros:
        # The c3d package would not find the header: only ezc3d reads these.
        notes = leading_notes + notes

    header_points = dec.u16(head, 2)
    header_analog = dec.u16(head, 4)
    first = dec.u16(head, 6)
    last = dec.u16(head, 8)
    header_scale = dec.f32(head, 12)
    header_rate = dec.f32(head, 20)

    used = _param_number(dec, params.get(("POINT", "USED")))
    if used is None:
        n_points = header_points
        if header_points:
            problems.append(
                f"no POINT:USED parameter (ezc3d would read 0 of the header's "
                f"{header_points} points)"
            )
    else:
        n_points = int(used) & 0xFFFF
        if n_points != header_points:
            notes.append(
                f"header says {header_points} points, POINT:USED {n_points}; "
                "POINT:USED used"
            )
    if n_points == 0:
        raise _no_data(name, "no 3D points (POINT:USED and the header say 0)")
    scale = _param_number(dec, params.get(("POINT", "SCALE")))
    is_float = (scale if scale is not None else header_scale) < 0
    word = 4 if is_float else 2

    # Analog words per frame: the header's count, or ANALOG:USED x samples per frame
    # from the rates; the larger bounds the frame (a reader may use either).
    analog_words = header_analog
    analog_used = _param_number(dec, params.get(("ANALOG", "USED")))
    analog_rate = _param_number(dec, params.get(("ANALOG", "RATE")))
    point_rate = _param_number(dec, params.get(("POINT", "RATE")))
    if analog_used and analog_rate and point_rate and point_rate > 0:
        per_frame = analog_rate / point_rate
        if math.isfinite(per_frame) and 0 <= per_frame < 2**16:
            analog_words = max(analog_words, int(analog_used) * int(per_frame))
    frame_bytes = (4 * n_points + analog_words) * word

    counts = [last - first + 1 if last >= first else 0]
    frames_param = _param_number(dec, params.get(("POINT", "FRAMES")))
    if frames_param is not None and math.isfinite(frames_param):
        counts.append(int(frames_param) if frames_param > 0 else 0)
    for trial in ("ACTUAL_END_FIELD",):
        param = params.get(("TRIAL", trial))
        if param is not None and param.type_code == 2 and len(param.data) >= 4:
            end_frame = dec.u16(param.data) + dec.u16(param.data, 2) * 65536
            counts.append(max(0, end_frame - max(first, 1) + 1))
    frames_declared = max(counts)

    data_offset = (data_start - 1) * BLOCK_BYTES if data_start >= 1 else -1
    if data_offset < 0 or data_offset >= size:
        raise _no_data(name, f"data start block {data_start} lies beyond the file")
    frames_present = (size - data_offset) // frame_bytes
    if frames_present == 0:
        raise _no_data(
            name,
            f"no complete frame ({size - data_offset} data bytes, one frame is "
            f"{frame_bytes})",
        )
    ezc3d_frames = counts[1] if len(counts) > 1 and counts[1] else counts[0]
    if ezc3d_frames > frames_present:
        problems.append(
            f"declares {ezc3d_frames} frames but holds {frames_present} complete ones"
        )
    problems += _rotation_problems(dec, params, ezc3d_frames, header_rate, size)
    if frames_declared > frames_present:
        notes.append(
            f"file ends after {frames_present} of {frames_declared} declared frames"
        )
    return C3DLayout(
        path=name,
        size_bytes=size,
        processor=PROCESSORS[proc_byte],
        n_points=n_points,
        frame_bytes=frame_bytes,
        data_offset=data_offset,
        frames_declared=frames_declared,
        frames_present=frames_present,
        header_rate_hz=header_rate if math.isfinite(header_rate) else 0.0,
        first_frame=first - 1 if first else 0,
        is_float=is_float,
        params=params,
        ezc3d_problems=tuple(problems),
        notes=tuple(notes),
        patches=patches,
    )


def param_value(layout: C3DLayout, param: RawParam) -> list[str] | np.ndarray:
    """A raw parameter's value in ezc3d's form.

    Args:
        layout: the file's layout (for the processor's byte order and float format).
        param: the raw parameter.

    Returns:
        Strings as a list (one per column of a 2-D or higher char array, trailing
        spaces stripped), numbers as a flat float64 (floats) or int64 (bytes, int16)
        array in file order.
    """
    if param.type_code == -1:
        if not param.dims:
            return []
        width = param.dims[0]
        text = param.data.decode("latin-1")
        if len(param.dims) == 1:
            return [text.rstrip(" \x00")]
        if width == 0:
            return [""] * math.prod(param.dims[1:])
        return [text[i : i + width].rstrip(" \x00") for i in range(0, len(text), width)]
    big = layout.processor == "MIPS"
    if param.type_code == 1:
        return np.frombuffer(param.data, dtype=np.int8).astype(np.int64)
    if param.type_code == 2:
        return np.frombuffer(param.data, dtype=">i2" if big else "<i2").astype(np.int64)
    if layout.processor == "DEC":
        words = np.frombuffer(param.data, dtype="<u2").reshape(-1, 2)[:, ::-1]
        ieee = np.ascontiguousarray(words).view("<f4").ravel().astype(np.float64)
        return np.where((words[:, 1] & 0x7F80) == 0, 0.0, ieee / 4.0)
    return np.frombuffer(param.data, dtype=">f4" if big else "<f4").astype(np.float64)
