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

Loop integration (one thread, never blocks)::

    opts = parse_natnet_url("natnet://HOST")           # or from the config
    client = opts.client(out)                           # binds non-blocking sockets
    inp = NatNetInput(client, opts.up_axis)
    for sock in client.fds(): poller.register(sock, zmq.POLLIN)
    # every wake-up / poll timeout: client.tick()
    # for each readable sock: while (pkt := client.read(sock)) is not None:
    #     record pkt (form natnet, kind from packet_info(pkt)); code = inp.feed(pkt, t)
    #     code ACCEPTED / RESTART -> inp.stream.current.frame; -1 -> control message
    # close: client.close()

Replay: ``NatNetInput(None, up_axis).feed(pkt, t_ns)`` for every recorded datagram.
"""

from __future__ import annotations

import contextlib
import ipaddress
import logging
import math
import socket
import struct
import time
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


def encode_connect(version: Version = Version(4, 1)) -> bytes:
    """``NAT_CONNECT`` as the SDK's NatNetClient.py sends it: "Ping", zero padding,
    the requested bitstream version at bytes 265-268 of a 270-byte payload, and a
    trailing NUL."""
    payload = bytearray(271)
    payload[0:4] = b"Ping"
    payload[265] = version.major
    payload[266] = version.minor
    return _HEADER.pack(NAT_CONNECT, len(payload)) + bytes(payload)


#: Wait this long for a command reply before asking again (Motive answers within a
#: frame; the SDK sample's command socket times out at 2 s, we re-ask sooner).
COMMAND_RETRY_S = 1.0
#: Unicast keep-alive period: the SDK's NatNetClient.py sends one per second.
KEEPALIVE_S = 1.0
#: No packet for this long: the server is gone (2 s, the SDK sample's timeout).
SERVER_TIMEOUT_S = 2.0


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
        version: Version = Version(4, 1),
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


class NatNetClient:
    """Command-port client and data socket for one Motive server; never blocks.

    All sockets are non-blocking UDP. The loop polls :meth:`fds`, reads every
    datagram with :meth:`read` and hands it to :meth:`NatNetInput.feed` (frames and
    control messages alike, so a recording holds both). :meth:`tick` (every wake-up
    or poll timeout) sends the connect and model-definition requests until answered,
    the unicast keep-alive, and notices a silent server.

    Unicast: requests go from the command socket to Motive's command port, and Motive
    answers and streams to that socket's address (the SDK's NatNetClient.py reads
    frames on its command socket too). Multicast: frames arrive on a data socket bound
    to ``data_port`` and joined to ``group``.

    Args:
        host: Motive's address.
        command_port / data_port: Motive's ports (1510 / 1511 by default).
        multicast: receive data from ``group`` (Motive's "Multicast" transmission).
        group: the multicast group.
        local: the local interface address for the binds and the group join.
        sets: the marker sets to read (all but ``all`` when None).
        subjects: label every marker ``<set>:<name>``.
        version: bitstream version asked for in ``NAT_CONNECT``.
        out: where status lines go.

    Attributes:
        session: what the server told us (decoder, label set, counts).
        timeouts: how often the server fell silent for :data:`SERVER_TIMEOUT_S`.
    """

    def __init__(
        self,
        host: str,
        command_port: int = DEFAULT_COMMAND_PORT,
        data_port: int = DEFAULT_DATA_PORT,
        *,
        multicast: bool = False,
        group: str = DEFAULT_MULTICAST_GROUP,
        local: str = "0.0.0.0",
        sets: Sequence[str] | None = None,
        subjects: bool = False,
        version: Version = Version(4, 1),
        out: Callable[[str], None] | None = None,
    ) -> None:
        self.server = (host, command_port)
        self.requested = version
        self._say = out or logger.info
        self.session = NatNetSession(sets, version, self._say, host, subjects)
        self.timeouts = 0
        self.cmd = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.cmd.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        self.cmd.bind((local, 0))
        self.cmd.setblocking(False)
        self.data: socket.socket | None = None
        if multicast:
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
            sock.bind(("", data_port))
            mreq = socket.inet_aton(group) + socket.inet_aton(local)
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, mreq)
            sock.setblocking(False)
            self.data = sock
        self._buf = bytearray(65536)
        self._view = memoryview(self._buf)
        self._last_rx = 0.0
        self._last_connect = -math.inf
        self._last_modeldef = -math.inf
        self._last_keepalive = -math.inf
        self._silent = False

    def fds(self) -> list[socket.socket]:
        """The sockets to poll (register them with ``zmq.POLLIN``)."""
        return [self.cmd] + ([self.data] if self.data is not None else [])

    def close(self) -> None:
        """Close the sockets (idempotent)."""
        for sock in self.fds():
            with contextlib.suppress(OSError):
                sock.close()

    def _send(self, packet: bytes) -> None:
        # UDP: a lost or refused request is sent again by tick().
        with contextlib.suppress(
            BlockingIOError, InterruptedError, ConnectionRefusedError
        ):
            self.cmd.sendto(packet, self.server)

    def tick(self, now_s: float | None = None) -> None:
        """Send what is due (connect, model definitions, keep-alive); never blocks."""
        now = time.monotonic() if now_s is None else now_s
        session = self.session
        if session.info is None and now - self._last_connect >= COMMAND_RETRY_S:
            self._last_connect = now
            self._send(encode_connect(self.requested))
        elif (
            session.info is not None
            and session.decoder is None
            and now - self._last_modeldef >= COMMAND_RETRY_S
        ):
            self.request_models(now)
        if self.data is None and now - self._last_keepalive >= KEEPALIVE_S:
            self._last_keepalive = now
            self._send(encode_request(NAT_KEEPALIVE))
        if (
            self._last_rx
            and not self._silent
            and now - self._last_rx >= SERVER_TIMEOUT_S
        ):
            self._silent = True
            self.timeouts += 1
            self._say(
                f"natnet: no packet from {self.server[0]} for {SERVER_TIMEOUT_S:g} s; "
                "holding the last pose, reconnecting"
            )
            session.info = None  # connect again (Motive restarted?)

    def request_models(self, now_s: float | None = None) -> None:
        """Ask for the model definitions (after a change or a ``count_mismatch``)."""
        self._last_modeldef = time.monotonic() if now_s is None else now_s
        self._send(encode_request(NAT_REQUEST_MODELDEF))

    def read(self, sock: socket.socket) -> memoryview | None:
        """One datagram from ``sock`` (a view into a buffer the next call reuses),
        or None when the socket is drained. Never blocks."""
        while True:
            try:
                n = sock.recv_into(self._buf)
            except (BlockingIOError, InterruptedError):
                return None
            except ConnectionRefusedError:
                continue  # ICMP from a closed port: server not (yet) there
            self._last_rx = time.monotonic()
            if self._silent:
                self._silent = False
                self._say(f"natnet: {self.server[0]} is back")
            return self._view[:n]


@dataclass(frozen=True, slots=True)
class NatNetOptions:
    """Where and how to reach Motive: what ``natnet://`` names.

    Attributes:
        host: Motive's address.
        command_port / data_port: 1510 / 1511 by default.
        multicast / group / local: transmission type, group, local interface.
        up_axis: Motive's streaming up axis (``+Y`` default).
        sets: the marker sets to read (None: all but ``all``).
        subjects: label every marker ``<set>:<name>`` (``subjects=1``).
    """

    host: str
    command_port: int = DEFAULT_COMMAND_PORT
    data_port: int = DEFAULT_DATA_PORT
    multicast: bool = False
    group: str = DEFAULT_MULTICAST_GROUP
    local: str = "0.0.0.0"
    up_axis: str = "+Y"
    sets: tuple[str, ...] | None = None
    subjects: bool = False

    def client(self, out: Callable[[str], None] | None = None) -> NatNetClient:
        """A client for these options."""
        return NatNetClient(
            self.host,
            self.command_port,
            self.data_port,
            multicast=self.multicast,
            group=self.group,
            local=self.local,
            sets=self.sets,
            subjects=self.subjects,
            out=out,
        )


def parse_natnet_url(url: str) -> NatNetOptions:
    """``natnet://HOST[:COMMAND_PORT][?data_port=N&multicast=1&group=G&local=A
    &up=+Z&sets=A,B&subjects=1]`` -> options.

    Raises:
        ValueError: naming the part that is wrong.
    """
    from urllib.parse import parse_qs, urlsplit

    from retargetd.protocols.conventions import normalize_up_axis

    parts = urlsplit(url)
    if parts.scheme != "natnet" or not parts.hostname:
        raise ValueError(f"expected natnet://HOST[:PORT][?...]; got {url!r}")
    query = {k: v[-1] for k, v in parse_qs(parts.query, strict_parsing=False).items()}
    known = {"data_port", "multicast", "group", "local", "up", "sets", "subjects"}
    if set(query) - known:
        raise ValueError(f"unknown natnet:// option(s) {sorted(set(query) - known)}")
    try:
        port = parts.port or DEFAULT_COMMAND_PORT
        data_port = int(query.get("data_port", DEFAULT_DATA_PORT))
    except ValueError as exc:
        raise ValueError(f"bad port in {url!r}: {exc}") from None
    multicast = query.get("multicast", "0").lower() in ("1", "true", "yes", "on")
    subjects = query.get("subjects", "0").lower() in ("1", "true", "yes", "on")
    sets = tuple(query["sets"].split(",")) if query.get("sets") else None
    return NatNetOptions(
        parts.hostname,
        port,
        data_port,
        multicast,
        query.get("group", DEFAULT_MULTICAST_GROUP),
        query.get("local", "0.0.0.0"),
        normalize_up_axis(query.get("up", "+Y")),
        sets,
        subjects,
    )


class NatNetInput:
    """A Motive marker input: any NatNet datagram in, frames into a stream.

    Live: built on a :class:`NatNetClient`; replay: on ``None`` (a socket-free
    session, fed the recorded datagrams in order).

    Args:
        client: the client, or None for replay.
        up_axis: Motive's streaming "Up Axis" (``"+Y"`` by default; the stream does
            not announce it).
        restart_gap_ns: see :class:`~retargetd.protocols.marker_input.FrameSequencer`.
        sets / subjects / out: for the replay session (the client has its own).

    Attributes:
        stream: the :class:`MarkerStream` (``stream.current.frame`` is the last
            accepted frame; counters by reason).
        session: the client's session (or the replay one).
    """

    def __init__(
        self,
        client: NatNetClient | None,
        up_axis: str = "+Y",
        restart_gap_ns: int | None = None,
        *,
        sets: Sequence[str] | None = None,
        subjects: bool = False,
        out: Callable[[str], None] | None = None,
    ) -> None:
        from retargetd.protocols.marker_input import RESTART_GAP_NS, MarkerStream

        self.client = client
        self.session = (
            client.session
            if client is not None
            else NatNetSession(sets, out=out, where="recording", subjects=subjects)
        )
        self.stream = MarkerStream(
            None,
            up_axis,
            "m",
            RESTART_GAP_NS if restart_gap_ns is None else restart_gap_ns,
        )
        self._last_models_request = -math.inf

    def feed(self, packet: Buffer, t_ns: int) -> int:
        """Handle one datagram.

        Returns:
            For a frame, the ``MarkerStream.feed`` reason index (``ACCEPTED`` /
            ``RESTART`` = use ``stream.current``); -1 for a control message.
        """
        if not (len(packet) >= 2 and packet[0] == NAT_FRAMEOFDATA and packet[1] == 0):
            msg_id = self.session.handle(packet)
            if msg_id == NAT_SERVERINFO and self.client is not None:
                self.client.request_models()
            return -1
        decoder = self.session.decoder
        stream = self.stream
        if decoder is None:
            return stream.feed(_no_labels, packet, t_ns=t_ns)  # unknown_label_set
        if decoder.label_set is not stream.label_set:
            stream.set_labels(decoder.label_set)
        code = stream.feed(decoder.decode_natnet_frame, packet, t_ns=t_ns)
        asked = decoder.models_changed or code == COUNT_MISMATCH
        now = time.monotonic()
        if (
            asked
            and self.client is not None
            and now - self._last_models_request >= COMMAND_RETRY_S
        ):
            self._last_models_request = now
            self.client.request_models()
        return code


def _no_labels(buf: Buffer, out: MarkerPacket) -> MarkerPacket:
    raise DecodeError("unknown_label_set", "no model definitions yet")
