"""The suite on two pytest-xdist workers (pyproject's ``addopts``): the kernels
compiled once, by the controller, before any test; an ``alone`` test with no other
beside it (``tests/helpers/alone.py``); and a port "nobody listens on" that no socket
bound to port 0 can be given (``live_harness._unused_udp_port``).

The first two run pytest on a small suite of their own in a fresh process (its
rootdir a temporary folder, ``tests/helpers`` on its path)."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import live_harness as lh
import pytest

HELPERS = Path(__file__).resolve().parent / "helpers"

#: The inner suite's conftest: the plugins the real one loads, the kernel compile
#: replaced by a note of which process ran it and when.
CONFTEST = """
import json, os, time
import live_harness

pytest_plugins = ["live_harness", "alone"]

def _note_compile():
    with open(os.environ["NOTES"], "a") as f:
        f.write(json.dumps({"compile": os.environ.get("PYTEST_XDIST_WORKER", ""),
                            "t": time.time()}) + "\\n")

live_harness.compile_kernels = _note_compile
"""

#: One test file: ``N`` tests that each note their interval (``alone`` ones marked).
TESTS = """
import json, os, time
import pytest

def _run(name, seconds):
    t0 = time.time()
    time.sleep(seconds)
    with open(os.environ["NOTES"], "a") as f:
        f.write(json.dumps({"test": name, "t0": t0, "t1": time.time()}) + "\\n")
"""


def _run_inner(tmp_path: Path, files: dict[str, str], *args: str) -> list[dict]:
    """pytest on ``files`` (test file name -> body) with ``args``; its notes."""
    (tmp_path / "conftest.py").write_text(CONFTEST)
    for name, body in files.items():
        (tmp_path / name).write_text(TESTS + body)
    notes = tmp_path / "notes.jsonl"
    env = dict(os.environ, NOTES=str(notes))
    env["PYTHONPATH"] = os.pathsep.join(
        p for p in (str(HELPERS), env.get("PYTHONPATH", "")) if p
    )
    # this run's own (an xdist worker's PYTEST_XDIST_WORKER would be the inner's)
    for name in ("PYTEST_ADDOPTS", "PYTEST_XDIST_WORKER", "PYTEST_XDIST_WORKER_COUNT",
                 "PYTEST_XDIST_TESTRUNUID"):  # fmt: skip
        env.pop(name, None)
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
         "-p", "no:randomly", "--basetemp", str(tmp_path / "base"), *args],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return [json.loads(line) for line in notes.read_text().splitlines()]


@pytest.mark.timeout(300)
@pytest.mark.parametrize("workers", ["2", "0"])
def test_the_kernels_compile_once_before_any_test(tmp_path: Path, workers: str) -> None:
    body = "\n".join(f"def test_{i}():\n    _run('{i}', 0.05)\n" for i in range(6))
    notes = _run_inner(tmp_path, {"test_a.py": body, "test_b.py": body}, "-n", workers)
    compiles = [n for n in notes if "compile" in n]
    tests = [n for n in notes if "test" in n]
    assert len(tests) == 12
    # once, in the controller (or the only process), before the first test starts
    assert [c["compile"] for c in compiles] == [""], compiles
    assert compiles[0]["t"] <= min(t["t0"] for t in tests)


@pytest.mark.timeout(300)
def test_an_alone_test_runs_with_no_other_beside_it(tmp_path: Path) -> None:
    def others(file: int) -> str:
        return "\n".join(
            f"def test_{i}():\n    _run('{file}.{i}', 0.3)\n" for i in range(8)
        )

    alone = (
        "@pytest.mark.alone\ndef test_alone():\n    _run('alone', 1.0)\n\n"
        "def test_after():\n    _run('after', 0.05)\n"
    )
    notes = _run_inner(
        tmp_path,
        {"test_1.py": others(1), "test_2.py": alone, "test_3.py": others(3)},
        "-n", "2", "--dist", "load",
        "-o", "markers=alone: beside nothing",
    )  # fmt: skip
    tests = {n["test"]: n for n in notes if "test" in n}
    a = tests.pop("alone")
    assert len(tests) == 17
    overlapping = [
        name for name, t in tests.items() if t["t0"] < a["t1"] and a["t0"] < t["t1"]
    ]
    assert overlapping == [], (a, tests)
    # tests ran before and after it (it waited, and held the others back)
    assert any(t["t1"] <= a["t0"] for t in tests.values())
    assert any(t["t0"] >= a["t1"] for t in tests.values())


def test_an_unused_port_is_none_that_port_zero_can_be_given() -> None:
    low = lh._ephemeral_low()
    if low <= 2048:
        pytest.skip(f"no room below the ephemeral range (it starts at {low})")
    for _ in range(20):
        port = lh._unused_udp_port()
        assert 1024 <= port < low
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
            udp.bind(("127.0.0.1", port))  # nothing holds it
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as tcp:
            tcp.bind(("127.0.0.1", port))
