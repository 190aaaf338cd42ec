"""Nothing the loop does between two frames holds the frame path up (issue 30 item 6:
the soak's ``loop_late`` pose gaps).

Measured in the soak (``loop_stalls``, ``live/stalls.py``): after a reload every
stream's pipeline was rebuilt on its next frame, in the loop: the fit's body solver
alone took 85-330 ms there, and the frames behind it waited. Now the body solver is
built on a worker thread (``live/rebuild.py``) while the old pipeline goes on solving,
and a reload of unchanged files parses and rebuilds nothing.

The daemon is driven here one wake-up at a time (``poll`` then ``_service``, as
``Daemon.run`` does) on real loopback sockets. The worker's build is held on a gate,
so what is asserted is the order of events (frames solved while the build ran, the
new pipeline taken by the first frame after it), never a duration.
"""

from __future__ import annotations

import gc
import json
import os
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import live_harness as lh
import numpy as np
import pytest
import zmq

from retargetd.daemon.face.training import TrainingSet
from retargetd.daemon.live import face as face_module
from retargetd.daemon.live import performers as performers_module
from retargetd.daemon.live import rebuild
from retargetd.daemon.live import validation as validation_module
from retargetd.daemon.live.config import DaemonConfig
from retargetd.daemon.live.loop import Daemon
from retargetd.daemon.live.ratelog import RateLimitedLog
from retargetd.daemon.live.stalls import STALL_NS, LoopStalls, is_waiting
from retargetd.protocols import osc_in, pose_stream
from retargetd.protocols.marker_input import LabelSet
from retargetd.replay import recording as rf


@pytest.fixture
def rig_copy(tmp_path: Path) -> Path:
    """The exact rig in a file of the test's own (a test edits it)."""
    path = tmp_path / "rig.toml"
    path.write_text(lh.EXACT_RIG.read_text())
    return path


@pytest.fixture
def daemon(exact_calibration: Path, rig_copy: Path, tmp_path: Path) -> Iterator[Daemon]:
    doc = lh._deep_merge(
        lh._ephemeral_doc(lh._unused_udp_port()),
        {
            "performer": {"rig": str(rig_copy), "calibration": str(exact_calibration)},
            "control": {"min_interval_s": 0.01},  # reloads 20 ms apart (_ctl)
            "record": {"folder": str(tmp_path)},
        },
    )
    d = Daemon(DaemonConfig.from_dict(doc, source="test"), out=lambda _line: None)
    try:
        d.open()
        yield d
    finally:
        d.close()


class _Source:
    """The exact take's frames, one datagram per call, to the daemon's OSC port:
    under its own labels, or another label set's (:meth:`announce`: its columns
    are the take's, moved and padded as its labels say)."""

    def __init__(self, d: Daemon) -> None:
        host, port = d.endpoints["osc markers"].split()[0][6:].rsplit(":", 1)
        self.addr = (host, int(port))
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.take = lh._take()
        self.i = 0
        self.announce(LabelSet(1, self.take.labels))

    def announce(self, label_set: LabelSet) -> None:
        self.label_set = label_set
        col = {name: k for k, name in enumerate(self.take.labels)}
        self.cols = [col.get(name, -1) for name in label_set.labels]
        self.sock.sendto(osc_in.encode_labels(label_set), self.addr)

    def send(self) -> None:
        take_row = np.asarray(self.take.markers_world[self.i % self.take.n_frames])
        row = np.full((len(self.cols), 3), np.nan)
        for k, c in enumerate(self.cols):
            if c >= 0:
                row[k] = take_row[c]
        self.sock.sendto(
            osc_in.encode_compact_frame(self.i, self.i / 100, self.label_set.id, row),
            self.addr,
        )
        self.i += 1


def _wake(d: Daemon) -> None:
    deadline = time.monotonic() + 2.0
    while True:
        events = d._poller.poll(50)
        if events:
            d._stalls.mark()  # as Daemon.run after each poll (its "poll" lap)
            d._service(events)
            return
        assert time.monotonic() < deadline, "no input event within 2 s"


def _frames(d: Daemon, src: _Source, n: int) -> None:
    """``n`` frames, each read and solved before the next is sent."""
    for _ in range(n):
        before = d.stats.frames_in
        src.send()
        while d.stats.frames_in == before:  # (the announcement may wake it first)
            _wake(d)


def _first_pipeline(d: Daemon, src: _Source) -> None:
    """One frame (its label set taken: the build started; solved if the build was
    quicker), every build under way waited for, and one more frame, by which the
    built pipeline is in."""
    _frames(d, src, 1)
    assert d.performers.done_building(60.0), "the pipeline was never built"
    _frames(d, src, 1)
    assert d.stats.pipeline_builds == 1 and d.performers.first.path.pipelines


