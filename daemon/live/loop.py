"""The live loop: one thread owns the sockets and the solve.

A ``zmq.Poller`` waits on every input at once (plain UDP sockets and ZeroMQ sockets
alike). Each wake-up drains every readable socket, decoding marker packets straight
into preallocated buffers (``retargetd.protocols``); malformed packets are counted by
reason and dropped. Accepted frames are solved as they are decoded while the wake-up is
within ``solve_budget_ms`` (frames that merely arrived together are all solved); past
that the loop is behind and the latest frame wins: the older ones are counted as
``stale`` and dropped. ``process_every_frame`` solves every accepted frame in order
whatever the time (offline replay). A solved frame is retargeted onto the engine
skeleton, encoded as VMC datagrams and a ZeroMQ pose message, and sent without ever
blocking (a slow subscriber loses messages, counted). Solve + send has a budget
(``solve_budget_ms``): a frame over it is sent late, flagged and counted, never queued.

Control requests (``retargetd ctl``: status, calibrate, reload, record) arrive on a
local ZeroMQ REP socket; show-control arrives as OSC on VMC's performer port
(``/VMC/Ext/Set/Calib/Ready``, ``/VMC/Ext/Set/Calib/Exec``, ``/rtd/calibrate``,
``/rtd/reload``). A live calibration averages the next N accepted frames while the
stream goes on with the old calibration, then swaps the new one in atomically (the
loop thread is the only one that reads it) and saves it.

``record`` starts and stops a recording inside the daemon (``live_recording.py``):
the loop hands packets, poses and control events to a writer thread with
``put_nowait`` only, and never writes to the disk itself.

With ``[face]`` on, the same frame is also solved for the face (``live_face.py``:
stabilized markers and blendshape weights) before the send: the weights go out as
VMC blendshapes under the target's names and in the pose stream with the stabilized
markers. ``face-capture`` captures training poses live.

With ``[validate]`` on, every sent pose is handed to the live validator
(``validate_live.py``) with a non-blocking submit after the send; its results come
back on later frames: their bits are ORed into the next pose and each is published
as an ``RTDV`` message (``protocols/PROTOCOLS.md``).
"""

from __future__ import annotations

import contextlib
import gc
import json
import logging
import math
import socket
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zmq

from retargetd.daemon.body.calibration import Calibration, calibrate, load_calibration
from retargetd.daemon.body.rig import Rig, load_rig
from retargetd.daemon.body.solve import FLAG_HELD, BodySolver
from retargetd.daemon.live.config import DaemonConfig
from retargetd.daemon.live.face import FaceStage, LiveFace
from retargetd.daemon.live.face import warm_up as warm_up_face
from retargetd.daemon.live.recording import (
    FORM_OSC,
    FORM_ZMQ,
    LiveRecording,
    input_infos,
)
from retargetd.daemon.live.stats import LoopStats
from retargetd.daemon.target.retarget import (
    Retargeter,
    TargetSkeleton,
    default_humanoid,
    warm_up,
)
from retargetd.daemon.validate.live import LiveValidator
from retargetd.protocols import engine_unity, osc_in, pose_stream, zmq_wire
from retargetd.protocols.errors import DecodeError
from retargetd.protocols.marker_input import ACCEPTED, RESTART, LabelSet, MarkerStream
from retargetd.protocols.osc_wire import iter_bundle_elements, parse_message
from retargetd.protocols.vmc_out import VmcEncoder

logger = logging.getLogger(__name__)

_UDP_MAX = 65536
#: Largest control request accepted (bytes); ZeroMQ drops the connection of a
#: peer that sends more. A request is a small JSON object (a path at most).
CONTROL_MAX_BYTES = 65536


@dataclass(slots=True)
class _Pipeline:
    """Everything that depends on (rig, calibration, label set); rebuilt off the hot
    path when one of them changes."""

    solver: BodySolver
    retargeter: Any
    pose: Any
    target_pose: Any
    vmc: VmcEncoder
    bone_pos_unity: np.ndarray
    bone_quat_xyzw: np.ndarray
    root_pos_unity: np.ndarray
    root_quat_xyzw: np.ndarray
    blend: np.ndarray
    pose_enc: pose_stream.PoseEncoder
    names_parts: list[bytes]
    weights: np.ndarray
    bone_flags: np.ndarray  # sent bone flags: the solve's | the latest validation's
    face: FaceStage | None = None


