"""No kernel compiles (or loads) on a live frame: the warm-up covers every kernel the
loop's paths call (issue 35; issue 30 item 6).

A fresh interpreter (``tests/helpers/live_compiles.py``) opens a daemon, counts every
numba dispatcher's overloads, streams every path (a new label set, a hidden marker,
every marker hidden, bursts of bad frames with their unexplained and reseeded frames,
a pause, a source restart, a recording) and counts again. Before the warm-up ran the
stance detector, its kernel compiled on the first solved frame: a 2352 ms ``markers``
stall in the 120 s soak on a fresh cache, 1144 ms of it on the loop's CPU (at load
4.9; 1039 ms, 996 ms on the CPU, in an earlier run), and ``[target] feet = "plant"``'s
kernel likewise: every configuration below (the fit, every stage, the construction,
the face) failed on that tree, naming those kernels.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from paths import DATASETS

HELPERS = Path(__file__).resolve().parents[1] / "helpers"

#: name -> (the config's overrides, the ICT face on)
CONFIGS: dict[str, tuple[dict[str, Any], bool]] = {
    "default": ({}, False),  # the fit and the validator (the soak's)
    "every_stage": (
        {
            "target": {"feet": "plant", "spine": "pivot"},
            "pipeline": [{"kind": "twist"}, {"kind": "one_euro"}],
            "loop": {"output_rate_hz": 60.0},
        },
        False,
    ),
    "construction": ({"solve": {"method": "construction"}}, False),
    # without the validator, the solve and the emit in one call (solve_emit.py)
    "fit_alone": ({"validate": {"enabled": False}}, False),
    "construction_alone": (
        {"solve": {"method": "construction"}, "validate": {"enabled": False}},
        False,
    ),
    "face": ({}, True),
}


#: name -> its interpreter, started (the next name's meanwhile: see _start_next)
#: and not yet waited for; every name ever started.
_RUNNING: dict[str, subprocess.Popen[str]] = {}
_STARTED: set[str] = set()


def _start(name: str, exact_calibration: Path) -> subprocess.Popen[str]:
    """``live_compiles.py`` for configuration ``name`` in a fresh interpreter."""
    overrides, face = CONFIGS[name]
    args = [str(exact_calibration), json.dumps(overrides)]
    if face:
        args.append(str(DATASETS))
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(
        p for p in (str(HELPERS), env.get("PYTHONPATH", "")) if p
    )
    _STARTED.add(name)
    return subprocess.Popen(
        [sys.executable, str(HELPERS / "live_compiles.py"), *args],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip


def _start_next(name: str, exact_calibration: Path) -> None:
    """Start the configuration after ``name`` (sorted, as parametrized) while
    ``name``'s runs: two interpreters at a time, each counting only its own
    kernels (on CI's two cores the second is otherwise idle here)."""
    names = sorted(CONFIGS)
    for later in names[names.index(name) + 1 :]:
        if later not in _STARTED:
            if not CONFIGS[later][1] or DATASETS.is_dir():
                _RUNNING[later] = _start(later, exact_calibration)
            return


@pytest.fixture(scope="module", autouse=True)
def _stop_leftovers() -> Iterator[None]:
    """An interpreter started ahead for a test that did not run (``-k``, ``-x``)
    is stopped with the module."""
    yield
    while _RUNNING:
        proc = _RUNNING.popitem()[1]
        proc.kill()
        proc.communicate()


@pytest.mark.timeout(300)
@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_no_kernel_compiles_after_the_warm_up(
    name: str, exact_calibration: Path, request: pytest.FixtureRequest
) -> None:
    overrides, face = CONFIGS[name]
    if face:  # (skipped without ../shared/datasets)
        request.getfixturevalue("datasets")
    if name not in _RUNNING:
        _RUNNING[name] = _start(name, exact_calibration)
    _start_next(name, exact_calibration)
    proc = _RUNNING.pop(name)
    try:
        stdout, stderr = proc.communicate(timeout=280)
    finally:
        if proc.poll() is None:  # timed out
            proc.kill()
            proc.communicate()
    done = subprocess.CompletedProcess(proc.args, proc.returncode, stdout, stderr)
    assert done.returncode == 0, done.stderr[-4000:]
    got = json.loads(done.stdout.strip().splitlines()[-1])
    stats = got["stats"]
    # the paths were taken (else no compile proves nothing)
    assert stats["frames_solved"] > 300, stats
    assert stats["restarts"] >= 1, stats
    if overrides.get("solve", {}).get("method", "fit") == "fit":
        assert stats["unseen"] > 0, stats
        assert stats["unexplained"] > 0, stats
        assert stats["reseeded"] > 0, stats
    if face:
        assert stats["face_solved"] > 300, stats
    assert got["new"] == {}, f"compiled or loaded while streaming: {got['new']}"
