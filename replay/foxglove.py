"""Foxglove channels in our MCAP files: the performer in 3D with no layout work.

Beside a recording's own channels (``retargetd.replay.recorder``), or in a file of
their own (:func:`write_solve_mcap`, for ``retargetd solve --out take.mcap``), these
channels carry the markers and the solved skeleton under Foxglove's published schemas,
encoded with Foxglove's own SDK (PyPI ``foxglove-sdk``, ``foxglove.messages``: the
schema records are its protobuf ``FileDescriptorSet`` s, so any reader decodes them
from the file alone):

``/foxglove/scene`` (``foxglove.SceneUpdate``)
    entity ``skeleton``: one ``LineList`` with both ends of every determined bone
    (blue; red where the bone is flagged), metres, frame ``world``; entity
    ``markers``: one sphere per seen marker (20 mm, orange).
``/foxglove/tf`` (``foxglove.FrameTransforms``)
    one frame per determined bone, child ``bone/<name>`` of its parent bone's frame
    (the root's parent is ``world``): translation = the bone's origin in its parent's
    frame, rotation = ``parent_from_bone`` (both world-referenced: ``world`` is Z up,
    as in the internal frame).
``/foxglove/health`` (JSON, ``retargetd.health`` JSON schema)
    the health figures for Foxglove's plot panel (``/foxglove/health.<field>``):
    live, every 0.5 s (``daemon.live.recording.health_figures``); in a solve's own
    file, one per frame (:func:`solve_health`).

``/face/weights`` (JSON, ``retargetd.face`` JSON schema; only with a face)
    per frame: ``t_ns``, ``flags`` (the pose stream's face flags, PROTOCOLS.md
    section 6), ``weights`` (``{shape: weight}``, every shape of the training set;
    Foxglove plots ``/face/weights.weights.jawOpen``), ``held`` (the shapes held
    this frame: a key marker hidden) and ``unobserved`` (the shapes left out of the
    solve, sent as 0).

Log times are those of the frames (nanoseconds; see :class:`FoxgloveChannels`).
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from retargetd.protocols.frames import F64Array

SCENE_TOPIC = "/foxglove/scene"
TF_TOPIC = "/foxglove/tf"
HEALTH_TOPIC = "/foxglove/health"
FACE_TOPIC = "/face/weights"
WORLD_FRAME = "world"
BONE_FRAME_PREFIX = "bone/"

#: RGBA 0-1, as the console draws them (``retargetd.daemon.console.app``).
BONE_RGBA = (40 / 255, 90 / 255, 230 / 255, 1.0)
FLAGGED_RGBA = (230 / 255, 30 / 255, 30 / 255, 1.0)
MARKER_RGBA = (1.0, 160 / 255, 0.0, 1.0)
#: Drawn sizes, metres: 25 mm bones, 20 mm markers (optical markers are 9.5-25 mm
#: spheres, Vicon and OptiTrack catalogues).
BONE_THICKNESS_M = 0.025
MARKER_SIZE_M = 0.02

_HEALTH_SCHEMA = {
    "title": "retargetd.health",
    "type": "object",
    "properties": {
        "t_ns": {"type": "integer"},
        "input_rate_hz": {"type": "number"},
        "drops": {"type": "integer"},
        "occluded": {"type": "integer"},
        "validation_flags": {"type": "integer"},
        "latency_p50_ms": {"type": "object"},
        "latency_p99_ms": {"type": "object"},
        "held_bones": {"type": "integer"},
        "marker_rms_mm": {"type": ["number", "null"]},
    },
    "required": ["t_ns"],
}


_FACE_SCHEMA = {
    "title": "retargetd.face",
    "type": "object",
    "properties": {
        "t_ns": {"type": "integer"},
        "flags": {"type": "integer"},
        "weights": {"type": "object", "additionalProperties": {"type": "number"}},
        "held": {"type": "array", "items": {"type": "string"}},
        "unobserved": {"type": "array", "items": {"type": "string"}},
    },
    "required": ["t_ns", "flags", "weights"],
}
#: The per-shape state bits of ``shape_state`` (the pose stream's ``RTDF``, which
#: replay may not import from the daemon: protocols/pose_stream.py SHAPE_*).
_SHAPE_UNOBSERVED = 1
_SHAPE_HIDDEN = 2


def _stamp(t_ns: int) -> Any:
    from foxglove.messages import Timestamp

    return Timestamp(int(t_ns // 1_000_000_000), int(t_ns % 1_000_000_000))


def _rotate(q: F64Array, v: F64Array) -> F64Array:
    """v (..., 3) rotated by unit quaternions q (..., 4) w x y z (replay may not
    import the daemon's rotations)."""
    w, u = q[..., :1], q[..., 1:]
    return v + 2.0 * np.cross(u, np.cross(u, v) + w * v)


def _mul(a: F64Array, b: F64Array) -> F64Array:
    """Hamilton products a * b of (..., 4) w x y z quaternions."""
    w1, v1, w2, v2 = a[..., :1], a[..., 1:], b[..., :1], b[..., 1:]
    w = w1 * w2 - np.sum(v1 * v2, axis=-1, keepdims=True)
    return np.concatenate([w, w1 * v2 + w2 * v1 + np.cross(v1, v2)], axis=-1)


class FoxgloveChannels:
    """Registers the Foxglove channels on an open ``mcap.writer.Writer`` and writes
    them: beside whatever else that writer holds (a recording's channels).

    Call from the thread that owns the writer (the recorder's writer thread): the
    messages are built here (Python objects, protobuf encoding), never on the loop.

    Args:
        writer: a started ``mcap.writer.Writer``.
        bone_names: (B,) bone names (frame names ``bone/<name>``).
        bone_parents: (B,) parent bone index, -1 for the root.
        face_shapes: (K,) the face's shape names: registers ``/face/weights``.
    """

    def __init__(
        self,
        writer: Any,
        bone_names: Sequence[str],
        bone_parents: Sequence[int],
        face_shapes: Sequence[str] = (),
    ) -> None:
        from foxglove.messages import FrameTransforms, SceneUpdate

        self._w = writer
        self.bone_names = tuple(bone_names)
        self.bone_parents = np.asarray(bone_parents, np.int64)
        if self.bone_parents.shape != (len(self.bone_names),):
            raise ValueError("bone_parents must have one entry per bone")
        channels = {}
        for topic, cls in ((SCENE_TOPIC, SceneUpdate), (TF_TOPIC, FrameTransforms)):
            sch = cls.get_schema()
            sid = writer.register_schema(sch.name, sch.encoding, sch.data)
            channels[topic] = writer.register_channel(topic, "protobuf", sid)
        hid = writer.register_schema(
            "retargetd.health", "jsonschema", json.dumps(_HEALTH_SCHEMA).encode()
        )
        channels[HEALTH_TOPIC] = writer.register_channel(HEALTH_TOPIC, "json", hid)
        self.face_shapes = tuple(face_shapes)
        if self.face_shapes:
            fid = writer.register_schema(
                "retargetd.face", "jsonschema", json.dumps(_FACE_SCHEMA).encode()
            )
            channels[FACE_TOPIC] = writer.register_channel(FACE_TOPIC, "json", fid)
        self._channels = channels
        self._frames = [BONE_FRAME_PREFIX + n for n in self.bone_names]
        self._parent_frames = [
            WORLD_FRAME if p < 0 else self._frames[p] for p in self.bone_parents
        ]
        self._seq = dict.fromkeys(channels, 0)

    def _add(self, topic: str, t_ns: int, data: bytes) -> None:
        self._seq[topic] += 1
        self._w.add_message(
            self._channels[topic], t_ns, data, t_ns, sequence=self._seq[topic]
        )

    def write_frame(
        self,
        t_ns: int,
        *,
        bone_ends: F64Array,
        world_from_bone_quat: F64Array,
        bone_flags: np.ndarray | None = None,
        markers: F64Array | None = None,
        marker_valid: np.ndarray | None = None,
    ) -> None:
        """Write one frame's scene and bone frames.

        Args:
            t_ns: log time, nanoseconds (the recording's clock).
            bone_ends: (B, 2, 3) metres world, origin and tip per bone (NaN:
                undetermined, left out); see
                ``retargetd.daemon.console.snapshot.bone_endpoints``.
            world_from_bone_quat: (B, 4) w x y z.
            bone_flags: (B,) uint8, non-zero = flagged (drawn red).
            markers: (M, 3) metres world.
            marker_valid: (M,) bool, seen this frame (default: finite rows).
        """
        from foxglove.messages import (
            Color,
            FrameTransform,
            FrameTransforms,
            LinePrimitive,
            LinePrimitiveLineType,
            Point3,
            Pose,
            Quaternion,
            SceneEntity,
            SceneUpdate,
            SpherePrimitive,
            Vector3,
        )

        stamp = _stamp(t_ns)
        ok = np.isfinite(bone_ends).all(axis=(1, 2))
        flags: np.ndarray = (
            np.zeros(ok.shape[0], dtype=np.bool_)
            if bone_flags is None
            else np.asarray(bone_flags) != 0
        )
        # Shared sub-messages (copied into each message on encode).
        blue, red = (
            Color(r=c[0], g=c[1], b=c[2], a=c[3]) for c in (BONE_RGBA, FLAGGED_RGBA)
        )
        pts = [
            Point3(x=x, y=y, z=z) for x, y, z in bone_ends[ok].reshape(-1, 3).tolist()
        ]
        cols = [red if f else blue for f in np.repeat(flags[ok], 2).tolist()]
        entities = [
            SceneEntity(
                timestamp=stamp,
                frame_id=WORLD_FRAME,
                id="skeleton",
                lines=[
                    LinePrimitive(
                        type=LinePrimitiveLineType.LineList,
                        thickness=BONE_THICKNESS_M,
                        points=pts,
                        colors=cols,
                    )
                ],
            )
        ]
        if markers is not None:
            seen = np.isfinite(markers).all(axis=1)
            if marker_valid is not None:
                seen &= marker_valid
            r, g, b_, a = MARKER_RGBA
            size = Vector3(x=MARKER_SIZE_M, y=MARKER_SIZE_M, z=MARKER_SIZE_M)
            orange, upright = Color(r=r, g=g, b=b_, a=a), Quaternion(w=1.0)
            spheres = [
                SpherePrimitive(
                    pose=Pose(position=Vector3(x=x, y=y, z=z), orientation=upright),
                    size=size,
                    color=orange,
                )
                for x, y, z in markers[seen].tolist()
            ]
            entities.append(
                SceneEntity(
                    timestamp=stamp,
                    frame_id=WORLD_FRAME,
                    id="markers",
                    spheres=spheres,
                )
            )
        self._add(SCENE_TOPIC, t_ns, SceneUpdate(entities=entities).encode())
        # Bone frames, each in its parent's: t = parent^-1 (origin - parent origin),
        # r = parent^-1 * bone (world_from_bone for a root), for all bones at once.
        q = world_from_bone_quat
        par = self.bone_parents
        root = par < 0
        pi = np.where(root, 0, par)
        inv = np.where(
            root[:, None], (1.0, 0.0, 0.0, 0.0), q[pi] * (1.0, -1.0, -1.0, -1.0)
        )
        base = np.where(root[:, None], 0.0, bone_ends[pi, 0])
        trans = _rotate(inv, bone_ends[:, 0] - base)
        rot = _mul(inv, q)
        good = ok & np.isfinite(q).all(axis=1)
        good = np.asarray(good)
        good &= root | good[pi]
        transforms = [
            FrameTransform(
                timestamp=stamp,
                parent_frame_id=self._parent_frames[bi],
                child_frame_id=self._frames[bi],
                translation=Vector3(x=tx, y=ty, z=tz),
                rotation=Quaternion(w=rw, x=rx, y=ry, z=rz),
            )
            for bi, (tx, ty, tz), (rw, rx, ry, rz) in zip(
                np.flatnonzero(good).tolist(),
                trans[good].tolist(),
                rot[good].tolist(),
                strict=True,
            )
        ]
        self._add(TF_TOPIC, t_ns, FrameTransforms(transforms=transforms).encode())

    def write_health(self, t_ns: int, figures: Mapping[str, Any]) -> None:
        """Write one health sample (JSON: ``t_ns`` and the given figures)."""
        msg = {"t_ns": int(t_ns), **figures}
        self._add(HEALTH_TOPIC, t_ns, json.dumps(msg, allow_nan=False).encode())

    def write_face(
        self, t_ns: int, flags: int, weights: np.ndarray, shape_state: np.ndarray
    ) -> None:
        """Write one frame of the face (``/face/weights``, module docstring).

        Args:
            t_ns: log time, nanoseconds.
            flags: the face flag bits.
            weights: (K,) in ``face_shapes`` order.
            shape_state: (K,) uint8 per-shape state bits.
        """
        names = self.face_shapes
        st = np.asarray(shape_state)
        msg = {
            "t_ns": int(t_ns),
            "flags": int(flags),
            "weights": dict(
                zip(names, np.asarray(weights, float).tolist(), strict=True)
            ),
            "held": [n for n, b in zip(names, st, strict=True) if b & _SHAPE_HIDDEN],
            "unobserved": [
                n for n, b in zip(names, st, strict=True) if b & _SHAPE_UNOBSERVED
            ],
        }
        self._add(FACE_TOPIC, t_ns, json.dumps(msg, allow_nan=False).encode())


def write_solve_mcap(
    path: str | os.PathLike[str],
    *,
    bone_names: Sequence[str],
    bone_parents: Sequence[int],
    bone_ends: F64Array,
    world_from_bone_quat: F64Array,
    rate_hz: float,
    bone_flags: np.ndarray | None = None,
    markers: F64Array | None = None,
    marker_valid: np.ndarray | None = None,
    start_ns: int = 0,
    library: str = "retargetd",
    progress: Callable[[int], None] | None = None,
    health: Sequence[Mapping[str, Any]] | None = None,
    face: Mapping[str, Any] | None = None,
) -> int:
    """Write a solved take as an MCAP of Foxglove channels (``solve --out x.mcap``).

    Args:
        path: the file (created or truncated).
        bone_names / bone_parents: as :class:`FoxgloveChannels`.
        bone_ends: (T, B, 2, 3) metres world.
        world_from_bone_quat: (T, B, 4) w x y z.
        rate_hz: frame rate: frame ``i`` is logged at ``start_ns + i / rate_hz``.
        bone_flags: (T, B) uint8, or None.
        markers / marker_valid: (T, M, 3) metres and (T, M) bool, or None.
        start_ns: log time of frame 0, nanoseconds.
        library: the MCAP header's library string.
        progress: called with 1 after each frame written (a progress bar).
        health: optional (T,) health figures per frame (:func:`solve_health`).
        face: optional, the face per frame (``/face/weights``): ``face_shapes``
            (K,), ``face_weights`` (T, K), ``face_shape_state`` (T, K) and
            ``face_flags`` (T,), as ``retargetd solve --face`` names them. With no
            bone (``bone_ends`` (T, 0, 2, 3)) the file holds the face and markers.

    Returns:
        The number of frames written.
    """
    from mcap.writer import CompressionType, Writer

    n = int(bone_ends.shape[0])
    with open(path, "wb") as out:
        w = Writer(out, compression=CompressionType.ZSTD)
        w.start(profile="", library=library)
        shapes = () if face is None else [str(x) for x in face["face_shapes"]]
        ch = FoxgloveChannels(w, bone_names, bone_parents, shapes)
        for i in range(n):
            t_ns = start_ns + round(i * 1e9 / rate_hz)
            ch.write_frame(
                t_ns,
                bone_ends=bone_ends[i],
                world_from_bone_quat=world_from_bone_quat[i],
                bone_flags=None if bone_flags is None else bone_flags[i],
                markers=None if markers is None else markers[i],
                marker_valid=None if marker_valid is None else marker_valid[i],
            )
            if health is not None:
                ch.write_health(t_ns, health[i])
            if face is not None:
                ch.write_face(
                    t_ns, int(face["face_flags"][i]), face["face_weights"][i],
                    face["face_shape_state"][i],
                )  # fmt: skip
            if progress is not None:
                progress(1)
        w.finish()
    return n


def solve_health(
    rate_hz: float,
    bone_flags: np.ndarray,
    marker_valid: np.ndarray | None = None,
    marker_rms: F64Array | None = None,
) -> list[dict[str, Any]]:
    """Per frame of an offline solve, the ``/foxglove/health`` figures it has: the
    take's rate (``input_rate_hz``), no ``drops`` (a file loses nothing), the markers
    not seen (``occluded``), the bones held (``held_bones``: any flag) and the fit's
    marker residual RMS in mm (``marker_rms_mm``; None for the construction or a
    frame it did not fit). The live figures it cannot have (latencies, the
    validator's flags) are left out.

    Args:
        rate_hz: the take's frame rate.
        bone_flags: (T, B) the solve's bone flags.
        marker_valid: (T, M) the markers seen, or None (occluded 0).
        marker_rms: (T,) metres, or None.
    """
    flags = np.asarray(bone_flags)
    n = flags.shape[0]
    held = (flags != 0).sum(axis=1)
    occ = (
        np.zeros(n, np.int64)
        if marker_valid is None
        else (~np.asarray(marker_valid, bool)).sum(axis=1)
    )
    out = []
    for i in range(n):
        rms = None if marker_rms is None else float(marker_rms[i])
        out.append({
            "input_rate_hz": float(rate_hz), "drops": 0, "occluded": int(occ[i]),
            "held_bones": int(held[i]),
            "marker_rms_mm": None if rms is None or not np.isfinite(rms)
            else round(1e3 * rms, 4),
        })  # fmt: skip
    return out


def add_to_recording(
    src: str | os.PathLike[str],
    dst: str | os.PathLike[str],
    *,
    bone_names: Sequence[str],
    bone_parents: Sequence[int],
    log_times_ns: Sequence[int],
    bone_ends: F64Array,
    world_from_bone_quat: F64Array,
    bone_flags: np.ndarray | None = None,
    markers: F64Array | None = None,
    marker_valid: np.ndarray | None = None,
    health: Sequence[Mapping[str, Any]] | None = None,
) -> int:
    """Copy a recording and add the Foxglove channels beside its own.

    Every schema, channel, message (same log and publish times, sequence numbers) and
    metadata record of ``src`` is copied to ``dst``; the Foxglove messages for frame
    ``i`` are logged at ``log_times_ns[i]`` (the recording's clock, e.g. the log time
    of the frame's raw packet), merged in time order.

    Args:
        src / dst: the recording and the new file (must differ).
        log_times_ns: (T,) log time per solved frame, nanoseconds.
        health: optional (T,) health figures per frame (:meth:`write_health`).
        others: (T, ...) per frame, as :func:`write_solve_mcap`.

    Returns:
        Foxglove frames written.
    """
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer

    if os.path.abspath(src) == os.path.abspath(dst):
        raise ValueError("add_to_recording: src and dst must differ")
    times = np.asarray(log_times_ns, np.int64)
    order = np.argsort(times, kind="stable")
    with open(src, "rb") as fin, open(dst, "wb") as fout:
        reader = make_reader(fin)
        header = reader.get_header()
        w = Writer(fout, compression=CompressionType.ZSTD)
        w.start(profile=header.profile, library=header.library)
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        ch = FoxgloveChannels(w, bone_names, bone_parents)
        summary = reader.get_summary()  # None for a crash-truncated recording
        if summary is not None:  # channels without messages too
            for sid, sch in sorted(summary.schemas.items()):
                schemas[sid] = w.register_schema(sch.name, sch.encoding, sch.data)
            for cid, chan in sorted(summary.channels.items()):
                channels[cid] = w.register_channel(
                    chan.topic, chan.message_encoding,
                    schemas.get(chan.schema_id, 0), dict(chan.metadata),
                )  # fmt: skip
        k = 0

        def flush_until(t: int | None) -> None:
            nonlocal k
            while k < len(order) and (t is None or times[order[k]] <= t):
                i = int(order[k])
                ch.write_frame(
                    int(times[i]),
                    bone_ends=bone_ends[i],
                    world_from_bone_quat=world_from_bone_quat[i],
                    bone_flags=None if bone_flags is None else bone_flags[i],
                    markers=None if markers is None else markers[i],
                    marker_valid=None if marker_valid is None else marker_valid[i],
                )
                if health is not None:
                    ch.write_health(int(times[i]), health[i])
                k += 1

        for schema, channel, message in reader.iter_messages(log_time_order=True):
            flush_until(message.log_time)
            if schema is not None and schema.id not in schemas:
                schemas[schema.id] = w.register_schema(
                    schema.name, schema.encoding, schema.data
                )
            if channel.id not in channels:
                channels[channel.id] = w.register_channel(
                    channel.topic, channel.message_encoding,
                    schemas.get(channel.schema_id, 0), dict(channel.metadata),
                )  # fmt: skip
            w.add_message(
                channels[channel.id], message.log_time, message.data,
                message.publish_time, sequence=message.sequence,
            )  # fmt: skip
        flush_until(None)
        fin.seek(0)
        for meta in make_reader(fin).iter_metadata():
            w.add_metadata(meta.name, dict(meta.metadata))
        w.finish()
    return len(order)
