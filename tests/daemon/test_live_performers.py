"""Several performers on one daemon (``[[performer]]``; issue 19 item 2), over real
loopback sockets: two copies of the synthetic performer on one OSC input, their
labels prefixed ``A:`` and ``B:`` and B standing 2 m further along world +X; each
calibrated on its own with ``retargetd ctl calibrate --performer``, each streamed to
its own VMC port, both on the one pose stream with their performer ids, both in the
status; an unknown performer is a clear error. Plus the config rules, the label
split and the pose header's performer byte.
"""

from __future__ import annotations

import json
import socket
import threading
import time
import tomllib
import tracemalloc
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import live_harness as lh
import numpy as np
import pytest
import zmq
from live_harness import (
    EXACT_RIG,
    WAIT_S,
    Live,
    OscSource,
    PoseSub,
    VmcReceiver,
    _json_strict,
    _take,
    _vmc_bones,
    _vmc_quats,
    _wait_until,
)
from pythonosc.osc_message_builder import OscMessageBuilder

from retargetd.daemon.cli.main import main as cli_main
from retargetd.daemon.live.catchup import CatchUp
from retargetd.daemon.live.config import ConfigError, DaemonConfig
from retargetd.daemon.live.loop import Daemon
from retargetd.daemon.live.performer import StreamView, build_performers
from retargetd.protocols import natnet, natnet_client, osc_in, pose_stream, zmq_wire
from retargetd.protocols.marker_input import LabelSet, MarkerStream
from retargetd.replay.recording import _capture_input

pytestmark = pytest.mark.timeout(120)

#: Performer B stands this far from A along world +X (metres).
B_OFFSET = np.array([2.0, 0.0, 0.0])


# ---- config ------------------------------------------------------------------------


def _doc(*performers: dict[str, Any], **extra: Any) -> dict[str, Any]:
    return {"performer": list(performers), **extra}


def test_performer_tables_parse_with_default_prefixes() -> None:
    c = DaemonConfig.from_dict(
        _doc(
            {"name": "A", "rig": str(EXACT_RIG), "vmc": "127.0.0.1:40001"},
            {"name": "B", "prefix": "", "input": "osc", "vmc": "127.0.0.1:40002"},
        )
    )
    assert [(p.name, p.prefix, p.input) for p in c.performers] == [
        ("A", "A:", "any"),
        ("B", "", "osc"),
    ]
    assert c.performer is c.performers[0]  # [performer] readers see the first
    assert DaemonConfig.from_dict({}).performers == ()  # none: one performer


@pytest.mark.parametrize(
    ("doc", "key", "words"),
    [
        (_doc({"name": "A"}, {"name": "A", "vmc": "127.0.0.1:1"}), "performer[1].name",
         "taken"),
        (_doc({"name": "A"}, {"name": "B"}), "performer[1].vmc", "one avatar per port"),
        (_doc({"name": "A", "vmc": "127.0.0.1:9"}, {"name": "B", "prefix": "A:",
               "vmc": "127.0.0.1:8"}), "performer[1].prefix", "another performer's"),
        (_doc({"rig": "menache"}), "performer[0].name", "needs a name"),
        (_doc({"name": "A", "vmc": "127.0.0.1"}), "performer[0].vmc", "HOST:PORT"),
        (_doc({"name": "A", "vmc": "0.0.0.0:5"}), "performer[0].vmc",
         "a receiver's address"),
        ({"performer": []}, "performer", "at least one"),
        (_doc({"name": "A", "input": "source"}), "performer[0].input",
         "never get a frame"),
        (_doc({"name": "A", "vmc": "239.1.2.3:5"}), "performer[0].vmc",
         "allow_broadcast"),
        ({"performers": []}, "performers", "[[performer]]"),
    ],
)  # fmt: skip
def test_performer_tables_refused_with_the_key_named(
    doc: dict[str, Any], key: str, words: str
) -> None:
    with pytest.raises(ConfigError) as info:
        DaemonConfig.from_dict(doc, source="t")
    assert f"t: {key}: " in str(info.value) and words in str(info.value)


def test_the_readme_example_loads() -> None:
    readme = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    section = readme.split("### Several performers", 1)[1]
    text = section.split("```toml\n", 1)[1].split("```", 1)[0]
    c = DaemonConfig.from_dict(tomllib.loads(text), source="README")
    assert [(p.name, p.prefix, p.vmc) for p in c.performers] == [
        ("A", "A:", "127.0.0.1:39541"),
        ("B", "B:", "127.0.0.1:39542"),
    ]


