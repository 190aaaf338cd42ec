"""The compiled per-frame face kernel (numba): stabilize, then bounded weights.

``solve_face_frame`` is one call per frame with every buffer passed in (no
allocation): the weighted rigid fit of the head markers (Horn's quaternion method,
the shared ``compiled.horn_fit``), the facial markers mapped to
head coordinates, the restricted normal matrix rebuilt only when the occlusion
pattern changes, and the box-constrained QP by block principal pivoting. The method
and the frames are described in ``solve_face``.
"""

from __future__ import annotations

import math

import numpy as np

from retargetd.daemon.compiled import horn_fit, kernel
from retargetd.protocols import pose_stream

# The pose stream's face flags, imported (numba freezes them at compile time).
FLAG_HEAD_PARTIAL = pose_stream.FACE_HEAD_PARTIAL  #: a head marker missing
FLAG_HEAD_LOST = pose_stream.FACE_HEAD_LOST  #: < 3 head markers: pose, weights held
FLAG_NOT_CONVERGED = pose_stream.FACE_NOT_CONVERGED  #: the iteration cap was hit
FLAG_FACE_PARTIAL = pose_stream.FACE_PARTIAL  #: some facial marker occluded
FLAG_NEVER = pose_stream.FACE_NEVER  #: no good frame yet: identity pose, zero weights
FLAG_SHAPE_HELD = pose_stream.FACE_SHAPE_HELD  #: a shape held: its key markers hidden
#: Per-shape state bits (``FaceOutput.shape_state``, the pose stream's ``RTDF``).
SHAPE_UNOBSERVED = pose_stream.SHAPE_UNOBSERVED  #: left out of the solve: sent as 0
SHAPE_HIDDEN = pose_stream.SHAPE_HIDDEN  #: a key marker hidden: weight held

#: Block exchanges without fewer infeasibilities before single (Murty) exchanges.
_BPP_TRIES = 3


@kernel
def _fit_head(
    markers: np.ndarray,  # (N, 3) world
    valid: np.ndarray,  # (N,) bool
    head_cols: np.ndarray,  # (H,) int64, -1 = absent
    layout: np.ndarray,  # (H, 3) head coords
    head_w: np.ndarray,  # (H,) weights
    n44: np.ndarray,
    v44: np.ndarray,
    q4: np.ndarray,
    rot: np.ndarray,  # (3, 3) out: world_from_head
    pos: np.ndarray,  # (3,) out
    cen: np.ndarray,  # (6,) scratch: centroids
) -> int:
    # Weighted Horn fit (the shared one): max sum_i w_i c_i . R l_i over centred
    # points. Returns the number of head markers used, 0 when not determined.
    n = horn_fit(layout, markers, head_cols, valid, head_w, n44, v44, q4, cen)
    if n == 0:
        return 0
    clx, cly, clz, ccx, ccy, ccz = cen[0], cen[1], cen[2], cen[3], cen[4], cen[5]
    for r in range(3):
        for c in range(3):
            rot[r, c] = n44[r, c]
    pos[0] = ccx - rot[0, 0] * clx - rot[0, 1] * cly - rot[0, 2] * clz
    pos[1] = ccy - rot[1, 0] * clx - rot[1, 1] * cly - rot[1, 2] * clz
    pos[2] = ccz - rot[2, 0] * clx - rot[2, 1] * cly - rot[2, 2] * clz
    return n


@kernel
def _solve_free(
    a: np.ndarray,
    b: np.ndarray,
    w: np.ndarray,
    state: np.ndarray,
    idx: np.ndarray,
    chol: np.ndarray,
    x: np.ndarray,
) -> int:
    # Minimize over the free variables with the others fixed at w:
    # A_FF x_F = b_F - A_F,fixed w_fixed, by Cholesky of the free block. x[p] is the
    # value of variable idx[p]; returns the number of free variables.
    k = a.shape[0]
    nf = 0
    for i in range(k):
        if state[i] == 0:
            idx[nf] = i
            nf += 1
    for p in range(nf):
        ip = idx[p]
        r = b[ip]
        for j in range(k):
            if state[j] != 0:
                r -= a[ip, j] * w[j]
        x[p] = r
        for q in range(p + 1):
            chol[p, q] = a[ip, idx[q]]
    for p in range(nf):
        for q in range(p + 1):
            s = chol[p, q]
            for t in range(q):
                s -= chol[p, t] * chol[q, t]
            if p == q:
                chol[p, p] = math.sqrt(s) if s > 0.0 else 1e-300
            else:
                chol[p, q] = s / chol[q, q]
    for p in range(nf):
        s = x[p]
        for t in range(p):
            s -= chol[p, t] * x[t]
        x[p] = s / chol[p, p]
    for p in range(nf - 1, -1, -1):
        s = x[p]
        for t in range(p + 1, nf):
            s -= chol[t, p] * x[t]
        x[p] = s / chol[p, p]
    return nf


