"""The body solve and the emit of one frame in one compiled call (issue 35 item 3).

On the default pipeline (no ``[[pipeline]]`` stage, pivot, foot plant or face, no
live validator) nothing runs between the body solve and the emit but book-keeping:
the fit's dt rule and its frame flags, the occluded count, the held flag and the
``solved_ns`` stamp. :func:`solve_emit_construction` and :func:`solve_emit_fit` do
that arithmetic themselves and call the body kernel (``body.kernel.solve_one`` /
``body.kernel_fit.fit_one``, unchanged) and :func:`emit.emit_frame` in turn, so the
loop crosses into compiled code twice per frame (the packet's feed, then this)
instead of three times. What they write is what ``solver.solve_frame`` and
``EmitPlan.call`` write one after the other, byte for byte
(``tests/daemon/test_solve_emit.py``, the PiG walk and mutated frames, both methods).

``solved_ns`` is read inside the call, between the solve and the emit, from the clock
``time.monotonic_ns()`` reads (``clock_gettime(CLOCK_MONOTONIC)``, called from the
compiled code: :func:`monotonic_ns`), so the stamps and the solve stage mean what
they meant. Where Python's monotonic clock is another one (not Linux), the loop
keeps the separate calls (:data:`AVAILABLE`).

numba caches a kernel by its own file and does not see a change in a callee from
another module; this module compiles with ``compiled.kernel``, whose cache folder is
named by the digest of every such module (``daemon/compiled.py``), the body kernels
and ``live/emit.py`` included, so an edit to any of them recompiles these too.
"""

from __future__ import annotations

import math
import sys
import time
from typing import Any

import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from retargetd.daemon.body import fit_terms as ft
from retargetd.daemon.body.kernel import solve_one
from retargetd.daemon.body.kernel_fit import fit_one
from retargetd.daemon.body.solve import warm_up as warm_up_construction
from retargetd.daemon.body.solve_fit import warm_up_solver as warm_up_fit
from retargetd.daemon.compiled import direct, kernel
from retargetd.daemon.live.emit import (
    DO_RETARGET,
    DO_STANCE,
    NO_FLAGS,
    EmitPlan,
    emit_frame,
    warm_args,
)
from retargetd.protocols.kernels import FORM_ZMQ, S_ACCEPTED, feed_frame
from retargetd.protocols.marker_input import LabelSet, MarkerStream
from retargetd.protocols.pose_stream import (
    FRAME_HELD,
    FRAME_RESEEDED,
    FRAME_UNEXPLAINED,
    FRAME_UNSEEN,
)

_CLOCK_ID = getattr(time, "CLOCK_MONOTONIC", -1)
#: Whether the compiled clock is ``time.monotonic_ns()``'s: the fused call is used
#: only then (Linux: ``clock_gettime(CLOCK_MONOTONIC)``).
AVAILABLE = (
    sys.platform.startswith("linux")
    and _CLOCK_ID >= 0
    and time.get_clock_info("monotonic").implementation
    == "clock_gettime(CLOCK_MONOTONIC)"
)


def _clock_gettime_impl(typingctx: Any) -> Any:
    # clock_gettime(CLOCK_MONOTONIC, &ts) from libc, an external symbol (cacheable:
    # resolved by name when the cached code loads); ts = {int64 sec, int64 nsec}.
    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        i32, i64 = ir.IntType(32), ir.IntType(64)
        ts_ty = ir.LiteralStructType([i64, i64])
        fnty = ir.FunctionType(i32, [i32, ts_ty.as_pointer()])
        fn = cgutils.get_or_insert_function(builder.module, fnty, "clock_gettime")
        ts = cgutils.alloca_once(builder, ts_ty)
        builder.call(fn, [ir.Constant(i32, max(_CLOCK_ID, 0)), ts])
        sec = builder.load(cgutils.gep_inbounds(builder, ts, 0, 0))
        nsec = builder.load(cgutils.gep_inbounds(builder, ts, 0, 1))
        return builder.add(builder.mul(sec, ir.Constant(i64, 1_000_000_000)), nsec)

    return types.int64(), codegen


