"""Synthetic props with ground truth: a virtual camera rig (5 markers) carried in the
synthetic performer's right hand and a sword (4 markers) in the left, each also
turned and shifted in the grip on its own, for the prop solve's evidence
(``tests/daemon/props/test_props_truth.py``) and ``retargetd synth --props``.

Truth: ``world_from_prop(t) = world_from_hand(t) ⊗ hand_from_grip ⊗ grip_from_prop(t)``
and the prop's origin ``hand(t) + world_from_hand(t) (grip_pos + own_pos(t))``; its
markers are ``world_from_prop(t) layout + origin(t)`` plus Gaussian noise per
coordinate. The layout is centred on the markers' centroid, so the prop's origin is
the centroid, as a calibration without a pivot puts it. The prop's own motion is a
sum of sines in the grip (irrational frequency ratios, as the performer's), weighted
by the performer's own ramp: 0 during its base-pose hold (the props lie still in the
hands, for their calibration), 1 after :data:`~retargetd.daemon.synth.motion.RAMP_S`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from retargetd.daemon import rotations as rot
from retargetd.daemon.synth.motion import RAMP_S, smootherstep
from retargetd.daemon.synth.performer import SynthTake
from retargetd.protocols.frames import BoolArray, F64Array

#: Marker layouts, metres, before centring. The camera: a shoulder rig ~35 cm
#: across (two handles, a monitor arm, the lens), any three of its markers at least
#: 13 cm from the line through two of them, so the three a swap or two hidden
#: markers leave still fix the roll (a 4 cm thin triple gave 2.6 deg of error at
#: 0.5 mm). The sword: one marker near the tip, two at the ends of a 28 cm
#: crossguard and one on a 13 cm stalk at the pommel (a marker tree): no three near
#: a line, so with any one hidden the roll about the blade is still seen (two blade
#: markers and one guard marker gave 1-2 deg p95 of roll noise at 0.5 mm). Neither
#: layout is symmetric: no swap of two keeps every distance (``ambiguous_pairs``).
LAYOUTS: dict[str, F64Array] = {
    "camera": np.array(
        [
            [-0.17, 0.00, 0.00],
            [0.15, 0.02, 0.00],
            [0.02, 0.14, 0.12],
            [0.06, -0.08, 0.15],
            [-0.08, 0.16, -0.06],
        ]
    ),
    "sword": np.array(
        [
            [0.00, 0.03, 0.80],
            [-0.15, 0.00, 0.10],
            [0.13, 0.02, 0.13],
            [0.03, 0.13, -0.10],
        ]
    ),
}
Sines = tuple[tuple[float, float, float], ...]  # per axis: amplitude, Hz, phase


@dataclass(frozen=True, slots=True)
class Carry:
    """Which hand carries a prop, the grip (the prop's centroid in the hand frame,
    metres) and its own motion in the grip: per axis (amplitude rad, frequency Hz,
    phase rad) of the rotation vector, and the same (amplitude m) of the shift."""

    hand: str
    grip: tuple[float, float, float]
    turn: Sines
    shift: Sines


CARRY: dict[str, Carry] = {
    "camera": Carry(
        "r_hand",
        (0.0, -0.08, 0.10),
        ((0.45, 0.31, 0.0), (0.60, 0.47, 1.1), (0.25, 0.23, 2.3)),
        ((0.04, 0.19, 0.4), (0.03, 0.29, 1.7), (0.05, 0.13, 2.9)),
    ),
    "sword": Carry(
        "l_hand",
        (0.0, -0.06, 0.0),
        ((1.0, 1.13, 0.0), (0.5, 0.71, 0.9), (0.8, 0.97, 2.0)),
        ((0.02, 0.41, 0.3), (0.02, 0.37, 1.3), (0.02, 0.53, 2.2)),
    ),
}


@dataclass(frozen=True, slots=True, kw_only=True)
class SynthProp:
    """One synthetic prop and its truth (metres, world; quaternions w x y z)."""

    name: str
    labels: tuple[str, ...]
    layout_prop_m: F64Array  # (K, 3), centred on the centroid
    markers_world: F64Array  # (T, K, 3), noisy; NaN = occluded (none here)
    valid: BoolArray  # (T, K)
    world_from_prop_quat: F64Array  # (T, 4)
    prop_pos_world: F64Array  # (T, 3): the centroid


def _sines(spec: Sines, t: F64Array) -> F64Array:
    out = np.zeros((t.size, 3))
    for axis, (amp, hz, phase) in enumerate(spec):
        out[:, axis] = amp * np.sin(2.0 * np.pi * hz * t + phase)
    return out


def synth_props(
    take: SynthTake,
    names: tuple[str, ...] = ("camera", "sword"),
    *,
    noise_mm: float = 0.5,
    seed: int = 0,
    base_pose_s: float = 1.0,
) -> tuple[SynthProp, ...]:
    """The props ``names`` (of :data:`LAYOUTS`) carried by ``take``'s performer.

    Args:
        take: the synthetic performer's take (its hands carry the props).
        names: which props.
        noise_mm: Gaussian noise std per coordinate, millimetres.
        seed: the noise's seed (one stream per prop).
        base_pose_s: the take's base-pose hold (the props' own motion is 0 there).

    Raises:
        ValueError: an unknown prop name.
    """
    unknown = [n for n in names if n not in LAYOUTS]
    if unknown:
        raise ValueError(f"unknown props {unknown}; from {', '.join(LAYOUTS)}")
    t = take.times_s
    w = smootherstep((t - base_pose_s) / RAMP_S)[:, None]
    out = []
    for i, name in enumerate(names):
        carry = CARRY[name]
        seg = take.segment_names.index(carry.hand)
        hand_q = take.world_from_segment_quat[:, seg]
        hand_p = take.joint_pos_world[:, seg]
        own_v = w * _sines(carry.turn, t)
        angle = np.linalg.norm(own_v, axis=1)
        unit = own_v / np.maximum(angle, 1e-12)[:, None]
        axis = np.where(angle[:, None] > 1e-12, unit, [1.0, 0.0, 0.0])
        grip_from_prop = rot.quat_from_axis_angle(axis, angle)
        world_q = rot.quat_mul(hand_q, grip_from_prop)
        grip = np.asarray(carry.grip, dtype=np.float64)
        pos = hand_p + rot.quat_rotate(hand_q, grip + w * _sines(carry.shift, t))
        layout = LAYOUTS[name] - LAYOUTS[name].mean(axis=0)
        k = len(layout)
        markers = rot.quat_rotate(world_q[:, None, :], layout[None]) + pos[:, None]
        rng = np.random.default_rng([seed, i])
        markers = markers + rng.normal(0.0, noise_mm / 1000.0, markers.shape)
        out.append(
            SynthProp(
                name=name,
                labels=tuple(f"{name}:{j + 1}" for j in range(k)),
                layout_prop_m=layout,
                markers_world=markers,
                valid=np.ones((t.size, k), dtype=np.bool_),
                world_from_prop_quat=world_q,
                prop_pos_world=pos,
            )
        )
    return tuple(out)
