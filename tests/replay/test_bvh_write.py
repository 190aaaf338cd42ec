"""BVH writing: write -> read round trips of the hierarchy and the motion."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from retargetd.replay.bvh import (
    ROTATION_ORDERS,
    BvhSkeleton,
    bvh_motion,
    bvh_skeleton,
    format_bvh,
    normalize_rotation_order,
    parse_bvh,
    read_bvh_hierarchy,
    split_bvh_motion,
    write_bvh,
)

MIXAMO = Path(__file__).resolve().parent.parent / "data" / "target-apose-mixamo.bvh"

# Not depth first: "b" (child of the root) comes before "a1" (child of "a").
NAMES = ("root", "a", "b", "a1", "b1", "a2 with space")
PARENTS = (-1, 0, 0, 1, 2, 1)
ORDERS = ("ZXY", "XYZ", "XZY", "YXZ", "YZX", "ZYX")


def _skeleton(rng: np.random.Generator) -> BvhSkeleton:
    offsets = rng.uniform(-20.0, 20.0, size=(6, 3))
    ends = np.full((6, 3), np.nan)
    ends[[3, 4, 5]] = rng.uniform(-5.0, 5.0, size=(3, 3))
    return bvh_skeleton(
        joint_names=NAMES,
        parents=PARENTS,
        offsets=offsets,
        rotation_orders=ORDERS,
        end_sites=ends,
    )


def test_hierarchy_and_motion_round_trip(
    tmp_path: Path, rng: np.random.Generator
) -> None:
    sk = _skeleton(rng)
    n_frames = 7
    angles = rng.uniform(-180.0, 180.0, size=(n_frames, 6, 3))
    positions = np.full((n_frames, 6, 3), np.nan)
    positions[:, 0] = rng.uniform(-100.0, 100.0, size=(n_frames, 3))
    frames = bvh_motion(sk, angles, positions)
    path = tmp_path / "t.bvh"
    write_bvh(path, sk, frames, 1 / 120)
    back = read_bvh_hierarchy(path, read_motion=True)
    # Depth first in the file: a's subtree, then b's.
    assert back.joint_names == ("root", "a", "a1", "a2 with space", "b", "b1")
    perm = [NAMES.index(n) for n in back.joint_names]
    assert [back.joint_names[p] if p >= 0 else None for p in back.parents] == [
        NAMES[PARENTS[j]] if PARENTS[j] >= 0 else None for j in perm
    ]
    np.testing.assert_allclose(back.offsets, sk.offsets[perm], atol=5e-7)
    np.testing.assert_allclose(back.end_sites, sk.end_sites[perm], atol=5e-7)
    assert back.channels == tuple(sk.channels[j] for j in perm)
    assert back.rotation_orders == tuple(ORDERS[j] for j in perm)
    assert back.channels[0][:3] == ("Xposition", "Yposition", "Zposition")
    assert back.n_frames == n_frames and back.frame_time_s == pytest.approx(1 / 120)
    assert back.frames is not None
    got_angles, got_pos = split_bvh_motion(back, back.frames)
    np.testing.assert_allclose(got_angles, angles[:, perm], atol=5e-7)
    np.testing.assert_allclose(got_pos[:, 0], positions[:, 0], atol=5e-7)
    assert np.isnan(got_pos[:, 1:]).all()


@pytest.mark.parametrize("order", ROTATION_ORDERS)
def test_every_rotation_order_round_trips(
    tmp_path: Path, rng: np.random.Generator, order: str
) -> None:
    rots = Rotation.random(200, rng=rng)
    # Near and at gimbal lock too: middle angle +-90 degrees.
    lock = Rotation.from_euler(
        order, [[30.0, 90.0, -20.0], [10.0, -90.0, 5.0], [1.0, 89.9999, 2.0]], True
    )
    rots = Rotation.concatenate([rots, lock])
    with pytest.warns(UserWarning, match="Gimbal lock"):
        angles = rots.as_euler(order, degrees=True)  # upper case: intrinsic
    n = len(rots)
    sk = bvh_skeleton(
        joint_names=["r", "c"],
        parents=[-1, 0],
        offsets=np.zeros((2, 3)),
        rotation_orders=[order, order],
        end_sites=np.array([[np.nan] * 3, [0.0, 1.0, 0.0]]),
        root_position=False,
    )
    per_joint = np.stack([angles, angles[::-1]], axis=1)
    path = tmp_path / f"{order}.bvh"
    write_bvh(path, sk, bvh_motion(sk, per_joint), 0.01)
    back = read_bvh_hierarchy(path, read_motion=True)
    assert back.rotation_orders == (order, order)
    assert back.channels[1] == tuple(f"{a}rotation" for a in order)
    assert back.frames is not None
    got, _ = split_bvh_motion(back, back.frames)
    # Channels compose in the listed order: R = R_1 R_2 R_3 (scipy upper case).
    for j, expected in enumerate((rots, rots[::-1])):
        got_rot = Rotation.from_euler(order, got[:, j], degrees=True)
        err = np.degrees((got_rot * expected.inv()).magnitude())
        assert err.max() < 1e-5
    assert parse_bvh(format_bvh(sk, bvh_motion(sk, per_joint), 0.01)).n_frames == n


def test_channel_composition_is_the_listed_product() -> None:
    # Zrotation 90, Xrotation 90 (ZXY): R = Rz(90) Rx(90) takes +Y to +Z.
    sk = bvh_skeleton(
        joint_names=["r"], parents=[-1], offsets=np.zeros((1, 3)),
        rotation_orders=["ZXY"], root_position=False,
    )  # fmt: skip
    frames = bvh_motion(sk, np.array([[[90.0, 90.0, 0.0]]]))
    assert frames.tolist() == [[90.0, 90.0, 0.0]]
    r = Rotation.from_euler("ZXY", frames[0], degrees=True)
    np.testing.assert_allclose(r.apply([0.0, 1.0, 0.0]), [0.0, 0.0, 1.0], atol=1e-12)


def test_rewrite_of_a_third_party_file(tmp_path: Path) -> None:
    sk = read_bvh_hierarchy(MIXAMO, read_motion=True)
    assert sk.frames is not None
    path = tmp_path / "again.bvh"
    write_bvh(path, sk, sk.frames, sk.frame_time_s)
    back = read_bvh_hierarchy(path, read_motion=True)
    assert back.joint_names == sk.joint_names and back.parents == sk.parents
    assert back.channels == sk.channels
    np.testing.assert_allclose(back.offsets, sk.offsets, atol=5e-7)
    np.testing.assert_allclose(back.frames, sk.frames, atol=5e-7)
    assert np.isnan(back.end_sites).all(axis=-1).sum() == len(sk.joint_names) - 5


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"rotation_orders": ["ZXZ", "ZXY"]}, "rotation order must be one of"),
        ({"parents": [0, 0]}, "parents must be -1 for joint 0"),
        ({"joint_names": ["a", "a"]}, "must be unique"),
        ({"joint_names": ["a", "b {"]}, "joint names must be"),
        ({"end_sites": [[0, 1, 0], [0, 1, 0]]}, "only go on leaf joints"),
        ({"offsets": [[0, 0, np.nan], [0, 1, 0]]}, "offsets must be finite"),
    ],
)
def test_bad_skeletons(kwargs: dict, message: str) -> None:
    args = {
        "joint_names": ["a", "b"],
        "parents": [-1, 0],
        "offsets": [[0, 0, 0], [0, 1, 0]],
        "rotation_orders": ["ZXY", "ZXY"],
        **kwargs,
    }
    with pytest.raises(ValueError, match=message):
        bvh_skeleton(**args)


def test_bad_motion(tmp_path: Path) -> None:
    sk = bvh_skeleton(
        joint_names=["a"], parents=[-1], offsets=np.zeros((1, 3)),
        rotation_orders=["ZXY"],
    )  # fmt: skip
    with pytest.raises(ValueError, match="give positions"):
        bvh_motion(sk, np.zeros((2, 1, 3)))
    with pytest.raises(ValueError, match="must be finite"):
        write_bvh(tmp_path / "x.bvh", sk, np.full((2, 6), np.nan), 0.01)
    with pytest.raises(ValueError, match="frame_time_s must be > 0"):
        write_bvh(tmp_path / "x.bvh", sk, np.zeros((2, 6)), 0.0)
    with pytest.raises(ValueError, match=r"frames must be \(frames, 6\)"):
        write_bvh(tmp_path / "x.bvh", sk, np.zeros((2, 5)), 0.01)
    assert not (tmp_path / "x.bvh").exists()
    assert normalize_rotation_order("z x y") == "ZXY"
