"""Fixtures for live-daemon tests: loopback sockets that are always closed, the
Plug-in Gait calibration, and ``retargetd run`` subprocesses.

Every socket binds 127.0.0.1 (port 0 or ``tcp://127.0.0.1:*``), so tests run in
parallel and never collide with the daemon's default ports.
"""

from __future__ import annotations

import dataclasses
import json
import os
import queue
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import zmq
from paths import DATASETS


@pytest.fixture
def udp_socket() -> Iterator[Callable[..., socket.socket]]:
    """A factory of UDP sockets, bound to 127.0.0.1 (port 0) when ``bind=True``;
    every one is closed at teardown."""
    made: list[socket.socket] = []

    def make(*, bind: bool = False, timeout_s: float = 0.05) -> socket.socket:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        made.append(sock)
        if bind:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 21)
            sock.bind(("127.0.0.1", 0))
        sock.settimeout(timeout_s)
        return sock

    yield make
    for sock in made:
        sock.close()


@pytest.fixture
def zmq_socket() -> Iterator[Callable[[int], Any]]:
    """A factory of ZeroMQ sockets (``linger = 0``) in a context of the test's own
    (as the daemon's is its own), all closed and the context shut at teardown."""
    ctx = zmq.Context()
    made: list[Any] = []

    def make(kind: int) -> Any:
        sock = ctx.socket(kind)
        sock.setsockopt(zmq.LINGER, 0)
        made.append(sock)
        return sock

    yield make
    for sock in made:
        sock.close()
    ctx.term()


# ---- the Plug-in Gait pair and daemons as subprocesses -----------------------------

#: Same place as ``tests/conftest.py``'s DATASETS (a conftest can't be imported).

PIG_STATIC = "btkdata/PiG_Calibration-FlatFoot-Full.c3d"
PIG_WALK = "btkdata/PiG_Motion-FlatFoot-Full.c3d"
_ENDPOINT_LINE = re.compile(r"^(listening on|sending to) (\S+)(?: \(.*\))?: (.+)$")


