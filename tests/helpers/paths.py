"""Where the tests find things: the repository, its test data, and the shared real
takes beside the repository (``../shared/datasets``, never copied into it). Every test
and fixture takes these paths from here (importable: ``tests/helpers`` is on pytest's
``pythonpath``), so the shared folder is named once."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]
TEST_DATA = REPO_ROOT / "tests" / "data"
#: ``../shared`` beside the repository; ``RETARGETD_SHARED`` points the suite at another
#: folder (an empty one checks that every test needing the shared data skips, saying
#: why, where it is absent: README "Tests").
SHARED = Path(os.environ.get("RETARGETD_SHARED") or REPO_ROOT.parent / "shared")
#: Real takes live beside the project, never inside it (../shared/datasets).
DATASETS = SHARED / "datasets"
#: C3D and TRC files in the odd variants labs write (../shared/formats).
FORMATS = SHARED / "formats"
IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")


def require(path: Path, what: str) -> Path:
    """``path`` when it exists; else skip (outside CI) or fail (in CI), saying why."""
    if path.exists():
        return path
    reason = f"{what} not found at {path}"
    if IN_CI:
        pytest.fail(f"{reason} (CI=true: nothing may skip)")
    pytest.skip(reason)


def require_datasets() -> Path:
    """The shared datasets folder; skip (outside CI) or fail (in CI) if absent."""
    return require(DATASETS, "shared datasets folder")
