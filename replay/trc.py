"""TRC takes (OpenSim / Motion Analysis track row column): read and write.

Layout (tab-separated text, one record per line, CRLF or LF)::

    PathFileType  4  (X/Y/Z)  <file name>
    DataRate  CameraRate  NumFrames  NumMarkers  Units  OrigDataRate  ...
    60.00     60.00       151        41          mm     60.00         ...
    Frame#  Time  <label 1>  ""  ""  <label 2>  ""  ""  ...
    ""      ""    X1  Y1  Z1  X2  Y2  Z2  ...
    <optional blank line>
    1  0.000000  x  y  z  x  y  z  ...            (one row per frame)

- Rate: the ``DataRate`` column of line 3 (Hz); ``--take-rate`` overrides it and is
  needed when it is 0. A file cut inside its 5-line header holds no data: one-line
  error. Frame count: the data rows present
  (a ``NumFrames`` that disagrees is logged).
- Units: the ``Units`` column (``"mm"`` when absent, with source "default").
- Labels: line 4, column ``2 + 3k`` for marker ``k``; ``Name:`` prefixes are split into
  subjects as for C3D. Labels are classified like C3D points by name (joint centres,
  Plug-in Gait segment points) and kept apart as references.
- Occlusion: an empty field, a missing trailing column or a non-finite value makes the
  marker occluded in that frame. Any other non-numeric field is an error naming the
  file and line. Trailing tabs and CRLF line ends are accepted.
- **Up axis:** TRC stores none. We default to ``+Y`` (OpenSim's convention, and the
  MOTEK files are Y-up), recorded as "default (TRC has no up axis)"; ``--take-up``
  overrides.
- ``first_frame``: the first row's ``Frame#`` (usually 1). Measurements: none.

:func:`write_trc` writes the same layout (frames numbered from 1, ``%.10g`` values,
occluded samples as empty fields).
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from retargetd.protocols import conventions as cv
from retargetd.protocols.frames import F64Array
from retargetd.replay import points as pts
from retargetd.replay.take import Take, TakeError

logger = logging.getLogger(__name__)

#: Up axis assumed for TRC files (they don't store one).
TRC_DEFAULT_UP = "+Y"
#: How ``take info`` names this reader.
TRC_READER = "retargetd TRC reader"
_HEADER_LINES = 5


def _float(text: str, path: str, line_no: int, what: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise TakeError(
            f"take {path}: line {line_no}: {what} {text!r} is not a number"
        ) from None


def _header_value(keys: list[str], values: list[str], key: str) -> str | None:
    lowered = [k.strip().lower() for k in keys]
    if key.lower() not in lowered:
        return None
    i = lowered.index(key.lower())
    return values[i].strip() if i < len(values) else None


def read_trc(
    path: str | os.PathLike[str],
    *,
    subject: str | None = None,
    units: str | None = None,
    up_axis: str | None = None,
    rate_hz: float | None = None,
) -> Take:
    """Load a TRC file as a take in world metres.

    Args:
        path: the ``.trc`` file.
        subject: the subject to load (required when labels carry several prefixes).
        units: override of the file's ``Units`` (``--take-units``).
        up_axis: the file's up axis (``--take-up``); ``+Y`` when not given.
        rate_hz: override of ``DataRate``, Hz (``--take-rate``); needed when the
            file's rate is 0.

    Returns:
        The take; markers (T, M, 3) float64 metres, world frame, NaN rows = occluded.

    Raises:
        TakeError: truncated header, non-numeric field, bad rate, bad override,
            ambiguous or unknown subject. The message names the file (and line).
    """
    name = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise TakeError(f"take {name}: cannot read ({exc.strerror or exc})") from None
    lines = text.splitlines()  # handles CRLF
    if lines and lines[0].startswith("PathFileType") and len(lines) < _HEADER_LINES:
        raise TakeError(
            f"take {name}: TRC file cut after {len(lines)} of {_HEADER_LINES} "
            "header lines: the file holds no data to load"
        )
    if len(lines) < _HEADER_LINES or not lines[0].startswith("PathFileType"):
        raise TakeError(
            f"take {name}: not a TRC file (needs a 5-line header starting with "
            "PathFileType)"
        )
    keys = lines[1].split("\t")
    values = lines[2].split("\t")
    rate_source = "file (DataRate)"
    if rate_hz is not None:
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise TakeError(f"take {name}: --take-rate must be > 0 Hz; got {rate_hz}")
        rate_source = "override (--take-rate)"
    else:
        rate_text = _header_value(keys, values, "DataRate")
        if not rate_text:
            raise TakeError(
                f"take {name}: line 3: no DataRate value; pass --take-rate HZ"
            )
        rate_hz = _float(rate_text, name, 3, "DataRate")
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise TakeError(
                f"take {name}: line 3: DataRate must be > 0; got {rate_text}; "
                "pass --take-rate HZ with the capture rate"
            )

    label_fields = lines[3].rstrip("\t").split("\t")
    if len(label_fields) < 2 or label_fields[0].strip() != "Frame#":
        raise TakeError(f"take {name}: line 4: expected 'Frame#<TAB>Time<TAB>labels'")
    labels = [f.strip() for f in label_fields[2::3]]
    n_markers = len(labels)
    declared = _header_value(keys, values, "NumMarkers")
    if declared and declared.isdigit() and int(declared) != n_markers:
        logger.warning(
            "take %s: NumMarkers says %s, line 4 has %d labels; using the labels",
            name,
            declared,
            n_markers,
        )

    rows: list[list[float]] = []
    frame_numbers: list[float] = []
    width = 2 + 3 * n_markers
    for line_no, line in enumerate(lines[_HEADER_LINES:], start=_HEADER_LINES + 1):
        if not line.strip():
            continue
        fields = line.rstrip("\t").split("\t")[:width]
        frame_numbers.append(_float(fields[0].strip(), name, line_no, "Frame#"))
        row = [
            _float(f, name, line_no, "field") if f.strip() else math.nan
            for f in fields[2:]
        ]
        row += [math.nan] * (3 * n_markers - len(row))
        rows.append(row)
    if not rows:
        raise TakeError(f"take {name}: no data rows after the header")
    points = np.asarray(rows, dtype=np.float64).reshape(len(rows), n_markers, 3)
    valid = np.asarray(np.isfinite(points).all(axis=-1), dtype=bool)
    declared_frames = _header_value(keys, values, "NumFrames")
    if (
        declared_frames
        and declared_frames.isdigit()
        and int(declared_frames) != len(rows)
    ):
        logger.warning(
            "take %s: NumFrames says %s, found %d rows; using the rows",
            name,
            declared_frames,
            len(rows),
        )

    unit = pts.resolve_units(
        name,
        units,
        _header_value(keys, values, "Units"),
        "file (Units)",
        "mm",
        "default (TRC without Units)",
    )
    up = pts.resolve_up_axis(name, up_axis) or pts.Resolved(
        TRC_DEFAULT_UP, "default (TRC has no up axis)"
    )
    return pts.assemble_take(
        path=name,
        fmt="trc",
        labels=labels,
        points=points,
        valid=valid,
        subject=subject,
        units=unit,
        up_axis=up,
        rate_hz=rate_hz,
        first_frame=int(frame_numbers[0]),
        reader=TRC_READER,
        rate_source=rate_source,
    )


def write_trc(
    path: str | os.PathLike[str],
    labels: Sequence[str],
    positions_world: F64Array,
    rate_hz: float,
    *,
    units: str = "mm",
    up_axis: str = "+Y",
) -> None:
    """Write markers to a TRC file in a chosen capture frame and unit.

    Args:
        path: the ``.trc`` file to create (overwritten).
        labels: (M,) marker labels (no tabs).
        positions_world: (T, M, 3) float, metres, internal world; NaN rows = occluded
            (written as empty fields).
        rate_hz: frame rate, Hz (``DataRate`` and ``CameraRate``).
        units: length unit of the file: "mm", "m" ...
        up_axis: up axis of the file's capture frame (TRC doesn't record it; readers
            assume ``+Y``, so pass the same value to :func:`read_trc` otherwise).

    Raises:
        ValueError: bad shape, rate, unit, up axis or label, naming the argument.
    """
    unit = cv.normalize_units(units)
    up = cv.normalize_up_axis(up_axis)
    if not (np.isfinite(rate_hz) and rate_hz > 0):
        raise ValueError(f"rate_hz must be > 0; got {rate_hz}")
    bad = [label for label in labels if not label or any(c in label for c in "\t\r\n")]
    if bad:
        raise ValueError(f"labels must be non-empty without tabs/newlines; got {bad!r}")
    pos = pts.check_positions(labels, positions_world)
    n_frames, n_markers = pos.shape[:2]
    capture = pts.capture_from_world_pos(pos, up, unit)
    valid = np.asarray(np.isfinite(capture).all(axis=-1), dtype=bool)
    out = [
        f"PathFileType\t4\t(X/Y/Z)\t{Path(path).name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate"
        "\tOrigDataStartFrame\tOrigNumFrames",
        f"{rate_hz:g}\t{rate_hz:g}\t{n_frames}\t{n_markers}\t{unit}\t{rate_hz:g}"
        f"\t1\t{n_frames}",
        "\t".join(["Frame#", "Time", *(f"{label}\t\t" for label in labels)]),
        "\t".join(["", "", *(f"X{k}\tY{k}\tZ{k}" for k in range(1, n_markers + 1))]),
        "",
    ]
    for t in range(n_frames):
        fields = [str(t + 1), f"{t / rate_hz:.6f}"]
        for m in range(n_markers):
            if valid[t, m]:
                fields += [f"{v:.10g}" for v in capture[t, m]]
            else:
                fields += ["", "", ""]
        out.append("\t".join(fields))
    Path(path).write_text("\n".join(out) + "\n", encoding="utf-8")
    logger.debug("wrote %s: %d frames x %d markers", path, n_frames, n_markers)
