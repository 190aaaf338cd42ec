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
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import live_harness as lh
import numpy as np
import pytest
import zmq

from retargetd.daemon.live import rebuild
from retargetd.daemon.live.config import DaemonConfig
from retargetd.daemon.live.loop import Daemon
from retargetd.daemon.live.ratelog import RateLimitedLog
from retargetd.daemon.live.stalls import STALL_NS, LoopStalls, is_waiting
from retargetd.protocols import osc_in
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
    """The exact take's frames, one datagram per call, to the daemon's OSC port."""

    def __init__(self, d: Daemon) -> None:
        host, port = d.endpoints["osc markers"].split()[0][6:].rsplit(":", 1)
        self.addr = (host, int(port))
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.take = lh._take()
        self.i = 0
        self.sock.sendto(osc_in.encode_labels(LabelSet(1, self.take.labels)), self.addr)

    def send(self) -> None:
        row = self.take.markers_world[self.i % self.take.n_frames]
        self.sock.sendto(
            osc_in.encode_compact_frame(self.i, self.i / 100, 1, np.asarray(row)),
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
    """One frame (its label set taken: the build started), every build under way
    waited for, and one more frame, which swaps the built pipeline in."""
    _frames(d, src, 1)
    assert d.performers.done_building(60.0), "the pipeline was never built"
    builds = d.stats.pipeline_builds
    _frames(d, src, 1)
    assert d.stats.pipeline_builds == builds + 1


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
        _ctl(d, {"cmd": "reload"})  # the first reload reads the files
        rig, cal = d.rig, d.calibration
        msg = _ctl(d, {"cmd": "reload"})["message"]
        assert "unchanged" in msg and d.rig is rig and d.calibration is cal, msg
        # An edited rig file is read again (a comment changes its bytes).
        rig_copy.write_text(rig_copy.read_text() + "\n# edited\n")
        msg = _ctl(d, {"cmd": "reload"})["message"]
        assert "unchanged" not in msg and d.rig is not rig, msg
        _frames(d, src, 1)
        # the first pipeline's build, and the rebuild for the newest rig only
        assert len(begun) == 2
    finally:
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
    assert stalls.waiting == 1 and "waiting for a CPU or the GIL" in lines[0]
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
