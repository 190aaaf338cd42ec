"""Touch the fit shortly before a steady stream's next frame (``[loop] prewarm_ms``).

On a shared machine a call that comes 4 ms after the last one finds the code and data
it touches cold: the fit on the real Plug-in Gait walk takes ~45 us back to back and
2-3x that paced at 240 Hz (README "The hot path, per frame"). A capture system sends at
a steady rate, so the loop knows when the next frame is due: ``prewarm_ms`` before
it, the loop runs each fit once on the last frame's markers, on a scratch solver built
from the real one's model with its own state (so nothing the stream sees changes),
and the real frame's solve then runs warm. ``bench/bench_prewarm.py`` measures it:
the frame's solve at 240 Hz fell to 0.50-0.61 of the untouched one's median (p99
0.54-0.75) with a lead of 0.5 or 1.5 ms; the touch itself costs ~90-130 us of the
loop's idle time per frame.

The period is a running mean of the accepted frames' spacing (weight 1/8 a frame); a
stream counts as steady while the running mean of the spacing's deviation stays under
half the lead: a frame that came earlier than the lead less the touch's own cost would
find the loop still touching, and would wait for it. A stream faster than
``2 x prewarm_ms`` per frame is warm anyway (frames 1 ms apart cost ~1.8x back to
back, not 3x) and is not touched, nor is one that is not steady (a replay sent as
fast as possible, a flood). The poll's timeout is in whole milliseconds, so the
touch comes between ``prewarm_ms`` and ``prewarm_ms + 1`` ms before the frame.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from retargetd.daemon.body.solve_fit import FitSolver
from retargetd.protocols.pose_stream import FRAME_UNEXPLAINED

#: Weight of each new spacing in the running means (a time constant of 8 frames).
GAIN = 0.125


class Cadence:
    """A stream's pace from its accepted frames' receive times: the running mean of
    their spacing (:data:`GAIN` a frame) and of its deviation, and the last one
    (shared by the touch and ``live/spin.py``).

    ``clock`` is the clock the receive times come from, read by the loop when it
    decides on a touch and by the spin (``time.monotonic_ns``; a test's own clock
    makes those decisions exact: tests/daemon/test_prewarm.py, test_spin.py)."""

    def __init__(self) -> None:
        self.period_ns = 0.0
        self.dev_ns = 0.0
        self.last_ns = 0
        self.clock: Callable[[], int] = time.monotonic_ns

    def observe(self, t_ns: int) -> None:
        """An accepted frame received at ``t_ns``."""
        if self.last_ns:
            d = float(t_ns - self.last_ns)
            if self.period_ns == 0.0:
                self.period_ns = d
            else:
                err = d - self.period_ns
                self.period_ns += GAIN * err
                self.dev_ns += GAIN * (abs(err) - self.dev_ns)
        self.last_ns = t_ns


class Prewarm(Cadence):
    """The predictor and the scratch solvers of one daemon (one loop)."""

    def __init__(self, lead_ms: float) -> None:
        super().__init__()
        self.lead_ns = int(lead_ms * 1e6)
        self.touched_ns = 0  # the last frame whose successor was touched for
        self.touches = 0
        self.resets = 0  # scratch solvers reset after a flagged or slow touch
        # (performer, input) -> (scratch fit, its pose, the input's frame buffer)
        self._scratch: dict[tuple[int, int], tuple[FitSolver, Any, Any]] = {}

    def next_ns(self) -> int:
        """When the next frame is due, or -1 (off, not steady, or too fast)."""
        p = self.period_ns
        if (
            self.lead_ns <= 0
            or p <= 2.0 * self.lead_ns
            or self.dev_ns >= 0.5 * self.lead_ns
        ):
            return -1
        return self.last_ns + int(p)

    def wait_ms(self, now_ns: int, wait_ms: int) -> int:
        """The poll's timeout: ``wait_ms``, or less to wake for the touch."""
        due = self.next_ns()
        if due < 0 or self.touched_ns == self.last_ns:
            return wait_ms
        left = due - self.lead_ns - now_ns
        return max(0, min(wait_ms, left // 1_000_000))

    def due(self, now_ns: int) -> bool:
        """The touch for the next frame is due now (and not done yet)."""
        due = self.next_ns()
        return (
            due >= 0
            and self.touched_ns != self.last_ns
            and due - self.lead_ns - 1_000_000 <= now_ns < due
        )

    def register(self, key: tuple[int, int], solver: Any, frame: Any) -> None:
        """A pipeline's solver and the frame buffer its input decodes into (off the
        hot path: when the pipeline is built). A fit gets its scratch solver, which
        shares its model; anything else is not touched."""
        if not isinstance(solver, FitSolver):
            self._scratch.pop(key, None)
            return
        scratch = FitSolver(
            solver.rig, solver.calibration, solver.labels,
            params=solver.params, model=solver.model, rate_hz=solver.rate_hz,
        )  # fmt: skip
        self._scratch[key] = (scratch, scratch.new_pose(), frame)

    def touch(self) -> None:
        """Run each registered fit once on its input's last frame, on its scratch
        solver."""
        self.touched_ns = self.last_ns
        for scratch, pose, frame in self._scratch.values():
            t0 = time.monotonic_ns()
            scratch.solve_frame(frame.markers_world, pose)
            self.touches += 1
            # A scratch whose markers fit no pose searches again at its next touch
            # (one touch flagged so took 98 ms of the loop's CPU in the soak, after
            # a burst of bad frames; measured), and a touch longer than the lead
            # makes the frame wait: reset it, its next touch starts afresh (a reset
            # fit's first solve took 0.1-0.2 ms on the walk, measured).
            if pose.frame_flags & FRAME_UNEXPLAINED or (
                time.monotonic_ns() - t0 > self.lead_ns
            ):
                scratch.reset()
                self.resets += 1
