"""OptiTrack Motive as a marker source: NatNet 3.x and 4.x, decoded by ourselves.

Layout source: NaturalPoint's NatNet SDK 4.x samples, the direct-depacketization
clients ``PacketClient.cpp`` and ``NatNetClient.py`` ("OptiTrack NatNet direct
depacketization library for Python 3.x", SDK 4.1-4.3), which are the vendor's published
description of the bitstream. Everything is little-endian. A packet is::

    uint16 message id | uint16 payload bytes | payload

Frame of data (``NAT_FRAMEOFDATA`` = 7), payload, NatNet 3.0 and later. Each list is an
int32 count followed, from NatNet 4.1 on, by an int32 byte size of the list's items:

- int32 frame number;
- marker sets: per set a NUL-terminated name, int32 marker count, count x 3 float32;
- legacy "other" markers: count x 3 float32;
- rigid bodies: 38 bytes each (int32 id, 3 float32 position, 4 float32 quaternion,
  float32 mean error, int16 params);
- skeletons: int32 id, int32 rigid-body count, rigid bodies as above;
- assets (4.1 and later only): skipped by their byte size;
- labelled markers: 26 bytes each (int32 id = model id << 16 | marker id, 3 float32
  position, float32 size, int16 params: 0x01 occluded, 0x02 point-cloud solved,
  0x04 model solved; float32 residual in metres);
- force plates and devices: int32 id, int32 channel count, per channel an int32 frame
  count and as many float32;
- suffix: uint32 SMPTE timecode, uint32 timecode subframe, float64 timestamp (s),
  3 x uint64 high-resolution stamps, (4.1 and later, when present: 2 x uint32
  precision timestamp), int16 params.

Model definitions (``NAT_MODELDEF`` = 5): int32 count, then per description an int32
type (0 marker set, 1 rigid body, 2 skeleton, 3 force plate, 4 device, 5 camera,
6 asset), from 4.1 on an int32 byte size, then the description. A marker set is its
NUL-terminated name, an int32 count and as many NUL-terminated marker names; rigid
bodies and skeletons start with their name and int32 id.

Units and axes: Motive streams metres; its up axis is a streaming setting ("Up Axis",
Y by default) that the stream does not announce, so it is configured here
(``up_axis``). Positions are converted once, at the input, like every other source.

What we read: the marker-set markers (named by the model definitions, in their order)
and, for those, the labelled-marker flags (occluded) and residuals; the frame number,
timestamp and timecode. Rigid bodies, skeleton bones, force plates and devices are
skipped. Why our own decoder rather than the PyPI ``natnet`` package:
``protocols/PROTOCOLS.md`` section 9 (benchmark ``bench/bench_natnet.py``).

The sockets, the session and the loop input are in ``protocols/natnet_client.py``.
"""

from __future__ import annotations

import ipaddress
import logging
import math
import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from retargetd.protocols.errors import DecodeError
from retargetd.protocols.frames import F64Array
from retargetd.protocols.marker_input import REASON_INDEX, LabelSet, MarkerPacket

logger = logging.getLogger(__name__)

# Message ids (NatNet SDK samples).
NAT_CONNECT = 0
NAT_SERVERINFO = 1
NAT_REQUEST = 2
NAT_RESPONSE = 3
NAT_REQUEST_MODELDEF = 4
NAT_MODELDEF = 5
NAT_REQUEST_FRAMEOFDATA = 6
NAT_FRAMEOFDATA = 7
NAT_MESSAGESTRING = 8
NAT_DISCONNECT = 9
NAT_KEEPALIVE = 10
NAT_UNRECOGNIZED_REQUEST = 100

#: Motive's defaults (NatNet SDK samples and Motive's streaming pane).
DEFAULT_COMMAND_PORT = 1510
DEFAULT_DATA_PORT = 1511
DEFAULT_MULTICAST_GROUP = "239.255.42.99"

#: NatNet major versions this decoder reads; others are ``bad_version``.
SUPPORTED_MAJORS = (3, 4)

#: Labelled-marker params bit: the marker is occluded (PacketClient.cpp).
MARKER_OCCLUDED = 0x01
#: Frame-suffix params bits (PacketClient.cpp): recording, tracked models changed.
FRAME_RECORDING = 0x01
FRAME_MODELS_CHANGED = 0x02

