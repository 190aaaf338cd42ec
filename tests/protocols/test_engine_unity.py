"""Unity adapter, pinned with hand-worked examples.

Unity_from_world M maps world +X, +Y, +Z to Unity +X, +Z, +Y (det M = -1), so a
world rotation R becomes M R Mᵀ and q = (w, v) becomes (w, -M v).

+90° yaw about world +Z: q = (c, 0, 0, s), c = s = √½. -M v = -(0, s, 0), so Unity
stores (x, y, z, w) = (0, -s, 0, c): -90° about Unity +Y. Check by hand: the world
yaw takes world +X (Unity +X) to world +Y (Unity +Z); in Unity's left-handed frame a
positive turn about +Y takes +Z to +X, so +X -> +Z is the negative turn. ✓

+90° pitch about world +Y: q = (c, 0, s, 0). -M v = -(0, 0, s), so Unity stores
(0, 0, -s, c): -90° about Unity +Z. The pitch takes world +X to world -Z, i.e. Unity
+X to Unity -Y, and a -90° turn about Unity +Z does exactly that (x -> -y). ✓
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from retargetd.protocols import engine_unity as eu

C = S = np.sqrt(0.5)


def _mat_from_quat_xyzw(q: np.ndarray) -> np.ndarray:
    wxyz = [q[3], q[0], q[1], q[2]]
    return Rotation.from_quat(wxyz, scalar_first=True).as_matrix()


def test_constants() -> None:
    assert np.linalg.det(eu.ENGINE_FROM_WORLD) == pytest.approx(-1.0)
    assert eu.QUAT_ORDER == "xyzw" and eu.LENGTH_SCALE == 1.0
    out = np.zeros((3, 3))
    eu.unity_pos_from_world(np.eye(3), out)
    # world +X, +Y, +Z -> Unity +X, +Z, +Y
    np.testing.assert_array_equal(out, [[1, 0, 0], [0, 0, 1], [0, 1, 0]])


@pytest.mark.parametrize(
    ("q_world", "q_unity"),
    [
        ((C, 0.0, 0.0, S), (0.0, -S, 0.0, C)),  # +90° yaw -> -90° about Unity +Y
        ((C, 0.0, S, 0.0), (0.0, 0.0, -S, C)),  # +90° pitch -> -90° about Unity +Z
        ((C, S, 0.0, 0.0), (-S, 0.0, 0.0, C)),  # +90° roll about world +X
    ],
)
def test_hand_worked_rotations(q_world: tuple, q_unity: tuple) -> None:
    out = np.zeros(4)
    assert eu.unity_quat_xyzw_from_world(np.array(q_world), out) is out
    np.testing.assert_allclose(out, q_unity, atol=1e-15)
    m = eu.ENGINE_FROM_WORLD
    r_world = Rotation.from_quat(q_world, scalar_first=True).as_matrix()
    np.testing.assert_allclose(_mat_from_quat_xyzw(out), m @ r_world @ m.T, atol=1e-12)


def test_yaw_moves_unity_x_to_unity_z() -> None:
    q = np.zeros(4)
    eu.unity_quat_xyzw_from_world(np.array([C, 0.0, 0.0, S]), q)
    np.testing.assert_allclose(
        _mat_from_quat_xyzw(q) @ [1, 0, 0], [0, 0, 1], atol=1e-12
    )


def test_random_rotations_match_m_r_mt(rng: np.random.Generator) -> None:
    rot = Rotation.random(50, random_state=rng)
    q_world = rot.as_quat(scalar_first=True)
    out = np.zeros((50, 4))
    eu.unity_quat_xyzw_from_world(q_world, out)
    m = eu.ENGINE_FROM_WORLD
    expected = m @ rot.as_matrix() @ m.T
    got = Rotation.from_quat(out[:, [3, 0, 1, 2]], scalar_first=True).as_matrix()
    np.testing.assert_allclose(got, expected, atol=1e-12)
    # Positions rotate with the same M: R' (M p) == M (R p).
    p = rng.normal(size=(50, 3))
    p_unity = np.zeros((50, 3))
    rp_unity = np.zeros((50, 3))
    eu.unity_pos_from_world(p, p_unity)
    eu.unity_pos_from_world(rot.apply(p), rp_unity)
    np.testing.assert_allclose(
        np.einsum("nij,nj->ni", got, p_unity), rp_unity, atol=1e-12
    )
