"""The rigid-skeleton fit's terms (numba): its parameter and statistics slots, small
quaternion helpers (exp and log of rotation vectors), forward kinematics, the soft
joint-limit penalty and the cost of the marker and regularization terms.

Used by :mod:`retargetd.daemon.body.fit_normal` (the normal equations) and
:mod:`retargetd.daemon.body.kernel_fit` (the Levenberg-Marquardt loop and the entry
points); the cost itself is described in ``kernel_fit``'s docstring.
"""

from __future__ import annotations

import math

import numpy as np

from retargetd.daemon.compiled import kernel, mat_from_unit_quat, qmul

# params (float64 array) slots (``solve_fit.FitParams``)
P_NOISE_M = 0  # marker noise sigma_m, metres
P_ALPHA_MAX = 1  # peak segment angular acceleration, rad/s^2
P_KAPPA_LIMIT = 2
P_KAPPA_HINGE = 3
P_CAUCHY_M = 4
P_GATE_M = 5
P_GATE_K = 6
P_LOST_FLOOR_M = 7  # a track is suspect above max(this, P_LOST_K x its level)
P_MAX_ITER = 8
P_TOL = 9
P_REJECT_FRAC = 10  # more markers rejected than this fraction: suspect
P_FTOL = 11
P_GATE_MEMORY = 12
P_ACC_MAX = 13  # peak linear acceleration of a root, m/s^2
P_LOST_K = 14
P_UNEXPLAINED_K = 15  # a frame is unexplained above max(gate, this x the level)
P_UNEXPLAINED_FRAC = 16  # ... or with more than this fraction rejected
P_LEVEL_TAU_S = 17  # time constant of the running residual level, seconds
P_PERSIST = 18  # seconds a marker stays rejected before a reseed is tried
P_JUMP_Z = 19  # a joint past max(this x its prediction's bound, P_JUMP_FLOOR_RAD)
P_JUMP_FLOOR_RAD = 20  # ... from its prediction is no motion a body makes
P_RESOLUTION_RAD = 21  # the hold: a joint angle's resolution (fit_observe)
P_VELOCITY_TAU_S = 22  # a hidden marker's velocity decays with this time constant
P_HOLD_STRAIGHT_RAD = 23  # the hold: a limb's hinge bent less reads the straight table
P_OMEGA_MAX = 24  # peak angular velocity of a joint (parent-relative), rad/s
P_OMEGA_ROOT = 25  # peak angular velocity of a root (its world rotation), rad/s
P_SPEED_MAX = 26  # peak speed of a root, m/s
N_PARAMS = 27

# per-frame scalars (the state's ``s[36]``)
C_GATE = 0  # this frame's gate, metres
C_SOLVES = 1  # linear solves this frame
C_MU = 2  # Levenberg-Marquardt damping carried between frames
C_DT = 3  # seconds since the last frame (set by the caller)
C_GAP = 4  # frames since the last explained frame (1: the last one)
C_LAM_ROT = 5  # this frame's continuity weights, m^2 / rad^2 and m^2 / m^2
C_LAM_TRANS = 6
C_LEVEL = 7  # the take's running inlier residual RMS, metres (0: none yet)
C_SINCE_TRY = 8  # frames since the last reseed attempt
C_LAST_RMS = 9  # the last explained, not suspect, frame's residual RMS, metres
N_SCALARS = 10

# stats (float64 array) slots
S_RMS = 0
S_REJECTED = 1
S_ITER = 2
S_RESEEDED = 3
S_COST = 4
S_SOLVES = 5
S_UNEXPLAINED = 6  # 1: the fit could not explain the markers; the pose is held
S_UNSEEN = 7  # 1: too few of the performer's markers seen; no pose
S_LEVEL = 8  # the running residual level after this frame, metres
N_STATS = 9

INF = 1e300

#: The regularization terms' values at a state, per bone (``reg_cost`` writes them:
#: s[65] for the current state, s[66] for the trial; ``fit_normal.build_normal``
#: reads the current state's instead of evaluating them again, since every build
#: follows the evaluation of the state it is built at): the continuity's rotation
#: vector (0:3), the prior's and the hold's charts (3:6, 6:9), the penalty residuals
#: (9:15) and 1 where they were evaluated, 0 where the joint is too far inside its
#: limits to have any (15).
R_CONT = 0
R_PRIOR = 3
R_HOLD = 6
R_PEN = 9
R_PEN_ON = 15
N_REG = 16

