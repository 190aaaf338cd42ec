"""C3D: write -> read round trips, up axis from Y_SCREEN, Plug-in Gait references."""

from __future__ import annotations

from pathlib import Path

import ezc3d
import numpy as np
import pytest

from retargetd.replay.c3d import read_c3d, write_c3d
from retargetd.replay.take import TakeError

F32_EPS = float(np.finfo(np.float32).eps)


def _walk(
    rng: np.random.Generator, n_frames: int = 40, n_markers: int = 5
) -> np.ndarray:
    """(T, M, 3) metres, world, around a standing person, with NaN gaps."""
    base = rng.uniform([-1.0, -1.0, 0.05], [1.0, 1.0, 1.8], size=(1, n_markers, 3))
    drift = np.linspace(0.0, 0.5, n_frames)[:, None, None] * np.array([1.0, 0.2, 0.0])
    pos = base + drift + rng.normal(0.0, 0.01, size=(n_frames, n_markers, 3))
    pos[3:9, 1] = np.nan
    pos[-1, 0] = np.nan
    pos[0, -1] = np.nan
    return pos


def _assert_round_trip(
    expected: np.ndarray, got: np.ndarray, valid: np.ndarray
) -> None:
    np.testing.assert_array_equal(valid, np.isfinite(expected).all(axis=-1))
    assert np.isnan(got[~valid]).all()
    # float32 storage: error up to half an ulp of the stored (capture-unit) value.
    tol = F32_EPS * np.nanmax(np.abs(expected))
    np.testing.assert_allclose(got[valid], expected[valid], rtol=0, atol=tol)


@pytest.mark.parametrize("units", ["mm", "m"])
@pytest.mark.parametrize("up", ["+Z", "+Y", "+X"])
def test_round_trip(
    tmp_path: Path, rng: np.random.Generator, units: str, up: str
) -> None:
    pos = _walk(rng)
    labels = ["LFHD", "RFHD", "LKNE", "RKNE", "LHEE"]
    path = tmp_path / "walk.c3d"
    write_c3d(
        path, labels, pos, 120.0, units=units, up_axis=up, first_frame=17,
        measurements={"LKneeWidth": 105.0, "Bodymass": 70.5},
    )  # fmt: skip
    take = read_c3d(path)
    _assert_round_trip(pos, take.positions, take.valid)
    assert take.labels == tuple(labels)
    assert take.rate_hz == pytest.approx(120.0)
    assert take.first_frame == 17
    assert (take.units, take.up_axis) == (units, up)
    assert take.units_source == "file (POINT:UNITS)"
    assert take.up_source == "file (POINT:Y_SCREEN)"
    assert take.measurements == {"LKneeWidth": 105.0, "Bodymass": 70.5}
    assert take.subject is None
    assert take.subjects == ()


def test_occluded_samples_are_written_with_residual_minus_one(
    tmp_path: Path, rng: np.random.Generator
) -> None:
    pos = _walk(rng)
    path = tmp_path / "gaps.c3d"
    write_c3d(path, ["a", "b", "c", "d", "e"], pos, 100.0)
    residuals = ezc3d.c3d(str(path))["data"]["meta_points"]["residuals"][0]  # (M, T)
    np.testing.assert_array_equal(residuals < 0, ~np.isfinite(pos).all(-1).T)


def test_subject_prefix_round_trip(tmp_path: Path, rng: np.random.Generator) -> None:
    pos = _walk(rng, n_markers=2)
    path = tmp_path / "prefixed.c3d"
    write_c3d(path, ["C7", "T10"], pos, 50.0, subject="Derrick")
    take = read_c3d(path)
    assert take.subject == "Derrick"
    assert take.subjects == ("Derrick",)
    assert take.labels == ("C7", "T10")
    with pytest.raises(TakeError, match=r"no subject 'Viktor'; it holds: Derrick"):
        read_c3d(path, subject="Viktor")