#: ``clock_gettime(CLOCK_MONOTONIC)`` in ns, callable from compiled code only.
_clock_gettime_ns: Any = intrinsic(_clock_gettime_impl)


@kernel
def monotonic_ns() -> int:
    """``time.monotonic_ns()`` from compiled code (where :data:`AVAILABLE`)."""
    return _clock_gettime_ns()


@kernel
def _emit_solved(
    what: int, n_held: int, n_occ: int, fit_bits: int,
    wfb: np.ndarray, pfb: np.ndarray, rfb: np.ndarray, root: np.ndarray,
    bone_flags: np.ndarray, ei: np.ndarray, ef: np.ndarray, tflags: np.ndarray,
    last_quat: np.ndarray, stage32: np.ndarray, offsets: np.ndarray,
    wire: np.ndarray, header: np.ndarray, body: np.ndarray, blend: np.ndarray,
    weights: np.ndarray, stance_ints: np.ndarray, stance_floats: np.ndarray,
    or_flags: np.ndarray, t0_ns: int, frame_id: int, source_t: float,
    received_ns: int, flags_word: int, dt: float,
) -> tuple[int, int, int, int, int]:  # fmt: skip
    # The solved frame's stamp, flags and emit: what BodyPath._emit did between
    # the solve's call and the emit's (the held flag, the fit's bits, solved_ns).
    if fit_bits & FRAME_UNSEEN:  # no pose to stream (the loop counts it)
        return n_held, n_occ, fit_bits, 0, 0
    solved_ns = _clock_gettime_ns()
    flags_word |= fit_bits
    if n_held:
        flags_word |= FRAME_HELD
    contact = emit_frame(
        what, wfb, pfb, rfb, root, bone_flags, ei, ef, tflags, last_quat, stage32,
        offsets, wire, header, body, blend, weights, stance_ints, stance_floats,
        or_flags, (solved_ns - t0_ns) * 1e-9, frame_id, source_t, received_ns,
        solved_ns, flags_word, dt,
    )  # fmt: skip
    return n_held, n_occ, fit_bits, contact, solved_ns


@kernel
def solve_emit_construction(
    what: int, markers: np.ndarray,
    pi: np.ndarray, pf: np.ndarray, sf: np.ndarray, sb: np.ndarray, si: np.ndarray,
    of: np.ndarray, oq: np.ndarray, ofl: np.ndarray,
    wfb: np.ndarray, pfb: np.ndarray, rfb: np.ndarray, root: np.ndarray,
    bone_flags: np.ndarray, ei: np.ndarray, ef: np.ndarray, tflags: np.ndarray,
    last_quat: np.ndarray, stage32: np.ndarray, offsets: np.ndarray,
    wire: np.ndarray, header: np.ndarray, body: np.ndarray, blend: np.ndarray,
    weights: np.ndarray, stance_ints: np.ndarray, stance_floats: np.ndarray,
    or_flags: np.ndarray, t0_ns: int, frame_id: int, source_t: float,
    received_ns: int, flags_word: int, dt: float,
) -> tuple[int, int, int, int, int]:  # fmt: skip
    """``BodySolver.solve_frame`` (``kernel.solve_one`` on its packed buffers,
    ``BodySolver.packed_buffers``) then :func:`emit.emit_frame` on the solved pose.

    Args:
        what: ``emit.DO_*`` bits.
        markers: (M, 3) float64, the frame's markers (the solver's stream order).
        pi .. ofl: ``BodySolver.packed_buffers(pose)``.
        wfb .. stance_floats: ``EmitPlan.args``; or_flags: the validation's.
        t0_ns: the daemon's start (``/VMC/Ext/T`` counts from it).
        frame_id, source_t, received_ns: the pose header's.
        flags_word: its flags before the solve's (the performer's id in it).
        dt: seconds since the pipeline's last frame (the stance's step).

    Returns:
        (bones held, rig markers occluded, the solve's frame flags (0 here), the
        contact's bits (``emit_frame``'s), ``solved_ns``).
    """
    both = solve_one(markers, pi, pf, sf, sb, si, of, oq, ofl)
    return _emit_solved(
        what, both & 0xFFFFFFFF, both >> 32, 0, wfb, pfb, rfb, root, bone_flags, ei,
        ef, tflags, last_quat, stage32, offsets, wire, header, body, blend, weights,
        stance_ints, stance_floats, or_flags, t0_ns, frame_id, source_t,
        received_ns, flags_word, dt,
    )  # fmt: skip


