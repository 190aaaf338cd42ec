"""``retargetd ctl record start FILE`` / ``stop``: recording inside a live daemon.

End to end (subprocesses, ephemeral ports on 127.0.0.1): frames of the btkdata
Plug-in Gait walk stream into ``retargetd run --process-every-frame`` over compact
OSC, the label set announced once, before anything is recorded; ``ctl record start``;
more frames (the walk's LFHD gap among them, and one malformed packet); ``ctl record
stop``. The file reads with ``read_recording`` (raw packets, the label set the daemon
was using, poses, start and stop events) and as a take, and ``retargetd replay`` of it
into a second daemon reproduces the recorded pose stream: a recording becomes a
regression test.

In-process: the control replies (errors included), control events, a writer whose
close is held back (``record stop`` still answers at once and the loop goes on
solving: the close happens off the loop thread), and a clean stop at shutdown.
"""

from __future__ import annotations

import functools
import socket
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from live_harness import _wait_until
from paths import DATASETS

from retargetd.daemon.cli.ctl import request
from retargetd.daemon.cli.main import main
from retargetd.daemon.live.config import DaemonConfig
from retargetd.daemon.live.loop import Daemon
from retargetd.protocols import osc_in, pose_stream
from retargetd.protocols.marker_input import LabelSet
from retargetd.replay import recorder as recorder_mod
from retargetd.replay import recording as rf
from retargetd.replay.take import Take
from retargetd.replay.takes import load_take

WALK = DATASETS / "btkdata/PiG_Motion-FlatFoot-Full.c3d"
#: Streamed before recording: walk rows 250..299 (frames 0..49); recorded: rows
#: 0..199 (frames 50..249; the LFHD gap is rows 0..29).
BEFORE_ROWS = range(250, 300)
RECORDED_ROWS = range(0, 200)
GARBAGE = b"/rtd/frame\0\0garbage"


@functools.cache
def _walk() -> Take:
    return load_take(WALK)


class Sender:
    """Compact OSC frames of the walk; the label set is announced once."""

    def __init__(self, addr: tuple[str, int]) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.addr = addr
        self.next_id = 0
        self.sock.sendto(osc_in.encode_labels(LabelSet(1, _walk().labels)), addr)

    def send_rows(self, rows: range, period_s: float = 0.004) -> None:
        pos = np.asarray(_walk().positions, dtype=np.float32)
        for row in rows:
            fid = self.next_id
            frame = osc_in.encode_compact_frame(fid, fid / 100, 1, pos[row])
            self.sock.sendto(frame, self.addr)
            self.next_id += 1
            time.sleep(period_s)  # a paced source, like a capture system

    def close(self) -> None:
        self.sock.close()


