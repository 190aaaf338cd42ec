"""One compiled call per frame on the default body path (issue 35 item 3): a frame
packet's feed (the decode into the stream's spare packet, the sequencer, the
counter), the body solve and the emit in one call (``solve_emit.feed_solve_emit_*``),
where the loop otherwise makes two (``MarkerStream.feed_packed``, then the frame's
``solve_emit_*``) with Python between them.

A stream's path is *armed* (:func:`arm`, ``stream.fast``) after a frame's two calls
(``send.BodyPath._solve_emit``) found that nothing of the Python between them
applies to its next frames: one performer reading the whole stream (no view), no
``[[prop]]`` (``Shared.fast_ok``), a packed input (compact OSC or ZeroMQ:
``MarkerStream.wire``), the pipeline's fused call (no stage, pivot, plant or face),
no live validator, face or live calibration, the calibration-match window over, the
pipeline the stream's own and none being built for it. Whatever may change one of
these bumps ``Shared.epoch``; a path armed at another epoch is not used, and the next
frame's two calls try to arm it again (once per epoch and stream, not per frame).
The drains (``inputs.py``) take it for a wake-up's first solve: that frame is solved
at once on the two calls too, while a later one may be left for latest-wins
(``catchup.py``).
"""

from __future__ import annotations

from typing import Any

from retargetd.daemon.live.emit import DO_POSE, DO_STANCE, DO_VMC
from retargetd.daemon.live.performer import FrameSource
from retargetd.daemon.live.pipeline import Pipeline
from retargetd.protocols import pose_stream
from retargetd.protocols.kernels import direct
from retargetd.protocols.marker_input import ACCEPTED, MarkerPacket, MarkerStream

#: :meth:`FastFrame.run` outcomes besides the stream's codes: the frame was solved
#: and sent in the one call; the armed path no longer fits the stream (nothing done:
#: the caller feeds the packet as before).
FAST_SOLVED = -100
FAST_NOT_TAKEN = -101

_PERFORMER_MASK = pose_stream.PERFORMER_MASK


class FastFrame:
    """A stream's armed one-call path for one performer's pipeline: the compiled
    function and its arguments bound once for each of the stream's two packets (the
    decode alternates between them).

    Attributes:
        path: the performer's frame path; pipe: its pipeline for the stream.
        shared: the loop's side (its ``epoch``).
        epoch: the ``Shared.epoch`` it was armed at.
        packets, tails: the stream's two packets and the call's arguments from
            ``form`` on for a feed into each.
        call: the compiled function (past numba's dispatcher).
        what: ``SolveEmit.what``; performer_bits: the pose header's.
    """

    def __init__(
        self,
        path: Any,  # send.BodyPath (which imports this module)
        pipe: Pipeline,
        packets: tuple[MarkerPacket, MarkerPacket],
        tails: tuple[tuple[Any, ...], tuple[Any, ...]],
    ) -> None:
        fused, emit = pipe.solve_emit, pipe.emit
        assert fused is not None and emit is not None
        self.path, self.pipe, self.shared = path, pipe, path.shared
        self.epoch = path.shared.epoch
        self.packets, self.tails = packets, tails
        self.what = fused.what
        self.performer_bits = emit.performer_bits
        self.call: Any = direct(
            fused.fast_kernel, 0, 0, 0, fused.what, 0, 0.0, 0, 0, *tails[0]
        )

    def run(self, stream: MarkerStream, n_head: int, n_payload: int, t_ns: int) -> int:
        """A received frame packet of ``stream`` (in its receive buffers, sizes
        ``n_head`` / ``n_payload``, received at ``t_ns``) fed, solved and emitted in
        the one call, then what the two calls' Python does for it: the packets'
        swap (``MarkerStream.take``), ``Daemon._accept``'s counters and cadence,
        ``BodyPath.begin``'s interval bookkeeping, ``BodyPath._solve_emit``'s after
        its call, and the sends (``BodyPath.sent``); the same bytes, counters and
        state as ``feed_packed`` then ``BodyPath.process``.

        Returns:
            :data:`FAST_SOLVED` (the frame sent, or counted unseen); the stream's
            code when its packet was not accepted as a continuing frame, as
            ``feed_packed`` returns it (a refusal, counted; a ``RESTART``, swapped
            in, to be solved by the two calls' path; a negative ``kernels.D_*``:
            nothing changed); or :data:`FAST_NOT_TAKEN` (nothing done).
        """
        packets = self.packets
        spare = stream.spare_packet()
        if spare is packets[0]:
            tail = self.tails[0]
        elif spare is packets[1]:
            tail = self.tails[1]
        else:  # (the packets changed without a label set's bump: not armed)
            stream.fast = None
            return FAST_NOT_TAKEN
        path, sh, pipe = self.path, self.shared, self.pipe
        vmc_on, publish = path.perf.vmc.on, sh.outputs.publishing
        what = self.what
        if vmc_on:
            what |= DO_VMC
        if publish:
            what |= DO_POSE
        flags = path.frame_flags | path.match_flags
        flags_word = (flags & ~_PERFORMER_MASK) | self.performer_bits
        last_t, last_id, last_ns = pipe.last_times
        got = self.call(
            n_head, n_payload, t_ns, what, flags_word, last_t, last_id, last_ns, *tail
        )
        code, frame_id, source_t, n_held, n_occ, fit_bits, contact, solved_ns, t0 = got
        if stream.take(code, frame_id, source_t, t_ns) != ACCEPTED:
            return code
        stats = sh.stats
        stats.frames_in += 1  # (Daemon._accept)
        sh.last_frame_ns = t_ns
        sh.prewarm.observe(t_ns)
        pipe.last_times = (source_t, frame_id, t_ns)  # (begin: frame_interval_s)
        fused_done(  # (the rest as BodyPath._solve_emit after its call)
            path, pipe, stream, frame_id, t_ns, t0, what, flags_word, vmc_on, publish,
            n_held, n_occ, fit_bits, contact, solved_ns,
        )  # fmt: skip
        return FAST_SOLVED


