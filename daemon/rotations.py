"""Vectorized quaternion and rotation kernels (numpy only, batched over leading dims).

Conventions (README "Conventions" table): quaternions are scalar-first ``(w, x, y, z)``,
Hamilton product, active rotations; ``v_a = quat_rotate(a_from_b_quat, v_b)`` and
``a_from_c = quat_mul(a_from_b, b_from_c)``. Angles are radians. Euler sequences follow
scipy: three letters from ``xyz``, lower case = extrinsic (fixed axes), upper case =
intrinsic (moving axes), e.g. ``"ZXY"`` is ``R = Rz(a) @ Rx(b) @ Ry(c)``.

Every function broadcasts over leading dimensions. The hot ones (``quat_mul``,
``quat_conj``, ``quat_normalize``, ``quat_rotate``, ``mat_from_quat``,
``quat_from_mat``, ``quat_canonical_hemisphere``) take ``out=`` and return it; ``out``
may alias an input. scipy is the test oracle, never called here.
"""

from __future__ import annotations

import numpy as np

from retargetd.protocols.frames import F64Array

_CONJ_SIGNS = np.array([1.0, -1.0, -1.0, -1.0])
_AXIS_INDEX = {"x": 0, "y": 1, "z": 2}
#: Below this angle between the two ends, slerp falls back to a normalized lerp.
SLERP_LINEAR_BELOW_RAD = 1e-6


def _as_f64(a: F64Array | float) -> F64Array:
    return np.asarray(a, dtype=np.float64)


def _check_last(a: F64Array, n: int, name: str) -> None:
    if a.ndim == 0 or a.shape[-1] != n:
        raise ValueError(f"{name} must have shape (..., {n}); got {a.shape}")


def _out(out: F64Array | None, shape: tuple[int, ...]) -> F64Array:
    if out is None:
        return np.empty(shape, dtype=np.float64)
    if out.shape != shape:
        raise ValueError(f"out must have shape {shape}; got {out.shape}")
    return out


def quat_mul(p: F64Array, q: F64Array, out: F64Array | None = None) -> F64Array:
    """Hamilton product ``p ⊗ q`` (apply ``q`` first, then ``p``).

    Args:
        p: (..., 4) float64 quaternions (w, x, y, z), e.g. ``a_from_b``.
        q: (..., 4) float64 quaternions (w, x, y, z), e.g. ``b_from_c``; broadcasts
            with ``p``.
        out: optional (..., 4) float64 destination (may alias ``p`` or ``q``).

    Returns:
        (..., 4) float64 quaternions (w, x, y, z), e.g. ``a_from_c`` (``out`` if given).
    """
    p = _as_f64(p)
    q = _as_f64(q)
    _check_last(p, 4, "p")
    _check_last(q, 4, "q")
    pw, px, py, pz = p[..., 0], p[..., 1], p[..., 2], p[..., 3]
    qw, qx, qy, qz = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    w = pw * qw - px * qx - py * qy - pz * qz
    x = pw * qx + px * qw + py * qz - pz * qy
    y = pw * qy - px * qz + py * qw + pz * qx
    z = pw * qz + px * qy - py * qx + pz * qw
    res = _out(out, np.broadcast_shapes(p.shape, q.shape))
    res[..., 0] = w
    res[..., 1] = x
    res[..., 2] = y
    res[..., 3] = z
    return res


def quat_conj(q: F64Array, out: F64Array | None = None) -> F64Array:
    """Conjugate ``(w, -x, -y, -z)``: the inverse of a unit quaternion.

    Args:
        q: (..., 4) float64 quaternions (w, x, y, z).
        out: optional (..., 4) float64 destination.

    Returns:
        (..., 4) float64 (``out`` if given).
    """
    q = _as_f64(q)
    _check_last(q, 4, "q")
    return np.multiply(q, _CONJ_SIGNS, out=_out(out, q.shape))


def quat_inv(q: F64Array) -> F64Array:
    """Inverse ``conj(q) / |q|²`` (also right for non-unit quaternions).

    Args:
        q: (..., 4) float64 quaternions (w, x, y, z), non-zero.

    Returns:
        (..., 4) float64 quaternions (w, x, y, z).
    """
    q = _as_f64(q)
    _check_last(q, 4, "q")
    return q * _CONJ_SIGNS / np.sum(q * q, axis=-1, keepdims=True)


