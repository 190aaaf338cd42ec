"""The synthetic performer: marker sets, truth consistency, motions, noise, dropouts."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from retargetd.daemon import rotations as rot
from retargetd.daemon.synth import performer as pf

PLUG_IN_GAIT = [
    "LFHD",
    "RFHD",
    "LBHD",
    "RBHD",
    "C7",
    "T10",
    "CLAV",
    "STRN",
    "RBAK",
    "LSHO",
    "LELB",
    "LWRA",
    "LWRB",
    "LFIN",
    "RSHO",
    "RELB",
    "RWRA",
    "RWRB",
    "RFIN",
    "LASI",
    "RASI",
    "LPSI",
    "RPSI",
    "LTHI",
    "LKNE",
    "LTIB",
    "LANK",
    "LHEE",
    "LTOE",
    "RTHI",
    "RKNE",
    "RTIB",
    "RANK",
    "RHEE",
    "RTOE",
]
MENACHE_MIDLINE = ["SACRUM", "L1", "T7", "T1", "C1", "C7", "STERNUM"]
MENACHE_BILATERAL = [
    *("HIP", "HEAD", "SHOULDER", "SCAPULA", "IELBOW", "EELBOW", "IWRIST", "EWRIST"),
    *("HAND", "IKNEE", "EKNEE", "HEEL", "FOOT", "ANKLE", "TOE"),
]


@pytest.fixture(scope="module")
def take() -> pf.SynthTake:
    """All motions, noise-free: 12 s at 60 Hz."""
    return pf.synthesize(seconds=12.0, rate_hz=60.0)


def _only(motion: str, seconds: float = 12.0) -> pf.SynthTake:
    return pf.synthesize(seconds=seconds, rate_hz=60.0, motions=[motion])


def _m(take: pf.SynthTake, label: str) -> np.ndarray:
    return take.markers_world[:, take.labels.index(label)]


def _seg(take: pf.SynthTake, name: str) -> int:
    return take.segment_names.index(name)


# --- marker sets -----------------------------------------------------------------


def test_shipped_markersets_load_and_name_real_segments() -> None:
    assert set(pf.shipped_markersets()) >= {"menache", "plug-in-gait"}
    for name in pf.shipped_markersets():
        ms = pf.load_markerset(name)
        assert ms.name == name
        assert len(set(ms.labels)) == len(ms.labels)
        assert set(ms.segments) <= set(pf.SEGMENT_NAMES)
        assert ms.offsets_mm.shape == (len(ms.labels), 3)
        assert all(ms.descriptions)
        assert not ms.offsets_mm.flags.writeable


def test_menache_and_plug_in_gait_labels() -> None:
    menache = pf.load_markerset("menache")
    expected = MENACHE_MIDLINE + [s + b for s in "LR" for b in MENACHE_BILATERAL]
    assert sorted(menache.labels) == sorted(expected)
    assert sorted(pf.load_markerset("plug-in-gait").labels) == sorted(PLUG_IN_GAIT)
    # Anatomy: the markers ride on the segment whose motion they follow.
    seg = dict(zip(menache.labels, menache.segments, strict=True))
    assert seg["LIWRIST"] == seg["LEWRIST"] == "l_forearm"
    assert seg["RIELBOW"] == seg["REELBOW"] == "r_upper_arm"
    assert seg["LIKNEE"] == seg["LEKNEE"] == "l_thigh"
    assert seg["LANKLE"] == "l_shank" and seg["LHEEL"] == seg["LFOOT"] == "l_foot"
    # TOE over the 2nd metatarsal head: the foot segment (the rig has no toes bone).
    assert seg["LTOE"] == "l_foot" and seg["LHIP"] == seg["SACRUM"] == "pelvis"


def test_load_markerset_by_path_and_errors(tmp_path: Path) -> None:
    good = tmp_path / "mine.toml"
    good.write_text('[markers.A]\nsegment = "head"\noffset_mm = [1, 2, 3]\n')
    ms = pf.load_markerset(good)
    assert ms.labels == ("A",) and ms.name == "mine"
    np.testing.assert_array_equal(ms.offsets_mm, [[1.0, 2.0, 3.0]])
    assert pf.load_markerset(str(good)).labels == ("A",)

    bad_seg = tmp_path / "bad_seg.toml"
    bad_seg.write_text('[markers.A]\nsegment = "tail"\noffset_mm = [1, 2, 3]\n')
    with pytest.raises(
        ValueError, match=r"bad_seg\.toml: markers\.A\.segment: .*'tail'"
    ):
        pf.load_markerset(bad_seg)
    bad_len = tmp_path / "bad_len.toml"
    bad_len.write_text('[markers.B]\nsegment = "head"\noffset_mm = [1, 2]\n')
    with pytest.raises(
        ValueError, match=r"bad_len\.toml: markers\.B\.offset_mm: .*\[1, 2\]"
    ):
        pf.load_markerset(bad_len)
    with pytest.raises(ValueError, match=r"unknown marker set 'nope'.*menache"):
        pf.load_markerset("nope")
    with pytest.raises(ValueError, match=r"missing\.toml: cannot read"):
        pf.load_markerset(tmp_path / "missing.toml")
    for base, why in (
        (
            "[base_pose]\nelbow_flexion_deg = 200\n",
            r"base_pose\.elbow_flexion_deg: expected 0-150",
        ),
        ("[base_pose]\nknee = 3\n", r"base_pose: expected a table"),
        ("pose = 1\n", r"unknown keys \['pose'\]"),
    ):
        bad = tmp_path / "bad_base.toml"
        bad.write_text(base + '[markers.A]\nsegment = "head"\noffset_mm = [1, 2, 3]\n')
        with pytest.raises(ValueError, match=r"bad_base\.toml: " + why):
            pf.load_markerset(bad)


def test_plug_in_gait_holds_its_static_with_the_elbows_bent() -> None:
    """Plug-in Gait's static bends the elbows (its marker set's ``[base_pose]``): a
    right angle in the hold, none once the motion has ramped out of it; menache's
    T-pose stays straight."""
    ms = pf.load_markerset("plug-in-gait")
    assert ms.elbow_flexion_deg == 90.0
    assert pf.load_markerset("menache").elbow_flexion_deg == 0.0
    take = pf.synthesize(seconds=2.0, rate_hz=60.0, markerset=ms, motions=())
    for side in ("l", "r"):
        q = take.parent_from_segment_quat[:, _seg(take, f"{side}_forearm")]
        bend = np.rad2deg(rot.quat_angle(q))
        np.testing.assert_allclose(bend[: take.base_pose_frames.stop], 90.0)
        np.testing.assert_allclose(bend[-10:], 0.0, atol=1e-9)
        # about the upper arm's z (the flexion axis in the T-pose)
        axis = q[0, 1:] / np.linalg.norm(q[0, 1:])
        assert abs(axis[2]) > 0.999
    assert np.all(take.markers_world[take.base_pose_frames] == take.markers_world[0])


# --- skeleton --------------------------------------------------------------------


def test_skeleton_is_immutable_and_ordered() -> None:
    sk = pf.make_skeleton(1.75)
    assert len(sk.names) == 21 and sk.names[0] == "pelvis" and sk.parents[0] == -1
    assert all(sk.parents[s] < s for s in range(1, len(sk.names)))
    with pytest.raises(dataclasses.FrozenInstanceError):
        sk.height_m = 2.0  # type: ignore[misc]
    with pytest.raises(ValueError, match="read-only"):
        sk.rest_offsets[0, 0] = 1.0
    # Pelvis at hip height, soles on the floor, left = +Y.
    np.testing.assert_allclose(sk.rest_pos[0], [0.0, 0.0, 0.530 * 1.75])
    assert sk.rest_pos[sk.index("l_hand"), 1] > 0.5
    assert sk.rest_pos[sk.index("r_hand"), 1] < -0.5
    np.testing.assert_allclose(
        sk.rest_pos[sk.index("l_foot")] + sk.sole_points[0],
        [-0.035 * 1.75, 0.05 * 1.75, 0.0],
        atol=1e-12,
    )
    with pytest.raises(ValueError, match="height_m"):
        pf.make_skeleton(-1.0)


# --- truth -----------------------------------------------------------------------


def test_truth_is_self_consistent(take: pf.SynthTake) -> None:
    # Copies: scipy's Cython code refuses read-only buffers.
    q_par = take.parent_from_segment_quat.copy()
    q_world = take.world_from_segment_quat.copy()
    pos = take.joint_pos_world
    n_frames, n_seg = q_par.shape[:2]
    assert q_world.shape == (n_frames, n_seg, 4) and pos.shape == (n_frames, n_seg, 3)
    np.testing.assert_allclose(np.linalg.norm(q_par, axis=-1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(q_world, axis=-1), 1.0, atol=1e-12)
    np.testing.assert_array_equal(q_world[:, 0], q_par[:, 0])
    for s in range(1, n_seg):
        p = take.segment_parents[s]
        # world_from_segment is the product down the chain (scipy as the oracle).
        chain = Rotation.from_quat(
            q_world[:, p], scalar_first=True
        ) * Rotation.from_quat(q_par[:, s], scalar_first=True)
        got = Rotation.from_quat(q_world[:, s], scalar_first=True)
        assert np.max((chain.inv() * got).magnitude()) < 1e-9
        expected = pos[:, p] + Rotation.from_quat(
            q_world[:, p], scalar_first=True
        ).apply(take.rest_offsets[s].copy())
        np.testing.assert_allclose(pos[:, s], expected, atol=1e-12)


def test_markers_ride_on_their_segments(take: pf.SynthTake) -> None:
    seg = take.marker_segments
    expected = take.joint_pos_world[:, seg] + rot.quat_rotate(
        take.world_from_segment_quat[:, seg], take.marker_offsets
    )
    np.testing.assert_allclose(take.markers_world, expected, atol=1e-12)
    assert take.valid.all()


def test_base_pose_is_the_exact_static_t_pose(take: pf.SynthTake) -> None:
    hold = take.base_pose_frames
    assert hold == slice(0, 60)
    identity = np.broadcast_to([1.0, 0.0, 0.0, 0.0], (60, 21, 4))
    np.testing.assert_array_equal(take.parent_from_segment_quat[hold], identity)
    np.testing.assert_array_equal(take.world_from_segment_quat[hold], identity)
    rest = pf.make_skeleton(1.75).rest_pos + take.origin_world
    np.testing.assert_allclose(
        take.joint_pos_world[hold], np.broadcast_to(rest, (60, 21, 3)), atol=1e-15
    )
    assert np.all(take.markers_world[hold] == take.markers_world[0])
    # The motion then starts smoothly: small first steps, then real movement.
    after = take.parent_from_segment_quat[60:63]
    assert np.all(rot.quat_angle(after) < np.deg2rad(0.5))


def test_menache_constructions_land_on_joint_centres(take: pf.SynthTake) -> None:
    b = take.base_pose_frames.stop - 1
    jp = take.joint_pos_world
    hip_mid = 0.5 * (_m(take, "LHIP") + _m(take, "RHIP"))
    pelvis = np.array([hip_mid[b, 0], hip_mid[b, 1], _m(take, "SACRUM")[b, 2]])
    np.testing.assert_allclose(pelvis, jp[b, _seg(take, "pelvis")], atol=1e-12)
    l1 = _m(take, "L1")[b]
    lumbar = np.array([0.5 * (l1[0] + pelvis[0]), pelvis[1], l1[2]])
    np.testing.assert_allclose(lumbar, jp[b, _seg(take, "abdomen")], atol=1e-12)
    t7 = _m(take, "T7")[b]
    thorax = np.array([0.5 * (t7[0] + lumbar[0]), lumbar[1], t7[2]])
    np.testing.assert_allclose(thorax, jp[b, _seg(take, "thorax")], atol=1e-12)
    # Midpoints of marker pairs on one rigid segment are joint centres in every frame.
    for a, c, joint in (
        ("LIELBOW", "LEELBOW", "l_forearm"),
        ("RIWRIST", "REWRIST", "r_hand"),
        ("LIKNEE", "LEKNEE", "l_shank"),
        ("RIKNEE", "REKNEE", "r_shank"),
    ):
        mid = 0.5 * (_m(take, a) + _m(take, c))
        np.testing.assert_allclose(mid, jp[:, _seg(take, joint)], atol=1e-12)


# --- motions ---------------------------------------------------------------------


def _p2p_deg(x: np.ndarray) -> float:
    return float(np.rad2deg(np.ptp(np.unwrap(x))))


def test_forearm_twist_twists_about_the_long_axis() -> None:
    tk = _only("forearm_twist")
    q = tk.parent_from_segment_quat[:, _seg(tk, "l_forearm")]
    twist = 2.0 * np.arctan2(q[:, 2], q[:, 0])  # swing-twist about the forearm's y
    assert _p2p_deg(twist) > 100.0
    # The long axis itself only moves by the elbow flexion (< 85 deg) ...
    axis = rot.quat_rotate(q, [0.0, 1.0, 0.0])
    assert np.rad2deg(np.arccos(np.clip(axis[:, 1], -1, 1))).max() < 85.0
    # ... and the upper arm (and everything proximal) does not move at all.
    for name in ("pelvis", "thorax", "l_clavicle", "l_upper_arm", "r_upper_arm"):
        assert np.all(
            rot.quat_angle(tk.parent_from_segment_quat[:, _seg(tk, name)]) == 0
        )
    right = tk.parent_from_segment_quat[:, _seg(tk, "r_forearm")]
    assert _p2p_deg(2.0 * np.arctan2(right[:, 2], right[:, 0])) > 100.0


def test_head_turn_yaws_the_head() -> None:
    tk = _only("head_turn")
    forward = rot.quat_rotate(
        tk.world_from_segment_quat[:, _seg(tk, "head")], [1, 0, 0]
    )
    assert _p2p_deg(np.arctan2(forward[:, 1], forward[:, 0])) > 100.0
    assert np.all(
        rot.quat_angle(tk.world_from_segment_quat[:, _seg(tk, "thorax")]) == 0
    )


def test_arm_raise_sweeps_both_arms() -> None:
    tk = _only("arm_raise")
    for name, along in (("l_upper_arm", [0, 1, 0]), ("r_upper_arm", [0, -1, 0])):
        axis = rot.quat_rotate(tk.world_from_segment_quat[:, _seg(tk, name)], along)
        elevation = np.rad2deg(np.arcsin(np.clip(axis[:, 2], -1, 1)))
        # 60 deg up and 55 deg down at most (motion._arm_raise: the amplitudes that
        # keep the performer's own segments apart), with the other components on top
        assert elevation.max() > 40.0 and elevation.min() < -40.0


def test_spine_bends_and_twists_the_trunk() -> None:
    tk = _only("spine")
    thorax = tk.world_from_segment_quat[:, _seg(tk, "thorax")]
    euler = np.rad2deg(rot.euler_from_quat(thorax, "ZXY"))  # yaw, lateral, flexion
    assert np.ptp(euler, axis=0).min() > 20.0
    assert np.all(tk.joint_pos_world[:, 0] == tk.joint_pos_world[0, 0])


def test_walk_travels_round_a_circle_with_feet_on_the_floor() -> None:
    tk = _only("walk", seconds=14.0)
    pelvis = tk.joint_pos_world[:, 0]
    step = np.linalg.norm(np.diff(pelvis[:, :2], axis=0), axis=1)
    assert step.sum() > 1.0
    assert np.abs(pelvis[:, :2]).max() < 1.8  # inside a ~4 m volume round the origin
    heading = rot.quat_rotate(tk.world_from_segment_quat[:, 0], [1.0, 0.0, 0.0])
    assert _p2p_deg(np.arctan2(heading[:, 1], heading[:, 0])) > 180.0
    assert np.ptp(pelvis[60:, 2]) > 0.01  # vertical bob
    for side in "lr":
        knee = tk.parent_from_segment_quat[:, _seg(tk, f"{side}_shank")]
        assert np.rad2deg(rot.quat_angle(knee)).max() > 50.0
    feet = [
        i
        for i, label in enumerate(tk.labels)
        if label[1:] in ("HEEL", "TOE", "FOOT", "ANKLE")
    ]
    assert tk.markers_world[:, feet, 2].min() > -0.02


def test_all_motions_keep_feet_above_the_floor(take: pf.SynthTake) -> None:
    feet = [
        i
        for i, label in enumerate(take.labels)
        if label[1:] in ("HEEL", "TOE", "FOOT", "ANKLE")
    ]
    assert take.markers_world[:, feet, 2].min() > -0.02


# --- noise, dropouts, determinism ------------------------------------------------


def test_noise_std_matches_request(take: pf.SynthTake) -> None:
    noisy = pf.synthesize(seconds=12.0, rate_hz=60.0, noise_mm=2.0, seed=3)
    residual_mm = (noisy.markers_world - take.markers_world) * 1e3
    assert abs(residual_mm.std() - 2.0) < 0.2
    assert abs(residual_mm.mean()) < 0.05
    np.testing.assert_array_equal(noisy.joint_pos_world, take.joint_pos_world)


def test_dropouts_come_in_runs_at_the_requested_fraction() -> None:
    tk = pf.synthesize(
        seconds=40.0, rate_hz=120.0, dropout=0.1, dropout_mean_frames=10, motions=[]
    )
    occluded = ~tk.valid
    assert abs(occluded.mean() - 0.1) < 0.02
    assert np.all(np.isnan(tk.markers_world[occluded]))
    assert np.all(np.isfinite(tk.markers_world[tk.valid]))
    starts = np.count_nonzero(occluded[1:] & ~occluded[:-1]) + np.count_nonzero(
        occluded[0]
    )
    mean_run = occluded.sum() / starts
    assert 7.0 < mean_run < 13.0


def test_deterministic_for_a_seed() -> None:
    kwargs = dict(seconds=3.0, rate_hz=100.0, noise_mm=1.0, dropout=0.05)
    a = pf.synthesize(seed=5, **kwargs)
    b = pf.synthesize(seed=5, **kwargs)
    c = pf.synthesize(seed=6, **kwargs)
    np.testing.assert_array_equal(a.markers_world, b.markers_world)
    np.testing.assert_array_equal(a.valid, b.valid)
    assert not np.array_equal(a.valid, c.valid)


def test_height_scales_the_performer() -> None:
    small = pf.synthesize(seconds=0.5, rate_hz=10.0, height_m=1.5, origin=(0, 0, 0))
    ref = pf.synthesize(seconds=0.5, rate_hz=10.0, origin=(0, 0, 0))
    np.testing.assert_allclose(
        small.markers_world, ref.markers_world * (1.5 / 1.75), atol=1e-12
    )


def test_truth_npz_round_trip(take: pf.SynthTake, tmp_path: Path) -> None:
    path = tmp_path / "truth.npz"
    take.save_truth(path)
    with np.load(path, allow_pickle=False) as npz:
        assert npz["labels"].dtype.kind == "U"
        assert (
            npz["world_from_segment_quat"].shape == take.world_from_segment_quat.shape
        )
    back = pf.load_truth(path)
    assert back.labels == take.labels and back.base_pose_frames == take.base_pose_frames
    assert back.motions == take.motions and back.markerset == "menache"
    np.testing.assert_array_equal(back.markers_world, take.markers_world)
    np.testing.assert_array_equal(
        back.parent_from_segment_quat, take.parent_from_segment_quat
    )


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"seconds": 0.0}, "seconds"),
        ({"rate_hz": -5.0}, "rate_hz"),
        ({"dropout": 1.0}, "dropout"),
        ({"noise_mm": -1.0}, "noise_mm"),
        ({"motions": ["dance"]}, "motions.*dance"),
        ({"origin": (0.0, 0.0)}, "origin"),
        ({"markerset": "nope"}, "nope"),
    ],
)
def test_bad_arguments_name_themselves(kwargs: dict, match: str) -> None:
    args = {"seconds": 1.0, "rate_hz": 60.0, **kwargs}
    with pytest.raises(ValueError, match=match):
        pf.synthesize(**args)
