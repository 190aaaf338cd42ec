"""Interop: Blender imports our .glb and poses every node where our solve has it.

Blender (Debian package ``blender``) runs headless and imports the file with
``bpy.ops.import_scene.gltf`` and its default options. Nodes without a mesh become
empties named as the nodes; the importer converts glTF's +Y up to Blender's +Z up
(glTF +Z -> Blender -Y), which undoes our ``world`` node (world +Z -> glTF +Y, world -Y
-> glTF +Z): Blender's world is our world, in metres. Keys land at
``first_key_frame + t * fps`` (read back from the imported curves, not assumed), so the
script sets frames with subframes at our frame times and dumps every empty's world
matrix.

The importer converts every node's own rotation too (``q -> C q C⁻¹``, ``C`` =
Blender from glTF = world from glTF), so an empty's axes in Blender are
``world_from_bone ⊗ gltf_from_world``: its local axes are the bone's, re-labelled
Y-up as glTF has them.

Compared at several frames of the PiG walk (every frame written): each bone's origin
against the calibrated skeleton posed by the solve (0.1 mm) and its axes against
``world_from_bone ⊗ gltf_from_world`` (0.1°).
"""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from retargetd.daemon.post.export_gltf import (
    GLTF_FROM_WORLD_QUAT,
    clip_from_solve,
    write_clip_glb,
)
from retargetd.daemon.target.bvh import posed_bone_origins

IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")
MAX_ANGLE_DEG = 0.1
MAX_POS_MM = 0.1

SCRIPT = r"""
import json, sys
import bpy

glb, out, times = sys.argv[sys.argv.index("--") + 1:]
bpy.ops.import_scene.gltf(filepath=glb)  # every option at its default
scene = bpy.context.scene
fps = scene.render.fps / scene.render.fps_base
first = min(
    kp.co[0]
    for o in scene.objects if o.animation_data and o.animation_data.action
    for fc in o.animation_data.action.fcurves for kp in fc.keyframe_points
)
doc = {"version": bpy.app.version_string, "fps": fps, "first": first, "frames": {}}
for t in [float(x) for x in times.split(",")]:
    f = first + t * fps
    scene.frame_set(int(f), subframe=f - int(f))
    doc["frames"][repr(t)] = {
        o.name: [list(row) for row in o.matrix_world] for o in scene.objects
    }
with open(out, "w") as fh:
    json.dump(doc, fh)
"""


def _blender() -> str:
    exe = shutil.which("blender")
    if exe is not None:
        return exe
    reason = "blender not found on PATH (Debian: apt-get install blender)"
    if IN_CI:
        pytest.fail(f"{reason} (CI=true: nothing may skip)")
    pytest.skip(reason)


@pytest.mark.timeout(300)
def test_blender_imports_our_glb(pig_walk: Any, tmp_path: Path) -> None:
    exe = _blender()
    cal, res = pig_walk.calibration, pig_walk.solve
    clip = clip_from_solve(res, cal, pig_walk.rate_hz)
    glb = tmp_path / "walk.glb"
    write_clip_glb(glb, clip, cal)
    frames = [0, clip.n_frames // 3, (2 * clip.n_frames) // 3, clip.n_frames - 1]
    times = [f / clip.rate_hz for f in frames]
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
    print(
        f"\nBlender {doc['version']}: fps {doc['fps']}, first key frame {doc['first']}"
    )
    posed = posed_bone_origins(cal, res.world_from_bone_quat, res.root_pos)
    worst_mm = worst_deg = 0.0
    for f, t in zip(frames, times, strict=True):
        objects = doc["frames"][repr(t)]
        for j, name in enumerate(cal.bone_names):
            m = np.array(objects[name])
            pos_mm = 1e3 * np.linalg.norm(m[:3, 3] - posed[f, j])
            want = Rotation.from_quat(res.world_from_bone_quat[f, j], scalar_first=True)
            want = want * Rotation.from_quat(GLTF_FROM_WORLD_QUAT, scalar_first=True)
            got = Rotation.from_matrix(m[:3, :3])
            ang = math.degrees((got * want.inv()).magnitude())
            worst_mm, worst_deg = max(worst_mm, pos_mm), max(worst_deg, ang)
            assert pos_mm < MAX_POS_MM, (name, f, pos_mm)
            assert ang < MAX_ANGLE_DEG, (name, f, ang)
    print(f"worst {worst_mm:.4f} mm, {worst_deg:.4f} deg")