def quat_normalize(q: F64Array, out: F64Array | None = None) -> F64Array:
    """Scale quaternions to unit norm.

    Args:
        q: (..., 4) float64 quaternions (w, x, y, z), non-zero.
        out: optional (..., 4) float64 destination.

    Returns:
        (..., 4) float64 unit quaternions (``out`` if given).
    """
    q = _as_f64(q)
    _check_last(q, 4, "q")
    norm = np.sqrt(np.sum(q * q, axis=-1, keepdims=True))
    return np.divide(q, norm, out=_out(out, q.shape))


def quat_rotate(q: F64Array, v: F64Array, out: F64Array | None = None) -> F64Array:
    """Rotate vectors: ``v_a = q v_b q*`` for ``q = a_from_b``.

    Uses ``v' = v + 2w (u x v) + 2 u x (u x v)`` with ``u = (x, y, z)``; ``q`` must be
    unit norm.

    Args:
        q: (..., 4) float64 unit quaternions (w, x, y, z).
        v: (..., 3) float64 vectors in the source frame; broadcasts with ``q[..., :3]``.
        out: optional (..., 3) float64 destination (may alias ``v``).

    Returns:
        (..., 3) float64 vectors in the target frame (``out`` if given).
    """
    q = _as_f64(q)
    v = _as_f64(v)
    _check_last(q, 4, "q")
    _check_last(v, 3, "v")
    w, ux, uy, uz = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    vx, vy, vz = v[..., 0], v[..., 1], v[..., 2]
    # t = 2 (u x v)
    tx = 2.0 * (uy * vz - uz * vy)
    ty = 2.0 * (uz * vx - ux * vz)
    tz = 2.0 * (ux * vy - uy * vx)
    # v' = v + w t + u x t
    rx = vx + w * tx + (uy * tz - uz * ty)
    ry = vy + w * ty + (uz * tx - ux * tz)
    rz = vz + w * tz + (ux * ty - uy * tx)
    res = _out(out, (*np.broadcast_shapes(q.shape[:-1], v.shape[:-1]), 3))
    res[..., 0] = rx
    res[..., 1] = ry
    res[..., 2] = rz
    return res


def mat_from_quat(q: F64Array, out: F64Array | None = None) -> F64Array:
    """Rotation matrices from quaternions (scaled by ``2/|q|²``, so any norm works).

    Args:
        q: (..., 4) float64 quaternions (w, x, y, z), non-zero.
        out: optional (..., 3, 3) float64 destination.

    Returns:
        (..., 3, 3) float64 rotation matrices, ``v_a = M @ v_b`` (``out`` if given).
    """
    q = _as_f64(q)
    _check_last(q, 4, "q")
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    s = 2.0 / (w * w + x * x + y * y + z * z)
    xx, yy, zz = s * x * x, s * y * y, s * z * z
    xy, xz, yz = s * x * y, s * x * z, s * y * z
    wx, wy, wz = s * w * x, s * w * y, s * w * z
    res = _out(out, (*q.shape[:-1], 3, 3))
    res[..., 0, 0] = 1.0 - yy - zz
    res[..., 0, 1] = xy - wz
    res[..., 0, 2] = xz + wy
    res[..., 1, 0] = xy + wz
    res[..., 1, 1] = 1.0 - xx - zz
    res[..., 1, 2] = yz - wx
    res[..., 2, 0] = xz - wy
    res[..., 2, 1] = yz + wx
    res[..., 2, 2] = 1.0 - xx - yy
    return res


