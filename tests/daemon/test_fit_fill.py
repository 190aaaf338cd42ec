"""A hidden marker filled from the markers that moved rigidly with it (``fit_fill``):
exact on a rigid set moved and turned, its expected error growing (its weight falling,
then no fill) as the set bends; donors only on its own bone or bones proximal to it;
the synthetic performer's trunk markers hidden 0.25 s, and the walk's left elbow
marker, whose wrist and finger donors took it 40 mm off (issue 28 items 3, 6)."""

from __future__ import annotations

import functools
import itertools
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from retargetd.daemon.body import fit_fill
from retargetd.daemon.body import fit_terms as ft
from retargetd.daemon.body.calibration import calibrate
from retargetd.daemon.body.method import make_body_solver
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.synth import performer as pf
from retargetd.daemon.synth.damage import damage, damage_metrics
from retargetd.daemon.validate.limits import JOINT_LIMITS_DEG
from retargetd.daemon.validate.model import SEGMENT_KIND
from retargetd.replay.takes import load_take

DT = 0.01
LEVEL_M = 0.004
#: four donors spanning a plane (and out of it), the hidden marker (row 4), and a
#: marker that moves on its own (row 5)
LAYOUT = np.array(
    [
        [0.00, 0.00, 0.00],
        [0.12, 0.00, 0.01],
        [0.00, 0.10, 0.00],
        [0.06, 0.05, 0.08],
        [0.05, 0.03, 0.04],
        [0.30, 0.30, 0.30],
    ]
)
HIDDEN = 4


def _tuples() -> tuple[tuple, tuple]:
    """The model and state tuples with the slots the fill reads; the rest empty."""
    n = len(LAYOUT)
    params = np.zeros(ft.N_PARAMS)
    params[ft.P_NOISE_M] = 1e-3
    params[ft.P_RESOLUTION_RAD] = math.radians(5.0)
    params[ft.P_LEVEL_TAU_S] = 1.0
    m = [np.zeros(1) for _ in range(27)]
    m[0] = np.array([-1, 0])  # two bones: 1 is distal to 0
    m[5] = np.zeros(n, dtype=np.int64)  # every marker on bone 0
    m[26] = fit_fill.chain_pairs(m[0], m[5])  # (both bones on one chain: every pair)
    m[7] = np.ones(n)
    m[18] = params
    s: list[np.ndarray] = [np.zeros(1) for _ in range(60)]
    s[12] = np.zeros((n, 3))
    s[13] = np.ones(n, dtype=bool)
    s[36] = np.zeros(ft.N_SCALARS)
    s[36][ft.C_DT] = DT
    s[36][ft.C_LEVEL] = LEVEL_M
    s[45] = np.zeros(n, dtype=bool)
    s[48] = np.zeros(n)
    s[58] = np.zeros(n)
    s.extend(fit_fill.new_fill_state(n))
    return tuple(m), tuple(s)


def _pose(k: int) -> tuple[Rotation, np.ndarray]:
    """A rigid motion: turning about a wandering axis and travelling."""
    t = k * DT
    rv = np.array([0.9 * math.sin(1.3 * t), 0.7 * t, 0.5 * math.cos(0.8 * t)])
    return Rotation.from_rotvec(rv), np.array([0.4 * t, 0.1 * math.sin(t), 1.0])


def _seen(m: tuple, s: tuple, frames: int, jitter: float = 0.0) -> None:
    """``frames`` explained frames of the rigid motion, every marker accepted (the
    free marker wanders; ``jitter``: each donor's random wobble, metres)."""
    rng = np.random.default_rng(1)
    for k in range(frames):
        r, p = _pose(k)
        pts = r.apply(LAYOUT) + p
        pts[5] += 0.05 * math.sin(7.0 * k * DT)
        pts[:4] += jitter * rng.standard_normal((4, 3))
        s[12][:] = pts
        fit_fill.fill_update(m, s)


def _hide_at(m: tuple, s: tuple, k: int, bend: float = 0.0) -> np.ndarray:
    """The frame ``k`` with the hidden marker hidden (accepted the frame before);
    ``bend``: donor 3 moved off the rigid set by so much. Returns its truth."""
    s[58][:] = 0.0  # (kernel_fit's gather: no stand-in but where one is put)
    r, p = _pose(k)
    pts = r.apply(LAYOUT) + p
    pts[3] += [0.0, 0.0, bend]
    s[12][:] = pts
    s[12][HIDDEN] = np.nan
    s[13][HIDDEN] = False
    fit_fill.rigid_fill(m, s, True)
    s[48][HIDDEN] += 1.0  # the frame explained: no longer the first hidden one
    return pts[HIDDEN]


