"""Interop: Blender imports the ``.glb`` that ``retargetd reduce`` writes (sparse keys,
each channel its own key times) as an armature whose action holds only the kept keys,
and poses every bone where the solve has it.

Blender (Debian package ``blender``) runs headless and imports the file with its
default options (``bpy.ops.import_scene.gltf``); the skin becomes one armature, a
bone per joint named as the nodes (the rig's humanoid names). The importer undoes our
Y-up ``world`` node, so Blender's world is ours; each bone's world pose times its
world rest inverse is ``world_from_bone(t) ⊗ rest_world_from_bone^-1`` whatever rest
axes the importer chose (see ``tests/daemon/post/test_gltf_blender.py``). Compared on
the Plug-in Gait walk at frames on and between keys: that rotation against the
unreduced solve, within the tolerance summed down the bone's chain (each local
rotation is within the tolerance, and errors compose along the chain) plus 0.05° for
Blender's own interpolation between quaternion keys and float32 storage; and against
the file's keys played back independently (pygltflib, scipy's Slerp, forward
kinematics down the nodes) within 0.05°, which catches keys landing at wrong times.
Every curve of the action holds as many keys as the file's channel.
"""

from __future__ import annotations

import json
import math
import subprocess
from pathlib import Path

import numpy as np
import pygltflib
import pytest
from gltf_tools import require_blender
from scipy.spatial.transform import Rotation, Slerp

from retargetd.daemon.cli.main import main

STATIC = "btkdata/PiG_Calibration-FlatFoot-Full.c3d"
WALK = "btkdata/PiG_Motion-FlatFoot-Full.c3d"
TOL_DEG = 0.5

SCRIPT = r"""
import json, sys
import bpy

glb, out, times = sys.argv[sys.argv.index("--") + 1:]
bpy.ops.import_scene.gltf(filepath=glb)
scene = bpy.context.scene
fps = scene.render.fps / scene.render.fps_base
(arma,) = [o for o in scene.objects if o.type == "ARMATURE"]
action = arma.animation_data.action
first = min(kp.co[0] for fc in action.fcurves for kp in fc.keyframe_points)
rows = lambda m: [list(r) for r in m]
doc = {
    "version": bpy.app.version_string, "frames": {},
    "rest": {b.name: rows(arma.matrix_world @ b.matrix_local) for b in arma.data.bones},
    "keys": {f"{fc.data_path}[{fc.array_index}]": len(fc.keyframe_points)
             for fc in action.fcurves},
}
for t in [float(x) for x in times.split(",")]:
    f = first + t * fps
    scene.frame_set(int(f), subframe=f - int(f))
    doc["frames"][repr(t)] = {
        pb.name: rows(arma.matrix_world @ pb.matrix) for pb in arma.pose.bones
    }
with open(out, "w") as fh:
    json.dump(doc, fh)
"""


def _played_world(
    glb: Path, names: list[str], times: list[float]
) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """The file's keys played back: (len(times), B, 4) x y z w each node's world
    rotation (slerp between keys, nodes composed down the hierarchy, the world node
    left out), (B, 4) the same at rest (the nodes' own rotations), and the key count
    of each node's rotation channel."""
    gltf = pygltflib.GLTF2().load(str(glb))
    blob = gltf.binary_blob()

    def accessor(i: int, width: int) -> np.ndarray:
        acc = gltf.accessors[i]
        view = gltf.bufferViews[acc.bufferView]
        start = (view.byteOffset or 0) + (acc.byteOffset or 0)
        a = np.frombuffer(blob, np.float32, acc.count * width, start)
        return a.reshape(acc.count, width).astype(np.float64)

    t = np.asarray(times)
    local: dict[int, Rotation] = {}
    n_keys: dict[str, int] = {}
    for ch in gltf.animations[0].channels:
        if ch.target.path != "rotation":
            continue
        sampler = gltf.animations[0].samplers[ch.sampler]
        key_t = accessor(sampler.input, 1)[:, 0]
        keys = Rotation.from_quat(accessor(sampler.output, 4))
        local[ch.target.node] = Slerp(key_t, keys)(np.clip(t, key_t[0], key_t[-1]))
        n_keys[gltf.nodes[ch.target.node].name] = len(key_t)
    parent = {c: i for i, node in enumerate(gltf.nodes) for c in node.children or []}
    node_of = {node.name: i for i, node in enumerate(gltf.nodes)}

    def world(i: int, rot: dict[int, Rotation]) -> Rotation:
        p = parent.get(i)
        if p is None or p not in rot:  # under the world node
            return rot[i]
        return world(p, rot) * rot[i]

    rest = {i: Rotation.from_quat(gltf.nodes[i].rotation) for i in local}
    played = np.stack([world(node_of[n], local).as_quat() for n in names], axis=1)
    rest_q = np.stack([world(node_of[n], rest).as_quat() for n in names])
    return played, rest_q, n_keys


