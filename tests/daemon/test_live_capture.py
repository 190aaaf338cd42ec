"""The daemon straight from a capture system: Motive (NatNet) and QTM (qtm-rt).

Each test runs ``retargetd run --listen natnet://…|qtm://…`` as a subprocess against
the emulators of ``tests/protocols`` (written from the vendors' protocol documents,
see their docstrings) serving the btkdata Plug-in Gait walk over loopback. The solved
pose stream is compared frame by frame with the batch solve of the same take (what
``retargetd solve`` computes; ``test_live_equals_batch`` proves that oracle) on the
positions as the wire carries them (NatNet: float32 metres in Motive's Y-up frame;
QTM: float32 millimetres). Faults: a server that vanishes, an unknown protocol version,
labels the rig does not know, a flood. ``retargetd record --listen`` records the
packets as they came, and the recording decodes through the same inputs.

ZeroMQ's slow joiner is beaten as in ``test_live_equals_batch``: frames go through the
daemon's OSC input until the SUB sees a pose, and only then does the capture system
start serving (Motive: the emulator starts answering; QTM: its port starts accepting,
and retargetd's client finds it on its next backoff retry).
"""

from __future__ import annotations

import functools
import importlib.util
import queue
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from paths import DATASETS, require
from pythonosc.osc_bundle import OscBundle
from pythonosc.osc_message import OscMessage

from retargetd.daemon.body.calibration import load_calibration
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.body.solve import BodySolve, BodySolver
from retargetd.daemon.rotations import quat_angle, quat_conj, quat_mul
from retargetd.protocols import pose_stream
from retargetd.replay.take import Take
from retargetd.replay.takes import load_take

WALK = DATASETS / "btkdata/PiG_Motion-FlatFoot-Full.c3d"
TOL_RAD = 1e-6  # float32 quaternions on the wire (~1e-7 relative), as for OSC/ZeroMQ
LOST = pose_stream.FRAME_SOURCE_LOST


def _load(name: str) -> Any:
    key = f"retargetd_tests_{name}"
    if key not in sys.modules:
        path = Path(__file__).resolve().parents[1] / "protocols" / f"{name}.py"
        spec = importlib.util.spec_from_file_location(key, path)
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        sys.modules[key] = module
        spec.loader.exec_module(module)
    return sys.modules[key]


nn_em = _load("natnet_emulator")
qtm_em = _load("qtm_emulator")


@functools.cache
def _walk() -> Take:
    # (skips outside CI, fails in CI, saying why, when ../shared is absent)
    return load_take(require(WALK, "the btkdata Plug-in Gait walk"))


def _wire_positions(system: str) -> np.ndarray:
    """The take's positions as the daemon decodes them (world metres, float64)."""
    pos = _walk().positions
    if system == "natnet":  # float32 metres; the axis swap is exact
        return np.asarray(pos, dtype=np.float32).astype(np.float64)
    return np.asarray(pos * 1000.0, dtype=np.float32).astype(np.float64) * 1e-3


@functools.cache
def _batch(calibration: Path, system: str) -> BodySolve:
    take = _walk()
    solver = BodySolver(
        load_rig("plug-in-gait"), load_calibration(calibration), take.labels
    )
    return solver.solve_take(_wire_positions(system))


class _Server:
    """An emulator serving the walk, not yet started (the daemon connects first)."""

    def __init__(self, system: str, **scenario: Any) -> None:
        take = _walk()
        self.system = system
        args = (take.positions, list(take.labels), take.rate_hz, take.first_frame)
        if system == "natnet":
            self.em = nn_em.NatNetEmulator(*args, nn_em.Scenario(**scenario))
            port = self.em.command_port
            self.url = f"natnet://127.0.0.1:{port}?local=127.0.0.1"
        else:
            self.em = qtm_em.QtmEmulator(*args, qtm_em.Scenario(**scenario))
            self.em.listener.close()  # QTM not running yet: connections refused
            self.url = f"qtm://127.0.0.1:{self.em.port}"
        self.started = False

    def start(self) -> None:
        if self.system == "qtm":
            self.em.listener = self.em._listen(self.em.port)
        self.em.start()
        self.started = True

    def close(self) -> None:
        if self.started:
            self.em.close()
        elif self.system == "natnet":
            self.em.sock.close()


@pytest.fixture
def serve() -> Any:
    made: list[_Server] = []

    def make(system: str, **scenario: Any) -> _Server:
        server = _Server(system, **scenario)
        made.append(server)
        return server

    yield make
    for server in made:
        server.close()


