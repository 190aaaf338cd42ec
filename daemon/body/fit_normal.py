"""The rigid-skeleton fit's linear algebra (numba): the normal equations from per-bone
marker moments, their tree-ordered Cholesky solve with Levenberg-Marquardt damping,
and the step applied to the state.

The unknowns, the ordering (children first, no fill-in) and the blocks are described
in :mod:`retargetd.daemon.body.kernel_fit`'s docstring; the terms come from
:mod:`retargetd.daemon.body.fit_terms`.
"""

from __future__ import annotations

import math

from retargetd.daemon.body.fit_terms import (
    C_LAM_ROT,
    C_LAM_TRANS,
    L_TWIST_AXIS,
    P_KAPPA_HINGE,
    P_KAPPA_LIMIT,
    R_CONT,
    R_HOLD,
    R_PEN,
    R_PEN_ON,
    R_PRIOR,
    pen_components,
    prior_normal,
    qexp,
)
from retargetd.daemon.compiled import kernel, qmul


@kernel
def build_normal(m: tuple, s: tuple) -> None:
    # Normal equations H (lower triangle, elimination order) and gradient g at the
    # current state (s: wm, o, pm, res, wrob of the current iterate).
    parent, root_of, rest_pfb = m[0], m[1], m[3]
    mk_bone = m[5]
    hinge, lim, left, fwd = m[10], m[11], m[12], m[13]
    anc_ptr, anc_idx = m[14], m[15]
    params, lock = m[18], m[20]
    q, t, tprev = s[0], s[1], s[3]
    wm, o, pm, res, wrob = s[8], s[9], s[10], s[14], s[15]
    s0, sa, sm, sr, sc = s[16], s[17], s[18], s[19], s[20]
    hh, g = s[21], s[23]
    pen, pen2, jac = s[26], s[27], s[28]
    node_ptr = m[16]
    n_b = parent.shape[0]
    for i in range(g.shape[0]):
        g[i] = 0.0
    # H is stored as its 3 x 3 blocks (fit_model.n_blocks): each node's diagonal
    # block, then one block per (node, ancestor) entry of node_idx
    n_nodes = node_ptr.shape[0] - 1
    for e in range(hh.shape[0]):
        for i in range(3):
            for j in range(3):
                hh[e, i, j] = 0.0
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
        if p >= 0:
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
        okx, oky, okz = o[k, 0] - c0x, o[k, 1] - c0y, o[k, 2] - c0z
        ok0 = (okx, oky, okz)
        mx, my, mz = sa[k, 0], sa[k, 1], sa[k, 2]
        m1 = (mx, my, mz)
        nk = n_b - 1 - k
        rk = 3 * nk
        # blocks: (root translation, k) is the last of k's entries
        tk = hh[n_nodes + node_ptr[nk + 1] - 1]
        tb = 3 * n_b + 3 * root_of[k]
        # gradient: sum w (p - o_k) x r = C - o_k x R
        g[rk + 0] += sc[k, 0] - (oky * sr[k, 2] - okz * sr[k, 1])
        g[rk + 1] += sc[k, 1] - (okz * sr[k, 0] - okx * sr[k, 2])
        g[rk + 2] += sc[k, 2] - (okx * sr[k, 1] - oky * sr[k, 0])
        if parent[k] < 0:
            for j in range(3):
                g[tb + j] += sr[k, j]
        if w0 <= 0.0:
            continue
        # translation block: rows t, cols k: -[v]x, v = sum w (p - o_k)
        vx = mx - w0 * okx
        vy = my - w0 * oky
        vz = mz - w0 * okz
        tk[0, 1] += vz
        tk[0, 2] -= vy
        tk[1, 0] -= vz
        tk[1, 2] += vx
        tk[2, 0] += vy
        tk[2, 1] -= vx
        for jj in range(anc_ptr[k], anc_ptr[k + 1]):
            la = anc_idx[jj]
            olx, oly, olz = o[la, 0] - c0x, o[la, 1] - c0y, o[la, 2] - c0z
            ol0 = (olx, oly, olz)
            # block (l, k): k's own diagonal, or its d-th ancestor's entry
            d = jj - anc_ptr[k]
            blk = hh[nk] if d == 0 else hh[n_nodes + node_ptr[nk] + d - 1]
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
                    blk[i, j] += (tt if i == j else 0.0) - gij
        if parent[k] < 0:
            for j in range(3):
                hh[n_b + root_of[k], j, j] += w0
    # Continuity: lambda I on every rotation block, gradient lambda W phi (phi the
    # rotation from the prediction, bone axes). The terms' values at this state
    # (phi, the priors' charts, the penalty residuals) are those the cost took at
    # it (fit_terms.reg_cost, s[65]): every build follows the evaluation of its
    # state (fit_lm.lm), and evaluated again they cost as much as the cost.
    sc = s[36]
    lam = sc[C_LAM_ROT]
    s_lim = math.sqrt(params[P_KAPPA_LIMIT])
    s_hinge = math.sqrt(params[P_KAPPA_HINGE])
    prior = m[21]
    hold, anchor, hold_on = s[53], s[54], s[55]
    reg = s[65]
    eps = 1e-6
    for b in range(n_b):
        rb = 3 * (n_b - 1 - b)
        hb = hh[n_b - 1 - b]
        rg = reg[b]
        if lam > 0.0:
            px, py, pz = rg[R_CONT], rg[R_CONT + 1], rg[R_CONT + 2]
            for j in range(3):
                hb[j, j] += lam
                g[rb + j] += lam * (
                    wm[b, j, 0] * px + wm[b, j, 1] * py + wm[b, j, 2] * pz
                )
        if parent[b] < 0:
            continue
        r = qmul(rest_pfb[b, 0], -rest_pfb[b, 1], -rest_pfb[b, 2], -rest_pfb[b, 3],
                  q[b, 0], q[b, 1], q[b, 2], q[b, 3])  # fmt: skip
        pb = prior[b]
        if pb[0, 0] + pb[1, 1] + pb[2, 2] > 0.0:  # the rig's and the automatic prior
            prior_normal(rest_pfb[b], q[b], pb, wm[b], hb, g, rb, jac, rg, R_PRIOR)
        if hold_on[b] > 0.0:  # the hold while a marker is hidden (kernel_fit)
            prior_normal(anchor[b], q[b], hold[b], wm[b], hb, g, rb, jac, rg, R_HOLD)
        if rg[R_PEN_ON] == 0.0:  # (fit_terms.neutral_w: far inside the limits)
            continue
        for k in range(6):
            pen[k] = rg[R_PEN + k]
        active = False
        for k in range(6):
            if pen[k] != 0.0:
                active = True
        if not active:
            continue
        lk = lock[b]
        if lk != 0.0 and pen[0] == 0.0 and pen[1] == 0.0 and pen[2] == 0.0:
            # Only a swing joint's twist or a hinge_twist's cone residual (pen[3]):
            # its Jacobian in the bone's own increments, analytic (most frames; the
            # numerical one below costs three more evaluations of every term).
            rw, rx, ry, rz = r[0], r[1], r[2], r[3]
            if rw < 0.0:
                rw, rx, ry, rz = -rw, -rx, -ry, -rz
            lb = lim[b]
            a0, a1 = lb[L_TWIST_AXIS], lb[L_TWIST_AXIS + 1]
            a2 = lb[L_TWIST_AXIS + 2]
            if lk == 1.0 and a0 == 0.0 and a2 == 0.0:  # twist = 2 atan2(y, w)
                den = rw * rw + ry * ry
                j0 = s_hinge * (rw * rz + rx * ry) / den
                j1 = s_hinge
                j2 = s_hinge * (ry * rz - rw * rx) / den
            elif lk == 1.0:  # twist = 2 atan2(p, w), p = v . a (v: r's vector part)
                # d p = (w a + a x v) . dw / 2, d w = -v . dw / 2 (dw: the increment)
                p = rx * a0 + ry * a1 + rz * a2
                den = rw * rw + p * p
                j0 = s_hinge * (rw * (rw * a0 + a1 * rz - a2 * ry) + p * rx) / den
                j1 = s_hinge * (rw * (rw * a1 + a2 * rx - a0 * rz) + p * ry) / den
                j2 = s_hinge * (rw * (rw * a2 + a0 * ry - a1 * rx) + p * rz) / den
            else:  # the twist axis R a off the cone about h: d (h . R a) / d w
                # = (R^T h) . (e_k x a) = (a x R^T h)_k (a: lim[b, L_TWIST_AXIS:])
                hv = hinge[b]
                ah = a0 * hv[0] + a1 * hv[1] + a2 * hv[2]
                sc_h = s_hinge / math.sqrt(1.0 - ah * ah)
                t0 = (
                    hv[0] * (1.0 - 2.0 * (ry * ry + rz * rz))  # h . R X
                    + hv[1] * 2.0 * (rx * ry + rw * rz)
                    + hv[2] * 2.0 * (rx * rz - rw * ry)
                )
                t1 = (
                    hv[0] * 2.0 * (rx * ry - rw * rz)  # h . R Y
                    + hv[1] * (1.0 - 2.0 * (rx * rx + rz * rz))
                    + hv[2] * 2.0 * (ry * rz + rw * rx)
                )
                t2 = (
                    hv[0] * 2.0 * (rx * rz + rw * ry)  # h . R Z
                    + hv[1] * 2.0 * (ry * rz - rw * rx)
                    + hv[2] * (1.0 - 2.0 * (rx * rx + ry * ry))
                )
                j0 = sc_h * (a1 * t2 - a2 * t1)
                j1 = sc_h * (a2 * t0 - a0 * t2)
                j2 = sc_h * (a0 * t1 - a1 * t0)
            u0 = j0 * wm[b, 0, 0] + j1 * wm[b, 0, 1] + j2 * wm[b, 0, 2]
            u1 = j0 * wm[b, 1, 0] + j1 * wm[b, 1, 1] + j2 * wm[b, 1, 2]
            u2 = j0 * wm[b, 2, 0] + j1 * wm[b, 2, 1] + j2 * wm[b, 2, 2]
            u = (u0, u1, u2)
            for i in range(3):
                g[rb + i] += u[i] * pen[3]
                for j in range(3):
                    hb[i, j] += u[i] * u[j]
            continue
        # Numerical Jacobian of the penalty residuals w.r.t. the bone's own increment.
        for c in range(3):
            e = qexp(eps if c == 0 else 0.0, eps if c == 1 else 0.0,
                      eps if c == 2 else 0.0)  # fmt: skip
            rp = qmul(r[0], r[1], r[2], r[3], e[0], e[1], e[2], e[3])
            pen_components(rp[0], rp[1], rp[2], rp[3], lim[b], left[b], fwd[b],
                            hinge[b], lock[b], s_lim, s_hinge, pen2)  # fmt: skip
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
                    hb[i, j] += u[i] * u[j]
    lt = sc[C_LAM_TRANS]
    for rr in range(t.shape[0]):
        tb = 3 * n_b + 3 * rr
        for j in range(3):
            hh[n_b + rr, j, j] += lt
            g[tb + j] += lt * (t[rr, j] - tprev[rr, j])


