"""Props on the command line, end to end on real files: ``synth --props`` writes a
C3D with the performer and the props' markers (and their truth), ``calibrate --prop``
calibrates each on the base-pose hold, ``solve --prop`` solves them beside the body
into the NPZ; the poses agree with the truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from retargetd.daemon.cli.main import main


def test_synth_calibrate_solve_props(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    take = tmp_path / "s.c3d"
    truth = tmp_path / "t.npz"
    argv = ["synth", "--seconds", "5", "--rate", "120", "--noise-mm", "0.5"]
    assert main([*argv, "--props", "camera,sword", "--out", str(take),
                 "--truth", str(truth)]) == 0  # fmt: skip
    props_truth = np.load(tmp_path / "t.props.npz")
    for name in ("camera", "sword"):
        out = tmp_path / f"{name}.json"
        assert main(["calibrate", str(take), "--prop", name, "--prefix", name,
                     "--frames", "0:120", "--out", str(out)]) == 0  # fmt: skip
    capsys.readouterr()
    npz = tmp_path / "solved.npz"
    solve = ["solve", str(take), "--rig", "menache", "--calibrate-frames", "0:120"]
    props = ["--prop", str(tmp_path / "camera.json"),
             "--prop", str(tmp_path / "sword.json")]  # fmt: skip
    assert main([*solve, *props, "--out", str(npz)]) == 0
    said = capsys.readouterr().out
    assert "prop camera: 5 markers, 600 frames" in said
    assert "prop sword: 4 markers, 600 frames" in said and "held 0 frames" in said
    solved = np.load(npz)
    assert solved["joint_centres"].shape[0] == 600  # the body is still solved
    for name in ("camera", "sword"):
        q_true = Rotation.from_quat(
            props_truth[f"{name}_world_from_prop_quat"], scalar_first=True
        )
        ref = q_true * q_true[60].inv()  # the solve's axes: the world's at calibration
        q = Rotation.from_quat(solved[f"prop_{name}_world_from_prop_quat"],
                               scalar_first=True)  # fmt: skip
        err = np.degrees((q * ref.inv()).magnitude())
        pos_mm = 1e3 * np.linalg.norm(
            solved[f"prop_{name}_pos_world"] - props_truth[f"{name}_pos_world"], axis=1
        )
        assert np.percentile(err, 95) < 0.5 and np.percentile(pos_mm, 95) < 1.0
        assert np.all(solved[f"prop_{name}_flags"] == 0)


def test_bad_prop_options_are_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    take = tmp_path / "s.c3d"
    base = ["synth", "--seconds", "1", "--rate", "60", "--out", str(take)]
    assert main([*base, "--props", "chair"]) == 2
    assert "--props: unknown props ['chair']" in capsys.readouterr().err
    assert main(base) == 0
    bad = tmp_path / "bad.json"
    bad.write_text("{}")
    solve = ["solve", str(take), "--rig", "menache", "--calibrate-frames", "0:30"]
    assert main([*solve, "--prop", str(bad), "--out", str(tmp_path / "o.npz")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not a retargetd-prop file" in err
