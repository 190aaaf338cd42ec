"""Files read totally and written whole.

Reading (:func:`read_text`, :func:`loads_toml`, :func:`loads_json`): every text file
retargetd reads (config, rig, face config, calibration, batch manifest, pipeline and
target files) goes through these, so a file of any size, encoding or depth gives one
:class:`FileFormatError` line, never a traceback: the CLI exits 2 with it and the
daemon's reload answers it and keeps its running configuration (issue 30: a 1 KB
config of 500 nested arrays used to raise ``RecursionError`` out of ``tomllib``,
print 3,002 lines and, reloaded from show control, kill the daemon). Bounds:

- :data:`MAX_TEXT_BYTES` 16 MiB: the largest file of these a user writes is a batch
  manifest (one line per take); a calibration is ~50 KB, a rig ~30 KB, so 16 MiB is
  over 300 times the largest and still read in well under a second;
- :data:`MAX_DEPTH` 32 levels of tables and arrays: the deepest shipped file is 5
  levels (the ``plug-in-gait`` and ``opensim-gait2354`` rigs; a calibration with
  functional joints is 5 too); checked without recursion, so nothing downstream
  recurses past it.

Writing (:func:`write_atomic`): a crash, a full disk or a power loss while a file is
replaced leaves the old file readable (the calibration file, which the live daemon
saves over while a show runs).
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Any

#: The largest text file read, bytes (module docstring).
MAX_TEXT_BYTES = 16 * 1024 * 1024
#: The deepest nesting of tables and arrays accepted (module docstring).
MAX_DEPTH = 32


class FileFormatError(ValueError):
    """A file that cannot be read as what it should be: one line, no path (the
    caller prefixes it)."""


def read_text(path: str | Path, what: str = "file") -> str:
    """The file's UTF-8 text; ``what`` it should be names it in the errors
    ("config", "rig file" ...).

    Raises:
        FileFormatError: unreadable, larger than :data:`MAX_TEXT_BYTES`, or not UTF-8.
    """
    try:
        with open(path, "rb") as fh:
            data = fh.read(MAX_TEXT_BYTES + 1)
    except OSError as exc:
        raise FileFormatError(f"cannot read {what}: {exc.strerror}") from None
    if len(data) > MAX_TEXT_BYTES:
        raise FileFormatError(
            f"larger than {MAX_TEXT_BYTES >> 20} MiB: not a {what} (too large to read)"
        )
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise FileFormatError(
            f"not UTF-8 text (byte 0x{data[exc.start]:02x} at offset {exc.start})"
        ) from None


def check_depth(doc: Any) -> None:
    """Raise :class:`FileFormatError` when ``doc`` nests dicts and lists deeper than
    :data:`MAX_DEPTH` (walked without recursion)."""
    stack: list[tuple[Any, int]] = [(doc, 1)]
    while stack:
        node, depth = stack.pop()
        children = (
            node.values() if isinstance(node, dict)
            else node if isinstance(node, list) else ()
        )  # fmt: skip
        for child in children:
            if isinstance(child, dict | list):
                if depth + 1 > MAX_DEPTH:
                    raise FileFormatError(
                        f"nested more than {MAX_DEPTH} levels deep (tables and arrays)"
                    )
                stack.append((child, depth + 1))


def loads_toml(text: str) -> dict[str, Any]:
    """Parse TOML text, any depth.

    Raises:
        FileFormatError: not valid TOML, or nested past :data:`MAX_DEPTH`.
    """
    doc: dict[str, Any] = _loads(tomllib.loads, tomllib.TOMLDecodeError, "TOML", text)
    return doc


def loads_json(text: str) -> Any:
    """Parse JSON text, any depth.

    Raises:
        FileFormatError: not valid JSON, or nested past :data:`MAX_DEPTH`.
    """
    return _loads(json.loads, json.JSONDecodeError, "JSON", text)


def _loads(
    parse: Callable[[str], Any], invalid: type[Exception], kind: str, text: str
) -> Any:
    """``parse(text)``, its ``invalid`` error and a parser's ``RecursionError`` as
    one :class:`FileFormatError` line, then the depth checked."""
    try:
        doc = parse(text)
    except invalid as exc:
        raise FileFormatError(f"not valid {kind}: {exc}") from None
    except RecursionError:
        raise FileFormatError(
            f"nested more than {MAX_DEPTH} levels deep (tables and arrays)"
        ) from None
    check_depth(doc)
    return doc


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
