"""What carries the rigid-skeleton fit from one frame to the next (numba): the pose
predicted for a frame, the hold on what hidden markers alone resolved, the hidden
markers measured where the prediction carries them, the gate with its memory of each
marker's residual, and the tests that tell a frame the markers do not explain
(``kernel_fit`` runs them; the rules and their numbers are ``solve_fit.FitParams``).
"""

from __future__ import annotations

import math

import numpy as np

from retargetd.daemon.body.fit_fill import FILL_DROPS_HOLD
from retargetd.daemon.body.fit_hold_robust import (
    freeze_robust,
    parent_gauges,
    robust_drop,
)
from retargetd.daemon.body.fit_terms import (
    C_DT,
    C_GAP,
    C_LAST_RMS,
    C_LEVEL,
    L_TWIST_AXIS,
    P_ACC_MAX,
    P_ALPHA_MAX,
    P_GATE_M,
    P_GATE_MEMORY,
    P_HOLD_STRAIGHT_RAD,
    P_JUMP_FLOOR_RAD,
    P_JUMP_Z,
    P_LEVEL_TAU_S,
    P_LOST_FLOOR_M,
    P_LOST_K,
    P_NOISE_M,
    P_OMEGA_MAX,
    P_OMEGA_ROOT,
    P_REJECT_FRAC,
    P_RESOLUTION_RAD,
    P_SPEED_MAX,
    P_UNEXPLAINED_K,
    P_VELOCITY_TAU_S,
    bone_y_cos,
    cp2,
    fk,
    limb_bent,
    qexp,
    qlog,
)
from retargetd.daemon.compiled import jacobi_eigen, kernel, qmul


@kernel
def truncated_rms(ss: float, n_in: int, n_rej: int, gate: float) -> float:
    # The frame's residual RMS with each rejected marker counted at the gate: what
    # the markers say of the fit, a misfit the gate hides included.
    n = n_in + n_rej
    return math.sqrt((ss + n_rej * gate * gate) / n) if n > 0 else math.inf


@kernel
def predict(m: tuple, s: tuple) -> None:
    # The pose predicted for this frame: the last explained frame advanced by its
    # joint-angle velocity when the frame before it was explained too, else held (a
    # velocity across a gap is not known). Written to the pull target s[2], s[3] and
    # to the warm start s[0], s[1].
    q, t, qpred, tpred = s[0], s[1], s[2], s[3]
    qlast, tlast, q2, t2 = s[49], s[50], s[41], s[42]
    have, sc = s[4], s[36]
    if have[0] >= 2 and sc[C_GAP] <= 1.0:
        for b in range(q.shape[0]):
            d = qmul(q2[b, 0], -q2[b, 1], -q2[b, 2], -q2[b, 3],
                      qlast[b, 0], qlast[b, 1], qlast[b, 2], qlast[b, 3])  # fmt: skip
            r = qmul(qlast[b, 0], qlast[b, 1], qlast[b, 2], qlast[b, 3],
                      d[0], d[1], d[2], d[3])  # fmt: skip
            nr = math.sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2] + r[3] * r[3])
            for j in range(4):
                qpred[b, j] = r[j] / nr
        for rr in range(t.shape[0]):
            for j in range(3):
                tpred[rr, j] = 2.0 * tlast[rr, j] - t2[rr, j]
    else:
        cp2(qpred, qlast)
        cp2(tpred, tlast)
    cp2(q, qpred)
    cp2(t, tpred)


@kernel
def jump_bound(
    z: float, a_max: float, v_max: float, h: float, known: bool, floor: float
) -> float:
    # How far a segment (or a root's position) can be from its prediction h seconds
    # after the last explained frame, at least the floor. With its velocity known
    # (predict extrapolated it) it misses by at most 1/2 a_max h^2 (times z, the
    # acceleration's margin), and by at most 2 v_max h (its speed then and now both
    # under v_max). With the prediction held (no velocity is known across a gap) it
    # has moved by at most v_max h: its speed never passes v_max, whatever it was
    # when the markers went.
    b = min(z * 0.5 * a_max * h * h, 2.0 * v_max * h) if known else v_max * h
    return max(b, floor)


