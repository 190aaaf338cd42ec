"""The face in the live daemon, over real loopback sockets: body and face solved from
one ZeroMQ marker stream, weights out as VMC blendshapes under the target's names and
in the pose stream, stabilized markers in the pose stream's face part, and training
poses captured live with ``retargetd ctl face-capture``.

The face is the ICT-FaceKit ARKit face (``face_synth``) riding on the synthetic
performer's own head: its four head markers (LFHD RFHD LBHD RBHD, shared with the
body rig) are the stabilization markers, their T-pose layout the head frame, and the
40 facial markers are placed exactly (no noise), so the live weights must equal an
offline :class:`FaceSolver` run on the same float32 frames.
"""

from __future__ import annotations

import socket
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import live_harness as _live
import numpy as np
import pytest
import zmq
from face_harness import _face, _stream

from retargetd.daemon.cli.main import main as cli_main
from retargetd.daemon.face.config import load_face_config
from retargetd.daemon.face.solve import FaceSolver, TrainingSet, observability
from retargetd.daemon.synth import face as fs
from retargetd.protocols import pose_stream, vmc_out, zmq_wire
from retargetd.protocols.marker_input import LabelSet

Live, VmcReceiver = _live.Live, _live.VmcReceiver
_f32, _take, _wait_until = _live._f32, _live._take, _live._wait_until


class Harness:
    """A daemon with ZeroMQ PUSH input, a pose SUB and a VMC receiver."""

    def __init__(
        self, live: Live, zmq_socket: Callable[[int], Any], vmc: VmcReceiver
    ) -> None:
        self.live, self.vmc = live, vmc
        self.push = zmq_socket(zmq.PUSH)
        self.push.connect(live.tcp("zmq markers"))
        self.sub = zmq_socket(zmq.SUB)
        self.sub.setsockopt(zmq.SUBSCRIBE, b"RTD")
        self.sub.setsockopt(zmq.RCVHWM, 100_000)
        self.sub.connect(live.tcp("zmq poses"))
        self.poses: list[pose_stream.PoseMessage] = []
        self.names: list[pose_stream.PoseNames] = []
        self.shapes: list[pose_stream.ShapeStateMessage] = []
        self.next_id = 0
        self.label_set: LabelSet | None = None

    def announce(self, labels: tuple[str, ...], label_set_id: int = 3) -> None:
        self.label_set = LabelSet(label_set_id, labels)
        self.push.send_multipart(zmq_wire.encode_zmq_labels(self.label_set))
        self.wait_pipelines()

    def wait_pipelines(self) -> None:
        """Until the daemon's pipelines for the label set, its calibration and
        its face's training set now are built (off its loop, ``live/rebuild.py``):
        the next frame is solved with them."""
        assert self.label_set is not None
        self.live.wait_pipelines(self.live.daemon.zmq_stream, self.label_set)

    def wait_saved(self) -> None:
        """Until the daemon has written its face's training set (off its loop,
        ``live/face.py``) and said so."""
        face = self.live.daemon.face
        _wait_until(lambda: not face.saving, "the training set written")

    def send(self, frames: np.ndarray) -> None:
        ls_id = self.label_set.id if self.label_set is not None else 3
        for f in frames:
            self.push.send_multipart(
                zmq_wire.encode_zmq_frame(self.next_id, self.next_id / 100.0, ls_id, f)
            )
            self.next_id += 1

    def pump(self, timeout_ms: int = 0) -> None:
        while self.sub.poll(timeout_ms):
            timeout_ms = 0
            parts = self.sub.recv_multipart()
            if parts[0][:4] == pose_stream.DATA_MAGIC:
                self.poses.append(pose_stream.decode_pose(parts))
            elif parts[0][:4] == pose_stream.NAMES_MAGIC:
                self.names.append(pose_stream.decode_pose_names(parts))
            elif parts[0][:4] == pose_stream.SHAPE_MAGIC:
                assert len(parts) == 1
                self.shapes.append(pose_stream.decode_shape_state(parts[0]))

    def prime(self, frame: np.ndarray) -> None:
        """Send until the SUB hears the daemon (slow joiner), then forget it all."""
        deadline = time.monotonic() + 10.0
        while not self.poses:
            assert time.monotonic() < deadline, "pose stream never reached the SUB"
            self.send(frame[None])
            self.pump(20)
        n = self.live.daemon.stats.frames_out
        _wait_until(lambda: self.live.daemon.stats.frames_solved >= n, "primed")
        # Until 100 ms pass with nothing new (a priming frame's pose, its shape
        # states): what was sent before the test's frames is forgotten whole.
        count = -1
        while count != len(self.poses) + len(self.shapes):
            count = len(self.poses) + len(self.shapes)
            self.pump(100)
        self.poses.clear()
        self.shapes.clear()
        self.vmc.pump()
        self.vmc.frames.clear()

    def wait_poses(self, n: int, timeout_s: float = 10.0) -> None:
        deadline = time.monotonic() + timeout_s
        while len(self.poses) < n:
            assert time.monotonic() < deadline, f"{len(self.poses)}/{n} poses"
            self.pump(20)


