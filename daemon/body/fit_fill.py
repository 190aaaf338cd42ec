"""A hidden marker filled from the markers that moved rigidly with it (numba).

Marker space, no model: per marker pair a running mean and variance of their distance
(exponentially weighted over the level's time constant, ``level_tau_s``, on explained
frames, accepted markers only). When a marker hides, the seen markers most rigid with
it (its donors) and its position among them at its last accepted frame are kept; each
hidden frame it is placed where their least-squares rigid fit (Horn's closed form,
``compiled.horn_fit``) carries it now: Vicon Nexus's "rigid body fill"; Howarth &
Callaghan, "Quantitative assessment of the accuracy for three interpolation
techniques in kinematic analysis of human movement", CMBBE 13(6):847-855, 2010;
Gloersen & Federolf, PLoS ONE 11(3):e0152616, 2016 for the correlation-based kind.
It is right where the model misfits (a marker on a segment the rig models rigid that
is not) and it is causal. Donors come only from the hidden marker's own bone and the
bones proximal to it (its ancestors in the rig): by forward kinematics its position
is a function of those bones' poses alone, while a distal donor is carried by the
joints between (the elbow and the wrist for an upper-arm marker), which can flex
with the donors still rigid with each other (the PiG walk's LELB, filled from the
wrist and finger markers, ran 33 mm off in 0.25 s as the wrist flexed). Where no
rigid set of donors exists the fit's model stand-in (``fit_track.virtual_markers``)
is unchanged.

Model: m[26] (P, 2) the pairs whose statistics are kept (:func:`chain_pairs`: only
those the donor rule can read, a marker and one on its own bone or on a proximal or
distal one; Plug-in Gait's 34 markers: 244 of 561 pairs). State
(``solve_fit.FitSolver``): s[60] (M, M, 3) per pair (in the row of its lower index;
zero for a pair not in m[26]) the distance's running mean, variance and coverage
(1 - exp(-t / tau) after t seconds seen together); s[61] (M, K) each marker's donors
(-1: none); s[62] (M, K + 1, 3) the donors' positions and the marker's own (row K) at
its last accepted frame; s[63] (M, 5) the last accepted position (0:3), the donors'
mean distance variance at the hide (3) and this frame's fill weight (4; 0: not
filled); s[64] (48,) scratch.
"""

from __future__ import annotations

import math

import numpy as np

from retargetd.daemon.body.fit_terms import (
    C_DT,
    C_LEVEL,
    P_LEVEL_TAU_S,
    P_NOISE_M,
    P_RESOLUTION_RAD,
)
from retargetd.daemon.compiled import horn_fit, jacobi_eigen, kernel

#: Donors per hidden marker: three fix a rigid frame, a fourth makes the fit
#: overdetermined so its misfit measures how rigid the set still is.
N_DONORS = 4
#: The coverage a pair's statistics need before its rigidity counts: seen together over
#: the statistics' own time constant (1 - 1/e). Over less the variance speaks for less
#: of the motion than it claims to: on the PiG walk 0.3 s in (coverage 0.26) the
#: left elbow marker was "rigid" with C7, both shoulders and the head (SD 1-3 mm) and
#: filled from them ran 53 mm off in 0.25 s as the arm began to swing.
MIN_COVERAGE = 1.0 - math.exp(-1.0)
#: Whether a filled marker's hold (``fit_track.hold_priors``) is dropped: the fill
#: measures what the marker alone saw. Measured both ways (h28g, on 2882d7f, before
#: the proximal-donor rule; bench/hide_sweep.py, past a limit, PiG / menache / the
#: walk at 0.25 and 1 s): held 10 / 11, 8 / 12, 14 / 17; dropped 8 / 10, 8 / 12,
#: 14 / 17 (the shoulders held against the fill: PiG's LSHO 1 s 155 -> 15 mm; the
#: walk's elbows the other way, RELB from row 150 1 s 14 -> 19 mm).
FILL_DROPS_HOLD = True


@kernel
def _on_chain(parent: np.ndarray, a: int, b: int) -> bool:
    # bone b is bone a or one of its ancestors in the rig
    k = a
    while k >= 0:
        if k == b:
            return True
        k = parent[k]
    return False


def chain_pairs(parent: np.ndarray, mk_bone: np.ndarray) -> np.ndarray:
    """The marker pairs ``(i, k)``, ``i < k``, whose statistics the donor rule can
    read (m[26]): one marker's bone is the other's or an ancestor of it. A donor is
    on the hidden marker's chain (``_on_chain``) and so is every other donor, and
    two bones on one chain are one the other's ancestor; no other pair is read.
    Rows in the order of the full double loop, ``(P, 2)`` int64."""
    chain: list[set[int]] = []  # each bone and its ancestors
    for b in range(len(parent)):
        up: set[int] = set()
        k = b
        while k >= 0:
            up.add(k)
            k = int(parent[k])
        chain.append(up)
    bone = [int(b) for b in mk_bone]
    n = len(bone)
    rows = [
        (i, k)
        for i in range(n)
        for k in range(i + 1, n)
        if min(bone[i], bone[k]) >= 0  # (a marker on no bone: on no chain)
        and (bone[k] in chain[bone[i]] or bone[i] in chain[bone[k]])
    ]
    return np.array(rows, dtype=np.int64).reshape((len(rows), 2))


