"""Files written whole or not at all: a crash, a full disk or a power loss while a
file is replaced leaves the old file readable (the calibration file, which the live
daemon saves over while a show runs)."""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path


def write_atomic(path: str | Path, data: bytes) -> None:
    """Replace ``path`` with ``data`` all at once: write a temporary file in the same
    folder, flush and fsync it, then ``os.replace`` it over ``path`` (atomic on POSIX
    within one file system) and fsync the folder, so the rename survives a power
    loss. A failure (ENOSPC, EIO, a crash) leaves the old file whole and readable;
    the temporary file is removed.

    Raises:
        OSError: one line, ``cannot write PATH: REASON``, with the errno kept.
    """
    path = Path(path)
    folder = path.parent
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=folder)
    except OSError as exc:
        raise OSError(exc.errno, f"cannot write {path}: {exc.strerror}") from None
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(exc, OSError):
            raise OSError(exc.errno, f"cannot write {path}: {exc.strerror}") from None
        raise
    with contextlib.suppress(OSError):  # not every file system syncs a folder
        dir_fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)