def _blends(frame: list[tuple[str, list[Any]]]) -> dict[str, float]:
    return {p[0]: p[1] for a, p in frame if a == vmc_out.BLEND_VAL_ADDRESS}


@pytest.fixture
def harness(
    start_daemon: Callable[..., Live],
    zmq_socket: Callable[[int], Any],
    udp_socket: Callable[..., socket.socket],
    exact_calibration: Path,
) -> Callable[..., Harness]:
    def make(face: dict[str, Any]) -> Harness:
        vmc = VmcReceiver(udp_socket(bind=True))
        live = start_daemon(
            {
                "performer": {"calibration": str(exact_calibration)},
                "loop": {"process_every_frame": True},
                "face": {"enabled": True, **face},
            },
            vmc_port=vmc.port,
        )
        return Harness(live, zmq_socket, vmc)

    return make


def test_face_solved_with_the_body_streamed_by_name(
    harness: Callable[..., Harness], datasets: Path, tmp_path: Path
) -> None:
    """ARKit 52 from a trained face: weights and stabilized markers in the pose
    stream equal an offline FaceSolver on the same float32 frames; VMC carries every
    ARKit name with the same value, then Apply."""
    training, rots, pos = _face(datasets)
    training.save(tmp_path / "face.npz")
    h = harness({"config": "arkit52", "training": str(tmp_path / "face.npz")})
    rows = np.arange(100, 300)
    # The daemon leaves out the shapes 40 markers cannot observe (issue 32); the
    # performer does not move them (a motion of them would leak into the others).
    seen = observability(training).observable
    unseen = tuple(np.array(training.expression_names)[~seen])
    assert 20 < seen.sum() < 52
    w = fs.synth_weights(np.random.default_rng(5), len(rows), 100.0, unseen)
    labels, frames = _stream(training, rots, pos, rows, w)
    h.announce(labels)
    h.prime(frames[0])
    h.send(frames)
    h.wait_poses(len(rows))
    h.vmc.wait_frames(len(rows))
    # Names: the solved expressions and the stabilized markers, in order.
    names = h.names[-1]
    assert names.weight_names == training.expression_names
    assert names.face_markers == training.marker_names
    assert names.unobserved == unseen
    # Oracle: the same solver on the frames as the daemon decoded them.
    solver = FaceSolver(training, labels=labels, head_weights=(1.0,) * 4, solved=seen)
    out = solver.new_output()
    solver.solve_frame(frames[0].astype(np.float64), np.ones(len(labels), bool), out)
    errs = []
    for t, msg in enumerate(h.poses):
        f64 = frames[t].astype(np.float64)
        solver.solve_frame(f64, np.isfinite(f64[:, 0]), out)
        assert msg.face_markers is not None and msg.face_markers.shape == (40, 3)
        np.testing.assert_allclose(msg.face_markers, out.markers_head, atol=2e-7)
        np.testing.assert_allclose(msg.weights, out.weights, atol=1e-6)
        assert msg.face_flags == 0
        # The head pose the markers were stabilized with is the performer's.
        np.testing.assert_allclose(msg.head_pos_world, pos[rows[t]], atol=1e-6)
        errs.append(np.abs(msg.weights - w[t]))
    # Noise-free markers: on the shapes 40 markers can see, the live weights are the
    # truth up to the regularization; the others are never sent above 0, and each
    # pose is followed by its per-shape states: unobserved, or solved.
    assert float(np.median(np.array(errs)[:, seen])) < 0.02
    assert not np.array([m.weights for m in h.poses])[:, ~seen].any()
    _wait_until(lambda: h.pump() or len(h.shapes) >= len(rows), "shape states")
    assert [m.frame_id for m in h.shapes] == [m.frame_id for m in h.poses]
    want = np.where(seen, 0, pose_stream.SHAPE_UNOBSERVED)
    for m in h.shapes:
        np.testing.assert_array_equal(m.states, want)
    # VMC: every ARKit name, the weight of its expression, then Apply.
    face_cfg = load_face_config("arkit52")
    for msg, frame in zip(h.poses, h.vmc.frames, strict=True):
        blends = _blends(frame)
        assert list(blends) == list(face_cfg.outputs)
        expr = dict(zip(training.expression_names, msg.weights, strict=True))
        for name, value in blends.items():
            assert value == pytest.approx(expr[name], abs=1e-6), name
        addresses = [a for a, _ in frame]
        assert addresses.index(vmc_out.BLEND_APPLY_ADDRESS) > max(
            i for i, a in enumerate(addresses) if a == vmc_out.BLEND_VAL_ADDRESS
        )
    s = h.live.daemon.stats
    assert s.face_solved >= len(rows) and s.face_head_lost == 0
    for frame in h.vmc.frames:  # an unobserved shape goes out as 0 over VMC too
        assert all(_blends(frame)[n] == 0.0 for n in unseen)
    reply = h.live.ctl({"cmd": "status"})
    status = reply["status"]
    assert status["face"]["trained"] and len(status["face"]["expressions"]) == 52
    assert status["face"]["unobserved"] == list(unseen)
    assert f"unobserved {len(unseen)} ({' '.join(unseen)})" in reply["line"]