def _ctl(d: Daemon, req: dict[str, Any]) -> dict[str, Any]:
    time.sleep(0.02)  # past control.min_interval_s since the last reload
    reply = d.control_reply([json.dumps(req).encode()])
    assert reply["ok"], reply
    return reply


def _accounted(d: Daemon) -> bool:
    s = d.stats
    return s.frames_in == s.frames_solved + s.stale + s.unsolved


@pytest.fixture
def gated_builds(monkeypatch: pytest.MonkeyPatch) -> tuple[threading.Event, list[int]]:
    """The worker's body-solver builds wait for the returned gate; the list counts
    the builds begun."""
    gate, begun = threading.Event(), []
    real = rebuild.body_solver

    def gated(*args: Any) -> Any:
        begun.append(1)
        assert gate.wait(30.0), "the test never opened the gate"
        return real(*args)

    monkeypatch.setattr(rebuild, "body_solver", gated)
    return gate, begun


@pytest.mark.timeout(120)
def test_a_reload_rebuilds_the_solver_off_the_loop_while_the_old_one_solves(
    daemon: Daemon,
    gated_builds: tuple[threading.Event, list[int]],
    tmp_path: Path,
) -> None:
    d, (gate, begun) = daemon, gated_builds
    src = _Source(d)
    try:
        gate.set()  # the stream's first pipeline, built off the loop too
        _first_pipeline(d, src)
        gate.clear()
        _ctl(d, {"cmd": "record", "action": "start", "path": "r.mcap"})
        _frames(d, src, 5)
        assert d.stats.pipeline_builds == 1
        (key, old), = d.performers.first.path.pipelines.items()  # fmt: skip
        out = d.stats.frames_out
        assert "reloaded rig" in _ctl(d, {"cmd": "reload"})["message"]
        _frames(d, src, 20)
        # The build runs (on the worker, held at the gate) while every frame is
        # solved and sent by the old pipeline: before, the reload dropped the
        # pipelines and the next frame rebuilt one in the loop.
        assert begun == [1, 1]
        assert (
            d.performers.first.path.pipelines[key] is old
            and d.stats.pipeline_builds == 1
        )
        assert d.stats.frames_out == out + 20 and _accounted(d)
        assert old.built_for[1] is not d.calibration  # the reload's is new
        gate.set()
        deadline = time.monotonic() + 30.0
        while d.stats.pipeline_builds == 1:
            assert time.monotonic() < deadline, "the rebuilt solver never swapped in"
            time.sleep(0.01)
            _frames(d, src, 1)
        swap_rx = d.osc_stream.current.frame.t_ns  # the frame that took it
        new = d.performers.first.path.pipelines[key]
        assert new is not old and new.built_for == (d.rig, d.calibration, None)
        assert not d.performers.first.path.builds and begun == [1, 1]
        assert _accounted(d)
        _frames(d, src, 3)
        assert d.performers.first.path.pipelines[key] is new  # swapped once, kept
        _ctl(d, {"cmd": "record", "action": "stop"})
        deadline = time.monotonic() + 30.0
        while d.recording.status()["finishing"]:
            assert time.monotonic() < deadline
            time.sleep(0.02)
    finally:
        gate.set()
        src.sock.close()
    # A replay resets its solver at the frame that took the new pipeline.
    events = rf.read_recording(tmp_path / "r.mcap").json(rf.CONTROL_TOPIC)
    kinds = [e["event"] for e in events]
    assert kinds == ["record_start", "reload", "pipeline", "record_stop"], kinds
    assert events[2]["received_ns"] == swap_rx > events[1]["t_ns"]


