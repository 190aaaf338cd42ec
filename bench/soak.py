"""A soak with faults (issue 12, item 7): the real PiG walk streamed at 240 Hz to a
``retargetd run`` process on loopback for ``--seconds`` (default 600) while
everything that goes wrong on a stage goes wrong. The walk is played forward, then
backward, and so on (:func:`walk_row`): never a jump from its end to its start.

Faults: 2 % extra malformed datagrams (mutations of valid ones, ``bench/fuzz.py``'s
mutator) on the marker input; 10 % of marker samples occluded in runs (a marker
disappears for 20-250 ms, the span of a typical occlusion by a limb), half of them
sent as (0, 0, 0) instead of NaN; the source restarting every 30 s (a 250 ms pause,
frame numbers from 0, labels announced again); a spoofed frame number (2^62) and a
spoofed label announcement (the names under the id in use rotated by one) every 5 s,
alternately; the VMC (engine) receiver absent half the time (bound 15 s, closed
15 s); a control command every 10 s (status, reload, an unknown command); a
recording running the whole time (``ctl record start`` into the daemon's working
directory's ``recordings/``); the live validator on; the face on when the ICT
training set is in ``../shared/datasets``.

Issue 30's attacks (``--no-attacks``: off), the daemon's control socket under CURVE
and its show control under a token: 50 ``record start``/``stop`` pairs back to back
before the recording starts (one file; the rest refused as rate limited); then, one
every 1.5 s in turn, 10 show-control bundles of 5,000 token-less messages, a bundle
nested 6 deep, a token-less message, a 10 MB control request (answered), a plain
client, an unlisted key and a wrong server key on control (one handshake each), and
three frames numbered from 2^62 back to back; and every 2.5 s a burst of 1-50 bad
frames in the walk's place, in turn every marker on one point, all zeros, left and
right swapped, every marker at 1e30.

Pass (all printed, exit 1 if any fails):

- up throughout: every control request answered, the process alive at the end;
- RSS growth <= 10 MB after warm-up (the first 20 % of the run, at least 10 s);
- every datagram accounted for exactly: sent = counted by reason (``drops``) +
  ``labels_taken`` (+ kernel drops), and ``frames_in = frames_solved + stale +
  unsolved``;
- no gap in the pose stream longer than 100 ms except where the source paused
  (restarts) or a spoofed label announcement held the id's frames until the source
  announced its names again (listed apart: ``label_conflict`` drops, by design), or
  where the daemon's loop was runnable without a CPU (``host_late``: every loop stall
  in the gap ``unscheduled``, from its thread's schedstat, ``daemon/live/stalls.py``;
  a stall blocked on the GIL or a lock, or a gap no stall explains, stays a failure);
- the recording replays to the same poses: its marker packets, fed through the live
  decoders and a fresh body solver of the daemon's method (the fit by default; reset
  where the daemon reset its own), give the recorded ``/poses`` (float32-equal);
- every attack counted as what it is (``attack_accounting``), and the pose back within
  0.25 s of every burst's last bad frame: every bone within 2 deg and the root within
  2 cm of a second solver's pose for the same frame, fed the walk's own frames in the
  burst's place (the pose just before a burst would not do: the walk moves on).

Run from the repository root::

    python bench/soak.py --minutes 10     # 10 minutes (the default)
    python bench/soak.py --seconds 60     # the CI version (tests/daemon/test_soak.py)
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import random
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import fuzz

LOCALHOST = "127.0.0.1"
RATE_HZ = 240.0
#: The daemon's ``[validate] rate_hz`` here (its default): the rate of the frame
#: numbers, which the fit's frame times come from (``live.interval.frame_interval_s``).
VALIDATE_RATE_HZ = 240.0
LABEL_SET_ID = 1
#: The pass thresholds (issue 12 item 7).
MAX_GAP_S = 0.100
MAX_RSS_GROWTH_MB = 10.0
#: A marker occlusion lasts 20-250 ms: a limb passing a camera's line of sight at
#: walking speed (~1.4 m/s) covers a 14 mm marker plus a few cm of ray in that time.
OCCLUSION_S = (0.020, 0.250)
SPOOF_FRAME = 2**62
#: Issue 30's attacks, one at a time in this order: show-control bundles of 5,000
#: token-less messages (amplification), bundles nested 6 deep, a token-less message,
#: a 10 MB control request, a plain client, an unlisted key and a wrong server key
#: on the CURVE control socket, three frames numbered from 2^62 back to back.
ATTACKS = ("amplify", "nested", "no_token", "oversize", "plain_client",
           "unlisted_key", "wrong_server_key", "spoof_triple")  # fmt: skip
#: The whole ZMTP 3.1 greeting of a client without CURVE (mechanism NULL).
PLAIN_GREETING = (
    b"\xff" + bytes(8) + b"\x7f" + b"\x03\x01" + b"NULL".ljust(20, b"\0") + bytes(32)
)
#: Bad frames in bursts: every marker on one point (the visible ones' mean), all
#: zeros (occluded: nothing seen), left and right labels swapped, every marker at
#: 1e30 (implausible: occluded and counted).
BURSTS = ("collapsed", "zeros", "swapped", "far")
#: The pose is back after a burst when every bone is within this of the intact
#: solve of the same frame (the walk's own frames solved as if the burst had not
#: happened), and the root within ``RECOVERED_M``; it must be within MAX_RECOVERY_S
#: of the burst's last bad frame.
RECOVERED_DEG = 2.0
RECOVERED_M = 0.02
MAX_RECOVERY_S = 0.25
#: Show-control token of the soak's daemon (with attacks).
TOKEN = "soak-token-0123456789abcdef"
#: ``ctl record start``/``stop`` pairs sent back to back before the soak's recording.
CHURN = 50
#: The largest IPv4 UDP payload (65,535 - 8 UDP - 20 IP header bytes).
UDP_MAX = 65_507


@dataclass(slots=True)
class Faults:
    """What goes wrong, and how often."""

    malformed: float = 0.02
    dropout: float = 0.10
    zeros: float = 0.5
    restart_every_s: float = 30.0
    restart_pause_s: float = 0.25
    spoof_every_s: float = 5.0
    vmc_toggle_s: float = 15.0
    control_every_s: float = 10.0
    labels_every_s: float = 1.0
    #: fuzz mode: mutated inputs per second on every input in the flood window.
    flood_hz: float = 0.0
    #: fuzz mode: label announcements among the mutated OSC and ZeroMQ inputs.
    flood_labels: bool = True
    flood_window: tuple[float, float] = (0.0, 0.0)  # fractions of the run
    #: issue 30's attacks (show-control token and CURVE control on in the daemon):
    #: one every ``attack_every_s``, the kinds in turn (:data:`ATTACKS`).
    attacks: bool = False
    attack_every_s: float = 1.5
    #: bursts of bad frames (:data:`BURSTS`, in turn) sent in place of the walk's,
    #: 1-50 frames long, one every ``burst_every_s`` (with ``attacks``).
    burst_every_s: float = 2.5
    burst_frames: tuple[int, int] = (1, 50)


@dataclass(slots=True)
class Sent:
    """What the driver sent, per destination."""

    osc: int = 0
    osc_frames: int = 0
    osc_malformed: int = 0
    osc_labels: int = 0
    spoofed_frames: int = 0
    spoofed_labels: int = 0
    zmq: int = 0
    show: int = 0
    control: int = 0
    control_replies: int = 0
    pauses: list[tuple[int, int]] = field(default_factory=list)  # (start, end) ns
    frame_ns: list[int] = field(default_factory=list)  # each good frame's send
    spoof_labels_ns: list[int] = field(default_factory=list)
    labels_ns: list[int] = field(default_factory=list)
    spoofed_triples: int = 0
    attacks: dict[str, int] = field(default_factory=dict)  # by kind
    churn_refused: int = 0  # record starts refused as rate limited
    churn_started: int = 0
    churn_s: float = 0.0  # how long the pairs took (one start a second allowed)
    bursts: list[tuple[str, int, int, int]] = field(default_factory=list)
    burst_frames: int = 0
    far_markers: int = 0  # markers sent at 1e30
    #: bad datagram -> the intact ones it replaced, in order (the replay's oracle)
    intact: dict[bytes, list[bytes]] = field(default_factory=dict)
    oversize_replies: list[float] = field(default_factory=list)  # seconds


def _amplification_bundle(n: int) -> bytes:
    """An OSC bundle of ``n`` 8-byte token-less messages (5,000: 60 KB): issue 30's
    show-control amplification (``bench/flood.py``)."""
    m = b"/x\0\0,\0\0\0"
    return b"#bundle\0" + (1).to_bytes(8, "big") + (len(m).to_bytes(4, "big") + m) * n


def walk_row(k: int, n_rows: int) -> int:
    """The walk's row for the ``k``-th frame sent: the take forward, then backward,
    and so on (a take looped from its end to its start would move the performer
    back ~3.5 m in one frame every 1.3 s at 240 Hz, a teleport that disturbs the
    second solver of :func:`replay_check` as much as the daemon and is no burst)."""
    period = 2 * (n_rows - 1)
    j = k % period if period else 0
    return j if j < n_rows else period - j


def occlusion_mask(rng: np.random.Generator, n: int, m: int, fraction: float) -> Any:
    """(n, m) bool, True = occluded: runs of OCCLUSION_S at RATE_HZ, ~``fraction``."""
    mask = np.zeros((n, m), dtype=bool)
    lo, hi = (max(1, round(s * RATE_HZ)) for s in OCCLUSION_S)
    mean_run = 0.5 * (lo + hi)
    for j in range(m):
        for _ in range(round(fraction * n / mean_run)):
            start = int(rng.integers(0, n))
            mask[start : start + int(rng.integers(lo, hi + 1)), j] = True
    return mask


def _other_names(data: bytes, labels: Any) -> bool:
    """Whether ``data`` is a well-formed announcement of other names under the id in
    use (a corrupted one looks like a spoofed one)."""
    from retargetd.protocols import osc_in
    from retargetd.protocols.errors import DecodeError

    if not data.startswith(b"/rtd/labels\0"):
        return False
    try:
        got = osc_in.decode_labels(data)
    except DecodeError:
        return False
    return bool(got.id == labels.id and got.labels != labels.labels)


def handshake_request(sock: Any, data: bytes, timeout_ms: int) -> bytes | None:
    """Send ``data`` on a REQ socket whose handshake may fail, and wait
    ``timeout_ms`` for a reply; the reply, or None. Never blocks longer: a REQ
    socket with reconnection off (``RECONNECT_IVL`` -1) whose CURVE handshake
    failed before the send has no peer left, and a plain ``send`` waits for one
    forever (measured, libzmq 4.3.5: 87 of 200 tries with a wrong server key had
    failed before an immediate send; the 10-minute soak's attack thread hung so
    after its 27th wrong server key, until the context's termination raised
    ``ContextTerminated`` in it). Such a send gives up: the handshake failed, as the
    attack meant, and the daemon counted it."""
    import zmq

    sock.setsockopt(zmq.SNDTIMEO, timeout_ms)
    try:
        sock.send(data)
    except zmq.Again:
        return None
    if sock.poll(timeout_ms):
        return bytes(sock.recv())
    return None


def _rss_kb(pid: int) -> int:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    return 0


def _config(
    calibration: Path, vmc_port: int, face_npz: Path | None, extra: str = "",
    keys: Path | None = None,
) -> str:  # fmt: skip
    """The soak daemon's config; with ``keys`` (attacks) control is CURVE (the
    driver holds ``operator``) and show control takes :data:`TOKEN`."""
    q = json.dumps
    control = ""
    show = ""
    if keys is not None:
        control = (
            f"secret_key = {q(str(keys / 'daemon.key_secret'))}\n"
            f"client_keys = [{q(str(keys / 'operator.key'))}]\n"
        )
        show = f'token = "{TOKEN}"\n'
    face = (
        f'[face]\nenabled = true\nconfig = "arkit52"\ntraining = {q(str(face_npz))}\n'
        if face_npz is not None
        else ""
    )
    return f"""[performer]
