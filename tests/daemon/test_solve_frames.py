"""``--frames a:b`` on ``solve`` and ``validate`` (issue 31, item 10): a take whose
first frames hold no marker solves from row a without ``export-c3d --frames`` first;
``--calibrate-frames`` still counts rows of the whole take; the NPZ keeps the take's
frame numbering (``first_frame``)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from retargetd.daemon.cli.main import main
from retargetd.replay.c3d import write_c3d
from retargetd.replay.takes import load_take

#: Rows of the synthetic take hidden (no marker seen), as a real take's empty start.
EMPTY = 40
#: The synthetic performer holds its calibration pose over the first second (120 Hz).
HOLD = f"{EMPTY + 10}:120"
FIRST_FRAME = 17


@pytest.fixture(scope="module")
def empty_start(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``retargetd synth`` (3 s, 120 Hz) with its first :data:`EMPTY` rows hidden and
    a first frame number of :data:`FIRST_FRAME`."""
    folder = tmp_path_factory.mktemp("frames")
    synth = folder / "synth.c3d"
    assert main(["synth", "--seconds", "3", "--rate", "120", "--out", str(synth)]) == 0
    take = load_take(synth)
    positions = take.positions.copy()
    positions[:EMPTY] = np.nan
    path = folder / "empty_start.c3d"
    write_c3d(path, take.labels, positions, take.rate_hz, first_frame=FIRST_FRAME)
    return path


def test_solve_frames_equals_the_exported_rows(
    empty_start: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``solve --frames a:b`` solves what ``export-c3d --frames a:b`` then ``solve``
    did, with the calibration taken on rows of the whole take."""
    cal = tmp_path / "cal.json"
    assert main(["calibrate", str(empty_start), "--rig", "menache", "--frames", HOLD,
                 "--out", str(cal)]) == 0  # fmt: skip
    n_rows = load_take(empty_start).n_frames
    rows = f"{EMPTY}:{n_rows}"
    cut = tmp_path / "cut.c3d"
    assert (
        main(["export-c3d", str(empty_start), "--out", str(cut), "--frames", rows]) == 0
    )
    two_step = tmp_path / "two_step.npz"
    assert main(["solve", str(cut), "--rig", "menache", "--calibration", str(cal),
                 "--out", str(two_step), "--quiet"]) == 0  # fmt: skip
    direct = tmp_path / "direct.npz"
    assert main(["solve", str(empty_start), "--rig", "menache", "--calibrate-frames",
                 HOLD, "--frames", rows, "--out", str(direct)]) == 0  # fmt: skip
    text = capsys.readouterr().out
    assert f"{n_rows - EMPTY} frames (rows {rows} of the take) at 120 Hz" in text
    with np.load(direct) as got, np.load(two_step) as want:
        assert got["world_from_bone_quat"].shape[0] == n_rows - EMPTY
        assert int(got["first_frame"]) == FIRST_FRAME + EMPTY
        assert int(want["first_frame"]) == FIRST_FRAME + EMPTY
        for key in ("world_from_bone_quat", "rest_from_bone_quat", "root_pos"):
            np.testing.assert_allclose(got[key], want[key], atol=1e-9, err_msg=key)


def test_solve_frames_json_and_bad_range(
    empty_start: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "s.npz"
    args = ["solve", str(empty_start), "--rig", "menache", "--calibrate-frames", HOLD]
    assert main([*args, "--frames", "200:260", "--out", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["frames"] == 60 and summary["frames_selected"] == "200:260"
    assert summary["first_frame"] == FIRST_FRAME + 200
    assert main([*args, "--frames", "300:300", "--out", str(tmp_path / "x.npz")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--frames: '300:300' selects no frames" in err[0]


def test_validate_frames(
    empty_start: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    report = tmp_path / "report"
    code = main(["validate", str(empty_start), "--rig", "menache",
                 "--calibrate-frames", HOLD, "--frames", "120:240",
                 "--report", str(report), "--no-snapshots", "--quiet"])  # fmt: skip
    assert code in (0, 1)
    doc = json.loads((report / "report.json").read_text())
    assert doc["frames"] == 120 and doc["frames_selected"] == "120:240"
    assert doc["first_frame"] == FIRST_FRAME + 120
    text = (report / "report.txt").read_text()
    assert "rows 120:240 of the take: frame f below is take row 120 + f" in text
