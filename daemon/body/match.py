"""Does a calibration fit this take? Each rigid segment's markers against their
calibrated layout.

A calibration holds, per rigid segment of the rig, where its markers sat on each other
in the base pose (``Calibration.segment_layouts``). The markers of the same performer,
unmoved, keep that layout through the take up to marker noise and the part of skin
motion that deforms a marker cluster; a wand re-seated or a marker re-stuck after the
static, or another performer's calibration, breaks it. So every frame each segment's
seen markers (>= 3) are fitted rigidly to the layout (``compiled.horn_fit``, the one
weighted Horn fit) and the fit's RMS residual kept; a segment's figure is the median
of that RMS over the frames where it has >= 3 markers (a median: a transient, a
mislabel or a few frames of skin slide do not make it). A segment past its threshold
(:data:`THRESHOLD_MM`) is named in one warning line (:meth:`CalibrationMatch.warning`)
and the performer flagged.

Used offline before solving (``solve``, ``validate`` ... through
``cli.args.solver_for_take``) on every frame of the take, and live over the first
second of each performer's stream (``live.performers``): the same function.

Thresholds. A bound D on how far each marker may sit off its calibrated place (noise
plus skin motion, mm) becomes a layout RMS by the fit's degrees of freedom: the rigid
fit of k markers takes 6 of their 3k coordinates, so isotropic errors of size D leave
an RMS of D sqrt(1 - 2/k) (the residual-variance correction: E[RSS] = sigma^2 (3k-6)),
and the threshold of a k-marker segment is ``D sqrt(1 - 2/k)``. The bounds are added,
not taken in quadrature (a worst case):

- marker noise: the optical system's dynamic position error, < 2 mm (Vicon, Merriaux
  et al. 2017, Sensors 17(7):1591: static 0.15 mm mean absolute error, dynamic
  "less than 2 mm");
- limb, pelvis and head segments: the non-rigid part of skin motion at the thigh, the
  lower-limb segment with the largest soft-tissue artefact (Leardini et al. 2005, Gait
  Posture 21:212-225): with bone pins, the thigh cluster's artefact beyond its rigid
  translations and rotations is at most 5.1 mm in walking (3.0 cutting, 3.5 hopping;
  the shank's 1.9; Andersen et al. 2012, Gait Posture 35(4):606-611). D = 2 + 5.1 =
  **7.1 mm** for every such segment (the thigh's bound is the largest published):
  4.1 mm of layout RMS for 3 markers, 5.0 for 4, 5.8 for 6;
- trunk segments (``thorax``, ``ribcage`` ...: markers on the spine and the sternum,
  which the spine's flexion moves apart): skin markers over the thoracic spine move
  9.3 +- 4.2 mm (mean +- SD over subjects) against the vertebrae between flexed and
  extended postures (open MRI; Zemp et al. 2014, PLoS ONE 9(4):e95426); the mean plus
  two SD as the bound: D = 2 + 17.7 = **19.7 mm** (13.9 mm of layout RMS for 4).

One marker of a k-marker layout moved by d (the others exact) leaves a layout RMS of
d sqrt(k - 1) / k when the fit can only translate (9.4 mm for 20 mm with k = 3), less
when a turn of the layout takes up part of the move (on subject01's thigh wand, 20 mm
along each world axis left 4.4-8.4 mm).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

# Imported as a module: this one only calls the compiled fit and compiles nothing,
# so it stays out of the kernels' cache digest (``compiled.kernel_sources``).
import retargetd.daemon.compiled as compiled_kernels
from retargetd.daemon.body.calibration import Calibration
from retargetd.protocols.frames import F64Array, IntArray

logger = logging.getLogger(__name__)

#: Marker noise bound, mm: Vicon's dynamic position error < 2 mm (Merriaux et al.
#: 2017, Sensors 17(7):1591).
NOISE_MM = 2.0
#: Non-rigid skin motion of a limb cluster, mm: the thigh's, at most 5.1 mm in walking
#: after its rigid modes (bone pins; Andersen et al. 2012, Gait Posture 35:606-611);
#: the thigh has the largest artefact of the lower limb (Leardini et al. 2005).
LIMB_SKIN_MM = 5.1
#: Skin motion over the thoracic spine, mm: 9.3 +- 4.2 mm between flexed and extended
#: postures, mean + 2 SD (open MRI; Zemp et al. 2014, PLoS ONE 9(4):e95426).
TRUNK_SKIN_MM = 9.3 + 2 * 4.2
#: Segment names (substrings) whose markers ride the trunk (spine and sternum).
TRUNK_SEGMENTS = ("thorax", "ribcage", "chest", "trunk", "spine", "back")
#: How far each marker may sit off its calibrated place, mm (module docstring):
#: "limb" for every segment not of the trunk.
MARKER_BOUND_MM = {
    "limb": NOISE_MM + LIMB_SKIN_MM,
    "trunk": NOISE_MM + TRUNK_SKIN_MM,
}
#: Seconds of a live stream the check runs over.
LIVE_WINDOW_S = 1.0


def marker_bound_mm(segment: str) -> float:
    """How far a marker of the segment (or bone) so named may sit off its calibrated
    place, mm: :data:`MARKER_BOUND_MM`'s "trunk" or "limb" bound, by the name."""
    kind = "trunk" if any(t in segment.lower() for t in TRUNK_SEGMENTS) else "limb"
    return MARKER_BOUND_MM[kind]


