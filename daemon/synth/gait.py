"""Gaits whose stance feet stay put: the root's travel derived from the stance leg.

A gait (``synth.motion``: ``level_walk``, ``run``, ``stair_ascent``,
``stair_descent``) gives joint angles and a contact schedule (each foot's phase, its
toe-off); this module places the body so that no foot slides or sinks
(:func:`plant_gait`).

- **Foot flat, toes flat.** In stance the foot is held flat from the moment its
  joint-angle pitch first comes down to the floor until the heel rises for good; from
  heel-off to toe-off the toes stay flat on the floor (the MTP joint extends) while
  the foot rolls about them, and they ease back to their joint angle over
  :data:`RELEASE_S` after toe-off.
- **Drive.** Frame by frame one foot in contact *drives*: its lowest sole point
  (heel, ball under the MTP joint, toe tip; relative to the ankle, a function of the
  foot's orientation alone) is an anchor on its support, and the root is that anchor
  less the point's offset from the root under the joint angles, in all three axes.
  The foot rolls: when another of its points goes lower, that point becomes the
  anchor where it is (level with the old one then, so nothing jumps).
- **Strike.** A foot in the air lands at its heel strike (phase 0) on the next
  support (the floor; on stairs the other foot's step plus the riser, up or down):
  it drives from then on, the foot that drove is *held* (two-bone inverse
  kinematics of hip-knee-ankle, the knee bending about its own hinge, the foot
  keeping its world rotation) until its own toe-off. The root passes from the old
  foot's placement to the new one's over :data:`LOAD_S` (smoothstep), so the pelvis
  keeps its velocity. Where the landing foot would still be above its support, the
  root is lowered over the terminal swing (:data:`LAND_S`; the stance leg bends);
  where it would be below, the swing foot is raised over the terminal swing and the
  new stance leg keeps that shortening until the other foot lets go, then gives it
  up over :data:`LOAD_S`.
- **Double support.** The pelvis sinks where the held foot's leg would otherwise
  straighten past :data:`REACH_FRACTION` of its length, and rises back over
  :data:`LOAD_S` once it lets go.
- **Toe-off.** A held foot lets go at its scheduled toe-off; the correction its hold
  needed blends out over :data:`RELEASE_S`, in the air. A foot in the air is never
  let below the support it left or the one it is to land on (the inverse kinematics
  raises it). With flight (``GaitPlan.flight``: the run) the driver lets go too: the
  root is eased over the push-off onto a ballistic path (gravity alone) whose
  take-off velocity lands it on time, and passes to the new stance foot's placement
  over :data:`LOAD_S`.
- **Swing.** A foot swinging from one support to a strike on the same level clears
  it by :data:`SWING_CLEARANCE_M` at mid-swing (the minimum toe clearance; the
  inverse kinematics raises it where the joint angles would not, as in a ramp's
  first strides).

The truth then holds where each foot is in contact (``foot_contact``: driving or
held, the held ankle within :data:`REACH_TOL_M` of its goal) and on which support
(``foot_support_m``); a foot in contact does not slide and no sole point is below its
support (``tests/daemon/test_synth_gait.py``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from retargetd.daemon import rotations as rot
from retargetd.daemon.synth.skeleton import Skeleton
from retargetd.protocols.frames import BoolArray, F64Array

#: Gravity, m/s^2 (the flight of a run).
GRAVITY_M_S2 = 9.81
#: A released foot's lock correction blends out over this (s): a third of a walk's
#: swing, which lasts 40 % of a 1.1 s cycle (Winter 2009, Biomechanics and Motor
#: Control of Human Movement, 4th ed., ch. 1 and table A.3 normative gait).
RELEASE_S = 0.15
#: A strike's height mismatch, carried by the new stance leg, blends out over the
#: loading response (0-10 % of a ~1.1 s cycle: Perry & Burnfield 2010, ch. 1).
LOAD_S = 0.10
#: ... and blends in over the terminal swing before it (85-100 %: ibid.).
LAND_S = 0.15

#: In double support a held foot's ankle stays within this fraction of the leg's
#: length (hip to ankle, straight) of the hip: the knee keeps 16 deg of flexion
#: (Winter 2009: ~10-20 deg at 50-60 % of the cycle), and a leg pulled straight would
#: pop its knee when it lets go.
REACH_FRACTION = 0.99
#: A held ankle this far from its goal has let go of its support (metres).
REACH_TOL_M = 3e-3
#: A swing foot between two supports on one level clears it by at least this in
#: mid-swing (metres): the minimum toe clearance, 1.29 +- 0.45 cm (Winter 1992, Phys
#: Ther 72:45-53). The floor it sets rises as sin^2 from 0 at toe-off to this at
#: mid-swing and back to 0 at the strike (no faster than the foot leaves and meets
#: the floor), so a swing that clears it anyway is unchanged; without it the joint
#: angles of a ramp's first strides (scaled down with the cadence) left the swing
#: foot on the floor, dragged along it (the run's first swing: 63 mm).
SWING_CLEARANCE_M = 0.0129

_DRIVE, _LOCK, _RELEASE, _SWING = 0, 1, 2, 3


@dataclass(frozen=True, slots=True, kw_only=True)
class GaitPlan:
    """What :func:`plant_gait` needs to know of a gait beyond its joint angles.

    Attributes:
        phase: (T, 2) float64 radians, each foot's gait phase (left, right): 0 at its
            heel strike, increasing.
        toe_off: toe-off as a fraction of the cycle (stance = [0, toe_off)), or (T,)
            one per frame (a gait whose stance shortens as it gets up to speed).
        rise_m: the support's change from one foot's step to the other's, metres (0:
            level ground; + up a stair, - down).
        flight: whether the driver may leave before the other foot lands (a run).
        moving: (T,) bool, the gait under way (no event before it).
        toes_flat: whether the toes stay flat on the floor from heel-off to toe-off
            (False: the foot rolls onto the tip of its toes, as in stair descent,
            where the stance foot lowers the body from its forefoot).
    """

    phase: F64Array
    toe_off: float | F64Array
    rise_m: float = 0.0
    flight: bool = False
    moving: BoolArray
    toes_flat: bool = True


@dataclass(frozen=True, slots=True, kw_only=True)
class PlantedGait:
    """The placed gait.

    Attributes:
        parent_from_segment: (T, S, 4) float64 (w, x, y, z), the legs corrected.
        root_pos: (T, 3) float64 metres, world: the pelvis.
        contact: (T, 2) bool, left / right foot in contact (driving or locked).
        support_m: (T, 2) float64 metres, world z of each foot's support (the last
            one it stood on while in the air).
        unreached_m: the largest distance by which a held ankle missed its goal (the
            leg straight), metres; where it does (by more than
            :data:`REACH_TOL_M`), the foot is not in contact.
    """

    parent_from_segment: F64Array
    root_pos: F64Array
    contact: BoolArray
    support_m: F64Array
    unreached_m: float


def _smoothstep(u: float) -> float:
    u = min(max(u, 0.0), 1.0)
    return u * u * (3.0 - 2.0 * u)


def plant_gait(
    skeleton: Skeleton,
    parent_from_segment: F64Array,
    world_from_segment: F64Array,
    joint_pos_root: F64Array,
    root0: F64Array,
    plan: GaitPlan,
    rate_hz: float,
) -> PlantedGait:
    """Place a gait so that its stance feet stay put (module docstring).

    Args:
        skeleton: the performer's skeleton.
        parent_from_segment: (T, S, 4) (w, x, y, z) from the joint angles.
        world_from_segment: (T, S, 4) (w, x, y, z) their forward kinematics.
        joint_pos_root: (T, S, 3) metres, the joint centres less the root's position.
        root0: (3,) metres, world: the pelvis at frame 0 (both soles on the floor).
        plan: the gait's :class:`GaitPlan`.
        rate_hz: frame rate.

    Returns:
        The :class:`PlantedGait`.
    """
    n_frames = parent_from_segment.shape[0]
    seg = skeleton.sole_segments.reshape(2, 3)
    pts = skeleton.sole_points.reshape(2, 3, 3)
    feet = np.array([skeleton.index("l_foot"), skeleton.index("r_foot")])
    frac = np.mod(plan.phase / (2.0 * np.pi), 1.0)
    toe = np.broadcast_to(np.asarray(plan.toe_off, dtype=np.float64), (n_frames,))
    world_from_segment = np.array(world_from_segment, dtype=np.float64)
    parent_from_segment = np.array(parent_from_segment, dtype=np.float64)
    _flat_feet(
        skeleton,
        parent_from_segment,
        world_from_segment,
        frac < toe[:, None],
        max(RELEASE_S * rate_hz, 1.0) if plan.toes_flat else 0.0,
    )
    joint_pos_root = np.array(joint_pos_root, dtype=np.float64)
    for side in ("l", "r"):  # the toes ride on the (flattened) foot
        ft, to = skeleton.index(f"{side}_foot"), skeleton.index(f"{side}_toes")
        joint_pos_root[:, to] = joint_pos_root[:, ft] + rot.quat_rotate(
            world_from_segment[:, ft], skeleton.rest_offsets[to]
        )
    sole = joint_pos_root[:, seg] + rot.quat_rotate(world_from_segment[:, seg], pts)
    ankle_rel = joint_pos_root[:, feet]  # (T, 2, 3)
    hip_rel = joint_pos_root[:, [skeleton.index("l_thigh"), skeleton.index("r_thigh")]]
    leg = float(
        np.linalg.norm(skeleton.rest_offsets[skeleton.index("l_shank")])
        + np.linalg.norm(skeleton.rest_offsets[skeleton.index("l_foot")])
    )
    on_ankle = sole - ankle_rel[:, :, None]  # (T, 2, 3, 3): orientation alone
    lowest = on_ankle[..., 2].min(axis=-1)  # (T, 2) lowest sole point below the ankle
    moving = plan.moving
    n_release = max(RELEASE_S * rate_hz, 1.0)
    n_load = max(LOAD_S * rate_hz, 1.0)
    n_land = max(LAND_S * rate_hz, 1.0)
    dt = 1.0 / rate_hz

    def walk_through(drop: F64Array, launches: dict[int, Flight]) -> tuple[Any, ...]:
        """One pass over the frames, the root lowered by ``drop`` (T,), each flight
        that starts at a frame of ``launches`` that one."""
        root = np.empty((n_frames, 3))
        goal = np.empty((n_frames, 2, 3))  # world ankle goals
        in_air = np.zeros((n_frames, 2), dtype=bool)
        contact = np.zeros((n_frames, 2), dtype=bool)
        support_out = np.zeros((n_frames, 2))
        strikes: list[tuple[int, int, float, float]] = []  # (foot, frame, lift, level)
        takeoffs: list[tuple[int, F64Array, F64Array, tuple[int, float]]] = []
        floor = float(root0[2] + sole[0].reshape(-1, 3)[:, 2].min())
        # From standing: the foot in its stance phase drives, the other is held until
        # the gait gets under way (then it is past its toe-off: it steps off).
        first = 1 if frac[0, 1] < toe[0] else 0
        mode = [_LOCK, _LOCK]
        mode[first] = _DRIVE
        pivot = [int(np.argmin(on_ankle[0, f, :, 2])) for f in range(2)]
        anchor = [root0 + sole[0, f, pivot[f]] for f in range(2)]
        for f in range(2):
            anchor[f][2] = floor
        support = [floor, floor]
        corr = [np.zeros(3), np.zeros(3)]  # a released foot's, blending out
        lift = np.zeros(3)  # the driver's leg correction: a strike's, held
        fades = [False]  # ... or a handover's, blending out
        fade_from = [n_frames]  # a strike's lift fades from here
        since = [0, 0]  # frame of the last release or drive start
        flight: Flight | None = None
        before: int | Flight | None = None
        lowered = [0.0]
        sag = [0.0, 0]  # double support's sink (metres) and its last frame

        def roll(f: int, t: int) -> None:
            """Pass the anchor to a lower point of the foot (it rolls): the new
            point is anchored where it was in the frame before, when the old one
            held the foot (level with it then). (Placed from this frame's pose
            about the old point instead, a flat foot whose heel rises 2.6 mm in a
            frame slid its toe tip 0.17 mm at the hand-off.)"""
            k = int(np.argmin(on_ankle[t, f, :, 2]))
            if (
                k != pivot[f]
                and on_ankle[t, f, k, 2] < on_ankle[t, f, pivot[f], 2] - 1e-9
            ):
                b = max(t - 1, 0)
                ankle = anchor[f] - on_ankle[b, f, pivot[f]]
                anchor[f] = ankle + on_ankle[b, f, k]
                anchor[f][2] = support[f]
                pivot[f] = k

        def land_at(o: int, t: int) -> tuple[int, float]:
            """The next strike of foot ``o`` after ``t`` and the root height that
            sets its lowest point on its level then."""
            wraps = np.flatnonzero(np.diff(frac[t:, o]) < 0.0)
            if not wraps.size:
                return -1, 0.0
            ts = t + int(wraps[0]) + 1
            return ts, support[1 - o] + plan.rise_m - float(sole[ts, o, :, 2].min())

        def place(t: int, dropped: bool = True) -> None:
            if _DRIVE in mode:
                d = mode.index(_DRIVE)
                roll(d, t)
                u = _smoothstep((t - since[d]) / n_load)
                root[t] = anchor[d] - on_ankle[t, d, pivot[d]] - ankle_rel[t, d]
                # A strike's lift is held until the other foot lets go (its leg has
                # no reach to spare for the pelvis to rise), then fades out.
                fade = u if fades[0] else _smoothstep((t - fade_from[0]) / n_load)
                root[t] -= lift * (1.0 - fade)
                # Weight passes from the foot (or the flight) before it over the
                # loading response, so the pelvis keeps its velocity at a strike.
                if u < 1.0 and isinstance(before, int) and mode[before] == _LOCK:
                    p = before
                    held = anchor[p] - on_ankle[t, p, pivot[p]] - ankle_rel[t, p]
                    held[2] += lowered[0]  # the drop it held at the strike
                    root[t] = held + u * (root[t] - held)
                elif u < 1.0 and isinstance(before, tuple):
                    root[t] = _ballistic(before, t, dt) + u * (
                        root[t] - _ballistic(before, t, dt)
                    )
                # Push-off: the pelvis joins the flight's path before it leaves.
                ahead = [k for k in launches if 0 <= k - t < n_load]
                if ahead:
                    u = _smoothstep((t - (ahead[0] - n_load)) / n_load)
                    path = _ballistic(launches[ahead[0]], t, dt)
                    root[t] += u * (path - root[t])
                # Double support: the pelvis sinks where the held foot's leg would
                # otherwise straighten (the stance leg bends), and rises back once
                # it lets go.
                if _LOCK in mode:
                    p = mode.index(_LOCK)
                    v = anchor[p] - on_ankle[t, p, pivot[p]] - root[t] - hip_rel[t, p]
                    cap2 = (REACH_FRACTION * leg) ** 2 - v[0] ** 2 - v[1] ** 2
                    need = -v[2] - np.sqrt(max(cap2, 0.0))
                    sag[0], sag[1] = max(need, 0.0), t
                    root[t, 2] -= sag[0]
                else:
                    root[t, 2] -= sag[0] * (1.0 - _smoothstep((t - sag[1]) / n_load))
            else:
                assert flight is not None
                root[t] = _ballistic(flight, t, dt)
            if dropped:  # a strike's or handover's new root already holds it
                root[t, 2] += drop[t]

        for t in range(n_frames):
            place(t)
            go = bool(moving[t])
            # Heel strike: a foot in the air lands at its phase 0, on the next support.
            for f in range(2):
                wrapped = t > 0 and frac[t, f] < frac[t - 1, f]
                if not (go and wrapped and mode[f] in (_RELEASE, _SWING)):
                    continue
                level = support[1 - f] + plan.rise_m
                k = int(np.argmin(on_ankle[t, f, :, 2]))
                at = root[t] + sole[t, f, k]
                strikes.append((f, t, level - at[2], level))
                anchor[f], pivot[f], support[f] = at.copy(), k, level
                anchor[f][2] = level
                lift = np.array([0.0, 0.0, level - at[2]])
                fades[0], fade_from[0] = False, n_frames
                before = mode.index(_DRIVE) if _DRIVE in mode else flight
                lowered[0] = drop[t]
                if _DRIVE in mode:
                    mode[mode.index(_DRIVE)] = _LOCK
                mode[f], since[f], flight = _DRIVE, t, None
                place(t, dropped=False)
            # Toe-off: at its time, or a held foot the leg can no longer reach.
            for f in range(2):
                if mode[f] in (_RELEASE, _SWING) or not go:
                    continue
                if frac[t, f] < toe[t]:
                    continue
                held = anchor[f] - on_ankle[t, f, pivot[f]]
                free = root[t] + ankle_rel[t, f]
                if mode[f] == _LOCK:  # from where it was held (the toes ease back)
                    corr[f] = (goal[t - 1, f] if t else held) - free
                    mode[f], since[f] = _RELEASE, t
                    fade_from[0] = t
                elif _LOCK in mode:  # the driver hands over to the locked foot
                    o = mode.index(_LOCK)
                    lift = (anchor[o] - on_ankle[t, o, pivot[o]]) - (
                        root[t] + ankle_rel[t, o]
                    )
                    mode[o], since[o], before = _DRIVE, t, None
                    mode[f], since[f] = _RELEASE, t
                    fades[0] = True
                    place(t, dropped=False)  # the same root: the lift is the lock's
                    corr[f] = held - (root[t] + ankle_rel[t, f])
                elif plan.flight:
                    v = (root[t] - root[t - 1]) * rate_hz if t else np.zeros(3)
                    landing = land_at(1 - f, t)
                    takeoffs.append((t, root[t].copy(), v, landing))
                    flight = launches.get(t) or _flight(t, root[t], v, landing, dt)
                    corr[f] = np.zeros(3)
                    mode[f], since[f] = _RELEASE, t
            for f in range(2):
                contact[t, f] = mode[f] in (_DRIVE, _LOCK)
                support_out[t, f] = support[f]
                if contact[t, f]:
                    if mode[f] == _LOCK:
                        roll(f, t)
                    goal[t, f] = anchor[f] - on_ankle[t, f, pivot[f]]
                    continue
                s = 1.0
                if mode[f] == _RELEASE:
                    s = _smoothstep((t - since[f]) / n_release)
                    if s >= 1.0:
                        mode[f] = _SWING
                goal[t, f] = root[t] + ankle_rel[t, f] + corr[f] * (1.0 - s)
                in_air[t, f] = True
        return root, goal, in_air, contact, support_out, strikes, takeoffs

    # A strike whose foot would still be above its support lowers the root over the
    # terminal swing instead (the stance leg bends), so the landing leg need not
    # reach past straight.
    drop = np.zeros(n_frames)
    first = walk_through(drop, {})
    for _, ts, dz, _ in first[5]:
        if dz < 0.0:
            a = max(ts - int(np.ceil(n_land)), 0)
            ramp = [_smoothstep((t - a + 1) / (ts - a + 1)) for t in range(a, ts + 1)]
            drop[a : ts + 1] += dz * np.asarray(ramp)
    # A run's flight is ballistic (gravity alone) from a take-off velocity that
    # lands it on time; the pelvis is eased onto that path over the push-off.
    launches: dict[int, Flight] = {}
    for t0, p0, v, (ts, z) in first[6]:
        if ts > t0:
            span = (ts - t0) * dt
            v0 = v.copy()
            v0[2] = (z - p0[2] + 0.5 * GRAVITY_M_S2 * span * span) / span
            launches[t0] = (t0, p0, v0, 0.0)
    root, goal, in_air, contact, support_out, strikes, _ = walk_through(drop, launches)
    # Terminal swing: blend in each strike's lift so the foot meets its support.
    last = [0, 0]
    for f, ts, dz, level in strikes:
        a = max(ts - int(np.ceil(n_land)), last[f])
        for t in range(a, ts):
            goal[t, f, 2] += dz * _smoothstep((t - a + 1) / (ts - a + 1))
        for t in range(last[f], ts):
            least = min(support_out[t, f], level) - lowest[t, f]
            if in_air[t, f]:
                goal[t, f, 2] = max(goal[t, f, 2], least)
        last[f] = ts
    for f in range(2):  # after the last strike: never below the support it left
        for t in range(last[f], n_frames):
            if in_air[t, f]:
                least = support_out[t, f] - lowest[t, f]
                goal[t, f, 2] = max(goal[t, f, 2], least)
    _swing_clearance(goal, in_air, support_out, lowest)
    pfs = np.array(parent_from_segment, dtype=np.float64)
    missed = _legs_to_goals(skeleton, pfs, world_from_segment, joint_pos_root, root,
                            goal)  # fmt: skip
    # A held foot the leg cannot reach (straight) has left its support: the heel
    # lifts a frame or two before the scheduled toe-off.
    return PlantedGait(
        parent_from_segment=pfs,
        root_pos=root,
        contact=contact & (missed <= REACH_TOL_M),
        support_m=support_out,
        unreached_m=float(missed[contact].max(initial=0.0)),
    )


Flight = tuple[int, F64Array, F64Array, float]


def _swing_clearance(
    goal: F64Array, in_air: BoolArray, support: F64Array, lowest: F64Array
) -> None:
    """Each swing from a support to a strike on the same level keeps its lowest sole
    point :data:`SWING_CLEARANCE_M` sin^2(pi u) above it (u from 0 at the last frame
    on the ground to 1 at the strike), in place on the ankle goals (T, 2, 3)."""
    n_frames = in_air.shape[0]
    for f in range(2):
        air = np.concatenate([[False], in_air[:, f], [False]])
        edges = np.flatnonzero(air[1:] != air[:-1])
        for a, b in zip(edges[::2], edges[1::2], strict=True):
            if a == 0 or b >= n_frames or support[a - 1, f] != support[b, f]:
                continue  # no strike to end it, or a step up or down
            u = (np.arange(a, b) - a + 1.0) / (b - a + 1.0)
            floor = support[b, f] + SWING_CLEARANCE_M * np.sin(np.pi * u) ** 2
            goal[a:b, f, 2] = np.maximum(goal[a:b, f, 2], floor - lowest[a:b, f])


def _flight(
    t0: int, p0: F64Array, v0: F64Array, landing: tuple[int, float], dt: float
) -> Flight:
    """A flight from take-off (frame, root, velocity) that lands on time: the
    vertical acceleration is gravity's plus the constant that brings the root to
    the landing height (frame, root z) at the landing frame (0 when the take-off
    velocity alone would)."""
    ts, z = landing
    if ts <= t0:
        return t0, p0, v0, 0.0
    s = (ts - t0) * dt
    extra = (z - p0[2] - v0[2] * s + 0.5 * GRAVITY_M_S2 * s * s) / (s * s)
    return t0, p0, v0, extra


def _ballistic(flight: Flight, t: int, dt: float) -> F64Array:
    """The root at frame ``t`` of a :func:`_flight`."""
    t0, p0, v0, extra = flight
    s = (t - t0) * dt
    out = p0 + v0 * s
    out[2] += (extra - 0.5 * GRAVITY_M_S2) * s * s
    return out


def _flat_feet(
    skeleton: Skeleton,
    pfs: F64Array,
    wfs: F64Array,
    stance: BoolArray,
    n_ease: float,
) -> None:
    """Foot flat: in each stance (T, 2), from the moment the foot's joint-angle pitch
    first comes down to the floor until the heel rises for good, the foot is held
    flat (the ankle angle is what the shank's turn over a still foot makes it), so
    it does not rock between heel and ball. In place on ``pfs`` and ``wfs``."""
    ex = np.array([1.0, 0.0, 0.0])
    for f, side in enumerate(("l", "r")):
        sh, ft, to = (skeleton.index(f"{side}_{k}") for k in ("shank", "foot", "toes"))
        up = rot.quat_rotate(wfs[:, ft], ex)[:, 2]  # + = toes up
        edges = np.diff(np.concatenate([[0], stance[:, f].astype(np.int8), [0]]))
        starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
        for a, b in zip(starts, stops, strict=True):
            down = np.flatnonzero(up[a:b] <= 0.0)
            rising = np.flatnonzero(up[a:b] >= 0.0)
            if not down.size or not rising.size:
                continue
            i0, i1 = a + down[0], a + rising[-1] + 1
            if i0 >= i1:
                continue
            _level(wfs, pfs, ft, sh, slice(i0, i1))
            wfs[i0:i1, to] = rot.quat_mul(wfs[i0:i1, ft], pfs[i0:i1, to])
            # Heel off to toe-off the toes stay flat on the floor (the MTP joint
            # extends) and the foot rolls about them.
            if n_ease <= 0.0:  # the toes keep their joint angle
                continue
            if b >= len(up) or i1 >= b:
                _level(wfs, pfs, to, ft, slice(i1, b))
                continue
            own = pfs[b - 1, to].copy()
            _level(wfs, pfs, to, ft, slice(i1, b))
            # ... and ease back to their joint angle after toe-off.
            extended = rot.quat_mul(pfs[b - 1, to], rot.quat_conj(own))
            back = range(int(b), min(int(b) + int(np.ceil(n_ease)), len(up)))
            for t in back:
                keep = 1.0 - _smoothstep((t - b + 1) / n_ease)
                ease = rot.slerp(np.array([1.0, 0.0, 0.0, 0.0]), extended, keep)
                pfs[t, to] = rot.quat_mul(ease, pfs[t, to])
                wfs[t, to] = rot.quat_mul(wfs[t, ft], pfs[t, to])


def _level(wfs: F64Array, pfs: F64Array, seg: int, parent: int, at: slice) -> None:
    """Turn segment ``seg`` about its lateral axis until its x axis is horizontal,
    over frames ``at``; its ``pfs`` follows from its parent's world rotation."""
    x = rot.quat_rotate(wfs[at, seg], np.array([1.0, 0.0, 0.0]))
    flat = x * np.array([1.0, 1.0, 0.0])
    wfs[at, seg] = rot.quat_mul(_quat_between(x, flat), wfs[at, seg])
    pfs[at, seg] = rot.quat_mul(rot.quat_conj(wfs[at, parent]), wfs[at, seg])


def _legs_to_goals(
    skeleton: Skeleton,
    pfs: F64Array,
    wfs: F64Array,
    joint_pos_root: F64Array,
    root: F64Array,
    goal: F64Array,
) -> F64Array:
    """Two-bone IK of each leg onto its ankle goal (T, 2, 3), in place on ``pfs``;
    returns (T, 2) each ankle's miss (metres)."""
    missed = np.zeros(goal.shape[:2])
    for f, side in enumerate(("l", "r")):
        th, sh, ft = (skeleton.index(f"{side}_{k}") for k in ("thigh", "shank", "foot"))
        hip = root + joint_pos_root[:, th]
        ankle = root + joint_pos_root[:, ft]
        todo = np.linalg.norm(goal[:, f] - ankle, axis=-1) > 1e-9
        if not todo.any():
            continue
        a_vec, b_vec = skeleton.rest_offsets[sh], skeleton.rest_offsets[ft]
        a, b = float(np.linalg.norm(a_vec)), float(np.linalg.norm(b_vec))
        w_th, w_sh, w_ft = wfs[todo, th], wfs[todo, sh], wfs[todo, ft]
        to_goal = goal[todo, f] - hip[todo]
        d = np.linalg.norm(to_goal, axis=-1)
        reach = np.clip(d, abs(a - b) + 1e-6, a + b)
        # Flexion f: |knee + ankle|^2 = a^2 + b^2 + 2ab cos f (both offsets along -z).
        flex_new = np.arccos(np.clip((reach**2 - a * a - b * b) / (2 * a * b), -1, 1))
        thigh_z = rot.quat_rotate(w_th, np.array([0.0, 0.0, 1.0]))
        shank_z = rot.quat_rotate(w_sh, np.array([0.0, 0.0, 1.0]))
        flex_old = np.arccos(np.clip(np.sum(thigh_z * shank_z, -1), -1.0, 1.0))
        hinge = rot.quat_rotate(w_th, np.array([0.0, 1.0, 0.0]))
        w_sh1 = rot.quat_mul(rot.quat_from_axis_angle(hinge, flex_new - flex_old), w_sh)
        v1 = rot.quat_rotate(w_th, a_vec) + rot.quat_rotate(w_sh1, b_vec)
        turn = _quat_between(v1, to_goal)
        w_th2 = rot.quat_mul(turn, w_th)
        w_sh2 = rot.quat_mul(turn, w_sh1)
        reached = rot.quat_rotate(w_th2, a_vec) + rot.quat_rotate(w_sh2, b_vec)
        missed[todo, f] = np.linalg.norm(reached - to_goal, axis=-1)
        w_pelvis = wfs[todo, 0]
        pfs[todo, th] = rot.quat_mul(rot.quat_conj(w_pelvis), w_th2)
        pfs[todo, sh] = rot.quat_mul(rot.quat_conj(w_th2), w_sh2)
        pfs[todo, ft] = rot.quat_mul(rot.quat_conj(w_sh2), w_ft)
    return missed


def _quat_between(u: F64Array, v: F64Array) -> F64Array:
    """(N, 4) the shortest rotation taking each u (N, 3) onto v's direction."""
    u = u / np.linalg.norm(u, axis=-1, keepdims=True)
    v = v / np.linalg.norm(v, axis=-1, keepdims=True)
    q = np.concatenate([1.0 + np.sum(u * v, -1, keepdims=True), np.cross(u, v)], -1)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)
