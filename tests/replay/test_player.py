"""Replay player: endpoints, what a take becomes on the wire, pacing, loops, windows
and re-sending recorded bytes. A fake sender collects what would be sent."""

from __future__ import annotations

import struct
import time
from typing import Any

import numpy as np
import pytest

from retargetd.protocols import marker_input as mi
from retargetd.protocols import osc_in, zmq_wire
from retargetd.replay import player as pl
from retargetd.replay import recording as rf
from retargetd.replay.take import Take


def _take(n_frames: int = 30, rate_hz: float = 60.0) -> Take:
    rng = np.random.default_rng(0)
    pos = rng.uniform(-1, 2, (n_frames, 3, 3))
    pos[2, 1] = np.nan
    return Take(
        path="mem", format="trc", subject=None, subjects=(), labels=("A", "B", "C"),
        positions=pos, valid=np.isfinite(pos).all(axis=-1), rate_hz=rate_hz,
        first_frame=0, units="m", up_axis="+Z", units_source="file",
        up_source="file", world_from_capture=np.eye(3),
    )  # fmt: skip


class FakeSender:
    def __init__(self, transport: str = "osc") -> None:
        self.transport = transport
        self.sent: list[tuple[float, tuple[bytes, ...]]] = []
        self.dropped = 0

    def send(self, parts: Any) -> None:
        self.sent.append((time.perf_counter(), tuple(parts)))


def _frame_numbers(sent: list[tuple[float, tuple[bytes, ...]]]) -> list[int]:
    return [
        struct.unpack_from(">q", p[0], 20)[0]
        for _, p in sent
        if p[0].startswith(b"/rtd/frame\0")
    ]


@pytest.mark.parametrize(
    "url",
    ["udp://127.0.0.1:5", "osc://127.0.0.1", "osc://:5", "osc://h:x", "osc://h:70000"],
)
def test_bad_endpoints_are_one_line_errors(url: str) -> None:
    with pytest.raises(ValueError) as err:
        pl.parse_endpoint(url)
    assert "\n" not in str(err.value)


def test_endpoints() -> None:
    assert pl.parse_endpoint("zmq://127.0.0.1:5570").tcp == "tcp://127.0.0.1:5570"
    ep = pl.parse_endpoint("zmq+sub://h:1", ("zmq+sub",))
    assert (ep.scheme, ep.host, ep.port) == ("zmq+sub", "h", 1)
    assert pl.parse_endpoint("osc://h:0", allow_port_0=True).port == 0


@pytest.mark.parametrize("transport,form", [("osc", "compact"), ("osc", "simple"),
                                            ("zmq", "compact")])  # fmt: skip
def test_take_frames_decode_to_the_take(transport: str, form: str) -> None:
    take = _take()
    sender = FakeSender(transport)
    src = pl.TakeSource(take, transport, form, slice(0, take.n_frames))
    report = pl.play(src, sender, speed=0)  # type: ignore[arg-type]
    assert report.frames == take.n_frames and report.lateness_s == []
    stream = mi.MarkerStream(mi.LabelSet(1, take.labels) if form == "simple" else None)
    got = []
    for _, parts in sender.sent:
        if transport == "zmq" and parts[0][:4] == zmq_wire.LABELS_MAGIC:
            stream.set_labels(zmq_wire.decode_zmq_labels(*parts))
        elif transport == "zmq":
            assert stream.feed(zmq_wire.decode_zmq_frame, *parts, t_ns=0) == 0
        elif parts[0].startswith(b"/rtd/labels"):
            stream.set_labels(osc_in.decode_labels(parts[0]))
        else:
            decode = getattr(osc_in, f"decode_{form}_frame", None)
            decode = decode or osc_in.decode_simple_bundle
            assert stream.feed(decode, parts[0], t_ns=0) == 0
        if stream.counters["accepted"] > len(got):
            got.append(stream.current.frame.markers_world.copy())
            assert stream.current.frame.frame_id == len(got) - 1
    np.testing.assert_array_equal(got, take.positions.astype(np.float32))
    if form == "compact":  # labels go first
        assert report.label_packets == 1 and sender.sent[0][1][0][:4] in (
            b"/rtd", zmq_wire.LABELS_MAGIC,
        )  # fmt: skip