def test_face_vrm_names_mix_and_a_lost_head(
    harness: Callable[..., Harness], datasets: Path, tmp_path: Path
) -> None:
    """The VRM 1.0 preset: VMC sends its names with clip(M w); with two head markers
    occluded (< 3) the face part says head_lost and the weights are held. After a
    source restart nothing is held from the old run: the face starts afresh."""
    training, rots, pos = _face(datasets)
    training.save(tmp_path / "face.npz")
    h = harness({"config": "vrm1", "training": str(tmp_path / "face.npz")})
    rows = np.arange(100, 160)
    w = fs.synth_weights(np.random.default_rng(6), len(rows), 100.0)
    labels, frames = _stream(training, rots, pos, rows, w)
    lost = frames[-10:].copy()
    for n in ("LFHD", "RBHD"):
        lost[:, labels.index(n)] = np.nan
    h.announce(labels)
    h.prime(frames[0])
    h.send(np.concatenate([frames, lost]))
    h.wait_poses(len(rows) + 10)
    h.vmc.wait_frames(len(rows) + 10)
    vrm = load_face_config("vrm1")
    m = vrm.output_matrix(training.expression_names)
    for msg, frame in zip(h.poses, h.vmc.frames, strict=True):
        blends = _blends(frame)
        assert tuple(blends) == vrm.outputs
        want = np.clip(m @ msg.weights.astype(np.float64), 0.0, 1.0)
        np.testing.assert_allclose(list(blends.values()), want, atol=1e-5)
    held = h.poses[len(rows) - 1]
    for msg in h.poses[len(rows) :]:
        assert msg.face_flags & pose_stream.FACE_HEAD_LOST
        assert msg.face_markers is not None and np.isnan(msg.face_markers).all()
        np.testing.assert_array_equal(msg.weights, held.weights)
    assert h.live.daemon.stats.face_head_lost == 10
    # A restart (new label-set id), the head still lost: no pose or weights held
    # over from the previous run (the face solver was reset with the body's).
    h.poses.clear()
    h.announce(labels, label_set_id=4)
    h.next_id = 0  # frame numbers start again
    h.send(lost[:5])
    h.wait_poses(5)
    assert h.poses[0].flags & pose_stream.FRAME_RESTARTED
    for msg in h.poses:
        assert msg.face_flags & pose_stream.FACE_NEVER
        assert not msg.weights.any()


