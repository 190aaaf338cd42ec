"""A recorder that tells the truth when the disk fails.

Real failures, no fakes at the OS boundary:

- a full file system: a 128 KiB tmpfs (root only; CI runs as root), so ``os.write``
  gets the kernel's ``ENOSPC``, both inside a chunk closed by size (``add_message``)
  and inside the periodic flush;
- a file-size limit (``RLIMIT_FSIZE``, unprivileged, in a child process with
  ``SIGXFSZ`` ignored): ``os.write`` gets ``EFBIG`` after a short write, like a disk
  filling in the middle of a chunk;
- a read-only file system (a tmpfs mounted ``ro``): the recording is refused at start.

Each time the recording stops by itself, says why in ``error`` and one log line, and
the frames it reports are exactly the frames the file holds (read back with
``read_recording`` and the ``mcap`` library), the file cut back to a record boundary.
A full queue is counted as dropped, apart from write errors.
"""

from __future__ import annotations

import errno
import io
import json
import logging
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from small_fs import mounted_tmpfs

from retargetd.daemon.live import recording as live_recording
from retargetd.daemon.live.recording import LiveRecording
from retargetd.protocols import osc_in
from retargetd.protocols.marker_input import LabelSet
from retargetd.replay import recorder as recorder_mod
from retargetd.replay import recording as rf
from retargetd.replay.recorder import InputInfo, Recorder, open_recorder

#: 40 markers of noise: ~0.5 KB a frame that zstd cannot shrink much.
LABELS = LabelSet(2, tuple(f"M{i:02d}" for i in range(40)))
INPUTS = (InputInfo(name="osc", form="osc-compact"),)
#: The small file system: 32 pages, full after a few hundred frames.
TMPFS_BYTES = 128 * 1024


class _NonSeekable(io.BytesIO):
    def seekable(self) -> bool:
        return False


def _mcap_stream_messages(data: bytes) -> int:
    """Messages the mcap library's non-seeking reader yields before the end."""
    n = 0
    try:
        for _ in make_reader(_NonSeekable(data)).iter_messages(log_time_order=False):
            n += 1
    except Exception:  # no footer: the reader ends in EndOfFile
        pass
    return n


def _frame(rng: np.random.Generator, i: int) -> bytes:
    pos = rng.normal(size=(len(LABELS.labels), 3)).astype(np.float32)
    return osc_in.encode_compact_frame(i, i / 100, LABELS.id, pos)


def _feed_until_failed(
    rec: Recorder, rng: np.random.Generator, period_s: float, limit: int = 20_000
) -> list[bytes]:
    """Frames handed to ``rec`` (accepted or not) until it reports a failure."""
    sent = [osc_in.encode_labels(LABELS)]
    rec.record_packet("osc", rf.FORM_OSC_COMPACT, time.monotonic_ns(), sent[0])
    deadline = time.monotonic() + 30.0
    for i in range(limit):
        if rec.failed or time.monotonic() > deadline:
            break
        sent.append(_frame(rng, i))
        rec.record_packet("osc", rf.FORM_OSC_COMPACT, time.monotonic_ns(), sent[-1])
        time.sleep(period_s)
    return sent


def _check_truth(path: Path, rec: Recorder, sent: list[bytes]) -> rf.Recording:
    """The counts are the file's, the file ends on a record boundary, and what it
    holds is the start of what was sent, byte for byte."""
    st = rec.stats
    assert rec.failed and rec.finished
    recording = rf.read_recording(path)
    assert not recording.complete
    packets = [p for p in recording.packets() if p.input == "osc"]
    frames = [p.parts[0] for p in packets if p.kind == rf.KIND_FRAME]
    assert st.frames == len(frames) > 0, (st, len(frames))
    assert [p.parts[0] for p in packets] == sent[: len(packets)]
    assert st.label_packets == sum(p.kind == rf.KIND_LABELS for p in packets)
    # Cut back: nothing after the last whole record.
    assert recording.bytes_read == path.stat().st_size, recording.stop_reason
    assert recording.stop_reason == "end of file without a footer"
    n_lib = _mcap_stream_messages(path.read_bytes())
    assert n_lib == len(recording.messages)  # the mcap library reads the same
    # Every accepted item is in the file or lost to the error, none in limbo.
    assert st.accepted == st.items_written + st.write_errors
    assert st.write_errors > 0 and rec.queued == 0
    # Stopped: nothing more is accepted.
    assert not rec.record_packet("osc", rf.FORM_OSC_COMPACT, 0, sent[-1])
    assert not rec.record_event("late")
    return recording