@kernel
def unsettled(
    params: np.ndarray, sc: np.ndarray, rms: float, lost_at: float, n_rej: int,
    n_seen: int,
) -> bool:  # fmt: skip
    # After a gap the prediction is the last explained pose held: nothing tells a
    # marker the pose rejects from one the pose has wrong, so a frame still suspect
    # with the better candidate (a quarter rejected, or twice the take's level) does
    # not restart the track (a swapped frame came in at gap 11 with 14 of 29
    # rejected, and the true frames after the burst were held to it:
    # bench/burst_recovery.py). Only while the gap is shorter than the level's own
    # time constant: past it the level before the gap no longer speaks for the take
    # (a performer whose markers fit worse after the gap, every one 20 mm further off
    # on the PiG walk, was held for the rest of the take).
    return (
        sc[C_GAP] > 1.0
        and not stale(params, sc)
        and (rms > lost_at or n_rej > params[P_REJECT_FRAC] * n_seen)
    )


@kernel
def stale(params: np.ndarray, sc: np.ndarray) -> bool:
    # Whether the last explained frame is older than the running level's time
    # constant: the level before the gap no longer speaks for the take.
    return sc[C_GAP] * sc[C_DT] > params[P_LEVEL_TAU_S]


@kernel
def far_at(params: np.ndarray, sc: np.ndarray, level: float) -> float:
    # The residual past which a frame is unexplained: unexplained_k x the take's own
    # level. Bounded as unsettled is: past the level's time constant a frame is
    # judged as a first frame is (past gate_m: no performer's markers leave that),
    # and where it is explained the level starts again from it (kernel_fit). Without
    # the bound a performer whose markers fit far worse after a gap (the PiG walk,
    # every marker 35 mm further off after a 0.2 s gap: 5x the level before it) was
    # held for the rest of the take, the level never moving (it moves on explained
    # frames only).
    far = max(params[P_LOST_FLOOR_M], params[P_UNEXPLAINED_K] * level)
    if stale(params, sc):
        far = max(far, params[P_GATE_M])
    return far


@kernel
def advance_level(
    params: np.ndarray, sc: np.ndarray, rms: float, lost_at: float
) -> None:
    # An explained frame moves the take's running residual level (time constant
    # level_tau_s) and, where it is the take's own, the suspect test's reference
    # (the last explained frame's RMS). After a gap past the level's time constant
    # both start again from this frame, as from a take's first (far_at).
    tau = params[P_LEVEL_TAU_S]
    a = min(1.0, sc[C_DT] / tau) if tau > 0.0 else 1.0
    restart = stale(params, sc)
    if restart:
        sc[C_LAST_RMS] = 0.0
        lost_at = params[P_LOST_FLOOR_M]
    lv = 0.0 if restart else sc[C_LEVEL]
    sc[C_LEVEL] = rms if lv <= 0.0 else lv + a * (rms - lv)
    # a frame kept while still suspect (no candidate brought it under the
    # suspect level) is no reference for the next: counted as the take's
    # own it raised the level each frame judged by (a swapped burst got in
    # at 2-4x the level a frame and, once in, stayed). Nor is one past the
    # suspect factor of the running level alone: judged against the last
    # frame's RMS, a misfit growing under 2x a frame vouched for itself and
    # ratcheted the reference (the walk's LKNE hidden from row 30: 5.7 ->
    # 43 mm over rows 100-119, the thigh run 58 deg off, never suspect)
    own_at = lost_at
    if lv > 0.0:
        own_at = min(lost_at, max(params[P_LOST_FLOOR_M], params[P_LOST_K] * lv))
    if rms <= own_at:
        sc[C_LAST_RMS] = rms