@pytest.mark.timeout(300)
def test_blender_imports_the_reduced_glb(
    datasets: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    exe = require_blender()
    cal = tmp_path / "cal.json"
    assert main(["calibrate", str(datasets / STATIC), "--rig", "plug-in-gait",
                 "--out", str(cal)]) == 0  # fmt: skip
    base = [str(datasets / WALK), "--rig", "plug-in-gait", "--calibration", str(cal)]
    npz, glb = tmp_path / "w.npz", tmp_path / "w.glb"
    assert main(["solve", *base, "--out", str(npz)]) == 0
    assert main(["reduce", *base, "--tolerance-deg", str(TOL_DEG),
                 "--out", str(glb)]) == 0  # fmt: skip
    capsys.readouterr()
    with np.load(npz) as z:
        # Node (and Blender bone) names: the humanoid name where the rig has one.
        names = [
            str(h) or str(n)
            for n, h in zip(z["bone_names"], z["bone_humanoid"], strict=True)
        ]
        parents = z["bone_parents"]
        wfb = z["world_from_bone_quat"]
        rate = float(z["rate_hz"])
    n = len(wfb)
    frames = [0, n // 5, n // 3 + 1, n // 2, (2 * n) // 3 + 2, n - 1]
    times = [f / rate for f in frames]
    script = tmp_path / "dump.py"
    script.write_text(SCRIPT)
    out = tmp_path / "blender.json"
    cmd = [exe, "-b", "--factory-startup", "--python-exit-code", "1",
           "--python", str(script), "--", str(glb), str(out),
           ",".join(repr(t) for t in times)]  # fmt: skip
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=240, check=False)
    assert run.returncode == 0 and out.is_file(), (
        run.stdout[-2000:] + run.stderr[-2000:]
    )
    doc = json.loads(out.read_text())
    depth = np.zeros(len(names), dtype=int)
    for b, p in enumerate(parents):
        depth[b] = 0 if p < 0 else depth[p] + 1
    played, rest_q, n_keys = _played_world(glb, names, times)
    assert len(doc["keys"]) == 4 * len(names) + 3
    for name in names:  # every curve of a bone: the file's kept keys, no more
        for i in range(4):
            curve = f'pose.bones["{name}"].rotation_quaternion[{i}]'
            assert doc["keys"][curve] == n_keys[name], (curve, n_keys[name])
    assert sum(n_keys.values()) < len(names) * n / 2  # the reduction kept few keys
    worst = worst_keys = 0.0
    for k, (f, t) in enumerate(zip(frames, times, strict=True)):
        bones = doc["frames"][repr(t)]
        for b, name in enumerate(names):
            rest = np.array(doc["rest"][name])[:3, :3]
            got = Rotation.from_matrix(np.array(bones[name])[:3, :3] @ rest.T)
            rest_b = Rotation.from_quat(rest_q[b]).inv()
            want = Rotation.from_quat(wfb[f, b], scalar_first=True) * rest_b
            ang = math.degrees((got * want.inv()).magnitude())
            worst = max(worst, ang)
            assert ang <= TOL_DEG * (depth[b] + 1) + 0.05, (name, f, ang)
            keyed = Rotation.from_quat(played[k, b]) * rest_b
            ang_keys = math.degrees((got * keyed.inv()).magnitude())
            worst_keys = max(worst_keys, ang_keys)
            assert ang_keys < 0.05, (name, f, ang_keys)
    print(
        f"\nBlender {doc['version']}: {sum(n_keys.values())} rotation keys of "
        f"{len(names) * n}; worst bone axes {worst:.3f} deg against the "
        f"solve, {worst_keys:.4f} deg against the keys played back"
    )
