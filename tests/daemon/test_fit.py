"""The rigid-skeleton fit (``solve_fit``) against the synthetic performer's truth, the
validator's limits and real takes, and its kernel's contract.

Truth: the exact rig (``tests/data/synth-exact-rig.toml``) makes every bone a
performer segment up to a constant rotation, so ``world_from_bone *
conj(rest_world_from_bone)`` must equal the segment's ``world_from_segment`` (see
``test_solve_body``). For the shipped rigs the root's truth is the calibrated root
point carried rigidly by the true pelvis. Run with ``pytest -s`` for the figures.
"""

from __future__ import annotations

import functools
import tracemalloc
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import pytest

from retargetd.daemon import rotations as rot
from retargetd.daemon.body import fit_pack
from retargetd.daemon.body.calibration import (
    Calibration,
    CalibrationError,
    calibrate,
    match_markers,
)
from retargetd.daemon.body.fit_model import (
    FitOptions,
    build_fit_model,
    load_fit_rig,
    parse_fit_options,
)
from retargetd.daemon.body.rig import Rig, RigError, load_rig
from retargetd.daemon.body.rig_fit import stiffness_matrix
from retargetd.daemon.body.solve import BodySolver
from retargetd.daemon.body.solve_fit import (
    FLAG_HELD,
    FitParams,
    FitPose,
    FitSolve,
    FitSolver,
    warm_up,
)
from retargetd.daemon.synth import performer as pf
from retargetd.daemon.synth import skeleton as pf_skeleton
from retargetd.daemon.validate.limits import JOINT_LIMITS_DEG, limit_violation_deg
from retargetd.daemon.validate.model import SEGMENT_KIND, skeleton_from_calibration
from retargetd.replay.takes import load_take

DATA = Path(__file__).resolve().parent.parent / "data"
EXACT_RIG = DATA / "synth-exact-rig.toml"
EXACT_MARKERS = DATA / "synth-exact-markers.toml"
RATE_HZ = 120.0


def _solver(rig: Rig, take: pf.SynthTake) -> tuple[Calibration, FitSolver]:
    """The rig calibrated on the take's base pose, and its fit with the validator's
    limits."""
    base = take.markers_world[take.base_pose_frames]
    cal = calibrate(rig, base, take.labels)
    solver = FitSolver(
        rig,
        cal,
        take.labels,
        joint_limits=JOINT_LIMITS_DEG,
        segment_kind=SEGMENT_KIND,
        base_positions=base,
    )
    return cal, solver


def _fit(
    rig: Rig, take: pf.SynthTake, positions: np.ndarray | None = None
) -> tuple[Calibration, FitSolver, FitSolve]:
    cal, solver = _solver(rig, take)
    pos = take.markers_world if positions is None else positions
    return cal, solver, solver.solve_take(pos)


def _bone_errors_deg(
    rig: Rig, cal: Calibration, res: FitSolve, take: pf.SynthTake
) -> np.ndarray:
    """(T, B) world-rotation error of each bone of the exact rig, degrees."""
    seg = [take.segment_names.index(b) for b in rig.bone_names]
    wfs = take.world_from_segment_quat[:, seg]
    delta = rot.quat_mul(
        res.world_from_bone_quat, rot.quat_conj(cal.rest_world_from_bone_quat)
    )
    return np.degrees(rot.quat_angle(rot.quat_mul(rot.quat_conj(wfs), delta)))


@functools.cache
def _exact_take(
    noise_mm: float = 0.0, dropout: float = 0.0, seconds: float = 5.0
) -> pf.SynthTake:
    return pf.synthesize(
        seconds=seconds,
        rate_hz=RATE_HZ,
        markerset=EXACT_MARKERS,
        noise_mm=noise_mm,
        dropout=dropout,
        seed=3,
    )


# --- accuracy against the truth ---------------------------------------------------


def test_exact_rig_noise_free_every_bone_within_0_05_deg() -> None:
    rig, take = load_rig(EXACT_RIG), _exact_take()
    cal, _, res = _fit(rig, take)
    err = _bone_errors_deg(rig, cal, res, take)
    print(
        f"\nfit, exact rig, noise-free: max {err.max():.5f} deg, median "
        f"{np.median(err):.6f}; iterations {np.bincount(res.iterations)}"
    )
    assert err.max() <= 0.05
    # The motion is far from the calibration pose, so the fit had work to do.
    assert np.degrees(rot.quat_angle(res.rest_from_bone_quat)).max() > 60.0
    seg = [take.segment_names.index(j) for j in res.joint_names]
    np.testing.assert_allclose(
        res.joint_centres, take.joint_pos_world[:, seg], rtol=0, atol=1e-4
    )
    assert np.isfinite(res.marker_rms).all() and res.marker_rms.max() < 1e-4
    assert res.outliers_rejected == 0


def test_exact_rig_1mm_noise() -> None:
    rig, take = load_rig(EXACT_RIG), _exact_take(noise_mm=1.0)
    cal, _, res = _fit(rig, take)
    err = _bone_errors_deg(rig, cal, res, take)
    med, p95 = np.median(err), np.percentile(err, 95)
    print(
        f"\nfit, exact rig, 1 mm noise: median {med:.3f} deg, p95 {p95:.3f}, "
        f"max {err.max():.3f}; residual RMS median "
        f"{1000 * np.median(res.marker_rms):.2f} mm"
    )
    assert med <= 1.0 and p95 <= 3.0


def test_dropouts_in_runs() -> None:
    """10 % of samples occluded in runs (mean 0.1 s): median error <= 1.5 deg, and no
    bone is flagged held while two of its own markers are seen."""
    rig, take = load_rig(EXACT_RIG), _exact_take(noise_mm=0.5, dropout=0.10)
    cal, solver, res = _fit(rig, take)
    err = _bone_errors_deg(rig, cal, res, take)
    print(
        f"\nfit, 10 % dropouts ({100 * take.occluded_fraction:.1f} % occluded): "
        f"median {np.median(err):.3f} deg, p95 {np.percentile(err, 95):.3f}, max "
        f"{err.max():.3f}"
    )
    assert take.occluded_fraction > 0.08
    assert np.median(err) <= 1.5
    assert np.isfinite(res.world_from_bone_quat).all()
    seen = np.isfinite(take.markers_world).all(axis=-1)  # (T, M), labels = rig order
    cols = np.asarray(match_markers(rig, take.labels))
    bones = solver.model.marker_bone
    for b in range(len(rig.bones)):
        own = seen[:, cols[bones == b]].sum(axis=1)
        held = (res.bone_flags[:, b] & FLAG_HELD) != 0
        assert not (held & (own >= 2)).any(), rig.bone_names[b]
        assert (held == (own == 0)).all(), rig.bone_names[b]


def _root_truth(cal: Calibration, take: pf.SynthTake) -> np.ndarray:
    """(T, 3) the calibrated root point carried rigidly by the true pelvis."""
    base = take.base_pose_frames
    pelvis_q = take.world_from_segment_quat[:, 0]
    local = rot.quat_rotate(
        rot.quat_conj(pelvis_q[base.start]),
        cal.root_rest_pos - take.joint_pos_world[base.start, 0],
    )
    return take.joint_pos_world[:, 0] + rot.quat_rotate(pelvis_q, local)


