"""C3D takes: read any C3D into a :class:`~retargetd.replay.take.Take`, write markers.

Reading uses ezc3d. What we take from the file:

- **Points:** ``POINT:LABELS`` (+ ``LABELS2``, ``LABELS3`` ... past 255 points), data
  as ezc3d gives it (``data/points`` (4, N, T), file units, capture frame). A sample is
  occluded when a coordinate is non-finite or its residual is < 0 (the C3D rule; ezc3d
  already turns those into NaN).
- **Units:** ``POINT:UNITS`` (``"mm"`` when absent, as the C3D standard does).
- **Up axis:** the axis *letter* of ``POINT:Y_SCREEN`` (the screen-up axis), always
  taken as positive; ``+Z`` (the C3D lab convention) when absent. The sign is ignored on
  purpose: QTM writes a viewing convention there, e.g. ``ezc3d-testfiles/Qualisys.c3d``
  says ``Y_SCREEN = -Z`` / ``X_SCREEN = -X`` while its data is plainly +Z up (head at
  z ~ 1460 mm, heels at z ~ 78 mm). No file we have stores a truly downward axis;
  ``--take-up`` overrides when one does. ``up_source`` says when a sign was dropped.
- **References:** labels listed in ``POINT:ANGLES`` ("angle", ``POINT:ANGLE_UNITS``,
  default deg), ``FORCES``/``REACTIONS`` ("force"), ``MOMENTS`` ("moment"), ``POWERS``
  ("power"), ``SCALARS`` ("other"), plus joint centres, Plug-in Gait segment points and
  centre-of-mass points by name (``retargetd.replay.points.reference_kind``).
- **Subjects:** ``SUBJECTS:LABEL_PREFIXES``/``NAMES`` and ``Name:`` label prefixes.
- **Measurements:** every scalar numeric parameter of the ``PROCESSING`` group, as
  written (Vicon: lengths in mm, ``Bodymass`` in kg).
- **first_frame:** ezc3d's ``header/points/first_frame`` (0-based: the header's
  1-based number minus one, so Qualisys' "Cropped Measurement Start Frame 705" reads
  as 704).
- **Manufacturer:** ``MANUFACTURER:COMPANY``, ``SOFTWARE`` and ``VERSION_LABEL``.

Writing (:func:`write_c3d`) stores float points (``POINT:SCALE = -1``), occluded
samples as zeros with residual -1, ``POINT:UNITS``, ``POINT:X_SCREEN``/``Y_SCREEN``
so that :func:`read_c3d` finds the up axis again, ``POINT:RATE``, the header first
frame, optional ``Name:`` prefixes with a ``SUBJECTS`` group, and measurements in
``PROCESSING``.
"""

from __future__ import annotations

import logging
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import ezc3d
import numpy as np

from retargetd.protocols import conventions as cv
from retargetd.protocols.frames import F64Array
from retargetd.replay import points as pts
from retargetd.replay.take import Take, TakeError

logger = logging.getLogger(__name__)

#: ``POINT`` parameters listing labels of non-marker outputs, and their kind.
DECLARED_KIND_PARAMS = {
    "ANGLES": "angle",
    "FORCES": "force",
    "REACTIONS": "force",
    "MOMENTS": "moment",
    "POWERS": "power",
    "SCALARS": "other",
}
#: Reference kind -> (``POINT`` units parameter, default when absent).
KIND_UNIT_PARAMS = {
    "angle": ("ANGLE_UNITS", "deg"),
    "force": ("FORCE_UNITS", ""),
    "moment": ("MOMENT_UNITS", ""),
    "power": ("POWER_UNITS", ""),
    "other": ("SCALAR_UNITS", ""),
}
#: X_SCREEN written beside each Y_SCREEN (any axis orthogonal to up will do).
_X_SCREEN_FOR_UP = {"+Z": "+X", "+Y": "+X", "+X": "+Y"}
_AXIS = re.compile(r"([+-]?)([XYZ])")


def _param(params: Mapping[str, Any], group: str, name: str) -> Any:
    """A parameter's value, or None when the group or parameter is absent."""
    entry = params.get(group, {}).get(name)
    return None if entry is None else entry.get("value")


def _strings(value: Any) -> list[str]:
    """A string parameter's values, stripped (empty list when absent or numeric)."""
    if value is None or isinstance(value, np.ndarray):
        return []
    if isinstance(value, str):
        return [value.strip()]
    return [str(v).strip() for v in value]


def _first_string(value: Any) -> str | None:
    strings = _strings(value)
    return strings[0] if strings else None


