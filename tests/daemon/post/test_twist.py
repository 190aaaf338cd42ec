"""Twist distribution (5.59): the hand's world orientation is kept, each joint's twist
is as configured, on the synthetic forearm twist and the Plug-in Gait walk."""

from __future__ import annotations

import tracemalloc
from typing import Any

import numpy as np
import pytest

from retargetd.daemon import rotations as rot
from retargetd.daemon.post.pose import PoseBuffer
from retargetd.daemon.post.twist import TwistDistribution, arm_chains
from retargetd.daemon.synth import performer as pf

Y = np.array([0.0, 1.0, 0.0])


def _wrap(a: np.ndarray) -> np.ndarray:
    return np.angle(np.exp(1j * a))


def _chain_world(world_from_top_parent: np.ndarray, q: np.ndarray, chain: list[int]):
    out = []
    acc = world_from_top_parent
    for b in chain:
        acc = rot.quat_mul(acc, q[:, b])
        out.append(acc)
    return out


def _check(
    parents: np.ndarray,
    world_from_bone: np.ndarray,
    parent_from_bone: np.ndarray,
    chains: list[list[int]],
    fractions: tuple[float, ...],
    rest: np.ndarray | None = None,
) -> float:
    stage = TwistDistribution(
        parents, chains, fractions, rest_parent_from_bone_quat=rest
    )
    rest_q = np.tile([1.0, 0.0, 0.0, 0.0], (len(parents), 1)) if rest is None else rest
    out = np.empty_like(parent_from_bone)
    for t in range(len(parent_from_bone)):
        view = out[t]
        assert stage.apply_quat(parent_from_bone[t], view) is view
    pooled_max = 0.0
    for chain in chains:
        top = world_from_bone[:, parents[chain[0]]]
        before = _chain_world(top, parent_from_bone, chain)
        after = _chain_world(top, out, chain)
        # The end of the chain (the hand) does not move: 1e-9 of a unit quaternion.
        dot = np.abs(np.sum(before[-1] * after[-1], axis=-1))
        assert np.all(np.abs(dot - 1.0) < 1e-9)
        # Nor does the swing of any bone: its long axis points where it did.
        for b0, b1 in zip(before, after, strict=True):
            np.testing.assert_allclose(
                rot.quat_rotate(b1, Y), rot.quat_rotate(b0, Y), atol=1e-9
            )
        tw_in = np.stack([rot.twist_angle(parent_from_bone[:, b], Y) for b in chain])
        tw_out = np.stack([rot.twist_angle(out[:, b], Y) for b in chain])
        tw_rest = np.array([rot.twist_angle(rest_q[b], Y) for b in chain])
        pooled = _wrap(tw_in[1:] - tw_rest[1:, None]).sum(axis=0)
        pooled_max = max(pooled_max, float(np.abs(pooled).max()))
        np.testing.assert_allclose(
            _wrap(tw_out[0] - tw_in[0] - fractions[0] * pooled), 0.0, atol=1e-9
        )
        for k in range(1, len(chain)):
            np.testing.assert_allclose(
                _wrap(tw_out[k] - tw_rest[k] - fractions[k] * pooled), 0.0, atol=1e-9
            )
    assert np.max(np.abs(np.linalg.norm(out, axis=-1) - 1.0)) < 1e-12
    return pooled_max


@pytest.mark.parametrize(
    "fractions", [(1 / 3, 1 / 3, 1 / 3), (0.2, 0.3, 0.5), (0.0, 0.5, 0.5)]
)
def test_synthetic_forearm_twist(
    forearm_twist: pf.SynthTake, fractions: tuple[float, ...]
) -> None:
    take = forearm_twist
    chains = arm_chains(take.segment_names)
    assert len(chains) == 2
    pooled = _check(
        take.segment_parents,
        take.world_from_segment_quat,
        take.parent_from_segment_quat,
        chains,
        fractions,
    )
    assert pooled > np.radians(60.0)  # the motion's +-70 deg pronation is there


def test_real_take(pig_walk: Any) -> None:
    """The PiG walk: the stage on the solve's actual parent_from_bone (rest ⊗ the
    calibration-relative rotation), the hand checked against the solve's own world
    orientation; the rest pose's twist is kept."""
    cal, res = pig_walk.calibration, pig_walk.solve
    parents = np.asarray(cal.bone_parents)
    chains = arm_chains(cal.bone_names)
    assert len(chains) == 2
    rest = np.asarray(cal.rest_parent_from_bone_quat)
    actual = res.parent_from_bone_quat  # = rest * rest_from_bone
    world = res.world_from_bone_quat
    np.testing.assert_allclose(  # the relation the check below relies on
        np.abs(
            np.sum(
                rot.quat_mul(world[:, parents[1:]], actual[:, 1:]) * world[:, 1:], -1
            )
        ),
        1.0,
        atol=1e-12,
    )
    pooled = _check(parents, world, actual, chains, (1 / 3, 1 / 3, 1 / 3), rest)
    assert pooled > np.radians(5.0)  # the walk's forearms do turn
    # The calibration pose passes unchanged.
    stage = TwistDistribution(parents, chains, rest_parent_from_bone_quat=rest)
    out = stage.apply_quat(rest, np.empty_like(rest))
    np.testing.assert_allclose(np.abs(np.sum(out * rest, -1)), 1.0, atol=1e-12)


def test_pose_buffer_stage_is_allocation_free(forearm_twist: pf.SynthTake) -> None:
    take = forearm_twist
    stage = TwistDistribution(take.segment_parents, arm_chains(take.segment_names))
    pose, out = (
        PoseBuffer.new(len(take.segment_names)),
        PoseBuffer.new(len(take.segment_names)),
    )
    frames = take.parent_from_segment_quat
    for t in range(20):
        np.copyto(pose.parent_from_bone_quat, frames[t])
        assert stage.apply(pose, out) is out
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        start, _ = tracemalloc.get_traced_memory()
        for t in range(1000):
            pose.parent_from_bone_quat[:] = frames[t % len(frames)]
            stage.apply(pose, out)
        end, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert end - start < 1024
    # numba boxes each array argument per call (~2 KB, freed on return, as in
    # test_solve_body); a (21, 4) float64 copy more would add 0.8 KB.
    assert peak - start < 3072, peak - start
    # In place is the same as out of place.
    twin = PoseBuffer.new(pose.n_bones).copy_from(pose)
    stage.apply(twin, twin)
    np.testing.assert_array_equal(twin.parent_from_bone_quat, out.parent_from_bone_quat)


def test_bad_arguments_are_named() -> None:
    parents = [-1, 0, 1, 2]
    with pytest.raises(ValueError, match="not the child"):
        TwistDistribution(parents, [[0, 2, 3]])
    with pytest.raises(ValueError, match="fractions"):
        TwistDistribution(parents, [[1, 2, 3]], (0.5, 0.5, 0.5))
    with pytest.raises(ValueError, match="axis"):
        TwistDistribution(parents, [[1, 2, 3]], axis=(0.0, 0.0, 0.0))
