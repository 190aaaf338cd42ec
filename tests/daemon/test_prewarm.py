"""``[loop] prewarm_ms`` (daemon/live/prewarm.py): the loop touches the fit shortly
before a steady stream's next frame, on a scratch solver that shares the model, and
what the stream sees does not change."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import zmq
from fake_loop import Clock, Poller, run_passes
from live_harness import (
    EXACT_RIG,
    Live,
    OscSource,
    PoseSub,
    _fit_oracle,
    _prime,
    _take,
)

from retargetd.daemon.body.calibration import load_calibration
from retargetd.daemon.body.method import make_body_solver
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.live import prewarm
from retargetd.daemon.live.config import DaemonConfig
from retargetd.daemon.live.loop import Daemon
from retargetd.daemon.live.prewarm import Prewarm
from retargetd.protocols.pose_stream import FRAME_RESEEDED, FRAME_UNEXPLAINED

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
def test_the_daemon_streams_the_offline_fits_poses_with_the_touch_on(
    start_daemon: Callable[..., Live],
    osc_source: Callable[..., OscSource],
    zmq_socket: Callable[[int], Any],
    exact_calibration: Path,
) -> None:
    """A 100 Hz stream to a fit daemon over real sockets, the touch on: the poses
    still equal an offline fit of the same frames, as without the touch
    (test_live.py::test_fit_method_live_equals_batch)."""
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
    # How many frames are touched depends on the machine (a stream that a loaded
    # machine jitters is not touched): that the loop touches before the frame is
    # the loop test's below, on its own clock; that a touch leaves the poses as
    # they were, bit for bit, test_a_touch_changes_no_pose's.
    print(f"\nprewarm: {touches} touches over {len(rows)} paced frames")
    assert dots.min() > 1.0 - 1e-6, dots.min()


class _Scratch:
    """A scratch solver stand-in: its solve flags the pose and takes ``sleep_s``
    (on ``clock``, a fake monotonic clock in ns, when given: it moves it on)."""

    def __init__(
        self, flags: int, sleep_s: float, clock: list[int] | None = None
    ) -> None:
        self.flags, self.sleep_s, self.resets = flags, sleep_s, 0
        self.clock = clock

    def solve_frame(self, markers: Any, pose: Any) -> Any:
        if self.clock is None:
            time.sleep(self.sleep_s)  # never returns early
        else:
            self.clock[0] += round(self.sleep_s * 1e9)
        pose.frame_flags = self.flags
        return pose

    def reset(self) -> None:
        self.resets += 1


class _Pose:
    frame_flags = 0


class _Frame:
    markers_world = np.zeros((3, 3))


def test_a_flagged_or_slow_touch_resets_its_scratch_and_counts(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # The touch's own clock, moved only by the scratches: on the machine's, a touch
    # of no time preempted for the 1.5 ms lead (a loaded machine, the other xdist
    # worker's test beside it) was judged slow and reset (1 of 2 runs of the suite
    # under -n 2 at load 2.8-3.2).
    clock = [10**12]
    monkeypatch.setattr(prewarm, "time", SimpleNamespace(monotonic_ns=lambda: clock[0]))
    p = Prewarm(1.5)
    ok = _Scratch(FRAME_RESEEDED, 0.0, clock)  # reseeded alone: a pose explains them
    lost = _Scratch(FRAME_UNEXPLAINED, 0.0, clock)
    slow = _Scratch(0, 0.002, clock)  # longer than the 1.5 ms lead
    p._scratch = {
        (0, k): (s, _Pose(), _Frame()) for k, s in enumerate((ok, lost, slow))
    }
    p.touch()
    assert p.touches == 3 and p.resets == 2
    assert (ok.resets, lost.resets, slow.resets) == (0, 1, 1)


def _touch_daemon(clock: Clock, lead_ms: float, period_ns: int, jitter: float) -> Any:
    """A daemon (not opened) whose touch reads ``clock``, its cadence fed 40
    frames ``period_ns`` apart (jittered), the last one now, and one stand-in
    scratch registered."""
    d = Daemon(DaemonConfig.from_dict({"loop": {"prewarm_ms": lead_ms}}),
               out=lambda _line: None)  # fmt: skip
    p = d._prewarm
    p.clock = clock
    rng = np.random.default_rng(3)
    t = clock.t - 40 * period_ns
    for _ in range(40):
        t += int(period_ns * (1.0 + jitter * rng.uniform(-1.0, 1.0)))
        p.observe(t)
    clock.t = t
    p._scratch = {(0, 0): (_Scratch(0, 0.0), _Pose(), _Frame())}
    return d


def test_the_loop_touches_once_before_the_frame() -> None:
    """The loop itself on a fake poller and clock (100 Hz, lead 1.5 ms): it sleeps
    until the touch is due (8.5 ms: 8 whole ms), touches once, then sleeps its
    full timeout: no second wake-up for the same frame; the frame, when it comes,
    is served after the touch."""
    clock = Clock()
    d = _touch_daemon(clock, 1.5, 10 * MS, 0.0)
    try:
        p = d._prewarm
        last = p.last_ns
        poller = Poller(clock, lambda n: [("socket", 1)] if n == 3 else [])
        served = run_passes(d, poller, passes=3)
        assert poller.timeouts == [8, 100, 100]  # the 100 ms: the poll's default
        assert p.touches == 1 and p.touched_ns == last
        assert served == [[("socket", 1)]]  # the frame, after its touch
    finally:
        d.close()


@pytest.mark.parametrize(
    ("lead_ms", "period_ns", "jitter"),
    [(1.5, 10 * MS, 0.6), (1.5, MS, 0.0), (0.0, 10 * MS, 0.0)],
)
def test_the_loop_never_touches_when_off_too_fast_or_not_steady(
    lead_ms: float, period_ns: int, jitter: float
) -> None:
    clock = Clock()
    d = _touch_daemon(clock, lead_ms, period_ns, jitter)
    try:
        poller = Poller(clock, lambda n: [])
        run_passes(d, poller, passes=3)
        assert poller.timeouts == [100, 100, 100] and d._prewarm.touches == 0
    finally:
        d.close()


def test_a_touch_changes_no_pose(exact_calibration: Path) -> None:
    """A fit touched (on its scratch solver, the last frame's markers) before each
    frame gives the poses of the same fit untouched, bit for bit: the scratch
    shares only the model."""
    take = _take()
    rig, cal = load_rig(EXACT_RIG), load_calibration(exact_calibration)
    touched = make_body_solver("fit", rig, cal, take.labels)
    plain = make_body_solver("fit", rig, cal, take.labels)
    p = Prewarm(1.5)
    last = _Frame()
    last.markers_world = take.markers_world[99].copy()
    p.register((0, 0), touched, last)
    a, b = touched.new_pose(), plain.new_pose()
    for row in range(100, 160):
        p.touch()
        touched.solve_frame(take.markers_world[row], a)
        plain.solve_frame(take.markers_world[row], b)
        last.markers_world[:] = take.markers_world[row]
        for name in ("world_from_bone_quat", "root_pos", "joint_centres",
                     "bone_flags", "marker_residual"):  # fmt: skip
            assert np.array_equal(getattr(a, name), getattr(b, name), equal_nan=True)
        assert a.frame_flags == b.frame_flags
    assert p.touches == 60
