"""One side of ``tests/protocols/test_cache_lock.py``: a fresh interpreter that
imports the package (which locks numba's cache, ``protocols/cache_lock.py``), then
compiles ``total`` from the module ``racy`` for one array type and saves it to
``$NUMBA_CACHE_DIR``, or loads both types' code back (``check``).

``python cache_race.py SRC SYNC ROLE``: ``SRC`` holds ``racy.py``; ``SYNC`` is a folder
the two savers signal each other through (empty files); ``ROLE`` is ``float``, ``int``
or ``check``. The two savers meet before their saves, then force the one order in
which numba's unlocked save pairs a signature with the other's code: ``float`` loads
the index, ``int`` loads it, ``float`` writes it, ``int`` writes it and its data,
``float`` writes its data. Under the lock the second saver cannot load the index until
the first has saved, so each wait for a step the other cannot take runs out
(:data:`STEP_S`) and the saves run one after the other. Prints a JSON line.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from numba.core import caching

from retargetd.protocols import cache_lock, kernels  # noqa: F401 (installs the lock)

#: How long a saver waits for the other's step: both have met before saving, so an
#: unlocked one takes it within milliseconds.
STEP_S = 1.0
#: How long a saver waits for the other to be ready to save (its import and compile).
MEET_S = 60.0
ARRAYS = {
    "float": np.array([0.5, 1.5, 2.5, 3.5]),
    "int": np.array([1, 2, 3, 4], dtype=np.int64),
}


def _signal(sync: Path, name: str) -> None:
    (sync / name).touch()


def _wait(sync: Path, name: str, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while not (sync / name).exists():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.001)
    return True


def _hook(sync: Path, role: str) -> None:
    """Make this saver take its steps in the racy order (module docstring)."""
    other = "int" if role == "float" else "float"
    cls: Any = caching.IndexDataCacheFile
    load_index, save_index, save_data = cls._load_index, cls._save_index, cls._save_data
    cache: Any = caching.Cache
    save_overload = cache.save_overload

    def meet(self: Any, *args: Any) -> None:
        _signal(sync, f"{role}.ready")
        if not _wait(sync, f"{other}.ready", MEET_S):
            raise TimeoutError(f"the {other} saver never got ready")
        save_overload(self, *args)

    def hooked_load_index(self: Any) -> Any:
        got = load_index(self)
        if sys._getframe(1).f_code.co_name == "save":  # (not a load's)
            _signal(sync, f"{role}.loaded")
            _wait(sync, "int.loaded" if role == "float" else "float.indexed", STEP_S)
        return got

    def hooked_save_index(self: Any, overloads: Any) -> None:
        save_index(self, overloads)
        _signal(sync, f"{role}.indexed")

    def hooked_save_data(self: Any, name: str, data: Any) -> None:
        if role == "float":
            _wait(sync, "int.saved", STEP_S)
        save_data(self, name, data)
        _signal(sync, f"{role}.saved")

    cache.save_overload = meet
    cls._load_index = hooked_load_index
    cls._save_index = hooked_save_index
    cls._save_data = hooked_save_data


def main() -> None:
    src, sync, role = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3]
    sys.path.insert(0, str(src))
    if role != "check":
        _hook(sync, role)
    import racy

    types = list(ARRAYS) if role == "check" else [role]
    got = {t: racy.total(ARRAYS[t]) for t in types}
    stats = racy.total.stats
    print(
        json.dumps(
            {
                "locked": cache_lock.installed(),
                "total": got,
                "hits": sum(stats.cache_hits.values()),
                "misses": sum(stats.cache_misses.values()),
            }
        )
    )


if __name__ == "__main__":
    main()
