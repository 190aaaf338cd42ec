"""The calibration-match check (``body.match``, issue 29 item 2): each rigid
segment's markers fitted to their calibrated layout, offline before solving and live
over the first second.

- the fit's residuals against scipy's rigid fit; the cited thresholds;
- every real take with its performer's own calibration stays quiet (the figures are
  printed with ``pytest -s``);
- another subject's calibration is caught: ``solve`` warns in one line naming the
  segment, ``--json`` has ``calibration_match``, ``--strict-calibration`` exits 2;
- a marker moved 20 mm between the static and the take is named: on the synthetic
  performer's thigh wand and on the real opensim walk's thigh wand;
- the live window checks the first second once (the daemon:
  ``test_live_calibration_match.py``).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from live_harness import (
    EXACT_RIG,
    _f32,
    _take,
)
from paths import DATASETS, require, require_datasets
from scipy.spatial.transform import Rotation

from retargetd.daemon.body.calibration import (
    Calibration,
    calibrate,
    match_markers,
)
from retargetd.daemon.body.match import (
    MARKER_BOUND_MM,
    CalibrationMatch,
    MatchWindow,
    calibration_columns,
    layout_residuals,
    markers_of_calibration,
    match_calibration,
    segment_threshold_mm,
)
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.cli.main import main
from retargetd.replay.takes import load_take

pytestmark = pytest.mark.timeout(300)

PIG_STATIC = "btkdata/PiG_Calibration-FlatFoot-Full.c3d"  # BELT_C, 1.505 m
PIG_WALK = "btkdata/PiG_Motion-FlatFoot-Full.c3d"
PIG3_WALK = "btkdata/PiG_Motion3_FF.c3d"  # flatFoot, 1.76 m (another subject)
OS_STATIC = "opensim-core/subject01_static.trc"
OS_WALK = "opensim-core/subject01_walk1.trc"

#: Every real take with its own performer's calibration: (take, rig, static or the
#: take's own rows). The README's validation table's pairs.
OWN = [
    (PIG_WALK, "plug-in-gait", PIG_STATIC, None),
    (PIG_STATIC, "plug-in-gait", PIG_STATIC, None),
    (OS_WALK, "opensim-gait2354", OS_STATIC, None),
    ("peers/subject01_walk1.trc", "opensim-gait2354", OS_STATIC, None),
    (OS_STATIC, "opensim-gait2354", OS_STATIC, None),
    ("btkdata/MOTEK_T.trc", "cmu41", "btkdata/MOTEK_T.trc", None),
    ("btkdata/MOTEK_ballet_reduced.trc", "cmu41", "btkdata/MOTEK_T.trc", None),
    (
        "kineticstoolkit/kinematics_tennis_serve.c3d",
        "cmu41",
        "kineticstoolkit/kinematics_tennis_serve.c3d",
        slice(0, 50),
    ),
    (
        "kineticstoolkit/kinematics_tennis_serve.c3d",
        "plug-in-gait",
        "kineticstoolkit/kinematics_tennis_serve.c3d",
        slice(0, 50),
    ),
    (
        "peers/bioptim_gait_wholebody.c3d",
        "bioptim-wholebody",
        "peers/bioptim_gait_wholebody.c3d",
        slice(0, 10),
    ),
]


def _calibrate(
    rig_name: str,
    static: str,
    frames: slice | None = None,
    moved: tuple[str, np.ndarray] | None = None,
) -> Calibration:
    """A calibration on a real static (or rows of a take); ``moved``: one rig
    marker shifted in the base pose (it sits elsewhere in the take)."""
    rig = load_rig(rig_name)
    take = load_take(require(DATASETS / static, static))
    base = take.positions if frames is None else take.positions[frames]
    if moved is not None:
        base = base.copy()
        col = match_markers(rig, take.labels)[rig.marker_names.index(moved[0])]
        base[:, col] += moved[1]
    return calibrate(rig, base, take.labels, take_measurements=take.measurements)


def _match(cal: Calibration, rig_name: str, take_name: str) -> CalibrationMatch:
    take = load_take(require(DATASETS / take_name, take_name))
    rig = load_rig(rig_name)
    cols = match_markers(rig, take.labels)
    return match_calibration(
        cal, markers_of_calibration(cal, rig.marker_names, cols, take.positions)
    )


def _figures(found: CalibrationMatch) -> str:
    return ", ".join(f"{s.segment} {s.rms_mm:.1f}" for s in found.segments if s.frames)


# ---- the fit, by hand ---------------------------------------------------------------


def test_layout_residuals_against_scipys_rigid_fit() -> None:
    # A 3-marker layout, turned 30 deg about z and moved: residual 0. One marker
    # moved 20 mm: the fit's residuals equal the least-squares rigid fit's (scipy's
    # Kabsch, Rotation.align_vectors, on the centred points), and the RMS is at most
    # the translation-only d sqrt(k-1)/k = 9.4 mm (the module docstring's rule).
    layout = np.array([[0.0, 0.0, 0.0], [0.2, 0.0, 0.0], [0.0, 0.15, 0.0]])
    turn = Rotation.from_euler("z", 30.0, degrees=True)
    pts = turn.apply(layout) + np.array([1.0, 2.0, 0.9])
    frames = np.stack([pts, pts.copy()])
    frames[1, 1] += np.array([0.0, 0.02, 0.0])
    res = layout_residuals(layout, frames)
    assert np.nanmax(res[0]) < 1e-9
    lc, pc = layout - layout.mean(0), frames[1] - frames[1].mean(0)
    best, _ = Rotation.align_vectors(pc, lc)
    oracle = np.linalg.norm(pc - best.apply(lc), axis=1)
    np.testing.assert_allclose(res[1], oracle, atol=1e-9)
    rms = float(np.sqrt(np.mean(res[1] ** 2)))
    assert 0.003 < rms <= 0.02 * math.sqrt(2) / 3 + 1e-12
    # a frame with two markers seen is not fitted
    two = frames[:1].copy()
    two[0, 2] = np.nan
    assert np.isnan(layout_residuals(layout, two)).all()


def test_thresholds_come_from_the_cited_bounds() -> None:
    # 2 mm noise (Merriaux 2017) + 5.1 mm thigh deformation (Andersen 2012); 2 mm +
    # 9.3 + 2 x 4.2 mm thoracic skin motion (Zemp 2014); times sqrt(1 - 2/k).
    assert {
        "limb": pytest.approx(7.1),
        "trunk": pytest.approx(19.7),
    } == MARKER_BOUND_MM
    assert segment_threshold_mm("lthigh", 3) == pytest.approx(7.1 / math.sqrt(3))
    assert segment_threshold_mm("pelvis", 4) == pytest.approx(7.1 / math.sqrt(2))
    assert segment_threshold_mm("thorax", 4) == pytest.approx(19.7 / math.sqrt(2))
    assert segment_threshold_mm("ribcage", 6) == pytest.approx(19.7 * math.sqrt(2 / 3))


def test_calibrated_markers_are_matched_by_name() -> None:
    # A rig file edited since the calibration (markers reordered, one dropped): the
    # calibration's markers still find their columns by name; the dropped one is
    # absent (its segment fitted from the rest).
    take = _take()
    rig = load_rig(EXACT_RIG)
    cal = calibrate(rig, _f32(take.markers_world[take.base_pose_frames]), take.labels)
    cols = list(match_markers(rig, take.labels))
    names = list(rig.marker_names)
    direct = calibration_columns(cal, names, cols)
    assert list(direct) == cols
    edited = calibration_columns(cal, names[::-1][1:], cols[::-1][1:])
    gone = cal.marker_names.index(names[-1])
    assert edited[gone] == -1
    assert np.delete(edited, gone).tolist() == np.delete(direct, gone).tolist()
    with pytest.raises(ValueError, match="one per rig marker"):
        calibration_columns(cal, names, cols[:-1])


# ---- synthetic ----------------------------------------------------------------------


def test_a_thigh_wand_moved_20_mm_on_the_synthetic_performer_is_named() -> None:
    take = _take()  # exact markers, 1 s T-pose then every motion
    rig = load_rig(EXACT_RIG)
    base = _f32(take.markers_world[take.base_pose_frames])
    cols = match_markers(rig, take.labels)
    intact = calibrate(rig, base, take.labels)
    found = match_calibration(
        intact,
        markers_of_calibration(intact, rig.marker_names, cols, take.markers_world),
    )
    assert found.matches and found.warning() is None
    assert max(s.rms_mm for s in found.segments) < 0.5  # exact markers
    moved_base = base.copy()
    moved_base[:, take.labels.index("LTHI")] += np.array([0.0, 0.0, 0.020])
    moved = calibrate(rig, moved_base, take.labels)
    found = match_calibration(
        moved, markers_of_calibration(moved, rig.marker_names, cols, take.markers_world)
    )
    print(f"synthetic, LTHI moved 20 mm: {_figures(found)}")
    assert [s.segment for s in found.mismatched] == ["l_thigh"]
    line = found.warning()
    assert line is not None and "calibration" in line and "match" in line
    assert "l_thigh" in line and "LTHI" in line


# ---- real takes ---------------------------------------------------------------------


@pytest.mark.parametrize(
    ("take", "rig", "static", "frames"), OWN, ids=[f"{t}:{r}" for t, r, _, _ in OWN]
)
def test_own_calibration_is_quiet_on_every_real_take(
    take: str, rig: str, static: str, frames: slice | None
) -> None:
    require_datasets()
    found = _match(_calibrate(rig, static, frames), rig, take)
    worst = max((s for s in found.segments if s.frames), key=lambda s: s.rms_mm)
    print(f"{take} ({rig}, {static}): {_figures(found)}; worst {worst.segment}")
    assert found.matches, found.warning()


AXES = {"+x": (1, 0, 0), "-x": (-1, 0, 0), "+y": (0, 1, 0), "-y": (0, -1, 0),
        "+z": (0, 0, 1), "-z": (0, 0, -1)}  # fmt: skip


@pytest.mark.parametrize("axis", list(AXES))
def test_a_thigh_wand_moved_20_mm_on_a_real_take_is_named(axis: str) -> None:
    require_datasets()
    # subject01's right thigh wand (RTHF) re-stuck 20 mm along a world axis after
    # the static (-z: lower, further from the hip, as in the issue)
    shift = 0.020 * np.asarray(AXES[axis], dtype=np.float64)
    cal = _calibrate("opensim-gait2354", OS_STATIC, moved=("RTHF", shift))
    found = _match(cal, "opensim-gait2354", OS_WALK)
    print(f"subject01 walk, RTHF moved 20 mm {axis}: {_figures(found)}")
    assert [s.segment for s in found.mismatched] == ["rthigh"]
    line = found.warning()
    assert line is not None and "rthigh" in line


def _belt_calibration(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> tuple[Path, str]:
    """BELT_C's static calibrated to a file, and flatFoot's walk (another subject)."""
    require_datasets()
    cal_path = tmp_path / "belt.json"
    static = str(require(DATASETS / PIG_STATIC, PIG_STATIC))
    walk = str(require(DATASETS / PIG3_WALK, PIG3_WALK))
    assert (
        main(["calibrate", static, "--rig", "plug-in-gait", "--out", str(cal_path)])
        == 0
    )
    capsys.readouterr()
    return cal_path, walk


def test_another_subjects_calibration_is_caught_by_solve(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # BELT_C's static (1.505 m) on flatFoot's walk (1.76 m): the pelvis markers sit
    # 200 mm apart against 245 mm.
    cal_path, walk = _belt_calibration(tmp_path, capsys)
    argv = ["solve", walk, "--rig", "plug-in-gait", "--calibration", str(cal_path),
            "--method", "construction", "--quiet"]  # fmt: skip
    # --strict-calibration: exit 2, one line, nothing written
    out = tmp_path / "strict.npz"
    assert main([*argv, "--out", str(out), "--strict-calibration"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    assert "calibration does not match this take: pelvis" in err
    assert not out.exists()
    # the default: one warning line, then the solve; --json holds the figures
    assert main([*argv, "--out", str(tmp_path / "x.npz"), "--json"]) == 0
    captured = capsys.readouterr()
    warnings = [ln for ln in captured.err.splitlines() if "calibration" in ln]
    assert len(warnings) == 1 and "match" in warnings[0] and "pelvis" in warnings[0]
    doc = json.loads(captured.out)
    pelvis = doc["calibration_match"]["pelvis"]
    assert pelvis["matches"] is False and pelvis["rms_mm"] > 20.0
    assert doc["calibration_matches"] is False
    assert doc["calibration_match"]["head"]["matches"] is None  # no head markers
    # the performer's own calibration: quiet, and matches in --json
    own = tmp_path / "own.npz"
    walk1 = str(require(DATASETS / PIG_WALK, PIG_WALK))
    argv[1] = walk1
    assert main([*argv, "--out", str(own), "--json", "--strict-calibration"]) == 0
    captured = capsys.readouterr()
    assert "calibration does not match" not in captured.err
    assert json.loads(captured.out)["calibration_matches"] is True
    with capsys.disabled():
        print(f"BELT_C static on flatFoot's walk: pelvis {pelvis['rms_mm']:.1f} mm")


# ---- live ---------------------------------------------------------------------------


def test_match_window_checks_the_first_second_once() -> None:
    take = _take()
    rig = load_rig(EXACT_RIG)
    cal = calibrate(rig, _f32(take.markers_world[take.base_pose_frames]), take.labels)
    cols = np.asarray(match_markers(rig, take.labels), dtype=np.int64)
    window = MatchWindow(cal, rig.marker_names)
    results = [
        window.add(take.markers_world[k], cols, k / take.rate_hz)
        for k in range(int(1.5 * take.rate_hz))
    ]
    done = [k for k, r in enumerate(results) if r is not None]
    assert done == [int(take.rate_hz)]  # the frame one second after the first
    assert window.result is not None and window.result.matches
    assert window.n_frames == int(take.rate_hz)
    # Fitted frame by frame as they came, the figures are the offline check's on
    # the same frames; a marker moved 40 mm after the static is caught the same way.
    first = take.markers_world[: int(take.rate_hz)]
    for shift in (0.0, 0.040):
        moved = first.copy()
        moved[:, 0, 0] += shift
        window = MatchWindow(cal, rig.marker_names)
        for k in range(len(moved) + 1):
            found = window.add(moved[min(k, len(moved) - 1)], cols, k / take.rate_hz)
        assert found is not None
        offline = match_calibration(
            cal, markers_of_calibration(cal, rig.marker_names, cols, moved)
        )
        assert found.to_json() == offline.to_json()
        assert found.matches == (shift == 0.0)


@pytest.mark.usefixtures("mujoco_cwd")
def test_validate_names_the_calibration_not_only_the_joint_limits(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # The case: validate failed only on joint limits, pointing the user at
    # the wrong cause. Now the warning names the segment first, and the JSON and
    # report.json hold the figures; --strict-calibration stops before validating.
    cal_path, walk = _belt_calibration(tmp_path, capsys)
    argv = ["validate", walk, "--rig", "plug-in-gait", "--calibration", str(cal_path),
            "--method", "construction", "--no-snapshots", "--json"]  # fmt: skip
    report = tmp_path / "report"
    assert main([*argv, "--report", str(report)]) == 1
    captured = capsys.readouterr()
    assert "calibration does not match this take: pelvis" in captured.err
    doc = json.loads(captured.out)
    assert doc["calibration_match"]["pelvis"]["matches"] is False
    on_disk = json.loads((report / "report.json").read_text())
    assert on_disk["calibration_match"]["pelvis"]["matches"] is False
    assert (
        main([*argv, "--report", str(tmp_path / "strict"), "--strict-calibration"]) == 2
    )
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "pelvis" in err