#: A joint's penalty row (``m[11]``, ``lim``): fit_model's limit columns (N_LIM of
#: them), then a "hinge_twist"'s twist axis in the bone's rest axes (3).
L_TWIST_AXIS = 10


@kernel
def qexp(vx: float, vy: float, vz: float) -> tuple[float, float, float, float]:
    th = math.sqrt(vx * vx + vy * vy + vz * vz)
    if th < 1e-12:
        w, s = 1.0, 0.5
    else:
        w, s = math.cos(0.5 * th), math.sin(0.5 * th) / th
    n = (
        math.sqrt(w * w + s * s * th * th)
        if th >= 1e-12
        else math.sqrt(1.0 + 0.25 * th * th)
    )
    return w / n, s * vx / n, s * vy / n, s * vz / n


@kernel
def qlog(w: float, x: float, y: float, z: float) -> tuple[float, float, float]:
    if w < 0.0:
        w, x, y, z = -w, -x, -y, -z
    s = math.sqrt(x * x + y * y + z * z)
    if s < 1e-12:
        return 2.0 * x, 2.0 * y, 2.0 * z
    k = 2.0 * math.atan2(s, w) / s
    return k * x, k * y, k * z


@kernel
def prior_chart(w: float, x: float, y: float, z: float) -> tuple[float, float, float]:
    # A joint's rotation r relative to its calibration pose in swing-twist
    # coordinates of the bone's rest axes: (swing about x, twist about +Y, swing about
    # z), r = swing * twist with the twist about +Y and the swing perpendicular to it
    # (the validator's split, validate.limits). Near identity these are the rotation
    # vector's components; the twist stays the twist however far the bone swings.
    if w < 0.0:
        w, x, y, z = -w, -x, -y, -z
    tw = 2.0 * math.atan2(y, w)
    h = 0.5 * tw
    sw, sx, sy, sz = qmul(w, x, y, z, math.cos(h), 0.0, -math.sin(h), 0.0)
    vx, _vy, vz = qlog(sw, sx, sy, sz)
    return vx, tw, vz


@kernel
def prior_cost(
    a: np.ndarray, q: np.ndarray, pb: np.ndarray, reg: np.ndarray, k0: int
) -> float:
    # 1/2 c^T P c, c the swing-twist coordinates of conj(a) q (a: the prior's
    # anchor, a parent_from_bone w x y z; q: the joint's; pb: (3, 3) m^2 / rad^2);
    # c kept in reg[k0:k0 + 3] (prior_normal's c0 at the same state).
    r = qmul(a[0], -a[1], -a[2], -a[3], q[0], q[1], q[2], q[3])
    c = prior_chart(r[0], r[1], r[2], r[3])
    reg[k0], reg[k0 + 1], reg[k0 + 2] = c[0], c[1], c[2]
    cost = 0.0
    for i in range(3):
        for j in range(3):
            cost += 0.5 * c[i] * pb[i, j] * c[j]
    return cost