@kernel
def impossible(m: tuple, s: tuple, frames: float) -> bool:
    # Whether the fitted pose moved a joint (or a root) further from its prediction
    # than a body can in `frames` frames (jump_bound): a joint under the peak
    # angular acceleration and velocity, a root's world rotation under the whole
    # body's turn, a root's position under a sprint; at least the floor (noise on a
    # short lever makes a few degrees of jitter at any rate; a root's position: the
    # gate).
    params, parent = m[18], m[0]
    q, t, qpred, tpred = s[0], s[1], s[2], s[3]
    h = frames * s[36][C_DT]
    z = params[P_JUMP_Z]
    known = s[4][0] >= 2 and s[36][C_GAP] <= 1.0  # as predict decides
    a_rot, floor_r = params[P_ALPHA_MAX], params[P_JUMP_FLOOR_RAD]
    lim_j = jump_bound(z, a_rot, params[P_OMEGA_MAX], h, known, floor_r)
    lim_root = jump_bound(z, a_rot, params[P_OMEGA_ROOT], h, known, floor_r)
    lim_t = jump_bound(
        z, params[P_ACC_MAX], params[P_SPEED_MAX], h, known, params[P_GATE_M]
    )
    for b in range(parent.shape[0]):
        d = qmul(qpred[b, 0], -qpred[b, 1], -qpred[b, 2], -qpred[b, 3],
                  q[b, 0], q[b, 1], q[b, 2], q[b, 3])  # fmt: skip
        w = abs(d[0])
        ang = 2.0 * math.acos(w if w < 1.0 else 1.0)
        if ang > (lim_root if parent[b] < 0 else lim_j):
            return True
    for rr in range(t.shape[0]):
        dx = t[rr, 0] - tpred[rr, 0]
        dy = t[rr, 1] - tpred[rr, 1]
        dz = t[rr, 2] - tpred[rr, 2]
        if dx * dx + dy * dy + dz * dz > lim_t * lim_t:
            return True
    return False


@kernel
def hinge_bend(q: np.ndarray) -> float:
    # a joint's bend (rad): its bone's +Y from its parent's +Y, the joint at
    # parent_from_bone q (unit)
    c = bone_y_cos(q)
    return math.acos(1.0 if c > 1.0 else (-1.0 if c < -1.0 else c))


@kernel
def axis_of(m: tuple, b: int) -> tuple[float, float, float]:
    # a hinge_twist's twist axis, bone b's axes
    lim = m[11]
    return lim[b, L_TWIST_AXIS], lim[b, L_TWIST_AXIS + 1], lim[b, L_TWIST_AXIS + 2]


@kernel
def parent_turn_info(
    m: tuple, s: tuple, b: int
) -> tuple[float, tuple[float, float, float]]:
    # The information (m^2 / rad^2, every other joint fixed) the markers seen on
    # bone b's parent give about the parent's turn about b's twist axis (the line
    # through the hinge, b's origin), and that axis in the parent's axes (carried by
    # the joint at the last explained frame).
    parent, qlast = m[0], s[49]
    p = parent[b]
    a0, a1, a2 = axis_of(m, b)
    q = qlast[b]  # parent_from_bone: a in the parent's axes is q a q*
    t1 = qmul(q[0], q[1], q[2], q[3], 0.0, a0, a1, a2)
    t2 = qmul(t1[0], t1[1], t1[2], t1[3], q[0], -q[1], -q[2], -q[3])
    ap = (t2[1], t2[2], t2[3])
    mk_bone, mk_local, wt, off, vis = m[5], m[6], m[7], m[2], s[13]
    info = 0.0
    for i in range(mk_bone.shape[0]):
        if not vis[i] or wt[i] <= 0.0 or mk_bone[i] != p:
            continue
        d0 = mk_local[i, 0] - off[b, 0]
        d1 = mk_local[i, 1] - off[b, 1]
        d2 = mk_local[i, 2] - off[b, 2]
        c0 = ap[1] * d2 - ap[2] * d1
        c1 = ap[2] * d0 - ap[0] * d2
        c2 = ap[0] * d1 - ap[1] * d0
        info += wt[i] * (c0 * c0 + c1 * c1 + c2 * c2)
    return info, ap


