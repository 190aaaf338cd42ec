"""The fit's Levenberg-Marquardt (numba): one frame's minimization from the warm start,
ungated then without the markers the gate rejects (``kernel_fit``'s steps 3-4).

The cost, its terms and the unknowns are described in :mod:`kernel_fit`'s
docstring; the normal equations are :func:`fit_normal.build_normal`'s, with
:func:`fit_newton.add_curvature`'s terms from the second iteration on.
"""

from __future__ import annotations

import math

from retargetd.daemon.body.fit_newton import add_curvature
from retargetd.daemon.body.fit_normal import apply_step, build_normal, solve_step
from retargetd.daemon.body.fit_terms import (
    C_GATE,
    C_MU,
    C_SOLVES,
    P_FTOL,
    P_GATE_K,
    P_GATE_M,
    P_MAX_ITER,
    P_TOL,
    cp1,
    cp2,
    cp3,
    fk,
    marker_cost,
    reg_cost,
)
from retargetd.daemon.body.fit_track import mark_outliers, median_residual
from retargetd.daemon.compiled import kernel


@kernel
def evaluate_current(m: tuple, s: tuple, gated: bool) -> float:
    fk(m[0], m[1], m[2], s[0], s[1], s[29], s[8], s[9])
    return marker_cost(m, s, s[8], s[9], s[10], s[14], s[15], gated) + reg_cost(
        m, s, s[0], s[1], s[65]
    )


@kernel
def lm(m: tuple, s: tuple, gated: bool, max_iter: int) -> tuple[int, bool, float]:
    # Levenberg-Marquardt from the current state; returns (iterations, converged,
    # cost). The state (q, t and its FK / residual buffers) ends at the best iterate.
    params = m[18]
    tol = params[P_TOL]
    q, t, qt, tt = s[0], s[1], s[6], s[7]
    wq, wm, o, pm, res, wrob = s[29], s[8], s[9], s[10], s[14], s[15]
    wqt, wmt, ot, pmt, rest, wrobt = s[30], s[31], s[32], s[33], s[34], s[35]
    hh = s[21]
    g, x = s[23], s[24]
    cost = evaluate_current(m, s, gated)
    # damping from where the last fit left it (a stretch of frames whose markers
    # leave a direction nearly flat needs it every frame); Nielsen's update below
    # already lowers it by up to 3x per good step, so it is carried as it is: a
    # further decay per frame started most frames below what the problem needed and
    # paid for it in rejected steps (menache: 2.85 -> 2.45 solves a frame)
    mu_scale = max(1e-8, s[36][C_MU])
    converged = False
    it = 0
    # The first step, from the prediction, on the Gauss-Newton matrix with the
    # markers' IRLS weights: its quadratic bounds the Cauchy loss from above, so a
    # start far off (the walk reversing: every marker 10-20 mm from the
    # prediction) still takes a step that lowers the cost. From then on the
    # markers' own curvature too (fit_newton: Newton's model, converging
    # quadratically); a step it proposes that the cost refuses is taken again on
    # the Gauss-Newton matrix at the same damping before the damping is raised.
    exact = False
    while it < max_iter:
        it += 1
        build_normal(m, s)
        if exact:
            add_curvature(m, s)
        dmax = 0.0
        for e in range(m[16].shape[0] - 1):  # the diagonal blocks (fit_normal)
            for j in range(3):
                if hh[e, j, j] > dmax:
                    dmax = hh[e, j, j]
        accepted = False
        small = False
        refit = False
        step = 0.0
        for _try in range(8):
            mu = mu_scale * dmax
            step = solve_step(m, s, mu)
            s[36][C_SOLVES] += 1.0
            if step < tol:
                # converged: a step under the tolerance is not worth its evaluation
                # (one FK and cost, most frames' second iteration)
                break
            # decrease the quadratic model predicts: with (H + mu I) x = -g,
            # -g.x - x.H.x / 2 = (-g.x + mu |x|^2) / 2
            gx = 0.0
            xx = 0.0
            for e in range(g.shape[0]):
                gx += g[e] * x[e]
                xx += x[e] * x[e]
            pred = 0.5 * (mu * xx - gx)
            if exact and pred <= 0.0:
                # Newton's model not positive definite here: not a descent step
                exact = False
                refit = True
                break
            if pred <= params[P_FTOL] * cost:
                # converged too: the step would lower the cost by less than ftol
                # says is worth a step (tested on the model's prediction, exact
                # near the optimum, before its evaluation is paid for)
                break
            apply_step(m, s)
            fk(m[0], m[1], m[2], qt, tt, wqt, wmt, ot)
            ct = marker_cost(m, s, wmt, ot, pmt, rest, wrobt, gated) + reg_cost(
                m, s, qt, tt, s[66]
            )
            if ct <= cost and math.isfinite(ct):
                accepted = True
                exact = True
                cost_before = cost
                small = cost - ct <= params[P_FTOL] * cost
                cost = ct
                cp2(q, qt)
                cp2(t, tt)
                cp2(wq, wqt)
                cp3(wm, wmt)
                cp2(o, ot)
                cp2(pm, pmt)
                cp2(res, rest)
                cp1(wrob, wrobt)
                cp2(s[65], s[66])  # the terms' values (fit_terms.N_REG)
                # Nielsen's update from the gain ratio (Madsen, Nielsen & Tingleff,
                # "Methods for non-linear least squares problems", DTU 2004, 3.2)
                rho = (cost_before - ct) / pred if pred > 0.0 else 1.0
                mu_scale = max(mu_scale * max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3),
                               1e-12)  # fmt: skip
                break
            if exact:
                # refused on Newton's model: the Gauss-Newton one, same damping
                exact = False
                refit = True
                break
            # rejected: Marquardt's factor of 10 ("An algorithm for least-squares
            # estimation of nonlinear parameters", SIAM J Appl Math 11(2):431-441,
            # 1963), not Nielsen's 2, 4, 8...: every retry costs a solve and an FK,
            # and the damping carried from the last frame is seldom off by less
            # (menache: linear solves p99 6 -> 5, max 10 -> 7)
            mu_scale *= 10.0
        if refit:
            continue
        if not accepted or step < tol or small:
            converged = True
            break
    s[36][C_MU] = mu_scale
    return it, converged, cost


@kernel
def fit_phases(m: tuple, s: tuple) -> tuple[int, bool, float]:
    # Phase 1 ungated; phase 2 without the markers the gate rejects, from the same
    # start, when there are any.
    params = m[18]
    max_iter = int(params[P_MAX_ITER])
    cp2(s[43], s[0])
    cp2(s[44], s[1])
    it1, conv1, cost = lm(m, s, False, max_iter)
    gate = max(params[P_GATE_M], params[P_GATE_K] * median_residual(s))
    s[36][C_GATE] = gate
    if not mark_outliers(m, s, gate):
        return it1, conv1, cost
    # the outliers pulled phase 1 away: start again from the warm start without them
    cp2(s[0], s[43])
    cp2(s[1], s[44])
    it2, conv2, cost = lm(m, s, True, max_iter)
    return it1 + it2, conv2, cost
