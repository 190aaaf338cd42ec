"""A prop's marker layout: its markers in the prop's own frame, calibrated from still
frames, and the JSON file it is saved to.

**The prop frame.** Its axes are the world's axes at calibration (a prop held level
and facing the lab's +Y is at identity); its origin is the centroid of the markers
plus the pivot (``pivot_m``, in those axes). So a virtual camera calibrated level and
looking along the world's +Y streams the identity rotation, which Unity's frame
(``protocols/engine_unity.py``: world +Y is Unity +Z) reads as a camera looking along
its own forward, +Z, with +Y up: no camera-specific correction is needed.

File (JSON, UTF-8, ``"format": "retargetd-prop"``, ``"version": 1``): ``name``,
``kind`` ("rigid" or "camera"), ``labels`` (K marker labels as the stream names
them), ``layout_prop_m`` (K x 3, metres, prop frame), ``weights`` (K, the fit's
weight of each marker), ``pivot_m`` (3, the pivot used, metres, prop axes),
``spread_mm`` (K, each marker's RMS scatter over the calibration frames).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from retargetd.daemon.files import FileFormatError, loads_json, read_text, write_atomic
from retargetd.protocols.frames import F64Array

FORMAT = "retargetd-prop"
VERSION = 1
KINDS = ("rigid", "camera")

#: Markers a prop may have: the consensus is O(K^2) per frame (its search O(K^3),
#: up to ``kernel.MAX_SEARCH_MARKERS``), the bench covers clusters of 4 to 8, and the
#: prop message counts markers in one byte; 32 is four times the largest benched.
MAX_PROP_MARKERS = 32
#: The least spread of a layout across its second principal axis, metres: markers
#: closer to one line than this leave the roll about it unobserved. 5 mm is within
#: the radius of common passive markers (9.5-14 mm across) of a line.
MIN_PLANAR_SPREAD_M = 0.005


class PropError(ValueError):
    """A prop layout or calibration problem, one line."""


@dataclass(frozen=True, slots=True, kw_only=True)
class PropLayout:
    """A calibrated prop: its markers in its own frame (see the module docstring)."""

    name: str
    kind: str
    labels: tuple[str, ...]
    layout_prop_m: F64Array  # (K, 3)
    weights: F64Array  # (K,)
    pivot_m: F64Array  # (3,)
    spread_mm: F64Array  # (K,)

    def to_json(self) -> dict[str, Any]:
        """The file's document."""
        return {
            "format": FORMAT,
            "version": VERSION,
            "name": self.name,
            "kind": self.kind,
            "labels": list(self.labels),
            "layout_prop_m": self.layout_prop_m.tolist(),
            "weights": self.weights.tolist(),
            "pivot_m": self.pivot_m.tolist(),
            "spread_mm": self.spread_mm.tolist(),
        }

    def save(self, path: str | Path) -> None:
        """Write the layout (the whole file, then a rename: never half a file)."""
        write_atomic(path, (json.dumps(self.to_json(), indent=1) + "\n").encode())


def _readonly(a: Any, shape: tuple[int, ...] | None = None) -> F64Array:
    out = np.array(a, dtype=np.float64)
    if shape is not None and out.shape != shape:
        raise PropError(f"expected shape {shape}; got {out.shape}")
    out.flags.writeable = False
    return out


def layout_from_json(doc: Any, source: str = "prop") -> PropLayout:
    """Validate a parsed prop file. Raises PropError naming the key."""
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise PropError(f"{source}: not a {FORMAT} file")
    if doc.get("version") != VERSION:
        raise PropError(f"{source}: version {doc.get('version')!r} (expected 1)")
    try:
        labels = tuple(str(x) for x in doc["labels"])
        k = len(labels)
        if not 3 <= k <= MAX_PROP_MARKERS or len(set(labels)) != k:
            raise PropError(
                f"{source}: labels: 3 to {MAX_PROP_MARKERS} distinct names; got {k}"
            )
        kind = doc.get("kind", "rigid")
        if kind not in KINDS:
            raise PropError(f"{source}: kind: one of {', '.join(KINDS)}; got {kind!r}")
        layout = PropLayout(
            name=str(doc["name"]),
            kind=kind,
            labels=labels,
            layout_prop_m=_readonly(doc["layout_prop_m"], (k, 3)),
            weights=_readonly(doc.get("weights", [1.0] * k), (k,)),
            pivot_m=_readonly(doc.get("pivot_m", [0.0] * 3), (3,)),
            spread_mm=_readonly(doc.get("spread_mm", [0.0] * k), (k,)),
        )
    except (KeyError, TypeError, ValueError) as exc:
        if isinstance(exc, PropError):
            raise
        raise PropError(f"{source}: {type(exc).__name__}: {exc}") from None
    for key in ("layout_prop_m", "weights", "pivot_m"):
        if not np.all(np.isfinite(getattr(layout, key))):
            raise PropError(f"{source}: {key}: not finite")
    if np.any(layout.weights < 0.0) or not np.any(layout.weights > 0.0):
        raise PropError(f"{source}: weights: >= 0 and at least one > 0")
    return layout