@pytest.mark.parametrize(
    ("markerset", "hip"), [("menache", "LHIP"), ("plug-in-gait", "LASI")]
)
def test_hip_marker_hidden_for_one_second(markerset: str, hip: str) -> None:
    rig = load_rig(markerset)
    take = pf.synthesize(seconds=6.0, rate_hz=RATE_HZ, markerset=markerset, seed=2)
    pos = take.markers_world.copy()
    gap = slice(int(3.0 * RATE_HZ), int(4.0 * RATE_HZ))
    pos[gap, take.labels.index(hip)] = np.nan
    cal, _, res = _fit(rig, take, pos)
    truth = _root_truth(cal, take)
    err = 1000 * np.linalg.norm(res.root_pos - truth, axis=-1)
    step = np.linalg.norm(np.diff(res.root_pos, axis=0), axis=-1)
    true_step = np.linalg.norm(np.diff(truth, axis=0), axis=-1)
    con = BodySolver(rig, cal, take.labels).solve_take(pos)
    con_err = 1000 * np.linalg.norm(con.root_pos - truth, axis=-1)
    print(
        f"\n{markerset}, {hip} hidden 1 s: root error max {err.max():.2f} mm (in the "
        f"gap {err[gap].max():.2f}); construction max {con_err.max():.1f} mm; "
        f"largest step ratio {(step / np.maximum(true_step, 1e-4)).max():.2f}"
    )
    assert err.max() <= 15.0
    assert (step <= 2.0 * true_step + 1e-4).all()  # (+0.1 mm: rounding on a still root)


def test_swapped_labels_rejected_and_counted() -> None:
    rig, take = load_rig(EXACT_RIG), _exact_take(noise_mm=0.5)
    pos = take.markers_world.copy()
    a, b = take.labels.index("LKNL"), take.labels.index("LANL")
    frames = slice(300, 303)
    pos[frames, a], pos[frames, b] = (
        take.markers_world[frames, b],
        take.markers_world[frames, a],
    )
    cal, _, res = _fit(rig, take, pos)
    err = _bone_errors_deg(rig, cal, res, take)
    ra, rb = rig.marker_names.index("LKNL"), rig.marker_names.index("LANL")
    print(
        f"\nswapped LKNL/LANL for 3 frames: rejected {res.outliers_rejected}, bone "
        f"error there max {err[frames].max():.3f} deg"
    )
    assert (
        res.marker_rejected[frames, ra].all() and res.marker_rejected[frames, rb].all()
    )
    assert err[frames].max() <= 3.0
    assert res.outliers_rejected >= 6
    assert res.marker_rejected[: frames.start].sum() == 0
    # the rejected markers leave their bones partly seen, never held
    thigh, shank = rig.bone_names.index("l_thigh"), rig.bone_names.index("l_shank")
    assert (res.bone_quality[frames, thigh] < 1.0).all()
    assert (res.bone_quality[frames, shank] < 1.0).all()
    assert not (res.bone_flags[frames] & FLAG_HELD).any()


def test_sliding_marker_kept_jumping_marker_rejected() -> None:
    """The gate rejects residuals that jump, not residuals that grow: a marker whose
    skin slides 80 mm over 40 frames (2 mm a frame) stays in the fit, while a swap
    during the slide is still rejected. With the level rule alone (no reference,
    ``gate_memory=-1``) the sliding marker is rejected once past the gate."""
    rig, take = load_rig(EXACT_RIG), _exact_take(noise_mm=0.5)
    pos = take.markers_world.copy()
    i = take.labels.index("LTHI")
    start, ramp = 200, 40
    slide = np.clip((np.arange(len(pos)) - start) / ramp, 0.0, 1.0) * 0.080
    pos[:, i, 2] += slide
    a, b = take.labels.index("RKNL"), take.labels.index("RANL")
    swap = slice(300, 303)
    truth = take.markers_world
    pos[swap, a], pos[swap, b] = truth[swap, b], truth[swap, a]
    base = take.markers_world[take.base_pose_frames]
    cal = calibrate(rig, base, take.labels)

    def solve(**kw: float) -> FitSolve:
        return FitSolver(
            rig, cal, take.labels, base_positions=base, params=FitParams(**kw)
        ).solve_take(pos)

    res, level = solve(), solve(gate_memory=-1)
    ri = rig.marker_names.index("LTHI")
    ra, rb = rig.marker_names.index("RKNL"), rig.marker_names.index("RANL")
    late = slice(start + ramp, start + ramp + 120)
    print(
        f"\nLTHI slid 80 mm: residual there median "
        f"{1e3 * np.median(res.marker_residual[late, ri]):.1f} mm, rejected on "
        f"{res.marker_rejected[:, ri].sum()} frames (level rule: "
        f"{level.marker_rejected[:, ri].sum()}); swap rejected on "
        f"{res.marker_rejected[swap, [ra, rb]].sum()} of 6 samples"
    )
    assert np.median(res.marker_residual[late, ri]) > 0.040  # past the gate
    assert not res.marker_rejected[:, ri].any()
    assert level.marker_rejected[late, ri].all()
    assert res.marker_rejected[swap, ra].all() and res.marker_rejected[swap, rb].all()
    assert np.isfinite(res.world_from_bone_quat).all()


def test_joint_past_its_limit_shows_as_residual_and_fails_validate() -> None:
    """Markers that hyperextend the left knee by 45 deg for 0.5 s (issue 28 item 4):
    the fit keeps the knee within 2 deg of the validator's table and leaves the
    mismatch in the residual of the knee's and foot's markers, so ``validate``
    fails on its residual check, naming them, not on a bent joint."""
    from retargetd.daemon.validate.checks import fit_pairs, validate_take
    from retargetd.daemon.validate.model import build_model

    rig = load_rig(EXACT_RIG)
    take = pf.synthesize(
        seconds=2.0, rate_hz=RATE_HZ, markerset=EXACT_MARKERS, motions=()
    )
    pos = take.markers_world.copy()
    shank = take.segment_names.index("l_shank")
    below = [
        i for i, s in enumerate(take.marker_segments)
        if take.segment_names[s] in ("l_shank", "l_foot", "l_toes")
    ]  # fmt: skip
    frames = slice(int(1.25 * RATE_HZ), int(1.75 * RATE_HZ))
    base = take.markers_world[take.base_pose_frames]
    cal = calibrate(rig, base, take.labels)
    skel = skeleton_from_calibration(rig, cal)
    # hyperextension: a rotation of the shank about the performer's left, opposite to
    # flexion (positive sagittal = flexion in the validator)
    q = rot.quat_from_axis_angle(skel.left_world, np.radians(45.0))
    knee = take.joint_pos_world[frames, shank][:, None, :]
    b = rig.bone_names.index("l_shank")
    for sign in (1.0, -1.0):
        qs = q.copy()
        qs[1:] *= sign
        trial = pos.copy()
        trial[frames, below] = knee + rot.quat_rotate(qs, pos[frames, below] - knee)
        con = BodySolver(rig, cal, take.labels).solve_take(trial)
        viol, which = limit_violation_deg(skel, con.rest_from_bone_quat)
        if viol[frames, b].min() > 20.0 and "sagittal -" in which[frames.start, b]:
            pos = trial
            break
    else:
        pytest.fail("could not build a knee hyperextension")
    solver = FitSolver(
        rig,
        cal,
        take.labels,
        joint_limits=JOINT_LIMITS_DEG,
        segment_kind=SEGMENT_KIND,
        base_positions=base,
        rate_hz=RATE_HZ,
    )
    res = solver.solve_take(pos)
    viol, which = limit_violation_deg(skel, res.rest_from_bone_quat)
    moved = [take.labels[i] for i in below]
    leg = [
        take.labels[i] for i, s in enumerate(take.marker_segments)
        if take.segment_names[s] in ("l_thigh", "l_shank", "l_foot", "l_toes")
    ]  # fmt: skip
    resid_mm = 1000 * np.nanmax(res.marker_residual[frames], axis=0)
    names = [m for m, r in zip(res.marker_names, resid_mm, strict=True) if r > 40.0]
    print(
        f"\nknee hyperextended 45 deg: fit's violation at most "
        f"{viol[:, b].max():.2f} deg; markers past 40 mm: {names}"
    )
    assert viol.max() <= 2.0  # no fitted pose more than 2 deg past the table
    # the mismatch is in the residual, of the moved markers and the knee's
    assert set(names) & set(moved) and set(names) <= set(leg), names
    vm = build_model(skel)
    rep = validate_take(vm, res, RATE_HZ, fit=fit_pairs(rig, res.joint_names))
    assert rep.checks["limits"].n_flagged == 0
    check = rep.checks["marker_residual_max"]
    assert check.n_flagged > 0 and not rep.passed
    named = set(check.markers)  # the markers validate names for the flagged runs
    assert named and named <= set(leg), named  # it points at the knee


