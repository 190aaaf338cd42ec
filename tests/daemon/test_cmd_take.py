"""``retargetd take info``: text and JSON output, errors as one line with exit 2."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from retargetd.daemon.cli.main import main
from retargetd.daemon.cli.take import longest_gaps

TWO_SUBJECT_FILES = {
    "pyomeca/markers_analogs.c3d": ("boite", "Daphnee"),
    "kineticstoolkit/kinematics_tennis_serve_2players_SYNTHETIC.c3d": (
        "Derrick",
        "Viktor",
    ),
}


def _info_json(capsys: pytest.CaptureFixture[str], *argv: str) -> dict:
    assert main(["take", "info", *argv, "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_walk_json(datasets: Path, capsys: pytest.CaptureFixture[str]) -> None:
    info = _info_json(capsys, str(datasets / "opensim-core" / "walking2.c3d"))
    assert info["format"] == "c3d"
    assert info["manufacturer"].startswith("Vicon Nexus")
    assert info["subjects"] == ["Treadmill"]
    assert info["subject"] == "Treadmill"
    assert info["markers"]["count"] == 38 == len(info["markers"]["labels"])
    assert info["rate_hz"] == 250.0
    assert info["frames"] == 1249
    assert info["duration_s"] == pytest.approx(1249 / 250)
    assert info["first_frame"] == 0
    gaps = info["gaps"]
    assert gaps["fraction"] == pytest.approx(0.47526442206396696, abs=1e-6)
    assert gaps["markers_with_gaps"] > 0
    assert 0 < gaps["longest_gap_frames"] <= 1249
    assert gaps["worst"]
    assert gaps["worst"][0]["gap_fraction"] >= gaps["worst"][-1]["gap_fraction"]
    assert (info["units"], info["units_source"]) == ("mm", "file (POINT:UNITS)")
    assert (info["up_axis"], info["up_source"]) == ("+Z", "file (POINT:Y_SCREEN)")
    assert info["world_from_capture"] == np.eye(3).tolist()
    assert info["references"]["count"] == 6
    assert sorted(info["references"]["by_kind"]["joint_centre"]) == [
        "LAJC", "LHJC", "LKJC", "RAJC", "RHJC", "RKJC",
    ]  # fmt: skip
    assert info["measurements"] == {}


def test_y_up_trc_json(datasets: Path, capsys: pytest.CaptureFixture[str]) -> None:
    info = _info_json(capsys, str(datasets / "btkdata" / "MOTEK_T.trc"))
    assert info["format"] == "trc"
    assert info["up_source"] == "default (TRC has no up axis)"
    assert info["world_from_capture"] == [[1, 0, 0], [0, 0, -1], [0, 1, 0]]
    assert info["first_frame"] == 1
    assert info["gaps"]["fraction"] == 0.0
    assert info["gaps"]["worst"] == []


def test_text_output(datasets: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = datasets / "btkdata" / "PiG_Motion-FlatFoot-Full.c3d"
    assert main(["take", "info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "subjects:      BELT_C (selected)" in out
    assert "markers:       35:" in out
    assert "segment_point (76):" in out
    assert "LKneeWidth = 105" in out
    assert "up axis:       +Z (file (POINT:Y_SCREEN))" in out


@pytest.mark.parametrize("rel", sorted(TWO_SUBJECT_FILES))
def test_two_subject_files(
    datasets: Path, capsys: pytest.CaptureFixture[str], rel: str
) -> None:
    path = str(datasets / rel)
    assert main(["take", "info", path]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    for name in TWO_SUBJECT_FILES[rel]:
        assert name in err
    assert "--subject" in err
    for name in TWO_SUBJECT_FILES[rel]:
        info = _info_json(capsys, path, "--subject", name)
        assert info["subject"] == name
        assert list(info["subjects"]) == list(TWO_SUBJECT_FILES[rel])


def test_bad_input_is_one_line_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    broken = tmp_path / "broken.trc"
    broken.write_text("PathFileType\t4\t(X/Y/Z)\tbroken.trc\nDataRate\n")
    cases = [
        [str(broken)],
        [str(tmp_path / "missing.c3d")],
        [str(tmp_path / "take.bvh")],
    ]
    for argv in cases:
        assert main(["take", "info", *argv]) == 2
        err = capsys.readouterr().err
        assert err.startswith("retargetd take: error: take ")
        assert err.count("\n") == 1
        assert "Traceback" not in err


def test_bad_take_up(datasets: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = str(datasets / "btkdata" / "MOTEK_T.trc")
    assert main(["take", "info", path, "--take-up", "sideways"]) == 2
    assert "--take-up" in capsys.readouterr().err
    info = _info_json(capsys, path, "--take-up", "z", "--take-units", "m")
    assert (info["up_axis"], info["up_source"]) == ("+Z", "override")
    assert (info["units"], info["units_source"]) == ("m", "override")


def test_take_needs_an_action(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["take"])
    assert exc.value.code == 2


def test_longest_gaps() -> None:
    valid = np.array(
        [[1, 0, 1], [0, 0, 1], [0, 1, 1], [1, 0, 1], [0, 0, 1]], dtype=bool
    )
    np.testing.assert_array_equal(longest_gaps(valid), [2, 2, 0])