@kernel
def _box_qp(
    a: np.ndarray,  # (K, K) SPD
    b: np.ndarray,  # (K,)
    w: np.ndarray,  # (K,) out: solution in [0, 1]
    state: np.ndarray,  # (K,) int64: 0 free, 1 at 0, 2 at 1, 3 held at w; warm start
    idx: np.ndarray,  # (K,) int64 scratch
    chol: np.ndarray,  # (K, K) scratch
    x: np.ndarray,  # (K,) scratch
    g: np.ndarray,  # (K,) scratch
    max_iter: int,
) -> int:
    # min 1/2 w'Aw - b'w on the box [0, 1]^K, as the mixed LCP of its KKT
    # conditions, by block principal pivoting (Judice & Pires 1994; Portugal, Judice
    # & Vicente 1994): from the last frame's active set, solve the free block; every
    # free variable out of the box goes to its bound and every bound with a
    # wrong-sign multiplier is freed, all at once. When the number of such
    # infeasibilities stops falling for _BPP_TRIES exchanges, only the one with the
    # largest index is exchanged (Murty's rule), which terminates for SPD A.
    # Returns the number of Cholesky solves, or -1 when max_iter was hit.
    k = a.shape[0]
    if k == 0:  # no expressions (a neutral-only training set): nothing to solve
        return 0
    scale = 0.0
    for i in range(k):
        scale += a[i, i]
    tol = 1e-12 * scale / k
    for i in range(k):
        if state[i] == 1:
            w[i] = 0.0
        elif state[i] == 2:
            w[i] = 1.0
    best = k + 1
    tries = _BPP_TRIES
    for it in range(max_iter):
        nf = _solve_free(a, b, w, state, idx, chol, x)
        for p in range(nf):
            w[idx[p]] = x[p]
        n_inf = 0
        last = -1
        for i in range(k):
            new = state[i]
            if state[i] == 3:  # held (its key markers hidden): never exchanged
                g[i] = 3
                continue
            if state[i] == 0:
                if w[i] < -1e-13:
                    new = 1
                elif w[i] > 1.0 + 1e-13:
                    new = 2
            else:
                gi = -b[i]
                for j in range(k):
                    gi += a[i, j] * w[j]
                viol = -gi if state[i] == 1 else gi
                if viol > tol:
                    new = 0
            g[i] = new
            if new != state[i]:
                n_inf += 1
                last = i
        if n_inf == 0:
            for i in range(k):
                w[i] = min(1.0, max(0.0, w[i]))
            return it + 1
        if n_inf < best:
            best = n_inf
            tries = _BPP_TRIES
        elif tries > 0:
            tries -= 1
        else:
            for i in range(k):
                g[i] = state[i]
            if state[last] == 0:
                g[last] = 1 if w[last] < 0.0 else 2
            else:
                g[last] = 0
        for i in range(k):
            state[i] = int(g[i])
            if state[i] == 1:
                w[i] = 0.0
            elif state[i] == 2:
                w[i] = 1.0
    for i in range(k):
        w[i] = min(1.0, max(0.0, w[i]))
    return -1


@kernel
def _add_pose_prior(
    a: np.ndarray,  # (K + 6, K + 6): the pose block a[K:, K:] is added to
    k: int,
    layout: np.ndarray,  # (H, 3) head coordinates
    head_w: np.ndarray,  # (H,)
    head_seen: np.ndarray,  # (H,) bool: used in this frame's fit
) -> None:
    # G = sum_i w_i H_i^T H_i over the head markers the fit used, with
    # H_i = [I, -[l_i]x] the change of head marker i under a small pose correction
    # (tau, theta): l -> l + tau + theta x l. ``solve_face``'s pose_information.
    for i in range(layout.shape[0]):
        if not head_seen[i]:
            continue
        w = head_w[i]
        x, y, z = layout[i, 0], layout[i, 1], layout[i, 2]
        for r in range(3):
            h0 = 1.0 if r == 0 else 0.0
            h1 = 1.0 if r == 1 else 0.0
            h2 = 1.0 if r == 2 else 0.0
            if r == 0:
                h3, h4, h5 = 0.0, z, -y
            elif r == 1:
                h3, h4, h5 = -z, 0.0, x
            else:
                h3, h4, h5 = y, -x, 0.0
            row = (h0, h1, h2, h3, h4, h5)
            for p in range(6):
                for q in range(6):
                    a[k + p, k + q] += w * row[p] * row[q]


