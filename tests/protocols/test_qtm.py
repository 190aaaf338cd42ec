"""QTM: documented bytes, the vendor SDK ``qtm-rt`` against the emulator, faults.

The client side is the real ``qtm-rt`` (connect, version, parameters, streaming,
events); the emulator's bytes are checked against a packet worked out by hand from
the RT protocol documentation (1.25) and against ``qtm-rt``'s own packet parser.
"""

from __future__ import annotations

import importlib.util
import re
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zmq
from qtm_rt.packet import QRTPacket

from retargetd.protocols import qtm
from retargetd.protocols.errors import DecodeError
from retargetd.protocols.marker_input import ACCEPTED, RESTART, LabelSet, MarkerStream
from retargetd.replay.takes import load_take


def _load(name: str) -> Any:
    key = f"retargetd_tests_{name}"
    if key not in sys.modules:
        spec = importlib.util.spec_from_file_location(
            key, Path(__file__).with_name(f"{name}.py")
        )
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        sys.modules[key] = module
        spec.loader.exec_module(module)
    return sys.modules[key]


em = _load("qtm_emulator")

# RT protocol 1.25 data packet worked out by hand: frame 7, timestamp 1000 us, one
# 3D-with-residuals component (type 9) of 2 markers: (1, 2, 3) mm residual 0.8, and
# one not seen (NaN, residual -1).
DATA_HEX = (
    "48000000 03000000"  # size 72, type 3 (data)
    "e803000000000000 07000000 01000000"  # timestamp, frame, 1 component
    "30000000 09000000 02000000 0000 0000"  # size 48, type 9, 2 markers, rates
    "0000803f 00000040 00004040 cdcc4c3f"  # (1, 2, 3), 0.8
    "0000c07f 0000c07f 0000c07f 000080bf"  # NaN x 3, -1
)

PARAMS_XML = (
    "<QTM_Parameters_Ver_1.25><General><Frequency>100</Frequency></General>"
    "<The_3D><AxisUpwards>+Y</AxisUpwards><Labels>2</Labels>"
    "<Label><Name>LASI</Name><RGBColor>255</RGBColor></Label>"
    "<Label><Name>RASI</Name><RGBColor>65280</RGBColor></Label>"
    "</The_3D></QTM_Parameters_Ver_1.25>"
)


def _hex(text: str) -> bytes:
    return bytes.fromhex(text.replace(" ", ""))


DOC = (Path(__file__).resolve().parents[2] / "protocols" / "PROTOCOLS.md").read_text()


def _doc_hex(name: str) -> bytes:
    """A hex dump block of PROTOCOLS.md (``<!-- hex: name -->``)."""
    match = re.search(rf"<!-- hex: {name} -->\n```\n(.*?)```", DOC, re.DOTALL)
    assert match, f"no hex block {name!r} in PROTOCOLS.md"
    data = bytearray()
    for line in match.group(1).splitlines():
        data += bytes.fromhex(line[6:].split("|")[0])
    return bytes(data)


def test_protocols_md_shows_the_hand_worked_bytes() -> None:
    assert _doc_hex("qtm_data_3dres") == _hex(DATA_HEX)


def test_emulator_packet_matches_the_hand_worked_bytes() -> None:
    got = em.data_packet(7, 1000, np.array([[1.0, 2.0, 3.0], [np.nan] * 3]))
    assert got == _hex(DATA_HEX)


def test_qtm_rt_reads_the_emulator_packet() -> None:
    """The vendor SDK's own parser reads what the emulator writes."""
    pkt = em.data_packet(11, 5000, np.array([[4.0, 5.0, 6.0], [np.nan] * 3]))
    parsed = QRTPacket(pkt[8:])
    assert parsed.framenumber == 11 and parsed.timestamp == 5000
    info, markers = parsed.get_3d_markers_residual()
    assert info.marker_count == 2
    assert tuple(markers[0]) == pytest.approx((4.0, 5.0, 6.0, 0.8))
    assert np.isnan(markers[1].x) and markers[1].residual == -1.0