@pytest.mark.timeout(120)
def test_a_reload_of_unchanged_files_parses_and_rebuilds_nothing(
    daemon: Daemon,
    gated_builds: tuple[threading.Event, list[int]],
    rig_copy: Path,
) -> None:
    d, (gate, begun) = daemon, gated_builds
    gate.set()
    src = _Source(d)
    try:
        _first_pipeline(d, src)
        _frames(d, src, 3)
        gate.clear()  # the reloads' builds held: their order, not their speed
        path = d.performers.first.path
        _ctl(d, {"cmd": "reload"})  # the first reload reads the files
        rig, cal = d.rig, d.calibration
        # Its rebuild starts with the reload, not with the stream's next frame.
        (job,) = path.builds.values()
        assert job.want[0] is rig and job.want[1] is cal
        assert d.performers.building() == 1
        msg = _ctl(d, {"cmd": "reload"})["message"]
        assert "unchanged" in msg and d.rig is rig and d.calibration is cal, msg
        assert list(path.builds.values()) == [job]  # unchanged: nothing started
        # An edited rig file is read again (a comment changes its bytes).
        rig_copy.write_text(rig_copy.read_text() + "\n# edited\n")
        msg = _ctl(d, {"cmd": "reload"})["message"]
        assert "unchanged" not in msg and d.rig is not rig, msg
        _frames(d, src, 1)
        # The newest rig's build waits for the one under way (one build per
        # stream at a time), the old pipeline solving meanwhile.
        assert list(path.builds.values()) == [job] and d.stats.pipeline_builds == 1
        lh._wait_until(lambda: len(begun) == 2, "the first reload's build begun")
        gate.set()
        deadline = time.monotonic() + 30.0
        while not d.performers.ready(d.osc_stream):
            assert time.monotonic() < deadline, "the newest rig's build never began"
            _frames(d, src, 1)  # loop passes: the waiting build starts on one
            d.performers.done_building(30.0)
        _frames(d, src, 3)
        # 3 begun: the first pipeline's; the first reload's (its files parsed
        # anew: a rig and calibration of their own, built for at once, its result
        # never used); the edited rig's, once. The unchanged reload's: none.
        assert len(begun) == 3 and d.stats.pipeline_builds == 2
        (pipe,) = path.pipelines.values()
        assert pipe.built_for[0] is d.rig
    finally:
        gate.set()
        src.sock.close()


@pytest.mark.timeout(120)
def test_a_reload_builds_the_new_pipeline_without_waiting_for_a_frame(
    daemon: Daemon, gated_builds: tuple[threading.Event, list[int]]
) -> None:
    """A source that sends its next frame only once its pipeline is ready (as the
    tests' streamer does after each announcement) is not left waiting by a reload:
    the new rig and calibration's pipeline is built with no frame after it."""
    d, (gate, begun) = daemon, gated_builds
    gate.set()
    src = _Source(d)
    try:
        _first_pipeline(d, src)
        assert d.performers.ready(d.osc_stream)
        gate.clear()  # (held: the state between the reload and its build's end)
        _ctl(d, {"cmd": "reload"})  # (control_reply swaps the new files in)
        assert not d.performers.ready(d.osc_stream)  # built for the old ones
        # Its build begun, no frame sent since.
        (job,) = d.performers.first.path.builds.values()
        assert job.want[0] is d.rig and job.want[1] is d.calibration
        gate.set()
        assert d.performers.done_building(60.0)
        assert d.performers.ready(d.osc_stream) and len(begun) == 2
        _frames(d, src, 1)  # the first frame after it takes the new pipeline
        (pipe,) = d.performers.first.path.pipelines.values()
        assert pipe.built_for[:2] == (d.rig, d.calibration)
        assert d.stats.pipeline_builds == 2 and len(begun) == 2
    finally:
        gate.set()
        src.sock.close()


@pytest.mark.timeout(60)
def test_a_slow_phase_is_counted_by_name_in_status(
    daemon: Daemon, monkeypatch: pytest.MonkeyPatch
) -> None:
    d = daemon
    real = d.control._control

    def slow(req: dict[str, Any], perf: Any) -> dict[str, Any]:
        time.sleep(2 * STALL_NS * 1e-9)  # never returns early
        return real(req, perf)

    monkeypatch.setattr(d.control, "_control", slow)
    req = zmq.Context.instance().socket(zmq.REQ)
    req.setsockopt(zmq.LINGER, 0)
    req.connect(d.endpoints["control"].split()[0])
    try:
        req.send(json.dumps({"cmd": "status"}).encode())
        while d.stats.control_requests == 0:  # (a monitor's event may come first)
            _wake(d)
        assert req.poll(5000), "no reply"
        assert json.loads(req.recv())["ok"]
    finally:
        req.close()
    stalls = d.status()["loop_stalls"]
    assert stalls["by_phase"] == {"control.status": 1}, stalls
    assert stalls["count"] == 1 and stalls["longest_phase"] == "control.status"
    assert stalls["waiting"] == 1  # (it slept)
    assert stalls["longest_ms"] >= 2 * STALL_NS / 1e6


