"""Solve and send: the pipeline of a (rig, calibration, label set) built once off the
hot path; per frame the body and face solve, the retarget, VMC datagrams and the
ZeroMQ pose message from reused buffers, sends that never block, the hand-off to the
live validator after the send, and the per-stage latency record.
"""

from __future__ import annotations

import logging
import math
import time
from typing import Any

import numpy as np
import zmq

from retargetd.daemon.body.match import MatchWindow
from retargetd.daemon.live.emit import DO_POSE, DO_RETARGET, DO_VMC, NO_FLAGS, EmitPlan
from retargetd.daemon.live.face_only import FaceOnlyMixin
from retargetd.daemon.live.performer import FrameSource
from retargetd.daemon.live.rebuild import body_solver, rebuilt_solver
from retargetd.daemon.live.state import Pipeline
from retargetd.daemon.post.pipeline import build_pipeline
from retargetd.daemon.post.pivot import spine_stage
from retargetd.daemon.post.plant import plant_stage
from retargetd.daemon.post.solve_post import SolvePost
from retargetd.daemon.post.stance import StanceDetector
from retargetd.daemon.target.retarget import Retargeter
from retargetd.protocols import engine_unity, pose_stream
from retargetd.protocols.vmc_out import (
    CALIBRATION_CALIBRATING,
    CALIBRATION_WAITING,
    VmcEncoder,
)

logger = logging.getLogger(__name__)


def frame_interval_s(
    last: tuple[float, int, int], frame: Any, received_ns: int, rate_hz: float
) -> tuple[float, tuple[float, int, int]]:
    """Seconds between a solved frame and the one solved before it, for the fit's
    prediction: the source's clock when it sends one, else its frame numbers at
    ``rate_hz`` (``[validate] rate_hz``), else the receive clock; 0 for the first
    frame (the solver's own rate then). Shared by the loop and the replays that
    reproduce it (``bench/soak.py``).

    Args:
        last: the previous solved frame's (source time s, frame number, receive ns);
            (NaN, -1, 0) before any.
        frame: this frame (``source_time_s``, ``frame_id``).
        received_ns: its receive time.
        rate_hz: the source's frame-number rate.

    Returns:
        (seconds, this frame's (source time, frame number, receive ns)).
    """
    last_t, last_id, last_ns = last
    t, fid = frame.source_time_s, frame.frame_id
    now = (t, fid, received_ns)
    if last_ns == 0:
        return 0.0, now
    if t == t and last_t == last_t and t > last_t:  # (NaN: no source clock)
        return float(t - last_t), now
    if fid > last_id >= 0:
        return (fid - last_id) / rate_hz, now
    return max(received_ns - last_ns, 0) * 1e-9, now


_NOBLOCK_MORE = zmq.NOBLOCK | zmq.SNDMORE
_PERFORMER_MASK = pose_stream.PERFORMER_MASK

#: How often the VMC state is sent while nothing is streamed (0.5 s).
VMC_STATE_INTERVAL_NS = 500_000_000


