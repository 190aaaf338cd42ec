"""Tests that run with no other test beside them, under pytest-xdist (a plugin:
``tests/conftest.py``'s ``pytest_plugins``).

The suite runs on two xdist workers (pyproject's ``addopts``: ``-n 2``), so every test
shares the machine's two cores with the other worker's test. A test marked
``@pytest.mark.alone`` (the reason beside each mark) measures time (a pose gap, a
latency, a rate) or needs the CPU it would have alone: while it runs (setup, call
and teardown) the other worker runs no test, and it starts only once the other
worker's current test has ended. The workers share a readers-writer lock, two
``flock`` files in the run's base temporary folder (each worker's own
``popen-gwN`` is under it): every test holds ``room`` shared, an ``alone`` test
holds it exclusive; a worker waiting for it exclusive first holds ``turnstile``,
which every test passes through before taking ``room``, so the other worker cannot
keep ``room`` shared test after test and starve it. The lock is taken outside
pytest-timeout's timer (``tryfirst``): a test's wait for it is not its own time.

Without xdist (``-n 0``) a test runs alone anyway and nothing is locked.
"""

from __future__ import annotations

import fcntl
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

#: ``name -> descriptor`` of this worker's lock files, opened on first use.
_FDS: dict[str, int] = {}


def _lock_fd(config: pytest.Config, name: str) -> int:
    fd = _FDS.get(name)
    if fd is None:
        # xdist gives each worker ``<the controller's basetemp>/popen-gwN``
        folder = Path(config.option.basetemp).parent
        fd = os.open(folder / f"{name}.lock", os.O_RDWR | os.O_CREAT, 0o600)
        _FDS[name] = fd
    return fd


def is_worker(config: pytest.Config) -> bool:
    """Whether this process is an xdist worker (xdist gives those ``workerinput``)."""
    return hasattr(config, "workerinput")


@pytest.hookimpl(wrapper=True, tryfirst=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: Any) -> Iterator[object]:
    if not is_worker(item.config) or item.config.option.basetemp is None:
        return (yield)
    room = _lock_fd(item.config, "room")
    turnstile = _lock_fd(item.config, "turnstile")
    if item.get_closest_marker("alone") is not None:
        fcntl.flock(turnstile, fcntl.LOCK_EX)
        try:
            fcntl.flock(room, fcntl.LOCK_EX)
            try:
                return (yield)
            finally:
                fcntl.flock(room, fcntl.LOCK_UN)
        finally:
            fcntl.flock(turnstile, fcntl.LOCK_UN)
    fcntl.flock(turnstile, fcntl.LOCK_SH)
    try:
        fcntl.flock(room, fcntl.LOCK_SH)
    finally:
        fcntl.flock(turnstile, fcntl.LOCK_UN)
    try:
        return (yield)
    finally:
        fcntl.flock(room, fcntl.LOCK_UN)
