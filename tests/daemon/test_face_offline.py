"""Issue 32 items 3 and 4: the face solved offline (``retargetd solve --face``) and on
its own (``--face-only``; a ``body = false`` performer live), against known truth.

The take (built once per module, written as a real C3D): 40 facial markers on the
scanned ICT-FaceKit mesh (``synth.face``: the shapes' peaks, the Multi-PIE landmarks),
its ARKit shapes driven by known weight curves, carried by the real head motion of the
tennis serve (``kineticstoolkit/kinematics_tennis_serve.c3d``: its own LFHD RFHD LBHD
RBHD, worn as the band over the face, up to 520 deg/s), the serve's 35 real body
markers beside the face, 0.4 mm noise (3-D RMS) on every head and facial marker. As in
the issue's test, the performer moves 22 shapes, drawn (seeded) among those the layout
observes at that noise; the others stay at 0. The training set is the mesh's own (the
exact deltas at the 40 sites: a face-train with no noise); a second case trains with
``retargetd face-train`` from held poses and reports what the training's own noise
costs (``test_face_trained_from_held_poses``).
"""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import struct
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zmq
from gltf_tools import issue_summary, validate_glb
from paths import DATASETS
from scipy.spatial.transform import Rotation

from retargetd.daemon.cli.main import main
from retargetd.daemon.face import solve as sf
from retargetd.daemon.synth import face as fs
from retargetd.protocols import pose_stream, vmc_out, zmq_wire
from retargetd.protocols.marker_input import LabelSet
from retargetd.replay.c3d import write_c3d
from retargetd.replay.takes import load_take

SERVE = "kineticstoolkit/kinematics_tennis_serve.c3d"
NOISE_RMS_M = 4e-4  # the issue's 0.4 mm
N_MOVED = 22  # the issue's 22 shapes with known weight curves
RATE_HZ = 50.0  # the serve's rate


@dataclasses.dataclass(frozen=True)
class ServeFace:
    truth: sf.TrainingSet
    face_npz: Path
    take: Path  # head + facial + body markers, every frame seen
    hidden_take: Path  # the same with one key marker hidden on HIDE
    labels: tuple[str, ...]
    world: np.ndarray  # (T, N, 3) as written (float32 values, metres)
    weights: np.ndarray  # (T, K) truth
    moved: np.ndarray  # (K,) bool
    observable: np.ndarray  # (K,) bool, at the training set's noise
    key_shape: str
    key_marker: str
    key_owners: tuple[str, ...]
    folder: Path


#: The frames the key marker is hidden on (0.8 s of the serve).
HIDE = slice(300, 340)


@pytest.fixture(scope="module")
def serve_face(tmp_path_factory: pytest.TempPathFactory) -> ServeFace:
    folder_ict = DATASETS / fs.ICT_DIR
    if not folder_ict.is_dir() or not (DATASETS / SERVE).is_file():
        reason = f"face or serve dataset not found under {DATASETS}"
        if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
            pytest.fail(f"{reason} (CI=true: nothing may skip)")
        pytest.skip(reason)
    folder = tmp_path_factory.mktemp("serve-face")
    layout, _quat, _pos, _complete = fs.take_head_motion(DATASETS, SERVE)
    truth = dataclasses.replace(
        fs.model_training_set(fs.ict_model(DATASETS), DATASETS, head_layout=layout),
        noise_rms_m=NOISE_RMS_M,
    )
    face_npz = folder / "face.npz"
    truth.save(face_npz)
    obs = sf.observability(truth)
    rng = np.random.default_rng(0)
    moved_cols = np.sort(rng.choice(np.flatnonzero(obs.observable), N_MOVED, False))
    w, world, body_names = _performance(truth, moved_cols, rng)
    moved = w.any(axis=0)
    labels = (*truth.head_names, *truth.marker_names, *body_names)
    take = folder / "serve-face.c3d"
    write_c3d(take, labels, world, RATE_HZ, units="m")
    # A key marker of a moved shape, hidden while that shape is on.
    solver = sf.FaceSolver(truth, solved=obs.observable)
    keys = solver.key_markers()
    key_shape, markers = next(
        (s, m) for s, m in keys.items() if m and moved[truth.expression_names.index(s)]
    )
    owners = tuple(s for s, m in keys.items() if markers[0] in m)
    hidden = world.copy()
    hidden[HIDE, labels.index(markers[0])] = np.nan
    hidden_take = folder / "serve-face-hidden.c3d"
    write_c3d(hidden_take, labels, hidden, RATE_HZ, units="m")
    return ServeFace(
        truth=truth, face_npz=face_npz, take=take, hidden_take=hidden_take,
        labels=labels, world=world, weights=w, moved=moved,
        observable=obs.observable, key_shape=key_shape, key_marker=markers[0],
        key_owners=owners, folder=folder,
    )  # fmt: skip


