"""NatNet (Motive): documented bytes, the emulator over loopback, faults.

The emulator's byte layout is checked against bytes worked out by hand from the NatNet
SDK 4.x samples' description (below) and against a third-party reader (the PyPI
``natnet`` package), so a test passes only if both sides read the vendor's layout,
not merely each other.
"""

from __future__ import annotations

import importlib.util
import re
import sys
import time
from pathlib import Path
from typing import Any

import natnet as natnet_pkg
import numpy as np
import pytest
import zmq
from natnet.packet_buffer import PacketBuffer

from retargetd.protocols import natnet, natnet_client
from retargetd.protocols.errors import DecodeError
from retargetd.protocols.marker_input import (
    ACCEPTED,
    REASON_INDEX,
    RESTART,
    MarkerStream,
)
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


em = _load("natnet_emulator")

# NatNet 3.1 frame of data, worked out by hand from the SDK's layout: frame 5, one
# marker set "Performer" with the marker (1, 2, 3) m, no other markers, one rigid
# body (id 7 at (0.5, 1, 0.25), identity quaternion, error 0.125, params 1), no
# skeletons, one labelled marker (id 1<<16|1, size 2^-6, params 0x04 model solved,
# residual 2^-10 m), no force plates or devices; timecode 0x01020304, subframe 0,
# timestamp 0.25 s, stamps 250000000 / +1000 / +2000, params 0.
FRAME_31_HEX = (
    "0700 a400"  # NAT_FRAMEOFDATA, 164 payload bytes
    "05000000"  # frame 5
    "01000000 506572666f726d657200 01000000"  # 1 set, "Performer\0", 1 marker
    "0000803f 00000040 00004040"  # (1, 2, 3)
    "00000000"  # other markers
    "01000000 07000000 0000003f 0000803f 0000803e"  # 1 rigid body: id 7, position
    "00000000 00000000 00000000 0000803f 0000003e 0100"  # quaternion, error, params
    "00000000"  # skeletons
    "01000000 01000100 0000803f 00000040 00004040"  # 1 labelled: id, position
    "0000803c 0400 0000803a"  # size 2^-6, params 0x04, residual 2^-10
    "00000000 00000000"  # force plates, devices
    "04030201 00000000 000000000000d03f"  # timecode, subframe, timestamp 0.25
    "80b2e60e00000000 68b6e60e00000000 50bae60e00000000 0000"  # stamps, params
)

