"""Implausible coordinates (issue 30 item 3): a marker with a world coordinate past
``max_coordinate_m`` is occluded and counted in every marker form, on the packet's
world metres (after the input's units). The daemon's status count:
``tests/daemon/test_accounting.py``."""

from __future__ import annotations

import numpy as np
import pytest

from retargetd.protocols import osc_in, zmq_wire
from retargetd.protocols.marker_input import (
    MAX_COORDINATE_M,
    LabelSet,
    MarkerPacket,
    MarkerStream,
)

LABELS = LabelSet(3, ("A", "B", "C", "D", "E"))
#: a marker at 1e30 (finite in float32), one 1.5 km up, one 999.9 m out, two plain
ROWS = np.array(
    [[1e30, 0.0, 0.0], [0.0, 0.0, 1500.0], [999.9, 0.0, 0.0], [0.1, 0.2, 0.3],
     [0.0, -0.5, 1.0]]
)  # fmt: skip
KEPT = np.array([False, False, True, True, True])


def _decoded(form: str, packet: MarkerPacket, rows: np.ndarray) -> MarkerPacket:
    if form == "compact":
        return osc_in.decode_compact_frame(
            osc_in.encode_compact_frame(7, 0.1, LABELS.id, rows), packet
        )
    if form == "simple":
        buf = osc_in.encode_simple_bundle(LABELS.labels, rows, frame_id=7)
        return osc_in.decode_simple_bundle(buf, packet)
    header, payload = zmq_wire.encode_zmq_frame(7, 0.1, LABELS.id, rows)
    return zmq_wire.decode_zmq_frame(header, payload, packet)


@pytest.mark.parametrize("form", ["compact", "simple", "zmq"])
def test_far_markers_are_occluded_and_counted(form: str) -> None:
    assert MAX_COORDINATE_M == 1000.0
    packet = MarkerPacket.create(LABELS)
    out = _decoded(form, packet, ROWS)
    np.testing.assert_array_equal(out.frame.valid, KEPT)
    assert np.isnan(out.frame.markers_world[~KEPT]).all()
    np.testing.assert_allclose(out.frame.markers_world[KEPT], ROWS[KEPT], rtol=1e-6)
    assert packet.implausible[0] == 2
    _decoded(form, packet, ROWS)
    assert packet.implausible[0] == 4  # counted per marker, per frame


def test_the_bound_is_in_world_metres() -> None:
    # 1500 in millimetres is 1.5 m: kept; a lower bound of 1 m drops it
    mm = MarkerPacket.create(LABELS, units="mm")
    out = _decoded("compact", mm, np.where(np.abs(ROWS) > 1e20, 0.0, ROWS))
    assert out.frame.valid[1] and mm.implausible[0] == 0
    tight = MarkerPacket.create(LABELS, units="mm", max_coordinate_m=1.0)
    _decoded("compact", tight, np.where(np.abs(ROWS) > 1e20, 0.0, ROWS))
    assert tight.implausible[0] == 1  # 1.5 m is past 1 m; 999.9 mm is not


def test_a_stream_shares_its_counter_across_label_sets() -> None:
    stream = MarkerStream(LABELS)
    assert stream.current.implausible is stream.implausible
    assert stream._spare.implausible is stream.implausible
    grown = stream.current.with_label_set(LabelSet(4, (*LABELS.labels, "F")))
    assert grown.implausible is stream.implausible
