"""``[loop] prewarm_ms`` (daemon/live/prewarm.py): the loop touches the fit shortly
before a steady stream's next frame, on a scratch solver that shares the model, and
what the stream sees does not change."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zmq
from live_harness import Live, OscSource, PoseSub, _fit_oracle, _prime, _take

from retargetd.daemon.live.prewarm import Prewarm

MS = 1_000_000


def _steady(p: Prewarm, period_ns: int, n: int, jitter: float = 0.0) -> int:
    rng = np.random.default_rng(1)
    t = 10**12
    for _ in range(n):
        t += int(period_ns * (1.0 + jitter * rng.uniform(-1.0, 1.0)))
        p.observe(t)
    return t


def test_a_steady_stream_is_predicted_and_touched_once_per_frame() -> None:
    period = 4_166_667  # 240 Hz
    p = Prewarm(1.5)
    last = _steady(p, period, 50, jitter=0.02)
    due = p.next_ns()
    assert abs(due - (last + period)) < 0.05 * period
    # just after the frame: the poll waits until the touch, in whole ms, not past it
    w = p.wait_ms(last + 100_000, 100)
    assert w == (due - 1_500_000 - last - 100_000) // MS and 1 <= w <= 3
    assert not p.due(last + 100_000)
    assert p.due(due - 1_800_000)  # within the ms the poll rounds to
    p.touch()  # nothing registered: nothing solved, but this frame is done
    assert p.touches == 0 and not p.due(due - 1_700_000)
    assert p.wait_ms(due - 1_700_000, 100) == 100  # no second wake-up for it
    p.observe(last + period)  # the next frame: armed again
    assert p.next_ns() > due


@pytest.mark.parametrize(
    ("lead_ms", "period_ns", "jitter"),
    [
        (1.5, 4_166_667, 0.6),  # not steady (a replay sent as fast as it can)
        (1.5, 1_000_000, 0.0),  # 1000 Hz: warm anyway, under 2 x the lead
        (0.0, 4_166_667, 0.0),  # off
    ],
)
def test_no_touch_when_off_too_fast_or_not_steady(
    lead_ms: float, period_ns: int, jitter: float
) -> None:
    p = Prewarm(lead_ms)
    last = _steady(p, period_ns, 60, jitter)
    assert p.next_ns() == -1
    assert p.wait_ms(last + 1000, 100) == 100
    assert not any(p.due(last + k * 100_000) for k in range(60))


@pytest.mark.timeout(120)
def test_the_daemon_touches_the_fit_and_streams_the_same_poses(
    start_daemon: Callable[..., Live],
    osc_source: Callable[..., OscSource],
    zmq_socket: Callable[[int], Any],
    exact_calibration: Path,
) -> None:
    """A 100 Hz stream to a fit daemon: the loop touches the fit before frames (the
    ``prewarm`` counter), and the poses still equal an offline fit of the same
    frames, as without the touch (test_live.py::test_fit_method_live_equals_batch)."""
    take = _take()
    live = start_daemon(
        {
            "performer": {"calibration": str(exact_calibration)},
            "solve": {"method": "fit"},
            "loop": {"process_every_frame": True, "prewarm_ms": 1.5},
        },
    )
    sub = PoseSub(zmq_socket(zmq.SUB), live.tcp("zmq poses"))
    src = osc_source(live)
    src.announce()
    _prime(sub, lambda: src.send(take.markers_world[0]))
    n0 = len(src.sent)
    rows = range(100, 250)
    src.send_paced([take.markers_world[row] for row in rows], 100.0)
    sub.wait(lambda: len(sub.poses) >= len(rows), "the fitted poses", 30.0)
    touches = live.ctl({"cmd": "status"})["status"]["counters"]["prewarm"]
    want = [q for q, _ in _fit_oracle(exact_calibration, [m for _, m in src.sent])]
    got = np.stack([p.world_from_bone_quat for p in sub.poses[-len(rows) :]])
    dots = np.abs(np.sum(got.astype(np.float64) * np.stack(want[n0:]), axis=-1))
    print(f"\nprewarm: {touches} touches over {len(rows)} paced frames")
    assert touches >= len(rows) // 2  # most frames (the first few set the period)
    assert dots.min() > 1.0 - 1e-6, dots.min()


class _Scratch:
    """A scratch solver stand-in: its solve flags the pose and takes ``sleep_s``."""

    def __init__(self, flags: int, sleep_s: float) -> None:
        self.flags, self.sleep_s, self.resets = flags, sleep_s, 0

    def solve_frame(self, markers: Any, pose: Any) -> Any:
        time.sleep(self.sleep_s)  # never returns early
        pose.frame_flags = self.flags
        return pose

    def reset(self) -> None:
        self.resets += 1


class _Pose:
    frame_flags = 0


class _Frame:
    markers_world = np.zeros((3, 3))


def test_a_flagged_or_slow_touch_resets_its_scratch_and_counts() -> None:
    from retargetd.protocols.pose_stream import FRAME_RESEEDED, FRAME_UNEXPLAINED

    p = Prewarm(1.5)
    ok = _Scratch(FRAME_RESEEDED, 0.0)  # reseeded alone: a pose explains them
    lost = _Scratch(FRAME_UNEXPLAINED, 0.0)
    slow = _Scratch(0, 0.002)  # longer than the 1.5 ms lead
    p._scratch = {
        (0, k): (s, _Pose(), _Frame()) for k, s in enumerate((ok, lost, slow))
    }
    p.touch()
    assert p.touches == 3 and p.resets == 2
    assert (ok.resets, lost.resets, slow.resets) == (0, 1, 1)