def test_each_performer_its_own_rig_face_and_destination(
    exact_calibration: Path,
) -> None:
    c = DaemonConfig.from_dict(
        _doc(
            {"name": "A", "rig": str(EXACT_RIG), "calibration": str(exact_calibration),
             "vmc": "127.0.0.1:40001", "face": "vrm1"},
            {"name": "B", "rig": "plug-in-gait", "vmc": "127.0.0.1:40002"},
            face={"enabled": True, "capture_frames": 7},
        )
    )  # fmt: skip
    a, b = build_performers(c)
    assert (a.index, a.name, b.index, b.name) == (0, "A", 1, "B")
    assert a.rig.name == "synth-exact" and b.rig.name == "plug-in-gait"
    assert a.calibration is not None and b.calibration is None
    assert a.face is not None and b.face is None  # B has no face config
    assert a.face.face.name == "vrm1" and a.face.settings.capture_frames == 7
    assert (a.vmc_addr, b.vmc_addr) == (("127.0.0.1", 40001), ("127.0.0.1", 40002))
    assert a.rivals_by_input["osc"] == ("A:", "B:")
    # No [[performer]]: the one performer of [performer], every label its own.
    (one,) = build_performers(DaemonConfig.from_dict({}))
    assert (one.name, one.prefix, one.face) == ("", "", None)


def test_one_performer_reads_the_stream_itself_several_read_views() -> None:
    """One performer is the N = 1 case of many, on the same path
    (``Performer.frame_of``): the one performer of ``[performer]`` reads each input's
    stream itself (nothing copied, its pipelines keyed by the stream); a performer
    of several reads its view, and none when a frame has none of its markers."""
    stream = MarkerStream(LabelSet(1, ("A:X", "B:X", "A:Y")))
    (one,) = build_performers(DaemonConfig.from_dict({}))
    assert one.key_of(stream) == 0  # not read yet
    assert one.frame_of(stream, "osc") is stream
    assert one.key_of(stream) == id(stream)
    c = DaemonConfig.from_dict(
        _doc(
            {"name": "A", "rig": str(EXACT_RIG), "vmc": "127.0.0.1:40001"},
            {"name": "B", "rig": str(EXACT_RIG), "vmc": "127.0.0.1:40002"},
        )
    )
    a, b = build_performers(c)
    view = a.frame_of(stream, "osc")
    assert isinstance(view, StreamView) and view.current.label_set.labels == ("X", "Y")
    assert a.key_of(stream) == id(view)  # its pipelines are keyed by its view
    assert b.frame_of(stream, "osc").current.label_set.labels == ("X",)
    stream.current = type(stream.current).create(LabelSet(2, ("B:X",)))
    assert a.frame_of(stream, "osc") is None  # none of A's markers in this frame


