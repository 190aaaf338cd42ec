"""Rate limits for the loop: log lines per reason and commands per interval.

A flood of one kind of message (a bundle of 200 ``/VMC/Ext/Set/Calib/Ready``, a
stream of malformed packets) must neither grow the log without bound nor block the
loop: :class:`RateLimitedLog` prints a reason's first line at once, counts the
repeats, and prints one summary with the count at most once per interval;
:class:`RateLimiter` lets a costly command (reload, calibrate) through at most once
per interval and counts what it turned away. :func:`print_line` is the daemon's
default ``out``: whole lines, whichever thread prints them.
"""

from __future__ import annotations

import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass

_PRINT_LOCK = threading.Lock()


def print_line(line: str) -> None:
    """Write ``line`` and its newline to stdout in one write, flushed, under a lock.

    ``print`` writes the text and the newline separately: a capture input's thread
    (QTM's, NatNet's) saying something while the loop announces its endpoints could
    splice two lines into one (``listening on ...: zmq poses`` ran into a ``qtm:``
    line, and a test waiting for that endpoint never saw it).
    """
    with _PRINT_LOCK:
        sys.stdout.write(line + "\n")
        sys.stdout.flush()


@dataclass(slots=True)
class _Reason:
    printed_ns: int  # when its last line (first occurrence or summary) was printed
    suppressed: int = 0  # repeats since then
    last: str = ""  # the latest suppressed line


class RateLimitedLog:
    """Per-reason rate-limited lines: the first at once, then a periodic summary.

    Args:
        out: where lines go (the daemon's ``out``).
        interval_s: the least time between two lines of one reason.
    """

    def __init__(self, out: Callable[[str], None], interval_s: float) -> None:
        self.out = out
        self.interval_ns = int(interval_s * 1e9)
        self._reasons: dict[str, _Reason] = {}
        self.suppressed_total = 0

    def line(self, reason: str, text: str, now_ns: int) -> None:
        """Print ``text`` unless ``reason`` printed within the interval (then count
        it; :meth:`flush` prints the summary)."""
        r = self._reasons.get(reason)
        if r is None:
            self._reasons[reason] = _Reason(now_ns)
            self.out(text)
            return
        if r.suppressed == 0 and now_ns - r.printed_ns >= self.interval_ns:
            r.printed_ns = now_ns
            self.out(text)
            return
        r.suppressed += 1
        r.last = text
        self.suppressed_total += 1

    def flush(self, now_ns: int) -> None:
        """Print one summary per reason whose repeats are due (call it often)."""
        for reason, r in self._reasons.items():
            if r.suppressed and now_ns - r.printed_ns >= self.interval_ns:
                seconds = (now_ns - r.printed_ns) * 1e-9
                self.out(
                    f"{reason}: {r.suppressed} more in the last {seconds:.0f} s "
                    f"(latest: {r.last})"
                )
                r.printed_ns, r.suppressed, r.last = now_ns, 0, ""


class RateLimiter:
    """At most one accepted call per interval; the rest counted.

    Args:
        interval_s: the least time between two accepted calls.
    """

    def __init__(self, interval_s: float) -> None:
        self.interval_ns = int(interval_s * 1e9)
        self._last_ns: int | None = None
        self.limited = 0

    def allow(self, now_ns: int) -> bool:
        """True (and the interval restarts) when the last accepted call is at least
        the interval ago; else False, counted in ``limited``."""
        if self._last_ns is not None and now_ns - self._last_ns < self.interval_ns:
            self.limited += 1
            return False
        self._last_ns = now_ns
        return True


class OncePer:
    """A line per key at most once per interval (the counters carry the numbers;
    the log only says that it happens): shared by the inputs and the capture input,
    so one key is one line however many parts say it.

    Args:
        interval_ns: the least time between two lines of one key.
    """

    def __init__(self, interval_ns: int) -> None:
        self.interval_ns = interval_ns
        self._after_ns: dict[str, int] = {}

    def due(self, key: str, t_ns: int) -> bool:
        """True (and the key's next line held back an interval) when ``key`` may
        say its line at ``t_ns``."""
        if t_ns < self._after_ns.get(key, 0):
            return False
        self._after_ns[key] = t_ns + self.interval_ns
        return True