@kernel
def solve_emit_fit(
    what: int, markers: np.ndarray,
    mf: np.ndarray, mi: np.ndarray, sf: np.ndarray, si: np.ndarray, sb: np.ndarray,
    lay: np.ndarray, con: tuple, of: np.ndarray, of4: np.ndarray, ou1: np.ndarray,
    ob: np.ndarray, scalars: np.ndarray, stats: np.ndarray,
    dt_default: float,
    wfb: np.ndarray, pfb: np.ndarray, rfb: np.ndarray, root: np.ndarray,
    bone_flags: np.ndarray, ei: np.ndarray, ef: np.ndarray, tflags: np.ndarray,
    last_quat: np.ndarray, stage32: np.ndarray, offsets: np.ndarray,
    wire: np.ndarray, header: np.ndarray, body: np.ndarray, blend: np.ndarray,
    weights: np.ndarray, stance_ints: np.ndarray, stance_floats: np.ndarray,
    or_flags: np.ndarray, t0_ns: int, frame_id: int, source_t: float,
    received_ns: int, flags_word: int, dt: float,
) -> tuple[int, int, int, int, int]:  # fmt: skip
    """``FitSolver.solve_frame`` (``kernel_fit.fit_one`` on its packed buffers, with
    its dt rule, frame flags and occluded count) then :func:`emit.emit_frame`, as
    :func:`solve_emit_construction` (``mf .. dt_default``:
    ``FitSolver.packed_buffers(pose)``). An unseen frame is not emitted (its flags
    returned with ``FRAME_UNSEEN``, ``solved_ns`` 0)."""
    scalars[ft.C_DT] = dt if dt > 0.0 else dt_default
    both = fit_one(markers, mf, mi, sf, si, sb, lay, con, of, of4, ou1, ob)
    n_held = both & 0xFFFFFFFF
    n_occ = both >> 32  # rig markers not seen: their residual is NaN
    fit_bits = 0
    if stats[ft.S_RESEEDED] != 0.0:  # (as Python's truth: NaN counts)
        fit_bits |= FRAME_RESEEDED
    if stats[ft.S_UNEXPLAINED] != 0.0:
        fit_bits |= FRAME_UNEXPLAINED
    if stats[ft.S_UNSEEN] != 0.0:
        fit_bits |= FRAME_UNSEEN
    return _emit_solved(
        what, n_held, n_occ, fit_bits, wfb, pfb, rfb, root, bone_flags, ei, ef, tflags,
        last_quat, stage32, offsets, wire, header, body, blend, weights, stance_ints,
        stance_floats, or_flags, t0_ns, frame_id, source_t, received_ns, flags_word,
        dt,
    )  # fmt: skip


@kernel
def interval_s(
    last_t: float, last_id: int, last_ns: int, t: float, fid: int, received_ns: int,
    rate_hz: float,
) -> float:  # fmt: skip
    """``interval.frame_interval_s``'s seconds, compiled (the same operations on
    the same float64 and int64 values: the same result, bit for bit)."""
    if last_ns == 0:
        return 0.0
    if t == t and last_t == last_t and t > last_t:  # (NaN: no source clock)
        return t - last_t
    if fid > last_id and last_id >= 0:
        return (fid - last_id) / rate_hz
    return max(received_ns - last_ns, 0) * 1e-9