DESC_MARKER_SET = 0
DESC_RIGID_BODY = 1
DESC_SKELETON = 2

_HEADER = struct.Struct("<HH")
_I32 = struct.Struct("<i")
_I32_2 = struct.Struct("<ii")
_I16 = struct.Struct("<h")
_LABELED = struct.Struct("<i16xhf")  # id, (position, size skipped), params, residual
_SUFFIX = struct.Struct("<IId")  # timecode, subframe, timestamp
_RIGID_BODY_SIZE = 38
_LABELED_SIZE = 26
_SUFFIX_MIN = 4 + 4 + 8 + 24 + 2  # 3.0-4.x, without the optional precision stamps
_LE_F32 = np.dtype("<f4")
#: Largest marker count believed in one list: the SDK sample's own sanity limit.
MAX_LIST_COUNT = 10000

Buffer = bytes | bytearray | memoryview
COUNT_MISMATCH = REASON_INDEX["count_mismatch"]


@dataclass(frozen=True, slots=True)
class Version:
    """A NatNet bitstream version (major, minor)."""

    major: int
    minor: int

    @property
    def sized_lists(self) -> bool:
        """True from NatNet 4.1 on: every list carries its byte size."""
        return (self.major, self.minor) >= (4, 1)

    def __str__(self) -> str:
        return f"{self.major}.{self.minor}"


@dataclass(frozen=True, slots=True)
class ServerInfo:
    """The answer to ``NAT_CONNECT`` (``sSender_Server`` in the SDK samples).

    Attributes:
        app_name: the server application ("Motive").
        app_version: its version, 4 bytes.
        natnet_version: the bitstream version it streams.
        data_port: the data port it announces (0 when the packet is too short).
        multicast: True when it streams multicast.
        multicast_group: the group address ("" when unicast or not announced).
    """

    app_name: str
    app_version: tuple[int, int, int, int]
    natnet_version: Version
    data_port: int = 0
    multicast: bool = False
    multicast_group: str = ""


@dataclass(frozen=True, slots=True)
class ModelDefs:
    """What the model definitions tell us.

    Attributes:
        version: the bitstream version they were decoded with.
        marker_sets: (set name, marker names) in the server's order.
        model_ids: model name -> id, for rigid bodies, skeletons and assets.
    """

    version: Version
    marker_sets: tuple[tuple[str, tuple[str, ...]], ...]
    model_ids: dict[str, int] = field(default_factory=dict)


#: The bitstream version a client asks for by default (the SDK 4.1 samples').
REQUESTED_VERSION = Version(4, 1)


def read_header(buf: Buffer) -> tuple[int, int]:
    """Message id and payload size of a NatNet packet.

    Raises:
        DecodeError: ``bad_length`` when shorter than its header or its payload.
    """
    if len(buf) < 4:
        raise DecodeError("bad_length", f"{len(buf)} bytes < 4-byte header")
    msg_id, nbytes = _HEADER.unpack_from(buf, 0)
    if len(buf) < 4 + nbytes:
        raise DecodeError("bad_length", f"{len(buf)} bytes for a {nbytes}-byte payload")
    return msg_id, nbytes


def _cstring(buf: Buffer, offset: int, end: int) -> tuple[str, int]:
    """A NUL-terminated UTF-8 string at ``offset`` (not on the hot path)."""
    raw = bytes(buf[offset:end])
    nul = raw.find(b"\0")
    if nul < 0:
        raise DecodeError("bad_string", "unterminated string")
    try:
        return raw[:nul].decode(), offset + nul + 1
    except UnicodeDecodeError as exc:
        raise DecodeError("bad_string", "string is not UTF-8") from exc