def load_layout(path: str | Path) -> PropLayout:
    """Read a prop file. Raises PropError (one line naming the file)."""
    try:
        doc = loads_json(read_text(path, "prop calibration"))
    except FileFormatError as exc:
        raise PropError(f"{path}: {exc}") from None
    return layout_from_json(doc, str(path))


def calibrate_prop(
    markers_world: F64Array,
    labels: Sequence[str],
    *,
    name: str,
    kind: str = "rigid",
    rate_hz: float,
    pivot_m: Sequence[float] = (0.0, 0.0, 0.0),
    max_speed_m_s: float = 0.05,
) -> PropLayout:
    """A prop's layout from still frames.

    Args:
        markers_world: (T, K, 3) float64, metres, world; NaN rows = occluded.
        labels: (K,) the prop's marker labels.
        name, kind: the prop's.
        rate_hz: the frames' rate (the stillness check's time base).
        pivot_m: (3,) the prop frame's origin from the markers' centroid, metres, in
            the world's axes at calibration.
        max_speed_m_s: the fastest a marker may drift between the first and last
            thirds of the frames (the performers' ``calibrate_max_speed_m_s``).

    Returns:
        The layout (the prop frame: see the module docstring).

    Raises:
        PropError: a marker never seen, fewer than 3, markers on one line, a prop
            that moved; one line.
    """
    pts = np.asarray(markers_world, dtype=np.float64)
    k = len(labels)
    if pts.ndim != 3 or pts.shape[1:] != (k, 3) or pts.shape[0] < 1:
        raise PropError(f"prop {name}: expected (T, {k}, 3) markers; got {pts.shape}")
    if not 3 <= k <= MAX_PROP_MARKERS:
        raise PropError(f"prop {name}: 3 to {MAX_PROP_MARKERS} markers; got {k}")
    seen = np.all(np.isfinite(pts), axis=2)
    never = [labels[i] for i in range(k) if not seen[:, i].any()]
    if never:
        raise PropError(f"prop {name}: never seen in the still frames: {never}")
    n = pts.shape[0]
    if n >= 3:
        third = max(n // 3, 1)
        with np.errstate(all="ignore"):
            head = np.nanmean(pts[:third], axis=0)
            tail = np.nanmean(pts[-third:], axis=0)
        dt = (n - third) / rate_hz
        drift = np.linalg.norm(tail - head, axis=1) / dt
        if np.nanmax(drift) > max_speed_m_s:
            worst = int(np.nanargmax(drift))
            raise PropError(
                f"prop {name}: not still: {labels[worst]} drifted at "
                f"{np.nanmax(drift) * 1000:.0f} mm/s (at most "
                f"{max_speed_m_s * 1000:.0f} mm/s)"
            )
    mean = np.nanmedian(pts, axis=0)
    spread = np.sqrt(np.nanmean(np.sum((pts - mean) ** 2, axis=2), axis=0)) * 1000
    pivot = np.asarray(pivot_m, dtype=np.float64)
    layout = mean - (mean.mean(axis=0) + pivot)
    sv = np.linalg.svd(layout - layout.mean(axis=0), compute_uv=False)
    if sv[1] / math.sqrt(k) < MIN_PLANAR_SPREAD_M:
        raise PropError(
            f"prop {name}: degenerate: its markers lie within "
            f"{sv[1] / math.sqrt(k) * 1000:.1f} mm of one line (the roll about it "
            "is unobserved)"
        )
    return PropLayout(
        name=name,
        kind=kind,
        labels=tuple(labels),
        layout_prop_m=_readonly(layout),
        weights=_readonly(np.ones(k)),
        pivot_m=_readonly(pivot),
        spread_mm=_readonly(spread),
    )


def ambiguous_pairs(
    layout_prop_m: F64Array, tol_m: float, labels: Sequence[str]
) -> list[tuple[str, str]]:
    """Pairs of markers whose swap no distance check can see: every other marker is
    within ``tol_m`` as far from one as from the other (a symmetric layout). A swap of
    such a pair is taken as a rotation of the prop."""
    d = np.linalg.norm(layout_prop_m[:, None] - layout_prop_m[None], axis=2)
    k = d.shape[0]
    out = []
    for i in range(k):
        for j in range(i + 1, k):
            others = [m for m in range(k) if m not in (i, j)]
            if np.all(np.abs(d[i, others] - d[j, others]) <= tol_m):
                out.append((labels[i], labels[j]))
    return out