def segment_threshold_mm(segment: str, n_markers: int) -> float:
    """The layout RMS threshold of a segment of ``n_markers`` (>= 3), mm: its
    marker bound (:func:`marker_bound_mm`) times sqrt(1 - 2/k)."""
    return marker_bound_mm(segment) * math.sqrt(1.0 - 2.0 / max(n_markers, 3))


@dataclass(frozen=True, slots=True, kw_only=True)
class SegmentMatch:
    """One segment's layout against the take.

    Attributes:
        segment: the rig's segment name.
        rms_mm: median over the frames of the rigid fit's RMS residual, mm (NaN when
            no frame had 3 of its markers).
        frames: frames with >= 3 of its markers seen (the median's count).
        threshold_mm: its threshold (:func:`segment_threshold_mm`).
        worst_marker: the marker with the largest median residual ("" when none).
        worst_marker_mm: that residual, mm.
    """

    segment: str
    rms_mm: float
    frames: int
    threshold_mm: float
    worst_marker: str
    worst_marker_mm: float

    @property
    def mismatched(self) -> bool:
        """Past its threshold (a segment never seen is not)."""
        return bool(self.rms_mm > self.threshold_mm)

    def to_json(self) -> dict[str, Any]:
        """The ``--json`` / status form."""
        return {
            "rms_mm": _finite_or_none(self.rms_mm),
            "threshold_mm": self.threshold_mm,
            "frames": self.frames,
            "matches": None if self.frames == 0 else not self.mismatched,
            "worst_marker": self.worst_marker or None,
            "worst_marker_mm": _finite_or_none(self.worst_marker_mm),
        }


@dataclass(frozen=True, slots=True, kw_only=True)
class CalibrationMatch:
    """Every segment's layout against the take (:func:`match_calibration`)."""

    segments: tuple[SegmentMatch, ...]
    frames: int

    @property
    def mismatched(self) -> tuple[SegmentMatch, ...]:
        """The segments past their threshold, worst (largest ratio) first."""
        bad = [s for s in self.segments if s.mismatched]
        return tuple(sorted(bad, key=lambda s: -s.rms_mm / s.threshold_mm))

    @property
    def matches(self) -> bool:
        """No segment past its threshold."""
        return not self.mismatched

    def warning(self) -> str | None:
        """One line naming every mismatched segment, or None when all match."""
        bad = self.mismatched
        if not bad:
            return None
        parts = ", ".join(
            f"{s.segment} {s.rms_mm:.0f} mm (limit {s.threshold_mm:.1f}; "
            f"{s.worst_marker} {s.worst_marker_mm:.0f} mm)"
            for s in bad
        )
        return (
            "calibration does not match this take: "
            f"{parts}: the markers' layout differs from the calibration's "
            "(a marker moved since the static, or another performer's calibration)"
        )

    def summary(self) -> str:
        """One line: every segment's figure against its limit."""
        parts = [
            f"{s.segment} {s.rms_mm:.1f}/{s.threshold_mm:.1f}"
            + (" MISMATCH" if s.mismatched else "")
            for s in self.segments
            if s.frames
        ]
        return "calibration match (segment layout RMS, median / limit, mm): " + (
            ", ".join(parts) if parts else "no segment with 3 markers seen"
        )

    def to_json(self) -> dict[str, dict[str, Any]]:
        """``calibration_match``: segment -> :meth:`SegmentMatch.to_json`."""
        return {s.segment: s.to_json() for s in self.segments}


