"""The live-daemon test harness (importable: ``tests/helpers`` is on pytest's
``pythonpath``): the exact synthetic performer and its calibration, a daemon serving
in a thread on ephemeral loopback ports (:func:`start_daemon`), marker senders
(:class:`OscSource`, ZeroMQ), receivers (:class:`VmcReceiver`, :class:`PoseSub`) and
the solve oracle. Every wait has a deadline; every socket is closed at teardown.

The performer is the synthetic one wearing ``tests/data/synth-exact-markers.toml``,
solved with ``tests/data/synth-exact-rig.toml`` (every bone rigid on one segment, so
the solve is exact and poses can be worked by hand).
"""

from __future__ import annotations

import functools
import json
import math
import os
import random
import re
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, Any

import numpy as np
import pytest
import zmq
from pythonosc.osc_bundle import OscBundle
from pythonosc.osc_message import OscMessage

from retargetd.daemon.body.calibration import calibrate, load_calibration
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.body.solve import BodySolver
from retargetd.daemon.cli.ctl import request
from retargetd.daemon.live.config import DaemonConfig
from retargetd.daemon.live.loop import Daemon
from retargetd.daemon.retarget.retarget import Retargeter, default_humanoid
from retargetd.daemon.synth import performer as pf
from retargetd.protocols import osc_in, pose_stream, vmc_out
from retargetd.protocols.marker_input import LabelSet

TESTS = Path(__file__).resolve().parents[1]
REPO_ROOT = TESTS.parent
DATA = TESTS / "data"
EXACT_RIG = DATA / "synth-exact-rig.toml"
EXACT_MARKERS = DATA / "synth-exact-markers.toml"
RATE_HZ = 100.0
C = S = math.sqrt(0.5)
IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")
VMC_FRAME = (
    ["/VMC/Ext/Root/Pos"]
    + ["/VMC/Ext/Bone/Pos"] * len(vmc_out.HUMANOID_BONES)
    + ["/VMC/Ext/Blend/Apply", "/VMC/Ext/OK", "/VMC/Ext/T"]
)
#: How long a wait for something the daemon will do allows it. A wait ends as soon as
#: the thing happens, so this only bounds a failure: generous, for a loaded 2-core
#: runner (a CI run at twice this VM's test time missed 5 s deadlines).
WAIT_S = 30.0
ENDPOINT_LINE = re.compile(r"^(listening on|sending to) (\S+)(?: \(.*\))?: (.+)$")


# ---- data --------------------------------------------------------------------------


@functools.cache
def _take() -> pf.SynthTake:
    """1 s exact T-pose, then every motion; exact markers, no noise."""
    return pf.synthesize(seconds=3.0, rate_hz=RATE_HZ, markerset=EXACT_MARKERS)


def _f32(a: np.ndarray) -> np.ndarray:
    """What the daemon decodes: float32 on the wire, float64 inside."""
    return np.asarray(a, dtype=np.float32).astype(np.float64)


