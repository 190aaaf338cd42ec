"""The solved PiG walk as a skinned .glb: the Khronos validator finds no error, the
joints are named by the humanoid map with the rig's names kept, the inverse bind
matrices are the calibration pose, and the capsule mesh skinned by the glTF rules
(read with pygltflib, played with numpy) lands where the solve puts each bone.

glTF skinning (specification, "Skins"): a vertex ``v`` of the skinned mesh moves to
``sum_i w_i G_{j_i}(t) IBM_{j_i} v`` with ``G_j(t)`` the joint node's scene transform
at time ``t`` (the skinned mesh node's own transform is ignored). Our vertices carry
one joint with weight 1, so each is ``G_j(t) IBM_j v``. Expected: the capsule in its
bone's frame (:func:`retargetd.daemon.post.export_gltf.bone_capsules`) moved by the
solve (``world_from_bone(t)``, the bone's posed origin), then into glTF's axes
(``gltf_from_world``). Tolerance 0.01 mm: float32 storage of metres a few metres
from the origin rounds by < 1e-3 mm per value, composed down a chain of 5 joints.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from gltf_tools import PIG_HUMANOID, issue_summary, validate_glb
from pygltflib import GLTF2
from scipy.spatial.transform import Rotation

from retargetd.daemon.post.export_gltf import (
    GLTF_FROM_WORLD_QUAT,
    bone_capsules,
    clip_from_solve,
    write_clip_glb,
    write_reduced_glb,
)
from retargetd.daemon.post.reduce import reduce_clip
from retargetd.daemon.retarget.bvh import posed_bone_origins
from retargetd.replay.gltf_mesh import capsule_mesh

MAX_VERTEX_MM = 0.01


def _accessor(gltf: GLTF2, index: int) -> np.ndarray:
    acc = gltf.accessors[index]
    view = gltf.bufferViews[acc.bufferView]
    width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4, "MAT4": 16}[acc.type]
    dtype = {5126: "<f4", 5121: "u1", 5123: "<u2", 5125: "<u4"}[acc.componentType]
    offset = (view.byteOffset or 0) + (acc.byteOffset or 0)
    data = np.frombuffer(gltf.binary_blob(), dtype, acc.count * width, offset)
    return data.reshape(acc.count, width)


def _mat(rotation_xyzw: Any, translation: Any) -> np.ndarray:
    m = np.eye(4)
    if rotation_xyzw is not None:
        m[:3, :3] = Rotation.from_quat(rotation_xyzw).as_matrix()
    if translation is not None:
        m[:3, 3] = translation
    return m


def _scene_transforms(gltf: GLTF2, frame: int | None) -> dict[int, np.ndarray]:
    """Every node's scene transform: at rest (``frame`` None) or at a key index of
    a file with every frame keyed (each channel's key ``frame``)."""
    local = {i: _mat(n.rotation, n.translation) for i, n in enumerate(gltf.nodes)}
    if frame is not None:
        anim = gltf.animations[0]
        for ch in anim.channels:
            out = _accessor(gltf, anim.samplers[ch.sampler].output).astype(np.float64)
            node = gltf.nodes[ch.target.node]
            if ch.target.path == "rotation":
                local[ch.target.node] = _mat(out[frame], node.translation)
        for ch in anim.channels:
            out = _accessor(gltf, anim.samplers[ch.sampler].output).astype(np.float64)
            if ch.target.path == "translation":
                local[ch.target.node][:3, 3] = out[frame]
    parent = {c: i for i, n in enumerate(gltf.nodes) for c in n.children or []}
    scene: dict[int, np.ndarray] = {}

    def walk(i: int) -> np.ndarray:
        if i not in scene:
            p = parent.get(i)
            scene[i] = local[i] if p is None else walk(p) @ local[i]
        return scene[i]

    for i in range(len(gltf.nodes)):
        walk(i)
    return scene


@pytest.mark.parametrize("mesh", ["none", "capsules"])
def test_the_validator_finds_no_error(pig_walk: Any, tmp_path: Path, mesh: str) -> None:
    cal, res = pig_walk.calibration, pig_walk.solve
    clip = clip_from_solve(res, cal, pig_walk.rate_hz)
    every, reduced = tmp_path / "every.glb", tmp_path / "reduced.glb"
    write_clip_glb(every, clip, cal, humanoid=PIG_HUMANOID, mesh=mesh)
    red = reduce_clip(clip, tolerance_deg=0.5, tolerance_mm=1.0)
    write_reduced_glb(reduced, red, cal, humanoid=PIG_HUMANOID, mesh=mesh)
    for path in (every, reduced):
        report = validate_glb(path)
        summary = issue_summary(report)
        print(f"\n{path.name} ({mesh}): {summary}")
        issues = report["issues"]
        assert issues["numErrors"] == 0, summary
        assert issues["numWarnings"] == 0, summary
        # Without a mesh nothing references the skin: the validator says so, as
        # an info ("may be unused"); importers build the armature from it anyway.
        codes = {m["code"] for m in issues["messages"]}
        assert codes == (set() if mesh == "capsules" else {"UNUSED_OBJECT"}), summary


def test_names_and_the_bind_pose(pig_walk: Any, tmp_path: Path) -> None:
    cal = pig_walk.calibration
    clip = clip_from_solve(pig_walk.solve, cal, pig_walk.rate_hz)
    path = tmp_path / "walk.glb"
    hum = list(PIG_HUMANOID)
    hum[4] = ""  # as if the rig left the head unmapped: it keeps the rig's name
    write_clip_glb(path, clip, cal, humanoid=hum)
    gltf = GLTF2().load(str(path))
    n = len(cal.bone_names)
    want = [h or b for b, h in zip(cal.bone_names, hum, strict=True)]
    assert [node.name for node in gltf.nodes[:n]] == want
    assert want[4] == "head" and want[0] == "Hips"
    for b, node in enumerate(gltf.nodes[:n]):
        assert node.extras["rig_bone"] == cal.bone_names[b]
        assert node.extras.get("humanoid", "") == hum[b]
    assert gltf.nodes[n].name == "world" and not gltf.meshes
    (skin,) = gltf.skins
    assert skin.joints == list(range(n))
    assert skin.skeleton is None  # see retargetd.replay.gltf: Blender reads it
    ibm = _accessor(gltf, skin.inverseBindMatrices).astype(np.float64)
    ibm = ibm.reshape(n, 4, 4).transpose(0, 2, 1)  # column-major in the file
    rest = _scene_transforms(gltf, None)
    # The bind pose is the calibration pose: each joint's rest transform, from the
    # calibration (not from the file's nodes), in glTF's axes.
    g = Rotation.from_quat(GLTF_FROM_WORLD_QUAT, scalar_first=True)
    origins = np.asarray(cal.rest_bone_origin_pos)
    for j in range(n):
        np.testing.assert_allclose(ibm[j] @ rest[j], np.eye(4), atol=1e-6)
        wfb = Rotation.from_quat(cal.rest_world_from_bone_quat[j], scalar_first=True)
        bind = _mat((g * wfb).as_quat(), g.apply(origins[j]))
        np.testing.assert_allclose(ibm[j] @ bind, np.eye(4), atol=1e-6)


def test_capsules_skin_to_the_solve(pig_walk: Any, tmp_path: Path) -> None:
    cal, res = pig_walk.calibration, pig_walk.solve
    clip = clip_from_solve(res, cal, pig_walk.rate_hz)
    path = tmp_path / "walk.glb"
    write_clip_glb(path, clip, cal, humanoid=PIG_HUMANOID, mesh="capsules")
    gltf = GLTF2().load(str(path))
    n = len(cal.bone_names)
    (mesh,) = gltf.meshes
    (prim,) = mesh.primitives
    body = next(i for i, node in enumerate(gltf.nodes) if node.mesh == 0)
    node = gltf.nodes[body]
    assert node.skin == 0 and node.name == "body"
    assert node.translation is None and node.rotation is None and node.matrix is None
    assert body in gltf.scenes[0].nodes  # a scene root, as the spec asks
    pos = _accessor(gltf, prim.attributes.POSITION).astype(np.float64)
    joints = _accessor(gltf, prim.attributes.JOINTS_0)
    weights = _accessor(gltf, prim.attributes.WEIGHTS_0)
    assert gltf.accessors[prim.attributes.JOINTS_0].componentType == 5121
    assert (weights[:, 0] == 1.0).all() and (weights[:, 1:] == 0.0).all()
    cap = capsule_mesh(bone_capsules(cal))
    np.testing.assert_array_equal(joints[:, 0], cap.joints)
    assert len(pos) == 34 * n
    acc = gltf.accessors[prim.attributes.POSITION]
    np.testing.assert_allclose(acc.min, pos.min(axis=0), atol=1e-7)
    np.testing.assert_allclose(acc.max, pos.max(axis=0), atol=1e-7)
    ibm = _accessor(gltf, gltf.skins[0].inverseBindMatrices).astype(np.float64)
    ibm = ibm.reshape(n, 4, 4).transpose(0, 2, 1)
    posed = posed_bone_origins(cal, res.world_from_bone_quat, res.root_pos)
    g = Rotation.from_quat(GLTF_FROM_WORLD_QUAT, scalar_first=True)
    v_h = np.concatenate([pos, np.ones((len(pos), 1))], axis=1)
    worst = 0.0
    for f in (0, clip.n_frames // 2, clip.n_frames - 1):
        scene = _scene_transforms(gltf, f)
        skinning = np.stack([scene[j] @ ibm[j] for j in range(n)])
        got = np.einsum("vij,vj->vi", skinning[cap.joints], v_h)[:, :3]
        wfb = Rotation.from_quat(
            res.world_from_bone_quat[f, cap.joints], scalar_first=True
        )
        want = g.apply(wfb.apply(cap.positions) + posed[f, cap.joints])
        err = 1e3 * np.linalg.norm(got - want, axis=-1).max()
        worst = max(worst, err)
        assert err < MAX_VERTEX_MM, (f, err)
    print(f"\ncapsules skinned by the file: worst vertex {worst:.5f} mm")
