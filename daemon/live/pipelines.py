"""One performer's pipelines (``send.BodyPath``'s part): one per stream or view it
reads, each built off the loop (``rebuild.py``) when what it depends on changes (the
label set, the rig, the calibration, the face's training set), swapped in by the
first frame that finds it built. What a frame gets meanwhile (the old pipeline when
it reads the same markers, else nothing: counted unsolved) is :meth:`for_frame`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from retargetd.daemon.live.performer import FrameSource, Performer
from retargetd.daemon.live.pipeline import Pipeline, adopt, start_build
from retargetd.daemon.live.rebuild import Build, build_failed, reads_same, same_want
from retargetd.daemon.live.shared import Shared


class Pipelines:
    """The pipelines of one performer's frame path, and their builds.

    Args:
        perf: the performer (its rig, calibration, face).
        shared: the loop's side (config, counters, recording, prewarm).
        announce: called when a new pipeline is swapped in (its names go out
            with the next pose).
    """

    def __init__(
        self, perf: Performer, shared: Shared, announce: Callable[[], None]
    ) -> None:
        self.perf = perf
        self.shared = shared
        self._announce = announce
        self.pipelines: dict[int, Pipeline] = {}  # id(stream or view) -> Pipeline
        self.labels_of: dict[int, tuple[str, ...]] = {}
        # id(stream or view) -> its next pipeline, being built off the loop
        self.builds: dict[int, Build] = {}
        # id(stream or view) -> what its last build was for, when that build
        # raised: its frames unsolved (``unsolved_failed``) until what it wants
        # changes (a label set, a calibration, a training set) or a reload
        # (``Performers.end_reload``: even of unchanged files) clears it
        self.failed: dict[int, tuple[Any, ...]] = {}

    def for_frame(self, stream: FrameSource) -> Pipeline | None:
        """The pipeline to solve ``stream``'s current frame with: its own, built for
        the current label set, rig, calibration and face training set; while that
        one is built off the loop (``rebuild.py``), the old one if it reads the same
        markers from this label set; else None (no calibration yet, or nothing that
        can solve the frame yet: counted unsolved)."""
        perf = self.perf
        if perf.calibration is None:
            return None
        labels = stream.current.label_set.labels
        key = id(stream)
        pipe = self.pipelines.get(key)
        if pipe is not None and self.labels_of.get(key) == labels:
            rig, cal, training = pipe.built_for
            face = perf.face
            if (
                rig is perf.rig
                and cal is perf.calibration
                and training is (face.training if face is not None else None)
            ):
                return pipe
        failed = self.failed.get(key)
        if failed is not None:
            if same_want(failed, self._want(labels)):
                return None  # counted unsolved_failed (send.BodyPath.process)
            del self.failed[key]  # something else wanted now: built again
        job = self._job(key, labels)
        if job is not None and job.done():
            return self._swap(key, job, stream)
        if pipe is not None and reads_same(self.labels_of[key], labels, pipe.cols):
            return pipe  # the old pipeline, until the new one is built
        if self.shared.config.loop.process_every_frame:
            # Offline replay: every frame solved, none dropped; the loop waits for
            # the build (latency is not what this mode is for), after the one that
            # runs for something else, if any.
            if job is None:
                self.builds[key].wait()
                job = self._job(key, labels)
                assert job is not None
            job.wait()
            return self._swap(key, job, stream)
        return None

    def _want(self, labels: tuple[str, ...]) -> tuple[Any, ...]:
        """What a pipeline for ``labels`` is built for now (``PipelineSpec.want``)."""
        perf = self.perf
        face = perf.face
        return (perf.rig, perf.calibration, face.training if face else None, labels)

    def is_failed(self, key: int) -> bool:
        """Whether ``key``'s last build raised and nothing since asked for another
        (its frames: ``unsolved_failed``)."""
        return key in self.failed

    def _job(self, key: int, labels: tuple[str, ...]) -> Build | None:
        """The build of the pipeline ``key`` for ``labels`` and the performer's rig,
        calibration and training set now: the one under way for them, else one
        started now; None while a build for anything else still runs (one build
        per stream at a time, however fast label sets or reloads come: the one
        wanted then starts when it ends; its result is never used)."""
        want = self._want(labels)
        job = self.builds.get(key)
        if job is not None and job.wants(want):
            return job
        if job is not None and not job.done():
            return None
        job = self.builds[key] = start_build(self.perf, self.shared, labels)
        self.shared.bump()  # a pipeline swapped in soon: by a frame's lookup
        return job

    def _swap(self, key: int, job: Build, stream: FrameSource) -> Pipeline | None:
        """The built pipeline ``job`` swapped in for ``key`` at ``stream``'s current
        frame (one replacing another is recorded: a replay resets its solver there;
        a stream's first starts with its first solved frame); its names are
        announced with this frame. A build that raised: None (:meth:`_failed`)."""
        del self.builds[key]
        sh = self.shared
        sh.bump()
        try:
            pipe = adopt(job.take(), sh)
        except Exception as exc:  # counted and said; the loop goes on
            self._failed(key, job.want, exc)
            return None
        frame = stream.current.frame
        if key in self.pipelines:
            sh.recording.event("pipeline", received_ns=frame.t_ns)
        self._announce()  # new names: announce them with the next frame
        sh.stats.pipeline_builds += 1
        self.pipelines[key] = pipe
        self.labels_of[key] = job.want[3]
        sh.prewarm.register((id(self.perf), key), pipe.solver, frame)
        return pipe

    def _failed(self, key: int, want: tuple[Any, ...], exc: Exception) -> None:
        """``key``'s build for ``want`` raised: counted, one line naming the
        performer and the reason; its frames unsolved until something else is
        wanted (:meth:`for_frame`)."""
        self.failed[key] = want
        sh = self.shared
        build_failed(self.perf.name, sh.stats, sh.out, "pipeline", len(want[3]), exc)

    def tick(self) -> None:
        """Every loop pass: a build that ended for what is no longer wanted (a
        calibration, rig or training set that changed while it ran) replaced by
        the one wanted now, for the same labels, without waiting for the stream's
        next frame (a source that waits for its pipeline before sending, as
        ``ready`` lets it, would otherwise wait forever)."""
        for key, job in list(self.builds.items()):
            labels = job.want[3]
            if (
                job.done()
                and self.perf.calibration is not None
                and not job.wants(self._want(labels))
            ):
                self.builds[key] = start_build(self.perf, self.shared, labels)
                self.shared.bump()

    def prepare(self, key: int, labels: tuple[str, ...]) -> None:
        """A stream (or view) ``key`` took a label set, ``labels`` being this
        performer's of it: its pipeline's build starts now (off the loop), so its
        first frames find it built, or nearly."""
        if self.perf.calibration is None or not labels:
            return
        failed = self.failed.get(key)
        if failed is not None and same_want(failed, self._want(labels)):
            return  # (the same as the one that raised: not again)
        if key in self.pipelines and self.labels_of.get(key) == labels:
            rig, cal, _ = self.pipelines[key].built_for
            if rig is self.perf.rig and cal is self.perf.calibration:
                return  # (the training set's change is caught by the next frame)
        self._job(key, labels)

    def ready(self, key: int, labels: tuple[str, ...]) -> bool:
        """Whether a frame of ``labels`` on ``key`` would now be solved by its own
        pipeline (built, or its build done; no calibration: nothing to build).
        Reads only (tests call it from another thread)."""
        if self.perf.calibration is None:
            return True
        want = self._want(labels)
        pipe = self.pipelines.get(key)
        if (
            pipe is not None
            and self.labels_of.get(key) == labels
            and all(a is b for a, b in zip(pipe.built_for, want, strict=False))
        ):
            return True
        job = self.builds.get(key)
        return job is not None and job.wants(want) and job.done()

    def done_building(self, timeout_s: float) -> bool:
        """Wait until every build under way has ended (tests, which drive the loop
        one wake-up at a time, and need a deterministic point where the next frame
        is solved by the new pipeline); False if ``timeout_s`` passed first."""
        deadline = time.monotonic() + timeout_s
        for job in list(self.builds.values()):
            if not job.wait(max(0.0, deadline - time.monotonic())):
                return False
        return True

    def renew(self, labels: tuple[str, ...], sources: list[FrameSource]) -> None:
        """The rig, calibration or face training set changed: the new pipeline of
        each of the ``sources`` carrying ``labels`` is built off the loop from now
        (``rebuild.py``), its old one solving meanwhile; the other streams' when
        their next frame comes."""
        for s in sources:
            if s.current.label_set.labels == labels:
                self._job(id(s), labels)
