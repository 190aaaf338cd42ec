"""Recordings survive the ways a daemon ends, and tell the truth when the disk fills.

Subprocesses over 127.0.0.1 (ephemeral ports), the btkdata Plug-in Gait walk streamed
as compact OSC:

- ``retargetd run`` recording (``ctl record start``) and stopped by SIGHUP, SIGTERM or
  SIGINT: exit 0 and a complete file (footer, ``record_stop`` reason ``shutdown``);
  the same for ``retargetd record``;
- ``retargetd run`` recording and killed with SIGKILL: the file reads (our reader and
  the ``mcap`` library's) and holds all but at most 1 s of the frames sent;
- ``retargetd run`` recording onto a full file system (a 256 KiB tmpfs; root only, CI
  runs as root): the recording stops by itself, ``ctl status --json`` ``record``
  says so with the file's own counts, stderr carries one line about it, and the
  daemon goes on solving;
- ``retargetd record`` under a file-size limit (``RLIMIT_FSIZE``, unprivileged: the
  kernel's ``EFBIG``): it stops by itself, prints the file's counts and exits 1.
"""

from __future__ import annotations

import functools
import io
import json
import re
import selectors
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from paths import DATASETS, require
from small_fs import mounted_tmpfs

from retargetd.daemon.cli.main import main
from retargetd.protocols import osc_in
from retargetd.protocols.marker_input import LabelSet
from retargetd.replay import recording as rf
from retargetd.replay.take import Take
from retargetd.replay.takes import load_take

WALK = DATASETS / "btkdata/PiG_Motion-FlatFoot-Full.c3d"
STOP_SIGNALS = [
    pytest.param(signal.SIGHUP, id="SIGHUP"),
    pytest.param(signal.SIGTERM, id="SIGTERM"),
    pytest.param(signal.SIGINT, id="SIGINT"),
]


@functools.cache
def _walk() -> Take:
    # (skips outside CI, fails in CI, saying why, when ../shared is absent)
    return load_take(require(WALK, "the btkdata Plug-in Gait walk"))


class Sender:
    """Compact OSC frames of the walk (looping), paced; the label set announced
    first and once a second, like a capture system."""

    def __init__(self, addr: tuple[str, int]) -> None:
        # The take first: a take that fails to load leaves no socket open.
        self.labels = osc_in.encode_labels(LabelSet(1, _walk().labels))
        self._pos = np.asarray(_walk().positions, dtype=np.float32)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.addr = addr
        self.sent: list[bytes] = []

    def send(self, seconds: float, rate_hz: float) -> None:
        start = time.perf_counter()
        for _ in range(round(seconds * rate_hz)):
            i = len(self.sent)
            if i % round(rate_hz) == 0:
                self.sock.sendto(self.labels, self.addr)
            row = self._pos[i % len(self._pos)]
            self.sent.append(osc_in.encode_compact_frame(i, i / rate_hz, 1, row))
            self.sock.sendto(self.sent[-1], self.addr)
            time.sleep(max(0.0, start + (i + 1) / rate_hz - time.perf_counter()))

    def close(self) -> None:
        self.sock.close()


@pytest.fixture
def sender_for() -> Iterator[Callable[[tuple[str, int]], Sender]]:
    made: list[Sender] = []

    def make(addr: tuple[str, int]) -> Sender:
        made.append(Sender(addr))
        return made[-1]

    yield make
    for s in made:
        s.close()


def _record_folder(folder: Path) -> str:
    """Config lines letting ``ctl record start`` write under ``folder``."""
    return f"[record]\nfolder = {json.dumps(str(folder))}\nmin_free_mb = 0.0\n"


def _record_status(daemon: Any) -> dict[str, Any]:
    reply = daemon.ctl({"cmd": "status"})
    assert reply is not None and reply["ok"], reply
    return dict(reply["status"]["record"])


