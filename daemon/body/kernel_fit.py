"""The compiled rigid-skeleton fit (numba): one frame or a whole take, same code.

Unknowns per frame: every bone's rotation relative to its parent (a quaternion
``Q_b``, updated by a rotation-vector increment) and every root's position. The model
(``fit_model.FitModel``) puts each rig marker at a fixed local position on one bone;
the fit minimizes

    1/2 sum_i w_i rho(|p_i(Q, t) - m_i|^2)           markers, Cauchy rho; the gate's
                                                      rejects out; a hidden marker
                                                      measured where predicted
  + 1/2 lambda_rot sum_b |log(conj(P_b) Q_b)|^2       pull to the predicted pose P
  + 1/2 lambda_trans sum_r |t_r - t_r^pred|^2         (weights from the peak
                                                      accelerations and the frame
                                                      time; speeds for a held one)
  + 1/2 kappa_limit |excess past the validator's swing/twist limits|^2
  + 1/2 kappa_hinge |rotation off a hinge's axis|^2   (hinge, hinge_twist, swing)
  + 1/2 c_b^T R_b c_b                                 priors towards the calibration
                                                      pose (the rig's stiffness, a
                                                      fixed joint, what no marker
                                                      observes: fit_observe)
  + 1/2 d_b^T H_b d_b                                 holds while markers are hidden,
                                                      towards the last seen pose

(c_b, d_b: swing-twist coordinates, ``fit_terms.prior_chart``) by Levenberg-Marquardt
(compiled with ``compiled.kernel``): the first step on the Gauss-Newton matrix with
the markers' IRLS weights, the next ones on Newton's, the markers' own curvature
added (``fit_newton``: the Cauchy loss's along each residual and the skeleton's).
Increments are rotation vectors in world axes at each joint (``omega_b``; a bone's
own increment is ``conj(W_b) omega_b``), so a marker on bone s has the Jacobian
``-[p_i - o_k]x`` for every ancestor-or-self k of s and ``I`` for its root's
position. The normal equations are assembled from per-bone
moment sums (no per-marker Jacobian rows) and solved by a Cholesky factorization
ordered children first, in which the kinematic tree produces no fill-in (the cost is
the sum over unknowns of (3 x depth)^2, not n^3).

Per frame (``fit_one_t``; the rules' numbers are ``solve_fit.FitParams``):

1. gather the markers; one at exactly (0, 0, 0) is lost, not measured. Too few seen
   (none, or fewer than three before the first pose): the frame is **unseen**, the
   last explained pose (the calibration pose before any) is held, flagged.
2. the first frame is seeded from the construction (``body.kernel.solve_one``) where
   the performer is; later ones start from the pose predicted from the last two
   explained frames (``fit_track.predict``), with hidden markers' holds
   (``fit_track.hold_priors``) and, unless the last frame was not explained (a
   gap: the prediction is then a held pose), virtual measurements: from the seen
   markers that moved rigidly with a hidden one where it has them
   (``fit_fill.rigid_fill``), else on the predicted pose (``virtual_markers``).
3. fit ungated, then again without the markers the gate rejects (``fit_track``).
4. suspect (residual above twice the take's own, too many rejects, the first frame
   after a gap, or a marker rejected for ``persist_s``): a second fit seeded from the
   construction, the one with the lower whole cost (every marker under the Cauchy
   loss, continuity, priors, limits) kept.
5. **unexplained** (residual far above the take's own, half the markers rejected, a
   joint further from its prediction than a body moves, or after a gap still suspect
   with the better candidate: nothing to judge it against but its own markers; a
   first frame, which has neither a level nor a past, only past an absolute
   residual no performer leaves):
   the last explained pose is held, flagged, and the next frame's prediction and
   continuity account for the gap (after a first frame: seeded afresh, the solver
   as ``FitSolver.reset`` left it). Else the frame is explained: the running
   residual level, the gate's references and the prediction's history move on.

No output is ever NaN. Everything is preallocated by ``solve_fit.FitSolver``: no
allocation per frame.

**No reference counting.** :func:`fit_one_t` and :func:`fit_many` compile with numba's
``_nrt`` option off, and so does every kernel they call that does not set it itself
(numba's flag inheritance): a kernel handed the model and state tuples (27 and 69
arrays) took a reference to each array it unpacked and gave it back on every exit, two
atomic operations per array per call, and the fit makes dozens of such calls a frame
(``fit_lm.evaluate_current`` alone: 137 increments, 138 decrements in its optimized
code). Nothing below them allocates or returns an array (which numba refuses without
reference counting), so nothing is counted that could be freed early: every array they
see belongs to the caller for the whole call. The construction's seed
(:func:`_seed_from_construction`, first frames and reseeds) keeps the counting: the
construction's views are returned by its kernels.
"""

