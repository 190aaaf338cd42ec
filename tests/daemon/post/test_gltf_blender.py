"""Interop: Blender imports our .glb as an armature with an action, and poses every
bone (and every capsule vertex) where our solve has it.

Blender (Debian package ``blender``) runs headless and imports the file with
``bpy.ops.import_scene.gltf``. The skin becomes one armature object (the ``world``
node, the joints' parent) with a bone per joint, named as the nodes (the humanoid
names), and one action holding every key. The importer converts glTF's +Y up to
Blender's +Z up (glTF +Z -> Blender -Y), which undoes our ``world`` node: Blender's
world is our world, in metres. Keys land at ``first_key_frame + t * fps`` (read back
from the imported curves, not assumed), so the script sets frames with subframes at
our frame times and dumps each pose bone's matrix and each mesh's evaluated vertices.

Blender's importer gives each bone its own rest axes (a bone-direction heuristic), a
constant rotation ``C_j`` on top of the node's: ``pose_j(t) = node_j(t) C_j`` and
``rest_j = node_j(rest) C_j``, so ``pose_j(t) rest_j^-1`` (armature object included)
is the node's own motion from the bind pose, ``world_from_bone(t) ⊗
rest_world_from_bone^-1`` in our terms, whatever ``C_j`` is. Compared at several
frames of the PiG walk (every frame written): each bone's head against the calibrated
skeleton posed by the solve (0.1 mm), that rotation (0.1°), and with capsules every
vertex of the skinned mesh against the capsule moved rigidly by its bone (0.1 mm,
matched as point sets: the importer may reorder vertices).

The file with no mesh is imported with every option at its default. Debian's Blender
3.4 runs its glTF importer on Debian's numpy 1.24, where ``np.bool`` no longer
exists, and its default ``import_shading="NORMALS"`` path uses it for any mesh; the
capsule file is therefore imported with ``import_shading="SMOOTH"`` (the "Shading:
Smooth" choice of the import dialog), which the same importer handles.
"""

from __future__ import annotations

import json
import math
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from gltf_tools import PIG_HUMANOID, require_blender
from scipy.spatial.transform import Rotation

from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.post.export_gltf import (
    bone_capsules,
    clip_from_solve,
    node_names,
    write_clip_glb,
)
from retargetd.daemon.retarget.bvh import posed_bone_origins
from retargetd.replay.gltf_mesh import capsule_mesh

MAX_ANGLE_DEG = 0.1
MAX_POS_MM = 0.1

SCRIPT = r"""
import json, sys
import bpy

glb, out, times, shading = sys.argv[sys.argv.index("--") + 1:]
options = {} if shading == "default" else {"import_shading": shading}
bpy.ops.import_scene.gltf(filepath=glb, **options)
scene = bpy.context.scene
fps = scene.render.fps / scene.render.fps_base
rows = lambda m: [list(r) for r in m]
armatures = [o for o in scene.objects if o.type == "ARMATURE"]
arma = armatures[0]
action = arma.animation_data.action
first = min(kp.co[0] for fc in action.fcurves for kp in fc.keyframe_points)
meshes = [o for o in scene.objects if o.type == "MESH" and o.parent == arma]
doc = {
    "version": bpy.app.version_string, "fps": fps, "first": first,
    "armatures": [a.name for a in armatures],
    "bones": [
        {"name": b.name, "parent": b.parent.name if b.parent else None,
         "rest": rows(b.matrix_local)}
        for b in arma.data.bones
    ],
    "action": {
        "name": action.name,
        "keys": {f"{fc.data_path}[{fc.array_index}]":
                 [kp.co[0] for kp in fc.keyframe_points] for fc in action.fcurves},
    },
    "meshes": [
        {"name": m.name, "vertices": len(m.data.vertices),
         "groups": [g.name for g in m.vertex_groups],
         "modifiers": [(d.type, d.object.name if d.object else None)
                       for d in m.modifiers]}
        for m in meshes
    ],
    "frames": {},
}
for t in [float(x) for x in times.split(",")]:
    f = first + t * fps
    scene.frame_set(int(f), subframe=f - int(f))
    graph = bpy.context.evaluated_depsgraph_get()
    frame = {"armature": rows(arma.matrix_world),
             "pose": {pb.name: rows(pb.matrix) for pb in arma.pose.bones},
             "mesh": {}}
    for m in meshes:
        ev = m.evaluated_get(graph)
        me = ev.to_mesh()
        frame["mesh"][m.name] = [list(ev.matrix_world @ v.co) for v in me.vertices]
        ev.to_mesh_clear()
    doc["frames"][repr(t)] = frame
with open(out, "w") as fh:
    json.dump(doc, fh)
"""


def _nearest_mm(a: np.ndarray, b: np.ndarray) -> float:
    """The largest distance (mm) from a point of ``a`` to its nearest in ``b``."""
    d = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=-1)
    return float(1e3 * d.min(axis=1).max())