rig = "plug-in-gait"
calibration = {q(str(calibration))}
[input.osc]
port = 0
[input.zmq]
mode = "pull"
endpoint = "tcp://{LOCALHOST}:*"
[output.vmc]
host = "{LOCALHOST}"
port = {vmc_port}
[output.pose]
endpoint = "tcp://{LOCALHOST}:*"
sndhwm = 100000
[control]
endpoint = "tcp://{LOCALHOST}:*"
{control}[show_control]
port = 0
{show}[loop]
stats_interval_s = 5.0
[validate]
enabled = true
{face}{extra}"""


class DaemonProcess:
    """``retargetd run --config FILE`` in ``cwd``; stdout and stderr into a log."""

    def __init__(self, config: Path, cwd: Path, keys: Path | None = None) -> None:
        #: (secret key, server key) files of a CURVE control socket's client
        self.keys = (
            (str(keys / "operator.key_secret"), str(keys / "daemon.key"))
            if keys is not None
            else (None, None)
        )
        self.log = cwd / "daemon.log"
        self._log = self.log.open("w")
        cmd = [sys.executable, "-m", "retargetd.daemon", "run", "--config", str(config)]
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        self.proc = subprocess.Popen(
            cmd, cwd=cwd, env=env, stdout=self._log, stderr=subprocess.STDOUT,
            start_new_session=True,
        )  # fmt: skip
        self.endpoints: dict[str, str] = {}
        try:
            self._wait_serving()
        except BaseException:  # not left running (nor its log open) on the way out
            self.kill()
            raise

    def _wait_serving(self) -> None:
        # A first start on a fresh machine compiles the kernels: 82 s on a quiet
        # 2-core VM (measured), so a slow runner gets several times that.
        deadline = time.monotonic() + 300.0
        import re

        pattern = re.compile(r"^listening on (\S+)(?: \(.*\))?: (.+)$")
        while "control" not in self.endpoints:
            if self.proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"daemon not ready:\n{self.log.read_text()}")
            for line in self.log.read_text().splitlines():
                m = pattern.match(line)
                if m:
                    self.endpoints[m.group(2)] = m.group(1)
            time.sleep(0.05)
        while self.ctl({"cmd": "status"}, 500) is None:
            if self.proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"daemon not serving:\n{self.log.read_text()}")

    def kill(self) -> None:
        """SIGKILL the daemon's process group, reap it, close its log."""
        if self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(timeout=10.0)
        self._log.close()

    def udp(self, what: str) -> tuple[str, int]:
        host, port = self.endpoints[what].removeprefix("udp://").rsplit(":", 1)
        return host, int(port)

    def ctl(self, req: dict[str, Any], timeout_ms: int = 2000) -> dict[str, Any] | None:
        from retargetd.daemon.cli.ctl import request

        return request(self.endpoints["control"], req, timeout_ms, *self.keys)

    def status(self) -> dict[str, Any]:
        reply = self.ctl({"cmd": "status"}, 5000)
        if reply is None or not reply.get("ok"):
            raise RuntimeError(f"no status reply: {reply}")
        return dict(reply["status"])

    def stop(self) -> int:
        """SIGINT (closes the recording), then SIGKILL after 20 s; the exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        self._log.close()
        return int(self.proc.returncode)


def face_training(walk: fuzz.Walk, folder: Path) -> tuple[Path, fuzz.Walk] | None:
    """The ICT face riding the walk's head (``bench_latency``'s face stream), saved
    as a training set; None when the ICT data is absent."""
    try:
        import bench_latency as bl

        from retargetd.replay.takes import load_take

        take = load_take(fuzz.PIG_MOTION)
        training, labels, positions = bl._face_stream(take, np.random.default_rng(0))
    except (OSError, ValueError, ImportError, KeyError) as exc:
        print(f"face off: no training set ({type(exc).__name__}: {exc})")
        return None
    path = folder / "face.npz"
    training.save(path)
    return path, fuzz.Walk(tuple(labels), np.asarray(positions), walk.rate_hz)


class Driver:
    """The sender, receivers and fault injectors of one run."""

    def __init__(
        self, daemon: DaemonProcess, walk: fuzz.Walk, seconds: float, faults: Faults,
        vmc_port: int, seed: int = 0, keys: Path | None = None,
    ) -> None:  # fmt: skip
        import zmq

        self.d = daemon
        self.walk = walk
        self.seconds = seconds
        self.f = faults
        self.vmc_port = vmc_port
        self.rng = np.random.default_rng(seed)
        self.r = random.Random(seed)
        self.sent = Sent()
        self.stop = threading.Event()
        self.errors: list[str] = []
        self.ctx = zmq.Context()
        self.pose_ns: list[int] = []
        self.pose_sent_ns: list[int] = []  # each one's own sent_ns (its header)
        self.rss: list[tuple[float, int]] = []
        self.vmc_datagrams = 0
        self.flood_ns = (0, 0)
        self._lock = threading.Lock()
        self.keys = keys
        self.t_end_ns = 0
        # the walk's left and right markers swapped (L... <-> R...)
        index = {name: i for i, name in enumerate(walk.labels)}
        self.swap = np.arange(len(walk.labels))
        for i, name in enumerate(walk.labels):
            twin = {"L": "R", "R": "L"}.get(name[:1], "") + name[1:]
            if twin in index and twin != name:
                self.swap[i] = index[twin]

    # ---- threads ----------------------------------------------------------------

    def _sub(self) -> None:
        import zmq

        from retargetd.protocols import pose_stream

        sub = self.ctx.socket(zmq.SUB)
        sub.setsockopt(zmq.LINGER, 0)
        sub.setsockopt(zmq.RCVHWM, 0)
        sub.setsockopt(zmq.SUBSCRIBE, pose_stream.DATA_MAGIC)
        sub.connect(self.d.endpoints["zmq poses"])
        at = pose_stream.SENT_NS_OFFSET  # the header's sent_ns, int64 LE
        try:
            while not self.stop.is_set():
                if sub.poll(50):
                    while True:
                        try:
                            parts = sub.recv_multipart(zmq.NOBLOCK)
                        except zmq.Again:
                            break
                        self.pose_ns.append(time.monotonic_ns())
                        self.pose_sent_ns.append(
                            int.from_bytes(parts[0][at : at + 8], "little")
                        )
        finally:
            sub.close()

    def _vmc(self) -> None:
        """The engine receiver: bound for ``vmc_toggle_s``, absent as long."""
        present = True
        while not self.stop.is_set():
            until = time.monotonic() + self.f.vmc_toggle_s
            if present:
                sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                sock.bind((LOCALHOST, self.vmc_port))
                sock.settimeout(0.05)
                try:
                    while time.monotonic() < until and not self.stop.is_set():
                        try:
                            sock.recv(65536)
                            self.vmc_datagrams += 1
                        except TimeoutError:
                            pass
                finally:
                    sock.close()
            else:
                self.stop.wait(max(0.0, until - time.monotonic()))
            present = not present

    def _rss(self) -> None:
        t0 = time.monotonic()
        while not self.stop.wait(1.0):
            try:
                self.rss.append((time.monotonic() - t0, _rss_kb(self.d.proc.pid)))
            except OSError:
                self.errors.append("daemon process vanished")
                return

    def ctl(self, req: dict[str, Any]) -> dict[str, Any] | None:
        with self._lock:
            self.sent.control += 1
            reply = self.d.ctl(req, 5000)
            if reply is not None:
                self.sent.control_replies += 1
            else:
                self.errors.append(f"no reply to {req}")
            return reply

    def _control(self) -> None:
        cycle = [{"cmd": "status"}, {"cmd": "reload"}, {"cmd": "no-such-command"}]
        k = 0
        while not self.stop.wait(self.f.control_every_s):
            self.ctl(cycle[k % len(cycle)])
            k += 1

    def _flood(self, t_start: float, t_end: float) -> None:
        """Mutated inputs at ``flood_hz`` each on OSC, ZeroMQ, show control and
        control (REQ), from ``t_start`` to ``t_end`` (monotonic s)."""
        import zmq

        from retargetd.protocols import osc_in, zmq_wire
        from retargetd.protocols.marker_input import LabelSet

        labels = LabelSet(LABEL_SET_ID, self.walk.labels)
        rows = fuzz._rows(self.walk, 8)
        osc_corpus = [
            osc_in.encode_compact_frame(i, i / RATE_HZ, LABEL_SET_ID, row)
            for i, row in enumerate(rows)
        ]
        if self.f.flood_labels:
            osc_corpus += [
                osc_in.encode_labels(LabelSet(i, ls))
                for i, ls in fuzz._label_variants(labels.labels)
            ]
        zmq_corpus = [
            zmq_wire.encode_zmq_frame(i, i / RATE_HZ, LABEL_SET_ID, row)
            for i, row in enumerate(rows)
        ]
        if self.f.flood_labels:
            zmq_corpus.append(zmq_wire.encode_zmq_labels(labels))
        show_corpus = fuzz.show_control_corpus()
        ctl_corpus = fuzz.control_corpus()
        udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        push = self.ctx.socket(zmq.PUSH)
        push.setsockopt(zmq.LINGER, 0)
        push.setsockopt(zmq.SNDHWM, 0)
        push.connect(self.d.endpoints["zmq markers"])
        req = self.ctx.socket(zmq.REQ)
        req.setsockopt(zmq.LINGER, 0)
        req.setsockopt(zmq.RCVTIMEO, 5000)
        req.connect(self.d.endpoints["control"])
        osc_addr, show_addr = self.d.udp("osc markers"), self.d.udp("show control")
        period = 1.0 / self.f.flood_hz
        r = random.Random(1)
        while time.monotonic() < t_start and not self.stop.is_set():
            time.sleep(0.01)
        self.flood_ns = (time.monotonic_ns(), 0)
        t_next = time.monotonic()
        k = 0
        try:
            while time.monotonic() < t_end and not self.stop.is_set():
                with self._lock:
                    udp.sendto(fuzz.mutate(r, osc_corpus)[:UDP_MAX], osc_addr)
                    self.sent.osc += 1
                push.send_multipart(fuzz.mutate_parts(r, zmq_corpus))
                self.sent.zmq += 1
                udp.sendto(fuzz.mutate(r, show_corpus)[:UDP_MAX], show_addr)
                self.sent.show += 1
                if k % 10 == 0:  # REQ: one at a time, each answered
                    n_parts = r.choice((1, 1, 1, 2, 3))
                    req.send_multipart(
                        [fuzz.mutate(r, ctl_corpus) for _ in range(n_parts)]
                    )
                    self.sent.control += 1
                    try:
                        json.loads(req.recv())
                        self.sent.control_replies += 1
                    except zmq.Again:
                        self.errors.append("a flood control request got no reply")
                        break
                k += 1
                t_next += period
                wait = t_next - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
        finally:
            self.flood_ns = (self.flood_ns[0], time.monotonic_ns())
            udp.close()
            push.close()
            req.close()

    def _attack(self, kind: str) -> None:
        """One of :data:`ATTACKS` (``kind``), counted in ``sent.attacks``."""
        import zmq

        from retargetd.daemon.live.surface import curve_client
        from retargetd.protocols import osc_in
        from retargetd.protocols.osc_wire import build_bundle, build_message

        s = self.sent
        s.attacks[kind] = s.attacks.get(kind, 0) + 1
        if kind in ("amplify", "nested", "no_token"):
            if kind == "amplify":  # 5,000 token-less messages (60 KB), 10 at once
                data, n = _amplification_bundle(5000), 10
            elif kind == "nested":  # a token-bearing message under 6 bundles
                data = build_message(f"/{TOKEN}/VMC/Ext/Set/Calib/Ready", "", [])
                for _ in range(6):
                    data = build_bundle([data])
                n = 1
            else:
                data, n = build_message("/rtd/reload", "", []), 1
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
                for _ in range(n):
                    udp.sendto(data, self.d.udp("show control"))
            with self._lock:
                s.show += n
            s.attacks[kind] += n - 1
            return
        if kind == "spoof_triple":  # issue 30: three frames from 2^62, back to back
            row = self.walk.positions[0]
            with self._lock, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
                for i in range(3):
                    data = osc_in.encode_compact_frame(SPOOF_FRAME + i, 0.0, 1, row)
                    udp.sendto(data, self.d.udp("osc markers"))
                    s.osc += 1
                s.spoofed_triples += 1
            return
        if kind == "oversize":  # a 10 MB request from a listed key: answered
            t0 = time.monotonic()
            reply = self.ctl({"cmd": "status", "pad": " " * 10_000_000})
            if reply is not None:
                s.oversize_replies.append(time.monotonic() - t0)
                if reply.get("ok") is not False or "too large" not in reply["error"]:
                    self.errors.append(f"oversize request answered {reply}")
            return
        if kind == "plain_client":  # a client without CURVE: its whole greeting
            self._plain_client(self.d.endpoints["control"])
            return
        # a failed CURVE handshake on control: one try each (no reconnect)
        sock = self.ctx.socket(zmq.REQ)
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.RECONNECT_IVL, -1)
        keys = self.keys
        assert keys is not None
        if kind == "unlisted_key":
            curve_client(sock, keys / "intruder.key_secret", keys / "daemon.key")
        elif kind == "wrong_server_key":
            curve_client(sock, keys / "operator.key_secret", keys / "intruder.key")
        sock.connect(self.d.endpoints["control"])
        try:
            if handshake_request(sock, b'{"cmd": "calibrate"}', 300) is not None:
                self.errors.append(f"a {kind} control client got a reply")
        finally:
            sock.close()

    def _plain_client(self, endpoint: str) -> None:
        """The whole ZMTP greeting of a client without CURVE in one write, then wait
        for the daemon to hang up: always ``plain_client``. (A plain libzmq client
        hangs up itself when it reads the daemon's greeting first, before sending its
        mechanism: the daemon sees a connection closed in the greeting, ``other``;
        a race, ``daemon/live/watch.py``.)"""
        host, _, port = endpoint.removeprefix("tcp://").rpartition(":")
        try:
            with socket.create_connection((host, int(port)), timeout=2.0) as tcp:
                tcp.sendall(PLAIN_GREETING)
                while tcp.recv(256):  # the daemon's greeting, then its hang-up
                    pass
        except OSError as exc:  # (a reset is a hang-up too)
            if not isinstance(exc, ConnectionResetError):
                self.errors.append(f"plain client: {exc}")

    def _attacks(self) -> None:
        k = 0
        while not self.stop.wait(self.f.attack_every_s):
            if time.monotonic_ns() > self.t_end_ns - 2_000_000_000:
                continue  # the last 2 s quiet: every attack counted by the end
            self._attack(ATTACKS[k % len(ATTACKS)])
            k += 1

    def churn(self) -> None:
        """``record start``/``stop`` pairs back to back (issue 30: 3,000 cycles
        wrote 3,000 files): the first starts, the rest refused as rate limited
        (on a host slow enough that the pairs outlast ``record.min_interval_s``,
        one more start a second is allowed: counted in ``churn_s``)."""
        t0 = time.monotonic()
        for i in range(CHURN):
            reply = self.ctl({"cmd": "record", "action": "start",
                              "path": f"churn-{i}.mcap"})  # fmt: skip
            if reply is not None and reply.get("ok"):
                self.sent.churn_started += 1
            elif reply is not None and "rate limited" in reply.get("error", ""):
                self.sent.churn_refused += 1
            self.ctl({"cmd": "record", "action": "stop"})
        self.sent.churn_s = time.monotonic() - t0

    def _bad_row(self, kind: str, row: np.ndarray) -> np.ndarray:
        """The burst ``kind``'s version of the walk's ``row`` (:data:`BURSTS`)."""
        if kind == "zeros":
            return np.zeros_like(row)
        if kind == "far":
            return np.full_like(row, 1e30)
        if kind == "swapped":
            return row[self.swap]
        bad = row.copy()  # collapsed: the visible markers all on their mean
        seen = np.isfinite(row).all(axis=1) & (row != 0.0).any(axis=1)
        if seen.any():
            bad[seen] = row[seen].mean(axis=0)
        return bad

    def _send(self) -> None:
        """The source: paced at RATE_HZ, with the faults."""
        from retargetd.protocols import osc_in
        from retargetd.protocols.marker_input import LabelSet

        f, s = self.f, self.sent
        pos = self.walk.positions
        n_rows, m = pos.shape[0], pos.shape[1]
        n_mask = int(RATE_HZ * 37)  # a period prime to the take's and the restarts'
        mask = occlusion_mask(self.rng, n_mask, m, f.dropout)
        zeros = self.rng.random((n_mask, m)) < f.zeros
        labels = LabelSet(LABEL_SET_ID, self.walk.labels)
        rotated = LabelSet(LABEL_SET_ID, labels.labels[1:] + labels.labels[:1])
        announce = osc_in.encode_labels(labels)
        spoof_announce = osc_in.encode_labels(rotated)
        corpus = [osc_in.encode_compact_frame(i, 0.0, 1, pos[i]) for i in range(8)]
        corpus.append(announce)
        udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        udp.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 1 << 20)
        addr = self.d.udp("osc markers")
        period_ns = int(1e9 / RATE_HZ)
        t0 = time.monotonic_ns()
        t_end = t0 + int(self.seconds * 1e9)
        next_labels = next_restart = next_spoof = t0
        next_restart = t0 + int(f.restart_every_s * 1e9)
        next_spoof = t0 + int(f.spoof_every_s * 1e9)
        spoof_kind = 0
        frame = 0
        k = 0
        t_next = t0
        row = np.empty((m, 3))
        next_burst = t0 + int(f.burst_every_s * 1e9)
        burst_left = burst_n = n_bursts = 0
        burst_kind, burst_t0 = "", 0

        def out(data: bytes) -> None:
            udp.sendto(data, addr)
            s.osc += 1

        try:
            while not self.stop.is_set():
                now = time.monotonic_ns()
                if now >= t_end:
                    break
                with self._lock:
                    if now >= next_restart:  # the source restarts: pause, from 0
                        pause_end = now + int(f.restart_pause_s * 1e9)
                        s.pauses.append((now, pause_end))
                        time.sleep(f.restart_pause_s)
                        frame, next_labels = 0, 0
                        next_restart += int(f.restart_every_s * 1e9)
                        t_next = time.monotonic_ns()
                        now = t_next
                    if now >= next_labels:
                        out(announce)
                        s.osc_labels += 1
                        s.labels_ns.append(now)
                        next_labels = now + int(f.labels_every_s * 1e9)
                    if now >= next_spoof:
                        if spoof_kind == 0:
                            row[:] = pos[walk_row(k, n_rows)]
                            out(osc_in.encode_compact_frame(SPOOF_FRAME, 0.0, 1, row))
                            s.spoofed_frames += 1
                        else:
                            out(spoof_announce)
                            s.spoofed_labels += 1
                            s.spoof_labels_ns.append(now)
                        spoof_kind ^= 1
                        next_spoof += int(f.spoof_every_s * 1e9)
                    j = k % n_mask
                    row[:] = pos[walk_row(k, n_rows)]
                    occ = mask[j]
                    row[occ & zeros[j]] = 0.0
                    row[occ & ~zeros[j]] = np.nan
                    data = osc_in.encode_compact_frame(frame, frame / RATE_HZ, 1, row)
                    if f.attacks and not burst_left and now >= next_burst:
                        burst_left = burst_n = self.r.randint(*f.burst_frames)
                        burst_kind = BURSTS[n_bursts % len(BURSTS)]
                        n_bursts += 1
                        burst_t0 = now
                        next_burst = now + int(f.burst_every_s * 1e9)
                    if burst_left:  # a bad frame in the walk's place
                        bad = osc_in.encode_compact_frame(
                            frame, frame / RATE_HZ, 1, self._bad_row(burst_kind, row)
                        )
                        s.intact.setdefault(bad, []).append(data)
                        data = bad
                        s.burst_frames += 1
                        s.far_markers += m if burst_kind == "far" else 0
                        burst_left -= 1
                        if not burst_left:
                            s.bursts.append(
                                (burst_kind, burst_n, burst_t0, time.monotonic_ns())
                            )
                    out(data)
                    s.osc_frames += 1
                    s.frame_ns.append(time.monotonic_ns())
                    if self.r.random() < f.malformed:
                        bad = fuzz.mutate(self.r, corpus)
                        out(bad)
                        s.osc_malformed += 1
                        if _other_names(bad, labels):  # a corrupted announcement
                            s.spoof_labels_ns.append(now)
                frame += 1
                k += 1
                t_next += period_ns
                wait = t_next - time.monotonic_ns()
                if wait > 0:
                    time.sleep(wait * 1e-9)
                elif wait < -period_ns:  # far behind: restart the schedule, no burst
                    t_next = time.monotonic_ns()
        finally:
            udp.close()

    # ---- the run ----------------------------------------------------------------

    def _guard(self, target: Any, *args: Any) -> None:
        """Run a thread's body; an exception is an error of the run, not silent."""
        try:
            target(*args)
        except Exception as exc:
            self.errors.append(f"{target.__name__}: {type(exc).__name__}: {exc}")

    def run(self) -> None:
        threads = [
            threading.Thread(
                target=self._guard, args=(fn,), daemon=True, name=fn.__name__
            )
            for fn in (self._sub, self._vmc, self._rss, self._control)
        ]
        if self.f.flood_hz > 0:
            now = time.monotonic()
            a, b = self.f.flood_window
            threads.append(
                threading.Thread(
                    target=self._guard,
                    args=(self._flood, now + a * self.seconds, now + b * self.seconds),
                    daemon=True,
                    name="_flood",
                )
            )
        if self.f.attacks:
            threads.append(
                threading.Thread(
                    target=self._guard,
                    args=(self._attacks,),
                    daemon=True,
                    name="_attacks",
                )
            )
        self.t_end_ns = time.monotonic_ns() + int((0.3 + self.seconds) * 1e9)
        for t in threads:
            t.start()
        time.sleep(0.3)  # the SUB connects (slow joiner) before the first frame
        self.t0_ns = time.monotonic_ns()
        try:
            self._send()
        finally:
            time.sleep(0.5)  # the last frames through
            self.t1_ns = time.monotonic_ns()
            self.stop.set()
            for t in threads:  # each blocking call of theirs is bounded (< 10 s)
                t.join(timeout=10.0)
                if t.is_alive():  # its socket closed under it below: said so
                    self.errors.append(f"{t.name} still running 10 s after the end")
            self.ctx.destroy(linger=0)