def test_face_capture_live_neutral_then_expressions(
    harness: Callable[..., Harness], datasets: Path, tmp_path: Path
) -> None:
    """No training set: the face is silent; `ctl face-capture neutral` (the CLI)
    then two expressions build one, saved, and the daemon solves with it at once."""
    training, rots, pos = _face(datasets)
    path = tmp_path / "face.npz"
    h = harness({"config": "arkit52", "training": str(path), "capture_frames": 12})
    k = training.expression_names
    jaw, smile = k.index("jawOpen"), k.index("mouthSmileLeft")
    rows = np.full(12, 50)  # the T-pose hold: a still head
    labels, neutral = _stream(training, rots, pos, rows, np.zeros((12, len(k))))
    h.announce(labels)
    h.prime(neutral[0])
    assert h.poses == [] and h.live.daemon.stats.face_solved == 0
    ep = h.live.tcp("control")
    # An expression before the neutral, and an unknown name, are refused.
    reply = h.live.ctl({"cmd": "face-capture", "name": "jawOpen"})
    assert not reply["ok"] and "neutral" in reply["error"]
    reply = h.live.ctl({"cmd": "face-capture", "name": "frown"})
    assert not reply["ok"] and "frown" in reply["error"]
    assert cli_main(["ctl", "--endpoint", ep, "face-capture", "neutral"]) == 0
    h.send(neutral)
    _wait_until(lambda: h.live.daemon.stats.face_captures == 1, "neutral captured")
    h.wait_pipelines()  # its pipeline, built off the loop
    h.wait_saved()  # its file, written off the loop
    t1 = TrainingSet.load(path)
    assert t1.k == 0 and t1.marker_names == training.marker_names
    # Neutral only: stabilized markers stream, no weights.
    h.wait_poses(len(neutral))
    h.poses.clear()
    h.send(neutral[:3])
    h.wait_poses(3)
    last = h.poses[-1]
    assert last.face_markers is not None and last.weights.size == 0
    np.testing.assert_allclose(last.face_markers, t1.neutral, atol=1e-6)
    for name, col in (("jawOpen", jaw), ("mouthSmileLeft", smile)):
        w = np.zeros((12, len(k)))
        w[:, col] = 1.0
        _, pose_frames = _stream(training, rots, pos, rows, w)
        argv = ["ctl", "--endpoint", ep, "face-capture", name, "--count", "12"]
        assert cli_main(argv) == 0
        before = h.live.daemon.stats.face_captures
        h.send(pose_frames)
        _wait_until(lambda b=before: h.live.daemon.stats.face_captures == b + 1, name)
        h.wait_pipelines()  # its pipeline, built off the loop
    h.wait_saved()
    t3 = TrainingSet.load(path)
    assert t3.expression_names == ("jawOpen", "mouthSmileLeft")  # config order
    np.testing.assert_allclose(t3.deltas[0], training.deltas[jaw], atol=2e-6)
    np.testing.assert_allclose(t3.deltas[1], training.deltas[smile], atol=2e-6)
    # Solve a mix of the two with the captured set, on a moving head.
    h.wait_poses(3 + 2 * 12)
    h.poses.clear()
    mix_rows = np.arange(100, 140)
    w = np.zeros((len(mix_rows), len(k)))
    w[:, jaw], w[:, smile] = 0.5, 0.3
    _, mix = _stream(training, rots, pos, mix_rows, w)
    h.send(mix)
    h.wait_poses(len(mix_rows))
    got = np.array([m.weights for m in h.poses])
    np.testing.assert_allclose(np.median(got, axis=0), [0.5, 0.3], atol=0.02)
    status = h.live.ctl({"cmd": "status"})["status"]["face"]
    assert status["expressions"] == ["jawOpen", "mouthSmileLeft"]
    assert status["captures"] == 3 and "saved" in status["last_capture"]


