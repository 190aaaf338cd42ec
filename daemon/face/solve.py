"""The stabilized face: head motion removed, blendshape weights solved per frame.

Two steps per frame, one compiled call (numba, no allocation in steady state):

1. **Stabilization.** A weighted rigid fit (Horn's quaternion form of Kabsch) of the
   visible head markers (>= 3, not collinear) to their neutral layout in head
   coordinates gives ``world_from_head`` (quat + pos). Every facial marker is mapped
   back, ``p_head = R^T (p_world - t)``: the stabilized markers (the chapter's "Mug"
   control points).
2. **Weights.** With ``d`` the stabilized displacement from the neutral layout over the
   visible facial markers, ``B`` (3 M x K) the training-set deltas of the solved
   shapes and ``J`` (3 M x 6) how the neutral facial markers move under a small
   correction ``delta = (tau, theta)`` of the head pose (``p -> p + tau + theta x p``),
   solve

       min_{w, delta}  |B_v w + J_v delta - d_v|^2 + delta^T G delta + lambda |w|^2
       subject to 0 <= w <= 1

   with ``G = sum_i w_i H_i^T H_i`` over the head markers the fit used (``H_i`` the
   same Jacobian at head marker ``i``). This is the least squares over every marker,
   facial and head, in the weights and the head pose together, linearized about the
   head markers' fit (whose residuals are orthogonal to ``H``, leaving only
   ``delta^T G delta``): by Gauss-Markov the best linear unbiased estimate for equal,
   independent marker noise. Fitting the head to the head markers alone and then
   solving the weights treats the fit's error (0.45 mm RMS at the face for 0.5 mm
   noise, as much as the markers' own) as if it were expression. The pose
   correction is used for the weights only: the stabilized markers and the head
   pose sent are the head markers' fit (they do not depend on the face model). The
   linearization at the neutral markers ignores ``theta x (B w)``: ~1e-3 rad times
   <= 2 cm, 0.02 mm, a tenth of the noise.

   This is the box QP ``min 1/2 x^T A x - b^T x`` over ``x = (w, delta)`` with ``A =
   [B_v J_v]^T [B_v J_v] + diag(lambda I, G)`` and ``b = [B_v J_v]^T d_v`` (``v`` =
   visible rows); ``delta`` unbounded, so it is eliminated first (the Schur complement
   ``A_ww - A_wd A_dd^-1 A_dw``, ``b_w - A_wd A_dd^-1 b_d``: the same ``w``), leaving a
   box QP in ``w`` alone. ``A`` is precomputed for all markers; when the occlusion
   pattern (facial or head) changes, the rows of the occluded markers are subtracted
   once (their ``B_m^T B_m``), ``G`` rebuilt and the pose eliminated again; per frame
   only ``b`` and its reduction (K x 6) are new. The QP is solved by block
   principal pivoting on its KKT conditions (free block by Cholesky, every bound
   violation exchanged at once, with Murty's single exchange as the finite
   fallback), warm-started from the last frame's active set: in steady state a few
   Cholesky solves of the free block.

``lambda = regularization * noise_rms_m^2`` (``face.observability.ridge``: the
maximum a posteriori ridge for a weight prior ``N(0, 1/3)``, Hoerl & Kennard 1970;
``regularization`` unitless, default 1), from the training set's noise.

**Stabilization error.** What stabilization adds is the error of the fitted head pose
carried to each facial marker: the stabilized marker minus the same observed marker
mapped by the true pose, ``R_fit^T (p - t_fit) - R^T (p - t)``. That is the
"stabilization residual" (issue 7: <= 0.5 mm RMS). The facial markers' own noise goes
through any rigid map unchanged, so the stabilized noisy markers against the
noise-free face hold both, in quadrature (``total^2 = stab^2 + noise^2``); the same
stabilization residual is what noise-free facial markers with noisy head markers show.
With independent, equal noise on the head markers, the least-squares fit is the best
linear unbiased pose (Gauss-Markov): no weighting does better, and the error is set by
the number and spread of the head markers and how far the face is from them.
:func:`stabilization_error` gives it to first order; the kernel reaches it. For the
synthetic face (``face_synth``: the Plug-in Gait take's four head markers as a band at
temple height, 0.5 mm 3-D RMS noise) it is 0.45 mm RMS over the 40 facial markers
(0.31-0.56 mm per marker; 0.42 mm measured), 0.55-0.79 mm with one head marker
missing. The pose is not filtered over time: a causal constant-velocity (alpha-beta)
filter of the head rotation took 20-30 % off on walks (100 and 250 Hz) but lagged on
fast head motion (a 50 Hz tennis serve: 0.87 -> 1.5 mm and worse).

The compiled kernels are in ``kernel_face``. Frames: markers in the internal world
(metres); head coordinates are the training set's: origin at the neutral head-marker
centroid. Quaternions are (w, x, y, z).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from retargetd.daemon.face.kernel import (
    FLAG_FACE_PARTIAL,
    FLAG_HEAD_LOST,
    FLAG_HEAD_PARTIAL,
    FLAG_NEVER,
    FLAG_NOT_CONVERGED,
    FLAG_SHAPE_HELD,
    SHAPE_HIDDEN,
    SHAPE_UNOBSERVED,
    solve_face_frame,
)
from retargetd.daemon.face.observability import (
    MAX_WEIGHT_STD,
    Observability,
    key_markers,
    observability,
    pose_information,
    pose_jacobian,
    ridge,
)
from retargetd.daemon.face.training import DEFAULT_NOISE_RMS_M, TrainingSet

logger = logging.getLogger(__name__)

F64Array = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


# ---- training set -------------------------------------------------------------------


def stabilization_error(
    training: TrainingSet,
    *,
    noise_rms_m: float = 5e-4,
    head_weights: Sequence[float] | None = None,
    head_seen: Sequence[bool] | None = None,
) -> F64Array:
    """Expected stabilization error of each facial marker from head-marker noise.

    First order, for independent isotropic noise of ``noise_rms_m`` (3-D RMS, metres)
    on every head marker: with ``u_i`` the layout, ``H_i = [I, -[u_i]x]`` the Jacobian
    of head marker ``i`` with respect to a small pose error ``(dt, dtheta)`` and
    ``w_i`` the fit weights, the weighted fit's pose error has covariance
    ``s^2 G^-1 (sum w_i^2 H_i^T H_i) G^-1`` with ``G = sum w_i H_i^T H_i`` and
    ``s^2 = noise_rms_m^2 / 3``; marker ``p`` is off by ``H_p (dt, dtheta)``.

    The facial markers' own noise is not in it (see the module docstring). Equal
    weights give the least error (Gauss-Markov); ``head_weights`` only help when
    some head markers are noisier than others (weight them ``1 / variance``).

    Args:
        training: layout and neutral facial markers (head coordinates).
        noise_rms_m: 3-D RMS noise of each head marker, metres.
        head_weights: (H,) fit weights (default 1).
        head_seen: (H,) which head markers are used (default all).

    Returns:
        (M,) float64, metres: the RMS 3-D error of each stabilized facial marker.

    Raises:
        ValueError: fewer than 3 head markers, or all on one line.
    """
    h = len(training.head_names)
    w = np.ones(h) if head_weights is None else np.asarray(head_weights, float)
    seen = np.ones(h, bool) if head_seen is None else np.asarray(head_seen, bool)
    if w.shape != (h,) or seen.shape != (h,):
        raise ValueError(f"head_weights / head_seen: expected ({h},)")
    w = np.where(seen, w, 0.0)

    hj = pose_jacobian(training.head_layout)
    g = np.einsum("i,iap,iaq->pq", w, hj, hj)
    if int(np.count_nonzero(w)) < 3 or np.linalg.cond(g) > 1e12:
        raise ValueError("head markers: need >= 3 weighted markers not on one line")
    g_inv = np.linalg.inv(g)
    cov = (noise_rms_m**2 / 3.0) * (
        g_inv @ np.einsum("i,iap,iaq->pq", w**2, hj, hj) @ g_inv
    )
    fj = pose_jacobian(training.neutral)
    return np.sqrt(np.einsum("map,pq,maq->m", fj, cov, fj))


# ---- output -------------------------------------------------------------------------


@dataclass(slots=True, eq=False)
class FaceOutput:
    """One frame's face solve, allocated once per stream (``FaceSolver.new_output``).

    Attributes:
        markers_head: (M, 3) float64, metres, head coordinates; NaN = occluded.
        weights: (K,) float64 in [0, 1], training-set expression order.
        world_from_head_quat: (4,) float64, (w, x, y, z).
        world_from_head_pos: (3,) float64, metres, world.
        status: (3,) int64: flags (``FLAG_*``), Cholesky solves of the QP, visible
            facial markers.
        shape_state: (K,) uint8 per expression: ``SHAPE_UNOBSERVED`` (left out of
            the solve, weight 0), ``SHAPE_HIDDEN`` (a key marker hidden this frame:
            the last weight held), 0 = solved.
    """

    markers_head: F64Array
    weights: F64Array
    world_from_head_quat: F64Array
    world_from_head_pos: F64Array
    status: npt.NDArray[np.int64]
    shape_state: npt.NDArray[np.uint8]

    @property
    def flags(self) -> int:
        """The ``FLAG_*`` bits of this frame."""
        return int(self.status[0])


# ---- the solver ---------------------------------------------------------------------


class FaceSolver:
    """Per-frame face solve from a training set (stabilize + bounded weights).

    Only the ``solved`` shapes are in the QP; the others are sent as 0 with
    ``SHAPE_UNOBSERVED``. A solved shape's **key markers** are those whose loss alone
    would make it unobservable (weight std above ``max_weight_std`` at the training
    set's noise, with the other solved shapes); while one of them is hidden the shape
    is held at its last weight (a fixed variable of the QP) and flagged
    ``SHAPE_HIDDEN``: held, not decayed, as the head and the bones are held (STYLE
    section 7): a decay would invent a motion toward neutral that nothing measured.

    Args:
        training: the performer's training set.
        labels: the stream's marker labels (column order of ``markers_world``);
            default: head markers then facial markers, in training-set order.
        regularization: unitless; ``lambda = regularization * noise_rms_m^2``
            (``observability.ridge``; 1 = the MAP ridge).
        head_weights: (H,) weight of each head marker in the rigid fit (default 1).
        max_iter: active-set iteration cap per frame.
        solved: (K,) bool, the shapes solved (default all; the daemon passes
            ``observability(training).observable``).
        max_weight_std: the observability threshold the key markers are found at.
    """

    def __init__(
        self,
        training: TrainingSet,
        *,
        labels: Sequence[str] | None = None,
        regularization: float = 1.0,
        head_weights: Sequence[float] | None = None,
        max_iter: int | None = None,
        solved: Sequence[bool] | BoolArray | None = None,
        max_weight_std: float = MAX_WEIGHT_STD,
    ) -> None:
        if not regularization >= 0.0:
            raise ValueError(f"regularization: expected >= 0, got {regularization}")
        self.training = training
        h, m, k_all = len(training.head_names), len(training.marker_names), training.k
        mask = np.ones(k_all, bool) if solved is None else np.asarray(solved, bool)
        if mask.shape != (k_all,):
            raise ValueError(f"solved: expected ({k_all},) bool, got {mask.shape}")
        self.solved = mask
        self._solved_cols = np.flatnonzero(mask).astype(np.int64)
        k = len(self._solved_cols)
        n = k + 6 if k else 0  # the pose correction's 6, when there is a shape
        basis = np.zeros((3 * m, n))
        basis[:, :k] = training.basis[:, self._solved_cols]
        if k:
            basis[:, k:] = pose_jacobian(training.neutral).reshape(-1, 6)
        self._basis = basis
        self.lambda_ = ridge(training.noise_rms_m, regularization)
        self._a_full = basis.T @ basis
        self._a_full[np.arange(k), np.arange(k)] += self.lambda_
        if head_weights is None:
            self._head_w = np.ones(h)
        else:
            self._head_w = np.asarray(head_weights, dtype=np.float64)
            if self._head_w.shape != (h,) or np.any(self._head_w < 0):
                raise ValueError(
                    f"head_weights: expected ({h},) >= 0, got {head_weights}"
                )
        prior = np.zeros((n, n))
        if k:
            prior[k:, k:] = pose_information(training.head_layout, self._head_w)
        self._key_ptr, self._key_idx = key_markers(
            basis, self._a_full - basis.T @ basis + prior, training.noise_rms_m,
            max_weight_std, k,
        )  # fmt: skip
        self._wr = np.zeros(k)
        self._a = self._a_full.copy()
        self._last_seen = np.zeros(m + h, dtype=np.bool_)  # A built on the first frame
        self._seen = np.ones(m + h, dtype=np.bool_)
        self._b = np.zeros(n)
        self._ared = np.zeros((k, k))
        self._schur = np.zeros((k, 6))
        self._c6 = np.zeros((6, 6))
        self._bred = np.zeros(k)
        self._w_prev = np.zeros(k)
        self._state = np.ones(k, dtype=np.int64)
        self._idx = np.zeros(k, dtype=np.int64)
        self._chol = np.zeros((k, k))
        self._x = np.zeros(k)
        self._g = np.zeros(k)
        self._n44 = np.zeros((4, 4))
        self._v44 = np.zeros((4, 4))
        self._q4 = np.array([1.0, 0.0, 0.0, 0.0])
        self._rot = np.eye(3)
        self._pos = np.zeros(3)
        self._have_good = np.zeros(1, dtype=np.bool_)
        self._cen = np.zeros(6)
        self._layout = np.ascontiguousarray(training.head_layout, dtype=np.float64)
        self._neutral = np.ascontiguousarray(training.neutral, dtype=np.float64)
        self.max_iter = int(max_iter if max_iter is not None else 3 * k + 20)
        self.bind(labels or (*training.head_names, *training.marker_names))

    def bind(self, labels: Sequence[str]) -> None:
        """Map the stream's labels to the training set's markers (absent = occluded)."""
        col = {name: i for i, name in enumerate(labels)}
        t = self.training
        self.labels = tuple(labels)
        self._head_cols = np.array([col.get(n, -1) for n in t.head_names], np.int64)
        self._face_cols = np.array([col.get(n, -1) for n in t.marker_names], np.int64)

    def columns(self) -> list[int]:
        """The stream columns it reads: the head's then the facial markers' (-1:
        not in the stream)."""
        return [int(c) for c in (*self._head_cols, *self._face_cols)]

    def reset(self) -> None:
        """Forget the warm start and the held pose (new take or performer)."""
        self._w_prev[:] = 0.0
        self._state[:] = 1
        self._have_good[0] = False
        self._q4[:] = (1.0, 0.0, 0.0, 0.0)
        self._rot[:] = np.eye(3)
        self._pos[:] = 0.0

    def new_output(self) -> FaceOutput:
        """An output buffer sized for this solver (allocate once per stream)."""
        m, k = len(self.training.marker_names), self.training.k
        state = np.where(self.solved, 0, SHAPE_UNOBSERVED).astype(np.uint8)
        return FaceOutput(
            markers_head=np.full((m, 3), np.nan),
            weights=np.zeros(k),
            world_from_head_quat=np.array([1.0, 0.0, 0.0, 0.0]),
            world_from_head_pos=np.zeros(3),
            status=np.zeros(3, dtype=np.int64),
            shape_state=state,
        )

    def key_markers(self) -> dict[str, tuple[str, ...]]:
        """Each solved shape's key markers (those whose loss alone hides it)."""
        t = self.training
        return {
            t.expression_names[c]: tuple(
                t.marker_names[i]
                for i in self._key_idx[self._key_ptr[j] : self._key_ptr[j + 1]]
            )
            for j, c in enumerate(self._solved_cols)
        }

    def solve_frame(
        self, markers_world: F64Array, valid: BoolArray, out: FaceOutput
    ) -> FaceOutput:
        """Solve one frame into ``out`` (no allocation) and return it.

        Args:
            markers_world: (N, 3) float64, metres, world; columns as ``labels``;
                NaN rows = occluded.
            valid: (N,) bool, True where the marker was seen.
            out: from :meth:`new_output`.
        """
        solve_face_frame(
            markers_world, valid, self._head_cols, self._face_cols, self._layout,
            self._head_w, self._neutral, self._basis, self._a_full, self._a,
            self._last_seen, self._seen, self._b, self._ared, self._schur, self._c6,
            self._bred, self._w_prev, self._state, self._idx,
            self._chol, self._x, self._g, self._n44, self._v44, self._q4, self._rot,
            self._pos, self._have_good, self._cen, self.max_iter, self._solved_cols,
            self._key_ptr, self._key_idx, self._wr, out.markers_head, out.weights,
            out.world_from_head_quat, out.world_from_head_pos, out.status,
            out.shape_state,
        )  # fmt: skip
        return out


# ---- offline helpers ----------------------------------------------------------------


def head_layout_from_frames(head_world: F64Array) -> F64Array:
    """The neutral head layout from (T, H, 3) world frames of the head markers.

    Each frame is fitted (Kabsch) to the first complete one and the fits averaged;
    the result is centred (head-coordinate origin = head-marker centroid, axes = the
    world axes of that first frame). Returns (H, 3) float64 metres.
    """
    ok = np.all(np.isfinite(head_world), axis=(1, 2))
    if not ok.any():
        raise ValueError("head markers: no frame with every head marker seen")
    frames = head_world[ok]
    ref = frames[0] - frames[0].mean(axis=0)
    acc = np.zeros_like(ref)
    for f in frames:
        c = f - f.mean(axis=0)
        u, _, vt = np.linalg.svd(c.T @ ref)
        d = np.sign(np.linalg.det(u @ vt))
        r = u @ np.diag([1.0, 1.0, d]) @ vt  # ref ~ r^T c  (rotation c -> ref)
        acc += c @ r
    layout = acc / len(frames)
    return layout - layout.mean(axis=0)


def stabilize_frames(
    head_world: F64Array, face_world: F64Array, head_layout: F64Array
) -> F64Array:
    """Facial markers in head coordinates, frame by frame (offline, numpy).

    Args:
        head_world: (T, H, 3) float64, metres, world; NaN = occluded.
        face_world: (T, M, 3) float64, metres, world; NaN = occluded.
        head_layout: (H, 3) float64, metres, head coordinates.

    Returns:
        (T, M, 3) float64, metres, head coordinates; NaN where the marker was
        occluded or fewer than 3 head markers were seen.
    """
    out = np.full(face_world.shape, np.nan)
    for t in range(len(head_world)):
        seen = np.all(np.isfinite(head_world[t]), axis=1)
        if seen.sum() < 3:
            continue
        p, q = head_world[t][seen], head_layout[seen]
        cp, cq = p.mean(axis=0), q.mean(axis=0)
        u, _, vt = np.linalg.svd((q - cq).T @ (p - cp))
        d = np.sign(np.linalg.det(vt.T @ u.T))
        rot = vt.T @ np.diag([1.0, 1.0, d]) @ u.T  # world_from_head
        out[t] = (face_world[t] - cp) @ rot + cq
    return out


def mean_pose(
    head_world: F64Array,
    face_world: F64Array,
    layout: F64Array,
    marker_names: Sequence[str],
) -> F64Array:
    """One held pose: the facial markers stabilized against ``layout`` frame by frame
    (:func:`stabilize_frames`) and averaged, in head coordinates, (M, 3).

    Raises:
        ValueError: no frame with >= 3 head markers, or a facial marker never seen.
    """
    stab = stabilize_frames(head_world, face_world, layout)
    never = ~np.any(np.isfinite(stab[..., 0]), axis=0)
    if never.all():
        raise ValueError("no frame with 3 head markers seen")
    if never.any():
        missing = [marker_names[int(i)] for i in np.flatnonzero(never)]
        raise ValueError(f"markers never seen: {missing}")
    return np.nanmean(stab, axis=0)


def train(
    head_world: F64Array,
    face_world: F64Array,
    poses: Sequence[tuple[str, slice]],
    *,
    head_names: Sequence[str],
    marker_names: Sequence[str],
) -> TrainingSet:
    """Build a training set from a take: each pose averaged over its frame range.

    The neutral range (``poses`` must hold ``"neutral"``) defines the head layout
    (:func:`head_layout_from_frames`); every frame of every range is stabilized
    against it, and each pose is the mean of its frames in head coordinates.

    Args:
        head_world: (T, H, 3) float64, metres, world; NaN = occluded.
        face_world: (T, M, 3) float64, metres, world; NaN = occluded.
        poses: (name, rows) pairs: ``"neutral"`` and one per expression.
        head_names / marker_names: (H,) and (M,) names.

    Raises:
        ValueError: no neutral, a repeated name, or a marker never seen in a range.
    """
    ranges = dict(poses)
    if len(ranges) != len(poses):
        raise ValueError("poses: a name appears twice")
    if "neutral" not in ranges:
        raise ValueError("poses: need a 'neutral' range")
    layout = head_layout_from_frames(head_world[ranges["neutral"]])
    means: dict[str, F64Array] = {}
    for name, rows in ranges.items():
        try:
            means[name] = mean_pose(
                head_world[rows], face_world[rows], layout, marker_names
            )
        except ValueError as exc:
            raise ValueError(f"pose {name}: {exc}") from None
    exprs = [n for n, _ in poses if n != "neutral"]
    neutral = means["neutral"]
    return TrainingSet(
        head_names=tuple(head_names),
        marker_names=tuple(marker_names),
        expression_names=tuple(exprs),
        head_layout=layout,
        neutral=neutral,
        deltas=np.array([means[e] - neutral for e in exprs]).reshape(
            len(exprs), len(marker_names), 3
        ),
    )


__all__ = [
    "DEFAULT_NOISE_RMS_M",
    "FLAG_FACE_PARTIAL",
    "FLAG_HEAD_LOST",
    "FLAG_HEAD_PARTIAL",
    "FLAG_NEVER",
    "FLAG_NOT_CONVERGED",
    "FLAG_SHAPE_HELD",
    "MAX_WEIGHT_STD",
    "SHAPE_HIDDEN",
    "SHAPE_UNOBSERVED",
    "FaceOutput",
    "FaceSolver",
    "Observability",
    "TrainingSet",
    "head_layout_from_frames",
    "mean_pose",
    "observability",
    "stabilization_error",
    "stabilize_frames",
    "train",
]
