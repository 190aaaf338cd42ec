"""MCAP recordings: the packet envelope, a crash-tolerant reader, recordings as takes.

The file layout (channels, schemas, the envelope) is specified in
``protocols/PROTOCOLS.md``, section "Recordings (MCAP)". In short:

- ``/markers/raw`` and ``/poses``: message encoding ``retargetd.packet``, no schema
  (id 0). Each message is one packet as received, in an envelope (little-endian):
  ``t_ns`` int64 (``time.monotonic_ns()`` at receive), source frame number int64
  (-1 unknown), source timestamp float64 s (NaN unknown), form uint8, kind uint8,
  part count P uint8, input-name length L uint8, the name (UTF-8), P x uint32 part
  sizes, then the parts' bytes, unchanged.
- ``/markers/labels`` and ``/control``: JSON with a JSON Schema.
- the MCAP log time is wall-clock ns since the Unix epoch, derived from ``t_ns`` with
  one anchor pair taken at the start (metadata ``retargetd.recording``), so it never
  jumps when the wall clock is stepped.

:func:`read_recording` walks the file record by record with the ``mcap`` library's
record parsers, and stops cleanly at the first incomplete record: a recorder killed
mid-write leaves a file without footer (and perhaps half a chunk), and everything
before the cut is returned (``Recording.complete`` is False). :func:`read_mcap_take`
decodes a recording's marker packets with the live decoders into a
:class:`~retargetd.replay.take.Take` (``load_take`` on ``.mcap``).
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import math
import os
import struct
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from retargetd.protocols import natnet, natnet_client, osc_in, qtm, zmq_wire
from retargetd.protocols.errors import DecodeError
from retargetd.protocols.marker_input import ACCEPTED, RESTART, LabelSet, MarkerStream
from retargetd.protocols.osc_wire import BUNDLE_TAG, iter_bundle_elements, read_string
from retargetd.replay import points as pts
from retargetd.replay.take import Take, TakeError

logger = logging.getLogger(__name__)

PROFILE = "retargetd"
FORMAT_VERSION = 1
#: Topics.
RAW_TOPIC = "/markers/raw"
LABELS_TOPIC = "/markers/labels"
POSES_TOPIC = "/poses"
CONTROL_TOPIC = "/control"
#: Message encoding of the binary envelope channels.
PACKET_ENCODING = "retargetd.packet"
#: Name of the MCAP metadata record written at the start.
METADATA_NAME = "retargetd.recording"

#: Envelope ``form`` (what sent the packet) ...
FORM_OSC_COMPACT = 1
FORM_OSC_SIMPLE = 2
FORM_ZMQ = 3
FORM_POSE = 4
FORM_NATNET = 5  # one NatNet datagram from Motive, as received (PROTOCOLS.md 9)
FORM_QTM = 6  # one QTM RT packet, header included, as qtm-rt got it (PROTOCOLS.md 10)
FORM_NAMES: dict[int, str] = {
    FORM_OSC_COMPACT: "osc-compact",
    FORM_OSC_SIMPLE: "osc-simple",
    FORM_ZMQ: "zmq",
    FORM_POSE: "pose-stream",
    FORM_NATNET: "natnet",
    FORM_QTM: "qtm",
}
FORM_CODES: dict[str, int] = {name: code for code, name in FORM_NAMES.items()}
#: ... and ``kind`` (what the bytes are, classified by their header).
KIND_OTHER = 0  # anything else, kept as received (malformed packets included)
KIND_FRAME = 1  # marker frame, or pose data message
KIND_LABELS = 2  # label announcement, or pose names message

ENVELOPE = struct.Struct("<qqdBBBB")  # 28 bytes
_PART_SIZE = struct.Struct("<I")
_COMPACT_SOURCE = struct.Struct(">qd")  # at offset 20 of a compact frame
_ZMQ_SOURCE = struct.Struct("<qd")  # at offset 8 of a ZeroMQ frame / pose header
_FRAME_NUMBER_PREFIX = b"/rtd/frame_number\0\0\0"

_MAGIC = b"\x89MCAP0\r\n"
_OP_HEADER, _OP_FOOTER, _OP_SCHEMA, _OP_CHANNEL = 0x01, 0x02, 0x03, 0x04
_OP_MESSAGE, _OP_CHUNK, _OP_DATA_END, _OP_METADATA = 0x05, 0x06, 0x0F, 0x0C


@dataclass(slots=True, eq=False)
class Packet:
    """One enveloped packet of ``/markers/raw`` or ``/poses``.

    Attributes:
        t_ns: ``time.monotonic_ns()`` at receive (recorder's clock).
        source_frame: the sender's frame number, -1 when unknown.
        source_time_s: the sender's timestamp, seconds, NaN when unknown.
        form: ``FORM_*`` code of the input.
        kind: ``KIND_*`` code.
        input: the input's name (``"osc"``, ``"zmq"`` ...).
        parts: the bytes as received: one datagram, or the ZeroMQ message parts.
    """

    t_ns: int
    source_frame: int
    source_time_s: float
    form: int
    kind: int
    input: str
    parts: tuple[bytes, ...]


def classify(form: int, parts: Sequence[bytes]) -> tuple[int, int, float]:
    """Kind, source frame number and source timestamp of a packet, from its header.

    Never raises: bytes that do not parse are ``KIND_OTHER`` (or a frame whose number
    is unknown, -1). Pose-stream data messages (2 parts, 3 with the face part) are
    ``KIND_FRAME``, names messages ``KIND_LABELS``; validation messages (``RTDV``)
    are ``KIND_OTHER``, kept as sent.
    """
    first = parts[0] if parts else b""
    if form == FORM_OSC_COMPACT and len(parts) == 1:
        if first[:12] == b"/rtd/labels\0":
            return KIND_LABELS, -1, math.nan
        if first[:12] == b"/rtd/frame\0\0":
            if len(first) >= 36:
                frame, time_s = _COMPACT_SOURCE.unpack_from(first, 20)
                return KIND_FRAME, frame, time_s
            return KIND_FRAME, -1, math.nan
    elif form == FORM_OSC_SIMPLE and len(parts) == 1:
        if first[:8] == BUNDLE_TAG:
            return KIND_FRAME, _simple_frame_number(first), math.nan
    elif (form == FORM_ZMQ and len(parts) == 2) or (
        form == FORM_POSE and len(parts) in (2, 3)  # a pose with its face part: 3
    ):
        magic = first[:4]
        if magic in (zmq_wire.LABELS_MAGIC, b"RTDN"):
            return KIND_LABELS, -1, math.nan
        if magic in (zmq_wire.FRAME_MAGIC, b"RTDP") and len(first) >= 24:
            frame, time_s = _ZMQ_SOURCE.unpack_from(first, 8)
            return KIND_FRAME, frame, time_s
    elif form == FORM_NATNET and len(parts) == 1:
        return natnet.packet_info(first)  # kinds 1 frame, 2 model defs, 0 other
    elif form == FORM_QTM and len(parts) == 1:
        return qtm.packet_info(first)  # kinds 1 data, 2 parameters XML, 0 other
    return KIND_OTHER, -1, math.nan


def simple_bundle_names(buf: bytes, depth: int = 1) -> list[str]:
    """Marker names of a simple bundle, in order (nested bundles flattened).

    Raises:
        DecodeError: a malformed bundle.
    """
    names: list[str] = []
    if depth > 4:
        raise DecodeError("bad_bundle", "nested too deep")
    for element in iter_bundle_elements(buf):
        data = bytes(element)
        if data[:8] == BUNDLE_TAG:
            names += simple_bundle_names(data, depth + 1)
        elif data[:12] == b"/rtd/marker\0":
            name, _ = read_string(data, 20)
            names.append(name)
    return names


def _simple_frame_number(buf: bytes) -> int:
    at = buf.find(_FRAME_NUMBER_PREFIX)
    if at < 0:
        return -1
    tags = buf[at + 20 : at + 24]
    try:
        if tags == b",h\0\0":
            return int(struct.unpack_from(">q", buf, at + 24)[0])
        if tags == b",i\0\0":
            return int(struct.unpack_from(">i", buf, at + 24)[0])
    except struct.error:
        pass
    return -1


def encode_packet(packet: Packet) -> bytes:
    """The envelope bytes of ``packet`` (see the module docstring)."""
    name = packet.input.encode()
    if len(name) > 255 or not 1 <= len(packet.parts) <= 255:
        raise ValueError(
            f"input name must be <= 255 bytes and parts 1..255; got {len(name)} "
            f"bytes and {len(packet.parts)} parts"
        )
    head = ENVELOPE.pack(
        packet.t_ns, packet.source_frame, packet.source_time_s, packet.form,
        packet.kind, len(packet.parts), len(name),
    )  # fmt: skip
    sizes = b"".join(_PART_SIZE.pack(len(p)) for p in packet.parts)
    return b"".join((head, name, sizes, *packet.parts))


def decode_packet(data: bytes) -> Packet:
    """Inverse of :func:`encode_packet`.

    Raises:
        ValueError: the bytes are not a whole envelope.
    """
    if len(data) < ENVELOPE.size:
        raise ValueError(f"packet envelope of {len(data)} bytes < {ENVELOPE.size}")
    t_ns, frame, time_s, form, kind, n_parts, name_len = ENVELOPE.unpack_from(data)
    offset = ENVELOPE.size
    name = data[offset : offset + name_len].decode()
    offset += name_len
    sizes = struct.unpack_from(f"<{n_parts}I", data, offset)
    offset += 4 * n_parts
    parts = []
    for size in sizes:
        parts.append(data[offset : offset + size])
        offset += size
    if offset != len(data):
        raise ValueError(f"packet envelope sizes add up to {offset}, not {len(data)}")
    return Packet(t_ns, frame, time_s, form, kind, name, tuple(parts))


# ---- reading ---------------------------------------------------------------------


@dataclass(slots=True, eq=False)
class Message:
    """One message of a recording: topic, MCAP times (ns since the epoch) and data."""

    topic: str
    log_time_ns: int
    publish_time_ns: int
    sequence: int
    data: bytes


@dataclass(slots=True, eq=False)
class Recording:
    """What :func:`read_recording` found.

    Attributes:
        path: the file.
        complete: True when the file ends with a footer (a clean close).
        profile: the MCAP header's profile.
        metadata: MCAP metadata records by name.
        channels: channel id -> (topic, message encoding, channel metadata).
        messages: every message in file order.
        stop_reason: why reading stopped early ("" when complete).
        bytes_read: offset of the end of the last whole record.
    """

    path: str
    complete: bool = False
    profile: str = ""
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    channels: dict[int, tuple[str, str, dict[str, str]]] = field(default_factory=dict)
    messages: list[Message] = field(default_factory=list)
    stop_reason: str = ""
    bytes_read: int = 0

    def topic(self, topic: str) -> list[Message]:
        """Messages of one topic, in file order."""
        return [m for m in self.messages if m.topic == topic]

    def packets(self, topic: str = RAW_TOPIC) -> list[Packet]:
        """Decoded envelopes of ``/markers/raw`` (or ``/poses``)."""
        return [decode_packet(m.data) for m in self.messages if m.topic == topic]

    def json(self, topic: str) -> list[dict[str, Any]]:
        """Decoded JSON messages of ``/markers/labels`` or ``/control``."""
        return [json.loads(m.data) for m in self.messages if m.topic == topic]

    def inputs(self) -> list[dict[str, Any]]:
        """The inputs declared in the recording's metadata.

        Raises:
            TakeError: the metadata's ``inputs`` is not a JSON list of objects.
        """
        meta = self.metadata.get(METADATA_NAME, {})
        try:
            inputs = json.loads(meta.get("inputs", "[]"))
        except ValueError as exc:  # JSONDecodeError, or a number too long to parse
            raise TakeError(f"recording {self.path}: bad inputs metadata") from exc
        if not isinstance(inputs, list) or not all(isinstance(i, dict) for i in inputs):
            raise TakeError(f"recording {self.path}: inputs metadata is not a list")
        return inputs


def read_recording(path: str | os.PathLike[str]) -> Recording:
    """Read an MCAP recording, tolerating a missing end (killed recorder).

    Records are framed (opcode, length) and read whole; the first record that is cut
    short ends the read, and what came before is returned. Record contents are
    parsed by the ``mcap`` library (chunks decompressed and CRC-checked).

    Raises:
        TakeError: not an MCAP file, or unreadable.
    """
    from mcap import records as mr
    from mcap.data_stream import ReadDataStream
    from mcap.stream_reader import breakup_chunk

    name = str(path)
    rec = Recording(path=name)
    try:
        f = open(path, "rb")  # noqa: SIM115 (closed below; the loop is long)
    except OSError as exc:
        raise TakeError(f"recording {name}: cannot read ({exc.strerror})") from None
    with f:
        size = os.fstat(f.fileno()).st_size
        if f.read(8) != _MAGIC:
            raise TakeError(f"recording {name}: not an MCAP file (bad magic)")
        offset = 8
        while True:
            head = f.read(9)
            if len(head) < 9:
                rec.stop_reason = "end of file without a footer"
                break
            opcode, length = struct.unpack("<BQ", head)
            # A length past the end of the file (a torn or damaged record) is never
            # read: f.read of 2^63 bytes raises MemoryError or OverflowError.
            body = f.read(length) if length <= size - offset - 9 else b""
            if len(body) < length:
                rec.stop_reason = f"record cut short at byte {offset}"
                break
            offset += 9 + length
            stream = ReadDataStream(io.BytesIO(body))
            try:
                if opcode == _OP_CHUNK:
                    inner = breakup_chunk(mr.Chunk.read(stream), validate_crc=True)
                elif opcode == _OP_MESSAGE:
                    inner = [mr.Message.read(stream, length)]
                elif opcode == _OP_SCHEMA:
                    inner = [mr.Schema.read(stream)]
                elif opcode == _OP_CHANNEL:
                    inner = [mr.Channel.read(stream)]
                elif opcode == _OP_METADATA:
                    inner = [mr.Metadata.read(stream)]
                elif opcode == _OP_HEADER:
                    rec.profile = mr.Header.read(stream).profile
                    inner = []
                elif opcode in (_OP_DATA_END, _OP_FOOTER):
                    rec.complete = True
                    rec.bytes_read = offset
                    break  # the summary repeats what the data section held
                else:
                    inner = []
            except Exception as exc:  # a damaged record: keep what came before
                rec.stop_reason = f"bad record at byte {offset}: {exc}"
                break
            rec.bytes_read = offset
            for r in inner:
                _take_record(rec, r)
    if not rec.complete:
        logger.warning("recording %s is incomplete: %s", name, rec.stop_reason)
    return rec


def _take_record(rec: Recording, record: Any) -> None:
    from mcap import records as mr

    if isinstance(record, mr.Message):
        channel = rec.channels.get(record.channel_id)
        topic = channel[0] if channel else f"#{record.channel_id}"
        rec.messages.append(
            Message(
                topic, record.log_time, record.publish_time, record.sequence,
                bytes(record.data),
            )
        )  # fmt: skip
    elif isinstance(record, mr.Channel):
        rec.channels[record.id] = (
            record.topic, record.message_encoding, dict(record.metadata)
        )  # fmt: skip
    elif isinstance(record, mr.Metadata):
        rec.metadata[record.name] = dict(record.metadata)


# ---- recordings as takes ----------------------------------------------------------


def main_input(rec: Recording) -> str:
    """The marker input with the most recorded frames.

    Raises:
        TakeError: the recording holds no marker frames.
    """
    counts: dict[str, int] = {}
    for p in rec.packets():
        if p.kind == KIND_FRAME and p.form != FORM_POSE:
            counts[p.input] = counts.get(p.input, 0) + 1
    if not counts:
        raise TakeError(f"recording {rec.path}: no marker frames recorded")
    return max(counts, key=lambda k: counts[k])


def _simple_label_set(rec: Recording, input_name: str) -> LabelSet:
    sets = [
        m for m in rec.json(LABELS_TOPIC) if m.get("input") == input_name
    ]  # the recorder extends the set as names appear: the last one holds them all
    if not sets:
        return LabelSet(0, ())
    return LabelSet(int(sets[-1]["label_set_id"]), tuple(sets[-1]["labels"]))


def read_mcap_take(
    path: str | os.PathLike[str],
    *,
    subject: str | None = None,
    units: str | None = None,
    up_axis: str | None = None,
) -> Take:
    """Load a recording's marker frames as a take in world metres.

    The main marker input's packets are fed, in recorded order, through the live
    decoders and frame sequencer (``MarkerStream``), so the take holds exactly the
    frames the daemon would accept. Columns are every label seen, in first-seen
    order (a label-set change adds columns; frames without a label hold NaN). The
    input's declared units and up axis (recording metadata; ``m``, ``+Z`` by
    default) convert to the world; ``units``/``up_axis`` override them.

    Args:
        path: the ``.mcap`` file (a file cut short by a crash is fine).
        subject: the subject to load (labels ``Name:MARKER``).
        units: override of the input's declared length unit.
        up_axis: override of the input's declared up axis.

    Returns:
        The take; rate from the source timestamps (else the receive times).

    Raises:
        TakeError: not a recording, no marker frames, bad override or subject, or a
            record whose contents are damaged (a packet envelope, the declared units
            or up axis).
    """
    try:
        return _read_mcap_take(path, subject, units, up_axis)
    except TakeError:
        raise
    except ValueError as exc:  # a damaged envelope or declared input (checked CRCs
        # do not cover unchunked records, and a chunk's CRC may be 0: unchecked)
        raise TakeError(f"recording {path}: damaged: {exc}") from exc


def _read_mcap_take(
    path: str | os.PathLike[str],
    subject: str | None,
    units: str | None,
    up_axis: str | None,
) -> Take:
    name = str(path)
    rec = read_recording(path)
    input_name = main_input(rec)
    declared = next((i for i in rec.inputs() if i.get("name") == input_name), {})
    form_name = declared.get("form", "") or next(
        (FORM_NAMES.get(p.form, "") for p in rec.packets() if p.input == input_name),
        "",
    )  # an input the metadata does not list: its packets' form
    simple = form_name == "osc-simple"
    # Decode in the capture frame (identity, metres): units and axes are applied by
    # assemble_take, as for the other formats, so overrides work the same way.
    stream = MarkerStream(_simple_label_set(rec, input_name) if simple else None)
    columns: dict[str, int] = {}
    rows: list[tuple[np.ndarray, np.ndarray]] = []
    frame_ids: list[int] = []
    times_s: list[float] = []
    t_ns: list[int] = []
    # A capture system's packets (Motive, QTM) go through the live input, control
    # packets included: it converts to world metres itself (NatNet's up axis is not
    # in the stream: the recording's declared one, or the override).
    capture = _capture_input(
        form_name, up_axis or declared.get("up", "+Y"), declared.get("endpoint", "")
    )
    for p in rec.packets():
        if p.input != input_name:
            continue
        if capture is not None:
            if len(p.parts) != 1 or capture.feed(p.parts[0], p.t_ns) not in (
                ACCEPTED,
                RESTART,
            ):
                continue
            stream = capture.stream
        elif p.kind == KIND_LABELS:
            try:
                if p.form == FORM_ZMQ:
                    stream.set_labels(
                        zmq_wire.decode_zmq_labels(p.parts[0], p.parts[1]), p.t_ns
                    )
                else:
                    stream.set_labels(osc_in.decode_labels(p.parts[0]), p.t_ns)
            except DecodeError:
                pass
            continue
        else:
            if p.kind != KIND_FRAME:
                continue
            if p.form == FORM_ZMQ:
                code = stream.feed(zmq_wire.decode_zmq_frame, *p.parts, t_ns=p.t_ns)
            elif p.form == FORM_OSC_SIMPLE:
                code = stream.feed(osc_in.decode_simple_bundle, p.parts[0], t_ns=p.t_ns)
            else:
                code = stream.feed(osc_in.decode_compact_frame, p.parts[0], t_ns=p.t_ns)
            if code not in (ACCEPTED, RESTART):
                continue
        frame = stream.current.frame
        cols = np.array(
            [
                columns.setdefault(lb, len(columns))
                for lb in stream.current.label_set.labels
            ],
            dtype=np.int64,
        )
        rows.append((cols, frame.markers_world.copy()))
        frame_ids.append(frame.frame_id)
        times_s.append(frame.source_time_s)
        t_ns.append(p.t_ns)
    if not rows:
        raise TakeError(f"recording {name}: no decodable marker frames")
    points = np.full((len(rows), len(columns), 3), np.nan)
    for i, (cols, xyz) in enumerate(rows):
        points[i, cols] = xyz
    valid = np.asarray(np.isfinite(points).all(axis=-1), dtype=bool)
    if capture is not None:  # already world metres (the input converted them)
        unit = pts.resolve_units(name, None, "m", "file (capture input)", "m", "m")
        up = pts.Resolved("+Z", "file (capture input, converted)")
    else:
        unit = pts.resolve_units(
            name, units, declared.get("units", "m"), "file (recording input)", "m",
            "default (m)",
        )  # fmt: skip
        up = pts.resolve_up_axis(name, up_axis) or pts.Resolved(
            declared.get("up", "+Z"), "file (recording input)"
        )
    return pts.assemble_take(
        path=name,
        fmt="mcap",
        labels=list(columns),
        points=points,
        valid=valid,
        subject=subject,
        units=unit,
        up_axis=up,
        rate_hz=_rate_hz(frame_ids, times_s, t_ns),
        first_frame=max(frame_ids[0], 0),
        manufacturer=rec.metadata.get(METADATA_NAME, {}).get("software", ""),
    )


def _capture_input(form_name: str, up_axis: str, endpoint: str = "") -> Any:
    """The live input of a capture system's recording (``natnet``, ``qtm``), fed the
    recorded packets socket-free; None for the other forms. A NatNet recording's
    source URL (``endpoint``) gives the marker sets and the labelling it was read
    with (``sets``, ``subjects``)."""
    if form_name == "natnet":
        from retargetd.protocols.conventions import normalize_up_axis

        sets, subjects = None, False
        if endpoint.startswith("natnet://"):
            with contextlib.suppress(ValueError):  # a URL of another version
                opts = natnet_client.parse_natnet_url(endpoint)
                sets, subjects = opts.sets, opts.subjects
        return natnet_client.NatNetInput(
            None, normalize_up_axis(up_axis), sets=sets, subjects=subjects,
            out=logger.info,
        )  # fmt: skip
    if form_name == "qtm":
        return qtm.QtmInput(None, out=logger.info)
    return None


def _rate_hz(frame_ids: list[int], times_s: list[float], t_ns: list[int]) -> float:
    """Frames per second: median source-time step per frame number, else receive."""
    frames = np.asarray(frame_ids, dtype=np.float64)
    steps = np.diff(frames) if (frames >= 0).all() else np.ones(len(frames) - 1)
    for stamps in (np.asarray(times_s), np.asarray(t_ns, dtype=np.float64) * 1e-9):
        d = np.diff(stamps)
        ok = np.isfinite(d) & (d > 0) & (steps > 0)
        if ok.any():
            return float(1.0 / np.median(d[ok] / steps[ok]))
    return 1.0


def recording_summary(rec: Recording) -> dict[str, Any]:
    """Counts per topic and kind, duration and completeness (for the CLI)."""
    counts: dict[str, int] = {}
    for m in rec.messages:
        counts[m.topic] = counts.get(m.topic, 0) + 1
    times = [m.log_time_ns for m in rec.messages]
    return {
        "file": rec.path,
        "complete": rec.complete,
        "messages": counts,
        "seconds": (max(times) - min(times)) * 1e-9 if times else 0.0,
    }
