"""Functional joints from a range of motion (issue 29 item 1): the estimators
(``body.functional``) recover a known centre and axis; ``calibrate --rom`` on the
synthetic performer's range of motion (``synth --motions rom``) places Plug-in Gait's
hip and knee centres and knee axes near the truth where the base pose's regression
does not; a motion that does not determine a joint leaves it as the base pose had it
and says so; the fit turns the knee about the functional axis.
"""

from __future__ import annotations

import functools
import json
import math
from pathlib import Path

import numpy as np
import pytest
from paths import DATASETS, require
from scipy.spatial.transform import Rotation

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.calibration import (
    Calibration,
    calibrate,
    compute_points,
    load_calibration,
    match_markers,
)
from retargetd.daemon.body.fit_model import build_fit_model
from retargetd.daemon.body.functional import hinge_axis, sphere_centre
from retargetd.daemon.body.rig import RigError, load_rig, parse_rig
from retargetd.daemon.cli.main import main
from retargetd.daemon.synth import performer as pf

RATE_HZ = 120.0
#: What issue 29 asks: centres within 10 mm (median), knee axes within 3 deg.
CENTRE_TOL_M = 0.010
AXIS_TOL_DEG = 3.0
#: Truth segment whose origin is each Plug-in Gait joint centre.
JOINTS = {"LHJC": "l_thigh", "RHJC": "r_thigh", "LKJC": "l_shank", "RKJC": "r_shank"}


@functools.cache
def _rom_take(noise_mm: float = 1.0) -> pf.SynthTake:
    """25 s of the range of motion (two turns of each leg) after the T-pose hold."""
    return pf.synthesize(
        seconds=25.0, rate_hz=RATE_HZ, markerset="plug-in-gait", motions=("rom",),
        noise_mm=noise_mm, seed=3,
    )  # fmt: skip


def _calibrations() -> tuple[pf.SynthTake, Calibration, Calibration]:
    take = _rom_take()
    rig = load_rig("plug-in-gait")
    base = take.markers_world[take.base_pose_frames]
    rom = (take.markers_world[take.base_pose_frames.stop :], take.labels, {})
    return (
        take,
        calibrate(rig, base, take.labels),
        calibrate(rig, base, take.labels, rom=rom),
    )


def _centre_errors(take: pf.SynthTake, cal: Calibration) -> dict[str, float]:
    """Median over the take of each joint centre's distance from the truth, metres."""
    rig = load_rig("plug-in-gait")
    cols = np.asarray(match_markers(rig, take.labels))
    pos = np.full((take.markers_world.shape[0], len(cols), 3), np.nan)
    pos[:, cols >= 0] = take.markers_world[:, cols[cols >= 0]]
    pts = compute_points(rig, pos, cal.point_offsets)
    names = list(take.segment_names)
    return {
        j: float(
            np.nanmedian(
                np.linalg.norm(pts[j] - take.joint_pos_world[:, names.index(s)], axis=1)
            )
        )
        for j, s in JOINTS.items()
    }


def _knee_axis_error_deg(cal: Calibration, axis_bone: np.ndarray, bone: str) -> float:
    """Angle between an axis in ``bone``'s rest axes and the truth's knee axis: the
    shank turns about its segment's y, which is the world's y in the T-pose."""
    b = cal.bone_names.index(bone)
    world = rot.quat_rotate(cal.rest_world_from_bone_quat[b], axis_bone)
    return math.degrees(math.acos(min(1.0, abs(world[1]) / np.linalg.norm(world))))