from __future__ import annotations

import math

import numpy as np

from retargetd.daemon.body import fit_pack
from retargetd.daemon.body import kernel as body_kernel
from retargetd.daemon.body.fit_fill import fill_update, rigid_fill
from retargetd.daemon.body.fit_lm import evaluate_current, fit_phases
from retargetd.daemon.body.fit_terms import (
    C_DT,
    C_GAP,
    C_GATE,
    C_LAST_RMS,
    C_LEVEL,
    C_MU,
    C_SINCE_TRY,
    C_SOLVES,
    P_GATE_M,
    P_LOST_FLOOR_M,
    P_LOST_K,
    P_PERSIST,
    P_REJECT_FRAC,
    P_UNEXPLAINED_FRAC,
    S_COST,
    S_ITER,
    S_LEVEL,
    S_REJECTED,
    S_RESEEDED,
    S_RMS,
    S_SOLVES,
    S_UNEXPLAINED,
    S_UNSEEN,
    continuity_weights,
    cp1,
    cp2,
)
from retargetd.daemon.body.fit_track import (
    advance_level,
    far_at,
    hinge_bend,
    hold_priors,
    impossible,
    predict,
    score,
    truncated_rms,
    unsettled,
    virtual_markers,
)
from retargetd.daemon.compiled import kernel, qmul

# Bone flags: the construction's bits with the same meaning (the pose stream's bone
# flags have no free bit for the fit: bits 4-7 carry validation results on main);
# what is per frame (reseeded, markers rejected) is in the stats and the per-marker
# outputs.
FLAG_HELD = (
    body_kernel.FLAG_HELD
)  #: no marker of the bone's own seen: carried by the fit
FLAG_PARTIAL = body_kernel.FLAG_PARTIAL  #: some marker of the bone not seen


@kernel
def _whole_cost(m: tuple, s: tuple) -> float:
    # The cost a candidate pose is judged on: every visible marker under the Cauchy
    # loss (none gated out: a marker one candidate rejects still counts against it)
    # plus continuity, priors and joint penalties, at the current state.
    return evaluate_current(m, s, False)


@kernel(_nrt=True)
def _seed_from_construction(markers: np.ndarray, m: tuple, s: tuple, c: tuple) -> None:
    # Run the construction kernel on this frame and take its bone rotations and root.
    # c: its packed plan, state and output buffers (``body.kernel.solve_one``): eight
    # arrays to unbox per call instead of their 35 fields. ``markers``: the stream's
    # frame with the markers the fit does not see (exact zeros) as NaN (s[52]).
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
            r = qmul(cw[p, 0], -cw[p, 1], -cw[p, 2], -cw[p, 3],
                      cw[b, 0], cw[b, 1], cw[b, 2], cw[b, 3])  # fmt: skip
            n = math.sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2] + r[3] * r[3])
            for j in range(4):
                q[b, j] = r[j] / n


@kernel
def fit_one(
    markers: np.ndarray,  # (M_stream, 3) world metres, NaN = occluded
    mf: np.ndarray,  # the model's float64 and int64 buffers (fit_pack)
    mi: np.ndarray,
    sf: np.ndarray,  # the state's float64, int64 and bool buffers
    si: np.ndarray,
    sb: np.ndarray,
    lay: np.ndarray,  # (fit_pack.N_ROWS, 4) the layout
    c: tuple,  # the construction kernel's (plan, state, output) buffers, its state kept
    of: np.ndarray,  # the pose's float64, float32, uint8 and bool buffers
    of4: np.ndarray,
    ou1: np.ndarray,
    ob: np.ndarray,
) -> int:
    """Fit one frame from packed buffers (:mod:`fit_pack`: the live call, whose
    dispatch unboxes 13 arguments instead of 90); returns the bones held, plus the
    rig markers not seen (their residual NaN) times 2^32, as the construction's
    ``body.kernel.solve_one`` returns its counts (counted here, not by the caller
    in numpy: ~4 us a frame of ``FitSolver.solve_frame``, PiG walk)."""
    m = fit_pack.model_views(mf, mi, lay)
    s = fit_pack.state_views(sf, si, sb, lay)
    o = fit_pack.out_views(of, of4, ou1, ob, lay)
    held = fit_one_t(
        markers, m, s, c, o[0], o[1], o[2], o[3], o[4], o[5], o[6], o[7], o[8], o[9]
    )
    resid = o[7]
    n_occ = 0
    for i in range(resid.shape[0]):
        if resid[i] != resid[i]:
            n_occ += 1
    return held | (n_occ << 32)


