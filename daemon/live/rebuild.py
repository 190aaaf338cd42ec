"""Body solvers rebuilt off the loop: after a reload or a new live calibration each
stream's pipeline needs a new body solver, and the fit's (its model, hold tables and
marginals: LAPACK calls by the thousand) took 85-330 ms on the soak's 2-core machine
and ~400-470 ms alone in a process (measured): built in the loop, it held every frame
that long (the soak's ``loop_late`` pose gaps, issue 30).

So the loop hands the build to a worker thread and goes on solving with the stream's
old pipeline (the old rig and calibration: a fraction of a second more of what it
streamed before the request); the first frame that finds the new solver built swaps
it into a new pipeline, recorded as a ``pipeline`` control event with that frame's
receive time (a replay resets its solver there). The rest of the pipeline
(retargeter, encoders, face stage: a few ms) is built in the loop at the swap: the
worker must not read the daemon's state, which only the loop thread touches, so a
build gets the rig, the calibration and the labels as they were when it was asked
for, and reads nothing else.

The worker shares the GIL with the loop: its Python and small LAPACK calls take turns
with the frames at the interpreter's switch interval (5 ms), so a frame may be solved a
few ms late while a build runs, never held for the whole build.

The first pipeline of a stream, and a new label set's, are still built in the loop:
there is no pipeline to solve their frames with meanwhile.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from typing import Any

from retargetd.daemon.body.method import make_body_solver
from retargetd.daemon.validate.limits import JOINT_LIMITS_DEG
from retargetd.daemon.validate.model import SEGMENT_KIND


def body_solver(
    method: str, rig: Any, calibration: Any, labels: Sequence[str], rate_hz: float
) -> Any:
    """The live pipeline's body solver (``body.method.make_body_solver`` with the
    validator's joint limits and segment kinds); reads only its arguments, so any
    thread may call it.

    Args:
        method: ``solve.method``.
        rig, calibration: the rig and its calibration.
        labels: (M,) the stream's marker labels.
        rate_hz: the frame numbers' rate (``validate.rate_hz``).
    """
    return make_body_solver(
        method, rig, calibration, labels, joint_limits=JOINT_LIMITS_DEG,
        segment_kind=SEGMENT_KIND, rate_hz=rate_hz,
    )  # fmt: skip


class Rebuild:
    """One body solver being built on its own (daemon) thread.

    Args:
        rig, calibration: what it is built for (kept: compared by identity).
        labels: (M,) the stream's marker labels.
        method, rate_hz: as :func:`body_solver`.
    """

    __slots__ = ("_done", "calibration", "error", "rig", "solver")

    def __init__(
        self, rig: Any, calibration: Any, labels: Sequence[str], method: str,
        rate_hz: float,
    ) -> None:  # fmt: skip
        self.rig, self.calibration = rig, calibration
        self.solver: Any = None
        self.error: BaseException | None = None
        self._done = threading.Event()
        args = (method, rig, calibration, tuple(labels), rate_hz)
        threading.Thread(
            target=self._run, args=args, name="retargetd-rebuild", daemon=True
        ).start()

    def _run(self, *args: Any) -> None:
        try:
            self.solver = body_solver(*args)
        except BaseException as exc:  # handed to the loop thread, raised there
            self.error = exc
        finally:
            self._done.set()

    def done(self) -> bool:
        """Whether the build has ended (built or failed)."""
        return self._done.is_set()


def rebuilt_solver(
    pipe: Any, rig: Any, calibration: Any, labels: Sequence[str], method: str,
    rate_hz: float,
) -> Any:  # fmt: skip
    """``pipe``'s new body solver for (``rig``, ``calibration``) when its build is
    done, else None, having started the build if none runs for these (one for
    anything else is forgotten: its result is never used).

    Args:
        pipe: the stream's current pipeline (``state.Pipeline``: its ``rebuild``).
        rig, calibration: the performer's current ones.
        labels: (M,) the stream's labels (the pipeline's own).
        method, rate_hz: as :func:`body_solver`.

    Raises:
        Exception: what the build raised (a calibration the fit cannot use), in the
            calling (loop) thread, as a build in the loop would have.
    """
    job = pipe.rebuild
    if job is None or job.rig is not rig or job.calibration is not calibration:
        pipe.rebuild = Rebuild(rig, calibration, labels, method, rate_hz)
        return None
    if not job.done():
        return None
    if job.error is not None:
        raise job.error
    return job.solver
