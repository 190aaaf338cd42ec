"""The live harness's kernel compile over two processes (``compile_kernels`` in
``tests/helpers/live_harness.py``): a failing or hung second process is raised with
its output and never outlives the call."""

from __future__ import annotations

import subprocess
from typing import IO

import live_harness as lh
import pytest


def test_a_failing_part_is_raised_with_its_output() -> None:
    child, log = lh._start_part("no-such-part")
    with log, pytest.raises(RuntimeError, match="exited with 1") as err:
        lh._join_part(child, log, "no-such-part")
    assert "no part 'no-such-part'" in str(err.value)  # the child's traceback


def test_a_hung_part_is_killed_and_raised(monkeypatch: pytest.MonkeyPatch) -> None:
    started: list[subprocess.Popen[bytes]] = []
    start = lh._start_part

    def spy(part: str) -> tuple[subprocess.Popen[bytes], IO[bytes]]:
        child, log = start(part)
        started.append(child)
        return child, log

    in_here: list[str] = []
    monkeypatch.setattr(lh, "_start_part", spy)
    monkeypatch.setattr(lh, "compile_part", in_here.append)
    # shorter than the child's imports alone: it is still running when the wait ends
    monkeypatch.setattr(lh, "PART_TIMEOUT_S", 0.2)
    with pytest.raises(RuntimeError, match=r"fit ran past 0\.2 s"):
        lh.compile_kernels()
    assert [c.returncode for c in started] == [-9]  # killed, and reaped
    assert in_here == ["apart"]  # not "after": the call stopped at the failure