def _labels(params: Mapping[str, Any], n_points: int) -> list[str]:
    labels = _strings(_param(params, "POINT", "LABELS"))
    for i in range(2, 100):
        more = _param(params, "POINT", f"LABELS{i}")
        if more is None:
            break
        labels += _strings(more)
    labels = labels[:n_points]
    # Unnamed points keep a name so that columns stay addressable.
    labels += [f"point{i}" for i in range(len(labels), n_points)]
    return labels


def _up_axis(
    params: Mapping[str, Any], path: str, override: str | None
) -> pts.Resolved:
    resolved = pts.resolve_up_axis(path, override)
    if resolved is not None:
        return resolved
    text = (_first_string(_param(params, "POINT", "Y_SCREEN")) or "").upper()
    match = _AXIS.fullmatch(text)
    if match is None:
        return pts.Resolved("+Z", "default (C3D lab convention; no POINT:Y_SCREEN)")
    if match.group(1) == "-":
        return pts.Resolved(
            "+" + match.group(2), f"file (POINT:Y_SCREEN = {text}, sign ignored)"
        )
    return pts.Resolved("+" + match.group(2), "file (POINT:Y_SCREEN)")


def _declared_kinds(params: Mapping[str, Any]) -> dict[str, str]:
    kinds: dict[str, str] = {}
    for name, kind in DECLARED_KIND_PARAMS.items():
        for label in _strings(_param(params, "POINT", name)):
            if label:
                kinds.setdefault(label, kind)
    return kinds


def _kind_units(params: Mapping[str, Any]) -> dict[str, str]:
    return {
        kind: _first_string(_param(params, "POINT", name)) or default
        for kind, (name, default) in KIND_UNIT_PARAMS.items()
    }


def _measurements(params: Mapping[str, Any]) -> dict[str, float]:
    out: dict[str, float] = {}
    for name, entry in params.get("PROCESSING", {}).items():
        if name.startswith("__"):
            continue
        value = entry.get("value")
        if (
            isinstance(value, np.ndarray)
            and value.size == 1
            and np.issubdtype(value.dtype, np.number)
        ):
            out[name] = float(value.ravel()[0])
    return out


def _manufacturer(params: Mapping[str, Any]) -> str:
    company = _first_string(_param(params, "MANUFACTURER", "COMPANY")) or ""
    software = _first_string(_param(params, "MANUFACTURER", "SOFTWARE")) or ""
    version = _first_string(_param(params, "MANUFACTURER", "VERSION_LABEL")) or ""
    if software.lower().startswith(company.lower()):
        company = ""  # "Vicon" + "Vicon Nexus" reads "Vicon Nexus"
    return " ".join(p for p in (company, software, version) if p)


def read_c3d(
    path: str | os.PathLike[str],
    *,
    subject: str | None = None,
    units: str | None = None,
    up_axis: str | None = None,
) -> Take:
    """Load a C3D file as a take in world metres.

    Args:
        path: the ``.c3d`` file.
        subject: the subject to load (required when the file holds several).
        units: override of the file's length unit (``--take-units``).
        up_axis: override of the file's up axis (``--take-up``).

    Returns:
        The take; markers (T, M, 3) float64 metres, world frame, NaN rows = occluded.

    Raises:
        TakeError: unreadable file, ambiguous or unknown subject, bad override.
    """
    name = str(path)
    try:
        c3d = ezc3d.c3d(name)
    except (RuntimeError, OSError, ValueError, IndexError) as exc:
        raise TakeError(f"take {name}: not a readable C3D file ({exc})") from None
    params = c3d["parameters"]
    data = np.asarray(c3d["data"]["points"], dtype=np.float64)  # (4, N, T)
    n_points = data.shape[1]
    residuals = np.asarray(c3d["data"]["meta_points"]["residuals"], dtype=np.float64)
    points = np.ascontiguousarray(data[:3].transpose(2, 1, 0))  # (T, N, 3)
    valid = np.asarray(np.isfinite(points).all(axis=-1), dtype=bool)
    if residuals.shape == (1, n_points, points.shape[0]):
        valid &= residuals[0].T >= 0
    rate = _param(params, "POINT", "RATE")
    rate_hz = (
        float(np.ravel(rate)[0])
        if isinstance(rate, np.ndarray) and rate.size
        else float(c3d["header"]["points"]["frame_rate"])
    )
    return pts.assemble_take(
        path=name,
        fmt="c3d",
        labels=_labels(params, n_points),
        points=points,
        valid=valid,
        subject=subject,
        units=pts.resolve_units(
            name,
            units,
            _first_string(_param(params, "POINT", "UNITS")),
            "file (POINT:UNITS)",
            "mm",
            "default (C3D: no POINT:UNITS)",
        ),
        up_axis=_up_axis(params, name, up_axis),
        rate_hz=rate_hz,
        first_frame=int(c3d["header"]["points"]["first_frame"]),
        declared_prefixes=_strings(_param(params, "SUBJECTS", "LABEL_PREFIXES")),
        declared_names=_strings(_param(params, "SUBJECTS", "NAMES")),
        declared_kinds=_declared_kinds(params),
        kind_units=_kind_units(params),
        measurements=_measurements(params),
        manufacturer=_manufacturer(params),
    )


