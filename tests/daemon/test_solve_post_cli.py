"""``retargetd solve`` with the post stages and the new outputs: ``--pipeline``
(the live stage objects run offline), ``--out take.csv --euler-order ORDER
--degrees`` (checked against scipy's own Euler composition), ``--out take.glb``
(read back with pygltflib) and the BVH order messages."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pygltflib
import pytest
from scipy.spatial.transform import Rotation

from retargetd.daemon import rotations as rot
from retargetd.daemon.cli.main import main


@pytest.fixture(scope="module")
def pig_synth(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A synthetic Plug-in Gait take (1 s static hold, then all motions, forearm
    twist included) and its calibration."""
    d = tmp_path_factory.mktemp("pig")
    take, cal = d / "s.c3d", d / "cal.json"
    assert main(["synth", "--markers", "plug-in-gait", "--seconds", "3", "--rate",
                 "100", "--base-pose-s", "1", "--out", str(take)]) == 0  # fmt: skip
    args = ["calibrate", str(take), "--rig", "plug-in-gait", "--frames", "0:100"]
    assert main([*args, "--out", str(cal)]) == 0
    return take, cal


def _solve(take_cal: tuple[Path, Path], out: Path, *extra: str) -> None:
    take, cal = take_cal
    args = ["solve", str(take), "--rig", "plug-in-gait", "--calibration", str(cal)]
    assert main([*args, "--out", str(out), *extra]) == 0


@pytest.fixture(scope="module")
def plain(
    pig_synth: tuple[Path, Path], tmp_path_factory: pytest.TempPathFactory
) -> Path:
    out = tmp_path_factory.mktemp("plain") / "plain.npz"
    _solve(pig_synth, out)
    return out


@pytest.mark.parametrize("order", ["YXZ", "zxz", "XYX", "xzy"])
def test_csv_euler_channels_rebuild_the_solve(
    pig_synth: tuple[Path, Path], plain: Path, tmp_path: Path, order: str
) -> None:
    out = tmp_path / "take.csv"
    _solve(pig_synth, out, "--euler-order", order, "--degrees")
    with open(out, newline="") as fh:
        rows = list(csv.reader(fh))
    header, data = rows[0], np.array(rows[1:], dtype=np.float64)
    with np.load(plain, allow_pickle=False) as npz:
        names = [str(n) for n in npz["bone_names"]]
        q = npz["parent_from_bone_quat"]
        root = npz["root_pos"]
    assert header[:5] == ["frame", "time_s", "root_x_m", "root_y_m", "root_z_m"]
    letters = order.upper()
    assert header[5:8] == [f"{names[0]}_{k + 1}{letters[k]}_deg" for k in range(3)]
    assert len(header) == 5 + 3 * len(names) and len(data) == len(q)
    np.testing.assert_allclose(data[:, 1], np.arange(len(q)) / 100.0, atol=1e-9)
    np.testing.assert_allclose(data[:, 2:5], root, atol=1e-8)
    angles = data[:, 5:].reshape(len(q), len(names), 3)
    # scipy composes the order independently of our rotations module.
    back = Rotation.from_euler(order, angles.reshape(-1, 3), degrees=True).as_quat(
        scalar_first=True
    )
    err = rot.quat_angle(rot.quat_mul(rot.quat_conj(q.reshape(-1, 4)), back))
    assert np.degrees(err).max() < 1e-5
    if len(set(letters)) == 3:
        # Tait-Bryan, unwrapped: no channel jumps away from gimbal lock (middle
        # angle ±90°; proper Euler orders are singular at rest, where the first and
        # third angles are only defined as a sum).
        clear = np.abs(angles[..., 1]) < 80.0
        clear = clear[1:] & clear[:-1]
        jumps = np.abs(np.diff(angles, axis=0)).max(axis=-1)
        assert clear.mean() > 0.5 and jumps[clear].max() < 30.0


