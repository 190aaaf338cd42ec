"""Nothing built or written off the loop kills the daemon (issue 30 items 2 and 6:
"the daemon never dies from a file"; "no pose gap over 100 ms the source did not
cause").

Before: a stream's pipeline built on the worker (``live/rebuild.py``) that raised
(a calibration the fit cannot use, a fault of ours) was raised again in the loop when
the first frame took it (``pipelines.Pipelines._swap``): the loop died, every output
with it. Now the failure is counted (``pipeline_failures``), said in one line naming
the performer, that stream's frames counted ``unsolved_failed``; the loop answers
``ctl status`` and serves on, and a reload (or a new label set) builds it again.

A live daemon on loopback serving in its own thread (``live_harness.Live``); the
builder is monkeypatched to raise.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import live_harness as lh
import numpy as np
import pytest

from retargetd.daemon.face.training import TrainingSet
from retargetd.daemon.live import face_only, rebuild
from retargetd.protocols import osc_in
from retargetd.protocols.marker_input import LabelSet


@pytest.mark.timeout(120)
def test_a_pipeline_build_that_raises_is_counted_and_the_loop_serves_on(
    start_daemon: Callable[..., lh.Live],
    osc_source: Callable[..., lh.OscSource],
    vmc: lh.VmcReceiver,
    exact_calibration: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    real = rebuild.body_solver
    broken = threading.Event()  # (set after the start's warm-up)

    def flaky(*args: Any) -> Any:
        if broken.is_set():
            raise ValueError("a calibration the fit cannot use\nsecond line")
        return real(*args)

    monkeypatch.setattr(rebuild, "body_solver", flaky)
    live = start_daemon(
        {
            "performer": {
                "rig": str(lh.EXACT_RIG),
                "calibration": str(exact_calibration),
            },
            "control": {"min_interval_s": 0.01},
        },
        vmc_port=vmc.port,
    )
    broken.set()
    src = osc_source(live)
    take = lh._take()
    rows = [take.markers_world[i % take.n_frames] for i in range(400)]
    src.announce(wait=False)
    k = 0
    deadline = time.monotonic() + lh.WAIT_S
    while live.status()["counters"]["pipeline_failures"] == 0:
        assert time.monotonic() < deadline, "the failed build was never counted"
        src.send(rows[k % len(rows)])
        k += 1
        time.sleep(0.01)
    # The loop lives on: frames still read, answered, counted unsolved.
    before = live.status()["counters"]
    for _ in range(20):
        src.send(rows[k % len(rows)])
        k += 1
        time.sleep(0.005)
    lh._wait_until(
        lambda: live.status()["counters"]["frames_in"] >= before["frames_in"] + 20,
        "the frames after the failure read",
    )
    c = live.status()["counters"]
    assert live.running
    assert c["pipeline_failures"] == 1  # not tried again for the same labels
    assert c["unsolved_failed"] >= before["unsolved_failed"] + 20
    assert c["frames_in"] == c["frames_solved"] + c["stale"] + c["unsolved"]
    assert c["frames_out"] == 0 and live.status()["pipelines_building"] == 0
    failed = [line for line in live.lines if "failed to build" in line]
    assert failed == [
        "performer (default): its pipeline for "
        f"{len(take.labels)} labels failed to build (ValueError: a calibration "
        "the fit cannot use); its frames unsolved until a new label set, reload "
        "or calibration; pipeline_failures 1"
    ], live.lines
    # A reload (its files unchanged) tries again; the builder fixed, poses flow.
    broken.clear()
    assert live.ctl({"cmd": "reload"})["ok"]
    deadline = time.monotonic() + lh.WAIT_S
    while len(vmc.frames) < 5:
        assert time.monotonic() < deadline, "no pose after the reload"
        src.send(rows[k % len(rows)])
        k += 1
        vmc.pump(max_datagrams=50)
    c = live.status()["counters"]
    assert c["pipeline_failures"] == 1 and c["frames_out"] >= 5
    assert c["pipeline_builds"] == 1
    # A new label set whose build raises again: counted again, the loop serves.
    broken.set()
    src.label_set = LabelSet(2, (*take.labels, "EXTRA"))
    src.raw(osc_in.encode_labels(src.label_set))
    deadline = time.monotonic() + lh.WAIT_S
    while live.status()["counters"]["pipeline_failures"] < 2:
        assert time.monotonic() < deadline, "the second failure was never counted"
        src.send(np.append(rows[k % len(rows)], [[0.0, 0.0, 0.0]], axis=0))
        k += 1
        time.sleep(0.01)
    assert live.running and live.status()["counters"]["pipeline_failures"] == 2


@pytest.mark.timeout(120)
def test_a_face_only_stage_build_that_raises_is_counted_and_the_loop_serves_on(
    start_daemon: Callable[..., lh.Live],
    osc_source: Callable[..., lh.OscSource],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The same for a performer with a face and no body: its stage's build raised
    in the loop (``face_only.FacePath._stage``); now counted, one line, its frames
    ``unsolved_failed``, the loop answering."""
    npz = tmp_path / "face.npz"
    layout = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0]])
    TrainingSet(
        head_names=("LFHD", "RFHD", "LBHD"), marker_names=("F1", "F2"),
        expression_names=("jawOpen",), head_layout=layout,
        neutral=np.array([[0.0, 0.05, -0.05], [0.05, 0.0, -0.05]]),
        deltas=np.array([[[0.0, 0.0, 0.01], [0.0, 0.01, 0.0]]]),
    ).save(npz)  # fmt: skip

    def broken(*args: Any) -> Any:
        raise RuntimeError("a fault of ours\nsecond line")

    live = start_daemon(
        {
            "performer": {"body": False},
            "face": {"enabled": True, "config": "arkit52", "training": str(npz)},
        }
    )
    monkeypatch.setattr(face_only, "build_stage", broken)
    src = osc_source(live)
    src.label_set = LabelSet(4, ("LFHD", "RFHD", "LBHD", "F1", "F2"))
    src.announce(wait=False)
    row = np.array(
        [[0.0, 0.0, 1.7], [0.1, 0.0, 1.7], [0.0, 0.1, 1.7], [0.0, 0.05, 1.65],
         [0.05, 0.0, 1.65]]
    )  # fmt: skip
    deadline = time.monotonic() + lh.WAIT_S
    while live.status()["counters"]["pipeline_failures"] == 0:
        assert time.monotonic() < deadline, "the failed build was never counted"
        src.send(row)
        time.sleep(0.01)
    before = live.status()["counters"]["unsolved_failed"]
    for _ in range(10):
        src.send(row)
        time.sleep(0.005)
    lh._wait_until(
        lambda: live.status()["counters"]["unsolved_failed"] >= before + 10,
        "the frames after the failure counted",
    )
    c = live.status()["counters"]
    assert live.running and c["pipeline_failures"] == 1
    assert c["frames_in"] == c["frames_solved"] + c["stale"] + c["unsolved"]
    failed = [line for line in live.lines if "failed to build" in line]
    assert failed == [
        "performer (default): its face stage for 5 labels failed to build "
        "(RuntimeError: a fault of ours); its frames unsolved until a new label "
        "set, reload or calibration; pipeline_failures 1"
    ], live.lines