# --- rig keys ---------------------------------------------------------------------


def test_fit_keys_parse_and_act(tmp_path: Path) -> None:
    text = EXACT_RIG.read_text() + (
        "\n[fit.markers.LTHI]\nweight = 0.0\n"
        '[fit.markers.LKNL]\nsegment = "l_shank"\n'
        '[fit.bones.l_shank]\ndof = "hinge"\naxis = "x"\n'
    )
    path = tmp_path / "rig.toml"
    path.write_text(text)
    rig, opts = load_fit_rig(path)
    assert load_rig(path).fit == opts == rig.fit  # the rig parser reads [fit]
    assert opts.markers["LTHI"].weight == 0.0
    assert opts.markers["LKNL"].segment == "l_shank"
    assert opts.bones["l_shank"].dof == "hinge"
    take = _exact_take(noise_mm=2.0, seconds=3.0)  # the true knee is a pure hinge
    base = take.markers_world[take.base_pose_frames]
    cal = calibrate(rig, base, take.labels)
    model = build_fit_model(rig, cal, base, take.labels, opts)
    i_thi, i_knl = rig.marker_names.index("LTHI"), rig.marker_names.index("LKNL")
    assert model.marker_weight[i_thi] == 0.0
    assert model.marker_bone[i_knl] == rig.bone_names.index("l_shank")
    b = rig.bone_names.index("l_shank")
    np.testing.assert_allclose(model.hinge_axis[b], [1.0, 0.0, 0.0])
    # without options the model takes the rig's own [fit] keys
    own = build_fit_model(rig, cal, base, take.labels)
    assert own.marker_bone[i_knl] == model.marker_bone[i_knl]
    np.testing.assert_array_equal(own.hinge_axis, model.hinge_axis)
    default = build_fit_model(rig, cal, base, take.labels, FitOptions())
    # by default LKNL rides the thigh (it builds the knee centre, the thigh's aim)
    assert default.marker_bone[i_knl] == rig.bone_names.index("l_thigh")
    # the hinge holds: the knee's rotation off its axis stays small
    res = FitSolver(rig, cal, take.labels, model=model).solve_take(take.markers_world)
    rv = rot.rotvec_from_quat(res.rest_from_bone_quat[:, b])
    off_axis = np.degrees(np.linalg.norm(rv[:, 1:], axis=-1))
    free = FitSolver(rig, cal, take.labels, model=default).solve_take(
        take.markers_world
    )
    rv_free = rot.rotvec_from_quat(free.rest_from_bone_quat[:, b])
    free_off = np.degrees(np.linalg.norm(rv_free[:, 1:], axis=-1))
    print(
        f"\nhinge knee: off-axis max {off_axis.max():.2f} deg "
        f"(ball: {free_off.max():.2f})"
    )
    assert np.median(free_off) > 0.2  # noise moves the free knee off its axis
    assert np.percentile(off_axis, 95) < 0.25 * np.percentile(free_off, 95)
    for bad, message in (
        ({"markers": {"NOPE": {}}}, "unknown marker"),
        ({"markers": {"LTHI": {"segment": "tail"}}}, "unknown bone"),
        ({"markers": {"LTHI": {"weight": -1}}}, "weight"),
        ({"markers": {"LTHI": {"weight": 1e3}}}, r"out of range: allowed \[0, 100\]"),
        ({"bones": {"l_shank": {"dof": "slider"}}}, "dof"),
        ({"bones": {"pelvis": {"dof": "hinge"}}}, "root"),
        ({"bones": {"l_shank": {"dof": "hinge", "axis": [0, 0, 0]}}}, "axis"),
        ({"bones": {"l_shank": {"dof": "hinge", "axis": [2, 0, 0]}}}, r"axis\[0\]"),
        ({"bones": {"l_shank": {"dof": "swing", "axis": "x"}}}, "only a hinge"),
        ({"bones": {"l_shank": {"axis_in": "parent"}}}, "only a hinge"),
        ({"bones": {"l_shank": {"dof": "hinge", "axis_in": "world"}}}, "axis_in"),
        ({"bones": {"l_shank": {"axis_from_bend_deg": 17}}}, "only a hinge"),
        (
            {"bones": {"l_shank": {"dof": "hinge", "axis_from_bend_deg": 95}}},
            r"axis_from_bend_deg: 95 is out of range: allowed \[0, 90\]",
        ),
        (
            {"bones": {"l_shank": {"dof": "hinge", "axis_from_bend_deg": "bent"}}},
            "axis_from_bend_deg: expected a number",
        ),
        ({"bones": {"l_shank": {"axis_markers": ["LKNL", "LTHI"]}}}, "only a hinge"),
        (
            {"bones": {"l_shank": {"dof": "hinge", "axis_markers": ["LKNL"]}}},
            "axis_markers: expected two marker names",
        ),
        (
            {"bones": {"l_shank": {"dof": "hinge", "axis_markers": ["LKNL", "NOPE"]}}},
            "axis_markers: unknown marker 'NOPE'",
        ),
        (
            {"bones": {"l_shank": {"dof": "hinge", "axis_markers": ["LKNL", "LKNL"]}}},
            "axis_markers: two different markers",
        ),
        (
            {
                "bones": {
                    "l_shank": {
                        "dof": "hinge",
                        "axis_markers": ["LKNL", "LTHI"],
                        "axis_from_bend_deg": 10,
                    }
                }
            },
            "not both",
        ),
        ({"bones": {"l_shank": {"dof": "hinge", "twist_to": "LANK"}}}, "hinge_twist"),
        (
            {"bones": {"l_shank": {"dof": "hinge_twist", "twist_to": "NOPE"}}},
            "twist_to: expected a marker or point: 'NOPE'",
        ),
        (
            {"bones": {"l_shank": {"dof": "hinge_twist", "twist_to": ["LANK"]}}},
            "twist_to: expected a marker or point",
        ),
        ({"bones": {"pelvis": {"dof": "swing"}}}, "root"),
        ({"bones": {"pelvis": {"stiffness_mm": 10}}}, "root"),
        ({"bones": {"l_shank": {"stiffness_mm": -1}}}, "out of range"),
        ({"bones": {"l_shank": {"stiffness_mm": 1e9}}}, "out of range"),
        ({"bones": {"l_shank": {"stiffness_mm": float("nan")}}}, "out of range"),
        ({"bones": {"l_shank": {"stiffness_mm": "stiff"}}}, "stiffness_mm"),
        (
            {
                "bones": {
                    "l_foot": {"stiffness_mm": 46, "stiffness_free_plane": ["LHEE"]}
                }
            },
            "stiffness_free_plane: expected two of the rig.s markers",
        ),
        (
            {
                "bones": {
                    "l_foot": {
                        "stiffness_mm": 46,
                        "stiffness_free_plane": ["LHEE", "X"],
                    }
                }
            },
            "stiffness_free_plane: expected two of the rig.s markers",
        ),
        (
            {"bones": {"l_foot": {"stiffness_free_plane": ["LHEE", "LMT1"]}}},
            "stiffness_free_plane: needs a stiffness_mm",
        ),
        ({"other": 1}, "unknown key"),
    ):
        with pytest.raises(RigError, match=message):
            parse_fit_options(rig, bad, source="t.toml")
    # the same errors from the rig file itself, naming the file and the key
    bad_file = tmp_path / "bad.toml"
    bad_file.write_text(text.replace('dof = "hinge"', 'dof = "slider"'))
    with pytest.raises(RigError, match=r"bad.toml: fit.bones.l_shank.dof: expected"):
        load_rig(bad_file)


