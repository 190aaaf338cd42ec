"""Stance from the solve: per foot, is it on the ground (issue 34, item 1).

One causal detector, frame by frame, shared by the live daemon (``live/send.py``, on
every solved frame before the post stages) and ``retargetd solve`` (the NPZ's
``foot_contact``), so offline equals live.

Foot points. The humanoid ``LeftFoot``/``RightFoot`` bones (every shipped rig maps
them): the foot bone's origin (the ankle) and its aim (the forefoot marker or point the
rig aims it at), the toes bone's aim when the rig maps ``LeftToes``/``RightToes``, and
a heel, under the ankle at the level of the foot's lowest point in the calibration. They
are posed from the solved world rotations, the root position and the calibrated
rest offsets (``origin_b = origin_p + wfb_p * offset_b``, ``aim_b = origin_b + wfb_b *
(0, L_b, 0)``), so any solver's output (the joint centres need not name them) works.

Height. The calibration is taken standing on the floor, so each point's calibrated
height is its height when standing; ``h = z - z_rest - s`` is its height above that,
with ``s`` the foot's support level: 0 (the calibration's floor) until the foot stops
somewhere else (a step, a riser), then that level.

Speed. Each point's frame-to-frame speed for the on/off thresholds (they sit far above
the solve's noise: a causal low-pass would delay each strike by its lag, 30-40 ms on the
PiG walk); the stop-at-any-height rule, whose speed is near the noise, uses the speed
low-passed by a one-pole filter at :data:`STANCE` ``cutoff_hz`` (causal).

One frame is one compiled call (:func:`_step`, numba, nothing allocated), on state the
detector owns.

Contact (with hysteresis: two speeds, after the foot-velocity algorithms):

* on when some point is slower than ``on_speed_m_s`` within ``near_m`` of the support
  level (above or below it); or when the foot has *landed* at another level while the
  other foot stands (a step onto a riser or down a stair: some point stationary,
  slower than ``still_speed_m_s``, in the frame its descent was braked, i.e. its
  vertical speed was negative and rose: gravity alone only speeds a descent up, so a
  foot at a ballistic apex never qualifies); or when the foot has been slower than
  ``still_speed_m_s`` for ``still_s`` at any height (a foot set down slowly, or
  landing from a flight);
* off when no point is both slower than ``off_speed_m_s`` and within ``near_m``, and the
  foot is not still; or when it *lifts off*: a foot on its support turns about its
  lowest point, which stays on it, so that point rising faster than
  ``still_speed_m_s`` (frame to frame) while more than ``heel_rise_m`` above the
  support has left it. A slow toe-off (stair ascent and descent, a run's first
  strides) reaches Bonci's foot-off speed only on the 3rd-4th frame after the toe
  leaves (synthetic stair ascent at 120 Hz: the forefoot at 0.21, 0.58, 0.93, 1.10
  m/s in the four frames after), its lowest point 11 mm up and rising at 0.9 m/s on
  the 3rd. A foot it let go is not on again by the near rule (a strike: slow near
  the support) until it comes down: its lowest point descending, or back within
  ``heel_rise_m`` of the support (the stop and landing rules are unchanged). A foot
  rising slower than the on-speed near the floor (the synthetic run's first swing,
  in its start-up ramp) was let go and struck again by turns, frame by frame.

Support. A contact that starts at another level (landed, or stopped) takes the level
of the foot's lowest point then; while the foot is still it follows that point as the
foot settles (a forefoot landing lowers its heel), until the heel rises (``heel_rise_m``
above the lowest point and going up: heel-off), when it is frozen for the rest of the
contact: from heel-off the foot rolls about its forefoot, and a point fixed in the foot
ahead of the roll's axis dips below its standing height (the PiG walk's forefoot aim:
6.6 mm) without the support moving. A level within ``near_m`` of the calibration's floor
is the floor (0): the solved foot's standing height wanders a few mm with the pose
(-2.5 to +4 mm on the synthetic walk), the floor's height is known.

Support, offline. Where the whole take is known (``solve --plant-feet`` and the other
offline commands, ``cli/post_io.retarget_solve``), each contact's support is, the
whole contact long, the level the detector had settled on by its last frame
(:func:`settled_support`): the foot's evidence over the whole contact rather than its
landing frame. The solved foot's height carries the solve's error of the moment, which
is largest with the thigh flexed: on the synthetic stair ascent (Plug-in Gait), the
regression hip joint centre 12 mm below the performer's puts the solved foot 2.9 mm
below the step at landing (thigh flexed) and 0.1 mm below it once settled, the thigh
near the calibration's standing pose. The contact itself is the live detector's, so
offline and live differ only in a support off the floor that moved during its
contact. (Off the floor the plant holds the foot on the level of the target's own
sole rather than on this one, which the points above the sole read high on a pitched
foot: ``post/plant_level.py``.)

Known limits: a foot held still in the air for longer than ``still_s`` (or, while the
other foot stands, braked to a stop there) reads as a foot on a support (the feet alone
cannot tell a riser from a held pose); a held (occluded) foot bone does not move, so it
reads as standing; a support within ``near_m`` of the floor (a mat, a low platform) is
the floor.
"""

