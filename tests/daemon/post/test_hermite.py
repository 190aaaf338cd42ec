"""Hermite spine (5.60-5.61): C1 at the joins, end points exact, a synthetic bend
followed within the interpolation error bound."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from retargetd.daemon.post.hermite import HermiteSpine


def _arc(radius_m: float, bend_rad: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """n points on a circular arc in the xz plane (a spine bent forward), centre."""
    ang = np.linspace(0.0, bend_rad, n)
    centre = np.array([radius_m, 0.2, 1.0])
    pts = centre + radius_m * np.stack([-np.cos(ang), np.zeros(n), np.sin(ang)], -1)
    return pts, centre


@pytest.mark.parametrize("n_points", [2, 3, 4, 6])
def test_c1_at_joins_and_exact_ends(n_points: int) -> None:
    rng = np.random.default_rng(n_points)
    steps = rng.normal(0.0, 0.05, size=(n_points, 3))
    steps[:, 2] += 0.1  # upwards
    points = np.cumsum(steps, axis=0)
    spine = HermiteSpine(n_points, 7)
    out = np.full((7, 3), np.nan)
    assert spine.apply(points, out) is out
    assert np.array_equal(out[0], points[0])
    assert np.array_equal(out[-1], points[-1])
    for i in range(n_points - 1):
        p0, _ = spine.evaluate(i, 0.0)
        p1, _ = spine.evaluate(i, 1.0)
        np.testing.assert_allclose(p0, points[i], atol=1e-15)
        np.testing.assert_allclose(p1, points[i + 1], atol=1e-15)
    for i in range(n_points - 2):
        _, left = spine.evaluate(i, 1.0)
        _, right = spine.evaluate(i + 1, 0.0)
        np.testing.assert_allclose(left, right, atol=1e-15)  # matching tangents
    # Joints lie on the curve: each is within the curve's own dense samples.
    dense = np.concatenate(
        [spine.evaluate(i, np.linspace(0, 1, 4001))[0] for i in range(n_points - 1)]
    )
    gaps = np.min(np.linalg.norm(out[:, None] - dense[None], axis=-1), axis=1)
    assert np.all(gaps < 1e-4)


def test_follows_a_synthetic_bend() -> None:
    # A 0.45 m spine (pelvis top to neck base of a 1.75 m adult is about a quarter of
    # the height) flexed 60°, solved at 4 points, placed on a 5-joint target spine.
    length_m, bend = 0.45, np.radians(60.0)
    radius = length_m / bend
    points, centre = _arc(radius, bend, 4)
    spine = HermiteSpine(4, 5)
    out = spine.apply(points, np.empty((5, 3)))
    # Bound, per segment of angle D in the parameter u: exact-tangent Hermite error
    # <= |p''''| / 384 = R D^4 / 384; a tangent error e moves the curve by at most
    # (4/27) e per end (max of u(1-u)^2); central differences err by <= R D^3 / 6,
    # the one-sided 3-point ones by <= R D^3 / 3.
    d = bend / 3
    bound = radius * d**4 / 384 + 4 / 27 * (radius * d**3 / 3) * 2
    radial = np.abs(np.linalg.norm(out - centre, axis=-1) - radius)
    print(f"\nradial error {1e3 * radial.max():.3f} mm (bound {1e3 * bound:.3f} mm)")
    assert radial.max() <= bound
    # Equal arc length between the joints, measured on the curve independently.
    u = np.linspace(0, 1, 20001)
    dense = np.concatenate([spine.evaluate(i, u)[0] for i in range(3)])
    cum = np.concatenate(
        [[0.0], np.cumsum(np.linalg.norm(np.diff(dense, axis=0), axis=-1))]
    )
    at = cum[np.argmin(np.linalg.norm(out[:, None] - dense[None], axis=-1), axis=1)]
    np.testing.assert_allclose(np.diff(at), cum[-1] / 4, rtol=1e-3)
    # The tangents at the joints follow the arc's (perpendicular to the radius): the
    # end tangents' error R D^3 / 3 against their length R D tilts them by <= D^2 / 3.
    radial_dir = (out - centre) / np.linalg.norm(out - centre, axis=-1, keepdims=True)
    tilt = np.abs(np.sum(spine.joint_tangents * radial_dir, axis=-1))
    assert np.all(tilt <= d**2 / 3)


def test_allocates_nothing() -> None:
    points, _ = _arc(0.4, 1.0, 4)
    spine = HermiteSpine(4, 6)
    out = np.empty((6, 3))
    spine.apply(points, out)
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        start, _ = tracemalloc.get_traced_memory()
        for _ in range(1000):
            spine.apply(points, out)
        end, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert end - start < 1024
    assert peak - start < 3072, peak - start  # numba's argument boxing


def test_bad_counts_are_named() -> None:
    with pytest.raises(ValueError, match="n_joints"):
        HermiteSpine(3, 1)
    with pytest.raises(ValueError, match="n_points"):
        HermiteSpine(1, 4)
