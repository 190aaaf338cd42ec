"""Stance from the solve: per foot, is it on the ground (issue 34, item 1).

One causal detector, frame by frame, shared by the live daemon (``live/send.py``, on
every solved frame before the post stages) and ``retargetd solve`` (the NPZ's
``foot_contact``), so offline equals live.

Foot points. The humanoid ``LeftFoot``/``RightFoot`` bones (every shipped rig maps
them): the foot bone's origin (the ankle) and its aim (the forefoot marker or point the
rig aims it at), and the toes bone's aim when the rig maps ``LeftToes``/``RightToes``.
They are posed from the solved world rotations, the root position and the calibrated
rest offsets (``origin_b = origin_p + wfb_p * offset_b``, ``aim_b = origin_b + wfb_b *
(0, L_b, 0)``), so any solver's output (the joint centres need not name them) works.

Height. The calibration is taken standing on the floor, so each point's calibrated
height is its height when standing; ``h = z - z_rest - s`` is its height above that,
with ``s`` the foot's support level: 0 (the calibration's floor) until the foot stops
somewhere else (a step, a riser), then that level.

Speed. Each point's velocity is the frame-to-frame difference smoothed by a one-pole
low-pass at :data:`STANCE` ``cutoff_hz`` (causal; what the live loop can do).

Contact (with hysteresis: two speeds, after the foot-velocity algorithms):

* on when some point is slower than ``on_speed_m_s`` within ``near_m`` of the support
  level, or when the foot has been slower than ``still_speed_m_s`` for ``still_s`` at
  any height (a foot that stops on a step: the level moves there);
* off when no point is both slower than ``off_speed_m_s`` and within ``near_m``, and the
  foot is not still.

Known limits: a foot held still in the air for longer than ``still_s`` reads as a foot
on a support (the feet alone cannot tell a riser from a held pose); a held (occluded)
foot bone does not move, so it reads as standing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.calibration import Calibration
from retargetd.daemon.body.rig import Rig
from retargetd.protocols.frames import F64Array
from retargetd.protocols.pose_stream import (
    FRAME_CONTACT_KNOWN,
    FRAME_CONTACT_LEFT,
    FRAME_CONTACT_RIGHT,
)

#: Detector parameters (SI). Which data chose each and which confirmed it: README
#: "Foot contact".
STANCE: dict[str, float] = {
    # On: a foot point slower than this (3D). Ghoussayni et al. 2004 (Gait Posture
    # 20:266-272): foot strike when the heel's sagittal speed falls below 500 mm/s;
    # Bonci et al. 2022 (Front Bioeng Biotechnol 10:868928, their "enhanced
    # Ghoussayni" M5): 3D heel or forefoot speed below 0.5 m/s.
    "on_speed_m_s": 0.5,
    # Off: every point faster than this (or lifted). Bonci et al. 2022 (M5): foot off
    # when the forefoot's 3D speed exceeds 1.0 m/s. The gap to on_speed is the
    # hysteresis: noise near one threshold cannot toggle the contact.
    "off_speed_m_s": 1.0,
    # Within this of the support level. Height alone cannot tell stance from swing:
    # the swing toe passes 1.29 +- 0.45 cm above the floor (Winter 1992, Phys Ther
    # 72:45-53; O'Connor et al. 2007, Gait Posture 25:469-474, likewise pair their
    # foot-velocity events with a foot-height gate), so the speed decides and the
    # height only excludes a slow foot aloft (a jump's apex); 4 cm admits the solved
    # foot's height error in stance (a heel or forefoot rocking on the floor).
    "near_m": 0.04,
    # Stopped at any height (a step): slower than this for still_s. 0.2 m/s is the
    # stationary speed of the floating check (validate/dynamics.py CONTACT); a
    # ballistic foot is under it for 2 * 0.2 / 9.81 = 41 ms at a jump's apex, so
    # still_s is twice that.
    "still_speed_m_s": 0.20,
    "still_s": 0.082,
    # Velocity low-pass, Hz: Winter's ~6 Hz for gait kinematics (Winter 2009,
    # Biomechanics and Motor Control of Human Movement, 4th ed., ch. 2).
    "cutoff_hz": 6.0,
}

#: The flag bits :meth:`StanceDetector.update` returns (the pose stream's).
LEFT, RIGHT, KNOWN = FRAME_CONTACT_LEFT, FRAME_CONTACT_RIGHT, FRAME_CONTACT_KNOWN
_Y = np.array([0.0, 1.0, 0.0])
_SIDES = (("LeftFoot", "LeftToes"), ("RightFoot", "RightToes"))


@dataclass(frozen=True, slots=True)
class _Foot:
    chain: tuple[int, ...]  # bone indices root .. foot bone (.. toes bone)
    offsets: F64Array  # (len(chain), 3): each chain bone's origin in its parent frame
    points: tuple[tuple[int, float], ...]  # (bone, length): a point at its aim; -1 L
    rest_z: F64Array  # (P,) calibrated height of each point
    heel: F64Array | None = None  # (3,) the heel in the foot bone's frame


def _feet(rig: Rig, cal: Calibration) -> tuple[_Foot, ...]:
    """The two feet's chains and points; () when the rig maps no LeftFoot/RightFoot."""
    if cal.rest_bone_origin_pos is None:
        return ()
    parents = [int(p) for p in cal.bone_parents]
    names = list(cal.bone_names)
    wfb = np.asarray(cal.rest_world_from_bone_quat, dtype=np.float64)
    origin = np.asarray(cal.rest_bone_origin_pos, dtype=np.float64)
    lengths = np.asarray(cal.bone_lengths, dtype=np.float64)
    feet = []
    for foot_name, toes_name in _SIDES:
        if foot_name not in rig.humanoid:
            return ()
        b = names.index(rig.humanoid[foot_name])
        chain: list[int] = []
        while b >= 0:
            chain.insert(0, b)
            b = parents[b]
        offsets = np.zeros((len(chain), 3))
        for k in range(1, len(chain)):
            c, p = chain[k], chain[k - 1]
            offsets[k] = rot.quat_rotate(rot.quat_conj(wfb[p]), origin[c] - origin[p])
        foot = chain[-1]
        pts = [(foot, -1.0), (foot, float(lengths[foot]))]
        toes = rig.humanoid.get(toes_name)
        if toes is not None and parents[names.index(toes)] == foot:
            t = names.index(toes)
            toe_off = rot.quat_rotate(
                rot.quat_conj(wfb[foot]), origin[t] - origin[foot]
            )
            offsets = np.vstack([offsets, toe_off])
            chain.append(t)
            pts.append((t, float(lengths[t])))
        plan = _Foot(tuple(chain), offsets, tuple(pts), np.zeros(len(pts)))
        rest = foot_points(plan, origin[chain[0]], wfb)[:, 2]
        # The heel: under the ankle at the level of the foot's lowest point in the
        # calibration (feet flat on the floor), fixed in the foot bone; the point
        # Ghoussayni's foot-strike threshold is applied to.
        drop = np.array([0.0, 0.0, rest.min() - rest[0]])
        heel = rot.quat_rotate(rot.quat_conj(wfb[foot]), drop)
        plan = _Foot(plan.chain, offsets, plan.points, rest, heel)
        rest = foot_points(plan, origin[chain[0]], wfb)[:, 2]
        feet.append(_Foot(plan.chain, offsets, plan.points, rest, heel))
    return tuple(feet)


