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

import mujoco
import numba
import numpy as np
from scipy.signal import butter

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.calibration import Calibration
from retargetd.daemon.body.rig import Rig
from retargetd.daemon.validate import dynamics as vd
from retargetd.daemon.validate.checks import THRESHOLDS, fit_pairs
from retargetd.daemon.validate.limits import JOINT_LIMITS_DEG
from retargetd.daemon.validate.model import (
    DEFAULT_BODY_MASS_KG,
    ValidationModel,
    build_model,
    capsule_radii,
    skeleton_from_calibration,
)
from retargetd.protocols import pose_stream as ps
from retargetd.protocols.frames import F32Array, F64Array, U8Array

logger = logging.getLogger(__name__)

N_CHECKS = len(ps.VALIDATION_CHECKS)
#: Frame bit of each check, in ``VALIDATION_CHECKS`` order.
CHECK_BITS = (
    ps.FRAME_V_CONVENTION,
    ps.FRAME_V_FIT,
    ps.FRAME_V_QUAT_NORM,
    ps.FRAME_V_LIMITS,
    ps.FRAME_V_SELF_PENETRATION,
    ps.FRAME_V_FLOOR_PENETRATION,
    ps.FRAME_V_SPEED,
    ps.FRAME_V_FLOATING,
)
_COST_RING = 1024  # recent per-frame check costs kept for p50 / p99
_STOP = -1

# Kernel constants (numba freezes module globals at compile time).
_F_CONV = ps.FRAME_V_CONVENTION
_F_FIT = ps.FRAME_V_FIT
_F_NORM = ps.FRAME_V_QUAT_NORM
_F_LIM = ps.FRAME_V_LIMITS
_F_SELF = ps.FRAME_V_SELF_PENETRATION
_F_FLOOR = ps.FRAME_V_FLOOR_PENETRATION
_F_SPEED = ps.FRAME_V_SPEED
_F_FLOAT = ps.FRAME_V_FLOATING
_B_LIM = ps.BONE_V_LIMIT
_B_PEN = ps.BONE_V_PENETRATION
_B_FIT = ps.BONE_V_FIT
_B_SPEED = ps.BONE_V_SPEED

# Per-bone float table columns (``_Tables.bone_f``).
_C_LEN, _C_OFF = 0, 1  # model length; offset in the parent's bone frame (3)
_C_TW, _C_SAG, _C_FRO, _C_CONE = 4, 6, 8, 9  # limits, degrees (lo, hi) / max; NaN none
_C_LEFT, _C_FWD = 10, 13  # performer's left / forward in the bone's rest frame (3)
_N_BONE_F = 16
# Per-bone int table columns (``_Tables.bone_i``).
_I_PARENT, _I_BODY, _I_SITE, _I_LIMITED = 0, 1, 2, 3
# Parameter vector (``_Tables.params``).
(_P_RATE, _P_CONV, _P_FIT, _P_NORM, _P_LIM, _P_SELF, _P_FLOOR, _P_ROOT_V, _P_EFF_V,
 _P_AIR_S, _P_NEAR, _P_FLOOR_Z, _P_STILL_V, _P_STILL_N, _P_B0, _P_B1, _P_B2, _P_A1,
 _P_A2) = range(19)  # fmt: skip
_N_PARAMS = 19


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
    parent_from_bone_quat: F64Array  # (B, 4)
    joint_centres: F64Array  # (J, 3)
    bone_lengths: F64Array  # (B,)