@kernel
def prior_normal(
    a: np.ndarray, q: np.ndarray, pb: np.ndarray, wmb: np.ndarray,
    hb: np.ndarray, g: np.ndarray, rb: int, jac: np.ndarray, reg: np.ndarray,
    k0: int,
) -> None:  # fmt: skip
    # The prior's Gauss-Newton terms in the bone's world increments (block hb,
    # gradient g[rb:rb + 3]): the chart's numerical Jacobian in the bone's own
    # increments (jac rows 0-2), turned into world increments U = jac W^T (rows
    # 3-5), then H += U^T P U, g += U^T P c. wmb: the bone's world rotation matrix;
    # c at q: reg[k0:k0 + 3], as prior_cost left it at the same state.
    eps = 1e-6
    r = qmul(a[0], -a[1], -a[2], -a[3], q[0], q[1], q[2], q[3])
    c0 = (reg[k0], reg[k0 + 1], reg[k0 + 2])
    for c in range(3):
        e = qexp(eps if c == 0 else 0.0, eps if c == 1 else 0.0,
                  eps if c == 2 else 0.0)  # fmt: skip
        rp = qmul(r[0], r[1], r[2], r[3], e[0], e[1], e[2], e[3])
        c1 = prior_chart(rp[0], rp[1], rp[2], rp[3])
        for k in range(3):
            dk = (c1[k] - c0[k]) / eps
            jac[k, c] = dk if abs(dk) < 1e3 else 0.0  # (a twist wrapping through pi)
    for k in range(3):
        for i in range(3):
            jac[3 + k, i] = (
                jac[k, 0] * wmb[i, 0] + jac[k, 1] * wmb[i, 1] + jac[k, 2] * wmb[i, 2]
            )
    for k in range(3):
        pc = pb[k, 0] * c0[0] + pb[k, 1] * c0[1] + pb[k, 2] * c0[2]
        for i in range(3):
            g[rb + i] += jac[3 + k, i] * pc
    for i in range(3):
        for j in range(3):
            acc = 0.0
            for k in range(3):
                pu = pb[k, 0] * jac[3, j] + pb[k, 1] * jac[4, j] + pb[k, 2] * jac[5, j]
                acc += jac[3 + k, i] * pu
            hb[i, j] += acc


@kernel
def continuity_weights(
    params: np.ndarray, sc: np.ndarray, frames: float, known: bool
) -> None:
    # The pull to the predicted pose: a constant-velocity prediction over `frames`
    # frames misses by at most 1/2 a (frames dt)^2 with a the peak acceleration, so
    # its weight is (sigma_m / that)^2 (the marker terms have unit weight per m^2).
    # A held one (no velocity known: after a gap, and the frame after the first one
    # explained) misses by the peak speed x h, as fit_track.jump_bound bounds it (a
    # joint's omega_max for every rotation, a root's speed_max for its position).
    h = frames * sc[C_DT]
    if known:
        srot = 0.5 * params[P_ALPHA_MAX] * h * h
        stra = 0.5 * params[P_ACC_MAX] * h * h
    else:
        srot = params[P_OMEGA_MAX] * h
        stra = params[P_SPEED_MAX] * h
    nm = params[P_NOISE_M]
    sc[C_LAM_ROT] = (nm / srot) ** 2 if srot > 0.0 else 0.0
    sc[C_LAM_TRANS] = (nm / stra) ** 2 if stra > 0.0 else 0.0


@kernel
def bone_y_cos(q: np.ndarray) -> float:
    # cos of a joint's bend: its bone's +Y against its parent's +Y, the joint at
    # parent_from_bone q (unit): the y component of q's rotation of +Y
    return 1.0 - 2.0 * (q[1] * q[1] + q[3] * q[3])


@kernel
def limb_bent(qlast: np.ndarray, h: int, sin_bent: float) -> float:
    # the bent-pose hold table's share for a marker on limb hinge h (h < 0: none,
    # 0): sin(bend) / sin(hold_straight) at the last explained frame (qlast, the
    # joints' parent_from_bone), at most 1 (fit_track.hold_priors,
    # fit_hold_robust.robust_drop)
    if h < 0:
        return 0.0
    c = bone_y_cos(qlast[h])
    return min(1.0, math.sqrt(max(0.0, 1.0 - c * c)) / sin_bent)


@kernel
def cp2(dst: np.ndarray, src: np.ndarray) -> None:
    for i in range(dst.shape[0]):
        for j in range(dst.shape[1]):
            dst[i, j] = src[i, j]


@kernel
def cp3(dst: np.ndarray, src: np.ndarray) -> None:
    for i in range(dst.shape[0]):
        for j in range(dst.shape[1]):
            for k in range(dst.shape[2]):
                dst[i, j, k] = src[i, j, k]


@kernel
def cp1(dst: np.ndarray, src: np.ndarray) -> None:
    for i in range(dst.shape[0]):
        dst[i] = src[i]


