"""numba's cache locked between processes (``protocols/cache_lock.py``): two processes
saving one function for two signatures at once, in the order that pairs a signature
with the other's machine code in numba's unlocked cache, leave both loadable and right.

Without the lock (``cache_lock.install`` made a no-op) this test failed: the fresh
process loaded the ``float64`` code for the ``int64`` array (README "A cold run's
compiles")."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np

from retargetd.protocols import cache_lock, kernels

HELPERS = Path(__file__).resolve().parents[1] / "helpers"
RACY = """
import numba


@numba.njit(cache=True)
def total(a):
    return a.sum()
"""


def _start(role: str, src: Path, sync: Path, cache: Path) -> subprocess.Popen[str]:
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache))
    return subprocess.Popen(
        [sys.executable, str(HELPERS / "cache_race.py"), str(src), str(sync), role],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip


def _result(proc: subprocess.Popen[str]) -> dict[str, Any]:
    try:
        stdout, stderr = proc.communicate(timeout=90)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, stderr[-4000:]
    got: dict[str, Any] = json.loads(stdout.strip().splitlines()[-1])
    return got


def test_the_lock_is_installed_with_the_kernels() -> None:
    assert kernels.__name__ and cache_lock.installed()
    assert cache_lock.install()  # (again: idempotent)


def test_two_signatures_saved_at_once_load_back_right(tmp_path: Path) -> None:
    src, sync, cache = tmp_path / "src", tmp_path / "sync", tmp_path / "cache"
    for d in (src, sync, cache):
        d.mkdir()
    (src / "racy.py").write_text(RACY)
    savers = {role: _start(role, src, sync, cache) for role in ("float", "int")}
    saved = {role: _result(proc) for role, proc in savers.items()}
    for got in saved.values():
        assert got["locked"], got
        assert got["misses"] == 1, got  # each compiled and saved its own
    # both savers went through their hooks (else the order proves nothing)
    assert {p.name for p in sync.iterdir()} >= {
        f"{r}.{step}" for r in ("float", "int") for step in ("loaded", "saved")
    }
    check = _result(_start("check", src, sync, cache))
    want = {"float": float(np.sum([0.5, 1.5, 2.5, 3.5])), "int": 10}
    assert check["total"] == want, check
    assert (check["hits"], check["misses"]) == (2, 0), check  # both from the cache
