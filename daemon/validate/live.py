"""Live pose validation: the MuJoCo checks on their own thread, never delaying a send.

The daemon's loop thread sends each solved pose first, then hands it to
:meth:`LiveValidator.submit`, which copies four or five small arrays into a
preallocated ring slot and returns: it never waits (when every slot is waiting the
frame is dropped and counted: drop, don't block). The validator thread
(``retargetd-validator``) checks the frames in order against the MuJoCo model of the
calibration (:func:`validate_model.build_model`, cached by skeleton hash) and queues a
:class:`ValidationResult` per frame; the loop drains them with :meth:`results` on a
later frame, ORs the latest result's bits into the next pose and publishes every result
as an ``RTDV`` message (``protocols/PROTOCOLS.md``).

Checks per frame, in ``pose_stream.VALIDATION_CHECKS`` order: the value measured, and
the bits set when it is beyond its :data:`validate.THRESHOLDS` entry.

- convention (mm): max distance between the model posed from the parent-relative
  chain (``qpos``) and the skeleton posed from the world rotations (``convention_mm``).
- fit (mm): max distance between a skeleton point and its solved joint centre (pairs
  of :func:`validate.fit_pairs`; occluded centres skipped, NaN when none is seen)
  (``fit_max_mm``); bone bit FIT on each bone whose origin or aim is beyond.
  **Blind for the fit** (the default method): the fit's joint centres are its rigid
  skeleton's own, so this reads ~0 whatever the markers do. Offline, ``retargetd
  validate`` reads the fit's marker residuals instead (``validate.residual``); live
  they are not checked yet: that needs the residuals in the ring slot and a ninth
  check, and RTDV's eight values and frame bits 8-15 are all taken (a protocol
  change, PROTOCOLS.md section 6). Live, watch the fit's frame flag ``reseeded``.
- quat_norm: max ``| |q| - 1 |`` over both rotation sets (``quat_norm``).
- limits (degrees beyond): the swing/twist table of :mod:`validate_limits`
  (``limit_deg``); bone bit LIMIT on each bone beyond.
- self_penetration (mm): deepest overlap of two non-excluded segments
  (``self_penetration_mm``); bone bit PENETRATION on both segments of every such
  contact.
- floor_penetration (mm): deepest segment below the floor (``floor_penetration_mm``);
  bone bit PENETRATION on the segment.
- speed (m/s): the fastest of the root and the end effectors (leaf bones' aims); the
  frame bit when the root is over ``root_speed_m_s`` or an effector over
  ``effector_speed_m_s``, bone bit SPEED on that bone.
- floating (s): time without foot support so far (``max_airborne_s``).

Every value but floating equals, to float rounding, what the offline
:func:`validate.validate_take` gives for that frame (tested on the PiG walk and on the
synthetic defects); the offline ``fit_median`` has no live bit. **No ghost force
live**: it needs the trajectory around a frame (zero-phase filtered finite
differences, inverse dynamics over ±0.1 s), so it stays offline (``retargetd
validate``).

Causal versions of the offline trajectory checks:

- speed: backward difference to the previous *validated* frame over
  ``(frame_id - previous frame_id) / rate_hz`` seconds. Frame numbers, not receive
  times: receive stamps jitter (frames that arrive together are microseconds apart),
  which would read as speed. After dropped frames it is the mean speed over the gap (a
  lower bound of the peak: no false flag). The history (speed, support) is reset when
  the frame number does not move forward by 1 to ``max_gap_s * rate_hz`` frames (a
  restarted source, a long gap) or the receive time moved by more than ``max_gap_s``
  or backwards; no speed is invented across a gap. Unnumbered sources (frame_id -1)
  count frames from the receive clock (approximate).
- floating: a foot point (the capsule bottom under each foot/toes bone's origin and
  aim, as ``validate_dynamics.foot_points``) supports the body when it is within
  ``airborne_clearance_mm`` of the floor, or stationary: its speed, low-passed by a
  causal 2nd-order Butterworth (``validate_dynamics.CONTACT`` cutoff; offline it is
  zero-phase), has stayed below ``still_speed_m_s`` for ``still_min_s`` so far. The
  value is the unsupported time up to this frame (offline: the whole unsupported run),
  so a floating performer is flagged ``max_airborne_s`` into the run and the live value
  at a run's last frame equals the offline one.

Cost (``bench/bench_validate_live.py``, this 2-core shared machine, 2026-11-22): the
check, one frame at a time, median 19-20 µs, p99 31-34 µs on the PiG walk and the
MOTEK ballet (target p99 <= 100 µs); in the thread, woken once per frame at 1000 Hz
(cold caches), p50 ~30 µs, p99 ~53 µs, submit -> result median ~44 µs. Baselines in
the same run: the offline per-frame MuJoCo step ``FrameChecker.check`` alone (which does
less) median 32 µs, p99 60 µs; ``validate_take`` (no ghost force) 64 µs per frame
amortised. ``submit`` median 2.5 µs, p99 2.9 µs; a dropped submit 0.5 µs. Per frame:
a compiled qpos write, ``mj_kinematics``, ``mj_collision``, the contacts copied to a
contiguous buffer, one compiled kernel for every check (numba, ``nogil``), and the
result object (the only allocations, on the validator thread: the result is handed to
another thread).

The GIL. The loop and the validator share it. MuJoCo's Python bindings release it in
every ``mj_*`` call (``python/mujoco/functions.h`` registers each function with
``call_guard<gil_scoped_release>``; measured here: a thread counting in Python kept
93 % of its rate while another thread ran one long ``mj_step``, 50 % against a
pure-Python thread), and both kernels here are ``nogil``, so the validator holds the
GIL only for its Python glue, in pieces of a few microseconds between those calls; a
loop thread waking from its poll waits for at most one piece. Measured with a
loop-like thread at 1000 Hz (solve + retarget + encode of the PiG walk, then
``results()`` + ``submit()``; cases interleaved so machine noise hits all alike):
validator on, one frame per tick as in the daemon: tick -> end-of-work p99 within
noise of validator off (-27 to +1 µs), work median +4 µs (cache effects: the check
of the previous frame is long finished by the next tick); validator saturated (ring
refilled every tick, ~46,000 checks/s, a whole core): p99 +66 to +113 µs, work
median +9 µs (GIL hand-overs at the loop's own nogil kernels). ``sys.setswitchinterval``
5, 1, 0.5 or 0.1 ms made no difference beyond that noise: the validator never runs a
long pure-Python stretch, which is all the interval bounds. So the daemon leaves it
at Python's default for the validator (no config key; below ~0.1 ms buys nothing).
What the interval cannot bound is a garbage collection, which holds the GIL:
a full (gen 2) collection of this process took 53 ms, 2 µs after ``gc.freeze()``;
the daemon should ``gc.freeze()`` once its models and solvers are built.

Threading model: one producer (the loop thread: :meth:`submit`, :meth:`results`) and
one consumer (the validator thread). The ring's head is written only by the producer,
its tail only by the consumer (CPython with the GIL: int stores are atomic and ordered;
a free-threaded build would need a lock). A wake-up token per accepted frame goes
through a ``queue.SimpleQueue`` (a C ``put`` that never blocks). Results go through a
bounded deque; results the loop never drains are counted in ``results_lost``.
"""

