"""Issue 28's evidence for the fit: what the markers observe is decided by the code and
held where they are silent; bursts of garbage heal; hidden markers do not carry the
pose off; a steady misfit is weighed down, not held out; a performer not yet seen is
not a pose. Against the synthetic performer's truth and the real Plug-in Gait walk's
intact solve. ``pytest -s`` prints the figures.
"""

from __future__ import annotations

import functools
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from retargetd.daemon import rotations as rot
from retargetd.daemon.body import fit_observe
from retargetd.daemon.body import fit_terms as ft
from retargetd.daemon.body.calibration import calibrate
from retargetd.daemon.body.method import make_body_solver
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.body.solve_fit import FitParams, FitSolve
from retargetd.daemon.cli.main import main
from retargetd.daemon.synth import performer as pf
from retargetd.daemon.synth.damage import damage, damage_metrics
from retargetd.daemon.validate.limits import JOINT_LIMITS_DEG
from retargetd.daemon.validate.model import SEGMENT_KIND
from retargetd.replay.takes import load_take

RATE_HZ = 120.0
PIG_STATIC = "btkdata/PiG_Calibration-FlatFoot-Full.c3d"
PIG_WALK = "btkdata/PiG_Motion-FlatFoot-Full.c3d"
#: The issue's recovery time.
RECOVER_S = 0.25


def _fit(rig_name: str, cal: Any, labels: tuple[str, ...], rate_hz: float) -> Any:
    return make_body_solver(
        "fit", load_rig(rig_name), cal, labels,
        joint_limits=JOINT_LIMITS_DEG, segment_kind=SEGMENT_KIND, rate_hz=rate_hz,
    )  # fmt: skip


@functools.cache
def _synthetic(markerset: str) -> tuple[pf.SynthTake, Any]:
    take = pf.synthesize(seconds=6.0, rate_hz=RATE_HZ, markerset=markerset, seed=0)
    cal = calibrate(
        load_rig(markerset), take.markers_world[take.base_pose_frames], take.labels
    )
    return take, cal


@functools.cache
def _pig(datasets: Path) -> tuple[Any, Any]:
    static, walk = load_take(datasets / PIG_STATIC), load_take(datasets / PIG_WALK)
    cal = calibrate(
        load_rig("plug-in-gait"), static.positions, static.labels,
        take_measurements=static.measurements,
    )  # fmt: skip
    return walk, cal


# --- item 1: observability ----------------------------------------------------------


