"""The progress bar (``retargetd.daemon.progress``): drawn on a terminal, nothing
into a pipe or a file, nothing when disabled (``--quiet``)."""

from __future__ import annotations

import io
import os
import pty

from retargetd.daemon.progress import BAR_WIDTH, Progress


def _read_all(fd: int) -> str:
    os.set_blocking(fd, False)
    out = b""
    while True:
        try:
            chunk = os.read(fd, 4096)
        except (BlockingIOError, OSError):
            break
        if not chunk:
            break
        out += chunk
    return out.decode()


def test_bar_on_a_pty() -> None:
    master, slave = pty.openpty()
    try:
        with (
            open(slave, "w", closefd=False) as tty,
            Progress(10, "solve", unit="frames", stream=tty) as bar,
        ):
            assert bar.active
            for _ in range(10):
                bar.update()
        seen = _read_all(master)
    finally:
        os.close(master)
        os.close(slave)
    assert seen.startswith("\rsolve [")
    assert f"[{'#' * BAR_WIDTH}] 10/10 frames" in seen
    assert seen.rstrip("\r\n").endswith("s\x1b[K") and "\n" in seen


def test_nothing_when_not_a_terminal_or_quiet() -> None:
    pipe = io.StringIO()
    with Progress(5, "solve", stream=pipe) as bar:
        bar.update(5)
    assert not bar.active and pipe.getvalue() == ""
    with Progress(5, "solve", stream=pipe, enabled=True) as bar:  # never into a file
        bar.update(5)
    assert pipe.getvalue() == ""
    master, slave = pty.openpty()
    try:
        with (
            open(slave, "w", closefd=False) as tty,
            Progress(5, "solve", stream=tty, enabled=False) as bar,
        ):
            bar.update(5)
        assert _read_all(master) == ""
    finally:
        os.close(master)
        os.close(slave)
