"""Real file systems that fail, for the recording tests: a tiny tmpfs that fills up
(``ENOSPC`` from the kernel's ``write``) and a read-only one (``EROFS`` on create).

Mounting needs root (``CAP_SYS_ADMIN``); CI runs as root. Elsewhere the fixtures
skip, printing why; with ``CI=true`` they fail instead (nothing may skip in CI).
A tmpfs rather than a loop-mounted ext4 image: no image file, no loop device, and
the same kernel ``ENOSPC`` on a full file system.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest
from paths import IN_CI


def _unavailable(reason: str) -> None:
    if IN_CI:
        pytest.fail(f"{reason} (CI=true: nothing may skip)")
    pytest.skip(reason)


@contextlib.contextmanager
def mounted_tmpfs(
    where: Path, size_bytes: int, *, read_only: bool = False
) -> Iterator[Path]:
    """A tmpfs of ``size_bytes`` mounted at ``where`` (created), unmounted after.

    Skips (outside CI) when not root or when ``mount`` refuses.
    """
    if os.geteuid() != 0:
        _unavailable("mounting a small tmpfs needs root (CI runs as root)")
    mount = shutil.which("mount")
    umount = shutil.which("umount")
    if mount is None or umount is None:
        _unavailable("mount/umount not found")
    assert mount is not None and umount is not None
    where.mkdir(parents=True, exist_ok=True)
    opts = f"size={size_bytes},mode=0755" + (",ro" if read_only else "")
    done = subprocess.run(
        [mount, "-t", "tmpfs", "-o", opts, "tmpfs", str(where)],
        capture_output=True, text=True, timeout=30,
    )  # fmt: skip
    if done.returncode != 0:
        _unavailable(f"cannot mount a tmpfs: {done.stderr.strip()}")
    try:
        yield where
    finally:
        subprocess.run([umount, "-l", str(where)], capture_output=True, timeout=30)