from __future__ import annotations

import collections
import logging
import math
import queue
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from retargetd.daemon.body.calibration import Calibration
from retargetd.daemon.body.rig import Rig
from retargetd.daemon.validate.checks import THRESHOLDS
from retargetd.daemon.validate.live_kernel import (
    CHECK_BITS,
    N_CHECKS,
)
from retargetd.daemon.validate.live_tables import (
    Checker,
    Tables,
)
from retargetd.daemon.validate.model import (
    DEFAULT_BODY_MASS_KG,
    build_model,
    skeleton_from_calibration,
)
from retargetd.protocols import pose_stream as ps
from retargetd.protocols.frames import F32Array, F64Array, U8Array

logger = logging.getLogger(__name__)

_COST_RING = 1024  # recent per-frame check costs kept for p50 / p99
_STOP = -1


@dataclass(slots=True, eq=False)
class ValidationResult:
    """One validated frame.

    Attributes:
        frame_id: the frame's number, as submitted.
        t_ns: the frame's ``t_ns`` as submitted (the loop passes its received_ns).
        validated_ns: ``time.monotonic_ns()`` when the checks finished.
        frame_flags: validation frame bits (``FRAME_V_*``, bits 8-15 only).
        bone_flags: (B,) uint8, validation bone bits (``BONE_V_*``, bits 4-7 only).
        values: (8,) float32, one measured value per check in
            ``pose_stream.VALIDATION_CHECKS`` order: convention mm, fit max mm,
            max | \\|q\\| - 1 |, limit degrees beyond, self-penetration mm,
            floor-penetration mm, max speed m/s, airborne seconds.
    """

    frame_id: int
    t_ns: int
    validated_ns: int
    frame_flags: int
    bone_flags: U8Array
    values: F32Array