def _twist_deg(q: np.ndarray) -> np.ndarray:
    """Twist about the bone's own +Y of (..., 4) w x y z rotations, degrees."""
    q = np.where(q[..., :1] < 0.0, -q, q)
    return np.degrees(2.0 * np.arctan2(q[..., 2], q[..., 0]))


class _Forearms(NamedTuple):
    text: str  # the rig file's text
    path: Path
    rig: Rig
    opts: FitOptions
    take: pf.SynthTake
    base: np.ndarray  # the base-pose frames
    cal: Calibration
    model: Any
    idx: list[int]  # the forearms' bone indices
    res: FitSolve  # the fit with the keys
    ball: FitSolve  # the fit with ball joints


def _forearms_as(tmp_path: Path, keys: str, noise_mm: float) -> _Forearms:
    """The exact rig with ``keys`` (TOML lines) on both forearms, on the synthetic
    take, fitted with those keys and with ball joints."""
    bones = ("l_forearm", "r_forearm")
    text = EXACT_RIG.read_text() + "".join(
        f"\n[fit.bones.{b}]\n{keys}\n" for b in bones
    )
    path = tmp_path / "rig.toml"
    path.write_text(text)
    rig, opts = load_fit_rig(path)
    take = _exact_take(noise_mm=noise_mm, seconds=3.0)
    base = take.markers_world[take.base_pose_frames]
    cal = calibrate(rig, base, take.labels)
    model = build_fit_model(rig, cal, base, take.labels, opts)
    idx = [rig.bone_names.index(b) for b in bones]
    res = FitSolver(rig, cal, take.labels, model=model).solve_take(take.markers_world)
    ball = FitSolver(
        rig, cal, take.labels, model=build_fit_model(rig, cal, base, take.labels,
                                                     FitOptions())
    ).solve_take(take.markers_world)  # fmt: skip
    return _Forearms(text, path, rig, opts, take, base, cal, model, idx, res, ball)


def _forearms_twist_to(
    tmp_path: Path, keys: str, noise_mm: float, name: str
) -> tuple[_Forearms, Path]:
    """:func:`_forearms_as`, then its rig again with the ulnar styloid's points
    (``LUS``/``RUS``, at u = 95 / 120 on the line from WRA to WRB) and each
    forearm's ``twist_to`` naming them, written to ``name``."""
    points = "".join(
        f'\n[points.{s.upper()}US]\nline = ["{s.upper()}WRA", "{s.upper()}WRB"]\n'
        f"u = {95.0 / 120.0!r}\n"
        for s in ("l", "r")
    )
    own = _forearms_as(tmp_path, keys, noise_mm=noise_mm)
    rig_text = EXACT_RIG.read_text()
    text = own.text.replace(rig_text, rig_text + points)
    for s in ("l", "r"):
        text = text.replace(
            f"[fit.bones.{s}_forearm]\n{keys}\n",
            f'[fit.bones.{s}_forearm]\n{keys}\ntwist_to = "{s.upper()}US"\n',
        )
    path = tmp_path / name
    path.write_text(text)
    return own, path


def test_swing_joint_has_no_twist(tmp_path: Path) -> None:
    """``dof = "swing"``: the joint keeps two rotations; its twist about the bone's
    long axis stays at the calibration's (a clavicle whose one marker cannot see its
    axial rotation), while the same bones as ball joints follow the truth's twist."""
    f = _forearms_as(tmp_path, 'dof = "swing"', noise_mm=0.5)
    model, idx, res, ball = f.model, f.idx, f.res, f.ball
    assert all(f.opts.bones[b].dof == "swing" for b in ("l_forearm", "r_forearm"))
    assert (model.twist_lock[idx] == 1.0).all() and model.twist_lock.sum() == 2.0
    locked = np.abs(_twist_deg(res.rest_from_bone_quat[:, idx]))
    free = np.abs(_twist_deg(ball.rest_from_bone_quat[:, idx]))
    print(
        f"\nswing forearms: twist max {locked.max():.3f} deg (ball: p95 "
        f"{np.percentile(free, 95):.1f}, max {free.max():.1f}); marker RMS median "
        f"{1e3 * np.nanmedian(res.marker_rms):.2f} mm (ball "
        f"{1e3 * np.nanmedian(ball.marker_rms):.2f})"
    )
    assert np.percentile(free, 95) > 5.0  # the performer's forearms do twist
    assert locked.max() < 0.5
    assert np.isfinite(res.world_from_bone_quat).all()


def test_swing_forbids_the_twist_about_twist_to(tmp_path: Path) -> None:
    """``dof = "swing"`` with ``twist_to``: the rotation the joint forbids is the one
    about the line from the bone's origin to that point (a hand's long axis, the
    forearm's at neutral, where the hand bone aims at a marker off it), not about
    the bone's own +Y: the model's twist axis is that line, the observed rotations
    are perpendicular to it, and the solve keeps the twist about it at the
    calibration's while the twist about +Y moves with the swing."""
    own, path = _forearms_twist_to(tmp_path, 'dof = "swing"', 0.5, "rig_swing_to.toml")
    rig, opts = load_fit_rig(path)
    assert opts.bones["r_forearm"].twist_to == "RUS"
    cal = calibrate(rig, own.base, own.take.labels)
    model = build_fit_model(rig, cal, own.base, own.take.labels, opts)
    assert (model.twist_lock[own.idx] == 1.0).all()
    res = FitSolver(rig, cal, own.take.labels, model=model).solve_take(
        own.take.markers_world
    )
    for b in own.idx:
        a = model.twist_axis[b]
        off = np.degrees(np.arccos(abs(float(a[1]))))
        assert 3.0 < off < 15.0, off  # the styloid line, 7.4 deg off the bone's axis
        obs = model.observation[b]
        np.testing.assert_allclose(obs.axes @ a, 0.0, atol=1e-12)
        q = res.rest_from_bone_quat[:, b]
        about_a = np.degrees(np.abs(rot.twist_angle(q, a)))
        about_y = np.degrees(np.abs(rot.twist_angle(q, np.array([0.0, 1.0, 0.0]))))
        own_y = np.abs(_twist_deg(own.res.rest_from_bone_quat[:, b]))
        print(
            f"\n{rig.bone_names[b]}: twist about twist_to max {about_a.max():.3f} "
            f"deg, about +Y max {about_y.max():.2f} (swing about +Y: {own_y.max():.3f})"
        )
        assert about_a.max() < 0.5  # locked about the line (as +Y is without it)
        assert about_y.max() > 1.0  # and no longer about +Y
        assert own_y.max() < 0.5
    assert np.isfinite(res.world_from_bone_quat).all()


def _off_cone_deg(q: np.ndarray, h: np.ndarray) -> np.ndarray:
    """How far (degrees) rotations q (..., 4) put the bone's +Y off the cone a hinge
    about the unit axis h (bone rest axes) sweeps it on."""
    y = rot.quat_rotate(q, np.array([0.0, 1.0, 0.0]))
    return np.degrees(np.abs(np.arcsin(np.clip(y @ h, -1, 1)) - np.arcsin(h[1])))


