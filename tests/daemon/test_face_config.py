"""Face configs (shipped presets, validation) and ``retargetd face-train``."""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import pytest
from paths import DATASETS
from scipy.spatial.transform import Rotation

from retargetd.daemon.cli.main import main
from retargetd.daemon.face import solve as sf
from retargetd.daemon.face.config import (
    FACE_KEYS,
    FaceConfigError,
    load_face_config,
    shipped_faces,
)
from retargetd.daemon.synth import face as fs


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
            "facial_markers: markers also in head_markers",
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


def test_reference_document_matches_the_parser(tmp_path: Path) -> None:
    # daemon/face/faces/FACES.md: its example loads, and its key table is the parser's.
    repo = Path(__file__).resolve().parents[2]
    doc = (repo / "daemon/face/faces/FACES.md").read_text()
    example = doc.split("```toml\n", 1)[1].split("```", 1)[0]
    path = tmp_path / "example.toml"
    path.write_text(example)
    cfg = load_face_config(path)
    assert cfg.name == "mh-avatar"
    assert cfg.outputs == ("Blink_L", "Blink_R", "Jaw_Open", "Smile", "Kiss")
    documented = set(re.findall(r"^\| `([a-z_\[\]]+)` \|", doc, flags=re.M))
    assert {k.strip("[]") for k in documented} >= set(FACE_KEYS)
    for preset in shipped_faces():
        assert f"| `{preset}` |" in doc, preset


def test_custom_map(tmp_path: Path) -> None:
    path = tmp_path / "mine.toml"
    path.write_text(
        'head_markers = ["A", "B", "C"]\nexpressions = ["x", "y"]\n'
        '[output]\nX = "x"\nXY = { x = 0.5, y = 0.5 }\n'
    )
    cfg = load_face_config(path)
    assert cfg.name == "mine" and cfg.outputs == ("X", "XY")
    np.testing.assert_array_equal(cfg.output_matrix(("x", "y")), [[1, 0], [0.5, 0.5]])


def _need_face_data(folder: str) -> None:
    if not (DATASETS / folder).is_dir():
        reason = f"face dataset not found at {DATASETS / folder}"
        if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
            pytest.fail(f"{reason} (CI=true: nothing may skip)")
        pytest.skip(reason)


def _write_take(
    path: Path, truth: sf.TrainingSet, w: np.ndarray, rng: np.random.Generator
) -> np.ndarray:
    # Frames with weights w (T, K) on the PiG walk's head motion (looped), 0.5 mm
    # noise (3-D RMS), written as a C3D; returns the world markers (T, N, 3).
    from retargetd.replay.c3d import write_c3d

    quat, pos = fs.pig_head_motion(DATASETS)
    n = len(w)
    t = np.arange(n) % len(quat)  # the head keeps moving through every pose
    face = truth.neutral + np.einsum("tk,kmc->tmc", w, truth.deltas)
    local = np.concatenate(
        [np.broadcast_to(truth.head_layout, (n, 4, 3)), face], axis=1
    )
    rot = Rotation.from_quat(quat[t], scalar_first=True).as_matrix()
    world = np.einsum("tij,tmj->tmi", rot, local) + pos[t][:, None]
    world += rng.normal(0.0, 5e-4 / np.sqrt(3.0), world.shape)
    world[3, 6] = np.nan  # an occluded sample inside the neutral range
    write_c3d(path, [*truth.head_names, *truth.marker_names], world, 100.0)
    return world


def _held(k: int, hold: int) -> np.ndarray:
    # Neutral, then each of k expressions fully on, ``hold`` frames each.
    w = np.zeros((hold * (k + 1), k))
    for i in range(k):
        w[(i + 1) * hold : (i + 2) * hold, i] = 1.0
    return w


def _solve(training: sf.TrainingSet, world: np.ndarray) -> np.ndarray:
    # As the daemon solves: the shapes the layout cannot observe left out (0).
    solver = sf.FaceSolver(training, solved=sf.observability(training).observable)
    res = solver.new_output()
    solved = np.zeros((len(world), training.k))
    for i, frame in enumerate(world):
        solver.solve_frame(frame, np.isfinite(frame[:, 0]), res)
        solved[i] = res.weights
    return solved