def test_decoder_reads_the_hand_worked_bytes() -> None:
    stream = MarkerStream(LabelSet(1, ("A", "B")), "+Z", "mm")
    dec = qtm.Qtm3dDecoder(2)
    assert stream.feed(dec.decode_qtm_3d, _hex(DATA_HEX), t_ns=5) == ACCEPTED
    frame = stream.current.frame
    np.testing.assert_allclose(frame.markers_world[0], [1e-3, 2e-3, 3e-3])
    assert np.isnan(frame.markers_world[1]).all()
    assert list(frame.valid) == [True, False]
    assert frame.frame_id == 7 and frame.source_time_s == pytest.approx(1e-3)
    assert dec.residuals_mm[0] == pytest.approx(0.8) and np.isnan(dec.residuals_mm[1])
    # The plain function form decodes the same packet.
    out = stream._spare
    assert qtm.decode_qtm_3d(_hex(DATA_HEX), out) is out


def test_qtm_urls() -> None:
    assert qtm.parse_qtm_url("qtm://10.0.0.7") == ("10.0.0.7", 22223)
    assert qtm.parse_qtm_url("qtm://qtm-host:4000") == ("qtm-host", 4000)
    for bad in ("natnet://x", "qtm://", "qtm://x:port", "qtm://x/path"):
        with pytest.raises(ValueError):
            qtm.parse_qtm_url(bad)


def test_parameters_give_labels_up_axis_and_rate() -> None:
    params = qtm.parse_qtm_parameters(PARAMS_XML.encode() + b"\0")
    assert params.labels == ("LASI", "RASI")
    assert params.up_axis == "+Y" and params.frequency_hz == 100.0
    with pytest.raises(DecodeError) as err:
        qtm.parse_qtm_parameters("<QTM_Parameters_Ver_1.25/>")
    assert err.value.reason == "no_3d"


def test_input_follows_the_parameters_up_axis() -> None:
    """QTM reports +Y up: the stream is built for it (capture +Y -> world +Z)."""
    source = qtm.QtmSource("127.0.0.1", 1)  # never started: only its socketpair
    try:
        inp = qtm.QtmInput(source)
        assert inp.feed(qtm.encode_packet(2, PARAMS_XML.encode() + b"\0"), 0) == -1
        pkt = em.data_packet(1, 0, np.array([[0.0, 1000.0, 0.0], [0.0, 0.0, 1000.0]]))
        assert inp.feed(pkt, 1) == ACCEPTED
        np.testing.assert_allclose(
            inp.stream.current.frame.markers_world, [[0, 0, 1], [0, -1, 0]], atol=0
        )
        assert inp.stream.label_set.labels == ("LASI", "RASI")
    finally:
        source.close()


def test_cut_and_garbled_packets_raise_only_decode_error(
    rng: np.random.Generator,
) -> None:
    stream = MarkerStream(LabelSet(1, ("A", "B", "C")), "+Z", "mm")
    dec = qtm.Qtm3dDecoder(3)
    pkt = em.data_packet(3, 10, rng.normal(size=(3, 3)) * 1000)
    for cut in range(len(pkt)):
        short = bytearray(pkt[:cut])
        if cut >= 8:
            short[0:4] = cut.to_bytes(4, "little")  # framing kept, content cut
        code = stream.feed(dec, bytes(short), t_ns=cut)
        assert code not in (ACCEPTED, RESTART)
    assert stream.counters.dropped() == len(pkt)
    for k in range(300):
        garbled = bytearray(pkt)
        at = int(rng.integers(8, len(pkt)))
        garbled[at : at + 4] = rng.bytes(4)[: len(garbled) - at]
        stream.feed(dec, bytes(garbled), t_ns=1000 + k)  # only DecodeError is caught


# ---- the SDK against the emulator ----------------------------------------------------


class _Loop:
    """A stand-in for the daemon's loop: a zmq.Poller on the source's fd."""

    def __init__(self, source: qtm.QtmSource) -> None:
        self.source = source
        self.input = qtm.QtmInput(source)
        self.poller = zmq.Poller()
        self.poller.register(source.fileno(), zmq.POLLIN)
        self.frames: list[tuple[int, tuple[str, ...], np.ndarray]] = []
        self.codes: dict[int, int] = {}
        self.recorded: list[bytes] = []  # every packet, as a recorder gets them

    def run_until(self, done: Any, timeout_s: float) -> None:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end and not done():
            if not self.poller.poll(5):
                continue
            while (pkt := self.source.read()) is not None:
                self.recorded.append(bytes(pkt))
                code = self.input.feed(pkt, time.monotonic_ns())
                self.codes[code] = self.codes.get(code, 0) + 1
                if code in (ACCEPTED, RESTART):
                    cur = self.input.stream.current
                    self.frames.append(
                        (
                            cur.frame.frame_id,
                            cur.label_set.labels,
                            cur.frame.markers_world.copy(),
                        )
                    )


