"""The plant's foot roll (``post/plant.py``, the leg's IK): a foot standing on its
ball whose leg is longer than the hip-goal distance (the knee lagging its flexion)
rolls about the ball, so the ankle reaches the leg's length without the ball going
into the floor. One compiled kernel, inlined into the plant's step."""

from __future__ import annotations

import math

import numpy as np

from retargetd.daemon.compiled import kernel, qrot


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
    the ankle at ``sqrt(r2)`` from the hip with the heel not below the ball;
    (1, 0, 0, 0) when there is none. With R a = a cos t + (n x a) sin t
    + n (n.a)(1 - cos t), |q + R a|^2 = r2 is A cos t + B sin t = C."""
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
    for t in (base - half, base + half):
        t = math.atan2(math.sin(t), math.cos(t))
        # the heel's height above the ball after the turn
        nh = nx * hx + ny * hy + nz * hz
        ch = nx * hy - ny * hx  # (n x h)_z
        up = hz * math.cos(t) + ch * math.sin(t) + nz * nh * (1.0 - math.cos(t))
        if up >= 0.0 and abs(t) < abs(best):
            best = t
    if best == math.inf:
        return 1.0, 0.0, 0.0, 0.0
    sh = math.sin(0.5 * best)
    return math.cos(0.5 * best), nx * sh, ny * sh, nz * sh