def write_c3d(
    path: str | os.PathLike[str],
    labels: Sequence[str],
    positions_world: F64Array,
    rate_hz: float,
    *,
    units: str = "mm",
    up_axis: str = "+Z",
    first_frame: int = 0,
    measurements: Mapping[str, float] | None = None,
    subject: str | None = None,
) -> None:
    """Write markers to a C3D file in a chosen capture frame and unit.

    Args:
        path: the C3D file to create (overwritten; any suffix is kept as given).
        labels: (M,) marker labels, without subject prefix.
        positions_world: (T, M, 3) float, metres, internal world; NaN rows = occluded
            (written as zeros with residual -1, so they read back as occluded).
        rate_hz: frame rate, Hz (``POINT:RATE``).
        units: length unit of the file (``POINT:UNITS``): "mm", "m" ...
        up_axis: up axis of the file's capture frame, "+X", "+Y" or "+Z" (written as
            ``POINT:Y_SCREEN``; negative axes are refused since readers drop the sign).
        first_frame: the source's number of row 0 (0-based, as ezc3d reports it).
        measurements: name -> value for a ``PROCESSING`` group (as the vendor writes
            them: lengths in mm, body mass in kg).
        subject: when given, labels are written as ``subject:label`` with a
            ``SUBJECTS`` group.

    Raises:
        ValueError: bad shape, rate, unit or up axis, naming the argument.
    """
    unit = cv.normalize_units(units)
    up = cv.normalize_up_axis(up_axis)
    if up not in _X_SCREEN_FOR_UP:
        raise ValueError(
            f"up_axis must be +X, +Y or +Z for C3D (readers take the POINT:Y_SCREEN "
            f"axis letter only); got {up_axis!r}"
        )
    if not (np.isfinite(rate_hz) and rate_hz > 0):
        raise ValueError(f"rate_hz must be > 0; got {rate_hz}")
    if first_frame < 0:
        raise ValueError(f"first_frame must be >= 0; got {first_frame}")
    pos = pts.check_positions(labels, positions_world)
    n_frames, n_markers = pos.shape[:2]
    valid = np.asarray(np.isfinite(pos).all(axis=-1), dtype=bool)  # (T, M)
    capture = np.where(valid[..., None], pts.capture_from_world_pos(pos, up, unit), 0.0)
    data = np.ones((4, n_markers, n_frames))
    data[:3] = capture.transpose(2, 1, 0)
    residuals = np.where(valid.T, 0.0, -1.0)[None]  # (1, M, T)

    c3d = ezc3d.c3d()
    point = c3d["parameters"]["POINT"]
    prefix = f"{subject}:" if subject else ""
    point["RATE"]["value"] = [float(rate_hz)]
    point["LABELS"]["value"] = [prefix + label for label in labels]
    point["DESCRIPTIONS"]["value"] = [""] * n_markers
    point["UNITS"]["value"] = [unit]
    c3d.add_parameter("POINT", "Y_SCREEN", [up])
    c3d.add_parameter("POINT", "X_SCREEN", [_X_SCREEN_FOR_UP[up]])
    if subject:
        c3d.add_parameter("SUBJECTS", "USED", [1])
        c3d.add_parameter("SUBJECTS", "USES_PREFIXES", [1])
        c3d.add_parameter("SUBJECTS", "NAMES", [subject])
        c3d.add_parameter("SUBJECTS", "LABEL_PREFIXES", [prefix])
    for name, value in (measurements or {}).items():
        c3d.add_parameter("PROCESSING", name, [float(value)])
    c3d.add_parameter("MANUFACTURER", "COMPANY", ["retargetd"])
    c3d["header"]["points"]["first_frame"] = int(first_frame)
    c3d["data"]["points"] = data
    c3d["data"]["meta_points"] = {
        "residuals": residuals,
        "camera_masks": np.zeros((7, n_markers, n_frames), dtype=bool),
    }
    # ezc3d appends ".c3d" to any name not ending in lower-case ".c3d" ("X.C3D" became
    # "X.C3D.c3d"): write beside the target under such a name, then rename (atomic).
    target = Path(path)
    tmp = target.with_name(f".{target.name}.{os.getpid()}.tmp.c3d")
    try:
        c3d.write(str(tmp))
        os.replace(tmp, target)
    finally:
        tmp.unlink(missing_ok=True)
    logger.debug("wrote %s: %d frames x %d markers", path, n_frames, n_markers)
