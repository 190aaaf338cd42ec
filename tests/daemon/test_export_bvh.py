"""``retargetd solve ... --out take.bvh``: the BVH holds our skeleton and motion.

The file is read back with our reader and posed with an independent forward
kinematics (scipy): every joint must land on the calibrated skeleton posed by the solved
rotations (within 0.1 mm) and every bone must point where the solve says (0.01 deg),
on every frame of a synthetic take and of the Plug-in Gait walk.
"""

from __future__ import annotations

import functools
import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.calibration import Calibration, calibrate, load_calibration
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.body.solve import BodySolve, BodySolver
from retargetd.daemon.cli.main import main
from retargetd.daemon.retarget.bvh import (
    BVH_CM_PER_M,
    BVH_FROM_WORLD,
    posed_bone_origins,
    write_solve_bvh,
)
from retargetd.replay.bvh import BvhSkeleton, read_bvh_hierarchy, split_bvh_motion
from retargetd.replay.takes import load_take

STATIC = "btkdata/PiG_Calibration-FlatFoot-Full.c3d"
WALK = "btkdata/PiG_Motion-FlatFoot-Full.c3d"


def bvh_forward_kinematics(sk: BvhSkeleton) -> tuple[Rotation, np.ndarray]:
    """BVH FK: global = parent global * R_1 R_2 R_3 (listed order, scipy upper
    case); position = parent position + parent global * OFFSET; the root's position
    channels are its absolute position (its OFFSET must then be 0).

    Returns:
        (T, J) global rotations as one flat Rotation of T*J, and (T, J, 3) positions,
        the file's unit and axes.
    """
    assert sk.frames is not None
    angles, positions = split_bvh_motion(sk, sk.frames)
    n_frames, n = angles.shape[:2]
    glob: list[Rotation] = []
    pos = np.zeros((n_frames, n, 3))
    for j, p in enumerate(sk.parents):
        local = Rotation.from_euler(sk.rotation_orders[j], angles[:, j], degrees=True)
        if p < 0:
            np.testing.assert_array_equal(sk.offsets[j], 0.0)
            glob.append(local)
            pos[:, j] = positions[:, j]
        else:
            glob.append(glob[p] * local)
            pos[:, j] = pos[:, p] + glob[p].apply(np.array(sk.offsets[j]))
    flat = Rotation.concatenate(glob)  # joint-major
    quats = flat.as_quat(scalar_first=True).reshape(n, n_frames, 4).swapaxes(0, 1)
    return Rotation.from_quat(quats.reshape(-1, 4), scalar_first=True), pos


def check_bvh_against_solve(
    path: Path, cal: Calibration, res: BodySolve, orders: tuple[str, str] = ("ZXY",) * 2
) -> dict[str, float]:
    """Assert the file reproduces the solve; returns the worst errors."""
    sk = read_bvh_hierarchy(path, read_motion=True)
    assert sk.rotation_orders[0] == orders[0]
    assert set(sk.rotation_orders[1:]) == {orders[1]}
    assert sk.channels[0][:3] == ("Xposition", "Yposition", "Zposition")
    n_frames, n_bones = res.world_from_bone_quat.shape[:2]
    assert sk.n_frames == n_frames
    perm = [cal.bone_names.index(n) for n in sk.joint_names]
    assert sorted(perm) == list(range(n_bones))
    glob, pos_cm = bvh_forward_kinematics(sk)
    # Positions: back to world metres, against the posed calibrated skeleton.
    pos_world = pos_cm @ BVH_FROM_WORLD / BVH_CM_PER_M
    expected = posed_bone_origins(cal, res.world_from_bone_quat, res.root_pos)
    pos_err_mm = 1000 * np.linalg.norm(pos_world - expected[:, perm], axis=-1).max()
    np.testing.assert_allclose(expected[:, 0], res.root_pos, atol=0)
    # Bone frames: G_j * (M rest_j) must be M world_from_bone_j(t) (+Y = direction).
    m = Rotation.from_matrix(BVH_FROM_WORLD)
    rest = Rotation.from_quat(cal.rest_world_from_bone_quat[perm], scalar_first=True)
    ours = Rotation.from_quat(
        res.world_from_bone_quat[:, perm].reshape(-1, 4), scalar_first=True
    )
    rest_tiled = Rotation.concatenate([rest] * n_frames)
    in_file = glob * m * rest_tiled
    dirs_file = in_file.apply([0.0, 1.0, 0.0])
    dirs_ours = (m * ours).apply([0.0, 1.0, 0.0])
    cos = np.clip(np.sum(dirs_file * dirs_ours, axis=-1), -1.0, 1.0)
    dir_err_deg = float(np.degrees(np.arccos(cos)).max())
    frame_err_deg = float(np.degrees((in_file * (m * ours).inv()).magnitude()).max())
    assert pos_err_mm < 0.1, pos_err_mm
    assert dir_err_deg < 0.01, dir_err_deg
    assert frame_err_deg < 0.01, frame_err_deg
    return {"pos_mm": pos_err_mm, "dir_deg": dir_err_deg}


