"""Shared fixtures: seeded RNG, the shared datasets folder, repository paths."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from paths import DATASETS, IN_CI, REPO_ROOT, require_datasets

#: The live-daemon harness's fixtures (``start_daemon``, ``exact_calibration``, ``vmc``,
#: ``osc_source``), the headless browser (``driver``) for every test, and the tests
#: that run with no other beside them under xdist (``alone``); ``tests/helpers`` is on
#: pytest's ``pythonpath``.
pytest_plugins = ["live_harness", "browser", "alone"]

__all__ = ["DATASETS", "IN_CI", "REPO_ROOT", "require_datasets"]


@pytest.fixture
def datasets() -> Path:
    """The ``../shared/datasets`` folder (skipped with the reason when absent)."""
    return require_datasets()


@pytest.fixture
def rng() -> np.random.Generator:
    """A seeded random generator."""
    return np.random.default_rng(0)
