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

# RateResampler._state slots.
_S_TICK, _S_HEAD, _S_QUEUED, _S_DROPPED, _S_COMPLETED = 0, 1, 2, 3, 4


@kernel
def _queue_ticks(
    prev_q: F64Array,
    last_q: F64Array,
    prev_p: F64Array,
    last_p: F64Array,
    prev_t: float,
    last_t: float,
    interpolate: bool,
    t0: float,
    period: float,
    now_ns: int,
    tag: int,
    q: F64Array,
    p: F64Array,
    t: F64Array,
    due: IntArray,
    tags: IntArray,
    arrival: IntArray,
    state: IntArray,
) -> None:  # pragma: no cover - compiled
    """Queue every tick in (prev_t, last_t]: slerp (root: lerp) between the two
    poses, send times ``now + (t - t_first)``; still-queued ticks due at once."""
    n_slots = q.shape[0]
    head, queued = state[_S_HEAD], state[_S_QUEUED]
    for k in range(queued):  # overdue: due at once
        due[(head + k) % n_slots] = now_ns
    completed = 0
    tick = state[_S_TICK]
    t_first = t0 + tick * period
    while t0 + tick * period <= last_t + 1e-12:
        tt = t0 + tick * period
        tick += 1
        if queued == n_slots:
            head = (head + 1) % n_slots
            queued -= 1
            state[_S_DROPPED] += 1
        slot = (head + queued) % n_slots
        if not interpolate or tt >= last_t:
            q[slot, :, :] = last_q
            p[slot, :] = last_p
        else:
            u = max(0.0, (tt - prev_t) / (last_t - prev_t))
            _slerp_pose(prev_q, last_q, prev_p, last_p, u, q[slot], p[slot])
        t[slot] = tt
        due[slot] = now_ns + np.int64(round((tt - t_first) * 1e9))
        tags[slot] = tag
        arrival[slot] = now_ns
        queued += 1
        completed += 1
    state[_S_TICK] = tick
    state[_S_HEAD] = head
    state[_S_QUEUED] = queued
    state[_S_COMPLETED] = completed


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
        self._prev = PoseBuffer.new(n_bones)
        self._last = PoseBuffer.new(n_bones)
        self._count = 0
        self._t0_s = 0.0
        # The queue: each tick's rotations, root, time, send time (ns), tag and its
        # input's arrival (ns); head, count and counters in _state (int64).
        self._q = np.zeros((QUEUE_TICKS, n_bones, 4))
        self._p = np.zeros((QUEUE_TICKS, 3))
        self._t = np.zeros(QUEUE_TICKS)
        self._due_ns = np.zeros(QUEUE_TICKS, dtype=np.int64)
        self._tags = np.zeros(QUEUE_TICKS, dtype=np.int64)
        self._arrival_ns = np.zeros(QUEUE_TICKS, dtype=np.int64)
        self._state = np.zeros(5, dtype=np.int64)
        # Mirrors of the queue's head and length and the oldest tick's send time as
        # Python ints (numpy scalar reads cost ~0.2 us each on the loop's every turn).
        self._head = 0
        self._queued = 0
        self._next_due_ns = -1
        #: The tag of the tick :meth:`pop` wrote last.
        self.popped_tag = 0
        #: The arrival (``now_ns`` of its push) of that tick's input.
        self.popped_arrival_ns = 0

    @property
    def completed(self) -> int:
        """Ticks the last push completed."""
        return int(self._state[_S_COMPLETED])

    @property
    def dropped(self) -> int:
        """Ticks dropped from a full queue (never sent)."""
        return int(self._state[_S_DROPPED])

    def reset(self) -> None:
        """Forget the stream and the queued ticks (e.g. after a source restart)."""
        self._count = 0
        st = self._state
        st[_S_TICK] = st[_S_QUEUED] = st[_S_COMPLETED] = 0
        self._queued, self._next_due_ns = 0, -1

    def push(self, pose: PoseBuffer, now_ns: int = 0, tag: int = 0) -> None:
        """Take the next input pose and queue the ticks it completes.

        Args:
            pose: the pose (copied); times must increase (an older one is ignored).
            now_ns: its arrival, ``time.monotonic_ns()`` (the send times' origin).
            tag: an integer kept with each tick it completes (e.g. the input frame's
                number), read back as :attr:`popped_tag`.
        """
        self._state[_S_COMPLETED] = 0
        if self._count and pose.t_s <= self._last.t_s:
            return
        self._prev, self._last = self._last, self._prev
        self._last.copy_from(pose)
        if self._count == 0:
            self._t0_s = pose.t_s
        self._count += 1
        prev, last, st = self._prev, self._last, self._state
        st[_S_HEAD], st[_S_QUEUED] = self._head, self._queued
        _queue_ticks(
            prev.parent_from_bone_quat, last.parent_from_bone_quat, prev.root_pos,
            last.root_pos, prev.t_s, last.t_s, self._count >= 2, self._t0_s,
            self.period_s, now_ns, tag, self._q, self._p, self._t, self._due_ns,
            self._tags, self._arrival_ns, st,
        )  # fmt: skip
        self._head, self._queued = int(st[_S_HEAD]), int(st[_S_QUEUED])
        self._next_due_ns = int(self._due_ns[self._head]) if self._queued else -1

    def pending(self) -> bool:
        """Whether any computed tick is queued (due or not)."""
        return self._queued > 0

    def next_due_ns(self) -> int:
        """The oldest queued tick's send time (``time.monotonic_ns()``), -1 if none."""
        return self._next_due_ns

    def due(self, now_ns: int) -> bool:
        """Whether the oldest queued tick's send time has come."""
        return self._queued > 0 and self._next_due_ns <= now_ns

    def pop(self, out: PoseBuffer) -> PoseBuffer:
        """Write the oldest queued tick (call only while :meth:`pending`).

        Args:
            out: the destination (B bones).

        Returns:
            ``out`` with ``t_s`` the tick time; :attr:`popped_tag` its tag,
            :attr:`popped_arrival_ns` its input's arrival.
        """
        slot = self._head
        np.copyto(out.parent_from_bone_quat, self._q[slot])
        np.copyto(out.root_pos, self._p[slot])
        out.t_s = float(self._t[slot])
        self.popped_tag = int(self._tags[slot])
        self.popped_arrival_ns = int(self._arrival_ns[slot])
        self._head = head = (slot + 1) % QUEUE_TICKS
        self._queued -= 1
        self._next_due_ns = int(self._due_ns[head]) if self._queued else -1
        return out
