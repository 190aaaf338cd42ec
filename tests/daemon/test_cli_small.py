"""Small things a user met (issue 16 item 6): a broken pipe exits quietly, a port in
use is named, ``solve`` prints its speed."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from retargetd.daemon.cli.main import EXIT_BROKEN_PIPE


def _retargetd(*args: str) -> list[str]:
    return [sys.executable, "-m", "retargetd.daemon.cli.main", *args]


@pytest.fixture
def busy_udp_port() -> Iterator[int]:
    """A UDP port on 127.0.0.1 held by this test."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.settimeout(1.0)
    sock.bind(("127.0.0.1", 0))
    try:
        yield int(sock.getsockname()[1])
    finally:
        sock.close()


@pytest.mark.timeout(60)
def test_broken_pipe_exits_quietly() -> None:
    """``retargetd rig check plug-in-gait | head -0``: the reader is gone before the
    first write; no traceback, no error line, exit 141."""
    proc = subprocess.Popen(
        _retargetd("rig", "check", "plug-in-gait"),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env={**os.environ, "PYTHONWARNINGS": "error"},
    )
    assert proc.stdout is not None and proc.stderr is not None
    proc.stdout.close()
    try:
        err = proc.stderr.read().decode()
        assert proc.wait(timeout=50) == EXIT_BROKEN_PIPE
    finally:
        proc.kill()
        proc.stderr.close()
    assert err == ""


@pytest.mark.timeout(60)
def test_udp_port_in_use_is_named(busy_udp_port: int, tmp_path: Path) -> None:
    config = tmp_path / "d.toml"
    config.write_text(f'[input.osc]\nhost = "127.0.0.1"\nport = {busy_udp_port}\n')
    done = subprocess.run(
        _retargetd("run", "--config", str(config)),
        capture_output=True,
        text=True,
        timeout=50,
    )
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert f"osc markers endpoint udp://127.0.0.1:{busy_udp_port}" in lines[0]
    assert "in use" in lines[0]
