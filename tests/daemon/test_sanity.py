"""Sanity before any solve (issue 16 item 2): wrong units, a wrong up axis, a base
pose that is not held and left/right bones that differ are caught at calibration,
on real takes and on the synthetic performer."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest

from retargetd.daemon.body import sanity
from retargetd.daemon.body.calibration import calibrate
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.cli.main import main
from retargetd.daemon.synth.performer import SynthTake, synthesize
from retargetd.replay.takes import load_take
from retargetd.replay.trc import write_trc

PIG_STATIC = "btkdata/PiG_Calibration-FlatFoot-Full.c3d"
PIG_WALK = "btkdata/PiG_Motion-FlatFoot-Full.c3d"


def _one_error(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


def _calibrate(argv: list[str], tmp_path: Path) -> list[str]:
    return ["calibrate", *argv, "--out", str(tmp_path / "cal.json")]


#: The up-lever warnings the real base poses do give (``check_up_levers``): the feet
#: of Plug-in Gait and cmu41 take their roll from the heel, 13-26 mm off the
#: ankle->toe line (RIGS.md "How much lever an up reference needs").
LEVER_WARNINGS = {
    PIG_STATIC: {"lfoot"},
    "btkdata/MOTEK_T.trc": {"lfoot", "rfoot"},
    "kineticstoolkit/kinematics_tennis_serve.c3d": set(),
}


def _warnings(err: str) -> tuple[list[str], set[str]]:
    """The warning lines other than up-lever ones, and the bones those name."""
    other, bones = [], set()
    for line in err.splitlines():
        m = re.match(r"warning: bone (\S+): its up reference is \d+ mm off", line)
        if m:
            bones.add(m.group(1))
        elif "warning" in line:
            other.append(line)
    return other, bones


# --- real takes ----------------------------------------------------------------------


def test_metres_labelled_mm_is_refused_naming_take_units(
    datasets: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The PiG static as a TRC in metres whose header says mm: exit 2, naming the
    override with the unit that fits (and it then calibrates)."""
    take = load_take(datasets / PIG_STATIC)
    trc = tmp_path / "static.trc"
    write_trc(trc, take.labels, take.positions, take.rate_hz, units="m", up_axis="+Z")
    lines = trc.read_text().split("\n")
    assert lines[2].split("\t")[4] == "m"
    fields = lines[2].split("\t")
    fields[4] = "mm"
    lines[2] = "\t".join(fields)
    trc.write_text("\n".join(lines))
    argv = [str(trc), "--rig", "plug-in-gait", "--take-up", "+Z"]
    assert main(_calibrate(argv, tmp_path)) == 2
    line = _one_error(capsys)
    assert "--take-units m" in line and "mm" in line
    assert main(_calibrate([*argv, "--take-units", "m"], tmp_path)) == 0
    assert _warnings(capsys.readouterr().err) == ([], LEVER_WARNINGS[PIG_STATIC])


