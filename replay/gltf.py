"""glTF 2.0 binary (``.glb``) writing: a skeleton as nodes and one animation.

The file (Khronos glTF 2.0 specification, "GLB File Format Specification" and
"Animations"):

- A 12-byte header: magic ``b"glTF"``, version 2, total length (uint32 little endian),
  then a JSON chunk (length, ``b"JSON"``, UTF-8 padded with spaces to 4 bytes) and a
  BIN chunk (length, ``b"BIN\\0"``, the buffer padded with zeros to 4 bytes).
- ``nodes``: one per joint, named, with its rest ``translation`` (metres, in the
  parent node's frame) and ``rotation``; ``children`` give the hierarchy. An optional
  scene root node holds a fixed rotation (e.g. our +Z-up world into glTF's +Y up).
- One ``animation``: per channel a sampler with ``interpolation: "LINEAR"`` (for
  ``rotation`` glTF defines LINEAR as slerp between the keys), ``input`` = key times
  (float32 seconds, strictly increasing, with ``min``/``max`` as the spec requires),
  ``output`` = float32 values: ``rotation`` as VEC4 quaternions in **x y z w** order
  (glTF's order; converted here from our w x y z), ``translation`` as VEC3 metres.

All accessors are tightly packed float32 in one buffer, each view 4-byte aligned.
The writer is independent of the solver: callers pass arrays (see
:mod:`retargetd.daemon.post.export_gltf` for a solved take).
"""

from __future__ import annotations

import json
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from retargetd.protocols.frames import F64Array

GLB_MAGIC = b"glTF"
GLB_VERSION = 2
_CHUNK_JSON = 0x4E4F534A
_CHUNK_BIN = 0x004E4942
_FLOAT = 5126  # GL_FLOAT
_PATHS = {"rotation": ("VEC4", 4), "translation": ("VEC3", 3)}


@dataclass(frozen=True, slots=True, kw_only=True)
class GltfChannel:
    """One animated property of one node.

    Attributes:
        node: joint index (into the ``names`` passed to :func:`write_glb`).
        path: ``"rotation"`` or ``"translation"``.
        times_s: (K,) float64 seconds, strictly increasing (also as float32).
        values: (K, 4) float64 quaternions (w, x, y, z), or (K, 3) float64 metres in
            the parent node's frame.
    """

    node: int
    path: str
    times_s: F64Array
    values: F64Array


def xyzw_from_wxyz(q: F64Array) -> F64Array:
    """glTF's quaternion order from ours.

    Args:
        q: (..., 4) float64 (w, x, y, z).

    Returns:
        (..., 4) float64 (x, y, z, w).
    """
    return np.concatenate([q[..., 1:], q[..., :1]], axis=-1)


class _Buffer:
    def __init__(self) -> None:
        self.data = bytearray()
        self.views: list[dict[str, Any]] = []
        self.accessors: list[dict[str, Any]] = []

    def add(self, arr: F64Array, kind: str, with_bounds: bool = False) -> int:
        f32 = np.ascontiguousarray(arr, dtype="<f4")
        offset = len(self.data)
        self.data += f32.tobytes()
        self.data += b"\0" * (-len(self.data) % 4)
        self.views.append({"buffer": 0, "byteOffset": offset, "byteLength": f32.nbytes})
        acc: dict[str, Any] = {
            "bufferView": len(self.views) - 1,
            "componentType": _FLOAT,
            "count": int(f32.shape[0]),
            "type": kind,
        }
        if with_bounds:
            flat = f32.reshape(f32.shape[0], -1)
            acc["min"] = [float(v) for v in flat.min(axis=0)]
            acc["max"] = [float(v) for v in flat.max(axis=0)]
        self.accessors.append(acc)
        return len(self.accessors) - 1


def _check_channel(ch: GltfChannel, n_nodes: int) -> None:
    if ch.path not in _PATHS:
        raise ValueError(
            f"channel path must be one of {sorted(_PATHS)}; got {ch.path!r}"
        )
    if not 0 <= ch.node < n_nodes:
        raise ValueError(f"channel node must be in 0..{n_nodes - 1}; got {ch.node}")
    width = _PATHS[ch.path][1]
    t = np.asarray(ch.times_s, dtype=np.float64)
    if t.ndim != 1 or len(t) < 1 or ch.values.shape != (len(t), width):
        raise ValueError(
            f"channel of node {ch.node} ({ch.path}) needs times (K,) and values "
            f"(K, {width}); got {t.shape} and {ch.values.shape}"
        )
    t32 = t.astype(np.float32)
    if np.any(np.diff(t32) <= 0.0):
        raise ValueError(
            f"channel of node {ch.node} ({ch.path}): times must increase strictly "
            "(also as float32)"
        )
    if not np.isfinite(ch.values).all():
        raise ValueError(f"channel of node {ch.node} ({ch.path}) has non-finite values")