@pytest.fixture
def take(datasets: Path) -> Any:
    return load_take(datasets / "ezc3d-testfiles" / "Qualisys.c3d")


def _start(take: Any, scenario: Any) -> tuple[Any, qtm.QtmSource, list[str]]:
    server = em.QtmEmulator(
        take.positions, list(take.labels), take.rate_hz, take.first_frame, scenario
    )
    server.start()
    lines: list[str] = []
    source = qtm.QtmSource("127.0.0.1", server.port, out=lines.append)
    source.start()
    return server, source, lines


@pytest.mark.timeout(60)
def test_served_take_arrives_equal_with_faults_counted(take: Any) -> None:
    scenario = em.Scenario(label_change_at=100, restart_at=200)
    server, source, lines = _start(take, scenario)
    loop = _Loop(source)
    n = take.positions.shape[0]
    try:
        loop.run_until(lambda: len(loop.frames) >= 201 + n, 30)
    finally:
        source.close()
        server.close()
    counters = loop.input.stream.counters
    ids = [f[0] - take.first_frame for f in loop.frames]
    assert ids == list(range(201)) + list(range(n))  # every frame, restart once
    for fid, _labels, markers in loop.frames:
        row = take.positions[fid - take.first_frame]
        np.testing.assert_allclose(markers, row, atol=1e-6, rtol=0)
        assert np.array_equal(np.isnan(markers), np.isnan(row))
    assert counters["bad_length"] == 2  # the truncated and the garbled packet
    assert counters["restart"] == 1
    assert loop.frames[99][1][0] == "L_IAS" and loop.frames[100][1][0] == "renamed"
    assert source.counts["connects"] == 2 and source.counts["param_reads"] == 3
    assert any("labels changed" in line or "streaming" in line for line in lines)
    assert sum("disconnected" in line for line in lines) >= 1
    # Replay: the recorded packets through a source-free input, same frames.
    replay = qtm.QtmInput(None)
    again = []
    pause_ns = 0
    for k, pkt in enumerate(loop.recorded):
        kind, frame_id, time_s = qtm.packet_info(pkt)
        if kind == 1 and frame_id == take.first_frame and k > 10:
            pause_ns = 2_000_000_000  # the restart's pause (the clock never goes back)
        t_ns = k * 5_000_000 + pause_ns
        if replay.feed(pkt, t_ns) in (ACCEPTED, RESTART):
            again.append((replay.stream.current.frame.frame_id, time_s))
    assert [a[0] for a in again] == [f[0] for f in loop.frames]
    assert again[1][1] == pytest.approx(1.0 / take.rate_hz)  # QTM's timestamp kept


@pytest.mark.timeout(30)
def test_occluded_markers_arrive_occluded(datasets: Path) -> None:
    """A take with occlusions (the PiG walk: 30 marker-frames missing) through
    qtm-rt: NaN where the take has NaN, equal elsewhere."""
    walk = load_take(datasets / "btkdata" / "PiG_Motion-FlatFoot-Full.c3d")
    assert np.isnan(walk.positions).any()
    server, source, _ = _start(walk, em.Scenario(faults=False))
    loop = _Loop(source)
    n = walk.positions.shape[0]
    try:
        loop.run_until(lambda: len(loop.frames) >= n, 20)
    finally:
        source.close()
        server.close()
    assert len(loop.frames) == n
    for fid, _labels, markers in loop.frames:
        row = walk.positions[fid - walk.first_frame]
        assert np.array_equal(np.isnan(markers), np.isnan(row))
        np.testing.assert_allclose(markers, row, atol=1e-6, rtol=0)
    residuals = loop.input.decoder.residuals_mm
    assert np.isnan(residuals).sum() == np.isnan(walk.positions[-1, :, 0]).sum()


@pytest.mark.timeout(30)
def test_no_measurement_is_said_and_counted(take: Any) -> None:
    server, source, lines = _start(take, em.Scenario(no_measurement=True))
    try:
        end = time.monotonic() + 10
        while source.state != "idle" and time.monotonic() < end:
            time.sleep(0.01)
    finally:
        source.close()
        server.close()
    assert source.counts["no_measurement"] == 1
    assert sum("runs no measurement" in line for line in lines) == 1


