"""Sequencer rules, drop counters, and a stream with bad packets between good ones."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from retargetd.protocols import marker_input as mi
from retargetd.protocols import osc_in, zmq_wire
from retargetd.protocols.errors import DecodeError

SEC = 1_000_000_000


def test_sequencer_forward_duplicate_backwards() -> None:
    seq = mi.FrameSequencer()
    assert seq.check(10, 1, 0) == mi.ACCEPTED
    assert seq.check(11, 1, 1000) == mi.ACCEPTED
    assert seq.check(11, 1, 2000) == mi.DUPLICATE
    assert seq.check(5, 1, 3000) == mi.BACKWARDS
    assert seq.check(12, 1, 4000) == mi.ACCEPTED
    assert seq.last_frame == 12


def test_restart_after_a_one_second_gap() -> None:
    seq = mi.FrameSequencer()
    assert seq.check(500, 1, 0) == mi.ACCEPTED
    assert seq.check(3, 1, SEC - 1) == mi.BACKWARDS  # not yet a gap
    assert seq.check(3, 1, SEC) == mi.RESTART  # >= 1 s since the last accepted
    assert seq.check(4, 1, SEC + 1) == mi.ACCEPTED  # state was reset to frame 3
    assert seq.check(4, 1, 3 * SEC) == mi.RESTART  # equal after a gap: restarted


def test_restart_on_a_new_label_set() -> None:
    seq = mi.FrameSequencer()
    seq.check(500, 1, 0)
    assert seq.check(0, 2, 10) == mi.RESTART
    assert seq.check(1, 2, 20) == mi.ACCEPTED
    assert seq.check(2, 3, 30) == mi.ACCEPTED  # forward with a new set: not a restart


def test_frames_without_numbers_are_accepted_unordered() -> None:
    seq = mi.FrameSequencer()
    assert seq.check(-1, 0, 0) == mi.ACCEPTED
    assert seq.check(-1, 0, 1) == mi.ACCEPTED


def test_counters_by_reason() -> None:
    counters = mi.DropCounters()
    counters.add(mi.ACCEPTED)
    counters.add(mi.BACKWARDS, 2)
    counters.add_reason("bad_length")
    counters.add_reason("no_such_reason")
    assert counters["backwards"] == 2 and counters["other"] == 1
    assert counters.dropped() == 4
    assert counters.as_dict() == {
        "accepted": 1,
        "backwards": 2,
        "bad_length": 1,
        "other": 1,
    }


def test_label_sets_refuse_bad_names() -> None:
    with pytest.raises(DecodeError, match="bad_label"):
        mi.LabelSet(1, ("A", "A"))
    with pytest.raises(DecodeError, match="bad_label"):
        mi.LabelSet(1, ("A\nB",))


def test_stream_solves_every_good_frame_around_bad_ones() -> None:
    labels = mi.LabelSet(7, ("A", "B", "C"))
    stream = mi.MarkerStream(up_axis="+Y", units="mm")
    pos = np.arange(9.0).reshape(3, 3)
    frame = osc_in.encode_compact_frame
    # Before the labels are announced, frames cannot be interpreted.
    assert (
        stream.feed(osc_in.decode_compact_frame, frame(1, 0.0, 7, pos), t_ns=0)
        == (mi.REASON_INDEX["unknown_label_set"])
    )
    assert stream.set_labels(osc_in.decode_labels(osc_in.encode_labels(labels)))
    assert not stream.set_labels(labels)
    packets = [
        (frame(1, 0.0, 7, pos), mi.ACCEPTED),
        (frame(2, 0.0, 7, pos)[:-1], mi.REASON_INDEX["bad_length"]),
        (frame(2, 0.0, 7, pos + 1), mi.ACCEPTED),
        (frame(2, 0.0, 7, pos + 9), mi.DUPLICATE),
        (frame(1, 0.0, 7, pos + 9), mi.BACKWARDS),
        (frame(3, 0.0, 8, pos + 9), mi.REASON_INDEX["unknown_label_set"]),
        (frame(3, 0.0, 7, pos[:2]), mi.REASON_INDEX["count_mismatch"]),
        (frame(3, 0.0, 7, pos + 2), mi.ACCEPTED),
    ]
    for i, (packet, expected) in enumerate(packets):
        assert stream.feed(osc_in.decode_compact_frame, packet, t_ns=i) == expected
    # The last accepted frame survived the bad ones after it... and is frame 3.
    assert stream.current.frame.frame_id == 3 and stream.current.frame.t_ns == 7
    np.testing.assert_allclose(
        stream.current.frame.markers_world[0], [0.002, -0.004, 0.003]
    )
    assert stream.counters["accepted"] == 3 and stream.counters.dropped() == 6
    assert stream.last_error is not None

    # A new label set of another size, with frame numbers restarting: a restart.
    bigger = mi.LabelSet(9, ("A", "B", "C", "D"))
    stream.set_labels(bigger)
    header, payload = zmq_wire.encode_zmq_frame(0, 0.0, 9, np.zeros((4, 3)))
    assert (
        stream.feed(zmq_wire.decode_zmq_frame, header, payload, t_ns=100) == mi.RESTART
    )
    assert stream.current.frame.markers_world.shape == (4, 3)
    assert stream.current.label_set is bigger


def test_stream_counts_unknown_simple_labels_and_keeps_the_frame() -> None:
    stream = mi.MarkerStream(mi.LabelSet(0, ("A", "B")))
    packet = osc_in.encode_simple_bundle(["A", "Z"], np.ones((2, 3)), 5)
    assert stream.feed(osc_in.decode_simple_bundle, packet, t_ns=1) == mi.ACCEPTED
    assert stream.counters["unknown_label"] == 1 and stream.counters.dropped() == 0
    np.testing.assert_array_equal(stream.current.frame.valid, [True, False])


# ---- hijack resistance (issue 12) --------------------------------------------------

MS = 1_000_000


def test_an_implausible_jump_is_dropped_and_the_stream_goes_on() -> None:
    seq = mi.FrameSequencer()
    for k in range(10):
        assert seq.check(100 + k, 1, k * 4 * MS) == mi.ACCEPTED  # 240 Hz-ish
    assert seq.check(2**62, 1, 41 * MS) == mi.IMPLAUSIBLE_JUMP
    assert seq.check(110, 1, 42 * MS) == mi.ACCEPTED  # the genuine frames go on
    # A flipped bit 30 in the frame number: far beyond 10 kHz x (elapsed + 0.1 s).
    assert seq.check(111 | 1 << 30, 1, 46 * MS) == mi.IMPLAUSIBLE_JUMP
    assert seq.check(111, 1, 47 * MS) == mi.ACCEPTED
    assert seq.last_frame == 111


def test_the_bound_grows_with_elapsed_time_and_the_configured_rate() -> None:
    seq = mi.FrameSequencer(max_rate_hz=100.0)
    assert seq.check(0, 1, 0) == mi.ACCEPTED
    # 100 Hz x (0 + 0.1 s) + 1 = 11 frames allowed at once; 12 is not.
    assert seq.check(12, 1, 0) == mi.IMPLAUSIBLE_JUMP
    assert seq.check(11, 1, 0) == mi.ACCEPTED
    # 2 s later: 100 x 2.1 + 1 = 211 more.
    assert seq.check(11 + 212, 1, 2 * SEC) == mi.IMPLAUSIBLE_JUMP
    assert seq.check(11 + 211, 1, 2 * SEC) == mi.ACCEPTED
    with pytest.raises(ValueError):
        mi.FrameSequencer(max_rate_hz=0.0)


def test_a_jumped_sequence_that_continues_alone_is_adopted_as_a_restart() -> None:
    seq = mi.FrameSequencer()
    assert seq.check(5, 1, 0) == mi.ACCEPTED
    base = 10**12  # the source seeked far ahead (no gap)
    assert seq.check(base, 1, 4 * MS) == mi.IMPLAUSIBLE_JUMP
    assert seq.check(base + 1, 1, 8 * MS) == mi.IMPLAUSIBLE_JUMP
    assert seq.check(base + 2, 1, 12 * MS) == mi.RESTART  # 3 in a row: adopted
    assert seq.check(base + 3, 1, 16 * MS) == mi.ACCEPTED
    # Interleaved with the accepted sequence, a jumped one never takes over.
    for k in range(10):
        assert seq.check(base + 4 + k, 1, (20 + 8 * k) * MS) == mi.ACCEPTED
        assert seq.check(2**62 + k, 1, (24 + 8 * k) * MS) == mi.IMPLAUSIBLE_JUMP


def test_a_spoofed_first_frame_costs_only_the_confirmation_frames() -> None:
    seq = mi.FrameSequencer()
    assert seq.check(2**62, 1, 0) == mi.ACCEPTED  # nothing to compare it with
    assert seq.check(0, 1, 4 * MS) == mi.BACKWARDS
    assert seq.check(1, 1, 8 * MS) == mi.BACKWARDS
    assert seq.check(2, 1, 12 * MS) == mi.RESTART  # not 1 s of "backwards"
    assert seq.check(3, 1, 16 * MS) == mi.ACCEPTED


def test_a_new_label_set_id_is_a_clean_boundary_for_any_number() -> None:
    seq = mi.FrameSequencer()
    assert seq.check(5, 1, 0) == mi.ACCEPTED
    assert seq.check(2**40, 2, MS) == mi.RESTART


NAMES = ("A", "B", "C")
ROTATED = ("B", "C", "A")


def _stream_with_frames() -> tuple[mi.MarkerStream, list[bytes]]:
    stream = mi.MarkerStream()
    assert stream.set_labels(mi.LabelSet(1, NAMES), 0)
    frames = [
        osc_in.encode_compact_frame(k, 0.0, 1, np.full((3, 3), 1.0 + k))
        for k in range(40)
    ]
    for k in range(3):
        assert stream.feed(osc_in.decode_compact_frame, frames[k], t_ns=k * MS) < 2
    return stream, frames


def test_renamed_labels_under_an_id_in_use_are_a_conflict_until_reannounced() -> None:
    stream, frames = _stream_with_frames()
    feed = osc_in.decode_compact_frame
    assert not stream.set_labels(mi.LabelSet(1, ROTATED), 3 * MS)
    assert stream.label_set == mi.LabelSet(1, NAMES)  # not adopted
    assert stream.pending_labels == mi.LabelSet(1, ROTATED)
    # The names in use stay in effect: the frame is read with them, no gap.
    assert stream.feed(feed, frames[3], t_ns=4 * MS) == mi.ACCEPTED
    assert stream.current.frame.frame_id == 3
    assert stream.current.label_set.labels == NAMES
    # The sender announces its real names again: the conflict is over.
    assert not stream.set_labels(mi.LabelSet(1, NAMES), 5 * MS)
    assert stream.pending_labels is None
    assert stream.feed(feed, frames[4], t_ns=6 * MS) == mi.ACCEPTED
    assert stream.counters["conflicting_labels"] == 1
    assert stream.counters["label_conflict"] == 0  # nothing dropped


def test_renamed_labels_that_persist_are_adopted_with_a_restart() -> None:
    stream, frames = _stream_with_frames()
    feed = osc_in.decode_compact_frame
    assert not stream.set_labels(mi.LabelSet(1, ROTATED), 3 * MS)
    assert stream.feed(feed, frames[3], t_ns=4 * MS) == mi.ACCEPTED  # old names
    # Announced again under 1 s later: still a conflict.
    assert not stream.set_labels(mi.LabelSet(1, ROTATED), 500 * MS)
    assert stream.feed(feed, frames[4], t_ns=501 * MS) == mi.ACCEPTED
    assert stream.current.label_set.labels == NAMES
    # Again >= 1 s after the conflict began, no old-name frame accepted since.
    assert stream.set_labels(mi.LabelSet(1, ROTATED), 3 * MS + SEC)
    assert stream.label_set == mi.LabelSet(1, ROTATED)
    assert stream.feed(feed, frames[5], t_ns=4 * MS + SEC) == mi.RESTART
    assert stream.current.label_set.labels == ROTATED
    assert stream.counters["conflicting_labels"] == 2


def test_renamed_labels_with_a_new_id_or_after_the_source_stopped_are_adopted() -> None:
    stream, _ = _stream_with_frames()
    assert stream.set_labels(mi.LabelSet(2, ROTATED), 3 * MS)  # new id: at once
    stream2, _ = _stream_with_frames()
    # Same id, but nothing carried it for >= 1 s: a restarted source, adopted.
    assert stream2.set_labels(mi.LabelSet(1, ROTATED), 2 * MS + SEC)
    assert stream.counters["conflicting_labels"] == 0
    assert stream2.counters["conflicting_labels"] == 0


def test_label_sets_over_max_markers_are_refused_before_decoding() -> None:
    stream = mi.MarkerStream(max_markers=2)
    assert not stream.set_labels(mi.LabelSet(1, NAMES))
    assert stream.label_set is None and stream.counters["too_many_markers"] == 1
    header, payload = zmq_wire.encode_zmq_labels(mi.LabelSet(1, NAMES))
    with pytest.raises(DecodeError, match="too_many_markers"):
        # The payload is never read: garbage after the header does not matter.
        zmq_wire.decode_zmq_labels(header, b"\xff" * len(payload), max_markers=2)


@pytest.mark.parametrize("zero", [0.0, -0.0])
def test_exact_zero_rows_are_occluded_unless_configured_otherwise(zero: float) -> None:
    labels = mi.LabelSet(1, NAMES)
    pos = np.array([[zero, zero, zero], [0.0, 0.0, 0.5], [1.0, 2.0, 3.0]])
    packet = osc_in.encode_compact_frame(1, 0.0, 1, pos)
    out = osc_in.decode_compact_frame(packet, mi.MarkerPacket.create(labels))
    np.testing.assert_array_equal(out.frame.valid, [False, True, True])
    assert np.isnan(out.frame.markers_world[0]).all()
    simple = osc_in.encode_simple_bundle(NAMES, pos, 1)
    out = osc_in.decode_simple_bundle(simple, mi.MarkerPacket.create(labels))
    np.testing.assert_array_equal(out.frame.valid, [False, True, True])
    kept = mi.MarkerPacket.create(labels, zero_is_occluded=False)
    out = osc_in.decode_compact_frame(packet, kept)
    np.testing.assert_array_equal(out.frame.valid, [True, True, True])
    np.testing.assert_array_equal(out.frame.markers_world[0], [0.0, 0.0, 0.0])


@given(
    steps=st.lists(st.integers(1, 3), min_size=5, max_size=60),
    strays=st.dictionaries(
        st.integers(0, 59),
        st.integers(-900, -1) | st.integers(2_000, 2**62),
        max_size=8,
    ),
)
def test_single_stray_frames_never_cost_a_genuine_frame(
    steps: list[int], strays: dict[int, int]
) -> None:
    """A genuine source at 240 Hz (frame numbers stepping by 1-3), with one stray frame
    (backwards, or beyond the plausible advance) before some of its frames: no stray
    frame is accepted and every genuine frame is."""
    seq = mi.FrameSequencer()
    frame, t_ns = 1000, 0
    assert seq.check(frame, 1, t_ns) == mi.ACCEPTED
    for i, step in enumerate(steps):
        t_ns += 4_166_667
        if i in strays:
            code = seq.check(frame + strays[i], 1, t_ns)
            assert code in (mi.BACKWARDS, mi.IMPLAUSIBLE_JUMP)
        frame += step
        assert seq.check(frame, 1, t_ns + 1000) == mi.ACCEPTED
