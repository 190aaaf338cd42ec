"""``retargetd reduce``, ``blend`` and ``loop`` end to end: the reduced ``.glb`` read
back with pygltflib and played with scipy's Slerp stays within the tolerance of every
solved frame (synthetic and the real Plug-in Gait walk); a blend at matching frames
and a loop of a walk cycle have no jump larger than the take's own frame-to-frame
motion; unit quaternions throughout."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pygltflib
import pytest
from gltf_tools import issue_summary, validate_glb
from scipy.spatial.transform import Rotation, Slerp

from retargetd.daemon.cli.main import main
from retargetd.daemon.post.interp import pose_distance

STATIC = "btkdata/PiG_Calibration-FlatFoot-Full.c3d"
WALK = "btkdata/PiG_Motion-FlatFoot-Full.c3d"


@pytest.fixture(scope="module")
def walk(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path]:
    """A synthetic walk (1 s static hold, then walking round a circle at 100 Hz),
    its calibration and its plain solve (NPZ)."""
    d = tmp_path_factory.mktemp("walk")
    take, cal, npz = d / "w.c3d", d / "cal.json", d / "w.npz"
    assert main(["synth", "--markers", "plug-in-gait", "--motions", "walk",
                 "--seconds", "4", "--rate", "100", "--base-pose-s", "1",
                 "--out", str(take)]) == 0  # fmt: skip
    args = ["calibrate", str(take), "--rig", "plug-in-gait", "--frames", "0:100"]
    assert main([*args, "--out", str(cal)]) == 0
    base = ["solve", str(take), "--rig", "plug-in-gait", "--calibration", str(cal)]
    assert main([*base, "--out", str(npz)]) == 0
    return take, cal, npz


def _accessor(gltf: pygltflib.GLTF2, index: int, width: int) -> np.ndarray:
    acc = gltf.accessors[index]
    view = gltf.bufferViews[acc.bufferView]
    start = (view.byteOffset or 0) + (acc.byteOffset or 0)
    data = np.frombuffer(gltf.binary_blob(), np.float32, acc.count * width, start)
    return data.reshape(acc.count, width).astype(np.float64)


def _check_reduced_glb(
    path: Path, names: list[str], quat: np.ndarray, root: np.ndarray, rate_hz: float,
    tol_deg: float, tol_mm: float,
) -> int:  # fmt: skip
    """Play every channel of the file at every frame; return the keys kept."""
    gltf = pygltflib.GLTF2().load(str(path))
    assert gltf.skins[0].joints == list(range(len(names)))  # a skin of every bone
    anim = gltf.animations[0]
    t = np.arange(len(quat)) / rate_hz
    kept = 0
    seen = set()
    for ch in anim.channels:
        sampler = anim.samplers[ch.sampler]
        assert sampler.interpolation == "LINEAR"
        times = _accessor(gltf, sampler.input, 1)[:, 0]
        # Nodes are named by the humanoid map; extras keep the rig's bone name.
        node = gltf.nodes[ch.target.node].extras["rig_bone"]
        kept += len(times)
        tt = np.clip(t, times[0], times[-1])  # float32 key times
        if ch.target.path == "rotation":
            vals = _accessor(gltf, sampler.output, 4)  # x y z w
            played = Slerp(times, Rotation.from_quat(vals))(tt)
            b = names.index(node)
            truth = Rotation.from_quat(quat[:, b], scalar_first=True)
            err = np.degrees((played.inv() * truth).magnitude())
            assert err.max() <= tol_deg + 1e-3, node
            seen.add(node)
        else:
            vals = _accessor(gltf, sampler.output, 3)
            played = np.stack([np.interp(tt, times, vals[:, k]) for k in range(3)], -1)
            err_mm = 1000 * np.linalg.norm(played - root, axis=-1)
            assert err_mm.max() <= tol_mm + 1e-3
    assert seen == set(names)
    return kept


def test_reduce_holds_the_tolerance(
    walk: tuple[Path, Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    take, cal, npz = walk
    out = tmp_path / "r.glb"
    args = ["reduce", str(take), "--rig", "plug-in-gait", "--calibration", str(cal)]
    assert main([*args, "--tolerance-deg", "0.5", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    with np.load(npz) as z:
        names = [str(n) for n in z["bone_names"]]
        q, root = z["parent_from_bone_quat"], z["root_pos"]
    kept = _check_reduced_glb(out, names, q, root, 100.0, 0.5, 1.0)
    assert kept < 0.5 * len(q) * (len(names) + 1)
    assert f"kept {kept} of {len(q) * (len(names) + 1)} keys" in text
    assert "lhand" in text and "root" in text and "worst" in text


def test_reduce_real_take(
    datasets: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cal = tmp_path / "cal.json"
    assert main(["calibrate", str(datasets / STATIC), "--rig", "plug-in-gait",
                 "--out", str(cal)]) == 0  # fmt: skip
    base = ["--rig", "plug-in-gait", "--calibration", str(cal)]
    npz, glb = tmp_path / "w.npz", tmp_path / "w.glb"
    assert main(["solve", str(datasets / WALK), *base, "--out", str(npz)]) == 0
    assert main(["reduce", str(datasets / WALK), *base, "--tolerance-deg", "1",
                 "--tolerance-mm", "2", "--out", str(glb)]) == 0  # fmt: skip
    capsys.readouterr()
    with np.load(npz) as z:
        names = [str(n) for n in z["bone_names"]]
        q, root, rate = z["parent_from_bone_quat"], z["root_pos"], float(z["rate_hz"])
    kept = _check_reduced_glb(glb, names, q, root, rate, 1.0, 2.0)
    assert kept < len(q) * (len(names) + 1)


def test_reduce_usage_errors(
    walk: tuple[Path, Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    take, cal, _ = walk
    args = ["reduce", str(take), "--rig", "plug-in-gait", "--calibration", str(cal)]
    assert main([*args, "--out", str(tmp_path / "r.bvh")]) == 2
    assert "expected a .glb file" in capsys.readouterr().err
    assert main([*args, "--tolerance-deg", "0", "--out", str(tmp_path / "r.glb")]) == 2
    assert "--tolerance-deg: expected a positive number" in capsys.readouterr().err


def test_blend_at_matching_frames_has_no_jump(
    walk: tuple[Path, Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    take, cal, npz = walk
    with np.load(npz) as z:
        q = z["parent_from_bone_quat"]
    own = np.degrees(pose_distance(q[130:-1], q[131:])).max()  # walking
    # The frame of the second walk most like frame 150 of the first, a cycle on.
    cand = np.arange(200, 350)
    at_b = int(cand[np.argmin(np.degrees(pose_distance(q[150], q[cand])))])
    out = tmp_path / "b.npz"
    args = ["blend", str(take), str(take), "--rig", "plug-in-gait",
            "--calibration", str(cal), "--at", f"150:{at_b}", "--frames", "12",
            "--out", str(out)]  # fmt: skip
    assert main(args) == 0
    assert "largest pose change across the fade" in capsys.readouterr().out
    with np.load(out) as z:
        bq, bp = z["parent_from_bone_quat"], z["root_pos"]
        assert z["world_from_bone_quat"].shape == bq.shape
    assert len(bq) == 150 + len(q) - at_b
    np.testing.assert_allclose(np.linalg.norm(bq, axis=-1), 1.0, atol=1e-12)
    steps = np.degrees(pose_distance(bq[140:170], bq[141:171]))
    assert steps.max() <= own
    # The root does not jump either: B moved onto A's floor position.
    hop = np.linalg.norm(np.diff(bp[140:170], axis=0), axis=-1)
    assert hop.max() < 2.0 * np.linalg.norm(np.diff(bp[150:170], axis=0), axis=-1).max()
    # Away from the fade the frames are the takes' own.
    np.testing.assert_array_equal(bq[:150], q[:150])
    assert pose_distance(bq[200], q[at_b + 50]) < 1e-9


@pytest.mark.parametrize("suffix", ["npz", "glb", "bvh"])
def test_loop_of_a_walk_is_seamless(
    walk: tuple[Path, Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str],
    suffix: str,
) -> None:  # fmt: skip
    take, cal, npz = walk
    out = tmp_path / f"l.{suffix}"
    args = ["loop", str(take), "--rig", "plug-in-gait", "--calibration", str(cal),
            "--range", "200:", "--frames", "10", "--find-cycle-s", "0.8",
            "--out", str(out)]  # fmt: skip
    assert main(args) == 0
    text = capsys.readouterr().out
    assert "seam (last frame -> first)" in text and out.stat().st_size > 0
    if suffix != "npz":
        return
    with np.load(npz) as z:
        q = z["parent_from_bone_quat"][200:]
    own = np.degrees(pose_distance(q[:-1], q[1:])).max()
    with np.load(out) as z:
        lq, travel = z["parent_from_bone_quat"], z["travel_m"]
    np.testing.assert_allclose(np.linalg.norm(lq, axis=-1), 1.0, atol=1e-12)
    cyc = np.concatenate([lq, lq[:1]])  # played round
    steps = np.degrees(pose_distance(cyc[:-1], cyc[1:]))
    assert steps[-1] <= own and steps.max() <= own
    assert travel.shape == (3,) and np.linalg.norm(travel) > 0.1  # it walks


def test_blend_and_loop_usage_errors(
    walk: tuple[Path, Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    take, cal, _ = walk
    base = ["--rig", "plug-in-gait", "--calibration", str(cal)]
    out = ["--out", str(tmp_path / "x.npz")]
    cases = [
        (["blend", str(take), str(take), *base, "--at", "150", "--frames", "5", *out],
         "--at: expected a:b"),
        (["blend", str(take), str(take), *base, "--at", "395:0", "--frames", "10",
          *out], "at_a + n_frames must fit"),
        (["loop", str(take), *base, "--frames", "300", *out], "--frames: n_frames"),
        (["loop", str(take), *base, "--frames", "5", "--bvh-order", "ZXZ",
          "--out", str(tmp_path / "x.bvh")], "BVH can express only"),
        (["loop", str(take), *base, "--frames", "5", "--out", str(tmp_path / "x.c3d")],
         "expected a .glb, .bvh or .npz"),
    ]  # fmt: skip
    for argv, message in cases:
        assert main(argv) == 2
        assert message in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def test_reduce_with_a_pipeline_reduces_the_processed_take(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``reduce --pipeline`` keys the take the pipeline made. The take twists its
    forearms (the synthetic walk alone has no forearm twist for the twist stage to
    share out since its Plug-in Gait wrist bar sits where the rule puts it: the
    solved twist was the old site's error)."""
    take, cal, plain = tmp_path / "t.c3d", tmp_path / "cal.json", tmp_path / "p.npz"
    assert main(["synth", "--markers", "plug-in-gait", "--motions",
                 "walk,forearm_twist", "--seconds", "4", "--rate", "100",
                 "--base-pose-s", "1", "--out", str(take)]) == 0  # fmt: skip
    assert main(["calibrate", str(take), "--rig", "plug-in-gait", "--frames", "0:100",
                 "--out", str(cal)]) == 0  # fmt: skip
    assert main(["solve", str(take), "--rig", "plug-in-gait", "--calibration",
                 str(cal), "--out", str(plain)]) == 0  # fmt: skip
    pipe = tmp_path / "pipe.toml"
    pipe.write_text('[[pipeline]]\nkind = "twist"\nfractions = [0.5, 0.25, 0.25]\n')
    base = ["--rig", "plug-in-gait", "--calibration", str(cal), "--pipeline", str(pipe)]
    npz, glb = tmp_path / "t.npz", tmp_path / "t.glb"
    assert main(["solve", str(take), *base, "--out", str(npz)]) == 0
    assert main(["reduce", str(take), *base, "--out", str(glb)]) == 0
    capsys.readouterr()
    with np.load(npz) as z, np.load(plain) as plain_solve:
        names = [str(n) for n in z["bone_names"]]
        q, root = z["parent_from_bone_quat"], z["root_pos"]
        up = names.index("lupperarm")
        # The pipeline changed the take (else this would prove nothing).
        a, b = q[:, up], plain_solve["parent_from_bone_quat"][:, up]
        d = 2 * np.arccos(np.clip(np.abs(np.sum(a * b, axis=-1)), 0.0, 1.0))
        assert np.degrees(d).max() > 1.0
    _check_reduced_glb(glb, names, q, root, 100.0, 0.5, 1.0)