def test_paced_play_takes_the_take_duration_and_reports_jitter() -> None:
    take = _take(n_frames=30, rate_hz=60.0)  # 0.5 s
    sender = FakeSender()
    src = pl.TakeSource(take, "osc", "compact", slice(None))
    report = pl.play(src, sender, speed=1.0)  # type: ignore[arg-type]
    jitter = report.jitter_us()
    print(f"speed 1: {report.wall_s:.3f} s for a 0.5 s take; jitter us {jitter}")
    assert 0.35 < report.wall_s < 0.65  # loose: a shared machine is noisy
    assert len(report.lateness_s) == 30 and jitter["median"] >= 0
    fast = pl.play(src, FakeSender(), speed=0)  # type: ignore[arg-type]
    assert fast.wall_s < report.wall_s / 2
    double = pl.play(src, FakeSender(), speed=2.0)  # type: ignore[arg-type]
    assert 0.15 < double.wall_s < 0.4


def test_loop_keeps_frame_numbers_increasing() -> None:
    take = _take(n_frames=10, rate_hz=100.0)
    sender = FakeSender()
    src = pl.TakeSource(take, "osc", "compact", slice(2, 6))
    report = pl.play(src, sender, speed=4.0, loop=True, max_seconds=0.1)  # type: ignore[arg-type]
    numbers = _frame_numbers(sender.sent)
    assert report.passes >= 3
    assert numbers[:9] == [2, 3, 4, 5, 6, 7, 8, 9, 10]
    assert (np.diff(numbers) > 0).all()


def _recorded(form: int, n: int = 6) -> list[rf.Packet]:
    pos = np.zeros((3, 3))
    labels = mi.LabelSet(1, ("A", "B", "C"))
    out = []
    for i in range(n):
        t = 1_000_000 + i * 10_000_000
        if i == 0 or i == 3:
            parts = (
                tuple(zmq_wire.encode_zmq_labels(labels)) if form == rf.FORM_ZMQ
                else (osc_in.encode_labels(labels),)
            )  # fmt: skip
            out.append(rf.Packet(t - 1, -1, np.nan, form, rf.KIND_LABELS, "x", parts))
        if form == rf.FORM_ZMQ:
            parts = tuple(zmq_wire.encode_zmq_frame(100 + i, i, 1, pos))
        elif form == rf.FORM_OSC_SIMPLE:
            parts = (osc_in.encode_simple_bundle(labels.labels, pos, 100 + i),)
        else:
            parts = (osc_in.encode_compact_frame(100 + i, i, 1, pos),)
        out.append(rf.Packet(t, 100 + i, i, form, rf.KIND_FRAME, "x", parts))
    return out


@pytest.mark.parametrize("form", [rf.FORM_OSC_COMPACT, rf.FORM_OSC_SIMPLE, rf.FORM_ZMQ])
def test_recording_source_resends_bytes_and_shifts_loops(form: int) -> None:
    packets = _recorded(form)
    src = pl.RecordingSource(packets, slice(None))
    first = [parts for _, parts, _ in src.iter_pass(0)]
    assert first == [p.parts for p in packets]  # byte-identical
    times = [t for t, _, _ in src.iter_pass(0)]
    assert times[1] == pytest.approx(0.0, abs=1e-6) and times[-1] == pytest.approx(
        0.05 + 1e-9
    )
    second = [pl.rf.Packet(0, -1, 0, form, k, "x", parts)
              for _, parts, k in src.iter_pass(1)]  # fmt: skip
    frames = [rf.classify(form, p.parts)[1] for p in second if p.kind == 1]
    if form != rf.FORM_OSC_SIMPLE:
        assert frames == [106, 107, 108, 109, 110, 111]
    else:
        assert [b.find(struct.pack(">q", 106)) > 0 for b in second[1].parts] == [True]


def test_recording_window_starts_with_the_last_labels() -> None:
    packets = _recorded(rf.FORM_OSC_COMPACT)
    src = pl.RecordingSource(packets, slice(4, 6))
    kinds = [k for _, _, k in src.iter_pass(0)]
    assert kinds == [rf.KIND_LABELS, rf.KIND_FRAME, rf.KIND_FRAME]
    assert src.packets[0].parts == packets[4].parts  # the announcement before frame 3
    with pytest.raises(ValueError, match="no recorded frames"):
        pl.RecordingSource(packets, slice(6, 9))