def test_run_rig_and_calibration_flags_refused_with_performer_tables(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "two.toml"
    path.write_text('[[performer]]\nname = "A"\n')
    assert cli_main(["run", "--config", str(path), "--rig", "cmu41"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "[[performer]]" in err, err


# ---- the label split ----------------------------------------------------------------


def test_stream_view_takes_its_prefix_longest_match_no_allocation() -> None:
    labels = ("A:X", "B:X", "AB:X", "X", "A:Y", "A:")
    stream = MarkerStream(LabelSet(3, labels))
    markers = np.arange(18, dtype=np.float64).reshape(6, 3)
    stream.current.frame.markers_world[:] = markers
    stream.current.frame.valid[:] = [True, True, False, True, True, True]
    stream.current.frame.frame_id = 41
    rivals = ("A:", "B:", "AB:", "")
    views = {p: StreamView(stream, p, rivals) for p in rivals}
    for v in views.values():
        assert v.refresh()
    got = {p: v.current.label_set.labels for p, v in views.items()}
    # "A:" exactly is nobody's marker; "AB:X" is AB's, not A's (longest prefix).
    assert got == {"A:": ("X", "Y"), "B:": ("X",), "AB:": ("X",), "": ("X",)}
    a = views["A:"].current.frame
    np.testing.assert_array_equal(a.markers_world, markers[[0, 4]])
    assert a.valid.tolist() == [True, True] and a.frame_id == 41
    assert views["AB:"].current.frame.valid.tolist() == [False]
    # The next frame: copied into the same buffers (nothing allocated per frame).
    before = (a.markers_world, a.valid)
    stream.current.frame.markers_world[4] = (-1.0, -2.0, -3.0)
    assert views["A:"].refresh()
    assert views["A:"].current.frame.markers_world is before[0]
    assert views["A:"].current.frame.valid is before[1]
    assert a.markers_world[1].tolist() == [-1.0, -2.0, -3.0]
    # A label set without a performer's markers: nothing to solve for it.
    stream.current = type(stream.current).create(LabelSet(4, ("B:X",)))
    assert not views["A:"].refresh() and views["B:"].refresh()


@pytest.mark.parametrize("interleaved", [False, True])
def test_stream_view_refresh_allocates_nothing(interleaved: bool) -> None:
    # 35 markers each for A and B, as one run each (slice copies) or interleaved
    # (take). What 1000 refreshes keep is nothing; the peak stays under one copy of
    # B's rows (35 x 3 float64 = 840 B, what fancy indexing would allocate).
    names = [f"M{i}" for i in range(35)]
    if interleaved:
        labels = tuple(x for n in names for x in (f"A:{n}", f"B:{n}"))
    else:
        labels = tuple(f"A:{n}" for n in names) + tuple(f"B:{n}" for n in names)
    stream = MarkerStream(LabelSet(1, labels))
    view = StreamView(stream, "B:", ("A:", "B:"))
    assert view.refresh() and (view.rows is None) == interleaved
    tracemalloc.start()
    try:
        start = tracemalloc.get_traced_memory()[0]
        tracemalloc.reset_peak()
        for _ in range(1000):
            view.refresh()
        now, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert now - start < 64 and peak - start < 840, (now - start, peak - start)


def test_natnet_subjects_label_every_set_for_the_split() -> None:
    # Motive's skeleton markers "A_LASI" in set "A": by default the first set's
    # names stay plain ("LASI") and only later conflicting ones get "B:"; with
    # subjects=1 every label is <set>:<name>, the prefixes [[performer]] split by.
    models = natnet.ModelDefs(
        natnet.Version(4, 1),
        (("A", ("A_LASI", "A_RASI")), ("B", ("B_LASI", "B_HEAD")), ("all", ("x",))),
    )
    plain = natnet.label_set_from_models(models, 1).labels
    assert plain == ("LASI", "RASI", "B:LASI", "HEAD")
    subjects = natnet.label_set_from_models(models, 1, subjects=True).labels
    assert subjects == ("A:LASI", "A:RASI", "B:LASI", "B:HEAD")
    stream = MarkerStream(LabelSet(1, subjects))
    views = [StreamView(stream, p, ("A:", "B:")) for p in ("A:", "B:")]
    assert [v.refresh() and v.current.label_set.labels for v in views] == [
        ("LASI", "RASI"),
        ("LASI", "HEAD"),
    ]
    opts = natnet_client.parse_natnet_url(
        "natnet://127.0.0.1?subjects=1&sets=A,B&local=127.0.0.1"
    )
    assert opts.subjects and opts.sets == ("A", "B")
    client = opts.client()
    try:
        assert client.session.subjects
    finally:
        client.close()
    assert not natnet_client.parse_natnet_url("natnet://10.0.0.2").subjects
    # A recording made so is read back so (its source URL in the metadata).
    inp = _capture_input("natnet", "+Y", "natnet://10.0.0.2?subjects=1")
    assert inp.session.subjects and not _capture_input("natnet", "+Y").session.subjects


# ---- the pose header's performer byte ----------------------------------------------


def test_pose_header_performer_byte_50_and_single_performer_bytes_unchanged() -> None:
    args = (
        7, 0.5, 1000, 2000, pose_stream.FRAME_HELD, np.zeros(3),
        np.tile([1.0, 0, 0, 0], (2, 1)), np.tile([1.0, 0, 0, 0], (2, 1)),
        np.tile([1.0, 0, 0, 0], (2, 1)), np.zeros(0), np.zeros(2, np.uint8),
    )  # fmt: skip
    plain = [bytes(p) for p in pose_stream.PoseEncoder(2, 0).encode(*args)]
    zero = [bytes(p) for p in pose_stream.PoseEncoder(2, 0, performer=0).encode(*args)]
    assert plain == zero  # one performer: the bytes of before
    third = [bytes(p) for p in pose_stream.PoseEncoder(2, 0, performer=3).encode(*args)]
    assert third[0][pose_stream.PERFORMER_OFFSET] == 3
    assert third[0][:50] == plain[0][:50] and third[0][51:] == plain[0][51:]
    msg = pose_stream.decode_pose(third)
    assert msg.performer == 3 and msg.flags == pose_stream.FRAME_HELD
    assert pose_stream.decode_pose(plain).performer == 0
    with pytest.raises(ValueError, match="performer"):
        pose_stream.PoseEncoder(2, 0, performer=256)
    bones = {"rig": "r", "bone_names": ("Hips",), "bone_parents": (-1,),
             "weight_names": ()}  # fmt: skip
    names = pose_stream.PoseNames(**bones, performer="B", performer_id=1)
    back = pose_stream.decode_pose_names(pose_stream.encode_pose_names(names))
    assert (back.performer, back.performer_id) == ("B", 1)
    one = pose_stream.encode_pose_names(pose_stream.PoseNames(**bones))
    assert b"performer" not in one[1]


# ---- two performers live -----------------------------------------------------------


class _TwoStreamer(threading.Thread):
    """A and B in one OSC frame at ~200 Hz: A holds the T-pose; B holds it too, or
    plays the take's motion when ``b_moving`` is set; B 2 m along +X."""

    def __init__(self, src: OscSource) -> None:
        super().__init__(name="test-two-performers", daemon=True)
        take = _take()
        self.src = src
        labels = take.labels
        src.label_set = LabelSet(1, tuple(f"A:{n}" for n in labels)
                                 + tuple(f"B:{n}" for n in labels))  # fmt: skip
        self.hold = take.markers_world[take.base_pose_frames]
        self.motion = take.markers_world[int(take.base_pose_frames.stop) :]
        self.b_moving = False
        self.stop_event = threading.Event()

    def run(self) -> None:
        k = 0
        while not self.stop_event.is_set():
            if k % 100 == 0:
                self.src.announce()
            a = self.hold[k % len(self.hold)]
            b = self.motion[k % len(self.motion)] if self.b_moving else a
            self.src.send(np.concatenate([a, b + B_OFFSET]))
            k += 1
            time.sleep(0.005)

    def stop(self) -> None:
        self.stop_event.set()
        self.join(timeout=2.0)
        assert not self.is_alive()


@pytest.fixture
def two_streamer() -> Iterator[Callable[[OscSource], _TwoStreamer]]:
    made: list[_TwoStreamer] = []

    def make(src: OscSource) -> _TwoStreamer:
        s = _TwoStreamer(src)
        made.append(s)
        s.start()
        return s

    yield make
    for s in made:
        s.stop()


def _pump_until(
    recv: list[VmcReceiver], pred: Callable[[], bool], what: str, timeout_s: float = 5
) -> None:
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        for r in recv:
            r.pump(max_datagrams=256)


def test_two_performers_calibrated_apart_each_to_its_own_vmc_port(
    start_daemon: Callable[..., Live],
    udp_socket: Callable[..., socket.socket],
    zmq_socket: Callable[[int], Any],
    two_streamer: Callable[[OscSource], _TwoStreamer],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    va = VmcReceiver(udp_socket(bind=True, timeout_s=0.01))
    vb = VmcReceiver(udp_socket(bind=True, timeout_s=0.01))
    live = start_daemon(
        {
            "performer": [
                {"name": "A", "rig": str(EXACT_RIG), "vmc": f"127.0.0.1:{va.port}",
                 "save_calibration": str(tmp_path / "a.json")},
                {"name": "B", "rig": str(EXACT_RIG), "vmc": f"127.0.0.1:{vb.port}",
                 "save_calibration": str(tmp_path / "b.json")},
            ],
            "control": {"min_interval_s": 0.01},
        }
    )  # fmt: skip
    assert "vmc out A" in live.daemon.endpoints and "vmc out B" in live.daemon.endpoints
    assert live.udp("vmc out B") == ("127.0.0.1", vb.port)
    ep = live.tcp("control")
    sub = PoseSub(zmq_socket(zmq.SUB), live.tcp("zmq poses"))
    src = OscSource(udp_socket(), live.udp("osc markers"), live=live)
    feed = two_streamer(src)

    def ctl(*argv: str) -> tuple[int, str, str]:
        rc = cli_main(["ctl", "--endpoint", ep, *argv])
        out, err = capsys.readouterr()
        return rc, out, err

    # With two performers a calibration names one; an unknown name is refused.
    rc, _, err = ctl("calibrate")
    assert rc == 1 and "2 performers (A, B)" in err and "--performer" in err
    rc, _, err = ctl("calibrate", "--performer", "Z")
    assert rc == 1 and "unknown performer 'Z'" in err and "A, B" in err
    rc, _, err = ctl("face-capture", "neutral", "--performer", "Z")
    assert rc == 1 and "unknown performer 'Z'" in err
    # Nobody calibrated: no pose anywhere, both avatars hear "waiting".
    _pump_until([va, vb], lambda: bool(va.states and vb.states), "VMC states")
    assert not va.frames and not vb.frames

    # A first: its avatar moves, B's still waits.
    rc, out, _ = ctl("calibrate", "--performer", "A", "--count", "10")
    assert rc == 0 and "next 10 frames" in out
    # ctl waited for A's outcome (issue 29: the result reaches the client)
    assert "calibrated on 10 frames; saved" in out and "a.json" in out, out
    _wait_until(lambda: any(ln.startswith("A: calibrated on 10 frames; saved")
                            for ln in live.lines), "A calibrated")  # fmt: skip
    _pump_until([va, vb], lambda: len(va.frames) > 10, "A's VMC frames")
    vb.pump()
    assert not vb.frames
    doc = _json_strict(ctl("status", "--json")[1])
    by_name = {p["name"]: p for p in doc["performers"]}
    assert by_name["A"]["calibrated"] and not by_name["B"]["calibrated"]
    assert not doc["calibrated"]  # not every performer is

    # Then B, over show control (/rtd/calibrate ,si "B" 10).
    msg = OscMessageBuilder("/rtd/calibrate")
    msg.add_arg("B")
    msg.add_arg(10)
    udp_socket().sendto(msg.build().dgram, live.udp("show control"))
    _wait_until(lambda: any(ln.startswith("B: calibrated on 10 frames; saved")
                            for ln in live.lines), "B calibrated")  # fmt: skip
    assert json.loads((tmp_path / "b.json").read_text())["base_pose"]["live"]
    _pump_until([va, vb], lambda: len(vb.frames) > 10, "B's VMC frames")

    # Both in T-pose, each calibrated where it stands: the same VMC bones (the
    # root relative to its calibration); in the pose stream (world) B's root is
    # 2 m along +X of A's.
    np.testing.assert_allclose(
        _vmc_quats(vb.frames[-1]), _vmc_quats(va.frames[-1]), atol=1e-6
    )
    sub.wait(lambda: {p.performer for p in sub.poses[-10:]} == {0, 1}, "both poses")
    last = {p.performer: p for p in sub.poses}
    np.testing.assert_allclose(
        last[1].root_pos_world - last[0].root_pos_world, B_OFFSET, atol=1e-5
    )

    # B moves, A holds: each avatar gets its own performer's bones.
    n_a, n_b = len(va.frames), len(vb.frames)
    feed.b_moving = True
    _pump_until([va, vb], lambda: len(vb.frames) > n_b + 150, "B moving")
    feed.stop()

    def spread(frames: list[Any], bone: str) -> float:
        q = np.array([_vmc_bones(f)[bone][3:] for f in frames])
        return float(np.max(np.abs(q - q[0])))

    moved = [spread(vb.frames[n_b + 20 :], b) for b in ("Hips", "LeftUpperArm")]
    still = [spread(va.frames[n_a:], b) for b in ("Hips", "LeftUpperArm")]
    assert min(moved) > 0.05 and max(still) < 1e-5, (moved, still)

    # The one pose stream carries both, each with its id and its names message.
    sub.pump(50)
    ids = {p.performer for p in sub.poses}
    assert ids == {0, 1}
    names = {n.names_id: (n.performer, n.performer_id) for n in sub.names}
    assert set(names.values()) >= {("A", 0), ("B", 1)}
    for p in sub.poses:  # every data message's names say the same performer
        if p.names_id in names:
            assert names[p.names_id][1] == p.performer

    # Status lists both, calibrated, each with its frames and latency.
    rc, out, _ = ctl("status", "--json")
    doc = _json_strict(out)
    assert rc == 0 and doc["calibrated"]
    assert [p["name"] for p in doc["performers"]] == ["A", "B"]
    assert [p["id"] for p in doc["performers"]] == [0, 1]
    for p in doc["performers"]:
        assert p["calibrated"] and p["frames_out"] > 10, p
        assert p["latency_us"]["receive_to_sent"][1] is not None
        assert p["vmc"] == f"127.0.0.1:{(va if p['name'] == 'A' else vb).port}"
    rc, out, _ = ctl("status")
    assert rc == 0 and "performers A out" in out and ", B out" in out
    # reload acts for the whole daemon (every performer), not one.
    rc, out, _ = ctl("reload")
    assert rc == 0 and out.startswith(
        "A: reloaded rig synth-exact and calibration; B: reloaded"
    )
    reply = live.ctl({"cmd": "reload", "performer": "A"})
    assert reply["ok"] is False and "whole daemon" in reply["error"]


def test_performers_on_separate_inputs_and_the_unprefixed_labels(
    start_daemon: Callable[..., Live],
    udp_socket: Callable[..., socket.socket],
    zmq_socket: Callable[[int], Any],
    exact_calibration: Path,
) -> None:
    # One performer per input (input = "osc" / "zmq"), no prefixes: each input's
    # frames are its performer's alone.
    va = VmcReceiver(udp_socket(bind=True, timeout_s=0.01))
    vb = VmcReceiver(udp_socket(bind=True, timeout_s=0.01))
    live = start_daemon(
        {
            "performer": [
                {"name": "osc", "input": "osc", "prefix": "", "rig": str(EXACT_RIG),
                 "calibration": str(exact_calibration), "vmc": f"127.0.0.1:{va.port}"},
                {"name": "zmq", "input": "zmq", "prefix": "", "rig": str(EXACT_RIG),
                 "calibration": str(exact_calibration), "vmc": f"127.0.0.1:{vb.port}"},
            ],
        }
    )  # fmt: skip
    src = OscSource(udp_socket(), live.udp("osc markers"), live=live)
    hold = _take().markers_world[_take().base_pose_frames]
    src.announce()
    for k in range(20):
        src.send(hold[k % len(hold)])
        time.sleep(0.003)
    # (Latest wins: on a loaded machine a few of the 20 may be dropped as stale.)
    _pump_until([va, vb], lambda: len(va.frames) >= 10, "the OSC performer's frames")
    time.sleep(0.2)
    va.pump()
    vb.pump()
    assert not vb.frames  # the ZeroMQ performer got none of the OSC frames
    doc = live.ctl({"cmd": "status"})["status"]["performers"]
    assert [d["frames_out"] for d in doc] == [len(va.frames), 0]


def test_two_performers_each_with_its_validator_and_face(
    start_daemon: Callable[..., Live],
    udp_socket: Callable[..., socket.socket],
    exact_calibration: Path,
) -> None:
    # [validate] runs one live validator per performer (each its own MuJoCo model
    # and thread); [face] is on for the performer that names a face config only.
    va = VmcReceiver(udp_socket(bind=True, timeout_s=0.01))
    vb = VmcReceiver(udp_socket(bind=True, timeout_s=0.01))
    base = {"rig": str(EXACT_RIG), "calibration": str(exact_calibration)}
    live = start_daemon(
        {
            "performer": [
                {"name": "A", **base, "vmc": f"127.0.0.1:{va.port}", "face": "arkit52"},
                {"name": "B", **base, "vmc": f"127.0.0.1:{vb.port}"},
            ],
            "validate": {"enabled": True},
            "face": {"enabled": True},
        }
    )
    assert sum("live validator on" in ln for ln in live.lines) == 2
    src = OscSource(udp_socket(), live.udp("osc markers"), live=live)
    take = _take()
    src.label_set = LabelSet(
        1, tuple(f"A:{n}" for n in take.labels) + tuple(f"B:{n}" for n in take.labels)
    )
    src.announce()
    hold = take.markers_world[take.base_pose_frames]
    for k in range(60):
        src.send(np.concatenate([hold[k % len(hold)], hold[k % len(hold)] + B_OFFSET]))
        time.sleep(0.004)
    _pump_until([va, vb], lambda: len(va.frames) >= 30 and len(vb.frames) >= 30,
                "both performers' frames")  # fmt: skip

    def validated() -> list[int]:
        docs = live.ctl({"cmd": "status"})["status"]["performers"]
        return [d["validate"]["validated"] if d["validate"] else -1 for d in docs]

    _wait_until(lambda: min(validated()) > 0, "both validators' results")
    docs = live.ctl({"cmd": "status"})["status"]["performers"]
    assert docs[0]["face"] is not None and docs[1]["face"] is None
    assert docs[0]["validate"]["model"] == docs[1]["validate"]["model"]  # same body


@pytest.mark.parametrize("several", [False, True])
def test_behind_each_input_keeps_its_own_latest_with_several_performers(
    exact_calibration: Path, several: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The loop behind (catch-up window 0: every accepted frame after the wake-up's
    # first solve waits for the end of the wake-up, latest wins). Two OSC frames and
    # a ZeroMQ frame in one wake-up: the first OSC frame is solved at once; of the
    # two left, with one performer only the newer is solved (the other is stale);
    # with a performer per input each input's latest is its own performer's, so
    # both are solved.
    monkeypatch.setattr(CatchUp, "window_ns", lambda _self: 0.0)
    doc = lh._deep_merge(lh._ephemeral_doc(lh._unused_udp_port()), {})
    base = {"rig": str(EXACT_RIG), "calibration": str(exact_calibration)}
    if several:
        doc["performer"] = [
            {"name": "osc", "input": "osc", "prefix": "", **base,
             "vmc": f"127.0.0.1:{lh._unused_udp_port()}"},
            {"name": "zmq", "input": "zmq", "prefix": "", **base,
             "vmc": f"127.0.0.1:{lh._unused_udp_port()}"},
        ]  # fmt: skip
    else:
        doc["performer"] = base
    d = Daemon(DaemonConfig.from_dict(doc, source="test"), out=lambda _line: None)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    push = zmq.Context.instance().socket(zmq.PUSH)
    push.setsockopt(zmq.LINGER, 0)
    try:
        d.open()
        host, port = d.endpoints["osc markers"].split()[0][6:].rsplit(":", 1)
        push.connect(d.endpoints["zmq markers"].split()[0])
        take = _take()
        labels = LabelSet(1, take.labels)
        tx.sendto(osc_in.encode_labels(labels), (host, int(port)))
        push.send_multipart(zmq_wire.encode_zmq_labels(labels))
        hold = take.markers_world[take.base_pose_frames]
        deadline = time.monotonic() + 20.0  # generous: a loaded 2-core machine
        while d.stats.labels_in < 2:  # both announcements taken first
            assert time.monotonic() < deadline, "labels did not arrive"
            events = d._poller.poll(20)
            if events:
                d._service(events)
        # their pipelines, built off the loop: the first frames are solved
        assert d.performers.done_building(60.0), "the pipelines were never built"
        for k in range(3):
            for j in (2 * k, 2 * k + 1):  # both in the socket before the wake-up
                tx.sendto(
                    osc_in.encode_compact_frame(j, j / 100, 1, hold[k]),
                    (host, int(port)),
                )
            push.send_multipart(zmq_wire.encode_zmq_frame(k, k / 100, 1, hold[k]))
            # Both waiting, then one wake-up drains both inputs.
            deadline = time.monotonic() + WAIT_S
            while True:
                assert time.monotonic() < deadline, "frames did not arrive"
                events = d._poller.poll(20)
                ready = {sock for sock, _ in events}
                inputs = d.inputs
                osc = inputs.osc
                if inputs.zin in ready and osc is not None and osc.fileno() in ready:
                    break
            d._service(events)
        s = d.status()
        c = s["counters"]
        if several:  # the osc performer both its frames, the zmq one its one
            assert [p["frames_out"] for p in s["performers"]] == [6, 3]
            assert c["stale"] == 0
        else:  # the first OSC frame and the ZeroMQ one; the second OSC one stale
            assert c["stale"] == 3 and c["frames_out"] == 6, c
        assert c["frames_in"] == c["frames_solved"] + c["stale"] + c["unsolved"]
    finally:
        tx.close()
        push.close()
        d.close()
