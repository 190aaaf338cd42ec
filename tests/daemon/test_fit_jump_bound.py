"""The fit's jump bound (``fit_track.jump_bound``, ``FitParams.omega_max`` and
``omega_root``) against the fastest real motion we have: the bound was chosen from the
literature (a pitcher's arm and trunk, a dancer's pirouette), these takes confirm it.
A segment held across a gap of one frame may have turned by its peak speed x dt: the
tightest case, where a real fast motion comes closest to being called impossible."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from retargetd.daemon.body.calibration import calibrate
from retargetd.daemon.body.method import make_body_solver
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.body.solve_fit import FitParams
from retargetd.daemon.synth import performer as pf
from retargetd.daemon.validate.limits import JOINT_LIMITS_DEG
from retargetd.daemon.validate.model import SEGMENT_KIND
from retargetd.replay.takes import load_take

TENNIS = "kineticstoolkit/kinematics_tennis_serve.c3d"
#: (static, its rows, take): the serve calibrates on its own first 50 frames, the
#: MOTEK ballet on MOTEK_T (as tests/daemon/test_validate_takes.py does)
TAKES = {
    "tennis-serve": (TENNIS, slice(0, 50), TENNIS),
    "motek-ballet": (
        "btkdata/MOTEK_T.trc",
        slice(None),
        "btkdata/MOTEK_ballet_reduced.trc",
    ),
}


@pytest.mark.parametrize("case", sorted(TAKES))
def test_real_fast_motion_is_within_the_bound(datasets: Path, case: str) -> None:
    """Every frame of the serve (50 Hz; the serving arm's shoulder 112.6 deg in one
    frame, 0.80 of a joint's 7000 deg/s x dt) and of the ballet (30 Hz; the pelvis 25.0
    deg in one frame in a turn, 0.70 of the root's 3 rev/s x dt) is explained, and no
    bone turns between two frames by more than its peak speed allows."""
    static_path, rows, take_path = TAKES[case]
    rig = load_rig("cmu41")
    static = load_take(datasets / static_path)
    cal = calibrate(
        rig, static.positions[rows], static.labels,
        take_measurements=static.measurements,
    )  # fmt: skip
    take = load_take(datasets / take_path)
    solver = make_body_solver(
        "fit", rig, cal, take.labels, joint_limits=JOINT_LIMITS_DEG,
        segment_kind=SEGMENT_KIND, rate_hz=take.rate_hz,
    )  # fmt: skip
    solve = solver.solve_take(take.positions)
    assert not np.asarray(solve.unexplained).any()
    q = np.asarray(solve.parent_from_bone_quat)
    dot = np.clip(np.abs(np.sum(q[1:] * q[:-1], axis=-1)), 0.0, 1.0)
    step = 2.0 * np.arccos(dot)  # (T - 1, B) rad, each bone's turn in one frame
    root = np.asarray(solver.model.bone_parent) < 0
    p = FitParams()
    floor = math.radians(p.jump_floor_deg)
    dt = 1.0 / take.rate_hz
    ratio_root = step[:, root].max() / max(p.omega_root * dt, floor)
    ratio_joint = step[:, ~root].max() / max(p.omega_max * dt, floor)
    print(f"{case}: root {ratio_root:.2f}, joints {ratio_joint:.2f} of the bound")
    assert ratio_root < 1.0
    assert ratio_joint < 1.0


def test_a_runner_after_a_dropout_is_not_impossible() -> None:
    """The synthetic performer running (``run``: the root ~32 mm a frame at 120 Hz,
    3.8 m/s) with every marker gone for one frame, 16 times: the frame after each gap
    is explained. Before, the root's position held across the gap was bounded by the
    peak acceleration alone (max(3 x 1/2 100 m/s^2 h^2, 40 mm): 42 mm after 2
    frames), and 12 of the 16 frames after a gap were unexplained (the root ~64 mm on
    in those 2 frames; the rotations' bounds are tighter now, so the position's is
    what let them in); a root's speed bound (12.3 m/s, a sprint:
    ``FitParams.speed_max``) allows 205 mm."""
    take = pf.synthesize(
        seconds=6.0, rate_hz=120.0, markerset="menache", motions=("run",), seed=0,
        noise_mm=1.0,
    )  # fmt: skip
    rig = load_rig("menache")
    cal = calibrate(rig, take.markers_world[take.base_pose_frames], take.labels)
    markers = take.markers_world.copy()
    gaps = list(range(240, 700, 30))
    markers[gaps] = np.nan
    solver = make_body_solver(
        "fit", rig, cal, take.labels, joint_limits=JOINT_LIMITS_DEG,
        segment_kind=SEGMENT_KIND, rate_hz=120.0,
    )  # fmt: skip
    solve = solver.solve_take(markers)
    step = np.linalg.norm(np.diff(np.asarray(solve.root_pos), axis=0), axis=1)
    assert np.nanmax(step) > 0.025  # the run is fast enough to have failed before
    assert np.asarray(solve.unseen)[gaps].all()
    assert not np.asarray(solve.unexplained).any()
