"""A performer's frame path (with a body): the pipeline of a (rig, calibration, label
set) built once off the hot path; per frame the body and face solve, the retarget,
VMC datagrams and the ZeroMQ pose message from reused buffers, sends that never
block, the hand-off to the live validator after the send, and the per-stage latency
record. Its state is its own (:class:`BodyPath`); the loop's side comes in as
:class:`~retargetd.daemon.live.shared.Shared`.
"""

from __future__ import annotations

import logging
import math
import time
from typing import Any

import numpy as np

from retargetd.daemon.body.match import MatchWindow
from retargetd.daemon.body.solve import FLAG_HELD
from retargetd.daemon.live import held
from retargetd.daemon.live.emit import (
    DO_POSE,
    DO_RETARGET,
    DO_STANCE,
    DO_VMC,
    NO_FLAGS,
)
from retargetd.daemon.live.interval import frame_interval_s
from retargetd.daemon.live.one_call import arm, fused_done
from retargetd.daemon.live.performer import FrameSource, Performer
from retargetd.daemon.live.pipeline import Pipeline, new_pipeline, warm_up_pipeline
from retargetd.daemon.live.pipelines import Pipelines
from retargetd.daemon.live.shared import Shared
from retargetd.daemon.live.validation import Validation
from retargetd.protocols import pose_stream

logger = logging.getLogger(__name__)


_PERFORMER_MASK = pose_stream.PERFORMER_MASK


