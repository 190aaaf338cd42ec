"""Sequencer rules, drop counters, and a stream with bad packets between good ones."""

from __future__ import annotations

import numpy as np
import pytest

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
