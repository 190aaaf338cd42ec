"""The synthetic performer's motion: each named component adds joint angles (and root
motion) that are smooth functions of time, weighted by a ramp that is exactly 0 during
the base-pose hold; :mod:`retargetd.daemon.synth.performer` composes them, poses the
skeleton and places the markers (its docstring describes the motion as a whole).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.interpolate import CubicSpline

from retargetd.daemon.synth.gait import GaitPlan
from retargetd.daemon.synth.skeleton import Skeleton
from retargetd.protocols.frames import F64Array

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
    "level_walk",
    "stair_ascent",
    "stair_descent",
    "run",
    "jump",
    "deep_squat",
    "kick",
)
#: The activities that are gaits placed from their stance feet (``synth.gait``): their
#: truth's ``foot_contact`` is each foot's stance.
GAIT_MOTIONS: tuple[str, ...] = ("level_walk", "run", "stair_ascent", "stair_descent")
#: A range-of-motion take for a functional calibration (``calibrate --rom``), meant to
#: be synthesized alone: :func:`_rom`.
CALIBRATION_MOTIONS: tuple[str, ...] = ("rom",)
#: Every motion component, in composition order.
ALL_MOTIONS: tuple[str, ...] = DEFAULT_MOTIONS + ACTIVITY_MOTIONS + CALIBRATION_MOTIONS
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
FLOOR_SOFTMIN_M = 0.003
_X, _Y, _Z = 0, 1, 2

# --- motion ----------------------------------------------------------------------


def smootherstep(u: F64Array) -> F64Array:
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
class Motion:
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
    # Gaits whose stance feet stay put (synth.gait): the root is placed from them.
    gait: GaitPlan | None = None

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


def _walk(m: Motion) -> None:
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


def _arm_raise(m: Motion) -> None:
    w = m.w
    s2, s3, s5 = np.sqrt(2.0), np.sqrt(3.0), np.sqrt(5.0)
    # Elevation from the T-pose (+ = up), the right arm at another frequency and
    # starting downward. The amplitudes keep the performer's own segments apart in
    # every combination the irrational frequencies reach (its truth validates
    # without self-penetration over a minute: tests/daemon/test_validate_activities):
    # with 75 deg up the bent left forearm met the head; with 70 deg down and 30 deg
    # forward the right forearm and hand met the thigh and the pelvis.
    elev_l = 60.0 * np.sin(2.0 * np.pi * 0.19 * m.t)
    elev_r = -45.0 * np.sin(2.0 * np.pi * 0.19 * s2 / 1.2 * m.t)
    horiz_l = 35.0 * np.sin(2.0 * np.pi * 0.11 * s3 * m.t)  # + = forward
    horiz_r = 20.0 * np.sin(2.0 * np.pi * 0.11 * s5 / 1.5 * m.t)
    flex_l = 30.0 * np.sin(2.0 * np.pi * 0.13 * s5 / 2.0 * m.t)  # + = forward
    flex_r = -30.0 * np.sin(2.0 * np.pi * 0.13 * s3 / 1.5 * m.t)
    m.add_bilateral("upper_arm", _X, w * elev_l, w * elev_r)  # elevation: up = +x
    m.add_bilateral("upper_arm", _Z, -w * horiz_l, -w * horiz_r)  # forward = -z
    m.add_bilateral("upper_arm", _Y, -w * flex_l, -w * flex_r)  # flexion: fwd = -y
    # The shoulder girdle follows: clavicle elevation and protraction.
    m.add_bilateral("clavicle", _X, w * 0.2 * elev_l, w * 0.2 * elev_r)
    m.add_bilateral("clavicle", _Z, -w * 0.2 * horiz_l, -w * 0.2 * horiz_r)


def _forearm_twist(m: Motion) -> None:
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


def _spine(m: Motion) -> None:
    w = m.w
    s2, s3, s5 = np.sqrt(2.0), np.sqrt(3.0), np.sqrt(5.0)
    flexion = 18.0 - 18.0 * np.cos(2.0 * np.pi * 0.09 * s2 * m.t)  # 0..36 deg forward
    lateral = 15.0 * m.osc(0.07 * s3)  # + = bend to the left
    twist = 25.0 * m.osc(0.06 * s5)  # + = face turns left
    for segment, share in (("abdomen", 0.4), ("thorax", 0.6)):
        m.add(segment, _Y, w * share * flexion)
        m.add(segment, _X, -w * share * lateral)
        m.add(segment, _Z, w * share * twist)


def _head_turn(m: Motion) -> None:
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


def _cycle(m: Motion, period_s: float) -> F64Array:
    """0 -> 1 -> 0 over each ``period_s`` after the hold (raised cosine), weighted."""
    return m.w * 0.5 * (1.0 - np.cos(2.0 * np.pi * np.maximum(m.t, 0.0) / period_s))


def _legs(m: Motion, side: str, hip: F64Array, knee: F64Array, ankle: F64Array) -> None:
    """Hip flexion, knee flexion, ankle dorsiflexion (deg, weighted) of one leg."""
    m.add(f"{side}_thigh", _Y, -hip)
    m.add(f"{side}_shank", _Y, knee)
    m.add(f"{side}_foot", _Y, -ankle)


def _arms_down(m: Motion, forward_deg: F64Array | float = 0.0) -> None:
    """Arms from the T-pose to hanging (72 deg down), raised forward by
    ``forward_deg`` (already weighted; for balance), unless another component drives
    them."""
    if "arm_raise" not in m.motions:
        m.add_bilateral("upper_arm", _X, -m.w * 72.0, -m.w * 72.0)
        fwd = forward_deg * np.ones_like(m.w)
        m.add_bilateral("upper_arm", _Z, -fwd, -fwd)


def _deep_squat(m: Motion) -> None:
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


def _kick(m: Motion) -> None:
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


def _jump(m: Motion) -> None:
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


#: A gait's anterior pelvic tilt, degrees: ~10 through the walking cycle (Perry &
#: Burnfield 2010, Gait Analysis, 2nd ed., ch. 8; hip angles are the thigh's on the
#: pelvis, so the thigh's angle to the vertical is the hip's less this).
PELVIS_TILT_DEG = 10.0

#: A joint's angle through a gait cycle: (percent of the cycle from heel strike,
#: degrees) key points, joined by a periodic cubic spline.
Profile = tuple[tuple[float, float], ...]


def _profile(points: Profile, phase: F64Array) -> F64Array:
    """The periodic cubic spline through ``points`` at ``phase`` (radians)."""
    pct = np.array([p for p, _ in points] + [points[0][0] + 100.0])
    deg = np.array([d for _, d in points] + [points[0][1]])
    spline = CubicSpline(pct, deg, bc_type="periodic")
    return np.asarray(spline(pct[0] + np.mod(100.0 * phase / (2.0 * np.pi) - pct[0],
                                             100.0)))  # fmt: skip


def _gait(
    m: Motion,
    *,
    cadence_hz: float,
    hip: Profile,
    knee: Profile,
    ankle: Profile,
    trunk_deg: float,
    toe_off: float,
    start_toe_off: float | None = None,
    start_lag: float = 0.0,
    lag_close_s: float = 1.0,
    pelvis_tilt_deg: float = PELVIS_TILT_DEG,
    rise_m: float = 0.0,
    ramp_s: float = RAMP_S,
    flight: bool = False,
    toes_flat: bool = True,
) -> None:
    """A straight gait along +x: sagittal hip flexion, knee flexion and ankle
    dorsiflexion profiles (degrees against the percent of the cycle), ``cadence_hz``
    strides a second once the ramp is over (the phase speeds up with the angles over
    ``ramp_s``). The body is placed from the stance feet
    (:func:`synth.gait.plant_gait`): the feet do not slide, and the speed and stride
    length are the legs' own. The left starts ``start_lag`` of a cycle behind its
    steady half-cycle lead on the right and makes it up over ``lag_close_s``."""
    t0 = np.maximum(m.t, 0.0)
    # The right starts in mid-stance (30 % of its cycle), the left in mid-swing: the
    # first step is the left's, from standing.
    phase = (
        2.0 * np.pi * (0.3 + cadence_hz * ramp_s * _smootherstep_integral(t0 / ramp_s))
    )
    w = smootherstep(m.t / ramp_s)  # the angles grow with the cadence
    lag = start_lag * (1.0 - smootherstep(m.t / lag_close_s))
    left = phase + np.pi - 2.0 * np.pi * lag
    for side_phase, side in ((left, "l"), (phase, "r")):
        _legs(m, side, w * _profile(hip, side_phase), w * _profile(knee, side_phase),
              w * _profile(ankle, side_phase))  # fmt: skip
    # The pelvis tilts forward (hip angles are the thigh's on the pelvis), the trunk
    # above it comes back up to lean ``trunk_deg``.
    m.add("pelvis", _Y, w * pelvis_tilt_deg)
    m.add("abdomen", _Y, w * (trunk_deg - pelvis_tilt_deg))
    _arms_down(m)
    m.add_bilateral(
        "upper_arm", _Y, w * 25.0 * np.cos(phase), -w * 25.0 * np.cos(phase)
    )
    m.add_bilateral("forearm", _Z, -w * 60.0, -w * 60.0)
    # A gait that starts with longer stances (``start_toe_off``) shortens them with
    # the angles and the cadence: the stance's share of the cycle falls as the
    # speed rises (Novacheck 1998: toe-off at 62 % walking, 39 % running at 3.2 m/s,
    # 36 % sprinting), so a run gets up to speed from a walk's double support and
    # its flight grows with its speed.
    toe = (
        toe_off
        if start_toe_off is None
        else start_toe_off + w * (toe_off - start_toe_off)
    )
    m.gait = GaitPlan(
        phase=np.stack([left, phase], axis=1),
        toe_off=toe,
        rise_m=rise_m,
        flight=flight,
        moving=m.t > 0.0,
        toes_flat=toes_flat,
    )


#: Walking toe-off, fraction of the cycle (Winter 2009, normative gait: ~60 %).
WALK_TOE_OFF = 0.60
#: Stair toe-off (McFadyen & Winter 1988, J Biomech 21:733-744: stance ~64 % of the
#: stair cycle, up and down).
STAIR_TOE_OFF = 0.64
#: The stairs' riser, metres: a common domestic rise (the stance detector's stair
#: test climbs 0.17 m risers too).
STAIR_RISER_M = 0.17


def _level_walk(m: Motion) -> None:
    """A straight level walk at a natural cadence (~54 strides a minute), the
    sagittal angles' key points read off the normative curves (Winter 2009,
    Biomechanics and Motor Control of Human Movement, 4th ed., app. A; Perry &
    Burnfield 2010, ch. 5-8): hip flexion 30 at heel strike to extension 10 at 50 %,
    33 in terminal swing; knee 18 in loading, 38 at toe-off, 62 in swing; ankle
    plantarflexion 6 at foot flat, dorsiflexion 10 at 45 %, plantarflexion 18 at
    toe-off; pelvis tilted 10 forward, trunk 3."""
    _gait(
        m,
        cadence_hz=0.9,
        hip=((0, 30), (10, 28), (30, 10), (50, -10), (60, -2), (73, 20), (87, 33)),
        knee=((0, 3), (15, 18), (40, 4), (60, 38), (73, 62), (87, 25), (97, 3)),
        ankle=((0, 0), (7, -6), (45, 10), (62, -18), (75, -4), (87, 1)),
        trunk_deg=3.0,
        toe_off=WALK_TOE_OFF,
    )


def _stair_ascent(m: Motion) -> None:
    """Stair ascent, step over step on 0.17 m risers (McFadyen & Winter 1988;
    Protopapadaki et al. 2007, Clin Biomech 22:203-210), key points read off their
    curves: hip flexion 60 at foot contact, 5 late in stance, 65 in swing; knee 60 at
    contact, 10 at 50 %, 95 in swing; ankle dorsiflexion 20 early in stance,
    plantarflexion 15 at push-off; trunk forward 10; 0.55 strides a second.

    The foot reaches the tread forefoot first (Riener et al. 2002, Gait Posture
    15:32-44: in every subject, at every inclination, up and down) and is flat on it
    in mid-stance (McFadyen & Winter 1988): at contact the ankle is dorsiflexed 5,
    less than the shank's forward lean there (hip 60 less the pelvis's 10 tilt, knee
    60: 10), so the sole is pitched 5 toes down and ``synth.gait`` holds the foot
    flat from contact to heel-off. (The value is not read off a curve: any contact
    dorsiflexion under the lean lands the forefoot first. At 10, the lean itself,
    the foot landed flat to within 0.2 deg toes up, the flat-foot rule never started,
    and the dorsiflexion to 20 stood the foot on its heel, 10 deg toes up at
    mid-stance on 7 of 8 step contacts, its TOE marker 32 mm above its flat height.)"""
    _gait(
        m,
        cadence_hz=0.55,
        hip=((0, 60), (20, 45), (50, 5), (64, 10), (80, 55), (92, 65)),
        knee=((0, 60), (20, 45), (50, 10), (64, 35), (78, 95), (92, 75)),
        ankle=((0, 5), (15, 20), (45, 5), (64, -15), (78, 10), (92, 15)),
        trunk_deg=10.0,
        toe_off=STAIR_TOE_OFF,
        rise_m=STAIR_RISER_M,
    )


def _stair_descent(m: Motion) -> None:
    """Stair descent, step over step on 0.17 m risers (McFadyen & Winter 1988), key
    points read off their curves: contact on the forefoot (plantarflexion 25), the
    ankle dorsiflexing (54 in the profile; 40-45 reported, and the held foot's
    inverse kinematics and the solve take some of it back: the solved peak is then
    the 40 ``tests/daemon/test_validate_activities.py`` asks) and the knee flexing
    to 90 as the stance leg lowers the body, knee 100 in swing, plantarflexion 30
    reaching for the step below; hip 10-35; trunk forward 5; 0.55 strides a
    second. The stance foot rolls onto the tips of its toes (no toe extension)."""
    _gait(
        m,
        cadence_hz=0.55,
        hip=((0, 10), (30, 8), (60, 25), (75, 35), (90, 20)),
        knee=((0, 10), (20, 20), (45, 45), (64, 90), (75, 100), (90, 40)),
        ankle=((0, -25), (15, 5), (50, 44), (64, 54), (78, 10), (95, -30)),
        trunk_deg=5.0,
        toe_off=STAIR_TOE_OFF,
        rise_m=-STAIR_RISER_M,
        toes_flat=False,
    )


#: Running toe-off, fraction of the cycle: 39 % at 3.2 m/s (Novacheck 1998, Gait
#: Posture 7:77-95; 36 % sprinting, 62 % walking), so each step has a flight of
#: (50 - 39) % of the cycle.
RUN_TOE_OFF = 0.39
#: Running strides a second: 1.4, a 0.71 s cycle (distance runners near 3-3.5 m/s
#: take about 1.4 strides a second: Cavanagh & Kram 1989, Med Sci Sports Exerc
#: 21:467-479), so a stance lasts 0.28 s (contact times of ~0.2-0.3 s in distance
#: running: Cavanagh & Lafortune 1980, J Biomech 13:397-406).
RUN_CADENCE_HZ = 1.4
#: The run gets up to speed (its cadence and angles) over this, seconds.
RUN_RAMP_S = 2.0
#: From standing both legs are in mid-stance (30 % of the cycle, the right's start):
#: the run's left starts half a cycle behind its steady lead on the right and makes
#: it up over :data:`RUN_LAG_CLOSE_S`, so it stays down while the body is set moving,
#: then swings a whole swing phase. Gait initiation keeps both feet down while the
#: body is set moving, then lifts the swing foot, heel first (Yiou et al. 2017, World
#: J Orthop 8:815-828, a review: anticipatory postural adjustments, then the swing
#: foot's heel-off and toe-off), and reaches the steady pattern over about three steps
#: (Mann et al. 1979, J Bone Joint Surg Am 61:232-239; here the ramp ends after the
#: third strike). Started half a cycle ahead (at 80 %, in its swing), the left let go
#: of the floor at the ramp's first frame, its phase barely moving: its first swing
#: (the last 20 % of a cycle, the cadence near 0) took 116 frames at 120 Hz, and the
#: stance detector held the foot through 86 of them (legs 1x). Now it stays down 61
#: frames (0.51 s), then swings 56 (steady: 52); the detector lets it go 6 frames
#: after the truth (but holds 7 frames of that swing, where the foot is still slow:
#: docs/feet.md).
RUN_START_LAG = 0.5
#: ... by the end of the first step: steady gait's velocity is reached there (Brenière
#: & Do 1986, J Biomech 19:1035-1040), and here the left's first strike comes 0.98 s
#: into the ramp, where the right's stance ends. Made up over the whole ramp (2 s),
#: the left struck 25 frames after the right's toe-off: a first flight of 25 frames
#: (9 at speed) that raised the pelvis 6 cm; over 0.7 s it let go 45 frames into the
#: ramp and swung 72 frames, slowly.
RUN_LAG_CLOSE_S = 1.0


def _run(m: Motion) -> None:
    """Running, straight, rearfoot strike, placed from its stance feet with a flight
    phase (``synth.gait``: the driver lets go at toe-off, the pelvis flies a
    ballistic path to the other foot's heel strike). Sagittal key points after
    Novacheck 1998 (running at 3.2 m/s; Dugan & Bhat 2005, Phys Med Rehabil Clin N
    Am 16:603-621): hip flexion 38 at initial contact, extending to 8 of extension
    at toe-off (39 %), 58 in late swing; knee 18 at contact, 44 at mid-stance
    (20 %), 22 at toe-off, 120 in swing (swing knee flexion 105-130, rising with
    speed: the figure ``test_validate_activities`` holds the run to); ankle neutral
    at contact (the foot lands heel first, 7-13 deg toes up), plantarflexion 22 at
    toe-off, ~10 dorsiflexion in swing; trunk forward 10; 1.4 strides a second, up
    to speed over 2 s (about 3.0 m/s follows from the legs).

    The stance ankle is the foot-flat constraint, not a curve read off: between
    contact and heel-off the rigid foot is flat on the floor only while the ankle's
    dorsiflexion equals the shank's forward lean (knee flexion less the thigh's
    forward angle, hip flexion less the pelvis's tilt), so the ankle key points at
    8, 15 and 22 % (3, 19, 28 deg) are the lean the hip and knee make there (28 deg
    at mid-stance, a little past the ~20-25 peak reported: the lean of this hip and
    knee). Read off the curves instead (dorsiflexion peaking 22 at 18 % with hip 25
    at 15 %), the foot stood on its toe tip from 5 % to toe-off, its heel 50-64 mm
    up, rocking heel -> tip within 4 frames of contact, and the pelvis's speed swung
    2.4-3.7 m/s within a stance (ghost force 1.02 body weights, past validation's
    0.75); the run's former profiles (hip 25 + 35 cos, knee and ankle bumps, its
    feet sliding), placed so, swung it 0.8-5.7 m/s (2.6 body weights)."""
    _gait(
        m,
        cadence_hz=RUN_CADENCE_HZ,
        hip=((0, 38), (20, 26), (39, -8), (55, 10), (85, 58)),
        knee=((0, 18), (20, 44), (39, 22), (72, 120), (90, 40)),
        ankle=((0, 0), (8, 3), (15, 19), (22, 28), (39, -22), (70, 10), (92, 5)),
        trunk_deg=10.0,
        toe_off=RUN_TOE_OFF,
        # From standing: walking's stance fraction, down to running's with the
        # ramp (a flight only past half the cycle, w > 0.48). With the running
        # fraction from the start, the first flight (the cadence still low) lasted
        # 25 frames against 9-10 at speed and raised the pelvis 7 cm.
        start_toe_off=WALK_TOE_OFF,
        start_lag=RUN_START_LAG,
        lag_close_s=RUN_LAG_CLOSE_S,
        ramp_s=RUN_RAMP_S,
        flight=True,
    )


#: The range of motion: each leg moves for half of this, the other standing.
ROM_PERIOD_S = 12.0


def _rom(m: Motion) -> None:
    """A range of motion as done on a stage before a take, for the functional joints
    (Camomilla et al. 2006, J Biomech 39:1096, the "star arc"; Vicon's ROM): each leg
    in turn, standing on the other, circles the hip (flexion -10..50 deg with
    abduction 0..30, two circles) while the knee flexes 0..90 three times; both
    elbows flex 10..110 with the forearm turned +-40 deg and both shoulders sweep
    elevation +-50 and horizontal +-35 deg, the right out of phase with the left.
    The standing sole stays on the floor; nothing is planted (the pelvis stays
    where it stood)."""
    t = np.maximum(m.t, 0.0)
    half = ROM_PERIOD_S / 2.0
    tau = t % ROM_PERIOD_S
    for side, start in (("l", 0.0), ("r", half)):
        u = np.clip((tau - start) / half, 0.0, 1.0)  # 0..1 through this leg's turn
        on = m.w * np.sin(np.pi * u) ** 2  # eases in and out of each turn
        circle = 2.0 * np.pi * 2.0 * u  # two hip circles
        flex = 20.0 - 30.0 * np.cos(circle)
        abd = 15.0 - 15.0 * np.cos(circle + 0.5 * np.pi)
        knee = 45.0 - 45.0 * np.cos(2.0 * np.pi * 3.0 * u)  # fullest mid-turn
        sign = 1.0 if side == "l" else -1.0  # mirror x for the right side
        m.add(f"{side}_thigh", _Y, -on * flex)
        m.add(f"{side}_thigh", _X, sign * on * abd)  # abduction: knee outward
        m.add(f"{side}_shank", _Y, on * knee)
    elbow_l = 60.0 - 50.0 * np.cos(2.0 * np.pi * 0.25 * t)
    elbow_r = 60.0 - 50.0 * np.cos(2.0 * np.pi * 0.25 * t + np.pi)
    m.add_bilateral("forearm", _Z, -m.w * elbow_l, -m.w * elbow_r)
    twist = 40.0 * np.sin(2.0 * np.pi * 0.15 * t)
    m.add_bilateral("forearm", _Y, m.w * twist, -m.w * twist)
    elev = 50.0 * np.sin(2.0 * np.pi * 0.1 * t)
    horiz = 35.0 * np.sin(2.0 * np.pi * 0.07 * t)
    m.add_bilateral("upper_arm", _X, m.w * elev, -m.w * elev)  # elevation: up = +x
    m.add_bilateral("upper_arm", _Z, -m.w * horiz, m.w * horiz)  # forward = -z
    m.floor_weight = m.w


COMPONENTS: dict[str, Callable[[Motion], None]] = {
    "walk": _walk,
    "level_walk": _level_walk,
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
    "rom": _rom,
}
