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
from live_harness import Live, OscSource, PoseSub, _prime, _take

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


def test_spinning_returns_what_arrives_and_gives_up_at_the_window_end() -> None:
    s = Spin(
        2000.0, Cadence()
    )  # 2 ms either side: the test's own clock jitter is far under
    last = _steady(s, 10 * MS, 30)  # 100 Hz, the last frame just now
    s.cadence.last_ns = (
        time.monotonic_ns() - 10 * MS + 1 * MS
    )  # due in 1 ms: window open
    calls = []

    def poll(timeout: int) -> list[int]:
        calls.append(timeout)
        return [1] if len(calls) == 5 else []

    assert s.spin(poll) == [1]
    assert calls == [0] * 5 and s.spins == 1 and s.caught == 1
    calls.clear()
    t0 = time.monotonic_ns()
    assert s.spin(lambda timeout: []) == []  # nothing comes: until the window ends
    assert time.monotonic_ns() >= s.cadence.last_ns + int(s.cadence.period_ns) + 2 * MS
    assert time.monotonic_ns() - t0 < 10 * MS
    assert s.spins == 2 and s.caught == 1
    # that due time is not spun for again, nor woken for
    assert s.due_ns() == -1 and s.wait_ms(time.monotonic_ns(), 100) == 100
    assert s.spin(lambda timeout: pytest.fail("spun for a missed frame")) == []
    s.cadence.observe(time.monotonic_ns())  # the frame came late: the next one is armed
    assert s.due_ns() > 0
    assert last > 0


def test_no_spin_before_the_window_nor_for_an_unsteady_or_too_fast_stream() -> None:
    s = Spin(500.0, Cadence())
    _steady(s, PERIOD, 50)
    s.cadence.last_ns = time.monotonic_ns()  # due in 4.2 ms: far before the window
    assert s.spin(lambda timeout: pytest.fail("spun early")) == []
    for period, jitter in ((PERIOD, 0.6), (MS, 0.0)):  # unsteady; 1000 Hz < 2 x 0.5
        s = Spin(500.0, Cadence())
        last = _steady(s, period, 60, jitter)
        assert s.due_ns() == -1
        assert s.wait_ms(last + 1000, 100) == 100
        assert s.spin(lambda timeout: pytest.fail("spun")) == []


def test_status_counts_zero_when_off() -> None:
    assert spin_counters(None) == {"spins": 0, "spins_caught": 0}
    s = Spin(100.0, Cadence())
    s.spins, s.caught = 3, 2
    assert spin_counters(s) == {"spins": 3, "spins_caught": 2}


@pytest.mark.timeout(120)
@pytest.mark.parametrize("spin_us", [0.0, 1500.0])
def test_the_daemon_spins_for_a_paced_stream_and_loses_no_frame(
    start_daemon: Callable[..., Live],
    osc_source: Callable[..., OscSource],
    zmq_socket: Callable[[int], Any],
    exact_calibration: Path,
    spin_us: float,
) -> None:
    """A 100 Hz stream: with ``spin_us`` the loop spins before frames and frames end
    most spins (counters ``spins`` / ``spins_caught``); every frame is still solved
    and sent, as with it off, which spins never."""
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
        # It spins. How often depends on the machine: a stream that a loaded
        # machine jitters by more than spin_us is not spun for (the steadiness
        # rule, pinned by the test of an unsteady stream above); a CI run under
        # load spun for 32 of these 150 frames, a quiet one for most. A spin ends
        # with a frame no more often than it starts.
        assert c["spins"] >= 1
        assert 0 <= c["spins_caught"] <= c["spins"]
    assert c["frames_in"] == c["frames_out"]
