"""A reload's files read off the loop (issue 30 item 6): ``ctl reload``, show control's
``/rtd/reload`` and the console's button re-read each performer's rig and calibration
files and the config file's ``[[pipeline]]``. Parsing and checking them took 23-70 ms
(measured in the loop, the soak's ``control.reload`` stall), so the loop hands
:func:`read_files` to a worker thread (``rebuild.Build``) with what it needs, taken
when the reload was asked for (:class:`ReloadRequest`: the paths, the running
calibration, the digest of the files the last reload read), and goes on solving; the
first loop pass that finds it done swaps in what it read (``Performers.end_reload``),
whole and validated, or keeps everything and answers the file's reason. ``ctl
reload`` is answered then (its reply waits; the REP socket takes no other request
meanwhile), show control's and the console's outcome is printed then.

:func:`read_files` reads only its arguments: any thread may call it.
"""

from __future__ import annotations

import contextlib
import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from retargetd.daemon.body.calibration import load_calibration
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.body.solve import BodySolver
from retargetd.daemon.files import MAX_TEXT_BYTES
from retargetd.daemon.live.config import DaemonConfig, check_pipeline
from retargetd.daemon.post.pivot import spine_stage


@dataclass(frozen=True, slots=True, kw_only=True)
class ReloadRequest:
    """One performer's reload, as things were when it was asked for (the loop)."""

    rig_path: str  # its config's rig (a shipped name or a path)
    calibration_path: str  # its config's calibration file ("" none: keep its own)
    rig: Any  # its rig then
    calibration: Any  # its calibration then (kept when no file is configured)
    last_digest: bytes | None  # the files' digest at the last reload of these objects


@dataclass(frozen=True, slots=True, kw_only=True)
class ReloadResult:
    """What :func:`read_files` found for one performer."""

    digest: bytes
    unchanged: bool = False  # the same files as the last reload: nothing parsed
    error: str = ""  # why the files were refused ("" read and checked)
    rig: Any = None
    calibration: Any = None
    stages: Any = ()  # the config file's [[pipeline]] now


def read_files(
    requests: tuple[ReloadRequest, ...],
    config_path: str | Path | None,
    config: DaemonConfig,
    target: Any,
) -> tuple[ReloadResult, ...]:
    """Read and check each performer's files (the worker's job).

    Args:
        requests: one per performer.
        config_path: the config file (its ``[[pipeline]]`` re-read; None: keep
            ``config``'s).
        config: the running configuration.
        target: the target skeleton (a new rig's spine must fit it).

    Returns:
        One result per request: unchanged, refused with the reason, or the new rig,
        calibration and stages.
    """
    stages: Any = None
    out = []
    for req in requests:
        digest = files_digest(req.rig_path, req.calibration_path, config_path)
        if req.last_digest is not None and req.last_digest == digest:
            out.append(ReloadResult(digest=digest, unchanged=True))
            continue
        try:
            rig = load_rig(req.rig_path)
            cal = (
                load_calibration(req.calibration_path)
                if req.calibration_path
                else req.calibration
            )
            if cal is not None:
                BodySolver(rig, cal, ())  # checks the calibration fits the rig
            if stages is None:
                stages = config.pipeline
                if config_path:  # the file's [[pipeline]] as it is now
                    stages = DaemonConfig.from_toml(config_path).pipeline
            check_pipeline(stages, rig, str(config_path or "config"))
            spine_stage(config.target, target, rig)  # its spine fits
        except ValueError as exc:
            out.append(ReloadResult(digest=digest, error=str(exc)))
            continue
        out.append(ReloadResult(digest=digest, rig=rig, calibration=cal, stages=stages))
    return tuple(out)


def files_digest(*paths: Any) -> bytes:
    """SHA-256 over the bytes of every file named (a shipped rig's name, an empty or
    None path, and a file that cannot be read count as their names: the reload that
    follows then parses and says what is wrong)."""
    h = hashlib.sha256()
    for p in paths:
        h.update(str(p).encode() + b"\0")
        with contextlib.suppress(OSError, ValueError):
            if p and Path(p).is_file():  # (at most MAX_TEXT_BYTES: as the readers)
                with open(p, "rb") as fh:
                    h.update(fh.read(MAX_TEXT_BYTES + 1))
    return h.digest()
