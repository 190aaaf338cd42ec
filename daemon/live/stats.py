"""Loop statistics: integer counters and per-stage latency rings (no allocation per
frame); summarized into the periodic stats line and ``retargetd ctl status``."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from retargetd.protocols.frames import IntArray

#: Latency stages, in pipeline order (ns rings).
STAGES = ("receive_to_solved", "solve", "encode_send", "receive_to_sent")
RING = 4096
#: The ``[[pipeline]]`` post stages are reported as ``post.<kind>`` (a repeated kind
#: ``post.<kind>#2``), each a part of ``solve``.
POST_PREFIX = "post."


@dataclass(slots=True)
class LoopStats:
    """Counters and latency rings owned by the loop thread.

    Attributes:
        frames_in: accepted marker frames (all inputs).
        frames_solved: frames solved (latest wins: <= frames_in).
        frames_out: frames sent.
        stale: accepted frames skipped because a newer one arrived first.
        overruns: frames whose solve + send exceeded ``solve_budget_ms``.
        send_drops: pose-stream messages dropped (subscriber slow: ``zmq.Again``).
        vmc_errors: VMC datagrams the OS refused.
        restarts: sources restarted.
        calibrations: live calibrations applied.
        calibrations_refused: live calibrations refused (the performer moved).
        calibrations_expired: live calibrations that collected no frame in time.
        calibration_failures: live calibrations that raised an internal error (not
            a refusal; ``calibrate.py``): said in one line, the old calibration
            kept, ``calibration_state`` "failed"; the loop serves on.
        rate_limited: reload and calibration requests refused as too frequent.
        held_bone_frames: bone-frames held (too little data).
        occluded_samples: rig-marker samples occluded in solved frames.
        pipeline_builds: per-stream pipelines built (the first frame after a new
            label set, a calibration or a reload); each one's cost is in that
            frame's solve stage.
        post_restarts: ``[[pipeline]]`` filter restarts (the source's clock went
            back or jumped over a second, or a pose was not finite).
        resample_skipped: solved frames not sent because no output tick fell due
            (``loop.output_rate_hz`` below the input's rate; counted in
            ``frames_solved``, not in ``frames_out``).
        resample_dropped: output ticks dropped unsent from a full queue
            (``interp.QUEUE_TICKS`` ticks waiting for their send time).
        resample_timer: output ticks sent from the loop's timer, between input
            frames (``output_rate_hz`` above the input's rate).
        rejected_sources: OSC datagrams from addresses not on the allow-list.
        face_solved: frames the face was solved on.
        face_head_lost: of those, frames with fewer than 3 head markers (face held).
        face_captures: live face training captures applied.
        face_save_failures: training sets a capture made that could not be written
            (its file kept as it was; ``face.py``, written off the loop).
        pipeline_failures: pipelines (and face-only stages) whose build (off the
            loop, ``rebuild.py``) raised: said in one line; the stream's frames
            unsolved (``unsolved_failed``) until a new label set, reload,
            calibration or training set asks for another.
        calibration_save_failures: live calibrations (in use) whose file could not
            be written (off the loop, ``calibrate.py``): said in one line, the old
            file kept whole, ``calibration_state`` "not_saved".
        validator_failures: live validators whose build (off the loop,
            ``validation.py``) raised: the validator off until the next
            calibration or reload.
        validated: frames the live validator finished (results taken by the loop).
        validation_flagged: of those, frames with at least one check over threshold.
        validation_drops: sent frames the validator's queue had no room for.
        zmq_disconnects: ZeroMQ marker peers disconnected: by libzmq for a message
            part over ``input.zmq.max_message_bytes`` (never buffered, so not
            counted by reason), or by the peer itself.
        unsolved: accepted frames not solved because no calibration is loaded yet,
            or their performer's pipeline for them is being built (so ``frames_in =
            frames_solved + stale + unsolved``).
        unsolved_building: of those, frames whose pipeline was being built off the
            loop (``rebuild.py``: a stream's first, or a label set that moved the
            markers the old one read): no pose sent for them, and the next pose
            flagged ``FRAME_INPUT_DROPPED``.
        unsolved_failed: of those, frames whose pipeline's build raised
            (``pipeline_failures``): no pose, the next one flagged as above.
        unseen: solved frames in which too few of the performer's markers were
            seen to place a pose (``FRAME_UNSEEN``): nothing streamed for them.
        unexplained: solved frames whose markers fit no pose the fit found
            (``FRAME_UNEXPLAINED``): the last explained pose streamed, flagged.
        reseeded: solved frames the fit reseeded from the construction
            (``FRAME_RESEEDED``).
        labels_in: label announcements decoded (any outcome; per input the adopted
            and confirming ones are ``MarkerStream.labels_taken``).
        show_control_in: show-control datagrams received (allow-list passed).
        show_control_malformed: of those, datagrams with a malformed element.
        control_requests: control requests answered.
        control_errors: of those, answered with ``ok: false``.
        control_oversize: of those, refused unread for their size (over
            ``control.CONTROL_MAX_BYTES``).
    """

    frames_in: int = 0
    frames_solved: int = 0
    frames_out: int = 0
    stale: int = 0
    overruns: int = 0
    send_drops: int = 0
    vmc_errors: int = 0
    restarts: int = 0
    calibrations: int = 0
    calibrations_refused: int = 0
    calibrations_expired: int = 0
    calibration_failures: int = 0
    rate_limited: int = 0
    held_bone_frames: int = 0
    occluded_samples: int = 0
    pipeline_builds: int = 0
    rejected_sources: int = 0
    face_solved: int = 0
    face_head_lost: int = 0
    face_captures: int = 0
    face_save_failures: int = 0
    pipeline_failures: int = 0
    calibration_save_failures: int = 0
    validator_failures: int = 0
    validated: int = 0
    validation_flagged: int = 0
    validation_drops: int = 0
    zmq_disconnects: int = 0
    unsolved: int = 0
    unsolved_building: int = 0
    unsolved_failed: int = 0
    unseen: int = 0
    unexplained: int = 0
    reseeded: int = 0
    labels_in: int = 0
    show_control_in: int = 0
    show_control_malformed: int = 0
    control_requests: int = 0
    control_errors: int = 0
    control_oversize: int = 0
    post_restarts: int = 0
    resample_skipped: int = 0
    resample_dropped: int = 0
    resample_timer: int = 0
    #: One list of RING ns per stage (:data:`STAGES`): a list item set per stage is
    #: half the time of a numpy one on a cold loop (1.9 against 3.6 us a frame at
    #: 1,000 Hz, load 3), and stores the int the caller made (nothing allocated).
    rings: list[list[int]] = field(default_factory=lambda: [[0] * RING for _ in STAGES])
    ring_pos: int = 0
    ring_count: int = 0
    post_names: tuple[str, ...] = ()
    post_rings: IntArray = field(default_factory=lambda: np.zeros((0, RING), np.int64))
    post_pos: int = 0
    post_count: int = 0
    spine_ring: IntArray = field(default_factory=lambda: np.zeros(RING, np.int64))
    spine_pos: int = 0
    spine_count: int = 0

    def record_spine(self, ns: int) -> None:
        """Store one frame's ``[target] spine = "pivot"`` duration (ns): reported as
        ``post.pivot`` with the ``[[pipeline]]`` stages."""
        self.spine_ring[self.spine_pos] = ns
        self.spine_pos = (self.spine_pos + 1) % RING
        if self.spine_count < RING:
            self.spine_count += 1

    def set_post_stages(self, names: tuple[str, ...]) -> None:
        """Name the post stages timed from now on (new names: their rings restart)."""
        if names != self.post_names:
            self.post_names = names
            self.post_rings = np.zeros((len(names), RING), np.int64)
            self.post_pos = self.post_count = 0

    def record_post(self, stage_ns: IntArray) -> None:
        """Store one frame's post-stage durations (ns), in :attr:`post_names` order."""
        rings = self.post_rings
        if len(stage_ns) != rings.shape[0]:
            return  # a stream whose stages are not the named ones (being rebuilt)
        i = self.post_pos
        rings[:, i] = stage_ns
        self.post_pos = (i + 1) % RING
        if self.post_count < RING:
            self.post_count += 1

    def record(
        self, receive_to_solved: int, solve: int, encode_send: int, receive_to_sent: int
    ) -> None:
        """Store one frame's stage durations (ns), the :data:`STAGES`."""
        i = self.ring_pos
        r0, r1, r2, r3 = self.rings
        r0[i] = receive_to_solved
        r1[i] = solve
        r2[i] = encode_send
        r3[i] = receive_to_sent
        self.ring_pos = (i + 1) % RING
        if self.ring_count < RING:
            self.ring_count += 1

    def last(self) -> tuple[int, int, int, int]:
        """The stage durations (ns) :meth:`record` stored last, in :data:`STAGES`
        order (zeros before the first)."""
        j = (self.ring_pos - 1) % RING
        r0, r1, r2, r3 = self.rings
        return int(r0[j]), int(r1[j]), int(r2[j]), int(r3[j])

    def latency_us(self) -> dict[str, tuple[float, float]]:
        """Per stage (p50, p99) in microseconds over the last frames."""
        nan = (float("nan"), float("nan"))
        n = self.ring_count
        out = {s: nan for s in STAGES}
        if n:
            ns = np.array([r[:n] for r in self.rings], dtype=np.float64)
            p = np.percentile(ns / 1000.0, [50.0, 99.0], axis=1)
            out = {s: (float(p[0, i]), float(p[1, i])) for i, s in enumerate(STAGES)}
        m = self.post_count
        pp = (
            np.percentile(self.post_rings[:, :m] / 1000.0, [50.0, 99.0], axis=1)
            if m and self.post_names
            else None
        )
        for i, name in enumerate(self.post_names):
            out[POST_PREFIX + name] = (
                nan if pp is None else (float(pp[0, i]), float(pp[1, i]))
            )
        k = self.spine_count
        if k:
            sp = np.percentile(self.spine_ring[:k] / 1000.0, [50.0, 99.0])
            out[POST_PREFIX + "pivot"] = (float(sp[0]), float(sp[1]))
        return out

    def counters(self) -> dict[str, int]:
        """All integer counters by name."""
        return {
            name: int(getattr(self, name))
            for name in (
                "frames_in", "frames_solved", "frames_out", "stale", "overruns",
                "send_drops", "vmc_errors", "restarts", "calibrations",
                "calibrations_refused", "calibrations_expired",
                "calibration_failures", "rate_limited",
                "held_bone_frames", "occluded_samples", "pipeline_builds",
                "rejected_sources",
                "face_solved", "face_head_lost", "face_captures", "face_save_failures",
                "pipeline_failures", "calibration_save_failures",
                "validator_failures", "validated",
                "validation_flagged", "validation_drops", "zmq_disconnects",
                "unsolved", "unsolved_building", "unsolved_failed",
                "unseen", "unexplained", "reseeded",
                "labels_in",
                "show_control_in", "show_control_malformed",
                "control_requests", "control_errors", "control_oversize",
                "post_restarts",
                "resample_skipped", "resample_dropped", "resample_timer",
            )
        }  # fmt: skip
