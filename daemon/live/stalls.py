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

Waiting for a core and waiting for the GIL are told apart by the loop thread's
scheduler statistics (``/proc/self/task/<tid>/schedstat``, its second field: the time
it spent runnable on a run queue without a CPU), read at the same mark: a waiting stall
in which the loop thread was runnable without a CPU for at least half the phase is
``unscheduled`` (the host did not run it: no thread of ours could have); the rest of a
waiting stall it was blocked (the GIL held by another thread, or a lock), ``blocked``:
the daemon's. Those two bounds (CPU and run queue since the iteration's mark) hold the
earlier phases of the iteration too, a poll's overrun (under 50 ms) included. For the
holder, the process's CPU (one more clock read at the mark) and every Python thread's
CPU and run-queue time (read at most every :data:`THREADS_EVERY_NS`) give the other
threads' share and the one that ran the most. Without schedstat (a kernel without
``CONFIG_SCHED_INFO``) a waiting stall stays ``waiting`` only.

``retargetd ctl status --json`` shows ``loop_stalls``: the count, how many of them
waiting (of them ``unscheduled`` and ``blocked``), the longest (ms and phase), the count
per phase and the last :data:`RECENT` stalls (``recent``: each one's end on the
host's CLOCK_MONOTONIC, ns, phase, ms, the loop's CPU and run-queue ms, the other
threads' CPU and run-queue ms, the busiest other thread, and ``why``). A lap is one
``monotonic_ns`` call and a subtraction (~0.1 µs): a dozen per iteration is nothing
beside a solve; a mark adds a ``pread`` of schedstat (3.4 µs at load 4.8 on a 2-core
VM; a whole mark 1.6 µs at load 1.6), and every :data:`THREADS_EVERY_NS` the threads'
times (39.5 µs for 12 threads: 0.2 % of a core), all measured.
"""

from __future__ import annotations

import gc
import os
import threading
import time
from collections import deque
from typing import Any

from retargetd.daemon.live.ratelog import RateLimitedLog

#: A phase this long is a stall: half the longest pose gap the soak allows (100 ms,
#: issue 30 item 6), 12 frames at 240 Hz, ten times the solve budget's default
#: (``loop.solve_budget_ms`` 5 ms): nothing the loop does in one phase on purpose.
STALL_NS = 50_000_000
#: The Python threads' CPU and run-queue times are read at a mark at most this often
#: (a stall is over 50 ms: their change since is the stall's, with at most this
#: much of what came before it).
THREADS_EVERY_NS = 20_000_000
#: The last stalls kept for ``status`` (``recent``).
RECENT = 64


def run_queue_ns(fd: int | None) -> int | None:
    """The run-queue time (ns) in a schedstat file open at ``fd`` (its second
    field: runnable, waiting for a CPU); None without one."""
    if fd is None:
        return None
    try:
        return int(os.pread(fd, 96, 0).split()[1])
    except (OSError, IndexError, ValueError):
        return None


def open_schedstat(native_id: int) -> int | None:
    """A thread's schedstat, open for :func:`run_queue_ns`; None if absent."""
    try:
        return os.open(f"/proc/self/task/{native_id}/schedstat", os.O_RDONLY)
    except OSError:
        return None


def thread_times() -> dict[int, tuple[str, int, int | None]]:
    """Every live Python thread's (name, CPU ns, run-queue ns or None) by ident."""
    out: dict[int, tuple[str, int, int | None]] = {}
    for t in threading.enumerate():
        if t.ident is None or t.native_id is None:
            continue
        try:
            cpu = time.clock_gettime_ns(time.pthread_getcpuclockid(t.ident))
        except OSError:  # (it ended)
            continue
        fd = open_schedstat(t.native_id)
        rq = run_queue_ns(fd)
        if fd is not None:
            os.close(fd)
        out[t.ident] = (t.name, cpu, rq)
    return out


def is_waiting(cpu_ns: int, took_ns: int) -> bool:
    """A stall of ``took_ns`` in which the loop thread ran ``cpu_ns`` was mostly
    waiting (for a core or the GIL), not the loop's own work: under half on a CPU."""
    return 2 * cpu_ns < took_ns


class LoopStalls:
    """Counts and names the loop's phases over :data:`STALL_NS`.

    Args:
        log: where a stall's line goes (rate limited per phase).
    """

    __slots__ = ("_cpu", "_gc_ns", "_log", "_owner", "_proc", "_rq", "_sched",
                 "_sched_tid", "_t", "_threads", "_threads_ns", "blocked", "by_phase",
                 "count", "longest_ns", "longest_phase", "recent", "unscheduled",
                 "waiting")  # fmt: skip

    def __init__(self, log: RateLimitedLog) -> None:
        self._log = log
        self._owner = threading.get_ident()  # the loop's thread: the one that logs
        self._t = time.monotonic_ns()
        self._sched: int | None = None  # the loop thread's schedstat, open
        self._sched_tid = 0  # whose (native id)
        self._threads: dict[int, tuple[str, int, int | None]] = {}
        self._threads_ns = 0  # when read
        self._gc_ns = 0  # when the running collector pass began (0: none)
        self.count = 0
        self.longest_ns = 0
        self.longest_phase = ""
        self.by_phase: dict[str, int] = {}
        self.waiting = 0  # of count: the loop thread on a CPU under half the time
        self.unscheduled = 0  # of waiting: runnable without a CPU half the time
        self.blocked = 0  # of waiting: neither (the GIL or a lock)
        self.recent: deque[dict[str, Any]] = deque(maxlen=RECENT)
        self._cpu, self._proc, self._rq = self._sample()

    def _sample(self) -> tuple[int, int, int | None]:
        """The calling thread's CPU, the process's CPU and the calling thread's
        run-queue time (None without schedstat), ns."""
        tid = threading.get_native_id()
        if tid != self._sched_tid:  # (the loop's thread: opened once)
            if self._sched is not None:
                os.close(self._sched)
            self._sched, self._sched_tid = open_schedstat(tid), tid
        rq = run_queue_ns(self._sched)
        return time.thread_time_ns(), time.process_time_ns(), rq

    def mark(self) -> int:
        """Start timing the next phase, and the iteration's CPU and run-queue time,
        now (the poll's start); returns the time (ns)."""
        self._cpu, self._proc, self._rq = self._sample()
        self._t = t = time.monotonic_ns()
        if t - self._threads_ns >= THREADS_EVERY_NS:
            self._threads, self._threads_ns = thread_times(), t
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
        entry: dict[str, Any] = {"end_ns": now_ns, "phase": phase,
                                 "ms": round(took_ns / 1e6, 1)}  # fmt: skip
        self.recent.append(entry)
        if threading.get_ident() != self._owner:  # a collector pass elsewhere:
            entry["why"] = "gc"
            return  # counted only (the log belongs to the loop's thread)
        # The loop thread's CPU and run-queue time since the iteration's mark: upper
        # bounds of the phase's own (the iteration's earlier phases are in them).
        cpu, proc, rq = self._sample()
        cpu_ns = cpu - self._cpu
        rq_ns = None if rq is None or self._rq is None else rq - self._rq
        others_ns = max(0, proc - self._proc - cpu_ns)
        waiting = is_waiting(cpu_ns, took_ns)
        self.waiting += waiting
        if not waiting:
            why, what = "own", "its own work"
        elif rq_ns is None:
            why, what = "waiting", "waiting for a CPU or the GIL"
        elif 2 * rq_ns >= took_ns:
            why, what = "unscheduled", "the host did not schedule it"
            self.unscheduled += 1
        else:
            why, what = "blocked", "blocked: the GIL held by another thread, or a lock"
            self.blocked += 1
        top, others_rq = self._busiest()
        entry.update(why=why, cpu_ms=round(cpu_ns / 1e6, 1),
                     runqueue_ms=None if rq_ns is None else round(rq_ns / 1e6, 1),
                     others_cpu_ms=round(others_ns / 1e6, 1),
                     others_runqueue_ms=others_rq, busiest=top)  # fmt: skip
        queued = "" if rq_ns is None else f", {rq_ns / 1e6:.0f} ms runnable without one"
        busiest = f", most {top[0]} {top[1]:.0f} ms" if top else ""
        self._log.line(
            f"loop stall {phase}",
            f"loop: {phase} held the frame path for {took_ns / 1e6:.0f} ms, "
            f"{cpu_ns / 1e6:.0f} ms of them on a CPU{queued} ({what}; the process's "
            f"other threads {others_ns / 1e6:.0f} ms on a CPU{busiest}; stalls so far "
            f"{self.count})",
            now_ns,
        )

    def _busiest(self) -> tuple[tuple[str, float] | None, float | None]:
        """The other Python thread that ran the most since the threads' last
        reading (its name, CPU ms), and the other threads' run-queue ms (None
        without schedstat)."""
        now = thread_times()
        best: tuple[str, float] | None = None
        rq_ns: int | None = 0
        me = threading.get_ident()
        for ident, (name, cpu, rq) in now.items():
            if ident == me or ident not in self._threads:
                continue
            _, cpu0, rq0 = self._threads[ident]
            ms = (cpu - cpu0) / 1e6
            if best is None or ms > best[1]:
                best = (name, round(ms, 1))
            if rq is None or rq0 is None or rq_ns is None:
                rq_ns = None
            else:
                rq_ns += rq - rq0
        return best, None if rq_ns is None else round(rq_ns / 1e6, 1)

    def watch_gc(self) -> LoopStalls:
        """Time the garbage collector's passes too (until :meth:`close`); the
        calling thread is the loop's. Returns self."""
        self._owner = threading.get_ident()
        if self._gc_callback not in gc.callbacks:
            gc.callbacks.append(self._gc_callback)
        return self

    def close(self) -> None:
        """Stop timing the collector; close the schedstat file."""
        if self._gc_callback in gc.callbacks:
            gc.callbacks.remove(self._gc_callback)
        if self._sched is not None:
            os.close(self._sched)
            self._sched, self._sched_tid = None, 0

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
            "unscheduled": self.unscheduled,
            "blocked": self.blocked,
            "longest_ms": round(self.longest_ns / 1e6, 1),
            "longest_phase": self.longest_phase or None,
            "by_phase": dict(self.by_phase),
            "recent": list(self.recent),
        }
