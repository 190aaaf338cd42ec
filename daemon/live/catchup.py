"""When the loop is behind: the catch-up window of a wake-up (latest wins past it).

A wake-up of the loop (``loop.Daemon._service``) solves the frames its inputs hand it
as they are decoded. The first frame solved in a wake-up waited for nothing of the
loop's; any frame accepted after a solve in the same wake-up waited in its socket for
that solve (it arrived during it, or behind the first frame): from that frame on the
loop is catching up. It goes on solving every waiting frame at once for one frame
period of the source (the running mean of the accepted frames' spacing,
``prewarm.Cadence``); past that the loop is behind, and each input's newest frame
wins: the older ones are counted ``stale`` (``inputs.py``, ``Daemon._leave``).

Why one frame period, counted from the first frame that waited: a loop that keeps up
with its source (its work for a frame well under the period: 455-493 us median for 4
performers of the fit on a quiet machine, README "Several performers", against
4,167 us at 240 Hz) clears the few frames that wait behind a stall in a fraction of a
period, so every frame goes out, each later by that fraction at most; a loop still
catching up a period later is not keeping up (the source sent another frame
meanwhile), and solving older frames would only delay the newest. The window used to
run from the wake-up itself (``solve_budget_ms`` per performer), so a stall inside the
wake-up's first solve (the process not scheduled) longer than the window dropped the
frames that arrived during it, while the same stall just before the wake-up dropped
none; now either delays those frames by its length and drops none of them. A
burst faster than the loop solves (a sender that does not pace) still drops: its
frames' spacing is the period, tiny. Until the source's cadence is known (its second
frame) the window is ``solve_budget_ms`` per performer, as before. It is never longer
than what the loop calls a stall (``stalls.STALL_NS``, 50 ms: half the longest pose gap
the soak allows): a source slower than 20 Hz, or one that paused (the running mean
then takes a few dozen frames to come back down), is caught up for that long at most.
"""

from __future__ import annotations

from retargetd.daemon.live.prewarm import Cadence
from retargetd.daemon.live.stalls import STALL_NS


class CatchUp:
    """A wake-up's catch-up state: has it solved a frame yet, and since when has it
    been solving frames that waited.

    Args:
        cadence: the sources' pace (the running mean of accepted frames' spacing).
        fallback_ns: the window before the cadence is known (ns).
    """

    __slots__ = ("_cadence", "_since_ns", "fallback_ns", "solved_any")

    def __init__(self, cadence: Cadence, fallback_ns: int) -> None:
        self._cadence = cadence
        self.fallback_ns = fallback_ns
        self.solved_any = False  # a frame solved in this wake-up (read by the drains)
        self._since_ns = 0  # the first frame that waited for a solve (0: none yet)

    def wake(self) -> None:
        """A wake-up begins: nothing solved in it yet, nothing waited."""
        self.solved_any = False
        self._since_ns = 0

    def solved(self) -> None:
        """A frame was solved in this wake-up: a frame accepted after this waited."""
        self.solved_any = True

    def window_ns(self) -> float:
        """How long the loop catches up before the latest wins (ns): one frame
        period of the source, at most ``STALL_NS``; ``fallback_ns`` until its cadence
        is known."""
        period = self._cadence.period_ns
        return min(period, STALL_NS) if period > 0.0 else float(self.fallback_ns)

    def behind(self, now_ns: int) -> bool:
        """Whether a frame accepted at ``now_ns`` should wait for the end of the
        wake-up (where only its input's newest is solved) rather than be solved
        now: the loop has been catching up for a window already."""
        if not self.solved_any:  # the wake-up's first solve: nothing of ours waited
            return False
        if not self._since_ns:  # the first frame that waited: catching up from now
            self._since_ns = now_ns
        return now_ns - self._since_ns >= self.window_ns()
