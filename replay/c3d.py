"""C3D takes: read any C3D into a :class:`~retargetd.replay.take.Take`, write markers.

Reading: :func:`retargetd.replay.c3d_layout.inspect_c3d` first checks the sizes the
file declares against its size, without reading data (an empty file, no points or no
complete frame is a one-line error). ezc3d then reads the file, unless that check
found something ezc3d cannot be trusted with (MIPS processor type, a parameter
section it would misread or allocate gigabytes for, missing ``POINT:USED``, fewer
frames than declared, a ``ROTATION`` section past the end of the file), or ezc3d
fails; then the ``c3d`` package reads it (:mod:`retargetd.replay.c3d_fallback`).
A file ezc3d reads is loaded exactly as before the fallback existed. ``Take.reader``
names the reader, ``Take.repairs`` lists what had to be worked around. What we take
from the file:

- **Points:** ``POINT:LABELS`` (+ ``LABELS2``, ``LABELS3`` ... past 255 points), data
  as ezc3d gives it (``data/points`` (4, N, T), file units, capture frame). A sample is
  occluded when a coordinate is non-finite or its residual is < 0 (the C3D rule; ezc3d
  already turns those into NaN).
- **Units:** ``POINT:UNITS`` (``"mm"`` when absent, as the C3D standard does); a
  spelled-out unit cut to 4 characters (``"mete"``) is read as that unit (a repair).
- **Rate:** ``--take-rate`` when given, else ``POINT:RATE``, else (absent or 0) the
  header's rate (a repair); when both are 0 the load fails naming ``--take-rate``.
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

import importlib.metadata
import logging
import math
import os
import re
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import ezc3d
import numpy as np

from retargetd.protocols import conventions as cv
from retargetd.protocols.frames import BoolArray, F64Array
from retargetd.replay import points as pts
from retargetd.replay.c3d_fallback import READER_NAME, layout_params, read_fallback
from retargetd.replay.c3d_layout import inspect_c3d
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
#: How ``take info`` names the first reader.
EZC3D_READER = f"ezc3d {importlib.metadata.version('ezc3d')}"
#: Spelled-out length units, for POINT:UNITS cut short ("mete").
_SPELLED_UNITS = {
    "meters": "m",
    "metres": "m",
    "millimeters": "mm",
    "millimetres": "mm",
    "centimeters": "cm",
    "centimetres": "cm",
    "decimeters": "dm",
    "decimetres": "dm",
    "inches": "in",
}


def _printable(text: str) -> str:
    """``text`` with every non-printable character escaped (one line, readable)."""
    return "".join(c if c.isprintable() else ascii(c)[1:-1] for c in text)


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


@dataclass(frozen=True, slots=True, kw_only=True)
class _Raw:
    """One reader's output, before the take is assembled."""

    reader: str
    params: Mapping[str, Any]
    points: F64Array  # (T, N, 3) file units, capture frame
    valid: BoolArray  # (T, N)
    header_rate_hz: float
    first_frame: int


def _read_ezc3d(name: str) -> _Raw:
    """Read with ezc3d exactly as before the fallback existed."""
    c3d = ezc3d.c3d(name)
    params = c3d["parameters"]
    data = np.asarray(c3d["data"]["points"], dtype=np.float64)  # (4, N, T)
    n_points = data.shape[1]
    residuals = np.asarray(c3d["data"]["meta_points"]["residuals"], dtype=np.float64)
    points = np.ascontiguousarray(data[:3].transpose(2, 1, 0))  # (T, N, 3)
    valid = np.asarray(np.isfinite(points).all(axis=-1), dtype=bool)
    if residuals.shape == (1, n_points, points.shape[0]):
        valid &= residuals[0].T >= 0
    return _Raw(
        reader=EZC3D_READER,
        params=params,
        points=points,
        valid=valid,
        header_rate_hz=float(c3d["header"]["points"]["frame_rate"]),
        first_frame=int(c3d["header"]["points"]["first_frame"]),
    )


def _file_rate(params: Mapping[str, Any], header_rate_hz: float) -> tuple[float, str]:
    """The frame rate the file gives, and where it came from."""
    rate = _param(params, "POINT", "RATE")
    if isinstance(rate, np.ndarray) and rate.size:
        return float(np.ravel(rate)[0]), "file (POINT:RATE)"
    return header_rate_hz, "file (header; no POINT:RATE)"


def _resolve_rate(
    name: str, params: Mapping[str, Any], header_rate_hz: float, override: float | None
) -> tuple[float, str, tuple[str, ...]]:
    """The frame rate: ``--take-rate``, else the file's, else the header's.

    Returns:
        ``(rate_hz, source, repairs)``.

    Raises:
        TakeError: no positive rate anywhere; the message names ``--take-rate``.
    """
    if override is not None:
        if not (math.isfinite(override) and override > 0):
            raise TakeError(f"take {name}: --take-rate must be > 0 Hz; got {override}")
        return float(override), "override (--take-rate)", ()
    rate_hz, source = _file_rate(params, header_rate_hz)
    if math.isfinite(rate_hz) and rate_hz > 0:
        if "no POINT:RATE" in source:
            return (
                rate_hz,
                source,
                (f"no POINT:RATE: the header's {rate_hz:g} Hz used",),
            )
        return rate_hz, source, ()
    if math.isfinite(header_rate_hz) and header_rate_hz > 0:
        return (
            header_rate_hz,
            "file (header)",
            (f"POINT:RATE is {rate_hz:g} Hz: the header's {header_rate_hz:g} Hz used",),
        )
    raise TakeError(
        f"take {name}: the frame rate is 0 Hz (POINT:RATE and the header); "
        "pass --take-rate HZ with the capture rate"
    )