def test_face_train_recovers_the_training_set(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _need_face_data(fs.ICT_DIR)
    truth = fs.ict_training_set(DATASETS)
    hold = 20
    names = ["neutral", *truth.expression_names[:10]]
    w = np.zeros((hold * len(names), truth.k))
    w[:, :10] = _held(10, hold)
    take = tmp_path / "train.c3d"
    world = _write_take(take, truth, w, np.random.default_rng(5))
    poses = ",".join(f"{p}={i * hold}:{(i + 1) * hold}" for i, p in enumerate(names))
    out = tmp_path / "face.npz"
    argv = ["face-train", str(take), "--face", "arkit52", "--poses", poses]
    assert main([*argv, "--out", str(out)]) == 0
    got = sf.TrainingSet.load(out)
    assert got.expression_names == tuple(names[1:])
    assert got.marker_names == truth.marker_names
    # It says what the layout cannot see: nothing among these ten (ICT's eyeBlink is
    # confused with its gaze shapes only when those are trained too).
    said = capsys.readouterr().out
    assert f"wrote {out}: 4 head markers, 40 facial markers, 10 expressions" in said
    assert "unobservable with this marker layout (0.5 mm noise): none" in said
    # Head coordinates are the take's own (axes of its first neutral frame): compare
    # rotation-invariant figures, then solve a frame with the trained set.
    np.testing.assert_allclose(
        np.linalg.norm(got.deltas, axis=2),
        np.linalg.norm(truth.deltas[:10], axis=2),
        atol=1e-3,  # noise and stabilization error, averaged over 20 frames
    )
    solved = _solve(got, world)
    # Each held pose, median over its frames: that expression at 1, the rest at 0.
    held = np.array(
        [
            np.median(solved[i * hold : (i + 1) * hold], axis=0)
            for i in range(1, len(names))
        ]
    )
    np.testing.assert_allclose(held, np.eye(10), atol=0.1)


#: A rig that is not ARKit: MakeHuman's own expression units, sent under a
#: custom avatar's names (one-to-one and mixed).
UNITS = (
    "eye-left-closure", "eye-right-closure", "eyebrows-left-up", "eyebrows-right-up",
    "mouth-corner-puller", "mouth-open", "mouth-pursing", "nose-left-elevation",
)  # fmt: skip
CUSTOM_FACE = """\
name = "mh-avatar"
head_markers = ["LFHD", "RFHD", "LBHD", "RBHD"]
expressions = [{expressions}]

[output]
Blink_L = "eye-left-closure"
Blink_R = "eye-right-closure"
BrowsUp = {{ "eyebrows-left-up" = 0.5, "eyebrows-right-up" = 0.5 }}
Smile = "mouth-corner-puller"
Jaw_Open = "mouth-open"
Kiss = {{ "mouth-pursing" = 1.0, "mouth-corner-puller" = -0.5 }}
Sneer_L = "nose-left-elevation"
"""


def test_custom_rig_trained_and_sent_by_its_own_names(tmp_path: Path) -> None:
    """A custom face config for a non-ARKit rig (MakeHuman's expression units on
    the real MakeHuman mesh): trained from a take with ``face-train`` under the
    rig's own names, solved, and sent under the avatar's output names."""
    _need_face_data(fs.MAKEHUMAN_DIR)
    truth = fs.model_training_set(fs.makehuman_units_model(DATASETS, UNITS), DATASETS)
    assert truth.expression_names == UNITS
    config = tmp_path / "mh-avatar.toml"
    config.write_text(
        CUSTOM_FACE.format(expressions=", ".join(f'"{u}"' for u in UNITS))
    )
    cfg = load_face_config(config)
    hold, n_mixed = 50, 300
    rng = np.random.default_rng(8)
    mixed = np.clip(rng.uniform(-0.4, 1.0, (n_mixed, len(UNITS))), 0.0, 1.0)
    w = np.concatenate([_held(len(UNITS), hold), mixed])
    take = tmp_path / "mh.c3d"
    world = _write_take(take, truth, w, rng)
    names = ("neutral", *UNITS)
    poses = ",".join(f"{p}={i * hold}:{(i + 1) * hold}" for i, p in enumerate(names))
    out = tmp_path / "mh.npz"
    argv = ["face-train", str(take), "--face", str(config), "--poses", poses]
    assert main([*argv, "--out", str(out)]) == 0
    got = sf.TrainingSet.load(out)
    assert got.expression_names == UNITS
    # Every unit of this rig is observable with its 40 markers.
    assert sf.observability(got).observable.all()
    solved = _solve(got, world)[-n_mixed:]
    m = cfg.output_matrix(got.expression_names)
    assert cfg.outputs == (
        "Blink_L", "Blink_R", "BrowsUp", "Smile", "Jaw_Open", "Kiss", "Sneer_L"
    )  # fmt: skip
    sent = np.clip(solved @ m.T, 0.0, 1.0)
    expected = np.clip(mixed @ m.T, 0.0, 1.0)
    err = np.abs(sent - expected)
    # Median 0.017 here; the 5 mm brow and sneer units are the weakest (noise alone
    # gives them a weight std of 0.05 with these markers; 0.065 and 0.071 sent).
    assert np.median(err) <= 0.05
    assert (np.median(err, axis=0) <= 0.1).all()


def test_face_train_usage_errors(tmp_path: Path) -> None:
    argv = ["face-train", str(tmp_path / "x.c3d"), "--face", "nope", "--poses", "a=1:2"]
    assert main([*argv, "--out", str(tmp_path / "f.npz")]) == 2


# ---- issue 32 item 1: facial markers are the config's or the layout's, not the body's


def _face_with_body(
    path: Path, truth: sf.TrainingSet, w: np.ndarray, rng: np.random.Generator
) -> tuple[list[str], np.ndarray]:
    # The Plug-in Gait walk's real body markers (its 31 non-head markers, their own
    # frames) with the synthetic face riding the same frames' head motion, the head
    # markers in their measured layout; one unnamed marker (a prop on the chest, 6 cm
    # in front of STRN) that no rig names. 0.5 mm noise; written as a C3D.
    from retargetd.replay.c3d import write_c3d
    from retargetd.replay.takes import load_take

    walk = load_take(DATASETS / fs.PIG_WALK)
    head_cols = [walk.labels.index(n) for n in fs.HEAD_NAMES]
    complete = np.all(walk.valid[:, head_cols], axis=1)
    body_names = [n for n in walk.labels if n not in fs.HEAD_NAMES]
    body = walk.positions[complete][:, [walk.labels.index(n) for n in body_names]]
    quat, pos = fs.pig_head_motion(DATASETS)
    assert len(quat) == len(body)
    n = len(w)
    t = np.arange(n) % len(quat)
    face = truth.neutral + np.einsum("tk,kmc->tmc", w, truth.deltas)
    local = np.concatenate(
        [np.broadcast_to(truth.head_layout, (n, 4, 3)), face], axis=1
    )
    rot = Rotation.from_quat(quat[t], scalar_first=True).as_matrix()
    head_face = np.einsum("tij,tmj->tmi", rot, local) + pos[t][:, None]
    prop = body[t][:, [body_names.index("STRN")]] + np.array([0.06, 0.0, 0.0])
    world = np.concatenate([head_face, body[t], prop], axis=1)
    world += rng.normal(0.0, 5e-4 / np.sqrt(3.0), world.shape)
    labels = [*truth.head_names, *truth.marker_names, *body_names, "PROP1"]
    write_c3d(path, labels, world, 100.0)
    return body_names, world


def test_face_train_keeps_body_markers_out_of_the_face(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A take with a real body (the Plug-in Gait walk's markers) beside a face:
    ``face-train`` with a preset (``facial_markers = []``) takes the 40 facial
    markers and none of the 31 body markers (the rig's names) nor the chest prop
    (below the neck), prints that list and solves as well as a face-only take."""
    _need_face_data(fs.ICT_DIR)
    truth = fs.ict_training_set(DATASETS)
    hold = 20
    # Ten shapes these 40 markers see, and two they cannot tell from eyeBlinkLeft.
    extra = ["eyeLookUpLeft", "eyeWideLeft"]
    names = ["neutral", *truth.expression_names[:10], *extra]
    cols = [*range(10), *(truth.expression_names.index(e) for e in extra)]
    w = np.zeros((hold * len(names), truth.k))
    w[:, cols] = _held(len(cols), hold)
    take = tmp_path / "body-face.c3d"
    body_names, world = _face_with_body(take, truth, w, np.random.default_rng(5))
    assert {"C7", "CLAV", "LSHO", "LANK"} <= set(body_names)
    poses = ",".join(f"{p}={i * hold}:{(i + 1) * hold}" for i, p in enumerate(names))
    out = tmp_path / "face.npz"
    argv = ["face-train", str(take), "--face", "arkit52", "--poses", poses]
    assert main([*argv, "--out", str(out)]) == 0
    got = sf.TrainingSet.load(out)
    assert got.marker_names == truth.marker_names
    said = capsys.readouterr().out
    how = "not head markers, not plug-in-gait's, above the neck"
    assert f"{how}): {' '.join(truth.marker_names)}\n" in said
    said_unseen = "unobservable with this marker layout (0.5 mm noise): "
    assert f"{said_unseen}eyeLookUpLeft, eyeWideLeft\n" in said
    for e in extra:  # which shape each is confused with, and by how much
        assert re.search(
            rf"^  {e}: confused with eyeBlinkLeft \(weight correlation \+0\.[89]\d\), "
            r"weight std 0\.\d\d$",
            said,
            flags=re.M,
        ), said
    solved = _solve(got, world[:, : 4 + len(truth.marker_names)])
    assert not solved[:, 10:].any()  # left out: 0 on every frame
    held = np.array(
        [np.median(solved[i * hold : (i + 1) * hold], axis=0) for i in range(1, 11)]
    )
    np.testing.assert_allclose(held[:, :10], np.eye(10), atol=0.1)
    # Without the rig, the neck still keeps the chest, arms and legs out; only the
    # markers at the top of the thorax (C7, the shoulders) reach above the chin's
    # level: why the rig's names come first.
    argv_none = [*argv, "--rig", "none", "--out", str(tmp_path / "none.npz")]
    assert main(argv_none) == 0
    loose = set(sf.TrainingSet.load(tmp_path / "none.npz").marker_names)
    assert set(truth.marker_names) <= loose
    extra = loose - set(truth.marker_names)
    assert extra and extra <= {"C7", "LSHO", "RSHO", "RBAK"}
    assert not {"PROP1", "CLAV", "STRN", "LANK", "LASI"} & loose


def test_a_body_marker_listed_as_facial_is_one_line_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _need_face_data(fs.ICT_DIR)
    truth = fs.ict_training_set(DATASETS)
    take = tmp_path / "body-face.c3d"
    _face_with_body(take, truth, np.zeros((40, truth.k)), np.random.default_rng(6))
    config = tmp_path / "mine.toml"
    facial = ", ".join(f'"{n}"' for n in (*truth.marker_names[:20], "C7"))
    config.write_text(
        'head_markers = ["LFHD", "RFHD", "LBHD", "RBHD"]\n'
        f'body_rig = "plug-in-gait"\nfacial_markers = [{facial}]\n'
        'expressions = ["jawOpen"]\n'
    )
    capsys.readouterr()
    poses = "neutral=0:20,jawOpen=20:40"
    argv = ["face-train", str(take), "--face", str(config), "--poses", poses]
    assert main([*argv, "--out", str(tmp_path / "f.npz")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "C7" in err and "body rig" in err, err
    assert not (tmp_path / "f.npz").exists()
    # The same list without C7 trains, and face-train prints it.
    config.write_text(config.read_text().replace(', "C7"', ""))
    assert main([*argv, "--out", str(tmp_path / "f.npz")]) == 0
    said = capsys.readouterr().out
    assert f"(listed by the face config): {' '.join(truth.marker_names[:20])}\n" in said


def test_the_daemon_refuses_a_body_marker_listed_as_facial(tmp_path: Path) -> None:
    # The daemon's own rig, or the config's body_rig: one line naming the marker,
    # a ConfigError (``make_daemon`` turns it into exit 2 before any socket opens).
    from retargetd.daemon.body.rig import load_rig
    from retargetd.daemon.live.config import ConfigError, FaceSectionConfig
    from retargetd.daemon.live.face import LiveFace

    config = tmp_path / "mine.toml"
    config.write_text(
        'head_markers = ["LFHD", "RFHD", "LBHD", "RBHD"]\n'
        'facial_markers = ["CHIN", "Sub:lsho"]\nexpressions = ["jawOpen"]\n'
    )
    settings = FaceSectionConfig(enabled=True, config=str(config))
    with pytest.raises(ConfigError, match=r"Sub:lsho is a marker of the body rig"):
        LiveFace(settings, load_rig("plug-in-gait"))
    LiveFace(settings)  # no rig named anywhere: nothing to refuse
    config.write_text(config.read_text() + 'body_rig = "plug-in-gait"\n')
    with pytest.raises(ConfigError, match="Sub:lsho") as info:
        LiveFace(settings)
    assert "\n" not in str(info.value)
