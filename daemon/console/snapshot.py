"""What the loop hands the console: a fixed layout, a latest-snapshot slot, commands.

The live loop never waits for the console. It publishes a decimated copy of its state
(:data:`DEFAULT_PUBLISH_HZ`) into a :class:`SnapshotSlot`: two preallocated
:class:`Snapshot` buffers. The loop fills the back buffer in place
(:meth:`SnapshotSlot.begin`, or :meth:`SnapshotSlot.publish` to copy one it already
has) and :meth:`SnapshotSlot.commit` swaps it to the front under a lock taken with a
non-blocking try: when the console thread happens to be copying the front buffer out
at that instant the publish is skipped and counted (``skipped``), never waited for.
The console thread copies the front buffer out under the same lock (a few kB).

Button presses travel the other way as :class:`Command` items in a bounded
:class:`CommandQueue` (``put_nowait`` on the console thread, dropped and counted when
full); the loop drains it with :meth:`CommandQueue.drain` when it likes. Nothing on the
console thread calls into the loop.

The skeleton is drawn bone by bone from origin to tip (:class:`SkeletonProgram`):
each end is a joint centre when the rig names one there, otherwise it is reached
through the bone's own frame (+Y along the bone, its calibrated length), as the
solver defines it (``retargetd.daemon.body.solve``).
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from retargetd.daemon.rotations import quat_conj, quat_mul, quat_rotate
from retargetd.protocols.frames import F64Array, IntArray

#: Console refresh rate: 30 Hz is the frame rate of broadcast video (and above the
#: ~24 Hz at which motion reads as continuous), plenty for an operator's view; the
#: loop runs at the capture rate (100-240 Hz) and publishes every ~4th-8th frame.
DEFAULT_PUBLISH_HZ = 30.0
#: Commands held before presses are dropped: an operator presses a few buttons a
#: second at most; 64 covers a loop stalled for many seconds.
DEFAULT_COMMAND_QUEUE_SIZE = 64

#: Command kinds the console sends.
CMD_CALIBRATE = "calibrate"
CMD_RECORD_START = "record_start"
CMD_RECORD_STOP = "record_stop"
CMD_FACE_CAPTURE = "face_capture"
CMD_RELOAD = "reload"
COMMAND_KINDS = (
    CMD_CALIBRATE,
    CMD_RECORD_START,
    CMD_RECORD_STOP,
    CMD_FACE_CAPTURE,
    CMD_RELOAD,
)


@dataclass(frozen=True, slots=True, kw_only=True)
class SkeletonProgram:
    """How to place each bone's two ends, as index arrays (built once per layout).

    Bones run between named points (a rig's bone ``origin`` and ``aim``). A point is
    known where it is a solved joint centre, or the root bone's origin (the solve's
    root position); from a known end, the other end of a bone is reached along the
    bone's +Y axis by its calibrated length (``world_from_bone * (0, L, 0)``, forward
    from the origin or back from the tip), repeated until nothing more is found. Which
    end is reached from which is planned once here (``steps``, in levels: each level
    a few index arrays), so placing a frame is a handful of vectorised numpy calls.

    Attributes:
        n_points: number of points P.
        joint_point: (J,) int64 point index of each joint centre, -1 when no bone
            uses it.
        origin_point: (B,) int64 point index of each bone's origin.
        tip_point: (B,) int64 point index of each bone's tip.
        root_point: point index of the root bone's origin, or -1.
    """

    n_points: int
    joint_point: IntArray
    origin_point: IntArray
    tip_point: IntArray
    root_point: int = -1
    #: Planned levels: (bone, source point, destination point, +1 forward / -1
    #: back) index arrays per level (computed from the fields above).
    steps: tuple[tuple[IntArray, IntArray, IntArray, F64Array], ...] = field(
        init=False, default=()
    )

    def __post_init__(self) -> None:
        known = {int(p) for p in self.joint_point if p >= 0}
        if self.root_point >= 0:
            known.add(self.root_point)
        levels = []
        while True:
            level: dict[int, tuple[int, int, float]] = {}  # dst -> (bone, src, sign)
            for b in range(self.n_bones):
                o, t = int(self.origin_point[b]), int(self.tip_point[b])
                if o in known and t not in known:
                    level.setdefault(t, (b, o, 1.0))
                elif t in known and o not in known:
                    level.setdefault(o, (b, t, -1.0))
            if not level:
                break
            dst = np.fromiter(level, np.int64, len(level))
            vals = list(level.values())
            levels.append(
                (
                    np.array([v[0] for v in vals], np.int64),
                    np.array([v[1] for v in vals], np.int64),
                    dst,
                    np.array([v[2] for v in vals])[:, None],
                )
            )
            known.update(level)
        object.__setattr__(self, "steps", tuple(levels))

    @property
    def n_bones(self) -> int:
        """Number of bones B."""
        return int(self.origin_point.shape[0])

    @staticmethod
    def from_joint_pairs(
        pairs: Sequence[tuple[int, int]], n_joints: int | None = None
    ) -> SkeletonProgram:
        """Bones that run from one joint centre to another (a stick figure).

        Args:
            pairs: (origin joint, tip joint) per bone.
            n_joints: J (default: the largest index + 1).
        """
        a = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        j = int(a.max()) + 1 if n_joints is None and a.size else int(n_joints or 0)
        return SkeletonProgram(
            n_points=j,
            joint_point=np.arange(j, dtype=np.int64),
            origin_point=a[:, 0].copy(),
            tip_point=a[:, 1].copy(),
        )

    @staticmethod
    def from_rig(rig: Any, joint_names: Sequence[str]) -> SkeletonProgram:
        """The program for a rig (``body.rig.Rig``), bones in rig order.

        Args:
            rig: the rig.
            joint_names: the solver's joint-centre names (its output order).
        """
        points: dict[str, int] = {}
        for bone in rig.bones:
            points.setdefault(bone.origin, len(points))
            points.setdefault(bone.aim, len(points))
        joint_point = np.array(
            [points.get(rig.joints.get(name, ""), -1) for name in joint_names],
            dtype=np.int64,
        )
        roots = [points[b.origin] for b in rig.bones if b.parent is None]
        return SkeletonProgram(
            n_points=len(points),
            joint_point=joint_point,
            origin_point=np.array([points[b.origin] for b in rig.bones], np.int64),
            tip_point=np.array([points[b.aim] for b in rig.bones], np.int64),
            root_point=roots[0] if roots else -1,
        )


def bone_endpoints(
    program: SkeletonProgram,
    joint_pos: F64Array,
    world_from_bone_quat: F64Array | None = None,
    root_pos: F64Array | None = None,
    bone_lengths: F64Array | None = None,
) -> F64Array:
    """Both ends of every bone, for one frame or many.

    Args:
        program: the skeleton program.
        joint_pos: (..., J, 3) metres, world joint centres (NaN when unknown).
        world_from_bone_quat: (..., B, 4) w x y z; needed for ends that are not
            joint centres (those stay NaN without it).
        root_pos: (..., 3) metres, world: the root bone's origin.
        bone_lengths: (B,) metres, calibrated origin-to-aim lengths.

    Returns:
        (..., B, 2, 3) float64 metres, world: origin then tip; NaN where undetermined.
    """
    lead = joint_pos.shape[:-2]
    pts = np.full((*lead, program.n_points, 3), np.nan)
    has = program.joint_point >= 0
    pts[..., program.joint_point[has], :] = joint_pos[..., has, :]
    if program.root_point >= 0 and root_pos is not None:
        r = pts[..., program.root_point, :]
        pts[..., program.root_point, :] = np.where(np.isnan(r), root_pos, r)
    o, t = program.origin_point, program.tip_point
    if world_from_bone_quat is not None and bone_lengths is not None:
        y = np.zeros((*lead, program.n_bones, 3))
        y[..., 1] = bone_lengths
        along = quat_rotate(world_from_bone_quat, y)  # (..., B, 3)
        for bone, src, dst, sign in program.steps:
            pts[..., dst, :] = pts[..., src, :] + sign * along[..., bone, :]
    return np.stack([pts[..., o, :], pts[..., t, :]], axis=-2)


def humanoid_positions(
    layout: ConsoleLayout,
    world_from_bone_quat: F64Array,
    hips_pos: F64Array,
    out: F64Array,
) -> F64Array:
    """Forward kinematics of the retargeted humanoid (on the console thread).

    ``x_h = x_p + E_p o_h`` with ``E_p = G_p ⊗ T̄_p`` (the parent's world rotation
    from rest) and ``x_root = hips_pos``: the target's own definition
    (``retargetd.daemon.retarget.retarget.joint_positions_world``).

    Args:
        layout: with ``humanoid_parents`` (parents before children),
            ``humanoid_rest_offsets`` and ``humanoid_rest_quat``.
        world_from_bone_quat: (H, 4) w x y z.
        hips_pos: (3,) metres world.
        out: (H, 3) float64, overwritten.

    Returns:
        ``out``, metres world.
    """
    par = layout.humanoid_parents
    delta = quat_mul(world_from_bone_quat, quat_conj(layout.humanoid_rest_quat))
    step = quat_rotate(delta[np.maximum(par, 0)], layout.humanoid_rest_offsets)
    for i, p in enumerate(par.tolist()):
        out[i] = hips_pos if p < 0 else out[p] + step[i]
    return out


@dataclass(frozen=True, slots=True, kw_only=True)
class ConsoleLayout:
    """What stays fixed between reloads: names, sizes and the skeletons' programs.

    Attributes:
        marker_names: (M,) marker labels.
        joint_names: (J,) solved joint-centre names.
        bone_names: (B,) bone names.
        bone_parents: (B,) int64 parent bone, -1 for the root.
        skeleton: program placing the solved bones.
        bone_lengths: (B,) float64 metres, calibrated (NaN before calibration).
        humanoid_names: (H,) retargeted humanoid joint names (empty: none).
        humanoid_pairs: (K, 2) int64 humanoid joint index pairs drawn as bones.
        humanoid_offset_m: (3,) where the humanoid is drawn relative to the
            performer's world positions (beside it, metres).
        humanoid_parents: (H,) int64 parent joint, -1 for the root; with the two
            below, the humanoid is posed on the console thread from the
            snapshot's ``humanoid_quat`` and ``humanoid_hips``
            (:func:`humanoid_positions`); empty: ``humanoid_pos`` is given.
        humanoid_rest_offsets: (H, 3) float64 metres, world axes: each joint's
            offset from its parent in the target's rest pose.
        humanoid_rest_quat: (H, 4) float64 w x y z: each bone's rest
            ``world_from_bone``.
        face_names: (F,) face weight names (empty: no face).
        stage_names: names of the timed pipeline stages (latency plots).
        check_names: (K,) the validation checks a snapshot's ``check_flags`` bits
            and ``check_values`` follow (live: ``pose_stream.VALIDATION_CHECKS``;
            offline: a report's checks); at most 64.
        check_units: (K,) each check's unit, for the page ("" for none).
        prop_names: (P,) the ``[[prop]]`` rigid bodies drawn as axes (empty: none).
    """

    marker_names: tuple[str, ...]
    joint_names: tuple[str, ...]
    bone_names: tuple[str, ...]
    bone_parents: IntArray
    skeleton: SkeletonProgram
    bone_lengths: F64Array
    humanoid_names: tuple[str, ...] = ()
    humanoid_pairs: IntArray = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    humanoid_offset_m: F64Array = field(
        default_factory=lambda: np.array([1.2, 0.0, 0.0])
    )
    humanoid_parents: IntArray = field(default_factory=lambda: np.zeros(0, np.int64))
    humanoid_rest_offsets: F64Array = field(default_factory=lambda: np.zeros((0, 3)))
    humanoid_rest_quat: F64Array = field(default_factory=lambda: np.zeros((0, 4)))
    face_names: tuple[str, ...] = ()
    stage_names: tuple[str, ...] = ()
    check_names: tuple[str, ...] = ()
    check_units: tuple[str, ...] = ()
    prop_names: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.skeleton.n_bones != len(self.bone_names):
            raise ValueError(
                f"skeleton has {self.skeleton.n_bones} bones, "
                f"bone_names {len(self.bone_names)}"
            )
        if len(self.check_names) > 64 or (
            self.check_units and len(self.check_units) != len(self.check_names)
        ):
            raise ValueError(
                f"check_names: at most 64, one unit each; got "
                f"{len(self.check_names)} names, {len(self.check_units)} units"
            )


@dataclass(slots=True, eq=False)
class Snapshot:
    """One published state (buffers preallocated from a :class:`ConsoleLayout`).

    Attributes:
        layout_id: which layout these arrays follow (bumped on reload).
        frame: the capture frame number.
        t_s: seconds since the run started: live, since the daemon started (the
            pose stream's ``t``); offline, since the take's first frame.
        marker_pos: (M, 3) float64 metres world (NaN or stale where occluded).
        marker_valid: (M,) bool, True where seen this frame.
        joint_pos: (J, 3) float64 metres world, solved joint centres.
        world_from_bone_quat: (B, 4) float64 w x y z.
        root_pos: (3,) float64 metres world.
        bone_flags: (B,) uint8 ``FLAG_*`` bits (non-zero = drawn red).
        humanoid_pos: (H, 3) float64 metres, the retargeted humanoid's joints
            (filled by the console thread when the layout poses the humanoid).
        humanoid_quat: (H, 4) float64 w x y z, the retargeted ``world_from_bone``
            of each target bone (``TargetPose.world_from_bone_quat``).
        humanoid_hips: (3,) float64 metres world, the target's Hips joint.
        face_weights: (F,) float32 in [0, 1].
        face_on: the face weights are live.
        calibrated: a calibration is loaded.
        recording: a recording is running.
        input_rate_hz: marker frames received per second.
        drops: marker frames dropped since start (cumulative).
        latency_p50_ms / latency_p99_ms: (K,) float64 per stage, milliseconds.
        occluded: markers occluded this frame.
        validation_flags: validation flags raised (cumulative).
        check_flags: bit k set when the layout's ``check_names[k]`` flags this
            frame (live: the latest validation result; offline: the report).
        check_values: (K,) float64, each check's value at this frame in its
            ``check_units`` (NaN: not known).
    """

    layout_id: int
    frame: int
    t_s: float
    marker_pos: F64Array
    marker_valid: np.ndarray
    joint_pos: F64Array
    world_from_bone_quat: F64Array
    root_pos: F64Array
    bone_flags: np.ndarray
    humanoid_pos: F64Array
    humanoid_quat: F64Array
    humanoid_hips: F64Array
    face_weights: np.ndarray
    face_on: bool
    calibrated: bool
    recording: bool
    input_rate_hz: float
    drops: int
    latency_p50_ms: F64Array
    latency_p99_ms: F64Array
    occluded: int
    validation_flags: int
    check_flags: int
    check_values: F64Array
    #: (P, 4) w x y z world_from_prop, (P, 3) metres world, (P,) prop flags
    #: (``props.kernel.FLAG_*``; NEVER: not drawn), one per ``layout.prop_names``.
    prop_quat: F64Array = field(default_factory=lambda: np.zeros((0, 4)))
    prop_pos: F64Array = field(default_factory=lambda: np.zeros((0, 3)))
    prop_flags: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint8))

    @staticmethod
    def for_layout(layout: ConsoleLayout, layout_id: int = 0) -> Snapshot:
        """An empty snapshot (NaN positions, nothing seen) sized for ``layout``."""
        m, j = len(layout.marker_names), len(layout.joint_names)
        b, h = len(layout.bone_names), len(layout.humanoid_names)
        k = len(layout.stage_names)
        quat = np.zeros((b, 4))
        quat[:, 0] = 1.0
        return Snapshot(
            layout_id=layout_id,
            frame=0,
            t_s=0.0,
            marker_pos=np.full((m, 3), np.nan),
            marker_valid=np.zeros(m, bool),
            joint_pos=np.full((j, 3), np.nan),
            world_from_bone_quat=quat,
            root_pos=np.full(3, np.nan),
            bone_flags=np.zeros(b, np.uint8),
            humanoid_pos=np.full((h, 3), np.nan),
            humanoid_quat=np.tile([1.0, 0.0, 0.0, 0.0], (h, 1)),
            humanoid_hips=np.full(3, np.nan),
            face_weights=np.zeros(len(layout.face_names), np.float32),
            face_on=False,
            calibrated=False,
            recording=False,
            input_rate_hz=0.0,
            drops=0,
            latency_p50_ms=np.full(k, np.nan),
            latency_p99_ms=np.full(k, np.nan),
            occluded=0,
            validation_flags=0,
            check_flags=0,
            check_values=np.full(len(layout.check_names), np.nan),
            prop_quat=np.tile([1.0, 0.0, 0.0, 0.0], (len(layout.prop_names), 1)),
            prop_pos=np.zeros((len(layout.prop_names), 3)),
            prop_flags=np.full(len(layout.prop_names), 8, np.uint8),  # never
        )

    def copy_from(self, other: Snapshot) -> None:
        """Copy ``other`` into these buffers (same layout; no allocation)."""
        self.layout_id = other.layout_id
        self.frame = other.frame
        self.t_s = other.t_s
        np.copyto(self.marker_pos, other.marker_pos)
        np.copyto(self.marker_valid, other.marker_valid)
        np.copyto(self.joint_pos, other.joint_pos)
        np.copyto(self.world_from_bone_quat, other.world_from_bone_quat)
        np.copyto(self.root_pos, other.root_pos)
        np.copyto(self.bone_flags, other.bone_flags)
        np.copyto(self.humanoid_pos, other.humanoid_pos)
        np.copyto(self.humanoid_quat, other.humanoid_quat)
        np.copyto(self.humanoid_hips, other.humanoid_hips)
        np.copyto(self.face_weights, other.face_weights)
        self.face_on = other.face_on
        self.calibrated = other.calibrated
        self.recording = other.recording
        self.input_rate_hz = other.input_rate_hz
        self.drops = other.drops
        np.copyto(self.latency_p50_ms, other.latency_p50_ms)
        np.copyto(self.latency_p99_ms, other.latency_p99_ms)
        self.occluded = other.occluded
        self.validation_flags = other.validation_flags
        self.check_flags = other.check_flags
        np.copyto(self.check_values, other.check_values)
        np.copyto(self.prop_quat, other.prop_quat)
        np.copyto(self.prop_pos, other.prop_pos)
        np.copyto(self.prop_flags, other.prop_flags)


class SnapshotSlot:
    """The latest snapshot, double-buffered: the writer never blocks.

    One writer (the loop) and one reader (the console thread). The writer owns the
    back buffer outright (the reader only ever reads the front one, under the lock),
    so filling it needs no lock; :meth:`commit` swaps front and back under a
    non-blocking lock try.

    Args:
        layout: sizes the buffers; :meth:`set_layout` replaces it (on reload; this
            allocates, so it is not for every frame).
        publish_hz: the rate :meth:`due` paces publishing to.
    """

    def __init__(
        self, layout: ConsoleLayout, *, publish_hz: float = DEFAULT_PUBLISH_HZ
    ) -> None:
        if not publish_hz > 0:
            raise ValueError(f"publish_hz must be > 0; got {publish_hz}")
        self._lock = threading.Lock()
        self._period_ns = int(1e9 / publish_hz)
        self._next_ns = 0
        self.layout = layout
        self.layout_id = 0
        self._bufs = [Snapshot.for_layout(layout), Snapshot.for_layout(layout)]
        self._front = 0
        #: Snapshots committed (the front buffer's sequence number).
        self.seq = 0
        #: Commits skipped because the reader held the lock.
        self.skipped = 0

    def set_layout(self, layout: ConsoleLayout) -> None:
        """Replace the layout (after a reload); the reader sees the new sizes at its
        next read. Called by the writer only."""
        with self._lock:
            self.layout_id += 1
            self.layout = layout
            self._bufs = [
                Snapshot.for_layout(layout, self.layout_id),
                Snapshot.for_layout(layout, self.layout_id),
            ]
            self.seq += 1

    def current_layout(self) -> tuple[ConsoleLayout, int]:
        """(layout, layout_id) as one consistent pair (for the reader)."""
        with self._lock:
            return self.layout, self.layout_id

    def due(self, now_ns: int | None = None) -> bool:
        """True when a publish is due at ``publish_hz`` (and schedules the next).

        Args:
            now_ns: ``time.monotonic_ns()`` (read here when None).
        """
        now = time.monotonic_ns() if now_ns is None else now_ns
        if now < self._next_ns:
            return False
        # Schedule from the due time, not from now, so the mean rate holds; resync
        # after a stall rather than bursting.
        self._next_ns = max(self._next_ns + self._period_ns, now)
        return True

    def begin(self) -> Snapshot:
        """The back buffer, for the writer to fill in place before :meth:`commit`."""
        return self._bufs[1 - self._front]

    def commit(self) -> bool:
        """Make the back buffer the latest snapshot, unless the reader is copying.

        Returns:
            False when skipped (counted in ``skipped``); the back buffer then keeps
            its contents and the next :meth:`begin` returns it again.
        """
        if not self._lock.acquire(blocking=False):
            self.skipped += 1
            return False
        try:
            self._front = 1 - self._front
            self.seq += 1
        finally:
            self._lock.release()
        return True

    def publish(self, snapshot: Snapshot) -> bool:
        """Copy ``snapshot`` (same layout) into the back buffer and commit it."""
        self.begin().copy_from(snapshot)
        return self.commit()

    def read(self, out: Snapshot, last_seq: int) -> int:
        """Copy the front buffer into ``out`` if it is newer than ``last_seq``.

        Args:
            out: the reader's own snapshot; must follow the current layout (compare
                ``out.layout_id`` with :attr:`layout_id` and reallocate with
                :meth:`Snapshot.for_layout` when they differ: this method copies
                nothing then and returns ``-1``).
            last_seq: the sequence number of the reader's last copy.

        Returns:
            The sequence number copied, ``last_seq`` when nothing newer was there, or
            -1 on a layout change.
        """
        with self._lock:
            if self.seq == last_seq:
                return last_seq
            front = self._bufs[self._front]
            if out.layout_id != front.layout_id:
                return -1
            out.copy_from(front)
            return self.seq


@dataclass(frozen=True, slots=True)
class Command:
    """A button press, for the loop.

    Attributes:
        kind: one of :data:`COMMAND_KINDS`.
        arg: the file name for ``record_start``, else "".
        t_ns: ``time.monotonic_ns()`` when it was queued.
    """

    kind: str
    arg: str = ""
    t_ns: int = 0


class CommandQueue:
    """Bounded queue of :class:`Command` from the console to the loop."""

    def __init__(self, maxsize: int = DEFAULT_COMMAND_QUEUE_SIZE) -> None:
        self._q: queue.Queue[Command] = queue.Queue(maxsize)
        #: Commands dropped because the queue was full.
        self.dropped = 0

    def put(self, kind: str, arg: str = "") -> bool:
        """Queue a command (never blocks); False when full (dropped, counted)."""
        if kind not in COMMAND_KINDS:
            raise ValueError(f"unknown command {kind!r}")
        try:
            self._q.put_nowait(Command(kind, arg, time.monotonic_ns()))
        except queue.Full:
            self.dropped += 1
            return False
        return True

    def get(self, timeout_s: float) -> Command | None:
        """The next command, waiting up to ``timeout_s`` (tests and tools)."""
        try:
            return self._q.get(timeout=timeout_s)
        except queue.Empty:
            return None

    def poll(self) -> Command | None:
        """The oldest queued command, or None (never blocks, allocates nothing when
        empty): the loop's per-frame call."""
        try:
            return self._q.get_nowait()
        except queue.Empty:
            return None

    def drain(self, max_items: int = DEFAULT_COMMAND_QUEUE_SIZE) -> list[Command]:
        """Every queued command, oldest first, at most ``max_items`` (never blocks)."""
        out: list[Command] = []
        while len(out) < max_items:
            try:
                out.append(self._q.get_nowait())
            except queue.Empty:
                break
        return out