@kernel
def fill_update(m: tuple, s: tuple) -> None:
    """On an explained frame: each accepted marker's position, and the running
    distance statistics of each chain pair (:func:`chain_pairs`) accepted together."""
    params, sc, wt = m[18], s[36], m[7]
    vis, rej, meas = s[13], s[45], s[12]
    pairs, pair, mem = m[26], s[60], s[63]
    tau = params[P_LEVEL_TAU_S]
    a = min(1.0, sc[C_DT] / tau) if tau > 0.0 else 1.0
    n = vis.shape[0]
    for i in range(n):
        if not vis[i] or rej[i] or wt[i] <= 0.0:
            continue
        for j in range(3):
            mem[i, j] = meas[i, j]
    for r in range(pairs.shape[0]):
        i, k = pairs[r, 0], pairs[r, 1]
        if not (vis[i] and vis[k]) or rej[i] or rej[k]:
            continue
        if wt[i] <= 0.0 or wt[k] <= 0.0:
            continue
        dx = meas[i, 0] - meas[k, 0]
        dy = meas[i, 1] - meas[k, 1]
        dz = meas[i, 2] - meas[k, 2]
        d = math.sqrt(dx * dx + dy * dy + dz * dz)
        # exponentially weighted mean and variance, bias-corrected by the
        # coverage (the first sample weighs 1): West, "Updating mean and
        # variance estimates", CACM 22(9):532-535, 1979
        c = pair[i, k, 2] + a * (1.0 - pair[i, k, 2])
        b = a / c
        dm = d - pair[i, k, 0]
        pair[i, k, 0] += b * dm
        pair[i, k, 1] = (1.0 - b) * (pair[i, k, 1] + b * dm * dm)
        pair[i, k, 2] = c


@kernel
def _pair(pair: np.ndarray, i: int, j: int, k: int) -> float:
    # a pair's statistic k: kept in the row of its lower index only (a value, not
    # the row: kernel_fit.fit_one_t compiles without reference counting, and numba
    # refuses to compile a function that returns a view without it, so a kernel
    # returning the row here would fail loudly at compile time)
    return pair[i, j, k] if i < j else pair[j, i, k]


@kernel
def _choose_donors(m: tuple, s: tuple, i: int) -> None:
    # Marker i accepted in the last explained frame and hidden now: from the seen
    # markers accepted in that frame too (their last positions are from it) on its
    # own bone or a bone proximal to it (its ancestors in the rig), the set rigid
    # with it and with each other, picked greedily: each next donor the
    # one whose largest distance variance, to i and to the donors already picked, is
    # smallest (a knee marker is rigid with the thigh's and with the shank's, but
    # the two are not rigid with each other). A pair counts when its distance
    # varies by less than what a seen marker misses the model by (the take's level,
    # at least the noise): a fill no better than that is no better than the model's
    # stand-in.
    params, sc, wt = m[18], s[36], m[7]
    parent, mk_bone = m[0], m[5]
    vis, rage = s[13], s[48]
    pair, donors, ref, mem, scr = s[60], s[61], s[62], s[63], s[64]
    n = vis.shape[0]
    for k in range(N_DONORS):
        donors[i, k] = -1
    mem[i, 3] = 0.0
    lim = max(params[P_NOISE_M], sc[C_LEVEL]) ** 2
    nd = 0
    for _pick in range(N_DONORS):
        best = -1
        bv = math.inf
        for j in range(n):
            if j == i or not vis[j] or wt[j] <= 0.0 or rage[j] != 0.0:
                continue
            if _pair(pair, i, j, 2) < MIN_COVERAGE:
                continue
            if not _on_chain(parent, mk_bone[i], mk_bone[j]):
                continue
            v = _pair(pair, i, j, 1)
            for k in range(nd):
                d = donors[i, k]
                if d == j or _pair(pair, j, d, 2) < MIN_COVERAGE:
                    v = math.inf
                else:
                    v = max(v, _pair(pair, j, d, 1))
            if v <= lim and v < bv:
                best, bv = j, v
        if best < 0:
            break
        donors[i, nd] = best
        nd += 1
    if nd < 3:
        donors[i, 0] = -1
        return
    # Spread: the donors' second principal extent (RMS distance from their best
    # line) at least noise / resolution (11.5 mm: fit_observe's threshold for a
    # rotation the markers observe), else the turn about their line is not resolved
    # to the joint-angle resolution and the fill swings with the noise.
    cx = cy = cz = 0.0
    for k in range(nd):
        d = donors[i, k]
        cx += mem[d, 0] / nd
        cy += mem[d, 1] / nd
        cz += mem[d, 2] / nd
    a3 = scr[0:16].reshape((4, 4))[:3, :3]
    v3 = scr[16:32].reshape((4, 4))[:3, :3]
    for r in range(3):
        for c in range(3):
            a3[r, c] = 0.0
    for k in range(nd):
        d = donors[i, k]
        p = (mem[d, 0] - cx, mem[d, 1] - cy, mem[d, 2] - cz)
        for r in range(3):
            for c in range(3):
                a3[r, c] += p[r] * p[c] / nd
    jacobi_eigen(a3, v3)
    e0, e1, e2 = a3[0, 0], a3[1, 1], a3[2, 2]
    mid = max(min(e0, e1), min(max(e0, e1), e2))
    spread = params[P_NOISE_M] / params[P_RESOLUTION_RAD]
    if mid < spread * spread:
        donors[i, 0] = -1
        return
    var = 0.0
    for k in range(nd):
        d = donors[i, k]
        var += _pair(pair, i, d, 1) / nd
        for j in range(3):
            ref[i, k, j] = mem[d, j]
    for j in range(3):
        ref[i, N_DONORS, j] = mem[i, j]
    mem[i, 3] = var


