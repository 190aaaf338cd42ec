"""Feet planted on the target (issue 34, item 2): ``[target] feet = "plant"``.

Rotations transfer, positions do not: on a target whose legs are longer or shorter
than the performer's, a stance foot slides on the avatar's floor or sinks into it.
This stage runs on each retargeted frame (after ``Retargeter.apply`` and the spine
pivot, before VMC), on the target's pose in place, with the contact the stance
detector (:mod:`~retargetd.daemon.post.stance`) found on the performer's solve.

1. **Root.** The retarget scales the root's displacement by the hips-height ratio;
   here it is scaled by the leg-length ratio ``k = leg_target / leg_performer`` (the
   hip joint's height above the floor at rest; the performer's in the calibration),
   height and horizontal travel alike: a longer leg takes a longer step.
2. **Hold.** Per foot, two points fixed in the foot: the heel (under the ankle) and
   the ball (under the Toes joint, else the foot's aim), both on the floor at rest.
   When contact starts, the lower of the two (the *pivot*) is anchored where it is
   (the foot's planted position, so nothing jumps); while contact lasts the foot is
   moved so its pivot stays on the anchor horizontally and its lowest point sits on
   the support level: the floor, or off it the level of the target's own sole
   (``post/plant_level.py``: where it came down, raised as the solve's foot rises
   until heel-off; offline, each contact's settled level). The pivot
   passes to the other point when that one is lower by :data:`PLANT`
   ``pivot_switch_m``: onto the ball (heel-off) re-anchored where the ball stood the
   frame before (on the floor: the switch does not move it while the solve's foot
   moves), onto the heel (coming down) where it lands. On the ball the foot
   rolls about its MTP joint (the target's Toes joint, :func:`roll_radius` above the
   ball at rest; the ball itself for a foot without toes): what is held is that
   joint, horizontally on the anchor and its rest height above the support, so the
   ball, a point of the foot under it, rises and moves back as the foot pitches, as
   a foot whose toes stay flat on the floor does (held on the floor instead, the
   ball put the synthetic walk's foot up to 18 mm below and 6 mm ahead of the solved
   one by toe-off: the leg ran straight and the foot dragged; docs/feet.md). The
   vertical correction blends in over ``blend_in_s``, except that the foot is never
   left below its support (no sink).
3. **Release.** When contact ends, the correction left blends out over
   ``blend_out_s`` (smoothstep), so the swing foot rejoins the unplanted path.
4. **Leg.** Analytic two-bone IK on the target's UpperLeg - LowerLeg - Foot: the knee is
   bent about its own hinge, the normal of the solved thigh and shank (the solved knee
   direction; the thigh's left axis when the leg is straight), to the flexion the law of
   cosines gives for the hip-ankle distance, then the leg is swung about the hip onto
   the ankle's goal. A zero correction leaves the leg exactly as solved. The foot keeps
   its solved world rotation (its rotation relative to the shank changes). A goal out of
   reach (farther than the straight leg, or nearer than the knee's most flexion,
   ``knee_max_deg``) leaves the leg straight (or at that flexion) aimed at it and sets
   the frame's ``plant_unreached`` flag; the knee is never bent backwards (the flexion
   is never below 0). A goal in reach that the knee's rate limit (``knee_step_deg``)
   leaves the leg too short for is lagged straight up, the ankle over the goal, not
   along the hip-goal line (up and toward the hip): a foot the leg cannot yet push down
   is lifted where it stands, not slid (the synthetic run's toe-off frame, where the
   solve's foot has risen 5 mm and the stance detector still holds it: the held ball
   slid 1.96 mm, legs 1.25x). On its ball (past heel-off), a foot whose leg the knee's
   rate limit leaves longer than the hip-goal distance rolls about its MTP joint (the
   heel comes down, never below the ball) until the ankle is at the leg's reach: aimed
   at the goal, the leg would push the ball into the floor (on the synthetic walk,
   0.7-1.6 mm for a frame as the leg comes back into reach late in stance). A stance
   foot whose ball the lagging leg leaves below the support is turned toes up about the
   ankle until the ball is on it (the heel not below it: where both cannot be, the foot
   levelled): the floor stops a forefoot coming down faster than the knee may follow
   (the tennis serve's 8.9 mm, the PiG walk's landings; ``post/foot_roll.py``).

One frame is one compiled call (:func:`_plant_step`, numba, nothing allocated), on
state the stage owns. Offline (``solve --plant-feet``) runs the same objects frame by
frame (``cli/post_io.retarget_solve``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from retargetd.daemon.compiled import direct, kernel, qmul, qrot, readonly_f64
from retargetd.daemon.post.foot_roll import ball_roll, keep_toe_world, pitch_onto_floor
from retargetd.daemon.post.plant_level import (
    LEVEL,
    N_LEVEL,
    settled_levels,
    sole_z,
    step_level,
)
from retargetd.daemon.post.plant_target import (
    foot_points,
    performer_leg_m,
    roll_radius,
    target_leg_m,
    warn_unplaced_centres,
)
from retargetd.daemon.post.stance import CONTACT_COLUMN, SUPPORT_COLUMN
from retargetd.protocols.frames import F64Array
from retargetd.protocols.pose_stream import FRAME_PLANT_UNREACHED

#: Stage parameters (SI).
PLANT: dict[str, float] = {
    # The vertical correction's blend-in: the loading response, 0-10 % of the gait
    # cycle, ~0.1 s in a 1.0-1.1 s cycle (Perry & Burnfield 2010, Gait Analysis, 2nd
    # ed., ch. 1): the foot settles onto the floor over it. (The horizontal hold needs
    # none: the anchor is where the foot is when contact starts.)
    "blend_in_s": 0.10,
    # The release: initial swing, 60-73 % of the cycle (Perry & Burnfield), ~0.13 s:
    # the correction is gone by mid-swing, where the toe passes closest to the floor
    # and the swing path matters.
    "blend_out_s": 0.13,
    # The pivot passes from heel to ball (or back) when the other is lower by this:
    # a quarter of the stance detector's near_m (4 cm), above the solved foot's
    # rocking on a flat floor, far below a heel-off's rise (several cm).
    "pivot_switch_m": 0.01,
    # The most the plant changes its own share of the knee's flexion in one frame:
    # near full extension the knee angle a goal needs changes fastest (the flexion
    # goes as the square root of the shortfall from the straight leg), so a goal
    # moving a few mm there would turn the knee by many degrees in a frame: the
    # issue's "no pop" bound, 3 deg between frames, less a margin. The foot lags its
    # goal for those frames instead.
    "knee_step_deg": 2.5,
    # The knee's most flexion: 140 deg, the knee's normal range (AAOS, Greene &
    # Heckman 1994, The Clinical Measurement of Joint Motion: 0-135/140).
    "knee_max_deg": 140.0,
}
_PARAMS = ("blend_in_s", "blend_out_s", "pivot_switch_m")

_SIDES = ("Left", "Right")
#: State columns per foot.
(_S_HAS, _S_PREV, _S_PIVOT, _S_ANX, _S_ANY, _S_AX, _S_AY, _S_AZ, _S_TAU, _S_RX, _S_RY,
 _S_RZ, _S_AZ0, _S_T, _S_FLEX, _S_MX, _S_MY, _N_STATE) = range(18)  # fmt: skip
#: Unreached bits :func:`_plant_step` returns (one per foot).
UNREACHED_LEFT, UNREACHED_RIGHT = 1, 2


@kernel(inline="always")
def _rot(
    q: np.ndarray, vx: float, vy: float, vz: float
) -> tuple[float, float, float]:  # pragma: no cover - compiled
    """(w x y z, unit) q applied to v."""
    return qrot(q[0], q[1], q[2], q[3], vx, vy, vz)


@kernel(inline="always")
def _smooth(u: float) -> float:  # pragma: no cover - compiled
    """Smoothstep 3u^2 - 2u^3 on [0, 1], clamped."""
    if u <= 0.0:
        return 0.0
    if u >= 1.0:
        return 1.0
    return u * u * (3.0 - 2.0 * u)


@kernel(inline="always")
def _swing(
    ax: float, ay: float, az: float, bx: float, by: float, bz: float
) -> tuple[float, float, float, float]:  # pragma: no cover - compiled
    """The least rotation taking direction a onto direction b (unit quaternion)."""
    na = math.sqrt(ax * ax + ay * ay + az * az)
    nb = math.sqrt(bx * bx + by * by + bz * bz)
    if not (na > 1e-12 and nb > 1e-12):
        return 1.0, 0.0, 0.0, 0.0
    ax, ay, az, bx, by, bz = ax / na, ay / na, az / na, bx / nb, by / nb, bz / nb
    d = ax * bx + ay * by + az * bz
    w = 1.0 + d
    x = ay * bz - az * by
    y = az * bx - ax * bz
    z = ax * by - ay * bx
    if w < 1e-12:  # opposite: half a turn about any normal (never here in practice)
        return 0.0, 1.0, 0.0, 0.0
    n = math.sqrt(w * w + x * x + y * y + z * z)
    return w / n, x / n, y / n, z / n


@kernel
def _plant_step(
    wfb: np.ndarray,  # (N, 4) G_h, in place
    rfb: np.ndarray,  # (N, 4) L_h, in place
    root: np.ndarray,  # (3,) in place
    hips: np.ndarray,  # (3,) in place
    stance: np.ndarray,  # (2, 4) the detector's state (contact, support)
    t_s: float,
    rest: np.ndarray,  # (N, 4) T_h
    offsets: np.ndarray,  # (N, 3) o_h
    parents: np.ndarray,  # (N,) int64
    chain: np.ndarray,  # (2, C) int64: Hips .. UpperLeg, LowerLeg, Foot
    chain_len: np.ndarray,  # (2,) int64
    heel: np.ndarray,  # (2, 3)
    ball: np.ndarray,  # (2, 3)
    roll_r: np.ndarray,  # (2,) each foot's roll centre's height above its ball
    toes: np.ndarray,  # (2,) int64: each Toes bone (child of Foot), -1 if none
    tip: np.ndarray,  # (2, 3): each Toes bone's aim (its tip), rest, world axes
    left: np.ndarray,  # (3,) the target's left at rest
    params: np.ndarray,  # (10,) blend in, blend out, switch, root factor, leg k,
    #                     knee max rad, contact column, support column, knee step,
    #                     own level (1: off the floor, the target's sole's; 0: given)
    e: np.ndarray,  # (2, C, 4) scratch: E along the chain
    x: np.ndarray,  # (2, C, 3) scratch: joint positions
    state: np.ndarray,  # (2, _N_STATE)
    level: np.ndarray,  # (2, N_LEVEL) plant_level's state
) -> int:  # pragma: no cover - compiled
    """One frame of both feet (module docstring); returns the unreached bits."""
    t_in, t_out, switch = params[0], params[1], params[2]
    factor, k, knee_max = params[3], params[4], params[5]
    c_col, s_col, knee_step = int(params[6]), int(params[7]), params[8]
    for c in range(3):
        root[c] *= factor
        hips[c] = root[c] + offsets[0, c]
    out = 0
    for s in range(2):
        n = chain_len[s]
        # E = G T̄ along the chain, and forward kinematics from the hips.
        for j in range(n):
            h = chain[s, j]
            e[s, j, 0], e[s, j, 1], e[s, j, 2], e[s, j, 3] = qmul(
                wfb[h, 0], wfb[h, 1], wfb[h, 2], wfb[h, 3],
                rest[h, 0], -rest[h, 1], -rest[h, 2], -rest[h, 3],
            )  # fmt: skip
            if j == 0:
                for c in range(3):
                    x[s, 0, c] = hips[c]
            else:
                rx, ry, rz = _rot(e[s, j - 1], offsets[h, 0], offsets[h, 1],
                                  offsets[h, 2])  # fmt: skip
                x[s, j, 0] = x[s, j - 1, 0] + rx
                x[s, j, 1] = x[s, j - 1, 1] + ry
                x[s, j, 2] = x[s, j - 1, 2] + rz
        f = n - 1  # the Foot; n - 2 the LowerLeg (knee), n - 3 the UpperLeg (hip)
        hx, hy, hz = _rot(e[s, f], heel[s, 0], heel[s, 1], heel[s, 2])
        bx, by, bz = _rot(e[s, f], ball[s, 0], ball[s, 1], ball[s, 2])
        r_ = roll_r[s]
        mx, my, mz = _rot(e[s, f], ball[s, 0], ball[s, 1], ball[s, 2] + r_)
        ax_, ay_, az_ = x[s, f, 0], x[s, f, 1], x[s, f, 2]
        heel_x, heel_y, heel_z = ax_ + hx, ay_ + hy, az_ + hz
        ball_z = az_ + bz
        mtp_x, mtp_y, mtp_z = ax_ + mx, ay_ + my, az_ + mz
        st = state[s]
        dt = 0.0
        if st[_S_HAS] != 0.0 and t_s > st[_S_T]:
            dt = t_s - st[_S_T]
        st[_S_T] = t_s
        st[_S_HAS] = 1.0
        contact = stance[s, c_col] != 0.0
        support = stance[s, s_col] * k
        lowest = min(heel_z, ball_z)
        if contact:
            # off the floor, the level of the target's own sole (plant_level.py)
            sole = sole_z(lowest, wfb, rest, offsets, e[s, f], az_, toes[s], tip[s])
            held = step_level(level[s], st[_S_PREV] == 0.0, sole, heel_z, switch)
            if support != 0.0 and params[9] != 0.0:
                support = held
            if st[_S_PREV] == 0.0:  # onset: anchor the lower point where it is
                st[_S_PIVOT] = 0.0 if heel_z <= ball_z else 1.0
                px, py = (heel_x, heel_y) if st[_S_PIVOT] == 0.0 else (mtp_x, mtp_y)
                st[_S_ANX] = px + st[_S_AX]
                st[_S_ANY] = py + st[_S_AY]
                st[_S_AZ0] = st[_S_AZ]
                st[_S_TAU] = 0.0
            else:
                st[_S_TAU] += dt
                other_lower = (
                    heel_z < ball_z - switch
                    if st[_S_PIVOT] == 1.0
                    else ball_z < heel_z - switch
                )
                if other_lower:
                    # Roll onto the other point. Onto the ball (heel-off), anchored
                    # where it stood last frame (the solve's, plus last frame's
                    # correction): it was on the floor, and the switch does not move
                    # it though the solve's foot moves. Onto the heel (it comes
                    # down), where it lands.
                    st[_S_PIVOT] = 1.0 - st[_S_PIVOT]
                    px, py = (
                        (heel_x, heel_y)
                        if st[_S_PIVOT] == 0.0
                        else (st[_S_MX], st[_S_MY])
                    )
                    st[_S_ANX] = px + st[_S_AX]
                    st[_S_ANY] = py + st[_S_AY]
            px, py = (heel_x, heel_y) if st[_S_PIVOT] == 0.0 else (mtp_x, mtp_y)
            st[_S_AX] = st[_S_ANX] - px
            st[_S_AY] = st[_S_ANY] - py
            need = support - lowest
            if st[_S_PIVOT] == 1.0:  # the roll centre r above the support
                need = max(need, support + r_ - mtp_z)
            w = _smooth(st[_S_TAU] / t_in) if t_in > 0.0 else 1.0
            st[_S_AZ] = max((1.0 - w) * st[_S_AZ0] + w * need, need)
            st[_S_PREV] = 1.0
        else:
            if st[_S_PREV] != 0.0:  # release: blend the correction out
                st[_S_RX], st[_S_RY], st[_S_RZ] = st[_S_AX], st[_S_AY], st[_S_AZ]
                st[_S_TAU] = 0.0
            else:
                st[_S_TAU] += dt
            w = 1.0 - (_smooth(st[_S_TAU] / t_out) if t_out > 0.0 else 1.0)
            st[_S_AX], st[_S_AY], st[_S_AZ] = (
                w * st[_S_RX], w * st[_S_RY], w * st[_S_RZ],
            )  # fmt: skip
            st[_S_PREV] = 0.0
        st[_S_MX], st[_S_MY] = mtp_x, mtp_y
        cx, cy, cz = st[_S_AX], st[_S_AY], st[_S_AZ]
        if not (cx == 0.0 and cy == 0.0 and cz == 0.0 and st[_S_FLEX] == 0.0):
            # on the ball (heel-off), a leg too long for its goal rolls the foot
            roll = contact and st[_S_PIVOT] == 1.0
            out |= _leg_ik(s, n, wfb, rfb, rest, chain, e, x, left, knee_max,
                           knee_step, ax_ + cx, ay_ + cy, az_ + cz, st, roll,
                           mtp_x + cx, mtp_y + cy, mtp_z + cz, toes[s],
                           hx - bx, hy - by, hz - bz)  # fmt: skip
        if contact:
            pitch_onto_floor(s, f, wfb, rfb, rest, chain, e, x, left, heel, ball,
                             toes[s], support)  # fmt: skip
        if contact and toes[s] >= 0:
            _toe_roll(s, wfb, rfb, toes[s], e[s, f], rest, offsets, tip,
                      x[s, f, 2], support)  # fmt: skip
    return out


@kernel(inline="always")
def _toe_roll(
    s: int,
    wfb: np.ndarray,
    rfb: np.ndarray,
    toe: int,
    ef: np.ndarray,  # (4,) the foot's E
    rest: np.ndarray,
    offsets: np.ndarray,
    tip: np.ndarray,
    az: float,  # the ankle's height
    support: float,
) -> None:  # pragma: no cover - compiled
    """A stance foot's toes turned up about their joint (in the vertical plane of the
    toe) just enough to keep the tip on the support, as the toes extend at push-off
    (a target whose Toes the rig does not drive keeps them rigid on the foot)."""
    tw, tx, ty, tz = qmul(
        wfb[toe, 0], wfb[toe, 1], wfb[toe, 2], wfb[toe, 3],
        rest[toe, 0], -rest[toe, 1], -rest[toe, 2], -rest[toe, 3],
    )  # fmt: skip
    _, _, jz = _rot(ef, offsets[toe, 0], offsets[toe, 1], offsets[toe, 2])
    vx, vy, vz = qrot(tw, tx, ty, tz, tip[s, 0], tip[s, 1], tip[s, 2])
    want = support - (az + jz)
    if not vz < want:
        return
    r = math.sqrt(vx * vx + vy * vy + vz * vz)
    hz = min(want, r)
    hh = math.sqrt(vx * vx + vy * vy)
    if hh < 1e-12:
        return
    sc = math.sqrt(max(r * r - hz * hz, 0.0)) / hh
    sw, sx, sy, sz = _swing(vx, vy, vz, vx * sc, vy * sc, hz)
    tw, tx, ty, tz = qmul(sw, sx, sy, sz, tw, tx, ty, tz)
    wfb[toe, 0], wfb[toe, 1], wfb[toe, 2], wfb[toe, 3] = qmul(
        tw, tx, ty, tz, rest[toe, 0], rest[toe, 1], rest[toe, 2], rest[toe, 3]
    )
    rfb[toe, 0], rfb[toe, 1], rfb[toe, 2], rfb[toe, 3] = qmul(
        ef[0], -ef[1], -ef[2], -ef[3], tw, tx, ty, tz
    )


@kernel(inline="always")
def _leg_ik(
    s: int,
    n: int,
    wfb: np.ndarray,
    rfb: np.ndarray,
    rest: np.ndarray,
    chain: np.ndarray,
    e: np.ndarray,
    x: np.ndarray,
    left: np.ndarray,
    knee_max: float,
    knee_step: float,
    gx: float,
    gy: float,
    gz: float,
    st: np.ndarray,
    roll: bool,
    px: float,
    py: float,
    pz: float,
    toe: int,
    hx: float,
    hy: float,
    hz: float,
) -> int:  # pragma: no cover - compiled
    """Two-bone IK of side ``s``'s leg, the ankle to the goal g (module docstring;
    with ``roll``, the foot on its ball at p may roll about it, ``toe`` its Toes bone
    or -1, h its heel less its ball); returns ``1 << s`` when the goal is out of
    reach, else 0."""
    out = 0
    f, kk, u = n - 1, n - 2, n - 3
    ax_, ay_, az_ = x[s, f, 0], x[s, f, 1], x[s, f, 2]
    cx, cy, cz = gx - ax_, gy - ay_, gz - az_
    hipx, hipy, hipz = x[s, u, 0], x[s, u, 1], x[s, u, 2]
    ux, uy, uz = x[s, kk, 0] - hipx, x[s, kk, 1] - hipy, x[s, kk, 2] - hipz
    vx, vy, vz = ax_ - x[s, kk, 0], ay_ - x[s, kk, 1], az_ - x[s, kk, 2]
    la = math.sqrt(ux * ux + uy * uy + uz * uz)
    lb = math.sqrt(vx * vx + vy * vy + vz * vz)
    # The hinge: the solved thigh x shank (points left for a knee bent forward).
    nx, ny, nz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
    sn = math.sqrt(nx * nx + ny * ny + nz * nz)
    cs = ux * vx + uy * vy + uz * vz
    flex0 = math.atan2(sn, cs)
    if sn < 1e-9 * la * lb:  # straight: the thigh's left, normal to the thigh
        nx, ny, nz = _rot(e[s, u], left[0], left[1], left[2])
        d_ = (nx * ux + ny * uy + nz * uz) / (la * la)
        nx, ny, nz = nx - d_ * ux, ny - d_ * uy, nz - d_ * uz
        sn = math.sqrt(nx * nx + ny * ny + nz * nz)
        flex0 = 0.0
    nx, ny, nz = nx / sn, ny / sn, nz / sn
    dx, dy, dz = gx - hipx, gy - hipy, gz - hipz
    dist = math.sqrt(dx * dx + dy * dy + dz * dz)
    cos_int = (la * la + lb * lb - dist * dist) / (2.0 * la * lb)
    if cos_int < -1.0:  # farther than the straight leg
        flex1 = 0.0
        out |= 1 << s
    else:
        flex1 = math.pi - math.acos(min(cos_int, 1.0))
        if flex1 > knee_max:
            flex1 = knee_max
            out |= 1 << s
    # The plant's share of the flexion, at most knee_step from the last frame's
    # (the foot lags its goal meanwhile), never below straight nor past the max.
    added = flex1 - flex0
    added = min(max(added, st[_S_FLEX] - knee_step), st[_S_FLEX] + knee_step)
    added = min(max(added, -flex0), knee_max - flex0)
    if cx == 0.0 and cy == 0.0 and cz == 0.0 and abs(added) < 1e-12:
        added = 0.0
    st[_S_FLEX] = added
    half = 0.5 * added
    sh = math.sin(half)
    qk = (math.cos(half), nx * sh, ny * sh, nz * sh)
    # The shank turned about the hinge at the knee, then the leg about the hip.
    qw_, qx_, qy_, qz_ = qk
    cxk = qy_ * vz - qz_ * vy
    cyk = qz_ * vx - qx_ * vz
    czk = qx_ * vy - qy_ * vx
    wx = vx + 2.0 * (qw_ * cxk + qy_ * czk - qz_ * cyk)
    wy = vy + 2.0 * (qw_ * cyk + qz_ * cxk - qx_ * czk)
    wz = vz + 2.0 * (qw_ * czk + qx_ * cyk - qy_ * cxk)
    lx, ly, lz = ux + wx, uy + wy, uz + wz
    r2 = lx * lx + ly * ly + lz * lz
    if roll and r2 > dist * dist * (1.0 + 1e-9):
        # The leg (its knee lagging, knee_step) is longer than the hip-goal distance:
        # aimed at the goal the ankle would go past it, the ball into the floor.
        # The foot rolls about its ball instead (the ball stays where it is held;
        # the heel, risen at heel-off, comes down, never below the ball) until the
        # ankle is at the leg's reach.
        rw, rx_, ry_, rz_ = ball_roll(e[s, f], left, gx - px, gy - py, gz - pz,
                                       px - hipx, py - hipy, pz - hipz, r2, hx, hy,
                                       hz)  # fmt: skip
        if rw < 1.0:
            ox, oy, oz = qrot(rw, rx_, ry_, rz_, gx - px, gy - py, gz - pz)
            dx, dy, dz = px + ox - hipx, py + oy - hipy, pz + oz - hipz
            ew, ex, ey, ez = qmul(rw, rx_, ry_, rz_, e[s, f, 0], e[s, f, 1],
                                  e[s, f, 2], e[s, f, 3])  # fmt: skip
            e[s, f, 0], e[s, f, 1], e[s, f, 2], e[s, f, 3] = ew, ex, ey, ez
            h = chain[s, f]
            wfb[h, 0], wfb[h, 1], wfb[h, 2], wfb[h, 3] = qmul(
                ew, ex, ey, ez, rest[h, 0], rest[h, 1], rest[h, 2], rest[h, 3]
            )
            keep_toe_world(wfb, rfb, rest, toe, ew, ex, ey, ez)
    hh = dx * dx + dy * dy
    if out == 0 and dz < 0.0 and hh < r2 < dist * dist:
        # The knee's rate limit leaves the leg short of a goal it can reach: the
        # ankle lags it straight up, over the goal, rather than along the hip-goal
        # line (up and toward the hip): a foot the leg cannot yet push down is
        # lifted off the floor where it stands, not slid on it.
        dz = -math.sqrt(r2 - hh)
    sw, sx, sy, sz = _swing(lx, ly, lz, dx, dy, dz)
    # E' of the thigh and shank; G = E' T, L = Ē'_parent E'.
    tw, tx, ty, tz = qmul(sw, sx, sy, sz, e[s, u, 0], e[s, u, 1], e[s, u, 2],
                          e[s, u, 3])  # fmt: skip
    kw, kx, ky, kz = qmul(qw_, qx_, qy_, qz_, e[s, kk, 0], e[s, kk, 1],
                          e[s, kk, 2], e[s, kk, 3])  # fmt: skip
    kw, kx, ky, kz = qmul(sw, sx, sy, sz, kw, kx, ky, kz)
    e[s, u, 0], e[s, u, 1], e[s, u, 2], e[s, u, 3] = tw, tx, ty, tz
    e[s, kk, 0], e[s, kk, 1], e[s, kk, 2], e[s, kk, 3] = kw, kx, ky, kz
    for j in (u, kk):
        h = chain[s, j]
        wfb[h, 0], wfb[h, 1], wfb[h, 2], wfb[h, 3] = qmul(
            e[s, j, 0], e[s, j, 1], e[s, j, 2], e[s, j, 3],
            rest[h, 0], rest[h, 1], rest[h, 2], rest[h, 3],
        )  # fmt: skip
    for j in (u, kk, f):
        h = chain[s, j]
        p = j - 1
        rfb[h, 0], rfb[h, 1], rfb[h, 2], rfb[h, 3] = qmul(
            e[s, p, 0], -e[s, p, 1], -e[s, p, 2], -e[s, p, 3],
            e[s, j, 0], e[s, j, 1], e[s, j, 2], e[s, j, 3],
        )  # fmt: skip
    # where the knee and ankle went (the toes are placed from the ankle)
    kx_, ky_, kz_ = qrot(sw, sx, sy, sz, ux, uy, uz)
    fx_, fy_, fz_ = qrot(sw, sx, sy, sz, wx, wy, wz)
    x[s, kk, 0], x[s, kk, 1], x[s, kk, 2] = hipx + kx_, hipy + ky_, hipz + kz_
    x[s, f, 0] = x[s, kk, 0] + fx_
    x[s, f, 1] = x[s, kk, 1] + fy_
    x[s, f, 2] = x[s, kk, 2] + fz_
    return out


def plant_stage(feet: str, retargeter: Any, stance: Any) -> FootPlant | None:
    """The ``[target] feet = "plant"`` stage for ``retargeter``'s target (None for
    ``"free"``), fed by ``stance`` (a
    :class:`~retargetd.daemon.post.stance.StanceDetector` on the performer's solve,
    whose rig and calibration give the performer's leg length): after the retarget
    and the spine pivot, on the target's pose (live ``send.py``, offline
    ``cli/post_io.retarget_solve``); its clock is the detector's (the sum of the
    frame intervals the detector was given), so live and offline blend alike.

    Raises:
        ValueError: the target or rig lacks a leg, or no performer leg length.
    """
    if feet != "plant":
        return None
    warn_unplaced_centres(stance.rig, stance.calibration)
    leg = performer_leg_m(stance.rig, stance.calibration)
    stage = FootPlant(retargeter.target, retargeter.root_scale, leg)
    stage.stance_state, stage.stance_clock = stance.state, stance.clock
    return stage


class FootPlant:
    """The plant stage for one target and performer (module docstring).

    Args:
        target: the target skeleton (``TargetSkeleton``: ``bone_names``,
            ``parents``, ``rest_offsets``, ``aim_offsets``,
            ``rest_world_from_bone_quat``, ``left_world``, ``index``).
        root_scale: the retarget's root scale (``Retargeter.root_scale``), which the
            stage replaces by the leg-length ratio.
        performer_leg: the performer's leg length, metres (:func:`performer_leg_m`).
        params: overrides of :data:`PLANT`.

    Raises:
        ValueError: the target lacks a leg bone (UpperLeg, LowerLeg, Foot per side)
            or a leg chain is not UpperLeg -> LowerLeg -> Foot.
    """

    def __init__(
        self,
        target: Any,
        root_scale: float,
        performer_leg: float,
        params: dict[str, float] | None = None,
    ) -> None:
        p = {**PLANT, **(params or {})}
        names: Sequence[str] = target.bone_names
        parents = [int(q) for q in target.parents]
        chains = []
        for side in _SIDES:
            idx = [target.index(side + b) for b in ("UpperLeg", "LowerLeg", "Foot")]
            if parents[idx[1]] != idx[0] or parents[idx[2]] != idx[1]:
                raise ValueError(
                    f"target {target.name!r}: {side} leg must be UpperLeg -> LowerLeg "
                    "-> Foot"
                )
            up = [idx[0]]
            while parents[up[0]] >= 0:
                up.insert(0, parents[up[0]])
            chains.append(up + idx[1:])
        n_chain = max(len(c) for c in chains)
        self.chain = np.zeros((2, n_chain), dtype=np.int64)
        self.chain_len = np.array([len(c) for c in chains], dtype=np.int64)
        for s, c in enumerate(chains):
            self.chain[s, : len(c)] = c
        self.leg_ratio = target_leg_m(target) / performer_leg
        """Target leg length over the performer's: the root's and supports' scale."""
        self.heel, self.ball = foot_points(target)
        self.roll_r = roll_radius(target)
        """(2,) m: each foot's roll centre (its MTP joint) above its ball."""
        self._toes = np.full(2, -1, dtype=np.int64)
        self._tip = np.zeros((2, 3))
        for s, side in enumerate(_SIDES):
            name = side + "Toes"
            if name in names and names[parents[target.index(name)]] == side + "Foot":
                t = target.index(name)
                self._toes[s] = t
                self._tip[s] = np.asarray(target.aim_offsets[t], dtype=np.float64)
        # Read-only copies whatever the target's are (a TargetSkeleton's are read-only,
        # a BVH's legs' writable): numba types the two apart and compiled _plant_step
        # once for each.
        self._rest = readonly_f64(target.rest_world_from_bone_quat)
        self._offsets = readonly_f64(target.rest_offsets)
        self._parents = np.asarray(parents, dtype=np.int64)
        self._left = np.ascontiguousarray(target.left_world, np.float64)
        self._params = np.array([
            *(p[key] for key in _PARAMS), self.leg_ratio / root_scale,
            self.leg_ratio, math.radians(p["knee_max_deg"]), CONTACT_COLUMN,
            SUPPORT_COLUMN, math.radians(p["knee_step_deg"]), 1.0,
        ])  # fmt: skip
        self._e = np.zeros((2, n_chain, 4))
        self._x = np.zeros((2, n_chain, 3))
        self._state = np.zeros((2, _N_STATE))
        self._level = np.zeros((2, N_LEVEL))
        self._call: object = _plant_step
        self.n_bones = len(names)
        self.stance_clock = np.zeros(1)
        """(1,) seconds: the clock :meth:`apply_pose` reads (:func:`plant_stage`
        binds the stance detector's)."""
        self.stance_state = np.zeros((2, 4))
        """The stance detector's state :meth:`apply_pose` reads (:func:`plant_stage`
        binds the detector's own array)."""
        self._const = (
            self._rest, self._offsets, self._parents, self.chain, self.chain_len,
            self.heel, self.ball, self.roll_r, self._toes, self._tip, self._left,
            self._params, self._e, self._x, self._state, self._level,
        )  # fmt: skip

    def apply_pose(self, pose: Any) -> int:
        """:meth:`apply` on a ``TargetPose`` with :attr:`stance_state` at
        :attr:`stance_clock`."""
        t_s = float(self.stance_clock[0])
        return self.apply(
            pose.world_from_bone_quat, pose.rest_from_bone_quat, pose.root_pos,
            pose.hips_pos, self.stance_state, t_s,
        )  # fmt: skip

    def reset(self) -> None:
        """Forget the history (a new stream): no foot held, no correction left."""
        self._state[:] = 0.0
        self._level[:] = 0.0

    def hold_settled(
        self,
        world_from_bone_quat: F64Array,
        rest_from_bone_quat: F64Array,
        root_pos: F64Array,
        hips_pos: F64Array,
        stance_states: F64Array,
        rate_hz: float,
    ) -> F64Array:
        """Offline, the whole take known: run the stage over copies of the take's
        retargeted frames ((T, N, 4), (T, N, 4), (T, 3), (T, 3), as :meth:`apply`'s)
        and return ``stance_states`` ((T, 2, C), the detector's per frame) with each
        contact off the floor given its own level as settled by its last frame
        (``post/plant_level.py``); from then on the stage holds the supports it is
        given (then :meth:`apply` each frame with the returned states)."""
        self.reset()
        self._params[9] = 1.0
        level = np.zeros((len(root_pos), 2))
        for t in range(len(root_pos)):
            self.apply(
                world_from_bone_quat[t].copy(), rest_from_bone_quat[t].copy(),
                root_pos[t].copy(), hips_pos[t].copy(), stance_states[t], t / rate_hz,
            )  # fmt: skip
            level[t] = self._level[:, LEVEL]
        self.reset()
        self._params[9] = 0.0
        return settled_levels(
            stance_states, level / self.leg_ratio, CONTACT_COLUMN, SUPPORT_COLUMN
        )

    def plant_take(
        self,
        world_from_bone_quat: F64Array,
        rest_from_bone_quat: F64Array,
        root_pos: F64Array,
        hips_pos: F64Array,
        stance_states: F64Array,
        rate_hz: float,
    ) -> np.ndarray:
        """Offline, a whole retargeted take planted in place: each contact's level
        settled first (:meth:`hold_settled`), then :meth:`apply` frame by frame at
        ``t = frame / rate_hz`` (``solve --plant-feet``, ``retarget --plant-feet``).

        Args:
            world_from_bone_quat, rest_from_bone_quat: (T, N, 4) the target poses'
                ``G`` and ``L``, rewritten on the legs.
            root_pos, hips_pos: (T, 3) the target's root and Hips, rescaled.
            stance_states: (T, 2, C) the stance detector's state per frame
                (:func:`~retargetd.daemon.post.stance.take_stance_states`).
            rate_hz: the take's frame rate.

        Returns:
            (T,) uint32: ``FRAME_PLANT_UNREACHED`` where a foot could not reach its
            hold, else 0.
        """
        states = self.hold_settled(
            world_from_bone_quat, rest_from_bone_quat, root_pos, hips_pos,
            stance_states, rate_hz,
        )  # fmt: skip
        flags = np.zeros(len(root_pos), dtype=np.uint32)
        for k in range(len(root_pos)):
            flags[k] = self.apply(
                world_from_bone_quat[k], rest_from_bone_quat[k], root_pos[k],
                hips_pos[k], states[k], k / rate_hz,
            )  # fmt: skip
        return flags

    def apply(
        self,
        world_from_bone_quat: F64Array,
        rest_from_bone_quat: F64Array,
        root_pos: F64Array,
        hips_pos: F64Array,
        stance_state: F64Array,
        t_s: float,
    ) -> int:
        """Plant one retargeted frame in place; returns ``FRAME_PLANT_UNREACHED`` when
        a foot could not reach its hold (else 0).

        Args:
            world_from_bone_quat, rest_from_bone_quat: (N, 4) the target pose's
                ``G`` and ``L`` (``TargetPose``), rewritten on the legs.
            root_pos, hips_pos: (3,) the target pose's root and Hips, rescaled.
            stance_state: the stance detector's state
                (:attr:`StanceDetector.state`), updated for this frame.
            t_s: this frame's time, seconds (any clock that only moves forward).
        """
        call = self._call
        if call is _plant_step:  # the compiled entry point once it exists
            call = self._call = direct(
                _plant_step, world_from_bone_quat, rest_from_bone_quat, root_pos,
                hips_pos, stance_state, float(t_s), *self._const,
            )  # fmt: skip
        bits: int = call(  # type: ignore[operator]
            world_from_bone_quat, rest_from_bone_quat, root_pos, hips_pos,
            stance_state, float(t_s), *self._const,
        )  # fmt: skip
        return FRAME_PLANT_UNREACHED if bits else 0
