"""world_from_capture: a rotation only, +90 deg about X for Y-up, units to metres."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from retargetd.protocols import conventions as cv


@pytest.mark.parametrize("up", cv.UP_AXES)
def test_world_from_capture_is_a_rotation_taking_up_to_z(up: str) -> None:
    mat = cv.world_from_capture_mat(up)
    np.testing.assert_allclose(mat @ mat.T, np.eye(3), atol=0)
    assert np.linalg.det(mat) == pytest.approx(1.0)
    np.testing.assert_array_equal(mat @ cv.up_vector(up), [0.0, 0.0, 1.0])


def test_y_up_is_plus_90_about_x() -> None:
    expected = Rotation.from_euler("x", 90, degrees=True).as_matrix()
    np.testing.assert_allclose(cv.world_from_capture_mat("+Y"), expected, atol=1e-15)


def test_z_up_keeps_the_lab_axes() -> None:
    np.testing.assert_array_equal(cv.world_from_capture_mat("z"), np.eye(3))


def test_positions_mm_y_up_to_world_metres() -> None:
    # A marker 1700 mm up and 250 mm towards capture +Z in a Y-up lab.
    pos = np.array([[100.0, 1700.0, 250.0], [np.nan, np.nan, np.nan]])
    world = cv.world_from_capture_pos(pos, "+Y", "mm")
    np.testing.assert_allclose(world[0], [0.1, -0.25, 1.7])
    assert np.isnan(world[1]).all()


def test_bad_values_are_named() -> None:
    with pytest.raises(ValueError, match="'sideways'"):
        cv.normalize_up_axis("sideways")
    with pytest.raises(ValueError, match="'furlong'"):
        cv.normalize_units("furlong")
