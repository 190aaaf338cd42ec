"""Face configs (shipped presets, validation) and ``retargetd face-train``."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from retargetd.daemon import face_synth as fs
from retargetd.daemon import solve_face as sf
from retargetd.daemon.cli import main
from retargetd.daemon.face_config import (
    FaceConfigError,
    load_face_config,
    shipped_faces,
)

DATASETS = Path(__file__).resolve().parents[2].parent / "shared" / "datasets"


def test_presets_load_and_map() -> None:
    assert set(shipped_faces()) >= {"arkit52", "vrm0", "vrm1"}
    arkit = load_face_config("arkit52")
    assert arkit.expressions == fs.ARKIT_52 and arkit.outputs == fs.ARKIT_52
    np.testing.assert_array_equal(arkit.output_matrix(arkit.expressions), np.eye(52))
    vrm0 = load_face_config("vrm0")
    assert {"A", "I", "U", "E", "O", "Blink_L", "Blink_R", "Joy"} <= set(vrm0.outputs)
    vrm1 = load_face_config("vrm1")
    assert {"aa", "blinkLeft", "happy", "surprised"} <= set(vrm1.outputs)
    m = vrm1.output_matrix(("eyeBlinkLeft", "jawOpen"))  # a partial training set
    assert m.shape == (len(vrm1.outputs), 2)
    assert m[vrm1.outputs.index("blinkLeft"), 0] == 1.0
    assert m[vrm1.outputs.index("aa"), 1] == 1.0


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ('head_markers = ["A", "B"]\nexpressions = ["x"]', "need >= 3"),
        ('head_markers = ["A", "B", "C"]', "missing key 'expressions'"),
        (
            'head_markers = ["A", "B", "C"]\nexpressions = ["x"]\n[output]\ny = "z"',
            "unknown expressions",
        ),
        (
            'head_markers = ["A", "B", "C"]\nfacial_markers = ["A"]\n'
            'expressions = ["x"]',
            "both head and facial",
        ),
        (
            'head_markers = ["A", "B", "C"]\nexpressions = ["x"]\nbogus = 1',
            "unknown keys",
        ),
    ],
)
def test_bad_configs_are_refused(tmp_path: Path, text: str, match: str) -> None:
    path = tmp_path / "face.toml"
    path.write_text(text)
    with pytest.raises(FaceConfigError, match=match):
        load_face_config(path)


def test_custom_map(tmp_path: Path) -> None:
    path = tmp_path / "mine.toml"
    path.write_text(
        'head_markers = ["A", "B", "C"]\nexpressions = ["x", "y"]\n'
        '[output]\nX = "x"\nXY = { x = 0.5, y = 0.5 }\n'
    )
    cfg = load_face_config(path)
    assert cfg.name == "mine" and cfg.outputs == ("X", "XY")
    np.testing.assert_array_equal(cfg.output_matrix(("x", "y")), [[1, 0], [0.5, 0.5]])


def test_face_train_recovers_the_training_set(tmp_path: Path) -> None:
    if not (DATASETS / fs.ICT_DIR).is_dir():
        reason = f"face dataset not found at {DATASETS / fs.ICT_DIR}"
        if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
            pytest.fail(f"{reason} (CI=true: nothing may skip)")
        pytest.skip(reason)
    from retargetd.replay.c3d import write_c3d

    rng = np.random.default_rng(5)
    truth = fs.ict_training_set(DATASETS)
    quat, pos = fs.pig_head_motion(DATASETS)
    hold = 20
    names = ["neutral", *truth.expression_names[:10]]
    n = hold * len(names)
    w = np.zeros((n, truth.k))
    for i in range(1, len(names)):
        w[i * hold : (i + 1) * hold, i - 1] = 1.0
    t = np.arange(n) % len(quat)  # the head keeps moving through every pose
    face = truth.neutral + np.einsum("tk,kmc->tmc", w, truth.deltas)
    local = np.concatenate(
        [np.broadcast_to(truth.head_layout, (n, 4, 3)), face], axis=1
    )
    rot = Rotation.from_quat(quat[t], scalar_first=True).as_matrix()
    world = np.einsum("tij,tmj->tmi", rot, local) + pos[t][:, None]
    world += rng.normal(0.0, 5e-4 / np.sqrt(3.0), world.shape)
    world[3, 6] = np.nan  # an occluded sample inside the neutral range
    labels = [*truth.head_names, *truth.marker_names]
    take = tmp_path / "train.c3d"
    write_c3d(take, labels, world, 100.0)
    poses = ",".join(f"{p}={i * hold}:{(i + 1) * hold}" for i, p in enumerate(names))
    out = tmp_path / "face.npz"
    argv = ["face-train", str(take), "--face", "arkit52", "--poses", poses]
    assert main([*argv, "--out", str(out)]) == 0
    got = sf.TrainingSet.load(out)
    assert got.expression_names == tuple(names[1:])
    assert got.marker_names == truth.marker_names
    # Head coordinates are the take's own (axes of its first neutral frame): compare
    # rotation-invariant figures, then solve a frame with the trained set.
    np.testing.assert_allclose(
        np.linalg.norm(got.deltas, axis=2),
        np.linalg.norm(truth.deltas[:10], axis=2),
        atol=1e-3,  # noise and stabilization error, averaged over 20 frames
    )
    solver = sf.FaceSolver(got)
    res = solver.new_output()
    solved = np.zeros((n, got.k))
    for i in range(n):
        solver.solve_frame(world[i], np.isfinite(world[i, :, 0]), res)
        solved[i] = res.weights
    # Each held pose, median over its frames: that expression at 1, the rest at 0.
    held = np.array(
        [
            np.median(solved[i * hold : (i + 1) * hold], axis=0)
            for i in range(1, len(names))
        ]
    )
    np.testing.assert_allclose(held, np.eye(10), atol=0.1)


def test_face_train_usage_errors(tmp_path: Path) -> None:
    argv = ["face-train", str(tmp_path / "x.c3d"), "--face", "nope", "--poses", "a=1:2"]
    assert main([*argv, "--out", str(tmp_path / "f.npz")]) == 2
