"""A bone whose up reference comes near its axis keeps its roll (issue 14 item 3).

The construction takes a bone's roll from its up reference; when that reference is
seen within the rig's ``up_min_mm`` of the bone's axis, the kernel keeps the new axis
and carries the previous frame's roll relative to the parent, flagged ``partial``
with every defining marker seen. The synthetic performer wears Plug-in Gait; its left
heel marker (the foot's up reference, ~40 mm off the ankle->toe axis) slides across
to 1.9 mm from the axis and back within a second, as a skin or marker slip would: the
geometric roll swings ~145 deg and back. Run with ``pytest -s`` for the figures.
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path

import numpy as np
import pytest

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.calibration import (
    Calibration,
    calibrate,
    compute_points,
    match_markers,
)
from retargetd.daemon.body.rig import UP_MIN_MM, Rig, RigError, load_rig, parse_rig
from retargetd.daemon.body.solve import FLAG_HELD, FLAG_PARTIAL, BodySolve, BodySolver
from retargetd.daemon.body.solve_fit import FitSolver
from retargetd.daemon.synth import performer as pf
from retargetd.daemon.validate.limits import JOINT_LIMITS_DEG
from retargetd.daemon.validate.model import SEGMENT_KIND

RATE_HZ = 120.0
#: the slip: from 1.8 s for 1 s, the heel's part across the axis moves on a straight
#: line from where it is to (-3 mm, 2 mm) in the (lever, lever x axis) plane and back
SLIP = slice(int(1.8 * RATE_HZ), int(2.8 * RATE_HZ))
SLIP_END_MM = (-3.0, 2.0)
#: the issue's bound on a roll change between two frames
MAX_ROLL_STEP_DEG = 5.0


@dataclasses.dataclass(frozen=True)
class Slipped:
    rig: Rig
    take: pf.SynthTake
    cal: Calibration
    positions: np.ndarray  # (T, M, 3) with the heel slipped
    lever_mm: np.ndarray  # (T,) the heel's distance from the ankle->toe axis


@functools.cache
def _slipped(noise_mm: float) -> Slipped:
    rig = load_rig("plug-in-gait")
    take = pf.synthesize(
        seconds=4.0, rate_hz=RATE_HZ, markerset="plug-in-gait", seed=4,
        noise_mm=noise_mm,
    )  # fmt: skip
    base = take.markers_world[take.base_pose_frames]
    cal = calibrate(rig, base, take.labels)
    cols = np.asarray(match_markers(rig, take.labels))
    rig_pos = np.full((take.markers_world.shape[0], len(cols), 3), np.nan)
    rig_pos[:, cols >= 0] = take.markers_world[:, cols[cols >= 0]]
    pts = compute_points(rig, rig_pos, cal.point_offsets)
    ankle, toe = pts["LAJC"][SLIP], pts["LTOE"][SLIP]
    heel = take.labels.index("LHEE")
    axis = (toe - ankle) / np.linalg.norm(toe - ankle, axis=-1, keepdims=True)
    v = take.markers_world[SLIP, heel] - ankle
    along = np.sum(v * axis, axis=-1, keepdims=True)
    across = v - along * axis
    lever = np.linalg.norm(across, axis=-1)
    e1 = across / lever[:, None]
    e2 = np.cross(axis, e1)
    n = SLIP.stop - SLIP.start
    alpha = 0.5 - 0.5 * np.cos(2.0 * np.pi * np.arange(n) / (n - 1))
    c1 = (1.0 - alpha) * lever + alpha * SLIP_END_MM[0] * 1e-3
    c2 = alpha * SLIP_END_MM[1] * 1e-3
    pos = take.markers_world.copy()
    pos[SLIP, heel] = ankle + along * axis + c1[:, None] * e1 + c2[:, None] * e2
    lever_mm = np.full(pos.shape[0], np.nan)
    lever_mm[SLIP] = 1000.0 * np.hypot(c1, c2)
    return Slipped(rig, take, cal, pos, lever_mm)


def _roll_steps_deg(res: BodySolve, bone: str) -> np.ndarray:
    """(T-1,) |rotation about the bone's own +Y| from each frame to the next."""
    b = res.bone_names.index(bone)
    q = res.world_from_bone_quat[:, b]
    d = rot.quat_mul(rot.quat_conj(q[:-1]), q[1:])
    twist = np.degrees(2.0 * np.arctan2(d[:, 2], d[:, 0]))
    return np.abs((twist + 180.0) % 360.0 - 180.0)


