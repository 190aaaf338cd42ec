"""``retargetd synth`` end to end: C3D/TRC out, read back, truth NPZ, bad arguments."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from retargetd.daemon.cli.main import main
from retargetd.daemon.synth.performer import load_truth, synthesize
from retargetd.replay.takes import load_take


def test_synth_writes_a_c3d_that_reads_back(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "take.c3d"
    truth = tmp_path / "truth.npz"
    argv = [
        "synth",
        "--seconds",
        "3",
        "--rate",
        "120",
        "--out",
        str(out),
        "--truth",
        str(truth),
        "--dropout",
        "0.05",
        "--seed",
        "4",
    ]
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "frames 360 at 120 Hz" in text and "base pose frames 0:120" in text
    assert "l_forearm" in text and "pelvis path" in text

    take = load_take(out)
    expected = synthesize(seconds=3, rate_hz=120, dropout=0.05, seed=4)
    assert take.labels == expected.labels
    assert take.rate_hz == 120 and take.up_axis == "+Z" and take.units == "mm"
    np.testing.assert_array_equal(take.valid, expected.valid)
    # float32 in the file: ~1e-7 relative of a few metres (in mm) -> < 1e-6 m.
    np.testing.assert_allclose(
        take.positions[take.valid], expected.markers_world[expected.valid], atol=1e-6
    )
    with np.load(truth, allow_pickle=False) as npz:
        assert npz["joint_pos_world"].shape == (360, 21, 3)
    back = load_truth(truth)
    np.testing.assert_array_equal(back.markers_world, expected.markers_world)


def test_synth_writes_trc_y_up_in_metres(tmp_path: Path) -> None:
    out = tmp_path / "take.trc"
    argv = [
        "synth",
        "--seconds",
        "0.5",
        "--rate",
        "50",
        "--out",
        str(out),
        "--units",
        "m",
        "--markers",
        "plug-in-gait",
        "--motions",
        "walk,head_turn",
    ]
    assert main(argv) == 0
    take = load_take(out)  # TRC readers assume +Y up: back in our +Z world
    expected = synthesize(
        seconds=0.5, rate_hz=50, markerset="plug-in-gait", motions=["walk", "head_turn"]
    )
    assert take.units == "m" and len(take.labels) == 35
    np.testing.assert_allclose(take.positions, expected.markers_world, atol=1e-5)


@pytest.mark.parametrize(
    ("extra", "match"),
    [
        (["--seconds", "0"], "--seconds"),
        (["--rate", "0.1"], "--rate"),
        (["--rate", "1e6"], "--rate"),
        (["--dropout", "1"], "--dropout"),
        (["--noise-mm", "-1"], "--noise-mm"),
        (["--motions", "walk,fly"], "fly"),
        (["--out", "x.bvh"], r"\.c3d or \.trc"),
        (["--markers", "nope"], "unknown marker set 'nope'"),
    ],
)
def test_bad_arguments_exit_2_with_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], extra: list[str], match: str
) -> None:
    args = {"--seconds": "1", "--rate": "60", "--out": str(tmp_path / "t.c3d")}
    for flag, value in zip(extra[::2], extra[1::2], strict=True):
        args[flag] = value
    argv = ["synth", *[x for kv in args.items() for x in kv]]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("retargetd synth: error:")
    assert re.search(match, err)
    assert not (tmp_path / "t.c3d").exists()
