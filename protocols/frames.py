"""Frame containers: the contract between ``protocols``, ``replay`` and ``daemon``.

Per-frame containers are slotted dataclasses holding fixed-shape arrays allocated once
per stream and refilled in place; occlusion is data (NaN rows plus a ``valid`` mask),
never an exception. Array aliases used across the package live here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

F64Array = npt.NDArray[np.float64]
F32Array = npt.NDArray[np.float32]
BoolArray = npt.NDArray[np.bool_]
IntArray = npt.NDArray[np.int64]
U8Array = npt.NDArray[np.uint8]


@dataclass(slots=True, eq=False)
class MarkerFrame:
    """One frame of labelled markers, in the internal world.

    Attributes:
        frame_id: the source's frame number (``source_frame``), never the local clock.
        t_ns: ``time.monotonic_ns()`` at receive (0 for frames read from a file).
        source_time_s: the source's own timestamp in seconds (NaN when unknown).
        markers_world: (n_markers, 3) float64, metres, world frame; NaN rows = occluded.
        valid: (n_markers,) bool, True where the marker was seen.
    """

    frame_id: int
    t_ns: int
    source_time_s: float
    markers_world: F64Array
    valid: BoolArray

    @classmethod
    def empty(cls, n_markers: int) -> MarkerFrame:
        """Allocate a frame for ``n_markers`` markers, all occluded."""
        if n_markers < 0:
            raise ValueError(f"n_markers must be >= 0; got {n_markers}")
        return cls(
            frame_id=-1,
            t_ns=0,
            source_time_s=float("nan"),
            markers_world=np.full((n_markers, 3), np.nan),
            valid=np.zeros(n_markers, dtype=bool),
        )