def test_stalls_count_phases_over_the_bound_and_collector_passes() -> None:
    lines: list[str] = []
    stalls = LoopStalls(RateLimitedLog(lines.append, 10.0))
    stalls.mark()
    time.sleep(1.2 * STALL_NS * 1e-9)
    stalls.lap("poll", allowed_ns=10**9)  # within its timeout: not a stall
    assert stalls.count == 0
    time.sleep(1.2 * STALL_NS * 1e-9)
    stalls.lap("markers")
    assert stalls.by_phase == {"markers": 1} and stalls.longest_phase == "markers"
    # asleep, not on a CPU: waiting (for a core or the GIL), not the loop's work
    # (asleep is not runnable: with schedstat, blocked, not the host's)
    why = "blocked: the GIL" if _schedstat() else "waiting for a CPU or the GIL"
    assert stalls.waiting == 1 and why in lines[0], lines
    assert lines[0].startswith("loop: markers held the frame path for"), lines
    assert is_waiting(10, 100) and not is_waiting(60, 100)
    # A collector pass, from start to stop, timed as its own phase.
    stalls._gc_callback("start", {"generation": 2})
    time.sleep(1.2 * STALL_NS * 1e-9)
    stalls._gc_callback("stop", {"generation": 2})
    assert stalls.status()["by_phase"] == {"markers": 1, "gc2": 1}
    stalls.watch_gc()
    try:
        assert stalls._gc_callback in gc.callbacks
    finally:
        stalls.close()
    assert stalls._gc_callback not in gc.callbacks


def _sent_flags(d: Daemon) -> int:
    """The frame flags of the pose the first pipeline sent last (its encoder's
    header, reused per frame)."""
    pipe = next(iter(d.performers.first.path.pipelines.values()))
    header = pipe.pose_enc.parts[0]
    (flags,) = struct.unpack_from("<I", header, struct.calcsize("<4sHHqdqqq"))
    return int(flags)


@pytest.mark.timeout(120)
def test_a_streams_first_pipeline_is_built_off_the_loop_its_frames_unsolved(
    daemon: Daemon, gated_builds: tuple[threading.Event, list[int]]
) -> None:
    """Before: the first frame of a stream built its pipeline in the loop (100-470
    ms: every frame behind it waited). Now the build starts when the label set is
    taken, on the worker; the frames meanwhile are counted unsolved (no pose: none
    solved yet), the loop goes on; the first pose after them is flagged."""
    d, (gate, begun) = daemon, gated_builds
    src = _Source(d)
    try:
        _frames(d, src, 12)  # the build held at the gate all along
        assert begun == [1] and d.status()["pipelines_building"] == 1
        assert not d.performers.first.path.pipelines
        c = d.stats
        assert c.unsolved == c.unsolved_building == 12 and c.frames_out == 0
        assert _accounted(d)
        gate.set()
        assert d.performers.done_building(60.0)
        assert d.status()["pipelines_building"] == 0
        _frames(d, src, 1)  # takes the built pipeline: solved and sent
        assert c.pipeline_builds == 1 and c.frames_out == 1 and _accounted(d)
        assert _sent_flags(d) & pose_stream.FRAME_INPUT_DROPPED  # 12 not posed
        _frames(d, src, 1)
        assert c.frames_out == 2 and c.unsolved == 12
        assert not _sent_flags(d) & pose_stream.FRAME_INPUT_DROPPED
    finally:
        gate.set()
        src.sock.close()


@pytest.mark.timeout(120)
def test_a_new_label_set_is_solved_by_the_old_pipeline_only_if_it_keeps_its_markers(
    daemon: Daemon, gated_builds: tuple[threading.Event, list[int]]
) -> None:
    """A new label set's pipeline is built off the loop too. Meanwhile a set that
    keeps, in every column the old pipeline reads, the same marker (here one marker
    added at the end) is solved by the old pipeline; one that moves them (the labels
    rotated by one) is not solved at all until its own is built: no pose from the
    wrong markers."""
    d, (gate, begun) = daemon, gated_builds
    src = _Source(d)
    path = d.performers.first.path
    labels = src.take.labels
    try:
        gate.set()
        _first_pipeline(d, src)
        gate.clear()
        (key, old), = path.pipelines.items()  # fmt: skip
        c = d.stats
        # One marker more, at the end: the old columns keep their markers.
        src.announce(LabelSet(2, (*labels, "EXTRA")))
        out, unsolved = c.frames_out, c.unsolved_building  # (the first frame's)
        _frames(d, src, 10)
        assert len(begun) == 2 and path.pipelines[key] is old  # still building
        assert c.frames_out == out + 10 and c.unsolved_building == unsolved
        gate.set()
        assert d.performers.done_building(60.0)
        _frames(d, src, 1)
        new = path.pipelines[key]
        assert new is not old and path.labels_of[key] == (*labels, "EXTRA")
        assert c.frames_out == out + 11 and _accounted(d)
        # The labels rotated by one: every column now holds another marker.
        gate.clear()
        src.announce(LabelSet(3, labels[1:] + labels[:1]))
        out = c.frames_out
        _frames(d, src, 10)
        assert len(begun) == 3 and path.pipelines[key] is new  # not used
        assert c.frames_out == out and c.unsolved_building == unsolved + 10
        assert _accounted(d)
        gate.set()
        assert d.performers.done_building(60.0)
        _frames(d, src, 1)
        assert path.labels_of[key] == labels[1:] + labels[:1]
        assert c.frames_out == out + 1 and _accounted(d)
        assert _sent_flags(d) & pose_stream.FRAME_INPUT_DROPPED
    finally:
        gate.set()
        src.sock.close()


