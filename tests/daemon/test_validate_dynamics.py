"""Contact inference from the feet and the ghost force (``validate_dynamics``).

Clean takes (the synthetic walk on the exact rig, the PiG walk) stay below the
ghost-force threshold; the body floating 30 cm and a 30 cm teleport are flagged by it;
a performer standing still on a 40 cm platform is supported (stationary feet), not
floating.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from retargetd.daemon.body.calibration import calibrate
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.body.solve import BodySolve, BodySolver
from retargetd.daemon.validate import dynamics as vd
from retargetd.daemon.validate.checks import (
    THRESHOLDS,
    TakeReport,
    pose_skeleton,
    validate_take,
)
from retargetd.daemon.validate.model import (
    build_model,
    skeleton_from_calibration,
)

DATA = Path(__file__).resolve().parent.parent / "data"
RATE_HZ = 120.0


pytestmark = pytest.mark.usefixtures("mujoco_cwd")


@pytest.fixture
def clean(clean_synth: Any) -> Any:
    """The shared clean synthetic take (``tests/daemon/conftest.py``)."""
    return clean_synth


def _run(c: Any, solve: BodySolve) -> TakeReport:
    return validate_take(c.vm, solve, RATE_HZ, fit=c.fit)


def _shift(solve: BodySolve, offset: list[float], frames: slice) -> BodySolve:
    root, joints = solve.root_pos.copy(), solve.joint_centres.copy()
    root[frames] += offset
    joints[frames] += offset
    return dataclasses.replace(solve, root_pos=root, joint_centres=joints)


def _stats(values: np.ndarray) -> str:
    return (
        f"median {np.nanmedian(values):.3f} p95 {np.nanpercentile(values, 95):.3f} "
        f"max {np.nanmax(values):.3f} BW"
    )


def test_clean_walk_below_threshold(clean: Any) -> None:
    rep = _run(clean, clean.solve)
    ghost = rep.checks["ghost_force"]
    print(f"\nsynthetic walk ghost force: {_stats(ghost.values)}")
    assert ghost.n_flagged == 0
    assert np.nanmedian(ghost.values) < 0.1
    assert np.isnan(ghost.values[0]) and np.isnan(ghost.values[-1])  # ends trimmed
    assert rep.passed, rep.failed()


def test_floating_30cm_flagged_by_ghost_force(clean: Any) -> None:
    n = clean.solve.root_pos.shape[0]
    rep = _run(clean, _shift(clean.solve, [0.0, 0.0, 0.3], slice(0, n)))
    ghost = rep.checks["ghost_force"]
    assert {"ghost_force", "floating"} <= set(rep.failed())
    # Once the walk starts (feet moving in the air, none near the floor): ~1 BW.
    moving = ghost.values[int(1.5 * RATE_HZ) : -int(0.2 * RATE_HZ)]
    assert 0.7 < np.nanmedian(moving) < 1.3
    # The T-pose hold at the start (feet stationary) reads as standing on a riser.
    assert np.nanmax(ghost.values[: int(0.9 * RATE_HZ)]) < THRESHOLDS["ghost_force_bw"]


def test_teleport_30cm_flagged_by_ghost_force(clean: Any) -> None:
    rep = _run(clean, _shift(clean.solve, [0.3, 0.0, 0.0], slice(200, None)))
    ghost = rep.checks["ghost_force"]
    flagged = np.flatnonzero(ghost.flagged)
    assert flagged.size and abs(flagged.mean() - 200) < 0.1 * RATE_HZ
    assert flagged.min() > 200 - 0.2 * RATE_HZ and flagged.max() < 200 + 0.2 * RATE_HZ
    assert np.nanmax(ghost.values) > 3.0


def test_standing_still_on_platform_is_supported(clean: Any) -> None:
    """Feet stationary 40 cm above the floor for 2 s: a platform, not floating."""
    hold = np.zeros(int(2.0 * RATE_HZ), dtype=np.int64)  # the T-pose, frame 0
    s = clean.solve
    per_frame = {
        name: getattr(s, name)[hold]
        for name in (
            "joint_centres",
            "world_from_bone_quat",
            "rest_from_bone_quat",
            "root_pos",
            "bone_quality",
            "bone_flags",
        )
    }
    still = dataclasses.replace(s, **per_frame)
    rep = _run(clean, _shift(still, [0.0, 0.0, 0.4], slice(None)))
    assert rep.checks["floating"].n_flagged == 0
    assert rep.checks["ghost_force"].n_flagged == 0
    assert rep.passed, rep.failed()
    # The same pose with its feet jittering (not stationary) in the air floats.
    origins, aims = pose_skeleton(
        clean.vm.skeleton, still.root_pos, still.world_from_bone_quat
    )
    pts, _, _ = vd.foot_points(clean.vm.skeleton, origins, aims)
    pts[..., 2] += 0.4
    assert vd.infer_contacts(pts, clean.vm.floor_z, RATE_HZ).all()
    t = np.arange(pts.shape[0]) / RATE_HZ
    swing = pts.copy()
    swing[..., 0] += 0.1 * np.sin(2 * np.pi * 1.5 * t)[:, None]
    assert not vd.infer_contacts(swing, clean.vm.floor_z, RATE_HZ).any()


def test_infer_contacts_jump_apex_is_not_support() -> None:
    """A ballistic foot (0.4 s flight, 20 cm up) is never 'stationary'."""
    rate = 200.0
    t = np.arange(int(0.4 * rate)) / rate
    z = 0.2 + 1.96 * t - 0.5 * 9.81 * t**2
    pts = np.zeros((t.size, 1, 3))
    pts[:, 0, 2] = z
    contact = vd.infer_contacts(pts, 0.0, rate)
    assert not contact[(z > 0.15)].any()


def test_pig_walk_ghost_force(datasets: Path) -> None:
    from retargetd.replay.takes import load_take

    rig = load_rig("plug-in-gait")
    static = load_take(datasets / "btkdata/PiG_Calibration-FlatFoot-Full.c3d")
    cal = calibrate(
        rig, static.positions, static.labels, take_measurements=static.measurements
    )
    walk = load_take(datasets / "btkdata/PiG_Motion-FlatFoot-Full.c3d")
    solve = BodySolver(rig, cal, walk.labels).solve_take(walk.positions)
    vm = build_model(
        skeleton_from_calibration(rig, cal), static.measurements.get("Bodymass", 70.0)
    )
    skel = vm.skeleton
    origins, aims = pose_skeleton(skel, solve.root_pos, solve.world_from_bone_quat)
    pts, _, _ = vd.foot_points(skel, origins, aims)
    contacts = vd.infer_contacts(pts, vm.floor_z, walk.rate_hz)
    root = skel.bone_parents.index(-1)
    gf = vd.ghost_force(
        vm,
        solve.root_pos,
        solve.world_from_bone_quat[:, root],
        solve.rest_from_bone_quat,
        walk.rate_hz,
        contacts,
    )
    print(
        f"\nPiG walk ghost force: {_stats(gf.ghost_bw)}, "
        f"{1e6 * gf.seconds_per_frame:.0f} us/frame"
    )
    assert np.nanmedian(gf.ghost_bw) < 0.05 and np.nanpercentile(gf.ghost_bw, 95) < 0.1
    assert np.nanmax(gf.ghost_bw) < THRESHOLDS["ghost_force_bw"]
    assert np.nanmedian(gf.root_force_bw) > 0.8  # gravity is there to be explained