@pytest.mark.parametrize("rig_name", ["menache", "plug-in-gait"])
def test_rig_check_prints_what_the_markers_observe(
    rig_name: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """``rig check --json`` on the synthetic performer: every bone's rotations with
    their lever, those under the threshold held by the automatic prior, and the
    model's prior is exactly there (a rotation no marker sees: Plug-in Gait's spine
    twist, which the chest above carries; menache's neck twist is C1's to see)."""
    assert main(["rig", "check", rig_name, "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    obs = doc["observability"]
    threshold = obs["min_lever_mm_per_rad"]
    assert threshold == pytest.approx(1e3 * fit_observe.MIN_LEVER_M, abs=1e-3)
    rig = load_rig(rig_name)
    assert set(obs["bones"]) == set(rig.bone_names)
    take, cal = _synthetic(rig_name)
    model = _fit(rig_name, cal, take.labels, RATE_HZ).model
    held = []
    for b, name in enumerate(rig.bone_names):
        for r in obs["bones"][name]["rotations"]:
            assert r["observed"] == (r["lever_mm_per_rad"] >= threshold)
            if not r["observed"] and rig.bones[b].parent is not None:
                u = np.asarray(r["axis"])
                held.append((name, u))
                # the automatic prior holds that direction, at (min lever)^2
                pull = u @ model.prior_mat[b] @ u
                assert pull >= fit_observe.PRIOR_STIFFNESS * 0.99, (name, pull)
    if rig_name == "plug-in-gait":  # its spine's twist, which the chest carries
        assert any(n == "spine" and abs(u[1]) > 0.9 for n, u in held), held
        # the feet's pull spares the plantarflexion: rig check names the axis the
        # model's stiffness leaves free (the automatic prior aside: both observed)
        for foot in ("lfoot", "rfoot"):
            entry = obs["bones"][foot]
            spared = np.asarray(entry["stiffness_spares_axis"])
            assert abs(np.linalg.norm(spared) - 1.0) < 1e-3, entry
            b = rig.bone_names.index(foot)
            k2 = (1e-3 * entry["stiffness_mm"]) ** 2
            assert spared @ model.prior_mat[b] @ spared < 1e-3 * k2, foot
            other = np.cross(spared, [1.0, 0.0, 0.0])
            other /= np.linalg.norm(other)
            assert other @ model.prior_mat[b] @ other >= 0.99 * k2, foot
    else:  # menache's neck twist, seen by C1 with the neck joints inside the neck
        assert all(e["stiffness_spares_axis"] is None for e in obs["bones"].values()), (
            "menache has no stiffness_free_plane"
        )
        # (menache.toml, LONECK: 8 mm/rad with them behind it, at d = 0)
        twist = [
            r
            for r in obs["bones"]["loneck"]["rotations"]
            if abs(np.asarray(r["axis"])[1]) > 0.9
        ]
        assert len(twist) == 1 and twist[0]["observed"], twist
    # the forearm twists about the ulna (elbow centre to ulnar styloid): menache's
    # forearm bone itself; 7.4 deg off Plug-in Gait's, which aims at the wrist
    # centre (the performer's styloid 35 mm beside it over 269.5 mm; the calibration's
    # elbow centre and bar moved it by 0.5 deg at most)
    for side in ("l", "r"):
        fore = {"menache": f"{side}ulna", "plug-in-gait": f"{side}lowerarm"}[rig_name]
        got = np.asarray(obs["bones"][fore]["twist_axis"])
        np.testing.assert_allclose(
            got, model.twist_axis[rig.bone_names.index(fore)], atol=1e-4
        )
        off = np.degrees(np.arccos(abs(got[1])))
        want = {"menache": 0.0, "plug-in-gait": np.degrees(np.arctan(35.0 / 269.5))}
        assert abs(off - want[rig_name]) <= 0.5, (fore, off)
    print(f"\n{rig_name}: held by the automatic prior: {[n for n, _ in held]}")


def test_a_rig_without_a_fit_table_gets_the_automatic_rule(tmp_path: Path) -> None:
    """A rig written from RIGS.md with no ``[fit]``: menache's own file without its
    table. Every bone whose markers leave a rotation unseen gets the prior (the
    forearm's twist: its radial styloid rides the radius, not the ulna, there)."""
    import retargetd.daemon.body.rigs as shipped

    text = (Path(shipped.__file__).parent / "menache.toml").read_text()
    bare = text[: text.index("# ---- The fit (RIGS.md")]
    path = tmp_path / "bare-menache.toml"
    path.write_text(bare.replace('name = "menache"', 'name = "bare-menache"'))
    rig = load_rig(path)
    assert not rig.fit.bones and not rig.fit.markers
    take, _ = _synthetic("menache")
    cal = calibrate(rig, take.markers_world[take.base_pose_frames], take.labels)
    model = _fit(str(path), cal, take.labels, RATE_HZ).model
    unseen = {
        o.bone for o in model.observation if (~o.observed).any() and o.dof != "root"
    }
    assert {"lulna", "rulna", "lhand", "rhand"} <= unseen, unseen
    for o in model.observation:
        b = model.bone_names.index(o.bone)
        for axis in o.axes[~o.observed]:
            assert (
                axis @ model.prior_mat[b] @ axis >= fit_observe.PRIOR_STIFFNESS * 0.99
            )


# --- item 3: bursts heal --------------------------------------------------------------


def _recovery(
    intact: FitSolve, damaged: FitSolve, window: slice, rate_hz: float
) -> float | None:
    m = damage_metrics(intact, damaged, window, rate_hz, tol_deg=2.0, tol_mm=10.0)
    assert not m.any_nan
    return m.recovery_s


@pytest.mark.parametrize("kind", ["collapse", "zeros", "swap"])
def test_bursts_heal_within_a_quarter_second_pig_walk(
    datasets: Path, kind: str
) -> None:
    """The btkdata Plug-in Gait walk, bursts of 1, 2, 10 and 50 frames of every marker
    collapsed onto one, all zeros, or left and right labels swapped: the solve is
    back on the intact take's (2 deg, 10 mm) within 0.25 s of the burst's end, and the
    burst's frames are flagged, not streamed as fitted poses."""
    walk, cal = _pig(datasets)
    fit = _fit("plug-in-gait", cal, walk.labels, walk.rate_hz)
    intact = fit.solve_take(walk.positions)
    rate = walk.rate_hz
    for n in (1, 2, 10, 50):
        window = slice(100, 100 + n)
        fit.reset()
        res = fit.solve_take(damage(walk.positions, walk.labels, kind, window))
        rec = _recovery(intact, res, window, rate)
        flagged = (res.unexplained | res.unseen)[window]
        print(f"\n{kind} {n}: recovered in {rec} s; flagged {int(flagged.sum())}/{n}")
        assert rec is not None and rec <= RECOVER_S, (kind, n, rec)
        assert flagged.all(), (kind, n)


@pytest.mark.parametrize("markerset", ["menache", "plug-in-gait"])
def test_bursts_heal_within_a_quarter_second_synthetic(markerset: str) -> None:
    """The synthetic performer, a 10- and a 50-frame burst of each kind, against
    its own intact solve."""
    take, cal = _synthetic(markerset)
    fit = _fit(markerset, cal, take.labels, RATE_HZ)
    intact = fit.solve_take(take.markers_world)
    for kind in ("collapse", "zeros", "swap"):
        for n in (10, 50):
            window = slice(int(3.0 * RATE_HZ), int(3.0 * RATE_HZ) + n)
            fit.reset()
            res = fit.solve_take(damage(take.markers_world, take.labels, kind, window))
            rec = _recovery(intact, res, window, RATE_HZ)
            assert rec is not None and rec <= RECOVER_S, (kind, n, rec)


# --- item 2 / the issue's own cases: one hidden marker ------------------------------


@pytest.mark.parametrize(("marker", "rows"), [("LELB", (30, 56)), ("LKNE", (150, 176))])
def test_the_issues_hidden_markers_keep_the_pose(
    datasets: Path, marker: str, rows: tuple[int, int]
) -> None:
    """The issue's cases on the btkdata walk: LELB hidden for rows 30-55 moved the
    elbow centre 126 mm and the clavicle 88 deg, LKNE for rows 150-175 the knee 114 mm
    and the thigh 50 deg. Now within 20 mm and 10 deg of the intact solve, no NaN."""
    walk, cal = _pig(datasets)
    fit = _fit("plug-in-gait", cal, walk.labels, walk.rate_hz)
    intact = fit.solve_take(walk.positions)
    window = slice(*rows)
    fit.reset()
    res = fit.solve_take(
        damage(
            walk.positions,
            walk.labels,
            "hide",
            window,
            marker=walk.labels.index(marker),
        )
    )
    m = damage_metrics(intact, res, window, walk.rate_hz)
    print(
        f"\n{marker} hidden rows {rows}: joint {m.max_joint_mm:.1f} mm "
        f"({m.max_joint}), bone {m.max_bone_deg:.1f} deg ({m.max_bone}), new steps "
        f"{m.new_steps} (largest {m.max_new_step_deg:.1f} deg)"
    )
    assert not m.any_nan
    assert m.max_joint_mm <= 20.0 and m.max_bone_deg <= 10.0


def test_a_slow_runaway_does_not_raise_its_own_reference(datasets: Path) -> None:
    """A misfit growing by under 2x a frame judged only against the frame before it
    raised its own reference: the walk's LKNE hidden 1 s from row 30 ran the thigh
    58 deg off from row 100 (RMS 5.7, 7.4, 11.3, 15.6 ... 43.0 mm, the suspect line
    11.5 -> 86 mm, no construction candidate tried). Here the same rule on a marker
    that slides off (LKNE moved 3 mm x 1.25^k along x from row 100 for 25 rows, then
    lost; the old rule: the reference 4.0 -> 27.1 mm, the running level 6.0): a
    frame's RMS becomes that reference only under the suspect line of the running
    level alone, max(lost_floor_m, lost_k x level)."""
    walk, cal = _pig(datasets)
    fit = _fit("plug-in-gait", cal, walk.labels, walk.rate_hz)
    pos = walk.positions.copy()
    k = walk.labels.index("LKNE")
    pos[100:125, k, 0] += 0.003 * 1.25 ** np.arange(25)
    pos[125:, k] = np.nan
    pose = fit.new_pose()
    ref = np.zeros(130)
    level_before = np.zeros(130)
    for f in range(130):
        level_before[f] = pose.stats[ft.S_LEVEL] if f else 0.0
        fit.solve_frame(pos[f], pose)
        ref[f] = fit._scalars[ft.C_LAST_RMS]
    p = FitParams()
    changed = np.flatnonzero(np.diff(ref) != 0.0) + 1
    bound = np.maximum(p.lost_floor_m, p.lost_k * level_before[changed])
    over = changed[ref[changed] > bound + 1e-12]
    assert changed[changed >= 110].size > 0  # the drift's frames counted
    assert over.size == 0, [(int(f), 1e3 * ref[f], 1e3 * level_before[f]) for f in over]


def test_the_walks_lkne_hidden_1s_keeps_the_pose(datasets: Path) -> None:
    """Item 6's limits on the walk's LKNE hidden 1 s from row 30: no joint centre
    past 20 mm, no bone past 10 deg, no step over 5 deg the intact solve lacks. Its
    virtual marker carried the 25.6 mm residual it had at row 29, the peak of its
    gait cycle, while its intact residual fell to 2-5 mm within 0.15 s: 59.0 mm,
    34.7 deg, 4 new steps (172.3 mm, 58.0 deg, 12 with the reference ratcheting). The
    offset now fades as the knee bends away from where it was measured (measured
    11.1 mm, 7.7 deg, no new step)."""
    walk, cal = _pig(datasets)
    fit = _fit("plug-in-gait", cal, walk.labels, walk.rate_hz)
    intact = fit.solve_take(walk.positions)
    fit.reset()
    window = slice(30, 130)
    res = fit.solve_take(
        damage(walk.positions, walk.labels, "hide", window,
               marker=walk.labels.index("LKNE"))
    )  # fmt: skip
    m = damage_metrics(intact, res, window, walk.rate_hz)
    print(
        f"\nLKNE hidden rows 30-129: joint {m.max_joint_mm:.1f} mm ({m.max_joint}), "
        f"bone {m.max_bone_deg:.1f} deg ({m.max_bone}), new steps {m.new_steps}"
    )
    assert not m.any_nan
    assert m.max_joint_mm <= 20.0 and m.max_bone_deg <= 10.0 and m.new_steps == 0


def test_hold_tables_for_a_straight_hinge_are_read_by_its_bend() -> None:
    """menache's T-pose holds the elbows and knees straight: each gets a second hold
    table made at a right angle, and each marker of a limb reads its limb's hinge."""
    take, cal = _synthetic("menache")
    model = _fit("menache", cal, take.labels, RATE_HZ).model
    names, bones = list(model.marker_names), list(model.bone_names)
    hinge = {m: (bones[h] if h >= 0 else None) for m, h in
             zip(names, model.hide_hinge, strict=True)}  # fmt: skip
    assert hinge["REELBOW"] == "rulna" and hinge["REWRIST"] == "rulna"
    assert hinge["RHAND"] == "rulna"  # up from the hand (its radius is fixed)
    assert hinge["LEKNEE"] == "lloleg" and hinge["LTOE"] == "lloleg"
    assert hinge["C7"] is None and hinge["SACRUM"] is None
    n = len(names) * len(bones)
    assert model.hide_lam.shape == (2 * n, 3)
    # the forearm's twist with an elbow marker hidden: merged with the upper arm's
    # (prior-only information) straight, its wrist markers' own at a right angle
    row = names.index("REELBOW") * len(bones) + bones.index("rulna")
    assert model.hide_lam[row, 0] < fit_observe.MIN_LEVER_M**2 * 2.5
    assert model.hide_lam[n + row, 0] > 10 * fit_observe.MIN_LEVER_M**2


@pytest.mark.parametrize("marker", ["REELBOW", "RIELBOW", "LEELBOW", "LIELBOW"])
def test_an_elbow_marker_hidden_leaves_the_forearm_its_wrist_markers(
    marker: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """menache's epicondyle markers hidden 1 s while the forearm turns (the synthetic
    performer's forearm twist): with the hold read from the straight calibration
    pose's tables alone the forearm stayed at its twist and the hand went 113-128 deg
    off the intact solve; read by the elbow's bend, within 10 deg and 20 mm (measured
    2.8-4.3 deg, 3-4 mm; 0.6-0.7 deg, 1.7-2.1 mm with the rule below). Since a
    hinge_twist's twist is not held for a marker above its hinge where the parent's
    own markers resolve the parent's turn
    (``fit_track.hold_priors``, issue 28 item 6), the straight tables alone hold it
    right too (1.9-2.4 deg measured; more than 45 before): two guards, each shown."""
    take, cal = _synthetic("menache")
    window = slice(int(3.0 * RATE_HZ), int(4.0 * RATE_HZ))
    hidden = damage(take.markers_world, take.labels, "hide", window,
                    marker=take.labels.index(marker))  # fmt: skip
    fit = _fit("menache", cal, take.labels, RATE_HZ)
    intact = fit.solve_take(take.markers_world)
    fit.reset()
    m = damage_metrics(intact, fit.solve_take(hidden), window, RATE_HZ)
    print(f"\n{marker} hidden 1 s: bone {m.max_bone_deg:.1f} deg ({m.max_bone}), "
          f"joint {m.max_joint_mm:.1f} mm")  # fmt: skip
    assert m.max_bone_deg <= 10.0 and m.max_joint_mm <= 20.0
    # the second guard: no limb hinge, the straight table alone; the epicondyle
    # marker rides the upper arm, whose other epicondyle marker resolves its turn
    # about the forearm's twist axis, so the forearm's twist is not held
    monkeypatch.setattr(
        fit_observe, "marker_hinges",
        lambda chain: np.full(len(chain.marker_bone), -1, dtype=np.int64),
    )  # fmt: skip
    import retargetd.daemon.body.fit_model as fit_model

    monkeypatch.setattr(fit_model, "marker_hinges", fit_observe.marker_hinges)
    straight = _fit("menache", cal, take.labels, RATE_HZ)
    base = straight.solve_take(take.markers_world)
    straight.reset()
    worse = damage_metrics(base, straight.solve_take(hidden), window, RATE_HZ)
    print(f"  the straight table alone: bone {worse.max_bone_deg:.1f} deg "
          f"({worse.max_bone}), joint {worse.max_joint_mm:.1f} mm")  # fmt: skip
    assert worse.max_bone_deg <= 10.0 and worse.max_joint_mm <= 20.0, worse


# --- item 2: a steady misfit; item 5: a performer not yet seen ----------------------


def test_a_marker_beyond_the_gate_from_the_first_frame_is_weighed_not_held_out() -> (
    None
):
    """A thigh marker 55 mm off where the calibration put it from the first frame on
    (a wand knocked before the take): never rejected by the gate (it has no
    jump to be told from a swap by), its residual reported, and the pose as right
    as without it; the issue's 7 deg step on readmission cannot happen."""
    take, cal = _synthetic("plug-in-gait")
    pos = take.markers_world.copy()
    i = take.labels.index("RKNE")
    pos[:, i] += np.array([0.0, 0.0, 0.055])
    fit = _fit("plug-in-gait", cal, take.labels, RATE_HZ)
    res = fit.solve_take(pos)
    fit.reset()
    intact = fit.solve_take(take.markers_world)
    k = res.marker_names.index("RKNE")
    assert not res.marker_rejected[:, k].any()
    assert np.nanmedian(res.marker_residual[:, k]) > 0.03
    dev = np.degrees(
        rot.quat_angle(
            rot.quat_mul(
                rot.quat_conj(intact.world_from_bone_quat), res.world_from_bone_quat
            )
        )
    )
    steps = np.degrees(
        rot.quat_angle(
            rot.quat_mul(
                rot.quat_conj(res.world_from_bone_quat[:-1]),
                res.world_from_bone_quat[1:],
            )
        )
    )
    print(f"\nRKNE 55 mm off: bones within {dev.max():.1f} deg of the intact solve")
    assert dev.max() <= 10.0
    assert (
        steps.max()
        <= 5.0
        + np.degrees(
            rot.quat_angle(
                rot.quat_mul(
                    rot.quat_conj(intact.world_from_bone_quat[:-1]),
                    intact.world_from_bone_quat[1:],
                )
            )
        ).max()
    )


def test_a_performer_not_yet_seen_is_no_pose_and_does_not_teleport() -> None:
    """The first 2 s without any marker: those frames are flagged unseen, hold the
    first seen pose (no jump from the calibration spot: the issue's 236 m/s root),
    and the first seen frame is seeded where the performer is."""
    take, cal = _synthetic("menache")
    pos = take.markers_world.copy()
    lead = int(2.0 * RATE_HZ)
    pos[:lead] = np.nan
    res = _fit("menache", cal, take.labels, RATE_HZ).solve_take(pos)
    assert res.unseen[:lead].all() and not res.unseen[lead:].any()
    assert (res.frame_flags[:lead] & (1 << 7)).all()
    speed = np.linalg.norm(np.diff(res.root_pos, axis=0), axis=-1) * RATE_HZ
    assert speed.max() < 3.0  # m/s: the synthetic walk's own pace, never a teleport
    np.testing.assert_allclose(
        res.root_pos[:lead], np.broadcast_to(res.root_pos[lead], (lead, 3))
    )


def test_a_flickering_pelvis_marker_does_not_swing_the_pelvis(datasets: Path) -> None:
    """A posterior pelvis marker seen every other frame for 2 s of the walk (the issue:
    a flickering sacrum swung the pelvis 24-36 deg every frame): the pelvis stays
    within 1 deg of the intact solve and never steps by more than its own motion."""
    walk, cal = _pig(datasets)
    fit = _fit("plug-in-gait", cal, walk.labels, walk.rate_hz)
    intact = fit.solve_take(walk.positions)
    pos = walk.positions.copy()
    pos[50:250:2, walk.labels.index("LPSI")] = np.nan
    fit.reset()
    res = fit.solve_take(pos)
    k = res.bone_names.index("pelvis")
    w, w0 = res.world_from_bone_quat[:, k], intact.world_from_bone_quat[:, k]
    dev = np.degrees(rot.quat_angle(rot.quat_mul(rot.quat_conj(w0), w)))
    step = np.degrees(rot.quat_angle(rot.quat_mul(rot.quat_conj(w[:-1]), w[1:])))
    own = np.degrees(rot.quat_angle(rot.quat_mul(rot.quat_conj(w0[:-1]), w0[1:])))
    print(f"\nLPSI flickering: pelvis within {dev.max():.2f} deg of the intact solve")
    assert dev.max() <= 1.0
    assert (step <= own + 0.5).all()
