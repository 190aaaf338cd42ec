"""Deterministic damage to a take's markers and what it does to a solve
(``synth.damage``, issue 28 item 6), and a short run of ``bench/fit_truth.py``."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from bench_scripts import bench_module

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.calibration import calibrate
from retargetd.daemon.body.method import make_body_solver
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.body.solve import BodySolve
from retargetd.daemon.synth import performer as pf
from retargetd.daemon.synth.damage import (
    collapse_markers,
    damage,
    damage_metrics,
    hide_marker,
    mirror_pairs,
    recovery_frames,
    swap_left_right,
    zero_markers,
)

DATA = Path(__file__).resolve().parent.parent / "data"
RATE_HZ = 120.0
Y = np.array([0.0, 1.0, 0.0])


def _about(axis: np.ndarray, deg: np.ndarray | float) -> np.ndarray:
    return rot.quat_from_axis_angle(axis, np.radians(deg))


# --- synth.damage -----------------------------------------------------------------


LABELS = ("SACRUM", "LKNE", "RKNE", "L1", "S:LeftHand", "S:RightHand", "RBAK", "l_toe",
          "r_toe")  # fmt: skip


def _markers() -> np.ndarray:
    rng = np.random.default_rng(0)
    pos = rng.normal(size=(20, len(LABELS), 3))
    pos[3:6, 2] = np.nan  # an occlusion of its own
    return pos


def test_mirror_pairs_by_label() -> None:
    pairs = {(LABELS[i], LABELS[j]) for i, j in mirror_pairs(LABELS)}
    assert pairs == {("LKNE", "RKNE"), ("S:LeftHand", "S:RightHand"),
                     ("l_toe", "r_toe")}  # fmt: skip
    assert mirror_pairs(("LASI", "RASI", "LeftX", "RightX", "L2")) == ((0, 1), (2, 3))


def test_damage_does_what_it_says() -> None:
    pos = _markers()
    keep = pos.copy()
    window = slice(5, 9)
    outside = np.r_[0:5, 9:20]

    hidden = hide_marker(pos, 1, window)
    assert np.isnan(hidden[5:9, 1]).all()
    np.testing.assert_array_equal(np.delete(hidden, 1, axis=1), np.delete(pos, 1, 1))
    np.testing.assert_array_equal(hidden[outside], pos[outside])

    collapsed = collapse_markers(pos, 0, window)
    np.testing.assert_array_equal(collapsed[5:9], np.repeat(pos[5:9, :1], 9, axis=1))
    np.testing.assert_array_equal(collapsed[outside], pos[outside])

    zeros = zero_markers(pos, window)
    assert (zeros[5:9] == 0.0).all() and not np.signbit(zeros[5:9]).any()
    np.testing.assert_array_equal(zeros[outside], pos[outside])

    swapped = swap_left_right(pos, LABELS, window)
    for a, b in (("LKNE", "RKNE"), ("S:LeftHand", "S:RightHand"), ("l_toe", "r_toe")):
        i, j = LABELS.index(a), LABELS.index(b)
        np.testing.assert_array_equal(swapped[5:9, i], pos[5:9, j])
        np.testing.assert_array_equal(swapped[5:9, j], pos[5:9, i])
    for lone in ("SACRUM", "L1", "RBAK"):
        i = LABELS.index(lone)
        np.testing.assert_array_equal(swapped[:, i], pos[:, i])
    np.testing.assert_array_equal(swapped[outside], pos[outside])

    np.testing.assert_array_equal(pos, keep)  # never in place
    np.testing.assert_array_equal(
        damage(pos, LABELS, "collapse", window, marker=0), collapsed
    )
    with pytest.raises(ValueError, match="kind"):
        damage(pos, LABELS, "melt", window)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="frames"):
        zero_markers(pos, slice(25, 30))
    with pytest.raises(ValueError, match="pair"):
        swap_left_right(pos, [f"M{i}" for i in range(len(LABELS))], window)


def test_recovery_frames() -> None:
    dev = np.array([0, 0, 9, 9, 9, 1, 3, 1, 0, 0], dtype=float)
    assert recovery_frames(dev, 2, 2.0) == 5  # outside until frame 6, so 7 - 2
    assert recovery_frames(dev, 7, 2.0) == 0
    assert recovery_frames(dev, 10, 2.0) == 0
    dev[-1] = 2.5
    assert recovery_frames(dev, 2, 2.0) is None  # still outside at the end
    dev[-1] = np.nan
    assert recovery_frames(dev, 2, 2.0) is None


def _solve_of(wfb: np.ndarray, joints: np.ndarray) -> BodySolve:
    n, n_b = wfb.shape[:2]
    return BodySolve(
        joint_names=tuple(f"J{j}" for j in range(joints.shape[1])),
        bone_names=tuple(f"B{b}" for b in range(n_b)),
        bone_parents=(-1, *range(n_b - 1)),
        joint_centres=joints,
        world_from_bone_quat=wfb,
        parent_from_bone_quat=wfb,
        rest_from_bone_quat=wfb,
        root_pos=joints[:, 0],
        bone_lengths=np.ones(n_b),
        bone_quality=np.ones((n, n_b), dtype=np.float32),
        bone_flags=np.zeros((n, n_b), dtype=np.uint8),
    )


def test_damage_metrics_on_a_constructed_solve() -> None:
    n = 50
    z = np.array([0.0, 0.0, 1.0])
    base = np.tile(_about(Y, 10.0), (n, 2, 1))
    joints = np.zeros((n, 2, 3))
    intact = _solve_of(base, joints)
    angle = np.zeros(n)
    angle[10:12], angle[12:15], angle[15] = 30.0, 10.0, 3.0
    angle[16:] = 1.0
    wfb = base.copy()
    wfb[:, 1] = rot.quat_mul(_about(z, angle), base[:, 1])
    moved = joints.copy()
    moved[10:12, 1, 0] = 0.025
    damaged = _solve_of(wfb, moved)
    m = damage_metrics(intact, damaged, slice(10, 12), 100.0, tol_deg=2.0)
    assert m.max_bone_deg == pytest.approx(30.0) and m.max_bone == "B1"
    assert m.max_joint_mm == pytest.approx(25.0) and m.max_joint == "J1"
    # steps into frame 10 (30), 12 (20), 15 (7); 15 -> 16 is 2 deg
    assert m.new_steps == 3 and m.max_new_step_deg == pytest.approx(30.0)
    assert m.recovery_frames == 4 and m.recovery_s == pytest.approx(0.04)
    assert not m.any_nan and m.nan_frames == 0
    # a step the intact solve has too is not new
    both = _solve_of(wfb, joints)
    assert damage_metrics(both, damaged, slice(10, 12), 100.0).new_steps == 0
    # a joint still off holds recovery back; NaN later never recovers by the end
    moved[20:30, 0, 2] = 0.02
    m = damage_metrics(intact, _solve_of(wfb, moved), slice(10, 12), 100.0)
    assert m.recovery_frames == 18
    assert damage_metrics(
        intact, _solve_of(wfb, moved), slice(10, 12), 100.0, tol_mm=None
    ).recovery_frames == 4  # fmt: skip
    wfb[49, 0] = np.nan
    m = damage_metrics(intact, _solve_of(wfb, joints), slice(10, 12), 100.0)
    assert m.any_nan and m.nan_frames == 1 and m.recovery_frames is None


def test_damage_metrics_against_the_truth() -> None:
    """The exact rig's construction is the truth: the damaged solve's truth error
    is its deviation from the intact solve."""
    rig = load_rig(DATA / "synth-exact-rig.toml")
    take = pf.synthesize(
        seconds=3.0, rate_hz=RATE_HZ, markerset=DATA / "synth-exact-markers.toml"
    )
    cal = calibrate(rig, take.markers_world[:120], take.labels)
    solver = make_body_solver("construction", rig, cal, take.labels)
    intact = solver.solve_take(take.markers_world)
    solver.reset()
    window = slice(200, 230)
    pos = hide_marker(take.markers_world, take.labels.index("LMC2"), window)
    m = damage_metrics(intact, solver.solve_take(pos), window, RATE_HZ,
                       truth=take, rig=rig)  # fmt: skip
    assert m.intact_truth_max_deg is not None and m.intact_truth_max_deg <= 1e-6
    assert m.truth_max_deg is not None and m.max_bone == "l_hand"
    assert m.max_bone_deg > 1.0  # the hand held, or rebuilt from two markers
    assert m.truth_max_deg == pytest.approx(m.max_bone_deg, abs=1e-6)


# --- bench/fit_truth.py -----------------------------------------------------------


def test_fit_truth_bench_writes_its_tables(tmp_path: Path) -> None:
    out = tmp_path / "fit-truth.md"
    script = bench_module("fit_truth")
    argv = ["--out", str(out), "--rigs", "menache", "--motions", "default",
            "--methods", "fit", "--seconds", "2", "--damage-at-s", "1.2",
            "--hide-s", "0.05", "--bursts", "2", "--burst-kinds", "zeros",
            "--jobs", "1"]  # fmt: skip
    assert script.main(argv) == 0
    text = out.read_text()
    assert "| menache | default | fit |" in text
    assert "### menache, fit: p95 / max, degrees" in text
    assert "| lhand |" in text
    hide = re.search(
        r"\| hide 0\.05 s \(37 markers, (\d+) past a limit, (\d+) beyond the "
        r"hold\) \|.* \| \**(-?\d+\.\d) \((\w+)\)\** \|\n",
        text,
    )
    assert hide is not None and int(hide.group(1)) <= 37 and int(hide.group(2)) <= 37
    assert hide.group(4) in load_rig("menache").marker_names  # the worst, named
    assert "| damage | joint mm | bone deg | new steps | NaN | recovery " in text
    assert "beyond the hold deg |" in text
    assert "| zeros 2 frames |" in text


def test_fit_truth_bench_adds_the_range_of_motion_calibration(tmp_path: Path) -> None:
    # fit+rom only for a rig with [functional] joints, truth tables only
    out = tmp_path / "fit-truth.md"
    script = bench_module("fit_truth")
    argv = ["--out", str(out), "--rigs", "menache,plug-in-gait", "--motions",
            "default", "--methods", "fit+rom", "--seconds", "2", "--no-damage",
            "--jobs", "1"]  # fmt: skip
    assert script.main(argv) == 0
    text = out.read_text()
    assert "| plug-in-gait | default | fit+rom |" in text
    assert "| menache | default | fit+rom |" not in text
    assert "### plug-in-gait, fit+rom: p95 / max, degrees" in text