def test_writer_rejects_bad_input(tmp_path: Path) -> None:
    pos = np.zeros((3, 2, 3))
    with pytest.raises(ValueError, match="up_axis"):
        write_c3d(tmp_path / "x.c3d", ["a", "b"], pos, 100.0, up_axis="-Z")
    with pytest.raises(ValueError, match=r"\(n_frames, n_labels, 3\)"):
        write_c3d(tmp_path / "x.c3d", ["a"], pos, 100.0)
    with pytest.raises(ValueError, match="rate_hz"):
        write_c3d(tmp_path / "x.c3d", ["a", "b"], pos, 0.0)


def test_not_a_c3d_file_is_a_take_error(tmp_path: Path) -> None:
    path = tmp_path / "junk.c3d"
    path.write_bytes(b"this is not a c3d file at all" * 10)
    with pytest.raises(TakeError, match=r"junk\.c3d"):
        read_c3d(path)


def test_qualisys_sign_of_y_screen_is_ignored(datasets: Path) -> None:
    take = read_c3d(datasets / "ezc3d-testfiles" / "Qualisys.c3d")
    assert take.up_axis == "+Z"
    assert "sign ignored" in take.up_source
    head = take.positions[:, take.marker_index("L_HDF"), 2].mean()
    heel = take.positions[:, take.marker_index("L_FCC"), 2].mean()
    assert head - heel > 1.2


def test_plug_in_gait_references(datasets: Path) -> None:
    path = datasets / "btkdata" / "PiG_Motion-FlatFoot-Full.c3d"
    take = read_c3d(path)
    refs = take.references
    for label in ("LFEP", "LFEO", "RFEP", "PELO", "LTIO", "LHUO"):
        assert refs.kinds[refs.index(label)] == "segment_point"
        assert refs.units[refs.index(label)] == "m"
    assert refs.kinds[refs.index("CentreOfMass")] == "model_point"
    assert refs.kinds[refs.index("LKneeAngles")] == "angle"
    assert refs.units[refs.index("LKneeAngles")] == "deg"
    assert refs.kinds[refs.index("LHipPower")] == "power"
    assert refs.kinds[refs.index("LKneeMoment")] == "moment"
    assert refs.kinds[refs.index("LGroundReactionForce")] == "force"
    assert not set(refs.labels) & set(take.labels)
    # Knee centre (femur origin) within 0.1 m of the knee marker, in world metres.
    gap = np.linalg.norm(
        refs.get("LFEO") - take.positions[:, take.marker_index("LKNE")], axis=-1
    )
    assert np.nanmedian(gap) < 0.1
    # Hip centre (femur proximal) above the knee centre by a thigh length.
    thigh = np.nanmedian(refs.get("LFEP")[:, 2] - refs.get("LFEO")[:, 2])
    assert 0.25 < thigh < 0.6
    # Angles are kept as written: not rotated, not scaled.
    raw = ezc3d.c3d(str(path))
    col = list(raw["parameters"]["POINT"]["LABELS"]["value"]).index("LKneeAngles")
    np.testing.assert_array_equal(
        refs.get("LKneeAngles"), raw["data"]["points"][:3, col].T
    )
    assert take.measurements["LKneeWidth"] == 105
    assert take.measurements["Bodymass"] == pytest.approx(47.5)
    assert take.manufacturer.startswith("Vicon Nexus")


def test_joint_centres_are_references_in_metres(datasets: Path) -> None:
    take = read_c3d(datasets / "opensim-core" / "walking2.c3d")
    refs = take.references
    assert set(refs.labels) == {"LAJC", "LHJC", "LKJC", "RAJC", "RHJC", "RKJC"}
    assert set(refs.kinds) == {"joint_centre"}
    hip = np.nanmedian(refs.get("LHJC")[:, 2])
    ankle = np.nanmedian(refs.get("LAJC")[:, 2])
    assert 0.6 < hip < 1.2
    assert 0.0 < ankle < 0.2