@kernel
def fk(
    parent: np.ndarray, root_of: np.ndarray, off: np.ndarray,
    q: np.ndarray, t: np.ndarray, wq: np.ndarray, wm: np.ndarray, o: np.ndarray,
) -> None:  # fmt: skip
    # World rotation (quat wq, matrix wm) and origin o of every bone.
    for b in range(parent.shape[0]):
        p = parent[b]
        if p < 0:
            for j in range(4):
                wq[b, j] = q[b, j]
            r = root_of[b]
            for j in range(3):
                o[b, j] = t[r, j]
        else:
            a = qmul(wq[p, 0], wq[p, 1], wq[p, 2], wq[p, 3],
                      q[b, 0], q[b, 1], q[b, 2], q[b, 3])  # fmt: skip
            n = math.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2] + a[3] * a[3])
            for j in range(4):
                wq[b, j] = a[j] / n
            for j in range(3):
                o[b, j] = (
                    o[p, j]
                    + wm[p, j, 0] * off[b, 0]
                    + wm[p, j, 1] * off[b, 1]
                    + wm[p, j, 2] * off[b, 2]
                )
        mat_from_unit_quat(wq[b], wm[b])


@kernel
def neutral_w(lim_b: np.ndarray, r: tuple) -> float:
    # The scalar part of neutral_from_rest (lim_b[6:10]) times r: the cosine of half
    # the joint's rotation from anatomical neutral (the penalties' skip test).
    return lim_b[6] * r[0] - lim_b[7] * r[1] - lim_b[8] * r[2] - lim_b[9] * r[3]


@kernel
def pen_components(
    qw: float, qx: float, qy: float, qz: float,
    lim: np.ndarray, left: np.ndarray, fwd: np.ndarray, hinge: np.ndarray,
    lock: float, s_lim: float, s_hinge: float, out: np.ndarray,
) -> None:  # fmt: skip
    # Residuals of one joint's penalties for its calibration-relative rotation q:
    # out[0] twist, out[1] sagittal, out[2] frontal or cone excess (the validator's
    # swing/twist split, validate_limits.swing_twist) of the rotation from anatomical
    # neutral, neutral_from_rest (lim[6:10], body.neutral) times q; out[3:6] the
    # rotation off the hinge axis, or out[3] a swing joint's twist (lock != 0), of q
    # itself; each scaled by the square root of its weight.
    if qw < 0.0:
        qw, qx, qy, qz = -qw, -qx, -qy, -qz
    for k in range(6):
        out[k] = 0.0
    hw, hx, hy, hz = qw, qx, qy, qz
    qw, qx, qy, qz = qmul(lim[6], lim[7], lim[8], lim[9], hw, hx, hy, hz)
    if qw < 0.0:
        qw, qx, qy, qz = -qw, -qx, -qy, -qz
    tw = 2.0 * math.atan2(qy, qw)
    tw = (tw + math.pi) % (2.0 * math.pi) - math.pi
    if math.isfinite(lim[0]):
        if tw > lim[1]:
            out[0] = s_lim * (tw - lim[1])
        elif tw < lim[0]:
            out[0] = s_lim * (tw - lim[0])
    if math.isfinite(lim[2]) or math.isfinite(lim[4]) or math.isfinite(lim[5]):
        h = 0.5 * tw
        # swing = q * conj(twist), twist = (cos h, 0, sin h, 0)
        sw, sx, sy, sz = qmul(qw, qx, qy, qz, math.cos(h), 0.0, -math.sin(h), 0.0)
        vx, vy, vz = qlog(sw, sx, sy, sz)
        if math.isfinite(lim[2]):
            sag = vx * left[0] + vy * left[1] + vz * left[2]
            if sag > lim[3]:
                out[1] = s_lim * (sag - lim[3])
            elif sag < lim[2]:
                out[1] = s_lim * (sag - lim[2])
        if math.isfinite(lim[4]):
            fro = vx * fwd[0] + vy * fwd[1] + vz * fwd[2]
            if fro > lim[4]:
                out[2] = s_lim * (fro - lim[4])
            elif fro < -lim[4]:
                out[2] = s_lim * (fro + lim[4])
        elif math.isfinite(lim[5]):
            cone = math.sqrt(vx * vx + vy * vy + vz * vz)
            if cone > lim[5]:
                out[2] = s_lim * (cone - lim[5])
    if lock == 2.0:
        # A hinge about h, then the twist about a (the bone's rest axes, lim[10:13]):
        # q = R_h(t) R_a(u) moves a on the cone about h, (q a) . h = a . h. The
        # residual is the distance off that cone, in radians (/ sin of the cone's
        # half-angle).
        a0, a1, a2 = lim[L_TWIST_AXIS], lim[L_TWIST_AXIS + 1], lim[L_TWIST_AXIS + 2]
        ax = (1.0 - 2.0 * (hy * hy + hz * hz)) * a0 + 2.0 * (hx * hy - hw * hz) * a1
        ax += 2.0 * (hx * hz + hw * hy) * a2
        ay = 2.0 * (hx * hy + hw * hz) * a0 + (1.0 - 2.0 * (hx * hx + hz * hz)) * a1
        ay += 2.0 * (hy * hz - hw * hx) * a2
        az = 2.0 * (hx * hz - hw * hy) * a0 + 2.0 * (hy * hz + hw * hx) * a1
        az += (1.0 - 2.0 * (hx * hx + hy * hy)) * a2
        ah = a0 * hinge[0] + a1 * hinge[1] + a2 * hinge[2]
        d = ax * hinge[0] + ay * hinge[1] + az * hinge[2] - ah
        out[3] = s_hinge * d / math.sqrt(1.0 - ah * ah)
    elif lock != 0.0:
        # Zero twist about the twist axis a (lim[10:13]; +Y unless the rig's
        # twist_to) <=> q's vector part is perpendicular to a: a pure swing (of the
        # calibration-relative rotation) about axes perpendicular to a.
        a0, a1, a2 = lim[L_TWIST_AXIS], lim[L_TWIST_AXIS + 1], lim[L_TWIST_AXIS + 2]
        if a0 == 0.0 and a2 == 0.0:  # +Y: q_y itself
            th = 2.0 * math.atan2(hy, hw)
        else:
            th = 2.0 * math.atan2(hx * a0 + hy * a1 + hz * a2, hw)
        out[3] = s_hinge * ((th + math.pi) % (2.0 * math.pi) - math.pi)
    elif hinge[0] != 0.0 or hinge[1] != 0.0 or hinge[2] != 0.0:
        vx, vy, vz = qlog(hw, hx, hy, hz)
        d = vx * hinge[0] + vy * hinge[1] + vz * hinge[2]
        out[3] = s_hinge * (vx - d * hinge[0])
        out[4] = s_hinge * (vy - d * hinge[1])
        out[5] = s_hinge * (vz - d * hinge[2])