@pytest.mark.timeout(30)
def test_measurement_opened_later_and_reloaded_is_followed(take: Any) -> None:
    """No measurement at first (said once), then QTM opens one: streaming starts;
    later the measurement is reloaded (closed, opened): streaming resumes, every
    frame arrives once."""
    scenario = em.Scenario(
        faults=False, no_measurement=True, measurement_after_s=0.5, reload_at=60
    )
    server, source, lines = _start(take, scenario)
    loop = _Loop(source)
    n = take.positions.shape[0]
    try:
        loop.run_until(lambda: len(loop.frames) >= n, 30)
    finally:
        source.close()
        server.close()
    assert [f[0] - take.first_frame for f in loop.frames] == list(range(n))
    assert server.sent["reloads"] == 1
    assert source.counts["no_measurement"] == 2  # at start, and during the reload
    assert source.counts["connects"] == 1 and source.counts["param_reads"] == 3
    assert sum("runs no measurement" in line for line in lines) == 2


@pytest.mark.timeout(30)
def test_packet_the_sdk_cannot_parse_costs_a_reconnect(take: Any) -> None:
    """qtm-rt raises inside its protocol on an unknown component type, and asyncio
    closes that connection: said, reconnected, streaming goes on (no frame twice)."""
    scenario = em.Scenario(faults=False, bad_component_at=50)
    server, source, lines = _start(take, scenario)
    loop = _Loop(source)
    n = take.positions.shape[0]
    try:
        loop.run_until(lambda: server.done.is_set() and len(loop.frames) >= n - 5, 30)
        loop.run_until(lambda: False, 0.2)
    finally:
        source.close()
        server.close()
    ids = [f[0] - take.first_frame for f in loop.frames]
    assert ids[:51] == list(range(51)) and ids == sorted(set(ids))
    assert source.counts["connects"] == 2 and source.counts["disconnects"] >= 1
    assert any("disconnected" in line for line in lines)


# alone (tests/helpers/alone.py): times a read (under 10 ms), shorter than one
# scheduler slice lost to the other xdist worker's test.
@pytest.mark.alone
@pytest.mark.timeout(30)
def test_vanished_server_reconnects_with_backoff_and_never_blocks(take: Any) -> None:
    server, source, lines = _start(take, em.Scenario(faults=False, vanish_at=40))
    loop = _Loop(source)
    try:
        loop.run_until(lambda: source.counts["connect_failures"] >= 2, 10)
        t0 = time.monotonic()
        assert source.read() is None
        assert time.monotonic() - t0 < 0.01
    finally:
        source.close()
        server.close()
    assert len(loop.frames) == 41
    assert source.counts["disconnects"] == 1
    assert sum("cannot connect" in line for line in lines) == 1  # said once


@pytest.mark.timeout(30)
def test_unknown_protocol_version_is_said_and_counted(take: Any) -> None:
    server, source, lines = _start(take, em.Scenario(refuse_version=True))
    try:
        end = time.monotonic() + 10
        while source.counts["bad_version"] < 2 and time.monotonic() < end:
            time.sleep(0.01)
    finally:
        source.close()
        server.close()
    assert source.counts["bad_version"] >= 2 and source.counts["connects"] == 0
    assert sum("refused RT protocol version 1.25" in line for line in lines) == 1


def test_close_right_after_start_returns_promptly() -> None:
    """close() racing the thread's start-up still stops it (bounded, no hang)."""
    for _ in range(20):
        source = qtm.QtmSource("127.0.0.1", 9)  # nothing listens: connect refused
        source.start()
        thread = source._thread
        assert thread is not None
        t0 = time.monotonic()
        source.close()
        assert time.monotonic() - t0 < 1.5 and not thread.is_alive()


def test_flood_drops_at_the_handover_counted() -> None:
    """A loop that reads nothing while QTM floods: the socketpair fills, the newest
    packets are dropped and counted, nothing blocks."""
    source = qtm.QtmSource("127.0.0.1", 1)
    try:
        pkt = em.data_packet(1, 0, np.zeros((100, 3)))
        sent = 5000
        t0 = time.monotonic()
        for _ in range(sent):
            source._forward(pkt)
        assert time.monotonic() - t0 < 5.0
        got = 0
        while source.read() is not None:
            got += 1
    finally:
        source.close()
    assert source.counts["handover_drops"] > 0
    assert got + source.counts["handover_drops"] == sent
