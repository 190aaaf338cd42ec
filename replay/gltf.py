"""glTF 2.0 binary (``.glb``) writing: a skinned skeleton, an animation, capsules.

The file (Khronos glTF 2.0 specification, "GLB File Format Specification",
"Skins" and "Animations"):

- A 12-byte header: magic ``b"glTF"``, version 2, total length (uint32 little endian),
  then a JSON chunk (length, ``b"JSON"``, UTF-8 padded with spaces to 4 bytes) and a
  BIN chunk (length, ``b"BIN\\0"``, the buffer padded with zeros to 4 bytes).
- ``nodes``: first one per joint, in the caller's order, named, with its rest
  ``translation`` (metres, in the parent node's frame) and ``rotation``, and optional
  ``extras``; ``children`` give the hierarchy. Then an optional scene root node
  holding a fixed rotation (e.g. our +Z-up world into glTF's +Y up), then, with
  capsules, the mesh node (a scene root with no transform, as the spec asks of a
  skinned mesh's node).
- ``skins[0]``: ``joints`` = every joint node; ``inverseBindMatrices`` = one MAT4
  float32 per joint (column-major), the inverse of the joint's scene transform in the
  rest pose (the bind pose *is* the rest pose), ``[R^T, -R^T t; 0 0 0 1]``;
  ``skeleton`` = the root joint when there is one and no scene root. Under a scene
  root it is left out: the IBMs are relative to the scene (the skinned mesh's space,
  as the spec has them), and Blender's importer (3.4) reads them as relative to the
  skeleton node's parent when ``skeleton`` is given, which would turn the bind pose
  by the scene root's rotation; without it Blender binds at the nodes' rest, which
  is the same pose. Written even without a mesh, so importers build an armature.
- ``meshes[0]`` (with capsules, :mod:`retargetd.replay.gltf_mesh`): one triangle
  primitive, ``POSITION`` and ``NORMAL`` float32 VEC3 in the bind pose's scene
  coordinates (``min``/``max`` on POSITION), ``JOINTS_0`` unsigned byte (unsigned
  short past 255 joints) VEC4 ``(j, 0, 0, 0)``, ``WEIGHTS_0`` float32 VEC4
  ``(1, 0, 0, 0)`` (each vertex moves rigidly with its one joint), ``indices``
  unsigned short (unsigned int past 65535 vertices), one grey material.
- One ``animation``: per channel a sampler with ``interpolation: "LINEAR"`` (for
  ``rotation`` glTF defines LINEAR as slerp between the keys), ``input`` = key times
  (float32 seconds, strictly increasing, with ``min``/``max`` as the spec requires),
  ``output`` = float32 values: ``rotation`` as VEC4 quaternions in **x y z w** order
  (glTF's order; converted here from our w x y z), ``translation`` as VEC3 metres.
  Channels target the joint nodes.

- With a face (:class:`MorphFace`): one more mesh, a ``POINTS`` primitive (mode 0) of
  the stabilized facial markers' neutral positions (float32 VEC3, head coordinates,
  metres) with one morph target per shape (its ``POSITION`` displacements, with
  ``min``/``max``), the shape names in the mesh's ``extras.targetNames`` (the
  convention Blender's importer reads into shape-key names) and default ``weights``
  0; its node (named as the face) hangs under the scene root and carries the head
  pose (``translation``, ``rotation`` channels: ``world_from_head``) and the
  ``weights`` channel: a LINEAR sampler whose output holds K scalars per key, the
  weights of that frame (the spec's layout for morph-target animation). With no
  joints (a face alone) there is no skin.

Every accessor is tightly packed in its own buffer view, each view 4-byte aligned;
vertex and index views carry their ``target``. The writer is independent of the
solver: callers pass arrays (see :mod:`retargetd.daemon.post.export_gltf` for a
solved take).
"""

from __future__ import annotations

import json
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from retargetd.protocols.frames import F64Array
from retargetd.replay.gltf_mesh import Capsule, capsule_mesh

