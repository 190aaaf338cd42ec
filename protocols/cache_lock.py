"""A lock between processes around numba's on-disk cache of compiled kernels.

numba (0.60-0.68, ``numba.core.caching.IndexDataCacheFile``) saves a compiled
signature of a function by loading the function's index (``<fn>.nbi``: signature ->
data file), taking the first ``<fn>.<n>.nbc`` the index does not name, writing the
index, then the data file; nothing holds off another process meanwhile. Two processes
that save one function for two signatures at once (two daemons starting on a fresh
cache, the tests' kernel compile split over two cores) can both take ``<fn>.1.nbc``:
the index then names one signature and the file holds the other's machine code, which
numba loads without checking its signature (wrong results, or a crash). Saves of one
signature are harmless (the same code, whichever lands).

:func:`install` wraps ``save`` and ``flush`` in an exclusive ``flock`` on
``<fn>.nbi.lock`` beside the index and ``load`` in a shared one. numba writes each file
to a temporary name and ``os.replace``s it into place, so an unlocked reader sees a
whole old or whole new index; the shared lock keeps it from reading an index whose new
data file is not yet written (numba then compiles again), or a data file a save
replaced between its index read and its data read. The lock file's descriptor is
closed when a process dies, so a killed compile never leaves the lock held. A lock that
stays held past :data:`WAIT_S` (a process stopped mid-save) is given up on: the save is
skipped (the code stays compiled in memory) and the load misses (the kernel compiles),
neither of which can pair a signature with another's code.
"""

from __future__ import annotations

import contextlib
import fcntl
import functools
import os
import time
from collections.abc import Callable, Iterator
from typing import Any

from numba.core import caching

#: How long a save or a load waits for another process's hold on one function's
#: cache: a save writes two files of at most a few MB (milliseconds); this only
#: bounds a holder that stopped.
WAIT_S = 60.0
_POLL_S = 0.002
_MARK = "_retargetd_cache_lock"


@contextlib.contextmanager
def _held(index_path: str, exclusive: bool) -> Iterator[bool]:
    """Hold ``index_path + ".lock"``; yields whether it is held (False: the folder
    is missing or read-only, where no save can race, or the wait ran out)."""
    try:
        fd = os.open(index_path + ".lock", os.O_RDWR | os.O_CREAT, 0o666)
    except OSError:
        yield False
        return
    try:
        op = (fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH) | fcntl.LOCK_NB
        deadline = time.monotonic() + WAIT_S
        while True:
            try:
                fcntl.flock(fd, op)
                break
            except BlockingIOError:
                if time.monotonic() > deadline:
                    yield False
                    return
                time.sleep(_POLL_S)
        yield True
    finally:
        os.close(fd)  # (releases the lock)


def _exclusive(method: Callable[..., Any]) -> Callable[..., Any]:
    @functools.wraps(method)
    def save(self: Any, *args: Any) -> None:
        with _held(self._index_path, exclusive=True) as held:
            if held:
                method(self, *args)

    return save


def _shared(method: Callable[..., Any]) -> Callable[..., Any]:
    @functools.wraps(method)
    def load(self: Any, *args: Any) -> Any:
        if not os.path.exists(self._index_path):
            return None  # nothing saved yet (numba's own answer: a miss)
        with _held(self._index_path, exclusive=False) as held:
            return method(self, *args) if held else None

    return load


def install() -> bool:
    """Lock numba's cache saves and loads in this process (idempotent). False when
    this numba's cache has no ``IndexDataCacheFile`` with ``save``, ``load`` and
    ``flush`` (another layout: nothing is patched; the test of this module fails)."""
    cls: Any = getattr(caching, "IndexDataCacheFile", None)
    if cls is None or not all(hasattr(cls, n) for n in ("save", "load", "flush")):
        return False
    if not getattr(cls, _MARK, False):
        cls.save = _exclusive(cls.save)
        cls.flush = _exclusive(cls.flush)
        cls.load = _shared(cls.load)
        setattr(cls, _MARK, True)
    return True


def installed() -> bool:
    """Whether :func:`install` has patched numba's cache in this process."""
    return bool(getattr(getattr(caching, "IndexDataCacheFile", None), _MARK, False))
