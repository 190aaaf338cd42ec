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

from retargetd.protocols import kernels
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
    "implausible_jump",
    "label_conflict",
    "conflicting_labels",
    "auth_failed",
    "auth_replayed",
    "too_large",
    "too_many_markers",
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
IMPLAUSIBLE_JUMP = REASON_INDEX["implausible_jump"]
LABEL_CONFLICT = REASON_INDEX["label_conflict"]
CONFLICTING_LABELS = REASON_INDEX["conflicting_labels"]
TOO_MANY_MARKERS = REASON_INDEX["too_many_markers"]
AUTH_FAILED = REASON_INDEX["auth_failed"]  # unsigned, or a tag not the key's
AUTH_REPLAYED = REASON_INDEX["auth_replayed"]  # signed, not newer than the last
OTHER = REASON_INDEX["other"]
UNKNOWN_LABEL_SET = REASON_INDEX["unknown_label_set"]

#: A frame number that goes back after this long without an accepted frame is a
#: restarted source (1 s).
RESTART_GAP_NS = 1_000_000_000

#: The fastest a source's frame numbers can plausibly count. The fastest optical
#: capture systems reach a few kHz only at reduced resolution: Vicon MX cameras up to
#: 2,000 fps (Vicon MX Hardware System Reference, "Increased Frame Rates"), Qualisys
#: Oqus high-speed cameras up to 10,000 fps (QTM manual, "Capture high-speed video").
#: Configurable per input (``max_rate_hz``).
MAX_RATE_HZ = 10_000.0

#: Delivery jitter allowed on top of the elapsed receive time: two frames' one-way
#: delays (network queues, the socket buffer while the loop is busy) may differ by
#: this much. At 10 kHz it allows 1,000 extra frames, still 2^52 times below a
#: spoofed 2^62; a larger real jump (frames lost in the kernel during a long stall)
#: costs only ``JUMP_CONFIRM_FRAMES`` frames before it is adopted as a restart.
JUMP_SLACK_NS = 100_000_000

#: A frame sequence that does not continue the accepted one (an implausible jump
#: forward, or backwards) is adopted, as a restart, once this many of its frames have
#: arrived in a row, each a plausible successor of the one before, with no frame of
#: the accepted sequence in between. One corrupted or spoofed packet never is; a
#: source that really jumped (a take seeked, looped or restarted) loses 2 frames.
JUMP_CONFIRM_FRAMES = 3

#: Markers in one label set, every input. A compact OSC frame must fit one UDP
#: datagram (65,507 bytes of IPv4 payload): (65,507 - 48) / 12 = 5,454 markers. The
#: same bound on ZeroMQ keeps every label set carriable by both inputs.
MAX_MARKERS = 5_454

