"""A body solve of the synthetic performer against the truth it was made from.

The evidence of issue 28 item 6: how far each rig bone's rotation and each rig joint
centre is from the performer segment it stands for (:func:`compare_with_truth`).

**Which truth.** A rig bone maps to a performer segment through its humanoid name
(:data:`HUMANOID_SEGMENT`: ``Hips`` -> ``pelvis``, ``LeftUpperArm`` -> ``l_upper_arm``
...); bones without a humanoid name, or with one no segment stands for
(``UpperChest``), are skipped. A rig joint maps to the segment whose origin it is: the
joint's point is the origin of a bone that maps to segment X, so the joint is X's
proximal joint centre (``joint_pos_world[:, X]``); other joints are skipped.

**Bone error.** A bone's rest axes are not its segment's (a rig chooses +Y along the
bone), so rotations are compared as changes since a reference frame ``r`` (frame 0,
in the calibration T-pose), both in the world frame::

    dW(t) = world_from_bone(t) conj(world_from_bone(r))
    dS(t) = world_from_segment(t) conj(world_from_segment(r))
    err(t) = angle(dW(t) conj(dS(t)))

zero for a bone that is its segment up to any constant rotation.

**Joint error.** A rig's joint centre sits at an offset from the true joint centre
(its construction estimates it from markers and measurements); that offset is taken
at the reference frame and carried rigidly by one of the two segments the joint
joins, the carrier ``c``::

    d = rotate(conj(S_c(r)), J(r) - P_X(r))          # in the carrier's frame
    err(t) = |J(t) - (P_X(t) + rotate(S_c(t), d))|

A rig's estimate need not be rigid on either (menache's shoulder is 15 % of the way
from an acromion marker to the elbow), so per joint the carrier is whichever of the
two gives the lower p95 over the statistics' frames: the parent segment (that of the
nearest ancestor bone that maps to one; the fit holds a bone's origin rigid in its
parent) or the joint's own segment X (the only one for the root). The error is what
no constant offset on either segment explains; the offset ``|J(r) - P_X(r)|`` and the
carrier are reported beside it. A point that is the origin of several mapped bones
(Plug-in Gait's ``TRXO``, both clavicles') is no one joint and is skipped.

**Unobserved rotations.** Where the markers do not determine a rotation of a bone
(an axis in the bone's rest axes, from an observability analysis), the solve holds it
at the calibration pose relative to the parent bone, so the bone is off by as much as
the truth turned about that axis. Per bone and frame :func:`compare_with_truth`
returns that excursion: the twist (swing-twist, :func:`rotations.twist_angle`) of the
truth segment relative to its parent segment, since the reference frame, about each
unobserved axis, summed in absolute value over the axes of the bone and of all its
ancestors. A test then asserts ``err <= tol + excursion``.

NaN in a solve counts as the worst error (180 deg, infinite mm); percentiles use
``method="higher"`` (an observed value, never an interpolation), so a statistic never
reads better than some frame was.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.rig import Rig
from retargetd.daemon.body.solve import BodySolve
from retargetd.daemon.synth.performer import SynthTake
from retargetd.daemon.validate.model import SEGMENT_KIND
from retargetd.protocols.frames import F64Array, IntArray

__all__ = [
    "HUMANOID_SEGMENT",
    "TruthComparison",
    "TruthMap",
    "compare_with_truth",
    "error_stats",
    "rotation_change_error_deg",
    "truth_map",
]

#: Standard humanoid bone -> the synthetic performer's segment it stands for
#: (``UpperChest`` has none: the performer's trunk is pelvis, abdomen, thorax).
HUMANOID_SEGMENT: dict[str, str] = {
    humanoid: ("l_" if humanoid.startswith("Left") else "r_") + kind
    if humanoid.startswith(("Left", "Right"))
    else kind
    for humanoid, kind in SEGMENT_KIND.items()
    if humanoid != "UpperChest"
}


@dataclass(frozen=True, slots=True, kw_only=True)
class TruthMap:
    """Which rig bones and joints stand for which performer segments.

    Attributes:
        bone_names: (K,) the rig bones compared, rig order.
        bones: (K,) int64 their indices in the rig (and the solve).
        segments: (K,) int64 the truth segment each stands for.
        carriers: (K,) int64 the truth segment of the nearest ancestor bone that maps
            to one, -1 for none (the root: its parent is the world).
        ancestors: (K,) for each compared bone, the rig indices of itself and all its
            ancestors, itself first.
        joint_names: (Jc,) the rig joints compared, rig order.
        joint_segments: (Jc,) int64 the segment whose origin each joint is.
        joint_parents: (Jc,) int64 the carrier of the bone whose origin it is (the
            joint's parent segment); its own segment for the root.
    """

    bone_names: tuple[str, ...]
    bones: IntArray
    segments: IntArray
    carriers: IntArray
    ancestors: tuple[tuple[int, ...], ...]
    joint_names: tuple[str, ...]
    joint_segments: IntArray
    joint_parents: IntArray


def truth_map(rig: Rig, segment_names: Sequence[str]) -> TruthMap:
    """Map a rig's bones and joints onto the performer's segments.

    Args:
        rig: the rig.
        segment_names: (S,) the take's segment names (``SynthTake.segment_names``).

    Returns:
        The :class:`TruthMap` (bones and joints with no segment left out).
    """
    names = list(segment_names)
    index = {b.name: i for i, b in enumerate(rig.bones)}
    seg_of = [
        names.index(HUMANOID_SEGMENT[b.humanoid])
        if b.humanoid in HUMANOID_SEGMENT and HUMANOID_SEGMENT[b.humanoid] in names
        else -1
        for b in rig.bones
    ]

    def chain(i: int) -> tuple[int, ...]:
        out = [i]
        while (parent := rig.bones[out[-1]].parent) is not None:
            out.append(index[parent])
        return tuple(out)

    def carrier(i: int) -> int:
        return next((seg_of[a] for a in chain(i)[1:] if seg_of[a] >= 0), -1)

    bones = [i for i, s in enumerate(seg_of) if s >= 0]
    joint_names, joint_segments, joint_parents = [], [], []
    for jname, point in rig.joints.items():
        owners = [i for i in bones if rig.bones[i].origin == point]
        if len(owners) != 1:
            continue
        joint_names.append(jname)
        joint_segments.append(seg_of[owners[0]])
        c = carrier(owners[0])
        joint_parents.append(seg_of[owners[0]] if c < 0 else c)
    return TruthMap(
        bone_names=tuple(rig.bones[i].name for i in bones),
        bones=np.array(bones, dtype=np.int64),
        segments=np.array([seg_of[i] for i in bones], dtype=np.int64),
        carriers=np.array([carrier(i) for i in bones], dtype=np.int64),
        ancestors=tuple(chain(i) for i in bones),
        joint_names=tuple(joint_names),
        joint_segments=np.array(joint_segments, dtype=np.int64),
        joint_parents=np.array(joint_parents, dtype=np.int64),
    )


def rotation_change_error_deg(
    world_from_bone_quat: F64Array, world_from_segment_quat: F64Array, ref_frame: int
) -> F64Array:
    """Angle between each bone's and its segment's rotation change since ``ref_frame``.

    Args:
        world_from_bone_quat: (T, K, 4) float64 (w, x, y, z), the solve's bones.
        world_from_segment_quat: (T, K, 4) float64 (w, x, y, z), their segments.
        ref_frame: the reference frame (the calibration pose).

    Returns:
        (T, K) float64 degrees, ``angle(dW conj(dS))``; 180 where the solve is NaN.
    """
    w = np.asarray(world_from_bone_quat, dtype=np.float64)
    s = np.asarray(world_from_segment_quat, dtype=np.float64)
    dw = rot.quat_mul(w, rot.quat_conj(w[ref_frame]))
    ds = rot.quat_mul(s, rot.quat_conj(s[ref_frame]))
    err = np.degrees(rot.quat_angle(rot.quat_mul(dw, rot.quat_conj(ds))))
    return np.where(np.isnan(err), 180.0, err)


def error_stats(err: F64Array) -> tuple[F64Array, F64Array, F64Array]:
    """p50, p95 and max over frames of ``err`` (T, K), each (K,) (NaN counts as inf).

    Percentiles are observed values (``method="higher"``); with no frames, NaN.
    """
    err = np.where(np.isnan(err), np.inf, np.asarray(err, dtype=np.float64))
    if err.shape[0] == 0:
        empty = np.full(err.shape[1:], np.nan)
        return empty, empty.copy(), empty.copy()
    p50, p95 = np.percentile(err, [50.0, 95.0], axis=0, method="higher")
    return p50, p95, err.max(axis=0)


@dataclass(frozen=True, slots=True, kw_only=True)
class TruthComparison:
    """A solve against the truth (see the module docstring for every definition).

    Statistics are over ``frames`` (``stats_frames``), errors are for every frame.

    Attributes:
        ref_frame: the reference frame (calibration pose).
        stats_frames: the frames the statistics cover.
        bone_names: (K,) rig bones compared.
        error_deg: (T, K) float64 degrees, rotation-change error (180 where NaN).
        excursion_deg: (T, K) float64 degrees, the truth's excursion in the bone's and
            its ancestors' unobserved axes (0 where none).
        p50_deg, p95_deg, max_deg: (K,) float64 degrees, of ``error_deg``.
        excess_p95_deg, excess_max_deg: (K,) float64 degrees, of ``error_deg -
            excursion_deg`` (equal to the above where no axis is unobserved).
        n_nan: (K,) int64 frames where the bone was NaN.
        joint_names: (Jc,) rig joints compared.
        joint_error_mm: (T, Jc) float64 mm, offset-carried joint error (inf at NaN).
        joint_offset_mm: (Jc,) float64 mm, rig joint to true joint at the reference.
        joint_carriers: (Jc,) the segment names that carry each joint's offset.
        joint_p50_mm, joint_p95_mm, joint_max_mm: (Jc,) float64 mm.
    """

    ref_frame: int
    stats_frames: slice
    bone_names: tuple[str, ...]
    error_deg: F64Array
    excursion_deg: F64Array
    p50_deg: F64Array
    p95_deg: F64Array
    max_deg: F64Array
    excess_p95_deg: F64Array
    excess_max_deg: F64Array
    n_nan: IntArray
    joint_names: tuple[str, ...]
    joint_error_mm: F64Array
    joint_offset_mm: F64Array
    joint_carriers: tuple[str, ...]
    joint_p50_mm: F64Array
    joint_p95_mm: F64Array
    joint_max_mm: F64Array

    def bones_past(self, p95_deg: float, max_deg: float) -> tuple[str, ...]:
        """The bones whose excess error is past ``p95_deg`` at p95 or ``max_deg`` at
        max (the plain error where no axis is unobserved)."""
        past = (self.excess_p95_deg > p95_deg) | (self.excess_max_deg > max_deg)
        return tuple(n for n, p in zip(self.bone_names, past, strict=True) if p)


def _unit_axes(axes: Sequence[Sequence[float]], bone: str) -> F64Array:
    arr = np.asarray(axes, dtype=np.float64).reshape(-1, 3)
    norms = np.linalg.norm(arr, axis=1)
    if arr.shape[0] == 0 or not np.all(np.isfinite(norms)) or np.any(norms < 1e-9):
        raise ValueError(
            f"unobserved[{bone!r}] must be non-zero 3-vectors (the bone's rest axes); "
            f"got {axes!r}"
        )
    return arr / norms[:, None]


def _excursion_deg(
    tmap: TruthMap,
    rig: Rig,
    world_from_segment_quat: F64Array,
    world_from_bone_ref_quat: F64Array,
    unobserved: Mapping[str, Sequence[Sequence[float]]],
    ref_frame: int,
) -> F64Array:
    """(T, K) degrees: per compared bone, the summed twist excursions (module doc)."""
    n_frames = world_from_segment_quat.shape[0]
    rig_names = [b.name for b in rig.bones]
    own = np.zeros((n_frames, len(rig_names)))  # per rig bone, its own axes
    for bone, axes in unobserved.items():
        if bone not in rig_names:
            raise ValueError(f"unobserved names bone {bone!r}, not in rig {rig.name}")
        b = rig_names.index(bone)
        if b not in tmap.bones:
            raise ValueError(
                f"unobserved bone {bone!r} stands for no performer segment "
                "(no humanoid name with a segment): its truth is unknown"
            )
        k = int(np.flatnonzero(tmap.bones == b)[0])
        seg, parent = tmap.segments[k], tmap.carriers[k]
        s = world_from_segment_quat[:, seg]
        rel = (
            s
            if parent < 0
            else rot.quat_mul(rot.quat_conj(world_from_segment_quat[:, parent]), s)
        )
        change = rot.quat_mul(rot.quat_conj(rel[ref_frame]), rel)
        # The bone's rest axis, in the segment's frame at the reference.
        seg_from_bone = rot.quat_mul(
            rot.quat_conj(s[ref_frame]), world_from_bone_ref_quat[b]
        )
        for axis in _unit_axes(axes, bone):
            axis_seg = rot.quat_rotate(seg_from_bone, axis)
            own[:, b] += np.abs(np.degrees(rot.twist_angle(change, axis_seg)))
    return np.stack([own[:, list(chain)].sum(axis=1) for chain in tmap.ancestors], 1)


def compare_with_truth(
    solve: BodySolve,
    take: SynthTake,
    rig: Rig,
    *,
    ref_frame: int = 0,
    frames: slice | None = None,
    unobserved: Mapping[str, Sequence[Sequence[float]]] | None = None,
) -> TruthComparison:
    """Compare a solve of a synthetic take with the take's truth.

    Args:
        solve: the take solved with ``rig`` (either method): ``world_from_bone_quat``
            (T, B, 4) (w, x, y, z), ``joint_centres`` (T, J, 3) metres, world.
        take: the synthetic take it solved (its truth: ``world_from_segment_quat``
            (T, S, 4), ``joint_pos_world`` (T, S, 3) metres).
        rig: the rig the solve used.
        ref_frame: the reference frame, in the calibration pose (default 0).
        frames: the frames the statistics cover (default all); errors cover all.
        unobserved: rig bone name -> unit axes (n, 3) in the bone's rest axes (the
            calibration pose's ``world_from_bone``, +Y along the bone for shipped
            rigs) that no marker determines.

    Returns:
        The :class:`TruthComparison`.

    Raises:
        ValueError: the solve and take differ in frames, ``ref_frame`` is out of
            range, or ``unobserved`` names an unknown bone, one with no segment or a
            zero axis.
    """
    wfb = np.asarray(solve.world_from_bone_quat, dtype=np.float64)
    n_frames = take.n_frames
    if wfb.shape[0] != n_frames:
        raise ValueError(
            f"solve has {wfb.shape[0]} frames, the take {n_frames}: not the same take"
        )
    if not 0 <= ref_frame < n_frames:
        raise ValueError(f"ref_frame must be in [0, {n_frames}); got {ref_frame}")
    frames = slice(0, n_frames) if frames is None else frames
    tmap = truth_map(rig, take.segment_names)
    wfs = np.asarray(take.world_from_segment_quat, dtype=np.float64)
    err = rotation_change_error_deg(
        wfb[:, tmap.bones], wfs[:, tmap.segments], ref_frame
    )
    excursion = np.zeros_like(err)
    if unobserved:
        excursion = _excursion_deg(
            tmap, rig, wfs, wfb[ref_frame], unobserved, ref_frame
        )
    p50, p95, top = error_stats(err[frames])
    _, ex_p95, ex_max = error_stats((err - excursion)[frames])
    bone_nan = np.asarray(np.isnan(wfb[:, tmap.bones]).any(axis=-1))
    n_nan = bone_nan[frames].sum(axis=0)

    cols = [solve.joint_names.index(j) for j in tmap.joint_names]
    centres = np.asarray(solve.joint_centres, dtype=np.float64)[:, cols]
    true_pos = np.asarray(take.joint_pos_world, dtype=np.float64)[
        :, tmap.joint_segments
    ]
    offset = centres[ref_frame] - true_pos[ref_frame]
    candidates = []
    for carriers in (tmap.joint_parents, tmap.joint_segments):
        carrier = wfs[:, carriers]
        offset_carrier = rot.quat_rotate(rot.quat_conj(carrier[ref_frame]), offset)
        predicted = true_pos + rot.quat_rotate(carrier, offset_carrier)
        cand = 1000.0 * np.linalg.norm(centres - predicted, axis=-1)
        candidates.append(np.where(np.isnan(cand), np.inf, cand))
    own = error_stats(candidates[1][frames])[1] < error_stats(candidates[0][frames])[1]
    joint_err = np.where(own, candidates[1], candidates[0])
    chosen = np.where(own, tmap.joint_segments, tmap.joint_parents)
    j50, j95, jmax = error_stats(joint_err[frames])
    return TruthComparison(
        ref_frame=ref_frame,
        stats_frames=frames,
        bone_names=tmap.bone_names,
        error_deg=err,
        excursion_deg=excursion,
        p50_deg=p50,
        p95_deg=p95,
        max_deg=top,
        excess_p95_deg=ex_p95,
        excess_max_deg=ex_max,
        n_nan=n_nan.astype(np.int64),
        joint_names=tmap.joint_names,
        joint_error_mm=joint_err,
        joint_offset_mm=1000.0 * np.linalg.norm(offset, axis=-1),
        joint_carriers=tuple(take.segment_names[int(c)] for c in chosen),
        joint_p50_mm=j50,
        joint_p95_mm=j95,
        joint_max_mm=jmax,
    )