class BodyPath:
    """One performer's frame path when it has a body: its pipelines (one per stream
    or view it reads, rebuilt off the hot path when the rig, calibration or label
    set changes), and per frame the body solve, the post stages, the face, the
    retarget, the encoding and the sends; the live validator fed after the send.

    Args:
        perf: the performer (its rig, calibration, face, VMC destination).
        shared: the loop's side (config, counters, outputs, clocks).
    """

    def __init__(self, perf: Performer, shared: Shared) -> None:
        self.perf = perf
        self.shared = shared
        # Its pipeline per stream or view, each built off the loop (pipelines.py);
        # the dicts are the store's own, read here.
        self.store = Pipelines(perf, shared, self.announce_names)
        self.pipelines = self.store.pipelines  # id(stream or view) -> Pipeline
        self.labels_of = self.store.labels_of
        self.builds = self.store.builds  # id(stream or view) -> its next, building
        self.failed = self.store.failed  # id(stream or view) -> a build that raised
        self.last_names_ns = 0  # the names message last sent (again every second)
        self.frame_flags = 0  # set for the next pose (restarted, input dropped)
        # The calibration-match check over the stream's first second
        # (``body.match.MatchWindow``) and the frame flag it leaves on every later
        # pose (``calibration_mismatch``).
        self.match_window: MatchWindow | None = None
        self.match_flags = 0
        # Its live validator ([validate] on), built off the loop (validation.py).
        self.validation = Validation(perf, shared)
        # The frame between begin() and finish(): its pipeline, interval, markers
        # and start time (set before its solve, read by the solve and the finish).
        self._begun: Pipeline | None = None
        self._begun_dt = 0.0
        self._begun_markers: Any = None
        self._t_start = 0
        #: id(stream) -> the ``Shared.epoch`` its one-call path was last tried at
        #: (``one_call.arm``)
        self.tried: dict[int, int] = {}

    def pipeline(self, stream: FrameSource) -> Pipeline | None:
        """The pipeline to solve ``stream``'s current frame with, or None
        (``pipelines.Pipelines.for_frame``)."""
        return self.store.for_frame(stream)

    def prepare(self, key: int, labels: tuple[str, ...]) -> None:
        """A stream (or view) ``key`` took a label set: its pipeline's build starts
        now, off the loop (``pipelines.Pipelines.prepare``)."""
        self.store.prepare(key, labels)

    def ready(self, key: int, labels: tuple[str, ...]) -> bool:
        """Whether a frame of ``labels`` on ``key`` would be solved by its own
        pipeline now (``pipelines.Pipelines.ready``; tests)."""
        return self.store.ready(key, labels)

    def done_building(self, timeout_s: float) -> bool:
        """Wait for every build under way (``pipelines.Pipelines``; tests)."""
        return self.store.done_building(timeout_s)

    def warm_up(self) -> None:
        """Every stage run once on a throwaway pipeline (``warm_up_pipeline``)."""
        self.last_names_ns = 0
        warm_up_pipeline(self.perf, self.shared)

    def rebuild(self, labels: tuple[str, ...], sources: list[FrameSource]) -> None:
        """The face's training set changed: as :meth:`renew` (the training set is
        part of what a pipeline is built for)."""
        self.store.renew(labels, sources)

    def renew(self, labels: tuple[str, ...], sources: list[FrameSource]) -> None:
        """The rig, calibration or face training set changed: the new pipelines
        are built off the loop from now (``pipelines.Pipelines.renew``)."""
        self.store.renew(labels, sources)

    def restart(self, key: int) -> None:
        """The source of the pipeline ``key`` restarted: it starts over."""
        pipe = self.pipelines.get(key)
        if pipe is not None:
            pipe.solver.reset()
            pipe.vmc.reset_continuity()
            if pipe.face is not None:
                pipe.face.solver.reset()

    def build_pipeline(
        self, labels: tuple[str, ...], *, with_face: bool = True
    ) -> Pipeline:
        """A new pipeline for a stream of ``labels`` (``pipeline.new_pipeline``);
        its names are announced with the next frame."""
        self.last_names_ns = 0
        return new_pipeline(self.perf, self.shared, labels, with_face=with_face)

    def process(self, stream: FrameSource, received_ns: int) -> None:
        """Solve ``stream``'s current frame (received at ``received_ns``), post-process,
        retarget, encode and send it: :meth:`begin`, :meth:`solve_begun` and
        :meth:`finish` in a row (``performers.Performers`` may run several
        performers' middle steps on more threads: ``solve_threads.py``)."""
        if not self.begin(stream, received_ns):
            return
        pipe = self._begun
        assert pipe is not None
        if pipe.solve_emit is not None and self.validation.validator is None:
            self._solve_emit(pipe, stream, received_ns)  # one compiled call
        else:
            self.solve_begun()
            self.finish(stream, received_ns)

    def begin(self, stream: FrameSource, received_ns: int) -> bool:
        """The frame's first step, on the loop thread: its pipeline (a frame with
        none is counted unsolved here: False), the calibration-match check and the
        interval since the pipeline's last frame. True: :meth:`solve_begun` and
        then :meth:`finish` follow, before another frame begins."""
        # The clock starts before the pipeline lookup: a pipeline swapped in here
        # shows its cost in this frame's solve stage and overrun check.
        t_start = time.monotonic_ns()
        sh, perf = self.shared, self.perf
        stats = sh.stats
        pipe = self.pipeline(stream)
        if pipe is None:  # no calibration, or no pipeline built yet: counted
            stats.unsolved += 1
            if perf.calibration is not None:  # its pipeline being built (rebuild.py)
                if self.store.is_failed(id(stream)):  # or its build raised
                    stats.unsolved_failed += 1
                else:
                    stats.unsolved_building += 1
                self.frame_flags |= pose_stream.FRAME_INPUT_DROPPED
            if perf.console is not None:  # the markers, for the base pose
                perf.console.publish_markers(
                    t_start, stream.current.frame, stream.current.label_set.labels,
                    stats, sh.status,
                )  # fmt: skip
            return False
        frame = stream.current.frame
        window = self.match_window
        if (
            window is None
            or window.result is None
            or window.calibration is not perf.calibration
        ):
            self._check_calibration_match(window, pipe, frame, received_ns)
        self._begun = pipe
        self._begun_dt = self._frame_dt_s(pipe, frame, received_ns)
        self._begun_markers = frame.markers_world
        self._t_start = t_start
        return True

    def solve_begun(self) -> None:
        """The body solve of the frame :meth:`begin` took: its compiled call, which
        releases the GIL, the one step that may run on another thread. It touches
        only the pipeline's own solver state and pose."""
        pipe = self._begun
        assert pipe is not None
        pipe.solver.solve_frame(self._begun_markers, pipe.pose, self._begun_dt)

    def finish(self, stream: FrameSource, received_ns: int, turn_ns: int = 0) -> None:
        """The rest of the frame :meth:`begin` took and :meth:`solve_begun` solved,
        on the loop thread: the fit's flags, stance, post stages, face, retarget,
        encodes and sends, counters and latencies. ``turn_ns`` (not 0): when the
        loop turned to this performer, its solve taken or waited for since (with
        solve threads): its budget and solve stage count from then, as the serial
        path's count from its begin, after the performers before it."""
        pipe = self._begun
        assert pipe is not None
        self._begun = None
        sh = self.shared
        stats = sh.stats
        t_start = turn_ns or self._t_start
        frame = stream.current.frame
        dt = self._begun_dt
        pose = pipe.pose
        fit_bits = pose.frame_flags
        if fit_bits:
            if fit_bits & pose_stream.FRAME_UNSEEN:
                self.unseen(stream, received_ns, t_start)
                return
            if fit_bits & pose_stream.FRAME_UNEXPLAINED:
                stats.unexplained += 1
            if fit_bits & pose_stream.FRAME_RESEEDED:
                stats.reseeded += 1
        emit = pipe.emit
        assert emit is not None
        # On the solve, before the post stages (as solve); inside the emit call
        # when nothing runs between (``EmitPlan.bind``: the default pipeline).
        if pipe.stance is not None and emit.stance is None:
            pipe.stance_bits = pipe.stance.update(
                pose.root_pos, pose.world_from_bone_quat, dt
            )
        post = pipe.post
        source_t = frame.source_time_s
        frame_id, arrival_ns = frame.frame_id, received_ns
        if post is not None:  # [[pipeline]]: on the source's clock when it has one
            counts = post.restarts, post.dropped_ticks
            pipe.tick_source_clock = math.isfinite(source_t)
            due = post.apply(
                pose,
                source_t if pipe.tick_source_clock else (received_ns - sh.t0_ns) * 1e-9,
                received_ns,
                frame.frame_id,
            )
            stats.post_restarts += post.restarts - counts[0]
            stats.resample_dropped += post.dropped_ticks - counts[1]
            stats.record_post(post.stage_ns)
            if not due:  # output_rate_hz: no output tick in this frame
                stats.frames_solved += 1
                stats.resample_skipped += 1
                return
            if post.resampler is not None:  # the tick's time and its input's
                if pipe.tick_source_clock:
                    source_t = post.t_s
                frame_id, arrival_ns = post.tag, post.arrival_ns
        stats.frames_solved += 1
        stats.held_bone_frames += pose.n_held
        stats.occluded_samples += pose.n_occluded
        self._emit(pipe, stream, frame_id, source_t, arrival_ns, t_start, dt)
        if post is not None and post.resampler is not None:
            self._send_due_ticks_of(pipe, time.monotonic_ns())  # overdue ones too

    def unseen(self, stream: FrameSource, received_ns: int, t_start: int) -> None:
        """The performer's markers not seen: no pose to stream (counted; the
        console still shows the markers)."""
        sh, perf = self.shared, self.perf
        stats = sh.stats
        stats.unseen += 1
        stats.frames_solved += 1
        if sh.recording.packets is not None:  # a replay solves it too
            sh.recording.event("unseen", received_ns=received_ns)
        if perf.console is not None:
            perf.console.publish_markers(
                t_start, stream.current.frame, stream.current.label_set.labels,
                stats, sh.status,
            )  # fmt: skip

    def _check_calibration_match(
        self, window: Any, pipe: Pipeline, frame: Any, received_ns: int
    ) -> None:
        """Over the performer's first second of frames with this calibration: its
        segments' markers against their calibrated layout (``body.match``). A
        mismatch is one warning line, ``calibration_match`` in status and the
        ``calibration_mismatch`` frame flag on every later pose."""
        perf = self.perf
        calibration = perf.calibration
        if calibration is None:
            return
        if window is None or window.calibration is not calibration:
            window = self.match_window = MatchWindow(calibration, perf.rig.marker_names)
            self.match_flags = 0
        t_s = frame.source_time_s
        if not math.isfinite(t_s):
            t_s = received_ns * 1e-9
        found = window.add(frame.markers_world, pipe.solver.marker_cols, t_s)
        if found is None:
            return
        self.shared.bump()  # the window is over: the one-call path may arm
        line = found.warning()
        if line is None:
            logger.info("%s: %s", perf.label, found.summary())
            return
        self.match_flags = pose_stream.FRAME_CALIBRATION_MISMATCH
        logger.warning("%s: %s", perf.label, line)

    def _frame_dt_s(self, pipe: Pipeline, frame: Any, received_ns: int) -> float:
        """Seconds since the pipeline's last solved frame (:func:`frame_interval_s`)."""
        dt, pipe.last_times = frame_interval_s(
            pipe.last_times, frame, received_ns, self.shared.config.validate.rate_hz
        )
        return dt

    def send_due_ticks(self, now_ns: int) -> None:
        """From the loop's timer: every resampled output tick whose send time has
        come (``output_rate_hz`` above the input's rate: between input frames)."""
        for pipe in self.pipelines.values():
            post = pipe.post
            if post is not None and post.resampler is not None:
                self._send_due_ticks_of(pipe, now_ns)

    def _send_due_ticks_of(self, pipe: Pipeline, now_ns: int) -> None:
        post = pipe.post
        assert post is not None
        while post.pop_due(pipe.pose, now_ns):
            self.shared.stats.resample_timer += 1
            source_t = post.t_s if pipe.tick_source_clock else math.nan
            self._emit(pipe, None, post.tag, source_t, post.arrival_ns, now_ns)

    def next_tick_ns(self) -> int:
        """The earliest send time of a queued output tick over the pipelines
        (``time.monotonic_ns()``), -1 when none is queued."""
        best = -1
        for pipe in self.pipelines.values():
            post = pipe.post
            if post is None or post.resampler is None:
                continue
            due = post.next_due_ns()
            if due >= 0 and (best < 0 or due < best):
                best = due
        return best

    def _emit(
        self,
        pipe: Pipeline,
        stream: FrameSource | None,
        frame_id: int,
        source_t: float,
        received_ns: int,
        t_start: int,
        dt: float = 0.0,
    ) -> None:
        """Retarget and send the pose in ``pipe.pose``: for ``stream``'s current
        frame (solved now: the face solved, the validator, recording and console fed,
        the latency recorded) or, with ``stream`` None, a resampled tick from the
        timer (VMC and the pose stream only; ``received_ns`` its input's arrival).

        The face is solved first; ``solved_ns`` is taken then, and one compiled call
        (``emit.emit_frame``) finds the foot contact (when the loop left it to it:
        ``dt`` its step's interval), retargets, converts to the engine's frame and
        packs the VMC datagrams and the pose message; Python sends them."""
        pose = pipe.pose
        perf, sh = self.perf, self.shared
        stats, outputs = sh.stats, sh.outputs
        frame = stream.current.frame if stream is not None else None
        emit = pipe.emit
        assert emit is not None
        tp = emit.target_pose
        what = DO_RETARGET
        stance_bits = pipe.stance_bits  # found before, or (0) inside the call
        if emit.stance is not None and frame is not None:
            what |= DO_STANCE
            stance_bits = 0
        if pipe.spine is not None:  # [target] spine = "pivot", timed as post.pivot
            pipe.retargeter.apply(pose, tp)
            what = 0
            t0 = time.perf_counter_ns()
            pipe.spine.apply(tp.world_from_bone_quat, tp.rest_from_bone_quat)
            stats.record_spine(time.perf_counter_ns() - t0)
        if pipe.plant is not None:  # [target] feet = "plant", after the retarget
            if what:
                pipe.retargeter.apply(pose, tp)
            what = 0  # its plant_unreached flag rides self.frame_flags
            self.frame_flags |= pipe.plant.apply_pose(tp)
        face = pipe.face
        fo = face.out if face is not None else None
        if face is not None and frame is not None:
            fo = face.solve(frame.markers_world, frame.valid)
            stats.face_solved += 1
            if fo.status[0] & pose_stream.FACE_HEAD_LOST:
                stats.face_head_lost += 1
        solved_ns = time.monotonic_ns()
        flags = (
            self.frame_flags
            | self.match_flags  # calibration_mismatch, from the first second on
            | pose.frame_flags  # the fit's reseeded and unexplained bits
            | (pose_stream.FRAME_HELD if pose.n_held else 0)
            | stance_bits  # foot contact (FRAME_CONTACT_*)
        )
        self.frame_flags = 0
        val = self.validation
        validator = val.validator
        n_results = 0
        if validator is not None:
            if frame is not None:
                results = val.results
                n_results = validator.drain_results(results)  # no allocation
                if n_results:
                    val.take_bits(results[n_results - 1])
            flags |= val.bits
        vmc = perf.vmc
        vmc_on = vmc.on  # False: [output.vmc] off
        publish = outputs.publishing
        if vmc_on:
            what |= DO_VMC
        if publish:
            what |= DO_POSE
        vb = val.bones
        flags_word = (flags & ~_PERFORMER_MASK) | emit.performer_bits
        contact = emit.call(  # emit_frame's compiled function (EmitPlan.bind)
            what, *emit.args, NO_FLAGS if vb is None else vb,
            (solved_ns - sh.t0_ns) * 1e-9, frame_id, source_t, received_ns,
            solved_ns, flags_word, dt,
        )  # fmt: skip
        if what & DO_STANCE:  # the contact found inside the call, in the header
            pipe.stance_bits = contact
            flags_word |= contact
        self.sent(
            pipe, stream, frame_id, received_ns, t_start, solved_ns, flags_word,
            vmc_on, publish, vb, fo, n_results,
        )  # fmt: skip

    def _solve_emit(
        self, pipe: Pipeline, stream: FrameSource, received_ns: int
    ) -> None:
        """:meth:`solve_begun`, :meth:`finish` and :meth:`_emit`'s call for the
        frame :meth:`begin` took, on a pipeline whose solve and emit are one
        compiled call (``pipe.solve_emit``: no post stage, pivot, plant or face;
        no live validator): the flags the solve cannot change are set before it,
        the counters after it, from what it returns; the sends as after the emit
        call (:meth:`sent`)."""
        self._begun = None
        sh = self.shared
        frame = stream.current.frame
        fused, emit = pipe.solve_emit, pipe.emit
        assert fused is not None and emit is not None
        what = fused.what
        vmc_on, publish = self.perf.vmc.on, sh.outputs.publishing
        if vmc_on:
            what |= DO_VMC
        if publish:
            what |= DO_POSE
        # (the contact is found inside the call: pipe.stance_bits is not ORed in)
        flags = self.frame_flags | self.match_flags
        flags_word = (flags & ~_PERFORMER_MASK) | emit.performer_bits
        frame_id = frame.frame_id
        n_held, n_occ, fit_bits, contact, solved_ns = fused.call(
            what, frame.markers_world, *fused.args, sh.t0_ns, frame_id,
            frame.source_time_s, received_ns, flags_word, self._begun_dt,
        )  # fmt: skip
        if not fused_done(
            self, pipe, stream, frame_id, received_ns, self._t_start, what, flags_word,
            vmc_on, publish, n_held, n_occ, fit_bits, contact, solved_ns,
        ):  # fmt: skip
            return
        if self.tried.get(id(stream)) != sh.epoch:  # once per change, not per frame
            arm(self, pipe, stream)  # its next frames' one call (one_call.py)

    def sent(
        self,
        pipe: Pipeline,
        stream: FrameSource | None,
        frame_id: int,
        received_ns: int,
        t_start: int,
        solved_ns: int,
        flags_word: int,
        vmc_on: bool,
        publish: bool,
        vb: Any,
        fo: Any,
        n_results: int,
    ) -> None:
        """After the emit call: the VMC send, the pose message's flags, face and
        sends, then (for a frame, not a timer tick) the recording, the validator,
        the console, the overrun check and the latencies."""
        pose = pipe.pose
        perf, sh = self.perf, self.shared
        stats, outputs, recording = sh.stats, sh.outputs, sh.recording
        frame = stream.current.frame if stream is not None else None
        vmc = perf.vmc
        val = self.validation
        validator = val.validator
        face = pipe.face
        tp = pipe.target_pose
        if vmc_on:  # (one datagram to a loopback receiver; never blocks)
            vmc.send(pipe.vmc.datagrams)
        bone_flags = pose.bone_flags
        if publish:
            if solved_ns - self.last_names_ns >= 1_000_000_000:
                outputs.send_pub(pipe.names_parts, solved_ns)
                self.last_names_ns = solved_ns
            parts = pipe.pose_enc.parts
            if time.monotonic_ns() - t_start > sh.budget_ns:  # sent late, flagged
                pose_stream.stamp_flags(parts[0], flags_word | pose_stream.FRAME_LATE)
            if vb is not None and len(vb) == len(bone_flags):  # as sent, for the rest
                bone_flags = np.bitwise_or(bone_flags, vb, out=pipe.bone_flags)
            if fo is not None:
                pipe.pose_enc.encode_face(
                    fo.flags, fo.world_from_head_quat, fo.world_from_head_pos,
                    fo.markers_head,
                )  # fmt: skip
            sent_ns = time.monotonic_ns()
            pose_stream.stamp_sent(parts[0], sent_ns)
            outputs.send_pub(parts, sent_ns)
            if fo is not None and pipe.shape_enc is not None:
                # per-shape states, right after their pose (not recorded)
                outputs.send_unrecorded(pipe.shape_enc.encode(frame_id, fo.shape_state))
        sent_ns = time.monotonic_ns()
        stats.frames_out += 1
        if frame is None or stream is None:  # a timer tick: sent, nothing else
            return
        if recording.skeleton is not None:  # Foxglove channels: a queued copy
            recording.record_skeleton(
                pipe.solver,
                received_ns,
                pose,
                bone_flags,
                frame.markers_world,
                frame.valid,
            )
            recording.record_health(
                received_ns, sh.status, pose.n_occluded, stats.validation_flagged
            )
        # After the send: a copy into the validator's ring, never a wait.
        if validator is not None and not validator.submit(
            frame.frame_id, received_ns, pose.root_pos, pose.world_from_bone_quat,
            pose.rest_from_bone_quat, pose.joint_centres,
        ):  # fmt: skip
            stats.validation_drops += 1
        if n_results:  # published after this frame's pose: never ahead of a send
            val.publish(n_results, pipe.pose_enc.names_id)
        if perf.console is not None:  # a decimated copy, only when one is due
            perf.console.publish(
                sent_ns, perf.rig, pipe.solver, frame, stream.current.label_set.labels,
                pose, bone_flags,
                face.weight_names if face is not None else (),
                pipe.weights if face is not None else None, stats, sh.status,
                sh.target, tp, val.bits, val.values, vb,
            )  # fmt: skip
        if sent_ns - t_start > sh.budget_ns:
            stats.overruns += 1
        stats.record(
            solved_ns - received_ns, solved_ns - t_start, sent_ns - solved_ns,
            sent_ns - received_ns,
        )  # fmt: skip

    def flag(self, bits: int) -> None:
        """Frame flags for the next pose (restarted, input dropped)."""
        self.frame_flags |= bits

    def announce_names(self) -> None:
        """The next pose is preceded by its names message."""
        self.last_names_ns = 0

    def match_status(self) -> dict[str, Any] | None:
        """``calibration_match`` of the status: None before the first second of
        frames with this calibration has been checked (``body.match``)."""
        window = self.match_window
        if window is None or window.result is None:
            return None
        found = window.result
        return {
            "matches": found.matches,
            "frames": found.frames,
            "warning": found.warning(),
            "segments": found.to_json(),
        }

    def resend_held(self, key: int, now_ns: int) -> tuple[bool, bool]:
        """The last pose of the pipeline ``key`` sent again, held and source_lost
        (``held.resend_held``); (False, False) without one."""
        pipe = self.pipelines.get(key)
        if pipe is None:
            return False, False
        return held.resend_held(pipe, self.perf, self.shared, now_ns)

    def send_vmc_state(self, now_ns: int, calibrating: bool) -> None:
        """The VMC calibration state while no pose streams (``held.send_vmc_state``)."""
        held.send_vmc_state(self.perf, self.shared, now_ns, calibrating)

    @property
    def validator(self) -> Any:
        """The running live validator (``validate.live.LiveValidator``), or None."""
        return self.validation.validator

    def start_validator(self, wait: bool = False) -> None:
        """(Re)start the live validator on the current calibration ([validate] on):
        built off the loop (``validation.Validation.start``; ``wait``: at once)."""
        self.validation.start(wait)

    def tick_validator(self) -> None:
        """Every loop pass: a validator built off the loop swapped in; a pipeline
        build that waited for another one started (``Pipelines.tick``)."""
        self.validation.tick()
        if self.builds:
            self.store.tick()

    def validator_building(self) -> bool:
        """A live validator is being built off the loop now."""
        return self.validation.building

    def validation_status(self) -> dict[str, Any] | None:
        """The live validator's status (``ctl status``'s ``validate``); None when
        none runs."""
        return self.validation.status()

    def close(self) -> None:
        """Stop the live validator (idempotent)."""
        self.validation.close()

    def occluded_and_held(self) -> tuple[list[str], list[str]]:
        """The rig markers occluded and the bones held in the last frame its first
        pipeline solved."""
        pipe = next(iter(self.pipelines.values()), None)
        occluded: list[str] = []
        flagged: list[str] = []
        if pipe is not None:
            rig = self.perf.rig
            seen = getattr(pipe.solver, "_seen", None)  # the construction's markers
            pts_seen = (
                seen[: len(rig.markers)]
                if seen is not None
                else np.isfinite(pipe.pose.marker_residual)  # the fit's
            )
            occluded = [
                m for m, s in zip(rig.marker_names, pts_seen, strict=True) if not s
            ]
            flags = pipe.pose.bone_flags
            names = rig.bone_names
            flagged = [b for b, f in zip(names, flags, strict=True) if f & FLAG_HELD]
        return occluded, flagged
