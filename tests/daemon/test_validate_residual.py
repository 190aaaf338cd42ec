"""``validate``'s marker residual checks (issue 28 items 4 and 5): for the fit, whose
joint centres are its rigid skeleton's own (``fit_median`` / ``fit_max`` read ~0),
the checks read the fit's marker residuals and name the markers the calibrated
skeleton cannot match.

The synthetic performer (``menache``, 1 mm noise) calibrated on its own base pose:
the intact take passes the residual checks; the same take with one marker moved 60 mm
along its segment (a marker that slipped after calibration: the fit can absorb no part
of a move along the limb, whose length is fixed) and a taller performer's take
(1.95 m on the 1.75 m performer's calibration) fail them through ``retargetd
validate``, and the report names the markers. Thresholds: ``validate.THRESHOLDS``
(``marker_residual_*``, set from the literature; the real takes are in
``test_validate_takes.py``).
"""

from __future__ import annotations

import functools
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from retargetd.daemon import rotations as rot
from retargetd.daemon.cli.main import main
from retargetd.daemon.synth import performer as pf
from retargetd.daemon.validate.checks import THRESHOLDS, THRESHOLDS_BASIS
from retargetd.daemon.validate.residual import min_frames, residual_checks
from retargetd.replay.c3d import write_c3d

pytestmark = pytest.mark.usefixtures("mujoco_cwd")

RATE_HZ = 60.0
MOVED = "LEKNEE"
MOVE_M = 0.060
RESIDUAL = ("marker_residual_median", "marker_residual_max")


@functools.cache
def _take(height_m: float = pf.REFERENCE_HEIGHT_M) -> pf.SynthTake:
    return pf.synthesize(
        seconds=5.0, rate_hz=RATE_HZ, markerset="menache", noise_mm=1.0,
        height_m=height_m,
    )  # fmt: skip


def _moved(take: pf.SynthTake) -> np.ndarray:
    """The take's markers with :data:`MOVED` 60 mm up its segment (+Z of the
    segment's frame: along the shank) in every frame."""
    i = take.labels.index(MOVED)
    wfs = take.world_from_segment_quat[:, take.marker_segments[i]]
    out = take.markers_world.copy()
    out[:, i] += rot.quat_rotate(wfs, np.array([0.0, 0.0, MOVE_M]))
    return out


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """intact / moved / taller C3D takes and the intact take's calibration."""
    root = tmp_path_factory.mktemp("residual")
    take = _take()
    tall = _take(1.95)
    out = {name: root / f"{name}.c3d" for name in ("intact", "moved", "taller")}
    for name, labels, pos in (
        ("intact", take.labels, take.markers_world),
        ("moved", take.labels, _moved(take)),
        ("taller", tall.labels, tall.markers_world),
    ):
        write_c3d(out[name], list(labels), pos, RATE_HZ)
    out["calibration"] = root / "calibration.json"
    n_base = take.base_pose_frames.stop
    argv = ["calibrate", str(out["intact"]), "--rig", "menache"]
    assert (
        main([*argv, "--frames", f"0:{n_base}", "--out", str(out["calibration"])]) == 0
    )
    return out


def _validate(
    files: dict[str, Path], name: str, tmp_path: Path, method: str = "fit"
) -> tuple[int, dict[str, Any], str]:
    report = tmp_path / name
    argv = [
        "validate", str(files[name]), "--rig", "menache",
        "--calibration", str(files["calibration"]), "--method", method,
        "--report", str(report), "--no-snapshots", "--quiet",
    ]  # fmt: skip
    rc = main(argv)
    doc = json.loads((report / "report.json").read_text())
    return rc, doc, (report / "report.txt").read_text()


def test_intact_take_passes_the_residual_checks(
    files: dict[str, Path], tmp_path: Path
) -> None:
    _, doc, text = _validate(files, "intact", tmp_path)
    checks = doc["checks"]
    for name in RESIDUAL:
        c = checks[name]
        assert c["frames_flagged"] == 0 and c["markers"] == {}, (name, c)
        assert c["threshold"] == THRESHOLDS[f"{name}_mm"] and c["unit"] == "mm"
        assert name not in doc["failed"]
        assert f"    {name}: {c['threshold']:g} mm - {THRESHOLDS_BASIS[name]}" in text
    # The fit's residual is measured, not ~0 (1 mm noise, skin-free performer)...
    assert 0.5 < checks["marker_residual_median"]["median"] < 5.0
    assert checks["marker_residual_max"]["max"] < THRESHOLDS["marker_residual_max_mm"]
    # ...while the joint-centre check reads the rigid chain's own centres.
    assert checks["fit_max"]["max"] < 1e-6