# ---- compiled kernels --------------------------------------------------------------


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _write_qpos(
    qpos: np.ndarray,
    root_pos: np.ndarray,
    wfb: np.ndarray,
    pfb: np.ndarray,
    root: int,
    root_adr: int,
    ball_adr: np.ndarray,
    ball_bones: np.ndarray,
) -> None:  # pragma: no cover - compiled
    # qpos = root position, root world_from_bone (w x y z), then each non-root bone's
    # parent_from_bone as its ball quaternion (validate.FrameChecker's layout).
    for k in range(3):
        qpos[root_adr + k] = root_pos[k]
    for k in range(4):
        qpos[root_adr + 3 + k] = wfb[root, k]
    for i in range(ball_bones.shape[0]):
        b = ball_bones[i]
        a = ball_adr[i]
        for k in range(4):
            qpos[a + k] = pfb[b, k]


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _rotate(
    q: np.ndarray, vx: float, vy: float, vz: float
) -> tuple[float, float, float]:  # pragma: no cover - compiled
    # rotations.quat_rotate: v' = v + w t + u x t, t = 2 (u x v).
    w, ux, uy, uz = q[0], q[1], q[2], q[3]
    tx = 2.0 * (uy * vz - uz * vy)
    ty = 2.0 * (uz * vx - ux * vz)
    tz = 2.0 * (ux * vy - uy * vx)
    return (
        vx + w * tx + (uy * tz - uz * ty),
        vy + w * ty + (uz * tx - ux * tz),
        vz + w * tz + (ux * ty - uy * tx),
    )


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _beyond(x: float, lo: float, hi: float) -> float:  # pragma: no cover - compiled
    return max(max(lo - x, x - hi), 0.0)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _check_frame(
    root_pos: np.ndarray,  # (3,)
    wfb: np.ndarray,  # (B, 4)
    pfb: np.ndarray,  # (B, 4)
    joints: np.ndarray,  # (J, 3)
    lengths: np.ndarray,  # (B,) streamed bone lengths
    xpos: np.ndarray,  # (nbody, 3) MuJoCo body origins
    site_xpos: np.ndarray,  # (nsite, 3) MuJoCo aim sites
    cdist: np.ndarray,  # (>= ncon,) contact distances
    cgeom: np.ndarray,  # (>= ncon, 2) contact geoms
    ncon: int,  # contacts this frame
    bone_f: np.ndarray,  # (B, 16) per-bone floats
    bone_i: np.ndarray,  # (B, 4) per-bone ints
    fit_j: np.ndarray,  # (K,) joint index of each fit pair
    fit_p: np.ndarray,  # (K,) skeleton point (b: origin, B + b: aim)
    eff: np.ndarray,  # (E,) end-effector bones (leaves)
    foot: np.ndarray,  # (P, 3) int: bone, at_aim, -
    foot_r: np.ndarray,  # (P,) capsule radius
    geom_bone: np.ndarray,  # (ngeom,) bone of each geom, -1 floor
    floor_geom: int,
    params: np.ndarray,  # (_N_PARAMS,)
    dt_frames: int,  # frames since the previous validated frame; 0 = no history
    origins: np.ndarray,  # (B, 3) scratch: streamed skeleton origins
    aims: np.ndarray,  # (B, 3) scratch: streamed skeleton aims
    prev: np.ndarray,  # (1 + E, 3) state: previous root and effector aims
    filt: np.ndarray,  # (P, 3, 3) state: filter z0, z1, previous output
    slow_run: np.ndarray,  # (P,) state: frames the filtered speed stayed slow
    airborne: np.ndarray,  # (1,) state: unsupported frames so far
    values: np.ndarray,  # (8,) out
    bone_bits: np.ndarray,  # (B,) uint8 out
) -> int:  # pragma: no cover - compiled
    n_bones = wfb.shape[0]
    rate = params[_P_RATE]
    for b in range(n_bones):
        bone_bits[b] = 0
    flags = 0

    # Streamed skeleton (validate.pose_skeleton, offsets scaled as
    # validate_model.skeleton_from_arrays): origin_b = origin_p + wfb_p . offset_b,
    # aim_b = origin_b + wfb_b . (0, L_b, 0).
    for b in range(n_bones):
        p = bone_i[b, _I_PARENT]
        if p < 0:
            origins[b, 0] = root_pos[0]
            origins[b, 1] = root_pos[1]
            origins[b, 2] = root_pos[2]
        else:
            s = lengths[p] / bone_f[p, _C_LEN]
            ox, oy, oz = _rotate(
                wfb[p],
                bone_f[b, _C_OFF] * s,
                bone_f[b, _C_OFF + 1] * s,
                bone_f[b, _C_OFF + 2] * s,
            )
            origins[b, 0] = origins[p, 0] + ox
            origins[b, 1] = origins[p, 1] + oy
            origins[b, 2] = origins[p, 2] + oz
        ax, ay, az = _rotate(wfb[b], 0.0, lengths[b], 0.0)
        aims[b, 0] = origins[b, 0] + ax
        aims[b, 1] = origins[b, 1] + ay
        aims[b, 2] = origins[b, 2] + az

    # Convention: model body origins / aim sites vs the streamed skeleton.
    worst = 0.0
    for b in range(n_bones):
        body = bone_i[b, _I_BODY]
        site = bone_i[b, _I_SITE]
        d0 = xpos[body, 0] - origins[b, 0]
        d1 = xpos[body, 1] - origins[b, 1]
        d2 = xpos[body, 2] - origins[b, 2]
        worst = max(worst, d0 * d0 + d1 * d1 + d2 * d2)
        d0 = site_xpos[site, 0] - aims[b, 0]
        d1 = site_xpos[site, 1] - aims[b, 1]
        d2 = site_xpos[site, 2] - aims[b, 2]
        worst = max(worst, d0 * d0 + d1 * d1 + d2 * d2)
    values[0] = 1e3 * math.sqrt(worst)
    if values[0] > params[_P_CONV]:
        flags |= _F_CONV

    # Fit: skeleton points vs solved joint centres (NaN = occluded, skipped).
    fit_max = -1.0
    for k in range(fit_j.shape[0]):
        j = fit_j[k]
        pt = fit_p[k]
        src = origins if pt < n_bones else aims
        b = pt if pt < n_bones else pt - n_bones
        d0 = src[b, 0] - joints[j, 0]
        d1 = src[b, 1] - joints[j, 1]
        d2 = src[b, 2] - joints[j, 2]
        d = 1e3 * math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        if d == d:  # finite (not NaN)
            fit_max = max(fit_max, d)
            if d > params[_P_FIT]:
                bone_bits[b] |= _B_FIT
    values[1] = fit_max if fit_max >= 0.0 else np.nan
    if fit_max > params[_P_FIT]:
        flags |= _F_FIT

    # Quaternion norms.
    worst = 0.0
    for b in range(n_bones):
        n1 = math.sqrt(
            wfb[b, 0] * wfb[b, 0]
            + wfb[b, 1] * wfb[b, 1]
            + wfb[b, 2] * wfb[b, 2]
            + wfb[b, 3] * wfb[b, 3]
        )
        n2 = math.sqrt(
            pfb[b, 0] * pfb[b, 0]
            + pfb[b, 1] * pfb[b, 1]
            + pfb[b, 2] * pfb[b, 2]
            + pfb[b, 3] * pfb[b, 3]
        )
        worst = max(worst, abs(n1 - 1.0), abs(n2 - 1.0))
    values[2] = worst
    if worst > params[_P_NORM]:
        flags |= _F_NORM

    # Limits: validate_limits.swing_twist / limit_violation_deg, one bone at a time.
    to_deg = 180.0 / math.pi
    worst = 0.0
    for b in range(n_bones):
        if bone_i[b, _I_LIMITED] == 0:
            continue
        qw, qx, qy, qz = pfb[b, 0], pfb[b, 1], pfb[b, 2], pfb[b, 3]
        tw = 2.0 * math.atan2(qy, qw) + math.pi
        tw = tw - 2.0 * math.pi * math.floor(tw / (2.0 * math.pi)) - math.pi
        c = math.cos(0.5 * tw)
        s = math.sin(0.5 * tw)
        # swing = q * conj(twist), conj(twist) = (c, 0, -s, 0)
        sw = qw * c + qy * s
        sx = qx * c + qz * s
        sy = qy * c - qw * s
        sz = qz * c - qx * s
        if sw < 0.0:
            sw, sx, sy, sz = -sw, -sx, -sy, -sz
        sin_half = math.sqrt(sx * sx + sy * sy + sz * sz)
        angle = 2.0 * math.atan2(sin_half, abs(sw))
        if sin_half > 1e-300:
            rx = sx / sin_half * angle * to_deg
            ry = sy / sin_half * angle * to_deg
            rz = sz / sin_half * angle * to_deg
        else:
            rx = angle * to_deg
            ry = 0.0
            rz = 0.0
        v = _beyond(tw * to_deg, bone_f[b, _C_TW], bone_f[b, _C_TW + 1])
        lo = bone_f[b, _C_SAG]
        if lo == lo:
            sag = (
                rx * bone_f[b, _C_LEFT]
                + ry * bone_f[b, _C_LEFT + 1]
                + rz * bone_f[b, _C_LEFT + 2]
            )
            v = max(v, _beyond(sag, lo, bone_f[b, _C_SAG + 1]))
        hi = bone_f[b, _C_FRO]
        if hi == hi:
            fro = (
                rx * bone_f[b, _C_FWD]
                + ry * bone_f[b, _C_FWD + 1]
                + rz * bone_f[b, _C_FWD + 2]
            )
            v = max(v, _beyond(fro, -hi, hi))
        hi = bone_f[b, _C_CONE]
        if hi == hi:
            v = max(v, _beyond(math.sqrt(rx * rx + ry * ry + rz * rz), 0.0, hi))
        if v > params[_P_LIM]:
            bone_bits[b] |= _B_LIM
        worst = max(worst, v)
    values[3] = worst
    if worst > params[_P_LIM]:
        flags |= _F_LIM

    # Penetration: every contact; the floor or segment/segment.
    self_d = 0.0
    floor_d = 0.0
    for k in range(ncon):
        g0 = cgeom[k, 0]
        g1 = cgeom[k, 1]
        depth = -cdist[k]
        if g0 == floor_geom or g1 == floor_geom:
            floor_d = max(floor_d, depth)
            other = geom_bone[g1] if g0 == floor_geom else geom_bone[g0]
            if 1e3 * depth > params[_P_FLOOR] and other >= 0:
                bone_bits[other] |= _B_PEN
        else:
            self_d = max(self_d, depth)
            if 1e3 * depth > params[_P_SELF]:
                if geom_bone[g0] >= 0:
                    bone_bits[geom_bone[g0]] |= _B_PEN
                if geom_bone[g1] >= 0:
                    bone_bits[geom_bone[g1]] |= _B_PEN
    values[4] = 1e3 * self_d
    values[5] = 1e3 * floor_d
    if values[4] > params[_P_SELF]:
        flags |= _F_SELF
    if values[5] > params[_P_FLOOR]:
        flags |= _F_FLOOR

    # Speed: root and end effectors, backward difference over dt_frames.
    root = 0
    for b in range(n_bones):
        if bone_i[b, _I_PARENT] < 0:
            root = b
    top = 0.0
    if dt_frames > 0:
        per_s = rate / dt_frames
        d0 = root_pos[0] - prev[0, 0]
        d1 = root_pos[1] - prev[0, 1]
        d2 = root_pos[2] - prev[0, 2]
        v = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2) * per_s
        top = v
        if v > params[_P_ROOT_V]:
            flags |= _F_SPEED
            bone_bits[root] |= _B_SPEED
        for e in range(eff.shape[0]):
            b = eff[e]
            d0 = aims[b, 0] - prev[1 + e, 0]
            d1 = aims[b, 1] - prev[1 + e, 1]
            d2 = aims[b, 2] - prev[1 + e, 2]
            v = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2) * per_s
            top = max(top, v)
            if v > params[_P_EFF_V]:
                flags |= _F_SPEED
                bone_bits[b] |= _B_SPEED
    values[6] = top
    for k in range(3):
        prev[0, k] = root_pos[k]
    for e in range(eff.shape[0]):
        for k in range(3):
            prev[1 + e, k] = aims[eff[e], k]

    # Floating: foot support (near the floor, or stationary so far), causal.
    b0, b1, b2 = params[_P_B0], params[_P_B1], params[_P_B2]
    a1, a2 = params[_P_A1], params[_P_A2]
    supported = foot.shape[0] == 0
    for p in range(foot.shape[0]):
        b = foot[p, 0]
        src = aims if foot[p, 1] else origins
        near = src[b, 2] - foot_r[p] - params[_P_FLOOR_Z] < params[_P_NEAR]
        if dt_frames == 0:
            # No history: the filter starts in its steady state at this point.
            for k in range(3):
                x = src[b, k] - (foot_r[p] if k == 2 else 0.0)
                filt[p, k, 1] = (b2 - a2) * x
                filt[p, k, 0] = (b1 - a1) * x + filt[p, k, 1]
                filt[p, k, 2] = x
            slow_run[p] = 0.0
        else:
            sq = 0.0
            for k in range(3):
                x = src[b, k] - (foot_r[p] if k == 2 else 0.0)
                # Direct form II transposed (scipy.signal.lfilter).
                y = b0 * x + filt[p, k, 0]
                filt[p, k, 0] = b1 * x - a1 * y + filt[p, k, 1]
                filt[p, k, 1] = b2 * x - a2 * y
                d = y - filt[p, k, 2]
                sq += d * d
                filt[p, k, 2] = y
            if math.sqrt(sq) * rate / dt_frames < params[_P_STILL_V]:
                slow_run[p] += dt_frames
            else:
                slow_run[p] = 0.0
        if near or slow_run[p] >= params[_P_STILL_N]:
            supported = True
    if supported:
        airborne[0] = 0.0
    else:
        airborne[0] += dt_frames if dt_frames > 0 else 1
    values[7] = airborne[0] / rate
    if values[7] > params[_P_AIR_S]:
        flags |= _F_FLOAT
    return flags


