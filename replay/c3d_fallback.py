"""The fallback C3D reader: the pure-Python ``c3d`` package, bounded by the layout.

Used only for files ezc3d cannot be trusted with (see
:func:`retargetd.replay.c3d_layout.inspect_c3d`) or fails on. Parameters come from
the layout's own bounded walk (so a parameter declaring more bytes than it holds is
skipped, not read); frames come from ``c3d.Reader.read_frames``, which handles the
Intel, DEC and MIPS number formats and integer or float data, and are read into
arrays sized from the frames the file *holds*, never from what it declares.

``c3d.Reader`` checks that header and parameters agree with ``assert`` and stops
there (``FP1.C3D``: "inconsistent analog count"); the layout check replaces those
checks here, and its notes are reported as repairs. The package's warnings (end of
file inside a frame, missing parameters ...) are collected, never raised.

The package walks the parameter section itself, following each next-entry offset.
Where the layout repaired the section (an offset pointing inside its entry or past
the section, a description longer than the bytes left), the package reads the file
through :class:`_Patched`, which overlays the layout's ``patches`` (a few bytes of
the parameter section) on what it reads, so both walks agree; the file is not
changed.
"""

from __future__ import annotations

import importlib.metadata
import os
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import IO, Any

import c3d
import numpy as np

from retargetd.protocols.frames import BoolArray, F64Array
from retargetd.replay.c3d_layout import C3DLayout, param_value

#: How ``take info`` names this reader.
READER_NAME = f"c3d {importlib.metadata.version('c3d')} (fallback)"


class _Patched:
    """A binary file read with some of its bytes replaced (``read``, ``seek``,
    ``tell``: what ``c3d.Reader`` uses)."""

    def __init__(self, handle: IO[bytes], patches: Sequence[tuple[int, bytes]]):
        self._handle = handle
        self._patches = tuple(patches)

    def read(self, size: int = -1) -> bytes:
        at = self._handle.tell()
        raw = self._handle.read(size)
        if not any(p < at + len(raw) and p + len(b) > at for p, b in self._patches):
            return raw
        out = bytearray(raw)
        for p, patch in self._patches:
            for i, byte in enumerate(patch):
                if 0 <= p + i - at < len(out):
                    out[p + i - at] = byte
        return bytes(out)

    def seek(self, offset: int, whence: int = os.SEEK_SET) -> int:
        return self._handle.seek(offset, whence)

    def tell(self) -> int:
        return self._handle.tell()


class _LenientReader(c3d.Reader):
    """``c3d.Reader`` without its consistency asserts, at a given frame rate."""

    rate_hz: float = 0.0

    def _check_metadata(self) -> None:
        # inspect_c3d checked the layout against the file size instead.
        return None

    @property
    def point_rate(self) -> float:
        # The file's rate (or --take-rate when the file says 0): the package
        # divides by it to find analog samples per frame.
        return self.rate_hz


@dataclass(frozen=True, slots=True, kw_only=True)
class FallbackData:
    """What the fallback read.

    Attributes:
        params: group -> name -> ``{"value": ...}``, the form ezc3d gives.
        points: (T, N, 3) float64, file units, capture frame; NaN where occluded.
        valid: (T, N) bool, True where the point was seen (residual >= 0).
        warnings: the package's warnings, one line each.
    """

    params: Mapping[str, Mapping[str, Mapping[str, Any]]]
    points: F64Array
    valid: BoolArray
    warnings: tuple[str, ...]


def layout_params(layout: C3DLayout) -> dict[str, dict[str, dict[str, Any]]]:
    """The layout's parameters in ezc3d's form (``params[GROUP][NAME]["value"]``)."""
    out: dict[str, dict[str, dict[str, Any]]] = {}
    for (group, name), raw in layout.params.items():
        out.setdefault(group, {})[name] = {"value": param_value(layout, raw)}
    return out


def read_fallback(layout: C3DLayout, rate_hz: float) -> FallbackData:
    """Read a file's 3D points with the ``c3d`` package.

    Args:
        layout: the file's checked layout.
        rate_hz: the file's frame rate, Hz (> 0; the package derives the analog
            samples per frame from it, so pass the file's own rate when it has one).

    Returns:
        Points and parameters; at most ``layout.frames_present`` frames.

    Raises:
        ValueError, OSError, AssertionError, struct.error: the package could not
            read the file (the caller turns these into a one-line TakeError).
    """
    n_frames = layout.frames_present
    n_points = layout.n_points
    points = np.full((n_frames, n_points, 3), np.nan)
    valid = np.zeros((n_frames, n_points), dtype=bool)
    read = 0
    with (
        open(os.fspath(layout.path), "rb") as handle,
        warnings.catch_warnings(record=True) as caught,
    ):
        warnings.simplefilter("always")
        reader = _LenientReader(
            _Patched(handle, layout.patches) if layout.patches else handle
        )
        reader.rate_hz = rate_hz
        if int(reader.point_used) != n_points:
            raise ValueError(
                f"the c3d package reads {reader.point_used} points, the layout "
                f"{n_points}"
            )
        frames = reader.read_frames(copy=False, analog_transform=False)
        for row, (_, values, _) in zip(range(n_frames), frames, strict=False):
            seen = values[:, 3] >= 0
            points[row][seen] = values[seen, :3]
            valid[row] = seen
            read = row + 1
    messages = tuple(" ".join(str(w.message).split()) for w in caught)
    if read < n_frames:
        points = points[:read]
        valid = valid[:read]
    return FallbackData(
        params=layout_params(layout),
        points=np.ascontiguousarray(points),
        valid=np.ascontiguousarray(valid),
        warnings=messages,
    )
