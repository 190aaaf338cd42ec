"""Poll without sleeping just before a steady stream's next frame (``[loop] spin_us``).

A loop that sleeps in ``poll`` is woken by the kernel when a datagram arrives: on a
busy or virtualized machine that wake-up is most of the added latency (issue 35: a
bare Python relay, which only polls, receives and sends, adds 140-245 us p99 at 240 Hz
on this 2-core VM, waking after a 4 ms sleep). A capture system sends at a steady
rate, so the loop knows when the next frame is due; with ``spin_us`` set it sleeps
until ``spin_us`` before that time (the poll's timeout is whole milliseconds: up to
1 ms earlier) and then polls with a zero timeout until the frame comes or ``spin_us``
after the time it was due, so the frame is received by a thread that is already on a
CPU.

**When it helps:** a machine with a core to spare for the loop (a dedicated core,
``taskset``/``isolcpus``, a workstation whose sender runs elsewhere). The loop then
burns up to ``2 x spin_us + 1 ms`` of that core per frame (at 240 Hz and 500 us, about
half of it). **When it hurts:** a machine whose cores are all busy, as this 2-core VM
with the sender on it: the spinning loop takes the core the sender (or libzmq's I/O
thread) needed, and the frame arrives later, not sooner (measured in issue 35; README
"The hot path, per frame"). Off (0, the default) the loop pays one ``is None`` test
per pass.

The period is a running mean of the accepted frames' spacing (``prewarm.Cadence``,
the touch's own estimate, weight 1/8 a frame); the loop spins only for a stream whose
spacing deviates on average by less than ``spin_us`` (a frame that jitters more would
mostly land outside the window) and whose period is over twice the window (a faster
stream keeps the loop awake anyway). A due time whose window passed without a frame
is not spun for again: the loop sleeps in ``poll`` as usual until the next frame.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from retargetd.daemon.live.prewarm import Cadence

#: The poll's timeout is whole milliseconds: it may wake up to this much before the
#: window opens, and the loop spins from there.
POLL_ROUNDING_NS = 1_000_000


class Spin:
    """The predictor and the spin of one loop (``[loop] spin_us`` > 0).

    Args:
        spin_us: the window, microseconds on either side of the frame's due time.
        cadence: the stream's pace (the loop's ``Prewarm``, which observes every
            accepted frame).
    """

    def __init__(self, spin_us: float, cadence: Cadence) -> None:
        self.window_ns = int(spin_us * 1000.0)
        # the poll phase's allowance beyond its timeout (live/stalls.py): the spin
        self.allow_ns = 2 * self.window_ns + POLL_ROUNDING_NS
        self.cadence = cadence
        self._missed = -1  # a due time whose window passed without a frame
        self.spins = 0  # windows spun in
        self.caught = 0  # ... that a frame ended (received while spinning)

    def due_ns(self) -> int:
        """When the next frame is due, or -1 (not steady, too fast, or its window
        already spun through without it)."""
        c = self.cadence
        p = c.period_ns
        if p <= 2.0 * self.window_ns or c.dev_ns >= self.window_ns:
            return -1
        due = c.last_ns + int(p)
        return -1 if due == self._missed else due

    def wait_ms(self, now_ns: int, wait_ms: int) -> int:
        """The poll's timeout: ``wait_ms``, or less to wake for the window."""
        due = self.due_ns()
        if due < 0:
            return wait_ms
        left = due - self.window_ns - now_ns
        return max(0, min(wait_ms, left // 1_000_000))

    def spin(self, poll: Callable[[int], Any]) -> Any:
        """After a poll that found nothing: when the window of the frame due is
        open (or opens within the poll's rounding), poll with a zero timeout until
        something is readable or the window closes. Returns what the last poll
        returned (empty: nothing came)."""
        due = self.due_ns()
        if due < 0:
            return []
        now = self.cadence.clock()
        if now < due - self.window_ns - POLL_ROUNDING_NS:
            return []  # woken for something else (the prewarm's touch, a tick)
        end = due + self.window_ns
        self.spins += 1
        while True:
            events = poll(0)
            if events:
                self.caught += 1
                return events
            if self.cadence.clock() >= end:
                self._missed = due
                return events


def spin_counters(spin: Spin | None) -> dict[str, int]:
    """``ctl status``'s ``counters.spins`` (windows spun in) and ``spins_caught``
    (those a frame ended); zeros when ``[loop] spin_us`` is off (``spin`` None)."""
    if spin is None:
        return {"spins": 0, "spins_caught": 0}
    return {"spins": spin.spins, "spins_caught": spin.caught}