@pytest.mark.timeout(300)
@pytest.mark.parametrize("mesh", ["none", "capsules"])
def test_blender_imports_an_armature(pig_walk: Any, tmp_path: Path, mesh: str) -> None:
    exe = require_blender()
    cal, res = pig_walk.calibration, pig_walk.solve
    clip = clip_from_solve(res, cal, pig_walk.rate_hz)
    glb = tmp_path / "walk.glb"
    write_clip_glb(glb, clip, cal, humanoid=PIG_HUMANOID, mesh=mesh)
    n_frames, n_bones = clip.n_frames, len(cal.bone_names)
    frames = [0, n_frames // 3, (2 * n_frames) // 3, n_frames - 1]
    times = [f / clip.rate_hz for f in frames]
    script = tmp_path / "dump.py"
    script.write_text(SCRIPT)
    out = tmp_path / "blender.json"
    shading = "default" if mesh == "none" else "SMOOTH"
    cmd = [exe, "-b", "--factory-startup", "--python-exit-code", "1",
           "--python", str(script), "--", str(glb), str(out),
           ",".join(repr(t) for t in times), shading]  # fmt: skip
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=240, check=False)
    assert run.returncode == 0 and out.is_file(), (
        run.stdout[-2000:] + run.stderr[-2000:]
    )
    doc = json.loads(out.read_text())

    # One armature, a bone per joint, named and parented as the nodes.
    assert tuple(b.humanoid for b in load_rig("plug-in-gait").bones) == PIG_HUMANOID
    names, _ = node_names(cal.bone_names, PIG_HUMANOID)
    assert names == list(PIG_HUMANOID)
    assert doc["armatures"] == ["world"]
    bones = {b["name"]: b for b in doc["bones"]}
    assert [b["name"] for b in doc["bones"]] == names
    for b, p in enumerate(cal.bone_parents):
        assert bones[names[b]]["parent"] == (names[p] if p >= 0 else None)
    # One action of T frames: every rotation channel (4 curves a bone) and the
    # root's location (3) keyed at each of our frames.
    keys = doc["action"]["keys"]
    assert len(keys) == 4 * n_bones + 3
    for curve, key_frames in keys.items():
        at = (np.array(key_frames) - doc["first"]) / doc["fps"] * clip.rate_hz
        assert len(at) == n_frames, curve
        np.testing.assert_allclose(at, np.arange(n_frames), atol=1e-3, err_msg=curve)
    if mesh == "capsules":
        (body,) = doc["meshes"]
        assert body["vertices"] == 34 * n_bones
        assert sorted(body["groups"]) == sorted(names)
        assert body["modifiers"] == [["ARMATURE", "world"]]
    else:
        assert doc["meshes"] == []

    posed = posed_bone_origins(cal, res.world_from_bone_quat, res.root_pos)
    rest_wfb = Rotation.from_quat(cal.rest_world_from_bone_quat, scalar_first=True)
    cap = capsule_mesh(bone_capsules(cal)) if mesh == "capsules" else None
    worst_mm = worst_deg = worst_vertex_mm = 0.0
    for f, t in zip(frames, times, strict=True):
        frame = doc["frames"][repr(t)]
        arma = np.array(frame["armature"])
        for j, name in enumerate(names):
            pose = arma @ np.array(frame["pose"][name])
            rest = arma @ np.array(bones[name]["rest"])
            pos_mm = 1e3 * np.linalg.norm(pose[:3, 3] - posed[f, j])
            got = Rotation.from_matrix(pose[:3, :3] @ np.linalg.inv(rest[:3, :3]))
            want = (
                Rotation.from_quat(res.world_from_bone_quat[f, j], scalar_first=True)
                * rest_wfb[j].inv()
            )
            ang = math.degrees((got * want.inv()).magnitude())
            worst_mm, worst_deg = max(worst_mm, pos_mm), max(worst_deg, ang)
            assert pos_mm < MAX_POS_MM, (name, f, pos_mm)
            assert ang < MAX_ANGLE_DEG, (name, f, ang)
        if cap is not None:
            wfb = Rotation.from_quat(
                res.world_from_bone_quat[f, cap.joints], scalar_first=True
            )
            want_v = wfb.apply(cap.positions) + posed[f, cap.joints]
            got_v = np.array(frame["mesh"]["body"])
            err = max(_nearest_mm(want_v, got_v), _nearest_mm(got_v, want_v))
            worst_vertex_mm = max(worst_vertex_mm, err)
            assert err < MAX_POS_MM, (f, err)
    print(
        f"\nBlender {doc['version']} ({mesh}): armature {doc['armatures'][0]!r}, "
        f"{len(doc['bones'])} bones, action {doc['action']['name']!r} with "
        f"{len(keys)} curves of {n_frames} keys; worst {worst_mm:.4f} mm, "
        f"{worst_deg:.4f} deg"
        + (f", vertices {worst_vertex_mm:.4f} mm" if cap is not None else "")
    )