@kernel
def _reduce_pose(
    a: np.ndarray,  # (K + 6, K + 6) the restricted joint normal matrix
    k: int,
    ared: np.ndarray,  # (K, K) out: A_ww - A_wd A_dd^-1 A_dw
    schur: np.ndarray,  # (K, 6) out: A_wd A_dd^-1
    c6: np.ndarray,  # (6, 6) scratch: Cholesky factor of A_dd
) -> None:
    # The pose correction is unbounded, so it is eliminated (Schur complement): the
    # box QP in w alone has A_red = A_ww - S A_dw and b_red = b_w - S b_d with
    # S = A_wd A_dd^-1, and the same solution in w. Built when the pattern changes.
    for p in range(6):
        for q in range(p + 1):
            s = a[k + p, k + q]
            for t in range(q):
                s -= c6[p, t] * c6[q, t]
            if p == q:
                c6[p, p] = math.sqrt(s) if s > 0.0 else 1e-300
            else:
                c6[p, q] = s / c6[q, q]
    for j in range(k):  # schur[j] = A_dd^-1 a[k:, j] (A_dd symmetric)
        for p in range(6):
            s = a[k + p, j]
            for t in range(p):
                s -= c6[p, t] * schur[j, t]
            schur[j, p] = s / c6[p, p]
        for p in range(5, -1, -1):
            s = schur[j, p]
            for t in range(p + 1, 6):
                s -= c6[t, p] * schur[j, t]
            schur[j, p] = s / c6[p, p]
    for p in range(k):
        for q in range(k):
            s = a[p, q]
            for r in range(6):
                s -= schur[p, r] * a[k + r, q]
            ared[p, q] = s


