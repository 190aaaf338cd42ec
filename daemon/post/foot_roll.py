"""The plant's foot roll (``post/plant.py``, the leg's IK): a foot standing on its
ball whose leg is longer than the hip-goal distance (the knee lagging its flexion)
rolls about the ball, so the ankle reaches the leg's length without the ball going
into the floor. One compiled kernel, inlined into the plant's step."""

from __future__ import annotations

import math

import numpy as np

from retargetd.daemon.compiled import kernel, qmul, qrot


@kernel(inline="always")
def _arc_range(k: float, p: float, r: float, t: float) -> tuple[float, float]:
    """The least and the greatest of k + p cos s + r sin s for s from 0 to t
    (|t| <= pi): the ends, and its minimum (at atan2(r, p) + pi) or maximum (at
    atan2(r, p)) where the arc passes them."""
    g0 = k + p
    g1 = k + p * math.cos(t) + r * math.sin(t)
    lo, hi = min(g0, g1), max(g0, g1)
    amp = math.sqrt(p * p + r * r)
    top = math.atan2(r, p)
    for s, v in ((top, k + amp), (top + math.pi, k - amp)):
        s = math.atan2(math.sin(s), math.cos(s))
        if (0.0 <= s <= t) or (t <= s <= 0.0):
            lo, hi = min(lo, v), max(hi, v)
    return lo, hi


@kernel(inline="always")
def ball_roll(
    ef: np.ndarray,  # (4,) the foot's E
    left: np.ndarray,  # (3,) the target's left at rest
    ax: float,  # the ankle less the ball (the roll's pivot)
    ay: float,
    az: float,
    qx: float,  # the ball less the hip
    qy: float,
    qz: float,
    r2: float,  # the squared distance from the hip the ankle is to be at
    hx: float,  # the heel less the ball
    hy: float,
    hz: float,
) -> tuple[float, float, float, float]:  # pragma: no cover - compiled
    """The least rotation of the foot about its left axis through the ball that puts
    the ankle at ``sqrt(r2)`` from the hip, the heel only coming down on the way and
    never below the ball (the roll brings the heel down: a turn that lifts it, or
    swings it round under the ball, is a flip: the tennis serve's left foot went heel
    up by 115 mm for a frame on one); (1, 0, 0, 0) when there is none. With
    R a = a cos t + (n x a) sin t + n (n.a)(1 - cos t), |q + R a|^2 = r2 is
    A cos t + B sin t = C."""
    nx, ny, nz = qrot(ef[0], ef[1], ef[2], ef[3], left[0], left[1], left[2])
    nn = math.sqrt(nx * nx + ny * ny + nz * nz)
    nx, ny, nz = nx / nn, ny / nn, nz / nn
    na = nx * ax + ny * ay + nz * az
    cx, cy, cz = ny * az - nz * ay, nz * ax - nx * az, nx * ay - ny * ax
    gam = (qx * nx + qy * ny + qz * nz) * na
    a_ = qx * ax + qy * ay + qz * az - gam
    b_ = qx * cx + qy * cy + qz * cz
    c_ = 0.5 * (r2 - (qx * qx + qy * qy + qz * qz) - (ax * ax + ay * ay + az * az))
    c_ -= gam
    m = math.sqrt(a_ * a_ + b_ * b_)
    if not (m > 1e-12 and abs(c_) <= m):
        return 1.0, 0.0, 0.0, 0.0
    base = math.atan2(b_, a_)
    half = math.acos(c_ / m)
    best = math.inf
    # the heel's height above the ball over the turn: k + p cos s + r sin s
    nh = nx * hx + ny * hy + nz * hz
    k_, p_, r_ = nz * nh, hz - nz * nh, nx * hy - ny * hx  # (n x h)_z
    for t in (base - half, base + half):
        t = math.atan2(math.sin(t), math.cos(t))
        lo, hi = _arc_range(k_, p_, r_, t)
        if lo >= -1e-12 and hi <= hz + 1e-12 and abs(t) < abs(best):
            best = t
    if best == math.inf:
        return 1.0, 0.0, 0.0, 0.0
    sh = math.sin(0.5 * best)
    return math.cos(0.5 * best), nx * sh, ny * sh, nz * sh


@kernel(inline="always")
def _turn_to(
    nx: float, ny: float, nz: float, vx: float, vy: float, vz: float, want: float
) -> float:  # pragma: no cover - compiled
    """The least angle t (radians) of a turn about the unit axis n that brings v's
    height to ``want``; nan when none does. With R v = v cos t + (n x v) sin t
    + n (n.v)(1 - cos t), (R v)_z = want is A cos t + B sin t = C."""
    nv = nx * vx + ny * vy + nz * vz
    a_ = vz - nz * nv
    b_ = nx * vy - ny * vx  # (n x v)_z
    c_ = want - nz * nv
    m = math.sqrt(a_ * a_ + b_ * b_)
    if not (m > 1e-12 and abs(c_) <= m):
        return math.nan
    base = math.atan2(b_, a_)
    half = math.acos(c_ / m)
    t0 = math.atan2(math.sin(base - half), math.cos(base - half))
    t1 = math.atan2(math.sin(base + half), math.cos(base + half))
    return t0 if abs(t0) <= abs(t1) else t1


@kernel(inline="always")
def _height(
    nx: float, ny: float, nz: float, vx: float, vy: float, vz: float, t: float
) -> float:  # pragma: no cover - compiled
    """(R v)_z for the turn t about the unit axis n."""
    nv = nx * vx + ny * vy + nz * vz
    c, s = math.cos(t), math.sin(t)
    return vz * c + (nx * vy - ny * vx) * s + nz * nv * (1.0 - c)


