"""MCAP recorder: the envelope, label tracking, a bounded queue that never blocks, and
files the ``mcap`` library reads, whole or cut short anywhere."""

from __future__ import annotations

import io
import json
import math
import re
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader

from retargetd.protocols import osc_in, pose_stream, zmq_wire
from retargetd.protocols.marker_input import LabelSet
from retargetd.replay import recording as rf
from retargetd.replay.recorder import InputInfo, Recorder, open_recorder
from retargetd.replay.takes import load_take

LABELS = LabelSet(3, ("LASI", "RASI", "LPSI"))
RATE_HZ = 100.0


def _positions(rng: np.random.Generator, n: int) -> np.ndarray:
    pos = rng.uniform(-1, 2, (n, len(LABELS.labels), 3))
    pos[5:9, 1] = np.nan  # an occluded run
    return pos


class _NonSeekable(io.BytesIO):
    def seekable(self) -> bool:
        return False


def _mcap_stream_messages(data: bytes) -> tuple[int, str]:
    """Messages the mcap library's non-seeking reader yields, and how it stopped."""
    n = 0
    reader = make_reader(_NonSeekable(data))
    try:
        for _ in reader.iter_messages(log_time_order=False):
            n += 1
    except Exception as exc:  # a cut file ends in EndOfFile or a short unpack
        return n, type(exc).__name__
    return n, ""


def _record_compact(path: Path, pos: np.ndarray, **kw: Any) -> list[bytes]:
    rec = open_recorder(path, (InputInfo(name="osc", form="osc-compact"),), **kw)
    t0 = time.monotonic_ns()
    sent = [osc_in.encode_labels(LABELS)]
    rec.record_packet("osc", rf.FORM_OSC_COMPACT, t0, memoryview(sent[0]))
    for i, row in enumerate(pos):
        sent.append(osc_in.encode_compact_frame(i, i / RATE_HZ, LABELS.id, row))
        rec.record_packet("osc", rf.FORM_OSC_COMPACT, t0 + int(i * 1e7), sent[-1])
    rec.record_event("calibrate", count=5, by="test")
    stats = rec.close()
    assert stats.frames == len(pos) and stats.dropped == 0
    return sent


def test_envelope_round_trip() -> None:
    p = rf.Packet(12, 7, 0.5, rf.FORM_ZMQ, rf.KIND_FRAME, "zmq", (b"ab", b"", b"c"))
    q = rf.decode_packet(rf.encode_packet(p))
    assert (q.t_ns, q.source_frame, q.source_time_s, q.form, q.kind, q.input) == (
        12, 7, 0.5, rf.FORM_ZMQ, rf.KIND_FRAME, "zmq",
    )  # fmt: skip
    assert q.parts == p.parts
    with pytest.raises(ValueError, match="sizes add up"):
        rf.decode_packet(rf.encode_packet(p) + b"x")


def test_classify_reads_source_frame_and_time() -> None:
    pos = np.zeros((3, 3))
    compact = osc_in.encode_compact_frame(41, 0.25, 3, pos)
    assert rf.classify(rf.FORM_OSC_COMPACT, [compact]) == (rf.KIND_FRAME, 41, 0.25)
    kind, frame, t = rf.classify(rf.FORM_OSC_COMPACT, [osc_in.encode_labels(LABELS)])
    assert (kind, frame, math.isnan(t)) == (rf.KIND_LABELS, -1, True)
    simple = osc_in.encode_simple_bundle(LABELS.labels, pos, 9)
    assert rf.classify(rf.FORM_OSC_SIMPLE, [simple])[:2] == (rf.KIND_FRAME, 9)
    zmq_frame = zmq_wire.encode_zmq_frame(5, 1.5, 3, pos)
    assert rf.classify(rf.FORM_ZMQ, zmq_frame) == (rf.KIND_FRAME, 5, 1.5)
    assert rf.classify(rf.FORM_ZMQ, [b"junk"])[0] == rf.KIND_OTHER
    # Pose-stream messages: data with and without the face part, validation.
    q = np.tile([1.0, 0.0, 0.0, 0.0], (2, 1))
    for n_face in (None, 3):
        enc = pose_stream.PoseEncoder(2, 0, n_face_markers=n_face)
        parts = enc.encode(12, 0.5, 1, 2, 0, np.zeros(3), q, q, q, np.zeros(0),
                           np.zeros(2, dtype=np.uint8))  # fmt: skip
        got = rf.classify(rf.FORM_POSE, [bytes(x) for x in parts])
        assert (len(parts), got) == (
            2 if n_face is None else 3,
            (rf.KIND_FRAME, 12, 0.5),
        )
    rtdv = pose_stream.encode_validation(
        0, 12, 1, 2, 0, np.zeros(8), np.zeros(2, np.uint8)
    )
    assert rf.classify(rf.FORM_POSE, rtdv)[:2] == (rf.KIND_OTHER, -1)