def _rot_z(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array(
        [[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0, 0, 1]]
    )


@pytest.fixture(scope="module")
def exact_calibration(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A calibration of the exact rig on the take's T-pose hold (float32 markers)."""
    take = _take()
    rig = load_rig(EXACT_RIG)
    cal = calibrate(rig, _f32(take.markers_world[take.base_pose_frames]), take.labels)
    path = tmp_path_factory.mktemp("calibration") / "exact.json"
    cal.save(path)
    return path


@pytest.hookimpl(wrapper=True)
def pytest_runtestloop(session: pytest.Session) -> Iterator[object]:
    """Every kernel a daemon runs, compiled (or loaded from numba's disk cache) once,
    before the first test (outside every test's timeout): :func:`compile_kernels`.

    The daemons the tests start, in threads or as processes, then load the kernels
    from the cache (~0.5 s) instead of compiling them while a test's deadline runs:
    on a fresh machine the fit alone compiles for 69 s on this 2-core VM (82 s for a
    daemon's whole warm-up; measured), and a CI runner twice as slow made tests that
    started the first daemons of a kind time out, then leave them running.

    Under pytest-xdist (``-n 2``) the controller compiles, before it hands the workers
    their first test (its ``session.items`` is empty: the workers collect, meanwhile),
    and the workers load every kernel from the cache; a worker compiles nothing here.
    """
    config = session.config
    if hasattr(config, "workerinput"):  # an xdist worker: the controller compiled
        return (yield)
    distributed = config.pluginmanager.has_plugin("dsession")  # xdist's controller
    if (session.items or distributed) and not config.option.collectonly:
        compile_kernels()
    return (yield)


def compile_kernels() -> None:
    """A daemon opened in-process with the fit, both ``[[pipeline]]`` stages, an output
    rate and the validator on, then closed; the face kernel; and the fused solve and
    emit of both methods.

    Over two processes: the fit (the costliest, its kernels compiled for one signature
    each) in a second interpreter (``compile_part.py fit``) while this one compiles
    every kernel that does not call it (the same daemon solving with the construction,
    the face, the construction's fused kernel); then this one opens the fit's daemon
    and compiles the fit's fused kernel, loading the fit from numba's cache. numba's
    cache is locked between processes (``protocols/cache_lock.py``): two that save one
    function at once leave each signature with its own code. A failure of the second
    process is raised here with its output; it never outlives this call."""
    child, log = _start_part("fit")
    with log:
        try:
            compile_part("apart")
            _join_part(child, log, "fit")
        finally:
            if child.poll() is None:  # (this one failed, or the child timed out)
                child.kill()
                child.wait()
    compile_part("after")


#: What ``compile_kernels`` compiles in each step: ``fit`` in the second process.
PARTS = ("fit", "apart", "after")
#: How long the second process may take (the fit compiled for 140 s of CPU on this
#: 2-core VM; a CI runner twice as slow and busy beside it stays well inside).
PART_TIMEOUT_S = 1800.0


def compile_part(part: str) -> None:
    """One step of :func:`compile_kernels` (:data:`PARTS`)."""
    from retargetd.daemon.body.solve_fit import warm_up as warm_up_fit
    from retargetd.daemon.live.face import warm_up as warm_up_face
    from retargetd.daemon.live.solve_emit import warm_up as warm_up_solve_emit

    if part == "fit":
        warm_up_fit()
    elif part == "apart":
        _open_kernel_daemon("construction")
        warm_up_face()
        warm_up_solve_emit(fit=False)
    elif part == "after":
        _open_kernel_daemon("fit")
        # The solve and the emit in one call (live/solve_emit.py), both methods: the
        # daemon, with its stages, does not run it; the tests' daemons do.
        warm_up_solve_emit(fit=True)
    else:
        raise ValueError(f"no part {part!r} (one of {', '.join(PARTS)})")


def _open_kernel_daemon(method: str) -> None:
    """A daemon with ``method``, both stages, an output rate and the validator,
    opened (its warm-up compiles its kernels) and closed."""
    import tempfile

    take = _take()
    rig = load_rig(EXACT_RIG)
    cal = calibrate(rig, _f32(take.markers_world[take.base_pose_frames]), take.labels)
    with tempfile.TemporaryDirectory(prefix="retargetd-kernels-") as tmp:
        path = Path(tmp) / "exact.json"
        cal.save(path)
        doc = _deep_merge(
            _ephemeral_doc(_unused_udp_port()),
            {
                "performer": {"calibration": str(path)},
                "solve": {"method": method},
                "loop": {"output_rate_hz": 60.0},
                "pipeline": [{"kind": "twist"}, {"kind": "one_euro"}],
                "validate": {"enabled": True},
            },
        )
        daemon = Daemon(DaemonConfig.from_dict(doc, source="kernels"), out=_ignore)
        try:
            daemon.open()
        finally:
            daemon.close()


def _start_part(part: str) -> tuple[subprocess.Popen[bytes], IO[bytes]]:
    """``compile_part(part)`` in a fresh interpreter, and the file of its output."""
    import tempfile

    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(
        p for p in (str(Path(__file__).parent), env.get("PYTHONPATH", "")) if p
    )
    log = tempfile.TemporaryFile()  # noqa: SIM115 (closed by the caller)
    try:
        child = subprocess.Popen(
            [sys.executable, str(Path(__file__).with_name("compile_part.py")), part],
            env=env, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
        )  # fmt: skip
    except BaseException:
        log.close()
        raise
    return child, log


def _join_part(child: subprocess.Popen[bytes], log: IO[bytes], part: str) -> None:
    """Wait for ``child`` (:data:`PART_TIMEOUT_S`); raise with its output unless it
    succeeded."""
    try:
        rc: int | None = child.wait(timeout=PART_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        rc = None
    if rc == 0:
        return
    log.seek(0)
    out = log.read().decode(errors="replace")[-8000:]
    what = f"ran past {PART_TIMEOUT_S:g} s" if rc is None else f"exited with {rc}"
    raise RuntimeError(f"compile_part.py {part} {what}:\n{out}")


def _ignore(_: str) -> None:
    pass


# ---- waiting -----------------------------------------------------------------------


def _wait_until(pred: Callable[[], bool], what: str, timeout_s: float = WAIT_S) -> None:
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(0.002)


# ---- the daemon in a thread --------------------------------------------------------


def _deep_merge(base: dict[str, Any], extra: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in extra.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _deep_merge(out[key], value)
        else:
            out[key] = value
    return out


def _unused_udp_port() -> int:
    """A port on 127.0.0.1 nobody listens on, by UDP or TCP, and that no socket bound
    to port 0 will be given while a test uses it.

    Below the kernel's ephemeral range (``ip_local_port_range``, from which every
    ``bind(("127.0.0.1", 0))`` and ZeroMQ ``tcp://127.0.0.1:*`` gets its port), in its
    lower half, a random port that binds now (nothing there). A port probed by binding
    port 0 and closing at once (as this did) can go to the next socket bound to port
    0, in another test process (the xdist workers) as well as in this one: a daemon's
    VMC, sent to the "unused" port, would then reach another test's receiver or
    input. Two tests that draw the same port here both send to nobody."""
    low = _ephemeral_low()
    rng = random.Random()  # seeded from os.urandom: each process its own draws
    for _ in range(100):
        port = rng.randrange(max(1024, low // 2), low) if low > 2048 else 0
        with (
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp,
            socket.socket(socket.AF_INET, socket.SOCK_STREAM) as tcp,
        ):
            try:
                udp.bind(("127.0.0.1", port))
                tcp.bind(("127.0.0.1", port or udp.getsockname()[1]))
            except OSError:
                continue
            return int(udp.getsockname()[1])
    raise RuntimeError("no unused port on 127.0.0.1 in 100 draws")


def _ephemeral_low() -> int:
    """The first port of the kernel's ephemeral range (Linux); 0 where unknown."""
    ports = Path("/proc/sys/net/ipv4/ip_local_port_range")
    try:
        return int(ports.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 0


def _ephemeral_doc(vmc_port: int) -> dict[str, Any]:
    # The harness's oracle is the construction (_solve_oracle: exact and cheap), so
    # its daemons solve with it; tests of the fit (the default) set method = "fit".
    return {
        "performer": {"rig": str(EXACT_RIG)},
        "solve": {"method": "construction"},
        "input": {
            "osc": {"port": 0},
            "zmq": {"endpoint": "tcp://127.0.0.1:*"},
        },
        "output": {
            "vmc": {"port": vmc_port},
            # Every pose reaches the test's subscriber (the default drops when slow).
            "pose": {"endpoint": "tcp://127.0.0.1:*", "sndhwm": 1000},
        },
        "control": {"endpoint": "tcp://127.0.0.1:*"},
        "show_control": {"port": 0},
        "loop": {"poll_timeout_ms": 20, "stats_interval_s": 0.5},
        # Tests start recordings back to back, on machines whose free space is
        # unknown: the recording limits have their own test (test_live_record).
        "record": {"min_interval_s": 0.0, "min_free_mb": 0.0},
    }


class Live:
    """An opened daemon serving in a thread."""

    def __init__(self, config: DaemonConfig) -> None:
        self.lines: list[str] = []
        self.daemon = Daemon(config, out=self.lines.append)
        try:
            self.daemon.open()
        except BaseException:
            self.daemon.close()
            raise
        self._stop = threading.Event()
        self._errors: list[BaseException] = []
        self.thread = threading.Thread(
            target=self._run, name="live-daemon", daemon=True
        )
        self.thread.start()

    def _run(self) -> None:
        try:
            self.daemon.run(self._stop.is_set)
        except BaseException as exc:  # re-raised in the test thread by stop()
            self._errors.append(exc)

    def stop(self) -> None:
        """Stop the loop (bounded), close every socket, re-raise a loop crash."""
        self._stop.set()
        self.thread.join(timeout=WAIT_S)
        alive = self.thread.is_alive()
        if not alive:
            self.daemon.close()
        assert not alive, f"the daemon loop did not stop within {WAIT_S:g} s"
        if self._errors:
            raise self._errors[0]

    @property
    def running(self) -> bool:
        return self.thread.is_alive()

    def udp(self, what: str) -> tuple[str, int]:
        where = self.daemon.endpoints[what].split()[0]  # "udp://host:port (form)"
        host, port = where.removeprefix("udp://").rsplit(":", 1)
        return host, int(port)

    def tcp(self, what: str) -> str:
        return self.daemon.endpoints[what].split()[0]

    def wait_pipelines(self, stream: Any, label_set: LabelSet) -> None:
        """Wait until ``stream`` took ``label_set`` and every performer's pipeline
        for it is built (off the loop: ``live/rebuild.py``), so that its next frame
        is solved; a performer without a calibration has none to wait for."""
        performers = self.daemon.performers
        _wait_until(
            lambda: stream.label_set == label_set and performers.ready(stream),
            f"the pipelines of label set {label_set.id}",
        )

    def ctl(self, req: dict[str, Any]) -> dict[str, Any]:
        reply = request(self.tcp("control"), req, int(WAIT_S * 1000))
        assert reply is not None, f"no control reply to {req}"
        return reply

    def status(self) -> dict[str, Any]:
        """``ctl status``'s status object (the reply asserted ok)."""
        reply = self.ctl({"cmd": "status"})
        assert reply["ok"], reply
        status: dict[str, Any] = reply["status"]
        return status


@pytest.fixture
def start_daemon() -> Iterator[Callable[..., Live]]:
    """``start(overrides, vmc_port=None)``: a daemon on ephemeral ports in a thread."""
    lives: list[Live] = []

    def start(overrides: dict[str, Any] | None = None, *, vmc_port: int = 0) -> Live:
        doc = _deep_merge(
            _ephemeral_doc(vmc_port or _unused_udp_port()), overrides or {}
        )
        live = Live(DaemonConfig.from_dict(doc, source="test"))
        lives.append(live)
        return live

    yield start
    errors = []
    for live in lives:
        try:
            live.stop()
        except BaseException as exc:
            errors.append(exc)
    if errors:
        raise errors[0]


# ---- senders and receivers ---------------------------------------------------------


class OscSource:
    """A compact-form OSC marker sender; remembers what it sent (for the oracle)."""

    def __init__(
        self,
        sock: socket.socket,
        addr: tuple[str, int],
        label_set_id: int = 1,
        live: Live | None = None,
    ):
        self.sock = sock
        self.addr = addr
        #: The daemon it sends to: :meth:`announce` waits for its pipelines.
        self.live = live
        self.label_set = LabelSet(label_set_id, _take().labels)
        self.next_id = 0
        self.sent: list[tuple[int, np.ndarray]] = []
        self.rate_hz = RATE_HZ  # source time = frame number / rate
        #: Applied to every datagram before it is sent (e.g. ``DatagramSigner.sign``).
        self.sign: Callable[[bytes], bytes] | None = None

    def announce(self, label_set_id: int | None = None, wait: bool = True) -> None:
        """Announce the labels (under ``label_set_id``: a new id); with a ``live``
        daemon and ``wait``, return once it has taken them and built every
        pipeline for them (off its loop), so the next frame is solved."""
        if label_set_id is not None:
            self.label_set = LabelSet(label_set_id, self.label_set.labels)
        self.raw(osc_in.encode_labels(self.label_set))
        if self.live is not None and wait:
            self.live.wait_pipelines(self.live.daemon.osc_stream, self.label_set)

    def send(self, markers: np.ndarray, frame_id: int | None = None) -> int:
        fid = self.next_id if frame_id is None else frame_id
        self.next_id = fid + 1
        self.raw(
            osc_in.encode_compact_frame(
                fid, fid / self.rate_hz, self.label_set.id, markers
            )
        )
        self.sent.append((fid, _f32(markers)))
        return fid

    def send_paced(self, rows: list[np.ndarray], rate_hz: float) -> None:
        """Send ``rows`` one every ``1 / rate_hz`` s, as a capture system sends
        (each at its own time, not as fast as possible)."""
        t_next = time.monotonic()
        for markers in rows:
            t_next += 1.0 / rate_hz
            time.sleep(max(0.0, t_next - time.monotonic()))
            self.send(markers)

    def raw(self, data: bytes) -> None:
        self.sock.sendto(data if self.sign is None else self.sign(data), self.addr)


class PoseSub:
    """A SUB on the daemon's pose stream: data and names messages, decoded."""

    def __init__(self, sock: Any, endpoint: str) -> None:
        sock.setsockopt(zmq.SUBSCRIBE, b"RTD")
        sock.setsockopt(zmq.RCVHWM, 10_000)
        sock.connect(endpoint)
        self.sock = sock
        self.poses: list[pose_stream.PoseMessage] = []
        self.names: list[pose_stream.PoseNames] = []
        self.events: list[tuple[str, int]] = []  # ("names"|"data", names_id) in order

    def clear(self) -> None:
        for received in (self.poses, self.names, self.events):
            received.clear()

    def pump(self, timeout_ms: int = 0) -> None:
        while self.sock.poll(timeout_ms):
            timeout_ms = 0
            parts = self.sock.recv_multipart()
            if parts[0][:4] == pose_stream.DATA_MAGIC:
                msg = pose_stream.decode_pose(parts)
                self.poses.append(msg)
                self.events.append(("data", msg.names_id))
            else:
                names = pose_stream.decode_pose_names(parts)
                self.names.append(names)
                self.events.append(("names", names.names_id))

    def wait(
        self, pred: Callable[[], bool], what: str, timeout_s: float = WAIT_S
    ) -> None:
        deadline = time.monotonic() + timeout_s
        while not pred():
            if time.monotonic() > deadline:
                raise AssertionError(
                    f"timed out after {timeout_s} s waiting for {what}"
                )
            self.pump(5)


def _prime(sub: PoseSub, send: Callable[[], int], timeout_s: float = WAIT_S) -> None:
    """Send frames (``send`` returns the frame number) until the subscriber receives
    one: poses published before its connection completes are lost (ZeroMQ's slow
    joiner). Then one more, waited for, so every later pose arrives; forget what the
    subscriber received so far."""
    deadline = time.monotonic() + timeout_s
    while not sub.poses:
        assert time.monotonic() < deadline, "the pose stream never reached the SUB"
        send()
        sub.pump(20)
    last = send()
    sub.wait(lambda: sub.poses[-1].frame_id == last, "the last priming frame")
    sub.clear()


class VmcReceiver:
    """Collects VMC datagrams; splits them into frames at ``/VMC/Ext/T`` with
    python-osc's generic parser (``OscBundle`` / ``OscMessage``); state bundles
    (``/VMC/Ext/OK`` + ``/VMC/Ext/T`` only, sent before a calibration) go to
    :attr:`states`."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.port = int(sock.getsockname()[1])
        self.datagrams: list[bytes] = []
        self.frames: list[list[tuple[str, list[Any]]]] = []
        self.states: list[list[tuple[str, list[Any]]]] = []
        self.frame_datagrams: list[int] = []
        self._pending: list[tuple[str, list[Any]]] = []
        self._pending_dgrams = 0

    def pump(self, max_datagrams: int | None = None) -> None:
        """Read the datagrams waiting (the first one waits up to the timeout), at
        most ``max_datagrams`` when given. A loop that pumps while the daemon still
        sends must give a cap: on a loaded machine python-osc's parser can be slower
        than the daemon sends, and reading "until none is waiting" then never
        returns to the loop's deadline or predicate (a CI run hung here until
        pytest's 120 s timeout). Without a cap, for a drain after the sender stopped.
        """
        try:
            data = self.sock.recv(65536)
        except TimeoutError:
            return
        self._parse(data)
        left = -1 if max_datagrams is None else max_datagrams - 1
        while left != 0:
            left -= 1
            try:
                data = self.sock.recv(65536, socket.MSG_DONTWAIT)
            except (BlockingIOError, TimeoutError):
                return
            self._parse(data)

    def _parse(self, data: bytes) -> None:
        self.datagrams.append(data)
        self._pending_dgrams += 1
        bundle = OscBundle(data)
        for element in bundle:
            assert isinstance(element, OscMessage), "VMC bundles hold messages only"
            self._pending.append((element.address, list(element.params)))
            if element.address == vmc_out.TIME_ADDRESS:
                if any(a == vmc_out.ROOT_ADDRESS for a, _ in self._pending):
                    self.frames.append(self._pending)
                    self.frame_datagrams.append(self._pending_dgrams)
                else:  # a state bundle (OK + T, before a calibration): not a pose
                    self.states.append(self._pending)
                self._pending, self._pending_dgrams = [], 0

    def wait_frames(self, n: int, timeout_s: float = WAIT_S) -> None:
        deadline = time.monotonic() + timeout_s
        while len(self.frames) < n:
            if time.monotonic() > deadline:
                raise AssertionError(
                    f"timed out: {len(self.frames)} of {n} VMC frames received"
                )
            self.pump()


def _vmc_bones(frame: list[tuple[str, list[Any]]]) -> dict[str, np.ndarray]:
    """Bone name -> (7,) position xyz + quaternion xyzw, plus "root"."""
    out = {}
    for address, params in frame:
        if address in (vmc_out.ROOT_ADDRESS, vmc_out.BONE_ADDRESS):
            out[params[0]] = np.array(params[1:], dtype=np.float64)
    return out


def _vmc_quats(frame: list[tuple[str, list[Any]]]) -> np.ndarray:
    """(1 + bones, 4) xyzw: root then bones, in message order."""
    return np.array(
        [p[4:] for a, p in frame if a in (vmc_out.ROOT_ADDRESS, vmc_out.BONE_ADDRESS)]
    )


@pytest.fixture
def vmc(udp_socket: Callable[..., socket.socket]) -> VmcReceiver:
    return VmcReceiver(udp_socket(bind=True))


@pytest.fixture
def osc_source(udp_socket: Callable[..., socket.socket]) -> Callable[..., OscSource]:
    def make(live: Live, label_set_id: int = 1) -> OscSource:
        return OscSource(udp_socket(), live.udp("osc markers"), label_set_id, live)

    return make


def _solve_oracle(
    calibration: Path, frames: list[np.ndarray]
) -> tuple[list[Any], Retargeter]:
    """The BodySolver on the same frames, in the same order (copies per frame)."""
    rig = load_rig(EXACT_RIG)
    cal = load_calibration(calibration)
    solver = BodySolver(rig, cal, _take().labels)
    pose = solver.new_pose()
    out = []
    for markers in frames:
        solver.solve_frame(markers, pose)
        out.append(
            (
                pose.world_from_bone_quat.copy(),
                pose.rest_from_bone_quat.copy(),
                pose.root_pos.copy(),
                pose.bone_flags.copy(),
            )
        )
    return out, Retargeter(rig, cal, default_humanoid())


def _fit_oracle(calibration: Path, frames: list[np.ndarray]) -> list[tuple[Any, int]]:
    """The fit, as the daemon builds it (``make_body_solver("fit", ...)`` with the
    validator's limits), on the same frames in the same order: per frame its
    ``world_from_bone_quat`` (a copy) and frame flags."""
    from retargetd.daemon.body.method import make_body_solver
    from retargetd.daemon.validate.limits import JOINT_LIMITS_DEG
    from retargetd.daemon.validate.model import SEGMENT_KIND

    # the daemon's frame time: OscSource's source clock, frame number / RATE_HZ
    # (live.interval.frame_interval_s), one frame apart
    solver = make_body_solver(
        "fit", load_rig(EXACT_RIG), load_calibration(calibration), _take().labels,
        joint_limits=JOINT_LIMITS_DEG, segment_kind=SEGMENT_KIND, rate_hz=RATE_HZ,
    )  # fmt: skip
    pose = solver.new_pose()
    out = []
    for markers in frames:
        solver.solve_frame(markers, pose)
        out.append((pose.world_from_bone_quat.copy(), int(pose.frame_flags)))
    return out


def _json_strict(text: str) -> Any:
    def reject(name: str) -> Any:
        raise ValueError(f"not JSON: {name}")

    return json.loads(text, parse_constant=reject)


def _import_vmcp() -> tuple[Any, Any]:
    try:
        from osc4py3 import oscbuildparse
        from vmcp import events
    except ImportError as exc:  # the test extra is installed in CI
        if IN_CI:
            pytest.fail(f"vmcp/osc4py3 missing (CI=true: nothing may skip): {exc}")
        pytest.skip(f"vmcp/osc4py3 not installed: {exc}")
    return oscbuildparse, events


class _Streamer(threading.Thread):
    """Streams the T-pose hold at ~200 Hz until stopped (a live source)."""

    def __init__(self, src: Any) -> None:
        super().__init__(name="test-streamer", daemon=True)
        self.src = src
        self.stop_event = threading.Event()

    def run(self) -> None:
        hold = _take().markers_world[_take().base_pose_frames]
        k = 0
        while not self.stop_event.is_set():
            if k % 100 == 0:
                self.src.announce()
            self.src.send(hold[k % len(hold)])
            k += 1
            time.sleep(0.005)

    def stop(self) -> None:
        self.stop_event.set()
        self.join(timeout=2.0)
        assert not self.is_alive()


@pytest.fixture
def streamer() -> Iterator[Callable[[Any], _Streamer]]:
    """``streamer(source)``: the T-pose hold streamed at ~200 Hz on a thread until
    the test ends (or ``.stop()``)."""
    made: list[_Streamer] = []

    def make(src: Any) -> _Streamer:
        s = _Streamer(src)
        made.append(s)
        s.start()
        return s

    yield make
    for s in made:
        s.stop()
