"""The prop's per-frame rigid fit (numba, no allocation): one call per prop per frame.

Given the prop's layout (K markers in the prop frame), the frame's markers and which
of them are the prop's, :func:`solve_prop` writes ``world_from_prop`` (a quaternion
w x y z and the origin's position) and the frame's statistics:

1. **Seen**: a marker of the prop whose row is present, valid and finite.
2. **Consensus** (the swap check, pose-free): a rigid body keeps its distances, so
   each seen marker counts the others whose distance to it differs from the layout's
   by more than the gate; the one with the most is dropped, until the rest agree.
   A swap of two labels leaves their own distance but breaks theirs to every other
   marker, so both go (a sword of 4 with 2 swapped keeps 2: the pose is held). Two
   dropped markers that agree with the kept ones once their labels are exchanged
   are counted as a swap (``FLAG_SWAP``). When the kept markers and the swaps do
   not explain every seen marker, every agreeing pair and triple is tried as a seed
   instead (three markers agree as their own mirror image too; the set that
   explains the most, two per recognized swap, wins). Fewer than 3 kept: the last
   pose is held and flagged ``FLAG_HELD``.
3. **Fit**: Horn's weighted closed form (``compiled.horn_fit``, the fit the body's
   rigid-segment rebuild and the face's head stabilization share) over the kept
   markers, then every seen marker within the gate rejoins, and iteratively
   reweighted with the Cauchy loss: weight ``w_i / (1 + (r_i / c)^2)`` (the body
   fit's robust loss, ``body/kernel_fit``), ``P_IRLS_ITER`` times.
4. **Gate**: while the worst marker's residual exceeds ``gate_m``, it is left out
   and the others refitted; it stays out when its residual to their fit exceeds
   ``max(gate_m, gate_k x their median residual)`` (the body fit's gate,
   ``body/fit_track.mark_outliers``, on a deletion residual: with 4 or 5 markers one
   outlier drags the fit and hides its own size; and without the body's memory of
   each marker's residual: a rigid cluster has no skin sliding to follow).

Flags are the pose stream's prop flags (``protocols/pose_stream.PROP_FLAG_BITS``).
"""

from __future__ import annotations

import math

import numpy as np

from retargetd.daemon.compiled import horn_fit, kernel

# params slots (``solve.PropParams``)
P_GATE_M = 0
P_GATE_K = 1
P_CAUCHY_M = 2
P_IRLS_ITER = 3
N_PARAMS = 4

# state slots: the last solved pose, and whether there is one
ST_QUAT = 0  # 4: world_from_prop w x y z
ST_POS = 4  # 3: the prop origin, metres, world
ST_HAVE = 7
N_STATE = 8

# stats slots
S_SEEN = 0  # markers of the prop seen this frame
S_USED = 1  # markers the pose was fitted to
S_REJECTED = 2  # seen but left out (consensus or gate)
S_SWAPS = 3  # label swaps recognized among them
S_RMS_M = 4  # RMS residual of the used markers, metres (NaN when held)
S_GATE_M = 5  # this frame's gate, metres
S_FLAGS = 6
N_STATS = 7

#: Props up to this many markers search every agreeing pair and triple when the
#: greedy consensus leaves seen markers unexplained (C(12, 3) + C(12, 2) = 286 seeds
#: at most).
MAX_SEARCH_MARKERS = 12

FLAG_HELD = 1  # fewer than 3 markers agree: the last good pose, held
FLAG_PARTIAL = 2  # solved, with some of its markers unseen or rejected
FLAG_SWAP = 4  # a label swap among its markers was seen (and left out)
FLAG_NEVER = 8  # no pose yet since the stream began: identity at the origin


@kernel
def _dist(a: np.ndarray, i: int, b: np.ndarray, j: int) -> float:
    dx = a[i, 0] - b[j, 0]
    dy = a[i, 1] - b[j, 1]
    dz = a[i, 2] - b[j, 2]
    return math.sqrt(dx * dx + dy * dy + dz * dz)


@kernel
def _agrees(
    layout_d: np.ndarray, pts: np.ndarray, cols: np.ndarray, keep: np.ndarray,
    i: int, as_i: int, tol: float,
) -> bool:  # fmt: skip
    # Whether marker i's point, read as layout marker as_i, keeps its distances to
    # every kept marker (and there is at least one).
    n = 0
    for m in range(keep.shape[0]):
        if not keep[m] or m in (i, as_i):
            continue
        if abs(_dist(pts, cols[i], pts, cols[m]) - layout_d[as_i, m]) > tol:
            return False
        n += 1
    return n > 0


