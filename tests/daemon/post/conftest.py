"""Shared takes for the post-stage tests: the Plug-in Gait walk solved once, and the
synthetic performer's truth."""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

from retargetd.daemon.body.calibration import Calibration, calibrate
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.body.solve import BodySolve, BodySolver
from retargetd.daemon.synth import performer as pf
from retargetd.replay.takes import load_take

STATIC = "btkdata/PiG_Calibration-FlatFoot-Full.c3d"
WALK = "btkdata/PiG_Motion-FlatFoot-Full.c3d"


@dataclass(frozen=True)
class Solved:
    """A real take solved with its calibration."""

    calibration: Calibration
    solve: BodySolve
    rate_hz: float


@functools.cache
def _solve_walk(root: Path) -> Solved:
    rig = load_rig("plug-in-gait")
    static = load_take(root / STATIC)
    cal = calibrate(
        rig, static.positions, static.labels, take_measurements=static.measurements
    )
    take = load_take(root / WALK)
    res = BodySolver(rig, cal, take.labels).solve_take(take.positions)
    return Solved(cal, res, float(take.rate_hz))


@pytest.fixture
def pig_walk(datasets: Path) -> Solved:
    """The Plug-in Gait walk (a real take), solved with the static's calibration."""
    return _solve_walk(datasets)


@functools.cache
def _synth(motions: tuple[str, ...], rate_hz: float, seconds: float) -> pf.SynthTake:
    return pf.synthesize(seconds=seconds, rate_hz=rate_hz, motions=motions)


@pytest.fixture
def forearm_twist() -> pf.SynthTake:
    """4 s of the synthetic performer's forearm-twist motion at 100 Hz (truth)."""
    return _synth(("forearm_twist",), 100.0, 4.0)


@pytest.fixture
def synth_take() -> Callable[[tuple[str, ...], float, float], pf.SynthTake]:
    """Cached synthetic takes: ``synth_take(motions, rate_hz, seconds)``."""
    return _synth