def write_glb(
    path: str | Path,
    *,
    names: Sequence[str],
    parents: Sequence[int],
    rest_translation: F64Array,
    rest_rotation_quat: F64Array,
    channels: Sequence[GltfChannel],
    scene_root_quat: F64Array | None = None,
    scene_root_name: str = "world",
    animation_name: str = "take",
    generator: str = "retargetd",
) -> None:
    """Write a skeleton and its animation as a ``.glb`` file (module docstring).

    Args:
        path: destination file.
        names: (N,) node names.
        parents: (N,) parent index per node, -1 for a root; parents before children
            is not required.
        rest_translation: (N, 3) float64, metres, each node's origin in its parent's
            frame (roots: in the scene root's).
        rest_rotation_quat: (N, 4) float64 (w, x, y, z), each node's rest
            ``parent_from_node``.
        channels: the animated properties.
        scene_root_quat: (4,) float64 (w, x, y, z): if given, the roots hang under a
            node ``scene_root_name`` with this rotation (``gltf_from_world``).
        scene_root_name: that node's name.
        animation_name: the animation's name.
        generator: ``asset.generator``.

    Raises:
        ValueError: inconsistent shapes, bad parents or channels.
    """
    n = len(names)
    par = np.asarray(parents, dtype=np.int64)
    trans = np.asarray(rest_translation, dtype=np.float64)
    quat = np.asarray(rest_rotation_quat, dtype=np.float64)
    if par.shape != (n,) or trans.shape != (n, 3) or quat.shape != (n, 4):
        raise ValueError(
            f"need parents ({n},), rest_translation ({n}, 3), rest_rotation_quat "
            f"({n}, 4); got {par.shape}, {trans.shape}, {quat.shape}"
        )
    if np.any((par < -1) | (par >= n)) or np.any(par == np.arange(n)):
        raise ValueError(f"parents must be -1 or another node's index; got {par}")
    for ch in channels:
        _check_channel(ch, n)
    quat = quat / np.linalg.norm(quat, axis=-1, keepdims=True)  # glTF: unit rotations
    nodes: list[dict[str, Any]] = []
    for i in range(n):
        node: dict[str, Any] = {
            "name": str(names[i]),
            "translation": [float(v) for v in trans[i]],
            "rotation": [float(v) for v in xyzw_from_wxyz(quat[i])],
        }
        kids = [int(c) for c in np.flatnonzero(par == i)]
        if kids:
            node["children"] = kids
        nodes.append(node)
    roots = [int(r) for r in np.flatnonzero(par < 0)]
    if scene_root_quat is not None:
        q = np.asarray(scene_root_quat, dtype=np.float64)
        q = q / np.linalg.norm(q)
        nodes.append(
            {
                "name": scene_root_name,
                "rotation": [float(v) for v in xyzw_from_wxyz(q)],
                "children": roots,
            }
        )
        roots = [n]
    buf = _Buffer()
    samplers, targets = [], []
    for ch in channels:
        values = ch.values
        if ch.path == "rotation":
            values = values / np.linalg.norm(values, axis=-1, keepdims=True)
            values = xyzw_from_wxyz(values)
        inp = buf.add(np.asarray(ch.times_s), "SCALAR", with_bounds=True)
        out = buf.add(values, _PATHS[ch.path][0])
        samplers.append({"input": inp, "output": out, "interpolation": "LINEAR"})
        targets.append(
            {"sampler": len(samplers) - 1, "target": {"node": ch.node, "path": ch.path}}
        )
    doc: dict[str, Any] = {
        "asset": {"version": "2.0", "generator": generator},
        "scene": 0,
        "scenes": [{"nodes": roots}],
        "nodes": nodes,
    }
    if channels:
        doc["buffers"] = [{"byteLength": len(buf.data)}]
        doc["bufferViews"] = buf.views
        doc["accessors"] = buf.accessors
        doc["animations"] = [
            {"name": animation_name, "samplers": samplers, "channels": targets}
        ]
    js = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    js += b" " * (-len(js) % 4)
    chunks = struct.pack("<II", len(js), _CHUNK_JSON) + js
    if channels:
        chunks += struct.pack("<II", len(buf.data), _CHUNK_BIN) + bytes(buf.data)
    header = GLB_MAGIC + struct.pack("<II", GLB_VERSION, 12 + len(chunks))
    Path(path).write_bytes(header + chunks)