def test_marker_moved_after_calibration_fails_and_is_named(
    files: dict[str, Path], tmp_path: Path
) -> None:
    rc, doc, text = _validate(files, "moved", tmp_path)
    assert rc == 1 and "marker_residual_max" in doc["failed"]
    assert "marker_residual_median" not in doc["failed"]  # one marker of 37
    c = doc["checks"]["marker_residual_max"]
    assert list(c["markers"]) == [MOVED], c["markers"]
    # Off by its 60 mm in every frame (1 mm noise; the fit absorbs none of it).
    assert c["frames_flagged"] == doc["frames"]
    assert 55.0 < c["median"] < 70.0
    assert c["markers"][MOVED]["frames"] == doc["frames"]
    assert c["detail"][0].startswith(f"frames 0-{doc['frames'] - 1} (5.00 s): {MOVED}")
    line = next(ln for ln in text.splitlines() if ln.startswith("marker_residual_max"))
    assert line.split()[1] == "FAIL" and f"    {c['detail'][0]}\n" in text


def test_another_performers_calibration_fails_and_names_markers(
    files: dict[str, Path], tmp_path: Path
) -> None:
    """A 1.95 m performer on the 1.75 m performer's calibration: every segment 11 %
    longer than the skeleton's, so markers sit far from where it can put them."""
    rc, doc, _ = _validate(files, "taller", tmp_path)
    assert rc == 1 and {*RESIDUAL} <= set(doc["failed"]), doc["failed"]
    c = doc["checks"]["marker_residual_max"]
    assert c["frames_flagged"] == doc["frames"]
    assert len(c["markers"]) >= 5
    # The median, too: the typical marker beyond 20 mm for runs of >= 0.25 s.
    med = doc["checks"]["marker_residual_median"]
    assert med["flagged_runs"] and all(
        b - a >= min_frames(THRESHOLDS["marker_residual_min_s"], RATE_HZ)
        for a, b in med["flagged_runs"]
    )
    assert med["markers"] and med["detail"]


def test_construction_has_no_residual_checks(
    files: dict[str, Path], tmp_path: Path
) -> None:
    """The construction's solve carries no marker residuals: its joint-centre checks
    (fit_median, fit_max) are the ones that measure it."""
    _, doc, _ = _validate(files, "moved", tmp_path, method="construction")
    assert not set(RESIDUAL) & set(doc["checks"])
    assert doc["checks"]["fit_max"]["max"] > 1.0  # mm: the moved knee marker


def test_residual_checks_by_hand() -> None:
    """Persistence, the same marker for the max, NaN frames, blame and transients,
    on numbers worked by hand (thresholds 20 / 40 mm, 3 frames)."""
    nan = np.nan
    r = np.array(
        [
            # A     B     C
            [5.0, 5.0, 5.0],  # 0
            [50.0, 5.0, 5.0],  # 1  A beyond the max: a 2-frame run, transient
            [50.0, 5.0, 5.0],  # 2
            [5.0, 50.0, 5.0],  # 3  B, then A, then B: no marker lasts 3 frames
            [50.0, 5.0, 5.0],  # 4
            [5.0, 50.0, 5.0],  # 5
            [nan, nan, nan],  # 6  nothing seen: NaN, never flagged
            [25.0, 25.0, 45.0],  # 7  median 25 for 3 frames: flagged; C for 3: too
            [25.0, 25.0, 45.0],  # 8
            [25.0, 25.0, 45.0],  # 9
        ]
    )
    got = residual_checks(
        r, ("A", "B", "C"), median_mm=20.0, max_mm=40.0, n_min=3, rate_hz=10.0
    )
    med, mx = got["marker_residual_median"], got["marker_residual_max"]
    np.testing.assert_array_equal(med.values, [5, 5, 5, 5, 5, 5, nan, 25, 25, 25])
    np.testing.assert_array_equal(mx.values, [5, 50, 50, 50, 50, 50, nan, 45, 45, 45])
    assert np.flatnonzero(med.flagged).tolist() == [7, 8, 9]
    assert np.flatnonzero(mx.flagged).tolist() == [7, 8, 9]
    assert mx.transients.tolist() == [1, 2, 3, 4, 5] and med.transients.size == 0
    assert mx.markers == {"C": {"frames": 3, "max_mm": 45.0}}
    assert med.markers == {
        "C": {"frames": 3, "max_mm": 45.0},
        "A": {"frames": 3, "max_mm": 25.0},
        "B": {"frames": 3, "max_mm": 25.0},
    }
    assert mx.detail == [
        "frames 7-9 (0.30 s): C 3 frames (max 45 mm)",
        "transient, frames 1-5 (0.50 s): A 3 frames (max 50 mm), "
        "B 2 frames (max 50 mm)",
    ]
    assert min_frames(0.25, 60.0) == 15 and min_frames(0.25, 30.0) == 8
    assert min_frames(0.25, 1.0) == 1
