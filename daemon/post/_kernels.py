"""Scalar quaternion helpers for the post stages' compiled kernels (numba); the
quaternion product is the shared :func:`retargetd.daemon.compiled.qmul` (re-exported).

Quaternions are (w, x, y, z) tuples of floats here, so nothing is allocated; the
functions mirror :mod:`retargetd.daemon.rotations` (the tests check them against it).
"""

from __future__ import annotations

import math

from retargetd.daemon.compiled import kernel, qmul
from retargetd.daemon.rotations import SLERP_LINEAR_BELOW_RAD

Quat = tuple[float, float, float, float]


@kernel
def twist_about(
    w: float, x: float, y: float, z: float, ux: float, uy: float, uz: float
) -> float:  # pragma: no cover - compiled
    """Signed twist angle about the unit child-frame axis u, radians in (-π, π]."""
    proj = x * ux + y * uy + z * uz
    if w < 0.0:
        proj, w = -proj, -w
    angle = 2.0 * math.atan2(proj, w)
    if angle <= -math.pi:
        angle += 2.0 * math.pi
    return angle


@kernel
def slerp_q(
    aw: float,
    ax: float,
    ay: float,
    az: float,
    bw: float,
    bx: float,
    by: float,
    bz: float,
    u: float,
) -> Quat:  # pragma: no cover - compiled
    """Shortest-arc slerp (5.86-5.87) with the small-angle lerp fallback, normalized."""
    dot = aw * bw + ax * bx + ay * by + az * bz
    if dot < 0.0:
        bw, bx, by, bz, dot = -bw, -bx, -by, -bz, -dot
    dot = min(dot, 1.0)
    theta = math.acos(dot)
    if theta < 0.5 * SLERP_LINEAR_BELOW_RAD:
        w0, w1 = 1.0 - u, u
    else:
        s = math.sin(theta)
        w0 = math.sin((1.0 - u) * theta) / s
        w1 = math.sin(u * theta) / s
    rw, rx = w0 * aw + w1 * bw, w0 * ax + w1 * bx
    ry, rz = w0 * ay + w1 * by, w0 * az + w1 * bz
    n = math.sqrt(rw * rw + rx * rx + ry * ry + rz * rz)
    return (rw / n, rx / n, ry / n, rz / n)


__all__ = ["Quat", "qmul", "slerp_q", "twist_about"]
