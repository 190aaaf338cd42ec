"""A saved calibration replaces the old file all at once (issue 29 item 4): written to
a temporary file in the same folder, flushed, fsynced and renamed over the target, so
a full disk (ENOSPC, simulated: a disk cannot be filled here) or a crash before the
rename leaves the old file whole and readable and no temporary file behind."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import pytest

from retargetd.daemon import files as filesmod
from retargetd.daemon.body.calibration import (
    Calibration,
    calibrate,
    load_calibration,
)
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.cli.main import main
from retargetd.daemon.synth.performer import synthesize


@pytest.fixture(scope="module")
def two_calibrations() -> tuple[Calibration, Calibration]:
    """Two different calibrations of menache on the synthetic T-pose hold."""
    take = synthesize(seconds=1.0, rate_hz=50.0, markerset="menache")
    rig = load_rig("menache")
    hold = take.markers_world[take.base_pose_frames]
    return calibrate(rig, hold[:10], take.labels), calibrate(
        rig, hold[:10] * 1.05, take.labels
    )


def _enospc(*_args: object) -> None:
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


@pytest.mark.parametrize("fails", ["fsync", "write", "replace"])
def test_a_failed_save_keeps_the_old_file(
    two_calibrations: tuple[Calibration, Calibration],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    fails: str,
) -> None:
    old, new = two_calibrations
    path = tmp_path / "performer.json"
    old.save(path)
    before = path.read_bytes()
    if fails == "write":  # the disk fills while the data is written
        fdopen = os.fdopen

        class Full:
            def __init__(self, fd: int, mode: str) -> None:
                self.f = fdopen(fd, mode)

            def __enter__(self) -> Full:
                return self

            def __exit__(self, *exc: object) -> None:
                self.f.close()

            def write(self, data: bytes) -> int:
                self.f.write(data[: len(data) // 2])
                _enospc()
                return 0

        monkeypatch.setattr(filesmod.os, "fdopen", Full)
    else:
        monkeypatch.setattr(filesmod.os, fails, _enospc)
    with pytest.raises(OSError) as info:
        new.save(path)
    monkeypatch.undo()
    assert info.value.errno == errno.ENOSPC
    text = str(info.value)
    assert "\n" not in text and str(path) in text and "No space left" in text, text
    assert path.read_bytes() == before  # the old file, whole
    assert load_calibration(path).bone_lengths.tolist() == old.bone_lengths.tolist()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["performer.json"]


def test_a_save_replaces_the_file_and_leaves_nothing_else(
    two_calibrations: tuple[Calibration, Calibration], tmp_path: Path
) -> None:
    old, new = two_calibrations
    path = tmp_path / "performer.json"
    old.save(path)
    new.save(path)
    assert load_calibration(path).bone_lengths.tolist() == new.bone_lengths.tolist()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["performer.json"]


def test_calibrate_on_a_full_disk_is_one_line_and_keeps_the_old_file(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    take = tmp_path / "t.c3d"
    assert main(["synth", "--seconds", "1", "--rate", "50", "--out", str(take)]) == 0
    out = tmp_path / "performer.json"
    argv = ["calibrate", str(take), "--rig", "menache", "--frames", "0:40"]
    assert main([*argv, "--out", str(out)]) == 0
    before = out.read_bytes()
    capsys.readouterr()
    monkeypatch.setattr(filesmod.os, "fsync", _enospc)
    assert main([*argv, "--measure", "MarkerRadius=9", "--out", str(out)]) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if "error" in ln]
    assert len(err) == 1 and "No space left" in err[0] and str(out) in err[0], err
    assert out.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["performer.json", "t.c3d"]