# ---- checks ----------------------------------------------------------------------


def accounting(status: dict[str, Any], sent: Sent) -> dict[str, Any]:
    """Sent against counted, per input; and the frame identity."""
    c = status["counters"]
    osc = dict(status["drops"]["osc"])
    markers_ignored = osc.pop("unknown_label", 0)
    kernel = status["kernel_drops"]["osc"] or 0
    counted = sum(osc.values()) + status["labels_taken"]["osc"]
    zmq = dict(status["drops"]["zmq"])
    zmq.pop("unknown_label", None)
    zmq_counted = sum(zmq.values()) + status["labels_taken"]["zmq"]
    frames_left = c["frames_in"] - c["frames_solved"] - c["stale"] - c["unsolved"]
    return {
        "osc_sent": sent.osc, "osc_counted": counted, "osc_kernel_drops": kernel,
        "osc_ok": sent.osc == counted + kernel,
        "zmq_sent": sent.zmq, "zmq_counted": zmq_counted,
        "zmq_disconnects": c["zmq_disconnects"],
        "zmq_ok": sent.zmq == zmq_counted,
        "show_sent": sent.show, "show_counted": c["show_control_in"],
        "show_kernel_drops": status["kernel_drops"]["show_control"] or 0,
        "show_ok": sent.show
        == c["show_control_in"] + (status["kernel_drops"]["show_control"] or 0),
        "frames_in": c["frames_in"], "frames_solved": c["frames_solved"],
        "stale": c["stale"], "unsolved": c["unsolved"],
        "frames_ok": frames_left == 0, "markers_ignored": markers_ignored,
        "drops": osc, "zmq_drops": zmq,
    }  # fmt: skip


