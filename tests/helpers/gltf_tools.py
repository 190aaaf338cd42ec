"""The two outside checkers of our ``.glb`` files: the Khronos glTF validator (npm
``gltf-validator``, run by ``tools/gltf-validator/validate.mjs`` under Node) and
Blender (headless, its bundled glTF importer). Each is a skip with the reason outside
CI when missing, and a failure in CI (CI=true), like the shared datasets."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest
from paths import IN_CI, REPO_ROOT

#: The Plug-in Gait rig's humanoid names, in rig order (the NPZ's ``bone_humanoid``;
#: all 19 mapped), written out: the oracle the glTF tests check node names against.
PIG_HUMANOID = (
    "Hips", "Spine", "Chest", "Neck", "Head",
    "LeftShoulder", "LeftUpperArm", "LeftLowerArm", "LeftHand",
    "RightShoulder", "RightUpperArm", "RightLowerArm", "RightHand",
    "LeftUpperLeg", "LeftLowerLeg", "LeftFoot",
    "RightUpperLeg", "RightLowerLeg", "RightFoot",
)  # fmt: skip

VALIDATOR_DIR = REPO_ROOT / "tools" / "gltf-validator"
VALIDATOR_SCRIPT = VALIDATOR_DIR / "validate.mjs"
VALIDATOR_PACKAGE = VALIDATOR_DIR / "node_modules" / "gltf-validator" / "package.json"


def _missing(reason: str) -> None:
    if IN_CI:
        pytest.fail(f"{reason} (CI=true: nothing may skip)")
    pytest.skip(reason)


def require_blender() -> str:
    """The ``blender`` executable; skip (outside CI) or fail (in CI) when absent."""
    exe = shutil.which("blender")
    if exe is None:
        _missing("blender not found on PATH (Debian: apt-get install blender)")
    assert exe is not None
    return exe


def validate_glb(path: Path) -> dict[str, Any]:
    """The Khronos glTF validator's report on ``path`` (its JSON, as a dict: read
    ``report["issues"]["numErrors"]`` and ``["messages"]``).

    Skips (outside CI) or fails (in CI) when Node or the validator is not installed:
    ``npm ci --prefix tools/gltf-validator`` installs the pinned version (.ci/run
    does).
    """
    node = shutil.which("node")
    if node is None:
        _missing("node not found on PATH (Debian: apt-get install nodejs npm)")
    if not VALIDATOR_PACKAGE.is_file():
        _missing(
            f"the glTF validator is not installed in {VALIDATOR_DIR} "
            "(npm ci --prefix tools/gltf-validator)"
        )
    assert node is not None
    run = subprocess.run(
        [node, str(VALIDATOR_SCRIPT), str(path)],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert run.returncode == 0, run.stderr[-2000:]
    report: dict[str, Any] = json.loads(run.stdout)
    return report


def issue_summary(report: dict[str, Any]) -> str:
    """``errors/warnings/infos/hints`` and each message's code, for a print or an
    assertion message."""
    issues = report["issues"]
    codes = sorted(
        {f"{m['code']} ({m.get('pointer', '')})" for m in issues["messages"]}
    )
    version = report.get("validatorVersion", "?")
    return (
        f"validator {version}: {issues['numErrors']} errors, "
        f"{issues['numWarnings']} warnings, {issues['numInfos']} infos, "
        f"{issues['numHints']} hints" + (f": {', '.join(codes)}" if codes else "")
    )