def test_hinge_twist_elbow_flexes_about_the_parents_axis_and_twists(
    tmp_path: Path,
) -> None:
    """``dof = "hinge_twist"``, ``axis_in = "parent"``: the synthetic performer's
    elbows flex about the upper arm's epicondyle axis (its +X, up = the epicondyle
    pair) and its forearms pronate +-70 deg (about the ISB's axis, 7.4 deg off
    their own; with ``twist_to`` below). As such joints, twisting about their own
    axis, the forearms stay on the hinge's cone (as ball joints noise moves them off
    it) and still follow the truth's twist."""
    keys = 'dof = "hinge_twist"\naxis = "x"\naxis_in = "parent"'
    f = _forearms_as(tmp_path, keys, noise_mm=1.0)
    text, path, rig, take, base, cal = f.text, f.path, f.rig, f.take, f.base, f.cal
    model, idx, res, ball = f.model, f.idx, f.res, f.ball
    assert all(f.opts.bones[b].axis_in == "parent" for b in ("l_forearm", "r_forearm"))
    assert (model.twist_lock[idx] == 2.0).all() and model.twist_lock.sum() == 4.0
    for b in idx:  # the parent's +X in the bone's rest axes
        want = rot.quat_rotate(rot.quat_conj(model.rest_pfb[b]), np.eye(3)[0])
        np.testing.assert_allclose(model.hinge_axis[b], want, atol=1e-12)
    off, off_ball = (
        np.stack([_off_cone_deg(r.rest_from_bone_quat[:, b], model.hinge_axis[b])
                  for b in idx])
        for r in (res, ball)
    )  # fmt: skip
    err = _bone_errors_deg(rig, cal, res, take)[:, idx]
    twist = np.abs(_twist_deg(res.rest_from_bone_quat[:, idx]))
    print(
        f"\nhinge_twist elbows: off the cone p95 {np.percentile(off, 95):.3f} deg "
        f"(ball {np.percentile(off_ball, 95):.3f}); forearm error median "
        f"{np.median(err):.2f} p95 {np.percentile(err, 95):.2f} deg; twist p95 "
        f"{np.percentile(twist, 95):.1f} deg"
    )
    assert np.percentile(twist, 95) > 30.0  # the twist stays free
    assert np.median(err) <= 1.0 and np.percentile(err, 95) <= 3.0
    assert np.percentile(off, 95) < 0.25 * np.percentile(off_ball, 95)
    # The axis must leave the bone a hinge: one along the bone's own axis is refused.
    along = text.replace('axis = "x"\naxis_in = "parent"', 'axis = "y"')
    path.write_text(along)
    with pytest.raises(CalibrationError, match="hinge axis is within 30 deg"):
        build_fit_model(rig, cal, base, take.labels, load_fit_rig(path)[1])


def test_hinge_twist_pronates_about_twist_to(tmp_path: Path) -> None:
    """``twist_to``: the performer pronates about the line from the elbow centre to
    the ulnar styloid (``synth.skeleton.pronation_axis``, the ISB's forearm axis),
    7.4 deg off the exact rig's forearm bone (which aims at the wrist centre). A
    point on that line (the styloid: 35 of the bar's 60 mm to the little-finger side)
    named in ``twist_to`` gives the fit that axis; twisting about the bone's own +Y
    instead, a pronation swings the styloid side off the hinge's plane and the fit
    turns the humerus to follow."""
    keys = 'dof = "hinge_twist"\naxis = "x"\naxis_in = "parent"'
    own, path = _forearms_twist_to(tmp_path, keys, 1.0, "rig_twist_to.toml")
    rig, opts = load_fit_rig(path)
    assert opts.bones["l_forearm"].twist_to == "LUS"
    cal = calibrate(rig, own.base, own.take.labels)  # (the rig has two more points)
    model = build_fit_model(rig, cal, own.base, own.take.labels, opts)
    for side, b in zip("lr", own.idx, strict=True):
        # the fit's axis and the truth's, as lines in the world at frame 0
        k = own.take.segment_names.index(f"{side}_forearm")
        truth = rot.quat_rotate(
            own.take.world_from_segment_quat[0, k], pf_skeleton.pronation_axis(side)
        )
        fit = rot.quat_rotate(cal.rest_world_from_bone_quat[b], model.twist_axis[b])
        off = np.degrees(np.arccos(min(1.0, abs(float(fit @ truth)))))
        assert off < 0.5, (side, off)  # 1 mm of noise over the 272 mm line: 0.2 deg
    res = FitSolver(rig, cal, own.take.labels, model=model).solve_take(
        own.take.markers_world
    )
    arms = [rig.bone_names.index(b) for b in ("l_upper_arm", "r_upper_arm")]
    err = _bone_errors_deg(rig, cal, res, own.take)
    err_own = _bone_errors_deg(own.rig, own.cal, own.res, own.take)
    p95 = np.percentile(err[:, arms + own.idx], 95, axis=0)
    p95_own = np.percentile(err_own[:, arms + own.idx], 95, axis=0)
    print(
        f"\ntwist_to: upper arms, forearms p95 {np.round(p95, 2)} deg; about +Y "
        f"{np.round(p95_own, 2)}"
    )
    assert (p95_own[:2] > 3.0).all()  # the own axis turns the humerus
    assert (p95 <= 3.0).all()  # test_exact_rig_1mm_noise: p95 within 3 deg


def test_a_hinge_bent_in_the_calibration_pose_turns_about_its_bend() -> None:
    """``axis_from_bend_deg``: a rest pose bent past it gives the hinge the axis
    perpendicular to the bone and its parent there (signed like ``axis``), whatever
    the declared axis; a straighter one keeps the declared axis."""
    from retargetd.daemon.body.rig_fit import BoneFitOptions, hinge_axes_in_bone

    true_axis = np.array([0.3, 0.0, -1.0]) / np.hypot(0.3, 1.0)  # in the parent
    declared = (1.0, 0.0, 0.2)  # the parent's +X, near the truth but not on it
    for bend_deg, from_bend in ((40.0, True), (10.0, False)):
        q = rot.quat_from_axis_angle(true_axis, np.deg2rad(bend_deg))
        opts = BoneFitOptions(
            dof="hinge_twist", axis=declared, axis_in="parent", axis_from_bend_deg=17.0
        )
        got = hinge_axes_in_bone({"fore": opts}, ["upper", "fore"], np.stack([q, q]))
        want_parent = true_axis if from_bend else np.asarray(declared)
        want = rot.quat_rotate(rot.quat_conj(q), want_parent)
        want = want / np.linalg.norm(want)
        if from_bend:
            want = want * np.sign(want @ rot.quat_rotate(rot.quat_conj(q), declared))
        np.testing.assert_allclose(got["fore"], want, atol=1e-12)


