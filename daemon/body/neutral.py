"""The calibration pose's own joint angles: how far it stands from anatomical neutral.

Joint ranges are anatomical: a knee flexes 0-165 deg from straight, whatever pose the
performer held while being calibrated. The solve measures every rotation from the
calibration pose (``rest_from_bone_quat``), so a calibration on a bent knee shifted
the validator's and the fit's knee range by that bend (issue 29: the same walk failed
the joint limits on 273 frames calibrated on a frame with the knee bent 26 deg, on 39
calibrated on a straight-knee frame). Here each bone's rotation from neutral to the
calibration pose, ``neutral_from_rest`` (in the bone's axes), is estimated, and the
ranges are applied to ``neutral_from_rest * rest_from_bone``.

Neutral is the standing anatomical position, in the sagittal plane (about the
performer's left-right axis, the one the ranges' flexion and extension turn about).
What the markers decide of it:

- **thighs and shanks** (the hip and the knee; segment kinds ``thigh`` and ``shank``
  of ``validate.model.SEGMENT_KIND``): each long axis (+Y, joint centre to joint
  centre) upright in the sagittal plane. So a knee's neutral has its thigh and shank
  in line seen from the side, and a hip's has its thigh hanging from the pelvis as the
  calibration holds the pelvis (a walking pelvis tilts only a few degrees about
  standing: Perry & Burnfield, *Gait Analysis*, 2nd ed. 2010, ch. 8-9: pelvic tilt
  within about 4 deg each way);
- **the frontal plane is left as calibrated** (each thigh's and shank's sideways
  lean, the stance's width): a leg turned out in a wide stance bends its knee about
  an axis 15-30 deg off the performer's left-right axis, so its flexion reads partly
  as frontal; taking a frontal neutral in the performer's axes would add that to the
  frontal readings (the tennis serve, calibrated in its serving stance: its knees'
  frontal readings grew from 26-33 to 35-38 deg). Until the knee's own axes define
  the plane, frontal angles are measured from the calibration pose;
- **a bend under** :data:`LEAN_MIN_DEG` is no bend: a hip whose thigh leans less
  than that from upright, a knee whose shank and thigh are that close to in line,
  stands in the calibration pose as neutral, as before (below what the joint centres'
  placement can tell apart; the tennis serve's stance reads its left knee 2.7 deg
  hyperextended, which moved three frames 0.2 deg past the -15 deg bound);
- **everything else** (pelvis, spine, neck, head, arms, ankles) is measured from the
  calibration pose, as before: a calibration is a standing pose, and the spine's and
  neck's curves, the arms' T or A pose and the feet's stance have no marker-defined
  neutral here. The ankle too: over a foot turned out in the stance, the shank's
  forward lean is part dorsiflexion, part rotation about the foot's long axis, and
  reading it so added 5 deg to the tennis serve's foot twist, past its 55.

Each thigh's and shank's neutral world orientation ``N_b`` is its calibration
orientation turned about the performer's left (a thigh by its lean from upright, a
shank by its bend from its thigh plus its thigh's turn); any other bone rides its
parent's as calibrated (``N_b = N_parent rest_parent_from_bone``);
the neutral joint rotation is ``conj(N_parent) N_b`` and ``neutral_from_rest =
conj(conj(N_parent) N_b) * rest_parent_from_bone``: identity for every joint but the
hips and knees. A standing static is its own neutral to within its posture; a
calibration on a walking frame is measured from neutral.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.calibration import Calibration
from retargetd.daemon.body.rig import Rig
from retargetd.protocols.frames import F64Array

#: Segment kinds (``validate.model.SEGMENT_KIND``) whose long axis is upright at
#: neutral (module docstring).
VERTICAL_KINDS = ("thigh", "shank")
#: A long axis leaning less than this from upright is taken as upright, degrees: the
#: lean is read from joint centres a base pose places to 22 mm (hips) and 9 mm (knees)
#: median on the synthetic performer (issue 29; 15 and 4 mm since its pelvis markers
#: follow Harrington et al. 2007: the threshold keeps the larger figures), 31 mm
#: across a 400 mm thigh, 4.4 deg;
#: the limit table's margins already allow for a rest pose that far from neutral
#: (``validate.limits``: 5-10 deg past the literature).
LEAN_MIN_DEG = 4.4
_DOWN = np.array([0.0, 0.0, -1.0])


def performer_left(rig: Rig, calibration: Calibration) -> F64Array:
    """(3,) the performer's left in the calibration pose, horizontal: from the right
    thigh's origin to the left's (the hips), else world +Y. The validator's and the
    fit's sagittal axis."""
    humanoid = [b.humanoid or "" for b in rig.bones]
    origins = calibration.rest_bone_origin_pos
    left = np.array([0.0, 1.0, 0.0])
    if origins is not None and {"LeftUpperLeg", "RightUpperLeg"} <= set(humanoid):
        left = np.array(
            origins[humanoid.index("LeftUpperLeg")]
            - origins[humanoid.index("RightUpperLeg")],
            dtype=np.float64,
        )
        left[2] = 0.0
        left /= np.linalg.norm(left)
    return left