def test_estimators_recover_a_known_centre_and_axis() -> None:
    rng = np.random.default_rng(0)
    t = np.linspace(0.0, 4.0 * np.pi, 800)
    centre = np.array([0.05, -0.08, -0.07])
    offsets = np.array([[0.1, 0.02, -0.25], [0.03, -0.01, -0.42]])
    turn = Rotation.from_euler(
        "yx", np.stack([np.radians(20 - 30 * np.cos(t)), np.radians(15 * np.sin(t))], 1)
    )
    pts = np.stack([centre + turn.apply(o) for o in offsets], axis=1)
    exact = sphere_centre(pts)
    assert np.linalg.norm(exact.value - centre) < 1e-9 and exact.determined
    noisy = sphere_centre(pts + rng.normal(0.0, 0.001, pts.shape))
    assert np.linalg.norm(noisy.value - centre) < 3.0 * noisy.se  # its own error bar
    still = sphere_centre(np.repeat(pts[:1], 50, axis=0))
    assert not still.determined

    axis = np.array([0.1, 1.0, 0.05]) / np.linalg.norm([0.1, 1.0, 0.05])
    hinge = Rotation.from_rotvec(np.outer(np.radians(45 - 45 * np.cos(t)), axis))
    knee = np.array([0.0, 0.0, -0.45])
    shank = np.stack(
        [knee + hinge.apply(o) for o in ([0.04, 0.02, -0.1], [0.03, -0.03, -0.38])], 1
    )
    est = hinge_axis(shank)
    assert abs(abs(est.value @ axis) - 1.0) < 1e-12 and est.determined
    assert np.linalg.norm(np.cross(est.point - knee, axis)) < 1e-9  # on the axis
    small = Rotation.from_rotvec(np.outer(np.radians(5 * np.sin(t)), axis))
    assert not hinge_axis(
        np.stack([knee + small.apply(o) for o in ([0.04, 0.02, -0.1],)], 1)
    ).determined  # 10 deg of arc is not enough


def test_rom_places_hip_and_knee_centres_and_knee_axes_near_the_truth() -> None:
    """The base pose's regression (Plug-in Gait's Davis hip) leaves the hips 15 mm off
    (the synthetic pelvis markers sit where Harrington et al. 2007 put the hip centres;
    22 mm, and the knees 9 mm, before they did); the range of motion brings each centre
    within 10 mm and the hips closer than the base pose, the knee axes within 3 deg
    (the rig's epicondyle axis: 4 deg, 9 before). The knees' base-pose centres (4 mm)
    are already within the tolerance, as close as the range of motion's at 1 mm
    noise."""
    take, base, rom = _calibrations()
    before, after = _centre_errors(take, base), _centre_errors(take, rom)
    moved = {j: f"{1e3 * before[j]:.1f} -> {1e3 * after[j]:.1f}" for j in JOINTS}
    print("median centre error (mm), base pose -> rom:", moved)
    for j in JOINTS:
        assert after[j] <= CENTRE_TOL_M, (j, after[j])
    for j in ("LHJC", "RHJC"):
        assert after[j] < before[j], (j, before[j], after[j])
    # the regression's error shows: past the tolerance the range of motion meets
    assert min(before["LHJC"], before["RHJC"]) > CENTRE_TOL_M
    joints = rom.functional["joints"]
    rig = load_rig("plug-in-gait")
    for bone in ("llowerleg", "rlowerleg"):
        assert joints[bone]["used"]
        functional = _knee_axis_error_deg(rom, rom.functional_axes[bone], bone)
        b = rig.bone_names.index(bone)
        wand = rot.quat_rotate(
            rot.quat_conj(base.rest_parent_from_bone_quat[b]), np.array([1.0, 0, 0])
        )
        rig_axis = _knee_axis_error_deg(base, wand, bone)
        print(f"{bone} axis: rig {rig_axis:.2f} deg, functional {functional:.2f} deg")
        assert functional <= AXIS_TOL_DEG
        assert rig_axis > functional
    for j in ("LHJC", "RHJC"):
        assert joints[j]["used"] and joints[j]["se_mm"] < 5.0