@pytest.mark.parametrize("noise_mm", [0.0, 0.2])
def test_heel_near_the_foot_axis_keeps_the_roll(noise_mm: float) -> None:
    s = _slipped(noise_mm)
    assert np.nanmin(s.lever_mm) < 5.0  # the heel passes within 5 mm of the axis
    foot = s.rig.bone_names.index("lfoot")
    con = BodySolver(s.rig, s.cal, s.take.labels).solve_take(s.positions)
    off = BodySolver(
        dataclasses.replace(s.rig, up_min_mm=0.0), s.cal, s.take.labels
    ).solve_take(s.positions)
    fit = FitSolver(
        s.rig, s.cal, s.take.labels,
        base_positions=s.take.markers_world[s.take.base_pose_frames],
        joint_limits=JOINT_LIMITS_DEG, segment_kind=SEGMENT_KIND,
    ).solve_take(s.positions)  # fmt: skip
    steps = {
        name: _roll_steps_deg(res, "lfoot")
        for name, res in (("construction", con), ("no hold", off), ("fit", fit))
    }
    print(
        f"\nheel slip to {np.nanmin(s.lever_mm):.1f} mm of the axis, noise "
        f"{noise_mm} mm: largest roll step "
        + ", ".join(f"{k} {v.max():.2f} deg" for k, v in steps.items())
    )
    # Without the hold the roll follows the heel round the axis: the case is real.
    assert steps["no hold"].max() > 3 * MAX_ROLL_STEP_DEG
    assert steps["construction"].max() <= MAX_ROLL_STEP_DEG
    assert steps["fit"].max() <= MAX_ROLL_STEP_DEG
    # Held exactly where the heel is within up_min_mm; flagged partial with every
    # defining marker seen (quality 1), never held.
    flags = con.bone_flags[:, foot]
    near = s.lever_mm < UP_MIN_MM
    partial = (flags & FLAG_PARTIAL) != 0
    assert s.rig.up_min_mm == UP_MIN_MM
    np.testing.assert_array_equal(partial, near)
    assert (con.bone_quality[:, foot] == 1.0).all()
    assert not (con.bone_flags & FLAG_HELD).any()
    # The aim keeps following the toe while the roll is held: +Y is the ankle->toe
    # direction of every frame.
    y_con = rot.quat_rotate(con.world_from_bone_quat[:, foot], np.array([0, 1.0, 0]))
    y_off = rot.quat_rotate(off.world_from_bone_quat[:, foot], np.array([0, 1.0, 0]))
    assert np.linalg.norm(np.cross(y_con, y_off), axis=-1).max() < 1e-9


def test_no_hold_on_a_clean_take() -> None:
    """The clean performer (heel 38-44 mm off the axis): no bone is ever flagged, so
    the hold changes nothing where the up references stand off their axes."""
    s = _slipped(0.0)
    con = BodySolver(s.rig, s.cal, s.take.labels).solve_take(s.take.markers_world)
    off = BodySolver(
        dataclasses.replace(s.rig, up_min_mm=0.0), s.cal, s.take.labels
    ).solve_take(s.take.markers_world)
    assert not con.bone_flags.any()
    np.testing.assert_array_equal(con.world_from_bone_quat, off.world_from_bone_quat)


def test_real_walk_foot_keeps_its_roll(datasets: Path) -> None:
    """The btkdata Plug-in Gait walk (the left heel 14-26 mm off the ankle->toe
    line): no foot turns about its axis by more than 5 deg between frames."""
    from retargetd.replay.takes import load_take

    rig = load_rig("plug-in-gait")
    static = load_take(datasets / "btkdata/PiG_Calibration-FlatFoot-Full.c3d")
    walk = load_take(datasets / "btkdata/PiG_Motion-FlatFoot-Full.c3d")
    cal = calibrate(
        rig, static.positions, static.labels, take_measurements=static.measurements
    )
    res = BodySolver(rig, cal, walk.labels).solve_take(walk.positions)
    worst = {bone: _roll_steps_deg(res, bone).max() for bone in ("lfoot", "rfoot")}
    print(f"\nPiG walk, construction: largest foot roll step {worst}")
    assert max(worst.values()) <= MAX_ROLL_STEP_DEG


def test_up_min_mm_key() -> None:
    text = """
[rig]
name = "t"
lateral = ["A", "B"]
up_min_mm = 20
[markers]
A = "A"
B = "B"
C = "C"
[bones.b]
origin = "A"
aim = "B"
up = "C"
"""
    assert parse_rig(text, source="t.toml").up_min_mm == 20.0
    assert parse_rig(text.replace("up_min_mm = 20\n", ""), source="t").up_min_mm == (
        UP_MIN_MM
    )
    for bad in ("-1", "101", "nan", '"x"'):
        with pytest.raises(RigError, match=r"t.toml: rig.up_min_mm: "):
            parse_rig(text.replace("= 20", f"= {bad}"), source="t.toml")
