"""Pose validation against a MuJoCo model of the calibrated skeleton.

The model (``validate_model``), the per-frame checks (``validate``) and the negative
tests: each synthetic defect is flagged by the check meant for it, while the clean
synthetic take and the real PiG walk pass every check (the MOTEK ballet and the tennis
serve, direct and recorded: ``test_validate_takes.py``).

Clean synthetic take: the exact rig on the synthetic performer without the
``forearm_twist`` component: with it, the performer's procedural right forearm passes
~75 mm into its right thigh around t = 2 s (a real defect of the synthetic motion, which
the self-penetration check reports).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import pytest

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.calibration import calibrate
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.body.solve import BodySolve, BodySolver
from retargetd.daemon.validate.checks import (
    THRESHOLDS,
    TakeReport,
    fit_pairs,
    pose_skeleton,
    validate_take,
)
from retargetd.daemon.validate.limits import swing_twist
from retargetd.daemon.validate.model import (
    ValidationModel,
    build_model,
    capsule_radii,
    segment_masses,
    skeleton_from_arrays,
    skeleton_from_calibration,
)

DATA = Path(__file__).resolve().parent.parent / "data"
RATE_HZ = 120.0
DEFECT = slice(20, 110)  # frames of the T-pose hold that get a defect


pytestmark = pytest.mark.usefixtures("mujoco_cwd")


@pytest.fixture
def clean(clean_synth: Any) -> Any:
    """The shared clean synthetic take (``tests/daemon/conftest.py``)."""
    return clean_synth


def _run(s: Any, solve: BodySolve, vm: ValidationModel | None = None) -> TakeReport:
    return validate_take(vm or s.vm, solve, RATE_HZ, fit=s.fit)


def _with(solve: BodySolve, **arrays: np.ndarray) -> BodySolve:
    return dataclasses.replace(solve, **arrays)


def _rechain(s: Any, pfb: np.ndarray) -> np.ndarray:
    """World rotations consistent with ``pfb`` (a defect sent consistently)."""
    rest = s.skel.rest_world_from_bone_quat
    wfb = s.solve.world_from_bone_quat.copy()
    for b, p in enumerate(s.skel.bone_parents):
        if p >= 0:
            rest_pfb = rot.quat_mul(rot.quat_conj(rest[p]), rest[b])
            wfb[:, b] = rot.quat_mul(wfb[:, p], rot.quat_mul(rest_pfb, pfb[:, b]))
    return wfb


def _rotate_bone(s: Any, bone: str, axis_world: np.ndarray, deg: float) -> BodySolve:
    """Bone ``bone`` turned about ``axis_world`` (calibration-pose axes) over the DEFECT
    frames, up to ``deg`` in a smooth bump (no jump), children following, sent
    consistently."""
    b = s.skel.bone_names.index(bone)
    axis = rot.quat_rotate(
        rot.quat_conj(s.skel.rest_world_from_bone_quat[b]), axis_world
    )
    pfb = s.solve.rest_from_bone_quat.copy()
    n = DEFECT.stop - DEFECT.start
    bump = np.sin(np.pi * (np.arange(n) + 0.5) / n)
    turn = rot.quat_from_axis_angle(axis, np.radians(deg) * bump)
    pfb[DEFECT, b] = rot.quat_mul(turn, pfb[DEFECT, b])
    return _with(
        s.solve, rest_from_bone_quat=pfb, world_from_bone_quat=_rechain(s, pfb)
    )


def _flagged(rep: TakeReport) -> set[str]:
    return set(rep.failed())


# --- the model ---------------------------------------------------------------------


def test_model_structure(clean: Any) -> None:
    vm, skel = clean.vm, clean.skel
    m = vm.model
    assert m.nbody == len(skel.bone_names) + 1
    assert m.njnt == len(skel.bone_names)
    assert m.jnt_type[0] == mujoco.mjtJoint.mjJNT_FREE
    assert (m.jnt_type[1:] == mujoco.mjtJoint.mjJNT_BALL).all()
    assert m.nq == 7 + 4 * (len(skel.bone_names) - 1)
    assert m.body_mass[1:].sum() == pytest.approx(70.0)
    masses = segment_masses(skel, 70.0)
    thigh = skel.bone_names.index("l_thigh")
    assert masses[thigh] / 70.0 == pytest.approx(0.1416, rel=0.05)  # de Leva
    radii = capsule_radii(skel)
    assert (radii > 0.01).all() and (radii < 0.15).all()
    # Excluded rest-pose contacts: the calibration pose collides with nothing but the
    # floor, on which the feet stand.
    data = mujoco.MjData(m)
    mujoco.mj_kinematics(m, data)
    mujoco.mj_collision(m, data)
    geoms = data.contact.geom[: data.ncon]
    assert (geoms == vm.floor_geom).any(axis=1).all()
    assert data.contact.dist[: data.ncon].min() > -1e-6
    # The XML reloads to the same model; the cache returns the same object.
    again = mujoco.MjModel.from_xml_string(vm.xml)
    assert again.nq == m.nq and np.allclose(again.body_pos, m.body_pos)
    assert build_model(skeleton_from_calibration(clean.rig, clean.cal)) is vm
    assert build_model(clean.skel, 80.0) is not vm


def test_rest_pose_is_identity(clean: Any) -> None:
    """qpos0 (identity ball joints) poses the calibrated rest origins."""
    data = mujoco.MjData(clean.vm.model)
    mujoco.mj_kinematics(clean.vm.model, data)
    rest = clean.skel.rest_origin_world
    assert np.abs(data.xpos[clean.vm.body_ids] - rest).max() < 1e-9


def test_swing_twist_recomposes() -> None:
    q = rot.quat_normalize(np.random.default_rng(1).normal(size=(50, 4)))
    swing, twist = swing_twist(q)
    assert np.abs(swing[:, 1]).max() < 1e-12  # swing axis perpendicular to +Y
    tq = rot.quat_from_axis_angle(np.array([0.0, 1.0, 0.0]), twist)
    back = rot.quat_mul(rot.quat_from_rotvec(swing), tq)
    assert np.abs(np.abs(np.sum(back * q, axis=-1)) - 1.0).max() < 1e-12


# --- clean takes pass ----------------------------------------------------------------


def test_clean_synthetic_take_passes(clean: Any) -> None:
    rep = _run(clean, clean.solve)
    assert rep.passed, {n: c.summary() for n, c in rep.checks.items() if c.n_flagged}
    assert rep.checks["convention"].values.max() < 1e-6  # mm
    assert rep.checks["fit_max"].values.max() < 1e-3  # mm: exact rig, no noise
    print(f"\nper-frame MuJoCo loop: {1e6 * rep.seconds_per_frame:.1f} us")


def test_pig_walk_passes(datasets: Path) -> None:
    from retargetd.replay.takes import load_take

    rig = load_rig("plug-in-gait")
    static = load_take(datasets / "btkdata/PiG_Calibration-FlatFoot-Full.c3d")
    cal = calibrate(
        rig, static.positions, static.labels, take_measurements=static.measurements
    )
    walk = load_take(datasets / "btkdata/PiG_Motion-FlatFoot-Full.c3d")
    solve = BodySolver(rig, cal, walk.labels).solve_take(walk.positions)
    mass = static.measurements.get("Bodymass", 70.0)
    vm = build_model(skeleton_from_calibration(rig, cal), mass)
    assert vm.model.body_mass[1:].sum() == pytest.approx(mass)
    rep = validate_take(vm, solve, walk.rate_hz, fit=fit_pairs(rig, solve.joint_names))
    lines = [
        f"{n}: max {c.summary()['max']:.3g} {c.unit} (threshold {c.threshold:g})"
        for n, c in rep.checks.items()
    ]
    print("\nPiG walk\n" + "\n".join(lines))
    assert rep.passed, rep.failed()


# --- negative tests ------------------------------------------------------------------


def test_xyzw_quaternions_fail_convention(clean: Any) -> None:
    s = clean.solve
    rep = _run(
        clean,
        _with(
            s,
            world_from_bone_quat=s.world_from_bone_quat[..., [1, 2, 3, 0]],
            rest_from_bone_quat=s.rest_from_bone_quat[..., [1, 2, 3, 0]],
        ),
    )
    assert {"convention", "fit_median"} <= _flagged(rep)
    assert np.median(rep.checks["convention"].values) > 100.0  # mm


def test_world_rotations_as_parent_relative_fail_convention(clean: Any) -> None:
    s = clean.solve
    rep = _run(clean, _with(s, rest_from_bone_quat=s.world_from_bone_quat))
    assert "convention" in _flagged(rep)
    assert rep.checks["convention"].n_flagged == s.root_pos.shape[0]


def test_longer_bone_in_model_fails_convention(clean: Any) -> None:
    lengths = clean.skel.bone_lengths.copy()
    b = clean.skel.bone_names.index("l_thigh")
    lengths[b] *= 1.03
    vm = build_model(skeleton_from_arrays(clean.skel, lengths))
    rep = _run(clean, clean.solve, vm)
    assert _flagged(rep) == {"convention"}
    expect_mm = 0.03 * 1e3 * clean.skel.bone_lengths[b]
    assert rep.checks["convention"].values.min() == pytest.approx(expect_mm, rel=0.02)


def test_teleport_fails_speed(clean: Any) -> None:
    s = clean.solve
    root = s.root_pos.copy()
    root[200:] += [0.3, 0.0, 0.0]
    joints = s.joint_centres.copy()
    joints[200:] += [0.3, 0.0, 0.0]
    rep = _run(clean, _with(s, root_pos=root, joint_centres=joints))
    assert _flagged(rep) == {"root_speed", "effector_speed", "ghost_force"}
    assert np.flatnonzero(rep.checks["root_speed"].flagged).tolist() == [200]


def test_floating_body_fails_floating(clean: Any) -> None:
    s = clean.solve
    lift = np.array([0.0, 0.0, 0.3])
    rep = _run(
        clean,
        _with(s, root_pos=s.root_pos + lift, joint_centres=s.joint_centres + lift),
    )
    assert _flagged(rep) == {"floating", "ghost_force"}


def test_knee_bent_backwards_fails_limits(clean: Any) -> None:
    # +angle about the performer's left flexes the knee: -40 deg is hyperextension.
    solve = _rotate_bone(clean, "l_shank", clean.skel.left_world, -40.0)
    rep = _run(clean, _with(solve, joint_centres=_posed_joints(clean, solve)))
    assert _flagged(rep) == {"limits"}
    limits = rep.checks["limits"]
    flagged = np.flatnonzero(limits.flagged)
    assert DEFECT.start < flagged[0] and flagged[-1] < DEFECT.stop
    assert limits.values.max() == pytest.approx(40.0 - 15.0, abs=0.1)
    assert "l_shank" in limits.detail[0] and "sagittal -" in limits.detail[0]
    # The same angle forwards is an ordinary knee flexion (its toes, turning with the
    # shank, do go through the floor: that check fires, not the limits).
    solve = _rotate_bone(clean, "l_shank", clean.skel.left_world, 40.0)
    rep = _run(clean, _with(solve, joint_centres=_posed_joints(clean, solve)))
    assert "limits" not in _flagged(rep)


def test_one_frame_knee_glitch_is_a_transient(clean: Any) -> None:
    """A knee bent 40 deg backwards for one frame (a marker glitch) is reported as a
    transient, not failed; held for two frames it fails."""
    b = clean.skel.bone_names.index("l_shank")
    axis = rot.quat_rotate(
        rot.quat_conj(clean.skel.rest_world_from_bone_quat[b]), clean.skel.left_world
    )
    for frames in ([60], [60, 61]):
        pfb = clean.solve.rest_from_bone_quat.copy()
        turn = rot.quat_from_axis_angle(axis, np.radians(-40.0))
        pfb[frames, b] = rot.quat_mul(turn, pfb[frames, b])
        solve = _with(
            clean.solve,
            rest_from_bone_quat=pfb,
            world_from_bone_quat=_rechain(clean, pfb),
        )
        rep = _run(clean, _with(solve, joint_centres=_posed_joints(clean, solve)))
        limits = rep.checks["limits"]
        if len(frames) == 1:
            assert "limits" not in _flagged(rep)
            assert limits.transients.tolist() == frames
            assert limits.summary()["transient_frames"] == frames
            assert len(limits.detail) == 1
            assert limits.detail[0].startswith("transient, frame 60: l_shank ")
            assert "sagittal -" in limits.detail[0]
        else:
            assert "limits" in _flagged(rep)
            assert np.flatnonzero(limits.flagged).tolist() == frames
            assert limits.transients.size == 0


def test_sunk_body_fails_floor_penetration(clean: Any) -> None:
    s = clean.solve
    drop = np.array([0.0, 0.0, -0.15])
    rep = _run(
        clean,
        _with(s, root_pos=s.root_pos + drop, joint_centres=s.joint_centres + drop),
    )
    assert _flagged(rep) == {"floor_penetration"}
    assert rep.checks["floor_penetration"].values.max() > 150.0  # mm


def test_legs_crossing_fail_self_penetration(clean: Any) -> None:
    # Adduct the left hip 30 deg (about -forward): the left leg crosses the right.
    forward = np.cross(clean.skel.left_world, [0.0, 0.0, 1.0])
    solve = _rotate_bone(clean, "l_thigh", forward, -30.0)
    rep = _run(clean, _with(solve, joint_centres=_posed_joints(clean, solve)))
    assert _flagged(rep) == {"self_penetration"}
    detail = rep.checks["self_penetration"].detail[0]
    assert "l_" in detail and "r_" in detail


def test_quaternion_norm(clean: Any) -> None:
    s = clean.solve
    pfb = s.rest_from_bone_quat.copy()
    pfb[DEFECT] *= 1.01  # MuJoCo normalises silently: poses unchanged
    rep = _run(clean, _with(s, rest_from_bone_quat=pfb))
    assert _flagged(rep) == {"quat_norm"}


def test_thresholds_are_documented() -> None:
    assert set(THRESHOLDS) >= {"convention_mm", "fit_median_mm", "root_speed_m_s"}


def _posed_joints(s: Any, solve: BodySolve) -> np.ndarray:
    """Joint centres that follow a defect (so only the check meant for it fires)."""
    origins, aims = pose_skeleton(s.skel, solve.root_pos, solve.world_from_bone_quat)
    points = np.concatenate([origins, aims], axis=1)
    joints = solve.joint_centres.copy()
    joints[:, s.fit[0]] = points[:, s.fit[1]]
    return joints


# --- retargetd validate ------------------------------------------------------------


def _validate_argv(datasets: Path, calibration: Path, report: Path) -> list[str]:
    walk = datasets / "btkdata/PiG_Motion-FlatFoot-Full.c3d"
    return [
        "validate", str(walk), "--rig", "plug-in-gait",
        "--calibration", str(calibration), "--report", str(report),
    ]  # fmt: skip


def test_cli_pig_walk_passes(
    datasets: Path, pig_calibration: Path, tmp_path: Path
) -> None:
    import json

    from retargetd.daemon.cli.main import main

    report = tmp_path / "report"
    assert main(_validate_argv(datasets, pig_calibration, report)) == 0
    doc = json.loads((report / "report.json").read_text())
    assert doc["passed"] and doc["body_mass_kg"] == pytest.approx(47.5)  # Bodymass
    assert set(doc["checks"]) >= {"convention", "fit_max", "limits", "floating"}
    assert "PASS" in (report / "report.txt").read_text()
    assert mujoco.MjModel.from_xml_path(str(report / "model.xml")).nbody == 20
    assert not (Path(__file__).resolve().parents[2] / "MUJOCO_LOG.TXT").exists()


def test_cli_exit_codes(
    datasets: Path,
    pig_calibration: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from retargetd.daemon.cli.main import main
    from retargetd.daemon.validate import checks as validate

    argv = _validate_argv(datasets, pig_calibration, tmp_path / "r")
    bad = [*argv[:5], str(tmp_path / "missing.json"), *argv[6:]]
    assert main(bad) == 2
    monkeypatch.setitem(validate.THRESHOLDS, "convention_mm", -1.0)
    assert main(argv) == 1
    assert "FAIL: convention" in (tmp_path / "r" / "report.txt").read_text()

    def boom(*args: object, **kwargs: object) -> None:
        raise RuntimeError("boom")

    monkeypatch.setattr(validate, "validate_take", boom)
    assert main(argv) == 2  # the report folder now holds a report: refused
    assert main([*argv, "--force"]) == 3


def test_limit_detail_names_the_worst_frames(clean: Any) -> None:
    """The detail names bone and angle at the frames most beyond the limit (the
    bump's peak), worst first, then the first flagged frame (issue 31, item 10)."""
    solve = _rotate_bone(clean, "l_shank", clean.skel.left_world, -40.0)
    rep = _run(clean, _with(solve, joint_centres=_posed_joints(clean, solve)))
    limits = rep.checks["limits"]
    flagged = np.flatnonzero(limits.flagged)
    assert flagged.size > 10
    excess = limits.values[flagged]
    worst = flagged[np.argsort(-excess, kind="stable")[:5]]
    lines = limits.detail
    assert len(lines) == 6
    assert [int(line.split(":")[0].split()[-1]) for line in lines[:5]] == list(worst)
    assert lines[5].startswith(f"first flagged, frame {flagged[0]}: l_shank ")
    assert flagged[0] not in worst
    for line, t in zip(lines[:5], worst, strict=True):
        assert f"frame {t}: l_shank " in line and "sagittal -" in line
        assert line.endswith(f"({limits.values[t]:.1f} deg beyond)")
    # Worst first: the values named fall.
    assert list(limits.values[worst]) == sorted(limits.values[worst], reverse=True)