@kernel
def marker_cost(
    m: tuple, s: tuple, wm: np.ndarray, o: np.ndarray, pm: np.ndarray,
    res: np.ndarray, wrob: np.ndarray, gated: bool,
) -> float:  # fmt: skip
    # Model marker positions pm, residuals res, IRLS weights wrob; returns the
    # robust marker cost 1/2 sum w c^2 log(1 + |r|^2 / c^2) over the visible markers
    # (gated: without those the gate rejected this frame, s[45]).
    mk_bone, mk_local, mk_weight = m[5], m[6], m[7]
    params = m[18]
    meas, vis, rej = s[12], s[13], s[45]
    # hidden markers measured where they are predicted, with their weight factor
    # (fit_track.virtual_markers; 0: none)
    virt = s[58]
    c2 = params[P_CAUCHY_M] * params[P_CAUCHY_M]
    # While a hidden marker is stood in for (s[58]), a seen marker past the Cauchy
    # scale keeps the loss's peak pull, c / 2, instead of the falling one. The
    # stand-in is measured on the predicted pose each frame, offset by its last
    # residual, so it pulls with a constant force and no stiffness: only the seen
    # markers resist, and a redescending tail resists less the further it is
    # pushed, a negative stiffness (Plug-in Gait's synthetic performer, STRN
    # hidden, T10 at 51 mm: its abdomen twists, the rig's thorax is rigid; the
    # chest 0.1, 0.7, 2.6, 10, 37, 43 deg off every second frame). A monotone
    # influence past the scale (Huber, Ann Math Statist 35(1):73-101, 1964; a
    # redescending one makes the loss non-convex: Hampel et al., Robust
    # Statistics, Wiley 1986) stops the feedback; with nothing stood in for
    # the Cauchy loss is as it was (README, "The fit's rules").
    stand_in = False
    for i in range(virt.shape[0]):
        if virt[i] != 0.0:
            stand_in = True
            break
    cost = 0.0
    for i in range(mk_bone.shape[0]):
        b = mk_bone[i]
        for j in range(3):
            pm[i, j] = (
                o[b, j]
                + wm[b, j, 0] * mk_local[i, 0]
                + wm[b, j, 1] * mk_local[i, 1]
                + wm[b, j, 2] * mk_local[i, 2]
            )
        if not vis[i] and virt[i] == 0.0:
            wrob[i] = 0.0
            continue
        n2 = 0.0
        for j in range(3):
            res[i, j] = pm[i, j] - meas[i, j]
            n2 += res[i, j] * res[i, j]
        w = mk_weight[i] if vis[i] else mk_weight[i] * virt[i]
        if gated and rej[i] and vis[i]:
            wrob[i] = 0.0
        elif stand_in and vis[i] and n2 > c2:
            # the Cauchy loss up to |r| = c, then its tangent there (pull c / 2)
            cc = params[P_CAUCHY_M]
            r = math.sqrt(n2)
            wrob[i] = w * 0.5 * cc / r
            cost += w * (0.5 * c2 * math.log(2.0) + 0.5 * cc * (r - cc))
        else:
            wrob[i] = w / (1.0 + n2 / c2)
            cost += 0.5 * w * c2 * math.log1p(n2 / c2)
    return cost