@dataclass(slots=True, eq=False)
class _Slot:
    """One ring entry: copies of a submitted frame (allocated once)."""

    frame_id: int
    t_ns: int
    has_lengths: bool
    root_pos: F64Array  # (3,)
    world_from_bone_quat: F64Array  # (B, 4)
    rest_from_bone_quat: F64Array  # (B, 4)
    joint_centres: F64Array  # (J, 3)
    bone_lengths: F64Array  # (B,)


# ---- the validator -----------------------------------------------------------------


class LiveValidator:
    """MuJoCo checks of streamed poses on their own thread, behind a drop-don't-block
    ring.

    Args:
        rig: the rig the poses are solved with.
        calibration: its calibration (the model's skeleton).
        thresholds: overrides of :data:`validate.THRESHOLDS` (keys must exist there).
        body_mass_kg: the model's mass (None: 70 kg); the live checks don't depend on
            it, but the model (and its cache key) does.
        rate_hz: the rate the frame numbers count at (speeds, airborne time, filter).
        queue_size: ring slots; a frame submitted while all are waiting is dropped.
        max_gap_s: longest gap (in frame numbers / ``rate_hz`` and in receive time)
            across which speed and support history are kept.

    Raises:
        ValueError: an unknown threshold, ``rate_hz`` or ``queue_size`` out of range, a
            calibration with no rest bone origins.

    Counters (read from any thread; each written by one thread): ``submitted``,
    ``validated``, ``dropped`` (ring full or closed), ``errors`` (a check raised: a
    bug, logged), ``results_lost`` (results not drained in time), ``flagged`` (per
    check, ``VALIDATION_CHECKS`` order), and the check cost p50 / p99 over the last
    1024 frames (:meth:`cost_us`). :meth:`counters` / :meth:`status` give them as dicts.
    """

    def __init__(
        self,
        rig: Rig,
        calibration: Calibration,
        *,
        thresholds: dict[str, float] | None = None,
        body_mass_kg: float | None = None,
        rate_hz: float = 240.0,
        queue_size: int = 16,
        max_gap_s: float = 0.25,
    ) -> None:
        unknown = set(thresholds or {}) - set(THRESHOLDS)
        if unknown:
            raise ValueError(
                f"thresholds: unknown keys {sorted(unknown)}; "
                f"known: {sorted(THRESHOLDS)}"
            )
        if not (rate_hz > 0.0 and math.isfinite(rate_hz)):
            raise ValueError(f"rate_hz: expected > 0 Hz; got {rate_hz}")
        if not 1 <= queue_size <= 100_000:
            raise ValueError(f"queue_size: expected [1, 100000]; got {queue_size}")
        if not max_gap_s > 0.0:
            raise ValueError(f"max_gap_s: expected > 0 s; got {max_gap_s}")
        self.thresholds = {**THRESHOLDS, **(thresholds or {})}
        self.rate_hz = float(rate_hz)
        self.queue_size = int(queue_size)
        mass = DEFAULT_BODY_MASS_KG if body_mass_kg is None else float(body_mass_kg)
        self.vm = build_model(skeleton_from_calibration(rig, calibration), mass)
        skel = self.vm.skeleton
        self.bone_names = skel.bone_names
        self.n_bones = len(skel.bone_names)
        self._tables = Tables(self.vm, rig, self.thresholds, self.rate_hz)
        self.n_joints = self._tables.n_joints
        self._cal_lengths = np.array(skel.bone_lengths, dtype=np.float64)
        self._cal_lengths.flags.writeable = False
        self._checker = Checker(self.vm, self._tables, self.rate_hz, max_gap_s)
        self._warm_up()
        b, j = self.n_bones, self.n_joints
        self._slots = [
            _Slot(
                0,
                0,
                False,
                np.zeros(3),
                np.zeros((b, 4)),
                np.zeros((b, 4)),
                np.zeros((j, 3)),
                np.zeros(b),
            )
            for _ in range(self.queue_size)
        ]
        self._head = 0  # written by the producer only
        self._tail = 0  # written by the consumer only
        self._wake: queue.SimpleQueue[int] = queue.SimpleQueue()
        maxlen = max(64, 4 * self.queue_size)
        self._results: collections.deque[ValidationResult] = collections.deque(
            maxlen=maxlen
        )
        # Result objects are pooled: the thread fills the next one in place (no
        # allocation per frame). A result handed to the loop is reused only after
        # ``len(pool)`` more results; between two drains at most ``queue_size`` finish
        # (one per submitted frame) while at most ``maxlen`` wait, so this size never
        # recycles one the loop may still be reading.
        n_pool = 2 * maxlen + 2 * self.queue_size + 1
        self._pool = [
            ValidationResult(
                0, 0, 0, 0, np.zeros(b, np.uint8), np.zeros(N_CHECKS, np.float32)
            )
            for _ in range(n_pool)
        ]
        self._next_pool = 0
        self._thread: threading.Thread | None = None
        self._closed = False
        self.submitted = 0
        self.dropped = 0
        self.validated = 0
        self.errors = 0
        self.results_lost = 0
        self.flagged = [0] * N_CHECKS
        self._costs_ns = np.zeros(_COST_RING, dtype=np.int64)
        self._n_costs = 0
        self._last_error_log = -math.inf

    # ---- loop thread ----------------------------------------------------------------

    def submit(
        self,
        frame_id: int,
        t_ns: int,
        root_pos: F64Array,
        world_from_bone_quat: F64Array,
        rest_from_bone_quat: F64Array,
        joint_centres: F64Array,
        bone_lengths: F64Array | None = None,
    ) -> bool:
        """Copy one frame into the ring for the validator thread; never waits.

        Args:
            frame_id: the frame's number (consecutive frames differ by 1).
            t_ns: its receive time, ``time.monotonic_ns()``.
            root_pos: (3,) float64, metres, world.
            world_from_bone_quat: (B, 4) float64, w x y z.
            rest_from_bone_quat: (B, 4) float64, w x y z, relative to calibration.
            joint_centres: (J, 3) float64, metres, world; NaN rows = not solved.
            bone_lengths: (B,) float64 metres, the streamed skeleton's lengths; None =
                the calibrated ones.

        Returns:
            True when queued; False when dropped (ring full, or closed), counted in
            ``dropped``.
        """
        head = self._head
        if head - self._tail >= self.queue_size or self._closed:
            self.dropped += 1
            return False
        slot = self._slots[head % self.queue_size]
        slot.frame_id = frame_id
        slot.t_ns = t_ns
        np.copyto(slot.root_pos, root_pos)
        np.copyto(slot.world_from_bone_quat, world_from_bone_quat)
        np.copyto(slot.rest_from_bone_quat, rest_from_bone_quat)
        np.copyto(slot.joint_centres, joint_centres)
        if bone_lengths is None:
            slot.has_lengths = False
        else:
            slot.has_lengths = True
            np.copyto(slot.bone_lengths, bone_lengths)
        self._head = head + 1  # publish the slot (after its data)
        self.submitted += 1
        self._wake.put(0)
        return True

    def results(self) -> Sequence[ValidationResult]:
        """Results finished since the last call, oldest first, as copies the caller
        may keep (never waits; an empty tuple when there are none). The loop uses the
        allocation-free :meth:`drain_results` instead."""
        dq = self._results
        if not dq:
            return ()
        out = []
        while dq:
            r = dq.popleft()
            out.append(
                ValidationResult(
                    r.frame_id,
                    r.t_ns,
                    r.validated_ns,
                    r.frame_flags,
                    r.bone_flags.copy(),
                    r.values.copy(),
                )
            )
        return out

    def drain_results(self, out: list[ValidationResult | None]) -> int:
        """Move the finished results into ``out`` (a list the caller keeps, of
        length >= the results queue's), oldest first; returns how many (the loop's
        allocation-free form of :meth:`results`). The results are the validator's
        pooled objects: read them before the next drain."""
        dq = self._results
        n = 0
        limit = len(out)
        while dq and n < limit:
            out[n] = dq.popleft()
            n += 1
        return n

    @property
    def results_capacity(self) -> int:
        """The most results :meth:`drain_results` can move at once."""
        return int(self._results.maxlen or 0)

    @property
    def pending(self) -> int:
        """Frames in the ring, not yet checked."""
        return self._head - self._tail

    # ---- lifecycle ------------------------------------------------------------------

    def start(self) -> None:
        """Start the validator thread (``retargetd-validator``, a daemon thread).

        Raises:
            RuntimeError: already started, or closed.
        """
        if self._closed:
            raise RuntimeError("LiveValidator is closed")
        if self._thread is not None:
            raise RuntimeError("LiveValidator already started")
        self._thread = threading.Thread(
            target=self._run, name="retargetd-validator", daemon=True
        )
        self._thread.start()

    def close(self, timeout: float = 1.0) -> None:
        """Stop the thread (frames still in the ring are not checked) and join it
        for up to ``timeout`` seconds. Idempotent."""
        if self._closed:
            return
        self._closed = True
        self._wake.put(_STOP)
        thread = self._thread
        if thread is not None:
            thread.join(timeout)
            if thread.is_alive():
                logger.warning(
                    "validator thread still running %.1f s after close", timeout
                )

    def __enter__(self) -> LiveValidator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def running(self) -> bool:
        """The thread is alive."""
        return self._thread is not None and self._thread.is_alive()

    # ---- validator thread -----------------------------------------------------------

    def _run(self) -> None:
        wake, slots, size = self._wake, self._slots, self.queue_size
        clock = time.perf_counter_ns
        while True:
            if wake.get() == _STOP or self._closed:
                return
            while self._tail < self._head and not self._closed:
                slot = slots[self._tail % size]
                t0 = clock()
                try:
                    result = self._check_slot(slot)
                except Exception:  # a bug: count it, log it (rate-limited), go on
                    result = None
                    self._on_error(slot.frame_id)
                self._tail += 1  # release the slot (its data was read)
                if result is None:
                    continue
                cost = clock() - t0
                self._costs_ns[self._n_costs % _COST_RING] = cost
                self._n_costs += 1
                self._publish(result)

    def _check_slot(self, slot: _Slot) -> ValidationResult:
        lengths = slot.bone_lengths if slot.has_lengths else self._cal_lengths
        return self._validate(
            slot.frame_id,
            slot.t_ns,
            slot.root_pos,
            slot.world_from_bone_quat,
            slot.rest_from_bone_quat,
            slot.joint_centres,
            lengths,
        )

    def _validate(
        self,
        frame_id: int,
        t_ns: int,
        root_pos: F64Array,
        wfb: F64Array,
        pfb: F64Array,
        joints: F64Array,
        lengths: F64Array,
        pooled: bool = True,
    ) -> ValidationResult:
        ck = self._checker
        flags = ck.check(frame_id, t_ns, root_pos, wfb, pfb, joints, lengths)
        if pooled:  # the thread: fill the next pooled result in place
            pool = self._pool
            r = pool[self._next_pool]
            self._next_pool = (self._next_pool + 1) % len(pool)
        else:  # a synchronous caller keeps what it gets
            r = ValidationResult(
                0, 0, 0, 0, ck.bone_bits.copy(), np.zeros(N_CHECKS, np.float32)
            )
        r.frame_id, r.t_ns, r.validated_ns = frame_id, t_ns, time.monotonic_ns()
        r.frame_flags = flags
        np.copyto(r.bone_flags, ck.bone_bits)
        np.copyto(r.values, ck.values, casting="same_kind")
        return r

    def _publish(self, result: ValidationResult) -> None:
        flags = result.frame_flags
        if flags:
            for k, bit in enumerate(CHECK_BITS):
                if flags & bit:
                    self.flagged[k] += 1
        dq = self._results
        if len(dq) == dq.maxlen:
            self.results_lost += 1
        dq.append(result)
        self.validated += 1

    def _on_error(self, frame_id: int) -> None:
        self.errors += 1
        now = time.monotonic()
        if now - self._last_error_log >= 10.0:
            self._last_error_log = now
            logger.exception(
                "validator: check of frame %d failed (%d errors so far)",
                frame_id,
                self.errors,
            )

    def _warm_up(self) -> None:
        """Compile / load the kernels now (not on the first live frame)."""
        skel = self.vm.skeleton
        pfb = np.zeros((self.n_bones, 4))
        pfb[:, 0] = 1.0
        wfb = np.ascontiguousarray(skel.rest_world_from_bone_quat, dtype=np.float64)
        joints = np.zeros((self.n_joints, 3))
        root_pos = np.ascontiguousarray(skel.rest_origin_world[self._tables.root])
        ck = self._checker
        for i in range(2):
            ck.check(i, i, root_pos, wfb, pfb, joints, self._cal_lengths)
        ck.reset()

    # ---- synchronous use (tests, benchmarks, offline) -------------------------------

    def check_frame(
        self,
        frame_id: int,
        t_ns: int,
        root_pos: F64Array,
        world_from_bone_quat: F64Array,
        rest_from_bone_quat: F64Array,
        joint_centres: F64Array,
        bone_lengths: F64Array | None = None,
    ) -> ValidationResult:
        """Check one frame on the calling thread (same state and code as the thread).

        Only while the thread is not running (it owns the state then). Arguments as
        :meth:`submit`; the result is not queued and counts nowhere.

        Raises:
            RuntimeError: the thread is running.
        """
        if self.running:
            raise RuntimeError("check_frame while the validator thread runs")
        lengths = self._cal_lengths if bone_lengths is None else bone_lengths
        return self._validate(
            frame_id,
            t_ns,
            np.ascontiguousarray(root_pos, dtype=np.float64),
            np.ascontiguousarray(world_from_bone_quat, dtype=np.float64),
            np.ascontiguousarray(rest_from_bone_quat, dtype=np.float64),
            np.ascontiguousarray(joint_centres, dtype=np.float64),
            np.ascontiguousarray(lengths, dtype=np.float64),
            pooled=False,
        )

    def reset_history(self) -> None:
        """Forget speed and support history (synchronous use, thread not running)."""
        self._checker.reset()

    # ---- counters -------------------------------------------------------------------

    def cost_us(self) -> tuple[float, float]:
        """(p50, p99) per-frame check cost over the last 1024 frames, µs (NaN: none)."""
        n = min(self._n_costs, _COST_RING)
        if n == 0:
            return math.nan, math.nan
        costs = self._costs_ns[:n] / 1e3
        p50, p99 = np.percentile(costs, [50.0, 99.0])
        return float(p50), float(p99)

    def counters(self) -> dict[str, Any]:
        """The counters as a JSON-ready dict."""
        p50, p99 = self.cost_us()
        return {
            "submitted": self.submitted,
            "validated": self.validated,
            "dropped": self.dropped,
            "errors": self.errors,
            "results_lost": self.results_lost,
            "flagged": dict(zip(ps.VALIDATION_CHECKS, self.flagged, strict=True)),
            "check_us_p50": None if math.isnan(p50) else round(p50, 1),
            "check_us_p99": None if math.isnan(p99) else round(p99, 1),
        }

    def status(self) -> dict[str, Any]:
        """``ctl status``'s ``validate`` entry: counters, ring, model, thresholds."""
        return {
            **self.counters(),
            "running": self.running,
            "pending": self.pending,
            "queue_size": self.queue_size,
            "rate_hz": self.rate_hz,
            "model": self.vm.digest[:12],
            "body_mass_kg": self.vm.body_mass_kg,
            "thresholds": dict(self.thresholds),
        }