class _LayoutFit:
    """One segment's rigid fit of its layout to a frame's points, with every buffer
    allocated once (the live check fits each frame as it arrives: no allocation, no
    burst of work on the frame that ends the window)."""

    def __init__(self, layout: F64Array) -> None:
        self.layout = np.ascontiguousarray(layout, dtype=np.float64).reshape(-1, 3)
        k = self.layout.shape[0]
        self._rows = np.arange(k, dtype=np.int64)
        self._use = np.ones(k, dtype=bool)
        self._weights = np.ones(k)
        self._n44, self._v44 = np.zeros((4, 4)), np.zeros((4, 4))
        self._q4, self._cen = np.zeros(4), np.zeros(6)
        self._centred, self._fitted = np.zeros((k, 3)), np.zeros((k, 3))

    def residuals(self, pts: F64Array, out: F64Array) -> None:
        """Each point's distance from the fitted layout into ``out`` (k,), metres:
        NaN where the point is not seen, and for all when fewer than 3 were seen
        (or they lie on one line).

        Args:
            pts: (k, 3) float64, C-contiguous, metres, world; NaN rows = not seen.
            out: (k,) float64.
        """
        cen = self._cen
        used = compiled_kernels.horn_fit(
            self.layout, pts, self._rows, self._use, self._weights,
            self._n44, self._v44, self._q4, cen,
        )  # fmt: skip
        if used < 3:
            out[:] = np.nan
            return
        # n44[:3, :3] is world_from_layout: p = R (l - c_l) + c_p
        fitted = self._fitted
        np.subtract(self.layout, cen[:3], out=self._centred)
        np.matmul(self._centred, self._n44[:3, :3].T, out=fitted)
        fitted += cen[3:]
        np.subtract(pts, fitted, out=fitted)
        fitted *= fitted
        np.sum(fitted, axis=1, out=out)
        np.sqrt(out, out=out)


def warm_up() -> None:
    """Load what the live check calls (the compiled fit's Python entry and the
    numpy paths of :class:`_LayoutFit`) before the first frame: a layout fitted to
    itself."""
    layout = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0]])
    out = np.zeros(3)
    _LayoutFit(layout).residuals(layout, out)


def layout_residuals(layout: F64Array, points: F64Array) -> F64Array:
    """Per frame, each point's distance from the layout fitted rigidly to the points.

    Args:
        layout: (k, 3) float64, metres, the layout (any frame).
        points: (T, k, 3) float64, metres, world; NaN rows = not seen.

    Returns:
        (T, k) float64 metres: NaN where the point was not seen, and for the whole
        frame when fewer than 3 points were seen (or they lie on one line).
    """
    fit = _LayoutFit(layout)
    points = np.asarray(points, dtype=np.float64)
    out = np.full(points.shape[:2], np.nan)
    seen = np.isfinite(points).all(axis=2)
    for t in np.flatnonzero(seen.sum(axis=1) >= 3):
        fit.residuals(np.ascontiguousarray(points[t]), out[t])
    return out


