"""Unity (and VMC) engine adapter: left-handed, +Y up, metres, quaternions x y z w.

Unity_from_world maps world +X, +Y, +Z to Unity +X, +Z, +Y (README "Conventions";
``shared/reference/engines.md``)::

              | 1 0 0 |
    M   =     | 0 0 1 |      det M = -1 (the handedness flips)
              | 0 1 0 |

Positions: ``p_unity = M p_world * LENGTH_SCALE``. Rotations: ``R_unity = M R Mᵀ``,
i.e. for ``q = (w, v)``: ``q_unity = (w, det(M) M v) = (w, -(vx, vz, vy))``, stored as
``x y z w``. A world +90° yaw about +Z becomes -90° about Unity +Y (see the test).
"""

from __future__ import annotations

import numpy as np

from retargetd.protocols.frames import F64Array

#: Rows = Unity axes, columns = world axes.
ENGINE_FROM_WORLD: F64Array = np.array(
    [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]]
)
ENGINE_FROM_WORLD.flags.writeable = False
QUAT_ORDER = "xyzw"
LENGTH_SCALE = 1.0

_DET = float(round(np.linalg.det(ENGINE_FROM_WORLD)))
_POS_RHS = np.ascontiguousarray((ENGINE_FROM_WORLD * LENGTH_SCALE).T)
_POS_RHS.flags.writeable = False
# q_xyzw = Q @ q_wxyz: rows x, y, z take det(M) M v from the vector part (columns
# 1..3 of q_wxyz); row w takes w.
_QUAT_MAP = np.zeros((4, 4))
_QUAT_MAP[0:3, 1:4] = _DET * ENGINE_FROM_WORLD
_QUAT_MAP[3, 0] = 1.0
_QUAT_RHS = np.ascontiguousarray(_QUAT_MAP.T)
_QUAT_RHS.flags.writeable = False


def unity_pos_from_world(pos_world: F64Array, out: F64Array) -> F64Array:
    """Positions from the world to Unity.

    Args:
        pos_world: (..., 3) float64, metres, world frame.
        out: (..., 3) float destination.

    Returns:
        ``out``: (..., 3), metres, Unity frame (left-handed, +Y up).
    """
    return np.matmul(pos_world, _POS_RHS, out=out)


def unity_quat_xyzw_from_world(quat_wxyz: F64Array, out: F64Array) -> F64Array:
    """Rotations from the world to Unity: ``R' = M R Mᵀ``, stored x y z w.

    Args:
        quat_wxyz: (..., 4) float64, (w, x, y, z), unit, world frame.
        out: (..., 4) float destination.

    Returns:
        ``out``: (..., 4), (x, y, z, w), Unity frame.
    """
    return np.matmul(quat_wxyz, _QUAT_RHS, out=out)
