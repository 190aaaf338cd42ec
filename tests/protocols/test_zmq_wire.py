"""ZeroMQ marker input: golden parts, round trips, fuzzing."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from retargetd.protocols import zmq_wire
from retargetd.protocols.errors import DecodeError
from retargetd.protocols.marker_input import REASON_INDEX, LabelSet, MarkerPacket

NAN = float("nan")
LABELS = LabelSet(3, ("LASI", "RASI"))
GOLDEN_HEADER = (
    b"RTDM\x01\x00\x00\x00"  # magic, version 1, flags 0
    b"\x07\x00\x00\x00\x00\x00\x00\x00"  # frame number 7
    b"\x00\x00\x00\x00\x00\x00\xe0?"  # source time 0.5
    b"\x03\x00\x00\x00\x02\x00\x00\x00"  # label set 3, 2 markers
)
GOLDEN_PAYLOAD = (
    b"\x00\x00\x80?\x00\x00\x00@\x00\x00@@"  # 1.0 2.0 3.0
    b"\x00\x00\xc0\x7f\x00\x00\xc0\x7f\x00\x00\xc0\x7f"  # NaN NaN NaN
)
GOLDEN_LABELS = [b"RTDL\x01\x00\x00\x00\x03\x00\x00\x00\x02\x00\x00\x00", b"LASI\nRASI"]


def test_golden_parts() -> None:
    pos = np.array([[1.0, 2.0, 3.0], [NAN, NAN, NAN]])
    assert zmq_wire.encode_zmq_frame(7, 0.5, 3, pos) == [GOLDEN_HEADER, GOLDEN_PAYLOAD]
    assert zmq_wire.encode_zmq_labels(LABELS) == GOLDEN_LABELS
    assert zmq_wire.decode_zmq_labels(*GOLDEN_LABELS) == LABELS
    out = MarkerPacket.create(LABELS, "+Z", "m")
    markers = out.frame.markers_world
    assert (
        zmq_wire.decode_zmq_frame(GOLDEN_HEADER, memoryview(GOLDEN_PAYLOAD), out) is out
    )
    assert out.frame.markers_world is markers and markers.dtype == np.float64
    assert (out.frame.frame_id, out.frame.source_time_s) == (7, 0.5)
    np.testing.assert_array_equal(markers[0], [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(out.frame.valid, [True, False])


def _with(buf: bytes, offset: int, fmt: str, value: object) -> bytes:
    data = bytearray(buf)
    struct.pack_into(fmt, data, offset, value)
    return bytes(data)


@pytest.mark.parametrize(
    ("header", "payload", "reason"),
    [
        (GOLDEN_HEADER[:31], GOLDEN_PAYLOAD, "bad_length"),
        (b"RTDX" + GOLDEN_HEADER[4:], GOLDEN_PAYLOAD, "bad_magic"),
        (_with(GOLDEN_HEADER, 4, "<H", 2), GOLDEN_PAYLOAD, "bad_version"),
        (GOLDEN_HEADER, GOLDEN_PAYLOAD[:-1], "bad_length"),
        (_with(GOLDEN_HEADER, 28, "<I", 3), GOLDEN_PAYLOAD, "bad_length"),
        (_with(GOLDEN_HEADER, 24, "<I", 4), GOLDEN_PAYLOAD, "unknown_label_set"),
        (_with(GOLDEN_HEADER, 8, "<q", -1), GOLDEN_PAYLOAD, "bad_frame_number"),
        (_with(GOLDEN_HEADER, 16, "<d", float("inf")), GOLDEN_PAYLOAD, "non_finite"),
        (GOLDEN_HEADER, _with(GOLDEN_PAYLOAD, 4, "<f", float("inf")), "non_finite"),
    ],
)
def test_malformed_frames(header: bytes, payload: bytes, reason: str) -> None:
    with pytest.raises(DecodeError) as info:
        zmq_wire.decode_zmq_frame(header, payload, MarkerPacket.create(LABELS))
    assert info.value.reason == reason


def test_count_mismatch() -> None:
    header, payload = zmq_wire.encode_zmq_frame(1, 0.0, 3, np.zeros((1, 3)))
    with pytest.raises(DecodeError, match="count_mismatch"):
        zmq_wire.decode_zmq_frame(header, payload, MarkerPacket.create(LABELS))


@pytest.mark.parametrize(
    ("parts", "reason"),
    [
        ([GOLDEN_LABELS[0][:15], b"A"], "bad_length"),
        ([b"RTDM" + GOLDEN_LABELS[0][4:], b"A"], "bad_magic"),
        ([_with(GOLDEN_LABELS[0], 4, "<H", 9), b"A"], "bad_version"),
        ([GOLDEN_LABELS[0], b"A\nB\nC"], "bad_count"),
        ([GOLDEN_LABELS[0], b"A\nA"], "bad_label"),
        ([GOLDEN_LABELS[0], b"A\n"], "bad_label"),
        ([GOLDEN_LABELS[0], b"\xff\nA"], "bad_string"),
    ],
)
def test_malformed_labels(parts: list[bytes], reason: str) -> None:
    with pytest.raises(DecodeError) as info:
        zmq_wire.decode_zmq_labels(*parts)
    assert info.value.reason == reason


def _mutate(base: bytes) -> st.SearchStrategy[bytes]:
    return st.one_of(
        st.binary(max_size=64),
        st.builds(lambda n: base[:n], st.integers(0, len(base))),
        st.builds(
            lambda i, v: base[:i] + bytes([v]) + base[i + 1 :],
            st.integers(0, len(base) - 1),
            st.integers(0, 255),
        ),
    )


@settings(max_examples=300)
@given(_mutate(GOLDEN_HEADER), _mutate(GOLDEN_PAYLOAD))
def test_frame_decoder_raises_only_decode_error(header: bytes, payload: bytes) -> None:
    out = MarkerPacket.create(LABELS)
    try:
        assert zmq_wire.decode_zmq_frame(header, payload, out) is out
    except DecodeError as exc:
        assert exc.reason in REASON_INDEX


@settings(max_examples=300)
@given(_mutate(GOLDEN_LABELS[0]), _mutate(GOLDEN_LABELS[1]))
def test_labels_decoder_raises_only_decode_error(header: bytes, payload: bytes) -> None:
    try:
        zmq_wire.decode_zmq_labels(header, payload)
    except DecodeError as exc:
        assert exc.reason in REASON_INDEX