def test_the_flush_interval_is_at_most_a_second() -> None:
    for bad in (0.0, -1.0, 1.5, float("nan")):
        with pytest.raises(ValueError, match="flush_interval_s"):
            Recorder(lambda stats: None, flush_interval_s=bad)
    Recorder(lambda stats: None, flush_interval_s=1.0)  # the bound itself is fine


def _error_lines(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [
        r.getMessage()
        for r in caplog.records
        if r.name == recorder_mod.__name__ and r.levelno >= logging.ERROR
    ]


@pytest.mark.timeout(60)
@pytest.mark.parametrize(
    "where,kw,period_s",
    [
        # A chunk closed by size inside add_message, between flushes.
        ("chunk", {"chunk_size": 4096, "flush_interval_s": 1.0}, 0.0005),
        # The periodic flush (chunks never reach their size between flushes).
        ("flush", {"chunk_size": 1 << 20, "flush_interval_s": 0.02}, 0.002),
    ],
)
def test_full_disk_stops_the_recording_and_counts_what_the_file_holds(
    tmp_path: Path,
    rng: np.random.Generator,
    caplog: pytest.LogCaptureFixture,
    where: str,
    kw: dict[str, Any],
    period_s: float,
) -> None:
    caplog.set_level(logging.INFO)
    with mounted_tmpfs(tmp_path / "small", TMPFS_BYTES) as small:
        path = small / "full.mcap"
        rec = open_recorder(path, INPUTS, **kw)
        sent = _feed_until_failed(rec, rng, period_s)
        rec.close(timeout_s=10.0)
        print(
            f"{where}: sent {len(sent)} packets, the file holds {rec.stats.frames} "
            f"frames ({path.stat().st_size} bytes); lost {rec.stats.write_errors}; "
            f"error: {rec.error}"
        )
        assert "No space left on device" in rec.error and "ENOSPC" in rec.error
        _check_truth(path, rec, sent)
        lines = _error_lines(caplog)
        assert len(lines) == 1 and str(path) in lines[0], lines
        assert f"keeps {rec.stats.frames} frames" in lines[0]


_CHILD = r"""
import json, resource, signal, sys, time
import numpy as np
from retargetd.protocols import osc_in
from retargetd.protocols.marker_input import LabelSet
from retargetd.replay import recording as rf
from retargetd.replay.recorder import InputInfo, open_recorder

path, limit = sys.argv[1], int(sys.argv[2])
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # the write fails with EFBIG instead
resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
labels = LabelSet(2, tuple(f"M{i:02d}" for i in range(40)))
rng = np.random.default_rng(3)
rec = open_recorder(path, (InputInfo(name="osc", form="osc-compact"),),
                    chunk_size=3000, flush_interval_s=0.05)
sent = [osc_in.encode_labels(labels)]
rec.record_packet("osc", rf.FORM_OSC_COMPACT, time.monotonic_ns(), sent[0])
i = 0
while not rec.failed and i < 20000:
    pos = rng.normal(size=(40, 3)).astype(np.float32)
    sent.append(osc_in.encode_compact_frame(i, i / 100, 2, pos))
    rec.record_packet("osc", rf.FORM_OSC_COMPACT, time.monotonic_ns(), sent[-1])
    i += 1
    time.sleep(0.0005)
st = rec.close(10.0)
print(json.dumps({
    "error": rec.error, "failed": rec.failed, "frames": st.frames,
    "accepted": st.accepted, "written": st.items_written,
    "write_errors": st.write_errors, "sent": [s.hex() for s in sent],
}))
"""


@pytest.mark.timeout(60)
def test_file_size_limit_mid_chunk_stops_the_recording_truthfully(
    tmp_path: Path,
) -> None:
    path = tmp_path / "limited.mcap"
    limit = 40_000  # bytes: ~80 frames, not a multiple of any chunk
    done = subprocess.run(
        [sys.executable, "-c", _CHILD, str(path), str(limit)],
        capture_output=True, text=True, timeout=50,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    doc = json.loads(done.stdout.splitlines()[-1])
    assert doc["failed"] and "File too large (EFBIG)" in doc["error"], doc["error"]
    assert path.stat().st_size <= limit
    recording = rf.read_recording(path)
    packets = [p for p in recording.packets() if p.input == "osc"]
    frames = sum(p.kind == rf.KIND_FRAME for p in packets)
    assert doc["frames"] == frames > 0
    sent = [bytes.fromhex(h) for h in doc["sent"]]
    assert [p.parts[0] for p in packets] == sent[: len(packets)]
    assert recording.bytes_read == path.stat().st_size  # cut back to a boundary
    assert doc["accepted"] == doc["written"] + doc["write_errors"]
    error_lines = [ln for ln in done.stderr.splitlines() if "stopped" in ln]
    assert len(error_lines) == 1, done.stderr
    print(f"EFBIG at {limit} bytes: {frames} frames kept; {doc['error']}")


@pytest.mark.timeout(60)
def test_read_only_file_system_refuses_the_recording(tmp_path: Path) -> None:
    with mounted_tmpfs(tmp_path / "ro", 64 * 1024, read_only=True) as ro:
        with pytest.raises(OSError) as exc:
            open_recorder(ro / "x.mcap", INPUTS)
        assert exc.value.errno == errno.EROFS
        live = LiveRecording()
        with pytest.raises(ValueError, match="Read-only file system"):
            live.start(str(ro / "x.mcap"), True, INPUTS, [])
        assert not live.active and not (ro / "x.mcap").exists()


@pytest.mark.timeout(60)
def test_live_recording_full_disk_ends_the_recording_in_status(
    tmp_path: Path, rng: np.random.Generator, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO)
    with mounted_tmpfs(tmp_path / "small", TMPFS_BYTES) as small:
        live = LiveRecording()
        path = small / "live.mcap"
        live.start(str(path), True, INPUTS, [])
        rec = live.packets
        assert rec is not None
        # ~80 frames (40 KB) a 0.25 s flush: the first chunks fit, then one fails.
        sent = _feed_until_failed(rec, rng, 0.003)
        deadline = time.monotonic() + 10.0
        while live.status()["active"] or live.status()["last"] is None:
            assert time.monotonic() < deadline, live.status()
            time.sleep(0.01)
        doc = live.status()
        assert live.packets is None and live.poses is None  # the loop stops feeding
        last = doc["last"]
        assert last["stopped"] == "write error", last
        assert "No space left on device (ENOSPC)" in last["error"], last
        recording = _check_truth(path, rec, sent)
        assert last["frames"] == rec.stats.frames
        t_ns = [p.t_ns for p in recording.packets()]
        assert last["seconds_in_file"] == round((max(t_ns) - min(t_ns)) * 1e-9, 3)
        assert last["events"] == len(recording.json(rf.CONTROL_TOPIC)) >= 1
        with pytest.raises(ValueError, match="stopped on a write error"):
            live.stop()
        live.close()
        assert len(_error_lines(caplog)) == 1


@pytest.mark.timeout(30)
def test_live_recording_reports_a_full_queue_as_dropped(
    tmp_path: Path, rng: np.random.Generator, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(live_recording, "QUEUE_SIZE", 8)
    release = threading.Event()
    original_write = recorder_mod.McapSink.write

    def stalled_write(self: Any, item: Any) -> None:  # a disk that hangs
        release.wait(10.0)
        original_write(self, item)

    monkeypatch.setattr(recorder_mod.McapSink, "write", stalled_write)
    live = LiveRecording()
    path = tmp_path / "stalled.mcap"
    live.start(str(path), False, INPUTS, [])
    rec = live.packets
    assert rec is not None
    accepted = sum(
        rec.record_packet(
            "osc", rf.FORM_OSC_COMPACT, time.monotonic_ns(), _frame(rng, i)
        )
        for i in range(100)
    )
    doc = live.status()
    assert doc["dropped_queue_full"] == doc["dropped"] == 100 - accepted >= 90, doc
    assert doc["frames"] == 0 and doc["write_errors"] == 0 and doc["queued"] >= 1
    release.set()
    live.close()
    last = live.status()["last"]
    recording = rf.read_recording(path)
    assert recording.complete
    frames = sum(p.kind == rf.KIND_FRAME for p in recording.packets())
    assert last["frames"] == frames == accepted and last["queued"] == 0, last
    # The record_stop event met the still-full queue, or not: counted either way.
    events = [e["event"] for e in recording.json(rf.CONTROL_TOPIC)]
    assert events[0] == "record_start" and last["events"] == len(events)
    assert last["dropped_queue_full"] == 100 - accepted + 2 - len(events)
    assert last["stopped"] == "shutdown"