GLB_MAGIC = b"glTF"
GLB_VERSION = 2
_CHUNK_JSON = 0x4E4F534A
_CHUNK_BIN = 0x004E4942
#: glTF componentType per little-endian numpy dtype (GL enums).
_COMPONENT = {"<f4": 5126, "|u1": 5121, "<u2": 5123, "<u4": 5125}
_ARRAY_BUFFER = 34962  # bufferView.target of vertex attributes
_ELEMENT_ARRAY_BUFFER = 34963  # ... of indices
#: The capsules' material: a light grey, matte (glTF metallic-roughness).
CAPSULE_BASE_COLOR = (0.8, 0.8, 0.8, 1.0)
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


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class MorphFace:
    """A face as morph targets on a point mesh, and its animation.

    Attributes:
        name: the mesh's and its node's name.
        neutral: (V, 3) float64, metres, head coordinates: the neutral points.
        targets: (K, V, 3) float64, metres: each shape's displacement.
        target_names: (K,) shape names.
        times_s: (T,) float64 seconds, strictly increasing (also as float32).
        weights: (T, K) float in [0, 1].
        world_from_head_quat: (T, 4) float64 (w, x, y, z).
        head_pos: (T, 3) float64, metres, in the scene root's frame (world).
    """

    name: str
    neutral: F64Array
    targets: F64Array
    target_names: tuple[str, ...]
    times_s: F64Array
    weights: npt.NDArray[np.floating[Any]]
    world_from_head_quat: F64Array
    head_pos: F64Array


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

    def add(
        self,
        arr: np.ndarray,
        kind: str,
        *,
        dtype: str = "<f4",
        with_bounds: bool = False,
        target: int | None = None,
    ) -> int:
        packed = np.ascontiguousarray(arr, dtype=dtype)
        offset = len(self.data)
        self.data += packed.tobytes()
        self.data += b"\0" * (-len(self.data) % 4)
        view: dict[str, Any] = {
            "buffer": 0,
            "byteOffset": offset,
            "byteLength": packed.nbytes,
        }
        if target is not None:
            view["target"] = target
        self.views.append(view)
        acc: dict[str, Any] = {
            "bufferView": len(self.views) - 1,
            "componentType": _COMPONENT[np.dtype(dtype).str],
            "count": int(packed.shape[0]),
            "type": kind,
        }
        if with_bounds:
            flat = packed.reshape(packed.shape[0], -1)
            cast = float if packed.dtype.kind == "f" else int
            acc["min"] = [cast(v) for v in flat.min(axis=0)]
            acc["max"] = [cast(v) for v in flat.max(axis=0)]
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


def scene_from_joint_rest(
    parents: Sequence[int] | npt.NDArray[np.int64],
    rest_translation: F64Array,
    rest_rotation_quat: F64Array,
    scene_root_quat: F64Array | None = None,
) -> F64Array:
    """Each joint's rest transform in scene coordinates (the bind pose).

    Args:
        parents: (N,) parent per joint, -1 for a root (any order, no cycles).
        rest_translation: (N, 3) float64, origin in the parent's frame.
        rest_rotation_quat: (N, 4) float64 (w, x, y, z) unit, ``parent_from_joint``.
        scene_root_quat: (4,) float64 (w, x, y, z), the roots' parent rotation.

    Returns:
        (N, 4, 4) float64 ``scene_from_joint`` (rotation and translation).
    """
    par = np.asarray(parents, dtype=np.int64)
    n = len(par)
    local = np.tile(np.eye(4), (n, 1, 1))
    local[:, :3, :3] = Rotation.from_quat(
        rest_rotation_quat, scalar_first=True
    ).as_matrix()
    local[:, :3, 3] = rest_translation
    root = np.eye(4)
    if scene_root_quat is not None:
        root[:3, :3] = Rotation.from_quat(
            scene_root_quat, scalar_first=True
        ).as_matrix()
    out = np.full((n, 4, 4), np.nan)
    done = np.zeros(n, dtype=bool)
    for _ in range(n):  # one level of the tree per pass, parents in any order
        ready = ~done & ((par < 0) | done[np.maximum(par, 0)])
        if not ready.any():
            break
        for j in np.flatnonzero(ready):
            out[j] = (root if par[j] < 0 else out[par[j]]) @ local[j]
        done |= ready
    if not done.all():
        raise ValueError(f"parents must form a tree; got {par}")
    return out


def _inverse_rigid(m: F64Array) -> F64Array:
    """``[R^T, -R^T t; 0 0 0 1]`` of (..., 4, 4) rigid transforms."""
    inv = np.zeros_like(m)
    rt = np.swapaxes(m[..., :3, :3], -1, -2)
    inv[..., :3, :3] = rt
    inv[..., :3, 3] = -np.einsum("...ij,...j->...i", rt, m[..., :3, 3])
    inv[..., 3, 3] = 1.0
    return inv