def _file_units(params: Mapping[str, Any]) -> tuple[str | None, str | None]:
    """``POINT:UNITS`` as a known unit, repairing a unit name cut short.

    Returns:
        ``(units, repair)``: the unit text to resolve (None when absent) and a
        one-line repair note, or None when nothing was repaired.
    """
    text = _first_string(_param(params, "POINT", "UNITS"))
    if not text:
        return text, None
    try:
        cv.normalize_units(text)
    except ValueError:
        pass
    else:
        return text, None
    # Some writers store only the first 4 characters of a spelled-out unit
    # (c3d.org sample15 FP1.C3D: "mete" for meters, its points reach 2.14).
    low = text.strip().lower()
    matches = {
        unit
        for long, unit in _SPELLED_UNITS.items()
        if len(low) >= 4 and long.startswith(low)
    }
    if len(matches) == 1:
        unit = matches.pop()
        return unit, f"POINT:UNITS {text!r} read as {unit} (a unit name cut short)"
    return text, None


def read_c3d(
    path: str | os.PathLike[str],
    *,
    subject: str | None = None,
    units: str | None = None,
    up_axis: str | None = None,
    rate_hz: float | None = None,
) -> Take:
    """Load a C3D file as a take in world metres.

    The file's declared sizes are checked first (:func:`inspect_c3d`); ezc3d reads
    it unless that check says ezc3d cannot be trusted with it, or ezc3d fails; then
    the ``c3d`` package reads it (:mod:`retargetd.replay.c3d_fallback`). The take
    records which reader read it (``Take.reader``) and every repair
    (``Take.repairs``).

    Args:
        path: the ``.c3d`` file.
        subject: the subject to load (required when the file holds several).
        units: override of the file's length unit (``--take-units``).
        up_axis: override of the file's up axis (``--take-up``).
        rate_hz: override of the file's frame rate, Hz (``--take-rate``); needed
            when the file's rate is 0.

    Returns:
        The take; markers (T, M, 3) float64 metres, world frame, NaN rows = occluded.

    Raises:
        TakeError: unreadable file, no data, zero rate without ``rate_hz``,
            ambiguous or unknown subject, bad override.
    """
    name = str(path)
    layout = inspect_c3d(name)
    raw: _Raw | None = None
    if layout.ezc3d_problems:
        why = "; ".join(layout.ezc3d_problems)
    else:
        try:
            raw = _read_ezc3d(name)
        except (RuntimeError, OSError, ValueError, IndexError) as exc:
            why = f"ezc3d: {exc}"
    repairs: list[str] = []
    if raw is None:
        params: Mapping[str, Any] = layout_params(layout)
        rate, rate_source, rate_repairs = _resolve_rate(
            name, params, layout.header_rate_hz, rate_hz
        )
        # The package derives analog samples per frame from the rate: give it the
        # file's own (a --take-rate override must not change the frame layout).
        file_rate = _file_rate(params, layout.header_rate_hz)[0]
        for layout_rate in (file_rate, layout.header_rate_hz, rate):
            if math.isfinite(layout_rate) and layout_rate > 0:
                break
        try:
            data = read_fallback(layout, layout_rate)
        except (ValueError, KeyError, OSError, AssertionError, struct.error) as exc:
            # A garbled section can put any byte in a name: keep the message one line.
            detail = _printable(f"ezc3d not used: {why}; c3d package: {exc}")
            raise TakeError(
                f"take {name}: not a readable C3D file ({detail})"
            ) from None
        if data.points.shape[0] == 0:
            raise TakeError(
                f"take {name}: no frame could be read: the file holds no data to load"
            )
        repairs.append(f"ezc3d not used: {why}")
        repairs += layout.notes
        repairs += (f"c3d package: {w}" for w in data.warnings)
        raw = _Raw(
            reader=READER_NAME,
            params=data.params,
            points=data.points,
            valid=data.valid,
            header_rate_hz=layout.header_rate_hz,
            first_frame=layout.first_frame,
        )
    else:
        rate, rate_source, rate_repairs = _resolve_rate(
            name, raw.params, raw.header_rate_hz, rate_hz
        )
    repairs += rate_repairs
    params = raw.params
    file_units, units_repair = _file_units(params)
    if units_repair and units is None:
        repairs.append(units_repair)
    n_points = raw.points.shape[1]
    return pts.assemble_take(
        path=name,
        fmt="c3d",
        labels=_labels(params, n_points),
        points=raw.points,
        valid=raw.valid,
        subject=subject,
        units=pts.resolve_units(
            name,
            units,
            file_units,
            "file (POINT:UNITS)",
            "mm",
            "default (C3D: no POINT:UNITS)",
        ),
        up_axis=_up_axis(params, name, up_axis),
        rate_hz=rate,
        first_frame=raw.first_frame,
        declared_prefixes=_strings(_param(params, "SUBJECTS", "LABEL_PREFIXES")),
        declared_names=_strings(_param(params, "SUBJECTS", "NAMES")),
        declared_kinds=_declared_kinds(params),
        kind_units=_kind_units(params),
        measurements=_measurements(params),
        manufacturer=_manufacturer(params),
        reader=raw.reader,
        rate_source=rate_source,
        repairs=tuple(repairs),
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
