"""All 12 rotation orders (intrinsic and extrinsic) against scipy, gimbal lock included;
the trace method's four branches (5.80-5.85); swing-twist decomposition."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from retargetd.daemon import rotations as rot

TAIT_BRYAN = ("xyz", "xzy", "yxz", "yzx", "zxy", "zyx")
PROPER = ("xyx", "xzx", "yxy", "yzy", "zxz", "zyz")
ALL_ORDERS = [*TAIT_BRYAN, *PROPER, *(o.upper() for o in TAIT_BRYAN + PROPER)]


def _same_rotation(a: np.ndarray, b: np.ndarray, atol: float) -> bool:
    return bool(np.all(np.abs(np.abs(np.sum(a * b, axis=-1)) - 1.0) < atol))


def _locked_angles(order: str) -> np.ndarray:
    """Angles with the middle one at each gimbal-lock value of ``order``."""
    proper = order[0].lower() == order[2].lower()
    middle = (0.0, np.pi) if proper else (0.5 * np.pi, -0.5 * np.pi)
    return np.array([[a, m, c] for m in middle for a, c in ((0.3, -0.7), (-2.0, 1.1))])


@pytest.mark.parametrize("order", ALL_ORDERS)
def test_matrix_and_quaternion_from_euler_match_scipy(order: str) -> None:
    rng = np.random.default_rng(3)
    angles = rng.uniform(-np.pi, np.pi, size=(300, 3))
    angles = np.concatenate([angles, _locked_angles(order)])
    expected = Rotation.from_euler(order, angles)
    np.testing.assert_allclose(
        rot.mat_from_euler(angles, order), expected.as_matrix(), atol=1e-14
    )
    q = rot.quat_from_euler(angles, order)
    assert _same_rotation(q, expected.as_quat(scalar_first=True), atol=1e-14)


@pytest.mark.parametrize("order", ALL_ORDERS)
def test_euler_from_matrix_matches_scipy_away_from_lock(order: str) -> None:
    r = Rotation.random(400, rng=11)
    m = r.as_matrix()
    np.testing.assert_allclose(
        rot.euler_from_mat(m, order), r.as_euler(order), atol=1e-10
    )
    back = rot.mat_from_euler(rot.euler_from_mat(m, order), order)
    np.testing.assert_allclose(back, m, atol=1e-12)


@pytest.mark.parametrize("order", ALL_ORDERS)
def test_euler_at_gimbal_lock_matches_scipy(order: str) -> None:
    angles = _locked_angles(order)
    r = Rotation.from_euler(order, angles)
    with pytest.warns(UserWarning, match="Gimbal lock"):
        expected = r.as_euler(order)  # scipy sets the third angle to 0 and warns
    for got in (
        rot.euler_from_quat(r.as_quat(scalar_first=True), order),
        rot.euler_from_mat(r.as_matrix(), order),
    ):
        # The same rotation, and the same angles as scipy (angles of +-pi may wrap).
        np.testing.assert_allclose(
            rot.mat_from_euler(got, order), r.as_matrix(), atol=1e-9
        )
        diff = np.angle(np.exp(1j * (got - expected)))
        np.testing.assert_allclose(diff, 0.0, atol=1e-7)


def test_convert_order_keeps_the_rotation() -> None:
    rng = np.random.default_rng(5)
    xyz = rng.uniform(-1.0, 1.0, size=(100, 3))
    zyx = rot.convert_euler_order(xyz, "XYZ", "ZYX")
    np.testing.assert_allclose(
        Rotation.from_euler("ZYX", zyx).as_matrix(),
        Rotation.from_euler("XYZ", xyz).as_matrix(),
        atol=1e-13,
    )


@pytest.mark.parametrize("branch", range(4))
def test_trace_method_each_branch_matches_scipy(branch: int) -> None:
    """Rotations whose largest of (trace, m00, m11, m22) is each in turn (5.81-5.85)."""
    rng = np.random.default_rng(branch)
    r = Rotation.random(4000, rng=branch)
    m = r.as_matrix()
    keys = np.stack(
        [np.trace(m, axis1=-2, axis2=-1), m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]]
    )
    pick = np.argmax(keys, axis=0) == branch
    assert pick.sum() > 100
    # Near-half-turns too: trace -> -1, where the w branch loses all precision.
    axis = np.eye(3)[branch - 1] if branch else np.array([1.0, 0.0, 0.0])
    near = Rotation.from_rotvec((np.pi - rng.uniform(0, 1e-7, 20))[:, None] * axis)
    mats = np.concatenate([m[pick], near.as_matrix() if branch else m[pick][:1]])
    expected = Rotation.from_matrix(mats).as_quat(scalar_first=True)
    assert _same_rotation(rot.quat_from_mat(mats), expected, atol=1e-13)


def test_swing_twist_recomposes_and_separates() -> None:
    q = Rotation.random(500, rng=2).as_quat(scalar_first=True)
    axis = np.array([0.0, 1.0, 0.0])
    swing, twist = rot.swing_twist(q, axis)
    assert _same_rotation(rot.quat_mul(swing, twist), q, atol=1e-13)
    # The twist turns about the axis only; the swing moves the axis but has no
    # component along it (its rotation axis is perpendicular to +Y).
    np.testing.assert_allclose(twist[:, [1, 3]], 0.0, atol=1e-15)
    np.testing.assert_allclose(swing[:, 2], 0.0, atol=1e-13)
    # Independent: a swing about an axis in the xz plane, then a turn about +Y.
    swing_ref = Rotation.from_rotvec([[0.3, 0.0, -0.5], [0.0, 0.0, 1.0]])
    turn = Rotation.from_rotvec([[0.0, 1.2, 0.0], [0.0, -2.5, 0.0]])
    got = rot.twist_angle((swing_ref * turn).as_quat(scalar_first=True), axis)
    np.testing.assert_allclose(got, [1.2, -2.5], atol=1e-14)
