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
from retargetd.replay.c3d import write_c3d
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


#: The up-lever warnings the real base poses do give the construction
#: (``check_up_levers``; the fit takes no bone's roll from its up reference, so its
#: calibrations give none): the feet of Plug-in Gait and cmu41 take their roll from
#: the heel, 13-26 mm off the ankle->toe line (RIGS.md "How much lever an up
#: reference needs").
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
    assert _warnings(capsys.readouterr().err) == ([], set())


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
    assert _warnings(capsys.readouterr().err) == ([], set())


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
    assert _warnings(capsys.readouterr().err) == ([], set())  # no warning at all
    # the construction takes each bone's roll from its up reference: the short
    # levers are named where it calibrates (and only those)
    solve = [
        "solve", str(datasets / path), "--rig", rig, "--method", "construction",
        "--calibrate-frames", frames or ":", "--out", str(tmp_path / "s.npz"),
    ]  # fmt: skip
    assert main(solve) == 0
    assert _warnings(capsys.readouterr().err)[1] == LEVER_WARNINGS[path]
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
    # Any window of 2 frames or more is judged (issue 29: 10 frames at 100 Hz were
    # shorter than the 0.1 s lag and passed unjudged), over the lag it has, the limit
    # raised to what marker noise can show over it; 1 frame cannot tell.
    for n in (2, 3, 5, 10):
        short_hold = sanity.base_pose_motion(pos[:n], labels, 100.0)
        assert short_hold.lag_frames == n - 1 and short_hold.still, short_hold
        walk = sanity.base_pose_motion(pos[-n:], labels, 100.0)
        assert not walk.still, walk
        with pytest.raises(sanity.SanityError, match="not still"):
            sanity.check_base_pose_still(pos[-n:], labels, 100.0)
    assert sanity.base_pose_motion(pos[:2], labels, 100.0).limit_m_s == pytest.approx(
        sanity.STILL_NOISE_M * 100.0
    )
    assert np.isnan(sanity.base_pose_motion(pos[:1], labels, 100.0).speed_m_s)


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


def test_a_straight_elbow_warns_for_plug_in_gait() -> None:
    """Plug-in Gait's elbow centre needs a bent elbow (rig: ``bend_min_deg``): its
    own static, elbows at a right angle, passes; the straight-armed T-pose warns once
    per elbow, naming the point and the bend."""
    from retargetd.daemon.synth.markerset import load_markerset

    rig = load_rig("plug-in-gait")
    bent = load_markerset("plug-in-gait")
    for markerset, n_warnings in (
        (bent, 0),
        (dataclasses.replace(bent, elbow_flexion_deg=0.0), 2),
    ):
        take = synthesize(seconds=0.5, rate_hz=60.0, markerset=markerset, motions=())
        cal = calibrate(rig, take.markers_world, take.labels)
        bends = sanity.base_pose_bends_deg(rig, cal, take.markers_world, take.labels)
        assert set(bends) == {"LEJC", "REJC"}
        got = sanity.check_bends(rig, cal, take.markers_world, take.labels)
        assert len(got) == n_warnings, got
        for side in "LR":
            if n_warnings:
                assert bends[f"{side}EJC"] < 24.0
                assert any(
                    w.startswith(
                        f"point {side}EJC: {side}ELB {side}SJC {side}WRI is bent"
                    )
                    for w in got
                )
            else:
                # the elbow's bend and the tilt ELB's own offset gives the frame
                b = bent.elbow_flexion_deg
                assert b < bends[f"{side}EJC"] < b + 15.0, bends


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


# --- issue 29: mirrored labels and short windows -------------------------------------

#: Every shipped rig on its own base pose (README's rig table; the synthetic performer
#: wearing the rig's marker set holds a T-pose for its first second): take, rig, rows.
GENUINE_BASE_POSES = [
    (PIG_STATIC, "plug-in-gait", None),
    ("opensim-core/subject01_static.trc", "opensim-gait2354", None),
    ("btkdata/MOTEK_T.trc", "cmu41", None),
    ("synth:menache", "menache", "0:100"),
    ("synth:plug-in-gait", "plug-in-gait", "0:100"),
]


def _swap_left_right(labels: tuple[str, ...]) -> list[str]:
    """Every ``L...`` label named ``R...`` and back, where both exist (``LASI``,
    ``L.ASIS``, ``L_fem_up``): the performer mirrored by its labels."""
    have = set(labels)
    out = []
    for label in labels:
        other = {"L": "R", "R": "L"}.get(label[:1], "") + label[1:]
        out.append(other if label[:1] in "LR" and other in have else label)
    return out


def _base_pose_file(datasets: Path, tmp_path: Path, name: str) -> Path:
    if not name.startswith("synth:"):
        return datasets / name
    markerset = name.removeprefix("synth:")
    path = tmp_path / f"synth-{markerset}.c3d"
    assert main(["synth", "--seconds", "2", "--rate", "100", "--out", str(path),
                 "--markers", markerset]) == 0  # fmt: skip
    return path