def pose_gaps(
    pose_ns: list[int],
    sent: Sent,
    t0_ns: int,
    t1_ns: int,
    received: list[tuple[int, int]] | None = None,
    stalls: list[dict[str, Any]] | None = None,
) -> dict[str, list[float]]:
    """Gaps over MAX_GAP_S between poses (s), by cause.

    Args:
        pose_ns: when each pose was sent (the recorded ``sent_ns``, the daemon's
            clock: CLOCK_MONOTONIC, shared by every process of the host), else when
            the driver's SUB received it.
        sent: what the driver sent, with its own frame times.
        t0_ns, t1_ns: the run.
        received: (receive time, reason index) of every marker frame the daemon
            read, from the recording (None without one).
        stalls: the daemon's last loop stalls (its status's ``loop_stalls``
            ``recent``: ``end_ns``, ``ms``, ``why``), None without them.

    Returns:
        Gap lengths (s) under ``paused`` (a source restart's pause), ``bad_burst``
        (a burst of bad frames: frames with no marker seen stream no pose),
        ``source_stalled`` (the driver itself sent nothing for over MAX_GAP_S: the
        source paused), ``label_conflict`` (the frames read in the gap were held by
        a conflicting announcement of other names under the id in use, until the
        source announced its own again), ``restart_confirm`` (frames of a restarted
        source dropped until its new sequence was confirmed), ``loop_late`` (the
        daemon read nothing, or read and queued frames, in the gap: its loop was not
        scheduled in time, or was busy elsewhere; a failure like ``other``, since on
        a quiet host it is the daemon's, whatever the load says), ``host_late`` (a
        ``loop_late`` gap that the daemon's loop stalls in it explain, every one of
        them ``unscheduled``: its loop thread runnable without a CPU for at least
        half the stall, the host's, not a failure; printed with the load) and
        ``other`` (none of these: a failure).
    """
    from retargetd.protocols.marker_input import BACKWARDS, LABEL_CONFLICT

    t = np.asarray([x for x in pose_ns if t0_ns <= x <= t1_ns], dtype=np.int64)
    kinds = ("paused", "bad_burst", "source_stalled", "label_conflict",
             "restart_confirm")  # fmt: skip
    out: dict[str, list[float]] = {
        k: [] for k in (*kinds, "loop_late", "host_late", "other")
    }
    if len(t) < 2:
        out["other"].append((t1_ns - t0_ns) * 1e-9)
        return out
    slack = int(MAX_GAP_S * 1e9)
    frames = np.asarray(sent.frame_ns, dtype=np.int64)
    rx_t = np.asarray([x for x, _ in received or ()], dtype=np.int64)
    rx_code = np.asarray([c for _, c in received or ()], dtype=np.int64)
    for i in np.flatnonzero(np.diff(t) > slack):
        a, b = int(t[i]), int(t[i + 1])
        gap = round((b - a) * 1e-9, 3)
        inside = frames[(frames > a - slack) & (frames < b)]
        edges = np.concatenate([[a], inside, [b]])
        in_gap = (rx_t > a) & (rx_t < b)
        codes = rx_code[in_gap]
        if any(p0 - slack <= b and a <= p1 + slack for p0, p1 in sent.pauses):
            kind = "paused"
        elif any(b0 - slack <= b and a <= b1 + slack for _, _, b0, b1 in sent.bursts):
            kind = "bad_burst"  # the source sent frames with no marker to see
        elif np.diff(edges).max() > slack:
            kind = "source_stalled"
        elif received is None:
            kind = "other"
        elif codes.size and np.count_nonzero(codes == LABEL_CONFLICT) * 2 >= codes.size:
            kind = "label_conflict"
        elif codes.size and np.count_nonzero(codes == BACKWARDS) * 2 >= codes.size:
            kind = "restart_confirm"
        elif codes.size == 0 or (rx_t >= b).any():
            # read nothing while frames were sent, or read late: the host's only
            # if the loop's stalls in the gap were all the loop not scheduled
            kind = "host_late" if host_stalled(a, b, stalls) else "loop_late"
        else:
            kind = "other"
        out[kind].append(gap)
    return out