#: Largest message an input takes, bytes: the IPv4 UDP payload limit (65,535 - 8-byte
#: UDP header - 20-byte IP header); a 5,454-marker ZeroMQ frame payload (65,448 bytes)
#: fits. Configurable per input (``max_message_bytes``).
MAX_MESSAGE_BYTES = 65_507


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
        zero_is_occluded: an exact (0, 0, 0) row is occluded (many capture systems
            send zeros, not NaN, for a marker they do not see).
        max_coordinate_m: a marker with a world coordinate past this (metres) is
            occluded and counted in ``implausible[0]`` (:data:`MAX_COORDINATE_M`).
    """

    frame: MarkerFrame
    label_set: LabelSet
    label_set_id: int
    unknown_labels: int
    world_from_capture_scaled_mat: F64Array
    label_index: dict[str, int]
    zero_is_occluded: bool
    max_coordinate_m: float
    #: (1,) int64: markers occluded for a coordinate past ``max_coordinate_m``; one
    #: array shared by the packets of a stream (they swap).
    implausible: IntArray
    # Scratch, allocated with the frame: the conversion's right-hand side (M^T), native
    # float32 rows, the occlusion mask, and the staging rows of the simple form.
    _rhs: F64Array = field(repr=False)
    _raw32: F32Array = field(repr=False)
    _occluded: BoolArray = field(repr=False)
    _staged: F64Array = field(repr=False)
    _seen: BoolArray = field(repr=False)
    #: The simple form's layout cache (``osc_in.SimpleLayout``): None until a bundle
    #: decoded; reset with the label set.
    _simple: Any = field(default=None, repr=False)
    #: ``kernels.decode_frame``'s per-packet arguments from ``zero_is_occluded`` to
    #: ``implausible``, in order (``MarkerStream.feed_packed``: one tuple read).
    packed_args: tuple[Any, ...] = field(default=(), repr=False)

    def __post_init__(self) -> None:
        frame = self.frame
        self.packed_args = (
            self.zero_is_occluded, self._rhs, self._raw32, self._occluded, frame.valid,
            frame.markers_world, self.max_coordinate_m, self.implausible,
        )  # fmt: skip

    @classmethod
    def create(
        cls,
        label_set: LabelSet,
        up_axis: str = "+Z",
        units: str = "m",
        zero_is_occluded: bool = True,
        max_coordinate_m: float = 0.0,
        implausible: IntArray | None = None,
    ) -> MarkerPacket:
        """Allocate a packet for ``label_set``.

        Args:
            label_set: the expected labels (configured, or announced by the sender).
            up_axis: the sender's up axis (``"+Y"``, ``"+Z"`` ...), see conventions.
            units: the sender's length unit (``"mm"``, ``"m"`` ...).
            zero_is_occluded: treat an exact (0, 0, 0) row as occluded.
            max_coordinate_m: the bound on a world coordinate, metres (0:
                :data:`MAX_COORDINATE_M`).
            implausible: the (1,) int64 counter to share (default: a new one).
        """
        mat = world_from_capture_mat(up_axis) * UNIT_TO_METRES[normalize_units(units)]
        mat.flags.writeable = False
        return cls._allocate(
            label_set, mat, zero_is_occluded, max_coordinate_m or MAX_COORDINATE_M,
            np.zeros(1, dtype=np.int64) if implausible is None else implausible,
        )  # fmt: skip

    @classmethod
    def _allocate(
        cls,
        label_set: LabelSet,
        mat: F64Array,
        zero_is_occluded: bool,
        max_coordinate_m: float,
        implausible: IntArray,
    ) -> MarkerPacket:
        n = len(label_set.labels)
        return cls(
            frame=MarkerFrame.empty(n),
            label_set=label_set,
            label_set_id=label_set.id,
            unknown_labels=0,
            world_from_capture_scaled_mat=mat,
            label_index={name: i for i, name in enumerate(label_set.labels)},
            zero_is_occluded=zero_is_occluded,
            max_coordinate_m=float(max_coordinate_m),
            implausible=implausible,
            _rhs=np.ascontiguousarray(mat.T),
            _raw32=np.zeros((n, 3), dtype=np.float32),
            _occluded=np.zeros(n, dtype=bool),
            _staged=np.full((n, 3), np.nan),
            _seen=np.zeros(n, dtype=bool),
        )

    def with_label_set(self, label_set: LabelSet) -> MarkerPacket:
        """This packet re-targeted at ``label_set`` (itself when the size is unchanged).

        Not for the hot path: called when a new label set is announced.
        """
        if len(label_set.labels) != len(self.label_set.labels):
            return MarkerPacket._allocate(
                label_set, self.world_from_capture_scaled_mat, self.zero_is_occluded,
                self.max_coordinate_m, self.implausible,
            )  # fmt: skip
        self.label_set = label_set
        self.label_index = {name: i for i, name in enumerate(label_set.labels)}
        self._simple = None  # the names moved: the layout cache no longer holds
        return self

    def store(self, raw: Any) -> None:
        """Check ``raw`` and convert it into ``frame`` (world metres) and ``valid``.

        Args:
            raw: (n, 3) float array (any byte order) in the sender's units and axes; a
                row with any NaN is occluded and becomes all NaN, and so is an exact
                (0, 0, 0) row (either sign of zero) when ``zero_is_occluded``.

        Raises:
            DecodeError: ``non_finite`` if any value is ±inf (``frame`` untouched).
        """
        raw32 = self._raw32
        np.copyto(raw32, raw)  # a byte swap, no arithmetic
        # One compiled pass (``kernels.store_rows``): the inf check first (nothing
        # written), then occlusion and the fused rotation to the world and unit scale
        # (M = R * scale, a scaled signed permutation: an all-NaN row stays all NaN).
        frame = self.frame
        if not kernels.store_rows(
            raw32, self.zero_is_occluded, self._rhs, self._occluded, frame.valid,
            frame.markers_world, self.max_coordinate_m, self.implausible,
        ):  # fmt: skip
            raise DecodeError(
                "non_finite", "infinite value (NaN is occluded, inf is not)"
            )

    def decode_packed(
        self,
        form: int,
        head: np.ndarray,
        n_head: int,
        payload: np.ndarray,
        n_payload: int,
    ) -> int:
        """Check a frame packet and store its markers in one compiled call
        (:func:`kernels.decode_frame`, ``form`` one of its ``FORM_*``).

        Args:
            head: uint8 array: the datagram (OSC) or the header part (ZeroMQ) in its
                first ``n_head`` bytes.
            payload: uint8 array: the ZeroMQ payload part in its first
                ``n_payload`` bytes (OSC: unused).

        Returns:
            The frame number, or a negative ``kernels.D_*`` code
            (:data:`KERNEL_REASONS`) with the frame untouched.
        """
        return kernels.decode_frame(
            form, head, n_head, payload, n_payload, self.label_set.id,
            *self.packed_args,
        )  # fmt: skip


#: :func:`kernels.decode_frame`'s refusals by reason.
KERNEL_REASONS: dict[int, str] = {
    kernels.D_BAD_LENGTH: "bad_length",
    kernels.D_BAD_ADDRESS: "bad_address",
    kernels.D_BAD_TYPETAGS: "bad_typetags",
    kernels.D_BAD_COUNT: "bad_count",
    kernels.D_BAD_BLOB_SIZE: "bad_blob_size",
    kernels.D_UNKNOWN_LABEL_SET: "unknown_label_set",
    kernels.D_COUNT_MISMATCH: "count_mismatch",
    kernels.D_BAD_FRAME_NUMBER: "bad_frame_number",
    kernels.D_NON_FINITE: "non_finite",
    kernels.D_BAD_MAGIC: "bad_magic",
    kernels.D_BAD_VERSION: "bad_version",
}


#: A marker with a world coordinate (x, y or z) past +-this, metres, is implausible:
#: occluded and counted (issue 30: every marker at 1e30 was held with no flag or
#: counter). The largest optical capture volumes are tens of metres across (stadium
#: and warehouse installations, ~100 m at most); 1 km is ten times that, and still
#: well inside float32's range (its step at 1 km is 0.06 mm).
MAX_COORDINATE_M = 1000.0


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
    receive). Rules, against the last *accepted* frame (number ``last``, received at
    ``last_t``):

    - larger and *plausible*, ``frame - last <= (t_ns - last_t + JUMP_SLACK_NS) x
      max_rate_hz + 1``: accepted;
    - larger but implausible: a new label-set id makes it a restart (a new id is a
      clean boundary); otherwise ``IMPLAUSIBLE_JUMP``, dropped;
    - not larger, and either ``t_ns`` is at least ``restart_gap_ns`` after the last
      accepted frame or the label-set id differs: a restarted source (``RESTART``:
      accepted, counted, state reset to this frame);
    - otherwise equal: ``DUPLICATE``, smaller: ``BACKWARDS`` (both dropped);
    - dropped jumps and backwards frames are candidates of a new sequence: once
      :data:`JUMP_CONFIRM_FRAMES` of them in a row continue each other plausibly, the
      last is accepted as a ``RESTART`` (a seeked, looped or restarted source);
    - a frame number of -1 (a simple bundle without one) is accepted unordered.
    """

    __slots__ = ("q", "qf")

    def __init__(
        self, restart_gap_ns: int = RESTART_GAP_NS, max_rate_hz: float = MAX_RATE_HZ
    ) -> None:
        if not max_rate_hz > 0.0:
            raise ValueError(f"max_rate_hz must be > 0; got {max_rate_hz}")
        # The state in one int64 array and the parameters in one float64 array
        # (``kernels.Q_*``, ``QF_*``): the compiled check reads and writes them in
        # place, from here and from ``MarkerStream.feed_packed``'s one call.
        self.q: IntArray = np.zeros(kernels.N_Q, dtype=np.int64)
        self.qf: F64Array = np.zeros(kernels.N_QF)
        rate_per_ns = max_rate_hz * 1e-9
        self.qf[kernels.QF_RATE_PER_NS] = rate_per_ns
        self.qf[kernels.QF_SLACK] = JUMP_SLACK_NS * rate_per_ns + 1.0
        self.q[kernels.Q_RESTART_GAP] = restart_gap_ns
        self.q[kernels.Q_CONFIRM] = JUMP_CONFIRM_FRAMES
        self.q[kernels.Q_LAST_FRAME] = -1
        self.q[kernels.Q_CAND_FRAME] = -1

    @property
    def last_frame(self) -> int:
        """The last accepted frame number (-1: none, or forgotten)."""
        return int(self.q[kernels.Q_LAST_FRAME])

    @property
    def last_label_set_id(self) -> int:
        """The label-set id of the last accepted frame."""
        return int(self.q[kernels.Q_LAST_SET])

    @property
    def last_t_ns(self) -> int:
        """When the last accepted frame was received (``time.monotonic_ns()``)."""
        return int(self.q[kernels.Q_LAST_T])

    @property
    def restart_gap_ns(self) -> int:
        """A frame number going back after this long is a restarted source."""
        return int(self.q[kernels.Q_RESTART_GAP])

    @restart_gap_ns.setter
    def restart_gap_ns(self, value: int) -> None:
        self.q[kernels.Q_RESTART_GAP] = value

    def reset(self) -> None:
        """Forget the last frame: the next one is accepted whatever its number."""
        self.q[kernels.Q_LAST_FRAME] = -1
        self.q[kernels.Q_CAND_N] = 0

    def restart_next(self) -> None:
        """Accept the next numbered frame as a ``RESTART`` whatever its number (the
        label set changed under the same id)."""
        self.q[kernels.Q_RESTART_NEXT] = 1

    def check(self, frame_id: int, label_set_id: int, t_ns: int) -> int:
        """Classify a frame and update the state when it is accepted
        (``kernels.sequence_check``, the rules above).

        Args:
            frame_id: the frame number (int64; -1: none).
            label_set_id: the label-set id it carries (int64).
            t_ns: ``time.monotonic_ns()`` at receive.

        Returns:
            ``ACCEPTED`` or ``RESTART`` (use the frame), ``DUPLICATE``, ``BACKWARDS``
            or ``IMPLAUSIBLE_JUMP`` (drop it).
        """
        code: int = kernels.sequence_check(
            self.q, self.qf, frame_id, label_set_id, t_ns
        )
        return code


