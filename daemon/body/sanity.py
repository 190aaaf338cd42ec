"""Sanity checks on a base pose and its calibration, run before any solve.

A take whose length unit or up axis is declared wrong, or a "base pose" taken while
the performer walks, calibrates without an error and gives a skeleton that is garbage
(bone lengths of 0 mm, a performer lying on the floor, left and right arms 30 %
apart). These checks catch that from the base pose alone:

- :func:`check_units`: the markers' vertical extent (before calibration) and the
  stature the calibrated long bones imply (after) against the range of adult human
  stature;
- :func:`check_up_axis`: the head must be above the feet along the declared up axis;
- :func:`base_pose_motion` / :func:`check_base_pose_still`: marker speeds over the
  calibration frames against quiet-standing postural sway (the live calibrate can
  call these on its buffered frames);
- :func:`check_mirrored`: the markers the rig calls left on the performer's left
  (forward from the toes ahead of the ankles and the pelvis' front ahead of its back);
- :func:`check_bilateral`: left and right calibrated bones within 10 %.

:func:`calibrate_checked` runs them all around the calibration: the offline
``calibrate`` (and ``--calibrate-frames``) and the live ``ctl calibrate`` share it.

Each returns the warnings (one line each) and raises :class:`SanityError` (one line
naming the override) where the result would be garbage. Positions are (F, M, 3)
float64 metres in the internal world (+Z up), NaN where occluded.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from retargetd.daemon.body.calibration import (
    Calibration,
    calibrate,
    compute_points,
    match_markers,
)
from retargetd.daemon.body.rig import Rig
from retargetd.daemon.body.rig_model import RigidPoint
from retargetd.protocols.conventions import UNIT_TO_METRES, normalize_units
from retargetd.protocols.frames import F64Array

#: Plausible standing height of a performer, metres. Adult mean heights by country
#: span about 1.50-1.83 m (NCD Risk Factor Collaboration, "A century of trends in
#: adult human height", eLife 2016;5:e13410; Roser, Appel & Ritchie, "Human Height",
#: Our World in Data, 2013/2019), with the spread within a population near 7 cm SD;
#: 1.0 m (a child of about 4, WHO growth standards) to 2.3 m (beyond the tallest
#: few per million) brackets every performer a studio will see.
STATURE_RANGE_M = (1.0, 2.3)

#: A unit confusion changes lengths by at least a factor of 2.54 (inch vs cm), usually
#: 10 or 1000; a stature more than a factor of 2 outside :data:`STATURE_RANGE_M` is
#: therefore a wrong unit, not an unusual person: refused (exit 2).
UNITS_GARBAGE_FACTOR = 2.0

#: Long-bone lengths as fractions of stature H (Drillis & Contini 1966, as tabulated in
#: Winter, "Biomechanics and Motor Control of Human Movement", 4th ed. 2009, Fig. 4.1):
#: thigh (hip to knee joint) 0.245 H, leg (knee to ankle) 0.246 H, upper arm (shoulder
#: to elbow) 0.186 H, forearm (elbow to wrist) 0.146 H. Keyed by the humanoid bone
#: name without its side.
LONG_BONE_FRACTION_OF_STATURE = {
    "UpperLeg": 0.245,
    "LowerLeg": 0.246,
    "UpperArm": 0.186,
    "LowerArm": 0.146,
}

#: Marker speed above which the base pose is not "held": quiet standing sways the
#: centre of pressure at a mean 8-15 mm/s in healthy adults (Prieto et al., IEEE Trans
#: Biomed Eng 1996;43(9):956-966, mean velocity 11 mm/s eyes open; Lin et al., Gait &
#: Posture 2008;28(2):337-342), the head at a few times that (inverted-pendulum
#: lever: Winter et al., J Neurophysiol 1998;80:1211-1221). 0.10 m/s is several times
#: any quiet-stance sway and a tenth of the slowest comfortable walking speed
#: (1.0-1.4 m/s, Bohannon, Age Ageing 1997;26:15-19), so a walk or an arm swing
#: exceeds it and standing still never does.
STILL_SPEED_LIMIT_M_S = 0.10

#: Marker speeds are displacements over this lag, not frame to frame: optical marker
#: noise of ~0.5 mm RMS (Merriaux et al., Sensors 2017;17:1591, Vicon residuals
#: under 1 mm) over 1/120 s would read as 85 mm/s of "motion"; over 0.1 s it is
#: 7 mm/s, well under :data:`STILL_SPEED_LIMIT_M_S`.
STILL_LAG_S = 0.1

#: The largest displacement marker noise alone gives a still marker between two
#: samples: optical noise of 0.5 mm RMS per coordinate (Merriaux et al., Sensors
#: 2017;17:1591: Vicon residuals under 1 mm) makes the difference of two samples
#: 0.71 mm RMS per coordinate, and its 3-D length (a chi distribution with 3 degrees of
#: freedom) exceeds 4 mm = 5.7 sigma with probability 5e-7 per marker. A window
#: shorter than :data:`STILL_LAG_S` is judged over the lag it has (its whole length),
#: with the speed limit raised to this over that lag when that is the larger: 2
#: frames at 100 Hz allow 0.4 m/s, still under the slowest walk's 1.0 m/s
#: (:data:`STILL_SPEED_LIMIT_M_S`); from 0.04 s on the limit is unchanged.
STILL_NOISE_M = 0.004

#: Left/right difference in a calibrated bone's length (relative to the mean of the
#: two) above which a warning names the bones. Healthy adults' bilateral long-bone
#: asymmetry is 1-3 % (humerus up to ~3 %, femur and tibia under 1-2 %: Auerbach &
#: Ruff, Am J Phys Anthropol 2006;131(1):118-130); anatomic leg-length differences
#: average ~5 mm (Knutson, Chiropr Osteopat 2005;13:11). 10 % is beyond anatomy:
#: a marker moved, swapped or mislabelled, or a base pose that was not held.
BILATERAL_LIMIT = 0.10

#: The head above the feet: the angle between the declared up axis and the feet->head
#: direction of the base pose above which the up axis is wrong. A person standing (or
#: leaning in a T-pose) is within ~15 deg of vertical; a wrong axis is 90 or 180 deg.
UP_ANGLE_LIMIT_DEG = 45.0


class SanityError(ValueError):
    """A base pose whose calibration would be garbage; the message names the
    override (one line)."""


@dataclass(frozen=True, slots=True)
class BasePoseMotion:
    """How much the markers moved over the calibration frames.

    Attributes:
        speed_m_s: the fastest marker's median speed over the frames, m/s (NaN when
            nothing can be told: fewer than 2 frames, no frame rate, no marker seen
            in two frames).
        marker: that marker's label ("" when NaN).
        lag_frames: frames between the two positions of each displacement.
        limit_m_s: the speed above which the pose is not still:
            :data:`STILL_SPEED_LIMIT_M_S`, or :data:`STILL_NOISE_M` over the lag
            when a short window makes that larger.
    """

    speed_m_s: float
    marker: str
    lag_frames: int
    limit_m_s: float = STILL_SPEED_LIMIT_M_S

    @property
    def still(self) -> bool:
        """Below :attr:`limit_m_s` (or nothing to tell)."""
        return not self.speed_m_s > self.limit_m_s


def base_pose_motion(
    positions: F64Array, labels: Sequence[str], rate_hz: float
) -> BasePoseMotion:
    """Median marker speeds over base-pose frames (see :data:`STILL_LAG_S`).

    Args:
        positions: (F, M, 3) float64, metres, world; NaN rows = occluded.
        labels: (M,) marker labels.
        rate_hz: frame rate, Hz.

    Returns:
        The fastest marker's median speed (per marker, the median over frames of its
        displacement over :data:`STILL_LAG_S`, or over the whole window when it is
        shorter, divided by the lag). Any window of 2 frames or more is judged.
    """
    pos = np.asarray(positions, dtype=np.float64)
    lag = max(1, round(STILL_LAG_S * rate_hz)) if rate_hz > 0 else 1
    if pos.ndim != 3 or pos.shape[0] < 2 or not rate_hz > 0:
        return BasePoseMotion(math.nan, "", lag)
    lag = min(lag, pos.shape[0] - 1)  # a short window: its whole length
    limit = max(STILL_SPEED_LIMIT_M_S, STILL_NOISE_M * rate_hz / lag)
    step = np.linalg.norm(pos[lag:] - pos[:-lag], axis=-1)  # (F - lag, M)
    finite = np.isfinite(step)
    if not finite.any():
        return BasePoseMotion(math.nan, "", lag, limit)
    step = np.where(finite, step, np.nan)
    seen = finite.any(axis=0)
    med = np.full(step.shape[1], -1.0)
    med[seen] = np.nanmedian(step[:, seen], axis=0) * rate_hz / lag
    m = int(np.argmax(med))
    return BasePoseMotion(float(med[m]), labels[m], lag, limit)


def check_base_pose_still(
    positions: F64Array,
    labels: Sequence[str],
    rate_hz: float,
    *,
    allow_moving: bool = False,
    override: str = "--allow-moving-base-pose",
) -> list[str]:
    """Refuse a base pose the performer did not hold.

    Args:
        positions: (F, M, 3) float64, metres, world; NaN rows = occluded.
        labels: (M,) marker labels.
        rate_hz: frame rate, Hz.
        allow_moving: warn instead of refusing.
        override: the option or command that allows it, named in the message.

    Returns:
        Warnings (one line each).

    Raises:
        SanityError: a marker's median speed is over the limit
            (:class:`BasePoseMotion`).
    """
    motion = base_pose_motion(positions, labels, rate_hz)
    if motion.still:
        return []
    text = (
        f"the base pose is not still: marker {motion.marker} moves at "
        f"{motion.speed_m_s:.2f} m/s over the calibration frames (quiet standing "
        f"sways under {motion.limit_m_s:.2g} m/s)"
    )
    if allow_moving:
        return [f"{text}; calibrating anyway ({override})"]
    raise SanityError(
        f"{text}: choose frames where the performer holds the base pose, or pass "
        f"{override}"
    )


def _units_hint(extent_m: float, units: str) -> str:
    """The declared unit that would put ``extent_m`` nearest a 1.7 m person."""
    in_file = extent_m / UNIT_TO_METRES.get(units, 1.0)
    best = min(
        ("mm", "cm", "m", "in"),
        key=lambda u: abs(math.log(max(in_file * UNIT_TO_METRES[u], 1e-12) / 1.7)),
    )
    return best


def _stature_bounds(factor: float) -> tuple[float, float]:
    lo, hi = STATURE_RANGE_M
    return lo / factor, hi * factor


def _finite_mean(x: F64Array, axis: int) -> F64Array:
    """Mean over ``axis`` of the finite values; NaN where there are none (no
    warning)."""
    ok = np.isfinite(x)
    n = ok.sum(axis=axis)
    s = np.where(ok, x, 0.0).sum(axis=axis)
    return np.where(n > 0, s / np.maximum(n, 1), np.nan)


def check_units(
    positions: F64Array,
    *,
    units: str,
    units_source: str,
    override: str = "--take-units",
) -> list[str]:
    """Refuse a base pose whose size says its declared unit is wrong.

    The markers' vertical extent (feet to head, about 0.9 of stature for a full
    body set, half of it for a lower-body set) must lie within
    :data:`STATURE_RANGE_M` widened by :data:`UNITS_GARBAGE_FACTOR` (and halved at the
    bottom for a partial marker set).

    Args:
        positions: (F, M, 3) float64, metres, world (+Z up); NaN rows = occluded.
        units: the unit the take was read in (``take.units``).
        units_source: where it came from (``take.units_source``).
        override: the option that sets the unit, named in the message.

    Returns:
        Warnings (none today: an extent inside the bounds is left to
        :func:`check_calibration`).

    Raises:
        SanityError: an extent no person in any unit of the file's could have.
    """
    pos = np.asarray(positions, dtype=np.float64)
    if pos.ndim != 3:
        return []
    mean_z = _finite_mean(pos[..., 2], axis=0)
    mean_z = mean_z[np.isfinite(mean_z)]
    if mean_z.size < 2:
        return []
    extent = float(mean_z.max() - mean_z.min())
    lo, hi = _stature_bounds(UNITS_GARBAGE_FACTOR)
    lo /= 2.0  # a lower-body marker set spans about half the stature
    if lo <= extent <= hi:
        return []
    hint = _units_hint(extent, units)
    text = (
        f"the base pose's markers span {extent:.4g} m vertically read as {units} "
        f"({units_source}); a person {STATURE_RANGE_M[0]:g}-{STATURE_RANGE_M[1]:g} m "
        "tall cannot"
    )
    if normalize_units(hint) == normalize_units(units):  # no unit would fit better
        raise SanityError(f"{text}: too few of the body's markers were seen")
    raise SanityError(f"{text}: the file's unit looks wrong, try {override} {hint}")


#: The least spread (bounding-box diagonal of the markers' mean positions) of a base
#: pose: the smallest a person can look through any unit confusion the units check
#: names is 1.0 m / :data:`UNITS_GARBAGE_FACTOR` read a thousand times too small
#: (metres declared as millimetres), 0.5 mm. Markers closer together than that are
#: not a body: a stream stuck at one point, zeros, or one marker's value repeated.
COLLAPSED_SPREAD_M = STATURE_RANGE_M[0] / UNITS_GARBAGE_FACTOR * 1e-3


def check_spread(positions: F64Array) -> list[str]:
    """Refuse a base pose whose markers collapse onto one point (under
    :data:`COLLAPSED_SPREAD_M` apart), before the up-axis and units checks give a
    misleading reason for it.

    Args:
        positions: (F, M, 3) float64, metres, world; NaN rows = occluded.

    Raises:
        SanityError: the markers span less than :data:`COLLAPSED_SPREAD_M`.
    """
    pos = np.asarray(positions, dtype=np.float64)
    if pos.ndim != 3:
        return []
    mean = _finite_mean(pos, axis=0)
    mean = mean[np.isfinite(mean).all(axis=-1)]
    if mean.shape[0] < 2:
        return []  # nothing to span: the calibration names the markers missing
    spread = float(np.linalg.norm(mean.max(axis=0) - mean.min(axis=0)))
    if spread >= COLLAPSED_SPREAD_M:
        return []
    raise SanityError(
        f"the base pose is degenerate: its {mean.shape[0]} markers lie within "
        f"{1000 * spread:.3g} mm of each other (a body spans metres): the marker "
        "stream is stuck, zeroed or mislabelled"
    )


def _side_markers(rig: Rig, humanoid: Sequence[str]) -> list[str]:
    out: list[str] = []
    for bone in rig.bones:
        if bone.humanoid in humanoid:
            for p in bone.inputs:
                out.extend(m for m in rig.markers_of(p, base_pose=True) if m not in out)
    return out


def check_up_axis(
    rig: Rig,
    positions: F64Array,
    labels: Sequence[str],
    *,
    up_axis: str,
    up_source: str,
    world_from_capture: F64Array,
    override: str = "--take-up",
) -> list[str]:
    """Refuse a base pose whose head is not above its feet along the declared up.

    Head markers: those of the rig's ``humanoid = "Head"`` bone; feet: those of
    ``LeftFoot``/``RightFoot``. Skipped (no warning) for a rig without them.

    Args:
        rig: the rig.
        positions: (F, M, 3) float64, metres, world (+Z up); NaN rows = occluded.
        labels: (M,) marker labels.
        up_axis: the take's up axis (``take.up_axis``) and ``up_source`` where it
            came from; an up axis the user gave (source ``override``) only warns.
        world_from_capture: (3, 3) the rotation the take was read with.
        override: the option that sets the up axis, named in the message.

    Returns:
        Warnings (one line each).

    Raises:
        SanityError: the feet->head direction is more than
            :data:`UP_ANGLE_LIMIT_DEG` from +Z and the up axis was not given by the
            user; the message names the capture axis the pose says is up.
    """
    cols = dict(zip(rig.marker_names, match_markers(rig, labels), strict=True))
    head = [cols[m] for m in _side_markers(rig, ("Head",)) if cols[m] >= 0]
    feet = [
        cols[m] for m in _side_markers(rig, ("LeftFoot", "RightFoot")) if cols[m] >= 0
    ]
    if not head or not feet:
        return []
    pos = np.asarray(positions, dtype=np.float64)
    h = _finite_mean(pos[:, head].reshape(-1, 3), axis=0)
    f = _finite_mean(pos[:, feet].reshape(-1, 3), axis=0)
    d = h - f
    norm = float(np.linalg.norm(d))
    if not np.isfinite(norm) or norm == 0.0:
        return []
    angle = math.degrees(math.acos(max(-1.0, min(1.0, d[2] / norm))))
    if angle <= UP_ANGLE_LIMIT_DEG:
        return []
    capture = np.asarray(world_from_capture, dtype=np.float64).T @ d
    k = int(np.argmax(np.abs(capture)))
    detected = ("+" if capture[k] > 0 else "-") + "XYZ"[k]
    text = (
        f"up axis {up_axis} ({up_source}) puts the head {angle:.0f} deg from above "
        f"the feet in the base pose; the pose says up is the file's {detected}"
    )
    if up_source.startswith("override"):
        return [f"{text} (keeping {up_axis} as given)"]
    raise SanityError(f"{text}: pass {override} {detected}")


#: Mirror check: the least horizontal length of a forward cue (toe markers ahead of
#: the ankle's, the pelvis' front markers ahead of its back ones) and of the rig's
#: right->left marker axis for the check to trust its direction. Marker noise of
#: ~1 mm (Merriaux et al., Sensors 2017;17:1591) across 30 mm turns the direction by
#: under 2 deg; the real cues are 5-10 times longer (the toes lie ~0.10-0.20 m ahead
#: of the malleoli: foot length 0.152 H, Drillis & Contini in Winter 2009, Fig. 4.1;
#: ASIS to PSIS ~0.15 m), so a shorter one means the markers collapsed or are missing.
MIRROR_CUE_MIN_M = 0.030

#: Mirror check: the angle between the rig's right->left marker axis and the
#: performer's left (up x forward, forward from a cue the swap of left and right
#: labels leaves unchanged) above which the labels are swapped. A genuine base pose
#: puts it near 0 deg, a swap near 180 deg: the feet cue sums both feet, so their
#: symmetric toe-out (foot progression angle ~10 deg, range -3 to +20 deg in adults:
#: Staheli et al., J Bone Joint Surg Am 1985;67(1):39-47) cancels, and the shipped
#: statics measure 0-11 deg, their swapped copies 169-180 deg (RIGS.md). 90 deg is
#: where left turns into right; 135 deg leaves 45 deg, four times the worst toe-out,
#: on either side. Between 45 and 135 deg the cue cannot tell: a warning.
MIRROR_ANGLE_LIMIT_DEG = 135.0
MIRROR_UNSURE_DEG = 45.0


def _own_markers(rig: Rig, keep: object) -> list[str]:
    """The markers feeding the bones whose humanoid name ``keep(name)`` accepts."""
    out: list[str] = []
    for bone in rig.bones:
        if bone.humanoid and keep(bone.humanoid):  # type: ignore[operator]
            for p in bone.inputs:
                out.extend(m for m in rig.markers_of(p, base_pose=True) if m not in out)
    return out


def _forward_cues(rig: Rig) -> dict[str, tuple[list[str], list[str]]]:
    """cue name -> (front markers, back markers), both sides together (so a swap of
    left and right labels leaves each cue's vector unchanged).

    - ``feet``: per side, the markers of the foot chain's distal aim (``*Toes`` bone,
      else ``*Foot``) not used by the foot's origin (the toes), against those of the
      foot's origin (the ankle centre) not used by the lower leg's origin (the
      ankle and shank markers);
    - ``pelvis``: the rig's ``lateral`` pair (ASIS / front waist / iliac crest)
      against the other markers of the ``Hips`` bone (PSIS, sacrum, back waist).
    """
    by_humanoid = {b.humanoid: b for b in rig.bones if b.humanoid}
    front: list[str] = []
    back: list[str] = []
    for side in ("Left", "Right"):
        foot = by_humanoid.get(f"{side}Foot")
        leg = by_humanoid.get(f"{side}LowerLeg")
        if foot is None or leg is None:
            continue
        distal = by_humanoid.get(f"{side}Toes", foot)
        at_ankle = rig.markers_of(foot.origin, base_pose=True)
        at_knee = rig.markers_of(leg.origin, base_pose=True)
        front += [m for m in rig.markers_of(distal.aim, base_pose=True)
                  if m not in at_ankle]  # fmt: skip
        back += [m for m in at_ankle if m not in at_knee]
    cues: dict[str, tuple[list[str], list[str]]] = {}
    if front and back:
        cues["feet"] = (front, back)
    hips = by_humanoid.get("Hips")
    if hips is not None and rig.lateral:
        pair = list(rig.lateral)
        rest = [m for m in _own_markers(rig, lambda h: h == "Hips") if m not in pair]
        if rest:
            cues["pelvis"] = (pair, rest)
    return cues


def mirror_angles_deg(
    rig: Rig, positions: F64Array, labels: Sequence[str]
) -> dict[str, float]:
    """Per forward cue (:func:`_forward_cues`), the angle between the rig's
    right->left axis (the mean of the markers only ``Left*`` bones use minus that of
    the markers only ``Right*`` bones use) and the performer's left, ``+Z x forward``,
    both horizontal; degrees. Near 0 for a genuine base pose, near 180 when the
    left and right labels are swapped. Cues the take lacks, or shorter than
    :data:`MIRROR_CUE_MIN_M`, are left out.

    Args:
        rig: the rig.
        positions: (F, M, 3) float64, metres, world (+Z up); NaN rows = occluded.
        labels: (M,) marker labels.
    """
    cols = dict(zip(rig.marker_names, match_markers(rig, labels), strict=True))
    pos = np.asarray(positions, dtype=np.float64)
    if pos.ndim != 3:
        return {}
    mean = _finite_mean(pos, axis=0)  # (M, 3)

    def centre(names: Sequence[str]) -> F64Array:
        rows = [cols[m] for m in names if cols.get(m, -1) >= 0]
        pts = mean[rows] if rows else np.full((1, 3), np.nan)
        return _finite_mean(pts, axis=0)

    left = _own_markers(rig, lambda h: h.startswith("Left"))
    right = _own_markers(rig, lambda h: h.startswith("Right"))
    across = centre([m for m in left if m not in right]) - centre(
        [m for m in right if m not in left]
    )
    across[2] = 0.0
    if not np.linalg.norm(across) >= MIRROR_CUE_MIN_M:  # NaN too
        return {}
    out: dict[str, float] = {}
    for name, (front, back) in _forward_cues(rig).items():
        fwd = centre(front) - centre(back)
        fwd[2] = 0.0
        if not np.linalg.norm(fwd) >= MIRROR_CUE_MIN_M:
            continue
        side = np.cross([0.0, 0.0, 1.0], fwd)  # up x forward = left
        cos = float(side @ across) / float(
            np.linalg.norm(side) * np.linalg.norm(across)
        )
        out[name] = math.degrees(math.acos(max(-1.0, min(1.0, cos))))
    return out


def check_mirrored(rig: Rig, positions: F64Array, labels: Sequence[str]) -> list[str]:
    """Refuse a base pose whose left and right labels are swapped.

    Forward comes from cues a swap leaves unchanged (the toes ahead of the ankles,
    the pelvis' front markers ahead of its back ones), up is +Z (checked by
    :func:`check_up_axis`), left = up x forward; the markers the rig calls left must
    lie on that side (:func:`mirror_angles_deg`). Skipped for a rig or take without
    the cues.

    Returns:
        A warning when the cues cannot tell (an angle between
        :data:`MIRROR_UNSURE_DEG` and :data:`MIRROR_ANGLE_LIMIT_DEG`, or cues that
        disagree).

    Raises:
        SanityError: every cue puts the rig's left markers on the performer's right
            (more than :data:`MIRROR_ANGLE_LIMIT_DEG` from the left).
    """
    angles = mirror_angles_deg(rig, positions, labels)
    if not angles:
        return []
    said = ", ".join(f"{name} {a:.0f} deg" for name, a in angles.items())
    if all(a > MIRROR_ANGLE_LIMIT_DEG for a in angles.values()):
        raise SanityError(
            f"the base pose is mirrored: the markers rig {rig.name} calls left lie on "
            f"the performer's right ({said} from the left that the toes ahead of "
            "the ankles and the pelvis' front ahead of its back give): the take's "
            "left and right labels look swapped; relabel them"
        )
    if all(a <= MIRROR_UNSURE_DEG for a in angles.values()):
        return []
    return [
        f"left and right unclear in the base pose ({said} between the rig's "
        "right->left markers and the performer's left): check the L/R labels"
    ]


def _bone_lengths(rig: Rig, cal: Calibration) -> dict[str, tuple[str, float]]:
    """humanoid name -> (bone name, length m) for mapped bones."""
    by_name = {b.name: b for b in rig.bones}
    out: dict[str, tuple[str, float]] = {}
    for name, length in zip(cal.bone_names, cal.bone_lengths, strict=True):
        bone = by_name.get(name)
        if bone is not None and bone.humanoid:
            out[bone.humanoid] = (name, float(length))
    return out


def estimated_stature_m(rig: Rig, cal: Calibration) -> float:
    """Stature implied by the calibrated long bones (median over the mapped ones of
    length / :data:`LONG_BONE_FRACTION_OF_STATURE`), metres; NaN without any."""
    lengths = _bone_lengths(rig, cal)
    est = [
        lengths[f"{side}{kind}"][1] / frac
        for kind, frac in LONG_BONE_FRACTION_OF_STATURE.items()
        for side in ("Left", "Right")
        if f"{side}{kind}" in lengths and lengths[f"{side}{kind}"][1] > 0
    ]
    return float(np.median(est)) if est else math.nan


def check_stature(
    rig: Rig, cal: Calibration, *, units: str, override: str = "--take-units"
) -> list[str]:
    """The stature the calibrated long bones imply against :data:`STATURE_RANGE_M`.

    Returns:
        A warning when outside the range.

    Raises:
        SanityError: more than :data:`UNITS_GARBAGE_FACTOR` outside it (a wrong unit).
    """
    h = estimated_stature_m(rig, cal)
    if not math.isfinite(h):
        return []
    lo, hi = STATURE_RANGE_M
    if lo <= h <= hi:
        return []
    text = (
        f"the calibrated long bones imply a performer {h:.3g} m tall (read as "
        f"{units}); a person is {lo:g}-{hi:g} m"
    )
    glo, ghi = _stature_bounds(UNITS_GARBAGE_FACTOR)
    if glo <= h <= ghi:
        return [f"{text}: check the file's unit ({override}) and the rig's markers"]
    raise SanityError(f"{text}: the unit looks wrong, try {override} "
                      f"{_units_hint(h, units)}")  # fmt: skip


def check_bilateral(rig: Rig, cal: Calibration) -> list[str]:
    """A warning for each left/right pair of long bones (humanoid ``UpperLeg``,
    ``LowerLeg``, ``UpperArm``, ``LowerArm``: joint centre to joint centre) whose
    calibrated lengths differ by more than :data:`BILATERAL_LIMIT` of their mean.

    Short segments (hand, foot, shoulder, toes) are left out: their length runs to a
    marker (a finger, toe or acromion marker) whose placement, not anatomy, sets it,
    so the anatomical asymmetry figures say nothing about them.
    """
    lengths = _bone_lengths(rig, cal)
    out = []
    for kind in LONG_BONE_FRACTION_OF_STATURE:
        lhs, rhs = lengths.get(f"Left{kind}"), lengths.get(f"Right{kind}")
        if lhs is None or rhs is None:
            continue
        (left, a), (right, b) = lhs, rhs
        mean = 0.5 * (a + b)
        if mean > 0 and abs(a - b) / mean > BILATERAL_LIMIT:
            out.append(
                f"left/right bones differ by {100 * abs(a - b) / mean:.0f} %: "
                f"{left} {1000 * a:.0f} mm, {right} {1000 * b:.0f} mm (healthy "
                f"adults differ by 1-3 %): check those markers and the base pose"
            )
    return out


def check_calibration(
    rig: Rig, cal: Calibration, *, units: str, override: str = "--take-units"
) -> list[str]:
    """:func:`check_stature` and :func:`check_bilateral` on a calibration."""
    return [
        *check_stature(rig, cal, units=units, override=override),
        *check_bilateral(rig, cal),
    ]


#: The least distance, in the base pose, between a bone's up reference and the bone's
#: axis (for ``up = [FROM, TO]``: the part of FROM->TO across the axis). The roll is
#: the angle of that lever about the axis, so marker noise sigma across it turns the
#: bone by about atan(sigma / lever): optical systems track markers to ~0.5-1 mm
#: (Merriaux et al., Sensors 2017;17(7):1591), so 30 mm keeps the roll jitter under
#: 2 deg from noise alone; skin movement moves markers by 10-30 mm more (Leardini et
#: al., Gait Posture 2005;21(2):212-225), which only a longer lever tolerates.
UP_LEVER_MIN_M = 0.030


def _base_pose_points(
    rig: Rig, cal: Calibration, positions: F64Array, labels: Sequence[str] | None
) -> dict[str, F64Array]:
    """The rig's points on the base pose's mean markers (each (1, 3))."""
    pos = np.asarray(positions, dtype=np.float64)
    cols = (
        np.arange(len(rig.markers))
        if labels is None
        else np.asarray(match_markers(rig, labels))
    )
    mean = _finite_mean(pos, axis=0)  # (M, 3)
    marker_pos = np.full((1, len(cols), 3), np.nan)
    have = cols >= 0
    marker_pos[0, have] = mean[cols[have]]
    return compute_points(rig, marker_pos, cal.point_offsets)


def up_levers(
    rig: Rig, cal: Calibration, positions: F64Array, labels: Sequence[str] | None
) -> dict[str, float]:
    """Each bone's up lever in the base pose (see :data:`UP_LEVER_MIN_M`), metres.

    Args:
        rig: the rig the calibration was made for.
        cal: the calibration.
        positions: (F, M, 3) float64, metres, world: the base-pose frames.
        labels: (M,) the take's marker labels; None: the columns are the rig's
            markers in rig order (``cal.base_marker_pos``), not matched by name.

    Returns:
        bone name -> lever (bones whose points were not all seen are left out).
    """
    pts = _base_pose_points(rig, cal, positions, labels)
    out: dict[str, float] = {}
    for bone in rig.bones:
        axis = pts[bone.aim][0] - pts[bone.origin][0]
        if len(bone.up) == 1:
            v = pts[bone.up[0]][0] - pts[bone.origin][0]
        else:
            v = pts[bone.up[1]][0] - pts[bone.up[0]][0]
        n = float(np.linalg.norm(axis))
        if not (np.isfinite(n) and n > 0 and np.isfinite(v).all()):
            continue
        y = axis / n
        out[bone.name] = float(np.linalg.norm(v - (v @ y) * y))
    return out


def check_up_levers(
    rig: Rig, cal: Calibration, positions: F64Array, labels: Sequence[str]
) -> list[str]:
    """One warning per bone whose up lever is under :data:`UP_LEVER_MIN_M`."""
    return [
        f"bone {name}: its up reference is {1000 * lever:.0f} mm off the bone's axis "
        f"in the base pose (under {1000 * UP_LEVER_MIN_M:.0f} mm its roll follows "
        f"marker noise): choose an up point farther from the axis"
        for name, lever in up_levers(rig, cal, positions, labels).items()
        if lever < UP_LEVER_MIN_M
    ]


def base_pose_bends_deg(
    rig: Rig, cal: Calibration, positions: F64Array, labels: Sequence[str] | None
) -> dict[str, float]:
    """The bend of each rigid point's frame that has ``bend_min_deg`` in the base
    pose: 180 deg less the angle at its first point between the other two.

    Args, labels: as :func:`up_levers`.

    Returns:
        point name -> bend, degrees (points whose frame was not seen left out).
    """
    needs = [p for p in rig.points if isinstance(p, RigidPoint) and p.bend_min_deg > 0]
    if not needs:
        return {}
    pts = _base_pose_points(rig, cal, positions, labels)
    out: dict[str, float] = {}
    for p in needs:
        a, b, c = (pts[n][0] for n in p.frame)
        u, v = b - a, c - a
        nu, nv = float(np.linalg.norm(u)), float(np.linalg.norm(v))
        if not (np.isfinite(nu * nv) and nu > 0 and nv > 0):
            continue
        cos = float(np.clip(u @ v / (nu * nv), -1.0, 1.0))
        out[p.name] = 180.0 - float(np.degrees(np.arccos(cos)))
    return out


def check_bends(
    rig: Rig, cal: Calibration, positions: F64Array, labels: Sequence[str]
) -> list[str]:
    """One warning per rigid point whose frame is straighter in the base pose than
    its ``bend_min_deg`` (RIGS.md: a construction that reads a joint's axis from the
    joint's bend, such as Plug-in Gait's elbow, cannot from a straight one)."""
    mins = {p.name: p.bend_min_deg for p in rig.points if isinstance(p, RigidPoint)}
    return [
        f"point {name}: {' '.join(_frame_of(rig, name))} is bent {bend:.0f} deg in the "
        f"base pose (the rig needs at least {mins[name]:g} deg to place it): "
        f"calibrate with that joint bent"
        for name, bend in base_pose_bends_deg(rig, cal, positions, labels).items()
        if bend < mins[name]
    ]


def _frame_of(rig: Rig, name: str) -> tuple[str, ...]:
    return next(
        p.frame for p in rig.points if isinstance(p, RigidPoint) and p.name == name
    )


#: A bone whose up lever is already short in the base pose would, with the rig's
#: ``up_min_mm`` alone, hold its roll in every frame (menache's torso takes its roll
#: from LONECK->C7, 4 mm across its axis). Such a bone takes its roll from the previous
#: frame only once its lever falls to this fraction of its base-pose lever: there the
#: noise on its roll is twice what the calibration saw (atan(sigma / d), see
#: :data:`UP_LEVER_MIN_M`), a collapse of the lever rather than the rig's design.
ROLL_HOLD_BASE_FRACTION = 0.5


def roll_hold_levels_m(rig: Rig, cal: Calibration) -> F64Array:
    """Per bone, the up lever (m) under which the construction keeps the bone's new
    axis and takes its roll from the previous frame (``body.kernel``, step 4): the
    rig's ``up_min_mm``, or :data:`ROLL_HOLD_BASE_FRACTION` of the bone's base-pose
    lever when that is less (from ``cal.base_marker_pos``; a calibration without it
    gives ``up_min_mm`` for every bone).

    Returns:
        (B,) float64, metres, in rig bone order.
    """
    levels = np.full(len(rig.bones), rig.up_min_mm * 1e-3)
    base = cal.base_marker_pos
    if base is None:
        return levels
    # base_marker_pos is in rig-marker order: never match the rig's names as labels
    # (a marker named apart from its aliases would count as unseen).
    levers = up_levers(rig, cal, np.asarray(base)[None], None)
    for b, bone in enumerate(rig.bones):
        lever = levers.get(bone.name)
        if lever is not None:
            levels[b] = min(levels[b], ROLL_HOLD_BASE_FRACTION * lever)
    return levels


@dataclass(frozen=True, slots=True, kw_only=True)
class BasePoseSource:
    """What a base pose was read as, and the options that change it (named in the
    refusals): a take's header offline, the marker input's config live.

    Attributes:
        units, units_source: the length unit the markers were read in and where it
            came from.
        up_axis, up_source: the capture's up axis and where it came from.
        world_from_capture: (3, 3) float64, the rotation they were read with.
        rate_hz: frame rate of the base-pose frames, Hz.
        units_override, up_override, moving_override: the option (offline) or
            config key (live) that sets each; named in the messages.
    """

    units: str = "m"
    units_source: str = "default"
    up_axis: str = "+Z"
    up_source: str = "default"
    world_from_capture: F64Array = field(default_factory=lambda: np.eye(3))
    rate_hz: float
    units_override: str = "--take-units"
    up_override: str = "--take-up"
    moving_override: str = "--allow-moving-base-pose"


def calibrate_checked(
    rig: Rig,
    positions: F64Array,
    labels: Sequence[str],
    source: BasePoseSource,
    *,
    allow_moving: bool = False,
    take_measurements: Mapping[str, float] | None = None,
    overrides: Mapping[str, float] | None = None,
    base_pose: Mapping[str, Any] | None = None,
    rom: tuple[F64Array, Sequence[str], Mapping[str, Any]] | None = None,
    up_levers: bool = False,
) -> tuple[Calibration, list[str]]:
    """Calibrate ``rig`` after every base-pose check and check the result: the
    spread, up axis, units, stillness and left/right labels of the base pose
    (:func:`check_spread`, :func:`check_up_axis`, :func:`check_units`,
    :func:`check_base_pose_still`, :func:`check_mirrored`), then the stature,
    left/right symmetry, up levers and bends of the calibration
    (:func:`check_calibration`, :func:`check_up_levers`, :func:`check_bends`). The
    one function both the offline ``calibrate`` and the live calibration run.

    Args:
        rig: the rig.
        positions: (F, M, 3) float64, metres, world (+Z up); NaN rows = occluded.
        labels: (M,) marker labels.
        source: how the markers were read (:class:`BasePoseSource`).
        allow_moving: a moving base pose warns instead of refusing.
        take_measurements, overrides, base_pose, rom: passed to ``calibrate`` (a
            range of motion's joints it does not determine are among the warnings).
        up_levers: warn of each bone whose up lever is short
            (:func:`check_up_levers`): for the construction, which takes every
            bone's roll from its up reference. The fit (the default) takes none: it
            decides from all the markers what each bone's rotations are measured
            by, and holds what they are not (``body.fit_observe``, printed by
            ``retargetd rig check``), so a short up lever says nothing of its solve.

    Returns:
        ``(calibration, warnings)`` (one line each).

    Raises:
        SanityError: a base pose whose calibration would be garbage.
        CalibrationError: a base pose that cannot calibrate the rig.
    """
    notes = check_spread(positions)
    notes += check_up_axis(
        rig, positions, labels, up_axis=source.up_axis, up_source=source.up_source,
        world_from_capture=source.world_from_capture, override=source.up_override,
    )  # fmt: skip
    notes += check_units(
        positions, units=source.units, units_source=source.units_source,
        override=source.units_override,
    )  # fmt: skip
    notes += check_base_pose_still(
        positions, labels, source.rate_hz, allow_moving=allow_moving,
        override=source.moving_override,
    )  # fmt: skip
    notes += check_mirrored(rig, positions, labels)
    cal = calibrate(
        rig, positions, labels, take_measurements=take_measurements,
        overrides=overrides, base_pose=base_pose, rom=rom,
    )  # fmt: skip
    notes += cal.functional.get("notes", [])  # rom: the joints it did not place
    notes += check_calibration(
        rig, cal, units=source.units, override=source.units_override
    )
    # a bone whose construction roll would follow noise: named, with its lever
    if up_levers:
        notes += check_up_levers(rig, cal, positions, labels)
    # a point whose construction needs a bent joint, calibrated on a straight one
    notes += check_bends(rig, cal, positions, labels)
    return cal, notes