def test_a_knee_turns_about_its_epicondyles_not_a_frame_made_from_the_hip() -> None:
    """``axis_markers``: menache's knee flexes about the line through the femoral
    epicondyle markers where the calibration saw them, not about the thigh frame's
    +X (that line made perpendicular to a thigh whose top is the hip centre's
    estimate, 21 mm off on the synthetic performer). Against the truth of a deep
    squat (hips and knees flexed past 100 deg), the thighs stay within 1 deg; with
    the frame's axis, the thigh turns about its own axis to let the knee's wrong
    hinge reach the ankle."""
    import dataclasses

    from retargetd.daemon.body.rig_fit import FitOptions
    from retargetd.daemon.synth.truth import compare_with_truth

    rig = load_rig("menache")
    take = pf.synthesize(
        seconds=6.0, rate_hz=60.0, markerset="menache", motions=("deep_squat",),
        noise_mm=0.0, seed=0,
    )  # fmt: skip
    base = take.markers_world[take.base_pose_frames]
    cal = calibrate(rig, base, take.labels)
    model = build_fit_model(rig, cal, base, take.labels)
    # the axis is the marker line, in the shank's rest axes
    for side in "lr":
        b = rig.bone_names.index(f"{side}loleg")
        p = rig.bone_names.index(f"{side}upleg")
        i, k = (rig.marker_names.index(f"{side.upper()}{m}KNEE") for m in "IE")
        line = model.marker_local[k] - model.marker_local[i]
        assert model.marker_bone[i] == model.marker_bone[k] == p
        want = rot.quat_rotate(rot.quat_conj(model.rest_pfb[b]), line)
        np.testing.assert_allclose(
            model.hinge_axis[b], want / np.linalg.norm(want), atol=1e-12
        )
    frames = slice(take.base_pose_frames.stop, None)
    thighs = {}
    for name, bones in (
        ("markers", rig.fit.bones),
        (
            "frame",
            {
                n: dataclasses.replace(o, axis_markers=())
                for n, o in rig.fit.bones.items()
            },
        ),
    ):
        opts = FitOptions(markers=rig.fit.markers, bones=bones)
        m = build_fit_model(rig, cal, base, take.labels, opts)
        res = FitSolver(rig, cal, take.labels, model=m).solve_take(take.markers_world)
        cmp = compare_with_truth(res, take, rig, frames=frames)
        thighs[name] = max(
            cmp.p95_deg[cmp.bone_names.index(b)] for b in ("lupleg", "rupleg")
        )
    print(f"\nthighs p95 against the truth, deep squat: {thighs}")
    assert thighs["markers"] <= 1.0
    assert thighs["frame"] > 5.0  # what the frame's axis did (the test can fail)


def test_stiffness_pulls_towards_the_calibration_pose(tmp_path: Path) -> None:
    """``stiffness_mm``: a pull of the joint towards its calibration pose. At a
    hinge's stiffness (1000 mm/rad) the forearms stay near their calibration pose
    while their markers move them; at 0 the model is the default one."""
    bones = ("l_forearm", "r_forearm")
    take = _exact_take(noise_mm=0.5, seconds=3.0)
    base = take.markers_world[take.base_pose_frames]
    results = {}
    for stiff in (0, 1000):
        path = tmp_path / f"rig{stiff}.toml"
        path.write_text(
            EXACT_RIG.read_text()
            + "".join(f"\n[fit.bones.{b}]\nstiffness_mm = {stiff}\n" for b in bones)
        )
        rig, opts = load_fit_rig(path)
        cal = calibrate(rig, base, take.labels)
        model = build_fit_model(rig, cal, base, take.labels, opts)
        idx = [rig.bone_names.index(b) for b in bones]
        assert np.allclose(model.prior_mat[idx], (stiff / 1000.0) ** 2 * np.eye(3))
        # the exact rig's markers observe every rotation: no automatic prior
        assert np.trace(model.prior_mat, axis1=1, axis2=2).sum() == pytest.approx(
            6 * (stiff / 1000.0) ** 2
        )
        res = FitSolver(rig, cal, take.labels, model=model).solve_take(
            take.markers_world
        )
        results[stiff] = (
            np.degrees(rot.quat_angle(res.rest_from_bone_quat[:, idx])),
            res,
        )
    free, stiff_ = results[0][0], results[1000][0]
    print(
        f"\nforearms from their calibration pose: free median {np.median(free):.1f}"
        f" deg, at 1000 mm/rad {np.median(stiff_):.1f} deg"
    )
    assert np.median(free) > 20.0  # the performer's elbows flex
    assert np.median(stiff_) < 0.5 * np.median(free)
    # stiffness 0 is the default model, frame for frame
    default = FitSolver(
        load_rig(EXACT_RIG),
        calibrate(load_rig(EXACT_RIG), base, take.labels),
        take.labels,
        base_positions=base,
    ).solve_take(take.markers_world)
    np.testing.assert_array_equal(
        default.world_from_bone_quat, results[0][1].world_from_bone_quat
    )


def test_stiffness_free_plane_spares_the_rotation_in_its_markers_plane(
    tmp_path: Path,
) -> None:
    """``stiffness_free_plane``: the pull spares the rotation about the normal of the
    plane through the joint and the two markers (a foot's plantarflexion, which its
    heel and toe markers see at their full lever) and acts on the two rotations in
    that plane (the roll about the heel-toe line, the turn about the vertical) as on
    every rotation without the key; two markers of another bone are the rig's
    error."""
    take = _exact_take(noise_mm=0.0, seconds=1.0)
    base = take.markers_world[take.base_pose_frames]
    path = tmp_path / "rig.toml"
    path.write_text(
        EXACT_RIG.read_text()
        + "\n[fit.bones.l_foot]\nstiffness_mm = 46\n"
        + 'stiffness_free_plane = ["LHEE", "LMT1"]\n'
    )
    rig, opts = load_fit_rig(path)
    cal = calibrate(rig, base, take.labels)
    model = build_fit_model(rig, cal, base, take.labels, opts)
    b = rig.bone_names.index("l_foot")
    i, k = (rig.marker_names.index(m) for m in ("LHEE", "LMT1"))
    heel, toe = model.marker_local[i], model.marker_local[k]
    normal = np.cross(heel, toe)
    normal /= np.linalg.norm(normal)
    pull = model.prior_mat[b]
    assert np.linalg.matrix_rank(pull, tol=1e-9) == 2
    np.testing.assert_allclose(pull @ normal, 0.0, atol=1e-12)  # spared
    line = (toe - heel) / np.linalg.norm(toe - heel)  # the roll: pulled in full
    np.testing.assert_allclose(pull @ line, 0.046**2 * line, atol=1e-12)
    third = np.cross(normal, line)  # the turn in the plane: pulled in full
    np.testing.assert_allclose(pull @ third, 0.046**2 * third, atol=1e-12)
    # the joint on the markers' line: no plane, the pull on every rotation
    np.testing.assert_allclose(
        stiffness_matrix(46.0, np.zeros(3)), 0.046**2 * np.eye(3), atol=1e-15
    )
    bad = tmp_path / "bad.toml"
    bad.write_text(path.read_text().replace('"LMT1"]', '"LKNL"]'))
    rig_bad, opts_bad = load_fit_rig(bad)
    with pytest.raises(
        CalibrationError, match=r"stiffness_free_plane.*must both ride l_foot"
    ):
        build_fit_model(rig_bad, calibrate(rig_bad, base, take.labels), base,
                        take.labels, opts_bad)  # fmt: skip


# --- kernel contract --------------------------------------------------------------