def test_z_up_trc_read_as_y_up_is_refused_naming_take_up(
    datasets: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A Z-up TRC (TRC stores no up axis; the reader assumes +Y): exit 2 naming
    ``--take-up +Z``; an explicit --take-up that disagrees only warns."""
    take = load_take(datasets / PIG_STATIC)
    trc = tmp_path / "static_zup.trc"
    write_trc(trc, take.labels, take.positions, take.rate_hz, up_axis="+Z")
    argv = [str(trc), "--rig", "plug-in-gait"]
    assert main(_calibrate(argv, tmp_path)) == 2
    line = _one_error(capsys)
    assert "--take-up +Z" in line and "+Y" in line
    assert main(_calibrate([*argv, "--take-up", "+Z"], tmp_path)) == 0
    assert _warnings(capsys.readouterr().err) == ([], LEVER_WARNINGS[PIG_STATIC])


def test_calibrating_on_walking_frames_is_refused(
    datasets: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = [str(datasets / PIG_WALK), "--rig", "plug-in-gait", "--frames", "100:200"]
    assert main(_calibrate(argv, tmp_path)) == 2
    line = _one_error(capsys)
    assert "not still" in line and "--allow-moving-base-pose" in line
    assert main(_calibrate([*argv, "--allow-moving-base-pose"], tmp_path)) == 0
    err = capsys.readouterr().err
    assert "warning: the base pose is not still" in err
    # The same refusal where solve and validate calibrate on the take itself.
    solve = [
        "solve", str(datasets / PIG_WALK), "--rig", "plug-in-gait",
        "--calibrate-frames", "100:200", "--out", str(tmp_path / "s.npz"),
    ]  # fmt: skip
    assert main(solve) == 2
    assert "--allow-moving-base-pose" in _one_error(capsys)


@pytest.mark.parametrize(
    ("path", "rig", "frames"),
    [
        (PIG_STATIC, "plug-in-gait", None),
        ("btkdata/MOTEK_T.trc", "cmu41", None),
        ("kineticstoolkit/kinematics_tennis_serve.c3d", "cmu41", "0:50"),
    ],
)
def test_real_base_poses_pass_every_check(
    datasets: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    path: str,
    rig: str,
    frames: str | None,
) -> None:
    argv = [str(datasets / path), "--rig", rig]
    argv += ["--frames", frames] if frames else []
    assert main(_calibrate(argv, tmp_path)) == 0
    # only the up-lever warnings, each naming its bone
    assert _warnings(capsys.readouterr().err) == ([], LEVER_WARNINGS[path])
    take = load_take(datasets / path)
    rows = slice(0, 50) if frames else slice(None)
    motion = sanity.base_pose_motion(take.positions[rows], take.labels, take.rate_hz)
    assert motion.still and 0.0 < motion.speed_m_s < sanity.STILL_SPEED_LIMIT_M_S


def test_wrong_rig_gives_one_error_line_without_warnings(
    datasets: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    caplog: pytest.LogCaptureFixture,
) -> None:
    """MOTEK's CMU markers lack Plug-in Gait's pelvis: the one error line, not the
    calibration's "markers never seen" warnings before it. A calibration that
    succeeds still logs them."""
    argv = [str(datasets / "btkdata/MOTEK_T.trc"), "--rig", "plug-in-gait"]
    with caplog.at_level("WARNING"):
        assert main(_calibrate(argv, tmp_path)) == 2
    line = _one_error(capsys)
    assert line.startswith("retargetd calibrate: error: rig plug-in-gait")
    assert not [r for r in caplog.records if "never seen" in r.getMessage()]
    argv = [str(datasets / PIG_STATIC), "--rig", "cmu41"]
    with caplog.at_level("WARNING"):
        assert main(_calibrate(argv, tmp_path)) == 0
    assert [r for r in caplog.records if "markers never seen" in r.getMessage()]


# --- the synthetic performer and the library ------------------------------------------


@pytest.fixture(scope="module")
def synth() -> SynthTake:
    """Menache markers with 0.5 mm of noise (a good optical system's residual)."""
    return synthesize(
        seconds=2.5, rate_hz=100.0, markerset="menache", noise_mm=0.5, seed=3
    )


def test_synthetic_hold_is_still_and_its_motion_is_not(synth: SynthTake) -> None:
    """The performer's base-pose hold (exact T-pose plus marker noise) is still; the
    frames after the ramp (walking) are not."""
    pos, labels = synth.markers_world, synth.labels
    hold = sanity.base_pose_motion(pos[:90], labels, 100.0)
    assert hold.still and hold.lag_frames == 10
    moving = sanity.base_pose_motion(pos[-80:], labels, 100.0)
    assert not moving.still and moving.speed_m_s > 0.5
    with pytest.raises(sanity.SanityError, match="--allow-moving-base-pose"):
        sanity.check_base_pose_still(pos[-80:], labels, 100.0)
    warned = sanity.check_base_pose_still(pos[-80:], labels, 100.0, allow_moving=True)
    assert len(warned) == 1 and moving.marker in warned[0]
    # Too few frames to tell: no verdict, no error.
    assert np.isnan(sanity.base_pose_motion(pos[:5], labels, 100.0).speed_m_s)


def test_units_from_the_marker_extent(synth: SynthTake) -> None:
    pos = synth.markers_world[:50]
    assert sanity.check_units(pos, units="m", units_source="file") == []
    # A marker never seen (an all-NaN column) is left out, without a warning.
    hole = pos.copy()
    hole[:, 3] = np.nan
    assert sanity.check_units(hole, units="m", units_source="file") == []
    assert sanity.base_pose_motion(hole, synth.labels, 100.0).still
    with pytest.raises(sanity.SanityError, match=r"--take-units m$"):
        sanity.check_units(pos * 1e-3, units="mm", units_source="file")
    with pytest.raises(sanity.SanityError, match=r"--take-units mm$"):
        sanity.check_units(pos * 1e3, units="m", units_source="file")
    with pytest.raises(sanity.SanityError, match=r"--take-units cm$"):
        sanity.check_units(pos * 1e-1, units="mm", units_source="file")


def test_stature_and_bilateral_from_the_calibration(synth: SynthTake) -> None:
    rig = load_rig("menache")
    cal = calibrate(rig, synth.markers_world[:50], synth.labels)
    h = sanity.estimated_stature_m(rig, cal)
    assert sanity.STATURE_RANGE_M[0] < h < sanity.STATURE_RANGE_M[1]
    assert sanity.check_calibration(rig, cal, units="m") == []
    tall = dataclasses.replace(cal, bone_lengths=cal.bone_lengths * 1.4)
    (warning,) = sanity.check_stature(rig, tall, units="m")
    assert "tall" in warning
    with pytest.raises(sanity.SanityError, match="--take-units"):
        huge = dataclasses.replace(cal, bone_lengths=cal.bone_lengths * 10)
        sanity.check_stature(rig, huge, units="cm")
    # One upper arm 20 % longer: a warning naming both bones; a 5 % one is anatomy.
    i = cal.bone_names.index("rupperarm")
    for factor, n_warnings in ((1.2, 1), (1.05, 0)):
        lengths = cal.bone_lengths.copy()
        lengths[i] *= factor
        got = sanity.check_bilateral(
            rig, dataclasses.replace(cal, bone_lengths=lengths)
        )
        assert len(got) == n_warnings
        if got:
            assert "lupperarm" in got[0] and "rupperarm" in got[0]


def test_up_axis_from_the_base_pose(synth: SynthTake) -> None:
    """The synthetic pose read with every wrong axis: the error names the axis the
    file's capture frame really has up."""
    from retargetd.protocols.conventions import world_from_capture_mat

    rig = load_rig("menache")
    pos, labels = synth.markers_world[:50], synth.labels
    ok = sanity.check_up_axis(
        rig, pos, labels, up_axis="+Z", up_source="file",
        world_from_capture=world_from_capture_mat("+Z"),
    )  # fmt: skip
    assert ok == []
    for wrong in ("+Y", "-Y", "+X", "-Z"):
        m = world_from_capture_mat(wrong)
        # A +Z-up capture read as `wrong`: world = m @ capture.
        read = pos @ m.T
        with pytest.raises(sanity.SanityError, match=r"--take-up \+Z$"):
            sanity.check_up_axis(
                rig, read, labels, up_axis=wrong, up_source="file",
                world_from_capture=m,
            )  # fmt: skip