from __future__ import annotations

import math

import numpy as np

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.calibration import Calibration
from retargetd.daemon.body.rig import Rig
from retargetd.daemon.compiled import direct, kernel, qrot
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
    # Stopped at any height (a step): slower than this for still_s, or at once in
    # the frame a descent is braked while the other foot stands (landed). 0.2 m/s is
    # the stationary speed of the floating check (validate/dynamics.py CONTACT); a
    # ballistic foot is under it for 2 * 0.2 / 9.81 = 41 ms at a jump's apex, so
    # still_s is twice that.
    "still_speed_m_s": 0.20,
    "still_s": 0.082,
    # Low-pass of the stillness speed, Hz: Winter's ~6 Hz for gait kinematics
    # (Winter 2009, Biomechanics and Motor Control of Human Movement, 4th ed., ch. 2).
    "cutoff_hz": 6.0,
    # Heel-off: the heel this far above the foot's lowest point and rising; and
    # lift-off: the lowest point this far above the support and rising. The plant's
    # pivot switch (post/plant.py PLANT pivot_switch_m, a quarter of near_m): above
    # the solved foot's rocking on a flat floor, far below a heel-off's rise.
    "heel_rise_m": 0.01,
}
_PARAMS = (
    "on_speed_m_s", "off_speed_m_s", "near_m", "still_speed_m_s", "still_s",
    "heel_rise_m",
)  # fmt: skip

#: The flag bits :meth:`StanceDetector.update` returns (the pose stream's).
LEFT, RIGHT, KNOWN = FRAME_CONTACT_LEFT, FRAME_CONTACT_RIGHT, FRAME_CONTACT_KNOWN
_SIDES = (("LeftFoot", "LeftToes"), ("RightFoot", "RightToes"))
_MAX_POINTS = 4  # ankle, forefoot (the foot's aim), toe tip (a toes bone), heel
# State columns per foot: has history, seconds still, support level, contact, the
# support frozen (heel-off) for the rest of this contact (1) or, out of contact, the
# foot lifted off and not come down since (_LIFTED).
_HAS, _STILL, _SUPPORT, _CONTACT, _FROZEN = 0, 1, 2, 3, 4
_LIFTED = 2.0
#: :attr:`StanceDetector.state`'s columns a later stage reads (post/plant.py): the
#: support level (metres above the calibration's floor) and the contact (0 or 1).
SUPPORT_COLUMN, CONTACT_COLUMN = _SUPPORT, _CONTACT


