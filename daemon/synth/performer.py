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
rotation last; the forearm's, its pronation, is about the ISB's forearm axis from the
elbow centre to the ulnar styloid, ``skeleton.pronation_axis``). Left-side formulas
are anatomical; the right side mirrors them through the sagittal plane (x and z
angles negated) with its own phases. Frequencies are irrational ratios of each other,
so the pose never repeats.

Root: the pelvis starts at ``origin + (0, 0, 0.530 H)`` (``origin`` is the floor point
under the pelvis; soles at z = 0). ``walk`` moves it counter-clockwise round a circle
of :data:`WALK_RADIUS_M` centred at ``origin + (0, R, 0)`` (the lab origin for the
default origin), heading along the tangent, with lateral sway; the vertical bob comes
from keeping the lowest sole point on the floor (a soft minimum, so it stays smooth).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from retargetd.daemon import rotations as rot
from retargetd.daemon.synth.gait import plant_gait
from retargetd.daemon.synth.markerset import (
    MarkerSet,
    load_markerset,
    shipped_markersets,
)
from retargetd.daemon.synth.motion import (
    ACTIVITY_MOTIONS,
    ALL_MOTIONS,
    COMPONENTS,
    DEFAULT_MOTIONS,
    DEFAULT_ORIGIN,
    FLOOR_SOFTMIN_M,
    RAMP_S,
    Motion,
    smootherstep,
)
from retargetd.daemon.synth.skeleton import (
    REFERENCE_HEIGHT_M,
    SEGMENT_NAMES,
    Skeleton,
    make_skeleton,
    pronation_axis,
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
        foot_contact: (T, 2) bool, left / right foot in contact with its support. The
            gaits (``level_walk``, ``run``, ``stair_ascent``, ``stair_descent``:
            ``synth.gait``) hold each foot put while this is set; other motions: a
            sole point within :data:`CONTACT_M` of the floor.
        foot_support_m: (T, 2) float64, metres, world z of each foot's support (the
            floor, or a stair's step).
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
    foot_contact: BoolArray
    foot_support_m: F64Array

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
#: Truth fields added later; a file without them reads as this (contact unknown).
_LATER_FIELDS = ("foot_contact", "foot_support_m")
#: Outside the gaits, a foot is in contact when a sole point is this near the floor
#: (metres): the soft floor contact keeps the lowest sole within 1 mm of it.
CONTACT_M = 1e-3


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
            if name in _LATER_FIELDS and name not in npz.files:
                continue
            value = npz[name]
            if name == "base_pose_frames":
                kwargs[name] = slice(int(value[0]), int(value[1]))
            elif value.dtype.kind == "U":
                kwargs[name] = str(value) if value.ndim == 0 else tuple(value.tolist())
            elif value.ndim == 0:
                kwargs[name] = value.item()
            else:
                kwargs[name] = readonly(value)
    n_frames = len(np.asarray(kwargs["times_s"]))
    kwargs.setdefault("foot_contact", readonly(np.zeros((n_frames, 2), dtype=bool)))
    kwargs.setdefault("foot_support_m", readonly(np.full((n_frames, 2), np.nan)))
    return SynthTake(**kwargs)  # type: ignore[arg-type]


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
    exact T-pose (the elbows bent by the marker set's ``elbow_flexion_deg``); the
    motion ramps in over :data:`RAMP_S` after that. Noise and
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
    unknown = [m for m in motions if m not in COMPONENTS]
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
    work = Motion(
        skeleton=skeleton,
        t=t_motion,
        w=smootherstep(t_motion / RAMP_S),
        angles=np.zeros((n_frames, n_seg, 3)),
        root_pos=np.tile(origin_world + skeleton.rest_pos[0], (n_frames, 1)),
        heading=np.zeros(n_frames),
        motions=motions,
    )
    for name in ALL_MOTIONS:  # fixed composition order, whatever order was asked
        if name in motions:
            COMPONENTS[name](work)
    if markerset.elbow_flexion_deg:
        # The marker set's static bends the elbows; the motion ramps out of it
        # (flexion about the upper arm's z, forward = -z on the left).
        hold = (1.0 - work.w) * markerset.elbow_flexion_deg
        work.add_bilateral("forearm", 2, -hold, -hold)

    parent_from_segment = np.empty((n_frames, n_seg, 4))
    orders = np.array(skeleton.euler_orders)
    for order in sorted(set(skeleton.euler_orders)):
        idx = np.flatnonzero(orders == order)
        columns = ["xyz".index(c) for c in order.lower()]
        parent_from_segment[:, idx] = rot.quat_from_euler(
            work.angles[:, idx][..., columns], order
        )
    # The forearm's long-axis angle (pronation) turns it about the ISB's forearm
    # axis, elbow -> ulnar styloid, not about its own y: Rz Rx Ry -> Rz Rx R_axis.
    y_axis = np.array([0.0, 1.0, 0.0])
    for side in ("l", "r"):
        i = skeleton.index(f"{side}_forearm")
        pron = work.angles[:, i, 1]
        about_axis = rot.quat_from_axis_angle(pronation_axis(side), pron)
        not_y = rot.quat_conj(rot.quat_from_axis_angle(y_axis, pron))
        parent_from_segment[:, i] = rot.quat_mul(
            parent_from_segment[:, i], rot.quat_mul(not_y, about_axis)
        )
    heading_quat = rot.quat_from_axis_angle(np.array([0.0, 0.0, 1.0]), work.heading)
    parent_from_segment[:, 0] = rot.quat_mul(heading_quat, parent_from_segment[:, 0])
    world_from_segment, joint_pos = _forward_kinematics(
        skeleton, parent_from_segment, work.root_pos
    )
    contact = np.zeros((n_frames, 2), dtype=bool)
    support = np.full((n_frames, 2), np.nan)
    if work.gait is not None:
        # Gaits: the body placed from the stance feet (synth.gait), legs corrected.
        placed = plant_gait(
            skeleton,
            parent_from_segment,
            world_from_segment,
            joint_pos - work.root_pos[:, None],
            work.root_pos[0],
            work.gait,
            rate_hz,
        )
        parent_from_segment = placed.parent_from_segment
        world_from_segment, joint_pos = _forward_kinematics(
            skeleton, parent_from_segment, placed.root_pos
        )
        contact, support = placed.contact, placed.support_m
    if work.walk_weight.size:
        # Vertical bob: keep the lowest sole point on the floor (soft minimum, so the
        # root height stays smooth); zero correction while the ramp weight is 0.
        seg = skeleton.sole_segments
        sole_z = (
            joint_pos[:, seg, 2]
            + rot.quat_rotate(world_from_segment[:, seg], skeleton.sole_points)[..., 2]
        )
        rest_z = origin_world[2] + (skeleton.rest_pos[seg] + skeleton.sole_points)[:, 2]
        lift = _softmin(rest_z, FLOOR_SOFTMIN_M) - _softmin(sole_z, FLOOR_SOFTMIN_M)
        joint_pos[..., 2] += (work.walk_weight * lift)[:, None]
    if work.floor_weight.size:
        # Activities: the same floor contact, then planted feet, then flight.
        seg = skeleton.sole_segments
        sole_z = (
            joint_pos[:, seg, 2]
            + rot.quat_rotate(world_from_segment[:, seg], skeleton.sole_points)[..., 2]
        )
        rest_z = origin_world[2] + (skeleton.rest_pos[seg] + skeleton.sole_points)[:, 2]
        lift = _softmin(rest_z, FLOOR_SOFTMIN_M) - _softmin(sole_z, FLOOR_SOFTMIN_M)
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
    if work.gait is None:
        seg = skeleton.sole_segments
        sole_z = (
            joint_pos[:, seg, 2]
            + rot.quat_rotate(world_from_segment[:, seg], skeleton.sole_points)[..., 2]
        ).reshape(n_frames, 2, -1)
        contact = sole_z.min(axis=-1) <= origin_world[2] + CONTACT_M
        support = np.full((n_frames, 2), origin_world[2])

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
        foot_contact=readonly(contact),
        foot_support_m=readonly(support),
    )
