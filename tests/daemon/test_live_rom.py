"""Live range of motion (``ctl calibrate --rom --seconds S``, issue 29 item 1): after
the base pose the daemon collects S seconds of the performer moving each joint and
places the rig's functional joints from them, with the offline checks.

The synthetic performer wearing Plug-in Gait holds its static, then does the ``rom``
motion, streamed over OSC with frame numbers at 100 Hz (the daemon times the range of
motion by them). The hip centres the daemon places are checked against the truth.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import live_harness as _live
import numpy as np
import pytest

from retargetd.daemon.body.calibration import calibrate, load_calibration
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.cli.main import main as cli_main
from retargetd.daemon.synth import performer as pf
from retargetd.protocols.marker_input import LabelSet

#: Base-pose frames the calibration averages; seconds of range of motion asked for.
COUNT = 20
ROM_S = 22.0
#: The streamer's rate (the daemon reads source time = frame number / 100 Hz).
RATE_HZ = _live.RATE_HZ
#: What issue 29 asks of a functional hip centre: within 10 mm of the truth.
CENTRE_TOL_M = 0.010


@functools.cache
def _take() -> pf.SynthTake:
    """The Plug-in Gait performer: 1 s of its static, then the range of motion."""
    return pf.synthesize(
        seconds=1.0 + ROM_S + 2.0, rate_hz=RATE_HZ, markerset="plug-in-gait",
        motions=("rom",), noise_mm=0.5, seed=5,
    )  # fmt: skip


def _status(live: Any) -> dict[str, Any]:
    status: dict[str, Any] = live.ctl({"cmd": "status"})["status"]
    return status


def _wait_state(live: Any, src: Any, hold: np.ndarray, states: tuple[str, ...]) -> str:
    """Stream the static until the calibration's state is one of ``states``."""
    deadline = time.monotonic() + _live.WAIT_S
    k = 0
    while time.monotonic() < deadline:
        src.send(hold[k % len(hold)])
        k += 1
        if k % 10 == 0:
            state = str(_status(live)["calibration_state"])
            if state in states:
                return state
        time.sleep(0.005)
    raise AssertionError(f"calibration never reached {states}")


def _daemon(start_daemon: Callable[..., Any], tmp_path: Path) -> tuple[Any, Path]:
    take = _take()
    rig = load_rig("plug-in-gait")
    cal_path = tmp_path / "performer.json"
    calibrate(rig, take.markers_world[take.base_pose_frames], take.labels).save(
        cal_path
    )
    live = start_daemon(
        {
            "performer": {"rig": "plug-in-gait", "calibration": str(cal_path)},
            "control": {"min_interval_s": 0.01},
        }
    )
    return live, cal_path


def test_live_rom_places_the_hips_and_says_which(
    start_daemon: Callable[..., Any],
    osc_source: Callable[..., Any],
    tmp_path: Path,
) -> None:
    take = _take()
    live, cal_path = _daemon(start_daemon, tmp_path)
    src = osc_source(live)
    src.label_set = LabelSet(3, take.labels)
    src.announce()
    hold = np.asarray(take.markers_world[take.base_pose_frames])
    reply = live.ctl({"cmd": "calibrate", "count": COUNT, "rom_s": ROM_S})
    assert reply["ok"], reply
    assert f"move each joint through its range for {ROM_S:g} s" in reply["message"]
    assert _wait_state(live, src, hold, ("rom", "refused")) == "rom"
    assert any(line.endswith(f"for {ROM_S:g} s") for line in live.lines), live.lines
    # The range of motion, every frame (a frame the daemon drops is not collected;
    # the span is timed by frame numbers all the same).
    rom = take.markers_world[take.base_pose_frames.stop :]
    deadline = time.monotonic() + _live.WAIT_S
    state = "rom"
    for k, frame in enumerate(rom):
        src.send(frame)
        if k % 50 == 0:
            time.sleep(0.02)  # let the loop keep up
    while state in ("rom", "saving") and time.monotonic() < deadline:
        time.sleep(0.05)
        state = str(_status(live)["calibration_state"])
    status = _status(live)
    assert state == "calibrated", status["calibration_message"]
    message = status["calibration_message"]
    print(f"\nlive range of motion: {message}")
    assert "frames of range of motion (placed: " in message, message
    assert "LHJC" in message and "RHJC" in message, message
    assert status["counters"]["calibrations"] == 1
    # The saved calibration's hips: where the truth's are, in the pelvis frame.
    cal = load_calibration(cal_path)
    joints = cal.functional["joints"]
    assert joints["LHJC"]["used"] and joints["RHJC"]["used"], joints
    assert cal.base_pose["live"] is True
    rig = load_rig("plug-in-gait")
    offline = calibrate(
        rig,
        hold[:COUNT],
        take.labels,
        rom=(rom[: int(ROM_S * RATE_HZ)], take.labels, {}),
    )
    for point in ("LHJC", "RHJC"):
        live_off = np.asarray(cal.point_offsets)[cal.point_names.index(point)]
        off_off = np.asarray(offline.point_offsets)[offline.point_names.index(point)]
        # the same estimator on (nearly) the same frames: the same centre
        gap = float(np.linalg.norm(live_off - off_off))
        print(f"{point}: live vs offline on the same frames {1000 * gap:.2f} mm")
        assert gap < CENTRE_TOL_M, (live_off, off_off)


def test_live_rom_is_refused_for_a_rig_without_functional_joints(
    start_daemon: Callable[..., Any],
    exact_calibration: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    # the harness's exact rig: no [functional] table (its calibration is not written)
    live = start_daemon({"performer": {"calibration": str(exact_calibration)}})
    argv = ["ctl", "--endpoint", live.tcp("control"), "--timeout-ms",
            str(int(_live.WAIT_S * 1000)), "calibrate",
            "--rom", "--seconds", "5"]  # fmt: skip
    assert cli_main(argv) == 1
    err = capsys.readouterr().err
    assert "has no [functional] joints: a range of motion has nothing to place" in err
    for bad in (0.5, 500, "ten", True):
        reply = live.ctl({"cmd": "calibrate", "rom_s": bad})
        assert not reply["ok"] and "seconds of range of motion" in reply["error"]
    assert cli_main([*argv[:-3], "--seconds", "5"]) == 2  # --seconds needs --rom
    assert "--seconds needs --rom" in capsys.readouterr().err
    assert _status(live)["counters"]["calibrations"] == 0
