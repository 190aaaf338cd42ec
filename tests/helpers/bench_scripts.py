"""The scripts of ``bench/`` as modules, for the tests that run their short versions
(importable: ``tests/helpers`` is on pytest's ``pythonpath``)."""

from __future__ import annotations

import importlib.util
import sys
from types import ModuleType

from paths import REPO_ROOT

BENCH = REPO_ROOT / "bench"


def bench_module(name: str) -> ModuleType:
    """``bench/<name>.py`` imported once (its folder on ``sys.path``: the scripts
    import each other)."""
    if str(BENCH) not in sys.path:
        sys.path.insert(0, str(BENCH))
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, BENCH / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module