@pytest.fixture
def gated_reads(monkeypatch: pytest.MonkeyPatch) -> threading.Event:
    """A reload's file reading (on the worker) waits for the returned gate."""
    gate = threading.Event()
    real = performers_module.read_files

    def gated(*args: Any) -> Any:
        assert gate.wait(30.0), "the test never opened the gate"
        return real(*args)

    monkeypatch.setattr(performers_module, "read_files", gated)
    return gate


@pytest.mark.timeout(120)
def test_ctl_reload_reads_its_files_off_the_loop_and_answers_after(
    daemon: Daemon,
    gated_builds: tuple[threading.Event, list[int]],
    gated_reads: threading.Event,
    rig_copy: Path,
) -> None:
    """Before: a reload parsed the rig, calibration and config in the loop (23-70
    ms). Now a worker reads them: the frames go on being solved while it does, the
    ``ctl reload`` reply comes once they are read, and only then is the new rig
    swapped in; a file that does not validate is answered with its reason and the
    running rig kept."""
    d, (gate, _begun), read_gate = daemon, gated_builds, gated_reads
    gate.set()
    src = _Source(d)
    req = zmq.Context.instance().socket(zmq.REQ)
    req.setsockopt(zmq.LINGER, 0)
    req.connect(d.endpoints["control"].split()[0])
    try:
        _first_pipeline(d, src)
        rig = d.rig
        rig_copy.write_text(rig_copy.read_text() + "\n# edited\n")
        asked = d.stats.control_requests
        req.send(json.dumps({"cmd": "reload"}).encode())
        while d.stats.control_requests == asked:
            _wake(d)
        out = d.stats.frames_out
        _frames(d, src, 10)  # the files being read: the loop goes on solving
        assert d.stats.frames_out == out + 10
        assert not req.poll(0), "answered before its files were read"
        assert d.rig is rig  # nothing swapped in yet
        read_gate.set()
        while not req.poll(0):  # the loop's tick swaps it in and answers
            _frames(d, src, 1)
            d.control.tick()  # (as Daemon.run, every pass)
        reply = json.loads(req.recv())
        assert reply["ok"] and reply["message"].startswith("reloaded rig"), reply
        assert d.rig is not rig
        # A rig file that no longer parses: its reason, the running rig kept.
        rig = d.rig
        rig_copy.write_text("[markers\n")
        time.sleep(0.02)  # past control.min_interval_s since the last reload
        req.send(json.dumps({"cmd": "reload"}).encode())
        while not req.poll(0):
            _frames(d, src, 1)
            d.control.tick()
        reply = json.loads(req.recv())
        assert not reply["ok"] and reply["message"].startswith("reload failed, kept")
        assert d.rig is rig, reply
    finally:
        gate.set()
        read_gate.set()
        req.close()
        src.sock.close()


@pytest.mark.timeout(120)
def test_one_build_at_a_time_per_stream_however_fast_label_sets_come(
    daemon: Daemon, gated_builds: tuple[threading.Event, list[int]]
) -> None:
    """Label sets announced faster than a pipeline builds (a sender cycling ids, or
    a hostile one) start one build per stream at a time, never a thread each: the
    one wanted last is built when the running one ends, and taken."""
    d, (gate, begun) = daemon, gated_builds
    src = _Source(d)
    path = d.performers.first.path
    labels = src.take.labels
    try:
        gate.set()
        _first_pipeline(d, src)
        gate.clear()
        (key,) = path.pipelines
        for k in range(1, 6):  # five label sets, each moving every marker
            src.announce(LabelSet(1 + k, labels[k:] + labels[:k]))
            _frames(d, src, 2)
        assert len(begun) == 2  # the first pipeline's, and one held at the gate
        assert d.status()["pipelines_building"] == 1
        gate.set()
        assert d.performers.done_building(60.0)  # the held one (no longer wanted)
        _frames(d, src, 1)  # starts the build for the labels in use
        assert d.performers.done_building(60.0)
        _frames(d, src, 1)
        assert len(begun) == 3 and path.labels_of[key] == labels[5:] + labels[:5]
        assert _accounted(d)
    finally:
        gate.set()
        src.sock.close()


