"""Marker sets: which markers the synthetic performer wears, and where.

A marker set is TOML package data in ``daemon/synth/markersets/*.toml`` (or any file): a
``name`` and one ``[markers.LABEL]`` table per marker with ``segment`` (a segment of
:mod:`retargetd.daemon.synth.skeleton`), ``offset_mm = [x, y, z]`` in that
segment's frame (forward, left, up in the rest T-pose, origin at the segment's
proximal joint centre, for the 1.75 m reference performer) and a ``description``;
optionally ``[base_pose]`` ``elbow_flexion_deg``: the elbows' bend while the performer
holds the base pose (a protocol's static, such as Plug-in Gait's, that needs them bent),
which the motion ramps out of.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from retargetd.daemon.files import FileFormatError, loads_toml, read_text
from retargetd.daemon.synth.skeleton import SEGMENT_NAMES, readonly
from retargetd.protocols.frames import F64Array


@dataclass(frozen=True, slots=True, kw_only=True)
class MarkerSet:
    """Markers worn by the performer (immutable; arrays read-only).

    Attributes:
        name: the set's name (``"menache"`` ...).
        source: the file it was read from.
        labels: (M,) marker labels, in file order.
        segments: (M,) segment name each marker rides on.
        offsets_mm: (M, 3) float64, millimetres, in the segment's frame (forward, left,
            up in the rest T-pose) for the :data:`REFERENCE_HEIGHT_M` performer.
        descriptions: (M,) where on the body each marker sits.
        elbow_flexion_deg: both elbows' flexion during the base-pose hold, degrees
            (0: the straight-armed T-pose); the motion ramps out of it.
    """

    name: str
    source: str
    labels: tuple[str, ...]
    segments: tuple[str, ...]
    offsets_mm: F64Array
    descriptions: tuple[str, ...]
    elbow_flexion_deg: float = 0.0


def shipped_markersets() -> tuple[str, ...]:
    """Names of the marker sets shipped as package data."""
    folder = resources.files("retargetd.daemon.synth.markersets")
    return tuple(
        sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml"))
    )


def load_markerset(name_or_path: str | Path) -> MarkerSet:
    """Load a marker set by shipped name (``"menache"``) or from a TOML file.

    The file holds ``name`` and one ``[markers.LABEL]`` table per marker with
    ``segment`` (one of :data:`SEGMENT_NAMES`), ``offset_mm = [x, y, z]`` and an
    optional ``description``.

    Args:
        name_or_path: a shipped name, or a path to a ``.toml`` file.

    Returns:
        The validated :class:`MarkerSet`.

    Raises:
        ValueError: naming the file, the key and the bad value (unknown name or
            segment, offset of the wrong length, ...).
    """
    text_name = str(name_or_path)
    path = Path(name_or_path)
    if isinstance(name_or_path, Path) or text_name.endswith(".toml") or path.exists():
        source = str(path)
        try:
            data = loads_toml(read_text(path, "marker set"))
        except FileFormatError as exc:
            raise ValueError(f"{source}: {exc}") from None
    else:
        res = resources.files("retargetd.daemon.synth.markersets") / f"{text_name}.toml"
        if not res.is_file():
            raise ValueError(
                f"unknown marker set {text_name!r}: use one of "
                f"{', '.join(shipped_markersets())} or a path to a .toml file"
            )
        source = f"retargetd.daemon.synth.markersets/{text_name}.toml"
        data = loads_toml(res.read_text(encoding="utf-8"))
    return _markerset_from_dict(data, source)


def _markerset_from_dict(data: dict[str, Any], source: str) -> MarkerSet:
    markers = data.get("markers")
    if not isinstance(markers, dict) or not markers:
        raise ValueError(
            f"{source}: markers: expected [markers.LABEL] tables; got none"
        )
    labels, segments, offsets, descriptions = [], [], [], []
    for label, entry in markers.items():
        key = f"markers.{label}"
        if not isinstance(entry, dict):
            raise ValueError(f"{source}: {key}: expected a table; got {entry!r}")
        unknown = set(entry) - {"segment", "offset_mm", "description"}
        if unknown:
            raise ValueError(f"{source}: {key}: unknown keys {sorted(unknown)}")
        segment = entry.get("segment")
        if segment not in SEGMENT_NAMES:
            raise ValueError(
                f"{source}: {key}.segment: unknown segment {segment!r} "
                f"(expected one of {', '.join(SEGMENT_NAMES)})"
            )
        offset = entry.get("offset_mm")
        if (
            not isinstance(offset, list)
            or len(offset) != 3
            or not all(
                isinstance(v, int | float) and not isinstance(v, bool) for v in offset
            )
            or not np.all(np.isfinite(offset))
        ):
            raise ValueError(
                f"{source}: {key}.offset_mm: expected 3 finite numbers [x, y, z] in "
                f"mm; got {offset!r}"
            )
        description = entry.get("description", "")
        if not isinstance(description, str):
            raise ValueError(f"{source}: {key}.description: expected a string")
        labels.append(str(label))
        segments.append(str(segment))
        offsets.append([float(v) for v in offset])
        descriptions.append(description)
    unknown_top = set(data) - {"name", "reference_height_m", "markers", "base_pose"}
    if unknown_top:
        raise ValueError(f"{source}: unknown keys {sorted(unknown_top)}")
    base = data.get("base_pose", {})
    if not isinstance(base, dict) or set(base) - {"elbow_flexion_deg"}:
        raise ValueError(
            f"{source}: base_pose: expected a table with elbow_flexion_deg; "
            f"got {base!r}"
        )
    flexion = base.get("elbow_flexion_deg", 0.0)
    if (
        not isinstance(flexion, int | float)
        or isinstance(flexion, bool)
        or not 0.0 <= flexion <= 150.0
    ):
        raise ValueError(
            f"{source}: base_pose.elbow_flexion_deg: expected 0-150 deg (the elbow's "
            f"range); got {flexion!r}"
        )
    name = data.get("name", Path(source).stem)
    if not isinstance(name, str):
        raise ValueError(f"{source}: name: expected a string; got {name!r}")
    return MarkerSet(
        name=name,
        source=source,
        labels=tuple(labels),
        segments=tuple(segments),
        offsets_mm=readonly(np.array(offsets, dtype=np.float64)),
        descriptions=tuple(descriptions),
        elbow_flexion_deg=float(flexion),
    )
