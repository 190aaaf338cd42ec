"""The loop's catch-up window (``daemon/live/catchup.py``): frames that waited behind a
solve are solved for one frame period of the source, then the latest wins. The rule
alone on a stand-in cadence, then a live daemon driven one wake-up at a time over a
real loopback socket, its solve stalled on purpose while frames arrive: a stall in
the wake-up's first solve drops nothing, a stall while catching up past the window
drops the older of the frames that waited (counted ``stale``).
"""

from __future__ import annotations

import socket
import time
from pathlib import Path
from typing import Any

import live_harness as lh
import pytest
from live_harness import EXACT_RIG, WAIT_S, _take

from retargetd.daemon.live.catchup import CatchUp
from retargetd.daemon.live.config import DaemonConfig
from retargetd.daemon.live.loop import Daemon
from retargetd.daemon.live.prewarm import Cadence
from retargetd.daemon.live.stalls import STALL_NS
from retargetd.protocols import osc_in
from retargetd.protocols.marker_input import LabelSet

pytestmark = pytest.mark.timeout(120)

MS = 1_000_000


def _cadence(period_ns: float) -> Cadence:
    cadence = Cadence()
    cadence.period_ns = period_ns
    return cadence


def test_first_solve_of_a_wake_up_never_waits() -> None:
    up = CatchUp(_cadence(4 * MS), 8 * MS)
    up.wake()
    assert not up.behind(10**12)  # however late the wake-up itself


def test_frames_that_waited_are_caught_up_for_one_period() -> None:
    up = CatchUp(_cadence(4 * MS), 8 * MS)
    up.wake()
    up.solved()  # (a stall inside that solve does not count)
    t0 = 10**9
    assert not up.behind(t0)  # the first frame that waited: catching up from here
    up.solved()
    assert not up.behind(t0 + 4 * MS - 1)
    assert up.behind(t0 + 4 * MS)  # a period of catching up: the latest wins
    up.wake()  # the next wake-up starts in step again
    assert not up.behind(t0 + 100 * MS)


def test_window_follows_the_cadence_and_falls_back_before_it() -> None:
    cadence = _cadence(0.0)
    up = CatchUp(cadence, 8 * MS)
    assert up.window_ns() == 8 * MS  # no cadence yet: the performers' budgets
    cadence.period_ns = 1e9 / 240
    assert up.window_ns() == pytest.approx(1e9 / 240)
    cadence.observe(10**9)  # a burst: back-to-back frames shrink the window
    for _ in range(40):
        cadence.observe(cadence.last_ns + 50_000)
    assert up.window_ns() < 0.5 * MS
    cadence.observe(cadence.last_ns + 10**10)  # after a 10 s pause: at most a stall
    assert up.window_ns() == STALL_NS


class _Stalled:
    """Wraps ``Performers.solve``: on call ``at`` (0-based), sends ``frames`` into
    the daemon's OSC socket, then sleeps ``stall_s`` (the process not scheduled)."""

    def __init__(self, solve: Any, send: Any, at: int, frames: list[int],
                 stall_s: float) -> None:  # fmt: skip
        self.solve, self.send, self.at = solve, send, at
        self.frames, self.stall_s = frames, stall_s
        self.calls = 0

    def __call__(self, stream: Any, t_ns: int) -> None:
        if self.calls == self.at:
            for j in self.frames:
                self.send(j)
            time.sleep(self.stall_s)
        self.calls += 1
        self.solve(stream, t_ns)


def _daemon(exact_calibration: Path) -> Daemon:
    doc = lh._ephemeral_doc(lh._unused_udp_port())
    doc["performer"] = {"rig": str(EXACT_RIG), "calibration": str(exact_calibration)}
    return Daemon(DaemonConfig.from_dict(doc, source="test"), out=lambda _line: None)


def _service_until(d: Daemon, done: Any, what: str) -> None:
    deadline = time.monotonic() + WAIT_S
    while not done():
        assert time.monotonic() < deadline, what
        events = d._poller.poll(20)
        if events:
            d._service(events)


@pytest.mark.parametrize("stall_in", ["first", "catch_up"])
def test_a_stall_drops_nothing_unless_catching_up_past_a_period(
    exact_calibration: Path, stall_in: str
) -> None:
    # A steady 40 ms cadence first (the window: 40 ms). Then frame A wakes the loop
    # with frame B already waiting behind it. "first": A's solve stalls 3 periods
    # while C, D, E arrive: B-E all waited, and are caught up in well under a
    # period: none stale (the window used to run from the wake-up: B-D stale).
    # "catch_up": B's solve (the first frame that waited) stalls 3 periods while C,
    # D arrive: C comes past the window, so D (the newest) wins and C is stale.
    period_s = 0.040
    d = _daemon(exact_calibration)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        d.open()
        host, port = d.endpoints["osc markers"].split()[0][6:].rsplit(":", 1)
        addr = (host, int(port))
        take = _take()
        hold = take.markers_world[take.base_pose_frames]
        tx.sendto(osc_in.encode_labels(LabelSet(1, take.labels)), addr)
        _service_until(d, lambda: d.stats.labels_in >= 1, "labels did not arrive")
        assert d.performers.done_building(60.0), "the pipeline was never built"

        def send(j: int) -> None:
            frame = osc_in.encode_compact_frame(j, j * period_s, 1, hold[j % 10])
            tx.sendto(frame, addr)

        for j in range(8):  # the cadence: one frame a period, each solved
            t_next = time.monotonic() + period_s
            send(j)
            _service_until(d, lambda j=j: d.stats.frames_in > j, "frame lost")
            time.sleep(max(0.0, t_next - time.monotonic()))
        # (a loaded machine may have held the paced frames up: the window is the
        # period they were sent at)
        d._prewarm.period_ns = period_s * 1e9
        solve = d.performers.solve
        if stall_in == "first":  # A's solve (call 0) stalls while C, D, E arrive
            stalled = _Stalled(solve, send, 0, [10, 11, 12], 3 * period_s)
        else:  # B's solve (call 1) stalls while C, D arrive
            stalled = _Stalled(solve, send, 1, [10, 11], 3 * period_s)
        d.performers.solve = stalled
        before = dict(d.stats.counters())
        send(8)  # A
        send(9)  # B, waiting behind A
        deadline = time.monotonic() + WAIT_S
        events: list[Any] = []
        while not events:
            assert time.monotonic() < deadline, "frames did not arrive"
            events = d._poller.poll(20)
        d._service(events)  # one wake-up: A, B and what arrived during the stall
        after = d.stats.counters()
        got = {k: after[k] - before[k] for k in ("frames_in", "frames_out", "stale")}
        if stall_in == "first":
            assert got == {"frames_in": 5, "frames_out": 5, "stale": 0}, got
        else:
            assert got == {"frames_in": 4, "frames_out": 3, "stale": 1}, got
        c = d.stats.counters()
        assert c["frames_in"] == c["frames_solved"] + c["stale"] + c["unsolved"]
    finally:
        tx.close()
        d.close()
