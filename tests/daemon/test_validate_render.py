"""Report pictures (``validate_render``): headless snapshots of the worst frames and
the plot of the checks over time, on a clean synthetic take.

Outside CI, a machine without the GL libraries (EGL or OSMesa) skips the snapshot
tests with the reason; in CI (``CI=true``, ``.ci/run`` installs the Debian packages)
they must run.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from matplotlib.image import imread

from retargetd.daemon.body.solve import BodySolve
from retargetd.daemon.validate.checks import TakeReport, validate_take
from retargetd.daemon.validate.model import (
    ValidationModel,
)
from retargetd.daemon.validate.render import (
    BLAMED_RGBA,
    HEIGHT,
    MAX_SNAPSHOTS,
    PLOT_NAME,
    WIDTH,
    render_snapshots,
    snapshot_jobs,
    worst_frames,
    write_visuals,
)

DATA = Path(__file__).resolve().parent.parent / "data"
RATE_HZ = 120.0


pytestmark = pytest.mark.usefixtures("mujoco_cwd")


@dataclasses.dataclass(frozen=True)
class Take:
    vm: ValidationModel
    solve: BodySolve
    rep: TakeReport


@pytest.fixture(scope="module")
def take(clean_synth: Any) -> Take:
    """The shared clean synthetic take (``tests/daemon/conftest.py``), validated."""
    c = clean_synth
    rep = validate_take(c.vm, c.solve, c.rate_hz, fit=c.fit)
    return Take(c.vm, c.solve, rep)


def _need_render(render: dict[str, Any]) -> None:
    """Skip (outside CI) or fail (CI) when no headless GL backend works."""
    if render["skipped"] is None:
        return
    if os.environ.get("CI") == "true":
        pytest.fail(f"CI must render snapshots: {render['skipped']}")
    pytest.skip(render["skipped"])


def _rgb(path: Path) -> np.ndarray:
    img = imread(path)  # PNG: float 0..1, (H, W, 3 or 4)
    assert img.dtype == np.float32
    return np.asarray(img[..., :3], dtype=np.float64)


def _reddish(rgb: np.ndarray) -> int:
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    return int(((r > 0.35) & (r > 2.0 * g) & (r > 2.0 * b)).sum())


def test_worst_frames_union_capped(take: Take) -> None:
    assert take.rep.passed  # no check fails: every check's worst frames
    frames = worst_frames(take.rep)
    assert 1 <= len(frames) <= MAX_SNAPSHOTS
    assert frames == sorted(set(frames))
    assert worst_frames(take.rep, cap=2) == sorted(worst_frames(take.rep, cap=2))
    assert len(worst_frames(take.rep, cap=2)) == 2
    # The frame of each check's maximum is among the first picks (round-robin).
    firsts = {int(np.nanargmax(c.values)) for c in take.rep.checks.values()}
    assert len(firsts) > MAX_SNAPSHOTS or firsts <= set(frames)


def test_snapshots_and_plot(take: Take, tmp_path: Path) -> None:
    vis = write_visuals(tmp_path, take.vm, take.solve, take.rep, RATE_HZ)
    plot = imread(tmp_path / PLOT_NAME)
    assert plot.ndim == 3 and plot.shape[0] > 100 and plot.shape[1] > 100
    assert plot[..., :3].std() > 0
    _need_render(vis["render"])
    assert vis["render"]["backend"] in ("egl", "osmesa")
    assert 1 <= len(vis["snapshots"]) <= MAX_SNAPSHOTS
    for snap in vis["snapshots"]:
        rgb = _rgb(tmp_path / snap["file"])
        assert rgb.shape == (HEIGHT, WIDTH, 3)
        assert rgb.std() > 0.01
        # The camera looks at the root: the skeleton is in the middle of the frame,
        # and its pixels differ from the background at the top corners.
        mid = rgb[HEIGHT // 3 : 2 * HEIGHT // 3, WIDTH // 3 : 2 * WIDTH // 3]
        corners = np.concatenate([rgb[:20, :20], rgb[:20, -20:]]).reshape(-1, 3)
        background = np.median(corners, axis=0)
        differs = np.abs(mid - background).max(axis=-1) > 0.1
        assert differs.mean() > 0.02, snap
        assert _reddish(rgb) == 0  # a clean take: nothing blamed
    assert vis["render"]["seconds_per_snapshot"] < 5.0


def test_blamed_bones_drawn_red(take: Take, tmp_path: Path) -> None:
    frame = take.rep.n_frames // 2
    (job,) = snapshot_jobs(take.vm, take.solve, take.rep, [frame])
    red = dict(job, file="red.png")
    geoms = np.flatnonzero(take.vm.geom_bone >= 0)
    rgba = np.asarray(job["rgba"])
    rgba[geoms] = BLAMED_RGBA
    red["rgba"] = rgba.tolist()
    render = render_snapshots(take.vm.xml, [job, red], tmp_path)
    _need_render(render)
    plain, blamed = _rgb(tmp_path / job["file"]), _rgb(tmp_path / "red.png")
    assert _reddish(plain) == 0
    assert _reddish(blamed) > 500  # the skeleton's pixels, all red
    assert np.abs(plain - blamed).max() > 0.3


def test_no_backend_skips_with_reason(take: Take, tmp_path: Path) -> None:
    vis = write_visuals(
        tmp_path, take.vm, take.solve, take.rep, RATE_HZ, backends=("no-such-gl",)
    )
    assert vis["render"]["skipped"].startswith("no headless GL backend works")
    assert "no-such-gl" in vis["render"]["skipped"]
    assert vis["snapshots"] == []
    assert (tmp_path / PLOT_NAME).is_file()
    assert not list(tmp_path.glob("snapshot_*.png"))


def test_cli_report_lists_pictures(
    datasets: Path, pig_calibration: Path, tmp_path: Path
) -> None:
    """``retargetd validate`` on the PiG walk: the plot and snapshots are written and
    named in report.json and report.txt."""
    import json

    from retargetd.daemon.cli.main import main

    report = tmp_path / "report"
    walk = datasets / "btkdata/PiG_Motion-FlatFoot-Full.c3d"
    argv = [
        "validate", str(walk), "--rig", "plug-in-gait",
        "--calibration", str(pig_calibration), "--report", str(report),
    ]  # fmt: skip
    assert main(argv) == 0
    doc = json.loads((report / "report.json").read_text())
    vis = doc["visuals"]
    text = (report / "report.txt").read_text()
    assert (report / vis["plot"]).is_file() and f"Plot: {vis['plot']}" in text
    _need_render(vis["render"])
    assert 1 <= len(vis["snapshots"]) <= MAX_SNAPSHOTS
    for snap in vis["snapshots"]:
        assert _rgb(report / snap["file"]).shape == (HEIGHT, WIDTH, 3)
        assert snap["file"] in text
    assert not (Path(__file__).resolve().parents[2] / "MUJOCO_LOG.TXT").exists()
