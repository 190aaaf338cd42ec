"""The face training set: the performer's neutral and one captured pose per
expression, in head coordinates, and its file (``face.npz``, no pickle). No compiled
code here, so the config check can read a training file without loading the solver.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from retargetd.protocols.frames import F64Array

TRAINING_FORMAT = "retargetd-face-training/1"


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class TrainingSet:
    """A performer's face training set.

    Attributes:
        head_names: (H,) head (stabilization) marker names.
        marker_names: (M,) facial marker names.
        expression_names: (K,) expression names.
        head_layout: (H, 3) float64, metres, head coordinates: neutral head markers.
        neutral: (M, 3) float64, metres, head coordinates: neutral facial markers.
        deltas: (K, M, 3) float64, metres, head coordinates: expression minus neutral.
    """

    head_names: tuple[str, ...]
    marker_names: tuple[str, ...]
    expression_names: tuple[str, ...]
    head_layout: F64Array
    neutral: F64Array
    deltas: F64Array

    def __post_init__(self) -> None:
        h, m, k = (
            len(self.head_names),
            len(self.marker_names),
            len(self.expression_names),
        )
        for name, arr, shape in (
            ("head_layout", self.head_layout, (h, 3)),
            ("neutral", self.neutral, (m, 3)),
            ("deltas", self.deltas, (k, m, 3)),
        ):
            if arr.shape != shape:
                raise ValueError(f"{name}: expected shape {shape}, got {arr.shape}")
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"{name}: non-finite values")
        if h < 3:
            raise ValueError(f"head_names: need >= 3 head markers, got {h}")

    @property
    def basis(self) -> F64Array:
        """B: (3 M, K) float64, metres; row 3 m + c is marker m, axis c."""
        m3 = 3 * len(self.marker_names)
        return np.ascontiguousarray(self.deltas.transpose(1, 2, 0).reshape(m3, self.k))

    @property
    def k(self) -> int:
        """Number of expressions."""
        return len(self.expression_names)

    def save(self, path: str | Path) -> None:
        """Write ``face.npz`` (no pickle)."""
        np.savez(
            path,
            format=np.array(TRAINING_FORMAT),
            head_names=np.array(self.head_names, dtype=str),
            marker_names=np.array(self.marker_names, dtype=str),
            expression_names=np.array(self.expression_names, dtype=str),
            head_layout=self.head_layout,
            neutral=self.neutral,
            deltas=self.deltas,
        )

    @classmethod
    def load(cls, path: str | Path) -> TrainingSet:
        """Read a file written by :meth:`save`.

        Raises:
            ValueError: not a face training set, or inconsistent shapes.
        """
        with np.load(path, allow_pickle=False) as z:
            if "format" not in z or str(z["format"]) != TRAINING_FORMAT:
                raise ValueError(f"{path}: not a {TRAINING_FORMAT} file")
            return cls(
                head_names=tuple(str(s) for s in z["head_names"]),
                marker_names=tuple(str(s) for s in z["marker_names"]),
                expression_names=tuple(str(s) for s in z["expression_names"]),
                head_layout=np.asarray(z["head_layout"], dtype=np.float64),
                neutral=np.asarray(z["neutral"], dtype=np.float64),
                deltas=np.asarray(z["deltas"], dtype=np.float64),
            )
