"""Shifting pivot: the chapter's prose example and its pseudocode (3 joints, 15°),
positive and negative, each axis; the per-frame stage against scipy."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from retargetd.daemon.post.pivot import ShiftingPivot, distribute, shifting_pivot


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_prose_example(sign: float) -> None:
    # "a vertebra has a range of rotation of 10°... rotating the whole spine 36° would
    # result in the rotation of the lowermost four vertebrae: the first three by 10°
    # and a fourth by 6°".
    out = distribute(sign * 36.0, 10.0, np.empty(6))
    np.testing.assert_allclose(out, sign * np.array([10, 10, 10, 6, 0, 0]), atol=1e-12)
    assert out.sum() == pytest.approx(sign * 36.0)


# (rx, ry, rz) in degrees -> per joint (rx, ry, rz), worked by hand from the listing:
# rx, rz doubled, 15° per joint, carried over; ry / 3 each.
CASES = [
    ((20.0, 0.0, 0.0), [[15, 0, 0], [15, 0, 0], [10, 0, 0]]),  # 40 = 15 + 15 + 10
    ((0.0, 0.0, 20.0), [[0, 0, 15], [0, 0, 15], [0, 0, 10]]),
    ((5.0, 0.0, 0.0), [[10, 0, 0], [0, 0, 0], [0, 0, 0]]),  # 10 <= 15: first joint
    ((0.0, 0.0, 7.5), [[0, 0, 15], [0, 0, 0], [0, 0, 0]]),  # 15 is not > 15
    ((30.0, 0.0, 0.0), [[15, 0, 0], [15, 0, 0], [15, 0, 0]]),  # 60: 15 dropped
    ((0.0, 30.0, 0.0), [[0, 10, 0], [0, 10, 0], [0, 10, 0]]),  # ry split, not doubled
    ((12.0, 9.0, 16.0), [[15, 3, 15], [9, 3, 15], [0, 3, 2]]),
]


@pytest.mark.parametrize("sign", [1.0, -1.0])
@pytest.mark.parametrize(("rot", "expected"), CASES)
def test_pseudocode(
    rot: tuple[float, float, float], expected: list[list[int]], sign: float
) -> None:
    out = np.full((3, 3), np.nan)
    rx, ry, rz = (sign * r for r in rot)
    assert shifting_pivot(rx, ry, rz, 15.0, out) is out
    np.testing.assert_allclose(out, sign * np.array(expected, dtype=float), atol=1e-12)


def test_without_doubling_the_total_is_kept_within_capacity() -> None:
    rng = np.random.default_rng(1)
    out = np.empty((4, 3))
    for rx, ry, rz in rng.uniform(-40.0, 40.0, size=(200, 3)):
        shifting_pivot(rx, ry, rz, 15.0, out, double=False)
        np.testing.assert_allclose(out.sum(axis=0), [rx, ry, rz], atol=1e-12)
        assert np.all(np.abs(out[:, [0, 2]]) <= 15.0)


def test_stage_matches_the_euler_version_and_scipy() -> None:
    stage = ShiftingPivot()  # 3 joints, 15°
    rng = np.random.default_rng(2)
    out = np.empty((3, 4))
    angles = np.empty((3, 3))
    for xyz_deg in rng.uniform(-25.0, 25.0, size=(100, 3)):
        q = Rotation.from_euler("XYZ", xyz_deg, degrees=True).as_quat(scalar_first=True)
        assert stage.apply(q, out) is out
        shifting_pivot(*xyz_deg, 15.0, angles)
        expected = Rotation.from_euler("XYZ", angles, degrees=True)
        dots = np.abs(np.sum(out * expected.as_quat(scalar_first=True), axis=-1))
        np.testing.assert_allclose(dots, 1.0, atol=1e-12)
        np.testing.assert_allclose(np.degrees(stage.angles_rad), angles, atol=1e-9)


def test_stage_allocates_nothing() -> None:
    stage = ShiftingPivot(5, 10.0)
    euler_deg = [30.0, -10.0, 20.0]
    q = Rotation.from_euler("XYZ", euler_deg, degrees=True).as_quat(scalar_first=True)
    out = np.empty((5, 4))
    stage.apply(q, out)
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        start, _ = tracemalloc.get_traced_memory()
        for _ in range(1000):
            stage.apply(q, out)
        end, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert end - start < 1024
    assert peak - start < 3072, peak - start  # numba's argument boxing, see test_twist


def test_bad_arguments_are_named() -> None:
    with pytest.raises(ValueError, match="limit"):
        distribute(10.0, 0.0, np.empty(3))
    with pytest.raises(ValueError, match="n_joints"):
        ShiftingPivot(0)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        shifting_pivot(1.0, 2.0, 3.0, 15.0, np.empty((3, 4)))
