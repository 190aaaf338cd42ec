"""The live half of the calibration-match check (issue 29 item 2; the check itself
and its offline use: ``test_calibration_match.py``): a daemon (real sockets on
127.0.0.1, every wait bounded) fed a performer its calibration does not fit reports
it in status and flags every later pose ``calibration_mismatch`` (bit 24); the
performer's own calibration stays quiet.
"""

from __future__ import annotations

import socket
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zmq
from live_harness import (
    EXACT_RIG,
    Live,
    OscSource,
    PoseSub,
    _f32,
    _prime,
    _take,
    _wait_until,
)

from retargetd.daemon.body.calibration import calibrate
from retargetd.daemon.body.rig import load_rig
from retargetd.protocols import pose_stream

pytestmark = pytest.mark.timeout(120)


def test_live_daemon_reports_a_mismatched_performer_in_status(
    start_daemon: Callable[..., Live],
    udp_socket: Callable[..., socket.socket],
    zmq_socket: Callable[[int], Any],
    tmp_path: Path,
) -> None:
    take = _take()
    rig = load_rig(EXACT_RIG)
    base = _f32(take.markers_world[take.base_pose_frames]).copy()
    base[:, take.labels.index("LTHI")] += np.array([0.0, 0.0, 0.020])
    path = tmp_path / "moved.json"
    calibrate(rig, base, take.labels).save(path)
    live = start_daemon(
        {"performer": {"rig": str(EXACT_RIG), "calibration": str(path)}}
    )
    sub = PoseSub(zmq_socket(zmq.SUB), live.tcp("zmq poses"))
    src = OscSource(udp_socket(), live.udp("osc markers"), live=live)
    src.announce()
    frames = iter(range(take.markers_world.shape[0]))
    # the subscriber connected before the frames that matter (slow joiner): poses
    # of the hold, sent from source time 0
    _prime(sub, lambda: src.send(take.markers_world[next(frames)]))
    # on to 1.5 s of source time: the window (source clock) ends at 1 s
    while src.next_id < int(1.5 * take.rate_hz):
        src.send(take.markers_world[next(frames)])
        time.sleep(0.002)

    def performer() -> dict[str, Any]:
        doc: dict[str, Any] = live.ctl({"cmd": "status"})["status"]["performers"][0]
        return doc

    _wait_until(lambda: performer()["calibration_match"] is not None, "the check")
    doc = performer()["calibration_match"]
    assert doc["matches"] is False
    assert "l_thigh" in doc["warning"] and "match" in doc["warning"]
    assert doc["segments"]["l_thigh"]["matches"] is False
    assert doc["segments"]["pelvis"]["matches"] is True
    # every pose after the check carries the calibration_mismatch flag; none before
    sub.clear()
    last = src.send(take.markers_world[next(frames)])
    sub.wait(lambda: bool(sub.poses) and sub.poses[-1].frame_id == last, "a pose")
    assert sub.poses[-1].flags & pose_stream.FRAME_CALIBRATION_MISMATCH


def test_live_daemon_own_calibration_stays_quiet(
    start_daemon: Callable[..., Live],
    udp_socket: Callable[..., socket.socket],
    exact_calibration: Path,
) -> None:
    take = _take()
    live = start_daemon(
        {"performer": {"rig": str(EXACT_RIG), "calibration": str(exact_calibration)}}
    )
    src = OscSource(udp_socket(), live.udp("osc markers"), live=live)
    src.announce()
    for k in range(int(1.2 * take.rate_hz)):
        src.send(take.markers_world[k])
        time.sleep(0.002)

    def check() -> Any:
        return live.ctl({"cmd": "status"})["status"]["performers"][0][
            "calibration_match"
        ]

    _wait_until(lambda: check() is not None, "the check")
    assert check()["matches"] is True and check()["warning"] is None
