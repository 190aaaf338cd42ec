"""One wake-up of the loop: drain every readable marker input (OSC and ZeroMQ), decoding
straight into preallocated buffers; malformed packets counted by reason and dropped;
accepted frames solved at once while the wake-up is within ``solve_budget_ms``, past it
the latest frame wins (the rest counted ``stale``).
"""

from __future__ import annotations

import logging
import time
from typing import Any

import zmq

from retargetd.daemon.live.recording import (
    FORM_ZMQ,
)
from retargetd.daemon.live.state import DaemonState
from retargetd.protocols import osc_in, pose_stream, zmq_wire
from retargetd.protocols.errors import DecodeError
from retargetd.protocols.marker_input import ACCEPTED, RESTART, MarkerStream

logger = logging.getLogger(__name__)


class InputsMixin(DaemonState):
    """Draining the marker inputs in one wake-up: decode into preallocated buffers,
    count what is dropped, solve while within the budget, latest wins past it.
    """

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