@kernel
def reg_cost(
    m: tuple, s: tuple, q: np.ndarray, t: np.ndarray, reg: np.ndarray
) -> float:
    # Continuity (pull to the predicted pose s[2], s[3]), priors and joint penalties
    # at (q, t); their values per bone into reg (N_REG columns).
    parent, rest_pfb = m[0], m[3]
    hinge, lim, left, fwd = m[10], m[11], m[12], m[13]
    params = m[18]
    qpred, tpred = s[2], s[3]
    pen = s[26]
    pen_cos, lock, prior = m[19], m[20], m[21]
    hold, anchor, hold_on = s[53], s[54], s[55]
    sc = s[36]
    lam = sc[C_LAM_ROT]
    s_lim = math.sqrt(params[P_KAPPA_LIMIT])
    s_hinge = math.sqrt(params[P_KAPPA_HINGE])
    cost = 0.0
    for b in range(parent.shape[0]):
        rg = reg[b]
        if lam > 0.0:
            d = qmul(qpred[b, 0], -qpred[b, 1], -qpred[b, 2], -qpred[b, 3],
                      q[b, 0], q[b, 1], q[b, 2], q[b, 3])  # fmt: skip
            vx, vy, vz = qlog(d[0], d[1], d[2], d[3])
            rg[R_CONT], rg[R_CONT + 1], rg[R_CONT + 2] = vx, vy, vz
            cost += 0.5 * lam * (vx * vx + vy * vy + vz * vz)
        if parent[b] >= 0:
            r = qmul(rest_pfb[b, 0], -rest_pfb[b, 1], -rest_pfb[b, 2], -rest_pfb[b, 3],
                      q[b, 0], q[b, 1], q[b, 2], q[b, 3])  # fmt: skip
            pb = prior[b]
            if pb[0, 0] + pb[1, 1] + pb[2, 2] > 0.0:
                cost += prior_cost(rest_pfb[b], q[b], pb, rg, R_PRIOR)
            if hold_on[b] > 0.0:
                cost += prior_cost(anchor[b], q[b], hold[b], rg, R_HOLD)
            if abs(neutral_w(lim[b], r)) > pen_cos[b]:
                rg[R_PEN_ON] = 0.0
                continue
            pen_components(r[0], r[1], r[2], r[3], lim[b], left[b], fwd[b],
                            hinge[b], lock[b], s_lim, s_hinge, pen)  # fmt: skip
            rg[R_PEN_ON] = 1.0
            for k in range(6):
                rg[R_PEN + k] = pen[k]
                cost += 0.5 * pen[k] * pen[k]
    lt = sc[C_LAM_TRANS]
    for rr in range(t.shape[0]):
        for j in range(3):
            dt = t[rr, j] - tpred[rr, j]
            cost += 0.5 * lt * dt * dt
    return cost