@pytest.fixture(scope="module")
def synth(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("synth")
    take, cal = folder / "s.c3d", folder / "cal.json"
    assert main(["synth", "--seconds", "3", "--rate", "60", "--out", str(take)]) == 0
    args = ["calibrate", str(take), "--rig", "menache", "--frames", "0:60"]
    assert main([*args, "--out", str(cal)]) == 0
    return take, cal


def _solve_api(take_path: Path, cal: Calibration, rig_name: str) -> BodySolve:
    take = load_take(take_path)
    return BodySolver(load_rig(rig_name), cal, take.labels).solve_take(take.positions)


@pytest.mark.parametrize("orders", [("ZXY", "ZXY"), ("XYZ", "YZX"), ("ZYX", "XZY")])
def test_synthetic_take_round_trip(
    synth: tuple[Path, Path], tmp_path: Path, orders: tuple[str, str]
) -> None:
    take, cal_path = synth
    out = tmp_path / "s.bvh"
    args = ["solve", str(take), "--rig", "menache", "--method", "construction"]
    args += ["--calibration", str(cal_path)]
    if orders != ("ZXY", "ZXY"):
        args += ["--bvh-root-order", orders[0], "--bvh-order", orders[1].lower()]
    assert main([*args, "--out", str(out)]) == 0
    cal = load_calibration(cal_path)
    res = _solve_api(take, cal, "menache")
    check_bvh_against_solve(out, cal, res, orders)


def test_hierarchy_is_the_calibrated_skeleton(
    synth: tuple[Path, Path], tmp_path: Path
) -> None:
    take, cal_path = synth
    cal = load_calibration(cal_path)
    assert cal.rest_bone_origin_pos is not None
    res = _solve_api(take, cal, "menache")
    sk = write_solve_bvh(tmp_path / "s.bvh", cal, res, 60.0)
    back = read_bvh_hierarchy(tmp_path / "s.bvh")
    # Depth first in the file (menache's rig order is depth first since its radius
    # hangs from the ulna, so the file keeps it; a rig that is not keeps its order
    # within each depth-first walk).
    perm = [cal.bone_names.index(n) for n in back.joint_names]
    assert sorted(perm) == list(range(len(perm)))
    assert [cal.bone_parents[j] for j in perm] == [
        -1 if p < 0 else perm[p] for p in back.parents
    ]
    # Rest positions (sums of offsets) = calibrated origins, root at the file origin.
    rest = (cal.rest_bone_origin_pos - cal.root_rest_pos) @ BVH_FROM_WORLD.T * 100
    np.testing.assert_allclose(back.rest_positions(), rest[perm], atol=1e-5)
    leaves = [k for k, j in enumerate(perm) if j not in cal.bone_parents]
    assert np.isfinite(back.end_sites[leaves]).all()
    assert np.isnan(np.delete(back.end_sites, leaves, axis=0)).all()
    for k in leaves:  # End Site length = bone length (cm)
        length = np.linalg.norm(back.end_sites[k]) / 100
        assert length == pytest.approx(cal.bone_lengths[perm[k]], abs=1e-7)
    # Y up: the head is above the pelvis in the rest pose, by world Z.
    head = cal.bone_names.index("head")
    assert rest[head, 1] > 40.0
    assert sk.joint_names == cal.bone_names
    # In the calibration hold the posed skeleton is the rest skeleton.
    posed = posed_bone_origins(cal, res.world_from_bone_quat[:60], res.root_pos[:60])
    assert np.abs(posed - cal.rest_bone_origin_pos).max() < 1e-3


@functools.cache
def _pig(root: Path) -> tuple[Calibration, BodySolve, float]:
    rig = load_rig("plug-in-gait")
    static = load_take(root / STATIC)
    cal = calibrate(
        rig, static.positions, static.labels, take_measurements=static.measurements
    )
    walk = load_take(root / WALK)
    res = BodySolver(rig, cal, walk.labels).solve_take(walk.positions)
    return cal, res, walk.rate_hz


def test_pig_walk_round_trip(datasets: Path, tmp_path: Path) -> None:
    cal, res, rate = _pig(datasets)
    path = tmp_path / "walk.bvh"
    write_solve_bvh(path, cal, res, rate)
    errors = check_bvh_against_solve(path, cal, res)
    assert errors["pos_mm"] < 0.1
    # The rigid skeleton against the marker-derived joint centres: bone lengths are
    # fixed in a BVH, so they differ by the segments' length changes (a few mm).
    sk = read_bvh_hierarchy(path)
    assert sk.joint_names[0] == "pelvis" and len(sk.joint_names) == 19
    rig = load_rig("plug-in-gait")
    posed = posed_bone_origins(cal, res.world_from_bone_quat, res.root_pos)
    point_to_joint = {p: j for j, p in rig.joints.items()}
    gaps = []
    for b, bone in enumerate(rig.bones):
        joint = point_to_joint.get(bone.origin)
        if joint is not None:
            centre = res.joint_centres[:, res.joint_names.index(joint)]
            gaps.append(np.linalg.norm(posed[:, b] - centre, axis=-1))
    gap_mm = 1000 * np.concatenate(gaps)
    assert np.nanmedian(gap_mm) < 15.0


def test_usage_errors(
    synth: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    take, cal_path = synth
    base = ["solve", str(take), "--rig", "menache", "--calibration", str(cal_path)]
    cases = [
        (["--out", str(tmp_path / "x.fbx")], ".npz, .bvh, .csv, .glb or .mcap"),
        (["--out", str(tmp_path / "x.bvh"), "--bvh-order", "ZXZ"], "--bvh-order: "),
        (["--out", str(tmp_path / "x.npz"), "--bvh-order", "ZXY"], "applies to .bvh"),
    ]
    for extra, message in cases:
        assert main([*base, *extra]) == 2
        assert message in capsys.readouterr().err
    # A calibration file from before bone rest origins: recalibrate.
    doc = json.loads(cal_path.read_text())
    for bone in doc["bones"].values():
        del bone["rest_origin_m"]
    old = tmp_path / "old.json"
    old.write_text(json.dumps(doc))
    assert load_calibration(old).rest_bone_origin_pos is None
    args = ["solve", str(take), "--rig", "menache", "--calibration", str(old)]
    assert main([*args, "--out", str(tmp_path / "x.bvh")]) == 2
    # the fit (the default) needs the rest origins to solve at all
    assert "no bone rest origins" in capsys.readouterr().err
    assert (
        main([*args, "--method", "construction", "--out", str(tmp_path / "x.bvh")]) == 2
    )
    assert "recalibrate to export BVH" in capsys.readouterr().err
    assert not (tmp_path / "x.bvh").exists()


def test_calibration_keeps_rest_origins(synth: tuple[Path, Path]) -> None:
    cal = load_calibration(synth[1])
    assert cal.rest_bone_origin_pos is not None
    np.testing.assert_allclose(cal.rest_bone_origin_pos[0], cal.root_rest_pos)
    # A child whose origin is its parent's aim sits at the parent's tip.
    lumbar = cal.bone_names.index("lumbar")
    tip = cal.rest_bone_origin_pos[0] + rot.quat_rotate(
        cal.rest_world_from_bone_quat[0], np.array([0.0, cal.bone_lengths[0], 0.0])
    )
    np.testing.assert_allclose(cal.rest_bone_origin_pos[lumbar], tip, atol=2e-3)