@kernel
def _residuals(
    layout: np.ndarray, pts: np.ndarray, cols: np.ndarray, seen: np.ndarray,
    r: np.ndarray, t: np.ndarray, res: np.ndarray,
) -> None:  # fmt: skip
    for i in range(layout.shape[0]):
        if not seen[i]:
            res[i] = math.inf
            continue
        c = cols[i]
        s = 0.0
        for a in range(3):
            p = r[a, 0] * layout[i, 0] + r[a, 1] * layout[i, 1] + r[a, 2] * layout[i, 2]
            d = p + t[a] - pts[c, a]
            s += d * d
        res[i] = math.sqrt(s)


@kernel
def _median_kept(res: np.ndarray, keep: np.ndarray, tmp: np.ndarray) -> float:
    n = 0
    for i in range(res.shape[0]):
        if keep[i]:
            v = res[i]
            j = n
            while j > 0 and tmp[j - 1] > v:  # insertion sort (K <= 32)
                tmp[j] = tmp[j - 1]
                j -= 1
            tmp[j] = v
            n += 1
    if n == 0:
        return 0.0
    return tmp[n // 2] if n % 2 == 1 else 0.5 * (tmp[n // 2 - 1] + tmp[n // 2])


@kernel
def _fit(
    layout: np.ndarray, pts: np.ndarray, cols: np.ndarray, valid: np.ndarray,
    w_eff: np.ndarray, n44: np.ndarray, v44: np.ndarray, q4: np.ndarray,
    cen: np.ndarray, t: np.ndarray,
) -> int:  # fmt: skip
    # Horn's fit; on success n44[:3, :3] = R and t = the prop origin (world).
    n = horn_fit(layout, pts, cols, valid, w_eff, n44, v44, q4, cen)
    if n == 0:
        return 0
    for a in range(3):
        t[a] = cen[3 + a] - (
            n44[a, 0] * cen[0] + n44[a, 1] * cen[1] + n44[a, 2] * cen[2]
        )
    return n


@kernel
def _greedy_consensus(
    layout_d: np.ndarray, pts: np.ndarray, cols: np.ndarray, keep: np.ndarray,
    gate_m: float,
) -> None:  # fmt: skip
    # Drop the marker with the most distances off the layout's (ties: the larger
    # summed excess) until the kept ones all agree.
    k = keep.shape[0]
    while True:
        worst = -1
        worst_n = 0
        worst_e = 0.0
        for i in range(k):
            if not keep[i]:
                continue
            n_bad = 0
            excess = 0.0
            for j in range(k):
                if j != i and keep[j]:
                    e = abs(_dist(pts, cols[i], pts, cols[j]) - layout_d[i, j])
                    excess += e
                    if e > gate_m:
                        n_bad += 1
            if n_bad > worst_n or (n_bad == worst_n and n_bad > 0 and excess > worst_e):
                worst_n = n_bad
                worst_e = excess
                worst = i
        if worst < 0:
            return
        keep[worst] = False


@kernel
def _explained(
    layout_d: np.ndarray, pts: np.ndarray, cols: np.ndarray, seen: np.ndarray,
    keep: np.ndarray, gate_m: float,
) -> tuple[int, int]:  # fmt: skip
    # (markers kept, swaps recognized): two left-out markers that agree with the
    # kept ones once their labels are exchanged.
    k = keep.shape[0]
    n_keep = 0
    for i in range(k):
        if keep[i]:
            n_keep += 1
    swaps = 0
    for i in range(k):
        for j in range(i + 1, k):
            if (
                seen[i]
                and seen[j]
                and not keep[i]
                and not keep[j]
                and _agrees(layout_d, pts, cols, keep, i, j, gate_m)
                and _agrees(layout_d, pts, cols, keep, j, i, gate_m)
            ):
                swaps += 1
    return n_keep, swaps


@kernel
def _fit_cauchy(
    layout: np.ndarray, pts: np.ndarray, cols: np.ndarray, valid: np.ndarray,
    weights: np.ndarray, keep: np.ndarray, res: np.ndarray, c2: float,
    w_eff: np.ndarray, n44: np.ndarray, v44: np.ndarray, q4: np.ndarray,
    cen: np.ndarray, t: np.ndarray,
) -> int:  # fmt: skip
    # One reweighted fit: the kept markers at their Cauchy weights for ``res``.
    for i in range(keep.shape[0]):
        w_eff[i] = weights[i] / (1.0 + res[i] * res[i] / c2) if keep[i] else 0.0
    return _fit(layout, pts, cols, valid, w_eff, n44, v44, q4, cen, t)


@kernel
def solve_prop(
    layout: np.ndarray,
    layout_d: np.ndarray,
    weights: np.ndarray,
    cols: np.ndarray,
    pts: np.ndarray,
    valid: np.ndarray,
    params: np.ndarray,
    state: np.ndarray,
    quat: np.ndarray,
    pos: np.ndarray,
    stats: np.ndarray,
    scratch: np.ndarray,
    seen: np.ndarray,
    keep: np.ndarray,
    alt: np.ndarray,
    n44: np.ndarray,
    v44: np.ndarray,
) -> int:
    """One prop, one frame (see the module docstring). Returns the flags.

    Args:
        layout: (K, 3) the prop's markers in its frame, metres.
        layout_d: (K, K) their distances, metres.
        weights: (K,) each marker's weight (0: never used).
        cols: (K,) int64 row of ``pts`` of each marker, -1 = not in the stream.
        pts, valid: (N, 3) the frame's markers (world, metres) and (N,) bool.
        params: (N_PARAMS,) gate, Cauchy scale, iterations.
        state: (N_STATE,) the last solved pose (updated).
        quat, pos: (4,), (3,) out: world_from_prop, w x y z, and its origin.
        stats: (N_STATS,) out.
        scratch: (4K + 14,) float64; seen, keep, alt: (K,) bool scratch.
        n44, v44: (4, 4) scratch.
    """
    k = layout.shape[0]
    gate_m = params[P_GATE_M]
    w_eff = scratch[0:k]
    res = scratch[k : 2 * k]
    tmp = scratch[2 * k : 3 * k]
    q4 = scratch[3 * k : 3 * k + 4]
    cen = scratch[3 * k + 4 : 3 * k + 10]
    t = scratch[3 * k + 10 : 3 * k + 13]
    n_seen = 0
    for i in range(k):
        c = cols[i]
        ok = c >= 0 and weights[i] > 0.0
        if ok:
            ok = bool(valid[c]) and (
                math.isfinite(pts[c, 0])
                and math.isfinite(pts[c, 1])
                and math.isfinite(pts[c, 2])
            )
        seen[i] = ok
        keep[i] = ok
        if ok:
            n_seen += 1
    # 2. consensus of distances
    # (ties: the larger summed excess goes)
    _greedy_consensus(layout_d, pts, cols, keep, gate_m)
    n_keep, swaps = _explained(layout_d, pts, cols, seen, keep, gate_m)
    if n_keep + 2 * swaps < n_seen and k <= MAX_SEARCH_MARKERS:
        # not every seen marker is explained: seed from every agreeing pair and
        # triple, grow it by the markers that agree with all of it, and keep the
        # set that explains most (its markers, plus two per recognized swap). A
        # triangle has no handedness, so three markers alone may agree as a mirror
        # image: the swap that explains the rest tells the true set from it.
        for i in range(k):
            alt[i] = keep[i]
        best_score = n_keep + 2 * swaps
        best_keep = n_keep
        for a in range(k):
            for b in range(a + 1, k):
                for c in range(b, k):  # c == b: the pair (a, b) alone as the seed
                    if not (seen[a] and seen[b] and seen[c]):
                        continue
                    for i in range(k):
                        keep[i] = i in (a, b, c)
                    if not _agrees(layout_d, pts, cols, keep, a, a, gate_m):
                        continue
                    if c != b and not _agrees(layout_d, pts, cols, keep, b, b, gate_m):
                        continue
                    for m in range(k):
                        if (
                            seen[m]
                            and not keep[m]
                            and _agrees(layout_d, pts, cols, keep, m, m, gate_m)
                        ):
                            keep[m] = True
                    nk, sw = _explained(layout_d, pts, cols, seen, keep, gate_m)
                    if nk + 2 * sw > best_score or (
                        nk + 2 * sw == best_score and nk > best_keep
                    ):
                        best_score = nk + 2 * sw
                        best_keep = nk
                        for i in range(k):
                            alt[i] = keep[i]
        for i in range(k):
            keep[i] = alt[i]
        n_keep, swaps = _explained(layout_d, pts, cols, seen, keep, gate_m)
    flags = FLAG_SWAP if swaps > 0 else 0
    gate = gate_m
    n_used = 0
    if n_keep >= 3:
        # 3. fit on the consensus, readmit within the gate, Cauchy reweighting
        for i in range(k):
            w_eff[i] = weights[i] if keep[i] else 0.0
        n_used = _fit(layout, pts, cols, valid, w_eff, n44, v44, q4, cen, t)
        if n_used > 0:
            _residuals(layout, pts, cols, seen, n44, t, res)
            gate = max(gate_m, params[P_GATE_K] * _median_kept(res, keep, tmp))
            for i in range(k):
                keep[i] = seen[i] and res[i] <= gate
            c2 = params[P_CAUCHY_M] * params[P_CAUCHY_M]
            for _it in range(int(params[P_IRLS_ITER])):
                n_used = _fit_cauchy(
                    layout,
                    pts,
                    cols,
                    valid,
                    weights,
                    keep,
                    res,
                    c2,
                    w_eff,
                    n44,
                    v44,
                    q4,
                    cen,
                    t,
                )
                if n_used == 0:
                    break
                _residuals(layout, pts, cols, seen, n44, t, res)
            # 4. the gate, on deletion residuals: while a marker is beyond gate_m,
            # each kept marker is left out in turn and the others refitted; the one
            # whose absence fits the rest best is rejected when its residual to
            # their fit exceeds max(gate_m, gate_k x their median residual). With
            # 4 or 5 markers one outlier drags the fit and hides its own size.
            while n_used > 3:
                worst_res = 0.0
                for i in range(k):
                    if keep[i] and res[i] > worst_res:
                        worst_res = res[i]
                if worst_res <= gate_m:
                    break
                best = -1
                best_ss = math.inf
                for i in range(k):
                    if not keep[i]:
                        continue
                    keep[i] = False
                    for j in range(k):
                        w_eff[j] = weights[j] if keep[j] else 0.0
                    if _fit(layout, pts, cols, valid, w_eff, n44, v44, q4, cen, t) > 0:
                        _residuals(layout, pts, cols, seen, n44, t, tmp)
                        ss = 0.0
                        for j in range(k):
                            if keep[j]:
                                ss += tmp[j] * tmp[j]
                        if ss < best_ss:
                            best_ss = ss
                            best = i
                    keep[i] = True
                if best < 0:
                    break
                keep[best] = False
                for j in range(k):
                    w_eff[j] = weights[j] if keep[j] else 0.0
                n_new = _fit(layout, pts, cols, valid, w_eff, n44, v44, q4, cen, t)
                _residuals(layout, pts, cols, seen, n44, t, res)
                gate = max(gate_m, params[P_GATE_K] * _median_kept(res, keep, tmp))
                keep[best] = res[best] <= gate
                n_used = _fit_cauchy(
                    layout,
                    pts,
                    cols,
                    valid,
                    weights,
                    keep,
                    res,
                    c2,
                    w_eff,
                    n44,
                    v44,
                    q4,
                    cen,
                    t,
                )
                _residuals(layout, pts, cols, seen, n44, t, res)
                if keep[best] or n_new == 0:
                    break
    stats[S_SEEN] = n_seen
    stats[S_SWAPS] = swaps
    stats[S_GATE_M] = gate
    if n_used < 3:
        # held: the last good pose (identity at the origin before the first)
        flags |= FLAG_HELD
        if state[ST_HAVE] > 0.0:
            for a in range(4):
                quat[a] = state[ST_QUAT + a]
            for a in range(3):
                pos[a] = state[ST_POS + a]
        else:
            flags |= FLAG_NEVER
            quat[0], quat[1], quat[2], quat[3] = 1.0, 0.0, 0.0, 0.0
            pos[0], pos[1], pos[2] = 0.0, 0.0, 0.0
        stats[S_USED] = 0
        stats[S_REJECTED] = n_seen
        stats[S_RMS_M] = math.nan
        stats[S_FLAGS] = flags
        return flags
    # sign-continuous with the last pose sent (engines blend: STYLE.md 3)
    sgn = 1.0
    if state[ST_HAVE] > 0.0:
        dot = (
            q4[0] * state[ST_QUAT] + q4[1] * state[ST_QUAT + 1]
            + q4[2] * state[ST_QUAT + 2] + q4[3] * state[ST_QUAT + 3]
        )  # fmt: skip
        if dot < 0.0:
            sgn = -1.0
    ss = 0.0
    n_in = 0
    for i in range(k):
        if keep[i] and w_eff[i] > 0.0:
            ss += res[i] * res[i]
            n_in += 1
    for a in range(4):
        quat[a] = sgn * q4[a]
        state[ST_QUAT + a] = quat[a]
    for a in range(3):
        pos[a] = t[a]
        state[ST_POS + a] = t[a]
    state[ST_HAVE] = 1.0
    if n_in < k:
        flags |= FLAG_PARTIAL
    stats[S_USED] = n_in
    stats[S_REJECTED] = n_seen - n_in
    stats[S_RMS_M] = math.sqrt(ss / n_in)
    stats[S_FLAGS] = flags
    return flags
