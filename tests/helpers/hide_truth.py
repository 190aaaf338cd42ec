"""One marker hidden on the synthetic performer, judged against the truth as
``bench/fit_truth.py`` judges it (``docs/fit-truth.md``'s "beyond the hold"): the
fit tests of issue 28 item 6 share the take, the solver and the figure."""

from __future__ import annotations

import functools
from typing import Any

import numpy as np

from retargetd.daemon.body import fit_gaps
from retargetd.daemon.body.calibration import calibrate
from retargetd.daemon.body.method import make_body_solver
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.synth import performer as pf
from retargetd.daemon.synth.damage import damage
from retargetd.daemon.synth.hold import held_directions, hide_truth_excess
from retargetd.daemon.validate.limits import JOINT_LIMITS_DEG
from retargetd.daemon.validate.model import SEGMENT_KIND

#: As bench/fit_truth.py makes the take: 120 Hz, seed 0, no noise, calibrated on
#: the first second (the T-pose hold), hides from 4 s; its first 5.5 s (the same
#: frames as the bench's 10 s: the solve is causal), which hold the hide and the
#: quarter second after it that the figure judges.
RATE_HZ = 120.0
SECONDS = 5.5
CALIBRATE = 120
HIDE_AT = 480
#: Issue 28 item 6's mark for a bone (and the hide tables' for a runaway).
BONE_DEG = 10.0


@functools.cache
def synthetic(markerset: str) -> tuple[pf.SynthTake, Any, Any, Any]:
    """The default motions as the bench makes them: take, rig, solver, intact solve."""
    take = pf.synthesize(seconds=SECONDS, rate_hz=RATE_HZ, markerset=markerset, seed=0)
    rig = load_rig(markerset)
    cal = calibrate(rig, take.markers_world[:CALIBRATE], take.labels)
    fit = make_body_solver(
        "fit", rig, cal, take.labels,
        joint_limits=JOINT_LIMITS_DEG, segment_kind=SEGMENT_KIND, rate_hz=RATE_HZ,
    )  # fmt: skip
    fit.reset()
    return take, rig, fit, fit.solve_take(take.markers_world)


def hidden_beyond_hold(
    markerset: str, marker: str, seconds: float, *, two_sided: bool = False
) -> tuple[Any, Any]:
    """``marker`` hidden ``seconds`` from HIDE_AT: the damaged solve and its
    ``hide_truth_excess`` (each bone's error since the hide, less the intact
    solve's and the truth's own turn in the rotations the fit holds). The causal
    solve (the live daemon's), or with ``two_sided`` the offline one
    (``body.fit_gaps``: the intact take has no span, so its solve is the same)."""
    take, rig, fit, intact = synthetic(markerset)
    window = slice(HIDE_AT, HIDE_AT + round(seconds * RATE_HZ))
    col = take.labels.index(marker)
    fit.reset()
    damaged = damage(take.markers_world, take.labels, "hide", window, marker=col)
    if two_sided:
        solve = fit_gaps.solve_two_sided(fit, damaged)
    else:
        solve = fit.solve_take(damaged)
    fit.reset()
    rig_marker = int(np.flatnonzero(fit.marker_cols == col)[0])
    held = held_directions(
        fit.model, fit.params, rig_marker,
        intact.parent_from_bone_quat[HIDE_AT - 1],
        float(intact.residual_level[HIDE_AT - 1]),
    )  # fmt: skip
    return solve, hide_truth_excess(take, rig, intact, solve, held, window, RATE_HZ)