def test_pipeline_twist_offline_keeps_hands_and_moves_twist(
    pig_synth: tuple[Path, Path], plain: Path, tmp_path: Path
) -> None:
    pipe = tmp_path / "pipe.toml"
    pipe.write_text('[[pipeline]]\nkind = "twist"\n')
    out = tmp_path / "twist.npz"
    _solve(pig_synth, out, "--pipeline", str(pipe))
    with np.load(plain) as a, np.load(out) as b:
        names = [str(n) for n in a["bone_names"]]
        for hand in ("lhand", "rhand"):
            j = names.index(hand)
            d = rot.quat_angle(
                rot.quat_mul(
                    rot.quat_conj(a["world_from_bone_quat"][:, j]),
                    b["world_from_bone_quat"][:, j],
                )
            )
            assert d.max() < 1e-9
        up = names.index("lupperarm")
        moved = rot.quat_angle(
            rot.quat_mul(
                rot.quat_conj(a["parent_from_bone_quat"][:, up]),
                b["parent_from_bone_quat"][:, up],
            )
        )
        # The forearm twist is shared up the arm: the upper arm turns.
        assert np.degrees(moved).max() > 5.0
        # The world rotation is consistent with the processed parent-relative one.
        wfb = b["world_from_bone_quat"]
        p = int(b["bone_parents"][up])
        chk = rot.quat_mul(wfb[:, p], b["parent_from_bone_quat"][:, up])
        assert rot.quat_angle(rot.quat_mul(rot.quat_conj(chk), wfb[:, up])).max() < 1e-9