def host_stalled(a_ns: int, b_ns: int, stalls: list[dict[str, Any]] | None) -> bool:
    """The daemon's loop stalls overlapping ``a_ns``-``b_ns`` (each from its end
    less its length) explain a gap there as the host's: at least one, and every
    one ``unscheduled`` with at least half the gap's length (the loop thread
    runnable without a CPU for at least half of it)."""
    within = [
        st for st in stalls or ()
        if st["end_ns"] - st["ms"] * 1e6 <= b_ns and st["end_ns"] >= a_ns
    ]  # fmt: skip
    return bool(within) and all(
        st.get("why") == "unscheduled" and 2 * st["ms"] * 1e6 >= b_ns - a_ns
        for st in within
    )


def late_deliveries(
    received_ns: list[int], sent_ns: list[int]
) -> list[dict[str, float]]:
    """The gaps over MAX_GAP_S at the driver's SUB that the daemon did not send: two
    poses received that far apart whose own ``sent_ns`` (the daemon's clock, the
    same CLOCK_MONOTONIC) are at most MAX_GAP_S apart. The pose ending such a gap
    was delivered late (the daemon's ZeroMQ I/O thread or the driver's receiving
    thread not run in time: the host or the driver's own GIL), after the daemon
    sent it on time. Each: the gap at the SUB, the daemon's gap between the same two
    sends, and the later pose's delivery latency (s)."""
    rx = np.asarray(received_ns, dtype=np.int64)
    tx = np.asarray(sent_ns, dtype=np.int64)
    slack = int(MAX_GAP_S * 1e9)
    out = []
    for i in np.flatnonzero(np.diff(rx) > slack):
        sent_gap = int(tx[i + 1] - tx[i])
        if 0 < sent_gap <= slack:
            out.append({
                "gap_s": round((rx[i + 1] - rx[i]) * 1e-9, 3),
                "sent_gap_s": round(sent_gap * 1e-9, 3),
                "latency_s": round(int(rx[i + 1] - tx[i + 1]) * 1e-9, 3),
            })  # fmt: skip
    return out


