"""A one-line progress bar on stderr, for long offline jobs and the first-start compile.

Drawn only on a terminal: :class:`Progress` writes nothing when its stream is not a TTY
(a pipe, a file, CI's log) or when ``enabled=False`` (a command's ``--quiet``), so
scripted output stays clean. The bar redraws in place (``\\r``) at most
:data:`REDRAW_HZ` times a second and ends its line on :meth:`Progress.close`.

    with Progress(n_frames, "solve", unit="frames") as bar:
        for chunk in chunks:
            ...
            bar.update(len(chunk))
"""

from __future__ import annotations

import sys
import time
from types import TracebackType
from typing import TextIO

#: Redraws per second: fast enough to look live, few enough to cost nothing.
REDRAW_HZ = 10.0
#: Width of the bar, characters.
BAR_WIDTH = 30


def on_terminal(stream: TextIO | None = None) -> bool:
    """True when ``stream`` (default stderr) is a terminal."""
    s = sys.stderr if stream is None else stream
    try:
        return bool(s.isatty())
    except (AttributeError, ValueError):  # closed or not a file
        return False


class Progress:
    """A progress bar over ``total`` units (see the module docstring).

    Args:
        total: units of work in all (> 0; 0 draws a bar that is full at once).
        desc: what is being done (a word or two: "solve", "checks").
        unit: the units' name ("frames", "steps").
        stream: where to draw (default ``sys.stderr``).
        enabled: False draws nothing (``--quiet``); None: only on a terminal.
    """

    def __init__(
        self,
        total: int,
        desc: str,
        *,
        unit: str = "",
        stream: TextIO | None = None,
        enabled: bool | None = None,
    ) -> None:
        self.stream = sys.stderr if stream is None else stream
        self.active = on_terminal(self.stream) if enabled is None else enabled
        if enabled and not on_terminal(self.stream):
            self.active = False  # never into a pipe or a file
        self.total = max(int(total), 0)
        self.desc = desc
        self.unit = unit
        self.done = 0
        self._t0 = time.monotonic()
        self._last = 0.0
        self._closed = False
        if self.active:
            self._draw()

    def update(self, n: int = 1) -> None:
        """Count ``n`` more units done (redraws at most :data:`REDRAW_HZ`)."""
        self.done = min(self.done + int(n), self.total) if self.total else self.done
        if not self.active:
            return
        now = time.monotonic()
        if now - self._last >= 1.0 / REDRAW_HZ or self.done >= self.total:
            self._draw()

    def set_description(self, desc: str) -> None:
        """Change what the bar says it is doing (redrawn at once)."""
        self.desc = desc
        if self.active:
            self._draw()

    def _draw(self) -> None:
        self._last = time.monotonic()
        frac = self.done / self.total if self.total else 1.0
        n = int(BAR_WIDTH * frac)
        unit = f" {self.unit}" if self.unit else ""
        self.stream.write(
            f"\r{self.desc} [{'#' * n}{'.' * (BAR_WIDTH - n)}] "
            f"{self.done}/{self.total}{unit} {self._last - self._t0:.1f} s\x1b[K"
        )
        self.stream.flush()

    def close(self) -> None:
        """Finish the line (once)."""
        if self._closed:
            return
        self._closed = True
        if self.active:
            self._draw()
            self.stream.write("\n")
            self.stream.flush()

    def __enter__(self) -> Progress:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
