"""``[loop] spin_us`` (daemon/live/spin.py): the loop wakes just before a steady
stream's next frame and polls without sleeping until it comes or the window closes;
off (the default) nothing changes."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zmq
from fake_loop import Clock, Poller, run_passes, steady
from live_harness import Live, OscSource, PoseSub, _prime, _take

from retargetd.daemon.live.config import DaemonConfig
from retargetd.daemon.live.loop import Daemon
from retargetd.daemon.live.prewarm import Cadence
from retargetd.daemon.live.spin import POLL_ROUNDING_NS, Spin, spin_counters

MS = 1_000_000
PERIOD = 4_166_667  # 240 Hz


def _steady(s: Spin, period_ns: int, n: int, jitter: float = 0.0) -> int:
    rng = np.random.default_rng(2)
    t = time.monotonic_ns() - n * period_ns
    for _ in range(n):
        t += int(period_ns * (1.0 + jitter * rng.uniform(-1.0, 1.0)))
        s.cadence.observe(t)
    return t


def test_a_steady_stream_wakes_the_poll_before_its_window() -> None:
    s = Spin(500.0, Cadence())
    last = _steady(s, PERIOD, 50, jitter=0.02)
    due = s.due_ns()
    assert abs(due - (last + PERIOD)) < 0.05 * PERIOD
    now = last + 100_000
    # whole milliseconds, never past the window's start
    assert s.wait_ms(now, 100) == (due - 500_000 - now) // MS
    assert (due - 500_000 - now) - s.wait_ms(now, 100) * MS < POLL_ROUNDING_NS
    assert s.wait_ms(now, 1) == 1  # a shorter wait stands


def _spin_on(clock: Clock, spin_us: float, period_ns: int, n: int) -> Spin:
    """A spin whose cadence reads ``clock`` and has seen ``n`` frames
    ``period_ns`` apart, the last one now."""
    cadence = Cadence()
    cadence.clock = clock
    steady(cadence, clock, period_ns, n)
    return Spin(spin_us, cadence)


def test_spinning_returns_what_arrives_and_gives_up_at_the_window_end() -> None:
    clock = Clock()
    s = _spin_on(clock, 500.0, 10 * MS, 30)  # 100 Hz, the last frame now
    due = s.due_ns()
    assert due == clock.t + 10 * MS
    polls: list[int] = []

    def poll(timeout: int) -> list[int]:  # 0.1 ms a poll
        polls.append(timeout)
        clock.t += 100_000
        return [1] if len(polls) == 5 else []

    clock.t = due - 200_000  # inside the window
    assert s.spin(poll) == [1]
    assert polls == [0] * 5 and s.spins == 1 and s.caught == 1
    # Nothing comes: it polls from the window's start until its end, 1 ms at
    # 0.1 ms a poll, then gives up.
    polls.clear()
    clock.t = due - 500_000

    def nothing(timeout: int) -> list[int]:
        polls.append(timeout)
        clock.t += 100_000
        return []

    assert s.spin(nothing) == []
    assert polls == [0] * 10 and clock.t == due + 500_000
    assert s.spins == 2 and s.caught == 1
    # that due time is not spun for again, nor woken for
    assert s.due_ns() == -1 and s.wait_ms(clock.t, 100) == 100
    assert s.spin(lambda timeout: pytest.fail("spun for a missed frame")) == []
    s.cadence.observe(clock.t)  # the frame came late: the next one is armed
    assert s.due_ns() == clock.t + int(s.cadence.period_ns)


def test_no_spin_before_the_window_nor_for_an_unsteady_or_too_fast_stream() -> None:
    clock = Clock()
    s = _spin_on(clock, 500.0, PERIOD, 50)  # due in 4.2 ms: far before the window
    assert s.spin(lambda timeout: pytest.fail("spun early")) == []
    clock.t += PERIOD - 500_000 - POLL_ROUNDING_NS - 1  # 1 ns before the rounding
    assert s.spin(lambda timeout: pytest.fail("spun early")) == []
    assert s.spins == 0
    for period, jitter in ((PERIOD, 0.6), (MS, 0.0)):  # unsteady; 1000 Hz < 2 x 0.5
        s = Spin(500.0, Cadence())
        last = _steady(s, period, 60, jitter)
        assert s.due_ns() == -1
        assert s.wait_ms(last + 1000, 100) == 100
        assert s.spin(lambda timeout: pytest.fail("spun")) == []


@pytest.mark.parametrize("frame_comes", [True, False])
def test_the_loop_wakes_for_the_window_and_serves_what_the_spin_caught(
    frame_comes: bool,
) -> None:
    """The loop itself, one pass on a fake poller and clock: its poll sleeps until
    the window of a steady 100 Hz stream's next frame (whole ms), then it spins
    (zero timeouts) and hands the frame caught to its service, or gives up at
    the window's end (``spin_us`` 1500)."""
    d = Daemon(DaemonConfig.from_dict({"loop": {"spin_us": 1500.0,
                                                "prewarm_ms": 0.0}}),
               out=lambda _line: None)  # fmt: skip
    try:
        clock = Clock()
        spin = d._spin
        assert spin is not None and spin.cadence is d._prewarm
        d._prewarm.clock = clock
        steady(d._prewarm, clock, 10 * MS, 30)  # 100 Hz, the last frame now
        due = clock.t + 10 * MS
        frame = ("socket", 1)
        poller = Poller(clock, lambda n: [frame] if frame_comes and n == 4 else [])
        served = run_passes(d, poller)
        # asleep until 1.5 ms before it is due (8.5 ms: 8 whole ms), then spinning
        assert poller.timeouts[0] == 8
        assert set(poller.timeouts[1:]) == {0}
        if frame_comes:
            assert served == [[frame]] and len(poller.timeouts) == 4
            assert (spin.spins, spin.caught) == (1, 1)
        else:  # from 8 ms to 11.5 ms after the last frame, 0.1 ms a poll
            assert served == [] and len(poller.timeouts) == 1 + 35
            assert clock.t == due + 1_500_000
            assert (spin.spins, spin.caught) == (1, 0)
    finally:
        d.close()


