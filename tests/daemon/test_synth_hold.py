"""A hidden marker's damage judged against the truth less what the fit holds
(``synth.hold``, issue 28 item 6): a solve that holds what the marker alone saw is
within the truth's own excursion in it; a solve that turns elsewhere, or a hold
judged on a rotation the truth did not make, is not."""

from __future__ import annotations

import dataclasses
import functools
import math
from pathlib import Path

import numpy as np
import pytest

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.calibration import calibrate
from retargetd.daemon.body.method import make_body_solver
from retargetd.daemon.body.rig import Rig, load_rig
from retargetd.daemon.body.solve import BodySolve
from retargetd.daemon.body.solve_fit import FitSolve, FitSolver
from retargetd.daemon.synth import performer as pf
from retargetd.daemon.synth.damage import damage_metrics, hide_marker
from retargetd.daemon.synth.hold import (
    chart,
    held_directions,
    hide_truth_excess,
    hold_excursion_deg,
)
from retargetd.daemon.synth.truth import truth_map
from retargetd.daemon.validate.limits import JOINT_LIMITS_DEG
from retargetd.daemon.validate.model import SEGMENT_KIND

DATA = Path(__file__).resolve().parent.parent / "data"
RATE_HZ = 120.0
X, Y, Z = np.eye(3)


def _about(axis: np.ndarray, deg: np.ndarray | float) -> np.ndarray:
    return rot.quat_from_axis_angle(axis, np.radians(deg))


def test_chart_is_the_hold_priors_coordinates() -> None:
    """Swing about x, twist about +Y, swing about z; a twist stays the twist after a
    swing (swing * twist)."""
    np.testing.assert_allclose(chart(_about(X, 30.0)), [math.radians(30.0), 0, 0],
                               atol=1e-12)  # fmt: skip
    np.testing.assert_allclose(chart(_about(Y, -50.0)), [0, math.radians(-50.0), 0],
                               atol=1e-12)  # fmt: skip
    q = rot.quat_mul(_about(Z, 40.0), _about(Y, 70.0))
    np.testing.assert_allclose(
        chart(q), [0.0, math.radians(70.0), math.radians(40.0)], atol=1e-12
    )
    np.testing.assert_allclose(chart(-q), chart(q), atol=1e-12)  # either sign


@functools.cache
def _still() -> tuple[Rig, pf.SynthTake, BodySolve]:
    """The exact rig's construction on the performer holding its T-pose: the truth."""
    rig = load_rig(DATA / "synth-exact-rig.toml")
    markers = DATA / "synth-exact-markers.toml"
    take = pf.synthesize(seconds=3.0, rate_hz=RATE_HZ, markerset=markers, motions=())
    cal = calibrate(rig, take.markers_world[:120], take.labels)
    solve = make_body_solver("construction", rig, cal, take.labels).solve_take(
        take.markers_world
    )
    return rig, take, solve


def test_a_hold_is_within_the_truths_excursion_and_a_runaway_is_not() -> None:
    """The truth's left hand flexes 40 deg about its own z while a marker is hidden.
    The intact solve follows it; a solve holding the hand (its flexion held) is off
    by exactly that, which the excursion in the held direction allows (0 beyond);
    a solve turning the hand the other way is 40 deg beyond, and so is the hold
    judged on a direction the truth did not turn in (x). A standing error both
    solves had before the hide is not the hide's."""
    rig, take, solve = _still()
    b = rig.bone_names.index("l_hand")
    seg = take.segment_names.index("l_hand")
    window = slice(200, 320)
    t = np.arange(take.n_frames)
    ramp = np.clip((t - 199) / 120.0, 0.0, 1.0)
    alpha = 40.0 * (3.0 * ramp**2 - 2.0 * ramp**3)  # 0 until the hide, then 40 deg
    wfs = take.world_from_segment_quat.copy()
    seg_from_bone = rot.quat_mul(rot.quat_conj(wfs[0, seg]),
                                 solve.world_from_bone_quat[0, b])  # fmt: skip
    flex = _about(rot.quat_rotate(seg_from_bone, Z), alpha)
    wfs[:, seg] = rot.quat_mul(wfs[:, seg], flex)
    truth = dataclasses.replace(take, world_from_segment_quat=wfs)

    def with_hand(turn: np.ndarray) -> BodySolve:
        wfb = solve.world_from_bone_quat.copy()
        # an error the solve took on after the calibration pose, before the hide
        standing = _about(Z, 20.0 * (t >= 100))
        wfb[:, b] = rot.quat_mul(rot.quat_mul(wfb[:, b], standing), turn)
        return dataclasses.replace(solve, world_from_bone_quat=wfb)

    intact = with_hand(_about(Z, alpha))
    held = with_hand(_about(Z, 0.0 * alpha))
    runaway = with_hand(_about(Z, -alpha))
    hold = {b: Z[None, :]}
    k = truth_map(rig, take.segment_names).bone_names.index("l_hand")

    ex = hold_excursion_deg(truth, rig, held, hold, 199)
    np.testing.assert_allclose(ex[:, k], np.abs(alpha), atol=1e-6)
    h = hide_truth_excess(truth, rig, intact, held, hold, window, RATE_HZ)
    assert ex[window, k].max() > 39.9  # the hold is off by that much
    assert h.excess_deg.max() <= 1e-6 and h.held_bones == ("l_hand",)
    assert np.abs(h.intact_deg).max() <= 1e-6  # the standing error is not the hide's
    r = hide_truth_excess(truth, rig, intact, runaway, hold, window, RATE_HZ)
    assert r.excess_deg[k] == pytest.approx(40.0, abs=1e-3) and r.worst == k
    wrong = hide_truth_excess(truth, rig, intact, held, {b: X[None, :]}, window,
                              RATE_HZ)  # fmt: skip
    assert wrong.excess_deg[k] == pytest.approx(40.0, abs=1e-3)
    # the forearm's hold counts for the hand it carries
    forearm = rig.bone_names.index("l_forearm")
    both = hold_excursion_deg(truth, rig, held, {forearm: Y[None, :], b: Z[None, :]},
                              199)  # fmt: skip
    np.testing.assert_allclose(both[:, k], np.abs(alpha), atol=1e-6)
    with pytest.raises(ValueError, match="start after frame 0"):
        hide_truth_excess(truth, rig, intact, held, hold, slice(0, 10), RATE_HZ)