class _Plan:
    """Both feet's chains (root .. foot bone), each bone's origin in its parent's
    rest frame, and the points: (bone, offset in that bone's frame), rest height."""

    def __init__(self, rig: Rig, cal: Calibration) -> None:
        parents = [int(p) for p in cal.bone_parents]
        names = list(cal.bone_names)
        wfb = np.asarray(cal.rest_world_from_bone_quat, dtype=np.float64)
        origin = np.asarray(cal.rest_bone_origin_pos, dtype=np.float64)
        lengths = np.asarray(cal.bone_lengths, dtype=np.float64)
        chains: list[list[int]] = []
        points: list[list[tuple[int, F64Array]]] = []
        for foot_name, toes_name in _SIDES:
            b = names.index(rig.humanoid[foot_name])
            chain: list[int] = []
            while b >= 0:
                chain.insert(0, b)
                b = parents[b]
            foot = chain[-1]
            pts = [(foot, np.zeros(3)), (foot, np.array([0.0, lengths[foot], 0.0]))]
            toes = rig.humanoid.get(toes_name)
            if toes is not None and parents[names.index(toes)] == foot:
                t = names.index(toes)
                chain.append(t)
                pts.append((t, np.array([0.0, lengths[t], 0.0])))
            chains.append(chain)
            points.append(pts)
        n_chain = max(len(c) for c in chains)
        self.chain = np.full((2, n_chain), -1, dtype=np.int64)
        self.chain_len = np.array([len(c) for c in chains], dtype=np.int64)
        self.offset = np.zeros((2, n_chain, 3))
        self.pt_link = np.zeros((2, _MAX_POINTS), dtype=np.int64)  # index in chain
        self.pt_local = np.zeros((2, _MAX_POINTS, 3))
        self.n_pts = np.zeros(2, dtype=np.int64)
        self.rest_z = np.zeros((2, _MAX_POINTS))
        for s, (chain, pts) in enumerate(zip(chains, points, strict=True)):
            self.chain[s, : len(chain)] = chain
            for k in range(1, len(chain)):
                c, p = chain[k], chain[k - 1]
                self.offset[s, k] = rot.quat_rotate(
                    rot.quat_conj(wfb[p]), origin[c] - origin[p]
                )
            for i, (b, local) in enumerate(pts):
                self.pt_link[s, i] = chain.index(b)
                self.pt_local[s, i] = local
            rest = [(origin[b] + rot.quat_rotate(wfb[b], local))[2] for b, local in pts]
            # The heel: under the ankle at the level of the foot's lowest point in
            # the calibration (feet flat on the floor), fixed in the foot bone; the
            # point Ghoussayni's foot-strike threshold is applied to.
            foot = pts[0][0]  # the ankle's bone
            drop = np.array([0.0, 0.0, min(rest) - rest[0]])
            n = len(pts)
            self.pt_link[s, n] = chain.index(foot)
            self.pt_local[s, n] = rot.quat_rotate(rot.quat_conj(wfb[foot]), drop)
            self.n_pts[s] = n + 1
            self.rest_z[s, :n] = rest
            self.rest_z[s, n] = min(rest)


@kernel(inline="always")
def _rotate(
    q: np.ndarray, b: int, vx: float, vy: float, vz: float
) -> tuple[float, float, float]:  # pragma: no cover - compiled
    """q[b] (w x y z, unit) applied to v: v + 2 w (u x v) + 2 u x (u x v)."""
    return qrot(q[b, 0], q[b, 1], q[b, 2], q[b, 3], vx, vy, vz)


