"""A body solve against the synthetic performer's truth (``synth.truth``, issue 28
item 6), checked where the answer is known: the exact rig
(``tests/data/synth-exact-rig.toml``, every bone rigid on its segment) solves to ~0;
a rotation injected into a solve, or a twist into the truth, comes back as the
error and the excursion it is.
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path

import numpy as np
import pytest

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.calibration import calibrate
from retargetd.daemon.body.method import make_body_solver
from retargetd.daemon.body.rig import Rig, load_rig
from retargetd.daemon.body.solve import BodySolve
from retargetd.daemon.body.solve_fit import FitSolver
from retargetd.daemon.synth import performer as pf
from retargetd.daemon.synth.truth import compare_with_truth, truth_map
from retargetd.daemon.validate.limits import JOINT_LIMITS_DEG
from retargetd.daemon.validate.model import SEGMENT_KIND

DATA = Path(__file__).resolve().parent.parent / "data"
EXACT_RIG = DATA / "synth-exact-rig.toml"
EXACT_MARKERS = DATA / "synth-exact-markers.toml"
RATE_HZ = 120.0
Y = np.array([0.0, 1.0, 0.0])


@functools.cache
def _exact(motions: tuple[str, ...] = pf.DEFAULT_MOTIONS) -> tuple[Rig, pf.SynthTake]:
    take = pf.synthesize(
        seconds=3.0, rate_hz=RATE_HZ, markerset=EXACT_MARKERS, motions=motions, seed=3
    )
    return load_rig(EXACT_RIG), take


@functools.cache
def _solve(method: str, motions: tuple[str, ...] = pf.DEFAULT_MOTIONS) -> BodySolve:
    rig, take = _exact(motions)
    cal = calibrate(rig, take.markers_world[:120], take.labels)
    solver = make_body_solver(
        method, rig, cal, take.labels,
        joint_limits=JOINT_LIMITS_DEG, segment_kind=SEGMENT_KIND,
    )  # fmt: skip
    return solver.solve_take(take.markers_world)


def _about(axis: np.ndarray, deg: np.ndarray | float) -> np.ndarray:
    return rot.quat_from_axis_angle(axis, np.radians(deg))


# --- synth.truth ------------------------------------------------------------------


def test_map_follows_humanoid_names() -> None:
    rig, take = _exact()
    tmap = truth_map(rig, take.segment_names)
    # the exact rig names its bones and joints for the segments they stand for
    assert tmap.bone_names == take.segment_names
    assert [take.segment_names[s] for s in tmap.segments] == list(tmap.bone_names)
    assert tmap.joint_names == take.segment_names
    hand = tmap.bone_names.index("l_hand")
    assert take.segment_names[tmap.carriers[hand]] == "l_forearm"
    assert tmap.carriers[0] == -1  # the root's parent is the world
    chain = [rig.bones[i].name for i in tmap.ancestors[hand]]
    assert chain == ["l_hand", "l_forearm", "l_upper_arm", "l_clavicle", "thorax",
                     "abdomen", "pelvis"]  # fmt: skip
    # menache: bones without a humanoid name are skipped, shared origins too
    menache = truth_map(load_rig("menache"), take.segment_names)
    assert "lradius" not in menache.bone_names and "torso" not in menache.bone_names
    assert len(menache.bone_names) == 19
    pig = truth_map(load_rig("plug-in-gait"), take.segment_names)
    assert "TRXO" not in pig.joint_names  # both clavicles' origin: no one joint


@pytest.mark.parametrize(
    ("method", "max_deg", "ref_frame"),
    [("construction", 1e-6, 0), ("fit", 0.1, 0), ("construction", 1e-6, 250)],
)
def test_exact_rig_solves_to_the_truth(
    method: str, max_deg: float, ref_frame: int
) -> None:
    """Any reference frame, in the T-pose (identity segments) or out of it (the
    changes are compared in the world frame, where they agree)."""
    rig, take = _exact()
    cmp = compare_with_truth(_solve(method), take, rig, ref_frame=ref_frame)
    print(
        f"\nexact rig, {method}, reference {ref_frame}: bone max "
        f"{cmp.max_deg.max():.2e} deg, joint max {cmp.joint_max_mm.max():.2e} mm"
    )
    assert cmp.max_deg.max() <= max_deg
    assert cmp.joint_max_mm.max() <= 0.1
    assert cmp.joint_offset_mm.max() <= 1e-3
    assert cmp.bones_past(5.0, 10.0) == ()
    assert (cmp.n_nan == 0).all()
    assert cmp.error_deg.shape == (take.n_frames, 21)


def _with(solve: BodySolve, **arrays: np.ndarray) -> BodySolve:
    return dataclasses.replace(solve, **arrays)


def test_injected_rotation_is_the_error() -> None:
    rig, take = _exact()
    solve = _solve("construction")
    b = rig.bone_names.index("l_forearm")
    k = truth_map(rig, take.segment_names).bone_names.index("l_forearm")
    wfb = solve.world_from_bone_quat.copy()
    axis = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
    wfb[200:, b] = rot.quat_mul(_about(axis, 20.0), wfb[200:, b])  # world frame
    wfb[300:, b] = rot.quat_mul(wfb[300:, b], _about(Y, -15.0))  # and bone frame
    wfb[250, b] = np.nan
    cmp = compare_with_truth(_with(solve, world_from_bone_quat=wfb), take, rig)
    err = cmp.error_deg[:, k]
    assert np.abs(err[:200]).max() <= 1e-6
    np.testing.assert_allclose(err[200:250], 20.0, atol=1e-6)
    assert err[250] == 180.0 and cmp.n_nan[k] == 1
    # -15 deg about the bone's own +Y, then 20 deg about `axis` (world)
    w = solve.world_from_bone_quat[300, b]
    own = rot.quat_mul(w, rot.quat_mul(_about(Y, -15.0), rot.quat_conj(w)))
    expected = np.degrees(rot.quat_angle(rot.quat_mul(_about(axis, 20.0), own)))
    np.testing.assert_allclose(err[300], expected, atol=1e-6)
    assert not np.isclose(expected, 20.0) and not np.isclose(expected, 15.0)
    assert cmp.max_deg[k] == 180.0
    others = np.delete(cmp.max_deg, k)
    assert others.max() <= 1e-6
    assert cmp.bones_past(5.0, 10.0) == ("l_forearm",)
    # the reference frame is the calibration pose: a rotation there is no error later
    ref = compare_with_truth(
        _with(solve, world_from_bone_quat=wfb), take, rig, frames=slice(0, 200)
    )
    assert ref.max_deg[k] <= 1e-6


def test_joint_error_carries_a_constant_offset_and_shows_drift() -> None:
    rig, take = _exact()
    solve = _solve("construction")
    j = solve.joint_names.index("l_forearm")  # the elbow
    upper = take.segment_names.index("l_upper_arm")
    offset_seg = np.array([0.004, -0.003, 0.012])  # 13 mm, rigid on the upper arm
    centres = solve.joint_centres.copy()
    centres[:, j] += rot.quat_rotate(take.world_from_segment_quat[:, upper], offset_seg)
    cmp = compare_with_truth(_with(solve, joint_centres=centres), take, rig)
    jc = cmp.joint_names.index("l_forearm")
    assert cmp.joint_offset_mm[jc] == pytest.approx(1000 * np.linalg.norm(offset_seg))
    assert cmp.joint_carriers[jc] == "l_upper_arm"
    assert cmp.joint_max_mm[jc] <= 1e-6
    # an offset rigid on the joint's own segment (the wrist's, on the hand)
    w = solve.joint_names.index("l_hand")
    hand = take.segment_names.index("l_hand")
    centres[:, w] += rot.quat_rotate(take.world_from_segment_quat[:, hand], offset_seg)
    cmp = compare_with_truth(_with(solve, joint_centres=centres), take, rig)
    jw = cmp.joint_names.index("l_hand")
    assert cmp.joint_carriers[jw] == "l_hand"
    assert cmp.joint_max_mm[jw] <= 1e-6
    # a drift no constant offset explains: 5 mm along world x from frame 200
    drift = solve.joint_centres.copy()
    drift[200:, j] += [0.005, 0.0, 0.0]
    cmp = compare_with_truth(_with(solve, joint_centres=drift), take, rig)
    assert cmp.joint_max_mm[jc] == pytest.approx(5.0)
    assert cmp.joint_p50_mm[jc] <= 1e-6


def test_unobserved_twist_is_the_allowed_excursion() -> None:
    """The performer holds the T-pose; the truth is given a forearm twist alpha
    about its long axis, and the hand a swing beta and a twist theta about its own:
    a solve that holds both twists (here: the still performer's) is off by no more
    than |alpha| + |theta|, the excursion summed over the hand and its ancestors."""
    rig, take = _exact(motions=())
    solve = _solve("construction", motions=())
    t = take.times_s
    alpha = 40.0 * np.sin(2.0 * t)
    theta = -25.0 * np.sin(3.1 * t + 0.4) * (t > 0.5)
    beta = 30.0 * np.sin(1.3 * t)
    wfs = take.world_from_segment_quat.copy()
    forearm = take.segment_names.index("l_forearm")
    hand = take.segment_names.index("l_hand")
    z = np.array([0.0, 0.0, 1.0])
    # T-pose: every segment's frame is the world's, the left arm along +Y
    wfs[:, forearm] = _about(Y, alpha)
    wfs[:, hand] = rot.quat_mul(
        wfs[:, forearm], rot.quat_mul(_about(z, beta), _about(Y, theta))
    )
    truth = dataclasses.replace(take, world_from_segment_quat=wfs)
    unobserved = {"l_forearm": [(0.0, 1.0, 0.0)], "l_hand": [(0.0, 2.0, 0.0)]}
    cmp = compare_with_truth(solve, truth, rig, unobserved=unobserved)
    kf, kh = cmp.bone_names.index("l_forearm"), cmp.bone_names.index("l_hand")
    np.testing.assert_allclose(cmp.excursion_deg[:, kf], np.abs(alpha), atol=1e-6)
    np.testing.assert_allclose(
        cmp.excursion_deg[:, kh], np.abs(alpha) + np.abs(theta), atol=1e-6
    )
    np.testing.assert_allclose(cmp.error_deg[:, kf], np.abs(alpha), atol=1e-6)
    # the hand's swing is observed: it stays an error
    assert (cmp.error_deg[:, kh] > cmp.excursion_deg[:, kh] + 1.0).any()
    others = np.delete(cmp.excursion_deg, [kf, kh], axis=1)
    assert not others.any()
    # without the swing the hand is within its excursion
    wfs[:, hand] = rot.quat_mul(wfs[:, forearm], _about(Y, theta))
    truth = dataclasses.replace(take, world_from_segment_quat=wfs)
    cmp = compare_with_truth(solve, truth, rig, unobserved=unobserved)
    assert (cmp.error_deg[:, kh] <= cmp.excursion_deg[:, kh] + 1e-6).all()
    assert (cmp.excess_max_deg <= 1e-6).all()
    assert cmp.max_deg[kh] > 30.0 and cmp.bones_past(5.0, 10.0) == ()


def test_unobserved_axis_is_read_in_the_bone_rest_axes() -> None:
    """The right forearm held flexed 60 deg (at the reference too) twists by alpha
    about an oblique axis given in the bone's rest axes: its excursion is |alpha|,
    the twist since the reference about that axis as the segment carries it."""
    rig, take = _exact(motions=())
    solve = _solve("construction", motions=())
    b = rig.bone_names.index("r_forearm")
    seg = take.segment_names.index("r_forearm")
    rest = solve.world_from_bone_quat[0, b]  # = segment_from_bone: T-pose
    axis_bone = np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0)
    axis_seg = rot.quat_rotate(rest, axis_bone)
    alpha = 35.0 * np.sin(2.0 * take.times_s)
    flexed = _about(np.array([0.0, 0.0, 1.0]), 60.0)
    wfs = take.world_from_segment_quat.copy()
    wfs[:, seg] = rot.quat_mul(flexed, _about(axis_seg, alpha))
    wfb = solve.world_from_bone_quat.copy()
    wfb[:, b] = rot.quat_mul(flexed, rest)  # the solve holds the twist
    cmp = compare_with_truth(
        _with(solve, world_from_bone_quat=wfb),
        dataclasses.replace(take, world_from_segment_quat=wfs),
        rig,
        unobserved={"r_forearm": [tuple(axis_bone)]},
    )
    k = cmp.bone_names.index("r_forearm")
    np.testing.assert_allclose(cmp.excursion_deg[:, k], np.abs(alpha), atol=1e-6)
    np.testing.assert_allclose(cmp.error_deg[:, k], np.abs(alpha), atol=1e-6)
    hand = cmp.bone_names.index("r_hand")  # carries its parent's excursion
    np.testing.assert_allclose(cmp.excursion_deg[:, hand], np.abs(alpha), atol=1e-6)


def test_unobserved_refuses_what_it_cannot_judge() -> None:
    rig, take = _exact()
    solve = _solve("construction")
    with pytest.raises(ValueError, match="not in rig"):
        compare_with_truth(solve, take, rig, unobserved={"nope": [(0, 1, 0)]})
    with pytest.raises(ValueError, match="non-zero"):
        compare_with_truth(solve, take, rig, unobserved={"l_hand": [(0, 0, 0)]})
    short = _with(solve, world_from_bone_quat=solve.world_from_bone_quat[:10])
    with pytest.raises(ValueError, match="not the same take"):
        compare_with_truth(short, take, rig)


# --- the shipped marker sets against the rigs' models ---------------------------------


def test_plug_in_gait_wrist_bar_sits_where_its_wrist_model_expects_it() -> None:
    """Plug-in Gait's wrist centre is the wrist bar's midpoint moved WristWidth/2 +
    MarkerDiameter/2 towards the palm: the bar lies across the back of the wrist. The
    synthetic performer wears it there (27 mm above the wrist's centre), so the rig's
    wrist centre is off the performer's joint only by the rig's default WristWidth
    (55 mm) against the performer's 40: 7.5 mm (10 allowed). A bar at the wrist's own
    centre put it 34.5 mm off and, with the elbow hinge taken from the static's bend,
    turned the upper arms 35 deg (p95) where the squat's arms hang straight (9.5 now;
    15 allowed)."""
    take = pf.synthesize(
        seconds=5.0, rate_hz=60.0, markerset="plug-in-gait", motions=("deep_squat",)
    )
    rig = load_rig("plug-in-gait")
    hold = take.base_pose_frames
    cal = calibrate(rig, take.markers_world[hold], take.labels)
    solver = make_body_solver(
        "fit", rig, cal, take.labels,
        joint_limits=JOINT_LIMITS_DEG, segment_kind=SEGMENT_KIND, rate_hz=60.0,
    )  # fmt: skip
    cmp = compare_with_truth(
        solver.solve_take(take.markers_world), take, rig, frames=slice(hold.stop, None)
    )
    offset = dict(zip(cmp.joint_names, cmp.joint_offset_mm, strict=True))
    assert offset["LWJC"] <= 10.0 and offset["RWJC"] <= 10.0, offset
    p95 = dict(zip(cmp.bone_names, cmp.p95_deg, strict=True))
    assert p95["lupperarm"] <= 15.0 and p95["rupperarm"] <= 15.0, p95


@functools.cache
def _menache_construction(motion: str) -> tuple[Rig, pf.SynthTake, BodySolve]:
    take = pf.synthesize(
        seconds=3.0, rate_hz=RATE_HZ, markerset="menache", motions=(motion,)
    )
    rig = load_rig("menache")
    cal = calibrate(rig, take.markers_world[take.base_pose_frames], take.labels)
    solver = make_body_solver(
        "construction", rig, cal, take.labels,
        joint_limits=JOINT_LIMITS_DEG, segment_kind=SEGMENT_KIND,
    )  # fmt: skip
    return rig, take, solver.solve_take(take.markers_world)


#: The menache limbs' humanoid names (arms, legs, feet, hands; not the trunk, neck or
#: head, whose points the chapter places by rules of its own).
LIMBS = ("Shoulder", "UpperArm", "LowerArm", "Hand", "UpperLeg", "LowerLeg", "Foot")


@pytest.mark.parametrize("motion", ["level_walk", "stair_descent"])
def test_menache_markers_sit_where_the_chapter_rules_put_the_joints(
    motion: str,
) -> None:
    """The synthetic performer wears menache's markers where the rig's site table puts
    them, so the chapter's construction lands UPARM on the shoulder and UPFOOT on the
    ankle and every limb bone solves to its segment: a wrong bone-to-segment map, or
    markers off the sites, shows here. Before the sites were followed (SHOULDER 25 mm
    lateral of the humeral head, FOOT 8 mm below the ankle with HEEL-FOOT's middle
    7.5 mm behind it, TOE on the toes) the shanks were 6-11 deg off (level_walk,
    stair_descent) and the upper arms 4.9 deg, a twist no solve can take out."""
    rig, take, solve = _menache_construction(motion)
    cmp = compare_with_truth(
        solve, take, rig, frames=slice(take.base_pose_frames.stop, None)
    )
    offset = dict(zip(cmp.joint_names, cmp.joint_offset_mm, strict=True))
    for joint in ("LSJC", "RSJC", "LAJC", "RAJC", "LKJC", "RKJC", "LEJC", "REJC"):
        assert offset[joint] <= 1e-3, (joint, offset[joint])
    humanoid = {b.name: b.humanoid for b in rig.bones}
    limbs = [
        (name, top)
        for name, top in zip(cmp.bone_names, cmp.max_deg, strict=True)
        if str(humanoid[name]).removeprefix("Left").removeprefix("Right") in LIMBS
    ]
    assert len(limbs) == 14, limbs
    # 0.01 deg, not exactly 0: the clavicle's CLAVICLE and the upper arm's UPARM are
    # built through LONECK, held in the frame of T1, THORAX and T7, and THORAX rides
    # the lumbar markers, so the trunk's counter-rotation in the walk moves LONECK
    # on the ribcage: 0.0028-0.0043 deg with LONECK 61 mm in front of T1 (the depth
    # shift, menache.toml), 0.0006-0.0010 at d = 0 (17 mm); a marker off its site is
    # degrees (above)
    assert all(top <= 1e-2 for _, top in limbs), limbs


@functools.cache
def _menache_fit_default() -> tuple[Rig, pf.SynthTake, BodySolve, dict[str, list]]:
    """The default motions (the head turning 60 deg, 18 of them in the neck), 10 s as
    ``docs/fit-truth.md``'s, solved with the fit; and the rotations its markers leave
    unobserved per bone (``fit_observe``)."""
    take = pf.synthesize(seconds=10.0, rate_hz=RATE_HZ, markerset="menache")
    rig = load_rig("menache")
    cal = calibrate(rig, take.markers_world[take.base_pose_frames], take.labels)
    solver = make_body_solver(
        "fit", rig, cal, take.labels, joint_limits=JOINT_LIMITS_DEG,
        segment_kind=SEGMENT_KIND, rate_hz=take.rate_hz,
    )  # fmt: skip
    assert isinstance(solver, FitSolver)
    unobserved = {
        o.bone: o.axes[~o.observed].tolist()
        for o in solver.model.observation
        if not o.observed.all() and o.dof != "root"
    }
    return rig, take, solver.solve_take(take.markers_world), unobserved


def test_menache_neck_joints_lie_inside_the_neck() -> None:
    """LONECK and UPNECK, "the same method as THORAX" with its depth shift carried
    from the joint below (menache.toml), lie in front of the posterior markers they
    are built from in the base pose. Halfway to the joint below (d = 0) put UPNECK
    18 mm behind the C1 marker, outside the body, on this performer whose cervical
    spine leans forward of T1 as a standing one does."""
    _, take, solve, _ = _menache_fit_default()
    f = take.base_pose_frames.start
    mk = dict(zip(take.labels, np.asarray(take.markers_world)[f], strict=True))
    joints = dict(
        zip(solve.joint_names, np.asarray(solve.joint_centres)[f], strict=True)
    )
    width = mk["LHIP"] - mk["RHIP"]
    width[2] = 0.0
    forward = np.cross(width / np.linalg.norm(width), [0.0, 0.0, 1.0])
    for joint, marker in (("LONECK", "T1"), ("UPNECK", "C1")):
        depth_mm = 1000.0 * float((joints[joint] - mk[marker]) @ forward)
        assert depth_mm > 0.0, (joint, marker, depth_mm)


@pytest.mark.parametrize("bone", ["loneck", "head"])
def test_menache_neck_and_head_follow_the_truth_as_the_head_turns(bone: str) -> None:
    """Issue 28 item 6 on the head and neck in the default motions, the fit: p95
    5 deg, max 10 deg against the truth (less the truth's excursion in a rotation the
    markers leave unobserved). At d = 0 (menache.toml, THORAX) loneck was 39.5/39.8
    deg (23.5/24.0 less the truth's twist excursion), the head 12.5/13.8."""
    rig, take, solve, unobserved = _menache_fit_default()
    cmp = compare_with_truth(
        solve, take, rig, frames=slice(take.base_pose_frames.stop, None),
        unobserved={b: a for b, a in unobserved.items() if b in ("loneck", "head")},
    )  # fmt: skip
    k = cmp.bone_names.index(bone)
    p95, top = cmp.excess_p95_deg[k], cmp.excess_max_deg[k]
    assert p95 <= 5.0 and top <= 10.0, (bone, p95, top)


@pytest.mark.parametrize("motion", ["level_walk", "jump"])
def test_plug_in_gait_arm_markers_sit_where_its_rules_put_the_joints(
    motion: str,
) -> None:
    """The synthetic performer wears Plug-in Gait's arm markers where its rules, with
    the rig's default measurements, put the joints: the shoulder chord from SHO lands
    on the glenohumeral centre and the elbow chord (the static's elbows at a right
    angle, the wrist bar WristWidth/2 + 7 mm above the wrist) on the elbow. Before
    (SHO 25 mm lateral, the bar 27 mm above the wrist for a 55 mm WristWidth, elbows at
    40 deg) they were 21 and 10 mm off, and the fit's upper arms 4.9 deg off in the
    walks and 9.7 in the jump. What stays is Plug-in Gait's own approximation: the
    elbow chord's normal leans with ELB's and the bar's heights (1.3 mm at a right
    angle)."""
    take = pf.synthesize(
        seconds=1.5, rate_hz=RATE_HZ, markerset="plug-in-gait", motions=(motion,)
    )
    rig = load_rig("plug-in-gait")
    cal = calibrate(rig, take.markers_world[take.base_pose_frames], take.labels)
    solver = make_body_solver(
        "construction", rig, cal, take.labels,
        joint_limits=JOINT_LIMITS_DEG, segment_kind=SEGMENT_KIND,
    )  # fmt: skip
    cmp = compare_with_truth(
        solver.solve_take(take.markers_world), take, rig,
        frames=slice(take.base_pose_frames.stop, None),
    )  # fmt: skip
    offset = dict(zip(cmp.joint_names, cmp.joint_offset_mm, strict=True))
    print({j: round(float(v), 2) for j, v in offset.items()})
    for joint in ("LSJC", "RSJC"):
        assert offset[joint] <= 0.5, (joint, offset[joint])
    for joint in ("LEJC", "REJC"):
        assert offset[joint] <= 2.0, (joint, offset[joint])


@functools.cache
@pytest.mark.parametrize("rig_name", ["plug-in-gait", "menache"])
def test_hands_follow_the_truth_in_the_default_motions(rig_name: str) -> None:
    """Issue 28 item 6 on the hands in the default motions (wrist flexion +-25 deg,
    deviation +-10), the fit, 10 s at 60 Hz: p95 5 deg, max 10 deg against the
    truth, the plain error. Both rigs aim the hand bone at a marker over the second
    metacarpal, 20 deg off the hand's long axis; a swing about axes perpendicular to
    that line (no ``twist_to``) turned part of every flexion into a twist about it,
    which the marker, on the line, cannot see: Plug-in Gait's hands were 7.6-8.0 /
    8.9-9.4 deg (docs/fit-truth.md, 120 Hz), the truth's own twist about the line
    7.4-7.9 p95; about the forearm's axis (``twist_to = HAND_AXIS``) it is 2.0."""
    take = pf.synthesize(seconds=10.0, rate_hz=60.0, markerset=rig_name)
    rig = load_rig(rig_name)
    cal = calibrate(rig, take.markers_world[take.base_pose_frames], take.labels)
    solver = make_body_solver(
        "fit", rig, cal, take.labels, joint_limits=JOINT_LIMITS_DEG,
        segment_kind=SEGMENT_KIND, rate_hz=take.rate_hz,
    )  # fmt: skip
    cmp = compare_with_truth(
        solver.solve_take(take.markers_world), take, rig,
        frames=slice(take.base_pose_frames.stop, None),
    )  # fmt: skip
    hands = [n for n in cmp.bone_names if n.endswith("hand")]
    assert len(hands) == 2, cmp.bone_names
    for name in hands:
        k = cmp.bone_names.index(name)
        p95, top = float(cmp.p95_deg[k]), float(cmp.max_deg[k])
        print(f"\n{rig_name} {name}: {p95:.1f} / {top:.1f} deg p95 / max")
        assert p95 <= 5.0 and top <= 10.0, (name, p95, top)


def _pig_squat_fit() -> tuple[dict[str, float], dict[str, float]]:
    """Plug-in Gait's fit of the deep squat (5 s at 60 Hz) against the truth: p95 and
    max per bone, degrees. The squat flexes the performer's trunk 30 deg, 15 at its
    lumbar joint (L1) and 15 at its thoracic one (T7); Plug-in Gait has no marker
    between the PSIS and T10, and its spine bone stands for the abdomen
    (``synth.truth``: Spine -> abdomen), its chest for the thorax."""
    take = pf.synthesize(
        seconds=5.0, rate_hz=60.0, markerset="plug-in-gait", motions=("deep_squat",)
    )
    rig = load_rig("plug-in-gait")
    cal = calibrate(rig, take.markers_world[take.base_pose_frames], take.labels)
    solver = make_body_solver(
        "fit", rig, cal, take.labels,
        joint_limits=JOINT_LIMITS_DEG, segment_kind=SEGMENT_KIND, rate_hz=60.0,
    )  # fmt: skip
    cmp = compare_with_truth(
        solver.solve_take(take.markers_world), take, rig,
        frames=slice(take.base_pose_frames.stop, None),
    )  # fmt: skip
    p95 = dict(zip(cmp.bone_names, (float(v) for v in cmp.p95_deg), strict=True))
    top = dict(zip(cmp.bone_names, (float(v) for v in cmp.max_deg), strict=True))
    print(f"\nspine {p95['spine']:.1f} / {top['spine']:.1f}, chest "
          f"{p95['chest']:.1f} / {top['chest']:.1f} deg p95 / max")  # fmt: skip
    return p95, top


def test_plug_in_gait_chest_follows_the_truth_in_the_deep_squat() -> None:
    """The chest, which the four thorax markers carry, within issue 28 item 6's
    marks (3.5 / 3.6 deg p95 / max in docs/fit-truth.md)."""
    p95, top = _pig_squat_fit()
    assert p95["chest"] <= 5.0 and top["chest"] <= 10.0, (p95["chest"], top["chest"])


@pytest.mark.xfail(
    strict=True,
    reason="measured (issue 28 item 6, docs/fit-open.md): the "
    "spine is 19.1 / 19.3 deg p95 / max off the abdomen in the deep squat (60 Hz, "
    "5 s; 19.1 / 19.3 in docs/fit-truth.md at 120 Hz). Plug-in Gait's spine is a rod "
    "from PELVIS_TOP, 113 mm below the performer's lumbar joint, to the STRN-T10 "
    "middle: with the squat's 15 + 15 deg of lumbar and thoracic flexion the fit "
    "turns it 4.3 deg backwards (the construction's chord 1.6 forwards) while the "
    "chest takes 33.6 (120 Hz). Its length's share of the trunk's rotation "
    "(0.52) brings it to 1.8 / 1.8 but puts the chest origin 81 mm from where the "
    "markers place it in the rig's own forward kinematics (not kept)",
)
def test_plug_in_gait_spine_follows_the_truth_in_the_deep_squat() -> None:
    p95, top = _pig_squat_fit()
    assert p95["spine"] <= 5.0 and top["spine"] <= 10.0, (p95["spine"], top["spine"])