def decode_server_info(buf: Buffer) -> ServerInfo:
    """Decode a ``NAT_SERVERINFO`` packet (the reply to ``NAT_CONNECT``).

    Layout: char[256] name, uint8[4] app version, uint8[4] NatNet version; NatNet 3.0
    and later add uint64 clock frequency, uint16 data port, uint8 multicast flag and
    uint8[4] multicast group.

    Raises:
        DecodeError: ``bad_length``, ``bad_address`` (not a server info packet),
            ``bad_string``.
    """
    msg_id, nbytes = read_header(buf)
    if msg_id != NAT_SERVERINFO:
        raise DecodeError("bad_address", f"message {msg_id}, expected server info")
    if nbytes < 264:
        raise DecodeError("bad_length", f"server info of {nbytes} bytes < 264")
    name, _ = _cstring(buf, 4, 4 + 256)
    app = tuple(buf[260:264])
    nn = tuple(buf[264:268])
    info = ServerInfo(name, (app[0], app[1], app[2], app[3]), Version(nn[0], nn[1]))
    if nbytes >= 264 + 8 + 2 + 1 + 4:
        (port,) = struct.unpack_from("<H", buf, 4 + 272)
        multicast = bool(buf[4 + 274])
        group = str(ipaddress.IPv4Address(bytes(buf[4 + 275 : 4 + 279])))
        info = ServerInfo(
            info.app_name,
            info.app_version,
            info.natnet_version,
            port,
            multicast,
            group if multicast else "",
        )
    return info


def decode_model_defs(buf: Buffer, version: Version) -> ModelDefs:
    """Decode a ``NAT_MODELDEF`` packet (not hot: Python objects are fine).

    Marker sets, rigid-body and skeleton names and ids are read; before NatNet 4.1
    (descriptions carry no size) decoding stops at the first description that is
    neither a marker set, a rigid body nor a skeleton (Motive sends those first).

    Raises:
        DecodeError: ``bad_version``, ``bad_length``, ``bad_address``, ``bad_count``,
            ``bad_string``.
    """
    _check_version(version)
    msg_id, nbytes = read_header(buf)
    if msg_id != NAT_MODELDEF:
        raise DecodeError("bad_address", f"message {msg_id}, expected model defs")
    end = 4 + nbytes
    try:
        (count,) = _I32.unpack_from(buf, 4)
    except struct.error as exc:
        raise DecodeError("bad_length", "model defs without a count") from exc
    if not 0 <= count <= MAX_LIST_COUNT:
        raise DecodeError("bad_count", f"{count} descriptions")
    off = 8
    sets: list[tuple[str, tuple[str, ...]]] = []
    ids: dict[str, int] = {}
    try:
        for _ in range(count):
            (kind,) = _I32.unpack_from(buf, off)
            off += 4
            next_off = -1
            if version.sized_lists:
                (size,) = _I32.unpack_from(buf, off)
                off += 4
                next_off = off + size
                if size < 0 or next_off > end:
                    raise DecodeError("bad_length", f"description of {size} bytes")
            if kind == DESC_MARKER_SET:
                name, off = _cstring(buf, off, end)
                (n,) = _I32.unpack_from(buf, off)
                off += 4
                if not 0 <= n <= MAX_LIST_COUNT:
                    raise DecodeError("bad_count", f"marker set {name!r}: {n} markers")
                names = []
                for _ in range(n):
                    marker, off = _cstring(buf, off, end)
                    names.append(marker)
                sets.append((name, tuple(names)))
            elif kind in (DESC_RIGID_BODY, DESC_SKELETON, 6):
                name, off2 = _cstring(buf, off, end)
                if kind == 6:  # asset: name, int32 type, int32 id
                    off2 += 4
                (model_id,) = _I32.unpack_from(buf, off2)
                ids[name] = model_id
                if next_off < 0:
                    off = _skip_unsized_description(buf, kind, off2 + 4, version, end)
            elif next_off < 0:
                break  # unsized force plate / device / camera: nothing after we need
            if next_off >= 0:
                off = next_off
    except struct.error as exc:
        raise DecodeError("bad_length", "model defs cut short") from exc
    return ModelDefs(version, tuple(sets), ids)


def _skip_rigid_body_desc(buf: Buffer, off: int, version: Version, end: int) -> int:
    """Skip a rigid-body description body after its name and id (NatNet 3.0-4.0)."""
    off += 4 + 12  # parent id, offset
    (n,) = _I32.unpack_from(buf, off)
    off += 4 + 12 * n + 4 * n  # marker offsets, active labels
    if version.major >= 4:
        for _ in range(n):
            _, off = _cstring(buf, off, end)
    return off


