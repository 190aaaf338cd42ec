"""The face training set: the performer's neutral and one captured pose per
expression, in head coordinates, and its file (``face.npz``, no pickle). No compiled
code here, so the config check can read a training file without loading the solver.
"""

from __future__ import annotations

import io
import math
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from retargetd.daemon.files import write_atomic
from retargetd.protocols.frames import F64Array

TRAINING_FORMAT = "retargetd-face-training/1"
#: Default 3-D RMS marker noise, metres, at which observability is judged
#: (``face-train --noise-mm``). Merriaux et al. 2017 (Sensors 17(7):1591, a Vicon
#: system) measured a 0.15 mm mean absolute error on static markers and under 2 mm on
#: moving ones; facial markers are small (3-4 mm) and move slowly on the head, so
#: 0.5 mm, the synthetic face's noise (issue 7), lies between the two.
DEFAULT_NOISE_RMS_M = 5e-4
#: The most a training file may unpack to, bytes: 52 expressions of 200 markers in
#: float64 are 250 KB; 64 MiB is 250 times that, and a zip that unpacks to more
#: (a bomb) is refused before anything is unpacked.
MAX_TRAINING_BYTES = 64 << 20
_ARRAYS = (
    "head_names", "marker_names", "expression_names", "head_layout", "neutral",
    "deltas",
)  # fmt: skip


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
        noise_rms_m: the 3-D RMS marker noise, metres, observability is judged at
            (``face-train --noise-mm``; files without it: the default).
    """

    head_names: tuple[str, ...]
    marker_names: tuple[str, ...]
    expression_names: tuple[str, ...]
    head_layout: F64Array
    neutral: F64Array
    deltas: F64Array
    noise_rms_m: float = DEFAULT_NOISE_RMS_M

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
        if not (math.isfinite(self.noise_rms_m) and self.noise_rms_m > 0.0):
            raise ValueError(
                f"noise_rms_m: expected > 0 metres, got {self.noise_rms_m}"
            )

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
        """Write ``face.npz`` (no pickle; ``.npz`` appended to a name without it, as
        ``numpy.savez`` does), atomically (``files.write_atomic``): a crash, a full
        disk or a process ending mid-write (a live capture's save runs on a worker
        thread) leaves the file that was there whole.

        Raises:
            OSError: not written (one line naming the file); the old file is kept.
        """
        path = Path(path)
        if path.suffix != ".npz":
            path = path.with_name(path.name + ".npz")
        buf = io.BytesIO()
        np.savez(
            buf,
            format=np.array(TRAINING_FORMAT),
            head_names=np.array(self.head_names, dtype=str),
            marker_names=np.array(self.marker_names, dtype=str),
            expression_names=np.array(self.expression_names, dtype=str),
            head_layout=self.head_layout,
            neutral=self.neutral,
            deltas=self.deltas,
            noise_rms_m=np.array(self.noise_rms_m),
        )
        write_atomic(path, buf.getvalue())

    @classmethod
    def load(cls, path: str | Path) -> TrainingSet:
        """Read a file written by :meth:`save`.

        Raises:
            ValueError: one line naming the file: not a face training set (not a
                zip of arrays, members past :data:`MAX_TRAINING_BYTES` unpacked,
                object arrays, a missing array), or inconsistent shapes.
        """
        try:
            with zipfile.ZipFile(path) as zf:  # sizes before anything is unpacked
                unpacked = sum(info.file_size for info in zf.infolist())
            if unpacked > MAX_TRAINING_BYTES:
                raise ValueError(
                    f"{unpacked >> 20} MiB unpacked, more than a training set holds "
                    f"({MAX_TRAINING_BYTES >> 20} MiB)"
                )
            with np.load(path, allow_pickle=False) as z:
                if "format" not in z or str(z["format"]) != TRAINING_FORMAT:
                    raise ValueError(f"not a {TRAINING_FORMAT} file")
                arrays = {k: z[k] for k in _ARRAYS}
                noise = (
                    float(z["noise_rms_m"])
                    if "noise_rms_m" in z
                    else DEFAULT_NOISE_RMS_M
                )
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
            reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
            raise ValueError(f"{path}: not a face training set ({reason})") from None
        return cls(
            head_names=tuple(str(s) for s in arrays["head_names"]),
            marker_names=tuple(str(s) for s in arrays["marker_names"]),
            expression_names=tuple(str(s) for s in arrays["expression_names"]),
            head_layout=np.asarray(arrays["head_layout"], dtype=np.float64),
            neutral=np.asarray(arrays["neutral"], dtype=np.float64),
            deltas=np.asarray(arrays["deltas"], dtype=np.float64),
            noise_rms_m=noise,
        )
