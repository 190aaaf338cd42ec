"""OSC marker input: golden datagrams, round trips, a python-osc sender, fuzzing."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from pythonosc.osc_message_builder import OscMessageBuilder

from retargetd.protocols import osc_in
from retargetd.protocols.errors import DecodeError
from retargetd.protocols.marker_input import (
    MAX_COORDINATE_M,
    REASON_INDEX,
    LabelSet,
    MarkerPacket,
)
from retargetd.protocols.osc_wire import build_bundle, build_message

NAN = float("nan")
LABELS = LabelSet(3, ("LASI", "RASI"))
POSITIONS = np.array([[1.0, 2.0, 3.0], [NAN, NAN, NAN]])

# Frame 7, source time 0.5 s, label set 3, markers (1, 2, 3) and occluded.
GOLDEN_COMPACT = (
    b"/rtd/frame\x00\x00,hdiib\x00\x00"
    b"\x00\x00\x00\x00\x00\x00\x00\x07"  # frame number, int64
    b"?\xe0\x00\x00\x00\x00\x00\x00"  # source time 0.5, float64
    b"\x00\x00\x00\x03"  # label-set id
    b"\x00\x00\x00\x02"  # marker count
    b"\x00\x00\x00\x18"  # blob size 24
    b"?\x80\x00\x00@\x00\x00\x00@@\x00\x00"  # 1.0 2.0 3.0
    b"\x7f\xc0\x00\x00\x7f\xc0\x00\x00\x7f\xc0\x00\x00"  # NaN NaN NaN
)
GOLDEN_LABELS = (
    b"/rtd/labels\x00,iiss\x00\x00\x00"
    b"\x00\x00\x00\x03\x00\x00\x00\x02"
    b"LASI\x00\x00\x00\x00RASI\x00\x00\x00\x00"
)
GOLDEN_SIMPLE = (
    b"#bundle\x00\x00\x00\x00\x00\x00\x00\x00\x01"
    b"\x00\x00\x00\x20/rtd/frame_number\x00\x00\x00,h\x00\x00"
    b"\x00\x00\x00\x00\x00\x00\x00\x07"
    b"\x00\x00\x00\x28/rtd/marker\x00,sfff\x00\x00\x00LASI\x00\x00\x00\x00"
    b"?\x80\x00\x00@\x00\x00\x00@@\x00\x00"
    b"\x00\x00\x00\x28/rtd/marker\x00,sfff\x00\x00\x00RASI\x00\x00\x00\x00"
    b"\x7f\xc0\x00\x00\x7f\xc0\x00\x00\x7f\xc0\x00\x00"
)


def _packet(
    up: str = "+Z", units: str = "m", labels: LabelSet = LABELS
) -> MarkerPacket:
    return MarkerPacket.create(labels, up, units)


def test_encoders_write_the_golden_datagrams() -> None:
    assert osc_in.encode_compact_frame(7, 0.5, 3, POSITIONS) == GOLDEN_COMPACT
    assert osc_in.encode_labels(LABELS) == GOLDEN_LABELS
    assert osc_in.encode_simple_bundle(LABELS.labels, POSITIONS, 7) == GOLDEN_SIMPLE


def test_golden_compact_decodes_into_world_metres() -> None:
    out = _packet("+Y", "mm")
    markers, valid = out.frame.markers_world, out.frame.valid
    result = osc_in.decode_compact_frame(GOLDEN_COMPACT, out)
    assert result is out
    assert out.frame.markers_world is markers and out.frame.valid is valid
    assert markers.dtype == np.float64 and valid.dtype == np.bool_
    assert (out.frame.frame_id, out.frame.source_time_s, out.label_set_id) == (
        7,
        0.5,
        3,
    )
    # Y-up mm: capture (x, y, z) -> world (x, -z, y) / 1000.
    np.testing.assert_allclose(markers[0], [0.001, -0.003, 0.002])
    assert np.isnan(markers[1]).all()
    np.testing.assert_array_equal(valid, [True, False])


def test_golden_labels_and_simple_bundle() -> None:
    assert osc_in.decode_labels(GOLDEN_LABELS) == LABELS
    out = _packet()
    assert osc_in.decode_simple_bundle(GOLDEN_SIMPLE, out) is out
    assert out.frame.frame_id == 7 and np.isnan(out.frame.source_time_s)
    np.testing.assert_array_equal(out.frame.markers_world[0], [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(out.frame.valid, [True, False])


def test_python_osc_sender_decodes() -> None:
    """A third-party sender (python-osc's builder) works with our hot decoder."""
    builder = OscMessageBuilder(osc_in.COMPACT_ADDRESS)
    blob = np.array([[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]], dtype=">f4").tobytes()
    for value, tag in ((42, "h"), (12.5, "d"), (3, "i"), (2, "i"), (blob, "b")):
        builder.add_arg(value, tag)
    out = osc_in.decode_compact_frame(builder.build().dgram, _packet())
    assert out.frame.frame_id == 42 and out.frame.source_time_s == 12.5
    np.testing.assert_allclose(
        out.frame.markers_world, np.float32([[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]])
    )


def test_partly_nan_row_is_occluded() -> None:
    pos = np.array([[1.0, NAN, 3.0], [4.0, 5.0, 6.0]])
    out = osc_in.decode_compact_frame(
        osc_in.encode_compact_frame(1, NAN, 3, pos), _packet()
    )
    np.testing.assert_array_equal(out.frame.valid, [False, True])
    assert np.isnan(out.frame.markers_world[0]).all()


def _with(buf: bytes, offset: int, fmt: str, value: float) -> bytes:
    data = bytearray(buf)
    struct.pack_into(fmt, data, offset, value)
    return bytes(data)


@pytest.mark.parametrize(
    ("packet", "reason"),
    [
        (GOLDEN_COMPACT[:40], "bad_length"),
        (GOLDEN_COMPACT[:-4], "bad_length"),
        (GOLDEN_COMPACT + b"\0\0\0\0", "bad_length"),
        (b"/rtd/frams" + GOLDEN_COMPACT[10:], "bad_address"),
        (GOLDEN_COMPACT[:12] + b",hdiif\0\0" + GOLDEN_COMPACT[20:], "bad_typetags"),
        (_with(GOLDEN_COMPACT, 40, ">i", -1), "bad_count"),
        (_with(GOLDEN_COMPACT, 40, ">i", 3), "bad_blob_size"),
        (_with(GOLDEN_COMPACT, 44, ">i", 20), "bad_blob_size"),
        (_with(GOLDEN_COMPACT, 36, ">i", 4), "unknown_label_set"),
        (_with(GOLDEN_COMPACT, 20, ">q", -5), "bad_frame_number"),
        (_with(GOLDEN_COMPACT, 28, ">d", float("inf")), "non_finite"),
        (_with(GOLDEN_COMPACT, 52, ">f", float("-inf")), "non_finite"),
    ],
)
def test_malformed_compact_is_refused_and_out_untouched(
    packet: bytes, reason: str
) -> None:
    out = _packet()
    osc_in.decode_compact_frame(GOLDEN_COMPACT, out)
    before = out.frame.markers_world.copy()
    with pytest.raises(DecodeError) as info:
        osc_in.decode_compact_frame(packet, out)
    assert info.value.reason == reason
    assert reason in REASON_INDEX
    np.testing.assert_array_equal(out.frame.markers_world, before)
    assert out.frame.frame_id == 7


def test_count_must_match_the_label_set() -> None:
    three = osc_in.encode_compact_frame(1, 0.0, 3, np.zeros((3, 3)))
    with pytest.raises(DecodeError, match="count_mismatch"):
        osc_in.decode_compact_frame(three, _packet())


@pytest.mark.parametrize(
    ("packet", "reason"),
    [
        (build_message("/rtd/label", ",iis", [1, 1, "a"]), "bad_address"),
        (build_message("/rtd/labels", ",iif", [1, 1, 0.0]), "bad_typetags"),
        (build_message("/rtd/labels", ",is", [1, "a"]), "bad_typetags"),
        (build_message("/rtd/labels", ",iiss", [1, 3, "a", "b"]), "bad_count"),
        (build_message("/rtd/labels", ",iiss", [1, 2, "a", "a"]), "bad_label"),
        (build_message("/rtd/labels", ",iis", [1, 1, ""]), "bad_label"),
        (b"/rtd/labels\0,iis\0\0\0\0\0\0\0\x01\0\0\0\x01\xff\xfe\0\0", "bad_string"),
    ],
)
def test_malformed_labels(packet: bytes, reason: str) -> None:
    with pytest.raises(DecodeError) as info:
        osc_in.decode_labels(packet)
    assert info.value.reason == reason


INF = float("inf")


def _msg(address: str, tags: str, *args: float | str) -> bytes:
    return build_message(address, tags, args)


def _marker(name: str, x: float = 0.0) -> bytes:
    return build_message("/rtd/marker", ",sfff", [name, x, 0.0, 0.0])


def test_simple_bundle_unknown_names_are_ignored_and_counted() -> None:
    bundle = build_bundle([_marker("LASI", 1.0), _marker("PROP"), _marker("XX")])
    out = osc_in.decode_simple_bundle(bundle, _packet())
    assert out.unknown_labels == 2 and out.frame.frame_id == -1
    np.testing.assert_array_equal(out.frame.valid, [True, False])


def test_simple_bundle_nested_and_other_addresses() -> None:
    inner = build_bundle([_marker("RASI", 2.0)])
    other = build_message("/td/other", ",i", [5])
    number = build_message("/rtd/frame_number", ",i", [9])
    out = osc_in.decode_simple_bundle(
        build_bundle([other, number, _marker("LASI", 0.5), inner]), _packet()
    )
    assert out.frame.frame_id == 9
    np.testing.assert_array_equal(out.frame.valid, [True, True])
    assert out.frame.markers_world[1, 0] == 2.0


@pytest.mark.parametrize(
    ("packet", "reason"),
    [
        (_marker("LASI"), "not_bundle"),
        (build_bundle([]), "no_markers"),
        (build_bundle([_marker("LASI"), _marker("LASI")]), "duplicate_marker"),
        (build_bundle([_msg("/rtd/marker", ",sff", "LASI", 0, 0)]), "bad_typetags"),
        (build_bundle([_msg("/rtd/marker", ",sfff", "A", INF, 0, 0)]), "non_finite"),
        (
            build_bundle([_msg("/rtd/frame_number", ",f", 1.0), _marker("A")]),
            "bad_typetags",
        ),
        (
            build_bundle([_msg("/rtd/frame_number", ",i", -2), _marker("A")]),
            "bad_frame_number",
        ),
        (
            build_bundle([_msg("/rtd/frame_number", ",i", 1)] * 2 + [_marker("A")]),
            "bad_bundle",
        ),
    ],
)
def test_malformed_simple_bundles(packet: bytes, reason: str) -> None:
    with pytest.raises(DecodeError) as info:
        osc_in.decode_simple_bundle(packet, _packet())
    assert info.value.reason == reason
    assert reason in REASON_INDEX


def test_too_deep_bundles_are_refused() -> None:
    bundle = build_bundle([_marker("LASI")])
    for _ in range(6):
        bundle = build_bundle([bundle])
    with pytest.raises(DecodeError, match="bad_bundle"):
        osc_in.decode_simple_bundle(bundle, _packet())


# --- properties -------------------------------------------------------------------

finite32 = st.floats(-1e6, 1e6, width=32)
coords = arrays(
    np.float32,
    st.tuples(st.integers(0, 8), st.just(3)),
    elements=st.one_of(finite32, st.just(np.float32(np.nan))),
)


@given(pos=coords, frame=st.integers(0, 2**63 - 1), t=st.floats(allow_infinity=False))
def test_valid_compact_frames_decode_exactly(
    pos: np.ndarray, frame: int, t: float
) -> None:
    labels = LabelSet(5, tuple(f"M{i}" for i in range(len(pos))))
    out = MarkerPacket.create(labels)
    osc_in.decode_compact_frame(osc_in.encode_compact_frame(frame, t, 5, pos), out)
    assert out.frame.frame_id == frame
    assert out.frame.source_time_s == t or (
        np.isnan(t) and np.isnan(out.frame.source_time_s)
    )
    # NaN anywhere, an exact (0, 0, 0) row (zero_is_occluded), or a coordinate past
    # MAX_COORDINATE_M (1 km; the values go to 1e6 m) is occluded.
    valid = (
        ~np.isnan(pos).any(axis=1)
        & (pos != 0).any(axis=1)
        & (np.abs(np.nan_to_num(pos)) <= MAX_COORDINATE_M).all(axis=1)
    )
    np.testing.assert_array_equal(out.frame.valid, valid)
    np.testing.assert_array_equal(out.frame.markers_world[valid], pos[valid])
    assert np.isnan(out.frame.markers_world[~valid]).all()


@given(pos=coords, frame=st.integers(0, 2**31 - 1))
def test_valid_simple_bundles_decode_exactly(pos: np.ndarray, frame: int) -> None:
    labels = LabelSet(0, tuple(f"M{i}" for i in range(len(pos))))
    out = MarkerPacket.create(labels)
    packet = osc_in.encode_simple_bundle(labels.labels, pos, frame)
    if len(pos) == 0:
        with pytest.raises(DecodeError, match="no_markers"):
            osc_in.decode_simple_bundle(packet, out)
        return
    osc_in.decode_simple_bundle(packet, out)
    # NaN anywhere, an exact (0, 0, 0) row (zero_is_occluded), or a coordinate past
    # MAX_COORDINATE_M (1 km; the values go to 1e6 m) is occluded.
    valid = (
        ~np.isnan(pos).any(axis=1)
        & (pos != 0).any(axis=1)
        & (np.abs(np.nan_to_num(pos)) <= MAX_COORDINATE_M).all(axis=1)
    )
    np.testing.assert_array_equal(out.frame.valid, valid)
    np.testing.assert_array_equal(out.frame.markers_world[valid], pos[valid])


def _mutations() -> st.SearchStrategy[bytes]:
    pos = np.array([[1.0, 2.0, 3.0], [4.0, NAN, 6.0]])
    valid = [
        osc_in.encode_compact_frame(7, 0.5, 3, pos),
        osc_in.encode_labels(LABELS),
        osc_in.encode_simple_bundle(LABELS.labels, pos, 7),
    ]
    base = st.sampled_from(valid)
    truncated = st.builds(lambda b, n: b[:n], base, st.integers(0, 120))
    flipped = st.builds(
        lambda b, i, v: b[: i % len(b)] + bytes([v]) + b[i % len(b) + 1 :],
        base,
        st.integers(0, 200),
        st.integers(0, 255),
    )
    counts = st.builds(
        lambda b, off, v: _with(b, off % (len(b) - 3) & ~3, ">i", v),
        base,
        st.integers(0, 200),
        st.integers(-(2**31), 2**31 - 1),
    )
    return st.one_of(st.binary(max_size=160), truncated, flipped, counts)


@settings(max_examples=400)
@given(_mutations())
def test_every_osc_decoder_raises_only_decode_error(data: bytes) -> None:
    for decode in (osc_in.decode_compact_frame, osc_in.decode_simple_bundle):
        out = _packet()
        try:
            assert decode(data, out) is out
        except DecodeError as exc:
            assert exc.reason in REASON_INDEX
    try:
        osc_in.decode_labels(data)
    except DecodeError as exc:
        assert exc.reason in REASON_INDEX


def test_simple_form_layout_cache_equals_the_parse(rng: np.random.Generator) -> None:
    """A sender repeats its layout (names, order, frame number form) every frame: the
    second bundle on is read from the cached layout's value slots (issue 13: no
    Python object per marker), and gives exactly what the full parse gives; a bundle
    with another layout (a renamed, dropped or reordered marker) takes the parse."""
    import tracemalloc

    labels = tuple(f"M{i}" for i in range(40))
    packet = MarkerPacket.create(LabelSet(0, labels), "+Z", "m")
    reference = MarkerPacket.create(LabelSet(0, labels), "+Z", "m")
    for frame in range(30):
        pos = rng.normal(0.0, 1.0, (40, 3))
        pos[frame % 40] = np.nan  # occluded: NaN values, the same layout
        order = [*labels, "X"]  # an unknown name too
        rows = np.vstack([pos, rng.normal(size=(1, 3))])
        if frame == 20:  # another layout: reordered
            order = order[::-1]
            rows = rows[::-1]
        buf = osc_in.encode_simple_bundle(order, rows, frame_id=1000 + frame)
        osc_in.decode_simple_bundle(buf, packet)
        reference._simple = None  # the full parse every time
        osc_in.decode_simple_bundle(buf, reference)
        np.testing.assert_array_equal(
            packet.frame.markers_world, reference.frame.markers_world
        )
        np.testing.assert_array_equal(packet.frame.valid, reference.frame.valid)
        assert packet.frame.frame_id == reference.frame.frame_id == 1000 + frame
        assert packet.unknown_labels == reference.unknown_labels == 1
        if frame in (0, 20, 21):  # a new layout: parsed, then cached
            assert packet._simple.hits == 0
        else:
            assert packet._simple.hits >= 1
    # The cached path keeps nothing per frame (the parse made a str, a tuple and a
    # bytes object per marker: ~120 objects a frame here, 7x the time).
    buf = osc_in.encode_simple_bundle(labels, rng.normal(size=(40, 3)), frame_id=5)
    osc_in.decode_simple_bundle(buf, packet)
    tracemalloc.start()
    try:
        for _ in range(50):  # tracemalloc's and numpy's first-use caches
            osc_in.decode_simple_bundle(buf, packet)
        tracemalloc.reset_peak()
        start, _ = tracemalloc.get_traced_memory()
        for _ in range(200):
            osc_in.decode_simple_bundle(buf, packet)
        end, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    # numpy keeps a small bounded cache for ``take`` (~28 x 120 B); nothing grows
    # with the frames (200 frames of a per-frame object would be > 8 KB).
    assert end - start < 8192
    del peak  # (numpy's temporaries for the checks and the scatter: a few kB)


def test_signalling_nan_hides_a_marker_on_both_paths() -> None:
    """Any NaN bit pattern is a hidden marker; a signalling NaN (0x7f800001) widened
    to float64 on the cached path raised numpy's "invalid" warning (found by the
    volume fuzz). Warnings are errors here: both paths read it as hidden, silently."""
    import warnings

    packet = MarkerPacket.create(LABELS, "+Z", "m")
    good = osc_in.encode_simple_bundle(LABELS.labels, POSITIONS, 7)
    signalling = good.replace(b"\x7f\xc0\x00\x00", b"\x7f\x80\x00\x01")
    assert signalling != good
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for buf in (signalling, good, signalling):  # parse, cache, cached path
            osc_in.decode_simple_bundle(buf, packet)
            assert packet.frame.valid.tolist() == [True, False]
            np.testing.assert_array_equal(packet.frame.markers_world[0], [1, 2, 3])
    assert packet._simple.hits >= 1
