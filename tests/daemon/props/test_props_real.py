"""A real rigid cluster: the 8-marker box of pyomeca's ``markers_analogs.c3d``
(labels ``boite:``, Vicon Nexus, 100 Hz, 580 frames) calibrated with
``retargetd calibrate --prop`` on its first 20 frames and solved on every frame."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from retargetd.daemon.cli.main import main
from retargetd.daemon.cli.prop_io import load_prop_take
from retargetd.daemon.props import kernel as pk
from retargetd.daemon.props.layout import load_layout
from retargetd.daemon.props.solve import solve_take


def test_the_pyomeca_box_is_solved_rigidly(
    datasets: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    take_path = datasets / "pyomeca" / "markers_analogs.c3d"
    out = tmp_path / "boite.json"
    argv = ["calibrate", str(take_path), "--prop", "boite", "--frames", "0:20"]
    assert main([*argv, "--out", str(out)]) == 0
    said = capsys.readouterr().out
    assert "prop boite (rigid), 8 markers" in said and "boite:gauche_ext" in said
    layout = load_layout(out)
    take, labels, cols = load_prop_take(str(take_path), layout.labels, "boite:")
    track = solve_take(layout, labels, take.positions, take.valid)
    seen = take.valid[:, cols].sum(axis=1)
    # every frame solved from every marker seen: none gated, none held
    assert not np.any(track.flags & pk.FLAG_HELD)
    np.testing.assert_array_equal(track.used, seen)
    rms_mm = track.rms_m * 1000
    # the rigidity residual (README "Props and a virtual camera"): median 0.27 mm,
    # p95 0.52 mm, max 1.5 mm measured; the gate is 10 mm
    assert np.median(rms_mm) < 0.5 and np.percentile(rms_mm, 95) < 1.0
    assert rms_mm.max() < 3.0
    # and the box did move: the check is not of a still take
    turned = Rotation.from_quat(track.world_from_prop_quat, scalar_first=True)
    assert np.degrees((turned * turned[0].inv()).magnitude()).max() > 20.0
    assert np.ptp(track.prop_pos_world, axis=0).max() > 0.3


def test_calibrate_prop_errors_are_one_line(
    datasets: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    take_path = str(datasets / "pyomeca" / "markers_analogs.c3d")
    out = str(tmp_path / "p.json")
    for extra, said in (
        (["--prop", "chair"], "has no subject 'chair'; it holds: boite, Daphnee"),
        (["--prop", "b", "--markers", "boite:gauche_ext,x,y"], "missing x, y"),
        (["--prop", "boite", "--pivot-mm", "1,2"], "--pivot-mm"),
        (["--prop", "boite", "--frames", "0:400"], "not still"),
        ([], "--rig is required"),
    ):
        assert main(["calibrate", take_path, *extra, "--out", out]) == 2, extra
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and said in err, (extra, err)
    assert not Path(out).exists()
