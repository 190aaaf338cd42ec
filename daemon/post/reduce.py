"""Keyframe reduction, not downsampling (the chapter's last section).

The frame rate stays; per channel (each bone's rotation, the root position) the keys
inside smooth stretches are dropped between boundary keys, as long as the curve
played back between the kept keys stays within a tolerance of every original frame:

1. Boundary keys: the first and last frame. The frame farthest from the curve
   between two kept keys (slerp for rotations, a straight line for positions) is
   kept, splitting the stretch, until no frame is farther than the tolerance (the
   Ramer-Douglas-Peucker "differences in the curves" search).
2. Least-squares refit ("a good method for curve fitting is the least squares
   method"): the kept keys' values are re-solved so the piecewise-linear curve
   through them fits all frames best, ``min Σ_t |Σ_k B_k(t) v_k - x_t|²`` with the
   hat functions ``B_k`` (a tridiagonal normal system); rotation keys are fitted on
   sign-continuous quaternion components and renormalized. The refit is kept only if
   the played-back curve still stays within the tolerance everywhere (else the
   original values are kept), so the stated tolerance always holds.

Playback is what glTF's LINEAR interpolation does: slerp between rotation keys,
lerp between translation keys (:mod:`retargetd.replay.gltf`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.linalg import solve_banded

from retargetd.daemon import rotations as rot
from retargetd.daemon.post.interp import Clip
from retargetd.protocols.conventions import MM_TO_M
from retargetd.protocols.frames import F64Array, IntArray

#: Rotation tolerance, degrees: a quarter of the ~2° trial-to-trial error of
#: optical gait kinematics (McGinley et al., Gait & Posture 29(3), 2009, a
#: systematic review: most angles within 2°), so the reduction is below what the
#: data itself can tell apart.
DEFAULT_TOLERANCE_DEG = 0.5
#: Root tolerance, millimetres: the order of an optical system's marker
#: reconstruction error (Merriaux et al., Sensors 17(7):1591, 2017, Vicon: sub-mm
#: static, about 2 mm in motion).
DEFAULT_TOLERANCE_MM = 1.0


@dataclass(frozen=True, slots=True, kw_only=True)
class KeyChannel:
    """One channel's kept keys.

    Attributes:
        frames: (K,) int64 frame indices, increasing, first 0 and last T-1.
        values: (K, 4) float64 unit quaternions (w, x, y, z), or (K, 3) float64
            positions (the input's unit and frame).
        max_error: largest deviation of the played-back curve from any frame:
            radians for rotations, the input's unit for positions.
        refitted: whether the least-squares values were kept.
    """

    frames: IntArray
    values: F64Array
    max_error: float
    refitted: bool


@dataclass(frozen=True, slots=True, kw_only=True)
class ReducedClip:
    """A clip as keys.

    Attributes:
        rotations: one :class:`KeyChannel` per bone (rotations ``parent_from_bone``).
        root: the root position's :class:`KeyChannel`, metres, world.
        n_frames: T of the original clip.
        rate_hz: its frame rate (key ``k`` plays at ``frames[k] / rate_hz``).
    """

    rotations: tuple[KeyChannel, ...]
    root: KeyChannel
    n_frames: int
    rate_hz: float


def _continuous(q: F64Array) -> F64Array:
    """Flip signs so each quaternion is in the hemisphere of the one before."""
    out = np.array(q, dtype=np.float64)
    dots = np.sum(out[1:] * out[:-1], axis=-1)
    flips = np.concatenate([[1.0], np.cumprod(np.where(dots < 0.0, -1.0, 1.0))])
    return out * flips[:, None]


def _params(frames: IntArray, n: int) -> tuple[IntArray, F64Array]:
    """Segment index and parameter u of every frame for keys at ``frames``."""
    t = np.arange(n)
    seg = np.clip(np.searchsorted(frames, t, side="right") - 1, 0, len(frames) - 2)
    u = (t - frames[seg]) / (frames[seg + 1] - frames[seg])
    return seg, u


def sample_rotation(frames: IntArray, values: F64Array, n_frames: int) -> F64Array:
    """Play rotation keys back at every frame (slerp between keys).

    Args:
        frames: (K,) int64 key frames, increasing, K >= 2.
        values: (K, 4) float64 (w, x, y, z).
        n_frames: T.

    Returns:
        (T, 4) float64 (w, x, y, z).
    """
    seg, u = _params(frames, n_frames)
    return rot.slerp(values[seg], values[seg + 1], u)


def sample_position(frames: IntArray, values: F64Array, n_frames: int) -> F64Array:
    """Play position keys back at every frame (lerp between keys).

    Args:
        frames: (K,) int64 key frames, increasing, K >= 2.
        values: (K, D) float64.
        n_frames: T.

    Returns:
        (T, D) float64.
    """
    seg, u = _params(frames, n_frames)
    return values[seg] + (values[seg + 1] - values[seg]) * u[:, None]


def _rot_error(a: F64Array, b: F64Array) -> F64Array:
    return rot.quat_angle(rot.quat_mul(rot.quat_conj(a), b))


def _split(x: F64Array, tol: float, is_rot: bool) -> IntArray:
    n = len(x)
    keep = np.zeros(n, dtype=bool)
    keep[0] = keep[-1] = True
    stack = [(0, n - 1)]
    while stack:
        i, j = stack.pop()
        if j - i < 2:
            continue
        u = (np.arange(i + 1, j) - i) / (j - i)
        if is_rot:
            err = _rot_error(rot.slerp(x[i], x[j], u), x[i + 1 : j])
        else:
            err = np.linalg.norm(
                x[i] + (x[j] - x[i]) * u[:, None] - x[i + 1 : j], axis=-1
            )
        worst = int(np.argmax(err))
        if err[worst] > tol:
            m = i + 1 + worst
            keep[m] = True
            stack.extend(((i, m), (m, j)))
    return np.flatnonzero(keep)


def _least_squares(frames: IntArray, x: F64Array) -> F64Array:
    """Key values minimizing the squared error of the hat-function curve."""
    n, k = len(x), len(frames)
    seg, u = _params(frames, n)
    w0, w1 = 1.0 - u, u
    diag = np.zeros(k)
    off = np.zeros(k - 1)
    rhs = np.zeros((k, x.shape[1]))
    np.add.at(diag, seg, w0 * w0)
    np.add.at(diag, seg + 1, w1 * w1)
    np.add.at(off, seg, w0 * w1)
    np.add.at(rhs, seg, w0[:, None] * x)
    np.add.at(rhs, seg + 1, w1[:, None] * x)
    ab = np.zeros((3, k))
    ab[0, 1:] = off
    ab[1] = diag
    ab[2, :-1] = off
    return solve_banded((1, 1), ab, rhs)


def _check_tolerance(tol: float, name: str) -> float:
    tol = float(tol)
    if not tol > 0.0 or not math.isfinite(tol):
        raise ValueError(f"{name} must be a positive finite number; got {tol!r}")
    return tol


def reduce_rotation(quat: F64Array, tolerance_rad: float) -> KeyChannel:
    """Reduce one rotation channel (module docstring).

    Args:
        quat: (T, 4) float64 unit quaternions (w, x, y, z), T >= 2, finite.
        tolerance_rad: largest rotation angle allowed between playback and data.

    Returns:
        The kept keys (sign-continuous values).

    Raises:
        ValueError: a bad shape, non-finite data or a bad tolerance.
    """
    tol = _check_tolerance(tolerance_rad, "tolerance_rad")
    q = np.asarray(quat, dtype=np.float64)
    if q.ndim != 2 or q.shape[1] != 4 or len(q) < 2 or not np.isfinite(q).all():
        raise ValueError(f"quat must be finite (T, 4) with T >= 2; got {q.shape}")
    q = _continuous(q)
    frames = _split(q, tol, is_rot=True)
    raw = q[frames]
    fit = rot.quat_normalize(_least_squares(frames, q))
    fit_err = float(_rot_error(sample_rotation(frames, fit, len(q)), q).max())
    if fit_err <= tol:
        return KeyChannel(frames=frames, values=fit, max_error=fit_err, refitted=True)
    raw_err = float(_rot_error(sample_rotation(frames, raw, len(q)), q).max())
    return KeyChannel(frames=frames, values=raw, max_error=raw_err, refitted=False)


def reduce_position(pos: F64Array, tolerance: float) -> KeyChannel:
    """Reduce one position channel (module docstring).

    Args:
        pos: (T, D) float64, any unit, T >= 2, finite.
        tolerance: largest distance allowed between playback and data, same unit.

    Returns:
        The kept keys.

    Raises:
        ValueError: a bad shape, non-finite data or a bad tolerance.
    """
    tol = _check_tolerance(tolerance, "tolerance")
    x = np.asarray(pos, dtype=np.float64)
    if x.ndim != 2 or len(x) < 2 or not np.isfinite(x).all():
        raise ValueError(f"pos must be finite (T, D) with T >= 2; got {x.shape}")
    frames = _split(x, tol, is_rot=False)
    fit = _least_squares(frames, x)
    fit_err = float(
        np.linalg.norm(sample_position(frames, fit, len(x)) - x, axis=-1).max()
    )
    if fit_err <= tol:
        return KeyChannel(frames=frames, values=fit, max_error=fit_err, refitted=True)
    raw = x[frames]
    raw_err = float(
        np.linalg.norm(sample_position(frames, raw, len(x)) - x, axis=-1).max()
    )
    return KeyChannel(frames=frames, values=raw, max_error=raw_err, refitted=False)


def reduce_clip(
    clip: Clip,
    *,
    tolerance_deg: float = DEFAULT_TOLERANCE_DEG,
    tolerance_mm: float = DEFAULT_TOLERANCE_MM,
) -> ReducedClip:
    """Reduce every channel of a clip.

    Args:
        clip: the take (finite rotations and root).
        tolerance_deg: rotation tolerance, degrees.
        tolerance_mm: root tolerance, millimetres.

    Returns:
        The keys per channel.
    """
    tol_rad = math.radians(_check_tolerance(tolerance_deg, "tolerance_deg"))
    tol_m = MM_TO_M * _check_tolerance(tolerance_mm, "tolerance_mm")
    q = clip.parent_from_bone_quat
    return ReducedClip(
        rotations=tuple(reduce_rotation(q[:, b], tol_rad) for b in range(q.shape[1])),
        root=reduce_position(clip.root_pos, tol_m),
        n_frames=clip.n_frames,
        rate_hz=clip.rate_hz,
    )


def describe(reduced: ReducedClip, bone_names: tuple[str, ...] | list[str]) -> str:
    """Keys kept per channel and the worst error, as ``retargetd reduce`` prints them.

    Args:
        reduced: the reduction.
        bone_names: (B,) names of the rotation channels.

    Returns:
        One line per channel plus a summary line (degrees, millimetres).
    """
    lines = []
    total = reduced.n_frames * (len(reduced.rotations) + 1)
    kept = len(reduced.root.frames)
    for name, ch in zip(bone_names, reduced.rotations, strict=True):
        kept += len(ch.frames)
        lines.append(
            f"{name:<16} rotation    {len(ch.frames):>6} of {reduced.n_frames} keys, "
            f"worst {math.degrees(ch.max_error):.3f} deg"
        )
    lines.append(
        f"{'root':<16} translation {len(reduced.root.frames):>6} of {reduced.n_frames} "
        f"keys, worst {reduced.root.max_error / MM_TO_M:.3f} mm"
    )
    worst = max((ch.max_error for ch in reduced.rotations), default=0.0)
    lines.append(
        f"kept {kept} of {total} keys ({100.0 * kept / total:.1f} %); worst "
        f"{math.degrees(worst):.3f} deg, root {reduced.root.max_error / MM_TO_M:.3f} mm"
    )
    return "\n".join(lines)