@kernel
def _step(
    root_pos: np.ndarray,  # (3,)
    wfb: np.ndarray,  # (B, 4)
    dt: float,
    chain: np.ndarray,  # (2, C) int64
    chain_len: np.ndarray,  # (2,) int64
    offset: np.ndarray,  # (2, C, 3)
    pt_link: np.ndarray,  # (2, P) int64
    pt_local: np.ndarray,  # (2, P, 3)
    n_pts: np.ndarray,  # (2,) int64
    rest_z: np.ndarray,  # (2, P)
    params: np.ndarray,  # (7,) _PARAMS, then the low-pass time constant, s
    origins: np.ndarray,  # (2, C, 3) scratch
    prev: np.ndarray,  # (2, P, 4) state: last frame's points, their vertical speed
    vel: np.ndarray,  # (2, P, 3) state: low-passed velocity
    state: np.ndarray,  # (2, 5) state: _HAS, _STILL, _SUPPORT, _CONTACT, _FROZEN
) -> int:  # pragma: no cover - compiled
    """One frame of both feet (module docstring); returns the contact bits 0-1."""
    on_v, off_v, near_m, still_v, still_s, rise_m, tau = (
        params[0], params[1], params[2], params[3], params[4], params[5], params[6],
    )  # fmt: skip
    out = 0
    # Last frame's contact of each foot: a landing at a new level is a step (the
    # other foot stands); a foot coming down from a flight waits to be still.
    stood = (state[0, _CONTACT] != 0.0, state[1, _CONTACT] != 0.0)
    for s in range(2):
        for k in range(3):
            origins[s, 0, k] = root_pos[k]
        for j in range(1, chain_len[s]):
            p = chain[s, j - 1]
            rx, ry, rz = _rotate(
                wfb, p, offset[s, j, 0], offset[s, j, 1], offset[s, j, 2]
            )
            origins[s, j, 0] = origins[s, j - 1, 0] + rx
            origins[s, j, 1] = origins[s, j - 1, 1] + ry
            origins[s, j, 2] = origins[s, j - 1, 2] + rz
        fresh = state[s, _HAS] == 0.0 or not dt > 0.0
        alpha = 0.0 if fresh else dt / (dt + tau)
        support = state[s, _SUPPORT]
        slowest = math.inf
        lowest = math.inf
        any_on = False
        any_hold = False
        landed = False
        heel = n_pts[s] - 1  # the heel is the last point (_Plan)
        heel_level = 0.0
        heel_vz = 0.0
        lowest_vz = 0.0
        for i in range(n_pts[s]):
            j = pt_link[s, i]
            b = chain[s, j]
            rx, ry, rz = _rotate(
                wfb, b, pt_local[s, i, 0], pt_local[s, i, 1], pt_local[s, i, 2]
            )
            px = origins[s, j, 0] + rx
            py = origins[s, j, 1] + ry
            pz = origins[s, j, 2] + rz
            speed = 0.0
            vz = 0.0
            if fresh:
                vel[s, i, 0] = vel[s, i, 1] = vel[s, i, 2] = 0.0
            else:
                dx = (px - prev[s, i, 0]) / dt
                dy = (py - prev[s, i, 1]) / dt
                vz = (pz - prev[s, i, 2]) / dt
                speed = math.sqrt(dx * dx + dy * dy + vz * vz)
                vel[s, i, 0] += alpha * (dx - vel[s, i, 0])
                vel[s, i, 1] += alpha * (dy - vel[s, i, 1])
                vel[s, i, 2] += alpha * (vz - vel[s, i, 2])
                # Landed: stationary (still_v) at once, its descent braked (it
                # came down and something stopped it: gravity alone only speeds a
                # descent up, so a ballistic foot at its apex never qualifies).
                vz_prev = prev[s, i, 3]
                if speed < still_v and vz_prev < 0.0 and vz > vz_prev:
                    landed = True
            prev[s, i, 0], prev[s, i, 1], prev[s, i, 2] = px, py, pz
            prev[s, i, 3] = vz
            v = vel[s, i]
            slowest = min(slowest, math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]))
            level = pz - rest_z[s, i]
            if level < lowest:
                lowest, lowest_vz = level, vz
            if i == heel:
                heel_level, heel_vz = level, vz
            if abs(level - support) < near_m:
                any_on = any_on or speed < on_v
                any_hold = any_hold or speed < off_v
        if fresh:
            state[s, _STILL] = 0.0
        elif slowest < still_v:
            state[s, _STILL] += dt
        else:
            state[s, _STILL] = 0.0
        state[s, _HAS] = 1.0
        still = state[s, _STILL] >= still_s
        was = state[s, _CONTACT] != 0.0
        # Lifted off and not come down since (below): the near rule's strike needs
        # the foot to come back down first.
        if not was and state[s, _FROZEN] == _LIFTED:
            if lowest_vz < 0.0 or lowest - support <= rise_m:
                state[s, _FROZEN] = 0.0
            else:
                any_on = False
        # held by the near rule (hysteresis), else on by it, or landed on a new
        # level while the other foot stands
        on = still or (any_hold if was else any_on or (landed and stood[1 - s]))
        # Lift-off: a foot on its support turns about its lowest point, which stays
        # on it; that point rising, faster than a stationary point moves
        # (still_v), and above the support by more than the solved foot rocks on a
        # flat floor (rise_m) has left it, whatever the other rules hold.
        lifted = was and lowest_vz > still_v and lowest - support > rise_m
        if lifted:
            on = False
        # The support: the calibration's floor where the foot stands within near_m
        # of it, else the level of its lowest point (a step, a riser).
        here = 0.0 if abs(lowest) < near_m else lowest
        if on and not was:
            state[s, _FROZEN] = 0.0
            if not any_on:  # a new level: the foot came down (or stopped) there
                state[s, _SUPPORT] = here
        if on and still and state[s, _FROZEN] == 0.0:
            # Settling (the foot lowering onto its support): the support follows
            # the foot's lowest point, until the heel rises (heel-off, Perry &
            # Burnfield's terminal stance): the foot then rolls about its
            # forefoot and its points' height no longer tells the support's.
            if heel_level - lowest > rise_m and heel_vz > 0.0:
                state[s, _FROZEN] = 1.0
            else:
                state[s, _SUPPORT] = here
        if lifted:
            state[s, _FROZEN] = _LIFTED
        elif not on and state[s, _FROZEN] != _LIFTED:
            state[s, _FROZEN] = 0.0
        state[s, _CONTACT] = 1.0 if on else 0.0
        if on:
            out |= 1 << s
    return out


