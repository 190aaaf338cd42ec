"""Nothing is overwritten silently: ``record``, ``solve --out``, ``export-c3d``,
``validate --report`` and ``face-train`` refuse an existing output with one line and
exit 2 unless ``--force`` (issue 16 item 3)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from retargetd.daemon.cli.main import main

SENTINEL = b"an earlier output that must survive\n"


@pytest.fixture(scope="module")
def synth_take(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("synth") / "s.c3d"
    assert main(["synth", "--seconds", "1.5", "--rate", "60", "--out", str(path)]) == 0
    return path


def _refused(
    argv: list[str], target: Path, capsys: pytest.CaptureFixture[str], option: str
) -> None:
    """``argv`` exits 2 with one line naming the option, the path and --force, and
    ``target`` keeps its bytes."""
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    named = str(target.parent if option == "--report" else target)
    assert option in lines[0] and named in lines[0] and "--force" in lines[0]
    assert target.read_bytes() == SENTINEL


def test_export_c3d_refuses_then_force_replaces(
    synth_take: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out.c3d"
    out.write_bytes(SENTINEL)
    argv = ["export-c3d", str(synth_take), "--out", str(out)]
    _refused(argv, out, capsys, "--out")
    assert main([*argv, "--force"]) == 0
    assert out.read_bytes()[:2] != SENTINEL[:2] and out.stat().st_size > 512


@pytest.mark.parametrize("suffix", ["npz", "bvh"])
def test_solve_refuses_then_force_replaces(
    synth_take: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], suffix: str
) -> None:
    out = tmp_path / f"out.{suffix}"
    out.write_bytes(SENTINEL)
    argv = [
        "solve", str(synth_take), "--rig", "menache", "--calibrate-frames", "0:30",
        "--out", str(out),
    ]  # fmt: skip
    _refused(argv, out, capsys, "--out")
    assert main([*argv, "--force"]) == 0
    assert out.read_bytes() != SENTINEL
    said = capsys.readouterr().out
    assert re.search(r"^solved in \d+\.\d\d s: \d+ frames/s$", said, re.M), said


def test_validate_refuses_a_report_folder_that_holds_a_report(
    synth_take: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    report = tmp_path / "report"
    report.mkdir()
    old = report / "report.json"
    old.write_bytes(SENTINEL)
    argv = [
        "validate", str(synth_take), "--rig", "menache", "--calibrate-frames", "0:30",
        "--report", str(report),
    ]  # fmt: skip
    _refused(argv, old, capsys, "--report")
    assert sorted(p.name for p in report.iterdir()) == ["report.json"]


def test_face_train_refuses(
    synth_take: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "face.npz"
    out.write_bytes(SENTINEL)
    argv = [
        "face-train", str(synth_take), "--face", "arkit52", "--poses", "neutral=0:10",
        "--out", str(out),
    ]  # fmt: skip
    _refused(argv, out, capsys, "--out")


@pytest.mark.timeout(30)
def test_record_refuses_then_force_replaces(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Refused before any socket is opened; with --force a short recording (nothing
    sent: a valid, empty MCAP) replaces the file."""
    out = tmp_path / "take.mcap"
    out.write_bytes(SENTINEL)
    argv = ["record", "--listen", "osc://127.0.0.1:0", "--out", str(out)]
    _refused([*argv, "--seconds", "0.2"], out, capsys, "--out")
    assert "listening on" not in capsys.readouterr().out
    assert main([*argv, "--seconds", "0.2", "--force"]) == 0
    assert out.read_bytes()[:8] == b"\x89MCAP0\r\n"