def _check_face(face: MorphFace) -> None:
    v = face.neutral.shape[0]
    k, t = len(face.target_names), len(face.times_s)
    shapes = {
        "neutral": (face.neutral.shape, (v, 3)),
        "targets": (face.targets.shape, (k, v, 3)),
        "weights": (np.shape(face.weights), (t, k)),
        "world_from_head_quat": (face.world_from_head_quat.shape, (t, 4)),
        "head_pos": (face.head_pos.shape, (t, 3)),
    }
    for name, (got, want) in shapes.items():
        if got != want:
            raise ValueError(f"face {name}: expected shape {want}, got {got}")
    if v == 0 or t == 0:
        raise ValueError("face: needs at least one point and one frame")
    if np.any(np.diff(np.asarray(face.times_s, np.float32)) <= 0.0):
        raise ValueError("face times must increase strictly (also as float32)")


def _add_face(
    buf: _Buffer,
    doc: dict[str, Any],
    face: MorphFace,
    parent: int | None,
    samplers: list[dict[str, Any]],
    channels: list[dict[str, Any]],
) -> None:
    """The face's mesh, node and animation channels (module docstring)."""
    meshes = doc.setdefault("meshes", [])
    position = buf.add(face.neutral, "VEC3", with_bounds=True, target=_ARRAY_BUFFER)
    morph = [
        {"POSITION": buf.add(d, "VEC3", with_bounds=True, target=_ARRAY_BUFFER)}
        for d in face.targets
    ]
    meshes.append(
        {
            "name": face.name,
            "primitives": [
                {"attributes": {"POSITION": position}, "targets": morph, "mode": 0}
            ],
            "weights": [0.0] * len(morph),
            "extras": {"targetNames": list(face.target_names)},
        }
    )
    nodes = doc["nodes"]
    nodes.append({"name": face.name, "mesh": len(meshes) - 1})
    node = len(nodes) - 1
    if parent is not None:
        nodes[parent].setdefault("children", []).append(node)
    else:
        doc["scenes"][0]["nodes"].append(node)
    times = buf.add(np.asarray(face.times_s), "SCALAR", with_bounds=True)
    quat = face.world_from_head_quat
    quat = xyzw_from_wxyz(quat / np.linalg.norm(quat, axis=-1, keepdims=True))
    for path, values, kind in (
        ("translation", face.head_pos, "VEC3"),
        ("rotation", quat, "VEC4"),
        ("weights", np.asarray(face.weights, np.float64).reshape(-1), "SCALAR"),
    ):
        out = buf.add(values, kind)
        samplers.append({"input": times, "output": out, "interpolation": "LINEAR"})
        channels.append(
            {"sampler": len(samplers) - 1, "target": {"node": node, "path": path}}
        )