def test_a_rigid_set_moved_and_turned_fills_the_marker_exactly() -> None:
    m, s = _tuples()
    _seen(m, s, 150)  # 1.5 s: past the coverage the pairs need
    for k in (150, 170, 230):  # hidden 0.8 s, the set turned ~30 deg further
        truth = _hide_at(m, s, k)
        # the wandering marker is not rigid with it
        assert set(s[61][HIDDEN].tolist()) == {0, 1, 2, 3}
        assert s[63][HIDDEN, 4] > 0.999  # weighed as a seen marker
        assert s[58][HIDDEN] == s[63][HIDDEN, 4]
        assert np.linalg.norm(s[12][HIDDEN] - truth) < 1e-9


def test_a_set_that_bends_has_a_growing_expected_error_then_no_fill() -> None:
    m, s = _tuples()
    _seen(m, s, 150)
    weights = []
    for i, bend in enumerate((0.0, 0.002, 0.004, 0.008, 0.016)):
        _hide_at(m, s, 150 + i, bend)
        weights.append(s[63][HIDDEN, 4])
    assert weights[0] > 0.999
    assert all(b < a for a, b in itertools.pairwise(weights))
    # past the take's level the fill is no better than the model's stand-in: none
    assert weights[-1] == 0.0 and s[58][HIDDEN] == 0.0


def test_a_set_that_was_never_rigid_weighs_less_or_gives_no_donors() -> None:
    m, s = _tuples()
    _seen(m, s, 150, jitter=0.0015)  # each donor wobbling 1.5 mm
    _hide_at(m, s, 150)
    wobbly = s[63][HIDDEN, 4]
    m2, s2 = _tuples()
    _seen(m2, s2, 150)
    _hide_at(m2, s2, 150)
    assert 0.0 < wobbly < s2[63][HIDDEN, 4]
    m3, s3 = _tuples()
    _seen(m3, s3, 150, jitter=0.006)  # past the level: no rigid set
    _hide_at(m3, s3, 150)
    assert s3[61][HIDDEN, 0] == -1 and s3[63][HIDDEN, 4] == 0.0


def test_donors_only_on_the_markers_bone_or_proximal_to_it() -> None:
    """A donor on a distal bone is carried by the joint between (the elbow, the wrist
    for an upper-arm marker), which the marker does not follow: rigid with it so
    far or not, it is not a donor; a proximal bone's marker is."""
    m, s = _tuples()
    m[5][3] = 1  # donor 3 on the bone distal to the hidden marker's
    _seen(m, s, 150)
    truth = _hide_at(m, s, 150)
    assert set(s[61][HIDDEN].tolist()) == {0, 1, 2, -1}
    assert np.linalg.norm(s[12][HIDDEN] - truth) < 1e-9
    m2, s2 = _tuples()
    m2[5][HIDDEN] = 1  # the hidden marker on the distal bone: the others proximal
    _seen(m2, s2, 150)
    _hide_at(m2, s2, 150)
    assert set(s2[61][HIDDEN].tolist()) == {0, 1, 2, 3}


def test_too_short_a_history_gives_no_donors() -> None:
    m, s = _tuples()
    _seen(m, s, 20)  # 0.2 s together: under a quarter of the level's time constant
    _hide_at(m, s, 20)
    assert s[61][HIDDEN, 0] == -1 and s[63][HIDDEN, 4] == 0.0


@functools.cache
def _pig_synthetic() -> tuple[pf.SynthTake, object]:
    take = pf.synthesize(seconds=10.0, rate_hz=120.0, markerset="plug-in-gait", seed=0)
    cal = calibrate(load_rig("plug-in-gait"), take.markers_world[:120], take.labels)
    return take, cal


@pytest.mark.parametrize("marker", ["STRN", "T10", "LSHO"])
def test_a_trunk_marker_hidden_a_quarter_second_keeps_the_spine(marker: str) -> None:
    """Plug-in Gait's rigid thorax misfits the performer's twisting spine (T10 51 mm
    off the model), but the trunk's markers move nearly rigidly: filled from them
    the hidden marker keeps the pose within item 6's limits (bench/hide_sweep.py, 4 s,
    main 73bf309, with the model's stand-in: T10 4.5 mm, chest 12.7 deg, 2 new
    steps; LSHO 39.6 mm, 16.8 deg, 4 steps. Filled from its own and proximal bones,
    its hold dropped: 0.4 mm, 0.8 deg; 8.8 mm, 2.4 deg; no new step). STRN has only
    CLAV and C7 rigid with it on the chest (a Horn fit needs 3) and is not filled: it
    ran 34.1 deg off with 15 new steps until the hold tables counted T10 at its
    robust weight (``fit_hold_robust``; 1.2 mm, 3.1 deg, no step)."""
    take, cal = _pig_synthetic()
    fit = make_body_solver(
        "fit", load_rig("plug-in-gait"), cal, take.labels,
        joint_limits=JOINT_LIMITS_DEG, segment_kind=SEGMENT_KIND, rate_hz=120.0,
    )  # fmt: skip
    intact = fit.solve_take(take.markers_world)
    window = slice(480, 510)
    fit.reset()
    hidden = damage(take.markers_world, take.labels, "hide", window,
                    marker=take.labels.index(marker))  # fmt: skip
    mt = damage_metrics(intact, fit.solve_take(hidden), window, 120.0, step_deg=5.0)
    print(
        f"\n{marker} hidden 0.25 s: joint {mt.max_joint_mm:.1f} mm, bone "
        f"{mt.max_bone_deg:.1f} deg ({mt.max_bone}), new steps {mt.new_steps}"
    )
    assert mt.max_joint_mm <= 20.0 and mt.max_bone_deg <= 10.0 and mt.new_steps == 0