def test_a_hidden_key_marker_flags_its_shape_in_the_stream(
    harness: Callable[..., Harness], datasets: Path, tmp_path: Path
) -> None:
    """Issue 32: a facial marker that alone makes a shape observable (its key
    marker) hidden for 20 frames: that shape, and only the shapes it is key to, is
    held at its last weight and flagged ``hidden`` in the shape-state message of
    exactly those frames; the face flags say ``shape_held`` (and ``face_partial``),
    not a face-wide failure; every weight equals the offline solver's."""
    training, rots, pos = _face(datasets)
    training.save(tmp_path / "face.npz")
    h = harness({"config": "arkit52", "training": str(tmp_path / "face.npz")})
    seen = observability(training).observable
    unseen = tuple(np.array(training.expression_names)[~seen])
    solver = FaceSolver(training, head_weights=(1.0,) * 4, solved=seen)
    keys = solver.key_markers()
    shape, markers = next((s, m) for s, m in keys.items() if m)
    owners = [
        training.expression_names.index(s) for s, m in keys.items() if markers[0] in m
    ]
    rows = np.arange(100, 160)
    w = fs.synth_weights(np.random.default_rng(7), len(rows), 100.0, unseen)
    k0 = training.expression_names.index(shape)
    w[:, k0] = 0.6  # on before and while hidden: the held value is not 0
    w[40:, k0] = 0.2  # and changed after: released, it follows again
    labels, frames = _stream(training, rots, pos, rows, w)
    hide = slice(20, 40)
    frames[hide, labels.index(markers[0])] = np.nan
    h.announce(labels)
    h.prime(frames[0])
    h.send(frames)
    h.wait_poses(len(rows))
    _wait_until(lambda: h.pump() or len(h.shapes) >= len(rows), "shape states")
    oracle = FaceSolver(training, labels=labels, head_weights=(1.0,) * 4, solved=seen)
    out = oracle.new_output()
    f0 = frames[0].astype(np.float64)
    oracle.solve_frame(f0, np.isfinite(f0[:, 0]), out)  # the priming frame
    expect = np.zeros(len(rows), bool)
    expect[hide] = True
    for t, (msg, st) in enumerate(zip(h.poses, h.shapes, strict=True)):
        f64 = frames[t].astype(np.float64)
        oracle.solve_frame(f64, np.isfinite(f64[:, 0]), out)
        np.testing.assert_allclose(msg.weights, out.weights, atol=1e-6)
        np.testing.assert_array_equal(st.states, out.shape_state)
        hidden = (st.states & pose_stream.SHAPE_HIDDEN) > 0
        assert set(np.flatnonzero(hidden)) == (set(owners) if expect[t] else set())
        assert bool(msg.face_flags & pose_stream.FACE_SHAPE_HELD) == expect[t]
        assert not msg.face_flags & pose_stream.FACE_HEAD_LOST
    held = np.array([m.weights[k0] for m in h.poses[hide]])
    assert (held == h.poses[hide.start - 1].weights[k0]).all()
    assert held[0] == pytest.approx(0.6, abs=0.05)
    assert h.poses[-1].weights[k0] == pytest.approx(0.2, abs=0.05)
