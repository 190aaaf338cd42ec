"""The offline fit filled across a hidden marker's span from both sides.

A causal solve (the live daemon's, :meth:`FitSolver.solve_take`) can only hold what a
hidden marker alone saw at its value when the marker vanished, and has to get back when
it reappears, while the performer kept moving in it (``menache``'s RIWRIST on the
ulna's twist axis: 112 deg of pronation in a hidden second). An offline take is known
at both ends of the gap, as every offline mocap pipeline uses it (Vicon Nexus's spline,
pattern and rigid-body fills, QTM's and Motive's gap fills).

:func:`solve_two_sided` solves the take forwards (as today) and backwards (the take
reversed in time through the same solver, reset: the same calibration, model and
parameters), the backward outputs reversed back. Both are valid solves: they agree
where the markers determine the pose and differ where a hold, or the recovery after
it, made one of them guess. :func:`fill_from_both_sides` then, per bone:

- **spans**: the frames where a marker its rotation depends on is not seen (the fit's
  own "not seen": its residual is NaN). A bone's world rotation depends on the markers
  riding it or a descendant (a marker's position moves with every rotation on its path
  to the root); the bones hanging from the marker's bone take the same span, since
  their joints are fitted relative to it (the joint models: a wrist's swing holds the
  hand's twist to the forearm's) and the hold's guess in it carries into them. A
  marker never seen in the take gives no span.
- **blend**: across a span seen before and after it, the two solves' world rotations
  of the bone slerped with a weight growing linearly from 0 at the last frame seen
  before (the forward side) to 1 at the first seen after (the backward side): the
  standard linear gap fill, the unobserved rotation interpolated between its two
  anchors, with no number of its own. A span open at the take's start takes the
  backward solve, one open at its end the forward (as it is).
- **hand-back**: after a span the forward solve is still coming back (its continuity
  prior, its hold let go) while the backward one has seen the marker throughout: the
  backward solve is kept until the two world rotations agree within
  :data:`AGREE_RAD` (the root's origin within :data:`AGREE_M`), then the forward one
  takes over (never past the bone's next span). A marker's return the forward solve
  could not explain (its frame unexplained: every bone's last pose held) hands every
  bone back so. Before a span the forward solve is the anchored one, kept as it is.

From the blended world rotations the parent-relative and rest-relative ones are
derived as the kernel derives them, the root position blended with the root's weight,
the joint centres by the fit's forward kinematics (``fit_model``'s offsets, the
kernel's ``fit_terms.fk`` in numpy) and the marker residuals and RMS of the blended
pose. Every other frame, and every per-frame statistic (iterations, reseeds, level),
is the forward solve's, bit for bit: an intact take's solve does not move.
``TwoSidedSolve.filled`` (the NPZ's ``fit_filled``) marks each filled bone-frame.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.solve_fit import FitSolve, FitSolver
from retargetd.protocols.frames import F64Array

__all__ = [
    "AGREE_M",
    "AGREE_RAD",
    "TwoSidedSolve",
    "backward_solve",
    "fill_from_both_sides",
    "solve_two_sided",
]

#: The forward solve takes a bone back after a span once its world rotation is within
#: this of the backward solve's: 0.5 deg, the rotation whose 1 mm of marker noise
#: (``FitParams.noise_m``, optical residuals < 1 mm: Merriaux et al., Sensors
#: 17(7):1591, 2017) a marker ~115 mm from the bone's axis sees (the lever of a
#: limb segment's markers, 50-150 mm): the two solves then differ by no more than
#: the markers can tell, and the switch is a step of at most that.
AGREE_RAD = math.radians(0.5)
#: The same for the root's position: the 1 mm of marker noise itself.
AGREE_M = 1e-3

#: FitSolve fields that hold one value for the take (not per frame).
_PER_TAKE = frozenset({"bone_lengths"})


def _empty_bool() -> np.ndarray:
    return np.zeros((0, 0), dtype=bool)


@dataclass(frozen=True, slots=True, kw_only=True)
class TwoSidedSolve(FitSolve):
    """A take solved by the fit and filled from both sides.

    Attributes:
        filled: (T, B) bool, the bone's rotation (and with it the frame's joint
            centres and residuals) blended from the forward and backward solves, or
            the backward one's (a span open at the take's start, a hand-back).
    """

    filled: np.ndarray = field(default_factory=_empty_bool)


def _reversed(solve: FitSolve) -> FitSolve:
    """Every per-frame array of ``solve`` reversed in time."""
    changes: dict[str, Any] = {}
    for f in dataclasses.fields(solve):
        v = getattr(solve, f.name)
        if isinstance(v, np.ndarray) and v.ndim and f.name not in _PER_TAKE:
            changes[f.name] = np.ascontiguousarray(v[::-1])
    return dataclasses.replace(solve, **changes)


def backward_solve(
    solver: FitSolver,
    positions: F64Array,
    solve: Callable[[FitSolver, F64Array], FitSolve] | None = None,
) -> FitSolve:
    """The take solved backwards in time by ``solver`` (reset before and after), its
    outputs reversed back into the take's order.

    Args:
        solver: the fit (its calibration, model and parameters).
        positions: (T, M, 3) float64, metres, world, NaN rows = occluded.
        solve: how to solve a take (default ``FitSolver.solve_take``; the CLI passes
            its progress bar's chunked solve).

    Returns:
        The backward solve, its per-frame arrays in the take's order.
    """
    run = solve if solve is not None else FitSolver.solve_take
    solver.reset()
    res = run(solver, np.ascontiguousarray(positions[::-1], dtype=np.float64))
    solver.reset()
    return _reversed(res)


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Half-open [start, stop) runs of True in a 1-d bool array."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    starts, stops = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    return [(int(a), int(b)) for a, b in zip(starts, stops, strict=True)]


def _bone_groups(
    parent: np.ndarray, marker_bone: np.ndarray, marker_weight: np.ndarray
) -> list[np.ndarray]:
    """Per rig marker, the bones whose span it opens: the marker's bone, its
    ancestors (their rotations move it) and its descendants (fitted relative to
    it). Empty for a marker the fit does not use (on no bone, or weight 0)."""
    n_b = parent.shape[0]
    groups = []
    for k, wt in zip(marker_bone, marker_weight, strict=True):
        if k < 0 or not wt > 0.0:
            groups.append(np.zeros(0, dtype=np.int64))
            continue
        on = np.zeros(n_b, dtype=bool)
        b = int(k)
        while b >= 0:  # the bone and its ancestors
            on[b] = True
            b = int(parent[b])
        below = np.zeros(n_b, dtype=bool)
        below[int(k)] = True
        for c in range(n_b):  # parents come first: one pass finds the subtree
            if parent[c] >= 0 and below[parent[c]]:
                below[c] = True
        groups.append(np.flatnonzero(on | below))
    return groups


def _angle(a: F64Array, b: F64Array) -> F64Array:
    """Angle (rad) between unit quaternions (w, x, y, z) along the last axis."""
    d = np.minimum(np.abs(np.sum(a * b, axis=-1)), 1.0)
    return 2.0 * np.arccos(d)


def bone_weights(
    seen: np.ndarray,
    groups: list[np.ndarray],
    agree: np.ndarray,
    stale: np.ndarray,
) -> tuple[F64Array, np.ndarray]:
    """Per bone and frame, the backward solve's weight and whether it is filled.

    Args:
        seen: (T, Mr) bool, each rig marker seen (its residual finite).
        groups: per rig marker, the bones its span covers (:func:`_bone_groups`).
        agree: (T, B) bool, the two solves within :data:`AGREE_RAD` (the root's
            origin within :data:`AGREE_M`): the hand-back test.
        stale: (T,) bool, the forward solve held its last explained pose (the frame
            unexplained) where the backward one explained the frame.

    Returns:
        ``(w, filled)``: (T, B) float64 in [0, 1] (0: forward, 1: backward) and
        (T, B) bool.
    """
    n, n_b = agree.shape
    ever = np.asarray(seen.any(axis=0))
    hidden = np.zeros((n, n_b), dtype=bool)
    for m, bones in enumerate(groups):
        if ever[m] and bones.size:
            hidden[:, bones] |= ~seen[:, m, None]
    w = np.zeros((n, n_b))
    filled = np.zeros((n, n_b), dtype=bool)

    def hand_back(b: int, e: int) -> None:
        # the backward solve from e until the two agree (and the forward explains
        # the frame again), never into the bone's next span
        t = e
        while t < n and not hidden[t, b] and (stale[t] or not agree[t, b]):
            t += 1
        w[e:t, b] = 1.0
        filled[e:t, b] = True

    for b in range(n_b):
        for s, e in _runs(hidden[:, b]):
            if e >= n:  # open at the take's end: the forward solve's hold
                continue
            if s == 0:  # open at its start: the backward solve, seen throughout
                w[:e, b] = 1.0
            else:  # anchored on both sides: the linear gap fill
                w[s:e, b] = (np.arange(s, e) - (s - 1)) / (e - (s - 1))
            filled[s:e, b] = True
            hand_back(b, e)
    # A marker's return that the forward solve could not explain (the rotation it
    # alone saw held far from where the performer took it) holds every bone's last
    # pose there, not only its chain's: every bone is handed back from that frame.
    for mk in np.flatnonzero(ever):
        for _, stop in _runs(~seen[:, mk]):
            if stop < n and stale[stop]:
                for b in range(n_b):
                    if not filled[stop, b]:
                        hand_back(b, stop)
    return w, filled


def _fk(
    parent: np.ndarray, off: F64Array, wq: F64Array, root: F64Array
) -> tuple[F64Array, F64Array]:
    """Bone origins (..., B, 3) and rotation matrices (..., B, 3, 3) from world
    rotations (..., B, 4) and the root's origin (..., 3): ``fit_terms.fk`` in world
    rotations (one root)."""
    wm = rot.mat_from_quat(wq)
    o = np.zeros((*wq.shape[:-1], 3))
    for b in range(parent.shape[0]):
        p = parent[b]
        o[..., b, :] = root if p < 0 else o[..., p, :] + wm[..., p, :, :] @ off[b]
    return o, wm


def fill_from_both_sides(
    solver: FitSolver,
    positions: F64Array,
    forward: FitSolve,
    backward: FitSolve,
) -> TwoSidedSolve:
    """``forward`` with each hidden span filled from ``backward`` (module docstring).

    Args:
        solver: the fit that made both (its model: parents, offsets, markers).
        positions: (T, M, 3) float64, metres, world, the take as solved.
        forward: its causal solve; backward: its backward solve
            (:func:`backward_solve`).

    Returns:
        The forward solve with the filled frames replaced and ``filled`` set.
    """
    model = solver.model
    parent = np.asarray(model.bone_parent)
    n, n_b = forward.world_from_bone_quat.shape[:2]
    seen = np.isfinite(forward.marker_residual)
    fq, bq = forward.world_from_bone_quat, backward.world_from_bone_quat
    agree = _angle(fq, bq) <= AGREE_RAD
    gap = np.linalg.norm(forward.root_pos - backward.root_pos, axis=-1)
    agree[:, 0] &= gap <= AGREE_M  # the root bone: its origin too
    if model.n_roots != 1:  # blends one tree: the root's origin is its only one
        return TwoSidedSolve(**_fields(forward), filled=np.zeros((n, n_b), bool))
    groups = _bone_groups(
        parent, np.asarray(model.marker_bone), np.asarray(model.marker_weight)
    )
    stale = forward.unexplained & ~backward.unexplained
    w, filled = bone_weights(seen, groups, agree, stale)
    rows = np.flatnonzero(filled.any(axis=1))
    out = {
        k: v.copy() for k, v in _fields(forward).items() if isinstance(v, np.ndarray)
    }
    if rows.size:
        _fill_rows(solver, positions, forward, backward, w[rows], rows, out)
    return TwoSidedSolve(**{**_fields(forward), **out}, filled=filled)


def _fields(solve: FitSolve) -> dict[str, Any]:
    return {f.name: getattr(solve, f.name) for f in dataclasses.fields(solve)}


def _fill_rows(
    solver: FitSolver,
    positions: F64Array,
    forward: FitSolve,
    backward: FitSolve,
    w: F64Array,
    rows: np.ndarray,
    out: dict[str, Any],
) -> None:
    """Write the blended pose of ``rows`` (weights ``w`` (R, B)) into ``out``."""
    model = solver.model
    parent = np.asarray(model.bone_parent)
    fq = forward.world_from_bone_quat[rows]
    bq = backward.world_from_bone_quat[rows]
    wq = rot.slerp(fq, bq, w)
    # sign: the forward solve's at the same frame (its stream is sign-continuous)
    wq = rot.quat_canonical_hemisphere(wq, fq)
    keep = w == 0.0  # bones not filled on a filled frame: the forward's own
    wq[keep] = fq[keep]
    w0 = w[:, 0:1]
    root = (1.0 - w0) * forward.root_pos[rows] + w0 * backward.root_pos[rows]
    root[w[:, 0] == 0.0] = forward.root_pos[rows][w[:, 0] == 0.0]
    o, wm = _fk(parent, np.asarray(model.off_parent), wq, root)
    # parent-relative (the root's parent: the world) and rest-relative, as the
    # kernel derives them from its streamed world rotations
    pfb = wq.copy()
    has_p = parent >= 0
    pfb[:, has_p] = rot.quat_mul(rot.quat_conj(wq[:, parent[has_p]]), wq[:, has_p])
    rfb = rot.quat_mul(rot.quat_conj(np.asarray(model.rest_pfb))[None], pfb)
    rfb = np.where(rfb[..., :1] < 0.0, -rfb, rfb)
    jb = np.asarray(model.joint_bone)
    joints = o[:, jb] + np.einsum("rjkl,jl->rjk", wm[:, jb], model.joint_local)
    out["world_from_bone_quat"][rows] = wq
    out["parent_from_bone_quat"][rows] = pfb
    out["rest_from_bone_quat"][rows] = rfb
    out["root_pos"][rows] = root
    out["joint_centres"][rows] = joints
    # the blended pose's marker residuals (seen markers only), and their inlier RMS
    mb = np.asarray(model.marker_bone)
    cols = np.asarray(solver.marker_cols)
    resid = out["marker_residual"][rows]
    ok = (mb >= 0) & (cols >= 0)
    idx = np.flatnonzero(ok)
    pred = o[:, mb[idx]] + np.einsum(
        "rmkl,ml->rmk", wm[:, mb[idx]], model.marker_local[idx]
    )
    meas = positions[rows][:, cols[idx]]
    new = np.linalg.norm(pred - meas, axis=-1)
    seen = np.isfinite(resid[:, idx])
    resid[:, idx] = np.where(seen, new, np.nan)
    out["marker_residual"][rows] = resid
    inl = np.isfinite(resid) & ~forward.marker_rejected[rows]
    sq = np.where(inl, resid, 0.0) ** 2
    cnt = inl.sum(axis=1)
    rms = np.sqrt(sq.sum(axis=1) / np.maximum(cnt, 1))
    out["marker_rms"][rows] = np.where(cnt > 0, rms, forward.marker_rms[rows])


def solve_two_sided(
    solver: FitSolver,
    positions: F64Array,
    solve: Callable[[FitSolver, F64Array], FitSolve] | None = None,
) -> TwoSidedSolve:
    """The take solved forwards and backwards and filled from both sides.

    Args:
        solver: the fit; left reset.
        positions: (T, M, 3) float64, metres, world, NaN rows = occluded.
        solve: how to solve a take (default ``FitSolver.solve_take``).

    Returns:
        The forward solve, each hidden span filled (module docstring).
    """
    run = solve if solve is not None else FitSolver.solve_take
    positions = np.ascontiguousarray(positions, dtype=np.float64)
    forward = run(solver, positions)
    backward = backward_solve(solver, positions, run)
    return fill_from_both_sides(solver, positions, forward, backward)