#: Markers a pose needs before the performer counts as seen: three points fix a rigid
#: body; with fewer the first pose would be the calibration pose wherever they are.
MIN_SEEN = 3


@kernel
def _hold(m: tuple, s: tuple) -> None:
    # The last explained pose (the calibration pose before any: ``FitSolver.reset``
    # puts it there), for a frame the fit cannot explain or a performer not seen.
    cp2(s[0], s[49])
    cp2(s[1], s[50])
    evaluate_current(m, s, True)


@kernel(_nrt=False)
def fit_one_t(
    markers: np.ndarray,  # (M_stream, 3) world metres, NaN = occluded
    m: tuple,  # the model (solve_fit.FitSolver._model)
    s: tuple,  # state and scratch (solve_fit.FitSolver._state)
    c: tuple,  # the construction kernel's (plan, state, output) buffers, its state kept
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
    q, t, have = s[0], s[1], s[4]
    prev_out = s[5]
    wq, wm, o = s[29], s[8], s[9]
    meas, vis, res = s[12], s[13], s[14]
    qb, tb = s[37], s[38]
    nvis, natt = s[39], s[40]
    qlast, tlast, rej_run, clean = s[49], s[50], s[51], s[52]
    sc = s[36]
    n_b = parent.shape[0]
    n_mk = mk_bone.shape[0]
    nan = math.nan
    # 1. gather: a marker at exactly (0, 0, 0) is one the capture system lost (many
    # send zeros for "no data"), not a measurement
    sc[C_SOLVES] = 0.0
    for k in range(markers.shape[0]):
        x, y, z = markers[k, 0], markers[k, 1], markers[k, 2]
        if x == 0.0 and y == 0.0 and z == 0.0:
            x = y = z = nan
        clean[k, 0], clean[k, 1], clean[k, 2] = x, y, z
    n_seen = 0
    for i in range(n_mk):
        col = cols[i]
        ok = False
        if col >= 0 and mk_weight[i] > 0.0:
            x, y, z = clean[col, 0], clean[col, 1], clean[col, 2]
            if math.isfinite(x) and math.isfinite(y) and math.isfinite(z):
                ok = True
                meas[i, 0], meas[i, 1], meas[i, 2] = x, y, z
        vis[i] = ok
        if ok:
            n_seen += 1
        else:
            meas[i, 0] = meas[i, 1] = meas[i, 2] = nan
            res[i, 0] = res[i, 1] = res[i, 2] = 0.0
    for i in range(n_mk):
        s[58][i] = 0.0  # no virtual marker but where _virtual_markers puts one
    reseeded = False
    known = False  # the prediction extrapolated (a velocity known), not held
    c_kept = False
    mu_kept = 0.0
    unseen = n_seen < MIN_SEEN if have[0] == 0 else n_seen == 0
    unexplained = False
    iters = 0
    cost = 0.0
    rms = nan
    if unseen:
        # 2a. nobody there: no pose to fit; the last one held (flagged)
        _hold(m, s)
        for i in range(n_mk):
            s[45][i] = False
    else:
        # 2b. seed (first frame), or predict and fit, and judge the result
        first = have[0] == 0
        if first:
            # (the construction's memory kept: a first frame that turns out
            # unexplained must not leave its bones in the construction, step 5)
            # (element by element: a slice assignment may copy its source through
            # a temporary, an allocation, which this kernel compiles without)
            cp1(c[8], c[2])
            cp1(c[9], c[3])
            cp1(c[10], c[4])
            c_kept = True
            mu_kept = sc[C_MU]
            _seed_from_construction(clean, m, s, c)
            cp2(s[2], q)
            cp2(s[3], t)
            sc[C_GAP] = 1.0
            continuity_weights(params, sc, math.inf, True)  # no continuity: no past
            reseeded = True
        else:
            predict(m, s)
            known = have[0] >= 2 and sc[C_GAP] <= 1.0  # as predict decides
            continuity_weights(params, sc, sc[C_GAP], known)
            # hidden markers with a rigid set of seen markers: placed by them
            # (fit_fill), on the same terms as the model's stand-in below
            rigid_fill(m, s, sc[C_GAP] <= 1.0 and have[0] >= 2)
            hold_priors(m, s)
            if sc[C_GAP] <= 1.0 and have[0] >= 2:
                # hidden markers are measured on the prediction only when it is one:
                # after a gap the prediction is the last explained pose held (no
                # velocity is known across it), where the body was gap frames ago,
                # root included; measured there they would pull the fit back to it
                # as hard as seen markers and gate out the markers that disagree
                # (the burst replay, bench/burst_recovery.py: an arm 25-49 deg off
                # with its seen markers rejected). The same holds one frame later:
                # the first explained frame after a gap has no velocity either
                # (predict holds it), so the second is predicted where the body was
                # a frame ago, and the velocity of the next ones starts from that
                # lag (the replay: a hidden knee marker measured 8 -> 36 mm from
                # where it was, the thigh turned 8 deg against its seen marker).
                # The holds, parent-relative, stay.
                virtual_markers(m, s)
        iters, _conv, cost = fit_phases(m, s)
        ss, n_in, n_rej = score(m, s)
        rms = truncated_rms(ss, n_in, n_rej, sc[C_GATE])
        # the take's own residual: its running level, or the last explained frame's
        # that was not suspect, when higher (a misfit that grows with the motion is
        # the take's own; a burst of garbage jumps from one frame to the next)
        level = max(sc[C_LEVEL], sc[C_LAST_RMS])
        persist = 0.0
        for i in range(n_mk):
            if vis[i] and s[45][i] and rej_run[i] + 1.0 > persist:
                persist = rej_run[i] + 1.0
        lost_at = max(params[P_LOST_FLOOR_M], params[P_LOST_K] * level)
        suspect = (level > 0.0 and rms > lost_at) or (
            n_rej > params[P_REJECT_FRAC] * n_seen
        )
        n_persist = params[P_PERSIST] / sc[C_DT]  # frames
        retry = persist >= n_persist and sc[C_SINCE_TRY] >= n_persist
        if not first and (sc[C_GAP] > 1.0 or suspect or retry):
            # A second candidate seeded from the construction, both judged on the
            # whole cost. The prediction is only as good as the time since the
            # markers last agreed with it: after a gap or a marker rejected for
            # `persist` frames its continuity weight is that of so many frames.
            sc[C_SINCE_TRY] = 0.0
            # the construction keeps a memory (a bone whose markers are hidden
            # holds its last value): what it took from a frame that turns out
            # unexplained (a burst's mirrored labels) must not be held into the
            # frames after it; its state is kept (c[8:11]) and restored below
            cp1(c[8], c[2])
            cp1(c[9], c[3])
            cp1(c[10], c[4])
            c_kept = True
            continuity_weights(params, sc, max(sc[C_GAP], persist), known)
            cost_a = _whole_cost(m, s)
            cp2(qb, q)
            cp2(tb, t)
            cp1(s[46], s[45])
            gate_a = sc[C_GATE]
            _seed_from_construction(clean, m, s, c)
            it2, _conv2, _cost2 = fit_phases(m, s)
            iters += it2
            cost_b = _whole_cost(m, s)
            if cost_b < cost_a and math.isfinite(cost_b):
                reseeded = True
                evaluate_current(m, s, True)
            else:
                cp2(q, qb)
                cp2(t, tb)
                cp1(s[45], s[46])
                sc[C_GATE] = gate_a
                evaluate_current(m, s, True)
            ss, n_in, n_rej = score(m, s)
            rms = truncated_rms(ss, n_in, n_rej, sc[C_GATE])
        else:
            sc[C_SINCE_TRY] += 1.0
        # Unexplained: the markers are far from any pose the fit found (a burst of
        # garbage, a collapse, mirrored labels). The pose is held, never carried.
        far = far_at(params, sc, level)  # (bounded after a long gap)
        if first:
            # no level of its own yet, nor a past to jump from: only a residual
            # no performer's markers leave (past the gate on average: a collapse
            # or mirrored labels as a restart's first frame), else that frame
            # would become the level that judges the next ones (FitParams.gate_m);
            # unexplained, the next is seeded afresh
            unexplained = rms > params[P_GATE_M]
        else:
            # after a gap, a frame still suspect with the better candidate
            # does not restart the track (fit_track.unsettled)
            unsettled_ = unsettled(params, sc, rms, lost_at, n_rej, n_seen)
            unexplained = (
                unsettled_
                or rms > far
                or n_rej > params[P_UNEXPLAINED_FRAC] * n_seen
                or impossible(m, s, max(sc[C_GAP], persist))
            )
        # never NaN: a non-finite state (cannot happen with finite inputs) is held
        for b in range(n_b):
            for j in range(4):
                if not math.isfinite(q[b, j]):
                    unexplained = True
        if unexplained:
            _hold(m, s)
            if first:
                # nor its damping (a fit to no body's markers ends far up,
                # Marquardt's x10 per refused step, and the next first frame would
                # start there and run out of iterations), nor a count towards a
                # retry: the solver stays as FitSolver.reset left it
                sc[C_MU] = mu_kept
                sc[C_SINCE_TRY] = 0.0
            if c_kept:
                cp1(c[2], c[8])
                cp1(c[3], c[9])
                cp1(c[4], c[10])
        else:
            advance_level(params, sc, rms, lost_at)
    # 3. outputs
    rej, rref, rage = s[45], s[47], s[48]
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
        if rej[i]:
            out_rejected[i] = True
            n_rej += 1
        else:
            nvis[b] += 1
            sq += n2
            n_in += 1
    held_all = unseen or unexplained
    n_held = 0
    for b in range(n_b):
        if natt[b] > 0:
            out_quality[b] = nvis[b] / natt[b]
            if nvis[b] < natt[b]:
                out_flags[b] |= FLAG_PARTIAL
        else:
            out_quality[b] = 1.0
        if held_all or (natt[b] > 0 and nvis[b] == 0):
            out_flags[b] |= FLAG_HELD
            n_held += 1
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
            a = qmul(wp[0], -wp[1], -wp[2], -wp[3], wb[0], wb[1], wb[2], wb[3])
            for j in range(4):
                out_pfb[b, j] = a[j]
        rp, pb = rest_pfb[b], out_pfb[b]
        r = qmul(rp[0], -rp[1], -rp[2], -rp[3], pb[0], pb[1], pb[2], pb[3])
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
    out_stats[S_SOLVES] = sc[C_SOLVES]
    out_stats[S_UNEXPLAINED] = 1.0 if unexplained else 0.0
    out_stats[S_UNSEEN] = 1.0 if unseen else 0.0
    out_stats[S_LEVEL] = sc[C_LEVEL]
    # 4. an explained frame is the next one's prediction base and the gate's
    # reference; a held one leaves them, and the gap grows
    if held_all:
        # (the gate's references do not age over frames no pose was fitted to: the
        # first frame after a burst is judged against the last explained one)
        if have[0] != 0:
            sc[C_GAP] += 1.0
        return n_held
    rloc, rbend, limb, rlevel = s[56], s[59], m[25], s[67]
    for i in range(n_mk):
        if vis[i] and not rej[i]:
            b = mk_bone[i]
            # the take's level where it was last accepted: the threshold of its hold
            # while it hides (fit_track.hold_priors)
            rlevel[i] = sc[C_LEVEL]
            for j in range(3):
                rref[i, j] = res[i, j]
                rloc[i, j] = (
                    wm[b, 0, j] * res[i, 0]
                    + wm[b, 1, j] * res[i, 1]
                    + wm[b, 2, j] * res[i, 2]
                )
            # its limb's hinge bend there: the pose the residual was measured at
            # (fit_track.virtual_markers)
            h = limb[i]
            rbend[i] = hinge_bend(q[h]) if h >= 0 else 0.0
            rage[i] = 0.0
            rej_run[i] = 0.0
        else:
            rage[i] += 1.0
            rej_run[i] = rej_run[i] + 1.0 if (vis[i] and rej[i]) else 0.0
    fill_update(m, s)
    cp2(s[41], qlast)
    cp2(s[42], tlast)
    cp2(qlast, q)
    cp2(tlast, t)
    # the velocity the next prediction takes from the last two explained frames is
    # known only when they were consecutive (fit_track.predict): one after a gap
    # starts the history again
    have[0] = 2 if (have[0] >= 1 and sc[C_GAP] <= 1.0) else 1
    sc[C_GAP] = 1.0
    return n_held


@kernel(_nrt=False)
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
    """Fit every frame of a take in order (the same code as :func:`fit_one_t`)."""
    held = 0
    for f in range(markers.shape[0]):
        held += fit_one_t(
            markers[f], m, s, c, out_joints[f], out_wfb[f], out_pfb[f],
            out_rfb[f], out_root[f], out_quality[f], out_flags[f], out_resid[f],
            out_rejected[f], out_stats[f],
        )  # fmt: skip
    return held