@kernel(inline="always")
def _dot3(a: tuple, b: tuple) -> float:
    # (a0 b0 + a1 b1) + a2 b2: the order solve_step always summed in
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@kernel
def solve_step(m: tuple, s: tuple, mu: float) -> float:
    # x = -(H + mu I)^-1 g by a Cholesky over 3 x 3 nodes in elimination order
    # (children first): a node's column only reaches its ancestors, so the factor
    # has the kinematic tree's pattern and no fill-in. H and L are stored as blocks
    # (build_normal): block k is node k's diagonal, block n_nodes + p the entry p of
    # node_idx (rows: the ancestor node, columns: the node). The ancestors of a node's
    # ancestor a_p are the node's own entries after p, so the block (a_p, a_q), p > q,
    # is entry p - q - 1 of a_q. Returns max |x|.
    node_ptr, node_idx = m[16], m[17]
    hh, ll, g, x = s[21], s[22], s[23], s[24]
    n_nodes = node_ptr.shape[0] - 1
    for e in range(hh.shape[0]):
        for i in range(3):
            for j in range(3):
                ll[e, i, j] = hh[e, i, j]
    for k in range(n_nodes):
        for i in range(3):
            ll[k, i, i] += mu
    for k in range(n_nodes):
        dk = ll[k]
        # 3 x 3 Cholesky of the diagonal block
        a00 = dk[0, 0]
        l00 = math.sqrt(a00 if a00 > 1e-300 else 1e-300)
        l10 = dk[1, 0] / l00
        l20 = dk[2, 0] / l00
        a11 = dk[1, 1] - l10 * l10
        l11 = math.sqrt(a11 if a11 > 1e-300 else 1e-300)
        l21 = (dk[2, 1] - l20 * l10) / l11
        a22 = dk[2, 2] - l20 * l20 - l21 * l21
        l22 = math.sqrt(a22 if a22 > 1e-300 else 1e-300)
        dk[0, 0], dk[1, 0], dk[2, 0] = l00, l10, l20
        dk[1, 1], dk[2, 1], dk[2, 2] = l11, l21, l22
        dk[0, 1] = 0.0
        dk[0, 2] = 0.0
        dk[1, 2] = 0.0
        p0, p1 = node_ptr[k], node_ptr[k + 1]
        # L_ak = A_ak L_kk^-T (forward substitution along each row)
        for p in range(p0, p1):
            bp = ll[n_nodes + p]
            for i in range(3):
                y0 = bp[i, 0] / l00
                y1 = (bp[i, 1] - l10 * y0) / l11
                y2 = (bp[i, 2] - l20 * y0 - l21 * y1) / l22
                bp[i, 0] = y0
                bp[i, 1] = y1
                bp[i, 2] = y2
        # A_ab -= L_ak L_bk^T for ancestors b <= a (L_ak, L_bk read once into
        # registers: the blocks written are other nodes', which the compiler cannot
        # know, and it reloaded them after every store)
        for p in range(p0, p1):
            bp = ll[n_nodes + p]
            u0 = (bp[0, 0], bp[0, 1], bp[0, 2])
            u1 = (bp[1, 0], bp[1, 1], bp[1, 2])
            u2 = (bp[2, 0], bp[2, 1], bp[2, 2])
            da = ll[node_idx[p]]
            da[0, 0] -= _dot3(u0, u0)
            da[1, 0] -= _dot3(u1, u0)
            da[1, 1] -= _dot3(u1, u1)
            da[2, 0] -= _dot3(u2, u0)
            da[2, 1] -= _dot3(u2, u1)
            da[2, 2] -= _dot3(u2, u2)
            for q in range(p0, p):
                bq = ll[n_nodes + q]
                v0 = (bq[0, 0], bq[0, 1], bq[0, 2])
                v1 = (bq[1, 0], bq[1, 1], bq[1, 2])
                v2 = (bq[2, 0], bq[2, 1], bq[2, 2])
                bt = ll[n_nodes + node_ptr[node_idx[q]] + (p - q - 1)]
                bt[0, 0] -= _dot3(u0, v0)
                bt[0, 1] -= _dot3(u0, v1)
                bt[0, 2] -= _dot3(u0, v2)
                bt[1, 0] -= _dot3(u1, v0)
                bt[1, 1] -= _dot3(u1, v1)
                bt[1, 2] -= _dot3(u1, v2)
                bt[2, 0] -= _dot3(u2, v0)
                bt[2, 1] -= _dot3(u2, v1)
                bt[2, 2] -= _dot3(u2, v2)
    for e in range(g.shape[0]):
        x[e] = -g[e]
    # forward: L y = b
    for k in range(n_nodes):
        rk = 3 * k
        dk = ll[k]
        y0 = x[rk] / dk[0, 0]
        y1 = (x[rk + 1] - dk[1, 0] * y0) / dk[1, 1]
        y2 = (x[rk + 2] - dk[2, 0] * y0 - dk[2, 1] * y1) / dk[2, 2]
        x[rk], x[rk + 1], x[rk + 2] = y0, y1, y2
        for p in range(node_ptr[k], node_ptr[k + 1]):
            bp = ll[n_nodes + p]
            ra = 3 * node_idx[p]
            for i in range(3):
                x[ra + i] -= bp[i, 0] * y0 + bp[i, 1] * y1 + bp[i, 2] * y2
    # backward: L^T x = y
    big = 0.0
    for k in range(n_nodes - 1, -1, -1):
        rk = 3 * k
        dk = ll[k]
        c0, c1, c2 = x[rk], x[rk + 1], x[rk + 2]
        for p in range(node_ptr[k], node_ptr[k + 1]):
            bp = ll[n_nodes + p]
            ra = 3 * node_idx[p]
            xa0, xa1, xa2 = x[ra], x[ra + 1], x[ra + 2]
            c0 -= bp[0, 0] * xa0 + bp[1, 0] * xa1 + bp[2, 0] * xa2
            c1 -= bp[0, 1] * xa0 + bp[1, 1] * xa1 + bp[2, 1] * xa2
            c2 -= bp[0, 2] * xa0 + bp[1, 2] * xa1 + bp[2, 2] * xa2
        x2 = c2 / dk[2, 2]
        x1 = (c1 - dk[2, 1] * x2) / dk[1, 1]
        x0 = (c0 - dk[1, 0] * x1 - dk[2, 0] * x2) / dk[0, 0]
        x[rk], x[rk + 1], x[rk + 2] = x0, x1, x2
        for v in (x0, x1, x2):
            if abs(v) > big:
                big = abs(v)
    return big


@kernel
def apply_step(m: tuple, s: tuple) -> None:
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
        e = qexp(ex, ey, ez)
        r = qmul(q[b, 0], q[b, 1], q[b, 2], q[b, 3], e[0], e[1], e[2], e[3])
        n = math.sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2] + r[3] * r[3])
        for j in range(4):
            qt[b, j] = r[j] / n
    for rr in range(t.shape[0]):
        tb = 3 * n_b + 3 * rr
        for j in range(3):
            tt[rr, j] = t[rr, j] + x[tb + j]
