"""The level a stance foot is held at off the floor (``post/plant.py``, "Hold").

On the calibration's floor the level is known (0). Off it (a step, a riser) the
stance detector's support (``post/stance.py``) is measured on the performer's foot
points: the ankle, the foot bone's aim (Plug-in Gait's TOE marker, 35 mm above the
floor at rest) and a heel under the ankle at that height, each as its height above
its standing height. Those read the sole's level only while the foot is flat: on the
synthetic stair descent, whose foot comes down on its toe tip pitched about 25 deg,
they read 36 mm above the step at landing and 6.3 mm above it still at heel-off
(legs 1x), and the plant held the target's foot that far up. So off the floor the
plant holds the target's foot at the level of its own sole (the lowest of its heel,
its ball and its toe tip; the solved pose, the root scaled by the leg ratio):

* live, causally, the level the sole came down to at the onset (so nothing jumps),
  raised to the highest the sole stands at as the contact goes on, until heel-off:
  the solve's foot rises through loading as the thigh comes up toward the
  calibration's standing pose (Plug-in Gait's regression hip centre 12 mm below the
  performer's: the solved foot 2.9 mm below the step at landing, 0.1 mm at heel-off,
  docs/feet.md), and a foot standing on a step does not go down through it. Heel-off
  (Perry & Burnfield's terminal stance) is the heel ``pivot_switch_m`` (1 cm: the
  stance detector's ``heel_rise_m``) above both the sole and its own lowest in this
  contact; from it the foot rolls about its forefoot and the level is set;
* offline (the whole take known), each contact the level it was set at, the whole
  contact long (:func:`settled_levels`), as the detector's support is settled offline.

The raise needs no blend of its own: it follows the solve's foot (on the synthetic
ascent 0.02 mm a frame), and the knee's share of it is rate-limited in the leg's IK
(``knee_step_deg``). What no causal rule sees is the solve's error at the landing
itself: live, the held foot is as low as the solved one there.
"""

from __future__ import annotations

import numpy as np

from retargetd.daemon.compiled import kernel, qmul, qrot
from retargetd.protocols.frames import F64Array

#: Columns of a foot's level state (the plant's ``(2, N_LEVEL)`` array): the level
#: held (metres, world), set at heel-off (0 or 1), the heel's lowest this contact.
LEVEL, SET, HEEL_MIN, N_LEVEL = 0, 1, 2, 3


@kernel(inline="always")
def sole_z(
    lowest: float,
    wfb: np.ndarray,  # (N, 4) G
    rest: np.ndarray,  # (N, 4) T
    offsets: np.ndarray,  # (N, 3)
    ef: np.ndarray,  # (4,) the foot's E (G T-bar)
    az: float,  # the ankle's height
    toe: int,  # the Toes bone, -1 if none
    tip: np.ndarray,  # (3,) its aim (the toe tip), rest, world axes
) -> float:  # pragma: no cover - compiled
    """The height of the foot's lowest point: ``lowest`` (its heel and ball), or its
    toe tip where that is lower."""
    if toe < 0:
        return lowest
    tw, tx, ty, tz = qmul(
        wfb[toe, 0], wfb[toe, 1], wfb[toe, 2], wfb[toe, 3],
        rest[toe, 0], -rest[toe, 1], -rest[toe, 2], -rest[toe, 3],
    )  # fmt: skip
    _, _, jz = qrot(ef[0], ef[1], ef[2], ef[3], offsets[toe, 0], offsets[toe, 1],
                    offsets[toe, 2])  # fmt: skip
    _, _, vz = qrot(tw, tx, ty, tz, tip[0], tip[1], tip[2])
    return min(lowest, az + jz + vz)


@kernel(inline="always")
def step_level(
    lv: np.ndarray,  # (N_LEVEL,) this foot's level state, updated
    onset: bool,
    sole: float,
    heel_z: float,
    rise: float,
) -> float:  # pragma: no cover - compiled
    """One contact frame of a foot's own level (module docstring); returns it."""
    if onset:
        lv[LEVEL], lv[SET], lv[HEEL_MIN] = sole, 0.0, heel_z
    elif lv[SET] == 0.0:
        lv[HEEL_MIN] = min(lv[HEEL_MIN], heel_z)
        if heel_z - sole > rise and heel_z - lv[HEEL_MIN] > rise:
            lv[SET] = 1.0  # heel-off
        else:
            lv[LEVEL] = max(lv[LEVEL], sole)
    return lv[LEVEL]


def settled_levels(
    states: F64Array, level: F64Array, contact_col: int, support_col: int
) -> F64Array:
    """Offline: ``states`` ((T, 2, C), the stance detector's per frame) with each
    contact off the floor (a support other than 0) given, the whole contact long,
    ``level`` ((T, 2), the plant's own level per frame, in the support's units) at
    the contact's last frame (module docstring)."""
    out = np.array(states, dtype=np.float64)
    for s in range(2):
        on = np.concatenate([[0], (states[:, s, contact_col] != 0.0).astype(np.int8),
                             [0]])  # fmt: skip
        d = np.diff(on)
        for a, b in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1), strict=True):
            if states[b - 1, s, support_col] != 0.0:
                out[a:b, s, support_col] = level[b - 1, s]
    return out
