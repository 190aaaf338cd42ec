"""glTF 2.0 binary writer, read back with an independent reader (pygltflib)."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest
from pygltflib import GLTF2

from retargetd.replay.gltf import GltfChannel, write_glb, xyzw_from_wxyz


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