@kernel
def hold_priors(m: tuple, s: tuple) -> None:
    # While markers are hidden, each bone's rotations that they observed and that
    # the markers still seen no longer resolve (information under (sigma /
    # resolution)^2, sigma the take's residual level: what the remaining markers'
    # misfit would turn them by; the level where each hidden marker was last
    # accepted, or now where lower: below) are held at their last seen value with the
    # information the hidden markers gave them (at most up to that threshold): the
    # balance of the fit is kept, not shifted to what the remaining misfit prefers
    # (fit_observe.hidden_information). s[53] the hold priors (bone axes, m^2 /
    # rad^2), s[54] their anchors (parent_from_bone), s[55] their traces (0: off).
    params, parent, wt, lock = m[18], m[0], m[7], m[20]
    axes, lam, lost, limb = m[22], m[23], m[24], m[25]
    vis = s[13]
    hold, anchor, on, qlast = s[53], s[54], s[55], s[49]
    n_b = parent.shape[0]
    # the tables (fit_observe.hidden_information): at the calibration pose, and from
    # row n_mk * n_b on with the nearly straight hinges at a right angle; a hidden
    # marker's hold blends them by how far its limb's hinge is bent at the last
    # explained frame: sin(bend) / sin(P_HOLD_STRAIGHT_RAD), at most 1 (what its
    # markers tell the two twists apart by, against what makes it count as bent), so
    # a hinge that bends through the threshold moves its hold smoothly
    n_tab = wt.shape[0] * n_b
    sin_bent = math.sin(params[P_HOLD_STRAIGHT_RAD])
    level = s[36][C_LEVEL]
    sig = max(params[P_NOISE_M], level) / params[P_RESOLUTION_RAD]
    thr_now = sig * sig
    rlevel = s[67]
    rage, fresh = s[48], s[40]  # (s[40], s[39]: scratch here, the outputs' later)
    rides = s[39]
    # (s[18], s[19]: scratch, fit_normal.build_normal's per-bone sums, rebuilt
    # there; local_floor below reuses s[18] after the last read of drop)
    drop, gauge = s[18], s[19]
    for b in range(n_b):
        fresh[b] = 0
        for i in range(3):
            for j in range(3):
                hold[b, i, j] = 0.0
    dropped = False
    for k in range(wt.shape[0]):
        if wt[k] <= 0.0 or vis[k] or (FILL_DROPS_HOLD and s[63][k, 4] > 0.0):
            continue
        if not dropped:
            freeze_robust(m, s)
            robust_drop(m, s, drop)
            parent_gauges(m, s, gauge)
            dropped = True
        new = rage[k] == 0.0  # accepted in the last explained frame: hidden now
        # The threshold is the level where the marker was last accepted, or the
        # level now where that is lower: the level is a running RMS of the markers
        # seen, and while the marker hides it takes up the misfit the hold itself
        # leaves, where the hold refuses a motion the seen markers report. Followed
        # upwards, the threshold grew with that misfit and the hold with it, and
        # new directions fell under it: menache's RIWRIST hidden 1 s from 4 s, the
        # ulna's twist hold 3.5e-4 -> 8.1e-4 m^2/rad^2 as the level rose 2.22 ->
        # 3.54 mm (the intact solve's 2.22 -> 3.16) while the performer pronated
        # 112 deg, and the upper arm's twist took it (29.6 deg off the intact
        # solve; the epicondyles 21 mm). The hold tables' allowance
        # (synth.hold.held_directions) is made at the level before the hide, too.
        # No new number.
        lv = level
        if 0.0 < rlevel[k] < lv:
            lv = rlevel[k]
        sig = max(params[P_NOISE_M], lv) / params[P_RESOLUTION_RAD]
        thr = sig * sig
        # the bones the marker rides (its own and its ancestors: twist_to_parent)
        for b in range(n_b):
            rides[b] = 0
        kb = m[5][k]
        while kb >= 0:
            rides[kb] = 1
            kb = parent[kb]
        bent = limb_bent(qlast, limb[k], sin_bent)
        for half in range(2):
            share = bent if half == 1 else 1.0 - bent
            if share <= 0.0:
                continue
            base = k * n_b + half * n_tab
            for b in range(n_b):
                row = base + b
                for j in range(3):
                    lo = lost[row, j]
                    if lo <= 0.0:
                        continue
                    u0, u1, u2 = (
                        axes[row, 3 * j],
                        axes[row, 3 * j + 1],
                        axes[row, 3 * j + 2],
                    )
                    # what the table counts as still seen, less what the robust
                    # loss took from the seen markers at the hide (robust_drop)
                    li = lam[row, j]
                    for a in range(3):
                        ua = axes[row, 3 * j + a]
                        for e in range(3):
                            li -= ua * drop[b, a, e] * axes[row, 3 * j + e]
                    if li >= thr:
                        continue
                    kk = share * min(lo, thr - max(li, 0.0))
                    if kk < 0.01 * thr:
                        # (a hold under 1 % of the threshold moves nothing by more
                        # than 1 % of the resolution: not worth its terms in every
                        # iteration)
                        continue
                    if new:
                        fresh[b] = 1
                    # never along the parent's gauge (parent_gauges): the priors
                    # decide that one at the proximal joint
                    ug = u0 * gauge[b, 0] + u1 * gauge[b, 1] + u2 * gauge[b, 2]
                    u0 -= ug * gauge[b, 0]
                    u1 -= ug * gauge[b, 1]
                    u2 -= ug * gauge[b, 2]
                    if (
                        lock[b] == 2.0
                        and not rides[b]
                        and (
                            not rides[parent[b]] or parent_turn_info(m, s, b)[0] >= thr
                        )
                    ):
                        # A hinge_twist below the marker (its hinge between the
                        # marker and the bone) whose parent's own markers seen
                        # resolve the parent's turn about the twist axis, or whose
                        # parent the marker does not ride: its twist is not held.
                        # That twist moves the hidden marker not at all; the table
                        # counts it lost only because the marker fixed the parent's
                        # turn about the same axis, which the markers below see as
                        # they see the twist (one direction,
                        # the hinge straight): what it resolved is how that turn
                        # splits between the two, and the parent's own markers
                        # decide that (as twist_to_parent passes nothing to such a
                        # parent). Held on the child relative to the parent, it
                        # refused the forearm's real pronation, which the seen
                        # markers report, and the parent took it: menache's
                        # RIELBOW hidden 1 s from 4 s, the upper arm 24.6 deg
                        # beyond the hold (REELBOW 14.2; bench/fit_truth.py).
                        # Where the parent's markers do not resolve that turn its
                        # own row holds it and the child's is kept: dropped for any
                        # parent, the PiG walk's LTHI hidden 1 s from row 150 ran the
                        # thigh 9.9 -> 15.3 deg and RELB (the upper arm's one
                        # marker) from row 30 got a new step. A marker above the
                        # parent (a shoulder marker for the forearm) moves with
                        # neither the twist nor the parent's turn about its axis:
                        # its table counts the twist lost only through the freedom
                        # of the bones it rides, whose own rows hold them, so it
                        # resolved no part of that split and the twist is not held
                        # whatever the parent's markers see. Held, Plug-in Gait's
                        # RSHO (alone on the clavicle) hidden 1 s from 4 s kept the
                        # forearm's twist at 13 deg while the performer pronated 81,
                        # and the upper arm, whose one marker RELB resolves that
                        # turn under the threshold, took it: 20.6 deg beyond the
                        # hold (bench/fit_truth.py). No new number.
                        a0, a1, a2 = axis_of(m, b)
                        cu = u0 * a0 + u1 * a1 + u2 * a2
                        u0, u1, u2 = u0 - cu * a0, u1 - cu * a1, u2 - cu * a2
                    u = (u0, u1, u2)
                    for a in range(3):
                        for c2 in range(3):
                            hold[b, a, c2] += kk * u[a] * u[c2]
                    if lock[b] == 2.0 and rides[b] and parent[parent[b]] >= 0:
                        twist_to_parent(m, s, b, kk, u, new, thr)
    local_floor(m, s, thr_now)
    for b in range(n_b):
        tr = hold[b, 0, 0] + hold[b, 1, 1] + hold[b, 2, 2]
        if tr > 0.0 and (on[b] == 0.0 or fresh[b]):
            # a hold that starts, or that another marker just hidden adds to, holds
            # from the last explained frame; otherwise it keeps its anchor while the
            # markers stay hidden (a threshold that grows with the residual must not
            # move it: the hold would follow a drift instead of stopping it)
            for j in range(4):
                anchor[b, j] = qlast[b, j]
        on[b] = tr