def quat_from_mat(m: F64Array, out: F64Array | None = None) -> F64Array:
    """Quaternions from rotation matrices by the trace method (DESIGN 5.80-5.85).

    Each of the four classic formulas divides by one of ``1 + trace``, ``1 + 2 m_ii -
    trace``; the one with the largest divisor (largest of trace and the diagonal) is
    used per matrix, so near-180° rotations stay accurate. The result is normalized;
    its sign is not forced (``w`` may be negative).

    Args:
        m: (..., 3, 3) float64 rotation matrices.
        out: optional (..., 4) float64 destination.

    Returns:
        (..., 4) float64 unit quaternions (w, x, y, z) (``out`` if given).
    """
    m = _as_f64(m)
    if m.ndim < 2 or m.shape[-2:] != (3, 3):
        raise ValueError(f"m must have shape (..., 3, 3); got {m.shape}")
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    trace = m00 + m11 + m22
    # Candidate (unnormalized) quaternions, one per branch: (4 branches, ..., 4).
    cand = np.empty((4, *m.shape[:-2], 4))
    cand[0] = np.stack([1.0 + trace, m21 - m12, m02 - m20, m10 - m01], axis=-1)
    cand[1] = np.stack([m21 - m12, 1.0 + m00 - m11 - m22, m01 + m10, m02 + m20], -1)
    cand[2] = np.stack([m02 - m20, m01 + m10, 1.0 - m00 + m11 - m22, m12 + m21], -1)
    cand[3] = np.stack([m10 - m01, m02 + m20, m12 + m21, 1.0 - m00 - m11 + m22], -1)
    choice = np.argmax(np.stack([trace, m00, m11, m22], axis=0), axis=0)
    picked = np.take_along_axis(cand, choice[None, ..., None], axis=0)[0]
    return quat_normalize(picked, out=_out(out, (*m.shape[:-2], 4)))


def quat_from_axis_angle(axis: F64Array, angle_rad: F64Array | float) -> F64Array:
    """Quaternions rotating by ``angle_rad`` about ``axis`` (right-hand rule).

    Args:
        axis: (..., 3) float64 axis directions (normalized here; must be non-zero).
        angle_rad: (...) float64 angles, radians; broadcasts with ``axis[..., 0]``.

    Returns:
        (..., 4) float64 unit quaternions (w, x, y, z).
    """
    axis = _as_f64(axis)
    _check_last(axis, 3, "axis")
    half = 0.5 * _as_f64(angle_rad)
    unit = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
    shape = np.broadcast_shapes(unit.shape[:-1], half.shape)
    res = np.empty((*shape, 4))
    res[..., 0] = np.cos(half)
    res[..., 1:] = unit * np.sin(half)[..., None]
    return res


def axis_angle_from_quat(q: F64Array) -> tuple[F64Array, F64Array]:
    """Axis and angle of rotations, angle in [0, π] (sign of ``q`` irrelevant).

    Args:
        q: (..., 4) float64 unit quaternions (w, x, y, z).

    Returns:
        ``(axis, angle_rad)``: (..., 3) float64 unit axes (``(1, 0, 0)`` for the
        identity) and (...) float64 angles in radians.
    """
    q = _as_f64(q)
    _check_last(q, 4, "q")
    # Flip to w >= 0 so the angle is the short way round.
    sign = np.where(q[..., :1] < 0.0, -1.0, 1.0)
    vec = q[..., 1:] * sign
    sin_half = np.linalg.norm(vec, axis=-1)
    angle = 2.0 * np.arctan2(sin_half, np.abs(q[..., 0]))
    safe = sin_half > 1e-300
    axis = np.where(
        safe[..., None], vec / np.where(safe, sin_half, 1.0)[..., None], [1.0, 0.0, 0.0]
    )
    return axis, angle


def quat_from_rotvec(rotvec: F64Array) -> F64Array:
    """Quaternions from rotation vectors (axis * angle, radians).

    Args:
        rotvec: (..., 3) float64 rotation vectors, radians.

    Returns:
        (..., 4) float64 unit quaternions (w, x, y, z).
    """
    rotvec = _as_f64(rotvec)
    _check_last(rotvec, 3, "rotvec")
    angle = np.linalg.norm(rotvec, axis=-1)
    half = 0.5 * angle
    # sin(θ/2)/θ, with its Taylor series near 0.
    small = angle < 1e-6
    scale = np.where(
        small, 0.5 - angle * angle / 48.0, np.sin(half) / np.where(small, 1.0, angle)
    )
    res = np.empty((*rotvec.shape[:-1], 4))
    res[..., 0] = np.cos(half)
    res[..., 1:] = rotvec * scale[..., None]
    return res


def rotvec_from_quat(q: F64Array) -> F64Array:
    """Rotation vectors (axis * angle, angle in [0, π]) from quaternions.

    Args:
        q: (..., 4) float64 unit quaternions (w, x, y, z).

    Returns:
        (..., 3) float64 rotation vectors, radians.
    """
    axis, angle = axis_angle_from_quat(q)
    return axis * angle[..., None]