def test_the_fit_turns_the_knee_about_the_functional_axis() -> None:
    _, base, rom = _calibrations()
    rig = load_rig("plug-in-gait")
    for cal, expect in ((base, None), (rom, rom.functional_axes)):
        assert cal.base_marker_pos is not None
        model = build_fit_model(rig, cal, cal.base_marker_pos[None], None, rig.fit)
        for bone in ("llowerleg", "rlowerleg"):
            b = rig.bone_names.index(bone)
            if expect is None:
                assert bone not in cal.functional_axes
            else:
                np.testing.assert_allclose(model.hinge_axis[b], expect[bone])


def test_a_motion_that_does_not_move_a_joint_keeps_the_base_pose_and_says_so() -> None:
    take = _rom_take()
    rig = load_rig("plug-in-gait")
    base = take.markers_world[take.base_pose_frames]
    still = calibrate(rig, base, take.labels, rom=(base, take.labels, {}))
    plain = calibrate(rig, base, take.labels)
    np.testing.assert_array_equal(still.point_offsets, plain.point_offsets)
    assert still.functional_axes == {}
    notes = still.functional["notes"]
    for name in ("LHJC", "RHJC", "llowerleg", "rlowerleg"):
        assert any(
            n.startswith(f"range of motion does not determine {name}'s") for n in notes
        ), notes