def _skip_unsized_description(
    buf: Buffer, kind: int, off: int, version: Version, end: int
) -> int:
    if kind == DESC_RIGID_BODY:
        return _skip_rigid_body_desc(buf, off, version, end)
    # skeleton: int32 rigid-body count, each a rigid-body description with name + id
    (n,) = _I32.unpack_from(buf, off)
    off += 4
    for _ in range(n):
        _, off = _cstring(buf, off, end)
        off = _skip_rigid_body_desc(buf, off + 4, version, end)
    return off


def _check_version(version: Version) -> None:
    if version.major not in SUPPORTED_MAJORS:
        raise DecodeError(
            "bad_version",
            f"NatNet {version}; this decoder reads "
            + " and ".join(f"{m}.x" for m in SUPPORTED_MAJORS),
        )


def label_set_from_models(
    models: ModelDefs,
    label_set_id: int,
    sets: Sequence[str] | None = None,
    subjects: bool = False,
) -> LabelSet:
    """The label set of the marker sets in ``models``.

    Labels are the marker names, with the ``<set>_`` prefix Motive gives skeleton
    markers removed; a name already taken by an earlier set becomes ``<set>:<name>``.
    Motive's aggregate set ``all`` is left out.

    Args:
        models: decoded model definitions.
        label_set_id: the id to give the set (a new one whenever the names change).
        sets: the marker sets to use (all but ``all`` when None).
        subjects: every label is ``<set>:<name>`` (the subject convention several
            performers on one daemon split by; ``natnet://...?subjects=1``).
    """
    labels: list[str] = []
    taken: set[str] = set()
    for set_name, names in _chosen_sets(models, sets):
        prefix = set_name + "_"
        for name in names:
            label = name[len(prefix) :] if name.startswith(prefix) else name
            if subjects or label in taken:
                label = f"{set_name}:{label}"
            taken.add(label)
            labels.append(label)
    return LabelSet(label_set_id, tuple(labels))


def _chosen_sets(
    models: ModelDefs, sets: Sequence[str] | None
) -> list[tuple[str, tuple[str, ...]]]:
    if sets is None:
        return [(n, m) for n, m in models.marker_sets if n.lower() != "all"]
    wanted = set(sets)
    return [(n, m) for n, m in models.marker_sets if n in wanted]


