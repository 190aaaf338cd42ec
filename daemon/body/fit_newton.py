"""The marker terms' own curvature for the fit's normal equations (numba): what the
Gauss-Newton matrix of :func:`fit_normal.build_normal` leaves out.

``build_normal`` weighs each marker's J^T J by its IRLS weight ``wrob`` = rho'
(the Cauchy loss rho(s) = c^2 log(1 + s / c^2) of s = |r|^2, ``fit_terms.
marker_cost``). The Hessian of 1/2 sum w rho(|r|^2) has two terms more:

- the loss's own: 2 rho'' J^T r r^T J (Triggs, McLauchlan, Hartley & Fitzgibbon,
  "Bundle adjustment - a modern synthesis", Vision Algorithms: Theory and Practice,
  LNCS 1883, 2000, section 4.3). For the Cauchy loss 2 rho'' = -2 rho'^2 / c^2, so
  a marker's stiffness along its residual is wrob (c^2 - s) / (c^2 + s), not wrob:
  0.22 wrob at 16 mm with c = 20 mm. Past c the loss is concave along r and the
  stiffness there is set to 0 (the Hessian kept positive semi-definite), as past the
  stand-in's tangent (``marker_cost``), linear in |r|;
- the skeleton's: sum rho' r . d2p, the markers' positions being rotations of
  their offsets. With world increments at each joint (``kernel_fit``) a marker at
  p below joints l (an ancestor) and k has d2p / dw_l dw_k = w_l x (w_k x v_k),
  v_k = p - o_k: the block (l, k) gains sum wrob (v_k r^T - (r . v_k) I) and the
  diagonal its symmetric part.

Without them the PiG walk's LM converged linearly, ~0.4 a step, where a marker far
from the model (a knee wand 15 mm off) or a short lever (the foot's markers about
the shank's axis) dominates a direction: the gain ratio was 1.3-1.5 at every step
and a frame took 3 to 7 linear solves. With them it converges quadratically
(``fit_lm.lm`` adds them from its second iteration on: the first, from the
prediction, keeps the IRLS matrix, whose quadratic bounds the Cauchy loss from
above). All terms are summed as moments over each bone's subtree, as
``build_normal``'s are.
"""

from __future__ import annotations

from retargetd.daemon.body.fit_terms import P_CAUCHY_M
from retargetd.daemon.compiled import kernel