def _performance(
    truth: sf.TrainingSet, moved_cols: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Weights (T, K) moving ``moved_cols`` (the others 0) and the world markers
    (T, 44 + 35, 3): the face on the serve's head, 0.4 mm noise, the serve's body
    beside; float32 values in metres (as the C3D holds them); the body's names."""
    _layout, quat, pos, complete = fs.take_head_motion(DATASETS, SERVE)
    n, k = len(quat), truth.k
    w = fs.synth_weights(rng, n, RATE_HZ, ())
    still = np.ones(k, bool)
    still[moved_cols] = False
    w[:, still] = 0.0
    face = truth.neutral + np.einsum("tk,kmc->tmc", w, truth.deltas)
    local = np.concatenate([np.broadcast_to(truth.head_layout, (n, 4, 3)), face], 1)
    rot = Rotation.from_quat(quat, scalar_first=True).as_matrix()
    head_face = np.einsum("tij,tmj->tmi", rot, local) + pos[:, None]
    head_face += rng.normal(0.0, NOISE_RMS_M / np.sqrt(3.0), head_face.shape)
    serve = load_take(DATASETS / SERVE)
    body_names = [n for n in serve.labels if n not in fs.HEAD_NAMES]
    body = serve.positions[complete][:, [serve.labels.index(b) for b in body_names]]
    world = np.concatenate([head_face, body], axis=1)
    return w, world.astype(np.float32).astype(np.float64), body_names


def _solve(sf_: ServeFace, out: str, *extra: str, take: Path | None = None) -> Path:
    path = sf_.folder / out
    argv = ["solve", str(take or sf_.take), "--face", str(sf_.face_npz), *extra]
    assert main([*argv, "--out", str(path), "--force", "--quiet"]) == 0
    return path


def _solve_hidden(sf_: ServeFace) -> Path:
    return _solve(sf_, "hidden.npz", "--face-only", take=sf_.hidden_take)


def _face_only(sf_: ServeFace) -> Path:
    """The take's face-only NPZ, solved once per session (any test may run alone)."""
    path = sf_.folder / "face-only.npz"
    return path if path.exists() else _solve(sf_, "face-only.npz", "--face-only")


def _npz(path: Path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


# ---- item 4: the evidence -------------------------------------------------------


def test_observable_shapes_within_p95_and_unobserved_never_sent(
    serve_face: ServeFace,
) -> None:
    """Observable shapes |w_hat - w| p95 <= 0.08 (issue 32 item 4); the shapes the
    layout cannot observe are 0 on every frame and say so, per shape, per frame.

    Measured here 0.071 (median 0.009, max 0.26); the same frames with the solver
    as it was before this change (ridge 1e-3 mean(diag B^T B), the head pose from
    the head markers alone): 0.104. Over six draws of the shapes and the noise
    0.070-0.075 (commit message)."""
    z = _npz(_solve(serve_face, "face-only.npz", "--face-only"))
    tr = serve_face.truth
    assert tuple(z["face_shapes"]) == tr.expression_names
    unobserved = set(z["face_unobserved"].tolist())
    seen = np.array([s not in unobserved for s in tr.expression_names])
    np.testing.assert_array_equal(seen, serve_face.observable)
    assert not (serve_face.moved & ~seen).any()  # the performer moves seen shapes
    w = z["face_weights"]
    assert w.dtype == np.float32 and w.shape == serve_face.weights.shape
    err = np.abs(w - serve_face.weights)[:, seen]
    assert np.percentile(err, 95) <= 0.08
    assert np.median(err) <= 0.02
    # Unobservable shapes: never above 0, flagged unobserved on every frame.
    assert (w[:, ~seen] == 0.0).all()
    st = z["face_shape_state"]
    assert (st[:, ~seen] == pose_stream.SHAPE_UNOBSERVED).all()
    assert (st[:, seen] == 0).all()  # every marker seen: nothing held
    assert (z["face_flags"] == 0).all()
    # The head pose is the head markers': the band's centroid, to the noise.
    band = serve_face.world[:, :4].mean(axis=1)
    assert np.abs(z["face_head_pos"] - band).max() < 1e-6
    assert z["face_markers"].shape == (len(w), 40, 3)


def test_a_hidden_key_marker_flags_its_shape(serve_face: ServeFace) -> None:
    """The key marker of a moved shape hidden for 40 frames: exactly the shapes it
    is key to are held (their last weight) and flagged hidden on exactly those
    frames; the frame says shape_held; every other shape is solved as before."""
    z = _npz(_solve_hidden(serve_face))
    full = _npz(_face_only(serve_face))
    names = serve_face.truth.expression_names
    hidden = (z["face_shape_state"] & pose_stream.SHAPE_HIDDEN) != 0
    expect = np.zeros(len(hidden), bool)
    expect[HIDE] = True
    for k, name in enumerate(names):
        want = expect if name in serve_face.key_owners else np.zeros_like(expect)
        assert np.array_equal(hidden[:, k], want), name
    held = (z["face_flags"] & pose_stream.FACE_SHAPE_HELD) != 0
    assert np.array_equal(held, expect)
    k0 = names.index(serve_face.key_shape)
    w = z["face_weights"]
    assert (w[HIDE, k0] == w[HIDE.start - 1, k0]).all()
    assert (w[: HIDE.start] == full["face_weights"][: HIDE.start]).all()


def test_face_trained_from_held_poses(
    serve_face: ServeFace, capsys: pytest.CaptureFixture[str]
) -> None:
    """The same performance solved with a training set from ``face-train`` (the
    neutral and each of the 52 shapes held 2 s, 100 frames, on the moving serve head,
    body beside, 0.4 mm): face-train keeps every body marker out, and the weights
    come within p95 0.10. The training's own noise is the difference from the exact
    set: each pose and the neutral are means of 100 noisy, stabilized frames, so
    every delta is off by ~0.07 mm RMS (0.17 mm with 30-frame holds), and the solve
    takes that error as expression (p95 0.074-0.091 over three draws at 100
    frames, 0.12 at 30): FACES.md "How long to hold a training pose"."""
    tr = serve_face.truth
    _layout, quat, pos, _ = fs.take_head_motion(DATASETS, SERVE)
    hold, k = 100, tr.k
    w = np.zeros((hold * (k + 1), k))
    for i in range(k):
        w[(i + 1) * hold : (i + 2) * hold, i] = 1.0
    t = np.arange(len(w)) % len(quat)
    rng = np.random.default_rng(1)
    face = tr.neutral + np.einsum("tk,kmc->tmc", w, tr.deltas)
    local = np.concatenate([np.broadcast_to(tr.head_layout, (len(w), 4, 3)), face], 1)
    rot = Rotation.from_quat(quat[t], scalar_first=True).as_matrix()
    head_face = np.einsum("tij,tmj->tmi", rot, local) + pos[t][:, None]
    head_face += rng.normal(0.0, NOISE_RMS_M / np.sqrt(3.0), head_face.shape)
    world = np.concatenate([head_face, serve_face.world[t, 44:]], axis=1)
    train = serve_face.folder / "train.c3d"
    write_c3d(train, serve_face.labels, world, RATE_HZ, units="m")
    names = ["neutral", *tr.expression_names]
    poses = ",".join(f"{p}={i * hold}:{(i + 1) * hold}" for i, p in enumerate(names))
    trained = serve_face.folder / "trained.npz"
    argv = ["face-train", str(train), "--face", "arkit52", "--poses", poses]
    assert main([*argv, "--noise-mm", "0.4", "--out", str(trained)]) == 0
    said = capsys.readouterr().out
    got = sf.TrainingSet.load(trained)
    assert got.marker_names == tr.marker_names  # no body marker among them
    assert "unobservable with this marker layout (0.4 mm noise): " in said
    # The performer moves 22 shapes this training set says the layout sees (of two
    # shapes it cannot tell apart, which one is kept can change with the training's
    # noise: jawLeft / jawRight here).
    seen = sf.observability(got).observable
    rng = np.random.default_rng(2)
    weights, world, _ = _performance(
        tr, np.sort(rng.choice(np.flatnonzero(seen), N_MOVED, False)), rng
    )
    perf = serve_face.folder / "trained-perf.c3d"
    write_c3d(perf, serve_face.labels, world, RATE_HZ, units="m")
    out = serve_face.folder / "trained-solve.npz"
    argv = ["solve", str(perf), "--face", str(trained), "--face-only"]
    assert main([*argv, "--out", str(out), "--quiet"]) == 0
    z = _npz(out)
    assert set(z["face_unobserved"]) == set(np.array(tr.expression_names)[~seen])
    err = np.abs(z["face_weights"] - weights)[:, seen]
    assert np.percentile(err, 95) <= 0.10
    assert (z["face_weights"][:, ~seen] == 0.0).all()


# ---- item 3: the formats ---------------------------------------------------------


def test_csv_glb_and_mcap_hold_the_npz_weights(serve_face: ServeFace) -> None:
    z = _npz(_face_only(serve_face))
    names = list(z["face_shapes"])
    w, st = z["face_weights"], z["face_shape_state"]
    # CSV: frame, time_s, face_flags, one column per shape, then its state.
    with open(_solve(serve_face, "face.csv", "--face-only"), newline="") as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == [
        "frame", "time_s", "face_flags", *names, *(f"state_{s}" for s in names)
    ]  # fmt: skip
    table = np.array(rows[1:], dtype=np.float64)
    assert len(table) == len(w)
    np.testing.assert_allclose(table[:, 1], np.arange(len(w)) / RATE_HZ)
    # 9 significant digits: every float32 back exactly
    np.testing.assert_array_equal(table[:, 3 : 3 + len(names)].astype(np.float32), w)
    np.testing.assert_array_equal(table[:, 3 + len(names) :], st)
    # glTF: a point mesh with one morph target per shape, the weights animated.
    glb = _solve(serve_face, "face.glb", "--face-only")
    report = validate_glb(glb)  # the Khronos validator (gltf_tools)
    assert report["issues"]["numErrors"] == 0, issue_summary(report)
    assert report["issues"]["numWarnings"] == 0, issue_summary(report)
    doc, blob = _read_glb(glb)
    assert "skins" not in doc
    mesh = doc["meshes"][0]
    assert mesh["extras"]["targetNames"] == names
    prim = mesh["primitives"][0]
    assert prim["mode"] == 0 and len(prim["targets"]) == len(names)
    tr = serve_face.truth
    np.testing.assert_allclose(_accessor(doc, blob, prim["attributes"]["POSITION"]),
                               tr.neutral, atol=1e-7)  # fmt: skip
    k0 = names.index("jawOpen")
    np.testing.assert_allclose(
        _accessor(doc, blob, prim["targets"][k0]["POSITION"]), tr.deltas[k0], atol=1e-7
    )
    anim = doc["animations"][0]
    node = next(i for i, n in enumerate(doc["nodes"]) if n.get("mesh") == 0)
    by_path = {
        c["target"]["path"]: anim["samplers"][c["sampler"]]
        for c in anim["channels"]
        if c["target"]["node"] == node
    }
    assert set(by_path) == {"weights", "translation", "rotation"}
    got = _accessor(doc, blob, by_path["weights"]["output"]).reshape(len(w), -1)
    np.testing.assert_array_equal(got, w)
    times = _accessor(doc, blob, by_path["weights"]["input"])
    np.testing.assert_allclose(times, np.arange(len(w)) / RATE_HZ, atol=1e-6)
    np.testing.assert_allclose(
        _accessor(doc, blob, by_path["translation"]["output"]), z["face_head_pos"],
        atol=1e-6,
    )  # fmt: skip
    world = next(n for n in doc["nodes"] if n.get("name") == "world")
    assert node in world["children"]  # under the +Z-up -> +Y-up root
    # MCAP: /face/weights per frame, the weights and the unobserved shapes.
    from mcap.reader import make_reader

    path = _solve(serve_face, "face.mcap", "--face-only")
    msgs = []
    with open(path, "rb") as fh:
        for _schema, channel, message in make_reader(fh).iter_messages():
            if channel.topic == "/face/weights":
                msgs.append(json.loads(message.data))
    assert len(msgs) == len(w)
    unobserved = sorted(z["face_unobserved"].tolist())
    for t in (0, 200, len(w) - 1):
        np.testing.assert_allclose([msgs[t]["weights"][s] for s in names], w[t])
        assert sorted(msgs[t]["unobserved"]) == unobserved
        assert msgs[t]["held"] == [] and msgs[t]["flags"] == 0


def test_body_and_face_in_one_solve(serve_face: ServeFace) -> None:
    """``--rig`` with ``--face``: the body's arrays and the face's in one NPZ; the
    face's equal the face-only solve's on the same rows."""
    rows = ("--frames", "0:150")
    both = _npz(
        _solve(serve_face, "both.npz", "--rig", "cmu41", "--calibrate-frames", "0:50",
               "--method", "construction", *rows)
    )  # fmt: skip
    alone = _npz(_solve(serve_face, "alone.npz", "--face-only", *rows))
    assert both["world_from_bone_quat"].shape[0] == 150
    for key in ("face_weights", "face_shape_state", "face_flags", "face_head_quat"):
        np.testing.assert_array_equal(both[key], alone[key], err_msg=key)
    csv_path = _solve(serve_face, "both.csv", "--rig", "cmu41", "--calibrate-frames",
                      "0:50", "--method", "construction", *rows)  # fmt: skip
    with open(csv_path, newline="") as fh:
        head = next(csv.reader(fh))
    assert head[:2] == ["frame", "time_s"] and "root_x_m" in head
    assert head[head.index("face_flags") + 1 :][:1] == [str(alone["face_shapes"][0])]


@pytest.mark.parametrize(
    ("extra", "needle"),
    [
        (["--face-only", "--rig", "cmu41"], "--face-only solves no body"),
        (["--face-only", "--out-bvh"], "BVH carries no blendshapes"),
        ([], "needs --rig"),
    ],
)
def test_face_usage_errors(
    serve_face: ServeFace, capsys: pytest.CaptureFixture[str], extra: list[str],
    needle: str,
) -> None:  # fmt: skip
    out = serve_face.folder / ("x.bvh" if "--out-bvh" in extra else "x.npz")
    extra = [e for e in extra if e != "--out-bvh"]
    argv = ["solve", str(serve_face.take), "--face", str(serve_face.face_npz), *extra]
    capsys.readouterr()
    assert main([*argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert needle in err and err.count("\n") == 1, err
    assert not out.exists()


# ---- item 3: offline equals live, a face with no body ------------------------------


def test_offline_equals_live_for_a_face_alone(
    serve_face: ServeFace,
    start_daemon: Callable[..., Any],
    zmq_socket: Callable[[int], Any],
    udp_socket: Callable[..., Any],
) -> None:
    """A performer with ``body = false`` and the face: the hidden-marker take sent
    over ZeroMQ on 127.0.0.1, every pose message's weights, shape states, face flags
    and head pose equal ``solve --face-only``'s NPZ for the same frames (1e-6);
    VMC carries the blendshapes alone (no root, no bones); nothing is calibrated."""
    from live_harness import VmcReceiver

    z = _npz(_solve_hidden(serve_face))
    take = load_take(serve_face.hidden_take)
    frames = np.where(take.valid[..., None], take.positions, np.nan).astype(np.float32)
    np.testing.assert_array_equal(
        np.nan_to_num(frames.astype(np.float64)), np.nan_to_num(take.positions)
    )  # the wire's float32 is the file's: the same numbers both ways
    vmc = VmcReceiver(udp_socket(bind=True))
    live = start_daemon(
        {
            "performer": {"body": False},
            "loop": {"process_every_frame": True},
            "face": {"enabled": True, "config": "arkit52",
                     "training": str(serve_face.face_npz)},
        },
        vmc_port=vmc.port,
    )  # fmt: skip
    push = zmq_socket(zmq.PUSH)
    push.connect(live.tcp("zmq markers"))
    sub = zmq_socket(zmq.SUB)
    sub.setsockopt(zmq.SUBSCRIBE, b"RTD")
    sub.setsockopt(zmq.RCVHWM, 100_000)
    sub.connect(live.tcp("zmq poses"))
    push.send_multipart(zmq_wire.encode_zmq_labels(LabelSet(3, take.labels)))
    poses: list[pose_stream.PoseMessage] = []
    names: list[pose_stream.PoseNames] = []
    shapes: list[pose_stream.ShapeStateMessage] = []

    def pump(timeout_ms: int) -> None:
        while sub.poll(timeout_ms):
            timeout_ms = 0
            parts = sub.recv_multipart()
            magic = parts[0][:4]
            if magic == pose_stream.DATA_MAGIC:
                poses.append(pose_stream.decode_pose(parts))
            elif magic == pose_stream.NAMES_MAGIC:
                names.append(pose_stream.decode_pose_names(parts))
            elif magic == pose_stream.SHAPE_MAGIC:
                shapes.append(pose_stream.decode_shape_state(parts[0]))

    # Prime with frame 0 until the SUB hears (slow joiner); the face solver is then
    # where the offline one is after its frame 0 (the same solution: the QP is
    # strictly convex, its warm start changes only the iterations).
    import time

    deadline = time.monotonic() + 10.0
    fid = 0  # frame numbers only increase (a step back reads as a restart)
    while not poses:
        assert time.monotonic() < deadline, "no pose reached the SUB"
        push.send_multipart(zmq_wire.encode_zmq_frame(fid, fid / RATE_HZ, 3, frames[0]))
        fid += 1
        pump(20)
    for _ in range(20):
        pump(20)
    poses.clear()
    shapes.clear()
    # In chunks the pose PUB's queue (sndhwm 1000 messages: a pose and its RTDF
    # per frame) always holds: a PUB drops what its queue cannot.
    deadline = time.monotonic() + 60.0
    for start in range(0, len(frames), 200):
        stop = min(start + 200, len(frames))
        for t in range(start, stop):
            push.send_multipart(
                zmq_wire.encode_zmq_frame(fid + t, (fid + t) / RATE_HZ, 3, frames[t])
            )
        while len(poses) < stop or len(shapes) < stop:
            assert time.monotonic() < deadline, f"{len(poses)} poses of {stop}"
            pump(50)
        vmc.pump(1000)  # read the datagrams before the socket's buffer fills
    assert [p.frame_id for p in poses] == list(range(fid, fid + len(frames)))
    assert [s.frame_id for s in shapes] == list(range(fid, fid + len(frames)))
    got = np.array([p.weights for p in poses])
    np.testing.assert_allclose(got, z["face_weights"], atol=1e-6, rtol=0)
    np.testing.assert_array_equal(np.array([s.states for s in shapes]),
                                  z["face_shape_state"])  # fmt: skip
    np.testing.assert_array_equal([p.face_flags for p in poses], z["face_flags"])
    head = np.array([p.head_pos_world for p in poses])
    np.testing.assert_allclose(head, z["face_head_pos"], atol=1e-6)
    assert all(p.world_from_bone_quat.shape == (0, 4) for p in poses)
    np.testing.assert_allclose(  # the header's root is the head
        np.array([p.root_pos_world for p in poses]), z["face_head_pos"], atol=1e-6
    )
    quat = np.array([p.world_from_head_quat for p in poses], np.float64)
    dots = np.abs(np.sum(quat * z["face_head_quat"], axis=1))
    assert dots.min() > 1.0 - 1e-6
    assert names[-1].bone_names == () and names[-1].weight_names == tuple(
        z["face_shapes"]
    )
    assert set(names[-1].unobserved) == set(z["face_unobserved"])
    # VMC: blendshape frames without a root or a bone, the weights by ARKit name.
    vmc.pump()
    blends = [
        {p[0]: p[1] for a, p in s if a == vmc_out.BLEND_VAL_ADDRESS}
        for s in vmc.states
        if any(a == vmc_out.BLEND_VAL_ADDRESS for a, _ in s)
    ]
    assert not vmc.frames  # no frame with a root
    assert len(blends) >= len(frames)
    sent = np.array([[b[str(s)] for s in z["face_shapes"]] for b in blends])
    np.testing.assert_allclose(sent[-len(frames) :], z["face_weights"], atol=1e-6)
    status = live.ctl({"cmd": "status"})["status"]
    perf = status["performers"][0]
    assert perf["body"] is False and perf["calibrated"] is True
    assert perf["face"]["unobserved"] == list(z["face_unobserved"])
    reply = live.ctl({"cmd": "calibrate"})
    assert not reply["ok"] and "no body" in reply["error"]


# ---- glb reading -------------------------------------------------------------------


def _read_glb(path: Path) -> tuple[dict[str, Any], bytes]:
    data = path.read_bytes()
    assert data[:4] == b"glTF"
    n_json = struct.unpack_from("<I", data, 12)[0]
    doc = json.loads(data[20 : 20 + n_json])
    n_bin = struct.unpack_from("<I", data, 20 + n_json)[0]
    blob = data[28 + n_json : 28 + n_json + n_bin]
    return doc, blob


def _accessor(doc: dict[str, Any], blob: bytes, index: int) -> np.ndarray:
    acc = doc["accessors"][index]
    view = doc["bufferViews"][acc["bufferView"]]
    width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[acc["type"]]
    assert acc["componentType"] == 5126
    arr = np.frombuffer(
        blob, "<f4", acc["count"] * width, view.get("byteOffset", 0)
    ).astype(np.float64)
    return arr.reshape(acc["count"], width) if width > 1 else arr


def test_a_performer_without_a_body_needs_a_face() -> None:
    from retargetd.daemon.live.config import DaemonConfig
    from retargetd.daemon.live.performer import build_performers

    config = DaemonConfig.from_dict({"performer": {"body": False}}, source="test")
    with pytest.raises(ValueError, match=r"body = false needs a face") as info:
        build_performers(config)
    assert "\n" not in str(info.value)