@pytest.fixture(scope="session")
def pig_calibration(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``retargetd calibrate`` of the plug-in-gait rig on the btkdata static."""
    if not DATASETS.is_dir():
        reason = f"shared datasets folder not found at {DATASETS}"
        if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
            pytest.fail(f"{reason} (CI=true: nothing may skip)")
        pytest.skip(reason)
    from retargetd.daemon.cli.main import main

    out = tmp_path_factory.mktemp("pig") / "performer.json"
    argv = ["calibrate", str(DATASETS / PIG_STATIC), "--rig", "plug-in-gait"]
    assert main([*argv, "--out", str(out)]) == 0
    return out


def retargetd_argv() -> list[str]:
    """The installed console script beside this interpreter, else ``-m``."""
    script = Path(sys.executable).with_name("retargetd")
    if script.is_file():
        return [str(script)]
    return [sys.executable, "-m", "retargetd.daemon"]


def daemon_config(
    path: Path,
    calibration: Path,
    extra: str = "",
    vmc_port: int = 0,
    rig: str = "plug-in-gait",
) -> Path:
    """A ``retargetd run`` config for ``rig`` (default plug-in-gait, a shipped name or
    a path; the calibration must be of it): every endpoint ephemeral
    on 127.0.0.1, VMC off (or to 127.0.0.1:``vmc_port``), a pose stream that queues
    (not drops) for a slow SUB. The body solve is the construction, these tests'
    oracle (the fit, the default, has its own live tests: test_live_equals_batch)."""
    q = json.dumps  # a JSON string is a valid TOML basic string for these paths
    vmc = f'host = "127.0.0.1"\nport = {vmc_port}' if vmc_port else "enabled = false"
    path.write_text(
        f"""[performer]
rig = {q(rig)}
calibration = {q(str(calibration))}
[solve]
method = "construction"
[input.osc]
port = 0
[input.zmq]
endpoint = "tcp://127.0.0.1:*"
[output.vmc]
{vmc}
[output.pose]
endpoint = "tcp://127.0.0.1:*"
sndhwm = 100000
[control]
endpoint = "tcp://127.0.0.1:*"
[show_control]
port = 0
[loop]
poll_timeout_ms = 20
{extra}"""
    )
    return path


class DaemonProc:
    """``retargetd run ARGS`` as a subprocess: its endpoints, control, a clean stop."""

    def __init__(self, args: list[str], cwd: Path, timeout_s: float = 60.0) -> None:
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        self.p = subprocess.Popen(
            [*retargetd_argv(), "run", *args], cwd=cwd, env=env,
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        self.lines: list[str] = []
        self._q: queue.Queue[str | None] = queue.Queue()
        self._reader = threading.Thread(target=self._pump, daemon=True)
        self._reader.start()
        self.endpoints: dict[str, str] = {}
        deadline = time.monotonic() + timeout_s
        while "control" not in self.endpoints:
            line = self._next_line(deadline)
            m = _ENDPOINT_LINE.match(line)
            if m:
                self.endpoints[m.group(3)] = m.group(2)
        # The loop serves once open() (and the kernel's warm-up) is done.
        while self.ctl({"cmd": "status"}, timeout_ms=500) is None:
            assert time.monotonic() < deadline, f"daemon not serving: {self.lines}"

    def _pump(self) -> None:
        assert self.p.stdout is not None
        for line in self.p.stdout:
            self._q.put(line.rstrip("\n"))
        self._q.put(None)

    def _next_line(self, deadline: float) -> str:
        left = deadline - time.monotonic()
        if left <= 0:
            raise AssertionError(f"timed out; stdout so far: {self.lines}")
        try:
            line = self._q.get(timeout=left)
        except queue.Empty:
            raise AssertionError(f"timed out; stdout: {self.lines}") from None
        if line is None:
            err = self.p.stderr.read() if self.p.stderr else ""
            raise AssertionError(f"daemon exited early: {self.lines} {err}")
        self.lines.append(line)
        return line

    def udp(self, what: str) -> tuple[str, int]:
        """(host, port) of a UDP endpoint, e.g. ``"osc markers"``."""
        host, port = self.endpoints[what].removeprefix("udp://").rsplit(":", 1)
        return host, int(port)

    def ctl(self, req: dict[str, Any], timeout_ms: int = 2000) -> dict[str, Any] | None:
        """One control request; the reply, or None on timeout."""
        from retargetd.daemon.cli.ctl import request

        return request(self.endpoints["control"], req, timeout_ms)

    def wait_pipelines(self, input: str = "osc", timeout_s: float = 30.0) -> None:
        """Wait until the daemon has taken a label set on ``input`` and built every
        pipeline for it (off its loop, ``live/rebuild.py``): the next frame is
        solved (status: ``labels_taken``, ``pipelines_building``)."""
        deadline = time.monotonic() + timeout_s
        while True:
            reply = self.ctl({"cmd": "status"})
            assert reply is not None and reply["ok"], reply
            st = reply["status"]
            if st["labels_taken"][input] and not st["pipelines_building"]:
                return
            assert time.monotonic() < deadline, "the pipelines were never built"
            time.sleep(0.01)

    def counters(self) -> dict[str, Any]:
        """The status document's counters."""
        reply = self.ctl({"cmd": "status"})
        assert reply is not None and reply["ok"], reply
        return dict(reply["status"]["counters"])

    def stop(self, timeout_s: float = 20.0) -> tuple[int, str]:
        """SIGINT, then wait (bounded): exit code and stderr."""
        self.p.send_signal(signal.SIGINT)
        rc = self.p.wait(timeout=timeout_s)
        self._reader.join(timeout=5.0)
        assert self.p.stderr is not None
        return rc, self.p.stderr.read()

    def close(self) -> None:
        """Kill if still running; close the pipes."""
        if self.p.poll() is None:
            self.p.kill()
            self.p.wait(timeout=10.0)
        self._reader.join(timeout=5.0)
        for stream in (self.p.stdout, self.p.stderr):
            if stream is not None:
                stream.close()


@pytest.fixture
def retargetd() -> list[str]:
    """argv prefix that runs the ``retargetd`` console script."""
    return retargetd_argv()


@pytest.fixture
def run_daemon(tmp_path: Path) -> Iterator[Callable[..., DaemonProc]]:
    """``start(calibration, *args, extra="", vmc_port=0, rig="plug-in-gait")``:
    ``retargetd run --config C ARGS`` in ``tmp_path``, C from :func:`daemon_config`;
    killed at teardown if still running."""
    procs: list[DaemonProc] = []

    def start(
        calibration: Path,
        *args: str,
        extra: str = "",
        vmc_port: int = 0,
        rig: str = "plug-in-gait",
    ) -> DaemonProc:
        config = daemon_config(
            tmp_path / f"daemon{len(procs)}.toml", calibration, extra, vmc_port, rig
        )
        proc = DaemonProc(["--config", str(config), *args], tmp_path)
        procs.append(proc)
        return proc

    yield start
    for proc in procs:
        proc.close()


class PoseCapture:
    """A SUB on a daemon's pose stream, every message decoded, in arrival order."""

    def __init__(self, sock: Any, endpoint: str) -> None:
        from retargetd.protocols import pose_stream

        self._ps = pose_stream
        sock.setsockopt(zmq.RCVHWM, 0)  # unlimited: the test must see every pose
        sock.setsockopt(zmq.SUBSCRIBE, b"RTD")
        sock.connect(endpoint)
        self.sock = sock
        self.poses: list[Any] = []  # pose_stream.PoseMessage
        self.names: list[Any] = []  # pose_stream.PoseNames
        self.order: list[tuple[str, int]] = []  # ("names" | "data", names id)

    def pump(self, timeout_ms: int = 0) -> None:
        """Receive what is waiting (the first poll waits up to ``timeout_ms``)."""
        while self.sock.poll(timeout_ms):
            timeout_ms = 0
            parts = self.sock.recv_multipart()
            if parts[0][:4] == self._ps.DATA_MAGIC:
                msg = self._ps.decode_pose(parts)
                self.poses.append(msg)
                self.order.append(("data", msg.names_id))
            else:
                names = self._ps.decode_pose_names(parts)
                self.names.append(names)
                self.order.append(("names", names.names_id))

    def wait_for(self, n: int, timeout_s: float) -> None:
        """Pump until ``n`` data messages arrived or the time is up."""
        deadline = time.monotonic() + timeout_s
        while len(self.poses) < n and time.monotonic() < deadline:
            self.pump(50)

    def clear(self) -> None:
        for received in (self.poses, self.names, self.order):
            received.clear()

    def prime(
        self, daemon: DaemonProc, via: str, labels: tuple[str, ...], row: Any
    ) -> set[int]:
        """Beat ZeroMQ's slow joiner without touching the input under test: send
        frames (markers ``row``) through the daemon's ``via`` input ("osc" or "zmq")
        until this SUB receives a pose. Each input has its own solver, so the other
        one starts fresh. Forgets what arrived; returns the names ids it used."""
        import numpy as np

        from retargetd.protocols import osc_in, zmq_wire
        from retargetd.protocols.marker_input import LabelSet

        label_set = LabelSet(PRIME_SET_ID, labels)
        row = np.asarray(row, dtype=np.float32)
        ctx = zmq.Context.instance()
        push = ctx.socket(zmq.PUSH)
        push.setsockopt(zmq.LINGER, 0)
        udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            if via == "zmq":
                push.connect(daemon.endpoints["zmq markers"])
                push.send_multipart(zmq_wire.encode_zmq_labels(label_set))
            else:
                udp.sendto(osc_in.encode_labels(label_set), daemon.udp("osc markers"))
            # its pipeline, built off the daemon's loop: the first frame is solved
            daemon.wait_pipelines(via)
            deadline = time.monotonic() + 10.0
            i = 0
            while not self.poses:
                assert time.monotonic() < deadline, "poses never reached the SUB"
                if via == "zmq":
                    push.send_multipart(
                        zmq_wire.encode_zmq_frame(i, i / 100, PRIME_SET_ID, row)
                    )
                else:
                    frame = osc_in.encode_compact_frame(i, i / 100, PRIME_SET_ID, row)
                    udp.sendto(frame, daemon.udp("osc markers"))
                i += 1
                self.pump(20)
            self.pump(100)
        finally:
            push.close()
            udp.close()
        used = {m.names_id for m in self.poses}
        self.clear()
        return used


#: Label-set id of the priming sender (the player announces 1).
PRIME_SET_ID = 7


@pytest.fixture
def pose_capture(
    zmq_socket: Callable[[int], Any],
) -> Callable[[str], PoseCapture]:
    """``capture(endpoint)``: a :class:`PoseCapture` on a pose stream."""

    def make(endpoint: str) -> PoseCapture:
        return PoseCapture(zmq_socket(zmq.SUB), endpoint)

    return make


@dataclasses.dataclass(frozen=True)
class CleanTake:
    """A clean synthetic take solved with the exact test rig, and its MuJoCo model."""

    rig: Any
    cal: Any
    solve: Any
    skel: Any
    vm: Any
    fit: tuple[Any, Any]
    rate_hz: float


@pytest.fixture(scope="session")
def clean_synth() -> CleanTake:
    """The synthetic performer (every motion but forearm_twist, which pushes a forearm
    into a thigh), 4 s at 120 Hz, solved with ``tests/data/synth-exact-rig.toml`` and
    modelled: shared by the validation tests."""
    from retargetd.daemon.body.calibration import calibrate
    from retargetd.daemon.body.rig import load_rig
    from retargetd.daemon.body.solve import BodySolver
    from retargetd.daemon.synth import performer as pf
    from retargetd.daemon.validate.checks import fit_pairs
    from retargetd.daemon.validate.model import build_model, skeleton_from_calibration

    data = Path(__file__).resolve().parent.parent / "data"
    rate_hz = 120.0
    rig = load_rig(data / "synth-exact-rig.toml")
    take = pf.synthesize(
        seconds=4.0,
        rate_hz=rate_hz,
        markerset=data / "synth-exact-markers.toml",
        motions=[m for m in pf.DEFAULT_MOTIONS if m != "forearm_twist"],
    )
    cal = calibrate(rig, take.markers_world[take.base_pose_frames], take.labels)
    solve = BodySolver(rig, cal, take.labels).solve_take(take.markers_world)
    skel = skeleton_from_calibration(rig, cal)
    return CleanTake(
        rig, cal, solve, skel, build_model(skel), fit_pairs(rig, solve.joint_names),
        rate_hz,
    )  # fmt: skip


@pytest.fixture
def mujoco_cwd(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """MuJoCo writes MUJOCO_LOG.TXT into the CWD when it warns: never the repo."""
    monkeypatch.chdir(tmp_path)
    yield