def test_one_frame_equals_batch_and_allocates_nothing() -> None:
    rig = load_rig(EXACT_RIG)
    take = _exact_take(noise_mm=0.5, dropout=0.05, seconds=3.0)
    _, solver = _solver(rig, take)
    # Writable frames, as the live loop's: the synthetic take's are read-only, a
    # type numba compiles the whole fit for a second time.
    frames = np.array(take.markers_world)
    batch = solver.solve_take(frames)
    solver.reset()
    pose = solver.new_pose()
    wfb = np.zeros_like(batch.world_from_bone_quat)
    for f in range(20):
        solver.solve_frame(frames[f], pose)
        wfb[f] = pose.world_from_bone_quat
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        start, _ = tracemalloc.get_traced_memory()
        for f in range(20, take.n_frames):
            out = solver.solve_frame(frames[f], pose)
        end, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert out is pose
    kept, top = end - start, peak - start
    print(f"\nsolve_frame: {kept} bytes kept, peak {top} bytes over the calls")
    assert kept < 1024
    # the peak is numba's boxing of one call's arguments: 1.1 KB for the packed
    # call's 13 (fit_pack), 5.2 KB when it took ~100 arrays; a per-frame (Mr, 3)
    # float64 array more (1.7 KB) would cross the line
    assert top < 2600
    # one frame at a time is the batch, bit for bit
    solver.reset()
    for f in range(take.n_frames):
        solver.solve_frame(frames[f], pose)
        wfb[f] = pose.world_from_bone_quat
    np.testing.assert_array_equal(wfb, batch.world_from_bone_quat)
    np.testing.assert_array_equal(pose.root_pos, batch.root_pos[-1])
    np.testing.assert_array_equal(pose.marker_residual, batch.marker_residual[-1])


def test_a_read_only_take_compiles_the_fit_once() -> None:
    """A read-only take (the synthetic performer's, a memory map) is its own type to
    numba: ``solve_take`` passes it on writable, so the batch fit is compiled for one
    type (a cold compile of its tree took ~50 s on this 2-core VM)."""
    from retargetd.daemon.body import kernel_fit

    rig = load_rig(EXACT_RIG)
    take = _exact_take(noise_mm=0.5, dropout=0.05, seconds=1.0)
    assert not take.markers_world.flags.writeable
    _, solver = _solver(rig, take)
    writable = solver.solve_take(np.array(take.markers_world))
    solver.reset()
    read_only = solver.solve_take(take.markers_world)
    assert kernel_fit.fit_many.signatures
    assert all(sig[0].mutable for sig in kernel_fit.fit_many.signatures)
    np.testing.assert_array_equal(
        read_only.world_from_bone_quat, writable.world_from_bone_quat
    )


def test_packed_call_equals_the_tuple_call() -> None:
    """The live call (fit_pack's flat buffers) and a hand-made pose's call (the
    arrays one by one) run the same kernel on the same memory: equal bit for bit."""
    rig = load_rig(EXACT_RIG)
    take = _exact_take(noise_mm=0.5, dropout=0.05, seconds=1.0)
    _, solver = _solver(rig, take)
    packed = solver.new_pose()
    assert packed.fit_buffers is not None
    by_hand = FitPose(
        **{
            name: getattr(packed, name).copy()
            for name in (
                "joint_centres", "world_from_bone_quat", "parent_from_bone_quat",
                "rest_from_bone_quat", "root_pos", "bone_quality", "bone_flags",
                "marker_residual", "marker_rejected", "stats",
            )
        }
    )  # fmt: skip
    assert by_hand.fit_buffers is None
    got = {
        k: np.zeros((take.n_frames, *packed.world_from_bone_quat.shape)) for k in "ab"
    }
    # the counts: the packed call's from the kernel (fit_one's high word), the
    # hand-made pose's counted in numpy from its residuals
    counts = {k: np.zeros((take.n_frames, 3), dtype=np.int64) for k in "ab"}
    frames = np.array(take.markers_world)  # writable, as the live loop's (one compile)
    for key, pose in (("a", packed), ("b", by_hand)):
        solver.reset()
        for f in range(take.n_frames):
            solver.solve_frame(frames[f], pose)
            got[key][f] = pose.world_from_bone_quat
            counts[key][f] = pose.n_held, pose.n_occluded, pose.frame_flags
    np.testing.assert_array_equal(got["a"], got["b"])
    np.testing.assert_array_equal(counts["a"], counts["b"])
    assert counts["a"][:, 1].max() > 0  # (5% dropout: markers hidden on some frames)
    np.testing.assert_array_equal(packed.marker_residual, by_hand.marker_residual)
    np.testing.assert_array_equal(packed.stats, by_hand.stats)
    assert np.isfinite(got["a"]).all() and np.abs(got["a"]).sum() > 0.0


def test_pack_checks_the_kinds() -> None:
    arrays = (np.arange(3, dtype=np.int64), np.ones((2, 4)), np.zeros(2, dtype=bool))
    bufs, rows, views = fit_pack.pack(arrays, (("i8", 1), ("f8", 2), ("b1", 1)))
    for a, v in zip(arrays, views, strict=True):
        np.testing.assert_array_equal(a, v)
        assert v.flags.c_contiguous and v.flags.writeable
    assert rows.tolist() == [[0, 3, 1, 1], [0, 2, 4, 1], [0, 2, 1, 1]]
    views[1][1, 2] = 7.0  # a view is the buffer's memory
    assert bufs["f8"][6] == 7.0
    with pytest.raises(ValueError, match="array 1"):
        fit_pack.pack(arrays, (("i8", 1), ("f8", 1), ("b1", 1)))


def test_pack_views_equal_reshaped_slices() -> None:
    """The views the kernels build (``fit_pack._view``, a numba intrinsic with no
    size check) are the slices ``reshape`` gives: same values, shape, strides and
    memory, 1 to 3 dimensions, at offsets inside the buffer."""
    import numba

    view = fit_pack._view

    @numba.njit
    def both(b: np.ndarray, lay: np.ndarray) -> tuple:
        a1, r1 = (
            view(b, lay[0, 0], (lay[0, 1],)),
            fit_pack.view_by_reshape(b, lay[0, 0], (lay[0, 1],)),
        )
        a2 = view(b, lay[1, 0], (lay[1, 1], lay[1, 2]))
        r2 = fit_pack.view_by_reshape(b, lay[1, 0], (lay[1, 1], lay[1, 2]))
        a3 = view(b, lay[2, 0], (lay[2, 1], lay[2, 2], lay[2, 3]))
        r3 = fit_pack.view_by_reshape(b, lay[2, 0], (lay[2, 1], lay[2, 2], lay[2, 3]))
        a3[1, 2, 0] = -1.0  # written through the view: the buffer's memory
        return a1, r1, a2, r2, a3, r3

    buf = np.arange(100.0)
    lay = np.array([[3, 7, 1, 1], [10, 4, 5, 1], [31, 2, 3, 4]], dtype=np.int64)
    a1, r1, a2, r2, a3, r3 = both(buf, lay)
    for a, r in ((a1, r1), (a2, r2), (a3, r3)):
        np.testing.assert_array_equal(a, r)
        assert a.shape == r.shape and a.strides == r.strides and a.flags.c_contiguous
        assert a.__array_interface__["data"][0] == r.__array_interface__["data"][0]
    assert buf[31 + 1 * 12 + 2 * 4] == -1.0 and a2[0, 0] == 10.0 and a3[1, 0, 0] == 43


def _nrt_allocs() -> int:
    nrt = pytest.importorskip("numba.core.runtime._nrt_python")
    if not hasattr(nrt, "memsys_enable_stats"):
        pytest.skip("numba has no NRT statistics switch")
    nrt.memsys_enable_stats()
    return int(nrt.memsys_get_stats_alloc())


def test_kernel_allocates_nothing_per_frame() -> None:
    """numba's own heap: the batch's allocations do not grow with the frames, through
    dropouts, a label swap (gating) and a gap that forces a reseed."""
    rig = load_rig(EXACT_RIG)
    take = _exact_take(noise_mm=0.5, dropout=0.05, seconds=3.0)
    frames = np.array(take.markers_world)
    frames[200:203, [0, 30]] = frames[200:203, [30, 0]]
    frames[250:260] = np.nan
    base = take.markers_world[take.base_pose_frames]
    solver = FitSolver(rig, calibrate(rig, base, take.labels), take.labels,
                       joint_limits=JOINT_LIMITS_DEG, segment_kind=SEGMENT_KIND,
                       base_positions=base)  # fmt: skip

    def allocs(pos: np.ndarray) -> int:
        solver.reset()
        solver.solve_take(pos[:2])
        solver.reset()
        start = _nrt_allocs()
        solver.solve_take(pos)
        return _nrt_allocs() - start

    assert allocs(frames) == allocs(frames[:1])


