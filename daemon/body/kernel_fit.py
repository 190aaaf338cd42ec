"""The compiled rigid-skeleton fit (numba): one frame or a whole take, same code.

Unknowns per frame: every bone's rotation relative to its parent (a quaternion
``Q_b``, updated by a rotation-vector increment) and every root's position. The model
(``fit_model.FitModel``) puts each rig marker at a fixed local position on one bone;
the fit minimizes

    1/2 sum_i w_i rho(|p_i(Q, t) - m_i|^2)           visible markers, Cauchy rho,
                                                      cut to a constant past the gate
  + 1/2 lambda_rot sum_b |log(conj(Q_b^prev) Q_b)|^2  weak pull to the last frame
  + 1/2 lambda_trans sum_r |t_r - t_r^prev|^2
  + 1/2 kappa_limit |excess past the validator's swing/twist limits|^2   (soft)
  + 1/2 kappa_hinge |rotation off a hinge's axis|^2   (bones the rig makes hinges)

by Levenberg-Marquardt (compiled with ``compiled.kernel``). Increments are rotation
vectors in world axes at each joint (``omega_b``; a bone's own increment is
``conj(W_b) omega_b``), so a marker on bone s has the Jacobian ``-[p_i - o_k]x``
for every ancestor-or-self k of s and ``I`` for its root's position. The normal
equations are assembled from per-bone moment sums (no per-marker Jacobian rows) and
solved by a Cholesky factorization ordered children
first, in which the kinematic tree produces no fill-in (the cost is the sum over
unknowns of (3 x depth)^2, not n^3); the blocks come from marker moments summed over
each bone's subtree, one block per (bone, ancestor) pair.

Per frame: warm start from the last frame; phase 1 without a gate; when some visible
marker's residual exceeds the gate ``max(gate_m, gate_k * median residual)``, phase 2
drops those markers (counted) and fits again from the same start; when the fit has
lost track (inlier RMS above ``reseed_rms_m``, too many markers rejected, or no
convergence within the iteration cap with the RMS above half that) the construction
kernel (``body.kernel.solve_one``) seeds a second fit and the better of the two
(truncated squared residual) is kept. The first frame after a reset is
seeded from the construction. Bones with no visible marker are carried by their
neighbours and the pull to the last frame, flagged; no output is ever NaN.

Everything is preallocated by ``solve_fit.FitSolver``: no allocation per frame.
"""

from __future__ import annotations

import math

import numpy as np

from retargetd.daemon.body import kernel as body_kernel
from retargetd.daemon.compiled import kernel, mat_from_unit_quat

# Bone flags: the construction's bits with the same meaning (the pose stream's bone
# flags have no free bit for the fit: bits 4-7 carry validation results on main);
# what is per frame (reseeded, markers rejected) is in the stats and the per-marker
# outputs.
FLAG_HELD = (
    body_kernel.FLAG_HELD
)  #: no marker of the bone's own seen: carried by the fit
FLAG_PARTIAL = body_kernel.FLAG_PARTIAL  #: some marker of the bone not seen

# params (float64 array) slots
P_LAM_ROT = 0
P_LAM_TRANS = 1
P_KAPPA_LIMIT = 2
P_KAPPA_HINGE = 3
P_CAUCHY_M = 4
P_GATE_M = 5
P_GATE_K = 6
P_RESEED_RMS_M = 7
P_MAX_ITER = 8
P_TOL = 9
P_RESEED_REJECT_FRAC = 10
P_FTOL = 11
N_PARAMS = 12

# stats (float64 array) slots
S_RMS = 0
S_REJECTED = 1
S_ITER = 2
S_RESEEDED = 3
S_COST = 4
S_SOLVES = 5
N_STATS = 6

_INF = 1e300


@kernel
def _qmul(
    aw: float, ax: float, ay: float, az: float,
    bw: float, bx: float, by: float, bz: float,
) -> tuple[float, float, float, float]:  # fmt: skip
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


@kernel
def _qexp(vx: float, vy: float, vz: float) -> tuple[float, float, float, float]:
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
def _qlog(w: float, x: float, y: float, z: float) -> tuple[float, float, float]:
    if w < 0.0:
        w, x, y, z = -w, -x, -y, -z
    s = math.sqrt(x * x + y * y + z * z)
    if s < 1e-12:
        return 2.0 * x, 2.0 * y, 2.0 * z
    k = 2.0 * math.atan2(s, w) / s
    return k * x, k * y, k * z


@kernel
def _cp2(dst: np.ndarray, src: np.ndarray) -> None:
    for i in range(dst.shape[0]):
        for j in range(dst.shape[1]):
            dst[i, j] = src[i, j]


@kernel
def _cp3(dst: np.ndarray, src: np.ndarray) -> None:
    for i in range(dst.shape[0]):
        for j in range(dst.shape[1]):
            for k in range(dst.shape[2]):
                dst[i, j, k] = src[i, j, k]


@kernel
def _cp1(dst: np.ndarray, src: np.ndarray) -> None:
    for i in range(dst.shape[0]):
        dst[i] = src[i]