def test_pipeline_errors_name_the_entry(
    pig_synth: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    take, cal = pig_synth
    base = ["solve", str(take), "--rig", "plug-in-gait", "--calibration", str(cal),
            "--out", str(tmp_path / "x.npz"), "--pipeline"]  # fmt: skip
    bad = tmp_path / "bad.toml"
    bad.write_text('[[pipeline]]\nkind = "twist"\n[[pipeline]]\nkind = "blur"\n')
    assert main([*base, str(bad)]) == 2
    assert "pipeline[1]: kind must be one of" in capsys.readouterr().err
    bad.write_text('[[pipeline]]\nkind = "one_euro"\nbeta = 1\n')
    assert main([*base, str(bad)]) == 2
    assert "unknown keys ['beta']" in capsys.readouterr().err
    assert not (tmp_path / "x.npz").exists()


def test_glb_holds_every_frame(
    pig_synth: tuple[Path, Path], plain: Path, tmp_path: Path
) -> None:
    out = tmp_path / "take.glb"
    _solve(pig_synth, out)
    gltf = pygltflib.GLTF2().load(str(out))
    blob = gltf.binary_blob()
    with np.load(plain) as npz:
        q = npz["parent_from_bone_quat"]
        names = [str(n) for n in npz["bone_names"]]
        humanoid = [str(h) for h in npz["bone_humanoid"]]
    # Each bone's node is named by its humanoid name (the rig's where it has none);
    # the node's extras keep the rig's name.
    node_names = [h or n for n, h in zip(names, humanoid, strict=True)]
    assert [n.name for n in gltf.nodes[: len(names)]] == node_names
    node_of = {n.extras["rig_bone"]: i for i, n in enumerate(gltf.nodes) if n.extras}
    anim = gltf.animations[0]
    checked = 0
    for ch in anim.channels:
        if ch.target.path != "rotation":
            continue
        sampler = anim.samplers[ch.sampler]
        assert sampler.interpolation == "LINEAR"
        acc = gltf.accessors[sampler.output]
        view = gltf.bufferViews[acc.bufferView]
        start = view.byteOffset + (acc.byteOffset or 0)
        vals = np.frombuffer(blob, np.float32, acc.count * 4, start).reshape(-1, 4)
        assert acc.count == len(q)
        b = node_names.index(gltf.nodes[ch.target.node].name)
        assert node_of[names[b]] == ch.target.node
        wxyz = vals[:, [3, 0, 1, 2]].astype(np.float64)
        err = rot.quat_angle(rot.quat_mul(rot.quat_conj(q[:, b]), wxyz))
        assert np.degrees(err).max() < 1e-3  # float32 storage
        checked += 1
    assert checked == len(names)


def test_order_options_say_what_they_accept(
    pig_synth: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    take, cal = pig_synth
    base = ["solve", str(take), "--rig", "plug-in-gait", "--calibration", str(cal)]
    cases = [
        (["--out", str(tmp_path / "x.bvh"), "--bvh-order", "ZXZ"],
         "BVH can express only the 6 Tait-Bryan channel orders"),
        (["--out", str(tmp_path / "x.bvh"), "--bvh-root-order", "YXY"],
         "--bvh-root-order: BVH can express only"),
        (["--out", str(tmp_path / "x.csv"), "--euler-order", "ZZX"],
         "--euler-order: order must be 3 letters"),
        (["--out", str(tmp_path / "x.npz"), "--euler-order", "ZXY"],
         "--euler-order applies to .csv"),
        (["--out", str(tmp_path / "x.glb"), "--degrees"], "--degrees applies to .csv"),
        (["--out", str(tmp_path / "x.fbx")],
         "expected a .npz, .bvh, .csv, .glb or .mcap"),
    ]  # fmt: skip
    for extra, message in cases:
        assert main([*base, *extra]) == 2
        assert message in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def test_pipeline_one_euro_offline_smooths_a_noisy_take(tmp_path: Path) -> None:
    take, cal = tmp_path / "n.c3d", tmp_path / "cal.json"
    assert main(["synth", "--markers", "plug-in-gait", "--motions", "walk",
                 "--seconds", "3", "--rate", "100", "--base-pose-s", "1",
                 "--noise-mm", "2", "--seed", "4",
                 "--out", str(take)]) == 0  # fmt: skip
    args = ["calibrate", str(take), "--rig", "plug-in-gait", "--frames", "0:100"]
    assert main([*args, "--out", str(cal)]) == 0
    pipe = tmp_path / "pipe.toml"
    pipe.write_text(
        '[[pipeline]]\nkind = "one_euro"\nmin_cutoff_hz = 1.0\nbeta_rot = 0.5\n'
        "beta_pos = 5.0\n"
    )
    raw, smooth = tmp_path / "raw.npz", tmp_path / "smooth.npz"
    _solve((take, cal), raw)
    _solve((take, cal), smooth, "--pipeline", str(pipe))

    def jitter_deg(path: Path) -> float:
        with np.load(path) as z:
            q = z["world_from_bone_quat"][100:]
        # Rotation between consecutive frames, then its change: noise dominates.
        step = rot.quat_mul(rot.quat_conj(q[:-1]), q[1:])
        return float(np.degrees(rot.quat_angle(
            rot.quat_mul(rot.quat_conj(step[:-1]), step[1:])
        )).mean())  # fmt: skip

    assert jitter_deg(smooth) < 0.7 * jitter_deg(raw)


def test_fill_gaps_slerps_short_held_runs(
    pig_synth: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``solve --fill-gaps N`` (issue 15 item 6): a take with occlusion runs, solved
    with the clean take's calibration; every run of <= N held frames between solved
    frames becomes the slerp across it, everything else is the plain solve's."""
    _take, cal = pig_synth
    drop = tmp_path / "drop.c3d"
    assert main(["synth", "--markers", "plug-in-gait", "--seconds", "3", "--rate",
                 "100", "--base-pose-s", "1", "--dropout", "0.1", "--seed", "3",
                 "--out", str(drop)]) == 0  # fmt: skip
    plain, filled = tmp_path / "plain.npz", tmp_path / "filled.npz"
    _solve((drop, cal), plain)
    capsys.readouterr()
    _solve((drop, cal), filled, "--fill-gaps", "8")
    text = capsys.readouterr().out
    with np.load(plain) as a, np.load(filled) as b:
        q0, q1 = a["parent_from_bone_quat"], b["parent_from_bone_quat"]
        held = (a["bone_flags"] & 1) != 0  # FLAG_HELD
        np.testing.assert_array_equal(a["bone_flags"], b["bone_flags"])
        parents = a["bone_parents"]
        wfb = b["world_from_bone_quat"]
    n = len(q0)
    expect = q0.copy()
    runs = count = 0
    for bone in range(q0.shape[1]):
        edges = np.diff(np.concatenate([[0], held[:, bone].astype(int), [0]]))
        for start, stop in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1),
                               strict=True):  # fmt: skip
            if start == 0 or stop == n or stop - start > 8:
                continue
            u = (np.arange(start, stop) - (start - 1)) / (stop - start + 1)
            expect[start:stop, bone] = rot.slerp(q0[start - 1, bone], q0[stop, bone], u)
            runs += 1
            count += stop - start
    assert runs >= 5, runs
    assert f"gaps filled (<= 8 held frames): {count} bone-frames" in text, text
    np.testing.assert_allclose(q1, expect, atol=1e-12)
    # world_from_bone follows: forward kinematics of the filled rotations.
    for bone, p in enumerate(parents):
        if p >= 0:
            fk = rot.quat_mul(wfb[:, p], q1[:, bone])
            dot = np.abs(np.sum(fk * wfb[:, bone], axis=-1))
            assert (dot > 1.0 - 1e-9).all()
    assert main(["solve", "x.c3d", "--rig", "plug-in-gait", "--calibration",
                 str(cal), "--out", str(tmp_path / "x.npz"), "--fill-gaps",
                 "0"]) == 2  # fmt: skip
    assert "--fill-gaps: expected >= 1" in capsys.readouterr().err


def test_pipeline_target_spine_pivot_offline(
    pig_synth: tuple[Path, Path], plain: Path, tmp_path: Path
) -> None:
    """``solve --pipeline FILE.toml`` with ``[target] spine = "pivot"``: the NPZ gains
    the take mapped onto the humanoid with the shifting pivot on Spine, Chest and
    UpperChest (``target_*``); the other bones are the plain mapping's. Other
    formats are refused before solving (exit 2, one line)."""
    from retargetd.daemon.body.calibration import load_calibration
    from retargetd.daemon.body.rig import load_rig
    from retargetd.daemon.cli.post_io import retarget_solve
    from retargetd.daemon.live.config_schema import TargetConfig

    toml = tmp_path / "spine.toml"
    toml.write_text('[target]\nspine = "pivot"\nspine_pivot_limit_deg = 10.0\n')
    out = tmp_path / "pivot.npz"
    _solve(pig_synth, out, "--pipeline", str(toml))
    with np.load(out, allow_pickle=False) as npz:
        names = [str(n) for n in npz["target_bone_names"]]
        rfb = npz["target_rest_from_bone_quat"]
        assert str(npz["target_spine"]) == "pivot"
        assert rfb.shape == (len(npz["root_pos"]), len(names), 4)
        processed = npz["parent_from_bone_quat"]
    with np.load(plain, allow_pickle=False) as npz:
        np.testing.assert_array_equal(processed, npz["parent_from_bone_quat"])
    # Against the mapping without the pivot: the spine differs, the limbs do not.
    rig, cal = load_rig("plug-in-gait"), load_calibration(pig_synth[1])
    with np.load(plain, allow_pickle=False) as npz:
        from types import SimpleNamespace

        keys = ("world_from_bone_quat", "root_pos", "bone_flags")
        solve = SimpleNamespace(**{k: npz[k] for k in keys})
    mapped = retarget_solve(solve, rig, cal, TargetConfig())
    plain_rfb = mapped["target_rest_from_bone_quat"]

    def angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return rot.quat_angle(rot.quat_mul(rot.quat_conj(a), b))

    spine = [names.index(b) for b in ("Spine", "Chest", "UpperChest")]
    limbs = [names.index(b) for b in ("LeftLowerArm", "RightUpperLeg", "Head")]
    assert np.degrees(angle(rfb[:, spine], plain_rfb[:, spine]).max()) > 1.0
    assert np.degrees(angle(rfb[:, limbs], plain_rfb[:, limbs]).max()) < 1e-9
    # The limit holds: no share turns more than 10 deg about x or z in the spine
    # frame (x the humanoid's left, -X; y up; z forward, +Y; intrinsic XYZ).
    s_mat = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]]).T
    m = Rotation.from_matrix(s_mat)
    shares = Rotation.from_quat(rfb[:, spine].reshape(-1, 4), scalar_first=True)
    xyz = np.degrees((m.inv() * shares * m).as_euler("XYZ"))
    assert np.abs(xyz[:, [0, 2]]).max() <= 10.0 + 1e-6, np.abs(xyz).max(axis=0)
    assert np.abs(xyz[:, [0, 2]]).max() > 9.0  # the limit is reached on this take
    bad = tmp_path / "pivot.bvh"
    take, cal_path = pig_synth
    args = ["solve", str(take), "--rig", "plug-in-gait", "--calibration", str(cal_path)]
    assert main([*args, "--out", str(bad), "--pipeline", str(toml)]) == 2
    assert not bad.exists()
