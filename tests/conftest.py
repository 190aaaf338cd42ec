"""Shared fixtures: seeded RNG, the shared datasets folder, repository paths."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

REPO_ROOT = Path(__file__).resolve().parent.parent
#: Real takes live beside the project, never inside it (../shared/datasets).
DATASETS = REPO_ROOT.parent / "shared" / "datasets"
IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")


def require_datasets() -> Path:
    """The shared datasets folder; skip (outside CI) or fail (in CI) if absent."""
    if DATASETS.is_dir():
        return DATASETS
    reason = f"shared datasets folder not found at {DATASETS}"
    if IN_CI:
        pytest.fail(f"{reason} (CI=true: nothing may skip)")
    pytest.skip(reason)


@pytest.fixture
def datasets() -> Path:
    """The ``../shared/datasets`` folder (skipped with the reason when absent)."""
    return require_datasets()


@pytest.fixture
def rng() -> np.random.Generator:
    """A seeded random generator."""
    return np.random.default_rng(0)
