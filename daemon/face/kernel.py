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
def solve_face_frame(
    markers: np.ndarray,  # (N, 3) world, metres
    valid: np.ndarray,  # (N,) bool
    head_cols: np.ndarray,  # (H,) int64
    face_cols: np.ndarray,  # (M,) int64
    layout: np.ndarray,  # (H, 3)
    head_w: np.ndarray,  # (H,)
    neutral: np.ndarray,  # (M, 3)
    basis: np.ndarray,  # (3M, K) the solved shapes' columns only
    a_full: np.ndarray,  # (K, K) = B^T B + lambda I
    a: np.ndarray,  # (K, K) scratch: restricted normal matrix (kept between frames)
    last_seen: np.ndarray,  # (M,) bool: pattern a was built for
    seen: np.ndarray,  # (M,) bool scratch
    b: np.ndarray,  # (K,) scratch
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
    # training set, and solved_cols says where each solved one goes.
    m = face_cols.shape[0]
    k = a.shape[0]
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
    if used < head_cols.shape[0]:
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
    if nvis < m:
        flags |= FLAG_FACE_PARTIAL
    if changed:
        # A = A_full - sum over occluded markers of B_m^T B_m.
        for p in range(k):
            for q in range(k):
                a[p, q] = a_full[p, q]
        for i in range(m):
            last_seen[i] = seen[i]
            if seen[i]:
                continue
            for r in range(3 * i, 3 * i + 3):
                for p in range(k):
                    brp = basis[r, p]
                    if brp == 0.0:
                        continue
                    for q in range(k):
                        a[p, q] -= brp * basis[r, q]
    for p in range(k):
        b[p] = 0.0
    for i in range(m):
        if not seen[i]:
            continue
        for c in range(3):
            d = out_markers[i, c] - neutral[i, c]
            r = 3 * i + c
            for p in range(k):
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
    iters = _box_qp(a, b, wr, state, idx, chol, x, g, max_iter)
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