@pytest.fixture
def daemon_lines(
    exact_calibration: Path, rig_copy: Path, tmp_path: Path
) -> Iterator[tuple[Daemon, list[str]]]:
    """The exact performer with the live validator and the face on (no training
    set: nothing to solve, a set to write), and the lines it prints."""
    doc = lh._deep_merge(
        lh._ephemeral_doc(lh._unused_udp_port()),
        {
            "performer": {"rig": str(rig_copy), "calibration": str(exact_calibration)},
            "control": {"min_interval_s": 0.01},
            "validate": {"enabled": True, "rate_hz": 100.0},
            "face": {"enabled": True, "config": "arkit52",
                     "training": str(tmp_path / "face.npz")},
        },
    )  # fmt: skip
    lines: list[str] = []
    d = Daemon(DaemonConfig.from_dict(doc, source="test"), out=lines.append)
    try:
        d.open()
        yield d, lines
    finally:
        d.close()


def _ticks(d: Daemon) -> None:
    """The loop pass's ticks after the wake-up (as ``Daemon.run``): a validator
    built or a training set written off the loop taken."""
    d.performers.tick_calibrations(time.monotonic_ns())


@pytest.mark.timeout(120)
def test_a_validators_restart_is_built_off_the_loop_and_a_failure_counted(
    daemon_lines: tuple[Daemon, list[str]],
    rig_copy: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Before: a reload or a live calibration built the new live validator in the
    loop (its MuJoCo model, tables and kernels: 3-32 ms, 300-380 ms where the
    process had not loaded its kernels). Now a worker builds it while the old one
    goes on checking the poses, every frame solved and sent; the loop swaps it in
    once built. A build that
    raises is counted and said in one line, the validator off, the loop serving."""
    (d, lines), gate = daemon_lines, threading.Event()
    real = validation_module.new_validator
    begun: list[int] = []

    def gated(*args: Any) -> Any:
        begun.append(1)
        assert gate.wait(30.0), "the test never opened the gate"
        return real(*args)

    monkeypatch.setattr(validation_module, "new_validator", gated)
    src = _Source(d)
    try:
        old = d.validator  # built at the start, waited for there
        assert old is not None and old.running
        _first_pipeline(d, src)
        _frames(d, src, 3)
        rig_copy.write_text(rig_copy.read_text() + "\n# edited\n")
        assert "reloaded rig" in _ctl(d, {"cmd": "reload"})["message"]
        submitted, out = old.submitted, d.stats.frames_out
        for _ in range(20):
            _frames(d, src, 1)
            _ticks(d)
        assert begun == [1] and d.status()["validators_building"] == 1
        assert d.stats.frames_out == out + 20 and _accounted(d)
        assert d.validator is old and old.submitted == submitted + 20  # still checking
        gate.set()
        deadline = time.monotonic() + 30.0
        while d.validator is old:
            assert time.monotonic() < deadline, "the new validator never swapped in"
            time.sleep(0.01)
            _ticks(d)
        new = d.validator
        assert (
            new is not None and new.running and d.status()["validators_building"] == 0
        )
        _frames(d, src, 3)
        assert new.submitted == 3
        _wait(lambda: not old.running, "the old validator closed (off the loop)")
        assert sum("live validator on" in line for line in lines) == 2, lines

        # A build that raises: counted, one line, the validator off; frames go on.
        def broken(*args: Any) -> Any:
            raise ValueError("a calibration without rest bone origins\nmore")

        monkeypatch.setattr(validation_module, "new_validator", broken)
        rig_copy.write_text(rig_copy.read_text() + "\n# edited again\n")
        _ctl(d, {"cmd": "reload"})
        out = d.stats.frames_out
        deadline = time.monotonic() + 30.0
        while d.validator is new:
            assert time.monotonic() < deadline, "the failed build never ended"
            _frames(d, src, 1)
            _ticks(d)
        assert d.validator is None and d.status()["validate"] is None
        assert d.status()["counters"]["validator_failures"] == 1
        off = [line for line in lines if "live validator off" in line]
        assert off == [
            "live validator off: its build failed (ValueError: a calibration "
            "without rest bone origins); validator_failures 1"
        ], lines
        _frames(d, src, 5)
        assert d.stats.frames_out > out + 4 and _accounted(d)
    finally:
        gate.set()
        src.sock.close()


def _wait(cond: Any, what: str, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, what
        time.sleep(0.01)


@pytest.mark.timeout(120)
def test_a_face_training_sets_save_runs_off_the_loop_and_a_failure_is_counted(
    daemon_lines: tuple[Daemon, list[str]],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Before: a face capture wrote its training set in the loop (np.savez; a slow
    or full disk held every frame for as long as it took). Now a worker writes it,
    atomically: here a writer held at a gate (a disk that does not answer) while
    the loop solves and sends every frame; ``face.saving`` says it is in flight.
    A write that fails is counted, said in one line, the old file kept whole."""
    (d, lines), gate = daemon_lines, threading.Event()
    real = TrainingSet.save

    def slow(self: TrainingSet, path: str | Path) -> None:
        assert gate.wait(30.0), "the test never opened the gate"
        if Path(path).parent.name == "full":
            raise OSError(28, f"cannot write {path}: No space left on device")
        real(self, path)

    monkeypatch.setattr(TrainingSet, "save", slow)
    face = d.face
    assert face is not None and not d.status()["face"]["saving"]
    training = _tiny_training()
    path = str(tmp_path / "face.npz")
    src = _Source(d)
    try:
        _first_pipeline(d, src)
        face._save_later(training, path, "face pose 'neutral' captured")
        face.last_message = f"face pose 'neutral' captured; saving {path}"
        out = d.stats.frames_out
        for _ in range(20):
            _frames(d, src, 1)
            _ticks(d)
        assert d.stats.frames_out == out + 20 and _accounted(d)
        assert d.status()["face"]["saving"] and not Path(path).exists()
        gate.set()
        _wait(lambda: face._save is not None and face._save.done(), "written")
        _ticks(d)
        assert not d.status()["face"]["saving"]
        assert TrainingSet.load(path).marker_names == training.marker_names
        assert d.status()["face"]["last_capture"].endswith(f"; saved {path}")
        assert lines[-1] == f"face training set (1 expressions) saved {path}"
        # A disk that is full: counted, one line, the file that was there kept.
        (tmp_path / "full").mkdir()
        bad = str(tmp_path / "full" / "face.npz")
        face._save_later(training, bad, "face pose 'jawOpen' captured")
        _wait(lambda: face._save is not None and face._save.done(), "refused")
        _ticks(d)
        assert d.status()["counters"]["face_save_failures"] == 1
        assert lines[-1].startswith("face training set (1 expressions) NOT saved: ")
        assert "No space left on device" in lines[-1]
        _frames(d, src, 3)
        assert _accounted(d)
        # The daemon's close waits for the write under way, and writes the one
        # waiting: the last capture is not lost.
        gate.clear()
        later = str(tmp_path / "later.npz")
        face._save_later(training, str(tmp_path / "first.npz"), "a")
        face._save_later(training, later, "b")  # waits for the first
        closing = threading.Thread(target=face.close)
        closing.start()
        closing.join(0.2)
        assert closing.is_alive() and not Path(later).exists()
        gate.set()
        closing.join(30.0)
        assert not closing.is_alive() and not face.saving
        assert TrainingSet.load(later).k == 1
    finally:
        gate.set()
        src.sock.close()


@pytest.mark.timeout(120)
def test_a_face_captures_averaging_runs_off_the_loop(
    daemon_lines: tuple[Daemon, list[str]], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Before: the frame that completed a face capture averaged its frames in the
    loop (``capture_into``: a rigid fit per frame, twice for the first neutral; 7.9
    ms for the default 60 frames, 31 ms for 240, measured: past a frame at 240 Hz).
    Now a worker averages them, held here at a gate, while the loop solves and sends
    every frame; ``face.averaging`` says so and a new capture is refused meanwhile;
    the loop pass that finds it done takes the new training set."""
    (d, lines), gate = daemon_lines, threading.Event()
    real = face_module.capture_into

    def held(*args: Any) -> Any:
        assert gate.wait(30.0), "the test never opened the gate"
        return real(*args)

    monkeypatch.setattr(face_module, "capture_into", held)
    face = d.face
    assert face is not None and face.training is None
    head = face.face.head_markers
    labels = (*head, "FLIPU", "FLIPL")
    rng = np.random.default_rng(3)
    pose = np.array(
        [[0.05, 0.1, 1.70], [-0.05, 0.1, 1.70], [0.05, -0.05, 1.72],
         [-0.05, -0.05, 1.72], [0.0, 0.12, 1.62], [0.0, 0.12, 1.60]]
    )  # fmt: skip
    src = _Source(d)
    try:
        _first_pipeline(d, src)
        face.request_capture("neutral", 3)
        for _ in range(3):
            assert face.collect(pose + rng.normal(0, 1e-4, pose.shape), labels) is None
        assert face.averaging and not face.capturing
        assert d.status()["face"]["averaging"]
        with pytest.raises(ValueError, match="still being averaged"):
            face.request_capture("neutral", 3)
        out = d.stats.frames_out
        for _ in range(20):
            _frames(d, src, 1)
            _ticks(d)
        assert d.stats.frames_out == out + 20 and _accounted(d)
        assert face.averaging and face.training is None
        gate.set()
        _wait(lambda: face._averaging is None or face._averaging.done(), "averaged")
        _ticks(d)
        assert not face.averaging and not d.status()["face"]["averaging"]
        assert face.training is not None and face.training.marker_names == (
            "FLIPU", "FLIPL",
        )  # fmt: skip
        assert d.stats.face_captures == 1
        assert any(
            line.startswith("face pose 'neutral' captured on 3 frames")
            for line in lines
        ), lines
        _frames(d, src, 3)
        assert _accounted(d)
    finally:
        gate.set()
        src.sock.close()


def _tiny_training() -> TrainingSet:
    """A training set of 3 head markers, 2 facial markers and one expression."""
    layout = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0]])
    return TrainingSet(
        head_names=("H1", "H2", "H3"), marker_names=("F1", "F2"),
        expression_names=("e",), head_layout=layout,
        neutral=np.array([[0.0, 0.05, -0.05], [0.05, 0.0, -0.05]]),
        deltas=np.array([[[0.0, 0.0, 0.01], [0.0, 0.01, 0.0]]]),
    )  # fmt: skip


def _schedstat() -> bool:
    return Path(f"/proc/self/task/{threading.get_native_id()}/schedstat").exists()


def test_a_stall_blocked_while_another_thread_ran_names_that_thread() -> None:
    """Off a CPU and not runnable (asleep, as when waiting for the GIL): ``blocked``,
    the daemon's, and the thread that ran meanwhile is named."""
    if not _schedstat():
        pytest.skip("no schedstat (a kernel without CONFIG_SCHED_INFO)")
    lines: list[str] = []
    stalls = LoopStalls(RateLimitedLog(lines.append, 10.0))
    go, stop = threading.Event(), threading.Event()

    def spin() -> None:
        go.wait()
        while not stop.is_set():
            pass

    spinner = threading.Thread(target=spin, name="spinner", daemon=True)
    spinner.start()
    try:
        stalls.mark()  # (the threads' times read)
        go.set()
        time.sleep(2 * STALL_NS * 1e-9)
        stalls.lap("markers")
    finally:
        stop.set()
        spinner.join()
    status = stalls.status()
    assert status["waiting"] == 1 and status["blocked"] == 1, status
    assert status["unscheduled"] == 0, status
    (entry,) = status["recent"]
    assert entry["why"] == "blocked" and entry["phase"] == "markers", entry
    assert entry["busiest"][0] == "spinner" and entry["others_cpu_ms"] > 0, entry
    assert "blocked: the GIL held by another thread" in lines[0], lines
    assert "most spinner" in lines[0], lines


def test_a_stall_runnable_without_a_cpu_is_the_hosts() -> None:
    """The loop's thread busy on one core with three busy processes on that core:
    runnable without a CPU most of the phase, ``unscheduled`` (the host's)."""
    if not _schedstat() or not hasattr(os, "sched_setaffinity"):
        pytest.skip("no schedstat or CPU affinity")
    lines: list[str] = []
    stalls = LoopStalls(RateLimitedLog(lines.append, 10.0))
    before = os.sched_getaffinity(0)
    cpu = min(before)
    busy = [
        subprocess.Popen(
            [sys.executable, "-c", "while True: pass"],
            preexec_fn=lambda: os.sched_setaffinity(0, {cpu}),
        )
        for _ in range(3)
    ]
    try:
        os.sched_setaffinity(0, {cpu})  # this thread only (Linux)
        time.sleep(0.2)  # the three running
        stalls.mark()
        end = time.monotonic() + 4 * STALL_NS * 1e-9
        while time.monotonic() < end:
            pass
        stalls.lap("markers")
    finally:
        os.sched_setaffinity(0, before)
        for p in busy:
            p.kill()
            p.wait()
    status = stalls.status()
    assert status["unscheduled"] == 1 and status["blocked"] == 0, status
    (entry,) = status["recent"]
    assert entry["why"] == "unscheduled", entry
    assert 2 * entry["runqueue_ms"] >= entry["ms"], entry
    assert "the host did not schedule it" in lines[0], lines