@kernel
def rigid_fill(m: tuple, s: tuple, known: bool) -> None:
    """Hidden markers placed by their donors' rigid fit: their measurement (s[12])
    and weight (s[58]) set and s[63][:, 4] marked, where the donors still seen fix a
    frame and the expected error is under the take's level; donors chosen at a marker's
    first hidden frame. ``known``: the fit's prediction is one (no gap), else only
    the donors are chosen (the fill is used as the model stand-in is)."""
    params, sc, wt = m[18], s[36], m[7]
    vis, rage, meas, virt = s[13], s[48], s[12], s[58]
    pair, donors, ref, mem, scr = s[60], s[61], s[62], s[63], s[64]
    n = vis.shape[0]
    n44 = scr[0:16].reshape((4, 4))
    v44 = scr[16:32].reshape((4, 4))
    q4 = scr[32:36]
    cen = scr[36:42]
    wts = scr[42 : 42 + N_DONORS]
    for i in range(n):
        mem[i, 4] = 0.0
        if vis[i] or wt[i] <= 0.0 or rage[i] == math.inf:
            continue
        if rage[i] == 0.0:
            _choose_donors(m, s, i)
        if not known or donors[i, 0] < 0:
            continue
        # each donor weighed by how rigid it is with the marker: 1 / (its distance
        # variance + the noise's), so a donor that moves a little (a shoulder
        # marker for the sternum) only fixes what the others leave open
        n2 = params[P_NOISE_M] ** 2
        for k in range(N_DONORS):
            d = donors[i, k]
            wts[k] = 1.0 / (n2 + _pair(pair, i, d, 1)) if d >= 0 else 0.0
        lay = ref[i, :N_DONORS]
        used = horn_fit(lay, meas, donors[i], vis, wts, n44, v44, q4, cen)
        if used < 3:
            continue
        # the donors' weighted misfit now: how far the set has bent since the hide
        ss = 0.0
        sw = 0.0
        for k in range(N_DONORS):
            d = donors[i, k]
            if d < 0 or not vis[d]:
                continue
            sw += wts[k]
            for j in range(3):
                p = cen[3 + j]
                for c in range(3):
                    p += n44[j, c] * (lay[k, c] - cen[c])
                ss += wts[k] * (p - meas[d, j]) ** 2
        e2 = mem[i, 3] + ss / sw
        s2 = max(params[P_NOISE_M], sc[C_LEVEL]) ** 2
        if e2 > s2:  # no better than the model's stand-in (_choose_donors)
            continue
        for j in range(3):
            p = cen[3 + j]
            for c in range(3):
                p += n44[j, c] * (ref[i, N_DONORS, c] - cen[c])
            meas[i, j] = p
        # weighed as a seen marker is, less by its expected error: a seen marker
        # misses the model by the take's level (at least the noise), a filled one
        # by that and its own error
        w = s2 / (s2 + e2)
        virt[i] = w
        mem[i, 4] = w


def new_fill_state(n_m: int) -> tuple[np.ndarray, ...]:
    """The fill's state arrays (s[60:65]) for ``n_m`` markers, reset."""
    donors = np.full((n_m, N_DONORS), -1, dtype=np.int64)
    return (
        np.zeros((n_m, n_m, 3)), donors, np.zeros((n_m, N_DONORS + 1, 3)),
        np.zeros((n_m, 5)), np.zeros(48),
    )  # fmt: skip
