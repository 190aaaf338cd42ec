"""Packaging contracts: the package list matches the folders, imports flow one way,
the console script answers ``--version`` and ``--help``."""

from __future__ import annotations

import ast
import subprocess
import sys
import tomllib
from importlib.metadata import version
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parent.parent
FOLDERS = {
    "daemon": "retargetd.daemon",
    "protocols": "retargetd.protocols",
    "replay": "retargetd.replay",
}
# protocols imports neither sibling; replay may import protocols; daemon both.
ALLOWED = {
    "protocols": {"protocols"},
    "replay": {"protocols", "replay"},
    "daemon": {"protocols", "replay", "daemon"},
}


def _pyproject() -> dict:
    return tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())


def test_package_list_matches_folders() -> None:
    found = set()
    for folder, name in FOLDERS.items():
        for init in (REPO_ROOT / folder).rglob("__init__.py"):
            rel = init.parent.relative_to(REPO_ROOT / folder)
            found.add(".".join([name, *rel.parts]))
    listed = set(_pyproject()["tool"]["setuptools"]["packages"])
    assert found == listed, (
        f"missing from pyproject: {found - listed}; stale: {listed - found}"
    )


def test_package_guards() -> None:
    for folder, name in FOLDERS.items():
        text = (REPO_ROOT / folder / "__init__.py").read_text()
        assert f'if __name__ != "{name}":' in text
    # Importing the repository folder directly is refused with a clear message.
    proc = subprocess.run(
        [sys.executable, "-c", "import protocols"],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode != 0
    assert "import as retargetd.protocols" in proc.stderr


@pytest.mark.parametrize("folder", sorted(FOLDERS))
def test_import_direction(folder: str) -> None:
    bad = []
    for path in (REPO_ROOT / folder).rglob("*.py"):
        tree = ast.parse(path.read_text(), filename=str(path))
        for node in ast.walk(tree):
            names: list[str] = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
            elif isinstance(node, ast.ImportFrom) and node.level:
                bad.append(
                    f"{path}: relative import (use absolute retargetd.* imports)"
                )
            for mod in names:
                parts = mod.split(".")
                if parts[0] in FOLDERS:
                    bad.append(f"{path}: imports top-level {mod!r}")
                if (
                    parts[0] == "retargetd"
                    and len(parts) > 1
                    and parts[1] not in ALLOWED[folder]
                ):
                    bad.append(f"{path}: {folder} must not import {mod}")
    assert not bad, "\n".join(bad)


def test_console_script_version_and_help() -> None:
    exe = Path(sys.executable).parent / "retargetd"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "retargetd.daemon"]
    proc = subprocess.run(
        [*cmd, "--version"], capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == f"retargetd {version('mocap-retargetd')}"
    proc = subprocess.run([*cmd, "--help"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert "usage: retargetd" in proc.stdout


def test_python_dash_m_matches_console_script() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "retargetd.daemon", "--version"],
        capture_output=True,
        text=True,
        timeout=60,
        cwd="/",
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("retargetd ")
