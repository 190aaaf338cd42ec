"""Live calibration is as careful as offline (issue 29 item 4): a still performer who
is 10x too large (a unit slip), mirrored (left and right labels swapped) or degenerate
(every marker on one point, or too few markers) is refused by ``ctl calibrate``; the
reason reaches the ``ctl`` client (exit 1, its one line), ``calibrations_refused``
counts it, the old calibration keeps streaming and its file stays byte-identical. A
genuine still performer still calibrates and ``ctl`` says so (exit 0).

Real sockets on 127.0.0.1 (the harness's daemon in a thread, an OSC marker source,
the ``ctl`` CLI over the control socket); every wait has a deadline.
"""

from __future__ import annotations

import errno
import os
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import live_harness as _live
import numpy as np
import pytest

from retargetd.daemon.body import sanity
from retargetd.daemon.body.calibration import Calibration, load_calibration
from retargetd.daemon.cli.main import main as cli_main
from retargetd.daemon.live import calibrate as calibrate_module
from retargetd.daemon.live.calibrate import marker_drift_speeds_m_s
from retargetd.protocols.marker_input import LabelSet

_take = _live._take
#: Frames a calibration averages here (a third of a second at the source's 100 Hz).
COUNT = 10


def _hold() -> np.ndarray:
    """The exact T-pose hold (frames, markers, 3), metres, world."""
    return np.asarray(_take().markers_world[_take().base_pose_frames])


def _mirror_columns(labels: tuple[str, ...]) -> list[int]:
    """Column order that puts each L* marker where its R* twin is and back: the
    performer as a left/right label swap gives it."""
    index = {name: i for i, name in enumerate(labels)}
    out = []
    for i, name in enumerate(labels):
        twin = {"L": "R", "R": "L"}.get(name[:1], "") + name[1:]
        out.append(index.get(twin, i) if name[:1] in "LR" else i)
    return out


def _performer(case: str) -> tuple[tuple[str, ...], np.ndarray]:
    """(labels, frames) of the still performer ``case`` sends."""
    labels, hold = tuple(_take().labels), _hold()
    if case == "giant":  # a unit slip: 10x
        return labels, hold * 10.0
    if case == "mirrored":
        return labels, hold[:, _mirror_columns(labels)]
    if case == "collapsed":  # every marker on the first one (a stuck stream)
        return labels, np.repeat(hold[:, :1], hold.shape[1], axis=1)
    if case == "few":  # the left leg's markers alone: the rest never seen
        keep = [i for i, n in enumerate(labels) if n[1:] in _LEG]
        keep = [i for i in keep if labels[i].startswith("L")]
        return tuple(labels[i] for i in keep), hold[:, keep]
    assert case == "genuine"
    return labels, hold


_LEG = {"THI", "KNL", "KNM", "TIB", "ANL", "ANM", "HEE", "TOE", "MT1", "MT5"}

#: What the refusal's line says, per case.
REASON = {
    "giant": "span",
    "mirrored": "mirrored",
    "collapsed": "degenerate",
    "few": "never all seen",
}


class _Streamer(threading.Thread):
    """Streams ``frames`` (cycled) at ~200 Hz under ``labels`` until stopped."""

    def __init__(self, src: Any, labels: tuple[str, ...], frames: np.ndarray) -> None:
        super().__init__(name="test-streamer", daemon=True)
        self.src = src
        self.src.label_set = LabelSet(7, labels)
        self.frames = frames
        self.stop_event = threading.Event()

    def run(self) -> None:
        k = 0
        while not self.stop_event.is_set():
            if k % 50 == 0:
                self.src.announce()
            self.src.send(self.frames[k % len(self.frames)])
            k += 1
            time.sleep(0.005)

    def stop(self) -> None:
        self.stop_event.set()
        self.join(timeout=_live.WAIT_S)
        assert not self.is_alive()


@pytest.fixture
def stream() -> Iterator[Callable[..., _Streamer]]:
    made: list[_Streamer] = []

    def make(src: Any, case: str) -> _Streamer:
        s = _Streamer(src, *_performer(case))
        made.append(s)
        s.start()
        return s

    yield make
    for s in made:
        s.stop()


