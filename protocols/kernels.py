"""Compiled inner loops of the wire codecs (numba), each replacing a run of numpy calls
on the live path by one call.

- :func:`decode_frame`: a compact OSC frame's or a ZeroMQ frame's checks and then
  :func:`store_rows`, what ``decode_compact_frame`` / ``decode_zmq_frame`` do in a
  dozen Python checks, a struct unpack and a byte swap;
- :func:`store_rows`: a decoded marker block into the frame (occlusion by NaN or an
  exact zero row, the inf check, the fused axis and unit conversion), what
  ``MarkerPacket.store`` did in twelve numpy calls (~1 µs each);
- :func:`sequence_check`: ``marker_input.FrameSequencer``'s rules over its state
  array (the sequencer calls it: one implementation), and :func:`feed_frame`: a
  packet's decode, its sequencing and its counter in one call, what
  ``MarkerStream.feed`` did around the decode in Python (the live loop's drains call
  it through :func:`direct`);
- :func:`vmc_pack`: one VMC frame's floats, hemisphere-continuous quaternions,
  big-endian into the datagram bytes, what ``VmcEncoder.encode`` did in ten numpy
  calls and a scatter;
- :func:`pose_pack`: one pose data message into its two parts, what
  ``PoseEncoder.encode`` does with a struct pack and five numpy copies (the live
  loop calls it inside its one compiled call per frame, ``daemon/live/emit.py``).

The numpy forms stay beside them as the reference (the tests compare both, byte for
byte). The kernels here call nothing outside this module, so numba's per-file cache
(which does not see a change in a callee from another module) cannot go stale:
``tests/protocols/test_kernels.py`` keeps it so. ``protocols`` sits below ``daemon``,
so these do not use ``daemon.compiled.kernel``; they compile with the same options.

Importing this module locks numba's cache between processes (:mod:`.cache_lock`, which
compiles nothing): every process that compiles a kernel of the package imports it
first (``daemon.compiled`` does), and none of its kernels compiles before that.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from retargetd.protocols import cache_lock

cache_lock.install()


@numba.njit(cache=True, nogil=True, error_model="numpy")
def store_rows(
    raw32: np.ndarray,
    zero_is_occluded: bool,
    rhs: np.ndarray,
    occluded: np.ndarray,
    valid: np.ndarray,
    markers_world: np.ndarray,
    limit_m: float,
    counts: np.ndarray,
) -> bool:
    """Convert ``raw32`` (n, 3) float32 (native order) into ``markers_world`` (n, 3)
    float64 world metres, ``markers_world[i] = raw32[i] @ rhs``; a row with a NaN (or,
    with ``zero_is_occluded``, exactly (0, 0, 0), either sign of zero) is occluded: all
    NaN, ``occluded[i]`` True, ``valid[i]`` False; so is a row with a world coordinate
    past ``limit_m`` metres, and ``counts[0]`` counts those (implausible, not lost).

    Returns False, writing nothing, when any value is infinite."""
    n = raw32.shape[0]
    for i in range(n):
        for c in range(3):
            if math.isinf(raw32[i, c]):
                return False
    nan = math.nan
    for i in range(n):
        x = np.float64(raw32[i, 0])
        y = np.float64(raw32[i, 1])
        z = np.float64(raw32[i, 2])
        hidden = math.isnan(x) or math.isnan(y) or math.isnan(z)
        if zero_is_occluded and x == 0.0 and y == 0.0 and z == 0.0:
            hidden = True
        if not hidden:
            far = False
            for c in range(3):
                w = x * rhs[0, c] + y * rhs[1, c] + z * rhs[2, c]
                markers_world[i, c] = w
                if abs(w) > limit_m:
                    far = True
            if far:
                hidden = True
                counts[0] += 1
        occluded[i] = hidden
        valid[i] = not hidden
        if hidden:
            markers_world[i, 0] = nan
            markers_world[i, 1] = nan
            markers_world[i, 2] = nan
    return True


#: :func:`decode_frame` failures, in the order the checks run (negative returns).
(D_BAD_LENGTH, D_BAD_ADDRESS, D_BAD_TYPETAGS, D_BAD_COUNT, D_BAD_BLOB_SIZE,
 D_UNKNOWN_LABEL_SET, D_COUNT_MISMATCH, D_BAD_FRAME_NUMBER, D_NON_FINITE, D_BAD_MAGIC,
 D_BAD_VERSION) = range(-1, -12, -1)  # fmt: skip
#: :func:`decode_frame` forms.
FORM_OSC_COMPACT = 0  #: ``/rtd/frame ,hdiib``: big-endian, one datagram
FORM_ZMQ = 1  #: ``RTDM``: little-endian, a 32-byte header part then the payload
_OSC_HEAD = np.frombuffer(b"/rtd/frame\0\0,hdiib\0\0", dtype=np.uint8)
_ZMQ_MAGIC = np.frombuffer(b"RTDM\x01\x00", dtype=np.uint8)  # magic, version 1


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _be(buf: np.ndarray, at: int, size: int) -> int:
    v = 0
    for i in range(size):
        v = (v << 8) | buf[at + i]
    return v


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _le(buf: np.ndarray, at: int, size: int) -> int:
    v = 0
    for i in range(size - 1, -1, -1):
        v = (v << 8) | buf[at + i]
    return v


@numba.njit(cache=True, nogil=True, error_model="numpy")
def decode_frame(
    form: int,
    head: np.ndarray,
    n_head: int,
    payload: np.ndarray,
    n_payload: int,
    label_set_id: int,
    zero_is_occluded: bool,
    rhs: np.ndarray,
    raw32: np.ndarray,
    occluded: np.ndarray,
    valid: np.ndarray,
    markers_world: np.ndarray,
    limit_m: float,
    counts: np.ndarray,
) -> int:
    """A marker frame's checks and its markers into the frame, in one call: what
    ``osc_in.decode_compact_frame`` (``form`` :data:`FORM_OSC_COMPACT`, the datagram
    in ``head[:n_head]``) and ``zmq_wire.decode_zmq_frame`` (:data:`FORM_ZMQ`, the
    header part in ``head[:n_head]``, the payload in ``payload[:n_payload]``) check,
    in the same order, then :func:`store_rows`.

    Args:
        head, payload: uint8 receive buffers (``payload`` unused for OSC).
        label_set_id: the label set the packet must carry; its marker count is
            ``markers_world.shape[0]``.
        raw32: (n, 3) float32 scratch (the markers in native order).

    Returns:
        the frame number (>= 0), or a ``D_*`` code (< 0) with nothing written but
        ``raw32``. The source time is left to the caller (struct: a Python float).
    """
    n = markers_world.shape[0]
    if form == FORM_OSC_COMPACT:
        if n_head < 48:
            return D_BAD_LENGTH
        for i in range(12):
            if head[i] != _OSC_HEAD[i]:
                return D_BAD_ADDRESS
        for i in range(12, 20):
            if head[i] != _OSC_HEAD[i]:
                return D_BAD_TYPETAGS
        frame_id = _be(head, 20, 8)  # int64: >= 2^63 reads as negative below
        time_bits = _be(head, 28, 8)
        set_id = _be(head, 36, 4)
        count = _be(head, 40, 4)
        blob = _be(head, 44, 4)
        if set_id >= 1 << 31:
            set_id -= 1 << 32
        if count >= 1 << 31:
            count -= 1 << 32
        if blob >= 1 << 31:
            blob -= 1 << 32
        if count < 0:
            return D_BAD_COUNT
        if blob != 12 * count:
            return D_BAD_BLOB_SIZE
        if n_head != 48 + blob:
            return D_BAD_LENGTH
        data, at = head, 48
    else:
        if n_head != 32:
            return D_BAD_LENGTH
        for i in range(4):
            if head[i] != _ZMQ_MAGIC[i]:
                return D_BAD_MAGIC
        if head[4] != _ZMQ_MAGIC[4] or head[5] != _ZMQ_MAGIC[5]:
            return D_BAD_VERSION
        frame_id = _le(head, 8, 8)
        time_bits = _le(head, 16, 8)
        set_id = _le(head, 24, 4)  # uint32
        count = _le(head, 28, 4)
        if n_payload != 12 * count:
            return D_BAD_LENGTH
        data, at = payload, 0
    if set_id != label_set_id:
        return D_UNKNOWN_LABEL_SET
    if count != n:
        return D_COUNT_MISMATCH
    if frame_id < 0:
        return D_BAD_FRAME_NUMBER
    if (time_bits & 0x7FFF_FFFF_FFFF_FFFF) == 0x7FF0_0000_0000_0000:  # +-inf
        return D_NON_FINITE
    bits = raw32.reshape(3 * n).view(np.uint32)
    if form == FORM_OSC_COMPACT:
        for k in range(3 * n):
            bits[k] = _be(data, at + 4 * k, 4)
    else:
        for k in range(3 * n):
            bits[k] = _le(data, at + 4 * k, 4)
    if not store_rows(
        raw32, zero_is_occluded, rhs, occluded, valid, markers_world, limit_m, counts
    ):
        return D_NON_FINITE
    return frame_id


def direct(dispatcher: object, *args: object) -> object:
    """``dispatcher``'s compiled function for the types of ``args``, called without
    the dispatcher's per-call type resolution, or ``dispatcher`` itself when no
    compiled overload has those types yet (``daemon.compiled.direct`` is this one).

    Only for a call whose arguments keep these types on every call: the compiled
    function converts each argument to the type it was compiled for without
    checking it."""
    try:
        sig = tuple(numba.typeof(a) for a in args)
        return dispatcher.overloads[sig].entry_point  # type: ignore[attr-defined]
    except (KeyError, AttributeError, ValueError, TypeError):
        return dispatcher


#: Sequencer outcomes (``marker_input.REASON_INDEX``'s first entries, in its order:
#: ``tests/protocols/test_kernels.py`` checks they agree).
S_ACCEPTED, S_RESTART, S_BACKWARDS, S_DUPLICATE = 0, 1, 2, 3
S_IMPLAUSIBLE_JUMP = 6
#: :func:`sequence_check`'s int64 state, by slot (``marker_input.FrameSequencer``).
(Q_LAST_FRAME, Q_LAST_SET, Q_LAST_T, Q_CAND_N, Q_CAND_FRAME, Q_CAND_T, Q_RESTART_NEXT,
 Q_RESTART_GAP, Q_CONFIRM, N_Q) = range(10)  # fmt: skip
#: Its float64 parameters: frames per ns at the input's ``max_rate_hz``, and the
#: jitter slack in frames (``JUMP_SLACK_NS`` at that rate, plus one).
QF_RATE_PER_NS, QF_SLACK, N_QF = range(3)


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _plausible(qf: np.ndarray, advance: int, elapsed_ns: int) -> bool:
    return advance <= elapsed_ns * qf[QF_RATE_PER_NS] + qf[QF_SLACK]


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _candidate(
    q: np.ndarray, qf: np.ndarray, frame_id: int, t_ns: int, code: int
) -> int:
    n = q[Q_CAND_N]
    if (
        n
        and frame_id > q[Q_CAND_FRAME]
        and _plausible(qf, frame_id - q[Q_CAND_FRAME], t_ns - q[Q_CAND_T])
    ):
        n += 1
    else:
        n = 1
    if n >= q[Q_CONFIRM]:
        q[Q_CAND_N] = 0
        q[Q_LAST_FRAME] = frame_id
        q[Q_LAST_T] = t_ns
        return S_RESTART
    q[Q_CAND_N] = n
    q[Q_CAND_FRAME] = frame_id
    q[Q_CAND_T] = t_ns
    return code


@numba.njit(cache=True, nogil=True, error_model="numpy")
def sequence_check(
    q: np.ndarray, qf: np.ndarray, frame_id: int, label_set_id: int, t_ns: int
) -> int:
    """``marker_input.FrameSequencer.check``: classify a frame by its number against
    the last accepted one (state ``q``, int64 ``Q_*`` slots; parameters ``qf``,
    float64 ``QF_*``) and update the state when it is accepted.

    Returns:
        ``S_ACCEPTED`` or ``S_RESTART`` (use the frame), ``S_DUPLICATE``,
        ``S_BACKWARDS`` or ``S_IMPLAUSIBLE_JUMP`` (drop it).
    """
    code = S_ACCEPTED
    last = q[Q_LAST_FRAME]
    if frame_id >= 0 and q[Q_RESTART_NEXT]:
        code = S_RESTART
    elif frame_id >= 0 and last >= 0:
        new_set = label_set_id != q[Q_LAST_SET]
        if frame_id > last:
            if not _plausible(qf, frame_id - last, t_ns - q[Q_LAST_T]):
                if not new_set:
                    return _candidate(q, qf, frame_id, t_ns, S_IMPLAUSIBLE_JUMP)
                code = S_RESTART
        elif new_set or t_ns - q[Q_LAST_T] >= q[Q_RESTART_GAP]:
            code = S_RESTART
        elif frame_id == last:
            return S_DUPLICATE
        else:
            return _candidate(q, qf, frame_id, t_ns, S_BACKWARDS)
    if frame_id >= 0:
        q[Q_LAST_FRAME] = frame_id
        q[Q_RESTART_NEXT] = 0
    q[Q_CAND_N] = 0
    q[Q_LAST_SET] = label_set_id
    q[Q_LAST_T] = t_ns
    return code


@numba.njit(cache=True, nogil=True, error_model="numpy")
def feed_frame(
    form: int,
    head: np.ndarray,
    n_head: int,
    payload: np.ndarray,
    n_payload: int,
    t_ns: int,
    label_set_id: int,
    zero_is_occluded: bool,
    rhs: np.ndarray,
    raw32: np.ndarray,
    occluded: np.ndarray,
    valid: np.ndarray,
    markers_world: np.ndarray,
    limit_m: float,
    implausible: np.ndarray,
    q: np.ndarray,
    qf: np.ndarray,
    counts: np.ndarray,
    source_time: np.ndarray,
) -> tuple[int, int, float]:
    """A frame packet fed to its stream in one call (``MarkerStream.feed_packed``):
    :func:`decode_frame` into the spare packet's arrays, then, when it decoded,
    :func:`sequence_check` and the outcome counted in ``counts`` (the stream's
    ``DropCounters``), what ``MarkerStream.feed`` does in Python around the decode.

    Args:
        form .. implausible: :func:`decode_frame`'s (``implausible`` its ``counts``).
        t_ns: ``time.monotonic_ns()`` at receive.
        q, qf: the stream's sequencer state and parameters.
        counts: the stream's drop counters, by ``REASON_INDEX``.
        source_time: (1,) float64 scratch: the packet's source time, seconds.

    Returns:
        (code, frame number, source time s): the code a ``D_*`` (< 0) when the
        decode refused it (nothing counted, the sequencer untouched: the caller
        asks the Python decoder why), else the sequencer's outcome (counted),
        ``S_ACCEPTED`` or ``S_RESTART`` when the spare now holds an accepted frame.
        (One tuple back: two reads of numpy scalars cost more, cold.)
    """
    frame_id = decode_frame(
        form, head, n_head, payload, n_payload, label_set_id, zero_is_occluded, rhs,
        raw32, occluded, valid, markers_world, limit_m, implausible,
    )  # fmt: skip
    if frame_id < 0:
        return frame_id, frame_id, math.nan
    bits = source_time.view(np.int64)
    if form == FORM_OSC_COMPACT:
        bits[0] = _be(head, 28, 8)
    else:
        bits[0] = _le(head, 16, 8)
    code = sequence_check(q, qf, frame_id, label_set_id, t_ns)
    counts[code] += 1
    return code, frame_id, source_time[0]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def vmc_pack(
    root_pos: np.ndarray,
    root_quat: np.ndarray,
    bone_pos: np.ndarray,
    bone_quat: np.ndarray,
    blend: np.ndarray,
    t_s: float,
    last_quat: np.ndarray,
    stage: np.ndarray,
    stage_bits: np.ndarray,
    offsets: np.ndarray,
    wire: np.ndarray,
) -> None:
    """One VMC frame into the datagram bytes ``wire`` (uint8).

    ``stage`` is a float32 scratch of the frame's floats in slot order, ``stage_bits``
    the same memory as uint32; slot ``k`` goes big-endian to ``wire[offsets[k]:+4]``.
    Slot order: the root's position and quaternion (x y z w), each bone's position
    and quaternion, the blend values, the time. Each quaternion is negated when its
    dot product with ``last_quat`` (its row, updated) is negative."""
    n_b = bone_pos.shape[0]
    k = 0
    for r in range(n_b + 1):
        for c in range(3):
            stage[k + c] = root_pos[c] if r == 0 else bone_pos[r - 1, c]
        if r == 0:
            qx, qy, qz, qw = root_quat[0], root_quat[1], root_quat[2], root_quat[3]
        else:
            qx, qy, qz, qw = (
                bone_quat[r - 1, 0], bone_quat[r - 1, 1], bone_quat[r - 1, 2],
                bone_quat[r - 1, 3],
            )  # fmt: skip
        dot = (
            qx * last_quat[r, 0] + qy * last_quat[r, 1] + qz * last_quat[r, 2]
            + qw * last_quat[r, 3]
        )  # fmt: skip
        if dot < 0.0:
            qx, qy, qz, qw = -qx, -qy, -qz, -qw
        last_quat[r, 0] = qx
        last_quat[r, 1] = qy
        last_quat[r, 2] = qz
        last_quat[r, 3] = qw
        stage[k + 3] = qx
        stage[k + 4] = qy
        stage[k + 5] = qz
        stage[k + 6] = qw
        k += 7
    for j in range(blend.shape[0]):
        stage[k] = blend[j]
        k += 1
    stage[k] = t_s
    k += 1
    for s in range(k):
        bits = stage_bits[s]
        o = offsets[s]
        wire[o] = (bits >> 24) & 0xFF
        wire[o + 1] = (bits >> 16) & 0xFF
        wire[o + 2] = (bits >> 8) & 0xFF
        wire[o + 3] = bits & 0xFF


@numba.njit(cache=True, nogil=True, error_model="numpy")
def pose_pack(
    header: np.ndarray,
    body: np.ndarray,
    frame_id: int,
    source_time_s: float,
    received_ns: int,
    solved_ns: int,
    flags_word: int,
    root_pos: np.ndarray,
    wfb: np.ndarray,
    pfb: np.ndarray,
    rfb: np.ndarray,
    weights: np.ndarray,
    bone_flags: np.ndarray,
    or_flags: np.ndarray,
) -> None:
    """One pose data message into ``header`` (68) and ``body`` (uint8, the
    ``pose_stream`` layout, little-endian), as ``PoseEncoder.encode`` writes it.

    The header's constant fields (magic, version, names id, counts) are written once
    by the encoder; this writes the frame number, the source time, the received and
    solved stamps, ``sent_ns`` = 0, ``flags_word`` (the performer id already in bits
    16-23) and the root position. The bone flags are ``bone_flags | or_flags`` when
    ``or_flags`` has one entry per bone, else ``bone_flags``."""
    hi = header[8:48].view(np.int64)
    hi[0] = frame_id
    header[16:24].view(np.float64)[0] = source_time_s
    hi[2] = received_ns
    hi[3] = solved_ns
    hi[4] = 0
    header[48:52].view(np.uint32)[0] = flags_word
    hf = header[56:68].view(np.float32)
    for c in range(3):
        hf[c] = root_pos[c]
    b = wfb.shape[0]
    k = weights.shape[0]
    bf = body[: 48 * b + 4 * k].view(np.float32)
    for i in range(b):
        for j in range(4):
            bf[4 * i + j] = wfb[i, j]
            bf[4 * (b + i) + j] = pfb[i, j]
            bf[4 * (2 * b + i) + j] = rfb[i, j]
    for j in range(k):
        bf[12 * b + j] = weights[j]
    o = 48 * b + 4 * k
    both = or_flags.shape[0] == b
    for i in range(b):
        f = bone_flags[i]
        if both:
            f |= or_flags[i]
        body[o + i] = f


def warm_up() -> None:
    """Compile (or load from the cache) every kernel on tiny inputs, so no streamed
    frame pays for it."""
    rows = np.zeros((2, 3), dtype=np.float32)
    rows[1] = np.nan
    counts = np.zeros(1, dtype=np.int64)
    store_rows(
        rows, True, np.eye(3), np.zeros(2, dtype=np.bool_), np.zeros(2, dtype=np.bool_),
        np.zeros((2, 3)), 1000.0, counts,
    )  # fmt: skip
    stage = np.zeros(16, dtype=np.float32)
    vmc_pack(
        np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]), np.zeros((1, 3)),
        np.array([[0.0, 0.0, 0.0, 1.0]]), np.zeros(1), 0.0, np.zeros((2, 4)), stage,
        stage.view(np.uint32), np.arange(16, dtype=np.int64) * 4,
        np.zeros(64, dtype=np.uint8),
    )  # fmt: skip
    wire = np.zeros(64, dtype=np.uint8)
    for form in (FORM_OSC_COMPACT, FORM_ZMQ):  # refused at once: typed, not run
        decode_frame(
            form, wire, 0, wire, 0, 0, True, np.eye(3), rows, np.zeros(2, np.bool_),
            np.zeros(2, dtype=np.bool_), np.zeros((2, 3)), 1000.0, counts,
        )  # fmt: skip
    q = np.zeros(N_Q, dtype=np.int64)
    qf = np.zeros(N_QF)
    sequence_check(q, qf, 0, 0, 0)
    for form in (FORM_OSC_COMPACT, FORM_ZMQ):  # the stream's types: refused at once
        feed_frame(
            form, wire, 0, wire, 0, 0, 0, True, np.eye(3), rows,
            np.zeros(2, np.bool_), np.zeros(2, dtype=np.bool_), np.zeros((2, 3)),
            1000.0, counts, q, qf, np.zeros(32, dtype=np.int64), np.zeros(1),
        )  # fmt: skip
    quat = np.array([[1.0, 0.0, 0.0, 0.0]])
    pose_pack(
        np.zeros(68, dtype=np.uint8), np.zeros(56, dtype=np.uint8), 0, 0.0, 0, 0, 0,
        np.zeros(3), quat, quat, quat, np.zeros(1), np.zeros(1, dtype=np.uint8),
        np.zeros(0, dtype=np.uint8),
    )  # fmt: skip
