"""Shifting pivot: the chapter's prose example and its pseudocode (3 joints, 15°),
positive and negative, each axis; the per-frame stage against scipy."""

from __future__ import annotations

import tracemalloc
from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from retargetd.daemon.post.pivot import (
    ShiftingPivot,
    SpinePivot,
    distribute,
    shifting_pivot,
)
from retargetd.daemon.retarget.skeleton import default_humanoid


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


def _humanoid_frame(
    bend: Rotation, rng: np.random.Generator
) -> tuple[Any, np.ndarray, np.ndarray]:
    """A retargeted frame on the default humanoid (rest rotations identity): every
    bone's world delta random, the Chest's the Hips' times ``bend``; L from them."""
    target = default_humanoid()
    n = len(target.bone_names)
    e = Rotation.random(n, random_state=rng)
    hips, chest = target.index("Hips"), target.index("Chest")
    e_list = list(e)
    e_list[chest] = e_list[hips] * bend
    e = Rotation.concatenate(e_list)
    g = e.as_quat(scalar_first=True)  # T = I: G = E
    rfb = np.empty_like(g)
    for j, p in enumerate(target.parents):
        rel = e[j] if p < 0 else e[p].inv() * e[j]
        rfb[j] = rel.as_quat(scalar_first=True)
    return target, g, rfb


def test_spine_pivot_on_a_humanoid_frame() -> None:
    """``SpinePivot`` (``[target] spine = "pivot"``): a 36° forward bend of the Chest
    against the Hips (about the target's left, the listing's x) becomes the listing's
    shares on Spine, Chest and UpperChest (72° doubled: 15, 15, 15), each joint's L is
    its share, every other bone keeps its world rotation, and every bone's L is
    consistent with its parent's new world rotation (E_h = E_parent L_h)."""
    rng = np.random.default_rng(0)
    target0 = default_humanoid()
    left = target0.left_world
    bend = Rotation.from_rotvec(np.radians(36.0) * left)
    target, g, rfb = _humanoid_frame(bend, rng)
    before = g.copy()
    mapped = {"Hips", "Spine", "Chest", "Neck", "Head"}
    stage = SpinePivot(
        target.bone_names, target.parents, target.rest_world_from_bone_quat, mapped,
        left,
    )  # fmt: skip
    assert stage.bones == ("Spine", "Chest", "UpperChest") and stage.end == "Chest"
    stage.apply(g, rfb)
    spine = [target.index(b) for b in stage.bones]
    shares = Rotation.from_quat(rfb[spine], scalar_first=True)
    np.testing.assert_allclose(
        np.degrees(shares.magnitude()), [15.0, 15.0, 15.0], atol=1e-9
    )
    # Each share turns about the target's left (a pure flexion stays one).
    axes = shares.as_rotvec() / shares.magnitude()[:, None]
    np.testing.assert_allclose(axes, np.tile(left, (3, 1)), atol=1e-9)
    others = [j for j in range(len(g)) if j not in spine]
    np.testing.assert_array_equal(g[others], before[others])
    e = Rotation.from_quat(g, scalar_first=True)
    for j, p in enumerate(target.parents):
        if p < 0:
            continue
        back = e[p] * Rotation.from_quat(rfb[j], scalar_first=True)
        assert np.degrees((back.inv() * e[j]).magnitude()) < 1e-9, target.bone_names[j]


def test_spine_pivot_matches_the_listing_on_any_rotation() -> None:
    """A random group: the shares equal :class:`ShiftingPivot` on the group taken in
    the spine frame (x left, y up, z forward: a scipy-built matrix), back in world
    axes; without doubling the shares multiply back to the group within capacity."""
    rng = np.random.default_rng(1)
    target0 = default_humanoid()
    left = target0.left_world
    s_mat = np.stack([left, [0, 0, 1.0], np.cross(left, [0, 0, 1.0])], axis=1)
    m = Rotation.from_matrix(s_mat)
    for double in (True, False):
        group = Rotation.from_rotvec(rng.normal(scale=0.3, size=3))
        target, g, rfb = _humanoid_frame(group, rng)
        stage = SpinePivot(
            target.bone_names, target.parents, target.rest_world_from_bone_quat,
            {"Hips", "Chest"}, left, 15.0, double=double,
        )  # fmt: skip
        stage.apply(g, rfb)
        want = np.empty((3, 4))
        ShiftingPivot(3, 15.0, double=double).apply(
            (m.inv() * group * m).as_quat(scalar_first=True), want
        )
        want_w = m * Rotation.from_quat(want, scalar_first=True) * m.inv()
        spine = [target.index(b) for b in ("Spine", "Chest", "UpperChest")]
        got = Rotation.from_quat(rfb[spine], scalar_first=True)
        assert np.degrees((got.inv() * want_w).magnitude()).max() < 1e-9
    # Rig maps no spine bone: refused, named.
    with pytest.raises(ValueError, match="the rig must drive one of them"):
        rest = target.rest_world_from_bone_quat
        SpinePivot(target.bone_names, target.parents, rest, {"Hips", "Neck"}, left)


def test_spine_pivot_allocates_nothing() -> None:
    rng = np.random.default_rng(2)
    target, g, rfb = _humanoid_frame(Rotation.from_rotvec([0.3, 0.1, 0.2]), rng)
    stage = SpinePivot(target.bone_names, target.parents,
                       target.rest_world_from_bone_quat, {"Chest"},
                       target.left_world)  # fmt: skip
    stage.apply(g, rfb)
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        start, _ = tracemalloc.get_traced_memory()
        for _ in range(1000):
            stage.apply(g, rfb)
        end, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert end - start < 1024
    assert peak - start < 3072, peak - start  # numba's argument boxing