@kernel
def feed_solve_emit_construction(
    n_head: int, n_payload: int, t_ns: int, what: int, flags_word: int,
    last_t: float, last_id: int, last_ns: int,
    form: int, head: np.ndarray, payload: np.ndarray, set_id: int,
    zero_is_occluded: bool, rhs: np.ndarray, raw32: np.ndarray, occluded: np.ndarray,
    valid: np.ndarray, markers: np.ndarray, limit_m: float, implausible: np.ndarray,
    q: np.ndarray, qf: np.ndarray, counts: np.ndarray, source_time: np.ndarray,
    pi: np.ndarray, pf: np.ndarray, sf: np.ndarray, sb: np.ndarray, si: np.ndarray,
    of: np.ndarray, oq: np.ndarray, ofl: np.ndarray,
    wfb: np.ndarray, pfb: np.ndarray, rfb: np.ndarray, root: np.ndarray,
    bone_flags: np.ndarray, ei: np.ndarray, ef: np.ndarray, tflags: np.ndarray,
    last_quat: np.ndarray, stage32: np.ndarray, offsets: np.ndarray,
    wire: np.ndarray, header: np.ndarray, body: np.ndarray, blend: np.ndarray,
    weights: np.ndarray, stance_ints: np.ndarray, stance_floats: np.ndarray,
    or_flags: np.ndarray, t0_ns: int, rate_hz: float,
) -> tuple[int, int, float, int, int, int, int, int, int]:  # fmt: skip
    """A packet's feed (``kernels.feed_frame``: the decode into the stream's spare
    packet, the sequencer, the outcome's counter) and, when the frame is
    ``ACCEPTED``, its interval (:func:`interval_s`) and
    :func:`solve_emit_construction` on it: the one compiled call per frame of the
    default live path (``one_call.FastFrame.run``).

    Args:
        n_head .. t_ns: the packet's sizes and receive time.
        what, flags_word: as :func:`solve_emit_construction`'s.
        last_t, last_id, last_ns: the pipeline's ``last_times``.
        form .. source_time: ``feed_frame``'s per-stream and per-packet arrays
            (``MarkerStream.fused_tail``); ``markers`` the spare's frame, solved.
        pi .. or_flags: ``SolveEmit.args``.
        t0_ns: the daemon's start; rate_hz: ``[validate] rate_hz``.

    Returns:
        (code, frame number, source time, then, when the code is ``S_ACCEPTED``,
        :func:`solve_emit_construction`'s five and the clock read after the feed
        (the frame's start), else zeros: nothing solved, the caller goes on as after
        ``feed_frame``).
    """
    code, frame_id, source_t = feed_frame(
        form, head, n_head, payload, n_payload, t_ns, set_id, zero_is_occluded, rhs,
        raw32, occluded, valid, markers, limit_m, implausible, q, qf, counts,
        source_time,
    )  # fmt: skip
    if code != S_ACCEPTED:
        return code, frame_id, source_t, 0, 0, 0, 0, 0, 0
    t_start = _clock_gettime_ns()
    dt = interval_s(last_t, last_id, last_ns, source_t, frame_id, t_ns, rate_hz)
    n_held, n_occ, fit_bits, contact, solved_ns = solve_emit_construction(
        what, markers, pi, pf, sf, sb, si, of, oq, ofl, wfb, pfb, rfb, root,
        bone_flags, ei, ef, tflags, last_quat, stage32, offsets, wire, header, body,
        blend, weights, stance_ints, stance_floats, or_flags, t0_ns, frame_id,
        source_t, t_ns, flags_word, dt,
    )  # fmt: skip
    return (
        code, frame_id, source_t, n_held, n_occ, fit_bits, contact, solved_ns, t_start
    )  # fmt: skip


