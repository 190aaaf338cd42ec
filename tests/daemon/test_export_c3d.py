"""``retargetd export-c3d``: markers from any take to C3D, read back unchanged."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from retargetd.daemon.cli.main import main
from retargetd.replay.c3d import write_c3d
from retargetd.replay.takes import load_take
from retargetd.replay.trc import write_trc

F32_EPS = float(np.finfo(np.float32).eps)


def _positions(rng: np.random.Generator, n_frames: int = 30) -> np.ndarray:
    pos = rng.uniform([-1.0, -1.0, 0.0], [1.0, 1.0, 1.9], size=(n_frames, 4, 3))
    pos[2:7, 1] = np.nan
    pos[-1, 3] = np.nan
    return pos


def _same(a, b, scale: float = 2.0) -> None:
    np.testing.assert_array_equal(b.valid, a.valid)
    tol = F32_EPS * scale * 1000  # float32 in mm
    np.testing.assert_allclose(b.positions[b.valid], a.positions[a.valid], atol=tol)
    assert np.isnan(b.positions[~b.valid]).all()


@pytest.mark.parametrize(("units", "up"), [("mm", "+Z"), ("m", "+Y")])
def test_c3d_round_trip_with_subject(
    tmp_path: Path, rng: np.random.Generator, units: str, up: str
) -> None:
    src = tmp_path / "in.c3d"
    labels = ["LASI", "RASI", "LPSI", "RPSI"]
    write_c3d(src, labels, _positions(rng), 100.0, subject="Pat", first_frame=5,
              measurements={"Bodymass": 70.0})  # fmt: skip
    out = tmp_path / "out.c3d"
    args = ["export-c3d", str(src), "--out", str(out), "--units", units, "--up", up]
    assert main(args) == 0
    a, b = load_take(src), load_take(out)
    _same(a, b)
    assert b.labels == a.labels and b.subject == "Pat" and b.subjects == ("Pat",)
    assert (b.units, b.up_axis) == (units, up)
    assert b.rate_hz == 100.0 and b.first_frame == 5
    assert b.measurements == {"Bodymass": 70.0}
    # Prefix renamed, then dropped.
    assert main([*args, "--out-subject", "Sam", "--force"]) == 0
    assert load_take(out).subject == "Sam"
    assert main([*args, "--out-subject", "", "--force"]) == 0
    assert load_take(out).subjects == () and load_take(out).labels == a.labels


def test_trc_to_c3d_with_frames(
    tmp_path: Path, rng: np.random.Generator, capsys: pytest.CaptureFixture[str]
) -> None:
    src = tmp_path / "in.trc"
    pos = _positions(rng)
    write_trc(src, ["A", "B", "C", "D"], pos, 60.0)
    out = tmp_path / "out.c3d"
    assert main(["export-c3d", str(src), "--out", str(out), "--frames", "3:20"]) == 0
    assert "17 frames at 60 Hz, 4 markers" in capsys.readouterr().out
    a, b = load_take(src), load_take(out)
    assert b.n_frames == 17 and b.first_frame == a.first_frame + 3
    np.testing.assert_array_equal(b.valid, a.valid[3:20])
    np.testing.assert_allclose(
        b.positions[b.valid], a.positions[3:20][b.valid], atol=F32_EPS * 2000
    )


def test_pig_references(
    datasets: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    src = datasets / "btkdata" / "PiG_Motion-FlatFoot-Full.c3d"
    out = tmp_path / "w.c3d"
    assert main(["export-c3d", str(src), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "not exported: 158 vendor references (add --with-references" in text
    a, b = load_take(src), load_take(out)
    _same(a, b)
    assert b.subject == a.subject == "BELT_C" and b.references.labels == ()
    assert (
        main(
            ["export-c3d", str(src), "--out", str(out), "--with-references", "--force"]
        )
        == 0
    )
    assert "never written" in capsys.readouterr().out
    c = load_take(out)
    assert c.labels == a.labels
    kept = [i for i, k in enumerate(a.references.kinds) if k != "angle"]
    assert set(c.references.labels) <= {a.references.labels[i] for i in kept}
    assert c.references.kinds[c.references.index("LFEP")] == "segment_point"
    np.testing.assert_allclose(
        c.references.get("LFEP"), a.references.get("LFEP"), atol=1e-6
    )


def test_usage(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["export-c3d", "x.trc", "--out", str(tmp_path / "o.trc")]) == 2
    assert "expected a .c3d file" in capsys.readouterr().err