def quat_angle(q: F64Array) -> F64Array:
    """Rotation angle of each quaternion, in [0, π] (``q`` and ``-q`` agree).

    Args:
        q: (..., 4) float64 unit quaternions (w, x, y, z).

    Returns:
        (...) float64 angles, radians.
    """
    q = _as_f64(q)
    _check_last(q, 4, "q")
    return 2.0 * np.arctan2(np.linalg.norm(q[..., 1:], axis=-1), np.abs(q[..., 0]))


def _parse_order(order: str) -> tuple[list[int], bool]:
    if (
        not isinstance(order, str)
        or len(order) != 3
        or not (order.islower() or order.isupper())
        or any(c not in _AXIS_INDEX for c in order.lower())
        or order[0].lower() == order[1].lower()
        or order[1].lower() == order[2].lower()
    ):
        raise ValueError(
            "order must be 3 letters from xyz (all lower = extrinsic, all upper = "
            f"intrinsic, no axis twice in a row); got {order!r}"
        )
    return [_AXIS_INDEX[c] for c in order.lower()], order.isupper()


def quat_from_euler(angles_rad: F64Array, order: str) -> F64Array:
    """Quaternions from Euler angles, scipy's convention (``from_euler``).

    Args:
        angles_rad: (..., 3) float64 angles in radians, in the order of ``order``.
        order: e.g. ``"xyz"`` (extrinsic: ``R = Rz Ry Rx``) or ``"ZXY"`` (intrinsic:
            ``R = Rz Rx Ry``); any of the 12 sequences.

    Returns:
        (..., 4) float64 unit quaternions (w, x, y, z).

    Raises:
        ValueError: naming the bad ``order``.
    """
    axes, intrinsic = _parse_order(order)
    angles = _as_f64(angles_rad)
    _check_last(angles, 3, "angles_rad")
    half = 0.5 * angles
    cos, sin = np.cos(half), np.sin(half)
    elem = np.zeros((3, *angles.shape[:-1], 4))
    for n, axis in enumerate(axes):
        elem[n, ..., 0] = cos[..., n]
        elem[n, ..., 1 + axis] = sin[..., n]
    if intrinsic:
        return quat_mul(quat_mul(elem[0], elem[1]), elem[2])
    return quat_mul(quat_mul(elem[2], elem[1]), elem[0])


def euler_from_quat(q: F64Array, order: str) -> F64Array:
    """Euler angles from quaternions, scipy's convention (``as_euler``).

    Direct method of Bernardes & Viollet (2022), as in scipy. Angles are in
    [-π, π], the middle one in [0, π] (proper) or [-π/2, π/2] (Tait-Bryan). At gimbal
    lock the third angle is set to 0 (no warning).

    Args:
        q: (..., 4) float64 unit quaternions (w, x, y, z).
        order: any of the 12 sequences, e.g. ``"xyz"`` or ``"ZXY"``.

    Returns:
        (..., 3) float64 angles, radians, in the order of ``order``.

    Raises:
        ValueError: naming the bad ``order``.
    """
    axes, intrinsic = _parse_order(order)
    q = _as_f64(q)
    _check_last(q, 4, "q")
    if intrinsic:
        axes = axes[::-1]
    i, j, k = axes
    symmetric = i == k
    if symmetric:
        k = 3 - i - j
    sign = (i - j) * (j - k) * (k - i) // 2
    w, qi, qj, qk = q[..., 0], q[..., 1 + i], q[..., 1 + j], q[..., 1 + k] * sign
    if symmetric:
        a, b, c, d = w, qi, qj, qk
    else:
        a, b, c, d = w - qj, qi + qk, qj + w, qk - qi
    angles = np.empty((*q.shape[:-1], 3))
    second = 2.0 * np.arctan2(np.hypot(c, d), np.hypot(a, b))
    eps = 1e-7
    case1 = np.abs(second) <= eps
    case2 = np.abs(second - np.pi) <= eps
    half_sum = np.arctan2(b, a)
    half_diff = np.arctan2(d, c)
    first = half_sum - half_diff
    third = half_sum + half_diff
    # At gimbal lock only a sum (case1) or difference (case2) of the outer angles is
    # defined: like scipy, the angle that ends up last in ``order`` is set to 0.
    degenerate = case1 | case2
    if intrinsic:  # the first angle here becomes the last after the reversal below
        first = np.where(degenerate, 0.0, first)
        third = np.where(case1, 2.0 * half_sum, third)
        third = np.where(case2, 2.0 * half_diff, third)
    else:
        third = np.where(degenerate, 0.0, third)
        first = np.where(case1, 2.0 * half_sum, first)
        first = np.where(case2, -2.0 * half_diff, first)
    if not symmetric:
        third = third * sign
        second = second - 0.5 * np.pi
    if intrinsic:
        first, third = third, first
    angles[..., 0] = first
    angles[..., 1] = second
    angles[..., 2] = third
    # Wrap into [-π, π].
    angles = np.where(angles < -np.pi, angles + 2.0 * np.pi, angles)
    return np.where(angles > np.pi, angles - 2.0 * np.pi, angles)


