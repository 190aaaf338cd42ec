"""The daemon's output lines stay whole when several threads print (a capture
input's thread and the loop): ``ratelog.print_line``."""

from __future__ import annotations

import io
import sys
import threading
import time

from retargetd.daemon.live.ratelog import print_line


class _SlowStdout(io.StringIO):
    """A stdout whose every write gives the other threads the GIL: any line written
    in two pieces is split by another thread's write."""

    def write(self, s: str) -> int:
        n = super().write(s)
        time.sleep(0)  # a GIL release between writes
        return n


def _spray(out: object, say: object, n_threads: int = 4, n_lines: int = 100) -> str:
    def run(k: int) -> None:
        for i in range(n_lines):
            say(f"thread {k} line {i} " + "x" * 40)  # type: ignore[operator]

    old = sys.stdout
    sys.stdout = out  # type: ignore[assignment]
    try:
        threads = [threading.Thread(target=run, args=(k,)) for k in range(n_threads)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout=30)
    finally:
        sys.stdout = old
    return out.getvalue()  # type: ignore[attr-defined]


def _whole(text: str, n_threads: int = 4, n_lines: int = 100) -> bool:
    lines = text.splitlines()
    want = {f"thread {k} line {i} " + "x" * 40 for k in range(n_threads)
            for i in range(n_lines)}  # fmt: skip
    return len(lines) == len(want) and set(lines) == want


def test_lines_printed_from_several_threads_stay_whole() -> None:
    assert _whole(_spray(_SlowStdout(), print_line))


def test_print_splices_them_which_is_why() -> None:
    """The check above can fail: ``print`` (text, then the newline) splices lines
    on the same stdout."""
    spliced = _spray(_SlowStdout(), lambda line: print(line, flush=True))
    assert not _whole(spliced)
