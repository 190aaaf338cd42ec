"""The live validator's compiled kernel: one call checks one posed frame against its
thresholds (qpos write, then every check of :mod:`retargetd.daemon.validate.live`'s
list from MuJoCo's kinematics and contacts), with its table layouts and bit
constants (numba freezes module globals at compile time)."""

from __future__ import annotations

import math

import numpy as np

from retargetd.daemon.compiled import kernel
from retargetd.protocols import pose_stream as ps

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

# Per-bone float table columns (``Tables.bone_f``).
_C_LEN, _C_OFF = 0, 1  # model length; offset in the parent's bone frame (3)
_C_TW, _C_SAG, _C_FRO, _C_CONE = 4, 6, 8, 9  # limits, degrees (lo, hi) / max; NaN none
_C_LEFT, _C_FWD = 10, 13  # performer's left / forward in the bone's neutral frame (3)
_C_REF = 16  # neutral_from_rest (4, w x y z): the limits apply to it * rest_from_bone
_N_BONE_F = 20
# Per-bone int table columns (``Tables.bone_i``).
_I_PARENT, _I_BODY, _I_SITE, _I_LIMITED = 0, 1, 2, 3
# Parameter vector (``Tables.params``).
(_P_RATE, _P_CONV, _P_FIT, _P_NORM, _P_LIM, _P_SELF, _P_FLOOR, _P_ROOT_V, _P_EFF_V,
 _P_AIR_S, _P_NEAR, _P_FLOOR_Z, _P_STILL_V, _P_STILL_N, _P_B0, _P_B1, _P_B2, _P_A1,
 _P_A2) = range(19)  # fmt: skip
_N_PARAMS = 19


# ---- compiled kernels --------------------------------------------------------------


@kernel
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


@kernel(inline="always")
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


@kernel(inline="always")
def _beyond(x: float, lo: float, hi: float) -> float:  # pragma: no cover - compiled
    return max(max(lo - x, x - hi), 0.0)


@kernel
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
        aw, ax, ay, az = (
            bone_f[b, _C_REF], bone_f[b, _C_REF + 1], bone_f[b, _C_REF + 2],
            bone_f[b, _C_REF + 3],
        )  # fmt: skip
        pw, px, py, pz = pfb[b, 0], pfb[b, 1], pfb[b, 2], pfb[b, 3]
        qw = aw * pw - ax * px - ay * py - az * pz
        qx = aw * px + ax * pw + ay * pz - az * py
        qy = aw * py - ax * pz + ay * pw + az * px
        qz = aw * pz + ax * py - ay * px + az * pw
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