def _ctl_calibrate(live: Any) -> list[str]:
    return [
        "ctl", "--endpoint", live.tcp("control"), "--timeout-ms",
        str(int(_live.WAIT_S * 1000)), "calibrate", "--count", str(COUNT),
        "--wait-s", str(_live.WAIT_S),
    ]  # fmt: skip


class _Session:
    """A daemon on a copy of the exact calibration, the performer ``case`` streaming."""

    def __init__(
        self,
        start_daemon: Callable[..., Any],
        osc_source: Callable[..., Any],
        stream: Callable[..., _Streamer],
        exact_calibration: Path,
        tmp_path: Path,
        case: str,
    ) -> None:
        self.cal_path = tmp_path / "performer.json"
        self.cal_path.write_bytes(exact_calibration.read_bytes())
        self.before = self.cal_path.read_bytes()
        self.live = start_daemon(
            {
                "performer": {"calibration": str(self.cal_path)},
                "control": {"min_interval_s": 0.01},
            }
        )
        self.first_cal = self.live.daemon.calibration
        stream(osc_source(self.live), case)

    def __iter__(self) -> Iterator[Any]:
        """``live, cal_path, before, first_cal``."""
        return iter((self.live, self.cal_path, self.before, self.first_cal))


@pytest.fixture
def session(
    start_daemon: Callable[..., Any],
    osc_source: Callable[..., Any],
    stream: Callable[..., _Streamer],
    exact_calibration: Path,
    tmp_path: Path,
) -> Callable[[str], _Session]:
    """``session(case)``: a :class:`_Session` with the performer ``case``."""
    return lambda case: _Session(
        start_daemon, osc_source, stream, exact_calibration, tmp_path, case
    )


def test_the_bad_performers_are_what_the_checks_refuse() -> None:
    """The cases are what they claim, judged offline by the same function (so the
    live test below fails if the live path skips it)."""
    from retargetd.daemon.body.rig import load_rig

    rig = load_rig(_live.EXACT_RIG)
    source = sanity.BasePoseSource(rate_hz=_live.RATE_HZ)
    labels, frames = _performer("genuine")
    sanity.calibrate_checked(rig, frames[:COUNT], labels, source)
    assert max(sanity.mirror_angles_deg(rig, frames, labels).values()) < 1.0
    labels, frames = _performer("mirrored")
    assert min(sanity.mirror_angles_deg(rig, frames, labels).values()) > 179.0
    for case, reason in REASON.items():
        labels, frames = _performer(case)
        with pytest.raises(ValueError, match=reason):
            sanity.calibrate_checked(rig, frames[:COUNT], labels, source)


@pytest.mark.parametrize("case", list(REASON))
def test_a_bad_still_performer_is_refused_live_and_ctl_told(
    session: Callable[[str], _Session],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    case: str,
) -> None:
    live, cal_path, before, first_cal = session(case)
    capsys.readouterr()
    assert cli_main(_ctl_calibrate(live)) == 1
    out, err = capsys.readouterr()
    assert f"calibrating over the next {COUNT} frames" in out
    lines = err.strip().splitlines()
    assert len(lines) == 1, lines
    assert lines[0].startswith("retargetd ctl: calibration refused: "), lines
    assert REASON[case] in lines[0], lines
    assert "the old calibration is kept" in lines[0]
    status = live.ctl({"cmd": "status"})["status"]
    assert status["counters"]["calibrations_refused"] == 1
    assert status["counters"]["calibrations"] == 0
    assert status["calibration_state"] == "refused"
    assert status["calibration_message"] in lines[0]
    assert any(ln.startswith("calibration refused") for ln in live.lines)
    assert live.daemon.calibration is first_cal  # the old one streams on
    assert cal_path.read_bytes() == before  # and its file is untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["performer.json"]


