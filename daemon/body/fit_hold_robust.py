"""The hold tables (``fit_track.hold_priors``) less what the robust loss takes from
the markers still seen (issue 28 items 2 and 6).

``fit_observe.hidden_information`` makes the tables with every seen marker at full
weight; the fit weighs a marker in the Cauchy loss's tail at w_rob = w / (1 + |r|^2 /
c^2). Where such a marker is the one that still resolves a rotation after another
hides, the tables hold nothing and that rotation runs off (Plug-in Gait's synthetic
performer, STRN hidden: T10 51 mm off, the chest 34.1 deg off the intact solve).
State: s[68] (M,) each marker's share taken at the hide (:func:`freeze_robust`);
scratch s[18], s[19] (``hold_priors`` passes them).
"""

from __future__ import annotations

import math

import numpy as np

from retargetd.daemon.body.fit_terms import (
    P_CAUCHY_M,
    P_HOLD_STRAIGHT_RAD,
    limb_bent,
)
from retargetd.daemon.compiled import kernel, qrot


@kernel
def freeze_robust(m: tuple, s: tuple) -> None:
    # s[68]: each seen marker's share of its information that the robust loss takes,
    # 1 - w_rob / w = |r|^2 / (c^2 + |r|^2) at its residual in the last explained
    # frame (s[14]), taken when a hide starts (a marker newly hidden with no hold on
    # from the frame before) and kept while the hide lasts; 0 inside the Cauchy
    # scale (the loss convex there, the marker a measurement as the tables count
    # it), for a marker the gate rejected (the gate's, not the loss's: dropping what
    # a rejected marker gave held the pose it disagrees with) and for one not seen
    # then. Frozen, not renewed each frame: renewed, a seen marker pushed off by a
    # hidden one's stand-in lost information, a hold started on its bone where the
    # pose had already gone, and held it there (helper h28t's variant (c):
    # Plug-in Gait's RSHO hidden 1 s, the forearm 9 -> 26 steps).
    params, wt, vis, res, rej = m[18], m[7], s[13], s[14], s[45]
    rage, on, frozen = s[48], s[55], s[68]
    starts = False
    for k in range(wt.shape[0]):
        if wt[k] > 0.0 and not vis[k] and rage[k] == 0.0:
            starts = True
            break
    if not starts:
        return
    for b in range(on.shape[0]):
        if on[b] > 0.0:
            return
    c2 = params[P_CAUCHY_M] * params[P_CAUCHY_M]
    for i in range(wt.shape[0]):
        frozen[i] = 0.0
        if not vis[i] or wt[i] <= 0.0 or rej[i]:
            continue
        n2 = res[i, 0] ** 2 + res[i, 1] ** 2 + res[i, 2] ** 2
        if n2 > c2:
            frozen[i] = n2 / (c2 + n2)


@kernel
def robust_drop(m: tuple, s: tuple, drop: np.ndarray) -> None:
    # Per bone (its rest axes, m^2 / rad^2), the information about its rotation that
    # the robust loss took from the seen markers at the hide: each seen marker's own
    # rows of the hold tables (what each bone loses when that marker hides: its
    # share of the bone's information, blended by its limb's bend as a hidden
    # marker's are, hold_priors), times its frozen share (freeze_robust). The tables
    # count every seen marker at full weight; a marker far in the loss's tail gives
    # the fit a fraction of that (Plug-in Gait's synthetic performer: T10, on an
    # abdomen that twists under the rig's rigid thorax, 51 mm off and weighed 0.13,
    # the only seen chest marker off the C7-CLAV line; with STRN hidden the table
    # found the chest's turn about that line still seen, held nothing, and the
    # chest ran 34 deg off).
    params, wt, vis, res, rej = m[18], m[7], s[13], s[14], s[45]
    axes, lost, limb, qlast, frozen = m[22], m[24], m[25], s[49], s[68]
    n_b = drop.shape[0]
    n_tab = wt.shape[0] * n_b
    sin_bent = math.sin(params[P_HOLD_STRAIGHT_RAD])
    c2 = params[P_CAUCHY_M] * params[P_CAUCHY_M]
    for b in range(n_b):
        for a in range(3):
            for c in range(3):
                drop[b, a, c] = 0.0
    for i in range(wt.shape[0]):
        if not vis[i] or wt[i] <= 0.0 or frozen[i] <= 0.0 or rej[i]:
            continue
        n2 = res[i, 0] ** 2 + res[i, 1] ** 2 + res[i, 2] ** 2
        if n2 <= c2:
            continue
        lw = min(frozen[i], n2 / (c2 + n2))
        bent = limb_bent(qlast, limb[i], sin_bent)
        for half in range(2):
            share = lw * (bent if half == 1 else 1.0 - bent)
            if share <= 0.0:
                continue
            base = i * n_b + half * n_tab
            for b in range(n_b):
                row = base + b
                for j in range(3):
                    lo = share * lost[row, j]
                    if lo <= 0.0:
                        continue
                    for a in range(3):
                        ua = axes[row, 3 * j + a]
                        for c in range(3):
                            drop[b, a, c] += lo * ua * axes[row, 3 * j + c]


@kernel
def parent_gauges(m: tuple, s: tuple, gauge: np.ndarray) -> None:
    # Per bone, in its axes at the last explained frame, the line from its parent's
    # joint to its own where the parent turns about it unseen: a parent with a ball
    # joint, no marker and this bone its only child (Plug-in Gait's spine under the
    # chest) turns about that line moving no marker, the bone turning back; the
    # priors decide that gauge at the proximal joint (fit_observe). A hold on the
    # bone made at the calibration pose (hold_priors) has a component along it once
    # the bone has turned from there, and held that way the parent took what the
    # bone was held against (helper h28t's variant (a): STRN hidden on the
    # synthetic performer, the chest 1.7 deg and the spine 10.8 deg off about its
    # own axis). Zero: no gauge.
    parent, off, mk_bone, wt = m[0], m[2], m[5], m[7]
    hinge, lock, qlast = m[10], m[20], s[49]
    n_b = parent.shape[0]
    for b in range(n_b):
        gauge[b, 0] = gauge[b, 1] = gauge[b, 2] = 0.0
        p = parent[b]
        if p < 0 or lock[p] != 0.0:
            continue
        if hinge[p, 0] != 0.0 or hinge[p, 1] != 0.0 or hinge[p, 2] != 0.0:
            continue
        only = True
        for c in range(n_b):
            if c != b and parent[c] == p:
                only = False
                break
        for i in range(mk_bone.shape[0]):
            if mk_bone[i] == p and wt[i] > 0.0:
                only = False
                break
        n = math.sqrt(off[b, 0] ** 2 + off[b, 1] ** 2 + off[b, 2] ** 2)
        if not only or n <= 0.0:
            continue
        # the parent-axes line in the bone's axes: q's inverse applied to it, q =
        # parent_from_bone
        q = qlast[b]
        gauge[b, 0], gauge[b, 1], gauge[b, 2] = qrot(
            q[0], -q[1], -q[2], -q[3], off[b, 0] / n, off[b, 1] / n, off[b, 2] / n
        )
