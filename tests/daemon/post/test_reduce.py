"""Keyframe reduction: tolerance held on every frame, smooth stretches collapse to
their boundary keys, the least-squares refit never hurts, keys are not a downsample."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from retargetd.daemon import rotations as rot
from retargetd.daemon.post.interp import Clip
from retargetd.daemon.post.reduce import (
    describe,
    reduce_clip,
    reduce_position,
    reduce_rotation,
    sample_position,
    sample_rotation,
)
from retargetd.daemon.synth import performer as pf

Synth = Callable[[tuple[str, ...], float, float], pf.SynthTake]


def test_piecewise_linear_keeps_exactly_its_corners() -> None:
    t = np.arange(300.0)
    corners = [0, 80, 170, 299]
    x = np.interp(t, corners, [0.0, 0.4, -0.1, 0.2])
    pos = np.stack([x, 2 * x, np.full_like(x, 0.9)], -1)
    ch = reduce_position(pos, 1e-4)
    assert ch.frames.tolist() == corners
    assert ch.max_error < 1e-12
    # A rotation at constant angular velocity about one axis: two keys.
    q = rot.quat_from_axis_angle([0.2, 0.9, -0.3], np.linspace(0.0, 2.5, 200))
    ch = reduce_rotation(q, np.radians(0.01))
    assert ch.frames.tolist() == [0, 199]


@pytest.mark.parametrize(("tol_deg", "tol_mm"), [(0.5, 1.0), (2.0, 5.0)])
def test_tolerance_holds_and_keys_follow_the_motion(
    synth_take: Synth, tol_deg: float, tol_mm: float
) -> None:
    take = synth_take(
        ("walk", "arm_raise", "forearm_twist", "spine", "head_turn"), 100.0, 6.0
    )
    clip = Clip(
        parent_from_bone_quat=take.parent_from_segment_quat,
        root_pos=take.joint_pos_world[:, 0],
        rate_hz=100.0,
    )
    red = reduce_clip(clip, tolerance_deg=tol_deg, tolerance_mm=tol_mm)
    kept = 0
    for b, ch in enumerate(red.rotations):
        back = sample_rotation(ch.frames, ch.values, clip.n_frames)
        err = rot.quat_angle(
            rot.quat_mul(rot.quat_conj(back), clip.parent_from_bone_quat[:, b])
        )
        assert np.degrees(err.max()) <= tol_deg + 1e-9
        assert ch.max_error == pytest.approx(err.max(), abs=1e-12)
        assert ch.frames[0] == 0 and ch.frames[-1] == clip.n_frames - 1
        kept += len(ch.frames)
        q_b = clip.parent_from_bone_quat[:, b]
        moving = rot.quat_angle(rot.quat_mul(rot.quat_conj(q_b[:1]), q_b)).max()
        if moving < np.radians(tol_deg):  # a still bone (its rest hold and ramp)
            assert len(ch.frames) == 2
    back = sample_position(red.root.frames, red.root.values, clip.n_frames)
    assert 1e3 * np.linalg.norm(back - clip.root_pos, axis=-1).max() <= tol_mm + 1e-9
    total = clip.n_frames * len(red.rotations)
    print(
        f"\n{tol_deg} deg: {kept} of {total} rotation keys ({100 * kept / total:.1f} %)"
    )
    assert kept < total / 3
    # Not a downsample: during the first second's T-pose hold no key is needed, and
    # the gaps between keys vary with the motion.
    gaps = np.concatenate([np.diff(ch.frames) for ch in red.rotations])
    assert gaps.max() >= 100 and gaps.min() < 10
    text = describe(red, take.segment_names)
    assert text.splitlines()[-1].startswith(f"kept {kept + len(red.root.frames)} of ")
    assert len(text.splitlines()) == len(red.rotations) + 2


def test_refit_is_least_squares_and_kept_only_within_tolerance(
    rng: np.random.Generator,
) -> None:
    t = np.linspace(0.0, 4.0, 400)
    pos = np.stack([np.sin(t), np.cos(1.3 * t), 0.1 * t], -1) + rng.normal(
        0, 2e-4, (400, 3)
    )
    ch = reduce_position(pos, 5e-3)
    raw = pos[ch.frames]
    fit = sample_position(ch.frames, ch.values, len(pos))
    rms_fit = np.sqrt(np.mean(np.sum((fit - pos) ** 2, -1)))
    rms_raw = np.sqrt(
        np.mean(np.sum((sample_position(ch.frames, raw, len(pos)) - pos) ** 2, -1))
    )
    assert ch.refitted and rms_fit < rms_raw
    # Least squares: the residual is orthogonal to every hat function.
    eye = np.eye(len(ch.frames))
    basis = np.stack(
        [
            sample_position(ch.frames, eye[:, [k]], len(pos))[:, 0]
            for k in range(len(eye))
        ]
    )
    np.testing.assert_allclose(basis @ (fit - pos), 0.0, atol=1e-10)


def test_bad_input_is_named() -> None:
    with pytest.raises(ValueError, match="tolerance_rad"):
        reduce_rotation(np.tile([1.0, 0, 0, 0], (5, 1)), 0.0)
    with pytest.raises(ValueError, match="finite"):
        reduce_position(np.full((5, 3), np.nan), 1e-3)
