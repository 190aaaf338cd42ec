"""The live loop's one compiled call per frame (``one_call.FastFrame``: the packet's
feed, the body solve and the emit) in a running daemon: armed after the
calibration-match window on the default pipeline without a validator, it solves the
frames, and what they stream is the solver's (``test_feed_solve_emit.py`` compares
the call with the two it replaces byte for byte); a label announcement disarms it and
the next frames' two calls arm it again; with a ``[[pipeline]]`` stage it is never
armed."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zmq
from live_harness import (
    RATE_HZ,
    Live,
    OscSource,
    PoseSub,
    VmcReceiver,
    _prime,
    _solve_oracle,
    _take,
)

from retargetd.daemon.live.one_call import FAST_SOLVED, FastFrame
from retargetd.daemon.live.solve_emit import AVAILABLE

pytestmark = pytest.mark.skipif(
    not AVAILABLE, reason="the compiled clock is not time.monotonic_ns()'s here"
)


def _count(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """What each ``FastFrame.run`` returned (the drains call it on the armed path)."""
    got: list[int] = []
    run = FastFrame.run

    def counted(self: FastFrame, *args: Any) -> int:
        code = run(self, *args)
        got.append(code)
        return code

    monkeypatch.setattr(FastFrame, "run", counted)
    return got


@pytest.mark.timeout(120)
def test_one_call_solves_the_stream_and_rearms_after_labels(
    start_daemon: Callable[..., Live],
    osc_source: Callable[..., OscSource],
    zmq_socket: Callable[[int], Any],
    vmc: VmcReceiver,
    exact_calibration: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    take = _take()
    live = start_daemon(
        {
            "performer": {"calibration": str(exact_calibration)},
            "validate": {"enabled": False},
        },
        vmc_port=vmc.port,
    )
    calls = _count(monkeypatch)
    sub = PoseSub(zmq_socket(zmq.SUB), live.tcp("zmq poses"))
    src = osc_source(live)
    src.announce()
    _prime(sub, lambda: src.send(take.markers_world[0]))
    k = len(src.sent)
    stream = live.daemon.osc_stream
    marks = []
    rows = [*range(60, 300), *range(0, 60)]  # 3 s of source time, sent in 1.5 s
    for i, row in enumerate(rows):
        if i == 190:  # the labels again: the armed path is off until re-armed
            marks.append(len(calls))
            src.announce(wait=False)
        src.send(take.markers_world[row])
        sub.pump()
        time.sleep(0.005)
    n = len(src.sent)
    sub.wait(lambda: len(sub.poses) == n - k, f"{n - k} poses")
    vmc.wait_frames(n)
    live.stop()
    sub.pump(50)

    s = live.daemon.stats
    assert (s.frames_in, s.frames_solved, s.frames_out) == (n, n, n), (
        s.frames_in, s.frames_solved, s.frames_out,
    )  # fmt: skip
    assert live.daemon.osc_stream.counters.as_dict() == {"accepted": n}
    # One call solved most frames: from the end of the first second's match
    # window (100 frames of source time) on, and again after the announcement.
    solved = [c for c in calls if c == FAST_SOLVED]
    assert len(solved) == len(calls) and len(solved) > n // 2, (len(solved), n)
    assert sum(c == FAST_SOLVED for c in calls[marks[0] :]) > 50
    fast = stream.fast
    assert fast is not None and fast.epoch == live.daemon.shared.epoch
    # What went out is the solver's, frame for frame.
    assert [p.frame_id for p in sub.poses] == [fid for fid, _ in src.sent[k:]]
    oracle, _ = _solve_oracle(exact_calibration, [m for _, m in src.sent])
    for msg, (fid, _), (wfb, pfb, root, bone_flags) in zip(
        sub.poses, src.sent[k:], oracle[k:], strict=True
    ):
        assert msg.received_ns <= msg.solved_ns <= msg.sent_ns
        assert msg.source_time_s == fid / RATE_HZ
        np.testing.assert_array_equal(msg.bone_flags, bone_flags)
        np.testing.assert_allclose(
            msg.root_pos_world, root.astype(np.float32), rtol=0, atol=1e-7
        )
        np.testing.assert_allclose(
            msg.world_from_bone_quat, wfb.astype(np.float32), rtol=0, atol=1e-6
        )
        np.testing.assert_allclose(
            msg.rest_from_bone_quat, pfb.astype(np.float32), rtol=0, atol=1e-6
        )


@pytest.mark.timeout(120)
def test_a_pipeline_stage_keeps_the_two_calls(
    start_daemon: Callable[..., Live],
    osc_source: Callable[..., OscSource],
    zmq_socket: Callable[[int], Any],
    vmc: VmcReceiver,
    exact_calibration: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    take = _take()
    live = start_daemon(
        {
            "performer": {"calibration": str(exact_calibration)},
            "validate": {"enabled": False},
            "pipeline": [{"kind": "one_euro"}],
        },
        vmc_port=vmc.port,
    )
    calls = _count(monkeypatch)
    sub = PoseSub(zmq_socket(zmq.SUB), live.tcp("zmq poses"))
    src = osc_source(live)
    src.announce()
    _prime(sub, lambda: src.send(take.markers_world[0]))
    k = len(src.sent)
    for row in range(60, 220):
        src.send(take.markers_world[row])
        sub.pump()
        time.sleep(0.005)
    n = len(src.sent)
    sub.wait(lambda: len(sub.poses) == n - k, f"{n - k} poses")
    live.stop()
    assert live.daemon.stats.frames_out == n
    assert calls == [] and live.daemon.osc_stream.fast is None