# ---- per-frame checker (validator thread) ------------------------------------------


class _Tables:
    """Everything the kernels need, resolved once from the model."""

    def __init__(
        self, vm: ValidationModel, rig: Rig, th: dict[str, float], rate_hz: float
    ) -> None:
        skel = vm.skeleton
        n_bones = len(skel.bone_names)
        parents = np.asarray(skel.bone_parents, dtype=np.int64)
        self.root = int(np.flatnonzero(parents < 0)[0])
        self.root_adr = int(vm.model.jnt_qposadr[0])  # the free joint comes first
        self.ball_adr = np.ascontiguousarray(vm.ball_qpos_idx[:, 0], dtype=np.int64)
        self.ball_bones = np.ascontiguousarray(vm.ball_bones, dtype=np.int64)
        bone_f = np.full((n_bones, _N_BONE_F), np.nan)
        bone_i = np.zeros((n_bones, 4), dtype=np.int64)
        bone_f[:, _C_LEN] = skel.bone_lengths
        bone_f[:, _C_OFF : _C_OFF + 3] = skel.offset_parent
        bone_i[:, _I_PARENT] = parents
        bone_i[:, _I_BODY] = vm.body_ids
        bone_i[:, _I_SITE] = vm.site_ids
        forward_world = np.cross(skel.left_world, [0.0, 0.0, 1.0])
        for b, kind in enumerate(skel.bone_kinds):
            lim = JOINT_LIMITS_DEG.get(kind)
            if lim is None or parents[b] < 0:
                continue
            bone_i[b, _I_LIMITED] = 1
            bone_from_world = rot.quat_conj(skel.rest_world_from_bone_quat[b])
            bone_f[b, _C_TW : _C_TW + 2] = lim.twist
            if lim.sagittal is not None:
                bone_f[b, _C_SAG : _C_SAG + 2] = lim.sagittal
            if lim.frontal is not None:
                bone_f[b, _C_FRO] = lim.frontal
            if lim.cone is not None:
                bone_f[b, _C_CONE] = lim.cone
            bone_f[b, _C_LEFT : _C_LEFT + 3] = rot.quat_rotate(
                bone_from_world, skel.left_world
            )
            bone_f[b, _C_FWD : _C_FWD + 3] = rot.quat_rotate(
                bone_from_world, forward_world
            )
        self.bone_f, self.bone_i = bone_f, bone_i
        self.fit_j, self.fit_p = fit_pairs(rig, tuple(rig.joints))
        self.n_joints = len(rig.joints)
        leaves = [b for b in range(n_bones) if b not in set(skel.bone_parents)]
        self.eff = np.asarray(leaves, dtype=np.int64)
        zeros = np.zeros((1, n_bones, 3))
        _, feet, at_aim = vd.foot_points(skel, zeros, zeros)
        self.foot = np.zeros((len(feet), 3), dtype=np.int64)
        self.foot[:, 0] = feet
        self.foot[:, 1] = at_aim
        self.foot_r = np.ascontiguousarray(capsule_radii(skel)[feet])
        self.geom_bone = np.ascontiguousarray(vm.geom_bone, dtype=np.int64)
        self.floor_geom = int(vm.floor_geom)
        contact = vd.CONTACT
        wn = contact["cutoff_hz"] / (0.5 * rate_hz)
        if wn < 1.0:
            bq, aq = butter(2, wn)
        else:  # the offline lowpass leaves data unfiltered too
            bq, aq = np.array([1.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0])
        p = np.zeros(_N_PARAMS)
        p[_P_RATE] = rate_hz
        p[_P_CONV] = th["convention_mm"]
        p[_P_FIT] = th["fit_max_mm"]
        p[_P_NORM] = th["quat_norm"]
        p[_P_LIM] = th["limit_deg"]
        p[_P_SELF] = th["self_penetration_mm"]
        p[_P_FLOOR] = th["floor_penetration_mm"]
        p[_P_ROOT_V] = th["root_speed_m_s"]
        p[_P_EFF_V] = th["effector_speed_m_s"]
        p[_P_AIR_S] = th["max_airborne_s"]
        p[_P_NEAR] = 1e-3 * th["airborne_clearance_mm"]
        p[_P_FLOOR_Z] = vm.floor_z
        p[_P_STILL_V] = contact["still_speed_m_s"]
        p[_P_STILL_N] = max(1, round(contact["still_min_s"] * rate_hz))
        p[_P_B0 : _P_B2 + 1] = bq / aq[0]
        p[_P_A1 : _P_A2 + 1] = aq[1:] / aq[0]
        self.params = p
        for arr in (self.bone_f, self.bone_i, self.eff, self.foot, self.params):
            arr.flags.writeable = False


