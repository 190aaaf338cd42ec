"""What a marker layout can see: observable shapes, and each solved shape's key markers.

A training set's basis ``B`` (3 M x K) and the marker noise say how well each weight
is determined: with per-axis noise ``sigma`` the unbounded least-squares weights have
covariance ``sigma^2 (B^T B + lambda I)^-1``. :func:`observability` keeps the shapes
whose weight standard deviation stays under :data:`MAX_WEIGHT_STD` (dropping the worst
first); :func:`key_markers` finds, per kept shape, the markers whose loss alone would
push it over. Reference: ``daemon/face/faces/FACES.md`` "What a marker layout can see".
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
            the marker noise: ``noise * sqrt(((B^T B + lambda I)^-1)_kk)`` over the
            observable shapes; for an unobservable one, with it added back alone.
        observable: (K,) bool: solved. Shapes are dropped worst first (largest
            std) until every one left has ``weight_std <= max_weight_std``; those
            moving no marker by ``min_peak_m`` are dropped first.
        confused_with: (K,) for an unobservable shape the observable shape whose
            weight its own trades against most ("" for one that moves nothing,
            and for observable shapes).
        correlation: (K,) the correlation of the two weight estimates (NaN where
            ``confused_with`` is "").
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


def _covariance(b: F64Array, cols: npt.NDArray[np.intp], lam: float) -> F64Array:
    bs = b[:, cols]
    return np.asarray(np.linalg.inv(bs.T @ bs + lam * np.eye(len(cols))), np.float64)


def observability(
    training: TrainingSet,
    *,
    noise_rms_m: float | None = None,
    regularization: float = 1e-3,
    min_peak_m: float | None = None,
    max_weight_std: float = MAX_WEIGHT_STD,
) -> Observability:
    """Report the shapes the training set's markers cannot see or separate.

    A shape is unobservable when it moves no marker by ``min_peak_m`` (default
    :data:`MIN_PEAK_SNR` times the noise), or when marker noise of ``noise_rms_m``
    (3-D RMS, metres; per axis ``/ sqrt 3``; default the training set's, the
    ``face-train --noise-mm`` it was made with) gives its weight a standard deviation
    above ``max_weight_std`` in the solve of the shapes kept: its column of B is too
    close to a combination of the others (e.g. gaze vs. eyelid shapes). The worst
    shape is dropped first and the rest judged again, so of two shapes that look
    alike the better seen one stays.
    """
    if noise_rms_m is None:
        noise_rms_m = training.noise_rms_m
    if not noise_rms_m > 0.0:
        raise ValueError(f"noise_rms_m: expected > 0 metres, got {noise_rms_m}")
    peak_min = MIN_PEAK_SNR * noise_rms_m if min_peak_m is None else min_peak_m
    sigma = noise_rms_m / math.sqrt(3.0)
    b = training.basis
    k = training.k
    peak = np.linalg.norm(training.deltas, axis=2).max(axis=1)
    kept = peak >= peak_min
    lam = regularization * float(np.mean(np.diag(b.T @ b))) if k else 0.0
    lam = max(lam, 1e-12)
    std = np.full(k, np.inf)
    while kept.any():
        cols = np.flatnonzero(kept)
        s = sigma * np.sqrt(np.diag(_covariance(b, cols, lam)))
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
        cov = _covariance(b, with_j, lam)
        std[j] = sigma * math.sqrt(cov[-1, -1])
        if cols.size:
            d = np.sqrt(np.diag(cov))
            rho = cov[-1, :-1] / (d[-1] * d[:-1])
            best = int(np.argmax(np.abs(rho)))
            partner[j] = training.expression_names[cols[best]]
            corr[j] = rho[best]
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
    basis: F64Array, lam: float, noise_rms_m: float, max_weight_std: float
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """Per solved shape, the markers whose loss alone puts its weight std above
    ``max_weight_std`` (CSR: ``idx[ptr[j]:ptr[j + 1]]``).

    Without marker m, ``A_m = A - B_m^T B_m`` (B_m: its 3 rows); by the Woodbury
    identity ``A_m^-1 = A^-1 + A^-1 B_m^T (I - B_m A^-1 B_m^T)^-1 B_m A^-1``.
    A shape already unobservable with every marker (solved anyway: the caller's
    choice) has none."""
    k = basis.shape[1]
    m = basis.shape[0] // 3
    ptr = np.zeros(k + 1, np.int64)
    if k == 0:
        return ptr, np.zeros(0, np.int64)
    sigma2 = noise_rms_m**2 / 3.0
    a_inv = np.linalg.inv(basis.T @ basis + lam * np.eye(k))
    var_max = (max_weight_std**2) / sigma2
    hidden = np.zeros((k, m), bool)
    seen_all = np.diag(a_inv) <= var_max
    for i in range(m):
        bm = basis[3 * i : 3 * i + 3]  # (3, k)
        u = a_inv @ bm.T  # (k, 3)
        s = np.eye(3) - bm @ u
        try:
            var = np.diag(a_inv) + np.einsum("ka,ab,kb->k", u, np.linalg.inv(s), u)
        except np.linalg.LinAlgError:  # the marker alone carries a shape
            var = np.full(k, np.inf)
        hidden[:, i] = (var > var_max) & seen_all
    counts = hidden.sum(axis=1)
    ptr[1:] = np.cumsum(counts)
    return ptr, np.flatnonzero(hidden.reshape(-1)) % m
