"""The target's and the performer's leg geometry the plant stage is built from
(``post/plant.py``): the leg lengths whose ratio scales the root and the supports, and
each target foot's heel, ball and roll centre at rest; and the performer's hip centres
no range of motion placed (:func:`warn_unplaced_centres`)."""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from retargetd.daemon.body.calibration import Calibration
from retargetd.daemon.body.rig import Rig
from retargetd.protocols.frames import F64Array

logger = logging.getLogger(__name__)

_SIDES = ("Left", "Right")
#: The shortest leg taken for a leg, metres: shorter, the calibration (or a BVH's
#: unit) is wrong.
LEG_MIN_M = 0.2


def performer_leg_m(rig: Rig, calibration: Calibration) -> float:
    """The performer's leg length: the mean height of the hip joints (the rig's
    LeftUpperLeg and RightUpperLeg bone origins) above the calibration's floor
    (z = 0; the calibration is taken standing on it).

    Raises:
        ValueError: the rig maps no upper legs, or the calibration has no bone
            origins.
    """
    origins = calibration.rest_bone_origin_pos
    names = list(calibration.bone_names)
    legs = [rig.humanoid.get(s + "UpperLeg") for s in _SIDES]
    if origins is None or not all(legs):
        raise ValueError(
            f"rig {rig.name}: feet = 'plant' needs LeftUpperLeg and RightUpperLeg "
            "mapped and a calibration with bone origins"
        )
    z = [float(np.asarray(origins)[names.index(str(b)), 2]) for b in legs]
    leg = 0.5 * (z[0] + z[1])
    if not leg > LEG_MIN_M:
        raise ValueError(
            f"performer leg length must be > {LEG_MIN_M} m; got {leg:.3f} m"
        )
    return leg


def target_rest_joints(target: Any) -> F64Array:
    """(N, 3) each target joint at rest, world, the root on the floor at the origin."""
    offsets = np.asarray(target.rest_offsets, dtype=np.float64)
    pos = np.zeros_like(offsets)
    for i, p in enumerate(target.parents):
        pos[i] = offsets[i] if p < 0 else pos[p] + offsets[i]
    return pos


def target_leg_m(target: Any) -> float:
    """The target's leg length: the mean height of its UpperLeg joints at rest."""
    pos = target_rest_joints(target)
    z = [pos[target.index(s + "UpperLeg"), 2] for s in _SIDES]
    return float(0.5 * (z[0] + z[1]))


def foot_points(target: Any) -> tuple[F64Array, F64Array]:
    """Each foot's heel and ball, (2, 3) each: offsets from the ankle (the Foot joint)
    at rest, world axes, both at floor level (z = -ankle height): the heel under the
    ankle, the ball under the Toes joint (else the foot's aim)."""
    pos = target_rest_joints(target)
    heel, ball = np.zeros((2, 3)), np.zeros((2, 3))
    for s, side in enumerate(_SIDES):
        f = target.index(side + "Foot")
        toes = side + "Toes"
        if toes in target.bone_names:
            ahead = pos[target.index(toes)] - pos[f]
        else:
            ahead = np.asarray(target.aim_offsets[f], dtype=np.float64).copy()
        heel[s] = (0.0, 0.0, -pos[f, 2])
        ball[s] = (ahead[0], ahead[1], -pos[f, 2])
    return heel, ball


def roll_radius(target: Any) -> F64Array:
    """(2,) each foot's roll centre's height above its ball at rest: the Toes joint's
    (the MTP joint, which the foot rolls about from heel-off on) height above the
    floor; 0 for a foot without a Toes bone (it rolls about its ball)."""
    pos = target_rest_joints(target)
    r = np.zeros(2)
    for s, side in enumerate(_SIDES):
        if side + "Toes" in target.bone_names:
            r[s] = max(float(pos[target.index(side + "Toes"), 2]), 0.0)
    return r


def unplaced_centres(rig: Rig, cal: Calibration) -> tuple[str, ...]:
    """The functional joint centres of ``rig`` (its ``[functional]`` points:
    Plug-in Gait's hip centres) that ``cal`` did not place from a range of motion
    (``calibrate --rom``), so left at the rig's regression. With the regression's hip
    12 mm below the synthetic performer's, the solved foot lands on a stair step 2.3
    mm below it (thigh flexed, legs 1x), which the plant holds live; placed from a
    range of motion, 0.00 (docs/feet.md: "The stairs' sink is the calibration's
    hip")."""
    joints = cal.functional.get("joints", {})
    return tuple(
        c.point
        for c in rig.functional.points
        if not joints.get(c.point, {}).get("used")
    )


def warn_unplaced_centres(rig: Rig, cal: Calibration) -> None:
    """One warning line when :func:`unplaced_centres` names any (``feet = "plant"``,
    ``post/plant.py`` ``plant_stage``: live at each pipeline build, offline once a
    take)."""
    unplaced = unplaced_centres(rig, cal)
    if unplaced:
        logger.warning(
            'feet = "plant": %s from rig %s\'s regression, not a range of motion: a '
            "stance foot on a stair step can stand a few mm below it (docs/feet.md); "
            "calibrate with --rom to place them",
            " ".join(unplaced),
            rig.name,
        )
