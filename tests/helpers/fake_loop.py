"""The live loop on a test's own clock and a fake poller, one pass at a time: what the
loop decides from a stream's cadence (when to wake, to touch the fit, to spin) made
exact, whatever the machine's load (tests/daemon/test_spin.py, test_prewarm.py)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

MS = 1_000_000
#: How far a poll with a zero timeout moves the clock on (ns).
ZERO_POLL_NS = 100_000


class Clock:
    """A test's clock (``Cadence.clock``): ``t`` ns, moved only by the test and by
    the fake polls."""

    def __init__(self, t: int = 10**12) -> None:
        self.t = t

    def __call__(self) -> int:
        return self.t


class Poller:
    """The loop's poller, faked: each poll moves the clock on by its timeout (a zero
    timeout by :data:`ZERO_POLL_NS`) and returns ``answer(n)`` for the n-th poll."""

    def __init__(self, clock: Clock, answer: Callable[[int], list[Any]]) -> None:
        self.clock, self.answer = clock, answer
        self.timeouts: list[int] = []

    def poll(self, timeout: int) -> list[Any]:
        self.timeouts.append(timeout)
        self.clock.t += timeout * MS if timeout else ZERO_POLL_NS
        return self.answer(len(self.timeouts))


def steady(cadence: Any, clock: Clock, period_ns: int, n: int) -> None:
    """``n`` frames ``period_ns`` apart observed by ``cadence``, the last one now."""
    for k in range(n):
        cadence.observe(clock.t - (n - 1 - k) * period_ns)


def run_passes(d: Any, poller: Poller, passes: int = 1) -> list[Any]:
    """Run the daemon ``d``'s loop (``Daemon.run``) for ``passes`` passes on
    ``poller``; returns the events each wake-up handed to its service."""
    served: list[Any] = []
    d._poller = poller
    d._service = served.append
    left = [passes]

    def should_exit() -> bool:
        left[0] -= 1
        return left[0] < 0

    d.run(should_exit)
    return served
