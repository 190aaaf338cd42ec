"""``--plant-feet`` on ``blend`` and ``loop`` (issue 34 item 2): the clip written with
the ``target_*`` arrays of its motion planted on the target, as ``solve
--plant-feet`` plants a solve; any output but ``.npz`` refused in one line, exit 2.
On the synthetic level walk (feet that stay put), Plug-in Gait, 6 s at 60 Hz."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

CLI = [sys.executable, "-m", "retargetd.daemon"]
RIG = ["--rig", "plug-in-gait", "--calibrate-frames", "0:30"]
FADE = 10


def _run(*argv: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*CLI, *argv], capture_output=True, text=True, timeout=300, check=False
    )


@pytest.fixture(scope="module")
def walk(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    """The take and ``solve --plant-feet``'s target arrays."""
    root = tmp_path_factory.mktemp("plant_clip")
    take = root / "walk.c3d"
    synth = ["synth", "--seconds", "6", "--rate", "60", "--motions", "level_walk"]
    done = _run(*synth, "--markers", "plug-in-gait", "--out", str(take))
    assert done.returncode == 0, done.stderr
    out = root / "solve.npz"
    done = _run("solve", str(take), *RIG, "--out", str(out), "--plant-feet",
                "--quiet")  # fmt: skip
    assert done.returncode == 0, done.stderr
    with np.load(out) as d:
        return take, {k: d[k] for k in d.files if k.startswith("target_")}


def test_blend_plants_the_blended_motion(
    walk: tuple[Path, dict], tmp_path: Path
) -> None:
    """The take blended into itself at the same frame is the take: its planted
    target equals ``solve --plant-feet``'s (1e-9), flags included."""
    take, solved = walk
    out = tmp_path / "b.npz"
    done = _run("blend", str(take), str(take), *RIG, "--at", "150:150", "--frames",
                str(FADE), "--out", str(out), "--plant-feet")  # fmt: skip
    assert done.returncode == 0, done.stderr
    with np.load(out) as d:
        assert str(d["target_feet"]) == "plant"
        for key in ("target_world_from_bone_quat", "target_root_pos"):
            np.testing.assert_allclose(d[key], solved[key], atol=1e-9)
        np.testing.assert_array_equal(
            d["target_plant_flags"], solved["target_plant_flags"]
        )
        assert float(d["target_leg_ratio"]) == float(solved["target_leg_ratio"])
        assert d["world_from_bone_quat"].shape[0] == len(d["target_root_pos"])


def test_loop_plants_the_loop(walk: tuple[Path, dict], tmp_path: Path) -> None:
    """The loop of rows 60..359: past the fade and one second for the stance
    detector and the holds to catch up, its planted target is ``solve
    --plant-feet``'s on the same rows (1e-9); within the fade it is not (a fade is
    a motion of its own)."""
    take, solved = walk
    out = tmp_path / "l.npz"
    done = _run("loop", str(take), *RIG, "--frames", str(FADE), "--range",
                "60:360", "--out", str(out), "--plant-feet")  # fmt: skip
    assert done.returncode == 0, done.stderr
    with np.load(out) as d:
        wfb = d["target_world_from_bone_quat"]
        assert wfb.shape[0] == 300 - FADE == len(d["target_plant_flags"])
        rows = solved["target_world_from_bone_quat"][60 + FADE : 360 - FADE]
        settled = FADE + 60
        np.testing.assert_allclose(wfb[settled:], rows[settled - FADE :], atol=1e-9)
        assert (
            np.abs(wfb[:FADE] - solved["target_world_from_bone_quat"][60:70]).max()
            > 1e-3
        )


@pytest.mark.parametrize("command", ["blend", "loop"])
def test_plant_feet_wants_npz(
    walk: tuple[Path, dict], tmp_path: Path, command: str
) -> None:
    take, _ = walk
    extra = ["--at", "150:150"] if command == "blend" else []
    argv = [command, str(take), *([str(take)] if command == "blend" else []), *RIG,
            *extra, "--frames", str(FADE), "--out", str(tmp_path / "x.glb"),
            "--plant-feet"]  # fmt: skip
    done = _run(*argv)
    assert done.returncode == 2
    assert "--plant-feet" in done.stderr and ".npz only" in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "x.glb").exists()