class NatNetDecoder:
    """Decodes frames of one NatNet server, for one set of model definitions.

    Built off the hot path whenever the model definitions (or the version) change;
    :meth:`decode_natnet_frame` is the hot path. Besides the :class:`MarkerPacket`
    it keeps the last decoded frame's timecode and residuals.

    Args:
        models: the server's model definitions (their version is the bitstream's).
        label_set: from :func:`label_set_from_models` with the same ``sets``.
        sets: the marker sets to read (all but ``all`` when None).

    Attributes:
        timecode: SMPTE timecode of the last decoded frame (packed uint32, as sent).
        timecode_sub: its subframe.
        residuals_m: (n,) float64, metres, the labelled-marker residual of each label
            in the last decoded frame (NaN when not reported).
        models_changed: the last frame's "tracked models changed" flag (the suffix
            params, read as the packet's last int16): request the model definitions
            again (:meth:`NatNetClient.request_models`).
    """

    def __init__(
        self,
        models: ModelDefs,
        label_set: LabelSet,
        sets: Sequence[str] | None = None,
    ) -> None:
        _check_version(models.version)
        self.version = models.version
        self.label_set = label_set
        self._sized = models.version.sized_lists
        # name + NUL -> (first row, marker count), in the server's order.
        self._sets: dict[bytes, tuple[int, int]] = {}
        self._row_of_id: dict[int, int] = {}
        row = 0
        for set_name, names in _chosen_sets(models, sets):
            self._sets[set_name.encode() + b"\0"] = (row, len(names))
            model_id = models.model_ids.get(set_name)
            if model_id is not None:
                for k in range(len(names)):
                    # Marker ids within a model are 1-based (PacketClient DecodeID).
                    self._row_of_id[(model_id << 16) | (k + 1)] = row + k
            row += len(names)
        if row != len(label_set.labels):
            raise ValueError(f"label set has {len(label_set.labels)} labels, not {row}")
        self._expected = list(self._sets)
        self.timecode = 0
        self.timecode_sub = 0
        self.models_changed = False
        self.residuals_m: F64Array = np.full(row, np.nan)

    def __call__(self, buf: Buffer, out: MarkerPacket) -> MarkerPacket:
        return self.decode_natnet_frame(buf, out)

    def _list(self, buf: Buffer, off: int, end: int) -> tuple[int, int, int]:
        """(count, offset of the first item, byte size or -1) of a list at ``off``."""
        if off + 4 > end:
            raise DecodeError("bad_length", "frame cut short")
        (count,) = _I32.unpack_from(buf, off)
        off += 4
        size = -1
        if self._sized:
            if off + 4 > end:
                raise DecodeError("bad_length", "frame cut short")
            (size,) = _I32.unpack_from(buf, off)
            off += 4
            if size < 0 or off + size > end:
                raise DecodeError("bad_length", f"list of {size} bytes")
        if not 0 <= count <= MAX_LIST_COUNT:
            raise DecodeError("bad_count", f"list of {count} items")
        return count, off, size

    def decode_natnet_frame(self, buf: Buffer, out: MarkerPacket) -> MarkerPacket:
        """Decode a ``NAT_FRAMEOFDATA`` packet into ``out`` (the hot path).

        Args:
            buf: one UDP datagram.
            out: packet allocated for ``self.label_set`` (positions are converted with
                its ``world_from_capture_scaled_mat``: metres, the configured up axis).

        Returns:
            ``out``: ``frame.frame_id`` (Motive's frame number),
            ``frame.source_time_s`` (Motive's timestamp), ``frame.markers_world``
            (n, 3) float64 metres world, NaN rows = occluded, ``frame.valid``;
            ``unknown_labels`` counts markers of sets not in the label set.

        Raises:
            DecodeError: ``bad_length`` (truncated or inconsistent sizes),
                ``bad_address`` (not a frame), ``bad_count``, ``bad_string``,
                ``unknown_label_set`` (``out`` is for another label set),
                ``count_mismatch`` (a set's marker count differs from the model
                definitions: request them again), ``bad_frame_number`` or
                ``non_finite``. Nothing is written into ``out`` unless the whole
                packet is good.
        """
        size = len(buf)
        if size < 8:
            raise DecodeError("bad_length", f"{size} bytes")
        msg_id, nbytes = _HEADER.unpack_from(buf, 0)
        if msg_id != NAT_FRAMEOFDATA:
            raise DecodeError("bad_address", f"message {msg_id}, expected a frame")
        end = 4 + nbytes
        if end > size:
            raise DecodeError("bad_length", f"{size} bytes for a {nbytes}-byte payload")
        if out.label_set is not self.label_set and out.label_set != self.label_set:
            raise DecodeError("unknown_label_set", "packet is for another label set")
        (frame_id,) = _I32.unpack_from(buf, 4)
        staged = out._staged
        staged.fill(np.nan)
        unknown = 0
        # Marker sets.
        count, off, list_size = self._list(buf, 8, end)
        list_end = off + list_size
        expected, sets = self._expected, self._sets
        for i in range(count):
            name = expected[i] if i < len(expected) else b""
            n_name = len(name)
            if not (name and buf[off : off + n_name] == name):
                # Not the set expected here: find its name the slow way.
                nul = bytes(buf[off : min(end, off + 256)]).find(b"\0")
                if nul < 0:
                    raise DecodeError("bad_string", "unterminated marker-set name")
                name = bytes(buf[off : off + nul + 1])
                n_name = nul + 1
            off += n_name
            if off + 4 > end:
                raise DecodeError("bad_length", "frame cut short")
            (n,) = _I32.unpack_from(buf, off)
            off += 4
            if not 0 <= n <= MAX_LIST_COUNT or off + 12 * n > end:
                raise DecodeError("bad_count", f"marker set of {n} markers")
            place = sets.get(name)
            if place is None:
                unknown += n
            else:
                row, m = place
                if n != m:
                    raise DecodeError(
                        "count_mismatch", f"{n} markers, model definitions say {m}"
                    )
                staged[row : row + m] = np.frombuffer(buf, _LE_F32, 3 * m, off).reshape(
                    m, 3
                )
            off += 12 * n
        if list_size >= 0 and off != list_end:
            raise DecodeError("bad_length", "marker-set list size disagrees")
        # Legacy other markers, rigid bodies, skeletons, assets.
        count, off, list_size = self._list(buf, off, end)
        off = self._skip(off, list_size, 12 * count, end)
        count, off, list_size = self._list(buf, off, end)
        off = self._skip(off, list_size, _RIGID_BODY_SIZE * count, end)
        count, off, list_size = self._list(buf, off, end)
        if list_size >= 0:
            off += list_size
        else:
            for _ in range(count):
                if off + 8 > end:
                    raise DecodeError("bad_length", "frame cut short")
                _, n_rb = _I32_2.unpack_from(buf, off)
                if not 0 <= n_rb <= MAX_LIST_COUNT:
                    raise DecodeError("bad_count", f"skeleton of {n_rb} bodies")
                off += 8 + _RIGID_BODY_SIZE * n_rb
        if self._sized:
            count, off, list_size = self._list(buf, off, end)
            off += list_size
        # Labelled markers: occlusion flags and residuals of our rows.
        count, off, list_size = self._list(buf, off, end)
        if off + _LABELED_SIZE * count > end:
            raise DecodeError("bad_length", "labelled markers cut short")
        if list_size >= 0 and list_size != _LABELED_SIZE * count:
            raise DecodeError("bad_length", "labelled-marker list size disagrees")
        residuals = self.residuals_m
        row_of_id = self._row_of_id
        occluded_rows = 0
        if row_of_id:
            residuals.fill(np.nan)
            for k in range(count):
                marker_id, params, residual = _LABELED.unpack_from(
                    buf, off + _LABELED_SIZE * k
                )
                r = row_of_id.get(marker_id)
                if r is not None:
                    residuals[r] = residual
                    if params & MARKER_OCCLUDED:
                        staged[r] = np.nan
                        occluded_rows += 1
        off += _LABELED_SIZE * count
        # Force plates and devices: same shape.
        for _ in range(2):
            count, off, list_size = self._list(buf, off, end)
            if list_size >= 0:
                off += list_size
                continue
            for _ in range(count):
                if off + 8 > end:
                    raise DecodeError("bad_length", "frame cut short")
                _, n_ch = _I32_2.unpack_from(buf, off)
                off += 8
                for _ in range(n_ch):
                    if off + 4 > end:
                        raise DecodeError("bad_length", "frame cut short")
                    (n_frames,) = _I32.unpack_from(buf, off)
                    if not 0 <= n_frames <= MAX_LIST_COUNT:
                        raise DecodeError("bad_count", f"{n_frames} analog frames")
                    off += 4 + 4 * n_frames
        if off + _SUFFIX_MIN > end:
            raise DecodeError("bad_length", "frame suffix cut short")
        timecode, timecode_sub, timestamp_s = _SUFFIX.unpack_from(buf, off)
        if frame_id < 0:
            raise DecodeError("bad_frame_number", f"frame number {frame_id}")
        if math.isinf(timestamp_s):
            raise DecodeError("non_finite", "infinite timestamp")
        out.store(staged)  # raises non_finite before writing anything
        frame = out.frame
        frame.frame_id = frame_id
        frame.source_time_s = timestamp_s
        out.label_set_id = self.label_set.id
        out.unknown_labels = unknown
        self.timecode = timecode
        self.timecode_sub = timecode_sub
        (params,) = _I16.unpack_from(buf, end - 2)
        self.models_changed = bool(params & FRAME_MODELS_CHANGED)
        return out

    @staticmethod
    def _skip(off: int, list_size: int, computed: int, end: int) -> int:
        if list_size >= 0 and list_size != computed:
            raise DecodeError("bad_length", "list size disagrees with its count")
        if off + computed > end:
            raise DecodeError("bad_length", "frame cut short")
        return off + computed


