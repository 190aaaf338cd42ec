"""Several performers' body solves on more than one thread (``[loop] solve_threads``).

A frame that carries several performers is solved for each in turn
(``performers.Performers.solve``). Most of a performer's work is its body solve,
the fit's or the construction's one compiled call (``FitSolver.solve_frame``,
``BodySolver.solve_frame``); the kernels are compiled with ``nogil``
(``compiled.kernel``), so the GIL is free while one runs. With ``solve_threads``
= T > 1 the loop keeps T - 1 threads here, started with the daemon and joined at
its close, each blocked on a lock of its own between frames.

Per frame, with the frame's performers that have a pipeline numbered 0, 1, ... in
config order (``Performers.solve``): the loop thread takes each one's first step
(``begin``: the pipeline, the interval); hands solve j to thread j mod T (0 is the
loop itself) and releases the workers; then walks the performers in order: solves
its own share, or waits on solve j's lock, and finishes each (post stages, face,
retarget, encodes, sends, counters) on the loop thread as before. So everything but
the solve itself stays on the loop thread, the poses go out in config order, the
counters count the same things, and a solve reads and writes only its own
pipeline's solver state and pose: the poses are the serial path's, bit for bit
(tests/daemon/test_solve_threads.py). A solve that raises does not stop the
others: their frames are finished and sent, then the first exception is raised on
the loop thread, as the serial path would raise it (an escaping exception is a
bug: STYLE.md section 7). The loop never leaves a frame before every solve handed
out has ended, so a worker never runs while the loop resets or swaps a pipeline.

Nothing is allocated per frame beyond what the serial path allocates: the job
lists and the locks (``threading.Lock`` used as a binary semaphore: its
``acquire`` and ``release`` allocate nothing) are made once.
"""

from __future__ import annotations

import threading
from typing import Any

#: How long :meth:`SolveThreads.close` waits for each worker to end (s). A worker
#: between frames ends at once; one inside a solve ends when the solve returns
#: (tens to hundreds of microseconds).
JOIN_TIMEOUT_S = 5.0


class _Worker:
    """One solve thread: its jobs for the current frame and the lock it waits on."""

    def __init__(
        self, name: str, n_slots: int, done: list[Any], errors: list[Any]
    ) -> None:
        self.go = threading.Lock()
        self.go.acquire()  # released once per frame that hands it jobs
        self.paths: list[Any] = [None] * n_slots  # its frame's paths, in order
        self.slots = [0] * n_slots  # ... and their positions in the frame
        self.count = 0
        self.closing = False
        self.solves = 0  # solves run on this thread (status, tests)
        self._done = done
        self._errors = errors
        self.thread = threading.Thread(target=self._run, name=name, daemon=True)

    def _run(self) -> None:
        done, errors = self._done, self._errors
        while True:
            self.go.acquire()
            if self.closing:
                return
            for i in range(self.count):
                slot = self.slots[i]
                try:
                    self.paths[i].solve_begun()
                except Exception as exc:  # handed back to the loop thread
                    errors[slot] = exc
                finally:
                    self.solves += 1
                    done[slot].release()


class SolveThreads:
    """The loop's solve threads (``solve_threads`` - 1 of them).

    Args:
        n_slots: the most solves one frame can hand out (the performers).
        n_threads: ``[loop] solve_threads``, the loop thread included (>= 2).
    """

    def __init__(self, n_slots: int, n_threads: int) -> None:
        self.n_threads = n_threads
        self._done = [threading.Lock() for _ in range(n_slots)]
        for lock in self._done:
            lock.acquire()  # released by the worker when solve j ends
        self._handed = [False] * n_slots  # handed out, not yet waited for
        self._errors: list[Exception | None] = [None] * n_slots
        self.workers = [
            _Worker(f"retargetd-solve-{k}", n_slots, self._done, self._errors)
            for k in range(1, n_threads)
        ]
        self._started = False

    def start(self) -> None:
        """Start the threads (the daemon's ``open``)."""
        if not self._started:
            self._started = True
            for w in self.workers:
                w.thread.start()

    def mine(self, j: int) -> bool:
        """Whether solve ``j`` of a frame is the loop thread's own."""
        return j % self.n_threads == 0

    def hand(self, j: int, path: Any) -> None:
        """Hand solve ``j`` (``path.solve_begun``) to its thread (not the loop's)."""
        w = self.workers[j % self.n_threads - 1]
        w.paths[w.count] = path
        w.slots[w.count] = j
        w.count += 1
        self._handed[j] = True

    def go(self) -> None:
        """Release every worker that was handed solves for this frame."""
        for w in self.workers:
            if w.count:
                w.go.release()

    def wait(self, j: int) -> Exception | None:
        """Wait for solve ``j`` (handed out) to end; what it raised, or None."""
        self._done[j].acquire()
        self._handed[j] = False
        exc = self._errors[j]
        self._errors[j] = None
        return exc

    def settle(self, n: int) -> None:
        """The frame's end (``n`` solves): wait for any handed out and not waited
        for yet (a finish raised), so no worker runs once the frame is left."""
        for j in range(n):
            if self._handed[j]:
                self.wait(j)
        for w in self.workers:
            w.count = 0

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
                w.go.release()
        for w in self.workers:
            if w.thread.is_alive():
                w.thread.join(JOIN_TIMEOUT_S)
