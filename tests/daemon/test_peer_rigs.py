"""The rigs written for the peers' marker sets (``bioptim-wholebody``,
``opensim-gait2354``) on the peers' own takes: every marker matched, every bone built in
every frame, and the calibrated points where their definitions put them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from retargetd.daemon.body.calibration import calibrate
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.body.solve import FLAG_HELD, BodySolver
from retargetd.replay.takes import load_take

BIOPTIM = "peers/bioptim_gait_wholebody.c3d"
WALK = "peers/subject01_walk1.trc"
STATIC = "opensim-core/subject01_static.trc"
#: Standing still, a marker held in a rigid cluster's frame stays within a couple of
#: millimetres of itself (postural sway moves the cluster with the leg; skin motion of
#: a quiet stance is ~1 mm): 3 mm leaves room for marker noise (~1 mm, optical).
STATIC_HOLD_M = 0.003


def _col(labels: tuple[str, ...], name: str) -> int:
    return labels.index(name)


def test_bioptim_rig_on_the_gait(datasets: Path) -> None:
    rig = load_rig("bioptim-wholebody")
    take = load_take(datasets / BIOPTIM)
    cal = calibrate(rig, take.positions[:10], take.labels)
    solver = BodySolver(rig, cal, take.labels)
    assert solver.missing_markers == ()
    res = solver.solve_take(take.positions)
    assert not ((res.bone_flags & FLAG_HELD) != 0).any()
    joints = dict(
        zip(res.joint_names, np.moveaxis(res.joint_centres, 1, 0), strict=True)
    )
    pos = take.positions
    for side in "RL":
        # The knee centre is the epicondyles' midpoint, frame by frame.
        mid = 0.5 * (
            pos[:, _col(take.labels, f"{side}LFE")]
            + pos[:, _col(take.labels, f"{side}MFE")]
        )
        np.testing.assert_allclose(joints[f"{side}KJC"], mid, atol=1e-9)
        # Harrington's hip lies below the ASIS and inside the pelvis width.
        asis = pos[:, _col(take.labels, f"{side}ASIS")]
        assert (joints[f"{side}HJC"][:, 2] < asis[:, 2]).all()
    width = np.linalg.norm(joints["LHJC"] - joints["RHJC"], axis=-1)
    pelvis = np.linalg.norm(
        pos[:, _col(take.labels, "LASIS")] - pos[:, _col(take.labels, "RASIS")], axis=-1
    )
    # Harrington places each hip 0.33 PW + 7.3 mm lateral of the ASIS midpoint: the
    # hips are closer together than the ASIS.
    assert (width < pelvis).all()


def test_opensim_rig_static_then_walk(datasets: Path) -> None:
    rig = load_rig("opensim-gait2354")
    static = load_take(datasets / STATIC)
    cal = calibrate(rig, static.positions, static.labels)
    # In the static trial, the knee and ankle centres held in the clusters' frames are
    # the epicondyle and malleolus midpoints they were calibrated from.
    res = BodySolver(rig, cal, static.labels).solve_take(static.positions)
    joints = dict(
        zip(res.joint_names, np.moveaxis(res.joint_centres, 1, 0), strict=True)
    )
    for side in "RL":
        for joint, marker in (("KJC", "Knee"), ("AJC", "Ankle")):
            mid = 0.5 * (
                static.positions[:, _col(static.labels, f"{side}.{marker}.Lat")]
                + static.positions[:, _col(static.labels, f"{side}.{marker}.Med")]
            )
            d = np.linalg.norm(joints[f"{side}{joint}"] - mid, axis=-1)
            assert np.median(d) < STATIC_HOLD_M, (side, joint, np.median(d))
    # The walk lacks those eight markers; every bone is still built in every frame.
    walk = load_take(datasets / WALK)
    solver = BodySolver(rig, cal, walk.labels)
    assert len(solver.missing_markers) == 8
    res = solver.solve_take(walk.positions)
    assert not ((res.bone_flags & FLAG_HELD) != 0).any()
    assert np.isfinite(res.joint_centres).all()


@pytest.mark.parametrize("name", ["bioptim-wholebody", "opensim-gait2354"])
def test_peer_rigs_are_shipped(name: str) -> None:
    from retargetd.daemon.body.rig import shipped_rigs

    assert name in shipped_rigs()
    assert load_rig(name).name == name