@kernel
def step_packed(
    root_pos: np.ndarray,  # (3,)
    wfb: np.ndarray,  # (B, 4)
    dt: float,
    ints: np.ndarray,  # int64: StanceDetector.pack()'s
    floats: np.ndarray,  # float64: StanceDetector.pack()'s
) -> int:  # pragma: no cover - compiled
    """:meth:`StanceDetector.update` over the detector's arrays packed into two flat
    arrays (:meth:`StanceDetector.pack`), for a caller that runs it inside its own
    compiled call (``live/emit.py``: two arguments, not thirteen): the clock, then
    :func:`_step`; returns the pose stream's flag bits (LEFT, RIGHT, KNOWN)."""
    c, p, n_par = ints[0], ints[1], ints[2]
    at = 3
    chain = ints[at : at + 2 * c].reshape((2, c))
    at += 2 * c
    chain_len = ints[at : at + 2]
    at += 2
    pt_link = ints[at : at + 2 * p].reshape((2, p))
    at += 2 * p
    n_pts = ints[at : at + 2]
    offset = floats[1 : 1 + 6 * c].reshape((2, c, 3))
    k = 1 + 6 * c
    pt_local = floats[k : k + 6 * p].reshape((2, p, 3))
    k += 6 * p
    rest_z = floats[k : k + 2 * p].reshape((2, p))
    k += 2 * p
    params = floats[k : k + n_par]
    k += n_par
    origins = floats[k : k + 6 * c].reshape((2, c, 3))
    k += 6 * c
    prev = floats[k : k + 8 * p].reshape((2, p, 4))
    k += 8 * p
    vel = floats[k : k + 6 * p].reshape((2, p, 3))
    k += 6 * p
    state = floats[k : k + 10].reshape((2, 5))
    if dt > 0.0:
        floats[0] += dt  # the clock
    bits = _step(
        root_pos, wfb, dt, chain, chain_len, offset, pt_link, pt_local, n_pts,
        rest_z, params, origins, prev, vel, state,
    )  # fmt: skip
    return KNOWN | (LEFT if bits & 1 else 0) | (RIGHT if bits & 2 else 0)