def rss_growth(
    rss: list[tuple[float, int]], seconds: float
) -> tuple[float, float, float]:
    """(RSS after warm-up MB, max after MB, growth MB); warm-up 20 % (>= 10 s)."""
    warm = max(10.0, 0.2 * seconds) if seconds > 12.5 else 0.2 * seconds
    after = [kb for t, kb in rss if t >= warm]
    if not after:
        return math.nan, math.nan, math.nan
    base, peak = after[0] / 1024, max(after) / 1024
    return base, peak, peak - base


def replay_check(
    path: Path, calibration: Path, method: str = "fit",
    intact: dict[bytes, list[bytes]] | None = None,
) -> dict[str, Any]:  # fmt: skip
    """The recording's marker packets through the live decoders and a fresh body
    solver of the daemon's ``method`` (the default, the fit; reset where the daemon
    reset its own: restarts, new label sets, and the frame a pipeline rebuilt after
    a reload took over: its ``pipeline`` control event), solving exactly the frames the
    daemon solved (the recorded poses, matched by receive time, and the frames it
    solved with no marker seen, streaming no pose: its ``unseen`` control events),
    against the recorded ``/poses``.

    With ``intact`` (bad datagram -> the walk's datagrams it replaced, in order), a
    second solver gets the walk's own frames in the bad ones' place, as if no burst
    had happened: each streamed pose's largest bone angle (deg) and root distance (m)
    from it are returned as ``track`` [(receive ns, bad, deg, m)], and the bad
    packets' receive times as ``bad_rx``."""
    from retargetd.daemon.body.calibration import load_calibration
    from retargetd.daemon.body.method import make_body_solver
    from retargetd.daemon.body.rig import load_rig
    from retargetd.daemon.live.interval import frame_interval_s
    from retargetd.daemon.validate.limits import JOINT_LIMITS_DEG
    from retargetd.daemon.validate.model import SEGMENT_KIND
    from retargetd.protocols import osc_in, pose_stream
    from retargetd.protocols.errors import DecodeError
    from retargetd.protocols.marker_input import ACCEPTED, RESTART, MarkerStream
    from retargetd.replay import recording as rf

    substitute = {k: list(v) for k, v in (intact or {}).items()}
    rec = rf.read_recording(path)
    received: list[tuple[int, int]] = []
    poses: dict[int, Any] = {}
    for p in rec.packets(rf.POSES_TOPIC):
        if p.kind == rf.KIND_FRAME:
            msg = pose_stream.decode_pose(p.parts)
            poses[msg.received_ns] = msg
    pose_sent_ns = sorted(m.sent_ns for m in poses.values())
    events = list(rec.json(rf.CONTROL_TOPIC))
    # where the daemon swapped in a pipeline rebuilt off its loop after a reload
    # (live/rebuild.py): the receive time of the first frame it solved
    swaps = sorted(e["received_ns"] for e in events if e.get("event") == "pipeline")
    # frames the daemon solved with nothing seen (no pose streamed)
    unseen_rx = {e["received_ns"] for e in events if e.get("event") == "unseen"}
    rig = load_rig("plug-in-gait")
    cal = load_calibration(calibration)
    # [0]: the packets as received (the daemon's replay); [1]: the intact walk
    streams = [MarkerStream(), MarkerStream()]
    solvers: list[Any] = [None, None]
    out: list[Any] = [None, None]
    labels: tuple[str, ...] = ()
    worst_q = worst_p = 0.0
    n_compared = missing = unseen = 0
    first_diff: tuple[int, int] | None = None  # (receive ns, unseen solved before)
    track: list[tuple[int, bool, float, float]] = []
    bad_rx: list[int] = []
    r_i = 0
    last = (math.nan, -1, 0)
    for p in rec.packets():
        if p.input != "osc":
            continue
        while r_i < len(swaps) and swaps[r_i] <= p.t_ns:
            solvers, r_i = [None, None], r_i + 1  # the daemon rebuilt its pipeline
        if p.kind == rf.KIND_LABELS:
            for stream in streams:
                with contextlib.suppress(DecodeError):  # counted by the stream
                    stream.set_labels(osc_in.decode_labels(p.parts[0]), p.t_ns)
            continue
        data = bytes(p.parts[0])
        queue = substitute.get(data)
        good = queue.pop(0) if queue else data
        bad = good is not data
        if bad:
            bad_rx.append(p.t_ns)
        code = streams[0].feed(osc_in.decode_compact_frame, data, t_ns=p.t_ns)
        streams[1].feed(osc_in.decode_compact_frame, good, t_ns=p.t_ns)
        received.append((p.t_ns, code))
        if code not in (ACCEPTED, RESTART):
            continue
        if solvers[0] is None or streams[0].current.label_set.labels != labels:
            labels = streams[0].current.label_set.labels
            for i in range(2):
                solvers[i] = make_body_solver(
                    method, rig, cal, labels,
                    joint_limits=JOINT_LIMITS_DEG, segment_kind=SEGMENT_KIND,
                    rate_hz=VALIDATE_RATE_HZ,
                )  # fmt: skip
                out[i] = solvers[i].new_pose()
            last = (math.nan, -1, 0)  # a new pipeline: its first frame
        elif code == RESTART:
            for solver in solvers:
                solver.reset()
        frame = streams[0].current.frame
        msg = poses.pop(p.t_ns, None)
        if msg is None and p.t_ns not in unseen_rx:
            missing += 1  # stale (latest wins): the daemon did not solve it either
            continue
        # solved; with no marker seen (a burst of zeros or 1e30) without a pose
        dt, last = frame_interval_s(last, frame, p.t_ns, VALIDATE_RATE_HZ)
        pose = solvers[0].solve_frame(frame.markers_world, out[0], dt)
        twin = solvers[1].solve_frame(
            streams[1].current.frame.markers_world, out[1], dt
        )
        if msg is None:
            unseen += 1
            track.append((p.t_ns, bad, math.nan, math.nan))
            continue
        dq = np.abs(
            pose.world_from_bone_quat.astype(np.float32) - msg.world_from_bone_quat
        )
        if first_diff is None and float(dq.max()) > 1e-6:
            first_diff = (p.t_ns, unseen)
        dp = np.abs(pose.root_pos.astype(np.float32) - msg.root_pos_world)
        worst_q, worst_p = max(worst_q, float(dq.max())), max(worst_p, float(dp.max()))
        n_compared += 1
        if intact is not None:
            dot = np.abs(
                np.sum(msg.world_from_bone_quat * twin.world_from_bone_quat, 1)
            )
            deg = np.degrees(2.0 * np.arccos(np.clip(dot, 0.0, 1.0)))
            root = float(np.linalg.norm(msg.root_pos_world - twin.root_pos))
            track.append((p.t_ns, bad, float(np.nanmax(deg, initial=0.0)), root))
    return {
        "complete": rec.complete, "poses_compared": n_compared,
        "frames_not_solved": missing, "unseen_solved": unseen,
        "poses_unmatched": len(poses),
        "max_quat_diff": worst_q, "max_root_diff_m": worst_p,
        "ok": n_compared > 0 and not poses and worst_q <= 1e-6 and worst_p <= 1e-6,
        "received": received, "pose_sent_ns": pose_sent_ns, "track": track,
        "bad_rx": bad_rx, "first_diff": first_diff,
    }  # fmt: skip