@kernel
def feed_solve_emit_fit(
    n_head: int, n_payload: int, t_ns: int, what: int, flags_word: int,
    last_t: float, last_id: int, last_ns: int,
    form: int, head: np.ndarray, payload: np.ndarray, set_id: int,
    zero_is_occluded: bool, rhs: np.ndarray, raw32: np.ndarray, occluded: np.ndarray,
    valid: np.ndarray, markers: np.ndarray, limit_m: float, implausible: np.ndarray,
    q: np.ndarray, qf: np.ndarray, counts: np.ndarray, source_time: np.ndarray,
    mf: np.ndarray, mi: np.ndarray, sf: np.ndarray, si: np.ndarray, sb: np.ndarray,
    lay: np.ndarray, con: tuple, of: np.ndarray, of4: np.ndarray, ou1: np.ndarray,
    ob: np.ndarray, scalars: np.ndarray, stats: np.ndarray,
    dt_default: float,
    wfb: np.ndarray, pfb: np.ndarray, rfb: np.ndarray, root: np.ndarray,
    bone_flags: np.ndarray, ei: np.ndarray, ef: np.ndarray, tflags: np.ndarray,
    last_quat: np.ndarray, stage32: np.ndarray, offsets: np.ndarray,
    wire: np.ndarray, header: np.ndarray, body: np.ndarray, blend: np.ndarray,
    weights: np.ndarray, stance_ints: np.ndarray, stance_floats: np.ndarray,
    or_flags: np.ndarray, t0_ns: int, rate_hz: float,
) -> tuple[int, int, float, int, int, int, int, int, int]:  # fmt: skip
    """:func:`feed_solve_emit_construction` with the fit: ``mf .. dt_default``
    ``FitSolver.packed_buffers(pose)``, then :func:`solve_emit_fit`."""
    code, frame_id, source_t = feed_frame(
        form, head, n_head, payload, n_payload, t_ns, set_id, zero_is_occluded, rhs,
        raw32, occluded, valid, markers, limit_m, implausible, q, qf, counts,
        source_time,
    )  # fmt: skip
    if code != S_ACCEPTED:
        return code, frame_id, source_t, 0, 0, 0, 0, 0, 0
    t_start = _clock_gettime_ns()
    dt = interval_s(last_t, last_id, last_ns, source_t, frame_id, t_ns, rate_hz)
    n_held, n_occ, fit_bits, contact, solved_ns = solve_emit_fit(
        what, markers, mf, mi, sf, si, sb, lay, con, of, of4, ou1, ob, scalars, stats,
        dt_default, wfb, pfb, rfb, root, bone_flags, ei, ef, tflags, last_quat,
        stage32, offsets, wire, header, body, blend, weights, stance_ints,
        stance_floats, or_flags, t0_ns, frame_id, source_t, t_ns, flags_word, dt,
    )  # fmt: skip
    return (
        code, frame_id, source_t, n_held, n_occ, fit_bits, contact, solved_ns, t_start
    )  # fmt: skip


class SolveEmit:
    """One pipeline's fused call: its solver's packed buffers and its emit plan's
    arrays bound once (``args``), the compiled function found for their types
    (``call``, past numba's dispatcher, as ``EmitPlan.call``).

    Per frame: ``call(what, markers, *args, t0_ns, frame_id, source_t,
    received_ns, flags_word, dt)``.

    Args:
        solver: the pipeline's ``BodySolver`` or ``FitSolver``.
        pose: its pose (``solver.new_pose()``, bound in ``plan``).
        plan: the pipeline's bound emit plan (:meth:`EmitPlan.bind`).
    """

    def __init__(self, solver: Any, pose: Any, plan: EmitPlan) -> None:
        fit = hasattr(pose, "fit_buffers")
        self.kernel: Any = solve_emit_fit if fit else solve_emit_construction
        #: the packet's feed, this and the frame's interval in one call
        #: (``one_call.FastFrame``)
        self.fast_kernel: Any = (
            feed_solve_emit_fit if fit else feed_solve_emit_construction
        )
        #: the ``what`` bits every frame has (the retarget, the contact when the
        #: plan runs it); the loop adds VMC and the pose when they are on
        self.what = DO_RETARGET | (0 if plan.stance is None else DO_STANCE)
        self.args: tuple[Any, ...] = (
            *solver.packed_buffers(pose),
            *plan.args,
            NO_FLAGS,
        )
        markers = np.zeros((solver.n_stream, 3))
        self.call: Any = direct(
            self.kernel, self.what, markers, *self.args, 0, 0, 0.0, 0, 0, 0.0
        )


