"""Rotation kernels against scipy (``scalar_first=True``) and quaternion identities."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation, Slerp

from retargetd.daemon import rotations as rot

ORDERS = [
    *("xyz", "xzy", "yxz", "yzx", "zxy", "zyx"),
    *("xyx", "xzx", "yxy", "yzy", "zxz", "zyz"),
]
ALL_ORDERS = ORDERS + [o.upper() for o in ORDERS]


def _same_rotation(a: np.ndarray, b: np.ndarray, atol: float = 1e-12) -> bool:
    """q and -q are the same rotation."""
    return bool(np.all(np.abs(np.abs(np.sum(a * b, axis=-1)) - 1.0) < atol))


@pytest.fixture
def quats() -> np.ndarray:
    return Rotation.random(500, rng=7).as_quat(scalar_first=True)


_finite = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False)
_raw_quat = arrays(np.float64, (4,), elements=_finite).filter(
    lambda q: np.linalg.norm(q) > 0.1
)
unit_quat = _raw_quat.map(lambda q: q / np.linalg.norm(q))


# --- against scipy ---------------------------------------------------------------


def test_quat_mul_matches_scipy(quats: np.ndarray) -> None:
    other = quats[::-1].copy()
    expected = (
        Rotation.from_quat(quats, scalar_first=True)
        * Rotation.from_quat(other, scalar_first=True)
    ).as_quat(scalar_first=True)
    assert _same_rotation(rot.quat_mul(quats, other), expected)


def test_rotate_and_matrix_match_scipy(
    quats: np.ndarray, rng: np.random.Generator
) -> None:
    r = Rotation.from_quat(quats, scalar_first=True)
    v = rng.normal(size=(len(quats), 3))
    np.testing.assert_allclose(rot.quat_rotate(quats, v), r.apply(v), atol=1e-12)
    np.testing.assert_allclose(rot.mat_from_quat(quats), r.as_matrix(), atol=1e-12)
    assert _same_rotation(rot.quat_from_mat(r.as_matrix()), quats)


def test_conj_inv_normalize(quats: np.ndarray) -> None:
    r_inv = Rotation.from_quat(quats, scalar_first=True).inv()
    assert _same_rotation(rot.quat_conj(quats), r_inv.as_quat(scalar_first=True))
    scaled = quats * 3.0
    assert _same_rotation(rot.quat_inv(scaled) * 3.0, r_inv.as_quat(scalar_first=True))
    np.testing.assert_allclose(rot.quat_normalize(scaled), quats, atol=1e-15)


def test_axis_angle_rotvec_and_angle_match_scipy(quats: np.ndarray) -> None:
    r = Rotation.from_quat(quats, scalar_first=True)
    rotvec = r.as_rotvec()
    np.testing.assert_allclose(rot.rotvec_from_quat(quats), rotvec, atol=1e-12)
    np.testing.assert_allclose(rot.rotvec_from_quat(-quats), rotvec, atol=1e-12)
    assert _same_rotation(rot.quat_from_rotvec(rotvec), quats)
    angle = np.linalg.norm(rotvec, axis=-1)
    np.testing.assert_allclose(rot.quat_angle(quats), angle, atol=1e-12)
    np.testing.assert_allclose(rot.quat_angle(-quats), angle, atol=1e-12)
    axis, angle2 = rot.axis_angle_from_quat(quats)
    np.testing.assert_allclose(angle2, angle, atol=1e-12)
    assert _same_rotation(rot.quat_from_axis_angle(axis * 2.5, angle2), quats)
    identity_axis, identity_angle = rot.axis_angle_from_quat([1.0, 0.0, 0.0, 0.0])
    assert identity_angle == 0.0
    np.testing.assert_array_equal(identity_axis, [1.0, 0.0, 0.0])


def test_quat_from_axis_angle_pinned() -> None:
    # +90 deg about Z takes +X to +Y (active, right-handed).
    q = rot.quat_from_axis_angle([0.0, 0.0, 1.0], np.pi / 2)
    np.testing.assert_allclose(q, [np.sqrt(0.5), 0.0, 0.0, np.sqrt(0.5)], atol=1e-15)
    np.testing.assert_allclose(
        rot.quat_rotate(q, [1.0, 0.0, 0.0]), [0, 1, 0], atol=1e-15
    )


@pytest.mark.parametrize("order", ALL_ORDERS)
def test_euler_matches_scipy(order: str, quats: np.ndarray) -> None:
    r = Rotation.from_quat(quats, scalar_first=True)
    euler = r.as_euler(order)
    np.testing.assert_allclose(rot.euler_from_quat(quats, order), euler, atol=1e-12)
    expected = Rotation.from_euler(order, euler).as_quat(scalar_first=True)
    assert _same_rotation(rot.quat_from_euler(euler, order), expected)


@pytest.mark.parametrize("order", ["xyz", "ZXY", "zxz", "YXY"])
def test_euler_at_gimbal_lock_still_round_trips(order: str) -> None:
    proper = order[0].lower() == order[2].lower()
    middle = [0.0, np.pi] if proper else [np.pi / 2, -np.pi / 2]
    angles = np.array([[0.3, m, -0.7] for m in middle])
    q = rot.quat_from_euler(angles, order)
    back = rot.euler_from_quat(q, order)
    assert _same_rotation(rot.quat_from_euler(back, order), q, atol=1e-9)


def test_bad_euler_order_is_named() -> None:
    with pytest.raises(ValueError, match="'xYz'"):
        rot.quat_from_euler([0.0, 0.0, 0.0], "xYz")
    with pytest.raises(ValueError, match="'xxy'"):
        rot.euler_from_quat([1.0, 0.0, 0.0, 0.0], "xxy")


def test_quat_from_mat_near_180_degrees(rng: np.random.Generator) -> None:
    axes = rng.normal(size=(200, 3))
    angles = np.pi - rng.uniform(0.0, 1e-6, size=200)
    angles[:50] = np.pi
    q = rot.quat_from_axis_angle(axes, angles)
    back = rot.quat_from_mat(rot.mat_from_quat(q))
    assert _same_rotation(back, q, atol=1e-12)
    scipy_back = Rotation.from_matrix(rot.mat_from_quat(q)).as_quat(scalar_first=True)
    assert _same_rotation(back, scipy_back, atol=1e-12)
    # Exactly 180 deg about a coordinate axis: w = 0, one component ±1.
    half_turn = rot.quat_from_mat(np.diag([1.0, -1.0, -1.0]))
    np.testing.assert_allclose(np.abs(half_turn), [0.0, 1.0, 0.0, 0.0], atol=1e-15)


def test_slerp_matches_scipy(quats: np.ndarray) -> None:
    q0, q1 = quats[:250], quats[250:]
    u = np.linspace(0.0, 1.0, 250)
    got = rot.slerp(q0, q1, u)
    for i in range(0, 250, 25):
        pair = Rotation.from_quat(np.stack([q0[i], q1[i]]), scalar_first=True)
        expected = Slerp([0.0, 1.0], pair)(u[i]).as_quat(scalar_first=True)
        assert _same_rotation(got[i], expected)
    # Ends are hit exactly (up to sign for q1).
    assert _same_rotation(rot.slerp(q0, q1, 0.0), q0)
    assert _same_rotation(rot.slerp(q0, q1, 1.0), q1)


def test_slerp_small_angle_falls_back_to_lerp() -> None:
    q0 = np.array([1.0, 0.0, 0.0, 0.0])
    q1 = rot.quat_from_axis_angle([0.0, 0.0, 1.0], 1e-9)
    mid = rot.slerp(q0, q1, 0.5)
    assert np.all(np.isfinite(mid))
    np.testing.assert_allclose(rot.quat_angle(mid), 0.5e-9, rtol=1e-6)
    same = rot.slerp(q0, q0, np.linspace(0.0, 1.0, 5))
    np.testing.assert_array_equal(same, np.tile(q0, (5, 1)))


def test_slerp_takes_short_arc() -> None:
    q0 = np.array([1.0, 0.0, 0.0, 0.0])
    q1 = -rot.quat_from_axis_angle([1.0, 0.0, 0.0], 0.4)
    np.testing.assert_allclose(rot.quat_angle(rot.slerp(q0, q1, 0.5)), 0.2, atol=1e-12)


def test_canonical_hemisphere(quats: np.ndarray) -> None:
    ref = quats[0]
    got = rot.quat_canonical_hemisphere(-quats, ref)
    assert np.all(got @ ref >= 0.0)
    assert _same_rotation(got, quats)


# --- hot-path contract -----------------------------------------------------------


def test_out_is_returned_and_may_alias(
    quats: np.ndarray, rng: np.random.Generator
) -> None:
    p = quats[:100].copy()
    q = quats[100:200].copy()
    expected = rot.quat_mul(p, q)
    out = np.empty((100, 4))
    assert rot.quat_mul(p, q, out=out) is out
    assert rot.quat_mul(p, q, out=p) is p  # aliasing the first argument
    np.testing.assert_array_equal(p, expected)
    assert rot.quat_conj(q, out=out) is out
    assert rot.quat_normalize(q * 2.0, out=out) is out
    assert rot.quat_canonical_hemisphere(q, q[0], out=out) is out
    v = rng.normal(size=(100, 3))
    expected_v = rot.quat_rotate(q, v)
    out3 = np.empty((100, 3))
    assert rot.quat_rotate(q, v, out=out3) is out3
    assert rot.quat_rotate(q, v, out=v) is v
    np.testing.assert_array_equal(v, expected_v)
    mats = np.empty((100, 3, 3))
    assert rot.mat_from_quat(q, out=mats) is mats
    assert mats.dtype == np.float64
    assert rot.quat_from_mat(mats, out=out) is out
    with pytest.raises(ValueError, match="out must have shape"):
        rot.quat_mul(p, q, out=np.empty((3, 4)))


def test_shapes_broadcast() -> None:
    q = Rotation.random(6, rng=1).as_quat(scalar_first=True).reshape(2, 3, 4)
    assert rot.quat_mul(q, q[0]).shape == (2, 3, 4)
    assert rot.quat_rotate(q, np.ones(3)).shape == (2, 3, 3)
    assert rot.mat_from_quat(q).shape == (2, 3, 3, 3)
    assert rot.quat_from_euler(np.zeros((2, 3, 3)), "XYZ").shape == (2, 3, 4)
    with pytest.raises(ValueError, match=r"q must have shape \(\.\.\., 4\)"):
        rot.quat_angle(np.zeros(3))


# --- properties ------------------------------------------------------------------


@settings(max_examples=60, deadline=None)
@given(unit_quat, unit_quat)
def test_product_keeps_norm_and_sign_is_irrelevant(
    p: np.ndarray, q: np.ndarray
) -> None:
    pq = rot.quat_mul(p, q)
    assert abs(np.linalg.norm(pq) - 1.0) < 1e-12
    v = np.array([0.3, -1.2, 2.0])
    np.testing.assert_allclose(
        rot.quat_rotate(-p, v), rot.quat_rotate(p, v), atol=1e-12
    )
    np.testing.assert_allclose(rot.mat_from_quat(-p), rot.mat_from_quat(p), atol=1e-12)
    assert abs(np.linalg.norm(rot.quat_rotate(p, v)) - np.linalg.norm(v)) < 1e-12


@settings(max_examples=60, deadline=None)
@given(_raw_quat)
def test_inverse(q: np.ndarray) -> None:
    np.testing.assert_allclose(
        rot.quat_mul(q, rot.quat_inv(q)), [1.0, 0.0, 0.0, 0.0], atol=1e-12
    )
    u = rot.quat_normalize(q)
    v = np.array([1.0, 2.0, 3.0])
    np.testing.assert_allclose(
        rot.quat_rotate(rot.quat_conj(u), rot.quat_rotate(u, v)), v, atol=1e-12
    )


@settings(max_examples=60, deadline=None)
@given(unit_quat, unit_quat, unit_quat)
def test_associativity(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> None:
    np.testing.assert_allclose(
        rot.quat_mul(rot.quat_mul(a, b), c),
        rot.quat_mul(a, rot.quat_mul(b, c)),
        atol=1e-12,
    )


@settings(max_examples=100, deadline=None)
@given(unit_quat)
def test_mat_round_trip(q: np.ndarray) -> None:
    assert _same_rotation(rot.quat_from_mat(rot.mat_from_quat(q)), q, atol=1e-12)


@settings(max_examples=40, deadline=None)
@given(
    st.sampled_from(ALL_ORDERS),
    st.floats(-3.1, 3.1),
    st.floats(0.05, 1.5),
    st.floats(-3.1, 3.1),
    st.booleans(),
)
def test_euler_round_trip_all_orders(
    order: str, a: float, b: float, c: float, negative_middle: bool
) -> None:
    proper = order[0].lower() == order[2].lower()
    # Away from gimbal lock: middle in (0, π) for proper, (-π/2, π/2) for Tait-Bryan.
    middle = b + 0.05 if proper else (-b if negative_middle else b)
    angles = np.array([a, middle, c])
    back = rot.euler_from_quat(rot.quat_from_euler(angles, order), order)
    np.testing.assert_allclose(back, angles, atol=1e-9)
