"""The fit's marker residual checks: how far the calibrated skeleton, as fitted, leaves
each measured marker (``retargetd validate`` on a solve that carries residuals: the
fit's :class:`~retargetd.daemon.body.solve_fit.FitSolve`).

Why: the fit's skeleton is rigid, so its joint centres are the skeleton's own and the
``fit_median`` / ``fit_max`` checks read ~1e-12 mm for it. What the fit cannot match
shows in its marker residuals instead (issue 28: "mismatch shows as residual, not in
the joints"), so these checks read them. Per frame, over the rig markers seen in that
frame (a marker the rig gives no weight is not fitted and not seen):

- ``marker_residual_median`` (mm): the median residual: the typical marker;
- ``marker_residual_max`` (mm): the largest residual: the worst marker.

A marker the fit's gate rejected counts with its residual, like any other: rejecting
it keeps it from pulling the pose, but a marker the skeleton cannot match (moved after
calibration, another session's placement, a segment the rig holds rigid that bends) is
exactly what the user must hear about, and a residual that only the gate hides would
read as a clean take.

A frame is flagged when its value has been beyond the threshold for at least
``min_frames`` consecutive frames; for the max, the same marker must stay beyond it
that long (one marker's sustained misfit, not different markers' artefact peaks taking
turns). Shorter excursions (a swapped label, a ghost, a tracking glitch the fit
recovers from) are reported as transients, not failed, as the limits check does.
Thresholds and their reasons: ``validate.checks.THRESHOLDS`` (``marker_residual_*``).

The report names the markers: per flagged run of frames, the markers most often
beyond the threshold in it, and over the take each such marker's frame count and
largest residual (``CheckResult.markers``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from retargetd.daemon.validate.dynamics import run_lengths
from retargetd.protocols.frames import F64Array

#: Flagged runs (and transient runs) described in a check's detail lines.
DETAIL_RUNS = 5
#: Markers named per run.
MARKERS_PER_RUN = 3


@dataclass(slots=True, eq=False)
class ResidualCheck:
    """One residual check over a take.

    Attributes:
        values: (T,) float64, mm, the per-frame median or max (NaN: no marker seen).
        flagged: (T,) bool, frames in a sustained excursion.
        transients: (n,) int64, frames beyond the threshold in a shorter one.
        detail: one line per flagged run (then per transient run), naming markers.
        markers: marker -> {"frames": frames it is blamed for in flagged frames,
            "max_mm": its largest residual there}, most frames first.
    """

    values: F64Array
    flagged: np.ndarray
    transients: np.ndarray
    detail: list[str] = field(default_factory=list)
    markers: dict[str, dict[str, float]] = field(default_factory=dict)


def min_frames(min_s: float, rate_hz: float) -> int:
    """Frames an excursion must last to be flagged: ``min_s`` at ``rate_hz``, at
    least 1."""
    return max(1, math.ceil(min_s * rate_hz - 1e-9))


def residual_checks(
    residual_mm: F64Array,
    marker_names: Sequence[str],
    *,
    median_mm: float,
    max_mm: float,
    n_min: int,
    rate_hz: float,
) -> dict[str, ResidualCheck]:
    """The two residual checks of a take.

    Args:
        residual_mm: (T, Mr) float64, millimetres, |fitted marker - measured| per rig
            marker; NaN where not seen (``FitSolve.marker_residual`` x 1000).
        marker_names: (Mr,) rig marker names.
        median_mm, max_mm: thresholds of the per-frame median and max.
        n_min: frames an excursion must last to be flagged (:func:`min_frames`).
        rate_hz: frame rate (seconds in the detail lines).

    Returns:
        ``{"marker_residual_median": ..., "marker_residual_max": ...}``.
    """
    r = np.asarray(residual_mm, dtype=np.float64)
    n = r.shape[0]
    seen = np.isfinite(r)
    any_seen = seen.any(axis=1)
    med = np.full(n, np.nan)
    mx = np.full(n, np.nan)
    med[any_seen] = np.nanmedian(r[any_seen], axis=1)
    mx[any_seen] = np.nanmax(r[any_seen], axis=1)
    r0 = np.where(seen, r, 0.0)

    beyond = np.isfinite(med) & (med > median_mm)
    flagged = beyond & (run_lengths(beyond) >= n_min)
    # The typical marker is off: blame the markers beyond the threshold there.
    above = r0 > median_mm
    median = _named(med, flagged, beyond, above, above, r0, marker_names, rate_hz)

    over = r0 > max_mm  # (T, Mr)
    sustained = np.zeros_like(over)
    for i in np.flatnonzero(over.any(axis=0)):
        sustained[:, i] = over[:, i] & (run_lengths(over[:, i]) >= n_min)
    # Flagged frames blame the markers in a sustained excursion; a transient frame
    # every marker beyond the threshold in it.
    worst = np.asarray(sustained.any(axis=1), dtype=bool)
    maximum = _named(
        mx, worst, np.asarray(over.any(axis=1), dtype=bool), sustained, over, r0,
        marker_names, rate_hz,
    )  # fmt: skip
    return {"marker_residual_median": median, "marker_residual_max": maximum}


def _named(
    values: F64Array,
    flagged: np.ndarray,
    beyond: np.ndarray,
    blame: np.ndarray,
    blame_transient: np.ndarray,
    r0: F64Array,
    names: Sequence[str],
    rate_hz: float,
) -> ResidualCheck:
    """A check from its per-frame values, flagged frames, frames beyond the
    threshold (flagged or not) and the (T, Mr) markers blamed per frame in flagged
    and in transient frames."""
    transients = np.flatnonzero(beyond & ~flagged)
    detail = _run_lines("", _runs(flagged), blame, r0, names, rate_hz)
    detail += _run_lines(
        "transient, ",
        _runs(_mask(len(values), transients)),
        blame_transient,
        r0,
        names,
        rate_hz,
    )
    counts = (blame & flagged[:, None]).sum(axis=0)
    peak = np.where(blame & flagged[:, None], r0, 0.0).max(axis=0, initial=0.0)
    order = sorted(
        (int(i) for i in np.flatnonzero(counts)), key=lambda i: (-counts[i], -peak[i])
    )
    markers = {
        names[i]: {"frames": int(counts[i]), "max_mm": round(float(peak[i]), 1)}
        for i in order
    }
    return ResidualCheck(
        values=values,
        flagged=np.asarray(flagged, dtype=bool),
        transients=transients.astype(np.int64),
        detail=detail,
        markers=markers,
    )


def _run_lines(
    prefix: str,
    runs: list[tuple[int, int]],
    blame: np.ndarray,
    r0: F64Array,
    names: Sequence[str],
    rate_hz: float,
) -> list[str]:
    """One line per run (the first :data:`DETAIL_RUNS`): its frames and the markers
    most often blamed in it, with their largest residual there."""
    lines = []
    for a, b in runs[:DETAIL_RUNS]:
        counts = blame[a:b].sum(axis=0)
        peak = np.where(blame[a:b], r0[a:b], 0.0).max(axis=0)
        top = sorted(
            (int(i) for i in np.flatnonzero(counts)),
            key=lambda i: (-counts[i], -peak[i]),
        )
        who = ", ".join(
            f"{names[i]} {int(counts[i])} frame{'' if counts[i] == 1 else 's'} "
            f"(max {peak[i]:.0f} mm)"
            for i in top[:MARKERS_PER_RUN]
        )
        extra = len(top) - MARKERS_PER_RUN
        more = f" and {extra} more" if extra > 0 else ""
        lines.append(
            f"{prefix}frames {a}-{b - 1} ({(b - a) / rate_hz:.2f} s): {who}{more}"
        )
    if len(runs) > DETAIL_RUNS:
        lines.append(f"{prefix}... {len(runs) - DETAIL_RUNS} more runs")
    return lines


def _mask(n: int, frames: np.ndarray) -> np.ndarray:
    out = np.zeros(n, dtype=bool)
    out[frames] = True
    return out


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[(start, stop), ...] of the True runs of a (T,) bool mask."""
    m = np.concatenate([[False], np.asarray(mask, dtype=bool), [False]])
    edges = np.flatnonzero(m[1:] != m[:-1])
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True)]
