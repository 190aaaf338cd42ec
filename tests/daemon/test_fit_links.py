"""A link (a bone no marker rides between two the markers see, ``body.fit_links``)
takes its length's share of its chain's rotation in the fit's output: which bones
are links, the spread's arithmetic, and Plug-in Gait's spine against the synthetic
performer's truth (issue 28 item 6). ``pytest -s`` prints the figures.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.calibration import calibrate
from retargetd.daemon.body.fit_links import link_spread, spread_link
from retargetd.daemon.body.method import make_body_solver
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.body.solve import BodySolve
from retargetd.daemon.body.solve_fit import FitSolver
from retargetd.daemon.synth import performer as pf
from retargetd.daemon.synth.truth import compare_with_truth
from retargetd.daemon.validate.limits import JOINT_LIMITS_DEG
from retargetd.daemon.validate.model import SEGMENT_KIND

RATE_HZ = 60.0


def test_link_spread_finds_the_marker_less_bones_between_observed_ones() -> None:
    """pelvis(markers) -> spine(none) -> chest(markers) -> neck(none) -> head(markers);
    chest -> clav(none) -> scap(fixed, markers): the clavicle is one body with its
    scapula, not a link; chest -> arm(none) -> hand(none): a chain of two marker-less
    bones ends in nothing observed, no link; a hinge child is no ball to spread on."""
    names = ["pelvis", "spine", "chest", "neck", "head", "clav", "scap", "arm", "hand",
             "knee_link", "shin"]  # fmt: skip
    parent = np.array([-1, 0, 1, 2, 3, 2, 5, 2, 7, 0, 9])
    dof = ["root", "ball", "ball", "ball", "ball", "ball", "fixed", "ball", "ball",
           "ball", "hinge"]  # fmt: skip
    marker_bone = np.array([0, 0, 2, 2, 4, 6, 10, -1])
    weight = np.array([1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0])
    lengths = np.array([0.1, 0.3, 0.1, 0.2, 0.2, 0.15, 0.1, 0.3, 0.1, 0.4, 0.4])
    frac, child = link_spread(parent, marker_bone, weight, dof, lengths)
    links = {names[b]: (round(float(frac[b]), 6), names[child[b]])
             for b in np.flatnonzero(frac)}  # fmt: skip
    assert links == {"spine": (0.75, "chest"), "neck": (0.5, "head")}, links
    assert (child[frac == 0.0] == -1).all()
    # a marker the fit ignores (weight 0) sees nothing: with the chest's unseen the
    # spine's child is unobserved (no link), and the chest has three children
    weight[2:4] = 0.0
    frac, _ = link_spread(parent, marker_bone, weight, dof, lengths)
    assert not frac[1] and not frac[2] and frac[3] == pytest.approx(0.5)
    # no joint models: no links
    frac, child = link_spread(parent, marker_bone, weight, (), lengths)
    assert not frac.any() and (child == -1).all()


def _q(r: Rotation) -> np.ndarray:
    return np.asarray(r.as_quat(scalar_first=True), dtype=np.float64)


@pytest.mark.parametrize("f", [0.0, 0.3, 1.0])
def test_spread_link_takes_its_share_of_the_chains_rotation(f: float) -> None:
    """Against scipy: link b on parent p turns E^f times its calibration rotation,
    E the chain's (b then c) rotation on p since calibration, in p's frame."""
    rng = np.random.default_rng(7)
    rest_b, rest_c = Rotation.random(2, random_state=rng)
    w_p = Rotation.random(random_state=rng)
    e = Rotation.from_rotvec(rng.normal(size=3) * 0.6)  # < pi: one shortest way
    split = Rotation.from_rotvec(rng.normal(size=3) * 0.3)  # how the fit split it
    w_b_fit = w_p * split * rest_b
    w_c = w_p * e * rest_b * rest_c  # chain = E * rest chain
    wq = np.stack([_q(w_p), _q(w_b_fit), _q(w_c)])
    wq[2] *= -1.0  # either sign of a quaternion is the same rotation
    rest = np.stack([[1.0, 0.0, 0.0, 0.0], _q(rest_b), _q(rest_c)])
    got = np.array(spread_link(wq, rest, 0, 1, 2, f))
    want = _q(w_p * Rotation.from_rotvec(f * e.as_rotvec()) * rest_b)
    assert abs(float(got @ want)) == pytest.approx(1.0, abs=1e-12), (got, want)
    assert np.linalg.norm(got) == pytest.approx(1.0, abs=1e-12)


def _pig_squat_solves() -> tuple[pf.SynthTake, FitSolver, BodySolve, BodySolve]:
    """The synthetic performer's deep squat in Plug-in Gait, solved by the fit as
    shipped and with its links switched off (the chord the fit's rigid rods give)."""
    take = pf.synthesize(
        seconds=5.0, rate_hz=RATE_HZ, markerset="plug-in-gait", motions=("deep_squat",)
    )
    rig = load_rig("plug-in-gait")
    cal = calibrate(rig, take.markers_world[take.base_pose_frames], take.labels)
    solver = make_body_solver(
        "fit", rig, cal, take.labels,
        joint_limits=JOINT_LIMITS_DEG, segment_kind=SEGMENT_KIND, rate_hz=RATE_HZ,
    )  # fmt: skip
    assert isinstance(solver, FitSolver)
    spread = solver.solve_take(take.markers_world)
    solver.reset()
    solver._model[26][:] = 0.0  # the packed model's link shares (fit_pack.M_KINDS)
    chord = solver.solve_take(take.markers_world)
    return take, solver, spread, chord


_squat = functools.cache(_pig_squat_solves)


def test_plug_in_gaits_spine_and_neck_are_its_links() -> None:
    _, solver, _, _ = _squat()
    frac, child = solver.links
    names = solver.bone_names
    links = {names[b]: names[child[b]] for b in np.flatnonzero(frac)}
    assert links == {"spine": "chest", "neck": "head"}, links
    lengths = np.asarray(solver.calibration.bone_lengths)
    spine, chest = names.index("spine"), names.index("chest")
    assert frac[spine] == pytest.approx(
        lengths[spine] / (lengths[spine] + lengths[chest])
    )
    # menache: every trunk bone carries a marker, the clavicle rides with its
    # scapula (fixed): no links
    rig = load_rig("menache")
    men = pf.synthesize(seconds=1.5, rate_hz=RATE_HZ, markerset="menache")
    cal = calibrate(rig, men.markers_world[men.base_pose_frames], men.labels)
    fit = make_body_solver("fit", rig, cal, men.labels, rate_hz=RATE_HZ)
    assert isinstance(fit, FitSolver)
    assert not fit.links[0].any(), fit.links


def test_the_spread_moves_only_the_links_split() -> None:
    """The chest, everything below it and every joint centre are the fit's own: only
    how the chain's rotation is split between the link and its child changes."""
    _, solver, spread, chord = _squat()
    names = solver.bone_names
    links = [names.index("spine"), names.index("neck")]
    others = [b for b in range(len(names)) if b not in links]
    dot = np.abs(
        np.sum(
            spread.world_from_bone_quat[:, others]
            * chord.world_from_bone_quat[:, others],
            axis=-1,
        )
    )
    assert np.all(dot > 1.0 - 1e-12)
    np.testing.assert_allclose(spread.joint_centres, chord.joint_centres, atol=1e-12)
    chain = rot.quat_mul(
        spread.parent_from_bone_quat[:, links[0]],
        spread.parent_from_bone_quat[:, names.index("chest")],
    )
    chain_chord = rot.quat_mul(
        chord.parent_from_bone_quat[:, links[0]],
        chord.parent_from_bone_quat[:, names.index("chest")],
    )
    assert np.all(np.abs(np.sum(chain * chain_chord, axis=-1)) > 1.0 - 1e-12)


def test_plug_in_gaits_spine_follows_the_truth_in_the_squat() -> None:
    """Issue 28 item 6 (p95 5, max 10 deg): the squat flexes the performer's trunk 30
    deg, 15 in the abdomen (its L1 joint) and 15 in the thorax. The spine rod from the
    sacrum's height to T10 / the xiphoid hardly turns (the sternum drops as the
    thorax flexes): as a chord the spine was 19 deg p95 off its truth (19.1 in
    docs/fit-truth.md at 120 Hz); with its length's share of the trunk (0.52), 1.8."""
    take, solver, spread, chord = _squat()
    rig = solver.rig
    frames = slice(take.base_pose_frames.stop, None)
    after = compare_with_truth(spread, take, rig, frames=frames)
    before = compare_with_truth(chord, take, rig, frames=frames)
    k = after.bone_names.index("spine")
    c = after.bone_names.index("chest")
    print(
        f"\nspine p95/max {before.p95_deg[k]:.1f}/{before.max_deg[k]:.1f} as the chord,"
        f" {after.p95_deg[k]:.1f}/{after.max_deg[k]:.1f} spread; chest "
        f"{after.p95_deg[c]:.1f}/{after.max_deg[c]:.1f}"
    )
    assert before.p95_deg[k] > 10.0  # the mechanism: the chord is not the abdomen
    assert after.p95_deg[k] <= 5.0 and after.max_deg[k] <= 10.0
    assert after.p95_deg[c] == before.p95_deg[c]


@pytest.mark.xfail(
    strict=True,
    reason="measured: the default motions' spine is 7.7/7.9 deg p95/max from its "
    "truth (docs/fit-truth.md's take, 10 s at 120 Hz): the performer's abdomen takes "
    "0.40 of the trunk's flexion, side bend and twist (synth.motion._spine) where the "
    "length share gives the link 0.52 (4.9/5.1 deg with the true thorax), and the "
    "chest is itself 7.4/7.6 off (T10 rides the abdomen, the chest's twist is held)",
)
def test_plug_in_gaits_spine_follows_the_truth_in_the_default_motions() -> None:
    take = pf.synthesize(seconds=10.0, rate_hz=120.0, markerset="plug-in-gait")
    rig = load_rig("plug-in-gait")
    cal = calibrate(rig, take.markers_world[take.base_pose_frames], take.labels)
    solver = make_body_solver(
        "fit", rig, cal, take.labels,
        joint_limits=JOINT_LIMITS_DEG, segment_kind=SEGMENT_KIND, rate_hz=120.0,
    )  # fmt: skip
    cmp = compare_with_truth(
        solver.solve_take(take.markers_world), take, rig,
        frames=slice(take.base_pose_frames.stop, None),
    )  # fmt: skip
    k = cmp.bone_names.index("spine")
    print(f"\nspine p95/max {cmp.p95_deg[k]:.1f}/{cmp.max_deg[k]:.1f}")
    assert cmp.p95_deg[k] <= 5.0 and cmp.max_deg[k] <= 10.0