def recovery(
    bursts: list[tuple[str, int, int, int]],
    track: list[tuple[int, bool, float, float]],
    bad_rx: list[int],
) -> list[dict[str, Any]]:
    """Per burst of bad frames: its kind and length, how long after its last bad
    frame was read the streamed pose was back (within RECOVERED_DEG / RECOVERED_M of
    the intact solve of the same frame; inf if not before the next burst), and the
    largest bone angle from the intact solve while it lasted."""
    t = np.asarray([x[0] for x in track], dtype=np.int64)
    flags = np.asarray([x[1] for x in track], dtype=bool)
    deg = np.asarray([x[2] for x in track])
    root = np.asarray([x[3] for x in track])
    rx = np.asarray(bad_rx, dtype=np.int64)
    out = []
    for i, (kind, n, t0, t1) in enumerate(bursts):
        nxt = bursts[i + 1][2] if i + 1 < len(bursts) else np.iinfo(np.int64).max
        mine = rx[(rx >= t0) & (rx <= t1 + 200_000_000) & (rx < nxt)]
        if not mine.size:  # (none of it reached the daemon: kernel drops)
            continue
        end = int(mine.max())
        after = (t > end) & (t < nxt) & ~flags
        back = after & (deg <= RECOVERED_DEG) & (root <= RECOVERED_M)
        rec_s = (int(t[back][0]) - end) * 1e-9 if back.any() else math.inf
        # (not back before the next burst: the whole span to it; int(inf) raised)
        stop = end + int(max(rec_s, 0) * 1e9) if math.isfinite(rec_s) else nxt
        during = (t >= int(mine.min())) & (t <= stop)
        worst = float(np.nanmax(deg[during], initial=0.0)) if during.any() else 0.0
        out.append({"kind": kind, "frames": n, "recovery_s": round(rec_s, 4),
                    "worst_deg": round(worst, 2)})  # fmt: skip
    return out


def attack_accounting(status: dict[str, Any], sent: Sent) -> dict[str, Any]:
    """Each attack against what the daemon counted for it: (sent, counted)."""
    refused = status["show_control"]["refused"]
    curve = status["curve_refused"].get("control", {})
    c = status["counters"]
    a = sent.attacks
    kernel = status["kernel_drops"]["show_control"] or 0
    pairs = {
        "too_many_messages": (a.get("amplify", 0), refused.get("too_many_messages", 0)),
        "nested_too_deep": (a.get("nested", 0), refused.get("nested_too_deep", 0)),
        "bad_token": (a.get("no_token", 0), refused.get("bad_token", 0)),
        "control_oversize": (a.get("oversize", 0), c["control_oversize"]),
        **{k: (a.get(k, 0), curve.get(k, 0))
           for k in ("plain_client", "unlisted_key", "wrong_server_key")},
        "record_rate_limited": (CHURN - sent.churn_started, sent.churn_refused),
        "implausible_markers": (sent.far_markers, c["implausible_markers"]),
    }  # fmt: skip
    ok = all(
        got == want
        or (k in ("too_many_messages", "nested_too_deep", "bad_token")
            and want - kernel <= got <= want)
        or (k == "implausible_markers" and got >= want)  # + mutated frames' markers
        for k, (want, got) in pairs.items()
    )  # fmt: skip
    return {
        # one start, and one more per record.min_interval_s (1 s) the pairs lasted
        "pairs": pairs,
        "ok": ok and 1 <= sent.churn_started <= 1 + int(sent.churn_s),
        "churn_started": sent.churn_started, "rate_limited": c["rate_limited"],
        "spoofed_triples": sent.spoofed_triples,
    }  # fmt: skip


# ---- main ------------------------------------------------------------------------


def run(
    seconds: float, faults: Faults, *, face: bool = True, record: bool = True,
    folder: Path | None = None, seed: int = 0,
) -> dict[str, Any]:  # fmt: skip
    """One soak; returns the figures and the pass flags."""
    with tempfile.TemporaryDirectory(prefix="soak_") as tmp_name:
        tmp = folder or Path(tmp_name)
        calibration = fuzz.calibrate_pig(tmp)
        walk = fuzz.load_walk()
        face_npz = None
        if face:
            got = face_training(walk, tmp)
            if got is not None:
                face_npz, walk = got
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
            probe.bind((LOCALHOST, 0))
            vmc_port = int(probe.getsockname()[1])
        config = tmp / "soak.toml"
        keys = None
        if faults.attacks:  # CURVE control: the driver is "operator"
            from retargetd.daemon.live.surface import write_keypair

            keys = tmp / "keys"
            keys.mkdir()
            for name in ("daemon", "operator", "intruder"):
                write_keypair(keys, name)
        config.write_text(_config(calibration, vmc_port, face_npz, keys=keys))
        daemon = DaemonProcess(config, tmp, keys)
        rec_path = tmp / "recordings" / "soak.mcap"
        result: dict[str, Any] = {"seconds": seconds, "face": face_npz is not None,
                                  "load_before": os.getloadavg()}  # fmt: skip
        try:
            driver = Driver(daemon, walk, seconds, faults, vmc_port, seed, keys)
            if faults.attacks:
                driver.churn()
                time.sleep(1.05)  # past record.min_interval_s: the soak's recording
            if record:
                rec_path.parent.mkdir(exist_ok=True)
                reply = driver.ctl(
                    {"cmd": "record", "action": "start", "path": str(rec_path)}
                )
                if not reply or not reply.get("ok"):
                    raise RuntimeError(f"record start failed: {reply}")
            driver.run()
            alive = daemon.proc.poll() is None
            status = daemon.status()
            driver.sent.control += 1
            driver.sent.control_replies += 1
            if record:
                driver.ctl({"cmd": "record", "action": "stop"})
                deadline = time.monotonic() + 20
                while (
                    daemon.status()["record"]["finishing"]
                    and time.monotonic() < deadline
                ):
                    time.sleep(0.1)
        finally:
            rc = daemon.stop()
        # the stalls' log lines (rate limited per phase): own work or waiting, ms
        log = daemon.log.read_text().splitlines()
        stall_lines = [ln for ln in log if ln.startswith("loop: ")]
        sent = driver.sent
        result.update(
            alive=alive, rc=rc, errors=driver.errors,
            control_sent=sent.control, control_replies=sent.control_replies,
            sent={k: v for k, v in vars_of(sent).items() if isinstance(v, int)},
            accounting=accounting(status, driver.sent),
            counters=status["counters"],
            loop_stalls=status.get("loop_stalls"),  # phases over 50 ms (stalls.py)
            loop_stall_lines=stall_lines,
            gaps_sub=pose_gaps(driver.pose_ns, driver.sent, driver.t0_ns, driver.t1_ns),
            # SUB gaps the daemon did not send: delivered late after a timely send
            late_deliveries=late_deliveries(driver.pose_ns, driver.pose_sent_ns),
            poses=len(driver.pose_ns),
            pose_rate_hz=len(driver.pose_ns) / ((driver.t1_ns - driver.t0_ns) * 1e-9),
            vmc_datagrams=driver.vmc_datagrams,
            load_after=os.getloadavg(),
        )  # fmt: skip
        base, peak, growth = rss_growth(driver.rss, seconds)
        result["rss_mb"] = {
            "after_warmup": base,
            "max": peak,
            "growth": growth,
            "first": driver.rss[0][1] / 1024 if driver.rss else None,
        }
        result["rss_series_mb"] = [round(kb / 1024, 1) for _, kb in driver.rss]
        result["pose_rate_phases"] = phase_rates(driver)
        result["rss_phases_mb"] = phase_rss(driver)
        if record:
            replay = replay_check(
                rec_path, calibration,
                intact=sent.intact if faults.attacks else None,
            )  # fmt: skip
            received = replay.pop("received")
            track, bad_rx = replay.pop("track"), replay.pop("bad_rx")
            if faults.attacks:
                result["recovery"] = recovery(sent.bursts, track, bad_rx)
            result["gaps"] = pose_gaps(
                replay.pop("pose_sent_ns"), sent, driver.t0_ns, driver.t1_ns, received,
                (status.get("loop_stalls") or {}).get("recent"),
            )  # fmt: skip
            result["replay"] = replay
        else:
            result["gaps"] = result["gaps_sub"]
        a = result["accounting"]
        if faults.attacks:
            result["attacks"] = attack_accounting(status, sent)
            result["oversize_reply_s"] = sent.oversize_replies
        rec_times = [b["recovery_s"] for b in result.get("recovery", [])]
        result["pass"] = {
            "attacks": (not faults.attacks) or result["attacks"]["ok"],
            "recovery": (not faults.attacks)
            or (bool(rec_times) and max(rec_times) <= MAX_RECOVERY_S),
            "up": alive
            and not driver.errors
            and sent.control == sent.control_replies,
            "rss": growth <= MAX_RSS_GROWTH_MB,
            "accounting": a["osc_ok"]
            and a["frames_ok"]
            and a["zmq_ok"]
            and a["show_ok"],
            "gaps": not any(
                v
                for k, v in result["gaps"].items()
                if k not in ("paused", "source_stalled", "bad_burst", "host_late")
            ),
            "replay": (not record) or result["replay"]["ok"],
        }  # fmt: skip
        return result