@functools.cache
def _pig() -> tuple[Rig, pf.SynthTake, FitSolver, FitSolve]:
    take = pf.synthesize(seconds=6.0, rate_hz=RATE_HZ, markerset="plug-in-gait",
                         motions=pf.DEFAULT_MOTIONS, seed=0)  # fmt: skip
    rig = load_rig("plug-in-gait")
    cal = calibrate(rig, take.markers_world[:120], take.labels)
    solver = make_body_solver(
        "fit", rig, cal, take.labels, joint_limits=JOINT_LIMITS_DEG,
        segment_kind=SEGMENT_KIND, rate_hz=RATE_HZ,
    )  # fmt: skip
    assert isinstance(solver, FitSolver)
    intact = solver.solve_take(take.markers_world)
    return rig, take, solver, intact


def _held(solver: FitSolver, intact: FitSolve, label: str, t0: int) -> dict:
    col = solver.labels.index(label)
    k = int(np.flatnonzero(solver.marker_cols == col)[0])
    return held_directions(solver.model, solver.params, k,
                           intact.parent_from_bone_quat[t0],
                           float(intact.residual_level[t0]))  # fmt: skip


def test_plug_in_gait_lfin_hidden_is_a_hold_of_the_hand() -> None:
    """LFIN is the only marker on Plug-in Gait's hand: hidden 1 s, the fit holds the
    hand, past 10 deg from the intact solve (the plain figure), within 10 deg of the
    truth beyond the truth's own excursion in what it held; the same solve with the
    hand turned 20 deg more about its long axis after the hide's start is not. A
    hidden knee marker holds nothing of the hand."""
    rig, take, solver, intact = _pig()
    window = slice(480, 600)
    held = _held(solver, intact, "LFIN", 479)
    hand = rig.bone_names.index("lhand")
    # all of it: every rotation the hand's joint has (a swing: no twist of its own;
    # the local floor, which added a third direction, needs two markers hidden)
    free = len(solver.model.observation[hand].axes)
    assert hand in held and np.linalg.matrix_rank(held[hand]) == free
    assert hand not in _held(solver, intact, "LKNE", 479)
    solver.reset()
    pos = hide_marker(take.markers_world, take.labels.index("LFIN"), window)
    damaged = solver.solve_take(pos)
    plain = damage_metrics(intact, damaged, window, RATE_HZ)
    assert plain.max_bone == "lhand" and plain.max_bone_deg > 10.0
    h = hide_truth_excess(take, rig, intact, damaged, held, window, RATE_HZ)
    k = h.bone_names.index("lhand")
    print(f"\nLFIN hidden 1 s: lhand {plain.max_bone_deg:.1f} deg off the intact "
          f"solve; against the truth {h.error_deg[k]:.1f} - intact "
          f"{h.intact_deg[k]:.1f} - excursion {h.allowance_deg[k]:.1f} = "
          f"{h.excess_deg[k]:.1f} deg")  # fmt: skip
    assert h.excess_deg[k] <= 10.0
    wfb = damaged.world_from_bone_quat.copy()
    wfb[480:, hand] = rot.quat_mul(wfb[480:, hand], _about(Y, 20.0))
    worse = dataclasses.replace(damaged, world_from_bone_quat=wfb)
    w = hide_truth_excess(take, rig, intact, worse, held, window, RATE_HZ)
    print(f"turned 20 deg more: {w.excess_deg[k]:.1f} deg beyond the hold")
    assert w.excess_deg[k] > 10.0


def test_plug_in_gait_finger_hidden_moves_no_joint_centre_20mm() -> None:
    """Issue 28 item 6 on the synthetic performer: RFIN (the hand's one marker)
    hidden 1 s moves no joint centre more than 20 mm from the intact solve. With
    the local floor made for one hidden marker, the forearm's twist, which the wrist
    bar still sees, was held against the performer's 115 deg pronation in that
    second and the wrist ran 79 mm off (``bench/hide_sweep.py``)."""
    label = "RFIN"
    _, take, solver, intact = _pig()
    window = slice(480, 600)
    solver.reset()
    pos = hide_marker(take.markers_world, take.labels.index(label), window)
    damaged = solver.solve_take(pos)
    mt = damage_metrics(intact, damaged, window, RATE_HZ)
    print(f"\n{label} hidden 1 s: joint {mt.max_joint_mm:.1f} mm ({mt.max_joint}), "
          f"bone {mt.max_bone_deg:.1f} deg ({mt.max_bone})")  # fmt: skip
    assert mt.max_joint_mm <= 20.0