class SendMixin(FaceOnlyMixin):
    """Building the per-stream pipelines and solving, retargeting, encoding and sending
    one frame.
    """

    def _pipeline(self, stream: FrameSource) -> Pipeline | None:
        perf = self._perf  # (its attributes directly: no descriptor per frame)
        if perf.calibration is None:
            return None
        labels = stream.current.label_set.labels
        key = id(stream)
        pipe = perf.pipelines.get(key)
        solver = None
        if pipe is not None and perf.labels_of.get(key) == labels:
            rig, cal = pipe.built_for
            if rig is perf.rig and cal is perf.calibration:
                return pipe
            # A reload or a new calibration: the old pipeline solves until the new
            # solver is built off the loop (rebuild.py).
            solver = rebuilt_solver(pipe, perf.rig, perf.calibration, labels,
                                    self.config.solve.method,
                                    self.config.validate.rate_hz)  # fmt: skip
            if solver is None:
                return pipe
            self.recording.event("pipeline", received_ns=stream.current.frame.t_ns)
        pipe = self._build_pipeline(labels, solver=solver)
        self.stats.pipeline_builds += 1
        self._pipelines[key] = pipe
        self._labels_of[key] = labels
        self._prewarm.register((id(perf), key), pipe.solver, stream.current.frame)
        return pipe

    def _build_pipeline(
        self, labels: tuple[str, ...], *, with_face: bool = True, solver: Any = None
    ) -> Pipeline:
        """A stream's pipeline; ``solver``: its body solver, built already (off the
        loop: rebuild.py), else built here."""
        assert self.calibration is not None
        if solver is None:
            solver = body_solver(self.config.solve.method, self.rig, self.calibration,
                                 labels, self.config.validate.rate_hz)  # fmt: skip
        if solver.missing_markers:
            logger.warning(
                "rig %s markers not in the stream (occluded): %s",
                self.rig.name,
                " ".join(solver.missing_markers),
            )
        retargeter = Retargeter(
            self.rig, self.calibration, self.target,
            compensate_base_pose=self.config.target.compensate_base_pose,
        )  # fmt: skip
        target_pose = retargeter.new_pose()
        names = tuple(self.target.bone_names)
        n = len(names)
        bone_pos_unity = np.zeros((n, 3))
        engine_unity.unity_pos_from_world(
            np.asarray(target_pose.rest_offsets, dtype=np.float64), bone_pos_unity
        )
        self._names_id = (self._names_id + 1) % 65536
        self._last_names_ns = 0  # new names: announce them with the next frame
        n_bones = len(self.rig.bones)
        face = None
        if with_face and self.face is not None:
            face = self.face.stage(labels)
        weight_names = face.weight_names if face is not None else ()
        face_markers = face.marker_names if face is not None else ()
        names_msg = pose_stream.PoseNames(
            rig=self.rig.name,
            bone_names=self.rig.bone_names,
            bone_parents=self.rig.bone_parent_indices(),
            weight_names=weight_names,
            names_id=self._names_id,
            face_markers=face_markers,
            performer=self._perf.name,
            performer_id=self._perf.index,
            bone_humanoid=tuple(b.humanoid or "" for b in self.rig.bones),
            unobserved=face.unobserved if face is not None else (),
        )
        vmc = VmcEncoder(
            names,
            face.output_names if face is not None else (),
            max_datagram=self._perf.vmc_max_datagram,
        )
        pose_enc = pose_stream.PoseEncoder(
            n_bones,
            len(weight_names),
            names_id=self._names_id,
            n_face_markers=len(face_markers) if face is not None else None,
            performer=self._perf.index,
        )
        emit = EmitPlan(retargeter, vmc, pose_enc, bone_pos_unity)
        stance = StanceDetector(self.rig, self.calibration)
        pose = solver.new_pose()
        blend = face.blend if face is not None else np.zeros(0)
        weights = face.weights if face is not None else np.zeros(0)
        emit.bind(pose, blend, weights)
        return Pipeline(
            built_for=(self.rig, self.calibration),
            solver=solver,
            retargeter=retargeter,
            pose=pose,
            target_pose=emit.target_pose,
            vmc=vmc,
            bone_pos_unity=bone_pos_unity,
            bone_quat_xyzw=np.zeros((n, 4)),
            root_pos_unity=np.zeros(3),
            root_quat_xyzw=np.array([0.0, 0.0, 0.0, 1.0]),
            blend=blend,
            pose_enc=pose_enc,
            names_parts=pose_stream.encode_pose_names(names_msg),
            weights=weights,
            bone_flags=np.zeros(n_bones, dtype=np.uint8),
            face=face,
            shape_enc=(
                pose_stream.ShapeStateEncoder(len(weight_names), self._names_id)
                if face is not None
                else None
            ),
            post=self._build_post(),
            spine=spine_stage(self.config.target, self.target, self.rig),
            plant=plant_stage(self.config.target.feet, retargeter, stance),
            emit=emit,
            stance=stance,
        )

    def _build_post(self) -> SolvePost | None:
        """The ``[[pipeline]]`` stages for this rig and calibration (fresh state)."""
        rate = self.config.loop.output_rate_hz
        if not self.config.pipeline and not rate > 0.0:
            return None
        assert self.calibration is not None
        parents = self.rig.bone_parent_indices()
        rest = np.asarray(self.calibration.rest_parent_from_bone_quat, np.float64)
        stages = build_pipeline(
            self.config.pipeline,
            bone_names=self.rig.bone_names,
            bone_parents=parents,
            rest_parent_from_bone_quat=rest,
        )
        post = SolvePost(stages, parents, rest, output_rate_hz=rate)
        self.stats.set_post_stages(post.stage_names)
        return post

    def _solve_and_send(self, stream: FrameSource, received_ns: int) -> None:
        # The clock starts before the pipeline lookup: a pipeline built here (the
        # first frame after a new label set) shows its cost in this frame's solve
        # stage and overrun check, not hidden before it.
        if not self._perf.body:  # a face alone (face_only.py)
            return self._solve_and_send_face(stream, received_ns)
        t_start = time.monotonic_ns()
        pipe = self._pipeline(stream)
        if pipe is None:  # no calibration yet: counted, never silent
            self.stats.unsolved += 1
            if self.console is not None:  # the markers, for the base pose
                self.console.publish_markers(
                    t_start, stream.current.frame, stream.current.label_set.labels,
                    self.stats, self.status,
                )  # fmt: skip
            return
        frame = stream.current.frame
        perf = self._perf
        window = perf.match_window
        if (
            window is None
            or window.result is None
            or window.calibration is not perf.calibration
        ):
            self._check_calibration_match(window, pipe, frame, received_ns)
        dt = self._frame_dt_s(pipe, frame, received_ns)
        pose = pipe.solver.solve_frame(frame.markers_world, pipe.pose, dt)
        fit_bits = pose.frame_flags
        if fit_bits:
            if fit_bits & pose_stream.FRAME_UNSEEN:
                # the performer's markers not seen: no pose to stream (counted;
                # the console still shows the markers)
                self.stats.unseen += 1
                self.stats.frames_solved += 1
                if self.recording.packets is not None:  # a replay solves it too
                    self.recording.event("unseen", received_ns=received_ns)
                if self.console is not None:
                    self.console.publish_markers(
                        t_start, frame, stream.current.label_set.labels,
                        self.stats, self.status,
                    )  # fmt: skip
                return
            if fit_bits & pose_stream.FRAME_UNEXPLAINED:
                self.stats.unexplained += 1
            if fit_bits & pose_stream.FRAME_RESEEDED:
                self.stats.reseeded += 1
        if pipe.stance is not None:  # on the solve, before the post stages (as solve)
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
                source_t
                if pipe.tick_source_clock
                else (received_ns - self._t0_ns) * 1e-9,
                received_ns,
                frame.frame_id,
            )
            self.stats.post_restarts += post.restarts - counts[0]
            self.stats.resample_dropped += post.dropped_ticks - counts[1]
            self.stats.record_post(post.stage_ns)
            if not due:  # output_rate_hz: no output tick in this frame
                self.stats.frames_solved += 1
                self.stats.resample_skipped += 1
                return
            if post.resampler is not None:  # the tick's time and its input's
                if pipe.tick_source_clock:
                    source_t = post.t_s
                frame_id, arrival_ns = post.tag, post.arrival_ns
        self.stats.frames_solved += 1
        self.stats.held_bone_frames += pose.n_held
        self.stats.occluded_samples += pose.n_occluded
        self._emit(pipe, stream, frame_id, source_t, arrival_ns, t_start)
        if post is not None and post.resampler is not None:
            self._send_due_ticks_of(pipe, time.monotonic_ns())  # overdue ones too

    def _check_calibration_match(
        self, window: Any, pipe: Pipeline, frame: Any, received_ns: int
    ) -> None:
        """Over the performer's first second of frames with this calibration: its
        segments' markers against their calibrated layout (``body.match``). A
        mismatch is one warning line, ``calibration_match`` in status and the
        ``calibration_mismatch`` frame flag on every later pose."""
        perf = self._perf
        calibration = perf.calibration
        if calibration is None:
            return
        if window is None or window.calibration is not calibration:
            window = perf.match_window = MatchWindow(calibration, perf.rig.marker_names)
            perf.match_flags = 0
        t_s = frame.source_time_s
        if not math.isfinite(t_s):
            t_s = received_ns * 1e-9
        found = window.add(frame.markers_world, pipe.solver.marker_cols, t_s)
        if found is None:
            return
        line = found.warning()
        if line is None:
            logger.info("%s: %s", perf.label, found.summary())
            return
        perf.match_flags = pose_stream.FRAME_CALIBRATION_MISMATCH
        logger.warning("%s: %s", perf.label, line)

    def _frame_dt_s(self, pipe: Pipeline, frame: Any, received_ns: int) -> float:
        """Seconds since the pipeline's last solved frame (:func:`frame_interval_s`)."""
        dt, pipe.last_times = frame_interval_s(
            pipe.last_times, frame, received_ns, self.config.validate.rate_hz
        )
        return dt

    def _send_due_ticks(self, now_ns: int) -> None:
        """From the loop's timer: every resampled output tick whose send time has
        come (``output_rate_hz`` above the input's rate: between input frames)."""
        for pipe in self._pipelines.values():
            post = pipe.post
            if post is not None and post.resampler is not None:
                self._send_due_ticks_of(pipe, now_ns)

    def _send_due_ticks_of(self, pipe: Pipeline, now_ns: int) -> None:
        post = pipe.post
        assert post is not None
        while post.pop_due(pipe.pose, now_ns):
            self.stats.resample_timer += 1
            source_t = post.t_s if pipe.tick_source_clock else math.nan
            self._emit(pipe, None, post.tag, source_t, post.arrival_ns, now_ns)

    def next_tick_ns(self) -> int:
        """The earliest send time of a queued output tick over every performer's
        pipelines (``time.monotonic_ns()``), -1 when none is queued: the loop's
        poll wakes up for it."""
        best = -1
        for perf in self.performers:
            for pipe in perf.pipelines.values():
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
    ) -> None:
        """Retarget and send the pose in ``pipe.pose``: for ``stream``'s current
        frame (solved now: the face solved, the validator, recording and console fed,
        the latency recorded) or, with ``stream`` None, a resampled tick from the
        timer (VMC and the pose stream only; ``received_ns`` its input's arrival).

        The face is solved first; ``solved_ns`` is taken then, and one compiled call
        (``emit.emit_frame``) retargets, converts to the engine's frame and packs the
        VMC datagrams and the pose message; Python sends them."""
        pose = pipe.pose
        perf = self._perf  # its attributes read once (not one descriptor each)
        stats = self.stats
        frame = stream.current.frame if stream is not None else None
        emit = pipe.emit
        assert emit is not None
        tp = emit.target_pose
        what = DO_RETARGET
        if pipe.spine is not None:  # [target] spine = "pivot", timed as post.pivot
            pipe.retargeter.apply(pose, tp)
            what = 0
            t0 = time.perf_counter_ns()
            pipe.spine.apply(tp.world_from_bone_quat, tp.rest_from_bone_quat)
            stats.record_spine(time.perf_counter_ns() - t0)
        if pipe.plant is not None:  # [target] feet = "plant", after the retarget
            if what:
                pipe.retargeter.apply(pose, tp)
            what = 0  # its plant_unreached flag rides perf.frame_flags
            perf.frame_flags |= pipe.plant.apply_pose(tp)
        face = pipe.face
        fo = face.out if face is not None else None
        if face is not None and frame is not None:
            fo = face.solve(frame.markers_world, frame.valid)
            stats.face_solved += 1
            if fo.status[0] & pose_stream.FACE_HEAD_LOST:
                stats.face_head_lost += 1
        solved_ns = time.monotonic_ns()
        flags = (
            perf.frame_flags
            | perf.match_flags  # calibration_mismatch, from the first second on
            | pose.frame_flags  # the fit's reseeded and unexplained bits
            | (pose_stream.FRAME_HELD if pose.n_held else 0)
            | pipe.stance_bits  # foot contact (FRAME_CONTACT_*)
        )
        perf.frame_flags = 0
        validator = perf.validator
        results = perf.validation_results
        n_results = 0
        if validator is not None:
            if frame is not None:
                n_results = validator.drain_results(results)  # no allocation
                if n_results:
                    self._take_validation_bits(results[n_results - 1])
            flags |= perf.validation_bits
        vmc_sock = perf.vmc_sock  # None: [output.vmc] off
        publish = self._pub is not None or self.recording.poses is not None
        if vmc_sock is not None:
            what |= DO_VMC
        if publish:
            what |= DO_POSE
        vb = perf.validation_bones
        flags_word = (flags & ~_PERFORMER_MASK) | emit.performer_bits
        emit.call(  # emit_frame's compiled function (EmitPlan.bind)
            what, *emit.args, NO_FLAGS if vb is None else vb,
            (solved_ns - self._t0_ns) * 1e-9, frame_id, source_t, received_ns,
            solved_ns, flags_word,
        )  # fmt: skip
        if vmc_sock is not None:
            if perf.vmc_connected:  # (one datagram to a loopback receiver)
                for dgram in pipe.vmc.datagrams:
                    try:
                        vmc_sock.send(dgram)
                    except OSError:  # receiver absent, buffer full: never block
                        stats.vmc_errors += 1
            else:
                self._send_vmc_datagrams(pipe.vmc.datagrams)
        bone_flags = pose.bone_flags
        if publish:
            if solved_ns - perf.last_names_ns >= 1_000_000_000:
                self._send_pub(pipe.names_parts, solved_ns)
                perf.last_names_ns = solved_ns
            parts = pipe.pose_enc.parts
            if time.monotonic_ns() - t_start > self._budget_ns:  # sent late, flagged
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
            self._send_pub(parts, sent_ns)
            if fo is not None and pipe.shape_enc is not None and self._pub is not None:
                try:  # per-shape states, right after their pose (not recorded)
                    self._pub.send(
                        pipe.shape_enc.encode(frame_id, fo.shape_state), zmq.NOBLOCK
                    )
                except zmq.Again:
                    self.stats.send_drops += 1
        sent_ns = time.monotonic_ns()
        self.stats.frames_out += 1
        if frame is None or stream is None:  # a timer tick: sent, nothing else
            return
        if self.recording.skeleton is not None:  # Foxglove channels: a queued copy
            self.recording.record_skeleton(
                pipe.solver,
                received_ns,
                pose,
                bone_flags,
                frame.markers_world,
                frame.valid,
            )
            self.recording.record_health(
                received_ns, self.status, pose.n_occluded, self.stats.validation_flagged
            )
        # After the send: a copy into the validator's ring, never a wait.
        if validator is not None and not validator.submit(
            frame.frame_id, received_ns, pose.root_pos, pose.world_from_bone_quat,
            pose.rest_from_bone_quat, pose.joint_centres,
        ):  # fmt: skip
            self.stats.validation_drops += 1
        if n_results:  # published after this frame's pose: never ahead of a send
            self._publish_validation(results, n_results, pipe)
        if self.console is not None:  # a decimated copy, only when one is due
            self.console.publish(
                sent_ns, self.rig, pipe.solver, frame, stream.current.label_set.labels,
                pose, bone_flags,
                face.weight_names if face is not None else (),
                pipe.weights if face is not None else None, self.stats, self.status,
                self.target, tp, perf.validation_bits, perf.validation_values, vb,
            )  # fmt: skip
        if sent_ns - t_start > self._budget_ns:
            self.stats.overruns += 1
        self.stats.record(
            solved_ns - received_ns, solved_ns - t_start, sent_ns - solved_ns,
            sent_ns - received_ns,
        )  # fmt: skip

    def _take_validation_bits(self, last: Any) -> None:
        """Keep the latest result's bits for this and the next poses."""
        self._validation_bits = last.frame_flags & pose_stream.FRAME_VALIDATION_MASK
        bones = last.bone_flags
        if self._validation_bones is None or len(self._validation_bones) != len(bones):
            self._validation_bones = np.zeros(len(bones), dtype=np.uint8)
        np.bitwise_and(bones, pose_stream.BONE_VALIDATION_MASK,
                       out=self._validation_bones)  # fmt: skip
        np.copyto(self._validation_values, last.values, casting="same_kind")

    def _publish_validation(self, results: list[Any], n: int, pipe: Pipeline) -> None:
        """Count the first ``n`` results and publish each as an ``RTDV`` message (the
        frame it belongs to, its values), written into a reused buffer. The validator
        sets only the validation bits (frame bits 8-15, bone bits 4-7)."""
        for k in range(n):
            r = results[k]
            self.stats.validated += 1
            if r.frame_flags:
                self.stats.validation_flagged += 1
            if self._pub is not None or self.recording.poses is not None:
                enc = self._validation_enc
                if enc is None or enc.n_bones != len(r.bone_flags):
                    enc = pose_stream.ValidationEncoder(len(r.bone_flags))
                    self._validation_enc = enc
                msg = enc.encode(
                    pipe.pose_enc.names_id, r.frame_id, r.t_ns, r.validated_ns,
                    r.frame_flags, r.values, r.bone_flags,
                )  # fmt: skip
                self._send_pub(msg, r.validated_ns)

    def _send_pub(self, parts: list[Any], t_ns: int) -> None:
        rec = self.recording.poses
        if rec is not None:
            rec.record_pose(t_ns, *parts)
        pub = self._pub
        if pub is None:
            return
        # Part by part, each copied into its message: for parts this small a copy is
        # cheaper than send_multipart's zero-copy Frames (pose send at 240 Hz 45 -> ~20
        # µs median, bench/profile_loop.py). libzmq queues the parts and delivers the
        # message whole; a PUB at its high-water mark drops it whole (Again is
        # raised, if ever, by the first part only, before anything is queued).
        last = len(parts) - 1
        try:
            for i in range(last):
                pub.send(parts[i], _NOBLOCK_MORE)
            pub.send(parts[last], zmq.NOBLOCK)
        except zmq.Again:
            self.stats.send_drops += 1

    def _send_vmc_state(self, now_ns: int) -> None:
        """Before a calibration, and while one collects frames, tell the VMC receiver
        the state (``/VMC/Ext/OK`` calibration state 1 waiting or 2 calibrating, the
        tracking flag) about twice a second: no pose is streamed then, and silence
        reads as "no performer" in EVMC4U and VSeeFace."""
        if not self._vmc or now_ns < self._next_vmc_state_ns or not self._perf.body:
            return
        calibrating = self._calib_target > 0
        if self.calibration is not None and not calibrating:
            return
        self._next_vmc_state_ns = now_ns + VMC_STATE_INTERVAL_NS
        state = CALIBRATION_CALIBRATING if calibrating else CALIBRATION_WAITING
        tracking = now_ns - self._last_frame_ns < 1_000_000_000
        dgram = self._vmc_state.encode_state(
            state, tracking, (now_ns - self._t0_ns) * 1e-9
        )
        self._send_vmc_datagrams((dgram,))

    def _send_vmc_datagrams(self, datagrams: Any) -> None:
        """Send datagrams to the current performer's VMC receiver, never blocking: a
        refused one (receiver absent, buffer full, no route) is counted."""
        sock, addr = self._vmc_sock, self._vmc_addr
        assert sock is not None
        for dgram in datagrams:
            try:
                if self._vmc_connected:
                    sock.send(dgram)
                else:
                    sock.sendto(dgram, addr)
            except OSError:
                self.stats.vmc_errors += 1