@kernel
def twist_to_parent(
    m: tuple, s: tuple, b: int, kk: float, u: tuple, new: bool, thr: float
) -> None:
    # A hinge_twist's twist held (information kk along u, bone b's axes, from a
    # hidden marker's table) is held on its parent too, about the same axis in the
    # world: the twist axis runs along the limb through the hinge, and the markers
    # seen below the hinge see the parent's turn about that axis and the twist
    # nearly alike (the hold tables' straight-hinge case; bent, the forearm's
    # markers still see both through a lever under the hold threshold). Held at the
    # joint alone, the performer's own twist, which the seen markers report, turns
    # the parent instead: Plug-in Gait's synthetic performer, RWRA hidden 1 s from
    # 4 s, the forearm's twist held while the performer pronates 115 deg, and the
    # upper arm (RELB, the one marker on it) turned 62 deg with every seen marker
    # within 6 mm (bench/fit_truth.py: 58.2 deg beyond the hold; holds off, 5.3).
    # The parent gets the twist's share of the hold, kk (u . a)^2, along a (the
    # twist axis) carried into its axes by the joint at the last explained frame.
    # Only for a hidden marker that rides the twisting bone or one below it: one
    # above the hinge (a thigh or an upper-arm marker) holds the child's twist
    # only as far as the parent's twist, which its own table row holds, and the
    # child's are one direction to the markers left; passed up, it added to the
    # parent's own hold (the PiG walk's RTHI and RKNE hidden 1 s from row 30, LTHI
    # from row 150: a new step over 5 deg each, or the thigh 9.9 -> 11.8 deg).
    parent, lim = m[0], m[11]
    hold, fresh = s[53], s[40]
    p = parent[b]
    a0 = lim[b, L_TWIST_AXIS]
    a1 = lim[b, L_TWIST_AXIS + 1]
    a2 = lim[b, L_TWIST_AXIS + 2]
    cu = u[0] * a0 + u[1] * a1 + u[2] * a2
    k = kk * cu * cu
    if k <= 0.0:
        return
    # what the parent's own markers seen tell about its turn about that axis (the
    # line through the hinge, the child's origin): as a hold is made, only what they
    # resolve worse than the threshold, up to it (passed to a thigh regardless,
    # whose wand sees that turn, the walk's shank markers hidden got new steps:
    # RTIB from row 90, LTIB from row 200; an upper arm's one epicondyle marker sits
    # on the hinge's axis, near the twist axis)
    info, ap = parent_turn_info(m, s, b)
    if info >= thr:
        return
    k = min(k, thr - info)
    if new:
        fresh[p] = 1
    for i in range(3):
        for j in range(3):
            hold[p, i, j] += k * ap[i] * ap[j]


