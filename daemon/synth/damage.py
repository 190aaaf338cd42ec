"""Deterministic damage to a take's markers, and what it does to a solve.

The faults of issue 28 items 3 and 6, made on purpose: a marker hidden over a window
(:func:`hide_marker`) and bursts of bad frames, every marker collapsed onto one
marker's position (:func:`collapse_markers`), every coordinate exactly 0.0
(:func:`zero_markers`, what some systems send for lost markers) or the left and right
labels swapped (:func:`swap_left_right`). Each returns a damaged copy of a
``(T, M, 3)`` marker array (metres, world, NaN rows = occluded); frames outside the
window are untouched.

:func:`damage_metrics` compares the solve of the damaged take with the solve of the
intact one (and optionally both with the truth, :mod:`~retargetd.daemon.synth.truth`):
the largest joint-centre distance and bone angle, steps between frames the intact
solve does not have, NaN, and the recovery time after the window. A NaN pose counts
as the worst (180 deg, infinite mm).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.rig import Rig
from retargetd.daemon.body.solve import BodySolve
from retargetd.daemon.synth.performer import SynthTake
from retargetd.daemon.synth.truth import compare_with_truth
from retargetd.protocols.frames import F64Array

__all__ = [
    "DAMAGE_KINDS",
    "DamageKind",
    "DamageMetrics",
    "bone_deviation_deg",
    "collapse_markers",
    "damage",
    "damage_metrics",
    "hide_marker",
    "mirror_pairs",
    "recovery_frames",
    "swap_left_right",
    "zero_markers",
]

DamageKind = Literal["hide", "collapse", "zeros", "swap"]
#: Every kind of damage :func:`damage` makes.
DAMAGE_KINDS: tuple[DamageKind, ...] = ("hide", "collapse", "zeros", "swap")

#: Label prefixes that name a side, checked longest first, with their mirror.
_SIDE_PREFIXES = (
    ("Left", "Right"),
    ("left", "right"),
    ("LEFT", "RIGHT"),
    ("L_", "R_"),
    ("l_", "r_"),
    ("L", "R"),
    ("l", "r"),
)


def _window(positions: F64Array, frames: slice) -> tuple[F64Array, range]:
    pos = np.array(positions, dtype=np.float64)
    if pos.ndim != 3 or pos.shape[-1] != 3:
        raise ValueError(f"positions must be (frames, markers, 3); got {pos.shape}")
    span = range(*frames.indices(pos.shape[0]))
    if frames.step not in (None, 1) or len(span) == 0:
        raise ValueError(
            f"frames must be a non-empty contiguous slice of the take's "
            f"{pos.shape[0]} frames; got {frames}"
        )
    return pos, span


def _marker(positions: F64Array, marker: int, name: str) -> int:
    n = positions.shape[1]
    if not -n <= marker < n:
        raise ValueError(f"{name} must index one of the {n} markers; got {marker}")
    return marker % n


def hide_marker(positions: F64Array, marker: int, frames: slice) -> F64Array:
    """A copy with one marker occluded (NaN rows) over ``frames``.

    Args:
        positions: (T, M, 3) float64, metres, world; NaN rows = occluded.
        marker: the marker's column.
        frames: a contiguous window of frames.

    Returns:
        (T, M, 3) float64, the damaged copy.
    """
    pos, span = _window(positions, frames)
    pos[span.start : span.stop, _marker(pos, marker, "marker")] = np.nan
    return pos


def collapse_markers(positions: F64Array, onto: int, frames: slice) -> F64Array:
    """A copy where, over ``frames``, every marker (occluded ones too) reports the
    position of marker ``onto`` (NaN rows where that one is occluded): a bad
    reconstruction that labels one point with every name.

    Args:
        positions: (T, M, 3) float64, metres, world; NaN rows = occluded.
        onto: the column whose position every marker takes.
        frames: a contiguous window of frames.

    Returns:
        (T, M, 3) float64, the damaged copy.
    """
    pos, span = _window(positions, frames)
    onto = _marker(pos, onto, "onto")
    window = slice(span.start, span.stop)
    pos[window] = pos[window, onto][:, None, :]
    return pos


def zero_markers(positions: F64Array, frames: slice) -> F64Array:
    """A copy where every coordinate of every marker is exactly 0.0 over ``frames``
    (what some capture systems send for markers they lost).

    Args:
        positions: (T, M, 3) float64, metres, world; NaN rows = occluded.
        frames: a contiguous window of frames.

    Returns:
        (T, M, 3) float64, the damaged copy.
    """
    pos, span = _window(positions, frames)
    pos[span.start : span.stop] = 0.0
    return pos


def _split_subject(label: str) -> tuple[str, str]:
    head, sep, name = label.rpartition(":")
    return head + sep, name


def mirror_pairs(labels: Sequence[str]) -> tuple[tuple[int, int], ...]:
    """The left/right pairs among ``labels``: columns ``(i, j)``, ``i < j``, whose
    names differ only in a side prefix (``LKNE``/``RKNE``, ``LeftHand``/
    ``RightHand``, ``l_knee``/``r_knee``; a subject prefix ``Name:`` kept). A label
    whose mirror is absent pairs with nothing, and a label pairs at most once (the
    first of its names' left-side readings, in label order, that has a mirror).

    Args:
        labels: (M,) marker labels.

    Returns:
        The pairs, in order of their first column.
    """
    column = {label: i for i, label in enumerate(labels)}
    pairs: list[tuple[int, int]] = []
    used: set[int] = set()
    for i, label in enumerate(labels):
        subject, name = _split_subject(label)
        for left, right in _SIDE_PREFIXES:
            if not name.startswith(left) or len(name) == len(left):
                continue
            j = column.get(subject + right + name[len(left) :])
            if j is not None and j != i and not {i, j} & used:
                pairs.append((min(i, j), max(i, j)))
                used.update((i, j))
                break
    return tuple(sorted(pairs))


def swap_left_right(
    positions: F64Array, labels: Sequence[str], frames: slice
) -> F64Array:
    """A copy where, over ``frames``, every left/right pair of labels
    (:func:`mirror_pairs`) has its positions exchanged: the capture system's
    labelling mirrored.

    Args:
        positions: (T, M, 3) float64, metres, world; NaN rows = occluded.
        labels: (M,) marker labels.
        frames: a contiguous window of frames.

    Returns:
        (T, M, 3) float64, the damaged copy.

    Raises:
        ValueError: ``labels`` is not (M,), or has no left/right pair.
    """
    pos, span = _window(positions, frames)
    if len(labels) != pos.shape[1]:
        raise ValueError(f"labels must be {pos.shape[1]} names; got {len(labels)}")
    pairs = np.array(mirror_pairs(labels), dtype=np.int64).reshape(-1, 2)
    if pairs.size == 0:
        raise ValueError("labels hold no left/right pair to swap")
    window = slice(span.start, span.stop)
    cols = np.concatenate([pairs[:, 0], pairs[:, 1]])
    pos[window, cols] = pos[window, np.concatenate([pairs[:, 1], pairs[:, 0]])]
    return pos


def damage(
    positions: F64Array,
    labels: Sequence[str],
    kind: DamageKind,
    frames: slice,
    *,
    marker: int = 0,
) -> F64Array:
    """One kind of damage by name (:data:`DAMAGE_KINDS`).

    Args:
        positions: (T, M, 3) float64, metres, world; NaN rows = occluded.
        labels: (M,) marker labels (``"swap"``).
        kind: ``"hide"``, ``"collapse"``, ``"zeros"`` or ``"swap"``.
        frames: a contiguous window of frames.
        marker: the marker hidden (``"hide"``) or collapsed onto (``"collapse"``).

    Returns:
        (T, M, 3) float64, the damaged copy.

    Raises:
        ValueError: an unknown kind, or an argument the kind refuses.
    """
    if kind == "hide":
        return hide_marker(positions, marker, frames)
    if kind == "collapse":
        return collapse_markers(positions, marker, frames)
    if kind == "zeros":
        return zero_markers(positions, frames)
    if kind == "swap":
        return swap_left_right(positions, labels, frames)
    raise ValueError(f"kind must be one of {DAMAGE_KINDS}; got {kind!r}")


# --- what the damage did to the solve ---------------------------------------------


def bone_deviation_deg(a_quat: F64Array, b_quat: F64Array) -> F64Array:
    """Angle between two solves' world rotations, per frame and bone.

    Args:
        a_quat, b_quat: (T, B, 4) float64 (w, x, y, z), ``world_from_bone``.

    Returns:
        (T, B) float64 degrees, 180 where either is NaN.
    """
    rel = rot.quat_mul(np.asarray(a_quat), rot.quat_conj(np.asarray(b_quat)))
    out = np.degrees(rot.quat_angle(rel))
    return np.where(np.isnan(out), 180.0, out)


def _steps_deg(world_from_bone_quat: F64Array) -> F64Array:
    """(T-1, B) degrees: each bone's rotation from one frame to the next."""
    q = np.asarray(world_from_bone_quat)
    return bone_deviation_deg(q[1:], q[:-1])


def recovery_frames(deviation: F64Array, end: int, tolerance: float) -> int | None:
    """Frames from ``end`` until ``deviation`` is within ``tolerance`` for good.

    Args:
        deviation: (T,) float64, the worst deviation per frame (NaN = never within).
        end: the first frame after the damage.
        tolerance: in ``deviation``'s unit.

    Returns:
        The least ``k >= 0`` with ``deviation[t] <= tolerance`` for every ``t >= end
        + k``; 0 when ``end`` is the take's end; None when the last frame is still
        outside (never recovered within the take).
    """
    dev = np.asarray(deviation, dtype=np.float64)
    if not 0 <= end <= dev.shape[0]:
        raise ValueError(f"end must be in [0, {dev.shape[0]}]; got {end}")
    outside = np.flatnonzero(~(dev[end:] <= tolerance))
    if outside.size == 0:
        return 0
    if outside[-1] == dev.shape[0] - end - 1:
        return None
    return int(outside[-1]) + 1


@dataclass(frozen=True, slots=True, kw_only=True)
class DamageMetrics:
    """A damaged take's solve against the intact take's (same rig, calibration,
    method), over every frame.

    Attributes:
        max_joint_mm: largest joint-centre distance, mm (inf where NaN).
        max_joint: the joint it is at.
        max_bone_deg: largest bone rotation difference (world), degrees.
        max_bone: the bone it is at.
        new_steps: (frame, bone) pairs where the damaged solve turns by more than
            ``step_deg`` from the previous frame and the intact solve does not.
        max_new_step_deg: the largest of those steps, degrees (0 when none).
        any_nan: any NaN in the damaged solve's rotations or joint centres.
        nan_frames: the frames that hold one.
        recovery_frames: frames from the window's end until every bone is within
            ``tol_deg`` (and every joint within ``tol_mm``, when given) of the intact
            solve and stays there; None = not by the take's end.
        recovery_s: the same in seconds (``recovery_frames / rate_hz``), or None.
        truth_max_deg: with a truth, the damaged solve's largest bone error against
            it (``truth.compare_with_truth``, every frame), else None.
        intact_truth_max_deg: the intact solve's, for scale, else None.
    """

    max_joint_mm: float
    max_joint: str
    max_bone_deg: float
    max_bone: str
    new_steps: int
    max_new_step_deg: float
    any_nan: bool
    nan_frames: int
    recovery_frames: int | None
    recovery_s: float | None
    truth_max_deg: float | None = None
    intact_truth_max_deg: float | None = None


def damage_metrics(
    intact: BodySolve,
    damaged: BodySolve,
    window: slice,
    rate_hz: float,
    *,
    tol_deg: float = 2.0,
    tol_mm: float | None = 10.0,
    step_deg: float = 5.0,
    truth: SynthTake | None = None,
    rig: Rig | None = None,
) -> DamageMetrics:
    """What the damage over ``window`` did to the solve.

    Args:
        intact: the intact take's solve: ``world_from_bone_quat`` (T, B, 4) (w, x,
            y, z), ``joint_centres`` (T, J, 3) metres, world.
        damaged: the damaged take's solve, same solver settings.
        window: the damaged frames (contiguous).
        rate_hz: frame rate, for ``recovery_s``.
        tol_deg: a bone within this of the intact solve has recovered (degrees).
        tol_mm: a joint centre within this has recovered (mm); None: bones only.
        step_deg: a frame-to-frame rotation above this is a step (degrees).
        truth, rig: the take's truth and the rig solved, to add the truth errors.

    Returns:
        The :class:`DamageMetrics`.

    Raises:
        ValueError: the solves differ in shape, or an empty window.
    """
    qa = np.asarray(intact.world_from_bone_quat, dtype=np.float64)
    qd = np.asarray(damaged.world_from_bone_quat, dtype=np.float64)
    ja = np.asarray(intact.joint_centres, dtype=np.float64)
    jd = np.asarray(damaged.joint_centres, dtype=np.float64)
    if qa.shape != qd.shape or ja.shape != jd.shape:
        raise ValueError(
            f"the solves differ: bones {qa.shape} vs {qd.shape}, joints {ja.shape} "
            f"vs {jd.shape}"
        )
    n_frames = qa.shape[0]
    span = range(*window.indices(n_frames))
    if len(span) == 0 or window.step not in (None, 1):
        raise ValueError(f"window must be a non-empty contiguous slice; got {window}")
    bone_dev = bone_deviation_deg(qd, qa)
    joint_dev = 1000.0 * np.linalg.norm(jd - ja, axis=-1)
    joint_dev = np.where(np.isnan(joint_dev), np.inf, joint_dev)
    step_a, step_d = _steps_deg(qa), _steps_deg(qd)
    new = (step_d > step_deg) & ~(step_a > step_deg)
    worst = bone_dev.max(axis=1)
    if tol_mm is not None and joint_dev.shape[1]:
        # in degrees' terms: any joint past tol_mm reads as past tol_deg
        worst = np.where(joint_dev.max(axis=1) > tol_mm, np.inf, worst)
    rec = recovery_frames(worst, span.stop, tol_deg)
    b_t, b = np.unravel_index(int(np.argmax(bone_dev)), bone_dev.shape)
    j_t, j = (
        np.unravel_index(int(np.argmax(joint_dev)), joint_dev.shape)
        if joint_dev.size
        else (0, 0)
    )
    nan_frames = np.isnan(qd).any(axis=(1, 2)) | np.isnan(jd).any(axis=(1, 2))
    truth_max = intact_truth_max = None
    if truth is not None:
        if rig is None:
            raise ValueError("damage_metrics needs the rig to compare with the truth")
        truth_max = float(compare_with_truth(damaged, truth, rig).max_deg.max())
        intact_truth_max = float(compare_with_truth(intact, truth, rig).max_deg.max())
    return DamageMetrics(
        max_joint_mm=float(joint_dev[j_t, j]) if joint_dev.size else 0.0,
        max_joint=intact.joint_names[j] if joint_dev.size else "",
        max_bone_deg=float(bone_dev[b_t, b]),
        max_bone=intact.bone_names[b],
        new_steps=int(new.sum()),
        max_new_step_deg=float(step_d[new].max()) if new.any() else 0.0,
        any_nan=bool(nan_frames.any()),
        nan_frames=int(nan_frames.sum()),
        recovery_frames=rec,
        recovery_s=None if rec is None else rec / rate_hz,
        truth_max_deg=truth_max,
        intact_truth_max_deg=intact_truth_max,
    )
