"""The post pipeline on a body solve's pose, frame by frame, in place: what the live
loop runs between the body solve and the target mapping (README "Post stages").

Per frame (:meth:`SolvePost.apply`):

1. the solve's true parent-relative ``parent_from_bone_quat`` and ``root_pos`` are
   copied into one :class:`PoseBuffer` (time ``t_s``: the source's clock);
2. the :class:`~retargetd.daemon.post.pipeline.Pipeline` runs its stages on it, in
   the config's order, each timed (``stage_ns``);
3. the result is written back, and the rotations every consumer reads are rebuilt
   from it: ``world_from_bone_quat`` by forward kinematics down the chain (each bone
   put in the hemisphere of its value the frame before, STYLE §3), and
   ``rest_from_bone_quat = conj(rest_parent_from_bone) ⊗ parent_from_bone`` (w >= 0,
   the solve's convention).

This is exactly what ``retargetd solve --pipeline`` does to a whole take
(:func:`retargetd.daemon.cli.post_io.apply_pipeline_to_solve`), so a live stream and
the offline solve of the same frames agree. ``joint_centres`` stay the solve's (a
filter moves rotations, not the measured joints).

With ``output_rate_hz`` the processed poses then go through a
:class:`~retargetd.daemon.post.interp.RateResampler`: output ticks every ``1 /
output_rate_hz`` on the stream's clock from its first pose, each the slerp (root:
lerp) between the two processed poses around it, queued with a send time (the
first tick an input pose completes at once, the next ones spaced by the output
period). :meth:`SolvePost.apply` writes the first tick due, if any, and says
whether it did; :meth:`SolvePost.pop_due` writes each further tick when its time has
come, from the loop's timer (:meth:`SolvePost.next_due_ns`): above the input's rate
(60 Hz captured, 120 Hz sent) ticks go out between input frames, each at most one
input period less one output period behind the source (60 -> 120 Hz: 8.3 ms).

Stateful stages (the One Euro filter) restart when the stream's clock goes backwards
or jumps forward by more than :data:`RESTART_GAP_S` (a source restart, a replayed take
looping round), and when a pose is not finite (nothing non-finite is let into the
filter's state: the pose passes through unprocessed, and the count goes up).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from retargetd.daemon.body.solve import BodyPose
from retargetd.daemon.compiled import kernel, qmul
from retargetd.daemon.post.interp import RateResampler
from retargetd.daemon.post.pipeline import Pipeline
from retargetd.daemon.post.pose import PoseBuffer
from retargetd.protocols.frames import F64Array, IntArray

#: The marker inputs' restart gap (``protocols/marker_input.py`` ``RESTART_GAP_NS``):
#: a stream silent this long is a new session, so filters start again.
RESTART_GAP_S = 1.0


@kernel
def _load(
    q: F64Array, pos: F64Array, buf_q: F64Array, buf_pos: F64Array
) -> bool:  # pragma: no cover - compiled
    """Copy the pose into the buffer; False (nothing copied) if any value is not
    finite."""
    total = pos[0] + pos[1] + pos[2]
    for b in range(q.shape[0]):
        total += q[b, 0] + q[b, 1] + q[b, 2] + q[b, 3]
    if not np.isfinite(total * 0.0):
        return False
    buf_q[:, :] = q
    buf_pos[:] = pos
    return True


@kernel
def _refresh(
    order: IntArray,
    parents: IntArray,
    pfb: F64Array,
    rest: F64Array,
    wfb: F64Array,
    rfb: F64Array,
    last: F64Array,
    first: bool,
    buf_q: F64Array,
    buf_pos: F64Array,
    pos: F64Array,
) -> None:  # pragma: no cover - compiled
    """The processed pose back (``buf_*`` into ``pfb``, ``pos``), forward kinematics
    into ``wfb``, sign-continuous with ``last`` (the previous output, then updated)
    unless ``first``, and the rotations from rest."""
    pfb[:, :] = buf_q
    pos[:] = buf_pos
    for i in range(order.shape[0]):
        b = order[i]
        p = parents[b]
        if p < 0:
            w, x, y, z = pfb[b, 0], pfb[b, 1], pfb[b, 2], pfb[b, 3]
        else:
            w, x, y, z = qmul(
                wfb[p, 0], wfb[p, 1], wfb[p, 2], wfb[p, 3],
                pfb[b, 0], pfb[b, 1], pfb[b, 2], pfb[b, 3],
            )  # fmt: skip
        if (
            not first
            and w * last[b, 0] + x * last[b, 1] + y * last[b, 2] + z * last[b, 3] < 0
        ):
            w, x, y, z = -w, -x, -y, -z
        wfb[b, 0], wfb[b, 1], wfb[b, 2], wfb[b, 3] = w, x, y, z
        last[b, 0], last[b, 1], last[b, 2], last[b, 3] = w, x, y, z
        rw, rx, ry, rz = qmul(
            rest[b, 0], -rest[b, 1], -rest[b, 2], -rest[b, 3],
            pfb[b, 0], pfb[b, 1], pfb[b, 2], pfb[b, 3],
        )  # fmt: skip
        if rw < 0.0:
            rw, rx, ry, rz = -rw, -rx, -ry, -rz
        rfb[b, 0], rfb[b, 1], rfb[b, 2], rfb[b, 3] = rw, rx, ry, rz


def _chain_order(parents: Sequence[int]) -> IntArray:
    """Bone indices with every parent before its children."""
    n = len(parents)
    order: list[int] = []
    placed = [False] * n
    while len(order) < n:
        before = len(order)
        for b, p in enumerate(parents):
            if not placed[b] and (p < 0 or placed[p]):
                placed[b] = True
                order.append(b)
        if len(order) == before:
            raise ValueError(f"bone_parents has a cycle: {list(parents)}")
    return np.asarray(order, dtype=np.int64)


class SolvePost:
    """A post pipeline applied to body-solve poses in place (module docstring).

    Args:
        pipeline: the stages (:func:`~retargetd.daemon.post.pipeline.build_pipeline`
            for the solve's bones); at least one.
        bone_parents: (B,) parent index per bone, -1 for the root.
        rest_parent_from_bone_quat: (B, 4) float64 (w, x, y, z): the calibration's
            rest rotations.
        output_rate_hz: > 0: after the stages, resample to this rate
            (:class:`~retargetd.daemon.post.interp.RateResampler`, ticks on the
            stream's clock from its first pose): :meth:`apply` then says whether a
            tick fell due (module docstring); 0 = every pose goes out.

    Raises:
        ValueError: no stage and no resampling, a bad rate, or shapes that disagree.
    """

    def __init__(
        self,
        pipeline: Pipeline,
        bone_parents: Sequence[int],
        rest_parent_from_bone_quat: F64Array,
        output_rate_hz: float = 0.0,
    ) -> None:
        if not pipeline.stages and not output_rate_hz > 0.0:
            raise ValueError("SolvePost needs a stage or an output rate")
        n = len(bone_parents)
        rest = np.array(rest_parent_from_bone_quat, dtype=np.float64)
        if rest.shape != (n, 4):
            raise ValueError(
                f"rest_parent_from_bone_quat must be ({n}, 4); got {rest.shape}"
            )
        self.pipeline = pipeline
        self.stage_ns = pipeline.stage_ns
        self._parents = np.asarray(bone_parents, dtype=np.int64)
        self._order = _chain_order(bone_parents)
        self._rest = rest
        self._buf = PoseBuffer.new(n)
        self._tick = PoseBuffer.new(n)
        self.resampler = (
            RateResampler(n, output_rate_hz) if output_rate_hz > 0.0 else None
        )
        #: The time of the pose last written (a resampled tick's, else the input's).
        self.t_s = 0.0
        #: The tag (the caller's, from :meth:`apply`) of the pose last written: for a
        #: resampled tick, that of the input pose that completed it.
        self.tag = 0
        #: The arrival (``now_ns`` of :meth:`apply`) of the pose last written: for a
        #: resampled tick, that of the input pose that completed it.
        self.arrival_ns = 0
        self._last_wfb = np.zeros((n, 4))
        self._started = False  # the stateful stages have seen a pose
        self._signed = False  # world_from_bone_quat holds an output to follow
        self._last_t_s = 0.0
        #: Poses passed through unprocessed because they were not finite.
        self.non_finite = 0
        #: Times the stateful stages were restarted (clock back or a gap, or a
        #: non-finite pose after finite ones).
        self.restarts = 0

    @property
    def stage_names(self) -> tuple[str, ...]:
        """(S,) the stages' names in order: their kinds, ``kind#2`` for a repeat."""
        names: list[str] = []
        for kind in self.pipeline.kinds:
            name, k = kind, 1
            while name in names:
                k += 1
                name = f"{kind}#{k}"
            names.append(name)
        return tuple(names)

    def reset(self) -> None:
        """Restart every stateful stage (the next pose passes the filters as is)."""
        for stage in self.pipeline.stages:
            reset = getattr(stage, "reset", None)
            if reset is not None:
                reset()
        if self.resampler is not None:
            self.resampler.reset()
        self._started = False

    @property
    def dropped_ticks(self) -> int:
        """Output ticks dropped unsent from the resampler's full queue."""
        return self.resampler.dropped if self.resampler is not None else 0

    def apply(self, pose: BodyPose, t_s: float, now_ns: int = 0, tag: int = 0) -> bool:
        """Run the stages on one solved pose, in place.

        Args:
            pose: the body solve's frame (``parent_from_bone_quat``, ``root_pos`` read;
                those and ``world_from_bone_quat``, ``rest_from_bone_quat`` written).
            t_s: the pose's time, seconds (only differences matter).
            now_ns: its arrival, ``time.monotonic_ns()``: the origin of its resampled
                ticks' send times (the first is due then).
            tag: an integer kept with the pose and its ticks (:attr:`tag`), e.g. the
                input frame's number.

        Returns:
            True when ``pose`` holds a pose to send (always, without resampling): the
            processed pose, or with ``output_rate_hz`` the oldest output tick due
            (``t_s`` its time); False when none is due (``pose`` is then left as
            solved, not to be sent; a later tick may fall due: :meth:`pop_due`).
        """
        pfb = pose.parent_from_bone_quat
        buf = self._buf
        self.tag = tag
        self.arrival_ns = now_ns
        if not _load(pfb, pose.root_pos, buf.parent_from_bone_quat, buf.root_pos):
            self.non_finite += 1
            self.stage_ns[:] = 0
            if self._started:
                self.restarts += 1
                self.reset()
            self.t_s = t_s
            return True
        if self._started:
            dt = t_s - self._last_t_s
            if not 0.0 <= dt <= RESTART_GAP_S:
                self.restarts += 1
                self.reset()
        buf.t_s = t_s
        self.pipeline.apply(buf, buf)
        self._started = True
        self._last_t_s = t_s
        if self.resampler is not None:
            self.resampler.push(buf, now_ns, tag)
            return self.pop_due(pose, now_ns)
        self._write(pose, buf)
        return True

    def next_due_ns(self) -> int:
        """The next queued output tick's send time (``time.monotonic_ns()``), -1 for
        none (or no resampling)."""
        return self.resampler.next_due_ns() if self.resampler is not None else -1

    def pop_due(self, pose: BodyPose, now_ns: int) -> bool:
        """Write the oldest queued output tick into ``pose`` if its time has come.

        Args:
            pose: the body solve's frame buffers (as for :meth:`apply`).
            now_ns: ``time.monotonic_ns()``.

        Returns:
            Whether a tick was written (its time :attr:`t_s`, its input's
            :attr:`tag` and :attr:`arrival_ns`).
        """
        res = self.resampler
        if res is None or not res.due(now_ns):
            return False
        res.pop(self._tick)
        self.tag = res.popped_tag
        self.arrival_ns = res.popped_arrival_ns
        self._write(pose, self._tick)
        return True

    def _write(self, pose: BodyPose, buf: PoseBuffer) -> None:
        self.t_s = buf.t_s
        _refresh(
            self._order, self._parents, pose.parent_from_bone_quat, self._rest,
            pose.world_from_bone_quat, pose.rest_from_bone_quat, self._last_wfb,
            not self._signed, buf.parent_from_bone_quat, buf.root_pos, pose.root_pos,
        )  # fmt: skip
        self._signed = True
