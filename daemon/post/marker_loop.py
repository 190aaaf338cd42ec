"""A seamless loop of marker frames, for ``retargetd replay TAKE --loop --blend-frames
N``: the take's last N frames cross-faded into its first N, as
:func:`~retargetd.daemon.post.interp.loop` does for rotations (the same fade weights,
the loop N frames shorter), on marker positions.

A cyclic take rarely ends where it began: a walk has travelled and turned. So the
tail is first carried onto the head by one rigid motion of the floor, ``A(x) = R x +
t`` (a turn ``R`` about world +Z and a horizontal shift ``t``; heights kept), fitted
by least squares to every marker seen in both the last N and the first N frames
(the 2-D Kabsch/Horn solution: ``yaw = atan2(Σ (a_x b_y - a_y b_x), Σ a · b)`` over
the centred horizontal positions, ``t = b̄ - R ā``). Then, with ``u_k = (k + 1) /
(N + 1)``,

    loop[k]       = (1 - u_k) A(m[T - N + k]) + u_k m[k]      k < N
    loop[k]       = m[k]                                      N <= k < T - N

Per marker linear interpolation is the right blend here: after the alignment the two
frames blended are the same body in nearly the same pose, so every segment's markers
move along nearly parallel short paths and a linear mix of two rigid placements of a
segment stays rigid to second order in their difference (a segment turned by θ
between them shrinks by ``1 - cos(θ/2) ≈ θ²/8`` at mid-fade: 0.06 % at 4°); and it
never needs a skeleton, so it works on any marker set. A marker occluded in either
frame is occluded in the blend (a blend of one side only would jump).

Played round, pass ``p`` is the loop moved by ``A^{-p}``: frame ``T - N - 1`` of one
pass is followed by frame 0 of the next, which is mostly ``A^{-1} A m[T - N] = m[T -
N]`` in the previous pass's placement, its natural successor. A walk therefore walks
on (each pass one cycle further round, like root motion in an engine); a take that
stays in place has ``A`` near identity and stays in place.
"""

from __future__ import annotations

import math

import numpy as np

from retargetd.protocols.frames import F64Array


def fade_weights(n_frames: int) -> F64Array:
    """(N,) float64: ``(k + 1) / (N + 1)``, the weight of the head frame in fade frame
    ``k`` (strictly inside (0, 1): neither take's own frame is repeated); the
    weights of :func:`~retargetd.daemon.post.interp.loop` and ``blend``."""
    return np.asarray((np.arange(n_frames) + 1.0) / (n_frames + 1.0), np.float64)


def floor_motion(from_pos: F64Array, to_pos: F64Array) -> tuple[F64Array, F64Array]:
    """The rigid motion of the floor (turn about +Z, horizontal shift) that best
    carries ``from_pos`` onto ``to_pos`` (least squares over the pairs both see).

    Args:
        from_pos: (..., 3) float64, metres, world; NaN = not seen.
        to_pos: (..., 3) float64, same shape.

    Returns:
        ``(to_from_mat (3, 3), to_from_pos (3,))``: ``x_to = R x_from + t``, t z = 0.

    Raises:
        ValueError: fewer than 2 pairs seen in both.
    """
    a = np.asarray(from_pos, dtype=np.float64).reshape(-1, 3)
    b = np.asarray(to_pos, dtype=np.float64).reshape(-1, 3)
    both = np.isfinite(a).all(axis=1) & np.isfinite(b).all(axis=1)
    if np.count_nonzero(both) < 2:
        raise ValueError("the loop's first and last frames share fewer than 2 markers")
    a2, b2 = a[both, :2], b[both, :2]
    ca, cb = a2.mean(axis=0), b2.mean(axis=0)
    da, db = a2 - ca, b2 - cb
    cross = float(np.sum(da[:, 0] * db[:, 1] - da[:, 1] * db[:, 0]))
    dot = float(np.sum(da * db))
    yaw = math.atan2(cross, dot)
    c, s = math.cos(yaw), math.sin(yaw)
    mat = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    pos = np.zeros(3)
    pos[:2] = cb - mat[:2, :2] @ ca
    return mat, pos


def loop_markers(
    markers_world: F64Array, n_frames: int
) -> tuple[F64Array, F64Array, F64Array]:
    """The seamless marker loop of a cyclic take (module docstring).

    Args:
        markers_world: (T, M, 3) float64, metres, world; NaN = occluded. Its first and
            last N frames should be alike in pose and gait phase (pick the window).
        n_frames: fade length N (>= 1, ``2 N < T``).

    Returns:
        ``(loop, head_from_tail_mat, head_from_tail_pos)``: (T - N, M, 3) float64 the
        loop, and the rigid floor motion ``A`` (3, 3), (3,) that carried the tail
        onto the head (pass ``p`` is played moved by ``A^{-p}``).

    Raises:
        ValueError: ``n_frames`` out of range, or no markers shared by the ends.
    """
    m = np.asarray(markers_world, dtype=np.float64)
    t = m.shape[0]
    if m.ndim != 3 or m.shape[2] != 3:
        raise ValueError(f"markers_world must be (T, M, 3); got {m.shape}")
    if n_frames < 1 or 2 * n_frames >= t:
        raise ValueError(
            f"--blend-frames must be in 1 .. {(t - 1) // 2} for {t} frames; got "
            f"{n_frames}"
        )
    tail, head = m[t - n_frames :], m[:n_frames]
    mat, pos = floor_motion(tail, head)
    aligned = tail @ mat.T + pos
    u = fade_weights(n_frames)[:, None, None]
    fade = (1.0 - u) * aligned + u * head
    return np.concatenate([fade, m[n_frames : t - n_frames]]), mat, pos
