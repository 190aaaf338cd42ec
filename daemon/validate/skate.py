"""Stance-foot skate (issue 34, item 5): a foot that slides while it stands.

Stance. The frames come from the stance detector of ``post/stance.py`` (the NPZ's
``foot_contact``, the pose stream's contact bits), passed in by the caller as one
(T,) bool array per foot bone (``cli/validate.py`` runs ``post.stance.foot_contact``
on the solve). ``validate`` may not import ``post`` (the same layer,
``tests/test_layout.py``); rather than move the detector below both (it is imported by
``live/``, ``cli/`` and ``post/plant.py``) or restate its compiled kernel here (two
copies to keep in step), the command line, which may import both, hands the detected
stance over. Without it (a caller that passes none) the check is not run.

Skate. Per foot, points fixed in the solved foot filling its sole region
(:func:`floor_points`): from the heel (under the ankle, the foot bone's origin) past
the ball (under the foot bone's aim, over the metatarsal heads) to the toe tip (a
toes bone's aim, or as far beyond the ball as the heads lie at 0.73 of the foot's
length), across half the foot's breadth either side, and from the calibrated floor
up to the height of the metatarsal heads. A stance foot that does not slip has a
point of its own at rest on the floor: the heel in the loading response, the whole
sole in mid-stance, the ball and toes in terminal stance (the heel, ankle and
forefoot rockers, Perry & Burnfield 2010, *Gait Analysis*, 2nd ed., ch. 3), and the
point it turns about when it pivots (a dancer's turn on the ball, a heel pivot); the
point need not be one of heel, ball or toe (turning about the midfoot, the heel and
the toe each move ~0.13 m/s: ``tests/daemon/test_validate_skate.py``). The skate
speed is the horizontal speed of the slowest of them, from positions low-passed at
6 Hz (zero phase, Winter's gait cut-off, as the ghost force), by central
differences: the contact point that moves least.

Which frames. The detected stance less its first and last ``foot_skate_edge_s``: at
its start the detector has the heel below 0.5 m/s and still braking, at its end it
holds the contact until every point exceeds 1.0 m/s (its hysteresis), so the foot is
already leaving (loading response and pre-swing, each ~10 % of the cycle, ~0.1 s:
Perry & Burnfield); and of those, the frames whose lowest sole point is within
``foot_skate_support_m`` of the stance's support (its median height over the
stance): a foot the detector holds in stance but lifted above that is off the floor
(a shuffle step inside the detector's hysteresis), not sliding on it. A frame fails
when the skate speed stays above ``foot_skate_m_s`` for at least
``foot_skate_min_s`` on that foot; shorter excursions are transients.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from retargetd.daemon import rotations as rot
from retargetd.daemon.validate import dynamics as vd
from retargetd.daemon.validate.model import Skeleton, ground_height, rest_aim_world
from retargetd.protocols.frames import F64Array

#: Low-pass cut-off for the foot points, Hz (Winter's ~6 Hz for gait kinematics).
CUTOFF_HZ = 6.0


@dataclass(slots=True)
class SkateResult:
    """The check over a take: per-frame values (the faster foot, NaN where neither is
    in its stance core), flagged frames, transients and one line per flagged run."""

    values: F64Array
    flagged: np.ndarray
    transients: np.ndarray
    detail: list[str]
    per_foot: dict[str, F64Array]  # foot bone -> (T,) skate speed, NaN off the core


#: Half the foot's breadth, as a fraction of its length (heel to toe tip): a foot's
#: breadth is ~0.39 of its length (Winter 2009, Biomechanics and Motor Control of
#: Human Movement, 4th ed., fig. 4.1: foot breadth 0.055 H, foot length 0.152 H, H
#: the height: 0.36; 0.39 rounds it up so a wide forefoot is covered).
HALF_BREADTH_OF_LENGTH = 0.195
#: Without a toes bone the toe tip is taken as far beyond the ball (the foot bone's
#: aim, over the metatarsal heads) as the heads lie at 0.73 of the foot's length
#: from the heel (the synthetic skeleton's proportions, Winter 2009 / de Leva 1996).
BALL_OF_LENGTH = 0.73
#: Points of the sole region along the foot (heel to toe tip), across it, and from the
#: floor up to the rocker axis.
_ALONG, _ACROSS, _UP = 7, 3, 3


def floor_points(skel: Skeleton, foot: int) -> list[tuple[int, F64Array]]:
    """(bone, offset in that bone's frame) of points filling the foot's sole region:
    from the heel (under the ankle) to the ball (under the foot bone's aim) and on
    to the toe tip (under a toes bone's aim, where the rig has one), across half the
    foot's breadth either side, and from the calibrated floor (the lowest foot
    capsule of the calibration pose) up to the lowest of the foot's origin and aims
    (the metatarsal heads: the forefoot rocker's axis). A foot that rolls or turns
    about a point of its own on the floor has one of them at rest."""
    aims = rest_aim_world(skel)
    origin = skel.rest_origin_world
    toes = [
        b
        for b, p in enumerate(skel.bone_parents)
        if p == foot and skel.bone_kinds[b] == "toes"
    ]
    above = [(foot, origin[foot]), (foot, aims[foot]), *((t, aims[t]) for t in toes)]
    floor = ground_height(skel)
    top = max(floor, min(float(p[2]) for _, p in above))
    heel, ball = origin[foot][:2], aims[foot][:2]
    tip = aims[toes[0]][:2] if toes else heel + (ball - heel) / BALL_OF_LENGTH
    length = float(np.linalg.norm(tip - heel)) or 1e-3
    ahead = (tip - heel) / length
    side = np.array([-ahead[1], ahead[0]])
    out = []
    to_ball = float(np.linalg.norm(ball - heel)) / length
    for u in np.linspace(0.0, 1.0, _ALONG):
        along = heel + u * (tip - heel)
        bone = toes[0] if toes and u > to_ball else foot
        for w in np.linspace(-1.0, 1.0, _ACROSS):
            xy = along + w * HALF_BREADTH_OF_LENGTH * length * side
            for z in np.linspace(floor, top, _UP):
                p = np.array([xy[0], xy[1], z])
                q = rot.quat_conj(skel.rest_world_from_bone_quat[bone])
                out.append((bone, rot.quat_rotate(q, p - origin[bone])))
    return out


def skate_speed(
    skel: Skeleton,
    origins: F64Array,
    world_from_bone_quat: F64Array,
    foot: int,
    rate_hz: float,
) -> F64Array:
    """(T,) horizontal speed of the foot's slowest sole point, m/s (module
    docstring)."""
    return sole_motion(skel, origins, world_from_bone_quat, foot, rate_hz)[0]


def sole_motion(
    skel: Skeleton,
    origins: F64Array,
    world_from_bone_quat: F64Array,
    foot: int,
    rate_hz: float,
) -> tuple[F64Array, F64Array]:
    """(T,) horizontal speed of the foot's slowest sole point (m/s) and (T,) height
    of its lowest sole point (metres, world z)."""
    pts = np.stack(
        [
            origins[:, b] + rot.quat_rotate(world_from_bone_quat[:, b], local)
            for b, local in floor_points(skel, foot)
        ],
        axis=1,
    )  # (T, P, 3)
    n = pts.shape[0]
    lowest = pts[..., 2].min(axis=1)
    if n < 3:
        return np.zeros(n), lowest
    smooth = vd.lowpass(pts, rate_hz, CUTOFF_HZ)
    speed = np.empty(pts.shape[:2])
    step = smooth[2:, :, :2] - smooth[:-2, :, :2]
    speed[1:-1] = np.linalg.norm(step, axis=-1) * (0.5 * rate_hz)
    speed[0], speed[-1] = speed[1], speed[-2]
    return np.asarray(speed.min(axis=1)), lowest


def on_support(core: np.ndarray, lowest: F64Array, above_m: float) -> np.ndarray:
    """(T,) bool: core frames whose lowest sole point is within ``above_m`` of the
    stance's support, the median of that height over each core run (the
    floor, or a step: the stance need not be on the calibrated floor)."""
    out = np.zeros(core.shape[0], dtype=bool)
    m = np.concatenate([[False], core, [False]])
    edges = np.flatnonzero(m[1:] != m[:-1])
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        support = np.median(lowest[a:b])
        out[a:b] = lowest[a:b] <= support + above_m
    return out


def stance_core(contact: np.ndarray, edge_frames: int) -> np.ndarray:
    """(T,) bool: each contact run less ``edge_frames`` at either end."""
    core = np.zeros(contact.shape[0], dtype=bool)
    m = np.concatenate([[False], np.asarray(contact, bool), [False]])
    edges = np.flatnonzero(m[1:] != m[:-1])
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        if b - a > 2 * edge_frames:
            core[a + edge_frames : b - edge_frames] = True
    return core


def skate_check(
    skel: Skeleton,
    origins: F64Array,
    world_from_bone_quat: F64Array,
    stance: dict[str, np.ndarray],
    rate_hz: float,
    *,
    speed_m_s: float,
    min_s: float,
    edge_s: float,
    support_m: float,
) -> SkateResult:
    """The skate check (module docstring).

    Args:
        skel: the streamed skeleton.
        origins: (T, B, 3) bone origins (``validate.checks.pose_skeleton``).
        world_from_bone_quat: (T, B, 4) w x y z.
        stance: foot bone name -> (T,) bool, the detected contact.
        rate_hz: frame rate.
        speed_m_s, min_s, edge_s, support_m: the thresholds (``THRESHOLDS``
            ``foot_skate_*``).
    """
    n = origins.shape[0]
    values = np.full(n, np.nan)
    flagged = np.zeros(n, dtype=bool)
    transients = np.zeros(n, dtype=bool)
    detail: list[str] = []
    per_foot: dict[str, F64Array] = {}
    edge = round(edge_s * rate_hz)
    n_min = max(1, round(min_s * rate_hz))
    for name, contact in stance.items():
        foot = skel.bone_names.index(name)
        speed, lowest = sole_motion(skel, origins, world_from_bone_quat, foot, rate_hz)
        core = stance_core(np.asarray(contact, bool), edge)
        core &= on_support(core, lowest, support_m)
        on_core = np.where(core, speed, np.nan)
        per_foot[name] = on_core
        values = np.fmax(values, on_core)
        over = core & (speed > speed_m_s)
        bad = over & (vd.run_lengths(over) >= n_min)
        flagged |= bad
        transients |= over & ~bad
        m = np.concatenate([[False], bad, [False]])
        runs = np.flatnonzero(m[1:] != m[:-1])
        for a, b in zip(runs[::2], runs[1::2], strict=True):
            detail.append(
                f"{name}: frames {a}-{b - 1} ({(b - a) / rate_hz:.2f} s of stance), "
                f"slowest floor point up to {speed[a:b].max():.3f} m/s, slid "
                f"{1e3 * speed[a:b].sum() / rate_hz:.0f} mm"
            )
    return SkateResult(values, flagged, np.flatnonzero(transients), detail, per_foot)