def test_every_glb_command_writes_the_skin_and_capsules(
    walk: tuple[Path, Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``solve``, ``reduce``, ``blend`` and ``loop`` write the same skinned file:
    joints named by the humanoid map, ``--glb-mesh capsules`` a capsule per bone
    bound to them, no validator error or warning; ``--glb-mesh`` elsewhere is a
    usage error."""
    take, cal, npz = walk
    rig = ["--rig", "plug-in-gait", "--calibration", str(cal)]
    commands = {
        "solve": ["solve", str(take), *rig],
        "reduce": ["reduce", str(take), *rig],
        "blend": ["blend", str(take), str(take), *rig, "--at", "150:100",
                  "--frames", "10"],
        "loop": ["loop", str(take), *rig, "--range", "200:", "--frames", "10"],
    }  # fmt: skip
    with np.load(npz) as z:
        want = [str(h) or str(n) for n, h in zip(z["bone_names"], z["bone_humanoid"],
                                                  strict=True)]  # fmt: skip
    assert want[0] == "Hips"
    for name, argv in commands.items():
        for mesh in ("none", "capsules"):
            out = tmp_path / f"{name}_{mesh}.glb"
            assert main([*argv, "--glb-mesh", mesh, "--out", str(out)]) == 0, name
            capsys.readouterr()
            report = validate_glb(out)
            issues = report["issues"]
            assert issues["numErrors"] == 0, (name, issue_summary(report))
            assert issues["numWarnings"] == 0, (name, issue_summary(report))
            gltf = pygltflib.GLTF2().load(str(out))
            assert [n.name for n in gltf.nodes[: len(want)]] == want, name
            assert gltf.skins[0].joints == list(range(len(want)))
            assert len(gltf.meshes) == (mesh == "capsules"), name
            if mesh == "capsules":
                pos = gltf.meshes[0].primitives[0].attributes.POSITION
                assert gltf.accessors[pos].count == 34 * len(want)
    assert main([*commands["solve"], "--glb-mesh", "capsules",
                 "--out", str(tmp_path / "x.npz")]) == 2  # fmt: skip
    assert "--glb-mesh applies to .glb output" in capsys.readouterr().err
    assert main([*commands["loop"], "--glb-mesh", "capsules",
                 "--out", str(tmp_path / "x.bvh")]) == 2  # fmt: skip
    assert "--glb-mesh applies to .glb output" in capsys.readouterr().err