class MarkerStream:
    """One marker input: label set, double-buffered packets, sequencer and counters.

    Pure logic (no sockets): the receive loop hands it packets as they arrive.
    ``current.frame`` is always the last accepted frame; a packet is decoded into a
    spare and swapped in only once decoded and accepted.

    Label changes (``protocols/PROTOCOLS.md``, "Label sets"): an announcement with a
    new id is adopted at once (its frames restart the sequence). One that changes the
    names under the id in use (a frame carrying it accepted within ``restart_gap_ns``)
    is a *conflict*: counted ``conflicting_labels`` and kept as ``pending_labels``;
    the names in use stay in effect, so frames carrying the id go on being decoded
    with them (no gap in the stream), until a clean boundary: the old names
    announced again (the conflicting one was stray), a new id announced, or the new
    names announced again at least ``restart_gap_ns`` after the conflict began (the
    sender really changed them; adopted, the next frame a restart). A sender that
    changes its names must use a new id (PROTOCOLS.md): until it does, its frames are
    read with the names it announced first.

    Args:
        label_set: the configured labels (simple form), or None until the sender
            announces them (compact OSC, ZeroMQ).
        up_axis: the sender's up axis.
        units: the sender's length unit.
        restart_gap_ns: see :class:`FrameSequencer`.
        max_rate_hz: see :class:`FrameSequencer`.
        max_markers: label sets with more markers are refused
            (``too_many_markers``).
        zero_is_occluded: see :class:`MarkerPacket`.
        max_coordinate_m: see :class:`MarkerPacket` (:data:`MAX_COORDINATE_M`).
    """

    def __init__(
        self,
        label_set: LabelSet | None = None,
        up_axis: str = "+Z",
        units: str = "m",
        restart_gap_ns: int = RESTART_GAP_NS,
        *,
        max_rate_hz: float = MAX_RATE_HZ,
        max_markers: int = MAX_MARKERS,
        zero_is_occluded: bool = True,
        max_coordinate_m: float = MAX_COORDINATE_M,
    ) -> None:
        initial = label_set if label_set is not None else LabelSet(-1, ())
        self.label_set: LabelSet | None = label_set
        #: (1,) markers occluded for a coordinate past ``max_coordinate_m``.
        self.implausible = np.zeros(1, dtype=np.int64)
        args = (up_axis, units, zero_is_occluded, max_coordinate_m, self.implausible)
        self.current = MarkerPacket.create(initial, *args)
        self._spare = MarkerPacket.create(initial, *args)
        self.sequencer = FrameSequencer(restart_gap_ns, max_rate_hz)
        self.counters = DropCounters()
        self.last_error: DecodeError | None = None
        self.max_markers = max_markers
        self.pending_labels: LabelSet | None = None  # a conflicting announcement
        #: Announcements taken: adopted, or confirming the names in use (the refused
        #: and conflicting ones are counted by reason), so packets in = counts -
        #: ``unknown_label`` (markers, not packets) + ``labels_taken``.
        self.labels_taken = 0
        self._pending_since_ns = 0
        # feed_packed: the packet's source time (written by the compiled call), the
        # call's stream arguments, and the call (its compiled function once typed).
        self._source_time = np.zeros(1)
        seq = self.sequencer
        self._feed_tail = (seq.q, seq.qf, self.counters.counts, self._source_time)
        self._feed_call: Any = kernels.feed_frame
        #: The live loop's one compiled call per frame for this stream, while armed
        #: (``daemon/live/one_call.py``, ``FastFrame``; None: the feed, then the frame).
        self.fast: Any = None
        #: ``(form, head, payload)``: the ``kernels.FORM_*`` and the receive buffers
        #: of a live input that feeds it with :meth:`feed_packed` (set by the
        #: loop's inputs), else None.
        self.wire: tuple[int, np.ndarray, np.ndarray] | None = None

    def _in_use(self, t_ns: int | None) -> bool:
        """Whether frames carrying the current id were accepted recently (within the
        restart gap of ``t_ns``; ever, when ``t_ns`` is None)."""
        seq = self.sequencer
        assert self.label_set is not None
        if seq.last_label_set_id != self.label_set.id:
            return False
        counts = self.counters.counts
        if not counts[ACCEPTED] + counts[RESTART]:
            return False
        return t_ns is None or t_ns - seq.last_t_ns < seq.restart_gap_ns

    def set_labels(self, label_set: LabelSet, t_ns: int | None = None) -> bool:
        """Take a label announcement; True when it is adopted as a new label set.

        Args:
            label_set: the announced set.
            t_ns: ``time.monotonic_ns()`` at receive (None: offline, no clock).
        """
        if len(label_set.labels) > self.max_markers:
            self.counters.add(TOO_MANY_MARKERS)
            return False
        current = self.label_set
        if label_set == current:
            self.pending_labels = None  # the sender confirms the names in use
            self.labels_taken += 1
            return False
        if current is None or label_set.id != current.id or not self._in_use(t_ns):
            self._adopt(label_set)
            return True
        now = self.sequencer.last_t_ns if t_ns is None else t_ns
        if (
            label_set == self.pending_labels
            and now - self._pending_since_ns >= self.sequencer.restart_gap_ns
        ):
            self._adopt(label_set)
            return True
        if label_set != self.pending_labels:
            self.pending_labels = label_set
            self._pending_since_ns = now
        self.counters.add(CONFLICTING_LABELS)
        return False

    def _adopt(self, label_set: LabelSet) -> None:
        self.labels_taken += 1
        same_id = self.label_set is not None and self.label_set.id == label_set.id
        self.label_set = label_set
        self.pending_labels = None
        if same_id:  # new names, same id: the sequence restarts at the next frame
            self.sequencer.restart_next()

    def feed_packed(
        self,
        form: int,
        head: np.ndarray,
        n_head: int,
        payload: np.ndarray,
        n_payload: int,
        t_ns: int,
    ) -> int:
        """:meth:`feed` of a compact OSC frame or a ZeroMQ frame (``form``:
        ``kernels.FORM_*``) in one compiled call (``kernels.feed_frame``): the
        decode into the spare packet, the sequencer and the outcome's counter;
        Python only swaps the packets. The live loop's drains call it per frame.

        Args:
            head, payload: writable, contiguous uint8 arrays over the receive
                buffers (their type is fixed by the first call: the compiled
                function is then called past numba's dispatcher), the datagram or
                the header part in ``head[:n_head]``, the ZeroMQ payload in
                ``payload[:n_payload]`` (OSC: unused).
            t_ns: ``time.monotonic_ns()`` at receive.

        Returns:
            As :meth:`feed` when the packet decoded (``ACCEPTED``, ``RESTART`` or
            the sequencer's refusal, counted); a negative ``kernels.D_*`` code,
            nothing counted and nothing changed, when the compiled checks refused
            it: :meth:`feed` with the Python decoder then says why and counts it.
        """
        label_set = self.label_set
        if label_set is None:
            self.counters.add(UNKNOWN_LABEL_SET)
            return UNKNOWN_LABEL_SET
        spare = self._spare
        if spare.label_set is not label_set:
            spare = self._spare = spare.with_label_set(label_set)
        code, frame_id, source_t = self._feed_call(
            form, head, n_head, payload, n_payload, t_ns, label_set.id,
            *spare.packed_args, *self._feed_tail,
        )  # fmt: skip
        if self._feed_call is kernels.feed_frame:  # its types known now: direct
            self._feed_call = kernels.direct(
                kernels.feed_frame, form, head, n_head, payload, n_payload, t_ns,
                label_set.id, *spare.packed_args, *self._feed_tail,
            )  # fmt: skip
        return self.take(code, frame_id, source_t, t_ns)

    def take(self, code: int, frame_id: int, source_t: float, t_ns: int) -> int:
        """The end of :meth:`feed_packed` after its compiled call (``code``, the
        frame number and the source time it returned): an accepted frame (``ACCEPTED``
        or ``RESTART``) in the spare packet swapped in as ``current``; ``code``
        returned. Also the end of a call that fed the spare inside a larger one
        (the live loop's ``one_call.FastFrame.run``)."""
        if code > RESTART or code < 0:
            return code
        spare = self._spare
        frame = spare.frame
        frame.frame_id = frame_id
        frame.source_time_s = source_t
        frame.t_ns = t_ns
        assert self.label_set is not None
        spare.label_set_id = self.label_set.id
        spare.unknown_labels = 0
        self._spare, self.current = self.current, spare
        return code

    def packets(self) -> tuple[MarkerPacket, MarkerPacket]:
        """The two packets (``current``, then the spare the next packet decodes
        into), the spare re-targeted at the label set now, as :meth:`feed_packed`
        does before its decode (not for the hot path). Their arrays are fixed until
        the label set changes."""
        assert self.label_set is not None
        if self._spare.label_set is not self.label_set:
            self._spare = self._spare.with_label_set(self.label_set)
        return self.current, self._spare

    def spare_packet(self) -> MarkerPacket:
        """The packet the next frame packet decodes into."""
        return self._spare

    def fused_tail(
        self, form: int, head: np.ndarray, payload: np.ndarray, packet: MarkerPacket
    ) -> tuple[Any, ...]:
        """``kernels.feed_frame``'s arguments but the packet's sizes and receive
        time, for a feed into ``packet`` (one of :meth:`packets`), in order:
        ``form, head, payload, label_set_id, *packet.packed_args, q, qf, counts,
        source_time`` (``live/solve_emit.py``'s one call per frame takes them)."""
        assert self.label_set is not None
        return (form, head, payload, self.label_set.id, *packet.packed_args,
                *self._feed_tail)  # fmt: skip

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
        # A conflicting announcement pending: the names in use stay in effect (the
        # new ones take effect only at a clean boundary), so the stream goes on.
        code = self.sequencer.check(spare.frame.frame_id, spare.label_set_id, t_ns)
        self.counters.add(code)
        if code > RESTART:
            return code
        if spare.unknown_labels:
            self.counters.add(UNKNOWN_LABEL, spare.unknown_labels)
        spare.frame.t_ns = t_ns
        self._spare, self.current = self.current, spare
        return code