@kernel
def _fk(
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
            a = _qmul(wq[p, 0], wq[p, 1], wq[p, 2], wq[p, 3],
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
def _pen_components(
    qw: float, qx: float, qy: float, qz: float,
    lim: np.ndarray, left: np.ndarray, fwd: np.ndarray, hinge: np.ndarray,
    s_lim: float, s_hinge: float, out: np.ndarray,
) -> None:  # fmt: skip
    # Residuals of one joint's penalties for its calibration-relative rotation q:
    # out[0] twist, out[1] sagittal, out[2] frontal or cone excess (the validator's
    # swing/twist split, validate_limits.swing_twist), out[3:6] the rotation off the
    # hinge axis; each scaled by the square root of its weight.
    if qw < 0.0:
        qw, qx, qy, qz = -qw, -qx, -qy, -qz
    for k in range(6):
        out[k] = 0.0
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
        sw, sx, sy, sz = _qmul(qw, qx, qy, qz, math.cos(h), 0.0, -math.sin(h), 0.0)
        vx, vy, vz = _qlog(sw, sx, sy, sz)
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
    if hinge[0] != 0.0 or hinge[1] != 0.0 or hinge[2] != 0.0:
        vx, vy, vz = _qlog(qw, qx, qy, qz)
        d = vx * hinge[0] + vy * hinge[1] + vz * hinge[2]
        out[3] = s_hinge * (vx - d * hinge[0])
        out[4] = s_hinge * (vy - d * hinge[1])
        out[5] = s_hinge * (vz - d * hinge[2])


@kernel
def _marker_cost(
    m: tuple, s: tuple, wm: np.ndarray, o: np.ndarray, pm: np.ndarray,
    res: np.ndarray, wrob: np.ndarray, gate: float,
) -> float:  # fmt: skip
    # Model marker positions pm, residuals res, IRLS weights wrob; returns the
    # robust marker cost 1/2 sum w c^2 log(1 + |r|^2 / c^2) (constant past the gate).
    mk_bone, mk_local, mk_weight = m[5], m[6], m[7]
    params = m[18]
    meas, vis = s[12], s[13]
    c2 = params[P_CAUCHY_M] * params[P_CAUCHY_M]
    g2 = gate * gate
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
        if not vis[i]:
            wrob[i] = 0.0
            continue
        n2 = 0.0
        for j in range(3):
            res[i, j] = pm[i, j] - meas[i, j]
            n2 += res[i, j] * res[i, j]
        w = mk_weight[i]
        if n2 > g2:
            wrob[i] = 0.0
            cost += 0.5 * w * c2 * math.log1p(g2 / c2)
        else:
            wrob[i] = w / (1.0 + n2 / c2)
            cost += 0.5 * w * c2 * math.log1p(n2 / c2)
    return cost


@kernel
def _reg_cost(m: tuple, s: tuple, q: np.ndarray, t: np.ndarray) -> float:
    # Prior (pull to the last frame) and joint penalties at (q, t).
    parent, rest_pfb = m[0], m[3]
    hinge, lim, left, fwd = m[10], m[11], m[12], m[13]
    params = m[18]
    qprev, tprev = s[2], s[3]
    pen = s[26]
    pen_cos = m[19]
    lam = params[P_LAM_ROT]
    s_lim = math.sqrt(params[P_KAPPA_LIMIT])
    s_hinge = math.sqrt(params[P_KAPPA_HINGE])
    cost = 0.0
    for b in range(parent.shape[0]):
        d = _qmul(qprev[b, 0], -qprev[b, 1], -qprev[b, 2], -qprev[b, 3],
                  q[b, 0], q[b, 1], q[b, 2], q[b, 3])  # fmt: skip
        vx, vy, vz = _qlog(d[0], d[1], d[2], d[3])
        cost += 0.5 * lam * (vx * vx + vy * vy + vz * vz)
        if parent[b] >= 0:
            r = _qmul(rest_pfb[b, 0], -rest_pfb[b, 1], -rest_pfb[b, 2], -rest_pfb[b, 3],
                      q[b, 0], q[b, 1], q[b, 2], q[b, 3])  # fmt: skip
            if abs(r[0]) > pen_cos[b]:
                continue
            _pen_components(r[0], r[1], r[2], r[3], lim[b], left[b], fwd[b],
                            hinge[b], s_lim, s_hinge, pen)  # fmt: skip
            for k in range(6):
                cost += 0.5 * pen[k] * pen[k]
    lt = params[P_LAM_TRANS]
    for rr in range(t.shape[0]):
        for j in range(3):
            dt = t[rr, j] - tprev[rr, j]
            cost += 0.5 * lt * dt * dt
    return cost


@kernel
def _build(m: tuple, s: tuple) -> None:
    # Normal equations H (lower triangle, elimination order) and gradient g at the
    # current state (s: wm, o, pm, res, wrob of the current iterate).
    parent, root_of, rest_pfb = m[0], m[1], m[3]
    mk_bone = m[5]
    hinge, lim, left, fwd = m[10], m[11], m[12], m[13]
    anc_ptr, anc_idx = m[14], m[15]
    params = m[18]
    q, t, qprev, tprev = s[0], s[1], s[2], s[3]
    wm, o, pm, res, wrob = s[8], s[9], s[10], s[14], s[15]
    s0, sa, sm, sr, sc = s[16], s[17], s[18], s[19], s[20]
    hh, g = s[21], s[23]
    pen, pen2, jac = s[26], s[27], s[28]
    n_b = parent.shape[0]
    n = g.shape[0]
    for i in range(n):
        g[i] = 0.0
        for j in range(n):
            hh[i, j] = 0.0
    for b in range(n_b):
        s0[b] = 0.0
        for j in range(3):
            sa[b, j] = 0.0
            sr[b, j] = 0.0
            sc[b, j] = 0.0
            for k in range(3):
                sm[b, j, k] = 0.0
    # Moments of the weighted markers (positions about bone 0's origin, for
    # conditioning) summed over each bone's subtree: the block of H coupling a bone
    # k with an ancestor l sums over exactly the markers below k.
    c0x, c0y, c0z = o[0, 0], o[0, 1], o[0, 2]
    for i in range(mk_bone.shape[0]):
        w = wrob[i]
        if w <= 0.0:
            continue
        b = mk_bone[i]
        px = pm[i, 0] - c0x
        py = pm[i, 1] - c0y
        pz = pm[i, 2] - c0z
        rx, ry, rz = res[i, 0], res[i, 1], res[i, 2]
        s0[b] += w
        sa[b, 0] += w * px
        sa[b, 1] += w * py
        sa[b, 2] += w * pz
        sr[b, 0] += w * rx
        sr[b, 1] += w * ry
        sr[b, 2] += w * rz
        sc[b, 0] += w * (py * rz - pz * ry)
        sc[b, 1] += w * (pz * rx - px * rz)
        sc[b, 2] += w * (px * ry - py * rx)
        sm[b, 0, 0] += w * px * px
        sm[b, 0, 1] += w * px * py
        sm[b, 0, 2] += w * px * pz
        sm[b, 1, 1] += w * py * py
        sm[b, 1, 2] += w * py * pz
        sm[b, 2, 2] += w * pz * pz
    for b in range(n_b - 1, -1, -1):
        sm[b, 1, 0] = sm[b, 0, 1]
        sm[b, 2, 0] = sm[b, 0, 2]
        sm[b, 2, 1] = sm[b, 1, 2]
        p = parent[b]
        if p >= 0 and s0[b] > 0.0:
            s0[p] += s0[b]
            for j in range(3):
                sa[p, j] += sa[b, j]
                sr[p, j] += sr[b, j]
                sc[p, j] += sc[b, j]
            for j in range(3):
                for k2 in range(j, 3):
                    sm[p, j, k2] += sm[b, j, k2]
    for k in range(n_b):
        w0 = s0[k]
        if w0 <= 0.0:
            continue
        okx, oky, okz = o[k, 0] - c0x, o[k, 1] - c0y, o[k, 2] - c0z
        ok0 = (okx, oky, okz)
        mx, my, mz = sa[k, 0], sa[k, 1], sa[k, 2]
        m1 = (mx, my, mz)
        rk = 3 * (n_b - 1 - k)
        tb = 3 * n_b + 3 * root_of[k]
        # gradient: sum w (p - o_k) x r = C - o_k x R
        g[rk + 0] += sc[k, 0] - (oky * sr[k, 2] - okz * sr[k, 1])
        g[rk + 1] += sc[k, 1] - (okz * sr[k, 0] - okx * sr[k, 2])
        g[rk + 2] += sc[k, 2] - (okx * sr[k, 1] - oky * sr[k, 0])
        # translation block: rows t, cols k: -[v]x, v = sum w (p - o_k)
        vx = mx - w0 * okx
        vy = my - w0 * oky
        vz = mz - w0 * okz
        hh[tb + 0, rk + 1] += vz
        hh[tb + 0, rk + 2] -= vy
        hh[tb + 1, rk + 0] -= vz
        hh[tb + 1, rk + 2] += vx
        hh[tb + 2, rk + 0] += vy
        hh[tb + 2, rk + 1] -= vx
        for jj in range(anc_ptr[k], anc_ptr[k + 1]):
            la = anc_idx[jj]
            olx, oly, olz = o[la, 0] - c0x, o[la, 1] - c0y, o[la, 2] - c0z
            ol0 = (olx, oly, olz)
            rl = 3 * (n_b - 1 - la)
            # G = sum w (p - o_k)(p - o_l)^T; rows l, cols k: trace(G) I - G
            tt = (
                sm[k, 0, 0] + sm[k, 1, 1] + sm[k, 2, 2]
                - (mx * (okx + olx) + my * (oky + oly) + mz * (okz + olz))
                + w0 * (okx * olx + oky * oly + okz * olz)
            )  # fmt: skip
            for i in range(3):
                for j in range(3):
                    gij = (
                        sm[k, i, j]
                        - m1[i] * ol0[j]
                        - ok0[i] * m1[j]
                        + w0 * ok0[i] * ol0[j]
                    )
                    hh[rl + i, rk + j] += (tt if i == j else 0.0) - gij
        if parent[k] < 0:
            for j in range(3):
                hh[tb + j, tb + j] += w0
                g[tb + j] += sr[k, j]
    # Prior: lambda I on every rotation block, gradient lambda W phi.
    lam = params[P_LAM_ROT]
    s_lim = math.sqrt(params[P_KAPPA_LIMIT])
    s_hinge = math.sqrt(params[P_KAPPA_HINGE])
    eps = 1e-6
    for b in range(n_b):
        rb = 3 * (n_b - 1 - b)
        d = _qmul(qprev[b, 0], -qprev[b, 1], -qprev[b, 2], -qprev[b, 3],
                  q[b, 0], q[b, 1], q[b, 2], q[b, 3])  # fmt: skip
        px, py, pz = _qlog(d[0], d[1], d[2], d[3])
        for j in range(3):
            hh[rb + j, rb + j] += lam
            g[rb + j] += lam * (wm[b, j, 0] * px + wm[b, j, 1] * py + wm[b, j, 2] * pz)
        if parent[b] < 0:
            continue
        r = _qmul(rest_pfb[b, 0], -rest_pfb[b, 1], -rest_pfb[b, 2], -rest_pfb[b, 3],
                  q[b, 0], q[b, 1], q[b, 2], q[b, 3])  # fmt: skip
        if abs(r[0]) > m[19][b]:
            continue
        _pen_components(r[0], r[1], r[2], r[3], lim[b], left[b], fwd[b], hinge[b],
                        s_lim, s_hinge, pen)  # fmt: skip
        active = False
        for k in range(6):
            if pen[k] != 0.0:
                active = True
        if not active:
            continue
        # Numerical Jacobian of the penalty residuals w.r.t. the bone's own increment.
        for c in range(3):
            e = _qexp(eps if c == 0 else 0.0, eps if c == 1 else 0.0,
                      eps if c == 2 else 0.0)  # fmt: skip
            rp = _qmul(r[0], r[1], r[2], r[3], e[0], e[1], e[2], e[3])
            _pen_components(rp[0], rp[1], rp[2], rp[3], lim[b], left[b], fwd[b],
                            hinge[b], s_lim, s_hinge, pen2)  # fmt: skip
            for k in range(6):
                dk = (pen2[k] - pen[k]) / eps
                # a twist wrapping through +-pi is not a derivative
                jac[k, c] = dk if abs(dk) < 1e3 else 0.0
        # In world increments: d pen / d omega = jac W^T; H += (jac W^T)^T (jac W^T).
        for k in range(6):
            u0 = (
                jac[k, 0] * wm[b, 0, 0]
                + jac[k, 1] * wm[b, 0, 1]
                + jac[k, 2] * wm[b, 0, 2]
            )
            u1 = (
                jac[k, 0] * wm[b, 1, 0]
                + jac[k, 1] * wm[b, 1, 1]
                + jac[k, 2] * wm[b, 1, 2]
            )
            u2 = (
                jac[k, 0] * wm[b, 2, 0]
                + jac[k, 1] * wm[b, 2, 1]
                + jac[k, 2] * wm[b, 2, 2]
            )
            u = (u0, u1, u2)
            for i in range(3):
                g[rb + i] += u[i] * pen[k]
                for j in range(3):
                    hh[rb + i, rb + j] += u[i] * u[j]
    lt = params[P_LAM_TRANS]
    for rr in range(t.shape[0]):
        tb = 3 * n_b + 3 * rr
        for j in range(3):
            hh[tb + j, tb + j] += lt
            g[tb + j] += lt * (t[rr, j] - tprev[rr, j])


@kernel
def _solve_step(m: tuple, s: tuple, mu: float) -> float:
    # x = -(H + mu I)^-1 g by a Cholesky over 3 x 3 nodes in elimination order
    # (children first): a node's column only reaches its ancestors, so the factor
    # has the kinematic tree's pattern and no fill-in. Returns max |x|.
    node_ptr, node_idx = m[16], m[17]
    hh, ll, g, x = s[21], s[22], s[23], s[24]
    n_nodes = node_ptr.shape[0] - 1
    # copy the lower blocks the factorization touches
    for k in range(n_nodes):
        rk = 3 * k
        for i in range(3):
            for j in range(i + 1):
                ll[rk + i, rk + j] = hh[rk + i, rk + j]
            ll[rk + i, rk + i] += mu
        for p in range(node_ptr[k], node_ptr[k + 1]):
            ra = 3 * node_idx[p]
            for i in range(3):
                for j in range(3):
                    ll[ra + i, rk + j] = hh[ra + i, rk + j]
    for k in range(n_nodes):
        rk = 3 * k
        # 3 x 3 Cholesky of the diagonal block
        a00 = ll[rk, rk]
        l00 = math.sqrt(a00 if a00 > 1e-300 else 1e-300)
        l10 = ll[rk + 1, rk] / l00
        l20 = ll[rk + 2, rk] / l00
        a11 = ll[rk + 1, rk + 1] - l10 * l10
        l11 = math.sqrt(a11 if a11 > 1e-300 else 1e-300)
        l21 = (ll[rk + 2, rk + 1] - l20 * l10) / l11
        a22 = ll[rk + 2, rk + 2] - l20 * l20 - l21 * l21
        l22 = math.sqrt(a22 if a22 > 1e-300 else 1e-300)
        ll[rk, rk], ll[rk + 1, rk], ll[rk + 2, rk] = l00, l10, l20
        ll[rk + 1, rk + 1], ll[rk + 2, rk + 1], ll[rk + 2, rk + 2] = l11, l21, l22
        ll[rk, rk + 1] = 0.0
        ll[rk, rk + 2] = 0.0
        ll[rk + 1, rk + 2] = 0.0
        p0, p1 = node_ptr[k], node_ptr[k + 1]
        # L_ak = A_ak L_kk^-T (forward substitution along each row)
        for p in range(p0, p1):
            ra = 3 * node_idx[p]
            for i in range(3):
                y0 = ll[ra + i, rk] / l00
                y1 = (ll[ra + i, rk + 1] - l10 * y0) / l11
                y2 = (ll[ra + i, rk + 2] - l20 * y0 - l21 * y1) / l22
                ll[ra + i, rk] = y0
                ll[ra + i, rk + 1] = y1
                ll[ra + i, rk + 2] = y2
        # A_ab -= L_ak L_bk^T for ancestors b <= a
        for p in range(p0, p1):
            ra = 3 * node_idx[p]
            for p2 in range(p0, p + 1):
                rb = 3 * node_idx[p2]
                diag = p2 == p
                for i in range(3):
                    ui0, ui1, ui2 = (
                        ll[ra + i, rk],
                        ll[ra + i, rk + 1],
                        ll[ra + i, rk + 2],
                    )
                    for j in range(3):
                        if diag and j > i:
                            break
                        ll[ra + i, rb + j] -= (
                            ui0 * ll[rb + j, rk]
                            + ui1 * ll[rb + j, rk + 1]
                            + ui2 * ll[rb + j, rk + 2]
                        )
    for e in range(g.shape[0]):
        x[e] = -g[e]
    # forward: L y = b
    for k in range(n_nodes):
        rk = 3 * k
        y0 = x[rk] / ll[rk, rk]
        y1 = (x[rk + 1] - ll[rk + 1, rk] * y0) / ll[rk + 1, rk + 1]
        y2 = (x[rk + 2] - ll[rk + 2, rk] * y0 - ll[rk + 2, rk + 1] * y1) / ll[
            rk + 2, rk + 2
        ]
        x[rk], x[rk + 1], x[rk + 2] = y0, y1, y2
        for p in range(node_ptr[k], node_ptr[k + 1]):
            ra = 3 * node_idx[p]
            for i in range(3):
                x[ra + i] -= (
                    ll[ra + i, rk] * y0
                    + ll[ra + i, rk + 1] * y1
                    + ll[ra + i, rk + 2] * y2
                )
    # backward: L^T x = y
    big = 0.0
    for k in range(n_nodes - 1, -1, -1):
        rk = 3 * k
        c0, c1, c2 = x[rk], x[rk + 1], x[rk + 2]
        for p in range(node_ptr[k], node_ptr[k + 1]):
            ra = 3 * node_idx[p]
            xa0, xa1, xa2 = x[ra], x[ra + 1], x[ra + 2]
            c0 -= ll[ra, rk] * xa0 + ll[ra + 1, rk] * xa1 + ll[ra + 2, rk] * xa2
            c1 -= (
                ll[ra, rk + 1] * xa0
                + ll[ra + 1, rk + 1] * xa1
                + ll[ra + 2, rk + 1] * xa2
            )
            c2 -= (
                ll[ra, rk + 2] * xa0
                + ll[ra + 1, rk + 2] * xa1
                + ll[ra + 2, rk + 2] * xa2
            )
        x2 = c2 / ll[rk + 2, rk + 2]
        x1 = (c1 - ll[rk + 2, rk + 1] * x2) / ll[rk + 1, rk + 1]
        x0 = (c0 - ll[rk + 1, rk] * x1 - ll[rk + 2, rk] * x2) / ll[rk, rk]
        x[rk], x[rk + 1], x[rk + 2] = x0, x1, x2
        for v in (x0, x1, x2):
            if abs(v) > big:
                big = abs(v)
    return big


@kernel
def _apply(m: tuple, s: tuple) -> None:
    # Trial state (qt, tt) = current state + step x.
    parent = m[0]
    q, t, qt, tt, wm, x = s[0], s[1], s[6], s[7], s[8], s[24]
    n_b = parent.shape[0]
    for b in range(n_b):
        rb = 3 * (n_b - 1 - b)
        ox, oy, oz = x[rb], x[rb + 1], x[rb + 2]
        # bone-axis increment: conj(W_b) omega
        ex = wm[b, 0, 0] * ox + wm[b, 1, 0] * oy + wm[b, 2, 0] * oz
        ey = wm[b, 0, 1] * ox + wm[b, 1, 1] * oy + wm[b, 2, 1] * oz
        ez = wm[b, 0, 2] * ox + wm[b, 1, 2] * oy + wm[b, 2, 2] * oz
        e = _qexp(ex, ey, ez)
        r = _qmul(q[b, 0], q[b, 1], q[b, 2], q[b, 3], e[0], e[1], e[2], e[3])
        n = math.sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2] + r[3] * r[3])
        for j in range(4):
            qt[b, j] = r[j] / n
    for rr in range(t.shape[0]):
        tb = 3 * n_b + 3 * rr
        for j in range(3):
            tt[rr, j] = t[rr, j] + x[tb + j]