def test_calibrate_rom_cli_writes_and_reads_the_functional_joints(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    take_path = tmp_path / "rom.c3d"
    assert main(["synth", "--seconds", "25", "--rate", "120", "--markers",
                 "plug-in-gait", "--motions", "rom", "--noise-mm", "1",
                 "--out", str(take_path)]) == 0  # fmt: skip
    out = tmp_path / "performer.json"
    capsys.readouterr()
    assert main(["calibrate", str(take_path), "--rig", "plug-in-gait", "--frames",
                 "0:120", "--rom", str(take_path), "--rom-frames", "120:3000",
                 "--out", str(out), "--json"]) == 0  # fmt: skip
    summary = json.loads(capsys.readouterr().out)
    assert set(summary["functional"]) == {"LHJC", "RHJC", "llowerleg", "rlowerleg"}
    assert all(j["used"] for j in summary["functional"].values())
    doc = json.loads(out.read_text())
    assert doc["functional"]["source"]["frames"] == "120:3000"
    cal = load_calibration(out)
    assert set(cal.functional_axes) == {"llowerleg", "rlowerleg"}
    # Usage: a rig without functional joints, --rom-frames alone: exit 2, one line.
    for args in (["--rig", "menache", "--rom", str(take_path)],
                 ["--rig", "plug-in-gait", "--rom-frames", "0:10"]):  # fmt: skip
        assert main(["calibrate", str(take_path), "--out",
                     str(tmp_path / "x.json"), *args]) == 2  # fmt: skip
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "rom" in err[0], err


def test_a_bad_functional_table_is_named_in_one_line() -> None:
    from importlib import resources

    base = (
        resources.files("retargetd.daemon.body.rigs")
        .joinpath("plug-in-gait.toml")
        .read_text()
    )
    for bad, key in (
        ('[functional.points.NOPE]\nmarkers = ["LTHI"]\n', "functional.points.NOPE"),
        ('[functional.points.LKJC]\nmarkerz = ["LTHI"]\n', "functional.points.LKJC"),
        ('[functional.axes.lfoot]\nframe = ["LKNE"]\nmarkers = ["LANK"]\n',
         "functional.axes.lfoot.frame"),
    ):  # fmt: skip
        with pytest.raises(RigError) as exc:
            parse_rig(base + "\n" + bad, source="test")
        assert key in str(exc.value) and "\n" not in str(exc.value)


def test_the_real_walk_as_its_own_range_of_motion() -> None:
    """The btkdata Plug-in Gait walk: a walk barely abducts the hip, so its hips are
    named as not determined and keep the regression; a knee axis it determines is
    used, and the take still validates (``validate`` passes with either file)."""
    static = require(
        DATASETS / "btkdata" / "PiG_Calibration-FlatFoot-Full.c3d", "btkdata static"
    )
    walk = require(
        DATASETS / "btkdata" / "PiG_Motion-FlatFoot-Full.c3d", "btkdata walk"
    )
    from retargetd.replay.takes import load_take

    s, w = load_take(static), load_take(walk)
    rig = load_rig("plug-in-gait")
    cal = calibrate(rig, s.positions, s.labels, rom=(w.positions, w.labels, {}))
    joints, notes = cal.functional["joints"], cal.functional["notes"]
    assert not joints["LHJC"]["used"] and not joints["RHJC"]["used"]
    assert any("LHJC's centre" in n for n in notes)
    plain = calibrate(rig, s.positions, s.labels)
    k = rig.point_names.index("LHJC")
    np.testing.assert_array_equal(cal.point_offsets[k], plain.point_offsets[k])


@pytest.mark.xfail(
    strict=True,
    reason="measured 2.79 (left) and 3.74 (right) deg, 2.71 and 2.87 before the "
    "performer pronated about the ISB's forearm axis (elbow centre to ulnar styloid, "
    "7.4 deg off the forearm's centre line): SARA fits one hinge to the forearm's "
    "markers, and the range of motion pronates +-40 deg while it flexes, about an "
    "axis the wrist bar no longer straddles (hinge residual 18.7 mm, was 16.1)",
)
def test_rom_places_elbow_axes_on_a_rig_with_humerus_markers() -> None:
    """Elbows by SARA where a rig has three points on the humerus (the test rig of the
    exact marker set: LUPA and both epicondyles; Plug-in Gait has none, its LSHO rides
    the shoulder girdle): the rig's elbow axis tilted 20 deg as a wand's would be,
    the range of motion's elbow flexion (10-110 deg, the forearm turned +-40 deg at
    the same time) brings it within the 3 deg the issue asks of a knee axis."""
    from live_harness import EXACT_MARKERS, EXACT_RIG

    tilt = math.radians(20.0)
    axis = f"[0.0, {math.sin(tilt):.6f}, {math.cos(tilt):.6f}]"
    text = Path(EXACT_RIG).read_text() + "".join(
        f"""
[fit.bones.{s}_forearm]
dof = "hinge_twist"
axis = {axis}

[functional.axes.{s}_forearm]
frame = ["{s.upper()}UPA", "{s.upper()}ELL", "{s.upper()}ELM"]
markers = ["{s.upper()}WRA", "{s.upper()}WRB", "{s.upper()}FRM"]
"""
        for s in ("l", "r")
    )
    rig = parse_rig(text, source="exact rig with functional elbows")
    take = pf.synthesize(
        seconds=25.0, rate_hz=RATE_HZ, markerset=EXACT_MARKERS, motions=("rom",),
        noise_mm=1.0, seed=3,
    )  # fmt: skip
    base = take.markers_world[take.base_pose_frames]
    rom = (take.markers_world[take.base_pose_frames.stop :], take.labels, {})
    cal = calibrate(rig, base, take.labels, rom=rom)
    for bone in ("l_forearm", "r_forearm"):
        joint = cal.functional["joints"][bone]
        assert joint["used"], joint
        b = cal.bone_names.index(bone)
        world = rot.quat_rotate(
            cal.rest_world_from_bone_quat[b], cal.functional_axes[bone]
        )
        # the performer's forearm flexes about its segment's z: the world's z in the
        # T-pose hold
        off = math.degrees(math.acos(min(1.0, abs(world[2]) / np.linalg.norm(world))))
        print(
            f"{bone}: functional axis {off:.2f} deg from the truth (the rig's: "
            f"{joint['angle_from_rig_deg']:.1f} deg from it), residual "
            f"{joint['rms_mm']:.1f} mm, predicted error {joint['se_deg']:.2f} deg"
        )
        assert off <= AXIS_TOL_DEG
        assert joint["angle_from_rig_deg"] > 15.0