def test_status_counts_zero_when_off() -> None:
    assert spin_counters(None) == {"spins": 0, "spins_caught": 0}
    s = Spin(100.0, Cadence())
    s.spins, s.caught = 3, 2
    assert spin_counters(s) == {"spins": 3, "spins_caught": 2}


@pytest.mark.timeout(120)
@pytest.mark.parametrize("spin_us", [0.0, 1500.0])
def test_the_daemon_loses_no_frame_spinning_or_not(
    start_daemon: Callable[..., Live],
    osc_source: Callable[..., OscSource],
    zmq_socket: Callable[[int], Any],
    exact_calibration: Path,
    spin_us: float,
) -> None:
    """A 100 Hz stream over real sockets: with ``spin_us`` every frame is still
    solved and sent, as with it off, which spins never (counters ``spins`` /
    ``spins_caught``)."""
    take = _take()
    live = start_daemon(
        {
            "performer": {"calibration": str(exact_calibration)},
            "loop": {"process_every_frame": True, "spin_us": spin_us},
        },
    )
    sub = PoseSub(zmq_socket(zmq.SUB), live.tcp("zmq poses"))
    src = osc_source(live)
    src.announce()
    _prime(sub, lambda: src.send(take.markers_world[0]))
    n0 = len(sub.poses)
    rows = range(100, 250)
    src.send_paced([take.markers_world[row] for row in rows], 100.0)
    sub.wait(lambda: len(sub.poses) >= n0 + len(rows), "every frame's pose", 30.0)
    c = live.ctl({"cmd": "status"})["status"]["counters"]
    print(f"\nspin_us {spin_us}: {c['spins']} spins, {c['spins_caught']} caught")
    if spin_us == 0.0:
        assert c["spins"] == 0 and c["spins_caught"] == 0
    else:
        # How often it spins depends on the machine (a stream that a loaded
        # machine jitters by more than spin_us is not spun for): that it spins,
        # and serves the frame it caught, is the loop test's above, on its own
        # clock. A spin ends with a frame no more often than it starts.
        assert 0 <= c["spins_caught"] <= c["spins"]
    assert c["frames_in"] == c["frames_out"]