def _ms(seconds: list[float]) -> str:
    """``median / max ms`` of some durations."""
    a = np.asarray(seconds) * 1e3
    return f"{np.median(a):.1f} ms median, {a.max():.1f} ms max (n={a.size})"


def _by_kind(rec: list[dict[str, Any]]) -> dict[str, Any]:
    """Per burst kind: (bursts, worst recovery s, worst angle from intact deg)."""
    out: dict[str, Any] = {}
    for b in rec:
        n, worst, deg = out.get(b["kind"], (0, 0.0, 0.0))
        out[b["kind"]] = (n + 1, max(worst, b["recovery_s"]), max(deg, b["worst_deg"]))
    return out


def _late(rec: list[dict[str, Any]]) -> str:
    """The bursts back past MAX_RECOVERY_S, one line: their count, then each one's
    kind, length, recovery and worst angle from the intact solve."""
    late = [b for b in rec if b["recovery_s"] > MAX_RECOVERY_S]
    return f"late (past {MAX_RECOVERY_S} s): {len(late)} of {len(rec)}" + "".join(
        f"; {b['kind']} of {b['frames']} frames {b['recovery_s']} s "
        f"(worst {b['worst_deg']} deg)"
        for b in late
    )


def _load(avg: tuple[float, float, float]) -> str:
    return " ".join(f"{x:.2f}" for x in avg)


def vars_of(obj: Any) -> dict[str, Any]:
    return {k: getattr(obj, k) for k in obj.__slots__}


def phase_rates(driver: Driver) -> dict[str, float]:
    """Pose rate (Hz) before, during and after the flood (fuzz mode), else whole."""
    t = np.asarray(driver.pose_ns, dtype=np.int64)
    a, b = driver.flood_ns
    spans = {"whole": (driver.t0_ns, driver.t1_ns)}
    if a and b:
        spans = {
            "before": (driver.t0_ns, a),
            "during": (a, b),
            "after": (b, driver.t1_ns),
        }
    return {
        k: round(
            float(np.count_nonzero((t >= x) & (t < y))) / max((y - x) * 1e-9, 1e-9), 1
        )
        for k, (x, y) in spans.items()
    }


def phase_rss(driver: Driver) -> dict[str, float]:
    a, b = driver.flood_ns
    if not (a and b) or not driver.rss:
        return {}
    t0 = (a - driver.t0_ns) * 1e-9
    t1 = (b - driver.t0_ns) * 1e-9
    pick = {
        "before": [kb for t, kb in driver.rss if t < t0],
        "during": [kb for t, kb in driver.rss if t0 <= t < t1],
        "after": [kb for t, kb in driver.rss if t >= t1],
    }
    return {k: round(v[-1] / 1024, 1) for k, v in pick.items() if v}


def print_result(result: dict[str, Any]) -> None:
    a, r = result["accounting"], result["rss_mb"]
    face = "on" if result["face"] else "off"
    lines = [
        f"soak {result['seconds']:.0f} s at {RATE_HZ:.0f} Hz, face {face}, validator "
        f"on; load {_load(result['load_before'])} -> {_load(result['load_after'])}",
        f"sent: {result['sent']}",
        f"osc: sent {a['osc_sent']} = counted {a['osc_counted']} + kernel drops "
        f"{a['osc_kernel_drops']}: {a['osc_ok']}",
        f"zmq: sent {a['zmq_sent']} = counted {a['zmq_counted']}: {a['zmq_ok']} "
        f"(disconnects {a['zmq_disconnects']})",
        f"show control: sent {a['show_sent']} = counted {a['show_counted']} + kernel "
        f"{a['show_kernel_drops']}: {a['show_ok']}",
        f"frames: in {a['frames_in']} = solved {a['frames_solved']} + stale "
        f"{a['stale']} + unsolved {a['unsolved']}: {a['frames_ok']}",
        f"drops by reason: {a['drops']}",
        f"poses {result['poses']} ({result['pose_rate_hz']:.1f} Hz); rates "
        f"{result['pose_rate_phases']}",
        f"gaps > 100 ms (s), daemon side: {result['gaps']}",
        f"gaps > 100 ms (s), at the driver's SUB: {result['gaps_sub']}; of them "
        f"sent on time, delivered late: {result['late_deliveries']}",
        f"loop stalls (phases over 50 ms): {result['loop_stalls']}",
        *(f"  {ln}" for ln in result["loop_stall_lines"][:20]),
        f"RSS MB: first {r['first']:.1f}, after warm-up {r['after_warmup']:.1f}, max "
        f"{r['max']:.1f}, growth {r['growth']:.2f}; phases {result['rss_phases_mb']}",
        f"control: {result['control_sent']} sent, {result['control_replies']} "
        f"answered; VMC datagrams received {result['vmc_datagrams']}; daemon exit "
        f"{result['rc']}",
    ]
    print("\n".join(lines))
    if "replay" in result:
        print(f"replay: {result['replay']}")
    if result["errors"]:
        print(f"errors: {result['errors'][:5]}")
    if "attacks" in result:
        att = result["attacks"]
        print(f"attacks (sent, counted): {att['pairs']}; record starts: "
              f"{att['churn_started']} of {CHURN}, rate_limited {att['rate_limited']}; "
              f"spoofed triples {att['spoofed_triples']}")  # fmt: skip
        replies = result["oversize_reply_s"]
        if replies:
            print(f"10 MB control requests answered in {_ms(replies)}")
        rec = result.get("recovery", [])
        if rec:
            times = np.asarray([b["recovery_s"] for b in rec])
            print(f"bursts: {len(rec)}; recovery s median {np.median(times):.4f} max "
                  f"{times.max():.4f} (<= {MAX_RECOVERY_S}); by kind "
                  f"{_by_kind(rec)}")  # fmt: skip
            print(_late(rec))
    print(f"pass: {result['pass']}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    length = parser.add_mutually_exclusive_group()
    length.add_argument("--seconds", type=float, default=600.0)
    length.add_argument("--minutes", type=float, help="the length in minutes")
    parser.add_argument("--no-face", action="store_true", help="face off")
    parser.add_argument("--json", type=Path, help="write the figures here")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--no-attacks", action="store_true", help="issue 12's faults only"
    )
    args = parser.parse_args(argv)
    if args.minutes is not None:
        args.seconds = 60.0 * args.minutes
    if args.seconds < 5:
        parser.error("--seconds must be >= 5")
    faults = Faults(attacks=not args.no_attacks)
    result = run(args.seconds, faults, face=not args.no_face, seed=args.seed)
    print_result(result)
    if args.json:
        args.json.write_text(json.dumps(result, indent=1, default=str))
    return 0 if all(result["pass"].values()) else 1


if __name__ == "__main__":
    sys.exit(main())