@kernel(inline="always")
def floor_pitch(
    ef: np.ndarray,  # (4,) the foot's E
    left: np.ndarray,  # (3,) the target's left at rest
    bx: float,  # the ball less the ankle
    by: float,
    bz: float,
    hx: float,  # the heel less the ankle
    hy: float,
    hz: float,
    want: float,  # the support's height less the ankle's
) -> tuple[float, float, float, float]:  # pragma: no cover - compiled
    """The least turn of the foot about its left axis through the ankle that lifts
    the ball onto the support (``want`` above the ankle) with the heel not below it
    (:func:`_turn_to`); where the heel would go below the support (the ankle itself
    too low: both cannot be on it), the least turn that levels the foot (heel and
    ball at one height, the highest their lower can be), when that lifts the ball
    less far; (1, 0, 0, 0) when the ball is not below the support or neither turn
    helps."""
    if not bz < want:
        return 1.0, 0.0, 0.0, 0.0
    nx, ny, nz = qrot(ef[0], ef[1], ef[2], ef[3], left[0], left[1], left[2])
    nn = math.sqrt(nx * nx + ny * ny + nz * nz)
    nx, ny, nz = nx / nn, ny / nn, nz / nn
    t = _turn_to(nx, ny, nz, bx, by, bz, want)
    if math.isnan(t) or _height(nx, ny, nz, hx, hy, hz, t) < want - 1e-12:
        lv = _turn_to(nx, ny, nz, bx - hx, by - hy, bz - hz, 0.0)
        if math.isnan(lv) or (not math.isnan(t) and abs(lv) >= abs(t)):
            return 1.0, 0.0, 0.0, 0.0
        low = min(
            _height(nx, ny, nz, hx, hy, hz, lv), _height(nx, ny, nz, bx, by, bz, lv)
        )
        if not low > min(bz, hz):  # the foot's lowest point would not rise
            return 1.0, 0.0, 0.0, 0.0
        t = lv
    sh = math.sin(0.5 * t)
    return math.cos(0.5 * t), nx * sh, ny * sh, nz * sh


@kernel(inline="always")
def pitch_onto_floor(
    s: int,
    f: int,  # the foot's place in the chain (the shank's is f - 1)
    wfb: np.ndarray,  # (N, 4) G, in place
    rfb: np.ndarray,  # (N, 4) L, in place
    rest: np.ndarray,  # (N, 4) T
    chain: np.ndarray,  # (2, C)
    e: np.ndarray,  # (2, C, 4) E along the chain, in place
    x: np.ndarray,  # (2, C, 3) joint positions
    left: np.ndarray,  # (3,)
    heel: np.ndarray,  # (2, 3) rest offsets from the ankle
    ball: np.ndarray,  # (2, 3)
    toe: int,  # the Toes bone or -1
    support: float,
) -> None:  # pragma: no cover - compiled
    """A stance foot whose ball is below its support turned toes up about the ankle
    (:func:`floor_pitch`) until the ball is on it: the floor stops the foot's
    plantarflexion (the leg's knee lagging its goal, ``knee_step``, leaves the ankle
    low; a forefoot coming down faster than the knee may follow). The toes keep their
    world rotation."""
    ef = e[s, f]
    bx, by, bz = qrot(ef[0], ef[1], ef[2], ef[3], ball[s, 0], ball[s, 1], ball[s, 2])
    hx, hy, hz = qrot(ef[0], ef[1], ef[2], ef[3], heel[s, 0], heel[s, 1], heel[s, 2])
    rw, rx, ry, rz = floor_pitch(ef, left, bx, by, bz, hx, hy, hz,
                                 support - x[s, f, 2])  # fmt: skip
    if not rw < 1.0:
        return
    ew, ex, ey, ez = qmul(rw, rx, ry, rz, ef[0], ef[1], ef[2], ef[3])
    ef[0], ef[1], ef[2], ef[3] = ew, ex, ey, ez
    h = chain[s, f]
    wfb[h, 0], wfb[h, 1], wfb[h, 2], wfb[h, 3] = qmul(
        ew, ex, ey, ez, rest[h, 0], rest[h, 1], rest[h, 2], rest[h, 3]
    )
    ek = e[s, f - 1]
    rfb[h, 0], rfb[h, 1], rfb[h, 2], rfb[h, 3] = qmul(
        ek[0], -ek[1], -ek[2], -ek[3], ew, ex, ey, ez
    )
    keep_toe_world(wfb, rfb, rest, toe, ew, ex, ey, ez)


@kernel
def keep_toe_world(
    wfb: np.ndarray, rfb: np.ndarray, rest: np.ndarray, toe: int,
    ew: float, ex: float, ey: float, ez: float,
) -> None:  # fmt: skip
    # The toes keep their world rotation (the MTP extends) when the foot turns to
    # (ew, ex, ey, ez) (world_from_bone over rest): their rest_from_bone is taken
    # relative to the foot's new one. toe < 0: a foot without toes, nothing to do.
    if toe < 0:
        return
    tw, tx, ty, tz = qmul(
        wfb[toe, 0], wfb[toe, 1], wfb[toe, 2], wfb[toe, 3],
        rest[toe, 0], -rest[toe, 1], -rest[toe, 2], -rest[toe, 3],
    )  # fmt: skip
    rfb[toe, 0], rfb[toe, 1], rfb[toe, 2], rfb[toe, 3] = qmul(
        ew, -ex, -ey, -ez, tw, tx, ty, tz
    )
