"""Pipelines, face stages and reloaded files built off the loop (issue 30 item 6: "no
pose gap over 100 ms the source did not cause").

Built in the loop, each of these held every frame behind it (measured, in the loop,
on the soak's 2-core machine): a stream's pipeline 100-470 ms (the fit's body solver,
its model's eigh and pinv, ~410 ms of it), after a reload, a live calibration, a new
label set or a face capture; a reload's file parsing 23-70 ms. Now the loop hands
each to a worker thread (:class:`Build`: one daemon thread per job, running a function
of what the loop gave it when it asked: the rig, the calibration, the face training
set, the labels, the config as they were then; the worker never reads the daemon's
state, which only the loop thread touches) and goes on; the first loop pass that finds
the job done swaps the result in, whole.

What the frames get meanwhile (``send.BodyPath.pipeline``): a stream whose pipeline is
being replaced for a new rig, calibration or training set is solved by its old one (a
fraction of a second more of what it streamed before the request); so is a stream
whose new label set keeps, in every column the old pipeline reads, the marker it had
there (:func:`reads_same`: a label set that only adds markers, or renames ones the
solve ignores). Any other frame (no pipeline yet: a stream's first, or columns that now
hold other markers) is counted ``unsolved`` (and ``unsolved_building``) with no pose
sent, never a pose solved from the wrong markers; the first pose after such frames
carries ``FRAME_INPUT_DROPPED``. With ``[loop] process_every_frame`` (offline replay:
every frame solved, none dropped) such a frame waits for the build instead, in the
loop, as before. A swap is recorded as a ``pipeline`` control event
with its frame's receive time (a replay resets its solver there).

The worker shares the GIL with the loop: its Python and small LAPACK calls take turns
with the frames at the interpreter's switch interval (5 ms), so a frame may be solved a
few ms late while a build runs, never held for the whole build.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
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


class Build:
    """One job on its own (daemon) thread: ``fn(*args)``, its result or its error
    handed to the loop thread by :meth:`take`.

    Args:
        want: what the result is built for (the loop compares it, by identity, with
            what it wants now: a job for anything else is forgotten, never used).
        fn, args: the job; ``fn`` reads only its arguments.
    """

    __slots__ = ("_done", "error", "result", "want")

    def __init__(
        self, want: tuple[Any, ...], fn: Callable[..., Any], *args: Any
    ) -> None:
        self.want = want
        self.result: Any = None
        self.error: BaseException | None = None
        self._done = threading.Event()
        threading.Thread(
            target=self._run, args=(fn, args), name="retargetd-build", daemon=True
        ).start()

    def _run(self, fn: Callable[..., Any], args: tuple[Any, ...]) -> None:
        try:
            self.result = fn(*args)
        except BaseException as exc:  # handed to the loop thread, raised there
            self.error = exc
        finally:
            self._done.set()

    def done(self) -> bool:
        """Whether the job has ended (built or failed)."""
        return self._done.is_set()

    def wait(self, timeout_s: float | None = None) -> bool:
        """Wait for the job to end (not on the loop: tests and offline callers);
        False when ``timeout_s`` passed first."""
        return self._done.wait(timeout_s)

    def wants(self, want: tuple[Any, ...]) -> bool:
        """Whether this job builds for ``want``: each item the same object, or an
        equal tuple (labels)."""
        return same_want(want, self.want)

    def take(self) -> Any:
        """The job's result (it must be done).

        Raises:
            Exception: what the job raised (a calibration the fit cannot use), in
                the calling (loop) thread, as the job run there would have.
        """
        if self.error is not None:
            raise self.error
        return self.result


def build_failed(
    performer: str,
    stats: Any,
    out: Callable[[str], None],
    what: str,
    n_labels: int,
    exc: BaseException,
) -> None:
    """A ``what`` (pipeline, face-only stage) build of the performer's for a
    stream of ``n_labels`` labels raised: ``stats.pipeline_failures`` counted, one
    line to ``out`` naming the performer and the reason's first line."""
    stats.pipeline_failures += 1
    why = str(exc).splitlines()[0] if str(exc) else ""
    out(
        f"performer {performer or '(default)'}: its {what} for {n_labels} labels "
        f"failed to build ({type(exc).__name__}: {why}); its frames unsolved until "
        f"a new label set, reload or calibration; pipeline_failures "
        f"{stats.pipeline_failures}"
    )


def same_want(a: tuple[Any, ...], b: tuple[Any, ...]) -> bool:
    """Whether two builds' ``want`` are for the same thing: each item the same
    object, or an equal tuple (labels)."""
    return len(a) == len(b) and all(
        x is y or (type(x) is tuple and x == y) for x, y in zip(a, b, strict=True)
    )


def reads_same(
    old_labels: Sequence[str], new_labels: Sequence[str], cols: Sequence[int]
) -> bool:
    """Whether a pipeline built for ``old_labels`` reading the columns ``cols`` (its
    body solver's and face's: -1 for a marker not in the stream) reads the same
    markers from a frame of ``new_labels``: every such column still holds the label
    it held (a marker the old one lacked stays ignored: less data, nothing wrong).

    Args:
        old_labels: (M,) the labels it was built for.
        new_labels: (M',) the stream's new ones.
        cols: the column indices it reads (any order, -1 ignored).
    """
    n = len(new_labels)
    for c in cols:
        c = int(c)
        if c < 0:
            continue
        if c >= n or new_labels[c] != old_labels[c]:
            return False
    return True