def _add_capsules(
    buf: _Buffer, capsules: Sequence[Capsule], bind: F64Array, n_joints: int
) -> dict[str, Any]:
    """The capsules as one skinned primitive, vertices in the bind pose."""
    mesh = capsule_mesh(tuple(capsules))
    rot, trans = bind[mesh.joints, :3, :3], bind[mesh.joints, :3, 3]
    pos = np.einsum("vij,vj->vi", rot, mesh.positions) + trans
    nrm = np.einsum("vij,vj->vi", rot, mesh.normals)
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    joints = np.zeros((len(pos), 4), dtype=np.int64)
    joints[:, 0] = mesh.joints
    weights = np.zeros((len(pos), 4))
    weights[:, 0] = 1.0
    joint_dtype = "|u1" if n_joints <= 256 else "<u2"
    index_dtype = "<u2" if len(pos) <= 65535 else "<u4"
    attributes = {
        "POSITION": buf.add(pos, "VEC3", with_bounds=True, target=_ARRAY_BUFFER),
        "NORMAL": buf.add(nrm, "VEC3", target=_ARRAY_BUFFER),
        "JOINTS_0": buf.add(joints, "VEC4", dtype=joint_dtype, target=_ARRAY_BUFFER),
        "WEIGHTS_0": buf.add(weights, "VEC4", target=_ARRAY_BUFFER),
    }
    indices = buf.add(
        mesh.indices, "SCALAR", dtype=index_dtype, target=_ELEMENT_ARRAY_BUFFER
    )
    return {
        "name": "capsules",
        "primitives": [
            {"attributes": attributes, "indices": indices, "material": 0, "mode": 4}
        ],
    }


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
    node_extras: Sequence[dict[str, Any]] | None = None,
    capsules: Sequence[Capsule] = (),
    face: MorphFace | None = None,
    skin_name: str = "skeleton",
    animation_name: str = "take",
    generator: str = "retargetd",
) -> None:
    """Write a skinned skeleton and its animation as a ``.glb`` file (module docstring).

    Args:
        path: destination file.
        names: (N,) joint node names.
        parents: (N,) parent index per joint, -1 for a root; parents before children
            is not required.
        rest_translation: (N, 3) float64, metres, each joint's origin in its parent's
            frame (roots: in the scene root's).
        rest_rotation_quat: (N, 4) float64 (w, x, y, z), each joint's rest
            ``parent_from_node``; the rest pose is the bind pose.
        channels: the animated properties.
        scene_root_quat: (4,) float64 (w, x, y, z): if given, the roots hang under a
            node ``scene_root_name`` with this rotation (``gltf_from_world``).
        scene_root_name: that node's name.
        node_extras: (N,) optional JSON objects, each joint node's ``extras``.
        capsules: a skinned mesh of these capsules (none: no mesh).
        face: a face as morph targets and its animation (module docstring); with
            no joints (``names`` empty) the file holds the face alone.
        skin_name: the skin's name.
        animation_name: the animation's name.
        generator: ``asset.generator``.

    Raises:
        ValueError: inconsistent shapes, bad parents, channels or capsules.
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
    if node_extras is not None and len(node_extras) != n:
        raise ValueError(f"need {n} node_extras; got {len(node_extras)}")
    for ch in channels:
        _check_channel(ch, n)
    for c in capsules:
        if not 0 <= c.joint < n:
            raise ValueError(f"capsule joint must be in 0..{n - 1}; got {c.joint}")
    quat = quat / np.linalg.norm(quat, axis=-1, keepdims=True)  # glTF: unit rotations
    root_quat = None
    if scene_root_quat is not None:
        root_quat = np.asarray(scene_root_quat, dtype=np.float64)
        root_quat = root_quat / np.linalg.norm(root_quat)
    if face is not None:
        _check_face(face)
    elif n == 0:
        raise ValueError("need at least one joint or a face")
    bind = scene_from_joint_rest(par, trans, quat, root_quat)
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
        if node_extras is not None and node_extras[i]:
            node["extras"] = dict(node_extras[i])
        nodes.append(node)
    roots = [int(r) for r in np.flatnonzero(par < 0)]
    skin: dict[str, Any] = {"name": skin_name, "joints": list(range(n))}
    if len(roots) == 1 and root_quat is None:
        skin["skeleton"] = roots[0]
    if root_quat is not None:
        node = {
            "name": scene_root_name,
            "rotation": [float(v) for v in xyzw_from_wxyz(root_quat)],
        }
        if roots:
            node["children"] = roots
        nodes.append(node)
        roots = [n]
    buf = _Buffer()
    doc: dict[str, Any] = {
        "asset": {"version": "2.0", "generator": generator},
        "scene": 0,
        "scenes": [{"nodes": roots}],
        "nodes": nodes,
    }
    if n:
        # Column-major MAT4: numpy's row-major bytes of the transpose.
        ibm = np.swapaxes(_inverse_rigid(bind), -1, -2).reshape(n, 16)
        skin["inverseBindMatrices"] = buf.add(ibm, "MAT4")
        doc["skins"] = [skin]
    if capsules:
        doc["meshes"] = [_add_capsules(buf, capsules, bind, n)]
        doc["materials"] = [
            {
                "name": "capsules",
                "pbrMetallicRoughness": {
                    "baseColorFactor": list(CAPSULE_BASE_COLOR),
                    "metallicFactor": 0.0,
                    "roughnessFactor": 0.8,
                },
            }
        ]
        nodes.append({"name": "body", "mesh": 0, "skin": 0})
        roots.append(len(nodes) - 1)
    samplers: list[dict[str, Any]] = []
    targets: list[dict[str, Any]] = []
    if face is not None:
        _add_face(buf, doc, face, n if root_quat is not None else None, samplers,
                  targets)  # fmt: skip
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
    if targets:
        doc["animations"] = [
            {"name": animation_name, "samplers": samplers, "channels": targets}
        ]
    doc["buffers"] = [{"byteLength": len(buf.data)}]
    doc["bufferViews"] = buf.views
    doc["accessors"] = buf.accessors
    js = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    js += b" " * (-len(js) % 4)
    chunks = struct.pack("<II", len(js), _CHUNK_JSON) + js
    chunks += struct.pack("<II", len(buf.data), _CHUNK_BIN) + bytes(buf.data)
    header = GLB_MAGIC + struct.pack("<II", GLB_VERSION, 12 + len(chunks))
    Path(path).write_bytes(header + chunks)