def test_full_queue_drops_and_counts_and_never_blocks() -> None:
    written: list[Any] = []
    release = threading.Event()

    class SlowSink:
        def write(self, item: Any) -> None:
            release.wait(5.0)  # a stalled disk
            written.append(item)

        def flush(self) -> None:
            pass

        def close(self) -> None:
            pass

    rec = Recorder(lambda stats: SlowSink(), queue_size=8, flush_interval_s=0.05)
    rec.start()
    worst = 0.0
    accepted = 0
    for i in range(200):
        t = time.perf_counter()
        accepted += rec.record_packet("osc", rf.FORM_OSC_COMPACT, i, b"/rtd/frame")
        worst = max(worst, time.perf_counter() - t)
    print(f"worst put_nowait with a stalled writer: {worst * 1e6:.0f} us")
    assert worst < 0.5  # a blocking put would wait the full 5 s for the writer
    release.set()
    stats = rec.close(timeout_s=5.0)
    assert stats.dropped == 200 - accepted and stats.dropped >= 190
    assert len(written) == accepted


def test_recording_is_a_complete_mcap_file(
    tmp_path: Path, rng: np.random.Generator
) -> None:
    path = tmp_path / "take.mcap"
    pos = _positions(rng, 50)
    sent = _record_compact(path, pos)
    with open(path, "rb") as f:  # the library's indexed (seeking) reader
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        topics = [ch.topic for _, ch, _ in reader.iter_messages()]
    assert topics.count(rf.RAW_TOPIC) == 51
    assert topics.count(rf.LABELS_TOPIC) == 1 and topics.count(rf.CONTROL_TOPIC) == 1
    rec = rf.read_recording(path)
    assert rec.complete and rec.profile == "retargetd"
    assert [p.parts[0] for p in rec.packets()] == sent
    frames = [p for p in rec.packets() if p.kind == rf.KIND_FRAME]
    assert [p.source_frame for p in frames] == list(range(50))
    assert rec.json(rf.LABELS_TOPIC)[0]["labels"] == list(LABELS.labels)
    assert rec.json(rf.CONTROL_TOPIC)[0]["event"] == "calibrate"
    # log_time is wall clock (ns since the epoch); t_ns stays monotonic inside.
    raw = rec.topic(rf.RAW_TOPIC)
    assert abs(raw[0].log_time_ns - time.time_ns()) < 60e9
    gaps = np.diff([m.log_time_ns for m in raw[1:]])
    np.testing.assert_array_equal(gaps, np.diff([p.t_ns for p in frames]))
    take = load_take(path)
    assert take.format == "mcap" and take.labels == LABELS.labels
    assert take.rate_hz == pytest.approx(RATE_HZ)
    np.testing.assert_array_equal(take.positions, pos.astype(np.float32))
    assert json.loads(rec.metadata[rf.METADATA_NAME]["inputs"])[0]["name"] == "osc"


def test_a_file_cut_anywhere_reads_up_to_the_cut(
    tmp_path: Path, rng: np.random.Generator
) -> None:
    path = tmp_path / "take.mcap"
    # A flush every packet's worth of time: many small chunks, as in a live session.
    sent = _record_compact(path, _positions(rng, 300), chunk_size=2048)
    data = path.read_bytes()
    cut_path = tmp_path / "cut.mcap"
    previous = -1
    for cut in range(100, len(data), 611):
        cut_path.write_bytes(data[:cut])
        rec = rf.read_recording(cut_path)
        got = [p.parts[0] for p in rec.packets()]
        assert got == sent[: len(got)]  # a prefix, byte for byte
        assert len(got) >= previous  # never less for a longer file
        previous = len(got)
        n_lib, _ = _mcap_stream_messages(data[:cut])
        assert n_lib == len(rec.messages)  # the mcap library reads the same
    assert previous > 250


def test_simple_bundles_grow_the_label_set(tmp_path: Path) -> None:
    path = tmp_path / "simple.mcap"
    rec = open_recorder(path, (InputInfo(name="osc", form="osc-simple"),))
    pos = np.arange(9.0).reshape(3, 3)
    rec.record_packet(
        "osc", rf.FORM_OSC_SIMPLE, 1000,
        osc_in.encode_simple_bundle(["A", "B"], pos[:2], 0),
    )  # fmt: skip
    rec.record_packet(
        "osc", rf.FORM_OSC_SIMPLE, 11_000_000,
        osc_in.encode_simple_bundle(["B", "C"], pos[1:], 1),
    )  # fmt: skip
    assert rec.close().label_sets == 2
    sets = rf.read_recording(path).json(rf.LABELS_TOPIC)
    assert [s["labels"] for s in sets] == [["A", "B"], ["A", "B", "C"]]
    take = load_take(path)
    assert take.labels == ("A", "B", "C")
    assert take.valid.tolist() == [[True, True, False], [False, True, True]]


def test_protocols_md_envelope_example() -> None:
    doc = (
        Path(__file__).resolve().parents[2] / "protocols" / "PROTOCOLS.md"
    ).read_text()
    match = re.search(r"<!-- hex: recording_packet -->\n```\n(.*?)```", doc, re.S)
    assert match, "no recording_packet example in PROTOCOLS.md"
    data = b"".join(
        bytes.fromhex(line[6:].split("|")[0]) for line in match.group(1).splitlines()
    )
    nan = float("nan")
    frame = osc_in.encode_compact_frame(
        7, 0.5, 3, np.array([[1.0, 2.0, 3.0], [nan, nan, nan]])
    )
    packet = rf.Packet(
        1000, 7, 0.5, rf.FORM_OSC_COMPACT, rf.KIND_FRAME, "osc", (frame,)
    )
    assert data == rf.encode_packet(packet)
    assert rf.classify(rf.FORM_OSC_COMPACT, [frame]) == (rf.KIND_FRAME, 7, 0.5)
