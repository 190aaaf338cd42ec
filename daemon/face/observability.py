"""What a marker layout can see: observable shapes, and each solved shape's key markers.

A training set's basis ``B`` (3 M x K) and the marker noise say how well each weight
is determined. The solve (``face.solve``) estimates the weights together with a small
correction ``(tau, theta)`` of the head pose the head markers gave (6 unbounded
variables, Jacobian ``J`` (3 M x 6) at the neutral facial markers, prior information
``G`` from the head markers themselves, :func:`pose_information`): the weighted least
squares over every marker, linearized about the head markers' fit. With per-axis noise
``sigma`` on every marker the weights then have covariance ``sigma^2`` times the
shape block of ``[[B^T B + lambda I, B^T J], [J^T B, J^T J + G]]^-1``: a shape that
looks like a head motion (a jaw sliding sideways under a head turning) is as poorly
seen as one that looks like another shape. :func:`observability` keeps the shapes
whose weight standard deviation stays under :data:`MAX_WEIGHT_STD` (dropping the worst
first); :func:`key_markers` finds, per kept shape, the markers whose loss alone would
push it over. Reference: ``daemon/face/faces/FACES.md`` "What a marker layout can see".

``lambda`` (:func:`ridge`) is the ridge of the maximum a posteriori weights under a
Gaussian prior ``w ~ N(0, tau_w^2 I)`` (Hoerl & Kennard 1970, Technometrics 12:55; the
Bayesian reading e.g. Bishop 2006, Pattern Recognition and Machine Learning, eq. 3.55):
``lambda = sigma^2 / tau_w^2``. With ``sigma^2 = noise_rms^2 / 3`` per axis and
``tau_w^2 = E[w^2] = 1/3`` (a weight spread evenly over [0, 1]) that is
``lambda = noise_rms^2``, times the unitless ``regularization`` (default 1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from retargetd.daemon.face.training import TrainingSet
from retargetd.protocols.frames import F64Array

BoolArray = npt.NDArray[np.bool_]

#: A shape is unobservable when noise alone gives its weight a standard deviation
#: above this (issue 7's figure, kept): at 0.1 noise alone spreads the weight over
#: +-0.2 (two sigma, 95 %), a fifth of its [0, 1] range; beyond that the weight
#: tells more about the noise than about the face.
MAX_WEIGHT_STD = 0.1
#: A shape must move some marker by this many times the 3-D RMS noise to be seen at
#: all (1 mm at 0.5 mm): a 3-D Gaussian's norm passes 2 RMS (3.46 sigma per axis,
#: chi-square 12 with 3 dof) in 0.7 % of frames, so such a motion is not noise.
MIN_PEAK_SNR = 2.0


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class Observability:
    """Which shapes a marker layout can see.

    Attributes:
        names: (K,) expression names.
        peak_m: (K,) largest marker displacement of each shape, metres.
        weight_std: (K,) standard deviation of each unbounded weight estimate under
            the marker noise: ``sigma * sqrt((A^-1)_kk)`` with ``A`` the joint
            normal matrix (module docstring) of the observable shapes and the pose;
            for an unobservable one, with it added back alone.
        observable: (K,) bool: solved. Shapes are dropped worst first (largest
            std) until every one left has ``weight_std <= max_weight_std``; those
            moving no marker by ``min_peak_m`` are dropped first.
        confused_with: (K,) for an unobservable shape the observable shape whose
            weight its own trades against most, or :data:`HEAD_MOTION` when the
            head pose's correction explains it better ("" for one that moves
            nothing, and for observable shapes).
        correlation: (K,) the correlation of the two weight estimates (against
            the head motion: the multiple correlation with its 6 components, > 0;
            NaN where ``confused_with`` is "").
        noise_rms_m: the 3-D RMS marker noise it was judged at, metres.
        min_peak_m: the displacement a shape must reach on some marker, metres.
    """

    names: tuple[str, ...]
    peak_m: F64Array
    weight_std: F64Array
    observable: BoolArray
    confused_with: tuple[str, ...]
    correlation: F64Array
    noise_rms_m: float
    min_peak_m: float

    @property
    def unobservable(self) -> tuple[str, ...]:
        """Names of the shapes this layout cannot see or tell apart."""
        return tuple(
            n for n, ok in zip(self.names, self.observable, strict=True) if not ok
        )

    def describe(self) -> list[str]:
        """One line per unobservable shape: why, and what it is confused with."""
        lines = []
        for k in np.flatnonzero(~self.observable):
            name = self.names[k]
            if self.peak_m[k] < self.min_peak_m:
                lines.append(
                    f"{name}: moves no marker by {1e3 * self.min_peak_m:.1f} mm "
                    f"(largest {1e3 * self.peak_m[k]:.2f} mm)"
                )
            else:
                lines.append(
                    f"{name}: confused with {self.confused_with[k]} (weight "
                    f"correlation {self.correlation[k]:+.2f}), weight std "
                    f"{self.weight_std[k]:.2f}"
                )
        return lines


#: The name an unobservable shape's partner takes when what it trades against most
#: is the head pose's correction (the head markers' fit), not another shape.
HEAD_MOTION = "head motion"


def ridge(noise_rms_m: float, regularization: float = 1.0) -> float:
    """``lambda``, m^2: ``regularization * noise_rms_m^2`` (the module docstring), at
    least 1e-12 so that the normal matrix stays positive definite."""
    return max(regularization * noise_rms_m**2, 1e-12)


def pose_jacobian(points: F64Array) -> F64Array:
    """(n, 3, 6): how each point (head coordinates) moves under a small correction
    ``(tau, theta)`` of the head pose: ``p -> p + tau + theta x p``."""
    j = np.zeros((len(points), 3, 6))
    j[:, :, :3] = np.eye(3)
    x, y, z = np.asarray(points, np.float64).T
    j[:, 0, 4], j[:, 0, 5] = z, -y
    j[:, 1, 3], j[:, 1, 5] = -z, x
    j[:, 2, 3], j[:, 2, 4] = y, -x
    return j


def pose_information(layout: F64Array, weights: F64Array | None = None) -> F64Array:
    """G (6, 6) = sum_i w_i H_i^T H_i over the head markers (``layout`` (H, 3), head
    coordinates; ``weights`` their fit weights, default 1): the head markers' own
    information on the pose correction, in units of the per-axis noise variance.
    The fit's residuals are orthogonal to ``H`` (it is a least-squares fit), so in the
    joint least squares the head-marker rows reduce to ``delta^T G delta``."""
    h = pose_jacobian(layout)
    w = np.ones(len(layout)) if weights is None else np.asarray(weights, np.float64)
    return np.asarray(np.einsum("i,iap,iaq->pq", w, h, h), np.float64)


def _joint_inverse(
    b: F64Array, cols: npt.NDArray[np.intp], lam: float, jac: F64Array, g: F64Array
) -> F64Array:
    # The inverse of the joint normal matrix over the shapes ``cols`` and the pose.
    bs = b[:, cols]
    k = len(cols)
    a = np.zeros((k + 6, k + 6))
    a[:k, :k] = bs.T @ bs + lam * np.eye(k)
    a[:k, k:] = bs.T @ jac
    a[k:, :k] = a[:k, k:].T
    a[k:, k:] = jac.T @ jac + g
    return np.asarray(np.linalg.inv(a), np.float64)


def observability(
    training: TrainingSet,
    *,
    noise_rms_m: float | None = None,
    regularization: float = 1.0,
    min_peak_m: float | None = None,
    max_weight_std: float = MAX_WEIGHT_STD,
    head_weights: F64Array | None = None,
) -> Observability:
    """Report the shapes the training set's markers cannot see or separate.

    A shape is unobservable when it moves no marker by ``min_peak_m`` (default
    :data:`MIN_PEAK_SNR` times the noise), or when marker noise of ``noise_rms_m``
    (3-D RMS, metres; per axis ``/ sqrt 3``; default the training set's, the
    ``face-train --noise-mm`` it was made with) gives its weight a standard deviation
    above ``max_weight_std`` in the joint solve of the shapes kept and the head pose's
    correction: its column of B is too close to a combination of the others and of
    a head motion (e.g. gaze vs. eyelid shapes). The worst shape is dropped first and
    the rest judged again, so of two shapes that look alike the better seen one
    stays. ``regularization``: as the solver's (:func:`ridge`); ``head_weights``: the
    head markers' fit weights (default 1).
    """
    if noise_rms_m is None:
        noise_rms_m = training.noise_rms_m
    if not noise_rms_m > 0.0:
        raise ValueError(f"noise_rms_m: expected > 0 metres, got {noise_rms_m}")
    peak_min = MIN_PEAK_SNR * noise_rms_m if min_peak_m is None else min_peak_m
    sigma = noise_rms_m / math.sqrt(3.0)
    b = training.basis
    k = training.k
    jac = pose_jacobian(training.neutral).reshape(-1, 6)
    g = pose_information(training.head_layout, head_weights)
    peak = np.linalg.norm(training.deltas, axis=2).max(axis=1)
    kept = peak >= peak_min
    lam = ridge(noise_rms_m, regularization)
    std = np.full(k, np.inf)
    while kept.any():
        cols = np.flatnonzero(kept)
        s = sigma * np.sqrt(np.diag(_joint_inverse(b, cols, lam, jac, g))[: len(cols)])
        worst = int(np.argmax(s))
        if s[worst] <= max_weight_std:
            std[cols] = s
            break
        kept[cols[worst]] = False
    partner = [""] * k
    corr = np.full(k, np.nan)
    cols = np.flatnonzero(kept)
    for j in np.flatnonzero(~kept & (peak >= peak_min)):
        with_j = np.append(cols, j)
        cov = _joint_inverse(b, with_j, lam, jac, g)
        n = len(with_j)
        std[j] = sigma * math.sqrt(cov[n - 1, n - 1])
        d = np.sqrt(np.diag(cov)[: n - 1])
        rho = cov[n - 1, : n - 1] / (math.sqrt(cov[n - 1, n - 1]) * d)
        # Against the pose: the multiple correlation with its 6 components.
        c_jp = cov[n - 1, n:]
        r_pose = math.sqrt(
            max(float(c_jp @ np.linalg.solve(cov[n:, n:], c_jp)), 0.0)
            / cov[n - 1, n - 1]
        )
        best = int(np.argmax(np.abs(rho))) if cols.size else -1
        if best >= 0 and abs(rho[best]) >= r_pose:
            partner[j] = training.expression_names[cols[best]]
            corr[j] = rho[best]
        else:
            partner[j] = HEAD_MOTION
            corr[j] = r_pose
    return Observability(
        names=training.expression_names,
        peak_m=peak,
        weight_std=std,
        observable=kept,
        confused_with=tuple(partner),
        correlation=corr,
        noise_rms_m=noise_rms_m,
        min_peak_m=peak_min,
    )


def key_markers(
    basis: F64Array,
    prior: F64Array,
    noise_rms_m: float,
    max_weight_std: float,
    k: int,
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """Per solved shape (the first ``k`` columns of ``basis``; the others are the
    pose's), the markers whose loss alone puts its weight std above
    ``max_weight_std`` (CSR: ``idx[ptr[j]:ptr[j + 1]]``).

    ``A = basis^T basis + prior`` (``prior``: ``lambda`` on the shapes, ``G`` on the
    pose, every head marker seen). Without marker m, ``A_m = A - B_m^T B_m`` (B_m:
    its 3 rows); by the Woodbury identity ``A_m^-1 = A^-1 + A^-1 B_m^T (I - B_m A^-1
    B_m^T)^-1 B_m A^-1``. A shape already unobservable with every marker (solved
    anyway: the caller's choice) has none."""
    m = basis.shape[0] // 3
    ptr = np.zeros(k + 1, np.int64)
    if k == 0:
        return ptr, np.zeros(0, np.int64)
    sigma2 = noise_rms_m**2 / 3.0
    a_inv = np.linalg.inv(basis.T @ basis + prior)
    var_max = (max_weight_std**2) / sigma2
    hidden = np.zeros((k, m), bool)
    seen_all = np.diag(a_inv)[:k] <= var_max
    for i in range(m):
        bm = basis[3 * i : 3 * i + 3]  # (3, n)
        u = a_inv @ bm.T  # (n, 3)
        s = np.eye(3) - bm @ u
        try:
            var = np.diag(a_inv) + np.einsum("ka,ab,kb->k", u, np.linalg.inv(s), u)
        except np.linalg.LinAlgError:  # the marker alone carries a shape
            var = np.full(len(a_inv), np.inf)
        hidden[:, i] = (var[:k] > var_max) & seen_all
    counts = hidden.sum(axis=1)
    ptr[1:] = np.cumsum(counts)
    return ptr, np.flatnonzero(hidden.reshape(-1)) % m