@kernel
def solve_face_frame(
    markers: np.ndarray,  # (N, 3) world, metres
    valid: np.ndarray,  # (N,) bool
    head_cols: np.ndarray,  # (H,) int64
    face_cols: np.ndarray,  # (M,) int64
    layout: np.ndarray,  # (H, 3)
    head_w: np.ndarray,  # (H,)
    neutral: np.ndarray,  # (M, 3)
    basis: np.ndarray,  # (3M, K + 6): the solved shapes' columns, then the pose's
    a_full: np.ndarray,  # (K + 6, K + 6) = basis^T basis + lambda I on the shapes
    a: np.ndarray,  # (K + 6, K + 6) scratch: restricted normal matrix (kept)
    last_seen: np.ndarray,  # (M + H,) bool: pattern a was built for (facial, head)
    seen: np.ndarray,  # (M + H,) bool scratch
    b: np.ndarray,  # (K + 6,) scratch
    ared: np.ndarray,  # (K, K) the pose eliminated (_reduce_pose), kept
    schur: np.ndarray,  # (K, 6) kept with ared
    c6: np.ndarray,  # (6, 6) scratch
    bred: np.ndarray,  # (K,) scratch
    w_prev: np.ndarray,  # (K,) last good weights (warm start), updated
    state: np.ndarray,  # (K,) int64 scratch, kept between frames
    idx: np.ndarray,
    chol: np.ndarray,
    x: np.ndarray,
    g: np.ndarray,
    n44: np.ndarray,
    v44: np.ndarray,
    q4: np.ndarray,
    rot: np.ndarray,  # (3, 3) world_from_head, kept (held when lost)
    pos: np.ndarray,  # (3,) kept (held when lost)
    have_good: np.ndarray,  # (1,) bool
    cen: np.ndarray,  # (6,) scratch: the head fit's centroids
    max_iter: int,
    solved_cols: np.ndarray,  # (K,) int64: each solved shape's output index
    key_ptr: np.ndarray,  # (K + 1,) int64: shape j's key markers are
    key_idx: np.ndarray,  # key_idx[key_ptr[j]:key_ptr[j + 1]] (facial indices)
    wr: np.ndarray,  # (K,) scratch: the solved shapes' weights
    out_markers: np.ndarray,  # (M, 3)
    out_w: np.ndarray,  # (K_all,): unsolved shapes stay 0
    out_quat: np.ndarray,  # (4,)
    out_pos: np.ndarray,  # (3,)
    out_status: np.ndarray,  # (3,) int64
    out_state: np.ndarray,  # (K_all,) uint8: SHAPE_* bits (unobserved preset)
) -> None:
    # K here counts the solved shapes; out_w and out_state hold every shape of the
    # training set, and solved_cols says where each solved one goes. With K > 0 the
    # least squares has 6 more variables, unbounded: the small correction (tau,
    # theta) of the head pose that the facial markers see, whose prior information
    # is the head markers' own (G, _add_pose_prior); they are eliminated before the
    # box QP (_reduce_pose). With K = 0 there are none (a is 0 x 0).
    m = face_cols.shape[0]
    nh = head_cols.shape[0]
    k = solved_cols.shape[0]
    n = a.shape[0]
    flags = 0
    used = _fit_head(
        markers, valid, head_cols, layout, head_w, n44, v44, q4, rot, pos, cen
    )
    if used == 0:
        flags |= FLAG_HEAD_LOST
        if not have_good[0]:
            flags |= FLAG_NEVER
        for i in range(m):
            out_markers[i, 0] = out_markers[i, 1] = out_markers[i, 2] = np.nan
        for j in range(k):
            out_w[solved_cols[j]] = w_prev[j]
        out_status[0] = flags
        out_status[1] = 0
        out_status[2] = 0
        # q4 / pos still hold the last good pose (the fit returns before writing).
        for j in range(4):
            out_quat[j] = q4[j] if have_good[0] else (1.0 if j == 0 else 0.0)
        for j in range(3):
            out_pos[j] = pos[j] if have_good[0] else 0.0
        return
    if used < nh:
        flags |= FLAG_HEAD_PARTIAL
    # Stabilize: p_head = R^T (p_world - t).
    nvis = 0
    changed = False
    for i in range(m):
        c = face_cols[i]
        ok = c >= 0 and valid[c]
        if ok:
            px, py, pz = (
                markers[c, 0] - pos[0],
                markers[c, 1] - pos[1],
                markers[c, 2] - pos[2],
            )
            hx = rot[0, 0] * px + rot[1, 0] * py + rot[2, 0] * pz
            hy = rot[0, 1] * px + rot[1, 1] * py + rot[2, 1] * pz
            hz = rot[0, 2] * px + rot[1, 2] * py + rot[2, 2] * pz
            ok = math.isfinite(hx) and math.isfinite(hy) and math.isfinite(hz)
        if ok:
            out_markers[i, 0], out_markers[i, 1], out_markers[i, 2] = hx, hy, hz
            nvis += 1
        else:
            out_markers[i, 0] = out_markers[i, 1] = out_markers[i, 2] = np.nan
        seen[i] = ok
        if ok != last_seen[i]:
            changed = True
    for i in range(nh):  # the head markers the fit used (as horn_fit picks them)
        c = head_cols[i]
        ok = c >= 0 and valid[c] and head_w[i] > 0.0
        if ok:
            ok = (
                math.isfinite(markers[c, 0])
                and math.isfinite(markers[c, 1])
                and math.isfinite(markers[c, 2])
            )
        seen[m + i] = ok
        if ok != last_seen[m + i]:
            changed = True
    if nvis < m:
        flags |= FLAG_FACE_PARTIAL
    if changed:
        # A = A_full - sum over occluded markers of B_m^T B_m, + the pose prior G.
        for p in range(n):
            for q in range(n):
                a[p, q] = a_full[p, q]
        for i in range(m + nh):
            last_seen[i] = seen[i]
        for i in range(m):
            if seen[i]:
                continue
            for r in range(3 * i, 3 * i + 3):
                for p in range(n):
                    brp = basis[r, p]
                    if brp == 0.0:
                        continue
                    for q in range(n):
                        a[p, q] -= brp * basis[r, q]
        if n > k:
            _add_pose_prior(a, k, layout, head_w, seen[m:])
            _reduce_pose(a, k, ared, schur, c6)
    for p in range(n):
        b[p] = 0.0
    for i in range(m):
        if not seen[i]:
            continue
        for c in range(3):
            d = out_markers[i, c] - neutral[i, c]
            r = 3 * i + c
            for p in range(n):
                b[p] += basis[r, p] * d
    # A shape whose key markers are hidden is held at its last weight (state 3: a
    # fixed variable of the QP), so it neither guesses nor pollutes the others.
    for j in range(k):
        hidden = False
        for p in range(key_ptr[j], key_ptr[j + 1]):
            if not seen[key_idx[p]]:
                hidden = True
                break
        if hidden:
            state[j] = 3
            flags |= FLAG_SHAPE_HELD
            out_state[solved_cols[j]] = SHAPE_HIDDEN
        else:
            if state[j] == 3:
                state[j] = 0
            out_state[solved_cols[j]] = 0
        wr[j] = w_prev[j]
    for p in range(k):
        s = b[p]
        for r in range(n - k):
            s -= schur[p, r] * b[k + r]
        bred[p] = s
    iters = _box_qp(ared, bred, wr, state, idx, chol, x, g, max_iter)
    if iters < 0:
        flags |= FLAG_NOT_CONVERGED
        iters = max_iter
    for j in range(k):
        w_prev[j] = wr[j]
        out_w[solved_cols[j]] = wr[j]
    for j in range(4):
        out_quat[j] = q4[j]
    for j in range(3):
        out_pos[j] = pos[j]
    have_good[0] = True
    out_status[0] = flags
    out_status[1] = iters
    out_status[2] = nvis
