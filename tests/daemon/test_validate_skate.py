"""The stance-foot skate check (issue 34 item 5, ``daemon/validate/skate.py``): the
real PiG walk passes it; the same take with the left foot's markers (LHEE, LTOE,
LANK) slid 5 cm forward during one detected stance fails it, naming the left foot and
frames inside that stance; turned about its midfoot instead it passes (a pivot is no
skate); the synthetic level walk (feet that stay put) passes. The stance is the
detector's (``post/stance.py``), handed
over as ``retargetd validate`` does (``cli.validate.stance_by_bone``)."""

from __future__ import annotations

import functools
import json
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from paths import DATASETS, require

from retargetd.daemon.body.calibration import calibrate
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.body.solve import BodySolver
from retargetd.daemon.cli.validate import stance_by_bone
from retargetd.daemon.validate.checks import (
    THRESHOLDS,
    CheckResult,
    fit_pairs,
    validate_take,
)
from retargetd.daemon.validate.model import build_model, skeleton_from_calibration
from retargetd.daemon.validate.skate import stance_core
from retargetd.replay.takes import load_take

pytestmark = pytest.mark.usefixtures("mujoco_cwd")

PIG_STATIC = "btkdata/PiG_Calibration-FlatFoot-Full.c3d"
PIG_WALK = "btkdata/PiG_Motion-FlatFoot-Full.c3d"
SLIDE_M = 0.05  # "a few cm" over one stance's core (~0.4 s): ~0.12 m/s


@functools.cache
def _pig() -> tuple[Any, Any, Any, Any]:
    require(DATASETS / PIG_WALK, "the PiG walk")
    rig = load_rig("plug-in-gait")
    static = load_take(DATASETS / PIG_STATIC)
    cal = calibrate(
        rig, static.positions, static.labels, take_measurements=static.measurements
    )
    walk = load_take(DATASETS / PIG_WALK)
    vm = build_model(skeleton_from_calibration(rig, cal), 47.5)
    return rig, cal, walk, vm


def _check(positions: np.ndarray) -> tuple[Any, dict[str, np.ndarray]]:
    rig, cal, walk, vm = _pig()
    solve = BodySolver(rig, cal, walk.labels).solve_take(positions)
    stance = stance_by_bone(rig, cal, solve, walk.rate_hz)
    rep = validate_take(
        vm, solve, walk.rate_hz, fit=fit_pairs(rig, solve.joint_names),
        dynamics=False, stance=stance,
    )  # fmt: skip
    return rep.checks["foot_skate"], stance


def _left_stance(stance: dict[str, np.ndarray], rate_hz: float) -> tuple[int, int]:
    """[start, stop) of the left foot's longest detected stance core."""
    edge = round(THRESHOLDS["foot_skate_edge_s"] * rate_hz)
    core = np.concatenate([[False], stance_core(stance["lfoot"], edge), [False]])
    edges = np.flatnonzero(core[1:] != core[:-1])
    runs = list(zip(edges[::2], edges[1::2], strict=True))
    a, b = max(runs, key=lambda r: r[1] - r[0])
    return int(a), int(b)


def test_pig_walk_does_not_skate() -> None:
    check, stance = _check(_pig()[2].positions)
    assert set(stance) == {"lfoot", "rfoot"}
    assert all(s.sum() > 100 for s in stance.values())  # both feet stand
    print(
        f"\nPiG walk foot_skate: max {np.nanmax(check.values):.3f} m/s, median "
        f"{np.nanmedian(check.values):.3f}, transients {check.transients.size}"
    )
    assert check.n_flagged == 0, check.detail
    assert np.isfinite(check.values).sum() > 100  # the stance cores were measured


def test_sliding_stance_foot_fails_and_is_named() -> None:
    walk = _pig()[2]
    _, stance = _check(walk.positions)
    a, b = _left_stance(stance, walk.rate_hz)
    assert b - a >= 30
    pos = walk.positions.copy()
    ramp = np.clip((np.arange(walk.n_frames) - a) / (b - a), 0.0, 1.0)
    forward = np.array([SLIDE_M, 0.0, 0.0])
    for m in ("LHEE", "LTOE", "LANK"):
        pos[:, walk.labels.index(m)] += ramp[:, None] * forward
    check, _ = _check(pos)
    print(f"\nslid {SLIDE_M * 1e3:.0f} mm over frames {a}-{b - 1}: {check.detail}")
    flagged = np.flatnonzero(check.flagged)
    assert flagged.size >= 10, check.detail
    assert a <= flagged.min() and flagged.max() < b  # inside the slid stance
    assert check.detail and all(d.startswith("lfoot: frames") for d in check.detail)