@kernel
def eig3(a: np.ndarray, v: np.ndarray) -> tuple[float, float, float]:
    # Eigenvalues of the symmetric 3 x 3 ``a`` (destroyed); ``v``'s columns become
    # the eigenvectors (compiled.jacobi_eigen).
    jacobi_eigen(a, v)
    return a[0, 0], a[1, 1], a[2, 2]


@kernel
def local_floor(m: tuple, s: tuple, thr: float) -> None:
    # Several markers of one bone hidden at once can leave a rotation that no
    # single-marker table (fit_observe.hidden_information) sees: the bone's own
    # information about its origin, from the markers seen on it and below it at the
    # predicted pose (sum w (|r|^2 I - r r^T)), is brought up to the threshold in
    # every direction under it, for each bone two or more hidden markers ride or
    # hang below. With one hidden, its table decides alone: the floor, a bone's
    # information with every other joint fixed, held what the table's marginal
    # finds observed (Plug-in Gait's RFIN hidden 1 s: the forearm's twist, which
    # the wrist bar still sees, held against a 115 deg pronation; the wrist 79 mm
    # off the intact solve, 3.3 without; bench/hide_sweep.py).
    parent, mk_bone, mk_local, wt = m[0], m[5], m[6], m[7]
    vis, hold = s[13], s[53]
    wq, wm, o = s[29], s[8], s[9]
    acc, touched, jac = s[18], s[39], s[28]
    n_b = parent.shape[0]
    any_hidden = False
    for b in range(n_b):
        touched[b] = 0
    for i in range(mk_bone.shape[0]):
        if wt[i] > 0.0 and not vis[i]:
            k = mk_bone[i]
            while k >= 0:
                touched[k] += 1
                k = parent[k]
            any_hidden = True
    if not any_hidden:  # (most frames: no FK to pay; the fit's own comes next)
        return
    fk(parent, m[1], m[2], s[0], s[1], wq, wm, o)
    for b in range(n_b):
        for i in range(3):
            for j in range(3):
                acc[b, i, j] = 0.0
    for i in range(mk_bone.shape[0]):
        if wt[i] <= 0.0 or not vis[i]:
            continue
        sb = mk_bone[i]
        px = o[sb, 0] + wm[sb, 0, 0] * mk_local[i, 0] + wm[sb, 0, 1] * mk_local[i, 1]
        px += wm[sb, 0, 2] * mk_local[i, 2]
        py = o[sb, 1] + wm[sb, 1, 0] * mk_local[i, 0] + wm[sb, 1, 1] * mk_local[i, 1]
        py += wm[sb, 1, 2] * mk_local[i, 2]
        pz = o[sb, 2] + wm[sb, 2, 0] * mk_local[i, 0] + wm[sb, 2, 1] * mk_local[i, 1]
        pz += wm[sb, 2, 2] * mk_local[i, 2]
        k = sb
        while k >= 0:
            if touched[k]:
                r = (px - o[k, 0], py - o[k, 1], pz - o[k, 2])
                r2 = r[0] * r[0] + r[1] * r[1] + r[2] * r[2]
                for a in range(3):
                    for c in range(3):
                        acc[k, a, c] += wt[i] * ((r2 if a == c else 0.0) - r[a] * r[c])
            k = parent[k]
    a3, v3 = jac[3:6], jac[0:3]
    for b in range(n_b):
        if touched[b] < 2 or parent[b] < 0:
            continue
        # in the bone's axes: W^T acc W
        for a in range(3):
            for c in range(3):
                x = 0.0
                for e in range(3):
                    for f in range(3):
                        x += wm[b, e, a] * acc[b, e, f] * wm[b, f, c]
                a3[a, c] = x
        lam = eig3(a3, v3)
        for j in range(3):
            if lam[j] >= thr:
                continue
            kk = thr - max(lam[j], 0.0)
            for a in range(3):
                for c in range(3):
                    hold[b, a, c] += kk * v3[a, j] * v3[c, j]


