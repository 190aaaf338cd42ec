"""Loop stalls: a phase of one loop iteration that held the frame path up.

One thread owns the sockets and the solve (``loop.py``), so anything slow it does
between two polls delays every frame waiting in the socket. The loop reads the clock
once per phase of an iteration (the poll's overrun past its timeout, the markers'
drain and solve, show control, control, the ticks, the stats line) and hands the
phase's name to :meth:`LoopStalls.lap`; a phase over :data:`STALL_NS` is counted under
its name and logged through the rate-limited log. A garbage-collector pass over
:data:`STALL_NS` is counted too (``gc``), from whichever thread ran it: a pass holds
the GIL, so it stops the loop as surely as the loop's own work.

A stall is the loop's own work, or the loop waiting: for a core (a loaded host did not
schedule it) or for the GIL (another thread held it). The loop thread's CPU time,
read once an iteration (at the poll's start: one more clock read), tells them apart:
a stall in which the loop thread ran for less than half the phase's time is counted
``waiting`` too. In the soak, all of these were seen (measured, 60 s runs): a pipeline
rebuilt in the loop (the loop's own CPU, now ``rebuild.py``), a prewarm touch of
98 ms of CPU (``prewarm.py``), and phases of 60-110 ms with under 1 ms of the loop's
CPU and at most 5 ms of the whole process's (the host, at load 1.3-1.9).

``retargetd ctl status --json`` shows ``loop_stalls``: the count, how many of them
waiting, the longest (ms and phase) and the count per phase. A lap is one
``monotonic_ns`` call and a subtraction (~0.1 µs): a dozen per iteration is nothing
beside a solve.
"""

from __future__ import annotations

import gc
import threading
import time
from typing import Any

from retargetd.daemon.live.ratelog import RateLimitedLog

#: A phase this long is a stall: half the longest pose gap the soak allows (100 ms,
#: issue 30 item 6), 12 frames at 240 Hz, ten times the solve budget's default
#: (``loop.solve_budget_ms`` 5 ms): nothing the loop does in one phase on purpose.
STALL_NS = 50_000_000


def is_waiting(cpu_ns: int, took_ns: int) -> bool:
    """A stall of ``took_ns`` in which the loop thread ran ``cpu_ns`` was mostly
    waiting (for a core or the GIL), not the loop's own work: under half on a CPU."""
    return 2 * cpu_ns < took_ns


class LoopStalls:
    """Counts and names the loop's phases over :data:`STALL_NS`.

    Args:
        log: where a stall's line goes (rate limited per phase).
    """

    __slots__ = ("_cpu", "_gc_ns", "_log", "_owner", "_t", "by_phase", "count",
                 "longest_ns", "longest_phase", "waiting")  # fmt: skip

    def __init__(self, log: RateLimitedLog) -> None:
        self._log = log
        self._owner = threading.get_ident()  # the loop's thread: the one that logs
        self._t = time.monotonic_ns()
        self._cpu = time.thread_time_ns()  # the loop thread's CPU at the last mark
        self._gc_ns = 0  # when the running collector pass began (0: none)
        self.count = 0
        self.longest_ns = 0
        self.longest_phase = ""
        self.by_phase: dict[str, int] = {}
        self.waiting = 0  # of count: the loop thread on a CPU under half the time

    def mark(self) -> int:
        """Start timing the next phase, and the iteration's CPU, now (the poll's
        start); returns the time (ns)."""
        self._cpu = time.thread_time_ns()
        self._t = t = time.monotonic_ns()
        return t

    def lap(self, phase: str, allowed_ns: int = 0) -> int:
        """End ``phase`` now (the next one starts): a stall when it took over
        ``allowed_ns`` (a poll's timeout) + :data:`STALL_NS`. Returns the time (ns)."""
        now = time.monotonic_ns()
        took = now - self._t - allowed_ns
        self._t = now
        if took > STALL_NS:
            self.stalled(phase, took, now)
        return now

    def stalled(self, phase: str, took_ns: int, now_ns: int) -> None:
        """Count a stall of ``took_ns`` in ``phase`` and log it (rate limited)."""
        self.count += 1
        self.by_phase[phase] = self.by_phase.get(phase, 0) + 1
        if took_ns > self.longest_ns:
            self.longest_ns, self.longest_phase = took_ns, phase
        if threading.get_ident() != self._owner:  # a collector pass elsewhere:
            return  # counted only (the log belongs to the loop's thread)
        # The loop thread's CPU since the iteration's mark: an upper bound of the
        # phase's own (the iteration's earlier phases took a few ms at most).
        cpu_ns = time.thread_time_ns() - self._cpu
        waiting = is_waiting(cpu_ns, took_ns)
        self.waiting += waiting
        why = "waiting for a CPU or the GIL" if waiting else "its own work"
        self._log.line(
            f"loop stall {phase}",
            f"loop: {phase} held the frame path for {took_ns / 1e6:.0f} ms, "
            f"{cpu_ns / 1e6:.0f} ms of them on a CPU ({why}; stalls so far "
            f"{self.count})",
            now_ns,
        )

    def watch_gc(self) -> LoopStalls:
        """Time the garbage collector's passes too (until :meth:`close`); the
        calling thread is the loop's. Returns self."""
        self._owner = threading.get_ident()
        if self._gc_callback not in gc.callbacks:
            gc.callbacks.append(self._gc_callback)
        return self

    def close(self) -> None:
        """Stop timing the collector."""
        if self._gc_callback in gc.callbacks:
            gc.callbacks.remove(self._gc_callback)

    def _gc_callback(self, phase: str, info: dict[str, Any]) -> None:
        now = time.monotonic_ns()
        if phase == "start":
            self._gc_ns = now
        elif self._gc_ns:
            took, self._gc_ns = now - self._gc_ns, 0
            if took > STALL_NS:
                self.stalled(f"gc{info.get('generation', '')}", took, now)

    def status(self) -> dict[str, Any]:
        """``loop_stalls`` in the status document."""
        return {
            "count": self.count,
            "waiting": self.waiting,
            "longest_ms": round(self.longest_ns / 1e6, 1),
            "longest_phase": self.longest_phase or None,
            "by_phase": dict(self.by_phase),
        }
