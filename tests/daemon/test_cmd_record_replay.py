"""``retargetd record`` and ``retargetd replay`` end to end, over real loopback sockets:
player -> recorder round trips in every input form, byte-identical re-sends, a
recorder killed with SIGKILL, SIGINT, pacing, loops, windows and bad URLs."""

from __future__ import annotations

import io
import re
import selectors
import signal
import socket
import struct
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zmq
from mcap.reader import make_reader

from retargetd.daemon.cli.main import main
from retargetd.protocols import osc_in
from retargetd.protocols.marker_input import LabelSet
from retargetd.replay import recording as rf
from retargetd.replay.c3d import write_c3d
from retargetd.replay.takes import load_take

RATE_HZ = 60.0
LABELS = ("LASI", "RASI", "LPSI", "RPSI")


@pytest.fixture
def take_path(tmp_path: Path) -> Path:
    """A 40-frame, 4-marker C3D in metres, +Z up, with an occluded run."""
    rng = np.random.default_rng(0)
    pos = rng.uniform(-1.0, 2.0, (40, len(LABELS), 3))
    pos[10:15, 2] = np.nan
    path = tmp_path / "source.c3d"
    write_c3d(path, LABELS, pos, RATE_HZ, units="m", up_axis="+Z")
    return path


class Recorder:
    """A ``retargetd record`` subprocess; killed at teardown if still running."""

    def __init__(self, tmp_path: Path, listen: str, *extra: str) -> None:
        self.out = tmp_path / "rec.mcap"
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "retargetd.daemon", "record", "--listen", listen,
             "--out", str(self.out), *extra],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        line = self._readline(30.0)
        match = re.search(r"(?:udp|tcp)://127\.0\.0\.1:(\d+)", line)
        assert match, f"no listening line: {line!r}"
        self.port = int(match.group(1))

    def _readline(self, timeout_s: float) -> str:
        assert self.proc.stdout is not None
        with selectors.DefaultSelector() as sel:
            sel.register(self.proc.stdout, selectors.EVENT_READ)
            if not sel.select(timeout_s):
                self.proc.kill()
                raise AssertionError("recorder did not start in time")
        return self.proc.stdout.readline()

    def wait_frames(self, n: int, timeout_s: float = 10.0) -> None:
        """Wait until the (flushed) file holds ``n`` marker frames."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.out.exists() and self.out.stat().st_size > 0:
                got = sum(
                    p.kind == rf.KIND_FRAME
                    for p in rf.read_recording(self.out).packets()
                )
                if got >= n:
                    return
            time.sleep(0.05)
        raise AssertionError(f"recorder did not get {n} frames in {timeout_s} s")

    def stop(self, sig: int = signal.SIGINT) -> tuple[int, str, str]:
        self.proc.send_signal(sig)
        out, err = self.proc.communicate(timeout=20)
        return self.proc.returncode, out, err

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.communicate(timeout=10)


@pytest.fixture
def recorders(tmp_path: Path) -> Iterator[list[Recorder]]:
    started: list[Recorder] = []
    yield started
    for r in started:
        r.kill()


def _udp_receiver() -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
    sock.bind(("127.0.0.1", 0))
    return sock


def _drain_udp(sock: socket.socket, timeout_s: float = 0.5) -> list[bytes]:
    sock.settimeout(timeout_s)
    got = []
    try:
        while True:
            got.append(sock.recv(65536))
            sock.settimeout(0.2)
    except TimeoutError:
        pass
    return got


def _compact_frame_numbers(datagrams: list[bytes]) -> list[int]:
    return [
        struct.unpack_from(">q", d, 20)[0]
        for d in datagrams
        if d.startswith(b"/rtd/frame\0")
    ]


def _wall_s(out: str) -> float:
    """The wall time of the last replay report in ``out``."""
    return float(re.findall(r"^replay: .* in ([\d.]+) s", out, flags=re.M)[-1])


@pytest.mark.timeout(90)
@pytest.mark.parametrize(
    "listen,form",
    [("osc", "compact"), ("osc", "simple"), ("zmq", "compact")],
)
def test_round_trip_player_to_recorder(
    tmp_path: Path, take_path: Path, recorders: list[Recorder], listen: str, form: str
) -> None:
    extra = ("--form", form) if listen == "osc" else ()
    rec = Recorder(tmp_path, f"{listen}://127.0.0.1:0", *extra)
    recorders.append(rec)
    to = f"{listen}://127.0.0.1:{rec.port}"
    # Simple bundles carry no source timestamp: the rate comes from receive times,
    # so that form is sent paced.
    speed = "1" if form == "simple" else "0"
    assert main(["replay", str(take_path), "--to", to, "--speed", speed,
                 *extra]) == 0  # fmt: skip
    rec.wait_frames(40)
    code, out, err = rec.stop(signal.SIGINT)
    assert code == 0, err
    assert "recorded 40 marker frames" in out and "dropped 0" in out

    # SIGINT leaves a complete file: the library's indexed reader needs the footer.
    recording = rf.read_recording(rec.out)
    assert recording.complete
    with open(rec.out, "rb") as f:
        reader = make_reader(f)
        assert reader.get_summary() is not None
        assert sum(1 for _ in reader.iter_messages(topics=[rf.RAW_TOPIC])) >= 40
    events = [e["event"] for e in recording.json(rf.CONTROL_TOPIC)]
    assert events == ["record_start", "record_stop"]

    source = load_take(take_path)
    take = load_take(rec.out)
    assert take.labels == source.labels and take.n_frames == source.n_frames
    assert (take.units, take.up_axis) == ("m", "+Z")
    assert take.rate_hz == pytest.approx(RATE_HZ, rel=1e-6 if speed == "0" else 0.1)
    np.testing.assert_array_equal(take.valid, source.valid)
    np.testing.assert_array_equal(
        take.positions, source.positions.astype(np.float32).astype(np.float64)
    )

    # The recording replays the very bytes it recorded.
    recorded = [p.parts for p in recording.packets()]
    if listen == "osc":
        with _udp_receiver() as rx:
            port = rx.getsockname()[1]
            assert main(["replay", str(rec.out), "--to", f"osc://127.0.0.1:{port}",
                         "--speed", "0"]) == 0  # fmt: skip
            resent = [(d,) for d in _drain_udp(rx)]
    else:
        ctx = zmq.Context()
        pull = ctx.socket(zmq.PULL)
        pull.linger = 0
        pull.rcvtimeo = 2000
        try:
            port = pull.bind_to_random_port("tcp://127.0.0.1")
            assert main(["replay", str(rec.out), "--to", f"zmq://127.0.0.1:{port}",
                         "--speed", "0"]) == 0  # fmt: skip
            resent = [tuple(pull.recv_multipart()) for _ in recorded]
        finally:
            pull.close()
            ctx.term()
    assert resent == recorded


@pytest.mark.timeout(90)
def test_record_with_a_key_file_keeps_only_signed_datagrams(
    tmp_path: Path, take_path: Path, recorders: list[Recorder]
) -> None:
    from retargetd.daemon.live.surface import load_hmac_key
    from retargetd.protocols.osc_auth import DatagramSigner

    assert main(["keys", "--hmac", "bridge", "--dir", str(tmp_path)]) == 0
    key = str(tmp_path / "bridge.hmac")
    rec = Recorder(tmp_path, "osc://127.0.0.1:0", "--key-file", key)
    recorders.append(rec)
    to = ["--to", f"osc://127.0.0.1:{rec.port}", "--speed", "0"]
    assert main(["replay", str(take_path), *to]) == 0  # unsigned: refused
    assert main(["replay", str(take_path), *to, "--key-file", key]) == 0
    rec.wait_frames(40)
    # A signed datagram of an older session than the replay's: a replay, refused.
    old = DatagramSigner(load_hmac_key(key), session=1)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
        labels = osc_in.encode_labels(LabelSet(9, LABELS))
        tx.sendto(old.sign(labels), ("127.0.0.1", rec.port))
    time.sleep(0.3)  # received before the stop
    code, out, err = rec.stop(signal.SIGINT)
    assert code == 0, err
    assert "recorded 40 marker frames, 1 label packets" in out, out
    assert "refused 41 unsigned or bad tag (auth_failed), 1 replayed" in out, out
    # Recorded without their trailers: the take decodes as sent.
    source, take = load_take(take_path), load_take(rec.out)
    assert take.labels == source.labels
    np.testing.assert_array_equal(
        take.positions, source.positions.astype(np.float32).astype(np.float64)
    )
    assert main(["record", "--listen", "zmq://127.0.0.1:0", "--out",
                 str(tmp_path / "z.mcap"), "--key-file", key]) == 2  # fmt: skip


@pytest.mark.timeout(60)
def test_sigkill_leaves_a_readable_file(
    tmp_path: Path, recorders: list[Recorder]
) -> None:
    rec = Recorder(tmp_path, "osc://127.0.0.1:0")
    recorders.append(rec)
    labels = LabelSet(1, LABELS)
    rng = np.random.default_rng(1)
    sent: list[bytes] = []
    rate = 120.0
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
        start = time.perf_counter()
        # 2.13 s at 120 Hz: not a multiple of the 0.25 s flush interval, so the kill
        # lands between flushes.
        for i in range(int(2.13 * rate)):
            if i % int(rate) == 0:
                tx.sendto(osc_in.encode_labels(labels), ("127.0.0.1", rec.port))
            sent.append(
                osc_in.encode_compact_frame(i, i / rate, 1, rng.normal(size=(4, 3)))
            )
            tx.sendto(sent[-1], ("127.0.0.1", rec.port))
            time.sleep(max(0.0, start + (i + 1) / rate - time.perf_counter()))
    rec.proc.kill()  # SIGKILL right after the last frame: no chance to finish
    rec.proc.communicate(timeout=10)
    assert rec.proc.returncode == -signal.SIGKILL

    recording = rf.read_recording(rec.out)
    assert not recording.complete
    got = [p.parts[0] for p in recording.packets() if p.kind == rf.KIND_FRAME]
    assert got == sent[: len(got)]  # everything kept is byte-identical, in order
    lost_s = (len(sent) - len(got)) / rate
    size = rec.out.stat().st_size
    print(
        f"SIGKILL: {len(got)}/{len(sent)} frames readable, lost {lost_s * 1e3:.0f} ms "
        f"(file {size} bytes, {size - recording.bytes_read} bytes past the last "
        f"whole record; stop: {recording.stop_reason})"
    )
    assert lost_s <= 1.0

    class NonSeekable(io.BytesIO):
        def seekable(self) -> bool:
            return False

    n_lib = 0
    reader = make_reader(NonSeekable(rec.out.read_bytes()))
    with pytest.raises(Exception):  # noqa: B017 (no footer: EndOfFile or short)
        for _ in reader.iter_messages(log_time_order=False):
            n_lib += 1
    assert n_lib == len(recording.messages)  # the mcap library reads them too
    assert load_take(rec.out).n_frames == len(got)


@pytest.mark.timeout(60)
def test_replay_pacing_loop_and_frames(
    take_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with _udp_receiver() as rx:
        to = f"osc://127.0.0.1:{rx.getsockname()[1]}"
        assert main(["replay", str(take_path), "--to", to]) == 0  # 40 / 60 Hz
        out = capsys.readouterr().out
        paced = _wall_s(out)
        print(out.strip().splitlines()[-1])
        assert abs(paced - 40 / RATE_HZ) < 0.3 * 40 / RATE_HZ
        assert _compact_frame_numbers(_drain_udp(rx)) == list(range(40))

        assert main(["replay", str(take_path), "--to", to, "--speed", "0"]) == 0
        fast = _wall_s(capsys.readouterr().out)
        assert fast < paced / 3
        _drain_udp(rx)

        assert main(["replay", str(take_path), "--to", to, "--speed", "4",
                     "--loop", "--seconds", "0.5"]) == 0  # fmt: skip
        numbers = _compact_frame_numbers(_drain_udp(rx))
        assert len(numbers) > 60  # more than one pass of 40
        assert (np.diff(numbers) > 0).all()

        assert main(["replay", str(take_path), "--to", to, "--speed", "0",
                     "--frames", "10:20"]) == 0  # fmt: skip
        datagrams = _drain_udp(rx)
        assert datagrams[0].startswith(b"/rtd/labels")  # labels first
        assert _compact_frame_numbers(datagrams) == list(range(10, 20))


@pytest.mark.parametrize(
    "argv,message",
    [
        (["--to", "udp://127.0.0.1:9"], "--to: expected osc://HOST:PORT"),
        (["--to", "osc://127.0.0.1:x"], "port must be an integer"),
        (["--to", "osc://127.0.0.1:9", "--speed", "-1"], "--speed must be >= 0"),
        (["--to", "osc://127.0.0.1:9", "--frames", "50:60"], "selects no frames"),
    ],
)
def test_bad_replay_arguments_are_one_line_exit_2(
    take_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str], message: str
) -> None:
    assert main(["replay", str(take_path), *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


def test_bad_record_listen_is_one_line_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = str(tmp_path / "x.mcap")
    assert main(["record", "--listen", "tcp://127.0.0.1:1", "--out", out]) == 2
    err = capsys.readouterr().err
    assert "expected osc://HOST:PORT" in err and err.count("\n") == 1