@kernel
def virtual_markers(m: tuple, s: tuple) -> None:
    # A hidden marker is measured where the predicted pose carries it, offset by its
    # residual at its last accepted frame in its bone's axes (s[56]): it keeps the
    # pull and the stiffness it gave the fit (the balance of a loosely fitting model
    # stays where it was; a marker's misfit, soft tissue or the model, changes
    # slowly), and it never enters the gate, the residual statistics or the outputs
    # (s[58] marks it; fit_terms.marker_cost measures it). Where the marker's
    # segment ends at a hinge (its own bone's or its child's: the knee for a thigh
    # marker), the offset fades as that hinge bends away from where it was
    # measured (s[59]), by exp(-change / P_HOLD_STRAIGHT_RAD): soft-tissue artefact
    # follows the joint's motion, not the clock (Leardini et al., Gait Posture
    # 21(2):212-225, 2005), and 30 deg is the bend over which the hold tables take
    # a hinge for another pose. A thigh marker hidden at the peak of its artefact
    # kept it: the walk's LKNE hidden 1 s from row 30 carried 25.6 mm while its
    # intact residual fell to 2-5 mm, and the thigh ran 35 deg off.
    # Where no marker of its bone is seen, there is no balance to keep: the bone's
    # pose is its prediction alone, whose velocity is known for about tau_v (below),
    # so the marker's weight (s[58]) fades by exp(-age / tau_v) with the time since
    # it was last accepted, and the markers seen below the bone carry it. At full
    # weight two hidden thigh markers held the thigh to its own prediction while
    # the shank's markers, seen, were left 76-96 mm off (the thigh 43-52 deg from
    # the solve with nothing hidden; bench/burst_recovery.py --seed 6).
    mk_bone, mk_local, wt = m[5], m[6], m[7]
    limb, rbend = m[25], s[59]
    vis, rage, meas = s[13], s[48], s[12]
    rloc, virt = s[56], s[58]
    wq, wm, o = s[29], s[8], s[9]
    # The pose they are measured on: the predicted root, every joint advanced from
    # its last explained value by its last velocity damped by exp(-dt / tau_v): a
    # marker that stays hidden must not carry a velocity on (the fit would follow
    # its own prediction and the velocity with it: a runaway), so what only it saw
    # slows to a hold within ~tau_v.
    params, parent, sc = m[18], m[0], s[36]
    qlast, q2, qv = s[49], s[41], s[6]
    hidden = False
    for i in range(mk_bone.shape[0]):
        if not vis[i] and wt[i] > 0.0 and rage[i] != math.inf:
            hidden = True
            break
    if not hidden:  # (most frames: nothing to measure, no FK to pay)
        return
    k = math.exp(-sc[C_DT] / params[P_VELOCITY_TAU_S])
    moving = s[4][0] >= 2 and sc[C_GAP] <= 1.0
    for b in range(parent.shape[0]):
        if parent[b] < 0:
            for j in range(4):
                qv[b, j] = s[0][b, j]
            continue
        if not moving:
            for j in range(4):
                qv[b, j] = qlast[b, j]
            continue
        d = qmul(q2[b, 0], -q2[b, 1], -q2[b, 2], -q2[b, 3],
                  qlast[b, 0], qlast[b, 1], qlast[b, 2], qlast[b, 3])  # fmt: skip
        vx, vy, vz = qlog(d[0], d[1], d[2], d[3])
        e = qexp(k * vx, k * vy, k * vz)
        r = qmul(qlast[b, 0], qlast[b, 1], qlast[b, 2], qlast[b, 3],
                  e[0], e[1], e[2], e[3])  # fmt: skip
        for j in range(4):
            qv[b, j] = r[j]
    fk(parent, m[1], m[2], qv, s[1], wq, wm, o)
    for i in range(mk_bone.shape[0]):
        if s[63][i, 4] > 0.0:  # filled from its rigid neighbours (fit_fill)
            continue
        if vis[i] or wt[i] <= 0.0 or rage[i] == math.inf:
            virt[i] = 0.0
            continue
        b = mk_bone[i]
        fo = 1.0
        h = limb[i]
        if h >= 0 and (h == b or parent[h] == b):
            fo = math.exp(
                -abs(hinge_bend(qv[h]) - rbend[i]) / params[P_HOLD_STRAIGHT_RAD]
            )
        for j in range(3):
            meas[i, j] = o[b, j] + (
                wm[b, j, 0] * (mk_local[i, 0] - fo * rloc[i, 0])
                + wm[b, j, 1] * (mk_local[i, 1] - fo * rloc[i, 1])
                + wm[b, j, 2] * (mk_local[i, 2] - fo * rloc[i, 2])
            )
        alone = True  # no marker of its bone seen
        for j in range(mk_bone.shape[0]):
            if vis[j] and wt[j] > 0.0 and mk_bone[j] == b:
                alone = False
                break
        virt[i] = (
            math.exp(-rage[i] * sc[C_DT] / params[P_VELOCITY_TAU_S]) if alone else 1.0
        )