def _wait(pred: Callable[[], bool], what: str, timeout_s: float = 15.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(0.01)


def _decode_poses(packets: list[rf.Packet]) -> list[pose_stream.PoseMessage]:
    return [
        pose_stream.decode_pose(p.parts) for p in packets if p.kind == rf.KIND_FRAME
    ]


def _check_foxglove_channels(path: Path, poses: list[pose_stream.PoseMessage]) -> None:
    """The recording carries the Foxglove channels beside its own: decoded with the
    protobuf schemas the file declares, one scene and one transform message per
    recorded pose, and the bone frames composed from ``world`` down give each bone's
    ``world_from_bone`` of the recorded pose stream."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory
    from scipy.spatial.transform import Rotation

    from retargetd.daemon.body.rig import load_rig

    rig = load_rig("plug-in-gait")
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        scene, tf = [], []
        for _, channel, _, msg in reader.iter_decoded_messages(
            topics=["/foxglove/scene", "/foxglove/tf"]
        ):
            (scene if channel.topic == "/foxglove/scene" else tf).append(msg)
    assert len(scene) == len(tf) == len(poses)
    # Health samples for Foxglove's plots: JSON under the file's JSON schema.
    rec = rf.read_recording(path)
    health = rec.json("/foxglove/health")
    assert health, "no health samples"
    t = [h["t_ns"] for h in health]
    assert t == sorted(t) and len(set(t)) == len(t)
    for h in health:
        assert h["input_rate_hz"] >= 0.0 and h["drops"] >= 0 and h["occluded"] >= 0
        assert set(h["latency_p50_ms"]) == set(h["latency_p99_ms"]) >= {"solve"}
    checked = 0
    for k in (0, len(poses) // 2, len(poses) - 1):
        frames = {t.child_frame_id: t for t in tf[k].transforms}
        lines = {e.id: e for e in scene[k].entities}["skeleton"].lines[0].points
        assert len(lines) == 2 * len(frames)  # both ends of every determined bone

        def world(name: str, frames: dict = frames) -> Rotation:  # type: ignore[type-arg]
            t = frames[name]
            r = Rotation.from_quat(
                [t.rotation.x, t.rotation.y, t.rotation.z, t.rotation.w]
            )
            up = t.parent_frame_id
            return r if up == "world" else world(up) * r

        for b, bone in enumerate(rig.bones):
            name = f"bone/{bone.name}"
            if name not in frames:
                continue
            want = poses[k].world_from_bone_quat[b].astype(np.float64)
            got = world(name).as_quat(scalar_first=True)
            assert abs(abs(float(np.dot(got, want))) - 1.0) < 1e-5, (k, bone.name)
            checked += 1
    assert checked >= len(rig.bones)  # every bone, in three frames


def test_ctl_record_in_a_live_daemon_then_replay_reproduces_the_pose_stream(
    pig_calibration: Path,
    run_daemon: Callable[..., Any],
    retargetd: list[str],
    pose_capture: Callable[[str], Any],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    take = _walk()
    a = run_daemon(pig_calibration, "--process-every-frame")
    ctl = a.endpoints["control"]
    sender = Sender(a.udp("osc markers"))
    try:
        sender.send_rows(BEFORE_ROWS)
        _wait(lambda: a.counters()["frames_out"] == len(BEFORE_ROWS), "frames before")
        rec_path = tmp_path / "recordings" / "live.mcap"  # the default folder
        assert main(["ctl", "--endpoint", ctl, "record", "start", str(rec_path)]) == 0
        assert capsys.readouterr().out.startswith(f"recording to {rec_path}")
        sender.sock.sendto(GARBAGE, sender.addr)  # recorded, and dropped as input
        sender.send_rows(RECORDED_ROWS)
        n_all = len(BEFORE_ROWS) + len(RECORDED_ROWS)
        _wait(lambda: a.counters()["frames_out"] == n_all, "recorded frames")
        assert main(["ctl", "--endpoint", ctl, "record", "stop"]) == 0
        assert "stopped recording" in capsys.readouterr().out
    finally:
        sender.close()

    def finished() -> bool:
        reply = a.ctl({"cmd": "status"})
        assert reply is not None
        rec = reply["status"]["record"]
        return not rec["active"] and not rec["finishing"] and rec["last"] is not None

    _wait(finished, "the writer to finish the file")
    last = a.ctl({"cmd": "status"})["status"]["record"]["last"]  # type: ignore[index]
    assert last["path"] == str(rec_path) and last["dropped"] == 0, last
    # The malformed packet has a frame's header: the recorder counts it as a frame.
    assert last["write_errors"] == 0 and last["frames"] == len(RECORDED_ROWS) + 1, last

    rec = rf.read_recording(rec_path)
    assert rec.complete, rec.stop_reason
    raw = rec.packets()
    # The label set announced before the start opens the file (the daemon's own).
    assert raw[0].kind == rf.KIND_LABELS and raw[0].input == "osc"
    assert osc_in.decode_labels(raw[0].parts[0]) == LabelSet(1, take.labels)
    frames = [p for p in raw if p.kind == rf.KIND_FRAME and p.source_frame >= 0]
    first = len(BEFORE_ROWS)
    assert [p.source_frame for p in frames] == list(range(first, first + 200))
    assert len(raw) == 1 + 1 + 200  # labels, the malformed packet, the frames
    assert [p.parts[0] for p in raw if p.source_frame < 0][1:] == [GARBAGE]
    recorded_poses = _decode_poses(rec.packets(rf.POSES_TOPIC))
    assert [m.frame_id for m in recorded_poses] == list(range(first, first + 200))
    assert rec.packets(rf.POSES_TOPIC)[0].kind == rf.KIND_LABELS  # names first
    events = rec.json(rf.CONTROL_TOPIC)
    assert [e["event"] for e in events] == ["record_start", "record_stop"]
    assert events[0]["path"] == str(rec_path) and events[0]["poses"] is True
    assert events[1]["reason"] == "ctl"
    _check_foxglove_channels(rec_path, recorded_poses)
    # As a take: the recorded rows, float32 as sent.
    as_take = load_take(rec_path)
    want = np.asarray(take.positions[RECORDED_ROWS.start : RECORDED_ROWS.stop])
    np.testing.assert_array_equal(as_take.positions, want.astype(np.float32))
    assert as_take.labels == take.labels

    # Replay the recording (its own bytes, at its own timing) into a fresh daemon.
    b = run_daemon(pig_calibration, "--process-every-frame")
    cap = pose_capture(b.endpoints["zmq poses"])
    cap.prime(b, "zmq", take.labels, take.positions[0])  # the other input
    host, port = b.udp("osc markers")
    argv = [*retargetd, "replay", str(rec_path), "--to", f"osc://{host}:{port}"]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert "sent 201 frames" in done.stdout, done.stdout  # the malformed one too
    cap.wait_for(200, timeout_s=30.0)
    cap.pump(200)
    replayed = cap.poses
    assert [m.frame_id for m in replayed] == [m.frame_id for m in recorded_poses]
    flipped = 0
    for live, again in zip(recorded_poses, replayed, strict=True):
        # Bit for bit, but for the sign of world_from_bone quaternions: the
        # recording started mid-stream, and the live daemon's sign continuity
        # carries its history from before the start (q and -q are one rotation).
        np.testing.assert_array_equal(
            again.rest_from_bone_quat, live.rest_from_bone_quat
        )
        np.testing.assert_array_equal(again.root_pos_world, live.root_pos_world)
        np.testing.assert_array_equal(again.bone_flags, live.bone_flags)
        sign = np.where(
            np.sum(again.world_from_bone_quat * live.world_from_bone_quat, -1) < 0,
            -1,
            1,
        ).astype(np.float32)
        np.testing.assert_array_equal(
            again.world_from_bone_quat * sign[:, None], live.world_from_bone_quat
        )
        flipped += int((sign < 0).sum())
    print(
        f"\nreplayed {len(replayed)} poses; world_from_bone sign differs in {flipped}"
    )
    for proc in (a, b):
        rc, err = proc.stop()
        assert rc == 0, err


# ---- in process: replies, events, a close held back, shutdown ------------------------


class InThread:
    """A daemon serving in a thread (ephemeral ports, VMC off)."""

    def __init__(self, calibration: Path, tmp_path: Path) -> None:
        doc = {
            "performer": {
                "rig": "plug-in-gait", "calibration": str(calibration),
                "save_calibration": str(tmp_path / "live-cal.json"),
            },
            "input": {"osc": {"port": 0}, "zmq": {"endpoint": "tcp://127.0.0.1:*"}},
            "output": {"vmc": {"enabled": False},
                       "pose": {"endpoint": "tcp://127.0.0.1:*"}},
            "control": {"endpoint": "tcp://127.0.0.1:*"},
            "show_control": {"port": 0},
            "loop": {"poll_timeout_ms": 20, "process_every_frame": True},
            # back-to-back starts; the limits have their own test below
            "record": {"folder": str(tmp_path), "min_interval_s": 0.0,
                       "min_free_mb": 0.0},
        }  # fmt: skip
        self.lines: list[str] = []
        self.daemon = Daemon(
            DaemonConfig.from_dict(doc, source="test"), self.lines.append
        )
        self.daemon.open()
        self._stop = threading.Event()
        self.thread = threading.Thread(
            target=self.daemon.run, args=(self._stop.is_set,), daemon=True
        )
        self.thread.start()

    def ctl(self, req: dict[str, Any]) -> dict[str, Any]:
        reply = request(self.daemon.endpoints["control"].split()[0], req, 2000)
        assert reply is not None, f"no reply to {req} within 2 s"
        return reply

    def osc_addr(self) -> tuple[str, int]:
        host, port = self.daemon.endpoints["osc markers"].split()[0][6:].rsplit(":", 1)
        return host, int(port)

    def stop(self) -> None:
        self._stop.set()
        self.thread.join(timeout=10.0)
        assert not self.thread.is_alive(), "the loop did not stop"
        self.daemon.close()


@pytest.fixture
def in_thread(pig_calibration: Path, tmp_path: Path) -> Iterator[InThread]:
    live = InThread(pig_calibration, tmp_path)
    try:
        yield live
    finally:
        if live.thread.is_alive():
            live.stop()


def test_record_replies_events_and_a_close_off_the_loop(
    in_thread: InThread, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    live = in_thread
    release = threading.Event()
    closing = threading.Event()
    original_close = recorder_mod.McapSink.close

    def held_close(self: Any) -> None:  # the writer thread's close, held back
        closing.set()
        release.wait(10.0)
        original_close(self)

    monkeypatch.setattr(recorder_mod.McapSink, "close", held_close)

    def refused(req: dict[str, Any], text: str) -> None:
        reply = live.ctl({"cmd": "record", **req})
        assert not reply["ok"] and text in reply["error"], reply

    refused({"action": "stop"}, "not recording")
    refused({"action": "pause"}, "'start' or 'stop'")
    refused({"action": "start"}, "needs a 'path'")
    refused({"action": "start", "path": "../rel.mcap"}, "may not contain '..'")
    refused({"action": "start", "path": "/tmp/x.mcap"}, "recordings go under the")
    refused({"action": "start", "path": str(tmp_path / "x.c3d")}, "end in .mcap")
    refused({"action": "start", "path": str(tmp_path / "no" / "x.mcap")}, "cannot")
    (tmp_path / "exists.mcap").write_bytes(b"keep me")
    refused({"action": "start", "path": str(tmp_path / "exists.mcap")}, "exists")
    assert (tmp_path / "exists.mcap").read_bytes() == b"keep me"
    refused(
        {"action": "start", "path": str(tmp_path / "exists.mcap"), "force": "yes"},
        "true or false",
    )
    path = tmp_path / "events.mcap"
    refused({"action": "start", "path": str(path), "poses": 1}, "true or false")

    reply = live.ctl(
        {"cmd": "record", "action": "start", "path": str(path), "poses": False}
    )
    assert reply["ok"] and reply["message"].endswith("(no poses)"), reply
    refused({"action": "start", "path": str(tmp_path / "b.mcap")}, "already recording")
    status = live.ctl({"cmd": "status"})
    assert status["status"]["record"]["active"] and "| REC " in status["line"]

    sender = Sender(live.osc_addr())
    try:
        sender.send_rows(range(100, 110), period_s=0.0)
        _wait(lambda: live.daemon.stats.frames_out == 10, "10 frames")
        assert live.ctl({"cmd": "reload"})["ok"]
        assert live.ctl({"cmd": "calibrate", "count": 3})["ok"]
        sender.send_rows([110] * 5, period_s=0.0)  # held still: calibrated on
        _wait(lambda: live.daemon.stats.calibrations == 1, "the live calibration")

        stop = live.ctl({"cmd": "record", "action": "stop"})  # answered at once ...
        assert stop["ok"], stop
        assert closing.wait(10.0)  # ... while the writer is still inside close
        rec = live.ctl({"cmd": "status"})["status"]["record"]
        assert not rec["active"] and rec["finishing"] == [str(path)], rec
        before = live.daemon.stats.frames_out
        sender.send_rows(range(115, 120), period_s=0.0)  # the loop goes on solving
        _wait(
            lambda: live.daemon.stats.frames_out == before + 5, "frames while closing"
        )
    finally:
        release.set()
        sender.close()
    _wait(lambda: live.ctl({"cmd": "status"})["status"]["record"]["last"] is not None,
          "the file to be finished")  # fmt: skip
    rec_file = rf.read_recording(path)
    assert rec_file.complete
    assert not rec_file.topic(rf.POSES_TOPIC)  # poses off
    events = [e["event"] for e in rec_file.json(rf.CONTROL_TOPIC)]
    assert events == [
        "record_start", "reload", "calibration_requested", "calibrated", "record_stop",
    ]  # fmt: skip
    n_frames = sum(p.kind == rf.KIND_FRAME for p in rec_file.packets())
    assert n_frames == 15  # rows 100..114; none after the stop

    # Shutdown finishes an active recording.
    second = tmp_path / "shutdown.mcap"
    assert live.ctl({"cmd": "record", "action": "start", "path": str(second)})["ok"]
    live.stop()
    rec_file = rf.read_recording(second)
    assert rec_file.complete
    last = rec_file.json(rf.CONTROL_TOPIC)[-1]
    assert last["event"] == "record_stop" and last["reason"] == "shutdown"


def test_ctl_record_usage(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["ctl", "record"])
    assert exc.value.code == 2
    assert main(["ctl", "record", "start", "take.c3d"]) == 2
    assert "end in .mcap" in capsys.readouterr().err


def test_ctl_record_start_force_replaces_an_existing_file(
    in_thread: Any, tmp_path: Path
) -> None:
    """Issue 16 item 3: ``ctl record start`` refuses an existing file unless
    ``--force`` (``"force": true``), which replaces it with a new recording."""
    live = in_thread
    old = tmp_path / "take.mcap"
    old.write_bytes(b"an old take")
    reply = live.ctl({"cmd": "record", "action": "start", "path": str(old)})
    assert not reply["ok"] and "--force" in reply["error"], reply
    assert old.read_bytes() == b"an old take"
    reply = live.ctl(
        {"cmd": "record", "action": "start", "path": str(old), "force": True}
    )
    assert reply["ok"], reply
    assert live.ctl({"cmd": "record", "action": "stop"})["ok"]
    _wait(lambda: not live.ctl({"cmd": "status"})["status"]["record"]["active"], "stop")
    deadline = time.monotonic() + 10.0
    while old.read_bytes()[:8] == b"an old t" and time.monotonic() < deadline:
        time.sleep(0.05)
    assert old.read_bytes().startswith(b"\x89MCAP"), old.read_bytes()[:16]


def test_recordings_cannot_fill_the_disk(
    start_daemon: Callable[..., Any],
    osc_source: Callable[..., Any],
    streamer: Callable[[Any], Any],
    tmp_path: Path,
) -> None:
    """Issue 30: 3,000 record start/stop cycles in 9.4 s wrote 3,000 files. A start
    within record.min_interval_s of the last is refused and counted rate_limited; the
    folder's recordings at record.max_total_mb refuse a start and stop a running
    recording (its file finished, the reason in status); a disk under
    record.min_free_mb free refuses a start. Each refusal is one line to ctl."""
    folder = tmp_path / "recordings"
    live = start_daemon({"record": {"folder": str(folder), "min_interval_s": 30.0,
                                    "max_total_mb": 1.0}})  # fmt: skip

    def record(action: str, name: str = "") -> dict[str, Any]:
        req = {"cmd": "record", "action": action}
        if name:
            req["path"] = str(folder / name)
        reply: dict[str, Any] = live.ctl(req)
        return reply

    assert record("start", "a.mcap")["ok"]
    assert record("stop")["ok"]
    reply = record("start", "b.mcap")
    assert reply == {
        "ok": False, "error": "rate limited: one record start per 30 s "
        "(record.min_interval_s)",
    }  # fmt: skip
    assert live.ctl({"cmd": "status"})["status"]["counters"]["rate_limited"] == 1
    assert not (folder / "b.mcap").exists()
    # The folder at its limit: 1 MB of an earlier take is there.
    live.daemon.recording.min_interval_ns = 0
    (folder / "old.mcap").write_bytes(b"\0" * 1_100_000)
    reply = record("start", "c.mcap")
    assert not reply["ok"] and "record start refused" in reply["error"]
    assert "record.max_total_mb = 1" in reply["error"], reply
    assert "\n" not in reply["error"]
    # A running recording stops when the folder reaches it: 0.97 MB were there
    # when it began (measured then), and the take grows past the last 0.03 MB.
    (folder / "old.mcap").write_bytes(b"\0" * 970_000)
    feed = streamer(osc_source(live))  # what the take records
    assert record("start", "d.mcap")["ok"]
    _wait_until(
        lambda: not live.ctl({"cmd": "status"})["status"]["record"]["active"],
        "the recording stopped at the limit",
    )
    _wait_until(
        lambda: (live.ctl({"cmd": "status"})["status"]["record"]["last"] or {}).get(
            "path") == str(folder / "d.mcap"),
        "its file finished",
    )  # fmt: skip
    feed.stop()
    last = live.ctl({"cmd": "status"})["status"]["record"]["last"]
    assert last["stopped"].startswith("limit: the recordings folder"), last
    assert last["frames"] > 0 and last["dropped"] == 0, last  # its true counts
    assert any("record.max_total_mb" in ln for ln in live.lines)
    # The free-space floor: more free space asked for than any disk has.
    (folder / "old.mcap").unlink()
    (folder / "d.mcap").unlink()
    live.daemon.recording.min_free_mb = 1e12
    reply = record("start", "e.mcap")
    assert not reply["ok"] and "record.min_free_mb" in reply["error"], reply