class Daemon:
    """The live daemon (one performer). ``open()``, then ``run(should_exit)``.

    Args:
        config: validated configuration.
        out: where the "listening on" and stats lines go (``print`` by default).
    """

    def __init__(
        self, config: DaemonConfig, out: Callable[[str], None] | None = None
    ) -> None:
        self.config = config
        self.out = out or (lambda line: print(line, flush=True))
        self.stats = LoopStats()
        self.rig: Rig = load_rig(config.performer.rig)
        self.calibration: Calibration | None = None
        if config.performer.calibration:
            self.calibration = load_calibration(config.performer.calibration)
        self.target = _load_target(config)
        self._ctx: Any = zmq.Context.instance()
        self._poller = zmq.Poller()
        self._sockets: list[Any] = []
        self._osc: socket.socket | None = None
        self._show: socket.socket | None = None
        self._vmc: socket.socket | None = None
        self._zin: zmq.Socket[bytes] | None = None
        self._pub: zmq.Socket[bytes] | None = None
        self._ctl: zmq.Socket[bytes] | None = None
        osc_cfg, zmq_cfg = config.input.osc, config.input.zmq
        simple_labels = (
            LabelSet(0, osc_cfg.labels) if osc_cfg.form == "simple" else None
        )
        self.osc_stream = MarkerStream(simple_labels, osc_cfg.up, osc_cfg.units)
        self.zmq_stream = MarkerStream(None, zmq_cfg.up, zmq_cfg.units)
        self._pipelines: dict[int, _Pipeline] = {}  # id(MarkerStream) -> pipeline
        self._labels_of: dict[int, tuple[str, ...]] = {}
        self._names_id = 0
        self._last_names_ns = 0
        self._t0_ns = time.monotonic_ns()
        self._buf = bytearray(_UDP_MAX)
        self._allow = frozenset(osc_cfg.allow)
        self._calib_target = 0  # frames still wanted by a live calibration
        self._calib_frames: list[np.ndarray] = []
        self._calib_labels: tuple[str, ...] = ()
        self._calib_requested_by = ""
        self._frame_flags = 0  # restarted / input dropped since the last pose sent
        self._wake_ns = 0  # when the current wake-up began
        self._catch_up_ns = int(config.loop.solve_budget_ms * 1e6)
        # (t_ns, frames_in, frames_out) at the last stats line: fps over that window.
        self._window = (self._t0_ns, 0, 0)
        self.last_stats_line = ""
        self.endpoints: dict[str, str] = {}
        self.recording = LiveRecording()
        self._osc_form = FORM_OSC[osc_cfg.form]
        self.face: LiveFace | None = None
        if config.face.enabled:
            self.face = LiveFace(config.face, self.rig.marker_names)
        self.validator: Any = None  # LiveValidator when [validate] is on
        self._validation_bits = 0  # frame bits of the latest validation result
        self._validation_bones: np.ndarray | None = None  # its bone bits
        self._validation_enc: pose_stream.ValidationEncoder | None = None  # RTDV

    # ---- lifecycle -------------------------------------------------------------------

    def open(self) -> None:
        """Bind every endpoint; prints one "listening on" line each."""
        c = self.config
        if c.input.osc.enabled:
            self._osc = self._udp_bind(c.input.osc.host, c.input.osc.port)
            form = c.input.osc.form
            self._announce("osc markers", f"udp://{self._addr(self._osc)} ({form})")
        if c.show_control.enabled:
            self._show = self._udp_bind(c.show_control.host, c.show_control.port)
            self._announce("show control", f"udp://{self._addr(self._show)} (OSC)")
        if c.input.zmq.enabled:
            if c.input.zmq.mode == "pull":
                self._zin = self._ctx.socket(zmq.PULL)
                self._zin.setsockopt(zmq.LINGER, 0)
                self._zin.setsockopt(zmq.RCVHWM, 1000)
                self._zin.bind(c.input.zmq.endpoint)
            else:
                self._zin = self._ctx.socket(zmq.SUB)
                self._zin.setsockopt(zmq.LINGER, 0)
                self._zin.setsockopt(zmq.SUBSCRIBE, b"RTD")
                self._zin.connect(c.input.zmq.endpoint)
            self._poller.register(self._zin, zmq.POLLIN)
            self._sockets.append(self._zin)
            ep = _last_endpoint(self._zin) or c.input.zmq.endpoint
            self._announce("zmq markers", f"{ep} ({c.input.zmq.mode})")
        if c.output.pose.enabled:
            self._pub = self._ctx.socket(zmq.PUB)
            self._pub.setsockopt(zmq.LINGER, 0)
            self._pub.setsockopt(zmq.SNDHWM, c.output.pose.sndhwm)
            self._pub.bind(c.output.pose.endpoint)
            self._sockets.append(self._pub)
            ep = _last_endpoint(self._pub)
            self._announce("zmq poses", f"{ep} (pub)")
        self._ctl = self._ctx.socket(zmq.REP)
        self._ctl.setsockopt(zmq.LINGER, 0)
        self._ctl.setsockopt(zmq.MAXMSGSIZE, CONTROL_MAX_BYTES)
        self._ctl.bind(c.control.endpoint)
        self._poller.register(self._ctl, zmq.POLLIN)
        self._sockets.append(self._ctl)
        ep = _last_endpoint(self._ctl)
        self._announce("control", f"{ep} (retargetd ctl --endpoint {ep})")
        if c.output.vmc.enabled:
            self._vmc = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self._vmc.setblocking(False)
            self._vmc_addr = (c.output.vmc.host, c.output.vmc.port)
            self._announce("vmc out", f"udp://{c.output.vmc.host}:{c.output.vmc.port}")
        self._warm_up()
        self._start_validator()
        # Everything built so far lives as long as the daemon: keep it out of the
        # garbage collector's full passes (one took ~50 ms here, holding the GIL).
        gc.collect()
        gc.freeze()
        if self.calibration is None:
            self.out(
                "no calibration loaded: streaming starts after 'retargetd ctl "
                "calibrate' (or /VMC/Ext/Set/Calib/Exec) with the performer in the "
                "base pose"
            )

    def _warm_up(self) -> None:
        """Load the compiled kernel and run every stage once before the first frame
        arrives, so no streamed frame pays for it (numba's cache load is ~0.3 s)."""
        warm_up()
        if self.face is not None:
            warm_up_face()
        if self.calibration is None:
            return
        pipe = self._build_pipeline(self.rig.marker_names, with_face=False)
        nan_frame = np.full((len(self.rig.marker_names), 3), np.nan)
        pose = pipe.solver.solve_frame(nan_frame, pipe.pose)
        pipe.retargeter.apply(pose, pipe.target_pose)
        pipe.solver.reset()
        self._names_id -= 1  # this pipeline is thrown away; keep the ids dense

    def _start_validator(self) -> None:
        """(Re)start the live validator on the current calibration ([validate] on).

        Builds the MuJoCo model (cached by skeleton hash) and warms the kernels
        (tens of ms; seconds on a cold numba cache): at start-up, and after a live
        calibration or a reload, never per frame."""
        v = self.config.validate
        old, self.validator = self.validator, None
        if old is not None:
            old.close()
        self._validation_bits = 0
        self._validation_bones = None
        if not v.enabled or self.calibration is None:
            return

        validator = LiveValidator(
            self.rig,
            self.calibration,
            body_mass_kg=v.body_mass_kg or None,
            rate_hz=v.rate_hz,
            queue_size=v.queue,
        )
        validator.start()
        self.validator = validator
        self.out(
            f"live validator on: MuJoCo model {validator.vm.digest[:12]}, "
            f"queue {v.queue}, frame numbers at {v.rate_hz:g} Hz"
        )

    def _announce(self, what: str, where: str) -> None:
        self.endpoints[what] = where
        self.out(f"listening on {where}: {what}" if what != "vmc out" else
                 f"sending to {where}: {what}")  # fmt: skip

    def _udp_bind(self, host: str, port: int) -> socket.socket:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        sock.bind((host, port))
        sock.setblocking(False)
        self._poller.register(sock, zmq.POLLIN)
        self._sockets.append(sock)
        return sock

    @staticmethod
    def _addr(sock: socket.socket) -> str:
        host, port = sock.getsockname()[:2]
        return f"{host}:{port}"

    def close(self) -> None:
        """Stop an active recording (its file is finished, bounded wait) and close
        every socket (idempotent)."""
        self.recording.close()
        if self.validator is not None:
            self.validator.close()
            self.validator = None
        for sock in self._sockets:
            with contextlib.suppress(KeyError):
                self._poller.unregister(sock)
            sock.close()
        self._sockets.clear()
        if self._vmc is not None:
            self._vmc.close()
            self._vmc = None

    def run(self, should_exit: Callable[[], bool]) -> None:
        """Serve until ``should_exit()`` is true (checked every poll timeout)."""
        c = self.config.loop
        timeout = c.poll_timeout_ms
        next_stats = time.monotonic_ns() + int(c.stats_interval_s * 1e9)
        while not should_exit():
            events = dict(self._poller.poll(timeout))
            if events:
                self._service(events)
            now = time.monotonic_ns()
            if now >= next_stats:
                self.last_stats_line = self.stats_line()
                self._window = (now, self.stats.frames_in, self.stats.frames_out)
                self.out(self.last_stats_line)
                next_stats = now + int(c.stats_interval_s * 1e9)

    # ---- one wake-up -----------------------------------------------------------------

    def _service(self, events: dict[Any, int]) -> None:
        every = self.config.loop.process_every_frame
        self._wake_ns = time.monotonic_ns()
        newest: MarkerStream | None = None
        newest_ns = 0
        if self._osc is not None and self._osc.fileno() in events:
            got = self._drain_osc(every)
            if got:
                newest, newest_ns = self.osc_stream, got
        if self._zin is not None and self._zin in events:
            got = self._drain_zmq(every)
            if got and newest is not None and not every:
                # Both inputs delivered in one wake-up: only the newer one is solved,
                # so the other's newest frame is stale too (counted, never silent).
                self.stats.stale += 1
                self._frame_flags |= pose_stream.FRAME_INPUT_DROPPED
            if got and got >= newest_ns:
                newest, newest_ns = self.zmq_stream, got
        if newest is not None and not every:
            self._solve_and_send(newest, newest_ns)
        if self._show is not None and self._show.fileno() in events:
            self._drain_show_control()
        if self._ctl is not None and self._ctl in events:
            self._serve_control()

    def _accept(self, stream: MarkerStream, code: int, t_ns: int, every: bool) -> int:
        """Book-keeping for one decoded packet; returns its receive time when it was
        accepted and left for later (latest wins), else 0."""
        if code != ACCEPTED and code != RESTART:
            return 0
        self.stats.frames_in += 1
        stream.current.frame.t_ns = t_ns
        if code == RESTART:
            self.stats.restarts += 1
            self._frame_flags |= pose_stream.FRAME_RESTARTED
            pipe = self._pipelines.get(id(stream))
            if pipe is not None:
                pipe.solver.reset()
                pipe.vmc.reset_continuity()
                if pipe.face is not None:
                    pipe.face.solver.reset()
        if self._calib_target:
            self._collect_calibration_frame(stream)
        if self.face is not None and self.face.capturing:
            self._collect_face_frame(stream)
        # Solve at once while this wake-up is within the budget (frames that merely
        # arrived together are all solved); past it the loop is behind, and the
        # latest frame wins: this one waits and is dropped if a newer one comes.
        if every or time.monotonic_ns() - self._wake_ns < self._catch_up_ns:
            self._solve_and_send(stream, t_ns)
            return 0
        return t_ns

    def _drain_osc(self, every: bool) -> int:
        assert self._osc is not None
        sock, buf, stream = self._osc, self._buf, self.osc_stream
        simple = self.config.input.osc.form == "simple"
        view = memoryview(buf)
        newest = 0  # receive time of the newest accepted frame not yet solved
        while True:
            try:
                n, addr = sock.recvfrom_into(buf)
            except (BlockingIOError, InterruptedError):
                break
            if self._allow and addr[0] not in self._allow:
                self.stats.rejected_sources += 1
                continue
            t_ns = time.monotonic_ns()
            packet = view[:n]
            rec = self.recording.packets
            if rec is not None:
                rec.record_packet("osc", self._osc_form, t_ns, packet)
            if simple:
                code = stream.feed(osc_in.decode_simple_bundle, packet, t_ns=t_ns)
            elif n >= 12 and buf.startswith(b"/rtd/labels\0"):  # no per-packet copy
                try:
                    label_set = osc_in.decode_labels(packet)
                except DecodeError as exc:
                    stream.counters.add_reason(exc.reason)
                    continue
                stream.set_labels(label_set)
                continue
            else:
                code = stream.feed(osc_in.decode_compact_frame, packet, t_ns=t_ns)
            got = self._accept(stream, code, t_ns, every)
            if got:
                if newest:  # a newer frame supersedes the unsolved one: stale
                    self.stats.stale += 1
                    self._frame_flags |= pose_stream.FRAME_INPUT_DROPPED
                newest = got
        return newest

    def _drain_zmq(self, every: bool) -> int:
        assert self._zin is not None
        sock, stream = self._zin, self.zmq_stream
        newest = 0  # receive time of the newest accepted frame not yet solved
        while True:
            try:
                parts = sock.recv_multipart(zmq.NOBLOCK, copy=False)
            except zmq.Again:
                break
            t_ns = time.monotonic_ns()
            rec = self.recording.packets
            if rec is not None:
                rec.record_packet("zmq", FORM_ZMQ, t_ns, *(p.buffer for p in parts))
            if len(parts) != 2:
                stream.counters.add_reason("bad_length")
                continue
            header, payload = parts[0].buffer, parts[1].buffer
            if bytes(header[:4]) == zmq_wire.LABELS_MAGIC:
                try:
                    stream.set_labels(zmq_wire.decode_zmq_labels(header, payload))
                except DecodeError as exc:
                    stream.counters.add_reason(exc.reason)
                continue
            code = stream.feed(zmq_wire.decode_zmq_frame, header, payload, t_ns=t_ns)
            got = self._accept(stream, code, t_ns, every)
            if got:
                if newest:  # a newer frame supersedes the unsolved one: stale
                    self.stats.stale += 1
                    self._frame_flags |= pose_stream.FRAME_INPUT_DROPPED
                newest = got
        return newest

    # ---- solve and send --------------------------------------------------------------

    def _pipeline(self, stream: MarkerStream) -> _Pipeline | None:
        if self.calibration is None:
            return None
        labels = stream.current.label_set.labels
        key = id(stream)
        pipe = self._pipelines.get(key)
        if pipe is not None and self._labels_of.get(key) == labels:
            return pipe
        pipe = self._build_pipeline(labels)
        self._pipelines[key] = pipe
        self._labels_of[key] = labels
        return pipe

    def _build_pipeline(
        self, labels: tuple[str, ...], *, with_face: bool = True
    ) -> _Pipeline:
        assert self.calibration is not None
        solver = BodySolver(self.rig, self.calibration, labels)
        if solver.missing_markers:
            logger.warning(
                "rig %s markers not in the stream (occluded): %s",
                self.rig.name,
                " ".join(solver.missing_markers),
            )
        retargeter = Retargeter(
            self.rig,
            self.calibration,
            self.target,
            compensate_base_pose=self.config.target.compensate_base_pose,
        )
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
        )
        return _Pipeline(
            solver=solver,
            retargeter=retargeter,
            pose=solver.new_pose(),
            target_pose=target_pose,
            vmc=VmcEncoder(names, face.output_names if face is not None else ()),
            bone_pos_unity=bone_pos_unity,
            bone_quat_xyzw=np.zeros((n, 4)),
            root_pos_unity=np.zeros(3),
            root_quat_xyzw=np.array([0.0, 0.0, 0.0, 1.0]),
            blend=face.blend if face is not None else np.zeros(0),
            pose_enc=pose_stream.PoseEncoder(
                n_bones,
                len(weight_names),
                names_id=self._names_id,
                n_face_markers=len(face_markers) if face is not None else None,
            ),
            names_parts=pose_stream.encode_pose_names(names_msg),
            weights=face.weights if face is not None else np.zeros(0),
            bone_flags=np.zeros(n_bones, dtype=np.uint8),
            face=face,
        )

    def _solve_and_send(self, stream: MarkerStream, received_ns: int) -> None:
        pipe = self._pipeline(stream)
        if pipe is None:
            return
        frame = stream.current.frame
        t_start = time.monotonic_ns()
        pose = pipe.solver.solve_frame(frame.markers_world, pipe.pose)
        tp = pipe.retargeter.apply(pose, pipe.target_pose)
        face = pipe.face
        if face is not None:
            fo = face.solve(frame.markers_world, frame.valid)
            self.stats.face_solved += 1
            if fo.status[0] & pose_stream.FACE_HEAD_LOST:
                self.stats.face_head_lost += 1
        solved_ns = time.monotonic_ns()
        self.stats.frames_solved += 1
        self.stats.held_bone_frames += pose.n_held
        flags = self._frame_flags | (pose_stream.FRAME_HELD if pose.n_held else 0)
        self._frame_flags = 0
        validator = self.validator
        results: Sequence[Any] = ()
        if validator is not None:
            results = validator.results()
            if results:
                self._take_validation_bits(results)
            flags |= self._validation_bits
        # VMC: Unity frame, x y z w.
        engine_unity.unity_quat_xyzw_from_world(
            tp.parent_from_bone_quat, pipe.bone_quat_xyzw
        )
        engine_unity.unity_pos_from_world(tp.root_pos, pipe.root_pos_unity)
        t_s = (solved_ns - self._t0_ns) * 1e-9
        if self._vmc is not None:
            datagrams = pipe.vmc.encode(
                pipe.root_pos_unity, pipe.root_quat_xyzw, pipe.bone_pos_unity,
                pipe.bone_quat_xyzw, pipe.blend, t_s,
            )  # fmt: skip
            for dgram in datagrams:
                try:
                    self._vmc.sendto(dgram, self._vmc_addr)
                except OSError:  # receiver absent, buffer full: never block, count
                    self.stats.vmc_errors += 1
        budget_ns = int(self.config.loop.solve_budget_ms * 1e6)
        if self._pub is not None or self.recording.poses is not None:
            if solved_ns - self._last_names_ns >= 1_000_000_000:
                self._send_pub(pipe.names_parts, solved_ns)
                self._last_names_ns = solved_ns
            if time.monotonic_ns() - t_start > budget_ns:
                flags |= pose_stream.FRAME_LATE
            bone_flags = pose.bone_flags
            vb = self._validation_bones
            if vb is not None and len(vb) == len(bone_flags):
                bone_flags = np.bitwise_or(bone_flags, vb, out=pipe.bone_flags)
            parts = pipe.pose_enc.encode(
                frame.frame_id, frame.source_time_s, received_ns, solved_ns, flags,
                pose.root_pos, pose.world_from_bone_quat, pose.parent_from_bone_quat,
                pipe.weights, bone_flags,
            )  # fmt: skip
            if face is not None:
                pipe.pose_enc.encode_face(
                    fo.flags, fo.world_from_head_quat, fo.world_from_head_pos,
                    fo.markers_head,
                )  # fmt: skip
            sent_ns = time.monotonic_ns()
            pose_stream.stamp_sent(parts[0], sent_ns)
            self._send_pub(parts, sent_ns)
        sent_ns = time.monotonic_ns()
        # After the send: a copy into the validator's ring, never a wait.
        if validator is not None and not validator.submit(
            frame.frame_id, received_ns, pose.root_pos, pose.world_from_bone_quat,
            pose.parent_from_bone_quat, pose.joint_centres,
        ):  # fmt: skip
            self.stats.validation_drops += 1
        if results:  # published after this frame's pose: never ahead of a send
            self._publish_validation(results, pipe)
        self.stats.frames_out += 1
        if sent_ns - t_start > budget_ns:
            self.stats.overruns += 1
        self.stats.record(
            solved_ns - received_ns, solved_ns - t_start, sent_ns - solved_ns,
            sent_ns - received_ns,
        )  # fmt: skip

    def _take_validation_bits(self, results: Sequence[Any]) -> None:
        """Keep the latest result's bits for this and the next poses."""
        last = results[-1]
        self._validation_bits = last.frame_flags & pose_stream.FRAME_VALIDATION_MASK
        bones = last.bone_flags
        if self._validation_bones is None or len(self._validation_bones) != len(bones):
            self._validation_bones = np.zeros(len(bones), dtype=np.uint8)
        np.bitwise_and(bones, pose_stream.BONE_VALIDATION_MASK,
                       out=self._validation_bones)  # fmt: skip

    def _publish_validation(self, results: Sequence[Any], pipe: _Pipeline) -> None:
        """Count every result and publish it as an ``RTDV`` message (the frame it
        belongs to, its values), written into a reused buffer. The validator sets
        only the validation bits (frame bits 8-15, bone bits 4-7)."""
        for r in results:
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
        if self._pub is None:
            return
        try:
            self._pub.send_multipart(parts, zmq.NOBLOCK, copy=False)
        except zmq.Again:
            self.stats.send_drops += 1

    # ---- control ---------------------------------------------------------------------

    def request_calibration(self, count: int | None = None, by: str = "") -> str:
        """Start a live calibration over the next ``count`` accepted frames."""
        n = count or self.config.performer.calibrate_frames
        if n < 1:
            raise ValueError(f"count must be >= 1; got {n}")
        self._calib_target = n
        self._calib_frames = []
        self._calib_labels = ()
        self._calib_requested_by = by
        self.recording.event("calibration_requested", count=n, by=by)
        logger.info("calibration requested (%s): averaging %d frames", by, n)
        return f"calibrating over the next {n} frames: hold the base pose"

    def _collect_calibration_frame(self, stream: MarkerStream) -> None:
        labels = stream.current.label_set.labels
        if self._calib_labels and labels != self._calib_labels:
            self._calib_frames = []  # the marker layout changed: start again
        self._calib_labels = labels
        self._calib_frames.append(stream.current.frame.markers_world.copy())
        if len(self._calib_frames) >= self._calib_target:
            self._finish_calibration()

    def _collect_face_frame(self, stream: MarkerStream) -> None:
        assert self.face is not None
        labels = stream.current.label_set.labels
        done = self.face.collect(stream.current.frame.markers_world, labels)
        if done is None:
            return
        ok, msg = done
        if ok:
            # The next frame solves with the new training set; pipelines rebuilt now,
            # off the frame that completed the capture.
            self.stats.face_captures += 1
            self._pipelines.clear()
            self._labels_of.clear()
            for s in (self.osc_stream, self.zmq_stream):
                if s.current.label_set.labels == labels:
                    self._pipeline(s)
        self.recording.event("face_capture", ok=ok, message=msg)
        self.out(msg)

    def request_face_capture(
        self, name: str, count: int | None = None, by: str = ""
    ) -> str:
        """Start capturing face pose ``name`` over the next ``count`` frames."""
        if self.face is None:
            raise ValueError("the face is off: set [face] enabled = true")
        msg = self.face.request_capture(name, count)
        self.recording.event("face_capture_requested", name=name, by=by)
        return msg

    def _finish_calibration(self) -> None:
        frames = np.stack(self._calib_frames)
        labels = self._calib_labels
        self._calib_target = 0
        self._calib_frames = []
        try:
            cal = calibrate(
                self.rig,
                frames,
                labels,
                base_pose={"live": True, "frames": int(frames.shape[0]),
                           "requested_by": self._calib_requested_by},
            )  # fmt: skip
        except ValueError as exc:
            logger.warning("live calibration failed: %s", exc)
            self.recording.event("calibration_failed", error=str(exc))
            self.out(f"calibration failed: {exc}")
            return
        # Atomic: the loop thread is the only reader; the next frame uses the new one,
        # with its pipeline built now rather than on the next frame.
        self.calibration = cal
        self._pipelines.clear()
        self._labels_of.clear()
        for stream in (self.osc_stream, self.zmq_stream):
            if stream.current.label_set.labels == labels:
                self._pipeline(stream)
        self._start_validator()
        self.stats.calibrations += 1
        path = (
            self.config.performer.save_calibration or self.config.performer.calibration
        )
        self.recording.event(
            "calibrated", frames=int(frames.shape[0]), by=self._calib_requested_by,
            path=path or "",
        )  # fmt: skip
        if path:
            try:
                cal.save(path)
                self.out(f"calibrated on {frames.shape[0]} frames; saved {path}")
            except OSError as exc:
                self.out(f"calibrated on {frames.shape[0]} frames; NOT saved: {exc}")
        else:
            self.out(f"calibrated on {frames.shape[0]} frames (not saved: no path)")

    def reload(self) -> str:
        """Reload the rig file and the calibration file from disk."""
        try:
            rig = load_rig(self.config.performer.rig)
            cal = (
                load_calibration(self.config.performer.calibration)
                if self.config.performer.calibration
                else self.calibration
            )
            if cal is not None:
                BodySolver(rig, cal, ())  # checks the calibration fits the rig
        except ValueError as exc:
            msg = f"reload failed, kept the running rig and calibration: {exc}"
            self.recording.event("reload", ok=False, message=msg)
            return msg
        self.rig, self.calibration = rig, cal
        self._pipelines.clear()
        self._labels_of.clear()
        self._start_validator()
        msg = f"reloaded rig {rig.name}" + (" and calibration" if cal else "")
        self.recording.event("reload", ok=True, message=msg)
        return msg

    def status(self) -> dict[str, Any]:
        """The status document (``retargetd ctl status --json``)."""
        # None until the first frame: NaN is not JSON (jq and browsers refuse it).
        latency = {
            k: [_round_or_none(p50), _round_or_none(p99)]
            for k, (p50, p99) in self.stats.latency_us().items()
        }
        up_s = (time.monotonic_ns() - self._t0_ns) * 1e-9
        pipe = next(iter(self._pipelines.values()), None)
        occluded: list[str] = []
        flagged: list[str] = []
        if pipe is not None:
            solver = pipe.solver
            pts_seen = solver._seen[: len(self.rig.markers)]
            occluded = [
                m for m, s in zip(self.rig.marker_names, pts_seen, strict=True) if not s
            ]
            flags = pipe.pose.bone_flags
            names = self.rig.bone_names
            flagged = [b for b, f in zip(names, flags, strict=True) if f & FLAG_HELD]
        return {
            "uptime_s": round(up_s, 3),
            "rig": self.rig.name,
            "calibrated": self.calibration is not None,
            "calibrating": self._calib_target > 0,
            "endpoints": self.endpoints,
            "counters": self.stats.counters(),
            "fps_in": self._fps(self.stats.frames_in, 1),
            "fps_out": self._fps(self.stats.frames_out, 2),
            "fps_window_s": round((time.monotonic_ns() - self._window[0]) * 1e-9, 3),
            "drops": {
                "osc": self.osc_stream.counters.as_dict(),
                "zmq": self.zmq_stream.counters.as_dict(),
            },
            "latency_us": latency,
            "occluded_markers": occluded,
            "held_bones": flagged,
            "record": self.recording.status(),
            "face": self.face.status() if self.face is not None else None,
            "validate": self._validate_status(),
        }

    def _validate_status(self) -> dict[str, Any] | None:
        v = self.validator
        if v is None:
            return None
        status: dict[str, Any] = v.status()
        return status

    def _fps(self, count: int, which: int) -> float:
        """Frames per second since the last stats line (the recent rate, not the
        lifetime average: it falls to 0 when a source stops)."""
        dt = (time.monotonic_ns() - self._window[0]) * 1e-9
        return round((count - self._window[which]) / dt, 2) if dt > 0 else 0.0

    def stats_line(self) -> str:
        """The periodic one-line health summary."""
        s = self.status()
        lat = s["latency_us"]
        drops = {
            **s["drops"]["osc"],
            **{f"zmq.{k}": v for k, v in s["drops"]["zmq"].items()},
        }
        drops.pop("accepted", None)
        drops.pop("zmq.accepted", None)
        c = s["counters"]
        return (
            f"fps in {s['fps_in']:.1f} out {s['fps_out']:.1f} | latency us p50/p99 "
            f"solve {_us(lat['solve'][0])}/{_us(lat['solve'][1])} "
            f"recv->sent {_us(lat['receive_to_sent'][0])}/"
            f"{_us(lat['receive_to_sent'][1])}"
            f" | stale {c['stale']} overruns {c['overruns']} send drops "
            f"{c['send_drops']} | drops {drops or 0} | occluded "
            f"{len(s['occluded_markers'])} held {len(s['held_bones'])}"
            + ("" if s["calibrated"] else " | NOT CALIBRATED")
            + (
                f" | REC {s['record']['path']} dropped {s['record']['dropped']}"
                if s["record"]["active"]
                else ""
            )
            + (
                f" | face head lost {c['face_head_lost']}/{c['face_solved']}"
                if s["face"] is not None
                else ""
            )
            + (
                f" | validated {c['validated']} flagged {c['validation_flagged']} "
                f"dropped {c['validation_drops']}"
                if s["validate"] is not None
                else ""
            )
        )

    def _serve_control(self) -> None:
        assert self._ctl is not None
        try:
            # Every part of the request, so the REP socket is always ready to reply
            # (a multipart request read with recv() left it mid-message).
            parts = self._ctl.recv_multipart(zmq.NOBLOCK)
        except zmq.Again:
            return
        try:
            if len(parts) != 1:
                raise ValueError(
                    f"a control request is one JSON message; got {len(parts)} parts"
                )
            req = json.loads(parts[0])
            if not isinstance(req, dict):
                raise ValueError("request must be a JSON object")
            reply = self._control(req)
        except RecursionError:  # nesting deeper than the parser's stack
            reply = {"ok": False, "error": "request nested too deeply"}
        except (ValueError, TypeError) as exc:
            reply = {"ok": False, "error": str(exc)}
        try:
            self._ctl.send(json.dumps(reply).encode(), zmq.NOBLOCK)
        except zmq.ZMQError as exc:  # the requester vanished: nothing to answer
            logger.warning("control reply not sent: %s", exc)

    def _control(self, req: dict[str, Any]) -> dict[str, Any]:
        cmd = req.get("cmd")
        if cmd == "status":
            return {"ok": True, "status": self.status(), "line": self.stats_line()}
        if cmd == "calibrate":
            count = req.get("count")
            if count is not None and (type(count) is not int or count < 1):
                raise ValueError(f"count must be a positive integer; got {count!r}")
            return {"ok": True, "message": self.request_calibration(count, "ctl")}
        if cmd == "reload":
            msg = self.reload()
            return {"ok": not msg.startswith("reload failed"), "message": msg}
        if cmd == "record":
            return {"ok": True, "message": self._record_control(req)}
        if cmd == "face-capture":
            name, count = req.get("name"), req.get("count")
            if not isinstance(name, str) or not name:
                raise ValueError(f"face-capture needs a 'name' string; got {name!r}")
            if count is not None and (type(count) is not int or count < 1):
                raise ValueError(f"count must be a positive integer; got {count!r}")
            return {
                "ok": True,
                "message": self.request_face_capture(name, count, "ctl"),
            }
        raise ValueError(
            f"unknown command {cmd!r} (status, calibrate, reload, record, face-capture)"
        )

    def _record_control(self, req: dict[str, Any]) -> str:
        """``{"cmd": "record", "action": "start", "path": FILE, "poses": bool}`` or
        ``{"cmd": "record", "action": "stop"}``; ValueError names what is wrong."""
        action = req.get("action")
        if action == "stop":
            return self.recording.stop("ctl")
        if action != "start":
            raise ValueError(f"record action must be 'start' or 'stop'; got {action!r}")
        path = req.get("path")
        poses = req.get("poses", True)
        if not isinstance(path, str) or not path:
            raise ValueError(f"record start needs a 'path' string; got {path!r}")
        if type(poses) is not bool:
            raise ValueError(f"'poses' must be true or false; got {poses!r}")
        announcements: list[tuple[str, int, tuple[bytes, ...]]] = []
        if self._osc is not None and self.config.input.osc.form == "compact":
            ls = self.osc_stream.label_set
            if ls is not None:
                announcements.append(
                    ("osc", self._osc_form, (osc_in.encode_labels(ls),))
                )
        if self._zin is not None and self.zmq_stream.label_set is not None:
            parts = tuple(zmq_wire.encode_zmq_labels(self.zmq_stream.label_set))
            announcements.append(("zmq", FORM_ZMQ, parts))
        msg = self.recording.start(
            path, poses, input_infos(self.config, self.endpoints), announcements
        )
        self._last_names_ns = 0  # the names message opens the recorded pose stream
        return msg

    def _drain_show_control(self) -> None:
        assert self._show is not None
        while True:
            try:
                n, addr = self._show.recvfrom_into(self._buf)
            except (BlockingIOError, InterruptedError):
                break
            if self._allow and addr[0] not in self._allow:
                self.stats.rejected_sources += 1  # the same allow-list as the markers
                continue
            packet = bytes(self._buf[:n])
            for message in _osc_messages(packet):
                try:
                    address, _tags, args = parse_message(message)
                except DecodeError:
                    continue
                self._show_control(address, args, addr)

    def _show_control(self, address: str, args: list[Any], addr: Any) -> None:
        if address == "/VMC/Ext/Set/Calib/Ready":
            self.out(f"show control {addr[0]}: calibration ready (hold the base pose)")
        elif address in ("/VMC/Ext/Set/Calib/Exec", "/rtd/calibrate"):
            count = args[0] if address == "/rtd/calibrate" and args else None
            if type(count) is not int or count < 1:  # bool (OSC T/F) is not a count
                count = None
            self.out(self.request_calibration(count, f"show control {addr[0]}"))
        elif address == "/rtd/reload":
            self.out(self.reload())


def _round_or_none(value: float) -> float | None:
    return round(value, 1) if math.isfinite(value) else None


def _us(value: float | None) -> str:
    return "-" if value is None else f"{value:.0f}"


def _osc_messages(packet: bytes, depth: int = 0) -> list[bytes]:
    """The messages of an OSC packet (a message, or a bundle, flattened)."""
    if not packet.startswith(b"#bundle\0"):
        return [packet]
    if depth > 4:
        return []
    try:
        out: list[bytes] = []
        for element in iter_bundle_elements(packet):
            out.extend(_osc_messages(bytes(element), depth + 1))
        return out
    except DecodeError:
        return []


def _last_endpoint(sock: Any) -> str:
    """The endpoint a socket bound (with the real port of a ``*`` wildcard)."""
    value = sock.getsockopt(zmq.LAST_ENDPOINT)
    return value.decode() if isinstance(value, bytes) else str(value)


def _load_target(config: DaemonConfig) -> Any:
    t = config.target
    if t.skeleton == "humanoid":
        return default_humanoid()
    return TargetSkeleton.from_bvh(Path(t.skeleton), units=t.bvh_units, up=t.bvh_up)
