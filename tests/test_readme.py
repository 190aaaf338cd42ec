"""The README's two fresh-machine commands: CI runs the test one; the main one runs."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from retargetd.daemon.cli.main import main

REPO_ROOT = Path(__file__).resolve().parent.parent


def _first_commands() -> list[str]:
    text = (REPO_ROOT / "README.md").read_text()
    blocks = re.findall(r"```sh\n(.*?)```", text, flags=re.S)
    return [blocks[0].strip(), blocks[1].strip()]


def test_readme_opens_with_two_single_line_commands() -> None:
    main_cmd, test_cmd = _first_commands()
    assert "\n" not in main_cmd and "\n" not in test_cmd
    assert "pip install" in main_cmd and "pytest" in test_cmd


def test_ci_runs_the_readme_test_command_verbatim() -> None:
    _, test_cmd = _first_commands()
    ci_lines = (REPO_ROOT / ".ci" / "run").read_text().splitlines()
    assert test_cmd in ci_lines


def test_readme_main_command_runs(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    main_cmd, _ = _first_commands()
    job = next(p for p in main_cmd.split("&&") if p.strip().startswith("retargetd"))
    argv = shlex.split(job)
    assert argv[:2] == ["retargetd", "demo"]
    # The README runs it for longer; 3 s shows the same path (calibration, streaming).
    argv[argv.index("--seconds") + 1] = "3"
    # Ephemeral ports, so parallel test runs never collide on the defaults.
    config = tmp_path / "ports.toml"
    config.write_text(
        "[input.osc]\nport = 0\n[input.zmq]\nendpoint = 'tcp://127.0.0.1:*'\n"
        "[output.pose]\nendpoint = 'tcp://127.0.0.1:*'\n"
        "[control]\nendpoint = 'tcp://127.0.0.1:*'\n[show_control]\nport = 0\n"
    )
    argv += ["--config", str(config), "--console", "127.0.0.1:0"]
    monkeypatch.chdir(tmp_path)
    assert main(argv[1:]) == 0
    out = capsys.readouterr().out
    assert "listening on" in out and "calibrated on" in out
    assert "streamed" in out
