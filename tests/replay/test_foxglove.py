"""Foxglove channels: decoded with the schemas the file declares (protobuf descriptors
read from the MCAP by ``mcap-protobuf-support``, not our code), bone positions and
frames checked against the synthetic performer they were written from."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from scipy.spatial.transform import Rotation

from retargetd.daemon.console.snapshot import SkeletonProgram, bone_endpoints
from retargetd.daemon.synth.performer import synthesize
from retargetd.protocols import osc_in
from retargetd.protocols.marker_input import LabelSet
from retargetd.replay import foxglove as fg
from retargetd.replay import recording as rf
from retargetd.replay.recorder import InputInfo, open_recorder
from retargetd.replay.takes import load_take

RATE_HZ = 60.0


def _performer() -> dict[str, Any]:
    """Bones of the synthetic performer: one per non-root segment s, from its
    parent's origin to its own, riding on (rotating with) the parent segment."""
    take = synthesize(seconds=1.5, rate_hz=RATE_HZ, dropout=0.15, seed=7)
    par = take.segment_parents
    segs = [s for s in range(len(par)) if par[s] >= 0]
    bone_of_child = {s: b for b, s in enumerate(segs)}
    ends = np.stack(
        [take.joint_pos_world[:, [par[s], s]] for s in segs], axis=1
    )  # (T, B, 2, 3)
    quats = take.world_from_segment_quat[:, [par[s] for s in segs]]
    parents = [bone_of_child.get(int(par[s]), -1) for s in segs]
    flags = np.zeros(quats.shape[:2], np.uint8)
    flags[20:30, 3] = 1
    return {
        "take": take,
        "bone_names": tuple(take.segment_names[s] for s in segs),
        "bone_parents": parents,
        "bone_ends": ends,
        "world_from_bone_quat": quats,
        "bone_flags": flags,
        "markers": take.markers_world,
        "marker_valid": take.valid,
    }


def _decoded(path: Path) -> dict[str, list[tuple[int, Any, Any]]]:
    out: dict[str, list[tuple[int, Any, Any]]] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message, msg in reader.iter_decoded_messages(
            topics=[fg.SCENE_TOPIC, fg.TF_TOPIC]
        ):
            out.setdefault(channel.topic, []).append((message.log_time, schema, msg))
    return out


