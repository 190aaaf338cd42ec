"""Interop: Blender imports the ``.glb`` that ``retargetd reduce`` writes (sparse keys,
each channel its own key times) and poses every bone where the solve has it.

Blender (Debian package ``blender``) runs headless and imports the file with its
default options (``bpy.ops.import_scene.gltf``); the importer undoes our Y-up ``world``
node, so Blender's world is ours and each empty's axes are ``world_from_bone ⊗
gltf_from_world`` (see ``tests/daemon/post/test_gltf_blender.py``). Compared on the
Plug-in Gait walk at frames on and between keys: each bone's world axes against the
unreduced solve, within the tolerance summed down the bone's chain (each local
rotation is within the tolerance, and errors compose along the chain) plus 0.05° for
Blender's own interpolation between quaternion keys and float32 storage; and against
the file's keys played back independently (pygltflib, scipy's Slerp, forward
kinematics down the nodes) within 0.05°, which catches keys landing at wrong times.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pygltflib
import pytest
from scipy.spatial.transform import Rotation, Slerp

from retargetd.daemon.cli.main import main
from retargetd.daemon.post.export_gltf import GLTF_FROM_WORLD_QUAT

IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")
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
first = min(
    kp.co[0]
    for o in scene.objects if o.animation_data and o.animation_data.action
    for fc in o.animation_data.action.fcurves for kp in fc.keyframe_points
)
doc = {"version": bpy.app.version_string, "frames": {}}
for t in [float(x) for x in times.split(",")]:
    f = first + t * fps
    scene.frame_set(int(f), subframe=f - int(f))
    doc["frames"][repr(t)] = {
        o.name: [list(row) for row in o.matrix_world] for o in scene.objects
    }
with open(out, "w") as fh:
    json.dump(doc, fh)
"""


def _played_world(glb: Path, names: list[str], times: list[float]) -> np.ndarray:
    """(len(times), B, 4) x y z w: each node's world rotation from the file's keys
    (slerp between keys, nodes composed down the hierarchy, the world node left
    out)."""
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
    for ch in gltf.animations[0].channels:
        if ch.target.path != "rotation":
            continue
        sampler = gltf.animations[0].samplers[ch.sampler]
        key_t = accessor(sampler.input, 1)[:, 0]
        keys = Rotation.from_quat(accessor(sampler.output, 4))
        local[ch.target.node] = Slerp(key_t, keys)(np.clip(t, key_t[0], key_t[-1]))
    parent = {c: i for i, node in enumerate(gltf.nodes) for c in node.children or []}
    node_of = {node.name: i for i, node in enumerate(gltf.nodes)}

    def world(i: int) -> Rotation:
        p = parent.get(i)
        if p is None or p not in local:  # under the world node
            return local[i]
        return world(p) * local[i]

    return np.stack([world(node_of[n]).as_quat() for n in names], axis=1)


def _blender() -> str:
    exe = shutil.which("blender")
    if exe is not None:
        return exe
    reason = "blender not found on PATH (Debian: apt-get install blender)"
    if IN_CI:
        pytest.fail(f"{reason} (CI=true: nothing may skip)")
    pytest.skip(reason)


@pytest.mark.timeout(300)
def test_blender_imports_the_reduced_glb(
    datasets: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    exe = _blender()
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
        names = [str(n) for n in z["bone_names"]]
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
    to_gltf = Rotation.from_quat(GLTF_FROM_WORLD_QUAT, scalar_first=True)
    played = _played_world(glb, names, times)
    worst = worst_keys = 0.0
    for k, (f, t) in enumerate(zip(frames, times, strict=True)):
        objects = doc["frames"][repr(t)]
        for b, name in enumerate(names):
            got = Rotation.from_matrix(np.array(objects[name])[:3, :3])
            want = Rotation.from_quat(wfb[f, b], scalar_first=True) * to_gltf
            ang = math.degrees((got * want.inv()).magnitude())
            worst = max(worst, ang)
            assert ang <= TOL_DEG * (depth[b] + 1) + 0.05, (name, f, ang)
            keyed = Rotation.from_quat(played[k, b]) * to_gltf
            ang_keys = math.degrees((got * keyed.inv()).magnitude())
            worst_keys = max(worst_keys, ang_keys)
            assert ang_keys < 0.05, (name, f, ang_keys)
    print(
        f"\nBlender {doc['version']}: worst bone axes {worst:.3f} deg against the "
        f"solve, {worst_keys:.4f} deg against the keys played back"
    )