def _wait(pred: Callable[[], bool], what: str, timeout_s: float = 15.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(0.02)


def _frames(recording: rf.Recording) -> list[bytes]:
    return [
        p.parts[0]
        for p in recording.packets()
        if p.kind == rf.KIND_FRAME and p.input == "osc"
    ]


class _NonSeekable(io.BytesIO):
    def seekable(self) -> bool:
        return False


def _mcap_library_count(data: bytes) -> int:
    """Messages the mcap library's non-seeking reader yields before the cut end."""
    n = 0
    try:
        for _ in make_reader(_NonSeekable(data)).iter_messages(log_time_order=False):
            n += 1
    except Exception:
        pass
    return n


@pytest.mark.timeout(120)
@pytest.mark.parametrize("sig", STOP_SIGNALS)
def test_a_signal_finishes_the_daemon_recording(
    sig: int,
    pig_calibration: Path,
    run_daemon: Callable[..., Any],
    sender_for: Callable[[tuple[str, int]], Sender],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    d = run_daemon(pig_calibration, extra=_record_folder(tmp_path))
    path = tmp_path / f"sig{int(sig)}.mcap"
    ctl = d.endpoints["control"]
    assert main(["ctl", "--endpoint", ctl, "record", "start", str(path)]) == 0
    assert capsys.readouterr().out.startswith(f"recording to {path}")
    sender = sender_for(d.udp("osc markers"))
    sender.send(0.6, 120.0)
    _wait(lambda: _record_status(d)["frames"] >= 1, "frames in the file")
    d.p.send_signal(sig)
    rc = d.p.wait(timeout=30.0)
    assert rc == 0, (rc, d.p.stderr.read() if d.p.stderr else "")
    recording = rf.read_recording(path)
    assert recording.complete, recording.stop_reason
    last = recording.json(rf.CONTROL_TOPIC)[-1]
    assert last["event"] == "record_stop" and last["reason"] == "shutdown", last
    got = _frames(recording)
    assert got and got == sender.sent[: len(got)]
    # The daemon had read every frame before the signal (paced at 120 Hz): all kept.
    assert len(got) == len(sender.sent)


@pytest.mark.timeout(120)
def test_sigkill_of_the_daemon_loses_at_most_a_second(
    pig_calibration: Path,
    run_daemon: Callable[..., Any],
    sender_for: Callable[[tuple[str, int]], Sender],
    tmp_path: Path,
) -> None:
    d = run_daemon(pig_calibration, extra=_record_folder(tmp_path))
    path = tmp_path / "killed.mcap"
    reply = d.ctl({"cmd": "record", "action": "start", "path": str(path)})
    assert reply is not None and reply["ok"], reply
    sender = sender_for(d.udp("osc markers"))
    rate_hz = 120.0
    # 2.13 s: not a multiple of the 0.25 s flush interval, so the kill lands between
    # flushes.
    sender.send(2.13, rate_hz)
    d.p.kill()  # right after the last frame: no chance to finish
    assert d.p.wait(timeout=10.0) == -signal.SIGKILL
    recording = rf.read_recording(path)
    assert not recording.complete
    got = _frames(recording)
    assert got == sender.sent[: len(got)]  # what is kept is byte-identical, in order
    lost_s = (len(sender.sent) - len(got)) / rate_hz
    size = path.stat().st_size
    print(
        f"SIGKILL of the daemon: {len(got)}/{len(sender.sent)} frames readable, "
        f"lost {lost_s * 1e3:.0f} ms ({size - recording.bytes_read} bytes past the "
        f"last whole record; {recording.stop_reason})"
    )
    assert lost_s <= 1.0
    assert recording.topic(rf.POSES_TOPIC)  # the pose stream is recorded too
    assert _mcap_library_count(path.read_bytes()) == len(recording.messages)
    assert load_take(path).n_frames == len(got)


@pytest.mark.timeout(120)
def test_a_full_disk_stops_the_daemon_recording_and_status_tells(
    pig_calibration: Path,
    run_daemon: Callable[..., Any],
    sender_for: Callable[[tuple[str, int]], Sender],
    tmp_path: Path,
) -> None:
    with mounted_tmpfs(tmp_path / "small", 256 * 1024) as small:
        d = run_daemon(pig_calibration, extra=_record_folder(small))
        path = small / "full.mcap"
        reply = d.ctl({"cmd": "record", "action": "start", "path": str(path)})
        assert reply is not None and reply["ok"], reply
        sender = sender_for(d.udp("osc markers"))
        deadline = time.monotonic() + 40.0
        while _record_status(d)["active"]:
            assert time.monotonic() < deadline, _record_status(d)
            sender.send(0.25, 200.0)
        rec = _record_status(d)
        last = rec["last"]
        assert not rec["active"] and last is not None, rec
        assert last["path"] == str(path) and last["stopped"] == "write error", last
        assert "No space left on device (ENOSPC)" in last["error"], last
        recording = rf.read_recording(path)
        got = _frames(recording)
        assert last["frames"] == len(got) > 0, (last, len(got))
        assert got == sender.sent[: len(got)]
        assert last["poses_written"] == len(recording.topic(rf.POSES_TOPIC)) > 0
        assert last["events"] == len(recording.json(rf.CONTROL_TOPIC))
        assert last["write_errors"] > 0 and last["queued"] == 0, last
        assert recording.bytes_read == path.stat().st_size  # cut back cleanly
        print(
            f"full disk: sent {len(sender.sent)} frames; the file holds {len(got)} "
            f"frames and {last['poses_written']} pose messages; status {last}"
        )
        # The daemon goes on: frames keep being solved and sent.
        before = d.counters()["frames_out"]
        sender.send(0.2, 200.0)
        _wait(lambda: d.counters()["frames_out"] > before, "frames after the error")
        rc, err = d.stop()
        assert rc == 0, err
        lines = [ln for ln in err.splitlines() if "write failed" in ln]
        assert len(lines) == 1 and str(path) in lines[0], err


#: Runs argv[2:] with a file-size limit of argv[1] bytes and SIGXFSZ ignored, so a
#: write past the limit fails with EFBIG (after a short write), unprivileged.
_LIMITED = (
    "import os, resource, signal, sys; "
    "signal.signal(signal.SIGXFSZ, signal.SIG_IGN); "
    "n = int(sys.argv[1]); resource.setrlimit(resource.RLIMIT_FSIZE, (n, n)); "
    "os.execv(sys.argv[2], sys.argv[2:])"
)


class RecordProc:
    """``retargetd record --listen osc://127.0.0.1:0 --out FILE``, optionally with a
    file-size limit (bytes)."""

    def __init__(self, out: Path, fsize_limit: int = 0) -> None:
        self.out = out
        limit = (
            [sys.executable, "-c", _LIMITED, str(fsize_limit)] if fsize_limit else []
        )
        self.proc = subprocess.Popen(
            [*limit, sys.executable, "-m", "retargetd.daemon", "record", "--listen",
             "osc://127.0.0.1:0", "--out", str(out)],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        assert self.proc.stdout is not None
        with selectors.DefaultSelector() as sel:
            sel.register(self.proc.stdout, selectors.EVENT_READ)
            assert sel.select(30.0), "recorder did not start in time"
        line = self.proc.stdout.readline()
        match = re.search(r"udp://127\.0\.0\.1:(\d+)", line)
        assert match, f"no listening line: {line!r}"
        self.addr = ("127.0.0.1", int(match.group(1)))

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.communicate(timeout=10)


@pytest.mark.timeout(60)
@pytest.mark.parametrize("sig", STOP_SIGNALS)
def test_a_signal_finishes_the_record_command(
    sig: int, tmp_path: Path, sender_for: Callable[[tuple[str, int]], Sender]
) -> None:
    rec = RecordProc(tmp_path / "rec.mcap")
    try:
        sender = sender_for(rec.addr)
        sender.send(0.5, 120.0)
        time.sleep(0.1)  # the last datagram received
        rec.proc.send_signal(sig)
        out, err = rec.proc.communicate(timeout=20)
    finally:
        rec.kill()
    assert rec.proc.returncode == 0, err
    recording = rf.read_recording(rec.out)
    assert recording.complete, recording.stop_reason
    got = _frames(recording)
    assert got == sender.sent
    assert f"recorded {len(got)} marker frames" in out, out
    assert recording.json(rf.CONTROL_TOPIC)[-1]["event"] == "record_stop"


@pytest.mark.timeout(60)
def test_a_write_error_stops_the_record_command_with_the_true_counts(
    tmp_path: Path, sender_for: Callable[[tuple[str, int]], Sender]
) -> None:
    rec = RecordProc(tmp_path / "limited.mcap", fsize_limit=60_000)
    try:
        sender = sender_for(rec.addr)
        deadline = time.monotonic() + 30.0
        while rec.proc.poll() is None:  # it stops by itself
            assert time.monotonic() < deadline, "the recorder did not stop"
            sender.send(0.25, 240.0)
        out, err = rec.proc.communicate(timeout=20)
    finally:
        rec.kill()
    assert rec.proc.returncode == 1, (out, err)
    assert "stopped early (write failed: File too large (EFBIG))" in err, err
    recording = rf.read_recording(rec.out)
    got = _frames(recording)
    assert got and got == sender.sent[: len(got)]
    assert f"recorded {len(got)} marker frames" in out, out
    assert recording.bytes_read == rec.out.stat().st_size <= 60_000
    print(f"record with a 60 kB limit: {len(got)}/{len(sender.sent)} frames kept")