@kernel
def _evaluate_current(m: tuple, s: tuple, gate: float) -> float:
    _fk(m[0], m[1], m[2], s[0], s[1], s[29], s[8], s[9])
    return _marker_cost(m, s, s[8], s[9], s[10], s[14], s[15], gate) + _reg_cost(
        m, s, s[0], s[1]
    )


@kernel
def _lm(m: tuple, s: tuple, gate: float, max_iter: int) -> tuple[int, bool, float]:
    # Levenberg-Marquardt from the current state; returns (iterations, converged,
    # cost). The state (q, t and its FK / residual buffers) ends at the best iterate.
    params = m[18]
    tol = params[P_TOL]
    q, t, qt, tt = s[0], s[1], s[6], s[7]
    wq, wm, o, pm, res, wrob = s[29], s[8], s[9], s[10], s[14], s[15]
    wqt, wmt, ot, pmt, rest, wrobt = s[30], s[31], s[32], s[33], s[34], s[35]
    hh = s[21]
    g, x = s[23], s[24]
    cost = _evaluate_current(m, s, gate)
    mu_scale = 1e-8
    nu = 2.0
    converged = False
    it = 0
    while it < max_iter:
        it += 1
        _build(m, s)
        dmax = 0.0
        for e in range(hh.shape[0]):
            if hh[e, e] > dmax:
                dmax = hh[e, e]
        accepted = False
        small = False
        step = 0.0
        for _try in range(8):
            mu = mu_scale * dmax
            step = _solve_step(m, s, mu)
            s[36][1] += 1.0
            # decrease the quadratic model predicts: with (H + mu I) x = -g,
            # -g.x - x.H.x / 2 = (-g.x + mu |x|^2) / 2
            gx = 0.0
            xx = 0.0
            for e in range(g.shape[0]):
                gx += g[e] * x[e]
                xx += x[e] * x[e]
            pred = 0.5 * (mu * xx - gx)
            _apply(m, s)
            _fk(m[0], m[1], m[2], qt, tt, wqt, wmt, ot)
            ct = _marker_cost(m, s, wmt, ot, pmt, rest, wrobt, gate) + _reg_cost(
                m, s, qt, tt
            )
            # (a step at the optimum may raise the cost by rounding: no retries then)
            if step < tol and not ct <= cost:
                break
            if ct <= cost and math.isfinite(ct):
                accepted = True
                cost_before = cost
                small = cost - ct <= params[P_FTOL] * cost
                cost = ct
                _cp2(q, qt)
                _cp2(t, tt)
                _cp2(wq, wqt)
                _cp3(wm, wmt)
                _cp2(o, ot)
                _cp2(pm, pmt)
                _cp2(res, rest)
                _cp1(wrob, wrobt)
                # Nielsen's update from the gain ratio (Madsen, Nielsen & Tingleff,
                # "Methods for non-linear least squares problems", DTU 2004, 3.2)
                rho = (cost_before - ct) / pred if pred > 0.0 else 1.0
                mu_scale = max(mu_scale * max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3),
                               1e-12)  # fmt: skip
                nu = 2.0
                break
            mu_scale *= nu
            nu *= 2.0
        if not accepted or step < tol or small:
            converged = True
            break
    return it, converged, cost


