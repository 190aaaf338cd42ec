"""A solved real take as .glb, read back with pygltflib: every frame poses the
skeleton as the solve does; a reduced file re-sampled stays within the tolerance."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from pygltflib import GLTF2
from scipy.spatial.transform import Rotation, Slerp

from retargetd.daemon.post.export_gltf import (
    GLTF_FROM_WORLD_QUAT,
    clip_from_solve,
    write_clip_glb,
    write_reduced_glb,
)
from retargetd.daemon.post.reduce import reduce_clip
from retargetd.daemon.retarget.bvh import posed_bone_origins
from retargetd.protocols.conventions import world_from_capture_mat

#: float32 storage: a unit quaternion's components are rounded by <= 2^-24, which
#: turns it by at most ~2 * 2 * 2^-24 rad; times by 2^-24 s relative. 1e-4° covers both.
F32_DEG = 1e-4


def _accessor(gltf: GLTF2, index: int) -> np.ndarray:
    acc = gltf.accessors[index]
    view = gltf.bufferViews[acc.bufferView]
    width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[acc.type]
    offset = (view.byteOffset or 0) + (acc.byteOffset or 0)
    data = np.frombuffer(gltf.binary_blob(), "<f4", acc.count * width, offset)
    return data.astype(np.float64).reshape(acc.count, width)


def _sampled(
    gltf: GLTF2, times: np.ndarray
) -> tuple[dict[int, Rotation], dict[int, np.ndarray]]:
    """Every channel re-sampled at ``times`` with scipy (glTF LINEAR: slerp / lerp)."""
    rots, trans = {}, {}
    for ch in gltf.animations[0].channels:
        s = gltf.animations[0].samplers[ch.sampler]
        assert s.interpolation == "LINEAR"
        t = _accessor(gltf, s.input)[:, 0]
        v = _accessor(gltf, s.output)
        if ch.target.path == "rotation":
            keys = Rotation.from_quat(v, scalar_first=False)  # glTF is x y z w
            rots[ch.target.node] = Slerp(t, keys)(np.clip(times, t[0], t[-1]))
        else:
            trans[ch.target.node] = np.stack(
                [np.interp(times, t, v[:, d]) for d in range(3)], -1
            )
    return rots, trans


def test_every_frame_poses_the_skeleton(pig_walk: Any, tmp_path: Path) -> None:
    cal, res = pig_walk.calibration, pig_walk.solve
    clip = clip_from_solve(res, cal, pig_walk.rate_hz)
    path = tmp_path / "walk.glb"
    write_clip_glb(path, clip, cal)
    gltf = GLTF2().load(str(path))
    names = [n.name for n in gltf.nodes]
    assert names == [*cal.bone_names, "world"]
    m = world_from_capture_mat("+Y").T  # glTF axes from ours, as the BVH export
    world_node = gltf.nodes[-1]
    np.testing.assert_allclose(
        Rotation.from_quat(world_node.rotation, scalar_first=False).as_matrix(),
        m,
        atol=1e-7,
    )
    np.testing.assert_allclose(
        Rotation.from_quat(GLTF_FROM_WORLD_QUAT, scalar_first=True).as_matrix(),
        m,
        atol=1e-15,
    )
    times = np.arange(clip.n_frames) / clip.rate_hz
    rots, trans = _sampled(gltf, times)
    # Forward kinematics of the file (independent: scipy), parents from the nodes.
    parent = {c: i for i, n in enumerate(gltf.nodes) for c in (n.children or [])}
    world_rot: dict[int, Rotation] = {}
    world_pos: dict[int, np.ndarray] = {}
    scene = Rotation.from_quat(world_node.rotation, scalar_first=False)
    for j in range(len(cal.bone_names)):  # parents come first in a rig
        node = gltf.nodes[j]
        t_local = trans.get(j, np.tile(node.translation, (len(times), 1)))
        p = parent[j]
        pr, pp = (
            (scene, np.zeros(3))
            if p == len(names) - 1
            else (world_rot[p], world_pos[p])
        )
        world_pos[j] = pp + pr.apply(t_local)
        world_rot[j] = pr * rots[j]
    expected_pos = posed_bone_origins(cal, res.world_from_bone_quat, res.root_pos) @ m.T
    for j in range(len(cal.bone_names)):
        got = world_rot[j].as_matrix()
        want = (
            m
            @ Rotation.from_quat(
                res.world_from_bone_quat[:, j], scalar_first=True
            ).as_matrix()
        )
        err_deg = np.degrees(
            Rotation.from_matrix(got @ np.swapaxes(want, 1, 2)).magnitude()
        )
        assert err_deg.max() < 1e-3, (cal.bone_names[j], err_deg.max())
        err_mm = 1e3 * np.linalg.norm(world_pos[j] - expected_pos[:, j], axis=-1)
        assert err_mm.max() < 1e-3, (cal.bone_names[j], err_mm.max())


def test_reduced_file_within_tolerance(pig_walk: Any, tmp_path: Path) -> None:
    cal, res = pig_walk.calibration, pig_walk.solve
    clip = clip_from_solve(res, cal, pig_walk.rate_hz)
    tol_deg, tol_mm = 0.5, 1.0
    red = reduce_clip(clip, tolerance_deg=tol_deg, tolerance_mm=tol_mm)
    path = tmp_path / "walk_reduced.glb"
    write_reduced_glb(path, red, cal)
    gltf = GLTF2().load(str(path))
    times = np.arange(clip.n_frames) / clip.rate_hz
    rots, trans = _sampled(gltf, times)
    kept = [len(ch.frames) for ch in red.rotations]
    worst = 0.0
    for b, name in enumerate(cal.bone_names):
        data = Rotation.from_quat(clip.parent_from_bone_quat[:, b], scalar_first=True)
        err = np.degrees((rots[b] * data.inv()).magnitude()).max()
        worst = max(worst, err)
        assert err <= tol_deg + F32_DEG, (name, err)
    root = int(np.flatnonzero(np.asarray(cal.bone_parents) < 0)[0])
    err_mm = 1e3 * np.linalg.norm(trans[root] - clip.root_pos, axis=-1).max()
    assert err_mm <= tol_mm + 1e-3  # float32 metres: 2^-24 of ~10 m is < 1e-3 mm
    print(
        f"\nPiG walk: {sum(kept)} of {clip.n_frames * len(kept)} rotation keys kept "
        f"(per bone {kept}), root {len(red.root.frames)} keys; worst {worst:.3f} deg, "
        f"root {err_mm:.3f} mm"
    )
    assert sum(kept) < clip.n_frames * len(kept) / 2