def warm_call(fit: bool) -> tuple[Any, tuple[Any, ...]]:
    """The fused kernel of a body method and arguments of the types a pipeline's
    :class:`SolveEmit` passes (``tests/daemon/test_solve_emit.py`` compares them):
    the warm-up rig's solver and pose (``solve.warm_up``, ``solve_fit.
    warm_up_solver``), a one-bone plan (``emit.warm_args``), an all-hidden frame,
    ``what`` 0 (the fit: an unseen frame, not emitted; the construction: an emit
    that only slices its arenas). Nothing here is a real pipeline's."""
    solver: Any
    pose: Any
    solver, pose = warm_up_fit() if fit else warm_up_construction()
    fused = solve_emit_fit if fit else solve_emit_construction
    markers = np.full((solver.n_stream, 3), np.nan)
    args = (
        0, markers, *solver.packed_buffers(pose), pose.world_from_bone_quat,
        pose.parent_from_bone_quat, pose.rest_from_bone_quat, pose.root_pos,
        pose.bone_flags, *warm_args(), NO_FLAGS, 0, 0, math.nan, 0, 0, 0.0,
    )  # fmt: skip
    return fused, args


def warm_fast_call(fit: bool) -> tuple[Any, tuple[Any, ...]]:
    """As :func:`warm_call`, for the packet's feed, the solve and the emit in one
    call (``feed_solve_emit_*``): a stream of the warm-up rig's marker count
    whose packets decode from receive buffers of the types the live inputs pass
    (``np.frombuffer`` over a ``bytearray``), an empty packet (refused at once by
    the decode: nothing solved), then :func:`warm_call`'s arrays."""
    _, warm = warm_call(fit)
    n = warm[1].shape[0]
    stream = MarkerStream(LabelSet(0, tuple(f"m{i}" for i in range(n))))
    head = np.frombuffer(bytearray(64), dtype=np.uint8)
    payload = np.frombuffer(bytearray(64), dtype=np.uint8)
    tail = stream.fused_tail(FORM_ZMQ, head, payload, stream.packets()[1])
    fused = feed_solve_emit_fit if fit else feed_solve_emit_construction
    solve_args = warm[2:-6]  # the solver's buffers, the plan's, the validation's
    args = (0, 0, 0, 0, 0, math.nan, -1, 0, *tail, *solve_args, 0, 240.0)
    return fused, args


def warm_up(fit: bool) -> None:
    """Compile (or load from numba's cache) the fused kernel of the body method at
    the daemon's start, with the other kernels (where :data:`AVAILABLE`).

    Without it the kernel was first found by the pipeline's first frame: on a
    start with a calibration the throwaway pipeline's warm-up found it, after the
    daemon had announced its endpoints; a daemon that calibrates live (``retargetd
    demo``) stalled its first streamed frame for the cache load (~0.3 s) or, on a
    cache without it, for the compile (13 s of CPU here, 29 s at load 5). A start
    killed during that compile (a test's deadline) never saved it, so every later
    start compiled it again (README "Fewer Python steps per frame")."""
    if AVAILABLE:
        fused, args = warm_call(fit)
        fused(*args)
        fast, args = warm_fast_call(fit)  # and the one with the packet's feed
        fast(*args)