@kernel
def _median_residual(s: tuple) -> float:
    # Median |residual| over visible markers (insertion sort in scratch).
    vis, res, buf = s[13], s[14], s[25]
    n = 0
    for i in range(vis.shape[0]):
        if vis[i]:
            v = math.sqrt(res[i, 0] ** 2 + res[i, 1] ** 2 + res[i, 2] ** 2)
            j = n
            while j > 0 and buf[j - 1] > v:
                buf[j] = buf[j - 1]
                j -= 1
            buf[j] = v
            n += 1
    if n == 0:
        return 0.0
    if n % 2 == 1:
        return buf[n // 2]
    return 0.5 * (buf[n // 2 - 1] + buf[n // 2])


@kernel
def _fit_phases(m: tuple, s: tuple) -> tuple[int, bool, float]:
    # Phase 1 ungated; phase 2 with the gate, from the same start, when some
    # residual is beyond it.
    params = m[18]
    max_iter = int(params[P_MAX_ITER])
    _cp2(s[43], s[0])
    _cp2(s[44], s[1])
    it1, conv1, cost = _lm(m, s, _INF, max_iter)
    gate = max(params[P_GATE_M], params[P_GATE_K] * _median_residual(s))
    vis, res = s[13], s[14]
    g2 = gate * gate
    beyond = False
    for i in range(vis.shape[0]):
        if vis[i] and res[i, 0] ** 2 + res[i, 1] ** 2 + res[i, 2] ** 2 > g2:
            beyond = True
    s[36][0] = gate
    if not beyond:
        return it1, conv1, cost
    # the outliers pulled phase 1 away: start again from the warm start without them
    _cp2(s[0], s[43])
    _cp2(s[1], s[44])
    it2, conv2, cost = _lm(m, s, gate, max_iter)
    return it1 + it2, conv2, cost


@kernel
def _score(m: tuple, s: tuple) -> tuple[float, int, int]:
    # Inlier sum of squares, number of inliers, number rejected (beyond the gate).
    vis, res, wt = s[13], s[14], m[7]
    g2 = s[36][0] ** 2
    ss = 0.0
    n_in = 0
    n_rej = 0
    for i in range(vis.shape[0]):
        if not vis[i] or wt[i] <= 0.0:
            continue
        n2 = res[i, 0] ** 2 + res[i, 1] ** 2 + res[i, 2] ** 2
        if n2 > g2:
            n_rej += 1
            ss += g2
        else:
            n_in += 1
            ss += n2
    return ss, n_in, n_rej


@kernel
def _seed_from_construction(markers: np.ndarray, m: tuple, s: tuple, c: tuple) -> None:
    # Run the construction kernel on this frame and take its bone rotations and root.
    # c: its packed plan, state and output buffers (``body.kernel.solve_one``): eight
    # arrays to unbox per call instead of their 35 fields.
    pi, sf, sb, si = c[0], c[2], c[3], c[4]
    cp = body_kernel.plan_views(pi, c[1])
    cs = body_kernel.state_views(pi, sf, sb, si)
    co = body_kernel.out_views(pi, c[5], c[6], c[7])
    body_kernel.solve_one_nt(markers, cp, cs, co)
    parent, root_of = m[0], m[1]
    q, t = s[0], s[1]
    cw, croot = co.wfb, co.root
    for b in range(parent.shape[0]):
        p = parent[b]
        if p < 0:
            for j in range(4):
                q[b, j] = cw[b, j]
            if b == 0:
                for j in range(3):
                    t[root_of[b], j] = croot[j]
        else:
            r = _qmul(cw[p, 0], -cw[p, 1], -cw[p, 2], -cw[p, 3],
                      cw[b, 0], cw[b, 1], cw[b, 2], cw[b, 3])  # fmt: skip
            n = math.sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2] + r[3] * r[3])
            for j in range(4):
                q[b, j] = r[j] / n


@kernel
def fit_one(
    markers: np.ndarray,  # (M_stream, 3) world metres, NaN = occluded
    m: tuple,  # the model (solve_fit.FitSolver._model)
    s: tuple,  # state and scratch (solve_fit.FitSolver._state)
    c: tuple,  # the construction kernel's (plan, state, output) plain tuples
    out_joints: np.ndarray,  # (J, 3)
    out_wfb: np.ndarray,  # (B, 4)
    out_pfb: np.ndarray,  # (B, 4) parent_from_bone
    out_rfb: np.ndarray,  # (B, 4) rest_from_bone (relative to calibration)
    out_root: np.ndarray,  # (3,)
    out_quality: np.ndarray,  # (B,) float32
    out_flags: np.ndarray,  # (B,) uint8
    out_resid: np.ndarray,  # (Mr,) metres, NaN where not seen
    out_rejected: np.ndarray,  # (Mr,) bool
    out_stats: np.ndarray,  # (N_STATS,) float64
) -> int:
    """Fit one frame; returns the number of bones flagged held."""
    parent, rest_pfb, cols = m[0], m[3], m[4]
    mk_bone, mk_weight, jt_bone, jt_local = m[5], m[7], m[8], m[9]
    params = m[18]
    q, t, qprev, tprev, have = s[0], s[1], s[2], s[3], s[4]
    prev_out = s[5]
    wq, wm, o = s[29], s[8], s[9]
    meas, vis, res = s[12], s[13], s[14]
    qb, tb = s[37], s[38]
    nvis, natt = s[39], s[40]
    n_b = parent.shape[0]
    n_mk = mk_bone.shape[0]
    nan = math.nan
    # 1. gather
    s[36][1] = 0.0
    n_seen = 0
    for i in range(n_mk):
        col = cols[i]
        ok = False
        if col >= 0 and mk_weight[i] > 0.0:
            x, y, z = markers[col, 0], markers[col, 1], markers[col, 2]
            if math.isfinite(x) and math.isfinite(y) and math.isfinite(z):
                ok = True
                meas[i, 0], meas[i, 1], meas[i, 2] = x, y, z
        vis[i] = ok
        if ok:
            n_seen += 1
        else:
            meas[i, 0] = meas[i, 1] = meas[i, 2] = nan
            res[i, 0] = res[i, 1] = res[i, 2] = 0.0
    # 2. seed, fit, and reseed when the fit lost track
    reseeded = False
    if have[0] == 0:
        _seed_from_construction(markers, m, s, c)
        _cp2(qprev, q)
        _cp2(tprev, t)
        reseeded = True
    elif have[0] >= 2:
        # warm start: the last frame, advanced by its joint-angle velocity
        q2, t2 = s[41], s[42]
        for b in range(n_b):
            d = _qmul(q2[b, 0], -q2[b, 1], -q2[b, 2], -q2[b, 3],
                      q[b, 0], q[b, 1], q[b, 2], q[b, 3])  # fmt: skip
            r = _qmul(q[b, 0], q[b, 1], q[b, 2], q[b, 3], d[0], d[1], d[2], d[3])
            nr = math.sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2] + r[3] * r[3])
            for j in range(4):
                q[b, j] = r[j] / nr
        for rr in range(t.shape[0]):
            for j in range(3):
                t[rr, j] = 2.0 * t[rr, j] - t2[rr, j]
    iters, conv, cost = _fit_phases(m, s)
    ss, n_in, n_rej = _score(m, s)
    rms = math.sqrt(ss / max(n_in + n_rej, 1))
    lost = (
        rms > params[P_RESEED_RMS_M]
        or n_rej > params[P_RESEED_REJECT_FRAC] * max(n_seen, 1)
        or ((not conv) and rms > 0.5 * params[P_RESEED_RMS_M])
    )
    if lost and have[0] != 0 and n_seen > 0:
        _cp2(qb, q)
        _cp2(tb, t)
        gate_b = s[36][0]
        _seed_from_construction(markers, m, s, c)
        it2, _conv2, _cost2 = _fit_phases(m, s)
        iters += it2
        ss2, n_in2, n_rej2 = _score(m, s)
        if ss2 < ss:
            reseeded = True
            ss, n_in, n_rej = ss2, n_in2, n_rej2
        else:
            _cp2(q, qb)
            _cp2(t, tb)
            s[36][0] = gate_b
            _evaluate_current(m, s, gate_b)
    # never NaN: a non-finite state (cannot happen with finite inputs) falls back
    finite = True
    for b in range(n_b):
        for j in range(4):
            if not math.isfinite(q[b, j]):
                finite = False
    if not finite:
        _cp2(q, qprev)
        _cp2(t, tprev)
        _evaluate_current(m, s, s[36][0])
    # 3. outputs
    g2 = s[36][0] ** 2
    n_rej = 0
    sq = 0.0
    n_in = 0
    for b in range(n_b):
        nvis[b] = 0
        natt[b] = 0
        out_flags[b] = 0
    for i in range(n_mk):
        out_rejected[i] = False
        b = mk_bone[i]
        if mk_weight[i] > 0.0:
            natt[b] += 1
        if not vis[i]:
            out_resid[i] = nan
            continue
        n2 = res[i, 0] ** 2 + res[i, 1] ** 2 + res[i, 2] ** 2
        out_resid[i] = math.sqrt(n2)
        if n2 > g2:
            out_rejected[i] = True
            n_rej += 1
        else:
            nvis[b] += 1
            sq += n2
            n_in += 1
    n_held = 0
    for b in range(n_b):
        if natt[b] > 0:
            out_quality[b] = nvis[b] / natt[b]
            if nvis[b] < natt[b]:
                out_flags[b] |= FLAG_PARTIAL
            if nvis[b] == 0:
                out_flags[b] |= FLAG_HELD
                n_held += 1
        else:
            out_quality[b] = 1.0
        # world rotation, sign continuous with the last frame's output
        dot = 0.0
        for j in range(4):
            dot += wq[b, j] * prev_out[b, j]
        sign = -1.0 if (have[0] != 0 and dot < 0.0) else 1.0
        for j in range(4):
            out_wfb[b, j] = sign * wq[b, j]
            prev_out[b, j] = out_wfb[b, j]
        # parent-relative (the root's parent: the world), from the streamed world
        # rotations as the construction does; and relative to the calibration pose
        p = parent[b]
        if p < 0:
            for j in range(4):
                out_pfb[b, j] = out_wfb[b, j]
        else:
            wp, wb = out_wfb[p], out_wfb[b]
            a = _qmul(wp[0], -wp[1], -wp[2], -wp[3], wb[0], wb[1], wb[2], wb[3])
            for j in range(4):
                out_pfb[b, j] = a[j]
        rp, pb = rest_pfb[b], out_pfb[b]
        r = _qmul(rp[0], -rp[1], -rp[2], -rp[3], pb[0], pb[1], pb[2], pb[3])
        sg = -1.0 if r[0] < 0.0 else 1.0
        for j in range(4):
            out_rfb[b, j] = sg * r[j]
    for j in range(jt_bone.shape[0]):
        b = jt_bone[j]
        for k in range(3):
            out_joints[j, k] = (
                o[b, k]
                + wm[b, k, 0] * jt_local[j, 0]
                + wm[b, k, 1] * jt_local[j, 1]
                + wm[b, k, 2] * jt_local[j, 2]
            )
    for k in range(3):
        out_root[k] = o[0, k]
    out_stats[S_RMS] = math.sqrt(sq / n_in) if n_in > 0 else nan
    out_stats[S_REJECTED] = n_rej
    out_stats[S_ITER] = iters
    out_stats[S_RESEEDED] = 1.0 if reseeded else 0.0
    out_stats[S_COST] = cost
    out_stats[S_SOLVES] = s[36][1]
    # 4. this frame is the next one's warm start and prior
    _cp2(s[41], qprev)
    _cp2(s[42], tprev)
    _cp2(qprev, q)
    _cp2(tprev, t)
    have[0] = 2 if have[0] >= 1 else 1
    return n_held


@kernel
def fit_many(
    markers: np.ndarray,  # (T, M_stream, 3)
    m: tuple,
    s: tuple,
    c: tuple,
    out_joints: np.ndarray,  # (T, J, 3)
    out_wfb: np.ndarray,  # (T, B, 4)
    out_pfb: np.ndarray,  # (T, B, 4)
    out_rfb: np.ndarray,  # (T, B, 4)
    out_root: np.ndarray,  # (T, 3)
    out_quality: np.ndarray,  # (T, B)
    out_flags: np.ndarray,  # (T, B)
    out_resid: np.ndarray,  # (T, Mr)
    out_rejected: np.ndarray,  # (T, Mr)
    out_stats: np.ndarray,  # (T, N_STATS)
) -> int:
    """Fit every frame of a take in order (the same code as :func:`fit_one`)."""
    held = 0
    for f in range(markers.shape[0]):
        held += fit_one(
            markers[f], m, s, c, out_joints[f], out_wfb[f], out_pfb[f],
            out_rfb[f], out_root[f], out_quality[f], out_flags[f], out_resid[f],
            out_rejected[f], out_stats[f],
        )  # fmt: skip
    return held