@kernel
def median_residual(s: tuple) -> float:
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
def mark_outliers(m: tuple, s: tuple, gate: float) -> bool:
    # The gate, on the ungated fit's residuals: a visible marker is rejected when its
    # residual exceeds the gate and, if it has a reference (its residual vector at
    # its last accepted frame, at most P_GATE_MEMORY frames ago), has also moved from
    # it by more than the gate. A swapped label or a ghost jumps by a marker spacing;
    # skin sliding or a loose fit grows a residual over many frames and keeps it.
    params = m[18]
    vis, res, rej, rref, rage = s[13], s[14], s[45], s[47], s[48]
    memory = params[P_GATE_MEMORY]
    g2 = gate * gate
    beyond = False
    for i in range(vis.shape[0]):
        rej[i] = False
        if not vis[i]:
            continue
        n2 = res[i, 0] ** 2 + res[i, 1] ** 2 + res[i, 2] ** 2
        if n2 <= g2:
            continue
        if rage[i] == math.inf:
            # never accepted since the take began: a steady misfit from the first
            # frame is not told from a swap by one frame; the Cauchy loss weighs it
            # down, and once seen its residual is its reference (step 4)
            continue
        if rage[i] <= memory:
            d0 = res[i, 0] - rref[i, 0]
            d1 = res[i, 1] - rref[i, 1]
            d2 = res[i, 2] - rref[i, 2]
            if d0 * d0 + d1 * d1 + d2 * d2 <= g2:
                continue
        rej[i] = True
        beyond = True
    return beyond


@kernel
def score(m: tuple, s: tuple) -> tuple[float, int, int]:
    # Inlier sum of squares, number of inliers, number rejected.
    vis, res, wt, rej = s[13], s[14], m[7], s[45]
    ss = 0.0
    n_in = 0
    n_rej = 0
    for i in range(vis.shape[0]):
        if not vis[i] or wt[i] <= 0.0:
            continue
        if rej[i]:
            n_rej += 1
        else:
            n_in += 1
            ss += res[i, 0] ** 2 + res[i, 1] ** 2 + res[i, 2] ** 2
    return ss, n_in, n_rej
