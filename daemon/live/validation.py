"""One performer's live validator (``[validate]``), built off the loop, and what its
results put in the stream (issue 30 item 6: no pose gap the source did not cause).

Building one (``validate.live.LiveValidator``: the MuJoCo model of the calibration's
skeleton, its check tables, its kernels warmed, its thread started) took 3-32 ms
(the PiG and exact synthetic rigs, load 4), 300-380 ms the first time in a process
that has not loaded its kernels (numba's cache; 5.4 s on a cold cache). It happens
at the start, after a live calibration and after a reload: in the loop, every frame
behind it waited (a live calibration's stalled phase: 31-41 ms of the loop's CPU
before, 12-16 ms without it, ``bench/bench_stalls.py``). Now the loop hands the
build to a worker thread
(``rebuild.Build``, with the rig, calibration and ``[validate]`` settings as they
were when it was asked for) and goes on; the old validator keeps checking the poses
meanwhile. The first loop pass that finds the build done (:meth:`Validation.tick`)
swaps the new one in and hands the old one's close (a thread join, up to 1 s) to a
worker too. One build at a time per performer: what is wanted when it ends (a newer
calibration) is built then, a result built for anything else is closed unused. A
build that raises is counted (``validator_failures``), said in one line, and leaves
the validator off until the next calibration or reload; the loop goes on.
``ctl status --json`` shows ``validators_building``. With ``[loop]
process_every_frame`` (offline replay) and at the start, the build is waited for.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from retargetd.daemon.live.config_schema import ValidateSectionConfig
from retargetd.daemon.live.performer import Performer
from retargetd.daemon.live.rebuild import Build
from retargetd.daemon.live.shared import Shared
from retargetd.daemon.validate.live import LiveValidator
from retargetd.protocols import pose_stream


def new_validator(
    rig: Any, calibration: Any, settings: ValidateSectionConfig
) -> LiveValidator:
    """A started live validator of ``rig`` and ``calibration`` (the worker's job;
    reads only its arguments)."""
    validator = LiveValidator(
        rig,
        calibration,
        body_mass_kg=settings.body_mass_kg or None,
        rate_hz=settings.rate_hz,
        queue_size=settings.queue,
    )
    validator.start()
    return validator


class Validation:
    """A performer's live validator: its build off the loop, and the bits and
    values of its latest result (ORed into the poses, shown in the console).

    Args:
        perf: the performer (its rig and calibration).
        shared: the loop's side (config, counters, outputs, out).
    """

    def __init__(self, perf: Performer, shared: Shared) -> None:
        self.perf = perf
        self.shared = shared
        self.validator: LiveValidator | None = None
        self.job: Build | None = None  # the next validator, being built
        self.bits = 0  # the latest result's frame bits (8-15)
        self.bones: np.ndarray | None = None  # and bone bits (4-7), (B,) uint8
        # the latest result's values (VALIDATION_CHECKS order), for the console
        self.values = np.full(len(pose_stream.VALIDATION_CHECKS), np.nan)
        self.enc: pose_stream.ValidationEncoder | None = None
        self.results: list[Any] = []  # reused by drain_results

    def _want(self) -> tuple[Any, ...] | None:
        """What a validator is wanted for now: (rig, calibration, settings); None
        when none is ([validate] off, or no calibration)."""
        v = self.shared.config.validate
        calibration = self.perf.calibration
        if not v.enabled or calibration is None:
            return None
        return (self.perf.rig, calibration, v)

    def start(self, wait: bool = False) -> None:
        """(Re)start on the current rig and calibration: its build starts off the
        loop now (after the one under way, if that one is for something else); the
        running one checks the poses until it is swapped in. ``wait`` (the
        daemon's start): swapped in before this returns, and a build that raises
        raises here (as it did in the loop); with ``[loop] process_every_frame``
        (offline replay) it is waited for too, and a failure counted.

        Raises:
            ValueError: ``wait`` and a calibration the validator cannot use."""
        self.shared.bump()  # a calibration, rig or reload: re-armed after
        want = self._want()
        if want is None:  # off: the running one stops
            self._swap(None)
            return
        job = self.job
        if job is None:
            self.job = job = Build(want, new_validator, *want)
        elif not job.wants(want) and job.done():
            self.tick()  # (starts the one wanted)
            job = self.job
        if (wait or self.shared.config.loop.process_every_frame) and job is not None:
            while self.job is not None:  # the one wanted, after any other
                self.job.wait()
                self.tick(strict=wait)

    def tick(self, strict: bool = False) -> None:
        """Every loop pass: a finished build swapped in (or counted as failed), or,
        built for what no longer runs, closed and the one wanted now started.
        ``strict``: a failed build raises (the start) instead."""
        job = self.job
        if job is None or not job.done():
            return
        self.job = None
        want = self._want()
        try:
            built: LiveValidator | None = job.take()
        except Exception as exc:  # counted and said; the loop goes on
            built = None
            if want is not None and job.wants(want):
                if strict:
                    raise
                self._failed(exc)
                return
        if want is None or not job.wants(want):
            if built is not None:
                _close_later(built)
            if want is not None:
                self.job = Build(want, new_validator, *want)
            return
        assert built is not None
        self._swap(built)
        v = want[2]
        self.shared.out(
            f"{self._who()}live validator on: MuJoCo model {built.vm.digest[:12]}, "
            f"queue {v.queue}, frame numbers at {v.rate_hz:g} Hz"
        )

    def _failed(self, exc: BaseException) -> None:
        """The build for what runs raised: counted, one line, the validator off."""
        self._swap(None)
        stats = self.shared.stats
        stats.validator_failures += 1
        why = str(exc).splitlines()[0] if str(exc) else ""
        self.shared.out(
            f"{self._who()}live validator off: its build failed "
            f"({type(exc).__name__}: {why}); validator_failures "
            f"{stats.validator_failures}"
        )

    def _swap(self, validator: LiveValidator | None) -> None:
        """``validator`` in (None: off), the old one closed off the loop, the
        latest result's bits cleared."""
        old, self.validator = self.validator, validator
        self.shared.bump()  # the one-call path runs without a validator only
        if old is not None:
            _close_later(old)
        self.bits = 0
        self.bones = None
        self.values.fill(np.nan)
        if validator is not None:
            self.results = [None] * validator.results_capacity

    @property
    def building(self) -> bool:
        """A validator is being built off the loop now."""
        return self.job is not None and not self.job.done()

    def take_bits(self, last: Any) -> None:
        """Keep the latest result's bits for this and the next poses."""
        self.bits = last.frame_flags & pose_stream.FRAME_VALIDATION_MASK
        bones = last.bone_flags
        if self.bones is None or len(self.bones) != len(bones):
            self.bones = np.zeros(len(bones), dtype=np.uint8)
        np.bitwise_and(bones, pose_stream.BONE_VALIDATION_MASK, out=self.bones)
        np.copyto(self.values, last.values, casting="same_kind")

    def publish(self, n: int, names_id: int) -> None:
        """Count the first ``n`` drained results and publish each as an ``RTDV``
        message (the frame it belongs to, its values; ``names_id``: the pose
        stream's names it refers to), written into a reused buffer. The validator
        sets only the validation bits (frame bits 8-15, bone bits 4-7)."""
        stats, outputs = self.shared.stats, self.shared.outputs
        results = self.results
        for k in range(n):
            r = results[k]
            stats.validated += 1
            if r.frame_flags:
                stats.validation_flagged += 1
            if outputs.publishing:
                enc = self.enc
                if enc is None or enc.n_bones != len(r.bone_flags):
                    enc = self.enc = pose_stream.ValidationEncoder(len(r.bone_flags))
                msg = enc.encode(
                    names_id, r.frame_id, r.t_ns, r.validated_ns, r.frame_flags,
                    r.values, r.bone_flags,
                )  # fmt: skip
                outputs.send_pub(msg, r.validated_ns)

    def status(self) -> dict[str, Any] | None:
        """``ctl status``'s ``validate``: the running validator's; None when none
        runs (off, or the first one still being built: ``validators_building``)."""
        v = self.validator
        return None if v is None else dict(v.status())

    def close(self) -> None:
        """Stop the live validator (idempotent; at the daemon's close, never in the
        loop). A build under way is waited for (it is finite: a model, tables and a
        kernel load) and its validator closed unused."""
        old, self.validator = self.validator, None
        if old is not None:
            old.close()
        job, self.job = self.job, None
        if job is not None:
            job.wait()
            if job.error is None and job.result is not None:
                job.result.close()

    def _who(self) -> str:
        return f"{self.perf.name}: " if self.perf.name else ""


def _close_later(validator: LiveValidator) -> None:
    """Close ``validator`` on a worker (its thread joined there, not in the loop)."""
    Build((), validator.close)
