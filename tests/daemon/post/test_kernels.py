"""The compiled scalar helpers agree with the numpy kernels of rotations.py."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from retargetd.daemon import rotations as rot
from retargetd.daemon.post._kernels import qmul, slerp_q, twist_about


def test_helpers_match_rotations() -> None:
    q = Rotation.random(200, rng=9).as_quat(scalar_first=True)
    p = Rotation.random(200, rng=10).as_quat(scalar_first=True)
    p[:20] = -q[:20]  # the same rotations, opposite sign: short arc is no turn
    p[20:40] = q[20:40] + 1e-9  # nearly equal: the small-angle lerp branch
    p[20:40] /= np.linalg.norm(p[20:40], axis=-1, keepdims=True)
    axis = np.array([0.0, 0.6, 0.8])
    us = np.linspace(0.0, 1.0, 7)
    for i in range(len(q)):
        np.testing.assert_allclose(
            qmul(*q[i], *p[i]), rot.quat_mul(q[i], p[i]), atol=1e-15
        )
        assert abs(twist_about(*q[i], *axis) - rot.twist_angle(q[i], axis)) < 1e-14
        for u in us:
            got = np.array(slerp_q(*q[i], *p[i], u))
            want = rot.slerp(q[i], p[i], u)
            assert abs(abs(got @ want) - 1.0) < 1e-13
            assert abs(np.linalg.norm(got) - 1.0) < 1e-15
