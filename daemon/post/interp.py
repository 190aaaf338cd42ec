"""Slerp at work (the chapter's 5.86-5.87): resampling, gap filling, blending and
looping takes, and live resampling to the engine's rate.

Every rotation in between two keys is :func:`retargetd.daemon.rotations.slerp` (the
shorter arc, a normalized lerp below :data:`~retargetd.daemon.rotations.
SLERP_LINEAR_BELOW_RAD`), so every result is a unit quaternion; root positions are
interpolated linearly (translations commute, as the chapter says).

A :class:`Clip` is a take's rotations and root at a fixed rate. Blending and looping
follow the chapter's advice that the frames joined should be alike in pose and
timing: :func:`blend` cross-fades over N frames from chosen frames of each take,
after turning and moving the second take's root onto the first's;
:func:`find_loop` picks the end of a cycle whose pose best matches the start, and
:func:`loop` cross-fades the cycle's last N frames into its first N.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from retargetd.daemon import rotations as rot
from retargetd.daemon.compiled import kernel
from retargetd.daemon.post._kernels import slerp_q
from retargetd.daemon.post.pose import PoseBuffer
from retargetd.protocols.frames import BoolArray, F64Array, IntArray

_UP = np.array([0.0, 0.0, 1.0])  # world +Z (STYLE §3)


@dataclass(frozen=True, slots=True, kw_only=True)
class Clip:
    """A take's motion at a fixed rate.

    Attributes:
        parent_from_bone_quat: (T, B, 4) float64 (w, x, y, z); bone 0 is the root,
            its rotation ``world_from_root``.
        root_pos: (T, 3) float64, metres, world.
        rate_hz: frame rate.
    """

    parent_from_bone_quat: F64Array
    root_pos: F64Array
    rate_hz: float

    def __post_init__(self) -> None:
        q, p = self.parent_from_bone_quat, self.root_pos
        if q.ndim != 3 or q.shape[-1] != 4 or p.shape != (q.shape[0], 3):
            raise ValueError(
                "Clip needs parent_from_bone_quat (T, B, 4) and root_pos (T, 3); got "
                f"{q.shape} and {p.shape}"
            )
        if not self.rate_hz > 0.0:
            raise ValueError(f"rate_hz must be > 0; got {self.rate_hz!r}")

    @property
    def n_frames(self) -> int:
        """Number of frames T."""
        return int(self.parent_from_bone_quat.shape[0])


def _lerp(a: F64Array, b: F64Array, u: F64Array) -> F64Array:
    return a + (b - a) * u[..., None]


def resample(
    times_s: F64Array, quat: F64Array, pos: F64Array, rate_hz: float
) -> tuple[F64Array, F64Array, F64Array]:
    """Resample a take to another rate (e.g. a 100 Hz capture to 60 or 120 Hz).

    Output frames are at ``times_s[0] + k / rate_hz`` up to the last input time.

    Args:
        times_s: (T,) float64 seconds, increasing (T >= 2).
        quat: (T, B, 4) float64 (w, x, y, z), unit.
        pos: (T, 3) float64, any unit (e.g. metres, world).
        rate_hz: the output rate (> 0).

    Returns:
        ``(times_s, quat, pos)`` at the new rate: (T',), (T', B, 4), (T', 3).

    Raises:
        ValueError: bad shapes, non-increasing times or a bad rate.
    """
    times_s = np.asarray(times_s, dtype=np.float64)
    if times_s.ndim != 1 or len(times_s) < 2 or np.any(np.diff(times_s) <= 0.0):
        raise ValueError("times_s must be (T,) increasing with T >= 2")
    if quat.shape[0] != len(times_s) or pos.shape[0] != len(times_s):
        raise ValueError(
            f"quat {quat.shape} and pos {pos.shape} need {len(times_s)} frames"
        )
    if not rate_hz > 0.0:
        raise ValueError(f"rate_hz must be > 0; got {rate_hz!r}")
    span = times_s[-1] - times_s[0]
    n_out = math.floor(span * rate_hz + 1e-9) + 1
    out_t = times_s[0] + np.arange(n_out) / rate_hz
    i = np.clip(np.searchsorted(times_s, out_t, side="right") - 1, 0, len(times_s) - 2)
    u = np.clip((out_t - times_s[i]) / (times_s[i + 1] - times_s[i]), 0.0, 1.0)
    q = rot.slerp(quat[i], quat[i + 1], u[:, None])
    return out_t, q, _lerp(pos[i], pos[i + 1], u)


def _runs(mask: BoolArray) -> list[tuple[int, int]]:
    """[start, stop) of each run of True in a 1-D mask."""
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(
        zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True)
    )


def fill_gaps(
    quat: F64Array, valid: BoolArray, max_frames: int
) -> tuple[F64Array, BoolArray]:
    """Fill short gaps of each bone's rotation by slerp between the frames around them.

    A gap is a run of invalid frames with a valid frame on each side; runs longer
    than ``max_frames`` and runs touching either end of the take are left as they are.

    Args:
        quat: (T, B, 4) float64 (w, x, y, z); invalid frames may hold anything.
        valid: (T, B) bool, True where the rotation was solved (e.g. not held).
        max_frames: longest gap filled, frames (>= 1).

    Returns:
        ``(quat, filled)``: (T, B, 4) float64 copy with the gaps filled and (T, B)
        bool, True where a frame was filled.

    Raises:
        ValueError: mismatched shapes or a bad ``max_frames``.
    """
    if valid.shape != quat.shape[:2]:
        raise ValueError(f"valid must have shape {quat.shape[:2]}; got {valid.shape}")
    if int(max_frames) != max_frames or max_frames < 1:
        raise ValueError(f"max_frames must be an integer >= 1; got {max_frames!r}")
    out = np.array(quat, dtype=np.float64)
    filled = np.zeros(valid.shape, dtype=bool)
    n = quat.shape[0]
    for b in range(quat.shape[1]):
        for start, stop in _runs(~valid[:, b]):
            if start == 0 or stop == n or stop - start > max_frames:
                continue
            u = (np.arange(start, stop) - (start - 1)) / (stop - (start - 1))
            out[start:stop, b] = rot.slerp(out[start - 1, b], out[stop, b], u)
            filled[start:stop, b] = True
    return out, filled


def fill_gaps_linear(
    values: F64Array, valid: BoolArray, max_frames: int
) -> tuple[F64Array, BoolArray]:
    """:func:`fill_gaps` for positions: linear between the frames around each gap.

    Args:
        values: (T, D) float64, any unit (e.g. the root, metres).
        valid: (T,) bool.
        max_frames: longest gap filled, frames (>= 1).

    Returns:
        ``(values, filled)``: (T, D) float64 copy and (T,) bool.

    Raises:
        ValueError: mismatched shapes or a bad ``max_frames``.
    """
    if valid.shape != values.shape[:1]:
        raise ValueError(f"valid must have shape {values.shape[:1]}; got {valid.shape}")
    if int(max_frames) != max_frames or max_frames < 1:
        raise ValueError(f"max_frames must be an integer >= 1; got {max_frames!r}")
    out = np.array(values, dtype=np.float64)
    filled = np.zeros(valid.shape, dtype=bool)
    for start, stop in _runs(~valid):
        if start == 0 or stop == len(valid) or stop - start > max_frames:
            continue
        u = (np.arange(start, stop) - (start - 1)) / (stop - (start - 1))
        out[start:stop] = _lerp(out[start - 1], out[stop], u)
        filled[start:stop] = True
    return out, filled


def _yaw_quat(angle_rad: F64Array | float) -> F64Array:
    return rot.quat_from_axis_angle(_UP, angle_rad)


def _fade(n_frames: int) -> F64Array:
    # Weights strictly inside (0, 1): frame k of the fade is (k + 1) / (N + 1) of
    # the way, so neither take's own frame is repeated at either end.
    return np.asarray((np.arange(n_frames) + 1.0) / (n_frames + 1.0), dtype=np.float64)


def blend(
    a: Clip, b: Clip, at_a: int, at_b: int, n_frames: int, *, align_root: bool = True
) -> Clip:
    """Cross-fade take ``a`` into take ``b`` over ``n_frames``.

    The result is ``a[:at_a]``, then N frames ``slerp(a[at_a + k], b[at_b + k],
    (k + 1) / (N + 1))``, then ``b[at_b + N:]``. With ``align_root``, ``b`` is first
    turned about world +Z and moved on the floor so that its root at ``at_b`` has
    the heading and horizontal position of ``a``'s at ``at_a`` (its height is kept).

    Args:
        a: the first take.
        b: the second take (same bones, same rate).
        at_a: frame of ``a`` where the fade starts.
        at_b: frame of ``b`` where the fade starts.
        n_frames: fade length N (>= 1); ``at_a + N <= len(a)``, ``at_b + N <= len(b)``.
        align_root: turn and move ``b`` onto ``a`` first.

    Returns:
        The blended clip, ``at_a + len(b) - at_b`` frames.

    Raises:
        ValueError: mismatched takes or frames out of range.
    """
    if a.parent_from_bone_quat.shape[1] != b.parent_from_bone_quat.shape[1]:
        raise ValueError("blend needs takes with the same bones")
    if a.rate_hz != b.rate_hz:
        raise ValueError(f"blend needs one rate; got {a.rate_hz} and {b.rate_hz} Hz")
    if n_frames < 1 or not (0 <= at_a <= a.n_frames - n_frames):
        raise ValueError(f"at_a + n_frames must fit in a ({a.n_frames} frames)")
    if not 0 <= at_b <= b.n_frames - n_frames:
        raise ValueError(f"at_b + n_frames must fit in b ({b.n_frames} frames)")
    bq = np.array(b.parent_from_bone_quat, dtype=np.float64)
    bp = np.array(b.root_pos, dtype=np.float64)
    if align_root:
        yaw = rot.twist_angle(a.parent_from_bone_quat[at_a, 0], _UP) - rot.twist_angle(
            bq[at_b, 0], _UP
        )
        turn = _yaw_quat(yaw)
        bq[:, 0] = rot.quat_mul(turn, bq[:, 0])
        bp = rot.quat_rotate(turn, bp - bp[at_b]) + bp[at_b]
        bp[:, :2] += a.root_pos[at_a, :2] - bp[at_b, :2]
    u = _fade(n_frames)
    fade_q = rot.slerp(
        a.parent_from_bone_quat[at_a : at_a + n_frames],
        bq[at_b : at_b + n_frames],
        u[:, None],
    )
    fade_p = _lerp(a.root_pos[at_a : at_a + n_frames], bp[at_b : at_b + n_frames], u)
    return Clip(
        parent_from_bone_quat=np.concatenate(
            [a.parent_from_bone_quat[:at_a], fade_q, bq[at_b + n_frames :]]
        ),
        root_pos=np.concatenate([a.root_pos[:at_a], fade_p, bp[at_b + n_frames :]]),
        rate_hz=a.rate_hz,
    )


def pose_distance(q0: F64Array, q1: F64Array) -> F64Array:
    """Root-mean-square rotation angle between poses, over bones (root excluded).

    Args:
        q0: (..., B, 4) float64 (w, x, y, z).
        q1: (..., B, 4) float64 (w, x, y, z), broadcasts with ``q0``.

    Returns:
        (...) float64 radians.
    """
    rel = rot.quat_mul(rot.quat_conj(q0[..., 1:, :]), q1[..., 1:, :])
    return np.sqrt(np.mean(rot.quat_angle(rel) ** 2, axis=-1))


def find_loop(clip: Clip, n_frames: int, min_cycle_frames: int) -> int:
    """The end of the cycle whose following N frames best match the first N.

    Args:
        clip: a cyclic take (e.g. a walk).
        n_frames: fade length N the loop will use (>= 1).
        min_cycle_frames: shortest cycle considered (> N), e.g. one gait cycle.

    Returns:
        ``end``: frames ``[0, end)`` are the cycle; ``end + N <= len(clip)``; pass
        ``clip`` cut to ``end + N`` frames to :func:`loop`.

    Raises:
        ValueError: no cycle of that length fits.
    """
    q = clip.parent_from_bone_quat
    last = clip.n_frames - n_frames
    if min_cycle_frames <= n_frames or min_cycle_frames > last:
        raise ValueError(
            f"a cycle of >= {min_cycle_frames} frames plus {n_frames} fade frames does "
            f"not fit in {clip.n_frames} frames (and must be longer than the fade)"
        )
    ends = np.arange(min_cycle_frames, last + 1)
    cost = np.array(
        [pose_distance(q[:n_frames], q[e : e + n_frames]).mean() for e in ends]
    )
    return int(ends[np.argmin(cost)])


def loop(clip: Clip, n_frames: int) -> tuple[Clip, F64Array]:
    """A seamless loop: the take's last N frames cross-faded into its first N.

    With ``T`` input frames the loop has ``T - N`` frames: frame ``k < N`` is
    ``slerp(q[T - N + k], q[k], (k + 1) / (N + 1))``, the rest are the take's own
    frames ``N .. T - N - 1``; played round, frame ``T - N - 1`` is followed by frame
    0, which is mostly ``q[T - N]``, its natural successor. The tail's root is moved
    on the floor by the cycle's travel ``d = root[0] - root[T - N]`` (x, y) so the
    fade does not slide; an engine playing the loop with root motion adds ``-d`` each
    time round (returned).

    Args:
        clip: a cyclic take, its first and last N frames alike in pose and timing
            (:func:`find_loop`).
        n_frames: fade length N (>= 1, ``2 N < T``).

    Returns:
        ``(loop, travel_m)``: the looping clip and (3,) float64, metres, world: the
        root's travel per cycle (z = 0).

    Raises:
        ValueError: ``n_frames`` out of range.
    """
    t = clip.n_frames
    if n_frames < 1 or 2 * n_frames >= t:
        raise ValueError(f"n_frames must be in 1 .. {(t - 1) // 2}; got {n_frames}")
    q, p = clip.parent_from_bone_quat, clip.root_pos
    travel = np.zeros(3)
    travel[:2] = p[t - n_frames, :2] - p[0, :2]
    u = _fade(n_frames)
    head_q = rot.slerp(q[t - n_frames :], q[:n_frames], u[:, None])
    head_p = _lerp(p[t - n_frames :] - travel, p[:n_frames], u)
    return (
        Clip(
            parent_from_bone_quat=np.concatenate([head_q, q[n_frames : t - n_frames]]),
            root_pos=np.concatenate([head_p, p[n_frames : t - n_frames]]),
            rate_hz=clip.rate_hz,
        ),
        travel,
    )


@kernel
def _slerp_pose(
    q0: F64Array,
    q1: F64Array,
    p0: F64Array,
    p1: F64Array,
    u: float,
    out_q: F64Array,
    out_p: F64Array,
) -> None:  # pragma: no cover - compiled
    for b in range(out_q.shape[0]):
        a, c = q0[b], q1[b]
        r = slerp_q(a[0], a[1], a[2], a[3], c[0], c[1], c[2], c[3], u)
        out_q[b, 0], out_q[b, 1], out_q[b, 2], out_q[b, 3] = r
    for d in range(3):
        out_p[d] = p0[d] + u * (p1[d] - p0[d])


#: Output ticks a :class:`RateResampler` holds computed and waiting for their send
#: time: one input period's worth at 16 times the input's rate (e.g. 10 -> 160 Hz);
#: beyond that the oldest are dropped (counted).
QUEUE_TICKS = 16

# RateResampler._ints slots: the state, then send times, tags and arrivals per slot.
_S_TICK, _S_HEAD, _S_QUEUED, _S_DROPPED, _S_COMPLETED, _S_LAST = 0, 1, 2, 3, 4, 5
_S_TAG, _S_ARRIVAL = 6, 7  # the tick popped last
_N_STATE = 8
# RateResampler._floats slots: the two input poses' times, t0, the period, the time
# of the tick popped last, then the queued ticks' times.
_F_T0, _F_PERIOD, _F_POPPED, _N_FLOATS = 2, 3, 4, 5


@kernel
def _next_due(ints: IntArray) -> int:  # pragma: no cover - compiled
    if ints[_S_QUEUED] == 0:
        return -1
    return ints[_N_STATE + ints[_S_HEAD]]


@kernel
def _queue_ticks(
    pose_q: F64Array,
    pose_p: F64Array,
    pose_t: float,
    in_q: F64Array,
    in_p: F64Array,
    q: F64Array,
    p: F64Array,
    floats: F64Array,
    ints: IntArray,
    now_ns: int,
    tag: int,
) -> int:  # pragma: no cover - compiled
    """Take the pose as the last input (the other row becomes prev) and queue every
    tick in (prev_t, last_t]: slerp (root: lerp) between the two, send times ``now
    + (t - t_first)``; ticks still queued are due at once. Returns the oldest queued
    tick's send time (-1: none). One call with few arguments: numba's dispatch costs
    per argument, and this runs on every input frame."""
    n_slots = q.shape[0]
    due, tags, arrival = _N_STATE, _N_STATE + n_slots, _N_STATE + 2 * n_slots
    last = 1 - ints[_S_LAST]
    prev = 1 - last
    ints[_S_LAST] = last
    in_q[last, :, :] = pose_q
    in_p[last, :] = pose_p
    floats[last] = pose_t
    interpolate = floats[prev] < pose_t  # a pose before (the first has none)
    prev_t, last_t = floats[prev], pose_t
    t0, period = floats[_F_T0], floats[_F_PERIOD]
    head, queued = ints[_S_HEAD], ints[_S_QUEUED]
    for k in range(queued):  # overdue: due at once
        ints[due + (head + k) % n_slots] = now_ns
    completed = 0
    tick = ints[_S_TICK]
    t_first = t0 + tick * period
    while t0 + tick * period <= last_t + 1e-12:
        tt = t0 + tick * period
        tick += 1
        if queued == n_slots:
            head = (head + 1) % n_slots
            queued -= 1
            ints[_S_DROPPED] += 1
        slot = (head + queued) % n_slots
        if not interpolate or tt >= last_t:
            q[slot, :, :] = in_q[last]
            p[slot, :] = in_p[last]
        else:
            u = max(0.0, (tt - prev_t) / (last_t - prev_t))
            _slerp_pose(in_q[prev], in_q[last], in_p[prev], in_p[last], u, q[slot],
                        p[slot])  # fmt: skip
        floats[_N_FLOATS + slot] = tt
        ints[due + slot] = now_ns + np.int64(round((tt - t_first) * 1e9))
        ints[tags + slot] = tag
        ints[arrival + slot] = now_ns
        queued += 1
        completed += 1
    ints[_S_TICK] = tick
    ints[_S_HEAD] = head
    ints[_S_QUEUED] = queued
    ints[_S_COMPLETED] = completed
    return _next_due(ints)


@kernel
def _pop_tick(
    q: F64Array,
    p: F64Array,
    floats: F64Array,
    ints: IntArray,
    out_q: F64Array,
    out_p: F64Array,
) -> int:  # pragma: no cover - compiled
    """The oldest queued tick into ``out_*`` (its time, tag and arrival into the
    popped slots); returns the next one's send time (-1: none)."""
    n_slots = q.shape[0]
    slot = ints[_S_HEAD]
    out_q[:, :] = q[slot]
    out_p[:] = p[slot]
    floats[_F_POPPED] = floats[_N_FLOATS + slot]
    ints[_S_TAG] = ints[_N_STATE + n_slots + slot]
    ints[_S_ARRIVAL] = ints[_N_STATE + 2 * n_slots + slot]
    ints[_S_HEAD] = (slot + 1) % n_slots
    ints[_S_QUEUED] -= 1
    return _next_due(ints)


class RateResampler:
    """Live resampling of the pose stream to the engine's rate (``output_rate_hz``).

    Output ticks run every ``1 / output_rate_hz`` on the stream's clock from the first
    pose pushed; each is slerped (root: a line) between the two input poses around
    it, never extrapolated, so a tick is computed when the input after it arrives:
    the values equal :func:`resample` of the same poses.

    Send times (``now_ns``: ``time.monotonic_ns()``). The ticks an input pose
    completes, ``t_1 < .. < t_m`` (those in ``(t_prev, t_k]``), are queued with send
    times ``w + (t_i - t_1)``, ``w`` the pose's arrival: the first at once, the rest
    spaced by the output period, so above the input's rate (60 Hz captured, 120 Hz
    sent) ticks go out between input frames, from the loop's timer
    (:meth:`next_due_ns`, :meth:`due`), and below it (one tick at most per input)
    every tick goes out on its input's arrival as before. A tick at ``t_i`` leaves
    ``t_k - t_1`` behind the source instant it shows (``t_k - t_i`` of source time
    plus ``t_i - t_1`` of waiting): the added latency, between 0 and one input period
    less one output period (60 -> 120 Hz: 8.3 ms on every tick; 100 -> 60 Hz: 0 to
    10 ms, the tick's age at its input's arrival). Ticks still queued when the next
    input pose arrives (a late loop, input jitter) are due at once.

    Per input pose: ``r.push(pose, now_ns)``, then ``while r.due(now_ns):
    send(r.pop(out))``; and from the loop's timer the same ``while`` when
    :meth:`next_due_ns` has passed. ``pending()`` says whether any tick is queued.

    Args:
        n_bones: bones B of the stream.
        output_rate_hz: the engine's rate (> 0), e.g. 60 or 120.

    Raises:
        ValueError: a bad count or rate.
    """

    def __init__(self, n_bones: int, output_rate_hz: float) -> None:
        if not output_rate_hz > 0.0 or not math.isfinite(output_rate_hz):
            raise ValueError(f"output_rate_hz must be > 0; got {output_rate_hz!r}")
        self.period_s = 1.0 / float(output_rate_hz)
        n = QUEUE_TICKS
        # The two latest input poses (rows; _ints[_S_LAST] the last), the queue's
        # ticks (rotations, root), times (_floats) and state, send times, tags and
        # input arrivals (_ints): a handful of arrays for the kernels' calls.
        self._in_q = np.zeros((2, n_bones, 4))
        self._in_p = np.zeros((2, 3))
        self._q = np.zeros((n, n_bones, 4))
        self._p = np.zeros((n, 3))
        self._floats = np.zeros(_N_FLOATS + n)
        self._floats[_F_PERIOD] = self.period_s
        self._ints = np.zeros(_N_STATE + 3 * n, dtype=np.int64)
        self._started = False
        self._last_t_s = 0.0
        # The oldest queued tick's send time as a Python int (-1: none queued): what
        # the loop asks on its every turn, without a numpy scalar read.
        self._next_due_ns = -1

    @property
    def completed(self) -> int:
        """Ticks the last push completed."""
        return int(self._ints[_S_COMPLETED])

    @property
    def dropped(self) -> int:
        """Ticks dropped from a full queue (never sent)."""
        return int(self._ints[_S_DROPPED])

    @property
    def popped_tag(self) -> int:
        """The tag of the tick :meth:`pop` wrote last."""
        return int(self._ints[_S_TAG])

    @property
    def popped_arrival_ns(self) -> int:
        """The arrival (``now_ns`` of its push) of that tick's input."""
        return int(self._ints[_S_ARRIVAL])

    def reset(self) -> None:
        """Forget the stream and the queued ticks (e.g. after a source restart)."""
        self._started = False
        st = self._ints
        st[_S_TICK] = st[_S_QUEUED] = st[_S_COMPLETED] = 0
        self._next_due_ns = -1

    def push(self, pose: PoseBuffer, now_ns: int = 0, tag: int = 0) -> None:
        """Take the next input pose and queue the ticks it completes.

        Args:
            pose: the pose (copied); times must increase (an older one is ignored).
            now_ns: its arrival, ``time.monotonic_ns()`` (>= 0; the send times'
                origin).
            tag: an integer kept with each tick it completes (e.g. the input frame's
                number), read back as :attr:`popped_tag`.
        """
        if self._started and pose.t_s <= self._last_t_s:
            self._ints[_S_COMPLETED] = 0
            return
        if not self._started:  # the first pose: ticks from its time, none before
            f = self._floats
            f[_F_T0] = pose.t_s
            f[0] = f[1] = math.inf  # no pose before: the kernel copies, never slerps
            self._started = True
        self._last_t_s = pose.t_s
        self._next_due_ns = _queue_ticks(
            pose.parent_from_bone_quat, pose.root_pos, pose.t_s, self._in_q,
            self._in_p, self._q, self._p, self._floats, self._ints, now_ns, tag,
        )  # fmt: skip

    def pending(self) -> bool:
        """Whether any computed tick is queued (due or not)."""
        return self._next_due_ns >= 0

    def next_due_ns(self) -> int:
        """The oldest queued tick's send time (``time.monotonic_ns()``), -1 if none."""
        return self._next_due_ns

    def due(self, now_ns: int) -> bool:
        """Whether the oldest queued tick's send time has come."""
        return 0 <= self._next_due_ns <= now_ns

    def pop(self, out: PoseBuffer) -> PoseBuffer:
        """Write the oldest queued tick (call only while :meth:`pending`).

        Args:
            out: the destination (B bones).

        Returns:
            ``out`` with ``t_s`` the tick time; :attr:`popped_tag` its tag,
            :attr:`popped_arrival_ns` its input's arrival.
        """
        self._next_due_ns = _pop_tick(
            self._q, self._p, self._floats, self._ints, out.parent_from_bone_quat,
            out.root_pos,
        )  # fmt: skip
        out.t_s = float(self._floats[_F_POPPED])
        return out