def _start(
    run_daemon: Callable[..., Any],
    pose_capture: Callable[[str], Any],
    calibration: Path,
    server: _Server,
    *args: str,
    vmc_port: int = 0,
) -> tuple[Any, Any, set[int]]:
    daemon = run_daemon(
        calibration,
        *args,
        "--listen",
        server.url,
        extra="stats_interval_s = 0.5\n",
        vmc_port=vmc_port,
    )
    cap = pose_capture(daemon.endpoints["zmq poses"])
    take = _walk()
    primed = cap.prime(daemon, "osc", take.labels, take.positions[0])
    server.start()
    return daemon, cap, primed


def _lines(daemon: Any) -> list[str]:
    """Every stdout line the daemon printed so far (its reader thread queues them)."""
    while True:
        try:
            line = daemon._q.get_nowait()
        except queue.Empty:
            return list(daemon.lines)
        if line is not None:
            daemon.lines.append(line)


def _said(daemon: Any, text: str) -> bool:
    return any(text in line for line in _lines(daemon))


def _capture_status(daemon: Any) -> dict[str, Any]:
    reply = daemon.ctl({"cmd": "status"})
    assert reply is not None and reply["ok"], reply
    return dict(reply["status"]["capture"])


def _wait(cond: Callable[[], bool], cap: Any, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if cond():
            return True
        cap.pump(50)
    return cond()


def _vmc_tracking_lost(sock: socket.socket, timeout_s: float) -> bool:
    """Drain ``sock`` (the VMC target) until a ``/VMC/Ext/OK 1 3 0 0`` arrives."""

    def messages(dgram: bytes) -> Iterator[OscMessage]:
        if OscBundle.dgram_is_bundle(dgram):
            for item in OscBundle(dgram):
                yield from messages(item.dgram)
        else:
            yield OscMessage(dgram)

    deadline = time.monotonic() + timeout_s
    sock.settimeout(0.2)
    while time.monotonic() < deadline:
        try:
            dgram = sock.recv(65536)
        except TimeoutError:
            continue
        for msg in messages(dgram):
            if msg.address == "/VMC/Ext/OK" and list(msg.params) == [1, 3, 0, 0]:
                return True
    return False


def _angles(live: np.ndarray, batch: np.ndarray) -> np.ndarray:
    return quat_angle(quat_mul(quat_conj(np.asarray(live, np.float64)), batch))


@pytest.mark.timeout(120)
@pytest.mark.parametrize("system", ["natnet", "qtm"])
def test_live_from_capture_system_equals_batch_solve(
    pig_calibration: Path,
    run_daemon: Callable[..., Any],
    pose_capture: Callable[[str], Any],
    serve: Any,
    system: str,
    request: pytest.FixtureRequest,
) -> None:
    take = _walk()
    n = take.n_frames
    server = serve(system, faults=False)
    vmc_rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    request.addfinalizer(vmc_rx.close)
    vmc_rx.bind(("127.0.0.1", 0))
    daemon, cap, primed = _start(
        run_daemon, pose_capture, pig_calibration, server, "--process-every-frame",
        vmc_port=vmc_rx.getsockname()[1],
    )  # fmt: skip

    def live() -> list[Any]:
        return [m for m in cap.poses if m.names_id not in primed and not m.flags & LOST]

    assert _wait(lambda: len(live()) >= n, cap, 40.0), "\n".join(_lines(daemon))
    # The take ends: the source falls silent, the last good pose is sent again,
    # flagged held + source_lost, and the status says so.
    assert _wait(lambda: any(m.flags & LOST for m in cap.poses), cap, 10.0), (
        daemon.lines
    )
    poses = live()
    held = [m for m in cap.poses if m.flags & LOST]
    assert len(poses) == n, (len(poses), n)
    assert [m.frame_id - take.first_frame for m in poses] == list(range(n))
    batch = _batch(pig_calibration, system)
    wfb = np.stack([m.world_from_bone_quat for m in poses])
    rfb = np.stack([m.rest_from_bone_quat for m in poses])
    pfb = np.stack([m.parent_from_bone_quat for m in poses])
    root = np.stack([m.root_pos_world for m in poses])
    wfb_rad = _angles(wfb, batch.world_from_bone_quat)
    print(
        f"\n{system}: {n} frames x {wfb.shape[1]} bones; max angle live vs batch "
        f"world_from_bone {wfb_rad.max():.3g} rad; root max "
        f"{np.abs(root - batch.root_pos).max():.3g} m; {len(held)} held poses"
    )
    assert wfb_rad.max() <= TOL_RAD
    assert _angles(rfb, batch.rest_from_bone_quat).max() <= TOL_RAD
    assert _angles(pfb, batch.parent_from_bone_quat).max() <= TOL_RAD
    np.testing.assert_allclose(root, batch.root_pos, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(
        np.stack([m.bone_flags for m in poses]), batch.bone_flags
    )
    last = poses[-1]
    for m in held:
        assert m.frame_id == last.frame_id and m.flags & pose_stream.FRAME_HELD
        np.testing.assert_array_equal(m.world_from_bone_quat, last.world_from_bone_quat)
    status = _capture_status(daemon)
    assert status["system"] == system and status["state"] == "lost", status
    assert status["counts"]["frames"] == n and status["counts"]["lost"] == 1, status
    assert status["counts"]["held_poses"] >= len(held)
    # VMC has no frame flags: while lost its target hears "calibrated, tracking lost"
    # (/VMC/Ext/OK 1 3 0 0, VMC 2.7), read here with python-osc, not our decoder.
    assert _vmc_tracking_lost(vmc_rx, 5.0), "no /VMC/Ext/OK 1 3 0 0 while lost"
    assert _capture_status(daemon)["counts"]["held_vmc"] >= 1
    connected = (
        "connected to Motive"
        if system == "natnet"
        else f"qtm: streaming {len(take.labels)} labelled markers"
    )
    assert _said(daemon, connected), daemon.lines
    assert _said(daemon, "sending the last good pose")
    # A stats line (every 0.5 s here) names the source's state.
    stats = f"| {system} lost frames {n}"
    assert _wait(lambda: _said(daemon, stats), cap, 5.0), [
        ln for ln in daemon.lines if "fps" in ln or system in ln
    ]


# alone (tests/helpers/alone.py): times control replies (under 0.5 s) from a daemon
# process while an emulator process serves it: three processes of this test, which
# the other xdist worker's test beside it would slow.
@pytest.mark.alone
@pytest.mark.timeout(120)
@pytest.mark.parametrize("system", ["natnet", "qtm"])
def test_faults_are_said_counted_and_the_last_pose_held(
    pig_calibration: Path,
    run_daemon: Callable[..., Any],
    pose_capture: Callable[[str], Any],
    serve: Any,
    system: str,
) -> None:
    """Truncated, garbled (and for NatNet duplicate and swapped) packets, a label the
    rig does not know, then the server vanishes: each said and counted; the daemon
    keeps answering and streams the last good pose flagged."""
    server = serve(system, faults=True, label_change_at=100, vanish_at=200)
    daemon, cap, _ = _start(
        run_daemon, pose_capture, pig_calibration, server, "--process-every-frame"
    )
    assert _wait(lambda: any(m.flags & LOST for m in cap.poses), cap, 30.0), (
        daemon.lines
    )
    status = _capture_status(daemon)
    drops = status["drops"]
    assert drops.get("bad_length", 0) + drops.get("bad_count", 0) >= 1, drops
    if system == "natnet":
        assert drops.get("duplicate") == 1 and drops.get("backwards") == 1, drops
    assert status["counts"]["unknown_label_sets"] >= 1, status
    rig_markers = set(load_rig("plug-in-gait").marker_names)
    renamed = ["renamed", *_walk().labels[1:]]  # the emulators rename marker 0
    assert status["unknown_labels"] == [lb for lb in renamed if lb not in rig_markers]
    assert "renamed" in status["unknown_labels"]
    assert _said(daemon, "not markers of rig plug-in-gait"), daemon.lines
    assert status["state"] == "lost" and status["counts"]["lost"] == 1, status
    # The loop never waits for the reconnect: control answers at once, repeatedly,
    # while the client keeps trying, and the held pose keeps coming.
    before = len([m for m in cap.poses if m.flags & LOST])
    for _ in range(5):
        t0 = time.monotonic()
        assert daemon.ctl({"cmd": "status"}, timeout_ms=1000) is not None
        assert time.monotonic() - t0 < 0.5
        cap.pump(100)
    assert len([m for m in cap.poses if m.flags & LOST]) > before
    if system == "natnet":
        assert _wait(
            lambda: _capture_status(daemon)["client"]["timeouts"] >= 1, cap, 5.0
        )
        assert _said(daemon, "reconnecting"), daemon.lines
    else:
        assert _said(daemon, "disconnected from"), daemon.lines
        assert _capture_status(daemon)["client"]["disconnects"] >= 1
    rc, err = daemon.stop()
    assert rc == 0, err


@pytest.mark.timeout(60)
@pytest.mark.parametrize("system", ["natnet", "qtm"])
def test_unknown_protocol_version_is_said_and_counted(
    pig_calibration: Path,
    run_daemon: Callable[..., Any],
    pose_capture: Callable[[str], Any],
    serve: Any,
    system: str,
) -> None:
    scenario = {"version": (2, 9)} if system == "natnet" else {"refuse_version": True}
    server = serve(system, faults=False, **scenario)
    daemon, cap, _ = _start(run_daemon, pose_capture, pig_calibration, server)
    key = "bad_control" if system == "natnet" else "bad_version"
    assert _wait(lambda: _capture_status(daemon)["client"][key] >= 1, cap, 20.0), (
        daemon.lines
    )
    status = _capture_status(daemon)
    assert (
        status["state"] in ("connecting", "waiting") and not status["counts"]["frames"]
    )
    said = "NatNet 2.9" if system == "natnet" else "refused RT protocol version"
    assert _said(daemon, said), daemon.lines
    assert daemon.ctl({"cmd": "status"}, timeout_ms=500) is not None


@pytest.mark.timeout(60)
def test_flood_is_drained_latest_wins_and_said(
    pig_calibration: Path,
    run_daemon: Callable[..., Any],
    pose_capture: Callable[[str], Any],
    serve: Any,
) -> None:
    """Motive sending the whole take at once: the loop drains it, solves what its
    budget allows (latest wins, the rest counted stale), says it floods and stays
    up."""
    server = serve("natnet", faults=False, flood=True)
    daemon, cap, _ = _start(run_daemon, pose_capture, pig_calibration, server)
    assert _wait(
        lambda: (
            _capture_status(daemon)["counts"]["frames"] > 0
            and any(m.flags & LOST for m in cap.poses)
        ),
        cap,
        20.0,
    ), daemon.lines
    status = _capture_status(daemon)
    counters = daemon.counters()
    n = _walk().n_frames
    assert status["counts"]["frames"] == n, status  # loopback: the kernel kept all
    # Every accepted frame was solved, counted stale (latest wins) or unsolved (its
    # pipeline still being built off the loop: the take's first frames), none lost.
    assert (
        counters["frames_in"] >= n
        and counters["frames_out"] + counters["stale"] + counters["unsolved"]
        >= counters["frames_in"]
    ), counters
    assert status["counts"]["floods"] >= 1, "\n".join([str(status), *_lines(daemon)])
    assert _said(daemon, "floods"), daemon.lines
    assert daemon.ctl({"cmd": "status"}, timeout_ms=500) is not None


@pytest.mark.timeout(90)
@pytest.mark.parametrize("system", ["natnet", "qtm"])
def test_record_keeps_the_packets_and_replay_decodes_them_alike(
    retargetd: list[str], tmp_path: Path, serve: Any, system: str
) -> None:
    """``retargetd record --listen`` against the emulator; the recording, read back
    (``load_take``, what ``retargetd replay`` plays), holds every frame decoded by the
    same input as live, control packets included."""
    from retargetd.replay import recording as rf

    take = _walk()
    server = serve(system, faults=True)
    server.start()
    out = tmp_path / f"{system}.mcap"
    argv = [*retargetd, "record", "--listen", server.url, "--out", str(out)]
    done = subprocess.run(
        [*argv, "--seconds", "7"], capture_output=True, text=True, timeout=60,
        cwd=tmp_path,
    )  # fmt: skip
    assert done.returncode == 0, (done.stdout, done.stderr)
    assert server.em.done.is_set(), done.stdout
    rec = rf.read_recording(out)
    packets = [p for p in rec.packets() if p.input == system]
    form = rf.FORM_NATNET if system == "natnet" else rf.FORM_QTM
    assert {p.form for p in packets} == {form}
    kinds = [p.kind for p in packets]
    assert rf.KIND_LABELS in kinds  # model definitions / parameters XML
    assert kinds.count(rf.KIND_FRAME) >= take.n_frames  # + truncated, garbled ...
    back = load_take(out)
    assert back.labels == take.labels
    expected = _wire_positions(system)
    if system == "natnet":  # the swapped pair: frame 21 before 20, 20 dropped
        expected = np.delete(expected, 20, axis=0)
    assert back.n_frames == expected.shape[0], (back.n_frames, expected.shape)
    assert back.rate_hz == pytest.approx(take.rate_hz, rel=1e-3)
    np.testing.assert_allclose(back.positions, expected, rtol=0, atol=1e-9)
    assert np.array_equal(np.isnan(back.positions), np.isnan(expected))
    assert "recorded" in done.stdout


@pytest.mark.timeout(120)
def test_recording_started_mid_stream_decodes_on_its_own(
    pig_calibration: Path,
    run_daemon: Callable[..., Any],
    pose_capture: Callable[[str], Any],
    serve: Any,
    tmp_path: Path,
) -> None:
    """``ctl record start`` while Motive streams: the daemon writes the server info
    and model definitions it kept before the frames, so the file loads alone and
    holds every frame from then on, decoded as live."""
    from retargetd.replay import recording as rf

    take = _walk()
    server = serve("natnet", faults=False)
    daemon, cap, _ = _start(
        run_daemon, pose_capture, pig_calibration, server, "--process-every-frame"
    )
    assert _wait(
        lambda: _capture_status(daemon)["counts"]["frames"] >= 60, cap, 30.0
    ), daemon.lines
    path = tmp_path / "recordings" / "mid.mcap"  # the default record.folder
    reply = daemon.ctl({"cmd": "record", "action": "start", "path": str(path)})
    assert reply is not None and reply["ok"], reply
    assert _wait(lambda: any(m.flags & LOST for m in cap.poses), cap, 20.0), (
        daemon.lines
    )
    reply = daemon.ctl({"cmd": "record", "action": "stop"})
    assert reply is not None and reply["ok"], reply
    deadline = time.monotonic() + 10.0
    while not rf.read_recording(path).complete:
        assert time.monotonic() < deadline, "recording never finished"
        time.sleep(0.1)
    packets = [p for p in rf.read_recording(path).packets() if p.input == "natnet"]
    assert [p.kind for p in packets[:2]] == [rf.KIND_OTHER, rf.KIND_LABELS]  # seeds
    back = load_take(path)
    start = back.first_frame - take.first_frame
    assert 60 <= start < take.n_frames - 50, start
    assert back.labels == take.labels
    assert back.n_frames == take.n_frames - start
    expected = _wire_positions("natnet")[start:]
    np.testing.assert_allclose(back.positions, expected, rtol=0, atol=1e-9)


@pytest.mark.timeout(90)
def test_replay_of_a_capture_recording_plays_the_decoded_frames(
    retargetd: list[str],
    tmp_path: Path,
    serve: Any,
    udp_socket: Callable[..., Any],
) -> None:
    """``retargetd replay natnet.mcap --to osc://…``: the recording decoded by the
    NatNet input, sent as compact OSC frames, one per decoded frame, same markers."""
    from retargetd.protocols import osc_in
    from retargetd.protocols.marker_input import ACCEPTED, MarkerStream

    server = serve("natnet", faults=False)
    server.start()
    out = tmp_path / "natnet.mcap"
    argv = [*retargetd, "record", "--listen", server.url, "--out", str(out)]
    done = subprocess.run(
        [*argv, "--seconds", "6"], capture_output=True, text=True, timeout=60,
        cwd=tmp_path,
    )  # fmt: skip
    assert done.returncode == 0, (done.stdout, done.stderr)
    sink = udp_socket(bind=True, timeout_s=2.0)
    host, port = sink.getsockname()
    played = subprocess.run(
        [*retargetd, "replay", str(out), "--to", f"osc://{host}:{port}", "--speed",
         "4"],
        capture_output=True, text=True, timeout=60, cwd=tmp_path,
    )  # fmt: skip
    assert played.returncode == 0, (played.stdout, played.stderr)
    stream = MarkerStream(None)
    rows: list[np.ndarray] = []
    while True:
        try:
            data = sink.recv(65536)
        except TimeoutError:
            break
        if data.startswith(b"/rtd/labels\0"):
            stream.set_labels(osc_in.decode_labels(data))
        elif (
            stream.feed(osc_in.decode_compact_frame, data, t_ns=len(rows) * 10**7)
            == ACCEPTED
        ):
            rows.append(stream.current.frame.markers_world.copy())
    expected = _wire_positions("natnet")
    assert len(rows) == expected.shape[0], (len(rows), played.stdout)
    np.testing.assert_allclose(np.stack(rows), expected, rtol=0, atol=1e-6)