class StanceDetector:
    """Per-foot contact, causal, frame by frame (module docstring)."""

    def __init__(
        self, rig: Rig, calibration: Calibration, params: dict[str, float] | None = None
    ) -> None:
        p = {**STANCE, **(params or {})}
        self.known = calibration.rest_bone_origin_pos is not None and all(
            f in rig.humanoid for f, _ in _SIDES
        )
        """Whether the rig maps both feet (else the contact is never set)."""
        self.rig, self.calibration = rig, calibration
        self._plan = _Plan(rig, calibration) if self.known else None
        tau = 1.0 / (2.0 * math.pi * p["cutoff_hz"])
        self._params = np.array([*(p[k] for k in _PARAMS), tau])
        n_chain = self._plan.chain.shape[1] if self._plan is not None else 1
        self._origins = np.zeros((2, n_chain, 3))
        self._prev = np.zeros((2, _MAX_POINTS, 4))
        self._vel = np.zeros((2, _MAX_POINTS, 3))
        self._state = np.zeros((2, 5))
        self.clock = np.zeros(1)
        """(1,) seconds: the sum of the frame intervals given to :meth:`update` (a
        later stage's clock, post/plant.py)."""
        self._call: object = _step

    @property
    def contact(self) -> tuple[bool, bool]:
        """Left and right foot in contact after the last frame."""
        return bool(self._state[0, _CONTACT]), bool(self._state[1, _CONTACT])

    @property
    def state(self) -> np.ndarray:
        """(2, 5) the detector's own state array (left, right), updated in place
        every frame: read :data:`SUPPORT_COLUMN` and :data:`CONTACT_COLUMN` without a
        copy (the plant stage's input)."""
        return self._state

    @property
    def support(self) -> tuple[float, float]:
        """Each foot's support level above the calibration's floor, metres."""
        return float(self._state[0, _SUPPORT]), float(self._state[1, _SUPPORT])

    def reset(self) -> None:
        """Forget the history (a new stream): the next frame starts afresh."""
        self._state[:] = 0.0
        self.clock[0] = 0.0

    def pack(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Its plan, parameters, scratch, state and clock in two flat arrays, int64
        and float64 (:func:`step_packed`'s layout), which its own arrays become
        views of (contents kept: :meth:`update`, :meth:`reset`, :attr:`state` and
        :attr:`clock` read and write the same memory as :func:`step_packed`). For a
        caller that runs the step inside its own compiled call (``live/emit.py``).
        None when the rig maps no feet (no step runs)."""
        plan = self._plan
        if plan is None:
            return None
        c, p = plan.chain.shape[1], plan.pt_link.shape[1]
        ints_of = (plan.chain, plan.chain_len, plan.pt_link, plan.n_pts)
        floats_of = (
            self.clock, plan.offset, plan.pt_local, plan.rest_z, self._params,
            self._origins, self._prev, self._vel, self._state,
        )  # fmt: skip
        head = np.array([c, p, len(self._params)], dtype=np.int64)
        ints = np.concatenate([head, *(a.ravel() for a in ints_of)]).astype(np.int64)
        floats = np.concatenate([a.ravel() for a in floats_of])
        plan.chain, plan.chain_len, plan.pt_link, plan.n_pts = _views(ints, 3, ints_of)
        (
            self.clock, plan.offset, plan.pt_local, plan.rest_z, self._params,
            self._origins, self._prev, self._vel, self._state,
        ) = _views(floats, 0, floats_of)  # fmt: skip
        self._call = _step  # (its entry point found again for the views)
        return ints, floats

    def update(
        self, root_pos: F64Array, world_from_bone_quat: F64Array, dt: float
    ) -> int:
        """Advance one frame; returns the pose stream's flag bits (LEFT, RIGHT, KNOWN).

        Args:
            root_pos: (3,) float64 metres, world.
            world_from_bone_quat: (B, 4) float64 w x y z.
            dt: seconds since the previous frame (0 or less: no history, e.g. the
                first frame).
        """
        if dt > 0.0:
            self.clock[0] += dt
        plan = self._plan
        if plan is None:
            return 0
        args = (
            root_pos, world_from_bone_quat, float(dt), plan.chain, plan.chain_len,
            plan.offset, plan.pt_link, plan.pt_local, plan.n_pts, plan.rest_z,
            self._params, self._origins, self._prev, self._vel, self._state,
        )  # fmt: skip
        if self._call is _step:  # the compiled entry point once it exists
            self._call = direct(_step, *args)
        bits: int = self._call(*args)  # type: ignore[operator]
        return KNOWN | (LEFT if bits & 1 else 0) | (RIGHT if bits & 2 else 0)


def _views(
    flat: np.ndarray, at: int, arrays: tuple[np.ndarray, ...]
) -> list[np.ndarray]:
    """Views of ``flat`` from ``at`` on, one after the other, shaped as ``arrays``."""
    out = []
    for a in arrays:
        out.append(flat[at : at + a.size].reshape(a.shape))
        at += a.size
    return out


def foot_contact(
    rig: Rig,
    calibration: Calibration,
    root_pos: F64Array,
    world_from_bone_quat: F64Array,
    rate_hz: float,
    support: np.ndarray | None = None,
) -> np.ndarray:
    """(T, 2) bool, left and right foot in contact per frame of a solved take: the
    live detector run over the frames at ``rate_hz`` (``retargetd solve``'s
    ``foot_contact``; all False when the rig maps no LeftFoot/RightFoot). With
    ``support`` ((T, 2) float64), also each foot's support level per frame, metres
    above the calibration's floor (the module docstring's; 0 where unknown)."""
    det = StanceDetector(rig, calibration)
    root = np.ascontiguousarray(root_pos, dtype=np.float64)
    wfb = np.ascontiguousarray(world_from_bone_quat, dtype=np.float64)
    n = root.shape[0]
    out = np.zeros((n, 2), dtype=bool)
    dt = 1.0 / rate_hz
    for t in range(n):
        bits = det.update(root[t], wfb[t], dt if t else 0.0)
        out[t, 0] = bool(bits & LEFT)
        out[t, 1] = bool(bits & RIGHT)
        if support is not None:
            support[t] = det.state[:, _SUPPORT]
    return out


def settled_support(contact: np.ndarray, support: np.ndarray) -> F64Array:
    """(T, 2) each foot's support level, per contact run the level the detector had
    settled on by the run's last frame (the contact's evidence as a whole, module
    docstring "Support, offline"); as ``support`` outside contact. ``contact``
    (T, 2) bool and ``support`` (T, 2) metres are :func:`foot_contact`'s."""
    out = np.array(support, dtype=np.float64)
    for s in range(2):
        d = np.diff(np.concatenate([[0], contact[:, s].astype(np.int8), [0]]))
        for a, b in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1), strict=True):
            out[a:b, s] = support[b - 1, s]
    return out


def take_stance_states(
    rig: Rig,
    calibration: Calibration,
    root_pos: F64Array,
    world_from_bone_quat: F64Array,
    rate_hz: float,
) -> F64Array:
    """(T, 2, 5) per frame of a whole take, the :attr:`StanceDetector.state` a later
    stage reads (:data:`CONTACT_COLUMN`, :data:`SUPPORT_COLUMN`; the other columns
    0): the live detector's contact, with the support of each contact settled over
    the whole contact (:func:`settled_support`). The offline plant's input
    (``cli/post_io.retarget_solve``), where the take is known in full."""
    support = np.zeros((len(root_pos), 2))
    contact = foot_contact(
        rig, calibration, root_pos, world_from_bone_quat, rate_hz, support
    )
    out = np.zeros((len(root_pos), 2, 5))
    out[:, :, CONTACT_COLUMN] = contact
    out[:, :, SUPPORT_COLUMN] = settled_support(contact, support)
    return out
