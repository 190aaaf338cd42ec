"""Marker input shared by every wire form: label sets, the decode target, drop counters,
the frame sequencer, and :class:`MarkerStream`, which ties them together.

Decoders (``osc_in``, ``zmq_wire``) are pure: ``decode_<fmt>(buf, out) -> out`` checks a
whole packet and only then writes it into ``out`` (a :class:`MarkerPacket`), converting
positions to world metres on the way (``p_world = world_from_capture @ p * scale``,
README "Conventions"). Ordering across packets is the :class:`FrameSequencer`'s job,
and :class:`MarkerStream` decodes into a spare packet and swaps it in only when the
sequencer accepts it, so a dropped packet never overwrites the last good frame.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from retargetd.protocols.conventions import (
    UNIT_TO_METRES,
    normalize_units,
    world_from_capture_mat,
)
from retargetd.protocols.errors import DecodeError
from retargetd.protocols.frames import (
    BoolArray,
    F32Array,
    F64Array,
    IntArray,
    MarkerFrame,
)

#: Every outcome a marker packet can have, in counter order. The first two are
#: accepted frames; ``unknown_label`` counts markers ignored inside kept frames.
REASONS: tuple[str, ...] = (
    "accepted",
    "restart",
    "backwards",
    "duplicate",
    "stale",
    "unknown_label",
    "bad_length",
    "bad_address",
    "bad_typetags",
    "bad_string",
    "bad_blob_size",
    "bad_count",
    "bad_magic",
    "bad_version",
    "not_bundle",
    "bad_bundle",
    "no_markers",
    "bad_frame_number",
    "non_finite",
    "unknown_label_set",
    "count_mismatch",
    "duplicate_marker",
    "bad_label",
    "no_3d",
    "other",
)
REASON_INDEX: dict[str, int] = {name: i for i, name in enumerate(REASONS)}
ACCEPTED = REASON_INDEX["accepted"]
RESTART = REASON_INDEX["restart"]
BACKWARDS = REASON_INDEX["backwards"]
DUPLICATE = REASON_INDEX["duplicate"]
STALE = REASON_INDEX["stale"]
UNKNOWN_LABEL = REASON_INDEX["unknown_label"]
OTHER = REASON_INDEX["other"]

#: A frame number that goes back after this long without an accepted frame is a
#: restarted source (1 s).
RESTART_GAP_NS = 1_000_000_000


@dataclass(frozen=True, slots=True)
class LabelSet:
    """Marker names for the frames that carry ``id``, in blob order.

    Attributes:
        id: the label-set id (int32 on OSC, uint32 on ZeroMQ).
        labels: marker names, unique, non-empty, no NUL or newline.
    """

    id: int
    labels: tuple[str, ...]

    def __post_init__(self) -> None:
        if len(set(self.labels)) != len(self.labels):
            raise DecodeError("bad_label", f"label set {self.id} repeats a name")
        for name in self.labels:
            if not name or "\0" in name or "\n" in name:
                raise DecodeError("bad_label", f"bad marker name {name!r}")


@dataclass(slots=True, eq=False)
class MarkerPacket:
    """The decode target of one marker input: the frame plus what decoding needs.

    Build it with :meth:`create`. Decoders fill ``frame`` (all but ``t_ns``, which the
    receive loop sets), ``label_set_id`` and ``unknown_labels``.

    Attributes:
        frame: the marker frame, sized to ``label_set``; world metres, NaN = occluded.
        label_set: the label set frames must carry (its size fixes the marker count).
        label_set_id: the label-set id of the last decoded packet.
        unknown_labels: markers of the last decoded simple bundle whose name is not in
            ``label_set`` (ignored; the rest of the frame is kept).
        world_from_capture_scaled_mat: (3, 3) float64, read-only: ``world_from_capture``
            times the input's unit-to-metres factor.
        label_index: name -> row, for the simple (per-marker) form.
    """

    frame: MarkerFrame
    label_set: LabelSet
    label_set_id: int
    unknown_labels: int
    world_from_capture_scaled_mat: F64Array
    label_index: dict[str, int]
    # Scratch, allocated with the frame: the matmul right-hand side (M^T), a per-value
    # mask, native float32 rows, the occlusion mask (and its column view), and the
    # staging rows of the simple form.
    _rhs: F64Array = field(repr=False)
    _mask3: BoolArray = field(repr=False)
    _mask_cols: tuple[BoolArray, BoolArray, BoolArray] = field(repr=False)
    _raw32: F32Array = field(repr=False)
    _raw64: F64Array = field(repr=False)
    _occluded: BoolArray = field(repr=False)
    _occluded_col: BoolArray = field(repr=False)
    _staged: F64Array = field(repr=False)
    _seen: BoolArray = field(repr=False)

    @classmethod
    def create(
        cls, label_set: LabelSet, up_axis: str = "+Z", units: str = "m"
    ) -> MarkerPacket:
        """Allocate a packet for ``label_set``.

        Args:
            label_set: the expected labels (configured, or announced by the sender).
            up_axis: the sender's up axis (``"+Y"``, ``"+Z"`` ...), see conventions.
            units: the sender's length unit (``"mm"``, ``"m"`` ...).
        """
        mat = world_from_capture_mat(up_axis) * UNIT_TO_METRES[normalize_units(units)]
        mat.flags.writeable = False
        return cls._allocate(label_set, mat)

    @classmethod
    def _allocate(cls, label_set: LabelSet, mat: F64Array) -> MarkerPacket:
        n = len(label_set.labels)
        occluded = np.zeros(n, dtype=bool)
        mask = np.zeros((n, 3), dtype=bool)
        return cls(
            frame=MarkerFrame.empty(n),
            label_set=label_set,
            label_set_id=label_set.id,
            unknown_labels=0,
            world_from_capture_scaled_mat=mat,
            label_index={name: i for i, name in enumerate(label_set.labels)},
            _rhs=np.ascontiguousarray(mat.T),
            _mask3=mask,
            _mask_cols=(mask[:, 0], mask[:, 1], mask[:, 2]),
            _raw32=np.zeros((n, 3), dtype=np.float32),
            _raw64=np.zeros((n, 3)),
            _occluded=occluded,
            _occluded_col=occluded[:, None],
            _staged=np.full((n, 3), np.nan),
            _seen=np.zeros(n, dtype=bool),
        )

    def with_label_set(self, label_set: LabelSet) -> MarkerPacket:
        """This packet re-targeted at ``label_set`` (itself when the size is unchanged).

        Not for the hot path: called when a new label set is announced.
        """
        if len(label_set.labels) != len(self.label_set.labels):
            return MarkerPacket._allocate(label_set, self.world_from_capture_scaled_mat)
        self.label_set = label_set
        self.label_index = {name: i for i, name in enumerate(label_set.labels)}
        return self

    def store(self, raw: Any) -> None:
        """Check ``raw`` and convert it into ``frame`` (world metres) and ``valid``.

        Args:
            raw: (n, 3) float array (any byte order) in the sender's units and axes; a
                row with any NaN is occluded and becomes all NaN.

        Raises:
            DecodeError: ``non_finite`` if any value is ±inf (``frame`` untouched).
        """
        raw32, mask, occluded = self._raw32, self._mask3, self._occluded
        np.copyto(raw32, raw)  # a byte swap, no arithmetic
        np.isinf(raw32, out=mask)
        if np.count_nonzero(mask):
            raise DecodeError(
                "non_finite", "infinite value (NaN is occluded, inf is not)"
            )
        np.isnan(raw32, out=mask)
        np.logical_or(self._mask_cols[0], self._mask_cols[1], out=occluded)
        np.logical_or(occluded, self._mask_cols[2], out=occluded)
        frame = self.frame
        np.logical_not(occluded, out=frame.valid)
        # Whole occluded rows become a quiet NaN: a signalling NaN from the wire would
        # raise "invalid value" in the cast below.
        np.copyto(raw32, np.nan, where=self._occluded_col)
        np.copyto(self._raw64, raw32)
        # One fused conversion: rotation to the world and unit scale (M = R * scale).
        # M is a scaled signed permutation, so an all-NaN row stays all NaN.
        np.dot(self._raw64, self._rhs, out=frame.markers_world)


class DropCounters:
    """Counts of packet outcomes by reason: a fixed int64 array indexed by
    :data:`REASON_INDEX` (no dict on the good-frame path)."""

    __slots__ = ("counts",)

    def __init__(self) -> None:
        self.counts: IntArray = np.zeros(len(REASONS), dtype=np.int64)

    def add(self, index: int, n: int = 1) -> None:
        """Count ``n`` outcomes of reason ``index`` (a constant: ``BACKWARDS`` ...)."""
        self.counts[index] += n

    def add_reason(self, reason: str) -> None:
        """Count a :class:`DecodeError` reason slug (unknown slugs: ``other``)."""
        self.counts[REASON_INDEX.get(reason, OTHER)] += 1

    def __getitem__(self, reason: str) -> int:
        return int(self.counts[REASON_INDEX[reason]])

    def dropped(self) -> int:
        """Packets dropped (everything but accepted, restart and ignored markers)."""
        kept = self.counts[ACCEPTED] + self.counts[RESTART] + self.counts[UNKNOWN_LABEL]
        return int(self.counts.sum() - kept)

    def as_dict(self) -> dict[str, int]:
        """Non-zero counts by reason name, for the stats line."""
        return {REASONS[i]: int(c) for i, c in enumerate(self.counts) if c}


class FrameSequencer:
    """Decides, from frame numbers alone, whether a decoded frame is accepted.

    Pure logic without a clock: the caller passes ``t_ns`` (``time.monotonic_ns()`` at
    receive). Rules, against the last *accepted* frame:

    - a larger frame number: accepted;
    - not larger, and either ``t_ns`` is at least ``restart_gap_ns`` after the last
      accepted frame or the label-set id differs: a restarted source (``RESTART``:
      accepted, counted, state reset to this frame);
    - otherwise equal: ``DUPLICATE``, smaller: ``BACKWARDS`` (both dropped);
    - a frame number of -1 (a simple bundle without one) is accepted unordered.
    """

    __slots__ = ("last_frame", "last_label_set_id", "last_t_ns", "restart_gap_ns")

    def __init__(self, restart_gap_ns: int = RESTART_GAP_NS) -> None:
        self.restart_gap_ns = restart_gap_ns
        self.last_frame = -1
        self.last_label_set_id = 0
        self.last_t_ns = 0

    def reset(self) -> None:
        """Forget the last frame: the next one is accepted whatever its number."""
        self.last_frame = -1

    def check(self, frame_id: int, label_set_id: int, t_ns: int) -> int:
        """Classify a frame and update the state when it is accepted.

        Returns:
            ``ACCEPTED`` or ``RESTART`` (use the frame), ``DUPLICATE`` or ``BACKWARDS``
            (drop it).
        """
        code = ACCEPTED
        if frame_id >= 0 and self.last_frame >= 0 and frame_id <= self.last_frame:
            if (
                label_set_id != self.last_label_set_id
                or t_ns - self.last_t_ns >= self.restart_gap_ns
            ):
                code = RESTART
            elif frame_id == self.last_frame:
                return DUPLICATE
            else:
                return BACKWARDS
        if frame_id >= 0:
            self.last_frame = frame_id
        self.last_label_set_id = label_set_id
        self.last_t_ns = t_ns
        return code


class MarkerStream:
    """One marker input: label set, double-buffered packets, sequencer and counters.

    Pure logic (no sockets): the receive loop hands it packets as they arrive.
    ``current.frame`` is always the last accepted frame; a packet is decoded into a
    spare and swapped in only once decoded and accepted.

    Args:
        label_set: the configured labels (simple form), or None until the sender
            announces them (compact OSC, ZeroMQ).
        up_axis: the sender's up axis.
        units: the sender's length unit.
        restart_gap_ns: see :class:`FrameSequencer`.
    """

    def __init__(
        self,
        label_set: LabelSet | None = None,
        up_axis: str = "+Z",
        units: str = "m",
        restart_gap_ns: int = RESTART_GAP_NS,
    ) -> None:
        initial = label_set if label_set is not None else LabelSet(-1, ())
        self.label_set: LabelSet | None = label_set
        self.current = MarkerPacket.create(initial, up_axis, units)
        self._spare = MarkerPacket.create(initial, up_axis, units)
        self.sequencer = FrameSequencer(restart_gap_ns)
        self.counters = DropCounters()
        self.last_error: DecodeError | None = None

    def set_labels(self, label_set: LabelSet) -> bool:
        """Adopt an announced label set; True when it differs from the current one."""
        if label_set == self.label_set:
            return False
        self.label_set = label_set
        return True

    def feed(self, decode: Callable[..., MarkerPacket], *parts: Any, t_ns: int) -> int:
        """Decode one packet and classify it.

        Args:
            decode: a decoder such as ``osc_in.decode_compact_frame``; called as
                ``decode(*parts, packet)``.
            parts: the packet (one datagram, or a ZeroMQ header and payload).
            t_ns: ``time.monotonic_ns()`` at receive.

        Returns:
            A reason index: ``ACCEPTED`` or ``RESTART`` when ``current`` now holds this
            frame, otherwise the reason it was dropped (already counted).
        """
        spare = self._spare
        if self.label_set is None:
            self.counters.add(REASON_INDEX["unknown_label_set"])
            return REASON_INDEX["unknown_label_set"]
        if spare.label_set is not self.label_set:
            spare = self._spare = spare.with_label_set(self.label_set)
        try:
            decode(*parts, spare)
        except DecodeError as exc:
            self.last_error = exc
            index = REASON_INDEX.get(exc.reason, OTHER)
            self.counters.add(index)
            return index
        code = self.sequencer.check(spare.frame.frame_id, spare.label_set_id, t_ns)
        self.counters.add(code)
        if code > RESTART:
            return code
        if spare.unknown_labels:
            self.counters.add(UNKNOWN_LABEL, spare.unknown_labels)
        spare.frame.t_ns = t_ns
        self._spare, self.current = self.current, spare
        return code