def test_a_foot_turning_on_its_sole_is_not_a_skate() -> None:
    """The left foot's markers (LHEE, LTOE, LANK) turned 30 deg about a vertical
    axis through the midfoot (40 % of the way from LHEE to LTOE) over one detected
    left stance core: the heel and the toe travel ~0.13 m/s (what the check on the
    heel, ball and toe tip alone flagged), but a point of the sole stays put, so it
    passes; the same foot translated 5 cm fails (the test above)."""
    walk = _pig()[2]
    _, stance = _check(walk.positions)
    a, b = _left_stance(stance, walk.rate_hz)
    pos = walk.positions.copy()
    heel = pos[a, walk.labels.index("LHEE")]
    toe = pos[a, walk.labels.index("LTOE")]
    pivot = heel + 0.4 * (toe - heel)
    angle = np.radians(30.0) * np.clip((np.arange(walk.n_frames) - a) / (b - a), 0, 1)
    c, s = np.cos(angle), np.sin(angle)
    for m in ("LHEE", "LTOE", "LANK"):
        d = pos[:, walk.labels.index(m), :2] - pivot[:2]
        pos[:, walk.labels.index(m), 0] = pivot[0] + c * d[:, 0] - s * d[:, 1]
        pos[:, walk.labels.index(m), 1] = pivot[1] + s * d[:, 0] + c * d[:, 1]
    heel_speed = np.linalg.norm(
        np.diff(pos[a:b, walk.labels.index("LHEE"), :2], axis=0), axis=-1
    )
    assert np.median(heel_speed) * walk.rate_hz > 0.1  # the heel itself moves
    check, _ = _check(pos)
    core = np.isfinite(check.values[a:b])
    print(f"\nturned 30 deg on the midfoot: {np.nanmax(check.values[a:b]):.3f} m/s")
    assert core.sum() >= 10
    assert check.n_flagged == 0, check.detail


def test_synthetic_walk_whose_feet_stay_put_passes() -> None:
    """Data not used to choose the threshold: the synthetic level walk, whose stance
    feet do not slide (``synth/gait.py``), Plug-in Gait markers, 6 s at 120 Hz,
    calibrated on its T-pose hold: no skate (0.033 m/s at most, measured)."""
    from retargetd.daemon.synth import performer as pf

    take = pf.synthesize(
        seconds=6.0, rate_hz=120.0, markerset="plug-in-gait", motions=("level_walk",)
    )
    rig = load_rig("plug-in-gait")
    cal = calibrate(rig, take.markers_world[take.base_pose_frames], take.labels)
    solve = BodySolver(rig, cal, take.labels).solve_take(take.markers_world)
    stance = stance_by_bone(rig, cal, solve, take.rate_hz)
    vm = build_model(skeleton_from_calibration(rig, cal))
    rep = validate_take(
        vm, solve, take.rate_hz, fit=fit_pairs(rig, solve.joint_names),
        dynamics=False, stance=stance,
    )  # fmt: skip
    check = rep.checks["foot_skate"]
    print(f"\nsynthetic level walk foot_skate: max {np.nanmax(check.values):.3f} m/s")
    assert np.isfinite(check.values).sum() > 300
    assert check.n_flagged == 0, check.detail


def test_cli_report_carries_the_skate_check(
    datasets: Path, pig_calibration: Path, tmp_path: Path
) -> None:
    from retargetd.daemon.cli.main import main

    report = tmp_path / "report"
    argv = [
        "validate", str(datasets / PIG_WALK), "--rig", "plug-in-gait",
        "--calibration", str(pig_calibration), "--report", str(report),
        "--method", "construction", "--no-snapshots",
    ]  # fmt: skip
    assert main(argv) == 0
    doc = json.loads((report / "report.json").read_text())
    skate = doc["checks"]["foot_skate"]
    assert skate["frames_flagged"] == 0 and skate["unit"] == "m/s"
    assert 0.0 < skate["max"] <= THRESHOLDS["foot_skate_m_s"]
    assert "foot_skate" in (report / "report.txt").read_text()


def test_a_check_with_no_frame_it_applies_to_summarises_as_empty() -> None:
    """A take with no detected stance leaves the skate check all NaN (the frames it
    does not apply to): its summary reads as an empty check, max and median 0, with
    no NumPy warning (``validate --frames 120:240`` of the synthetic default take
    stopped on "All-NaN slice encountered", exit 3)."""
    res = CheckResult("foot_skate", np.full(12, np.nan), 0.1, "m/s")
    res.flagged = np.zeros(12, dtype=bool)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        s = res.summary()
    assert s["max"] == 0.0 and s["median"] == 0.0 and s["frames_flagged"] == 0
    res.values[3] = 0.4  # one frame it applies to: that frame's value, NaN ignored
    assert res.summary()["max"] == 0.4