def encode_request(msg_id: int, text: str = "") -> bytes:
    """A client request: ``NAT_REQUEST_MODELDEF``, ``NAT_KEEPALIVE`` (empty payload)
    or ``NAT_REQUEST`` with a NUL-terminated command string."""
    payload = (text.encode() + b"\0") if msg_id == NAT_REQUEST else b""
    return _HEADER.pack(msg_id, len(payload)) + payload


def encode_connect(version: Version = REQUESTED_VERSION) -> bytes:
    """``NAT_CONNECT`` as the SDK's NatNetClient.py sends it: "Ping", zero padding,
    the requested bitstream version at bytes 265-268 of a 270-byte payload, and a
    trailing NUL."""
    payload = bytearray(271)
    payload[0:4] = b"Ping"
    payload[265] = version.major
    payload[266] = version.minor
    return _HEADER.pack(NAT_CONNECT, len(payload)) + bytes(payload)


def packet_info(buf: Buffer) -> tuple[int, int, float]:
    """(kind, frame number, source time) of a NatNet datagram, for the recording
    envelope: kind 1 frame (its frame number; the timestamp sits in the suffix and
    is left NaN), 2 model definitions, 0 anything else (-1, NaN)."""
    if len(buf) >= 8 and buf[0] == NAT_FRAMEOFDATA and buf[1] == 0:
        return 1, int(_I32.unpack_from(buf, 4)[0]), math.nan
    if len(buf) >= 2 and buf[0] == NAT_MODELDEF and buf[1] == 0:
        return 2, -1, math.nan
    return 0, -1, math.nan


