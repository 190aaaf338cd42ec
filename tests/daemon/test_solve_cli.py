"""calibrate + solve end to end on the synthetic performer, through the CLI."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.calibration import load_calibration
from retargetd.daemon.cli.main import main

NPZ_KEYS = {
    "joint_names", "joint_centres", "bone_names", "bone_parents",
    "world_from_bone_quat", "rest_from_bone_quat", "root_pos", "bone_lengths",
    "bone_quality", "bone_flags", "rate_hz", "world_from_capture", "foot_contact",
}  # fmt: skip


@pytest.fixture(scope="module")
def synth_take(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("synth") / "s.c3d"
    assert main(["synth", "--seconds", "4", "--rate", "120", "--out", str(path)]) == 0
    return path


def test_calibrate_then_solve(
    synth_take: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cal_path = tmp_path / "performer.json"
    args = ["calibrate", str(synth_take), "--rig", "menache", "--frames", "0:120"]
    assert main([*args, "--out", str(cal_path)]) == 0
    cal = load_calibration(cal_path)
    assert cal.rig_name == "menache" and cal.base_pose["frames"] == "0:120"
    out = tmp_path / "s.npz"
    solve = ["solve", str(synth_take), "--rig", "menache", "--calibration"]
    assert main([*solve, str(cal_path), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "joint-centre segment stability" in text
    with np.load(out, allow_pickle=False) as npz:
        assert set(npz.files) >= NPZ_KEYS
        n = 480
        b = len(npz["bone_names"])
        assert npz["world_from_bone_quat"].shape == (n, b, 4)
        assert npz["bone_quality"].dtype == np.float32
        assert npz["bone_flags"].dtype == np.uint8
        contact = npz["foot_contact"]  # (T, 2) bool; both feet down in the static hold
        assert contact.shape == (n, 2) and contact.dtype == np.bool_
        assert contact[:120].all()
        pfb = npz["rest_from_bone_quat"]
        assert np.isfinite(pfb).all()
        # Identity in the calibration pose (the static hold).
        assert np.degrees(rot.quat_angle(pfb[:120])).max() < 1e-6
        # The performer moves after the hold.
        assert np.degrees(rot.quat_angle(pfb[200:])).max() > 30.0
        np.testing.assert_allclose(
            np.linalg.norm(npz["world_from_bone_quat"], axis=-1), 1.0
        )


def test_solve_with_calibrate_frames_equals_two_step(
    synth_take: Path, tmp_path: Path
) -> None:
    cal_path = tmp_path / "p.json"
    assert main(["calibrate", str(synth_take), "--rig", "menache", "--frames", "0:120",
                 "--out", str(cal_path)]) == 0  # fmt: skip
    a, b = tmp_path / "a.npz", tmp_path / "b.npz"
    base = ["solve", str(synth_take), "--rig", "menache"]
    assert main([*base, "--calibration", str(cal_path), "--out", str(a)]) == 0
    assert main([*base, "--calibrate-frames", "0:120", "--out", str(b)]) == 0
    with np.load(a) as na, np.load(b) as nb:
        np.testing.assert_allclose(
            na["world_from_bone_quat"], nb["world_from_bone_quat"], atol=1e-9
        )


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["--rig", "nope", "--calibrate-frames", "0:10"],
            "no shipped rig named 'nope'",
        ),
        (["--rig", "menache", "--calibrate-frames", "5:2"], "selects no frames"),
        (["--rig", "menache", "--calibrate-frames", "x"], "expected a:b"),
        (
            ["--rig", "menache", "--calibration", "/no/such.json"],
            "cannot read calibration",
        ),
    ],
)
def test_solve_errors_are_one_line_exit_2(
    synth_take: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str],
    args: list[str], message: str,
) -> None:  # fmt: skip
    code = main(["solve", str(synth_take), *args, "--out", str(tmp_path / "o.npz")])
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]


def test_calibrating_without_a_needed_marker_is_one_clear_line(
    synth_take: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from retargetd.replay.c3d import write_c3d
    from retargetd.replay.takes import load_take

    full = load_take(synth_take)
    keep = [i for i, lab in enumerate(full.labels) if lab != "LHEAD"]
    part = tmp_path / "nohead.c3d"
    write_c3d(
        part, [full.labels[i] for i in keep], full.positions[:, keep], full.rate_hz
    )
    code = main(["calibrate", str(part), "--rig", "menache", "--frames", "0:10",
                 "--out", str(tmp_path / "p.json")])  # fmt: skip
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert "LHEAD" in err[0] and "never all seen" in err[0]