def mat_from_euler(angles_rad: F64Array, order: str) -> F64Array:
    """Rotation matrices from Euler angles (DESIGN 5.40-5.46), scipy's convention.

    The product of the three elemental matrices (5.40-5.42): intrinsic ``"XYZ"`` is
    ``Rx(a) @ Ry(b) @ Rz(c)``, extrinsic ``"xyz"`` is ``Rz(c) @ Ry(b) @ Rx(a)``.

    Args:
        angles_rad: (..., 3) float64 angles in radians, in the order of ``order``.
        order: any of the 12 sequences, lower case extrinsic, upper case intrinsic.

    Returns:
        (..., 3, 3) float64 rotation matrices, ``v_a = M @ v_b``.

    Raises:
        ValueError: naming the bad ``order``.
    """
    axes, intrinsic = _parse_order(order)
    angles = _as_f64(angles_rad)
    _check_last(angles, 3, "angles_rad")
    cos, sin = np.cos(angles), np.sin(angles)
    elem = np.zeros((3, *angles.shape[:-1], 3, 3))
    for n, axis in enumerate(axes):
        # Rows/columns of the two axes the elemental rotation mixes (5.40-5.42).
        i, j = (axis + 1) % 3, (axis + 2) % 3
        elem[n, ..., axis, axis] = 1.0
        elem[n, ..., i, i] = cos[..., n]
        elem[n, ..., j, j] = cos[..., n]
        elem[n, ..., i, j] = -sin[..., n]
        elem[n, ..., j, i] = sin[..., n]
    if intrinsic:
        return elem[0] @ elem[1] @ elem[2]
    return elem[2] @ elem[1] @ elem[0]


def euler_from_mat(m: F64Array, order: str) -> F64Array:
    """Euler angles from rotation matrices (the decomposition of 5.47-5.58).

    Goes through :func:`quat_from_mat` (the trace method with its robust branches)
    and :func:`euler_from_quat`, so the ranges and the gimbal-lock rule are those of
    :func:`euler_from_quat` (scipy's ``as_euler``).

    Args:
        m: (..., 3, 3) float64 rotation matrices.
        order: any of the 12 sequences.

    Returns:
        (..., 3) float64 angles, radians, in the order of ``order``.

    Raises:
        ValueError: naming the bad ``order`` or a bad matrix shape.
    """
    _parse_order(order)
    return euler_from_quat(quat_from_mat(m), order)


def convert_euler_order(
    angles_rad: F64Array, from_order: str, to_order: str
) -> F64Array:
    """Re-express Euler angles in another rotation order ("Switching the Order").

    Args:
        angles_rad: (..., 3) float64 angles, radians, in ``from_order``.
        from_order: the sequence the angles are in (any of the 12, either case).
        to_order: the sequence wanted.

    Returns:
        (..., 3) float64 angles, radians, in ``to_order`` (same rotation).

    Raises:
        ValueError: naming a bad order.
    """
    return euler_from_quat(quat_from_euler(angles_rad, from_order), to_order)


