"""Anatomical joint limits as swing/twist about each bone's axis.

A bone's streamed ``rest_from_bone_quat`` ``q`` is its rotation from the calibration
pose, in the bone's own rest axes (+Y along the bone). The limits apply to its
rotation from anatomical neutral, ``neutral_from_rest * q`` (``body.neutral``: a hip
or knee the calibration held flexed is measured from straight; every other joint from
the calibration pose), split as ``swing * twist``: ``twist`` about +Y (the long-axis
rotation, e.g. forearm pronation), ``swing`` about an axis perpendicular to the bone
(its rotation vector ``s``). The calibration pose is a standing pose (T-, A- or
anatomical): for legs, spine and neck that pose is close to anatomical neutral, so
their swing is split into a sagittal component (``s`` along the performer's left,
as in the calibration pose: positive = knee flexion, hip extension, ankle
plantarflexion, trunk / neck flexion) and a frontal component (``s`` along forward,
checked as a magnitude because its sign flips with the side). For the arms the rest
pose varies between rigs and takes (T vs A pose), so they get a cone on the swing
angle only (an elbow hyperextension is then not caught; noted).

Table :data:`JOINT_LIMITS_DEG`, degrees, per child segment kind (the joint between the
segment and its parent). Literature ranges of active motion in healthy adults, then a
margin for soft-tissue artefact and the rest pose not being exactly neutral, widened
where performers (dancers, overhead athletes) or skin-marker measurement exceed them:

- AAOS: American Academy of Orthopaedic Surgeons, *Joint Motion: Method of Measuring
  and Recording* (1965); Greene & Heckman, *The Clinical Measurement of Joint Motion*
  (AAOS 1994).
- Norkin C.C., White D.J., *Measurement of Joint Motion: A Guide to Goniometry*, 5th
  ed. (F.A. Davis 2016).
- Soucie J.M. et al., "Range of motion measurements: reference values and a database
  for comparison studies", Haemophilia 17(3):500-507 (2011).
- Fleisig G., Nicholls R., Elliott B., Escamilla R., "Kinematics used by world class
  tennis players to produce high-velocity serves", Sports Biomech 2(1):51-64 (2003):
  the upper arm reaches 172 deg of shoulder external rotation (mean, Sydney 2000
  Olympic players), the arm abducted ~100 deg.
- Reinschmidt C. et al., "Effect of skin movement on the analysis of skeletal knee
  joint motion during running", J Biomech 30(7):729-732 (1997): against bone pins,
  skin-marker knee errors were 21 % of the range (flexion), 63 % (internal/external
  rotation) and 70 % (abduction/adduction); Benoit D.L. et al., Gait Posture
  24(2):152-164 (2006): rotational errors up to 4.4 deg walking, 13.1 deg cutting.
- Ramakrishnan H.K., Kadaba M.P., "On the estimation of joint kinematics during gait",
  J Biomech 24(10):969-977 (1991): a knee flexion axis misaligned by a adds ~theta sin a
  of abduction/adduction at flexion theta (cross-talk).
- Activities (issue 16: the limits must hold beyond our own takes): McFadyen B.J.,
  Winter D.A., "An integrated biomechanical analysis of normal stair ascent and
  descent", J Biomech 21(9):733-744 (1988) (ankle dorsiflexion to ~40-45 descending);
  Novacheck T.F., "The biomechanics of running", Gait Posture 7(1):77-95 (1998) (hip
  flexion to ~65, knee swing flexion to ~130 sprinting); Decker M.J. et al., Clin
  Biomech 18(7):662-669 (2003) (landing: knee ~100, hip ~90, ankle ~30); Hemmerich A.
  et al., "Hip, knee, and ankle kinematics of high range of motion activities of daily
  living", J Orthop Res 24(4):770-781 (2006) (squatting: knee 157, ankle dorsiflexion
  38.5); Mulholland S.J., Wyss U.P., Int J Rehabil Res 24(3):191-198 (2001)
  (kneeling, sitting cross-legged: knee to 165); Bennell K. et al., Aust J Physiother
  44(3):175-180 (1998) (weight-bearing lunge dorsiflexion ~45); Nunome H. et al.,
  "Three-dimensional kinetic analysis of side-foot and instep soccer kicks", Med Sci
  Sports Exerc 34(12):2028-2036 (2002) (backswing hip extension ~30, knee flexion
  ~100); Russell J.A. et al., "Ankle and foot contributions to extreme plantar- and
  dorsiflexion in female ballet dancers", Foot Ankle Int 32(2):183-188 (2011) (en
  pointe); Fleisig G.S. et al., Am J Sports Med 23(2):233-239 (1995) (pitching:
  shoulder external rotation ~165-180). :data:`JOINT_LIMITS_DEG` fails beyond the
  widest of these (+ margin); :data:`TYPICAL_LIMITS_DEG` (the clinical norms + 10)
  only warns ("beyond the typical range").
- Hamilton W.G. et al., "A profile of the musculoskeletal characteristics of elite
  professional ballet dancers", Am J Sports Med 20(3):267-273 (1992): dancers' hip and
  ankle ranges differ markedly from population norms.

Per joint (segment): literature ranges; limit here; the real takes (how the validator
was tuned: ``validate.checks.THRESHOLDS``): PiG walk / MOTEK ballet / tennis
serve, extreme values of the component that set the limit.

- knee (shank): flexion 0-140/150, hyperextension <= 10, varus/valgus a few deg,
  tibial rotation ~30-40 at 90 flexion; skin markers: abduction/adduction and rotation
  errors of the order of their whole range (Reinschmidt, Benoit) and flexion cross-talk
  from the knee axis (Ramakrishnan & Kadaba);
  here sagittal -15..165 (deep squat 157, kneel-sitting to 165), frontal 35,
  twist +-55. Takes: frontal 13.9 / 21.2 / 32.9,
  twist 16.8 / 35.2 / 52.8 deg. The serve's calibration window (its first second) is a
  wide serving stance, legs turned 15-30 deg from the pelvis, while the rig sets the
  knee axis along the pelvis width: the serve's knee bends read frontal -26..-33 deg at
  47-54 deg of flexion (0.5-0.7 deg per deg of flexion: an axis ~30 deg off) and the
  knee marker slides (the shank reads 357 mm against 392 mm calibrated). A knee bent
  backwards is caught by the sagittal bound (-15).
- hip (thigh): flexion 120-125, extension 10-30, abduction 45, adduction 30,
  rotation 45/45; dancers: hip external rotation 45-60 (turnout), abduction beyond the
  norms (Hamilton 1992); a middle split, a pose trained performers hold, puts each hip
  at ~90 deg of abduction;
  here sagittal -150..45 (dance and a tucked deep squat), frontal 90 (a magnitude:
  adduction that far puts the thighs through each other, which self-penetration
  reports), twist +-60. Takes: frontal 7.6 / 64.2 (the ballet's side kick, frame 62)
  / 35.2.
- ankle (foot): dorsiflexion 20, plantarflexion 50, inversion 35, eversion 15;
  here sagittal -55..90 (stair descent, deep squat, lunge; en pointe), frontal 45,
  twist +-55: the foot's twist about the ankle-toe
  line is whole-foot inversion/eversion read from the heel marker on the heel pad,
  and with the foot plantarflexed the swing/twist split counts part of the foot's
  adduction as twist (6-10 deg at 35-50 deg of plantarflexion and 20 of adduction).
  Takes: twist 19.5 / 52.1 (the ballet's pointed foot, frames 48-50: 32-38 deg
  plantarflexion, 18-22 deg adduction) / 50.3.
- toes (MTP): extension 70-90, flexion 30-40;
  here cone 100, twist +-30.
- lumbar / thoracic (abdomen, thorax): thoracolumbar flexion 60-80, extension 25,
  lateral 25-35, rotation 30-45;
  here sagittal -40..80, frontal 45, twist +-50.
- neck / head: cervical flexion 45-50, extension 45-75, lateral 45, rotation 60-80;
  here sagittal -80..65, frontal 55, twist +-90.
- sternoclavicular (clavicle): elevation 35-45, protraction/retraction 15-30;
  here cone 60, twist +-60.
- shoulder (upper arm): flexion 180, extension 60, abduction 180, rotation 70/90
  (AAOS); overhead athletes rotate the humerus externally to 172 deg in the serve
  (Fleisig 2003: mean of world-class players; throwers reach similar values);
  here cone 175, twist not limited (+-180: the twist is measured from a calibration
  pose whose humeral rotation is not known, and the serve's 172 deg leaves no room
  below the half turn). Takes: twist 39.4 / -101.2 / +170.5 (the serve's cocking,
  right arm). A roll flipped by a marker-plane ambiguity (what cmu41's old elbow did)
  still shows as the forearm's twist against it.
- elbow (forearm): flexion 140-150, pronation/supination 75-85 each;
  here cone 165, twist +-160 (a).
- wrist (hand): flexion 80, extension 70, radial 20, ulnar 30;
  here cone 100, twist +-60.

(a) The forearm's twist is measured from the calibration pose, whose pronation is not
known (anatomical pose: supinated; PiG static: near neutral or pronated), so it may use
the whole pronation-supination arc (~160) either way; the PiG walk reaches +137.

Single-frame excursions: ``validate`` counts a frame beyond the table only when the
excursion lasts at least ``THRESHOLDS["limit_min_frames"]`` consecutive frames; shorter
ones are reported as transients (marker glitches: in the tennis serve, frame 400 has
LWRA and LWRB labelled on one marker, frame 744 a wrist bar 119 mm long against 101 mm
either side; the forearm and hand twists jump by 120-160 deg for that one frame). Frame
400 no longer shows since the construction keeps a bone's roll when its up reference
collapses onto its axis (``body.kernel`` step 4, RIGS.md ``up_min_mm``).

The root and bones with no humanoid mapping are not limited.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from retargetd.daemon import rotations as rot
from retargetd.daemon.validate.model import Skeleton
from retargetd.protocols.frames import F64Array


@dataclass(frozen=True, slots=True)
class JointLimit:
    """Degrees. ``sagittal`` (lo, hi) and ``frontal`` (max |.|) or ``cone`` (max)."""

    twist: tuple[float, float]
    sagittal: tuple[float, float] | None = None
    frontal: float | None = None
    cone: float | None = None


#: Failure limits: the widest range published for any activity (below, "Activities"),
#: plus a margin for skin-marker artefact and a calibration pose that is not exactly
#: neutral. Never set from our own takes. Where a change from the earlier table was
#: made, the activity that reaches past the old value is named.
JOINT_LIMITS_DEG: dict[str, JointLimit] = {
    # Knee: deep squat 157 deg flexion (Hemmerich 2006), kneel-sitting 155-165
    # (Mulholland & Wyss 2001); hyperextension <= 10 (AAOS) + 5 margin.
    "shank": JointLimit((-55, 55), sagittal=(-15, 165), frontal=35),
    # Hip: flexion to 150 in dance (grand battement devant; Hamilton 1992) and at a
    # deep squat's bottom with the pelvis tucked (Hemmerich 2006: 95-130 + pelvic
    # tilt); extension 45: arabesque and the kick's backswing (Nunome 2002: ~30) plus
    # margin; abduction 90 (a split).
    "thigh": JointLimit((-60, 60), sagittal=(-150, 45), frontal=90),
    # Ankle: dorsiflexion 45 in stair descent (McFadyen & Winter 1988; the issue's
    # stair walk reads 40-45), 38.5 in a deep squat (Hemmerich 2006), 45 in the
    # weight-bearing lunge (Bennell 1998) + 10 margin; plantarflexion 90 (AAOS 50;
    # en pointe the ankle and foot plantarflex to ~90 beyond neutral, Russell 2011).
    "foot": JointLimit((-55, 55), sagittal=(-55, 90), frontal=45),
    "toes": JointLimit((-30, 30), cone=100),
    "abdomen": JointLimit((-50, 50), sagittal=(-40, 80), frontal=45),
    "thorax": JointLimit((-50, 50), sagittal=(-40, 80), frontal=45),
    "neck": JointLimit((-90, 90), sagittal=(-80, 65), frontal=55),
    "head": JointLimit((-90, 90), sagittal=(-80, 65), frontal=55),
    "clavicle": JointLimit((-60, 60), cone=60),
    # Shoulder: throwing and serving rotate the humerus externally to 165-180 deg
    # (Fleisig 1995, 2003): the twist is not limited.
    "upper_arm": JointLimit((-180, 180), cone=175),
    "forearm": JointLimit((-160, 160), cone=165),
    "hand": JointLimit((-60, 60), cone=100),
}

#: The typical clinical range of active motion (AAOS 1965/1994; Norkin & White 2016;
#: Soucie 2011) + 10 deg for skin markers and the rest pose: a frame beyond it but
#: inside :data:`JOINT_LIMITS_DEG` is reported as "beyond the typical range", a
#: warning, not a failure (where the literature across activities is uncertain).
#: Components left None are not warned on.
TYPICAL_LIMITS_DEG: dict[str, JointLimit] = {
    # Knee flexion 140 (AAOS) + 10; hyperextension 0-5 (Soucie) + 5.
    "shank": JointLimit((-40, 40), sagittal=(-10, 150), frontal=20),
    # Hip flexion 120-125, extension 10-30, abduction 45 (AAOS) + 10.
    "thigh": JointLimit((-55, 55), sagittal=(-135, 40), frontal=55),
    # Ankle dorsiflexion 20, plantarflexion 50 (AAOS) + 10.
    "foot": JointLimit((-45, 45), sagittal=(-30, 60), frontal=40),
}

#: Where the numbers of both tables come from, for the validate report's header.
LIMITS_SOURCES = (
    "failure: the widest published range across activities (stairs: McFadyen & "
    "Winter 1988; running: Novacheck 1998; jumping and landing: Decker 2003; deep "
    "squat: Hemmerich 2006; kicking: Nunome 2002; dance: Hamilton 1992, Russell 2011; "
    "throwing and serving: Fleisig 1995, 2003) + skin-marker margin (Reinschmidt "
    "1997, Benoit 2006); warning (beyond the typical range): AAOS, Norkin & White "
    "2016, Soucie 2011 + 10 deg; never fitted to our takes"
)


def swing_twist(q: F64Array) -> tuple[F64Array, F64Array]:
    """Split rotations about +Y: swing rotation vectors (..., 3), twist angles (...,).

    ``q = swing * twist`` with ``twist = (w, 0, y, 0) / norm`` (radians in (-pi, pi]).
    """
    twist_angle = 2.0 * np.arctan2(q[..., 2], q[..., 0])
    twist_angle = (twist_angle + np.pi) % (2.0 * np.pi) - np.pi
    half = 0.5 * twist_angle
    twist = np.zeros(q.shape)
    twist[..., 0] = np.cos(half)
    twist[..., 2] = np.sin(half)
    swing = rot.quat_mul(q, rot.quat_conj(twist))
    return rot.rotvec_from_quat(swing), twist_angle


def neutral_frame(skel: Skeleton, b: int) -> tuple[F64Array, F64Array]:
    """Bone ``b``'s ``neutral_from_rest`` (4,) and ``neutral_from_world`` (4,)
    rotations: the limits apply to ``neutral_from_rest * rest_from_bone``, and the
    performer's left and forward are taken in the bone's axes at neutral
    (``body.neutral``; identity without ``skel.neutral_from_rest_quat``)."""
    ref = (
        np.array([1.0, 0.0, 0.0, 0.0])
        if skel.neutral_from_rest_quat is None
        else np.asarray(skel.neutral_from_rest_quat[b], dtype=np.float64)
    )
    return ref, rot.quat_mul(ref, rot.quat_conj(skel.rest_world_from_bone_quat[b]))


def limit_violation_deg(
    skel: Skeleton, pfb: F64Array, table: dict[str, JointLimit] | None = None
) -> tuple[F64Array, np.ndarray]:
    """Degrees beyond each bone's limits, per frame, and which limit.

    Args:
        skel: the skeleton (segment kinds, rest rotations, performer's left, the
            calibration pose's rotation from anatomical neutral).
        pfb: (T, B, 4) streamed ``rest_from_bone_quat``: the limits are checked on
            ``neutral_from_rest * rest_from_bone`` (``body.neutral``).
        table: the limits (default :data:`JOINT_LIMITS_DEG`; or
            :data:`TYPICAL_LIMITS_DEG`).

    Returns:
        (T, B) degrees beyond the limit (0 inside), (T, B) str: the component most
        beyond ("sagittal +12.3 deg" ...), "" where inside.
    """
    n, n_bones = pfb.shape[:2]
    viol = np.zeros((n, n_bones))
    which = np.full((n, n_bones), "", dtype=object)
    if skel.neutral_from_rest_quat is not None:
        pfb = rot.quat_mul(np.asarray(skel.neutral_from_rest_quat)[None], pfb)
    swing, twist = swing_twist(pfb)
    swing = np.degrees(swing)
    twist = np.degrees(twist)
    up = np.array([0.0, 0.0, 1.0])
    forward_world = np.cross(skel.left_world, up)
    for b, kind in enumerate(skel.bone_kinds):
        lim = (JOINT_LIMITS_DEG if table is None else table).get(kind)
        if lim is None or skel.bone_parents[b] < 0:
            continue
        _, bone_from_world = neutral_frame(skel, b)
        parts: list[tuple[str, F64Array, F64Array]] = [
            ("twist", twist[:, b], _beyond(twist[:, b], *lim.twist))
        ]
        if lim.sagittal is not None:
            left = rot.quat_rotate(bone_from_world, skel.left_world)
            sag = swing[:, b] @ left
            parts.append(("sagittal", sag, _beyond(sag, *lim.sagittal)))
        if lim.frontal is not None:
            fwd = rot.quat_rotate(bone_from_world, forward_world)
            fro = swing[:, b] @ fwd
            parts.append(("frontal", fro, _beyond(fro, -lim.frontal, lim.frontal)))
        if lim.cone is not None:
            cone = np.linalg.norm(swing[:, b], axis=-1)
            parts.append(("swing", cone, _beyond(cone, 0.0, lim.cone)))
        stack = np.stack([p[2] for p in parts], axis=-1)
        k = np.argmax(stack, axis=-1)
        viol[:, b] = stack[np.arange(n), k]
        for t in np.flatnonzero(viol[:, b] > 0.0):
            label, value, _ = parts[k[t]]
            which[t, b] = f"{kind} {label} {value[t]:+.1f} deg"
    return viol, which


def _beyond(x: F64Array, lo: float, hi: float) -> F64Array:
    return np.maximum(np.maximum(lo - x, x - hi), 0.0)
