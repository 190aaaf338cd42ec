"""The ``plug-in-gait`` rig against Vicon's own Plug-in Gait on the btkdata pair.

Calibrate on the static (whole take), solve the static and the walk, and compare the
joint centres with the points Vicon's solver wrote into the same files (in Plug-in Gait
the femur's proximal point is the hip centre, its origin the knee centre, and so on).
Run with ``pytest -s`` to see the figures.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from retargetd.daemon.body.calibration import (
    Calibration,
    calibrate,
    compute_points,
    match_markers,
)
from retargetd.daemon.body.rig import Rig, load_rig
from retargetd.daemon.body.solve import FLAG_HELD, FLAG_REBUILT, BodySolve, BodySolver
from retargetd.daemon.cli.main import main
from retargetd.replay.take import Take
from retargetd.replay.takes import load_take

STATIC = "btkdata/PiG_Calibration-FlatFoot-Full.c3d"
WALK = "btkdata/PiG_Motion-FlatFoot-Full.c3d"
VICON_NAMES = ("LHJC", "RHJC", "LKJC", "RKJC", "LAJC", "RAJC",
               "LSJC", "RSJC", "LEJC", "REJC", "LWJC", "RWJC")  # fmt: skip
#: Our joint (without side) -> Vicon's point (without side), median limit in mm.
REFERENCE = {
    "HJC": ("FEP", 25.0),
    "KJC": ("FEO", 15.0),
    "AJC": ("TIO", 15.0),
    "SJC": ("HUP", 30.0),
    "EJC": ("HUO", 15.0),
    "WJC": ("RAO", 15.0),
}
ADJACENT = (("HJC", "KJC"), ("KJC", "AJC"), ("SJC", "EJC"), ("EJC", "WJC"))
CV_LIMIT_PCT = 2.0


@dataclass(frozen=True)
class Solved:
    rig: Rig
    cal: Calibration
    take: Take
    res: BodySolve

    def joint(self, name: str) -> np.ndarray:
        return self.res.joint_centres[:, self.res.joint_names.index(name)]

    def vicon(self, name: str) -> np.ndarray:
        return self.take.references.get(name)


@functools.cache
def _solve(root: Path, which: str, marker_diameter: float | None = None) -> Solved:
    rig = load_rig("plug-in-gait")
    static = load_take(root / STATIC)
    overrides = None if marker_diameter is None else {"MarkerDiameter": marker_diameter}
    cal = calibrate(
        rig,
        static.positions,
        static.labels,
        take_measurements=static.measurements,
        overrides=overrides,
    )
    take = static if which == "static" else load_take(root / WALK)
    res = BodySolver(rig, cal, take.labels).solve_take(take.positions)
    return Solved(rig, cal, take, res)


def _distances_mm(s: Solved, side: str, key: str) -> np.ndarray:
    ref, _ = REFERENCE[key]
    return 1000.0 * np.linalg.norm(s.joint(side + key) - s.vicon(side + ref), axis=-1)


def _cv_pct(lengths: np.ndarray) -> float:
    return float(100.0 * lengths.std() / lengths.mean())


@pytest.mark.parametrize("which", ["static", "walk"])
def test_joint_centres_match_vicon(datasets: Path, which: str) -> None:
    s = _solve(datasets, which)
    print(f"\nplug-in-gait vs Vicon's Plug-in Gait, {which}, {s.take.n_frames} frames:")
    failures = []
    for key, (ref, limit) in REFERENCE.items():
        for side in "LR":
            d = _distances_mm(s, side, key)
            assert np.isfinite(d).all()
            med, p95, worst = np.median(d), np.percentile(d, 95), d.max()
            print(
                f"  {side}{key} vs {side}{ref}: median {med:5.1f}  p95 {p95:5.1f}  "
                f"max {worst:5.1f}  (limit {limit:g})"
            )
            if med > limit:
                failures.append(f"{side}{key} median {med:.1f} mm > {limit:g}")
    assert not failures, failures


@pytest.mark.parametrize("which", ["static", "walk"])
def test_adjacent_joint_distances_are_stable(datasets: Path, which: str) -> None:
    """CV of hip-knee, knee-ankle, shoulder-elbow, elbow-wrist over the take <= 2 %.

    Vicon's own right shank (RFEO-RTIO) varies 2.14 % on the walk: soft tissue moves
    the knee and ankle markers in swing, and Plug-in Gait, which the rig follows, has no
    length constraint. Where Vicon's own CV on the take is above the limit, ours must
    not exceed Vicon's (the 2 % holds everywhere else).
    """
    s = _solve(datasets, which)
    print(f"\nadjacent joint-centre distances, {which}: mean mm, CV % (Vicon's own):")
    failures = []
    for a, b in ADJACENT:
        for side in "LR":
            ours = np.linalg.norm(s.joint(side + a) - s.joint(side + b), axis=-1)
            ra, rb = REFERENCE[a][0], REFERENCE[b][0]
            vicon = np.linalg.norm(s.vicon(side + ra) - s.vicon(side + rb), axis=-1)
            cv, vcv = _cv_pct(ours), _cv_pct(vicon)
            print(
                f"  {side}{a}-{side}{b}: {1000 * ours.mean():6.1f} mm  CV {cv:4.2f} %"
                f"   (Vicon {side}{ra}-{side}{rb}: {1000 * vicon.mean():6.1f} mm, "
                f"CV {vcv:4.2f} %)"
            )
            if cv > max(CV_LIMIT_PCT, vcv):
                failures.append(f"{side}{a}-{side}{b} CV {cv:.2f} %")
    assert not failures, failures


def test_exact_parts_with_the_session_marker_size(datasets: Path) -> None:
    """Vicon's centres sit 1.00 mm from ours, each along the direction a 1 mm larger
    marker radius moves it: the session was processed with 16 mm markers (the file does
    not record it). With that one physical parameter, the parts of the rig that model
    Plug-in Gait exactly (hip regression, pelvis and thorax origins, wrist) agree to
    < 1 mm; the ankle too (its chord ratio, ~0.09, hardly matters). The knee, elbow and
    shoulder keep the error of their constant chord ratio."""
    s = _solve(datasets, "walk", marker_diameter=16.0)
    print("\nwalk with MarkerDiameter = 16 mm, median / max mm:")
    pairs = [("PELVIS", "PELO"), ("TRXO", "TRXO")]
    for key in ("HJC", "AJC", "WJC"):
        pairs += [(side + key, side + REFERENCE[key][0]) for side in "LR"]
    for ours, ref in pairs:
        d = 1000.0 * np.linalg.norm(s.joint(ours) - s.vicon(ref), axis=-1)
        print(f"  {ours} vs {ref}: {np.median(d):.2f} / {d.max():.2f}")
        assert np.median(d) < 1.0, (ours, ref)


def test_up_references_stay_off_the_bones(datasets: Path) -> None:
    for which in ("static", "walk"):
        s = _solve(datasets, which)
        cols = np.asarray(match_markers(s.rig, s.take.labels))
        pts = compute_points(s.rig, s.take.positions[:, cols], s.cal.point_offsets)
        for bone in s.rig.bones:
            axis = pts[bone.aim] - pts[bone.origin]
            if len(bone.up) == 2:
                up = pts[bone.up[1]] - pts[bone.up[0]]
            else:
                up = pts[bone.up[0]] - pts[bone.origin]
            cos = np.sum(axis * up, axis=-1) / (
                np.linalg.norm(axis, axis=-1) * np.linalg.norm(up, axis=-1)
            )
            angle = np.degrees(np.arccos(np.abs(cos)))
            assert np.nanmin(angle) > 3.0, (which, bone.name, np.nanmin(angle))


def test_rig_check_on_the_walk(datasets: Path, capsys: pytest.CaptureFixture) -> None:
    assert main(["rig", "check", "plug-in-gait", str(datasets / WALK)]) == 0
    out = capsys.readouterr().out
    assert "matched 34/34 rig markers" in out
    assert "every bone can be built from this take" in out


def test_head_gaps_are_rebuilt_not_held(datasets: Path) -> None:
    s = _solve(datasets, "walk")
    lfhd = s.take.labels.index("LFHD")
    gaps = ~s.take.valid[:, lfhd]
    assert gaps.sum() >= 10  # the walk's LFHD gaps
    res = s.res
    assert np.isfinite(res.joint_centres).all()
    assert np.isfinite(res.world_from_bone_quat).all()
    for name in ("neck", "head"):
        b = res.bone_names.index(name)
        assert not (res.bone_flags[:, b] & FLAG_HELD).any(), name
        assert (res.bone_flags[gaps, b] & FLAG_REBUILT).all(), name
    # Blank LFHD where it was seen: the rebuilt head agrees with the measured one.
    seen = np.flatnonzero(~gaps)
    blanked = s.take.positions.copy()
    blanked[seen, lfhd] = np.nan
    again = BodySolver(s.rig, s.cal, s.take.labels).solve_take(blanked)
    head = res.joint_names.index("HEAD")
    err = 1000.0 * np.linalg.norm(
        again.joint_centres[seen, head] - res.joint_centres[seen, head], axis=-1
    )
    b = res.bone_names.index("head")
    q_blanked = again.world_from_bone_quat[seen, b]
    dq = np.abs(np.sum(q_blanked * res.world_from_bone_quat[seen, b], axis=-1))
    angle = np.degrees(2.0 * np.arccos(np.clip(dq, 0.0, 1.0)))
    print(
        f"\nLFHD blanked in {seen.size} frames: head centre moves median "
        f"{np.median(err):.1f} mm (max {err.max():.1f}); head bone "
        f"{np.median(angle):.1f} deg (max {angle.max():.1f})"
    )
    assert np.median(err) < 5.0 and np.median(angle) < 3.0


def test_solve_cli_writes_the_vicon_joint_names(
    datasets: Path, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    cal = tmp_path / "pig.json"
    static, walk = str(datasets / STATIC), str(datasets / WALK)
    assert main(["calibrate", static, "--rig", "plug-in-gait", "--out", str(cal)]) == 0
    out = tmp_path / "walk.npz"
    solve = ["solve", walk, "--rig", "plug-in-gait", "--calibration", str(cal)]
    assert main([*solve, "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "bones held (frames): none" in text
    with np.load(out, allow_pickle=False) as npz:
        names = list(npz["joint_names"])
        assert set(VICON_NAMES) <= set(names)
        assert npz["joint_centres"].shape == (315, len(names), 3)
        assert np.isfinite(npz["joint_centres"]).all()
        assert str(npz["rig_name"]) == "plug-in-gait"