def _quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate v by q = (w, x, y, z), with scipy (an oracle apart from our code)."""
    return Rotation.from_quat(q, scalar_first=True).apply(v)


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    r = Rotation.from_quat(a, scalar_first=True) * Rotation.from_quat(
        b, scalar_first=True
    )
    return r.as_quat(scalar_first=True)


def _check_frames(dec: dict[str, list[tuple[int, Any, Any]]], p: dict[str, Any],
                  times: np.ndarray) -> None:  # fmt: skip
    scene, tf = dec[fg.SCENE_TOPIC], dec[fg.TF_TOPIC]
    assert len(scene) == len(tf) == len(times)
    assert scene[0][1].name == "foxglove.SceneUpdate"
    assert tf[0][1].name == "foxglove.FrameTransforms"
    np.testing.assert_array_equal([t for t, _, _ in scene], times)
    names = p["bone_names"]
    for i, ((_, _, su), (_, _, ft)) in enumerate(zip(scene, tf, strict=True)):
        ents = {e.id: e for e in su.entities}
        line = ents["skeleton"].lines[0]
        pts = np.array([[q.x, q.y, q.z] for q in line.points]).reshape(-1, 2, 3)
        np.testing.assert_allclose(pts, p["bone_ends"][i], atol=1e-9)
        red = np.array([c.r > 0.8 and c.b < 0.3 for c in line.colors]).reshape(-1, 2)
        np.testing.assert_array_equal(red[:, 0], p["bone_flags"][i] != 0)
        spheres = ents["markers"].spheres
        seen = p["marker_valid"][i]
        got = np.array([[s.pose.position.x, s.pose.position.y, s.pose.position.z]
                        for s in spheres]).reshape(-1, 3)  # fmt: skip
        np.testing.assert_allclose(got, p["markers"][i][seen], atol=1e-9)
        # Compose the bone frames down from "world": each bone's origin and rotation.
        tfs = {t.child_frame_id: t for t in ft.transforms}
        assert len(tfs) == len(names)
        identity = (np.zeros(3), np.r_[1.0, 0, 0, 0])
        world: dict[str, tuple[np.ndarray, np.ndarray]] = {"world": identity}
        pending = dict(tfs)
        while pending:
            for child, t in list(pending.items()):
                if t.parent_frame_id in world:
                    po, pq = world[t.parent_frame_id]
                    tr = np.array([t.translation.x, t.translation.y, t.translation.z])
                    r = t.rotation
                    rq = np.array([r.w, r.x, r.y, r.z])
                    world[child] = (po + _quat_rotate(pq, tr), _quat_mul(pq, rq))
                    del pending[child]
        for b, name in enumerate(names):
            origin, q = world[fg.BONE_FRAME_PREFIX + name]
            np.testing.assert_allclose(origin, p["bone_ends"][i, b, 0], atol=1e-9)
            qt = p["world_from_bone_quat"][i, b]
            assert abs(abs(q @ qt) - 1.0) < 1e-9


def test_solve_mcap_decodes_with_the_files_own_schemas(tmp_path: Path) -> None:
    p = _performer()
    path = tmp_path / "take.mcap"
    n = fg.write_solve_mcap(path, rate_hz=RATE_HZ, start_ns=1_000, **{
        k: v for k, v in p.items() if k != "take"})  # fmt: skip
    assert n == p["take"].n_frames
    times = 1_000 + np.round(np.arange(n) * 1e9 / RATE_HZ).astype(np.int64)
    _check_frames(_decoded(path), p, times)


def test_foxglove_channels_sit_beside_a_recordings_own(tmp_path: Path) -> None:
    p = _performer()
    take = p["take"]
    labels = LabelSet(1, take.labels)
    src, dst = tmp_path / "rec.mcap", tmp_path / "rec_fox.mcap"
    rec = open_recorder(src, (InputInfo(name="osc", form="osc-compact"),))
    t0 = time.monotonic_ns()
    rec.record_packet("osc", rf.FORM_OSC_COMPACT, t0, osc_in.encode_labels(labels))
    for i, row in enumerate(take.markers_world):
        buf = osc_in.encode_compact_frame(i, i / RATE_HZ, labels.id, row)
        rec.record_packet(
            "osc", rf.FORM_OSC_COMPACT, t0 + round(i * 1e9 / RATE_HZ), buf
        )
    assert rec.close().dropped == 0
    raw = [m.log_time_ns for m in rf.read_recording(src).topic(rf.RAW_TOPIC)][1:]
    health = [{"input_rate_hz": RATE_HZ, "occluded": int((~v).sum())}
              for v in take.valid]  # fmt: skip
    n = fg.add_to_recording(
        src, dst, log_times_ns=raw, health=health,
        **{k: v for k, v in p.items() if k != "take"},
    )  # fmt: skip
    assert n == take.n_frames
    _check_frames(_decoded(dst), p, np.asarray(raw))
    # The recording's own channels are intact: it still loads as the same take.
    before, after = rf.read_recording(src), rf.read_recording(dst)
    assert [m.data for m in after.topic(rf.RAW_TOPIC)] == [
        m.data for m in before.topic(rf.RAW_TOPIC)
    ]
    assert after.metadata == before.metadata
    np.testing.assert_array_equal(load_take(dst).positions, load_take(src).positions)
    hs = after.json(fg.HEALTH_TOPIC)
    assert [h["occluded"] for h in hs] == [h["occluded"] for h in health]
    with open(dst, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    enc = {c.topic: c.message_encoding for c in summary.channels.values()}
    assert enc[fg.SCENE_TOPIC] == enc[fg.TF_TOPIC] == "protobuf"
    health_schema = next(
        c.schema_id for c in summary.channels.values() if c.topic == fg.HEALTH_TOPIC
    )
    assert (
        json.loads(summary.schemas[health_schema].data)["title"] == "retargetd.health"
    )


def test_channels_refuse_mismatched_parents() -> None:
    import io

    from mcap.writer import Writer

    w = Writer(io.BytesIO())
    w.start()
    with pytest.raises(ValueError, match="one entry per bone"):
        fg.FoxgloveChannels(w, ("a", "b"), (-1,))


def test_live_recorder_writes_the_skeleton_beside_the_packets(tmp_path: Path) -> None:
    from retargetd.replay.foxglove_recorder import open_skeleton_recorder

    p = _performer()
    take = p["take"]
    labels = LabelSet(1, take.labels)
    par = take.segment_parents
    program = SkeletonProgram.from_joint_pairs(
        [(int(par[s]), s) for s in range(len(par)) if par[s] >= 0]
    )

    def bone_ends_fn(joints: np.ndarray, quats: np.ndarray, root: np.ndarray) -> Any:
        return bone_endpoints(program, joints)  # what the daemon supplies

    path = tmp_path / "live.mcap"
    rec = open_skeleton_recorder(
        path, (InputInfo(name="osc", form="osc-compact"),),
        bone_names=p["bone_names"], bone_parents=p["bone_parents"],
        bone_ends_fn=bone_ends_fn,
    )  # fmt: skip
    t0 = time.monotonic_ns()
    rec.record_packet("osc", rf.FORM_OSC_COMPACT, t0, osc_in.encode_labels(labels))
    for i, row in enumerate(take.markers_world):
        t = t0 + round(i * 1e9 / RATE_HZ)
        buf = osc_in.encode_compact_frame(i, i / RATE_HZ, labels.id, row)
        rec.record_packet("osc", rf.FORM_OSC_COMPACT, t, buf)
        joints = take.joint_pos_world[i]
        assert rec.record_skeleton(
            t, joints, p["world_from_bone_quat"][i], joints[0], p["bone_flags"][i],
            take.markers_world[i], take.valid[i],
        )  # fmt: skip
    assert rec.close().dropped == 0
    raw = [m.log_time_ns for m in rf.read_recording(path).topic(rf.RAW_TOPIC)][1:]
    # Same clock as the packets: frame i's skeleton is logged with its packet.
    _check_frames(_decoded(path), p, np.asarray(raw))
    np.testing.assert_array_equal(
        load_take(path).positions, take.markers_world.astype(np.float32)
    )
