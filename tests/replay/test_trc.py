"""TRC: write -> read round trips, Y-up default, malformed files as TakeError."""

from __future__ import annotations

import tempfile
from pathlib import Path

import hypothesis.extra.numpy as hnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from retargetd.replay.take import TakeError
from retargetd.replay.trc import read_trc, write_trc

F32_EPS = float(np.finfo(np.float32).eps)

HEADER = (
    "PathFileType\t4\t(X/Y/Z)\tsmall.trc\n"
    "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\n"
    "60.00\t60.00\t3\t2\tmm\n"
    "Frame#\tTime\tA\t\t\tB\t\t\n"
    "\t\tX1\tY1\tZ1\tX2\tY2\tZ2\n"
    "\n"
)


def _positions(rng: np.random.Generator) -> np.ndarray:
    pos = rng.uniform(-1.5, 1.8, size=(30, 4, 3))
    pos[2:7, 1] = np.nan
    pos[-1, 3] = np.nan
    return pos


@pytest.mark.parametrize("units", ["mm", "m"])
@pytest.mark.parametrize("up", ["+Y", "+Z"])
def test_round_trip(
    tmp_path: Path, rng: np.random.Generator, units: str, up: str
) -> None:
    pos = _positions(rng)
    labels = ["R.ASIS", "L.ASIS", "V.Sacral", "Top.Head"]
    path = tmp_path / "walk.trc"
    write_trc(path, labels, pos, 60.0, units=units, up_axis=up)
    take = read_trc(path, up_axis=None if up == "+Y" else up)
    valid = np.isfinite(pos).all(axis=-1)
    np.testing.assert_array_equal(take.valid, valid)
    assert np.isnan(take.positions[~valid]).all()
    np.testing.assert_allclose(
        take.positions[valid], pos[valid], rtol=0, atol=F32_EPS * 2.0
    )
    assert take.labels == tuple(labels)
    assert take.rate_hz == 60.0
    assert take.first_frame == 1
    assert take.units == units
    assert take.up_axis == up
    assert take.up_source == (
        "default (TRC has no up axis)" if up == "+Y" else "override"
    )
    assert take.measurements == {}


def test_crlf_trailing_tabs_blank_and_missing_fields(tmp_path: Path) -> None:
    rows = (
        "1\t0.000\t1.0\t2.0\t3.0\t4.0\t5.0\t6.0\t\n"
        "2\t0.017\t1.0\t2.0\t3.0\t\t\t\t\n"  # B blank
        "3\t0.033\t1.0\t2.0\t3.0\n"  # B's columns missing
    )
    path = tmp_path / "small.trc"
    path.write_bytes((HEADER + rows).replace("\n", "\r\n").encode())
    take = read_trc(path, up_axis="+Z")
    assert take.labels == ("A", "B")
    np.testing.assert_array_equal(
        take.valid, [[True, True], [True, False], [True, False]]
    )
    np.testing.assert_allclose(
        take.positions[0], [[1e-3, 2e-3, 3e-3], [4e-3, 5e-3, 6e-3]]
    )
    assert take.n_frames == 3


def test_y_up_file_is_rotated_plus_90_about_x(datasets: Path) -> None:
    path = datasets / "btkdata" / "MOTEK_T.trc"
    lines = path.read_text().splitlines()
    first = np.array([float(v) for v in lines[6].rstrip("\t").split("\t")[2:]])
    take = read_trc(path)
    expected = Rotation.from_euler("x", 90, degrees=True).apply(
        first.reshape(-1, 3) * 1e-3
    )
    np.testing.assert_allclose(take.positions[0], expected, atol=1e-12)
    assert take.up_axis == "+Y"
    assert take.up_source == "default (TRC has no up axis)"
    assert take.units_source == "file (Units)"


@pytest.mark.parametrize(
    ("text", "match"),
    [
        (HEADER.splitlines(keepends=True)[0], "cut after 1 of 5 header lines"),
        ("hello\nworld\n", "not a TRC file"),
        (HEADER + "1\t0.0\t1.0\tabc\t3.0\t4.0\t5.0\t6.0\n", r"line 7: field 'abc'"),
        (HEADER.replace("60.00\t60.00", "fast\t60.00") + "1\t0\t1\t2\t3\n", "DataRate"),
        (HEADER.replace("\tmm\n", "\tfurlong\n") + "1\t0\t1\t2\t3\n", "furlong"),
        (HEADER, "no data rows"),
    ],
)
def test_malformed_file_is_a_take_error_naming_it(
    tmp_path: Path, text: str, match: str
) -> None:
    path = tmp_path / "broken.trc"
    path.write_text(text)
    with pytest.raises(TakeError, match=match) as info:
        read_trc(path)
    assert "broken.trc" in str(info.value)
    assert "\n" not in str(info.value)


def test_prefixed_labels_split_into_subjects_and_strays_are_left_out(
    tmp_path: Path, rng: np.random.Generator
) -> None:
    pos = rng.uniform(-1.0, 1.0, size=(4, 4, 3))
    path = tmp_path / "two.trc"
    write_trc(path, ["A:x", "A:y", "B:x", "stray"], pos, 30.0)
    with pytest.raises(TakeError, match=r"holds 2 subjects \(A, B\): pass --subject"):
        read_trc(path)
    take = read_trc(path, subject="B")
    assert take.labels == ("x",)
    assert take.subjects == ("A", "B")
    assert take.unassigned_labels == ("stray",)
    np.testing.assert_allclose(take.positions[:, 0], pos[:, 2], atol=1e-9)


def test_writer_rejects_tabs_in_labels(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="labels"):
        write_trc(tmp_path / "x.trc", ["a\tb"], np.zeros((1, 1, 3)), 30.0)


@settings(max_examples=30, deadline=None)
@given(
    data=hnp.arrays(
        np.float64,
        hnp.array_shapes(min_dims=3, max_dims=3, min_side=1, max_side=5).map(
            lambda s: (s[0], s[1], 3)
        ),
        elements=st.one_of(
            st.floats(-5.0, 5.0, allow_nan=False), st.just(float("nan"))
        ),
    ),
    units=st.sampled_from(["mm", "cm", "m"]),
)
def test_round_trip_property(data: np.ndarray, units: str) -> None:
    # A sample with any NaN coordinate is occluded: the whole row reads back as NaN.
    labels = [f"M{i}" for i in range(data.shape[1])]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "prop.trc"
        write_trc(path, labels, data, 100.0, units=units)
        take = read_trc(path)
    valid = np.isfinite(data).all(axis=-1)
    np.testing.assert_array_equal(take.valid, valid)
    np.testing.assert_allclose(
        take.positions[valid], data[valid], rtol=1e-9, atol=1e-12
    )
