"""Several performers' body solves on more than one thread (``[loop] solve_threads``).

A frame that carries several performers is solved for each in turn
(``performers.Performers.solve``). Most of a performer's work is its body solve,
the fit's or the construction's one compiled call (``FitSolver.solve_frame``,
``BodySolver.solve_frame``); the kernels are compiled with ``nogil``
(``compiled.kernel``), so the GIL is free while one runs. With ``solve_threads``
= T > 1 the loop keeps T - 1 threads here, started with the daemon and joined at
its close, each blocked on a lock of its own between frames.

Per frame, with the frame's performers that have a pipeline numbered 0 .. m-1 in
config order (``Performers.solve``): the loop thread takes each one's first step
(``begin``: the pipeline, the interval), opens the frame's m solves and wakes the
workers; then walks the solves in order, taking each one no worker has taken yet
(solving it itself) or waiting for the worker that has, and finishes each
performer (post stages, face, retarget, encodes, sends, counters) on the loop
thread as before. The workers take solves from the end (m-1, m-2, ...), so the
loop and the workers meet in the middle. A solve is taken by one thread only: a
non-blocking ``acquire`` of its lock, held by the loop between frames. So a worker
that the machine does not schedule (both cores busy) costs nothing but its wake-up:
the loop solves everything itself, as with ``solve_threads = 1``; the loop waits
only for a solve a worker has started.

Everything but the solve itself stays on the loop thread, the poses go out in
config order, the counters count the same things, and a solve reads and writes
only its own pipeline's solver state and pose: the poses are the serial path's,
bit for bit, whichever thread solved them (tests/daemon/test_solve_threads.py). A
solve that raises does not stop the others: their frames are finished and sent,
then the first exception is raised on the loop thread, as the serial path would
raise it (an escaping exception is a bug: STYLE.md section 7). The loop never
leaves a frame before every solve a worker took has ended, so a worker never
runs a solve while the loop resets or swaps a pipeline.

Nothing is allocated per frame beyond what the serial path allocates: the tables
and the locks (``threading.Lock`` used as a binary semaphore: its ``acquire`` and
``release`` allocate nothing) are made once.
"""

from __future__ import annotations

import threading
from typing import Any

#: How long :meth:`SolveThreads.close` waits for each worker to end (s). A worker
#: between frames ends at once; one inside a solve ends when the solve returns
#: (tens to hundreds of microseconds).
JOIN_TIMEOUT_S = 5.0

# What the loop did with solve j of the current frame (SolveThreads._state).
_OPEN = 0  # not yet reached by the loop
_LOOP = 1  # taken and solved by the loop
_WAITED = 2  # taken by a worker, and waited for


class _Worker:
    """One solve thread: it wakes on ``go`` and takes the frame's open solves from
    the end."""

    def __init__(self, name: str, table: SolveThreads) -> None:
        self.go = threading.Lock()
        self.go.acquire()  # released to wake it (never twice: SolveThreads.open)
        self.closing = False
        self.solves = 0  # solves run on this thread (status, tests)
        self._table = table
        self.thread = threading.Thread(target=self._run, name=name, daemon=True)

    def _run(self) -> None:
        t = self._table
        claim, done, paths, errors = t.claim, t.done, t.paths, t.errors
        while True:
            self.go.acquire()
            if self.closing:
                return
            for j in range(t.count - 1, 0, -1):  # solve 0 is the loop's at once
                if not claim[j].acquire(False):
                    continue  # the loop's, another worker's, or not open
                try:
                    paths[j].solve_begun()
                except Exception as exc:  # handed back to the loop thread
                    errors[j] = exc
                finally:
                    self.solves += 1
                    done[j].release()


class SolveThreads:
    """The loop's solve threads (``solve_threads`` - 1 of them) and the frame's
    table of solves.

    Args:
        n_slots: the most solves one frame can hold (the performers).
        n_threads: ``[loop] solve_threads``, the loop thread included (>= 2).
    """

    def __init__(self, n_slots: int, n_threads: int) -> None:
        self.n_threads = n_threads
        #: solve j's frame path (``solve_begun``), set before :meth:`open`
        self.paths: list[Any] = [None] * n_slots
        # Solve j is taken by acquiring claim[j]; the loop holds every one between
        # frames (nothing open) and releases the frame's in open().
        self.claim = [threading.Lock() for _ in range(n_slots)]
        # done[j] is released by the worker that solved j; the loop acquires it.
        self.done = [threading.Lock() for _ in range(n_slots)]
        for lock in (*self.claim, *self.done):
            lock.acquire()
        self.errors: list[Exception | None] = [None] * n_slots
        self.count = 0  # the open frame's solves
        self._state = [_OPEN] * n_slots
        self.workers = [
            _Worker(f"retargetd-solve-{k}", self) for k in range(1, n_threads)
        ]
        self._started = False

    def start(self) -> None:
        """Start the threads (the daemon's ``open``)."""
        if not self._started:
            self._started = True
            for w in self.workers:
                w.thread.start()

    def open(self, m: int) -> None:
        """Open the frame's ``m`` solves (``paths[0:m]`` set, each path begun) and
        wake the workers."""
        self.count = m
        for j in range(m):
            self.claim[j].release()
        for w in self.workers:
            if w.go.locked():  # (else its wake-up is still pending: it comes)
                w.go.release()

    def take(self, j: int) -> bool:
        """Take solve ``j`` for the loop thread: True when no worker has (then the
        loop solves it), False when one has (then :meth:`wait` for it)."""
        if self.claim[j].acquire(False):
            self._state[j] = _LOOP
            return True
        return False

    def wait(self, j: int) -> Exception | None:
        """Wait for solve ``j``, taken by a worker; what it raised, or None."""
        self.done[j].acquire()
        self._state[j] = _WAITED
        exc = self.errors[j]
        self.errors[j] = None
        return exc

    def settle(self) -> None:
        """The frame's end: every solve the loop has not reached is taken (not
        solved) or, when a worker took it, waited for (a finish raised); no worker
        runs a solve of this frame once it returns, and nothing is open."""
        state = self._state
        for j in range(self.count):
            if state[j] == _OPEN and not self.take(j):
                self.wait(j)
                self.errors[j] = None
            state[j] = _OPEN
        self.count = 0

    @property
    def solves(self) -> int:
        """Solves run on the workers so far."""
        return sum(w.solves for w in self.workers)

    def alive(self) -> int:
        """How many worker threads are running."""
        return sum(w.thread.is_alive() for w in self.workers)

    def close(self) -> None:
        """End and join every worker (idempotent; never called inside a frame)."""
        for w in self.workers:
            if w.thread.is_alive() and not w.closing:
                w.closing = True
                if w.go.locked():
                    w.go.release()
        for w in self.workers:
            if w.thread.is_alive():
                w.thread.join(JOIN_TIMEOUT_S)