def test_never_nan_with_everything_hidden() -> None:
    rig, take = load_rig(EXACT_RIG), _exact_take(seconds=3.0)
    pos = take.markers_world.copy()
    pos[200:260] = np.nan  # half a second with no marker at all
    pos[280:300, :40] = np.nan  # then half the body
    _, _, res = _fit(rig, take, pos)
    assert (
        np.isfinite(res.world_from_bone_quat).all() and np.isfinite(res.root_pos).all()
    )
    assert np.isfinite(res.joint_centres).all()
    assert ((res.bone_flags[200:260] & FLAG_HELD) != 0).all()
    # everything held still: the pose of the last frame before the gap
    held = np.broadcast_to(res.root_pos[199], (60, 3))
    np.testing.assert_allclose(res.root_pos[200:260], held, rtol=0, atol=1e-3)


def test_warm_up_runs_the_kernel() -> None:
    pose = warm_up()
    assert np.isfinite(pose.world_from_bone_quat).all()
    assert np.isnan(pose.marker_residual[3])  # the hidden marker
    np.testing.assert_allclose(pose.marker_residual[:3], 0.0, atol=1e-6)


# --- real takes -------------------------------------------------------------------

PIG_STATIC = "btkdata/PiG_Calibration-FlatFoot-Full.c3d"
PIG_WALK = "btkdata/PiG_Motion-FlatFoot-Full.c3d"
#: Our joint -> Vicon's point and median limit (mm), as test_pig_fidelity.
PIG_REFERENCE = {
    "HJC": ("FEP", 25.0), "KJC": ("FEO", 15.0), "AJC": ("TIO", 15.0),
    "SJC": ("HUP", 30.0), "EJC": ("HUO", 15.0), "WJC": ("RAO", 15.0),
}  # fmt: skip


def test_pig_walk_joint_centres_against_vicon(datasets: Path) -> None:
    rig = load_rig("plug-in-gait")
    static = load_take(datasets / PIG_STATIC)
    cal = calibrate(
        rig, static.positions, static.labels, take_measurements=static.measurements
    )
    walk = load_take(datasets / PIG_WALK)
    solver = FitSolver(
        rig,
        cal,
        walk.labels,
        joint_limits=JOINT_LIMITS_DEG,
        segment_kind=SEGMENT_KIND,
        base_positions=static.positions,
        base_labels=static.labels,
    )
    res = solver.solve_take(walk.positions)
    print(
        f"\nfit, plug-in-gait walk ({walk.n_frames} frames): marker RMS median "
        f"{1000 * np.nanmedian(res.marker_rms):.1f} mm, p95 "
        f"{1000 * np.nanpercentile(res.marker_rms, 95):.1f}; rejected "
        f"{res.outliers_rejected}; reseeded {int(res.reseeded.sum())}"
    )
    failures = []
    for key, (ref, limit) in PIG_REFERENCE.items():
        for side in "LR":
            ours = res.joint_centres[:, res.joint_names.index(side + key)]
            d = 1000 * np.linalg.norm(ours - walk.references.get(side + ref), axis=-1)
            assert np.isfinite(d).all()
            print(
                f"  {side}{key}: median {np.median(d):5.1f} mm, p95 "
                f"{np.percentile(d, 95):5.1f} (limit {limit:g})"
            )
            if np.median(d) > limit:
                failures.append(f"{side}{key} {np.median(d):.1f} mm")
    assert not failures, failures
    assert np.isfinite(res.marker_rms).all()


def test_pig_walk_swapped_labels_rejected(datasets: Path) -> None:
    """LFHD and RFHD swapped (a left-right label swap) for 3 frames of the real walk:
    both rejected in those frames, every bone within 3 deg of the fit of the
    untouched take."""
    rig = load_rig("plug-in-gait")
    static = load_take(datasets / PIG_STATIC)
    cal = calibrate(
        rig, static.positions, static.labels, take_measurements=static.measurements
    )
    walk = load_take(datasets / PIG_WALK)

    def fit(pos: np.ndarray) -> FitSolve:
        solver = FitSolver(
            rig,
            cal,
            walk.labels,
            joint_limits=JOINT_LIMITS_DEG,
            segment_kind=SEGMENT_KIND,
            base_positions=static.positions,
            base_labels=static.labels,
        )
        return solver.solve_take(pos)

    clean = fit(walk.positions)
    pos = walk.positions.copy()
    a, b = walk.labels.index("LFHD"), walk.labels.index("RFHD")
    frames = slice(150, 153)
    assert np.isfinite(pos[frames, [a, b]]).all()
    pos[frames, a], pos[frames, b] = (
        walk.positions[frames, b],
        walk.positions[frames, a],
    )
    res = fit(pos)
    diff = rot.quat_mul(
        rot.quat_conj(clean.world_from_bone_quat), res.world_from_bone_quat
    )
    err = np.degrees(rot.quat_angle(diff))
    ra, rb = rig.marker_names.index("LFHD"), rig.marker_names.index("RFHD")
    extra = res.outliers_rejected - clean.outliers_rejected
    print(
        f"\nPiG walk, LFHD/RFHD swapped for 3 frames: {extra} more rejected; largest "
        f"bone change {err.max():.2f} deg "
        f"({rig.bone_names[int(np.argmax(err.max(axis=0)))]})"
    )
    assert (
        res.marker_rejected[frames, ra].all() and res.marker_rejected[frames, rb].all()
    )
    assert extra >= 6
    assert err.max() <= 3.0


def test_walking2_streams_every_frame_without_nan(datasets: Path) -> None:
    take = load_take(datasets / "opensim-core" / "walking2.c3d")
    rig = load_rig(DATA / "walking2-rig.toml")
    cols = np.asarray(match_markers(rig, take.labels))
    seen = np.isfinite(take.positions[:, cols]).all(axis=-1) & (cols >= 0)
    full = np.flatnonzero(seen.all(axis=1))
    start = next(i for i in full if (full[(full >= i) & (full < i + 10)].size == 10))
    window = slice(start, start + 10)
    pos = take.positions[window]

    def mean(label: str) -> np.ndarray:
        return pos[:, take.labels.index(label)].mean(axis=0)

    pw = 1000 * np.linalg.norm(mean("LASI") - mean("RASI"))
    pd = 1000 * np.linalg.norm(
        (mean("LASI") + mean("RASI")) / 2 - (mean("LPSI") + mean("RPSI")) / 2
    )
    cal = calibrate(
        rig, pos, take.labels, overrides={"InterAsisDistance": pw, "PelvisDepth": pd}
    )
    solver = FitSolver(
        rig,
        cal,
        take.labels,
        joint_limits=JOINT_LIMITS_DEG,
        segment_kind=SEGMENT_KIND,
        base_positions=pos,
    )
    pose = solver.new_pose()
    held = 0
    for f in range(take.n_frames):
        solver.solve_frame(take.positions[f], pose)
        assert np.isfinite(pose.world_from_bone_quat).all(), f
        assert (
            np.isfinite(pose.joint_centres).all() and np.isfinite(pose.root_pos).all()
        )
        held += pose.n_held
    print(f"\nwalking2 streamed: {take.n_frames} frames, {held} bone-frames held")
