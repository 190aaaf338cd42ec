"""Foot-contact inference and the ghost force (offline dynamics checks).

Contact inference (:func:`infer_contacts`). A foot point (the bottom of a foot or toes
capsule at the bone's origin and at its aim) supports the body when it is

* near the floor: within ``near_floor_m`` of the calibrated ground height, or
* stationary at any height: its (low-passed) speed stays below ``still_speed_m_s`` for
  at least ``still_min_s``, which is a box, a step, a stage riser. A foot at the apex of
  a jump or a swing is below that speed only for a few hundredths of a second. Slow
  runs split by a gap of at most ``still_gap_s`` are one run (a stance heel rocking
  over: the PiG walk's heel stance reads 0.19 + 0.18 s of slow frames); a run that
  touches the first or last frame (its length unknown) needs only ``edge_min_s``; or
* on a surface where a foot stood: within ``surface_radius_m`` horizontally of the
  spot where a foot point was stationary (a still run's mean position) and between
  ``surface_below_m`` below and ``near_floor_m`` above its height, which is what "near
  the floor" is on a platform: a heel striking it, a foot landing on it, a foot turning
  or sliding on it (the ballet's pivots move the toe point at ~1 m/s). The ghost force
  uses these contacts; the floating check counts only the direct evidence above (the
  floor, a still foot), as the live validator does frame by frame.

So a performer standing on a platform, walking or dancing on it, or stepping down from
it is supported, one whose feet move in the air is not: the PiG walk, the MOTEK ballet
and the tennis serve raised 35 cm (on a riser) infer the same support as on the floor
(tests). Free flight (a jump) needs no contact: its inverse-dynamics root wrench is ~0
(ballistic), so it leaves no ghost force either. Known limit: a performer hanging in
the air with perfectly still feet is indistinguishable, from the feet alone, from one
standing on a riser, and the surfaces are found over the whole take (offline).

Ghost force (:func:`ghost_force`), after the reference recipe (``mujoco.md``):

1. qpos per frame (root position, root quaternion, ball quaternions; quaternion signs
   made continuous), zero-phase Butterworth low-pass (2nd order, forward-backward,
   ``cutoff_hz`` ~6 Hz), quaternions renormalised;
2. qvel by a central ``mj_differentiatePos``, qacc by the second difference of
   ``mj_differentiatePos`` (root angular parts in the root body frame);
3. ``mj_inverse`` on a copy of the model with ``mjDSBL_CONSTRAINT`` (no floor contact
   forces: recorded floor penetration would turn into huge forces); the root wrench is
   ``qfrc_inverse[:6]``;
4. explained by non-negative forces in linearised friction cones (4-edge pyramids,
   normal +Z, ``mu``) at the contact points of the frame, mapped onto the root dofs by
   their Jacobians (``J[:, :6]^T f``, so the torque frame is MuJoCo's own): NNLS;
5. the ghost force is the norm of what is left, force rows in newtons and torque rows
   divided by ``moment_arm_m``, in body weights (``m g``). Frames within ``trim_s`` of
   either end (filter transients) are NaN.
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass

import mujoco
import numpy as np
from scipy.optimize import nnls
from scipy.signal import butter, filtfilt
from scipy.spatial import cKDTree

from retargetd.daemon import rotations as rot
from retargetd.daemon.validate.model import (
    FOOT_KINDS,
    Skeleton,
    ValidationModel,
    capsule_radii,
)
from retargetd.protocols.frames import F64Array

#: Contact inference and ghost-force parameters (SI). See the module docstring.
CONTACT: dict[str, float] = {
    # Capsule bottom within this of the floor: in contact (the floating check's
    # historical clearance; heel/toe clearance in swing is ~1-2 cm, but a foot that
    # close may push, so this errs towards "supported").
    "near_floor_m": 0.10,
    # Stationary: low-passed speed below this for at least still_min_s. Stance-phase
    # heel/toe speeds are < 0.1 m/s; a jump apex is below 0.2 m/s for ~0.04 s.
    "still_speed_m_s": 0.20,
    "still_min_s": 0.20,
    # Slow runs split by at most this are one run (a heel rocking over in stance).
    "still_gap_s": 0.05,
    # A slow run touching the first or last frame counts from this long.
    "edge_min_s": 0.05,
    # A surface where a foot stood (offline: over the whole take): within this radius
    # horizontally of the still run's mean position (~a foot length: a pivot, a heel
    # strike at the spot it then stands on), from surface_below_m below its height
    # to near_floor_m above.
    "surface_radius_m": 0.30,
    "surface_below_m": 0.03,
    # Low-pass for the speed (zero-phase), Hz.
    "cutoff_hz": 6.0,
}

GHOST: dict[str, float] = {
    "cutoff_hz": 6.0,  # Winter's ~6 Hz for gait kinematics
    "trim_s": 0.10,  # filter transients at the ends (NaN)
    "mu": 1.0,  # friction coefficient (rubber on floor ~0.8-1; generous)
    "moment_arm_m": 1.0,  # torque rows / this -> newtons
}

GRAVITY = 9.81


def foot_points(
    skel: Skeleton, origins: F64Array, aims: F64Array
) -> tuple[F64Array, np.ndarray, np.ndarray]:
    """Bottom points of the foot capsules.

    Returns:
        points (T, P, 3) (capsule bottom under each foot bone's origin and aim),
        bones (P,) bone index of each point, at_aim (P,) bool (aim site vs origin).
    """
    feet = [b for b, k in enumerate(skel.bone_kinds) if k in FOOT_KINDS]
    r = capsule_radii(skel)
    bones = np.array(feet + feet, dtype=np.int64)
    at_aim = np.array([False] * len(feet) + [True] * len(feet))
    pts = np.concatenate([origins[:, feet], aims[:, feet]], axis=1).copy()
    pts[..., 2] -= r[bones]
    return pts, bones, at_aim


def lowpass(x: F64Array, rate_hz: float, cutoff_hz: float, order: int = 2) -> F64Array:
    """Zero-phase Butterworth low-pass along axis 0 (unchanged if too short)."""
    wn = cutoff_hz / (0.5 * rate_hz)
    if wn >= 1.0:
        return x.copy()
    b, a = butter(order, wn)
    padlen = 3 * max(len(a), len(b))
    if x.shape[0] <= padlen:
        return x.copy()
    return filtfilt(b, a, x, axis=0)


def infer_contacts(
    points: F64Array,
    floor_z: float,
    rate_hz: float,
    params: dict[str, float] | None = None,
    *,
    surfaces: bool = True,
) -> np.ndarray:
    """(T, P) bool: point p supports the body at frame t (near the floor, stationary,
    or on a surface where a foot stood; module docstring).

    Args:
        points: (T, P, 3) foot points (:func:`foot_points`), metres, world.
        floor_z: the floor's height, metres.
        rate_hz: frame rate.
        params: overrides of :data:`CONTACT`.
        surfaces: also the surfaces where a foot stood (the ghost force's contacts);
            False: direct evidence only, near the floor or stationary (the floating
            check, as the live validator infers it frame by frame).
    """
    p = {**CONTACT, **(params or {})}
    n = points.shape[0]
    near = points[..., 2] - floor_z < p["near_floor_m"]
    if n < 3:
        return near
    smooth = lowpass(points, rate_hz, p["cutoff_hz"])
    speed = np.empty(points.shape[:2])
    speed[1:-1] = np.linalg.norm(smooth[2:] - smooth[:-2], axis=-1) * (0.5 * rate_hz)
    speed[0], speed[-1] = speed[1], speed[-2]
    slow = speed < p["still_speed_m_s"]
    min_frames = max(1, round(p["still_min_s"] * rate_hz))
    edge_frames = max(1, round(p["edge_min_s"] * rate_hz))
    gap_frames = round(p["still_gap_s"] * rate_hz)
    still = np.zeros_like(slow)
    spots: list[F64Array] = []  # (x, y, z) of each still run
    for j in range(slow.shape[1]):
        run = _close_gaps(slow[:, j], gap_frames)
        length = run_lengths(run)
        keep = length >= min_frames
        for end in (0, n - 1):  # a run at either end: its true length is unknown
            if run[end] and length[end] >= edge_frames:
                keep |= run & (np.abs(np.arange(n) - end) < length[end])
        still[:, j] = run & keep
        edges = np.flatnonzero(np.diff(np.concatenate([[0], still[:, j], [0]])))
        for start, stop in zip(edges[::2], edges[1::2], strict=True):
            seg = points[start:stop, j]
            spots.append(np.array([*seg[:, :2].mean(axis=0), np.median(seg[:, 2])]))
    if not surfaces:
        return near | still
    return near | still | _on_surface(points, np.asarray(spots), p)


def _close_gaps(mask: np.ndarray, max_gap: int) -> np.ndarray:
    """(T,) bool: ``mask`` with False gaps of at most ``max_gap`` frames filled."""
    out = mask.copy()
    idx = np.flatnonzero(mask)
    if max_gap <= 0 or idx.size < 2:
        return out
    gaps = np.diff(idx) - 1
    for k in np.flatnonzero((gaps > 0) & (gaps <= max_gap)):
        out[idx[k] + 1 : idx[k + 1]] = True
    return out


def _on_surface(points: F64Array, spots: F64Array, p: dict[str, float]) -> np.ndarray:
    """(T, P) bool: within a still spot's radius and height band (module docstring)."""
    out = np.zeros(points.shape[:2], dtype=bool)
    if spots.size == 0:
        return out
    flat = points.reshape(-1, 3)
    pairs = cKDTree(flat[:, :2]).sparse_distance_matrix(
        cKDTree(spots[:, :2]), p["surface_radius_m"], output_type="ndarray"
    )
    dz = flat[pairs["i"], 2] - spots[pairs["j"], 2]
    ok = (dz >= -p["surface_below_m"]) & (dz <= p["near_floor_m"])
    out.reshape(-1)[pairs["i"][ok]] = True
    return out


def run_lengths(mask: np.ndarray) -> F64Array:
    """(T,) length in frames of the run of True each frame belongs to (0 if False)."""
    out = np.zeros(mask.shape[0])
    if not mask.any():
        return out
    padded = np.concatenate([[False], mask, [False]])
    edges = np.flatnonzero(np.diff(padded.astype(np.int8)))
    for start, stop in zip(edges[::2], edges[1::2], strict=True):
        out[start:stop] = stop - start
    return out


def take_qpos(
    vm: ValidationModel,
    root_pos: F64Array,
    world_from_root_quat: F64Array,
    pfb: F64Array,
) -> F64Array:
    """(T, nq) qpos of a take (layout of ``validate.FrameChecker``)."""
    n = root_pos.shape[0]
    adr = int(vm.model.jnt_qposadr[0])
    qpos = np.tile(np.asarray(vm.model.qpos0, dtype=np.float64), (n, 1))
    qpos[:, adr : adr + 3] = root_pos
    qpos[:, adr + 3 : adr + 7] = world_from_root_quat
    qpos[:, vm.ball_qpos_idx.reshape(-1)] = pfb[:, vm.ball_bones].reshape(n, -1)
    return qpos


def _continuous_quats(q: F64Array) -> F64Array:
    """(T, K, 4) signs flipped so consecutive quaternions have a positive dot."""
    q = q.copy()
    dots = np.sum(q[1:] * q[:-1], axis=-1)
    flips = np.cumsum(dots < 0.0, axis=0) % 2
    q[1:][flips.astype(bool)] *= -1.0
    return q


@dataclass(slots=True)
class GhostForce:
    """Per-frame ghost force and what produced it."""

    ghost_bw: F64Array  # (T,) body weights, NaN in the trimmed ends
    root_force_bw: F64Array  # (T,) |inverse-dynamics root force| / m g
    contacts: np.ndarray  # (T, P) inferred contacts used
    seconds_per_frame: float


def ghost_force(
    vm: ValidationModel,
    root_pos: F64Array,
    world_from_root_quat: F64Array,
    pfb: F64Array,
    rate_hz: float,
    contacts: np.ndarray,
    params: dict[str, float] | None = None,
) -> GhostForce:
    """The root wrench inverse dynamics needs that the contacts cannot supply.

    Args:
        vm: the model.
        root_pos, world_from_root_quat, pfb: the take ((T, 3), (T, 4), (T, B, 4)).
        rate_hz: frame rate.
        contacts: (T, P) from :func:`infer_contacts` over :func:`foot_points`.
        params: overrides of :data:`GHOST`.
    """
    p = {**GHOST, **(params or {})}
    m0 = vm.model
    model = copy.copy(m0)
    model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONSTRAINT)
    data = mujoco.MjData(model)
    n = root_pos.shape[0]
    weight = vm.body_mass_kg * GRAVITY
    ghost = np.full(n, np.nan)
    root_f = np.full(n, np.nan)
    trim = max(1, round(p["trim_s"] * rate_hz))
    if n < 2 * trim + 3:
        return GhostForce(ghost, root_f, contacts, 0.0)

    qpos = take_qpos(vm, root_pos, world_from_root_quat, pfb)
    adr = int(m0.jnt_qposadr[0])
    quat_cols = [np.arange(adr + 3, adr + 7)]
    quat_cols += [row for row in vm.ball_qpos_idx]
    qi = np.stack(quat_cols)  # (K, 4)
    qpos[:, qi] = _continuous_quats(qpos[:, qi])
    qpos = lowpass(qpos, rate_hz, p["cutoff_hz"])
    qpos[:, qi] = rot.quat_normalize(qpos[:, qi])

    skel = vm.skeleton
    _, bones, at_aim = foot_points(
        skel,
        np.zeros((1, len(skel.bone_names), 3)),
        np.zeros((1, len(skel.bone_names), 3)),
    )
    radii = capsule_radii(skel)[bones]
    body_of_point = vm.body_ids[bones]
    site_of_point = vm.site_ids[bones]
    mu = p["mu"]
    cone = np.array(
        [[mu, 0.0, 1.0], [-mu, 0.0, 1.0], [0.0, mu, 1.0], [0.0, -mu, 1.0]]
    ).T  # (3, 4) edges of the friction pyramid
    scale = np.array([1.0, 1.0, 1.0, *([1.0 / p["moment_arm_m"]] * 3)]) / weight
    dt = 1.0 / rate_hz
    nv = model.nv
    v_prev = np.zeros(nv)
    v_next = np.zeros(nv)
    jacp = np.zeros((3, nv))
    point = np.zeros(3)
    t0 = time.perf_counter()
    for t in range(trim, n - trim):
        mujoco.mj_differentiatePos(model, v_prev, dt, qpos[t - 1], qpos[t])
        mujoco.mj_differentiatePos(model, v_next, dt, qpos[t], qpos[t + 1])
        data.qpos[:] = qpos[t]
        data.qvel[:] = 0.5 * (v_prev + v_next)
        data.qacc[:] = (v_next - v_prev) / dt
        mujoco.mj_inverse(model, data)
        b = data.qfrc_inverse[:6] * scale
        root_f[t] = float(np.linalg.norm(data.qfrc_inverse[:3])) / weight
        active = np.flatnonzero(contacts[t])
        if active.size == 0:
            ghost[t] = float(np.linalg.norm(b))
            continue
        cols = np.empty((6, 4 * active.size))
        for k, j in enumerate(active):
            if at_aim[j]:
                point[:] = data.site_xpos[site_of_point[j]]
            else:
                point[:] = data.xpos[body_of_point[j]]
            point[2] -= radii[j]
            mujoco.mj_jac(model, data, jacp, None, point, int(body_of_point[j]))
            cols[:, 4 * k : 4 * k + 4] = jacp[:, :6].T @ cone
        _, res = nnls(cols * scale[:, None], b)
        ghost[t] = float(res)
    per_frame = (time.perf_counter() - t0) / max(n - 2 * trim, 1)
    return GhostForce(ghost, root_f, contacts, per_frame)