def fused_done(
    path: Any, pipe: Pipeline, stream: FrameSource, frame_id: int, received_ns: int,
    t_start: int, what: int, flags_word: int, vmc_on: bool, publish: bool,
    n_held: int, n_occ: int, fit_bits: int, contact: int, solved_ns: int,
) -> bool:  # fmt: skip
    """After a compiled call that solved and emitted ``path``'s (a ``send.BodyPath``)
    frame (the frame's, ``BodyPath._solve_emit``, or the packet's with it,
    :class:`FastFrame`), from what it returned: the pose's and the loop's counters,
    the flags, then the sends (``BodyPath.sent``). False for a frame with no marker
    seen (counted, no pose: ``BodyPath.unseen``)."""
    stats = path.shared.stats
    pose = pipe.pose
    pose.n_held, pose.n_occluded, pose.frame_flags = n_held, n_occ, fit_bits
    if fit_bits:  # (as BodyPath.finish)
        if fit_bits & pose_stream.FRAME_UNSEEN:
            path.unseen(stream, received_ns, t_start)
            return False
        if fit_bits & pose_stream.FRAME_UNEXPLAINED:
            stats.unexplained += 1
        if fit_bits & pose_stream.FRAME_RESEEDED:
            stats.reseeded += 1
    stats.frames_solved += 1
    stats.held_bone_frames += n_held
    stats.occluded_samples += n_occ
    path.frame_flags = 0
    if what & DO_STANCE:
        pipe.stance_bits = contact
    flags_word |= fit_bits | contact | (pose_stream.FRAME_HELD if n_held else 0)
    path.sent(
        pipe, stream, frame_id, received_ns, t_start, solved_ns, flags_word, vmc_on,
        publish, None, None, 0,
    )  # fmt: skip
    return True


def arm(path: Any, pipe: Pipeline, stream: FrameSource) -> None:
    """After a frame's two calls (``path``'s, a ``send.BodyPath``, in its
    ``_solve_emit``): arm ``stream``'s one-call path (:class:`FastFrame`,
    ``stream.fast``) when its next frames can take it (the module's conditions).
    Tried once per ``Shared.epoch`` and stream (``path.tried``)."""
    sh, perf = path.shared, path.perf
    path.tried[id(stream)] = sh.epoch
    fused = pipe.solve_emit
    window = path.match_window
    if (
        not sh.fast_ok
        or fused is None
        or not isinstance(stream, MarkerStream)
        or stream.wire is None
        or path.validation.validator is not None
        or perf.face is not None
        or perf.calib.target
        or window is None
        or window.result is None
        or window.calibration is not perf.calibration
        or id(stream) in path.builds
        or path.pipelines.get(id(stream)) is not pipe
    ):
        return
    form, head, payload = stream.wire
    packets = stream.packets()
    rate_hz = float(sh.config.validate.rate_hz)
    tails = (
        (*stream.fused_tail(form, head, payload, packets[0]), *fused.args, sh.t0_ns,
         rate_hz),
        (*stream.fused_tail(form, head, payload, packets[1]), *fused.args, sh.t0_ns,
         rate_hz),
    )  # fmt: skip
    stream.fast = FastFrame(path, pipe, packets, tails)