def test_a_genuine_still_performer_calibrates_and_ctl_says_so(
    session: Callable[[str], _Session],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    live, cal_path, before, first_cal = session("genuine")
    capsys.readouterr()
    assert cli_main(_ctl_calibrate(live)) == 0
    out = capsys.readouterr().out
    assert f"calibrated on {COUNT} frames; saved {cal_path}" in out, out
    status = live.ctl({"cmd": "status"})["status"]
    assert status["counters"]["calibrations"] == 1
    assert status["counters"]["calibrations_refused"] == 0
    assert status["calibration_state"] == "calibrated"
    assert live.daemon.calibration is not first_cal
    assert cal_path.read_bytes() != before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["performer.json"]


def test_a_live_save_on_a_full_disk_keeps_the_old_file(
    session: Callable[[str], _Session],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """ENOSPC at the fsync (simulated: the daemon's thread shares this process): the
    new calibration is in use, its file NOT written, the old one whole and readable,
    no temporary file left; ``ctl`` says so and exits 1."""
    from retargetd.daemon import files as calmod

    def enospc(*_args: object) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    live, cal_path, before, first_cal = session("genuine")
    monkeypatch.setattr(calmod.os, "fsync", enospc)
    capsys.readouterr()
    assert cli_main(_ctl_calibrate(live)) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "NOT saved" in err[0] and "No space left" in err[0], err
    monkeypatch.undo()
    status = live.ctl({"cmd": "status"})["status"]
    assert status["calibration_state"] == "not_saved"
    assert status["counters"]["calibrations"] == 1
    assert status["counters"]["calibration_save_failures"] == 1
    assert live.daemon.calibration is not first_cal  # taken, in use
    assert cal_path.read_bytes() == before
    load_calibration(cal_path)  # readable
    assert sorted(p.name for p in tmp_path.iterdir()) == ["performer.json"]


@pytest.mark.parametrize("n", [2, 3, 5, 10])
def test_the_live_drift_check_judges_any_window(n: int) -> None:
    """Issue 29 item 5 for the live check: a window of any length >= 2 frames is
    judged (a walk refused at 1.3 m/s, the hold still), not skipped."""
    hold = _hold()[0]
    times = np.arange(n) / _live.RATE_HZ
    walk = np.stack([hold + np.array([1.3 * t, 0.0, 0.0]) for t in times])
    still = np.stack([hold] * n)
    assert np.nanmax(marker_drift_speeds_m_s(walk, times)) == pytest.approx(1.3)
    assert np.nanmax(marker_drift_speeds_m_s(still, times)) == 0.0


@pytest.mark.timeout(120)
def test_a_live_calibrations_file_is_written_off_the_loop_and_ctl_waits_for_it(
    session: Callable[[str], _Session],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Before: the frame that completed a live calibration also wrote its file, with
    fsync, in the loop (12-16 ms; a stalled disk held every frame). Now a worker
    writes it: here a writer held at a gate (a disk that does not answer) while the
    loop goes on sending poses with the new calibration and answering ``status``
    ("saving"); ``ctl calibrate`` waits through the save and answers its true
    outcome; a write that fails is counted."""
    gate, begun = threading.Event(), []
    real = Calibration.save

    def held(self: Calibration, path: str | Path) -> None:
        begun.append(1)
        assert gate.wait(60.0), "the test never opened the gate"
        if gate.is_set() and len(begun) > 1:  # the second write: a full disk
            raise OSError(errno.ENOSPC, f"cannot write {path}: No space left")
        real(self, path)

    monkeypatch.setattr(Calibration, "save", held)
    live, cal_path, before, first_cal = session("genuine")
    rc: list[int] = []
    ctl = threading.Thread(target=lambda: rc.append(cli_main(_ctl_calibrate(live))))
    ctl.start()
    try:
        _live._wait_until(lambda: begun == [1], "the calibration's write begun")
        out = live.status()["counters"]["frames_out"]
        _live._wait_until(
            lambda: live.status()["counters"]["frames_out"] >= out + 20,
            "poses sent while the write hangs",
        )
        status = live.status()
        assert status["calibration_state"] == "saving", status
        assert status["performers"][0]["calibration_saving"]
        assert live.daemon.calibration is not first_cal  # in use already
        assert cal_path.read_bytes() == before and ctl.is_alive() and not rc
    finally:
        gate.set()
    ctl.join(_live.WAIT_S)
    assert rc == [0], capsys.readouterr()
    assert f"calibrated on {COUNT} frames; saved {cal_path}" in capsys.readouterr().out
    status = live.status()
    assert status["calibration_state"] == "calibrated"
    assert not status["performers"][0]["calibration_saving"]
    assert cal_path.read_bytes() != before
    # A write that fails: counted, the state and ctl say so, the loop serves on.
    assert cli_main(_ctl_calibrate(live)) == 1
    err = capsys.readouterr().err
    assert "NOT saved" in err and "No space left" in err, err
    status = live.status()
    assert status["calibration_state"] == "not_saved"
    assert status["counters"]["calibration_save_failures"] == 1
    out = status["counters"]["frames_out"]
    _live._wait_until(
        lambda: live.status()["counters"]["frames_out"] >= out + 10,
        "poses after the failed write",
    )
    load_calibration(cal_path)  # the first write's file, whole


@pytest.mark.timeout(120)
def test_an_internal_error_in_the_checks_is_counted_and_the_daemon_serves_on(
    start_daemon: Callable[..., Any],
    osc_source: Callable[..., Any],
    stream: Callable[..., _Streamer],
    vmc: _live.VmcReceiver,
    exact_calibration: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """``calibrate_checked`` raising something other than a refusal (a fault of
    ours) used to propagate out of the loop and end the daemon. Now it is counted,
    said in one line, the old calibration kept, and the loop goes on sending VMC
    and answering ``status``; the next calibration is taken."""

    def broken(*_args: object, **_kwargs: object) -> None:
        raise TypeError("a bug of ours")

    cal_path = tmp_path / "performer.json"
    cal_path.write_bytes(exact_calibration.read_bytes())
    before = cal_path.read_bytes()
    live = start_daemon(
        {
            "performer": {"calibration": str(cal_path)},
            "control": {"min_interval_s": 0.01},
        },
        vmc_port=vmc.port,
    )
    first_cal = live.daemon.calibration
    stream(osc_source(live), "genuine")
    monkeypatch.setattr(calibrate_module, "calibrate_checked", broken)
    capsys.readouterr()
    assert cli_main(_ctl_calibrate(live)) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith(
        "retargetd ctl: calibration failed: internal error (TypeError: a bug of ours)"
    ), err
    assert "the old calibration is kept" in err[0]
    assert live.running  # the loop did not die
    status = live.status()
    assert status["counters"]["calibration_failures"] == 1
    assert status["counters"]["calibrations"] == 0
    assert status["counters"]["calibrations_refused"] == 0
    assert status["calibration_state"] == "failed"
    assert sum(ln.startswith("calibration failed") for ln in live.lines) == 1
    assert live.daemon.calibration is first_cal and cal_path.read_bytes() == before
    # VMC after the failure: the datagrams sent before it drained (reading is far
    # faster than the ~200 Hz they arrive at), then fresh ones received.
    vmc.sock.setblocking(False)
    for _ in range(1_000_000):
        try:
            vmc.sock.recv(65536)
        except BlockingIOError:
            break
    vmc.sock.settimeout(0.05)
    n = len(vmc.frames)
    deadline = time.monotonic() + _live.WAIT_S
    while len(vmc.frames) < n + 10:
        assert time.monotonic() < deadline, "no VMC frame after the failure"
        vmc.pump(50)
    out = status["counters"]["frames_out"]
    _live._wait_until(
        lambda: live.status()["counters"]["frames_out"] >= out + 10,
        "poses after the failure",
    )
    monkeypatch.undo()  # the real checks: the next calibration is taken
    assert cli_main(_ctl_calibrate(live)) == 0, capsys.readouterr()
    assert live.status()["calibration_state"] == "calibrated"
    assert live.daemon.calibration is not first_cal and live.running