class _Checker:
    """One MjData and the causal state; used by one thread at a time."""

    def __init__(
        self, vm: ValidationModel, tables: _Tables, rate_hz: float, max_gap_s: float
    ) -> None:
        self.vm, self.t = vm, tables
        n_bones = len(vm.skeleton.bone_names)
        self.model = vm.model
        self.data = mujoco.MjData(vm.model)
        # Views into MjData's buffers, taken once (an attribute read builds a view).
        self.qpos = self.data.qpos
        self.xpos = self.data.xpos
        self.site_xpos = self.data.site_xpos
        # Contacts copied into contiguous buffers (MuJoCo's fields are strided views,
        # one mjContact apart): one kernel specialisation, grown when needed.
        self.cdist = np.zeros(64)
        self.cgeom = np.zeros((64, 2), dtype=np.int32)
        self.origins = np.zeros((n_bones, 3))
        self.aims = np.zeros((n_bones, 3))
        self.prev = np.zeros((1 + tables.eff.shape[0], 3))
        self.filt = np.zeros((tables.foot.shape[0], 3, 3))
        self.slow_run = np.zeros(tables.foot.shape[0])
        self.airborne = np.zeros(1)
        self.values = np.zeros(N_CHECKS)
        self.bone_bits = np.zeros(n_bones, dtype=np.uint8)
        self.rate_hz = rate_hz
        self.max_gap_frames = max(1, math.floor(max_gap_s * rate_hz))
        self.max_gap_ns = int(max_gap_s * 1e9)
        self.has_prev = False
        self.prev_id = 0
        self.prev_t_ns = 0

    def reset(self) -> None:
        """Forget the history (speed, support)."""
        self.has_prev = False

    def check(
        self,
        frame_id: int,
        t_ns: int,
        root_pos: F64Array,
        wfb: F64Array,
        pfb: F64Array,
        joints: F64Array,
        lengths: F64Array,
    ) -> int:
        """Check one frame; values in ``self.values``, bone bits in ``self.bone_bits``.

        Returns:
            The frame bits (8-15).
        """
        t = self.t
        dt = t_ns - self.prev_t_ns
        if frame_id >= 0 and self.prev_id >= 0:
            gap = frame_id - self.prev_id
        else:  # an unnumbered source (frame_id -1): frames counted from receive time
            gap = max(1, round(dt * self.rate_hz * 1e-9))
        recent = self.has_prev and 0 < gap <= self.max_gap_frames
        dt_frames = gap if recent and 0 <= dt <= self.max_gap_ns else 0
        _write_qpos(
            self.qpos, root_pos, wfb, pfb, t.root, t.root_adr, t.ball_adr, t.ball_bones
        )
        m, d = self.model, self.data
        mujoco.mj_kinematics(m, d)
        mujoco.mj_collision(m, d)
        ncon = d.ncon
        if ncon:
            if ncon > self.cdist.shape[0]:  # rare: grow (allocates)
                self.cdist = np.zeros(2 * ncon)
                self.cgeom = np.zeros((2 * ncon, 2), dtype=np.int32)
            contact = d.contact
            self.cdist[:ncon] = contact.dist
            self.cgeom[:ncon] = contact.geom
        flags: int = _check_frame(
            root_pos,
            wfb,
            pfb,
            joints,
            lengths,
            self.xpos,
            self.site_xpos,
            self.cdist,
            self.cgeom,
            ncon,
            t.bone_f,
            t.bone_i,
            t.fit_j,
            t.fit_p,
            t.eff,
            t.foot,
            t.foot_r,
            t.geom_bone,
            t.floor_geom,
            t.params,
            dt_frames,
            self.origins,
            self.aims,
            self.prev,
            self.filt,
            self.slow_run,
            self.airborne,
            self.values,
            self.bone_bits,
        )
        self.has_prev = True
        self.prev_id = frame_id
        self.prev_t_ns = t_ns
        return flags


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
        self._tables = _Tables(self.vm, rig, self.thresholds, self.rate_hz)
        self.n_joints = self._tables.n_joints
        self._cal_lengths = np.array(skel.bone_lengths, dtype=np.float64)
        self._cal_lengths.flags.writeable = False
        self._checker = _Checker(self.vm, self._tables, self.rate_hz, max_gap_s)
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
        parent_from_bone_quat: F64Array,
        joint_centres: F64Array,
        bone_lengths: F64Array | None = None,
    ) -> bool:
        """Copy one frame into the ring for the validator thread; never waits.

        Args:
            frame_id: the frame's number (consecutive frames differ by 1).
            t_ns: its receive time, ``time.monotonic_ns()``.
            root_pos: (3,) float64, metres, world.
            world_from_bone_quat: (B, 4) float64, w x y z.
            parent_from_bone_quat: (B, 4) float64, w x y z, relative to calibration.
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
        np.copyto(slot.parent_from_bone_quat, parent_from_bone_quat)
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
        """Results finished since the last call, oldest first (never waits; an empty
        tuple, not a new list, when there are none)."""
        dq = self._results
        if not dq:
            return ()
        out = []
        while dq:
            out.append(dq.popleft())
        return out

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
            slot.parent_from_bone_quat,
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
    ) -> ValidationResult:
        ck = self._checker
        flags = ck.check(frame_id, t_ns, root_pos, wfb, pfb, joints, lengths)
        return ValidationResult(
            frame_id,
            t_ns,
            time.monotonic_ns(),
            flags,
            ck.bone_bits.copy(),
            ck.values.astype(np.float32),
        )

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
        parent_from_bone_quat: F64Array,
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
            np.ascontiguousarray(parent_from_bone_quat, dtype=np.float64),
            np.ascontiguousarray(joint_centres, dtype=np.float64),
            np.ascontiguousarray(lengths, dtype=np.float64),
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