def _segment_match(
    segment: str, names: Sequence[str], residual: F64Array
) -> SegmentMatch:
    """A segment's figures from its per-frame residuals ((T, k) metres)."""
    fitted = np.isfinite(residual).any(axis=1)
    frames = int(fitted.sum())
    rms_mm = worst_mm = math.nan
    worst = ""
    if frames:
        r = residual[fitted]
        per_marker = np.full(len(names), -np.inf)
        if np.isfinite(r).all():  # every marker seen: numpy's nan-free (fast) path
            rms = np.sqrt(np.mean(r**2, axis=1))
            per_marker[:] = np.median(r, axis=0)
        else:
            rms = np.sqrt(np.nanmean(r**2, axis=1))
            seen_any = np.isfinite(r).any(axis=0)
            per_marker[seen_any] = np.nanmedian(r[:, seen_any], axis=0)
        rms_mm = 1e3 * float(np.median(rms))
        w = int(np.argmax(per_marker))
        worst, worst_mm = names[w], 1e3 * float(per_marker[w])
    return SegmentMatch(
        segment=segment,
        rms_mm=rms_mm,
        frames=frames,
        threshold_mm=segment_threshold_mm(segment, len(names)),
        worst_marker=worst,
        worst_marker_mm=worst_mm,
    )


def match_calibration(calibration: Calibration, markers: F64Array) -> CalibrationMatch:
    """Fit each segment's markers to its calibrated layout on every frame.

    Args:
        calibration: the calibration (its ``segment_layouts``).
        markers: (T, Mr, 3) float64, metres, world: the rig's markers in
            ``calibration.marker_names`` order; NaN rows = not seen.

    Returns:
        The per-segment figures.

    Raises:
        ValueError: ``markers`` of the wrong shape.
    """
    markers = np.asarray(markers, dtype=np.float64)
    n_names = len(calibration.marker_names)
    if markers.ndim != 3 or markers.shape[1:] != (n_names, 3):
        raise ValueError(
            f"markers: expected (T, {n_names}, 3) metres in the calibration's marker "
            f"order; got shape {markers.shape}"
        )
    index = {m: i for i, m in enumerate(calibration.marker_names)}
    segments = []
    for segment, (names, layout) in calibration.segment_layouts.items():
        cols = [index[n] for n in names]
        residual = layout_residuals(np.asarray(layout).reshape(-1, 3), markers[:, cols])
        segments.append(_segment_match(segment, names, residual))
    return CalibrationMatch(segments=tuple(segments), frames=int(markers.shape[0]))


def calibration_columns(
    calibration: Calibration,
    rig_marker_names: Sequence[str],
    marker_cols: Sequence[int] | IntArray,
) -> IntArray:
    """Column of each calibrated marker in a stream, matched by name (a rig file
    edited since the calibration: its markers the rig no longer has are absent).

    Args:
        calibration: whose ``marker_names`` order the result follows.
        rig_marker_names: (Mr,) the rig's markers.
        marker_cols: (Mr,) column of each rig marker in the stream (-1 = absent;
            ``calibration.match_markers``, a solver's ``marker_cols``).

    Returns:
        (len(calibration.marker_names),) int64, -1 = absent.
    """
    if len(marker_cols) != len(rig_marker_names):
        raise ValueError(
            f"marker_cols: expected {len(rig_marker_names)} columns (one per rig "
            f"marker); got {len(marker_cols)}"
        )
    col_of = dict(zip(rig_marker_names, marker_cols, strict=True))
    return np.asarray(
        [int(col_of.get(m, -1)) for m in calibration.marker_names], dtype=np.int64
    )


def markers_of_calibration(
    calibration: Calibration,
    rig_marker_names: Sequence[str],
    marker_cols: Sequence[int],
    positions: F64Array,
) -> F64Array:
    """The take's columns of the calibration's markers: (T, Mc, 3) metres, world,
    NaN where the take (or the rig) lacks a marker.

    Args:
        calibration: whose ``marker_names`` order the result follows.
        rig_marker_names, marker_cols: as :func:`calibration_columns`.
        positions: (T, M, 3) float64 metres, world, the take's markers.
    """
    positions = np.asarray(positions, dtype=np.float64)
    cols = calibration_columns(calibration, rig_marker_names, marker_cols)
    out = np.full((positions.shape[0], len(cols), 3), np.nan)
    have = cols >= 0
    out[:, have] = positions[:, cols[have]]
    return out