def _to_upright_rad(y: F64Array, left: F64Array) -> float:
    """The angle about ``left`` (radians, right-handed) that brings unit vector
    ``y``'s projection on the sagittal plane (normal to ``left``) straight down."""
    ys = y - (y @ left) * left
    return math.atan2(float(np.cross(ys, _DOWN) @ left), float(ys @ _DOWN))


def neutral_from_rest(
    rig: Rig, calibration: Calibration, segment_kind: Mapping[str, str]
) -> F64Array:
    """(B, 4) w x y z: each bone's rotation from anatomical neutral to the
    calibration pose, in the bone's axes (module docstring); identity where the
    calibration pose is taken as neutral.

    Args:
        rig, calibration: the rig and its calibration (rest orientations).
        segment_kind: humanoid bone -> segment kind (``validate.model.SEGMENT_KIND``).
    """
    rest_w = np.asarray(calibration.rest_world_from_bone_quat, dtype=np.float64)
    rest_p = np.asarray(calibration.rest_parent_from_bone_quat, dtype=np.float64)
    n_b = len(rig.bones)
    left = performer_left(rig, calibration)
    parents = rig.bone_parent_indices()
    least = math.radians(LEAN_MIN_DEG)
    # per bone: its angle to upright (thighs, shanks) and the turn about the left
    # that neutral gives it
    to_upright = np.full(n_b, np.nan)
    turn = np.zeros(n_b)
    neutral_w = rest_w.copy()
    for b, bone in enumerate(rig.bones):  # parents first
        p = parents[b]
        if segment_kind.get(bone.humanoid or "") in VERTICAL_KINDS:
            y = rot.quat_rotate(rest_w[b], np.array([0.0, 1.0, 0.0]))
            u = to_upright[b] = _to_upright_rad(y / np.linalg.norm(y), left)
            if p >= 0 and np.isfinite(to_upright[p]):  # a knee: in line with its thigh
                bend = u - to_upright[p]
                turn[b] = turn[p] + (bend if abs(bend) >= least else 0.0)
            else:  # a hip: its thigh upright under the pelvis as calibrated
                turn[b] = u if abs(u) >= least else 0.0
            half = 0.5 * turn[b]
            about = np.concatenate([[math.cos(half)], math.sin(half) * left])
            neutral_w[b] = rot.quat_mul(about, rest_w[b])
        elif p >= 0:  # rides its parent as calibrated
            neutral_w[b] = rot.quat_mul(neutral_w[p], rest_p[b])
    out = np.zeros((n_b, 4))
    out[:, 0] = 1.0
    for b in range(n_b):
        p = parents[b]
        if p < 0 or not (turn[b] or turn[p]):
            continue
        neutral_p = rot.quat_mul(rot.quat_conj(neutral_w[p]), neutral_w[b])
        c = rot.quat_mul(rot.quat_conj(neutral_p), rest_p[b])
        out[b] = c if c[0] >= 0.0 else -c
    return out


def pose_from_neutral_deg(
    rig: Rig, calibration: Calibration, segment_kind: Mapping[str, str]
) -> dict[str, tuple[float, float]]:
    """Each bone whose calibration pose is off neutral: its (sagittal, frontal)
    angles from neutral, degrees (the validator's split: sagittal positive = knee
    flexion, hip extension), for the ``calibrate`` summary.

    Args:
        rig, calibration, segment_kind: as :func:`neutral_from_rest`.
    """
    c = neutral_from_rest(rig, calibration, segment_kind)
    rest_w = np.asarray(calibration.rest_world_from_bone_quat, dtype=np.float64)
    left = performer_left(rig, calibration)
    forward = np.cross(left, [0.0, 0.0, 1.0])
    out = {}
    for b, bone in enumerate(rig.bones):
        if abs(c[b, 0]) >= 1.0 - 1e-12:
            continue
        to_neutral = rot.quat_mul(c[b], rot.quat_conj(rest_w[b]))
        swing_q, _ = rot.swing_twist(c[b], np.array([0.0, 1.0, 0.0]))
        swing = np.degrees(rot.rotvec_from_quat(swing_q))
        out[bone.name] = (
            float(swing @ rot.quat_rotate(to_neutral, left)),
            float(swing @ rot.quat_rotate(to_neutral, forward)),
        )
    return out