class NatNetSession:
    """What one server has told us (socket-free: live and replay alike).

    Args:
        sets: the marker sets to read (all but ``all`` when None).
        subjects: label every marker ``<set>:<name>`` (:func:`label_set_from_models`).
        version: the bitstream version assumed until a server info says otherwise
            (replay of a recording that starts without one).
        out: where status lines go.

    Attributes:
        info: the server's info once it answered.
        models: the last model definitions.
        decoder: the frame decoder once model definitions arrived, else None.
        label_set: its label set.
        counts: ``connects``, ``model_defs``, ``not_frames``, ``bad_control``.
        last_error: the last control-packet error.
    """

    def __init__(
        self,
        sets: Sequence[str] | None = None,
        version: Version = REQUESTED_VERSION,
        out: Callable[[str], None] | None = None,
        where: str = "",
        subjects: bool = False,
    ) -> None:
        self.sets = sets
        self.subjects = subjects
        self.version = version
        self._say = out or logger.info
        self.where = where
        self.info: ServerInfo | None = None
        self.models: ModelDefs | None = None
        self.decoder: NatNetDecoder | None = None
        self.label_set: LabelSet | None = None
        self.counts: dict[str, int] = dict.fromkeys(
            ("connects", "model_defs", "not_frames", "bad_control"), 0
        )
        self.last_error: DecodeError | None = None
        self._next_label_id = 1

    def handle(self, packet: Buffer) -> int:
        """Handle a control packet; returns its message id (-1 when malformed)."""
        try:
            msg_id, _ = read_header(packet)
            if msg_id == NAT_SERVERINFO:
                info = decode_server_info(packet)
                _check_version(info.natnet_version)
                self.info = info
                self.version = info.natnet_version
                self.counts["connects"] += 1
                self._say(
                    f"natnet: connected to {info.app_name} "
                    f"{'.'.join(map(str, info.app_version))} at {self.where}, "
                    f"NatNet {info.natnet_version}"
                    + (f", multicast {info.multicast_group}" if info.multicast else "")
                )
            elif msg_id == NAT_MODELDEF:
                self.adopt_models(decode_model_defs(packet, self.version))
            else:
                self.counts["not_frames"] += 1
            return int(msg_id)
        except DecodeError as exc:
            self.counts["bad_control"] += 1
            if self.last_error is None or exc.reason != self.last_error.reason:
                self._say(f"natnet: bad packet from {self.where}: {exc}")
            self.last_error = exc
            return -1

    def adopt_models(self, models: ModelDefs) -> None:
        """Build the decoder for ``models`` (a new label-set id when names change)."""
        self.counts["model_defs"] += 1
        labels = label_set_from_models(
            models, self._next_label_id, self.sets, self.subjects
        )
        if self.label_set is not None and labels.labels == self.label_set.labels:
            labels = self.label_set
        else:
            self._next_label_id += 1
            self._say(
                f"natnet: {len(labels.labels)} markers in "
                f"{len(_chosen_sets(models, self.sets))} marker set(s)"
            )
        self.models = models
        self.label_set = labels
        self.decoder = NatNetDecoder(models, labels, self.sets)