def foot_points(foot: _Foot, root_pos: F64Array, wfb: F64Array) -> F64Array:
    """(P, 3) a foot's points posed from one frame's root position and rotations."""
    origins = {foot.chain[0]: np.asarray(root_pos, dtype=np.float64)}
    for k in range(1, len(foot.chain)):
        b, p = foot.chain[k], foot.chain[k - 1]
        origins[b] = origins[p] + rot.quat_rotate(wfb[p], foot.offsets[k])
    n = len(foot.points)
    out = np.empty((n + (foot.heel is not None), 3))
    for i, (b, ln) in enumerate(foot.points):
        out[i] = origins[b] if ln < 0 else origins[b] + rot.quat_rotate(wfb[b], ln * _Y)
    if foot.heel is not None:
        b = foot.points[0][0]
        out[n] = origins[b] + rot.quat_rotate(wfb[b], foot.heel)
    return out


class StanceDetector:
    """Per-foot contact, causal, frame by frame (module docstring)."""

    def __init__(
        self, rig: Rig, calibration: Calibration, params: dict[str, float] | None = None
    ) -> None:
        self.p = {**STANCE, **(params or {})}
        self.feet = _feet(rig, calibration)
        self.contact = [False, False]
        #: Each foot's support level above the calibration's floor, metres.
        self.support = [0.0, 0.0]
        self._still = [0.0, 0.0]
        self._prev: list[F64Array | None] = [None, None]
        self._vel = [np.zeros((len(f.rest_z), 3)) for f in self.feet]

    @property
    def known(self) -> bool:
        """Whether the rig maps both feet (else the contact is never set)."""
        return bool(self.feet)

    def reset(self) -> None:
        """Forget the history (a new stream): the next frame starts afresh."""
        self.contact = [False, False]
        self.support = [0.0, 0.0]
        self._still = [0.0, 0.0]
        self._prev = [None, None]

    def update(
        self, root_pos: F64Array, world_from_bone_quat: F64Array, dt: float
    ) -> int:
        """Advance one frame; returns the flag bits (LEFT, RIGHT, KNOWN).

        Args:
            root_pos: (3,) metres, world.
            world_from_bone_quat: (B, 4) w x y z.
            dt: seconds since the previous frame (0 or less: no history, e.g. the
                first frame).
        """
        if not self.feet:
            return 0
        p = self.p
        bits = KNOWN
        for s, foot in enumerate(self.feet):
            pts = foot_points(foot, root_pos, world_from_bone_quat)
            prev = self._prev[s]
            vel = self._vel[s]
            if prev is None or not dt > 0.0:
                vel[:] = 0.0
                self._still[s] = 0.0
                speed = np.zeros(len(pts))
            else:
                raw = (pts - prev) / dt
                speed = np.sqrt((raw * raw).sum(axis=1))
                alpha = dt / (dt + 1.0 / (2.0 * math.pi * p["cutoff_hz"]))
                vel += alpha * (raw - vel)
            self._prev[s] = pts
            level = pts[:, 2] - foot.rest_z
            h = level - self.support[s]
            slowest = float(np.sqrt((vel * vel).sum(axis=1)).min())
            if prev is not None and dt > 0.0:
                if slowest < p["still_speed_m_s"]:
                    self._still[s] += dt
                else:
                    self._still[s] = 0.0
            still = self._still[s] >= p["still_s"]
            if still:  # stopped here: this is the foot's support now
                self.support[s] = float(level.min())
                h = level - self.support[s]
            near = h < p["near_m"]
            if self.contact[s]:
                on = still or bool(np.any(near & (speed < p["off_speed_m_s"])))
            else:
                on = still or bool(np.any(near & (speed < p["on_speed_m_s"])))
            self.contact[s] = on
            if on:
                bits |= LEFT if s == 0 else RIGHT
        return bits


def foot_contact(
    rig: Rig,
    calibration: Calibration,
    root_pos: F64Array,
    world_from_bone_quat: F64Array,
    rate_hz: float,
) -> np.ndarray:
    """(T, 2) bool, left and right foot in contact per frame of a solved take: the
    live detector run over the frames at ``rate_hz`` (``retargetd solve``'s
    ``foot_contact``)."""
    det = StanceDetector(rig, calibration)
    n = root_pos.shape[0]
    out = np.zeros((n, 2), dtype=bool)
    dt = 1.0 / rate_hz
    for t in range(n):
        bits = det.update(root_pos[t], world_from_bone_quat[t], dt if t else 0.0)
        out[t, 0] = bool(bits & LEFT)
        out[t, 1] = bool(bits & RIGHT)
    return out
