"""Load any supported take file into one :class:`~retargetd.replay.take.Take`.

:func:`load_take` dispatches on the file suffix (case-insensitive): ``.c3d`` to
:func:`retargetd.replay.c3d.read_c3d`, ``.trc`` to
:func:`retargetd.replay.trc.read_trc`.
``units``, ``up_axis`` and ``rate_hz`` are explicit overrides (the CLI's
``--take-units``, ``--take-up`` and ``--take-rate``); without them each reader takes
the file's own values or the format's default and records where each came from
(``Take.units_source``, ``Take.up_source``, ``Take.rate_source``).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from pathlib import Path

from retargetd.replay.c3d import read_c3d
from retargetd.replay.recording import read_mcap_take
from retargetd.replay.take import Take, TakeError
from retargetd.replay.trc import read_trc

logger = logging.getLogger(__name__)

_Reader = Callable[..., Take]
#: Suffix (lower case) -> reader.
READERS: dict[str, _Reader] = {
    ".c3d": read_c3d,
    ".trc": read_trc,
    ".mcap": read_mcap_take,
}
#: Suffixes whose reader takes a frame-rate override (``--take-rate``).
RATE_READERS = (".c3d", ".trc")


def load_take(
    path: str | os.PathLike[str],
    *,
    subject: str | None = None,
    units: str | None = None,
    up_axis: str | None = None,
    rate_hz: float | None = None,
) -> Take:
    """Load a take file (C3D or TRC) in world metres.

    Args:
        path: the take file.
        subject: the subject to load; required when the file holds several.
        units: override of the file's length unit ("mm", "m" ...).
        up_axis: override of the file's up axis ("+Z", "+Y" ...).
        rate_hz: override of the file's frame rate, Hz (``--take-rate``; C3D and
            TRC only); needed when the file's rate is 0.

    Returns:
        The take (markers (T, M, 3) float64 metres, world frame, NaN rows = occluded).

    Raises:
        TakeError: missing file, unsupported suffix, or any reader error; one line
            naming the file.
    """
    file = Path(path)
    reader = READERS.get(file.suffix.lower())
    if reader is None:
        raise TakeError(
            f"take {file}: unsupported format {file.suffix or '(no suffix)'!r}; "
            f"supported: {', '.join(sorted(READERS))}"
        )
    if not file.is_file():
        raise TakeError(f"take {file}: no such file")
    if rate_hz is None:
        take = reader(file, subject=subject, units=units, up_axis=up_axis)
    elif file.suffix.lower() in RATE_READERS:
        take = reader(
            file, subject=subject, units=units, up_axis=up_axis, rate_hz=rate_hz
        )
    else:
        raise TakeError(
            f"take {file}: --take-rate applies to {', '.join(RATE_READERS)} takes; "
            "a recording keeps its own timestamps"
        )
    logger.info(
        "loaded %s: %d markers x %d frames at %g Hz (%s, %s up)",
        file,
        take.n_markers,
        take.n_frames,
        take.rate_hz,
        take.units,
        take.up_axis,
    )
    for repair in take.repairs:
        # `take info` prints these; other commands keep them in the log.
        logger.info("%s (%s): %s", file, take.reader, repair)
    return take