def _finite_or_none(v: float) -> float | None:
    return v if math.isfinite(v) else None


class MatchWindow:
    """The live check: a performer's markers over the first :data:`LIVE_WINDOW_S`
    of its stream against the calibration's layouts (:func:`match_calibration`'s
    figures), once.

    Every buffer is allocated here (off the hot path). :meth:`add` fits each
    segment's layout to the frame as it arrives (a rigid fit per segment, no array
    allocated), so the frame that ends the window only takes medians: the fits of a
    whole second on that one frame held the loop for milliseconds.

    Args:
        calibration: the calibration checked (kept: a new one needs a new window).
        rig_marker_names: (Mr,) the rig's markers (the order of ``marker_cols``).
        window_s: seconds of stream to check over.
        max_frames: at most this many frames (a faster stream ends the window early).
    """

    def __init__(
        self,
        calibration: Calibration,
        rig_marker_names: Sequence[str],
        *,
        window_s: float = LIVE_WINDOW_S,
        max_frames: int = 1000,
    ) -> None:
        self.calibration = calibration
        self.rig_marker_names = tuple(rig_marker_names)
        self.window_s = window_s
        n_markers = len(calibration.marker_names)
        self._row = np.full((n_markers, 3), np.nan)
        self._cols = np.zeros(n_markers, dtype=np.int64)
        self._absent = np.zeros(n_markers, dtype=bool)
        self._cols_of: object = None
        index = {m: i for i, m in enumerate(calibration.marker_names)}
        self._segments = []
        for segment, (names, layout) in calibration.segment_layouts.items():
            fit = _LayoutFit(np.asarray(layout))
            cols = np.asarray([index[n] for n in names], dtype=np.int64)
            pts = np.zeros((len(names), 3))
            residual = np.full((max_frames, len(names)), np.nan)
            self._segments.append((segment, tuple(names), fit, cols, pts, residual))
        self._max_frames = max_frames
        self.n_frames = 0
        self.first_s = math.nan
        self.result: CalibrationMatch | None = None

    @property
    def done(self) -> bool:
        """The check has run (``result`` is set)."""
        return self.result is not None

    def add(
        self, markers_world: F64Array, marker_cols: IntArray, t_s: float
    ) -> CalibrationMatch | None:
        """Add one frame; returns the check's result on the frame that ends the
        window (None before, and after: read ``result``).

        Args:
            markers_world: (n, 3) float64 metres, world, the stream's markers
                (NaN rows = occluded).
            marker_cols: (Mr,) int64, column of each rig marker in
                ``markers_world`` (-1 = absent; the solver's ``marker_cols``).
            t_s: the frame's time, seconds: the source's clock when it has one (a
                take replayed as fast as possible is checked over its own first
                second), else the receive time.
        """
        if self.result is not None:
            return None
        if math.isnan(self.first_s):
            self.first_s = t_s
        elif abs(t_s - self.first_s) >= self.window_s:
            return self.finish()
        if marker_cols is not self._cols_of:  # a new label set: its columns, once
            self._cols_of = marker_cols
            cols = calibration_columns(
                self.calibration, self.rig_marker_names, marker_cols
            )
            self._absent[:] = cols < 0
            self._cols[:] = np.where(self._absent, 0, cols)
        row = self._row
        np.take(markers_world, self._cols, axis=0, out=row)
        row[self._absent] = np.nan
        t = self.n_frames
        for _, _, fit, cols, pts, residual in self._segments:
            np.take(row, cols, axis=0, out=pts)
            fit.residuals(pts, residual[t])
        self.n_frames += 1
        if self.n_frames == self._max_frames:
            return self.finish()
        return None

    def finish(self) -> CalibrationMatch:
        """The figures over the frames so far (also when the stream stops early)."""
        n = self.n_frames
        self.result = CalibrationMatch(
            segments=tuple(
                _segment_match(segment, names, residual[:n])
                for segment, names, _, _, _, residual in self._segments
            ),
            frames=n,
        )
        return self.result