def swing_twist(q: F64Array, axis: F64Array) -> tuple[F64Array, F64Array]:
    """Swing-twist decomposition ``q = swing ⊗ twist`` about a child-frame axis.

    ``twist`` rotates about ``axis`` (expressed in the frame ``q`` maps from, e.g. a
    bone's long axis +Y in ``parent_from_bone``), applied first; ``swing`` rotates
    about an axis perpendicular to it. The twist is the projection of ``q``'s vector
    part on ``axis``, renormalized; when that projection and ``w`` both vanish (a
    half-turn swing) the twist is undefined and returned as the identity.

    Args:
        q: (..., 4) float64 unit quaternions (w, x, y, z).
        axis: (3,) float64 unit axis in the child frame.

    Returns:
        ``(swing, twist)``: (..., 4) float64 unit quaternions (w, x, y, z).
    """
    q = _as_f64(q)
    _check_last(q, 4, "q")
    axis = _as_f64(axis)
    proj = np.sum(q[..., 1:] * axis, axis=-1)
    twist = np.zeros(q.shape)
    twist[..., 0] = q[..., 0]
    twist[..., 1:] = proj[..., None] * axis
    norm = np.sqrt(np.sum(twist * twist, axis=-1, keepdims=True))
    degenerate = norm < 1e-12
    twist = np.where(
        degenerate, [1.0, 0.0, 0.0, 0.0], twist / np.where(degenerate, 1.0, norm)
    )
    swing = quat_mul(q, quat_conj(twist))
    return swing, twist


def twist_angle(q: F64Array, axis: F64Array) -> F64Array:
    """Signed twist angle of ``q`` about a child-frame ``axis``, in (-π, π].

    Args:
        q: (..., 4) float64 unit quaternions (w, x, y, z).
        axis: (3,) float64 unit axis in the child frame.

    Returns:
        (...) float64 angles, radians (right-hand rule about ``axis``).
    """
    q = _as_f64(q)
    _check_last(q, 4, "q")
    proj = np.sum(q[..., 1:] * _as_f64(axis), axis=-1)
    sign = np.where(q[..., 0] < 0.0, -1.0, 1.0)
    angle = 2.0 * np.arctan2(sign * proj, sign * q[..., 0])
    return np.where(angle <= -np.pi, angle + 2.0 * np.pi, angle)


def slerp(q0: F64Array, q1: F64Array, u: F64Array | float) -> F64Array:
    """Spherical linear interpolation along the shorter arc (DESIGN 5.86-5.87).

    ``q1`` is negated where ``dot(q0, q1) < 0`` so the path is the short way round.
    Where the two are closer than :data:`SLERP_LINEAR_BELOW_RAD` the weights
    ``sin((1-u)θ)/sinθ`` lose precision, so a normalized linear blend is used instead.

    Args:
        q0: (..., 4) float64 unit quaternions (w, x, y, z) at ``u = 0``.
        q1: (..., 4) float64 unit quaternions (w, x, y, z) at ``u = 1``.
        u: (...) float64 interpolation parameters (any real; [0, 1] interpolates).

    Returns:
        (..., 4) float64 unit quaternions (w, x, y, z), shape broadcast of the inputs.
    """
    q0 = _as_f64(q0)
    q1 = _as_f64(q1)
    _check_last(q0, 4, "q0")
    _check_last(q1, 4, "q1")
    u = _as_f64(u)[..., None]
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0.0, -q1, q1)
    dot = np.minimum(np.abs(dot), 1.0)
    theta = np.arccos(dot)  # half the rotation angle between the ends
    sin_theta = np.sin(theta)
    linear = theta < 0.5 * SLERP_LINEAR_BELOW_RAD
    safe_sin = np.where(linear, 1.0, sin_theta)
    w0 = np.where(linear, 1.0 - u, np.sin((1.0 - u) * theta) / safe_sin)
    w1 = np.where(linear, u, np.sin(u * theta) / safe_sin)
    return quat_normalize(w0 * q0 + w1 * q1)


def quat_canonical_hemisphere(
    q: F64Array, ref: F64Array, out: F64Array | None = None
) -> F64Array:
    """Negate each quaternion whose dot product with ``ref`` is negative.

    Makes a stream sign-continuous (STYLE §3: engines blend), without changing the
    rotation.

    Args:
        q: (..., 4) float64 quaternions (w, x, y, z).
        ref: (..., 4) float64 reference quaternions (w, x, y, z), e.g. the last sent;
            broadcasts with ``q``.
        out: optional (..., 4) float64 destination (may alias ``q``).

    Returns:
        (..., 4) float64 quaternions (w, x, y, z) (``out`` if given).
    """
    q = _as_f64(q)
    ref = _as_f64(ref)
    _check_last(q, 4, "q")
    _check_last(ref, 4, "ref")
    sign = np.where(np.sum(q * ref, axis=-1, keepdims=True) < 0.0, -1.0, 1.0)
    return np.multiply(q, sign, out=_out(out, np.broadcast_shapes(q.shape, ref.shape)))
