"""One Euro filter: equal to the paper's scalar filter about one axis, sign-blind,
unit quaternions, the EMA noise reduction at beta = 0, no allocation."""

from __future__ import annotations

import math
import tracemalloc

import numpy as np
import pytest

from retargetd.daemon import rotations as rot
from retargetd.daemon.post.one_euro import OneEuroFilter
from retargetd.daemon.post.pose import PoseBuffer


def _scalar_one_euro(
    x: np.ndarray, dt: float, fmin: float, beta: float, dcut: float
) -> np.ndarray:
    """Casiez et al. 2012, written out from the paper for (T, D) samples; the cutoff
    from the norm of the filtered velocity (one channel of D coordinates)."""

    def alpha(f: float) -> float:
        tau = 1.0 / (2.0 * math.pi * f)
        return 1.0 / (1.0 + tau / dt)

    out = np.empty_like(x)
    out[0], dx_hat = x[0], np.zeros(x.shape[1])
    for t in range(1, len(x)):
        dx = (x[t] - out[t - 1]) / dt
        dx_hat = dx_hat + alpha(dcut) * (dx - dx_hat)
        a = alpha(fmin + beta * float(np.linalg.norm(dx_hat)))
        out[t] = out[t - 1] + a * (x[t] - out[t - 1])
    return out


def _run(f: OneEuroFilter, q: np.ndarray, p: np.ndarray, dt: float) -> tuple:
    pose, out = PoseBuffer.new(q.shape[1]), PoseBuffer.new(q.shape[1])
    qs, ps = np.empty_like(q), np.empty_like(p)
    for t in range(len(q)):
        pose.t_s = t * dt
        pose.parent_from_bone_quat[:] = q[t]
        pose.root_pos[:] = p[t]
        assert f.apply(pose, out) is out
        qs[t], ps[t] = out.parent_from_bone_quat, out.root_pos
    return qs, ps


@pytest.mark.parametrize(("fmin", "beta"), [(1.0, 0.0), (0.5, 2.0), (2.0, 0.3)])
def test_single_axis_equals_the_scalar_filter(
    rng: np.random.Generator, fmin: float, beta: float
) -> None:
    dt, n = 0.01, 600
    t = np.arange(n) * dt
    angle = 1.2 * np.sin(2 * np.pi * 0.7 * t) + rng.normal(0, 0.02, n)
    axis = np.array([0.3, -0.5, 0.8])
    q = rot.quat_from_axis_angle(axis, angle)[:, None, :]
    p = np.stack([np.sin(t), 0.1 * t, np.cos(2 * t)], -1) + rng.normal(0, 0.002, (n, 3))
    qs, ps = _run(
        OneEuroFilter(1, min_cutoff_hz=fmin, beta_rot=beta, beta_pos=beta), q, p, dt
    )
    expected = _scalar_one_euro(angle[:, None], dt, fmin, beta, 1.0)[:, 0]
    got = rot.twist_angle(qs[:, 0], axis / np.linalg.norm(axis))
    np.testing.assert_allclose(got, expected, atol=1e-12)
    np.testing.assert_allclose(ps, _scalar_one_euro(p, dt, fmin, beta, 1.0), atol=1e-12)


def test_sign_of_the_input_does_not_matter(rng: np.random.Generator) -> None:
    n, b = 300, 5
    rv = np.cumsum(rng.normal(0, 0.05, (n, b, 3)), axis=0)
    q = rot.quat_from_rotvec(rv)
    flipped = np.where(rng.random((n, b, 1)) < 0.5, -q, q)
    p = np.zeros((n, 3))
    a, _ = _run(OneEuroFilter(b, beta_rot=0.5), q, p, 0.01)
    c, _ = _run(OneEuroFilter(b, beta_rot=0.5), flipped, p, 0.01)
    assert np.all(np.abs(np.abs(np.sum(a * c, -1)) - 1.0) < 1e-12)
    assert np.max(np.abs(np.linalg.norm(c, axis=-1) - 1.0)) < 1e-12


def test_noise_at_rest_is_reduced_as_an_ema(rng: np.random.Generator) -> None:
    # beta = 0: a first-order low-pass of a = 1 / (1 + 1 / (2 pi f dt)); on white noise
    # its output std is sqrt(a / (2 - a)) of the input's.
    n, dt, fmin = 20000, 0.01, 1.0
    noise = rng.normal(0, np.radians(1.0), (n, 1, 3))
    rest = rot.quat_from_axis_angle([0.0, 0.0, 1.0], 0.7)
    q = rot.quat_mul(rest, rot.quat_from_rotvec(noise))
    qs, _ = _run(OneEuroFilter(1, min_cutoff_hz=fmin), q, np.zeros((n, 3)), dt)
    err_in = rot.rotvec_from_quat(rot.quat_mul(rot.quat_conj(rest), q[1000:, 0]))
    err_out = rot.rotvec_from_quat(rot.quat_mul(rot.quat_conj(rest), qs[1000:, 0]))
    a = 1.0 / (1.0 + 1.0 / (2 * np.pi * fmin * dt))
    ratio = err_out.std(axis=0) / err_in.std(axis=0)
    # 10 %: the std of a low-passed series estimated from ~19000 correlated samples
    # (about 600 independent ones at this cutoff) is within a few per cent.
    np.testing.assert_allclose(ratio, math.sqrt(a / (2 - a)), rtol=0.1)


def test_first_pose_passes_and_nothing_is_allocated(rng: np.random.Generator) -> None:
    f = OneEuroFilter(19, beta_rot=0.5, beta_pos=1.0)
    pose, out = PoseBuffer.new(19), PoseBuffer.new(19)
    pose.parent_from_bone_quat[:] = rot.quat_from_rotvec(rng.normal(0, 1, (19, 3)))
    pose.root_pos[:] = [1.0, 2.0, 0.9]
    f.apply(pose, out)
    np.testing.assert_array_equal(out.parent_from_bone_quat, pose.parent_from_bone_quat)
    np.testing.assert_array_equal(out.root_pos, pose.root_pos)
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        start, _ = tracemalloc.get_traced_memory()
        for _ in range(1000):
            pose.t_s += 0.01
            f.apply(pose, out)
        end, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert end - start < 1024
    assert peak - start < 3072, peak - start  # numba's argument boxing
    with pytest.raises(ValueError, match="min_cutoff_hz"):
        OneEuroFilter(3, min_cutoff_hz=0.0)
