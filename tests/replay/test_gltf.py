"""glTF 2.0 binary writer, read back with an independent reader (pygltflib) and
checked by the Khronos validator: the skeleton, its skin and the capsule mesh."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest
from gltf_tools import issue_summary, validate_glb
from pygltflib import GLTF2
from scipy.spatial.transform import Rotation

from retargetd.replay.gltf import GltfChannel, write_glb, xyzw_from_wxyz
from retargetd.replay.gltf_mesh import (
    CAPSULE_CAP_RINGS,
    CAPSULE_SEGMENTS,
    Capsule,
    capsule_mesh,
)


def accessor_array(gltf: GLTF2, index: int) -> np.ndarray:
    """An accessor's float32 data, read with pygltflib's document and blob."""
    acc = gltf.accessors[index]
    view = gltf.bufferViews[acc.bufferView]
    width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[acc.type]
    assert acc.componentType == 5126
    offset = (view.byteOffset or 0) + (acc.byteOffset or 0)
    data = np.frombuffer(gltf.binary_blob(), "<f4", acc.count * width, offset)
    return data.reshape(acc.count, width) if width > 1 else data


def test_small_skeleton_round_trip(tmp_path: Path) -> None:
    half = np.sqrt(0.5)
    z90 = np.array([half, 0.0, 0.0, half])  # w x y z: +90° about z
    times = np.array([0.0, 0.5, 1.0])
    rot_keys = np.array([[1.0, 0, 0, 0], z90, [0.0, 0, 0, 1.0]])
    pos_keys = np.array([[0.0, 0, 1], [0.5, 0, 1], [1.0, 0.2, 1]])
    path = tmp_path / "s.glb"
    write_glb(
        path,
        names=["hips", "spine", "head"],
        parents=[-1, 0, 1],
        rest_translation=np.array([[0, 0, 1.0], [0, 0.1, 0], [0, 0.3, 0]]),
        rest_rotation_quat=np.array([[1.0, 0, 0, 0], z90, [1.0, 0, 0, 0]]),
        channels=[
            GltfChannel(node=1, path="rotation", times_s=times, values=rot_keys),
            GltfChannel(node=0, path="translation", times_s=times, values=pos_keys),
        ],
        scene_root_quat=np.array([half, -half, 0.0, 0.0]),
    )
    raw = path.read_bytes()
    magic, version, length = struct.unpack("<4sII", raw[:12])
    assert (magic, version, length) == (b"glTF", 2, len(raw))
    gltf = GLTF2().load(str(path))
    assert gltf.asset.version == "2.0"
    names = [n.name for n in gltf.nodes]
    assert names == ["hips", "spine", "head", "world"]
    assert gltf.scenes[gltf.scene].nodes == [3]
    assert gltf.nodes[3].children == [0]
    assert gltf.nodes[0].children == [1] and gltf.nodes[1].children == [2]
    # x y z w in the file.
    np.testing.assert_allclose(gltf.nodes[1].rotation, [0, 0, half, half])
    np.testing.assert_allclose(gltf.nodes[3].rotation, [-half, 0, 0, half])
    np.testing.assert_allclose(gltf.nodes[2].translation, [0, 0.3, 0])
    (anim,) = gltf.animations
    assert [s.interpolation for s in anim.samplers] == ["LINEAR", "LINEAR"]
    by_path = {
        c.target.path: (c.target.node, anim.samplers[c.sampler]) for c in anim.channels
    }
    node, sampler = by_path["rotation"]
    assert node == 1
    inp = gltf.accessors[sampler.input]
    assert inp.min == [0.0] and inp.max == [1.0]
    np.testing.assert_array_equal(accessor_array(gltf, sampler.input), times)
    np.testing.assert_allclose(
        accessor_array(gltf, sampler.output), xyzw_from_wxyz(rot_keys), atol=1e-7
    )
    node, sampler = by_path["translation"]
    assert node == 0
    np.testing.assert_allclose(
        accessor_array(gltf, sampler.output), pos_keys, atol=1e-7
    )
    for view in gltf.bufferViews:
        assert view.byteOffset % 4 == 0


def test_bad_channels_are_named(tmp_path: Path) -> None:
    base = dict(
        names=["a"],
        parents=[-1],
        rest_translation=np.zeros((1, 3)),
        rest_rotation_quat=np.array([[1.0, 0, 0, 0]]),
    )
    bad_times = GltfChannel(
        node=0, path="rotation", times_s=np.array([0.0, 0.0]), values=np.ones((2, 4))
    )
    with pytest.raises(ValueError, match="increase strictly"):
        write_glb(tmp_path / "x.glb", channels=[bad_times], **base)  # type: ignore[arg-type]
    bad_path = GltfChannel(
        node=0, path="scale", times_s=np.zeros(1), values=np.ones((1, 3))
    )
    with pytest.raises(ValueError, match="path"):
        write_glb(tmp_path / "x.glb", channels=[bad_path], **base)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="parents"):
        write_glb(tmp_path / "x.glb", channels=[], **{**base, "parents": [0]})  # type: ignore[arg-type]


def test_capsules_are_closed_and_face_outwards() -> None:
    zero, sphere_at = np.zeros(3), np.array([0.1, 0, 0])
    caps = [
        Capsule(joint=0, start=zero, end=np.array([0.0, 0.3, 0.0]), radius=0.05),
        Capsule(joint=2, start=sphere_at, end=sphere_at, radius=0.02),  # a sphere
        Capsule(joint=1, start=zero, end=np.array([-0.2, 0.1, 0.4]), radius=0.03),
    ]
    mesh = capsule_mesh(caps)
    per = 2 + 2 * CAPSULE_CAP_RINGS * CAPSULE_SEGMENTS
    assert len(mesh.positions) == 3 * per == 102
    np.testing.assert_array_equal(mesh.joints, np.repeat([0, 2, 1], per))
    tri = mesh.indices.reshape(-1, 3)
    assert len(tri) == 3 * 64
    np.testing.assert_allclose(np.linalg.norm(mesh.normals, axis=-1), 1.0)
    for k, c in enumerate(caps):
        v = mesh.positions[k * per : (k + 1) * per]
        # Every vertex at the radius from the axis segment.
        a, b = c.start, c.end
        ab = b - a
        u = np.clip((v - a) @ ab / max(ab @ ab, 1e-30), 0.0, 1.0)
        dist = np.linalg.norm(v - (a + u[:, None] * ab), axis=-1)
        np.testing.assert_allclose(dist, c.radius, rtol=1e-12)
    # Closed: every edge is shared by exactly two triangles, in opposite directions.
    edges = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    assert len({tuple(e) for e in edges}) == len(edges)
    assert {tuple(e) for e in edges} == {tuple(e) for e in edges[:, ::-1]}
    # Counter-clockwise from outside: each face's normal along its vertices'.
    p = mesh.positions[tri]
    face_n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    assert (np.einsum("fi,fi->f", face_n, mesh.normals[tri].sum(axis=1)) > 0).all()


def _scene_from_nodes(gltf: GLTF2, n: int) -> np.ndarray:
    """(n, 4, 4) each joint's rest transform in the scene, from the file's nodes."""
    parent = {c: i for i, node in enumerate(gltf.nodes) for c in node.children or []}

    def local(i: int) -> np.ndarray:
        node, m = gltf.nodes[i], np.eye(4)
        if node.rotation is not None:
            m[:3, :3] = Rotation.from_quat(node.rotation).as_matrix()  # x y z w
        if node.translation is not None:
            m[:3, 3] = node.translation
        return m

    def scene(i: int) -> np.ndarray:
        p = parent.get(i)
        return local(i) if p is None else scene(p) @ local(i)

    return np.stack([scene(i) for i in range(n)])


@pytest.mark.parametrize("scene_root", [False, True])
def test_skin_binds_at_the_rest_pose(tmp_path: Path, scene_root: bool) -> None:
    half = np.sqrt(0.5)
    z90 = np.array([half, 0.0, 0.0, half])
    path = tmp_path / "s.glb"
    caps = [
        Capsule(joint=j, start=np.zeros(3), end=np.array([0, 0.1, 0]), radius=0.02)
        for j in range(3)
    ]
    write_glb(
        path,
        names=["hips", "spine", "head"],
        parents=[-1, 0, 1],
        rest_translation=np.array([[0, 0, 1.0], [0, 0.1, 0], [0, 0.3, 0]]),
        rest_rotation_quat=np.array([[1.0, 0, 0, 0], z90, [1.0, 0, 0, 0]]),
        channels=[
            GltfChannel(
                node=1,
                path="rotation",
                times_s=np.array([0.0, 1.0]),
                values=np.array([[1.0, 0, 0, 0], z90]),
            ),
        ],
        scene_root_quat=np.array([half, -half, 0.0, 0.0]) if scene_root else None,
        node_extras=[{"rig_bone": "pelvis"}, {}, {}],
        capsules=caps,
    )
    report = validate_glb(path)
    assert report["issues"]["numErrors"] == 0, issue_summary(report)
    assert report["issues"]["numWarnings"] == 0, issue_summary(report)
    gltf = GLTF2().load(str(path))
    (skin,) = gltf.skins
    assert skin.joints == [0, 1, 2]
    assert skin.skeleton == (None if scene_root else 0)
    assert gltf.nodes[0].extras == {"rig_bone": "pelvis"} and not gltf.nodes[1].extras
    acc = gltf.accessors[skin.inverseBindMatrices]
    assert (acc.type, acc.componentType, acc.count) == ("MAT4", 5126, 3)
    view = gltf.bufferViews[acc.bufferView]
    assert view.byteStride is None and view.target is None
    raw = np.frombuffer(gltf.binary_blob(), "<f4", 48, view.byteOffset)
    ibm = raw.reshape(3, 4, 4).transpose(0, 2, 1)  # column-major
    bind = _scene_from_nodes(gltf, 3)
    for j in range(3):
        np.testing.assert_allclose(ibm[j] @ bind[j], np.eye(4), atol=1e-6)
    (prim,) = gltf.meshes[0].primitives
    pos_acc = gltf.accessors[prim.attributes.POSITION]
    pos = np.frombuffer(
        gltf.binary_blob(), "<f4", 3 * pos_acc.count,
        gltf.bufferViews[pos_acc.bufferView].byteOffset,
    ).reshape(-1, 3)  # fmt: skip
    # Bind-pose vertices: each capsule placed by its joint's rest transform.
    mesh = capsule_mesh(caps)
    want = np.einsum("vij,vj->vi", bind[mesh.joints, :3, :3], mesh.positions)
    np.testing.assert_allclose(pos, want + bind[mesh.joints, :3, 3], atol=1e-6)


def test_many_joints_use_wider_indices(tmp_path: Path) -> None:
    n = 300  # past what an unsigned byte JOINTS_0 can index
    path = tmp_path / "chain.glb"
    write_glb(
        path,
        names=[f"j{i}" for i in range(n)],
        parents=[-1, *range(n - 1)],
        rest_translation=np.tile([0.0, 0.01, 0.0], (n, 1)),
        rest_rotation_quat=np.tile([1.0, 0, 0, 0], (n, 1)),
        channels=[],
        capsules=[
            Capsule(
                joint=j, start=np.zeros(3), end=np.array([0, 0.01, 0]), radius=0.002
            )
            for j in range(n)
        ],
    )
    report = validate_glb(path)
    assert report["issues"]["numErrors"] == 0, issue_summary(report)
    gltf = GLTF2().load(str(path))
    (prim,) = gltf.meshes[0].primitives
    assert gltf.accessors[prim.attributes.JOINTS_0].componentType == 5123
    assert gltf.accessors[prim.indices].componentType == 5123  # 10200 vertices
