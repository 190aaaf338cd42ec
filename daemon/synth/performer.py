"""The synthetic performer: a known skeleton, procedural motion, any marker set.

Ground truth for tests and the embedded default for demos. :func:`synthesize` returns
the markers a capture system would see together with the true joint centres and
rotations they came from.

The skeleton is :mod:`retargetd.daemon.synth.skeleton`, marker sets are
:mod:`retargetd.daemon.synth.markerset`.

Motion: each named component in :data:`ALL_MOTIONS` adds joint angles (and root motion)
that are smooth functions of time, weighted by a ramp ``w(t)`` that is exactly 0 during
the base-pose hold (``t <= base_pose_s``, exact T-pose) and rises to 1 over
:data:`RAMP_S` with a quintic smoothstep. Angles are summed per joint into channels
about the segment's x, y, z axes and turned into ``parent_from_segment`` quaternions
with one intrinsic Euler sequence per segment (:data:`EULER_ORDERS`; the long-axis
rotation last). Left-side formulas are anatomical; the right side mirrors them through
the sagittal plane (x and z angles negated) with its own phases. Frequencies are
irrational ratios of each other, so the pose never repeats.

Root: the pelvis starts at ``origin + (0, 0, 0.530 H)`` (``origin`` is the floor point
under the pelvis; soles at z = 0). ``walk`` moves it counter-clockwise round a circle
of :data:`WALK_RADIUS_M` centred at ``origin + (0, R, 0)`` (the lab origin for the
default origin), heading along the tangent, with lateral sway; the vertical bob comes
from keeping the lowest sole point on the floor (a soft minimum, so it stays smooth).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.signal import butter, filtfilt

from retargetd.daemon import rotations as rot
from retargetd.daemon.synth.markerset import (
    MarkerSet,
    load_markerset,
    shipped_markersets,
)
from retargetd.daemon.synth.skeleton import (
    REFERENCE_HEIGHT_M,
    SEGMENT_NAMES,
    Skeleton,
    make_skeleton,
    readonly,
)
from retargetd.protocols.conventions import MM_TO_M
from retargetd.protocols.frames import BoolArray, F64Array, IntArray

__all__ = [
    "ACTIVITY_MOTIONS",
    "ALL_MOTIONS",
    "DEFAULT_MOTIONS",
    "REFERENCE_HEIGHT_M",
    "SEGMENT_NAMES",
    "MarkerSet",
    "Skeleton",
    "SynthTake",
    "load_markerset",
    "load_truth",
    "make_skeleton",
    "shipped_markersets",
    "synthesize",
]

#: The everyday motion components, in composition order: the default of
#: :func:`synthesize` (a walk round a circle with arm, forearm, spine and head motion).
DEFAULT_MOTIONS: tuple[str, ...] = (
    "walk",
    "arm_raise",
    "forearm_twist",
    "spine",
    "head_turn",
)
#: Activities that reach the published ranges of motion the validator's joint limits
#: come from (``validate.limits``), each meant to be synthesized alone (optionally
#: with ``head_turn``): see :func:`_deep_squat` ... :func:`_jump`.
ACTIVITY_MOTIONS: tuple[str, ...] = (
    "stair_ascent",
    "stair_descent",
    "run",
    "jump",
    "deep_squat",
    "kick",
)
#: Every motion component, in composition order.
ALL_MOTIONS: tuple[str, ...] = DEFAULT_MOTIONS + ACTIVITY_MOTIONS
#: Ramp from the base-pose hold into full motion, seconds.
RAMP_S = 0.5
#: Walk: circle radius, speed, stride length (one left + one right step).
WALK_RADIUS_M = 1.5
WALK_SPEED_M_S = 1.0
WALK_STRIDE_M = 1.1
#: Default floor point under the pelvis: the walk circle is then centred at the lab
#: origin.
DEFAULT_ORIGIN = (0.0, -WALK_RADIUS_M, 0.0)
#: Soft-minimum temperature for the floor contact (metres).
_FLOOR_SOFTMIN_M = 0.003
_X, _Y, _Z = 0, 1, 2

# --- motion ----------------------------------------------------------------------


def _smootherstep(u: F64Array) -> F64Array:
    u = np.clip(u, 0.0, 1.0)
    return u * u * u * (u * (6.0 * u - 15.0) + 10.0)


def _smootherstep_integral(u: F64Array) -> F64Array:
    """Integral of the smootherstep from 0 to ``u`` (u clipped to [0, 1] first)."""
    v = np.clip(u, 0.0, 1.0)
    return v**6 - 3.0 * v**5 + 2.5 * v**4 + np.maximum(u - 1.0, 0.0)


def _bump(x: F64Array, power: int) -> F64Array:
    """A smooth 2π-periodic bump peaking at x = 0 with height 1."""
    return (0.5 * (1.0 + np.cos(x))) ** power


@dataclass(slots=True, eq=False)
class _Motion:
    """Working buffers the motion components add into."""

    skeleton: Skeleton
    t: F64Array  # (T,) seconds since the motion started (negative during the hold)
    w: F64Array  # (T,) ramp weight in [0, 1]
    angles: F64Array  # (T, S, 3) radians about the segment's x, y, z
    root_pos: F64Array  # (T, 3) metres, world
    heading: F64Array  # (T,) radians about world +Z
    motions: tuple[str, ...]
    walk_weight: F64Array = field(default_factory=lambda: np.zeros(0))
    # Activities: keep the lowest sole on the floor with this weight (like the walk);
    # translate the body horizontally so these segments' origins stay where they
    # stood (a planted foot); add this vertical flight (metres) after both.
    floor_weight: F64Array = field(default_factory=lambda: np.zeros(0))
    plant: tuple[str, ...] = ()
    plant_weight: F64Array = field(default_factory=lambda: np.zeros(0))
    flight_m: F64Array = field(default_factory=lambda: np.zeros(0))
    # Gaits: low-pass the floor-contact lift (Hz; 0 = off): the hard switch of the
    # lowest sole from one foot to the other would drop the body faster than gravity.
    floor_smooth_hz: float = 0.0
    # Runs: the body never falls faster than gravity; where the floor contact would
    # drop it faster, it flies (the feet leave the floor: a flight phase).
    ballistic: bool = False

    def add(self, segment: str, axis: int, deg: F64Array) -> None:
        """Add ``deg`` (T,) degrees, already weighted, about one axis of one segment."""
        self.angles[:, self.skeleton.index(segment), axis] += np.deg2rad(deg)

    def add_bilateral(
        self, kind: str, axis: int, left_deg: F64Array, right_deg: F64Array
    ) -> None:
        """Add anatomical left/right angles; the right is mirrored (x, z negated)."""
        self.add("l_" + kind, axis, left_deg)
        self.add("r_" + kind, axis, right_deg if axis == _Y else -right_deg)

    def osc(self, freq_hz: float, phase: float = 0.0) -> F64Array:
        """``sin(2π f t + phase) - sin(phase)``: 0 at the start of the motion."""
        arg = 2.0 * np.pi * freq_hz * self.t
        return np.sin(arg + phase) - np.sin(phase)


def _walk(m: _Motion) -> None:
    t0 = np.maximum(m.t, 0.0)
    # Distance walked: the speed follows the ramp, so the gait phase starts at rest.
    dist = WALK_SPEED_M_S * RAMP_S * _smootherstep_integral(t0 / RAMP_S)
    phase = 2.0 * np.pi * dist / WALK_STRIDE_M  # right heel strike at 0 mod 2π
    w = m.w
    right, left = phase, phase + np.pi
    for side_phase, side in ((left, "l"), (right, "r")):
        sign = 1.0 if side == "l" else -1.0  # mirror x/z for the right side
        hip_flex = 8.0 + 22.0 * np.cos(side_phase)
        knee_flex = (
            5.0 + 55.0 * _bump(side_phase - 4.6, 4) + 12.0 * _bump(side_phase - 0.9, 8)
        )
        ankle_dorsi = (
            8.0 * _bump(side_phase - 2.8, 2)
            - 18.0 * _bump(side_phase - 3.9, 6)
            + 5.0 * _bump(side_phase - 5.0, 4)
        )
        toe_ext = 25.0 * _bump(side_phase - 3.6, 6)
        m.add(f"{side}_thigh", _Y, -w * hip_flex)  # flexion: knee forward = -y
        m.add(f"{side}_thigh", _X, sign * w * 3.0 * np.sin(side_phase))  # ab/adduction
        m.add(f"{side}_shank", _Y, w * knee_flex)  # flexion: ankle backward = +y
        m.add(f"{side}_foot", _Y, -w * ankle_dorsi)  # dorsiflexion: toes up = -y
        m.add(f"{side}_toes", _Y, -w * toe_ext)
    # Pelvis: rotation toward the forward leg, list (swing side drops), slight tilt.
    m.add("pelvis", _Z, w * 6.0 * np.cos(right))
    m.add("pelvis", _X, -w * 4.0 * np.sin(right))
    m.add("pelvis", _Y, w * (2.0 + 2.0 * np.cos(2.0 * right)))
    # Trunk counter-rotation keeps the chest facing ahead.
    m.add("abdomen", _Z, -w * 2.5 * np.cos(right))
    m.add("thorax", _Z, -w * 4.0 * np.cos(right))
    # Arms hang (unless arm_raise drives them) and counter-swing with the legs.
    if "arm_raise" not in m.motions:
        m.add_bilateral("upper_arm", _X, -w * 72.0, -w * 72.0)
    m.add_bilateral(
        "upper_arm", _Y, w * 20.0 * np.cos(right), -w * 20.0 * np.cos(right)
    )
    m.add_bilateral(
        "forearm",
        _Z,
        -w * (15.0 - 8.0 * np.cos(right)),
        -w * (15.0 + 8.0 * np.cos(right)),
    )
    # Root: round the circle (counter-clockwise, turning left), swaying over the stance
    # foot. The vertical bob is added after forward kinematics (floor contact).
    heading = dist / WALK_RADIUS_M
    sway = -0.02 * w * np.sin(right)  # + = to the performer's left
    m.heading += heading
    m.root_pos[:, 0] += (WALK_RADIUS_M - sway) * np.sin(heading)
    m.root_pos[:, 1] += WALK_RADIUS_M - (WALK_RADIUS_M - sway) * np.cos(heading)
    m.walk_weight = w


def _arm_raise(m: _Motion) -> None:
    w = m.w
    s2, s3, s5 = np.sqrt(2.0), np.sqrt(3.0), np.sqrt(5.0)
    # Elevation from the T-pose (+ = up): near the side to near overhead, the right
    # arm at another frequency and starting downward.
    elev_l = 75.0 * np.sin(2.0 * np.pi * 0.19 * m.t)
    elev_r = -70.0 * np.sin(2.0 * np.pi * 0.19 * s2 / 1.2 * m.t)
    horiz_l = 35.0 * np.sin(2.0 * np.pi * 0.11 * s3 * m.t)  # + = forward
    horiz_r = 30.0 * np.sin(2.0 * np.pi * 0.11 * s5 / 1.5 * m.t)
    flex_l = 30.0 * np.sin(2.0 * np.pi * 0.13 * s5 / 2.0 * m.t)  # + = forward
    flex_r = -30.0 * np.sin(2.0 * np.pi * 0.13 * s3 / 1.5 * m.t)
    m.add_bilateral("upper_arm", _X, w * elev_l, w * elev_r)  # elevation: up = +x
    m.add_bilateral("upper_arm", _Z, -w * horiz_l, -w * horiz_r)  # forward = -z
    m.add_bilateral("upper_arm", _Y, -w * flex_l, -w * flex_r)  # flexion: fwd = -y
    # The shoulder girdle follows: clavicle elevation and protraction.
    m.add_bilateral("clavicle", _X, w * 0.2 * elev_l, w * 0.2 * elev_r)
    m.add_bilateral("clavicle", _Z, -w * 0.2 * horiz_l, -w * 0.2 * horiz_r)


def _forearm_twist(m: _Motion) -> None:
    w = m.w
    s2, s3 = np.sqrt(2.0), np.sqrt(3.0)
    # Pronation/supination about the forearm's long axis (y), +-70 deg.
    twist_l = 70.0 * np.sin(2.0 * np.pi * 0.37 * m.t)
    twist_r = 70.0 * np.sin(2.0 * np.pi * 0.37 * s2 / 1.3 * m.t)
    m.add_bilateral("forearm", _Y, w * twist_l, w * twist_r)
    # Elbow flexion 10..80 deg (about the upper arm's z; forward = -z for the left).
    flex_l = 45.0 - 35.0 * np.cos(2.0 * np.pi * 0.23 * m.t)
    flex_r = 45.0 - 35.0 * np.cos(2.0 * np.pi * 0.23 * s3 / 1.6 * m.t)
    m.add_bilateral("forearm", _Z, -w * flex_l, -w * flex_r)
    # Wrist flexion (fingers down = -x) and radial deviation (thumb side = -z).
    m.add_bilateral(
        "hand", _X, -w * 25.0 * m.osc(0.29), -w * 25.0 * m.osc(0.29 * s3 / 1.6)
    )
    m.add_bilateral("hand", _Z, -w * 10.0 * m.osc(0.31 * s2), -w * 10.0 * m.osc(0.41))


def _spine(m: _Motion) -> None:
    w = m.w
    s2, s3, s5 = np.sqrt(2.0), np.sqrt(3.0), np.sqrt(5.0)
    flexion = 18.0 - 18.0 * np.cos(2.0 * np.pi * 0.09 * s2 * m.t)  # 0..36 deg forward
    lateral = 15.0 * m.osc(0.07 * s3)  # + = bend to the left
    twist = 25.0 * m.osc(0.06 * s5)  # + = face turns left
    for segment, share in (("abdomen", 0.4), ("thorax", 0.6)):
        m.add(segment, _Y, w * share * flexion)
        m.add(segment, _X, -w * share * lateral)
        m.add(segment, _Z, w * share * twist)


def _head_turn(m: _Motion) -> None:
    w = m.w
    yaw = 60.0 * m.osc(0.17 * np.sqrt(3.0))  # + = look left
    nod = 15.0 * m.osc(0.21 * np.sqrt(5.0) / 2.0)  # + = chin down
    tilt = 8.0 * m.osc(0.13 * np.sqrt(7.0) / 2.0)
    for segment, share in (("neck", 0.3), ("head", 0.7)):
        m.add(segment, _Z, w * share * yaw)
        m.add(segment, _Y, w * share * nod)
        m.add(segment, _X, -w * share * tilt)


# --- activities that reach the published ranges of motion --------------------------
#
# Peak angles (degrees, from the standing calibration pose) are those the literature
# reports for healthy adults; validate.limits cites the same papers. Legs: thigh -y =
# hip flexion, shank +y = knee flexion, foot -y = ankle dorsiflexion (see _walk).


def _cycle(m: _Motion, period_s: float) -> F64Array:
    """0 -> 1 -> 0 over each ``period_s`` after the hold (raised cosine), weighted."""
    return m.w * 0.5 * (1.0 - np.cos(2.0 * np.pi * np.maximum(m.t, 0.0) / period_s))


def _legs(
    m: _Motion, side: str, hip: F64Array, knee: F64Array, ankle: F64Array
) -> None:
    """Hip flexion, knee flexion, ankle dorsiflexion (deg, weighted) of one leg."""
    m.add(f"{side}_thigh", _Y, -hip)
    m.add(f"{side}_shank", _Y, knee)
    m.add(f"{side}_foot", _Y, -ankle)


def _arms_down(m: _Motion, forward_deg: F64Array | float = 0.0) -> None:
    """Arms from the T-pose to hanging (72 deg down), raised forward by
    ``forward_deg`` (already weighted; for balance), unless another component drives
    them."""
    if "arm_raise" not in m.motions:
        m.add_bilateral("upper_arm", _X, -m.w * 72.0, -m.w * 72.0)
        fwd = forward_deg * np.ones_like(m.w)
        m.add_bilateral("upper_arm", _Z, -fwd, -fwd)


def _deep_squat(m: _Motion) -> None:
    """Full squat, heels down, one every 4 s: hip flexion 115, knee flexion 152,
    ankle dorsiflexion 38, trunk flexion 30 (Hemmerich et al. 2006: squatting, knee
    157 and ankle 38.5 deg); feet planted, arms forward for balance."""
    s = _cycle(m, 4.0)
    for side in ("l", "r"):
        _legs(m, side, 115.0 * s, 152.0 * s, 38.0 * s)
    for segment, share in (("abdomen", 0.5), ("thorax", 0.5)):
        m.add(segment, _Y, share * 30.0 * s)
    _arms_down(m, 80.0 * s)
    m.floor_weight = m.w
    m.plant = ("l_foot", "r_foot")
    m.plant_weight = m.w


#: One kick every this many seconds.
KICK_PERIOD_S = 4.0


def _kick(m: _Motion) -> None:
    """Instep kick with the right leg, one every 3 s, standing on the left: backswing
    hip extension 30 with knee flexion 100, then the swing to hip flexion 85 with the
    knee straightening and the foot pointed (plantarflexion 45); the stance knee
    flexes 25 (Nunome et al. 2002; Lees & Nolan 1998). Left foot planted."""
    tau = (np.maximum(m.t, 0.0) % KICK_PERIOD_S) / KICK_PERIOD_S  # through one kick
    back = m.w * _bump(2.0 * np.pi * (tau - 0.3), 4)  # backswing peak at 30 %
    swing = m.w * _bump(2.0 * np.pi * (tau - 0.6), 4)  # follow-through at 60 %
    _legs(m, "r", -30.0 * back + 85.0 * swing, 100.0 * back + 15.0 * swing,
          -45.0 * np.maximum(back, swing))  # fmt: skip
    stance = np.maximum(back, swing)
    _legs(m, "l", 20.0 * stance, 25.0 * stance, 15.0 * stance)

    m.add("abdomen", _Y, -10.0 * swing)  # the trunk leans back as the leg swings up
    m.add("thorax", _Y, -5.0 * swing)
    m.add("pelvis", _Z, 15.0 * swing - 10.0 * back)
    _arms_down(m)
    m.add_bilateral("upper_arm", _X, m.w * 40.0 * stance, m.w * 30.0 * stance)
    m.floor_weight = m.w
    m.plant = ("l_foot",)
    m.plant_weight = m.w


def _jump(m: _Motion) -> None:
    """Countermovement jumps in place, one every 2.5 s: crouch to hip flexion 60,
    knee 100, ankle dorsiflexion 40, arms forward 60 (landing: Decker et al. 2003, hip
    ~60-90, knee ~90-100, ankle ~25-35), push-off, 0.40 s of ballistic flight (20 cm;
    the lift frozen at take-off, the legs still but for the ankles pointing 30), then
    the landing absorbed over 0.9 s into the same crouch. Feet planted."""
    period = 2.5
    tau = np.maximum(m.t, 0.0) % period
    flight_s = 0.40
    take_off = 1.0
    landing = take_off + flight_s

    def hump(centre: float, half: float) -> F64Array:
        x = np.clip((tau - centre) / half, -1.0, 1.0)
        return (0.5 * (1.0 + np.cos(np.pi * x))) ** 2

    # Countermovement down and up (0.1-1.0 s), landing absorbed (1.4-2.3 s).
    crouch = m.w * (hump(0.55, 0.45) + hump(landing + 0.45, 0.45))
    air = (tau >= take_off) & (tau < landing)
    u = np.where(air, (tau - take_off) / flight_s, 0.0)
    point = m.w * np.where(air, np.sin(np.pi * u), 0.0)
    for side in ("l", "r"):
        _legs(m, side, 60.0 * crouch, 100.0 * crouch, 40.0 * crouch - 30.0 * point)
    _arms_down(m, 60.0 * crouch)
    g = 9.81
    tf = np.where(air, tau - take_off, 0.0)
    m.flight_m = np.where(air, m.w * (0.5 * g * flight_s * tf - 0.5 * g * tf * tf), 0.0)
    m.floor_weight = m.w
    m.plant = ("l_foot", "r_foot")
    m.plant_weight = m.w


#: Sharpness of a gait's stance knee-flexion bump (a power of the raised cosine).
STANCE_POWER = 3


def _gait(
    m: _Motion,
    *,
    speed_m_s: float,
    stride_m: float,
    hip: tuple[float, float],
    knee_stance: float,
    knee_swing: float,
    ankle_dorsi: float,
    ankle_plantar: float,
    trunk_deg: float,
    smooth_hz: float = 4.0,
    radius_m: float = WALK_RADIUS_M,
    ramp_s: float = RAMP_S,
    ballistic: bool = False,
) -> None:
    """A gait round the walk circle with its own joint-angle profile: hip flexion
    ``hip[0] + hip[1] cos(phase)``, knee flexion bumps in stance and swing, ankle
    dorsiflexion in stance and plantarflexion at push-off; the lowest sole kept on
    the floor (the steps of a stair gait are not modelled: its angles are)."""
    t0 = np.maximum(m.t, 0.0)
    dist = speed_m_s * ramp_s * _smootherstep_integral(t0 / ramp_s)
    phase = 2.0 * np.pi * dist / stride_m
    w = _smootherstep(m.t / ramp_s)  # the angles grow with the speed
    for side_phase, side in ((phase + np.pi, "l"), (phase, "r")):
        hip_flex = hip[0] + hip[1] * np.cos(side_phase)
        knee = knee_swing * _bump(side_phase - 4.6, 4) + knee_stance * _bump(
            side_phase - 0.9, STANCE_POWER
        )
        ankle = ankle_dorsi * _bump(side_phase - 2.4, 3) - ankle_plantar * _bump(
            side_phase - 3.9, 6
        )
        _legs(m, side, w * hip_flex, w * knee, w * ankle)
    m.add("abdomen", _Y, w * trunk_deg)
    _arms_down(m)
    m.add_bilateral(
        "upper_arm", _Y, w * 25.0 * np.cos(phase), -w * 25.0 * np.cos(phase)
    )
    m.add_bilateral("forearm", _Z, -w * 60.0, -w * 60.0)
    heading = dist / radius_m
    m.heading += heading
    m.root_pos[:, 0] += radius_m * np.sin(heading)
    m.root_pos[:, 1] += radius_m - radius_m * np.cos(heading)
    m.floor_weight = w
    m.floor_smooth_hz = smooth_hz
    m.ballistic = ballistic


def _stair_ascent(m: _Motion) -> None:
    """Stair-ascent joint angles (McFadyen & Winter 1988; Protopapadaki et al. 2007):
    hip flexion to 65, knee flexion to 95, ankle dorsiflexion 20, push-off
    plantarflexion 15, trunk forward 10; 0.5 m/s."""
    _gait(
        m,
        speed_m_s=0.5,
        stride_m=0.6,
        hip=(27.5, 37.5),
        knee_stance=60.0,
        knee_swing=95.0,
        ankle_dorsi=20.0,
        ankle_plantar=15.0,
        trunk_deg=10.0,
    )


def _stair_descent(m: _Motion) -> None:
    """Stair-descent joint angles (McFadyen & Winter 1988; the issue's stair walk):
    hip flexion to 40, knee flexion to 100, ankle dorsiflexion to 45 as the stance
    leg lowers the body, plantarflexion 30 reaching for the step below; 0.5 m/s."""
    _gait(
        m,
        speed_m_s=0.5,
        stride_m=0.6,
        hip=(17.5, 22.5),
        knee_stance=85.0,
        knee_swing=100.0,
        ankle_dorsi=45.0,
        ankle_plantar=30.0,
        trunk_deg=5.0,
    )


#: The run's circle: at 3 m/s a 15 m radius asks 0.6 m/s^2 of centripetal
#: acceleration, the walk's on its 1.5 m circle (0.67 m/s^2); on the walk's circle it
#: would be 6 m/s^2, which a runner leans into and the synthetic one does not.
RUN_RADIUS_M = 15.0


def _run(m: _Motion) -> None:
    """Running (Novacheck 1998, running 3.2 m/s to sprinting): hip flexion 10..60
    about 25 +- 35 (extension 10 at toe-off), stance knee flexion 45, swing 120,
    ankle dorsiflexion 25, push-off plantarflexion 25, trunk forward 10; 3 m/s,
    speeding up over 2 s, on a 15 m circle. The body never falls faster than gravity:
    where the floor contact would drop it faster it flies, so each step has a flight
    phase (~0.1 s)."""
    _gait(
        m,
        speed_m_s=3.0,
        stride_m=2.4,
        hip=(25.0, 35.0),
        knee_stance=45.0,
        knee_swing=120.0,
        ankle_dorsi=25.0,
        ankle_plantar=25.0,
        trunk_deg=10.0,
        smooth_hz=0.0,
        radius_m=RUN_RADIUS_M,
        ramp_s=2.0,
        ballistic=True,
    )


_COMPONENTS = {
    "walk": _walk,
    "arm_raise": _arm_raise,
    "forearm_twist": _forearm_twist,
    "spine": _spine,
    "head_turn": _head_turn,
    "stair_ascent": _stair_ascent,
    "stair_descent": _stair_descent,
    "run": _run,
    "jump": _jump,
    "deep_squat": _deep_squat,
    "kick": _kick,
}


# --- the take --------------------------------------------------------------------


@dataclass(frozen=True, slots=True, kw_only=True)
class SynthTake:
    """A synthesized take: markers plus the truth they came from.

    All positions are metres in the internal world (+Z up); quaternions (w, x, y, z).

    Attributes:
        labels: (M,) marker labels.
        markers_world: (T, M, 3) float64, metres, world; NaN rows = occluded.
        valid: (T, M) bool, True where the marker is seen.
        rate_hz: frame rate.
        times_s: (T,) float64 seconds from the first frame.
        segment_names: (S,) segment names, parents before children.
        segment_parents: (S,) int64 parent index, -1 for the root.
        rest_offsets: (S, 3) float64, metres: each segment origin in its parent's frame
            (root: the pelvis above its floor point ``origin_world``).
        joint_pos_world: (T, S, 3) float64, metres: segment origins = joint centres.
        world_from_segment_quat: (T, S, 4) float64 (w, x, y, z).
        parent_from_segment_quat: (T, S, 4) float64 (w, x, y, z); for the root it is
            ``world_from_pelvis``. Rest rotations are identity, so these are also the
            rotations relative to the T-pose.
        base_pose_frames: the frames of the static T-pose hold (``slice(0, n)``).
        marker_segments: (M,) int64 segment index each marker rides on.
        marker_offsets: (M, 3) float64, metres, marker in its segment's frame.
        markerset: the marker set's name.
        motions: the motion components used.
        noise_mm: Gaussian noise std per coordinate, millimetres.
        dropout: requested occluded fraction.
        seed: the random seed.
        height_m: the performer's height.
        origin_world: (3,) float64, metres: floor point under the pelvis at rest.
    """

    labels: tuple[str, ...]
    markers_world: F64Array
    valid: BoolArray
    rate_hz: float
    times_s: F64Array
    segment_names: tuple[str, ...]
    segment_parents: IntArray
    rest_offsets: F64Array
    joint_pos_world: F64Array
    world_from_segment_quat: F64Array
    parent_from_segment_quat: F64Array
    base_pose_frames: slice
    marker_segments: IntArray
    marker_offsets: F64Array
    markerset: str
    motions: tuple[str, ...]
    noise_mm: float
    dropout: float
    seed: int
    height_m: float
    origin_world: F64Array

    @property
    def n_frames(self) -> int:
        """Number of frames T."""
        return int(self.markers_world.shape[0])

    @property
    def occluded_fraction(self) -> float:
        """Fraction of (frame, marker) samples that are occluded."""
        return float(1.0 - self.valid.mean()) if self.valid.size else 0.0

    def save_truth(self, path: str | Path) -> None:
        """Write everything to an uncompressed NPZ (loads with ``allow_pickle=False``).

        Strings are unicode arrays; ``base_pose_frames`` is stored as
        ``[start, stop]``; scalars as 0-d arrays. :func:`load_truth` reads it back.

        Args:
            path: destination ``.npz`` path.
        """
        arrays: dict[str, Any] = {}
        for name in _TRUTH_FIELDS:
            value = getattr(self, name)
            if isinstance(value, slice):
                value = np.array([value.start, value.stop], dtype=np.int64)
            elif isinstance(value, tuple):
                value = np.array(value, dtype=np.str_)
            arrays[name] = np.asarray(value)
        np.savez(path, **arrays)


_TRUTH_FIELDS = tuple(SynthTake.__dataclass_fields__)


def load_truth(path: str | Path) -> SynthTake:
    """Read a :meth:`SynthTake.save_truth` NPZ back (``allow_pickle=False``).

    Args:
        path: the ``.npz`` file.

    Returns:
        The :class:`SynthTake`, arrays read-only.
    """
    kwargs: dict[str, object] = {}
    with np.load(path, allow_pickle=False) as npz:
        for name in _TRUTH_FIELDS:
            value = npz[name]
            if name == "base_pose_frames":
                kwargs[name] = slice(int(value[0]), int(value[1]))
            elif value.dtype.kind == "U":
                kwargs[name] = str(value) if value.ndim == 0 else tuple(value.tolist())
            elif value.ndim == 0:
                kwargs[name] = value.item()
            else:
                kwargs[name] = readonly(value)
    return SynthTake(**kwargs)  # type: ignore[arg-type]


def _no_faster_than_gravity(z: F64Array, rate_hz: float) -> F64Array:
    """The least height curve >= ``z`` (T,) whose downward acceleration never exceeds
    g (9.81 m/s^2): ballistic flight wherever ``z`` would fall faster."""
    out = np.array(z, dtype=np.float64)
    drop = 9.81 / (rate_hz * rate_hz)
    for i in range(2, out.size):
        out[i] = max(out[i], 2.0 * out[i - 1] - out[i - 2] - drop)
    return out


def _low_pass(x: F64Array, cutoff_hz: float, rate_hz: float) -> F64Array:
    """Zero-phase 2nd-order Butterworth low-pass of ``x`` (T,)."""
    b, a = butter(2, min(cutoff_hz / (0.5 * rate_hz), 0.99))
    pad = min(3 * max(len(a), len(b)), len(x) - 1)
    return np.asarray(filtfilt(b, a, x, padlen=pad))


def _softmin(z: F64Array, temperature: float) -> F64Array:
    """Smooth minimum over the last axis, never above the true minimum."""
    low = z.min(axis=-1, keepdims=True)
    total = np.exp(-(z - low) / temperature).sum(axis=-1)
    return low[..., 0] - temperature * np.log(total)


def _forward_kinematics(
    skeleton: Skeleton, parent_from_segment: F64Array, root_pos: F64Array
) -> tuple[F64Array, F64Array]:
    """World rotations and joint centres, vectorized over frames, level by level."""
    n_frames, n_seg = parent_from_segment.shape[:2]
    world_from_segment = np.empty((n_frames, n_seg, 4))
    joint_pos = np.empty((n_frames, n_seg, 3))
    world_from_segment[:, 0] = parent_from_segment[:, 0]
    joint_pos[:, 0] = root_pos
    for level in skeleton.levels[1:]:
        parents = skeleton.parents[level]
        world_from_parent = world_from_segment[:, parents]
        world_from_segment[:, level] = rot.quat_mul(
            world_from_parent, parent_from_segment[:, level]
        )
        joint_pos[:, level] = joint_pos[:, parents] + rot.quat_rotate(
            world_from_parent, skeleton.rest_offsets[level]
        )
    return world_from_segment, joint_pos


def _dropout_mask(
    rng: np.random.Generator,
    n_frames: int,
    n_markers: int,
    fraction: float,
    mean_frames: float,
) -> BoolArray:
    """Occlusion in runs: an alternating renewal process per marker.

    Occluded runs have geometric lengths of mean ``mean_frames``; visible runs of mean
    ``mean_frames (1 - f) / f``, so the long-run occluded fraction is ``f``. The first
    state is drawn from that stationary split.
    """
    occluded = np.zeros((n_frames, n_markers), dtype=bool)
    if fraction <= 0.0 or n_frames == 0:
        return occluded
    mean_visible = max(mean_frames * (1.0 - fraction) / fraction, 1.0)
    n_pairs = int(np.ceil(n_frames / (mean_frames + mean_visible))) * 2 + 8
    for marker in range(n_markers):
        start_occluded = rng.random() < fraction
        lengths = np.empty(0, dtype=np.int64)
        while lengths.sum() < n_frames:
            occ = rng.geometric(1.0 / mean_frames, size=n_pairs)
            vis = rng.geometric(1.0 / mean_visible, size=n_pairs)
            pair = (occ, vis) if start_occluded else (vis, occ)
            lengths = np.concatenate([lengths, np.stack(pair, axis=1).ravel()])
        states = np.zeros(len(lengths), dtype=bool)
        states[0 if start_occluded else 1 :: 2] = True
        occluded[:, marker] = np.repeat(states, lengths)[:n_frames]
    return occluded


def _check_number(
    name: str,
    value: float,
    *,
    low: float,
    high: float = np.inf,
    low_open: bool = False,
    high_open: bool = False,
) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number; got {value!r}") from None
    ok = np.isfinite(number) and (number > low if low_open else number >= low)
    ok = ok and (number < high if high_open else number <= high)
    if not ok:
        lo, hi = ("(" if low_open else "["), (")" if high_open else "]")
        raise ValueError(f"{name} must be in {lo}{low:g}, {high:g}{hi}; got {value!r}")
    return number


def synthesize(
    *,
    seconds: float,
    rate_hz: float,
    markerset: str | Path | MarkerSet = "menache",
    motions: Sequence[str] = DEFAULT_MOTIONS,
    noise_mm: float = 0.0,
    dropout: float = 0.0,
    dropout_mean_frames: float | None = None,
    seed: int = 0,
    base_pose_s: float = 1.0,
    height_m: float = REFERENCE_HEIGHT_M,
    origin: Sequence[float] = DEFAULT_ORIGIN,
) -> SynthTake:
    """Synthesize a take of the performer wearing a marker set.

    Frame ``i`` is at ``t = i / rate_hz``. Frames with ``t < base_pose_s`` hold the
    exact T-pose; the motion ramps in over :data:`RAMP_S` after that. Noise and
    dropouts are drawn from independent streams of ``seed``, so the same arguments
    give bit-identical output.

    Args:
        seconds: duration (> 0); ``round(seconds * rate_hz)`` frames (at least 1).
        rate_hz: frame rate (> 0).
        markerset: shipped name, TOML path or a loaded :class:`MarkerSet`.
        motions: components from :data:`ALL_MOTIONS` (any subset, any order; empty =
            the T-pose throughout).
        noise_mm: Gaussian noise std per coordinate, millimetres (>= 0).
        dropout: fraction of samples occluded, in [0, 1).
        dropout_mean_frames: mean occlusion run length in frames (>= 1); default
            0.1 s worth of frames.
        seed: random seed for noise and dropouts.
        base_pose_s: length of the static T-pose hold, seconds (>= 0).
        height_m: the performer's height; marker offsets scale with it.
        origin: (3,) metres, world: floor point under the pelvis at rest.

    Returns:
        The :class:`SynthTake` with markers and truth.

    Raises:
        ValueError: naming the bad argument and value.
    """
    seconds = _check_number("seconds", seconds, low=0.0, low_open=True)
    rate_hz = _check_number("rate_hz", rate_hz, low=0.0, low_open=True)
    noise_mm = _check_number("noise_mm", noise_mm, low=0.0)
    dropout = _check_number("dropout", dropout, low=0.0, high=1.0, high_open=True)
    base_pose_s = _check_number("base_pose_s", base_pose_s, low=0.0)
    height_m = _check_number("height_m", height_m, low=0.0, low_open=True)
    if dropout_mean_frames is None:
        dropout_mean_frames = max(0.1 * rate_hz, 1.0)
    dropout_mean_frames = _check_number(
        "dropout_mean_frames", dropout_mean_frames, low=1.0
    )
    motions = tuple(motions)
    unknown = [m for m in motions if m not in _COMPONENTS]
    if unknown or len(set(motions)) != len(motions):
        raise ValueError(
            f"motions must be distinct names from {', '.join(ALL_MOTIONS)}; "
            f"got {', '.join(motions) or '(none)'}"
        )
    origin_world = np.asarray(origin, dtype=np.float64)
    if origin_world.shape != (3,) or not np.all(np.isfinite(origin_world)):
        raise ValueError(f"origin must be 3 finite numbers (metres); got {origin!r}")
    if not isinstance(markerset, MarkerSet):
        markerset = load_markerset(markerset)
    skeleton = make_skeleton(height_m)
    n_frames = max(round(seconds * rate_hz), 1)
    n_seg = len(skeleton.names)
    times = np.arange(n_frames) / rate_hz
    t_motion = times - base_pose_s
    work = _Motion(
        skeleton=skeleton,
        t=t_motion,
        w=_smootherstep(t_motion / RAMP_S),
        angles=np.zeros((n_frames, n_seg, 3)),
        root_pos=np.tile(origin_world + skeleton.rest_pos[0], (n_frames, 1)),
        heading=np.zeros(n_frames),
        motions=motions,
    )
    for name in ALL_MOTIONS:  # fixed composition order, whatever order was asked
        if name in motions:
            _COMPONENTS[name](work)

    parent_from_segment = np.empty((n_frames, n_seg, 4))
    orders = np.array(skeleton.euler_orders)
    for order in sorted(set(skeleton.euler_orders)):
        idx = np.flatnonzero(orders == order)
        columns = ["xyz".index(c) for c in order.lower()]
        parent_from_segment[:, idx] = rot.quat_from_euler(
            work.angles[:, idx][..., columns], order
        )
    heading_quat = rot.quat_from_axis_angle(np.array([0.0, 0.0, 1.0]), work.heading)
    parent_from_segment[:, 0] = rot.quat_mul(heading_quat, parent_from_segment[:, 0])
    world_from_segment, joint_pos = _forward_kinematics(
        skeleton, parent_from_segment, work.root_pos
    )
    if work.walk_weight.size:
        # Vertical bob: keep the lowest sole point on the floor (soft minimum, so the
        # root height stays smooth); zero correction while the ramp weight is 0.
        seg = skeleton.sole_segments
        sole_z = (
            joint_pos[:, seg, 2]
            + rot.quat_rotate(world_from_segment[:, seg], skeleton.sole_points)[..., 2]
        )
        rest_z = origin_world[2] + (skeleton.rest_pos[seg] + skeleton.sole_points)[:, 2]
        lift = _softmin(rest_z, _FLOOR_SOFTMIN_M) - _softmin(sole_z, _FLOOR_SOFTMIN_M)
        joint_pos[..., 2] += (work.walk_weight * lift)[:, None]
    if work.floor_weight.size:
        # Activities: the same floor contact, then planted feet, then flight.
        seg = skeleton.sole_segments
        sole_z = (
            joint_pos[:, seg, 2]
            + rot.quat_rotate(world_from_segment[:, seg], skeleton.sole_points)[..., 2]
        )
        rest_z = origin_world[2] + (skeleton.rest_pos[seg] + skeleton.sole_points)[:, 2]
        lift = _softmin(rest_z, _FLOOR_SOFTMIN_M) - _softmin(sole_z, _FLOOR_SOFTMIN_M)
        if work.floor_smooth_hz > 0.0 and n_frames > 12:
            lift = _low_pass(lift, work.floor_smooth_hz, rate_hz)
        if work.ballistic:
            lift = _no_faster_than_gravity(lift, rate_hz)
        if work.flight_m.size:
            # In flight the body is ballistic: the lift stays what it was at take-off.
            air = np.flatnonzero(work.flight_m > 0.0)
            if air.size:
                starts = air[np.r_[True, np.diff(air) > 1]]
                run_id = np.cumsum(np.r_[True, np.diff(air) > 1]) - 1
                lift[air] = lift[np.maximum(starts - 1, 0)][run_id]
        joint_pos[..., 2] += (work.floor_weight * lift)[:, None]
    if work.plant:
        planted = [skeleton.index(s) for s in work.plant]
        drift = joint_pos[:, planted, :2].mean(axis=1) - joint_pos[
            :1, planted, :2
        ].mean(axis=1)
        joint_pos[..., :2] -= (work.plant_weight[:, None] * drift)[:, None, :]
    if work.flight_m.size:
        joint_pos[..., 2] += work.flight_m[:, None]

    marker_segments = np.array(
        [skeleton.index(s) for s in markerset.segments], dtype=np.int64
    )
    marker_offsets = markerset.offsets_mm * (MM_TO_M * height_m / REFERENCE_HEIGHT_M)
    markers = joint_pos[:, marker_segments] + rot.quat_rotate(
        world_from_segment[:, marker_segments], marker_offsets
    )
    noise_rng, dropout_rng = (
        np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(2)
    )
    n_markers = len(markerset.labels)
    if noise_mm > 0.0:
        markers += noise_rng.normal(0.0, noise_mm * MM_TO_M, size=markers.shape)
    occluded = _dropout_mask(
        dropout_rng, n_frames, n_markers, dropout, dropout_mean_frames
    )
    markers[occluded] = np.nan
    n_hold = int(np.count_nonzero(times < base_pose_s)) if base_pose_s > 0 else 0
    return SynthTake(
        labels=markerset.labels,
        markers_world=readonly(markers),
        valid=readonly(~occluded),
        rate_hz=rate_hz,
        times_s=readonly(times),
        segment_names=skeleton.names,
        segment_parents=skeleton.parents,
        rest_offsets=skeleton.rest_offsets,
        joint_pos_world=readonly(joint_pos),
        world_from_segment_quat=readonly(world_from_segment),
        parent_from_segment_quat=readonly(parent_from_segment),
        base_pose_frames=slice(0, n_hold),
        marker_segments=readonly(marker_segments),
        marker_offsets=readonly(marker_offsets),
        markerset=markerset.name,
        motions=tuple(m for m in ALL_MOTIONS if m in motions),
        noise_mm=noise_mm,
        dropout=dropout,
        seed=int(seed),
        height_m=height_m,
        origin_world=readonly(origin_world.copy()),
    )