# NatNet 3.1 model definitions for a marker set "Performer" (markers "Performer_A",
# "Performer_B") and a skeleton "Performer" id 1 with no bones.
MODELDEF_31_HEX = (
    "0500 4400 02000000"  # NAT_MODELDEF, 68 bytes, 2 descriptions
    "00000000 506572666f726d657200 02000000"  # marker set "Performer", 2 names
    "506572666f726d65725f4100 506572666f726d65725f4200"  # "Performer_A\0" "_B\0"
    "02000000 506572666f726d657200 01000000 00000000"  # skeleton, id 1, 0 bones
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
    assert _doc_hex("natnet_frame_31") == _hex(FRAME_31_HEX)
    assert _doc_hex("natnet_modeldef_31") == _hex(MODELDEF_31_HEX)


def test_emulator_frame_matches_the_hand_worked_bytes() -> None:
    got = em.frame_of_data(
        (3, 1), 5, np.array([[1.0, 2.0, 3.0]]), 0.25, timecode=0x01020304
    )
    assert got == _hex(FRAME_31_HEX)


def test_emulator_model_defs_match_the_hand_worked_bytes() -> None:
    assert em.model_defs((3, 1), ["A", "B"]) == _hex(MODELDEF_31_HEX)


def test_decoder_reads_the_hand_worked_bytes() -> None:
    models = natnet.decode_model_defs(_hex(MODELDEF_31_HEX), natnet.Version(3, 1))
    assert models.marker_sets == (("Performer", ("Performer_A", "Performer_B")),)
    assert models.model_ids == {"Performer": 1}
    labels = natnet.label_set_from_models(models, 3)
    assert labels.labels == ("A", "B")
    one = natnet.ModelDefs(models.version, (("Performer", ("Performer_A",)),), {})
    ls = natnet.label_set_from_models(one, 4)
    dec = natnet.NatNetDecoder(one, ls)
    stream = MarkerStream(ls, "+Y", "m")
    assert stream.feed(dec, _hex(FRAME_31_HEX), t_ns=1) == ACCEPTED
    frame = stream.current.frame
    # Motive +Y up -> world +Z up: (x, y, z) -> (x, -z, y).
    np.testing.assert_array_equal(frame.markers_world, [[1.0, -3.0, 2.0]])
    assert frame.frame_id == 5 and frame.source_time_s == 0.25
    assert dec.timecode == 0x01020304 and not dec.models_changed


def test_server_info_hand_worked() -> None:
    payload = b"Motive".ljust(256, b"\0") + bytes([3, 1, 0, 0, 4, 1, 0, 0])
    payload += _hex("00ca9a3b00000000 f705 01 efff2a63")  # clock, port 1527, group
    info = natnet.decode_server_info(_hex("0100 1701") + payload)
    assert info.app_name == "Motive" and info.natnet_version == natnet.Version(4, 1)
    assert info.data_port == 1527 and info.multicast
    assert info.multicast_group == "239.255.42.99"
    assert em.server_info((4, 1), 1527)[:268] == (_hex("0100 1701") + payload)[:268]


@pytest.mark.parametrize("version", [(3, 1), (4, 0), (4, 1)])
def test_third_party_reader_agrees_with_the_emulator(version: tuple[int, int]) -> None:
    """The PyPI ``natnet`` package (its own reading of the SDK) reads what the
    emulator writes, including the 4.1 list sizes."""
    pos = np.array([[0.1, 0.2, 0.3], [np.nan, np.nan, np.nan]])
    pkt = em.frame_of_data(version, 9, pos, 1.5, timecode=77)
    frame = natnet_pkg.DataFrame.read_from_buffer(
        PacketBuffer(pkt[4:]), natnet_pkg.Version(*version)
    )
    assert frame.prefix.frame_number == 9
    (ms,) = frame.marker_sets
    np.testing.assert_allclose(ms.marker_pos_list[0], [0.1, 0.2, 0.3], rtol=1e-6)
    assert ms.marker_pos_list[1] == (0.0, 0.0, 0.0)
    assert [m.param for m in frame.labeled_markers] == [0x04, 0x01]
    assert frame.suffix.timecode == 77 and frame.suffix.timestamp == 1.5
    dd = natnet_pkg.DataDescriptions.read_from_buffer(
        PacketBuffer(em.model_defs(version, ["A", "B"])[4:]),
        natnet_pkg.Version(*version),
    )
    assert dd.marker_sets[0].marker_names == ("Performer_A", "Performer_B")


def _decoder(version: tuple[int, int], labels: list[str]) -> Any:
    models = natnet.decode_model_defs(
        em.model_defs(version, labels), natnet.Version(*version)
    )
    ls = natnet.label_set_from_models(models, 1)
    return natnet.NatNetDecoder(models, ls), ls


@pytest.mark.parametrize("version", [(3, 1), (4, 1)])
def test_cut_and_garbled_frames_raise_only_decode_error(
    version: tuple[int, int], rng: np.random.Generator
) -> None:
    dec, ls = _decoder(version, ["A", "B", "C"])
    stream = MarkerStream(ls, "+Y", "m")
    pos = rng.normal(size=(3, 3))
    pkt = em.frame_of_data(version, 3, pos, 0.1)
    reasons = set()
    for cut in range(len(pkt)):
        code = stream.feed(dec, pkt[:cut], t_ns=cut)
        assert code not in (ACCEPTED, RESTART)
        assert stream.last_error is not None
        reasons.add(stream.last_error.reason)
    for _ in range(300):
        garbled = bytearray(pkt)
        k = int(rng.integers(4, len(pkt)))
        garbled[k : k + 4] = rng.bytes(4)
        # feed() catches DecodeError only: anything else would fail the test.
        stream.feed(dec, bytes(garbled), t_ns=10_000 + k)
    assert "bad_length" in reasons
    assert stream.counters.dropped() >= len(pkt)


@pytest.mark.parametrize("version", [(3, 0), (3, 1), (4, 0), (4, 1), (4, 2)])
def test_model_defs_skip_rigid_bodies_in_every_layout(version: tuple[int, int]) -> None:
    packet = em.model_defs(version, ["LASI", "RASI"], rigid_body=True)
    models = natnet.decode_model_defs(packet, natnet.Version(*version))
    assert models.marker_sets == (("Performer", ("Performer_LASI", "Performer_RASI")),)
    assert models.model_ids == {"Wand": 7, "Performer": 1}


def test_label_set_names_sets_and_prefixes() -> None:
    models = natnet.ModelDefs(
        natnet.Version(4, 1),
        (
            ("all", ("Performer_LASI", "Wand_1")),
            ("Performer", ("Performer_LASI", "Performer_RASI")),
            ("Wand", ("Wand_1", "LASI")),
        ),
        {"Performer": 1, "Wand": 7},
    )
    labels = natnet.label_set_from_models(models, 9).labels
    assert labels == ("LASI", "RASI", "1", "Wand:LASI")  # "all" left out
    only = natnet.label_set_from_models(models, 9, sets=["Wand"]).labels
    assert only == ("1", "LASI")


def test_configured_z_up_is_used() -> None:
    """Motive set to Z up: positions pass unrotated (the stream cannot tell)."""
    dec, ls = _decoder((4, 1), ["A"])
    stream = MarkerStream(ls, "+Z", "m")
    pkt = em.frame_of_data((4, 1), 1, np.array([[0.5, 0.25, 2.0]]), 0.0)
    assert stream.feed(dec, pkt, t_ns=1) == ACCEPTED
    np.testing.assert_array_equal(stream.current.frame.markers_world, [[0.5, 0.25, 2]])


def test_count_change_is_count_mismatch_and_asks_again(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A marker set that grew: dropped as count_mismatch, model definitions asked."""
    client = natnet_client.NatNetClient("127.0.0.1", 9, local="127.0.0.1")
    asked: list[int] = []
    try:
        monkeypatch.setattr(client, "request_models", lambda: asked.append(1))
        inp = natnet_client.NatNetInput(client)
        inp.session.adopt_models(
            natnet.decode_model_defs(
                em.model_defs((4, 1), ["A", "B"]), natnet.Version(4, 1)
            )
        )
        pkt = em.frame_of_data((4, 1), 1, np.zeros((3, 3)), 0.0)
        assert inp.feed(pkt, 1) == REASON_INDEX["count_mismatch"]
        assert inp.stream.counters["count_mismatch"] == 1
        assert asked == [1]
    finally:
        client.close()


def test_multicast_client_joins_the_group_without_sending() -> None:
    """The multicast data socket is bound to the data port and joined; nothing is
    sent here (traffic stays on 127.0.0.1)."""
    client = natnet_client.NatNetClient(
        "127.0.0.1", 9, 0, multicast=True, local="127.0.0.1"
    )
    try:
        assert client.data is not None and len(client.fds()) == 2
        assert client.data.getsockname()[1] > 0
    finally:
        client.close()


def test_natnet_urls() -> None:
    opts = natnet_client.parse_natnet_url("natnet://10.0.0.5")
    assert (opts.host, opts.command_port, opts.data_port) == ("10.0.0.5", 1510, 1511)
    assert not opts.multicast and opts.up_axis == "+Y" and opts.sets is None
    opts = natnet_client.parse_natnet_url(
        "natnet://motive:1600?data_port=1601&multicast=1&up=z&sets=Performer,Wand"
    )
    assert (opts.command_port, opts.data_port, opts.multicast) == (1600, 1601, True)
    assert opts.up_axis == "+Z" and opts.sets == ("Performer", "Wand")
    for bad in ("qtm://x", "natnet://", "natnet://x?speed=1", "natnet://x?up=w"):
        with pytest.raises(ValueError):
            natnet_client.parse_natnet_url(bad)


def test_unknown_version_is_refused() -> None:
    with pytest.raises(DecodeError) as err:
        natnet.decode_model_defs(em.model_defs((4, 1), ["A"]), natnet.Version(2, 9))
    assert err.value.reason == "bad_version"


# ---- over loopback -------------------------------------------------------------------


class _Loop:
    """A stand-in for the daemon's loop: a zmq.Poller on the client's sockets."""

    def __init__(self, client: natnet_client.NatNetClient, up: str = "+Y") -> None:
        self.client = client
        self.input = natnet_client.NatNetInput(client, up)
        self.poller = zmq.Poller()
        for sock in client.fds():
            self.poller.register(sock, zmq.POLLIN)
        self.frames: list[tuple[int, tuple[str, ...], np.ndarray]] = []
        self.codes: list[int] = []
        self.recorded: list[bytes] = []  # every datagram, as a recorder gets them

    def run_until(self, done: Any, timeout_s: float) -> None:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end and not done():
            events = dict(self.poller.poll(5))
            self.client.tick()
            for sock in self.client.fds():
                if sock.fileno() not in events:
                    continue
                while (pkt := self.client.read(sock)) is not None:
                    self.recorded.append(bytes(pkt))
                    code = self.input.feed(pkt, time.monotonic_ns())
                    self.codes.append(code)
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
    return load_take(datasets / "btkdata" / "PiG_Motion-FlatFoot-Full.c3d")


def _serve(take: Any, scenario: Any) -> Any:
    server = em.NatNetEmulator(
        take.positions, list(take.labels), take.rate_hz, take.first_frame, scenario
    )
    server.start()
    return server


@pytest.mark.timeout(60)
@pytest.mark.parametrize("version", [(3, 1), (4, 1)])
def test_served_take_arrives_equal_with_faults_counted(
    take: Any, version: tuple[int, int]
) -> None:
    scenario = em.Scenario(version=version, label_change_at=150, restart_at=250)
    server = _serve(take, scenario)
    lines: list[str] = []
    client = natnet_client.NatNetClient(
        "127.0.0.1", server.command_port, local="127.0.0.1", out=lines.append
    )
    loop = _Loop(client)
    try:
        loop.run_until(lambda: server.done.is_set() and len(loop.frames) > 300, 30)
        loop.run_until(lambda: False, 0.2)  # drain the tail
    finally:
        client.close()
        server.close()
    n = take.positions.shape[0]
    counters = loop.input.stream.counters
    # Every frame served once before the restart, then 0..n-1 again after it.
    first_pass = [f for f in loop.frames[: 250 + 1]]
    ids = [f[0] - take.first_frame for f in first_pass]
    assert ids[:20] == list(range(20)) and 250 in ids
    for fid, _labels, markers in loop.frames:
        row = take.positions[fid - take.first_frame]
        np.testing.assert_allclose(markers, row, atol=2e-7, rtol=1e-6)
        assert np.array_equal(np.isnan(markers), np.isnan(row))
    assert counters["duplicate"] == 1
    assert counters["backwards"] == 1  # the second of the swapped pair
    assert counters["bad_length"] + counters["bad_count"] >= 1  # the truncated one
    assert counters.dropped() >= 4  # duplicate, backwards, truncated, garbled
    assert counters["restart"] == 1
    # The label change was followed: later frames carry the renamed marker.
    assert loop.frames[-1][1][0] == "renamed" and loop.frames[0][1][0] == "RFHD"
    assert client.session.counts["model_defs"] >= 2
    assert len(loop.frames) >= n + 250 - 10
    assert any("connected to Motive" in line for line in lines)
    # Replay: the recorded datagrams through a socket-free input, same frames.
    replay = natnet_client.NatNetInput(None, "+Y")
    again = []
    pause_ns = 0
    for k, pkt in enumerate(loop.recorded):
        # 10 ms apart, and the restart's pause from its first frame on (the receive
        # clock never goes back; frames after it come later still).
        if natnet.packet_info(pkt)[1] == take.first_frame and k > 10:
            pause_ns = 2_000_000_000
        t_ns = k * 10_000_000 + pause_ns
        if replay.feed(pkt, t_ns) in (ACCEPTED, RESTART):
            again.append(replay.stream.current.frame.frame_id)
    assert again == [f[0] for f in loop.frames]


# alone (tests/helpers/alone.py): times a read and a tick (under 50 ms), a few
# scheduler slices lost to the other xdist worker's test.
@pytest.mark.alone
@pytest.mark.timeout(30)
def test_vanished_server_is_reported_once_and_never_blocks(take: Any) -> None:
    server = _serve(take, em.Scenario(faults=False, vanish_at=50))
    lines: list[str] = []
    client = natnet_client.NatNetClient(
        "127.0.0.1", server.command_port, local="127.0.0.1", out=lines.append
    )
    loop = _Loop(client)
    try:
        loop.run_until(lambda: client.timeouts >= 1, 10)
        t0 = time.monotonic()
        for sock in client.fds():
            assert client.read(sock) is None
        client.tick()
        assert time.monotonic() - t0 < 0.05
    finally:
        client.close()
        server.close()
    assert client.timeouts == 1
    assert sum("no packet from 127.0.0.1" in line for line in lines) == 1
    assert 40 <= len(loop.frames) <= 51
    assert client.session.info is None  # connecting again


@pytest.mark.timeout(30)
def test_unknown_protocol_version_is_said_and_counted(take: Any) -> None:
    server = _serve(take, em.Scenario(faults=False, version=(2, 9)))
    lines: list[str] = []
    client = natnet_client.NatNetClient(
        "127.0.0.1", server.command_port, local="127.0.0.1", out=lines.append
    )
    loop = _Loop(client)
    try:
        loop.run_until(lambda: client.session.counts["bad_control"] >= 2, 5)
    finally:
        client.close()
        server.close()
    session = client.session
    assert session.decoder is None and session.info is None
    assert session.last_error is not None
    assert session.last_error.reason == "bad_version"
    assert sum("NatNet 2.9" in line for line in lines) == 1  # said once, counted


@pytest.mark.timeout(30)
def test_flood_is_drained_and_counted(take: Any) -> None:
    server = _serve(take, em.Scenario(faults=False, flood=True))
    client = natnet_client.NatNetClient(
        "127.0.0.1", server.command_port, local="127.0.0.1"
    )
    loop = _Loop(client)
    try:
        loop.run_until(lambda: server.done.is_set(), 10)
        loop.run_until(lambda: False, 0.3)
    finally:
        client.close()
        server.close()
    counters = loop.input.stream.counters
    sent = server.sent["frames"]
    got = counters["accepted"] + counters.dropped()
    # Unpaced: the kernel may drop datagrams; everything that arrived is counted.
    assert 0 < got <= sent
    assert counters["accepted"] == len(loop.frames) > 0