@pytest.mark.parametrize(("path", "rig", "frames"), GENUINE_BASE_POSES)
def test_genuine_base_poses_pass_and_their_mirror_is_refused(
    datasets: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    path: str,
    rig: str,
    frames: str | None,
) -> None:
    """Each shipped rig's own base pose calibrates (its left markers on the side the
    toes and the pelvis' front say is left, ~0 deg); the same pose with its left and
    right labels swapped is refused, exit 2, one line (~180 deg)."""
    src = _base_pose_file(datasets, tmp_path, path)
    extra = ["--frames", frames] if frames else []
    assert main(_calibrate([str(src), "--rig", rig, *extra], tmp_path)) == 0
    capsys.readouterr()
    take = load_take(src)
    rows = slice(0, 100) if frames else slice(None)
    angles = sanity.mirror_angles_deg(load_rig(rig), take.positions[rows], take.labels)
    assert set(angles) == {"feet", "pelvis"}
    assert max(angles.values()) < sanity.MIRROR_UNSURE_DEG, angles
    mirrored = tmp_path / "mirrored.c3d"
    write_c3d(mirrored, _swap_left_right(take.labels), take.positions, take.rate_hz)
    swapped = sanity.mirror_angles_deg(
        load_rig(rig), take.positions[rows], _swap_left_right(take.labels)
    )
    assert min(swapped.values()) > sanity.MIRROR_ANGLE_LIMIT_DEG, swapped
    assert main(_calibrate([str(mirrored), "--rig", rig, *extra], tmp_path)) == 2
    line = _one_error(capsys)
    assert "mirrored" in line and "swapped" in line, line


def test_mirror_check_skips_a_rig_without_its_cues() -> None:
    """No feet and no pelvis pair: nothing to tell forward by, no refusal."""
    rig = load_rig("menache")
    take = synthesize(seconds=1.0, rate_hz=50.0, markerset="menache")
    keep = [i for i, m in enumerate(take.labels) if "TOE" not in m and "HIP" not in m]
    labels = [take.labels[i] for i in keep]
    pos = take.markers_world[:10, keep]
    assert sanity.mirror_angles_deg(rig, pos, labels) == {}
    assert sanity.check_mirrored(rig, pos, _swap_left_right(tuple(labels))) == []


def test_ten_walking_frames_are_refused_like_eleven(
    datasets: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue 29: the walk's frames 430-439 (10 frames, 0.1 s at 100 Hz: no longer
    than the stillness lag) were accepted unjudged, 430-440 refused."""
    take = load_take(datasets / PIG_WALK)
    for last in (440, 441, 432):
        rows = f"{430 - take.first_frame}:{last - take.first_frame}"
        argv = [str(datasets / PIG_WALK), "--rig", "plug-in-gait", "--frames", rows]
        assert main(_calibrate(argv, tmp_path)) == 2, rows
        line = _one_error(capsys)
        assert "not still" in line and "m/s" in line, line
    assert not (tmp_path / "cal.json").exists()


#: Bones of each shipped rig whose up reference sits under ``UP_LEVER_MIN_M`` from
#: the bone's axis on the synthetic performer: menache's scapulae take their roll from
#: the acromion, 26 mm off the clavicle->scapula line (the chapter's choice). (Its neck
#: took its roll from T1 17 mm behind the LONECK->UPNECK line while LONECK and UPNECK
#: sat at d = 0, behind the cervical spine; 57 mm with the depth shift, menache.toml.)
SYNTH_LEVER_WARNINGS = {
    "menache": {"lscapula", "rscapula"},
    "plug-in-gait": set(),
}


@pytest.mark.parametrize("markerset", sorted(SYNTH_LEVER_WARNINGS))
def test_shipped_rigs_calibrate_and_solve_their_performer_without_a_warning(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], markerset: str
) -> None:
    """Issue 31 item 7: each shipped rig, on the synthetic performer wearing its
    marker set, calibrates and solves with the default method without a warning a
    user could not act on; the construction, which takes each bone's roll from its
    up reference, still names the short levers."""
    from retargetd.daemon.synth.markerset import shipped_markersets

    assert set(SYNTH_LEVER_WARNINGS) == set(shipped_markersets())
    take = tmp_path / "take.c3d"
    assert main(["synth", "--seconds", "2", "--rate", "60", "--markers", markerset,
                 "--out", str(take)]) == 0  # fmt: skip
    capsys.readouterr()
    assert main(_calibrate([str(take), "--rig", markerset, "--frames", "0:60"],
                           tmp_path)) == 0  # fmt: skip
    assert "warning" not in capsys.readouterr().err
    solve = ["solve", str(take), "--rig", markerset, "--calibrate-frames", "0:60"]
    assert main([*solve, "--out", str(tmp_path / "fit.npz")]) == 0
    assert "warning" not in capsys.readouterr().err
    assert main([*solve, "--method", "construction", "--out",
                 str(tmp_path / "con.npz")]) == 0  # fmt: skip
    other, bones = _warnings(capsys.readouterr().err)
    assert (other, bones) == ([], SYNTH_LEVER_WARNINGS[markerset])