@kernel
def add_curvature(m: tuple, s: tuple) -> None:
    # Adds the terms above to H (s[21]) after build_normal at the same state (its
    # subtree sums s0 = s[16] and sr = s[19] are read). rc = s[69], per bone:
    # [gam r r^T | gam r a^T | gam a a^T | wrob r p^T], a = p x r, p about bone 0's
    # origin, gam the loss's rank-1 weight (below).
    parent, root_of, mk_bone = m[0], m[1], m[5]
    anc_ptr, anc_idx, node_ptr, params = m[14], m[15], m[16], m[18]
    o, pm, res, wrob = s[9], s[10], s[14], s[15]
    s0, sr, hh, rc = s[16], s[19], s[21], s[69]
    n_b = parent.shape[0]
    n_nodes = node_ptr.shape[0] - 1
    c2 = params[P_CAUCHY_M] * params[P_CAUCHY_M]
    for b in range(n_b):
        for j in range(3):
            for k in range(12):
                rc[b, j, k] = 0.0
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
        n2 = rx * rx + ry * ry + rz * rz
        if n2 <= 0.0:
            continue
        # wrob - gam s: the stiffness along r, wrob (c^2 - s) / (c^2 + s) up to c,
        # 0 past it
        gam = w * min(2.0 / (c2 + n2), 1.0 / n2)
        pv = (px, py, pz)
        rv = (rx, ry, rz)
        av = (py * rz - pz * ry, pz * rx - px * rz, px * ry - py * rx)
        rb = rc[b]
        for j in range(3):
            gr = gam * rv[j]
            ga = gam * av[j]
            wr = w * rv[j]
            for k in range(3):
                rb[j, k] += gr * rv[k]
                rb[j, 3 + k] += gr * av[k]
                rb[j, 6 + k] += ga * av[k]
                rb[j, 9 + k] += wr * pv[k]
    for b in range(n_b - 1, -1, -1):
        p = parent[b]
        if p >= 0:
            for j in range(3):
                for k in range(12):
                    rc[p, j, k] += rc[b, j, k]
    for k in range(n_b):
        if s0[k] <= 0.0:
            continue
        ox, oy, oz = o[k, 0] - c0x, o[k, 1] - c0y, o[k, 2] - c0z
        rk = rc[k]
        # the loss's term: sum gam (u x r)(v x r)^T, u = p - o_l, v = p - o_k;
        # v x r = a + r x o_k, so with X = sum gam r (v x r)^T and
        # Y = sum gam a (v x r)^T the block (l, k) loses Y - [o_l]x X, the
        # translation's (rows t) X and the translation's own block sum gam r r^T
        xk = (
            (rk[0, 3] + rk[0, 1] * oz - rk[0, 2] * oy,
             rk[0, 4] + rk[0, 2] * ox - rk[0, 0] * oz,
             rk[0, 5] + rk[0, 0] * oy - rk[0, 1] * ox),
            (rk[1, 3] + rk[1, 1] * oz - rk[1, 2] * oy,
             rk[1, 4] + rk[1, 2] * ox - rk[1, 0] * oz,
             rk[1, 5] + rk[1, 0] * oy - rk[1, 1] * ox),
            (rk[2, 3] + rk[2, 1] * oz - rk[2, 2] * oy,
             rk[2, 4] + rk[2, 2] * ox - rk[2, 0] * oz,
             rk[2, 5] + rk[2, 0] * oy - rk[2, 1] * ox),
        )  # fmt: skip
        yk = (
            (rk[0, 6] + rk[1, 3] * oz - rk[2, 3] * oy,
             rk[0, 7] + rk[2, 3] * ox - rk[0, 3] * oz,
             rk[0, 8] + rk[0, 3] * oy - rk[1, 3] * ox),
            (rk[1, 6] + rk[1, 4] * oz - rk[2, 4] * oy,
             rk[1, 7] + rk[2, 4] * ox - rk[0, 4] * oz,
             rk[1, 8] + rk[0, 4] * oy - rk[1, 4] * ox),
            (rk[2, 6] + rk[1, 5] * oz - rk[2, 5] * oy,
             rk[2, 7] + rk[2, 5] * ox - rk[0, 5] * oz,
             rk[2, 8] + rk[0, 5] * oy - rk[1, 5] * ox),
        )  # fmt: skip
        # the skeleton's term: P = sum wrob (v r^T - (r . v) I)
        sk = sr[k]
        trp = rk[0, 9] + rk[1, 10] + rk[2, 11] - (ox * sk[0] + oy * sk[1] + oz * sk[2])
        pk = (
            (rk[0, 9] - ox * sk[0] - trp, rk[1, 9] - ox * sk[1],
             rk[2, 9] - ox * sk[2]),
            (rk[0, 10] - oy * sk[0], rk[1, 10] - oy * sk[1] - trp,
             rk[2, 10] - oy * sk[2]),
            (rk[0, 11] - oz * sk[0], rk[1, 11] - oz * sk[1],
             rk[2, 11] - oz * sk[2] - trp),
        )  # fmt: skip
        nk = n_b - 1 - k
        tk = hh[n_nodes + node_ptr[nk + 1] - 1]  # (root translation, k): rows t
        for i in range(3):
            for j in range(3):
                tk[i, j] -= xk[i][j]
        for jj in range(anc_ptr[k], anc_ptr[k + 1]):
            la = anc_idx[jj]
            lx, ly, lz = o[la, 0] - c0x, o[la, 1] - c0y, o[la, 2] - c0z
            d = jj - anc_ptr[k]
            blk = hh[nk] if d == 0 else hh[n_nodes + node_ptr[nk] + d - 1]
            for j in range(3):
                # ([o_l]x X)[:, j] = o_l x X[:, j]
                blk[0, j] -= yk[0][j] - (ly * xk[2][j] - lz * xk[1][j])
                blk[1, j] -= yk[1][j] - (lz * xk[0][j] - lx * xk[2][j])
                blk[2, j] -= yk[2][j] - (lx * xk[1][j] - ly * xk[0][j])
                for i in range(3):
                    blk[i, j] += 0.5 * (pk[i][j] + pk[j][i]) if d == 0 else pk[i][j]
        if parent[k] < 0:
            ht = hh[n_b + root_of[k]]
            for i in range(3):
                for j in range(3):
                    ht[i, j] -= rk[i, j]