def test_the_walks_left_elbow_marker_takes_no_forearm_donor(datasets: Path) -> None:
    """The PiG walk's LELB hidden 0.25 s from row 150: its wrist and finger markers
    had moved rigidly with it, then the wrist flexed and the fill from them ran 33 mm
    off (elbow 40.3 mm, upper arm 32.4 deg off the intact solve). From its own bone
    and the proximal ones it has no rigid set, and the model's stand-in keeps it
    within item 6's distance limits as without the fill (15.0 mm, 9.3 deg; the 3 new
    steps it has without the fill are not the fill's, so not asserted)."""
    static = load_take(datasets / "btkdata/PiG_Calibration-FlatFoot-Full.c3d")
    take = load_take(datasets / "btkdata/PiG_Motion-FlatFoot-Full.c3d")
    rig = load_rig("plug-in-gait")
    cal = calibrate(rig, static.positions, static.labels,
                    take_measurements=static.measurements)  # fmt: skip
    fit = make_body_solver(
        "fit", rig, cal, take.labels, joint_limits=JOINT_LIMITS_DEG,
        segment_kind=SEGMENT_KIND, rate_hz=take.rate_hz,
    )  # fmt: skip
    intact = fit.solve_take(take.positions)
    window = slice(150, 150 + round(0.25 * take.rate_hz))
    fit.reset()
    hidden = damage(take.positions, take.labels, "hide", window,
                    marker=list(take.labels).index("LELB"))  # fmt: skip
    mt = damage_metrics(intact, fit.solve_take(hidden), window, take.rate_hz)
    print(f"\nLELB hidden 0.25 s: joint {mt.max_joint_mm:.1f} mm ({mt.max_joint}), "
          f"bone {mt.max_bone_deg:.1f} deg ({mt.max_bone})")  # fmt: skip
    assert mt.max_joint_mm <= 20.0 and mt.max_bone_deg <= 10.0


def _all_pairs(parent: np.ndarray, mk_bone: np.ndarray) -> np.ndarray:
    return np.array(list(itertools.combinations(range(len(mk_bone)), 2)))


def test_only_the_chain_pairs_statistics_kept_same_donors_same_poses(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The pair statistics kept only where the donor rule can read them
    (``chain_pairs``): the same donors and the same poses as with every pair's, on
    the synthetic performer with trunk, shoulder and knee markers hidden 1 s."""
    take, cal = _pig_synthetic()

    def solver() -> object:
        return make_body_solver(
            "fit", load_rig("plug-in-gait"), cal, take.labels,
            joint_limits=JOINT_LIMITS_DEG, segment_kind=SEGMENT_KIND, rate_hz=120.0,
        )  # fmt: skip

    fit = solver()
    with monkeypatch.context() as mp:
        mp.setattr(fit_fill, "chain_pairs", _all_pairs)
        full = solver()
    n = len(fit.marker_names)
    kept, every = len(fit._model[26]), len(full._model[26])
    print(f"\nPiG: {kept} of {every} pairs kept")
    assert every == n * (n - 1) // 2 and 0 < kept < every
    read = np.zeros((n, n), dtype=bool)
    read[fit._model[26][:, 0], fit._model[26][:, 1]] = True
    read |= read.T
    for marker in ("T10", "LSHO", "LKNE"):
        i = fit.marker_names.index(marker)
        hidden = damage(take.markers_world, take.labels, "hide", slice(480, 600),
                        marker=take.labels.index(marker))  # fmt: skip
        fit.reset()
        full.reset()
        a, b = fit.solve_take(hidden), full.solve_take(hidden)
        donors = fit._state[61][i]
        print(marker, "donors", [fit.marker_names[d] for d in donors if d >= 0])
        if marker != "LKNE":  # (measured: no rigid set of 3 found for it)
            assert donors[0] >= 0  # the fill's donors chosen (and kept since)
        np.testing.assert_array_equal(donors, full._state[61][i])
        np.testing.assert_array_equal(fit._state[60][read], full._state[60][read])
        np.testing.assert_allclose(
            a.world_from_bone_quat, b.world_from_bone_quat, rtol=0.0, atol=1e-12
        )
