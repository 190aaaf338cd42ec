"""``retargetd retarget IN.bvh --target TARGET.bvh --out OUT.bvh|.glb``: a BVH written
by our own solve, mapped onto targets with another rest pose (every joint turned, the
lengths scaled, a root OFFSET) and other rotation orders, gives the same world bone
directions within 0.1°, by equal names, by a ``--map`` file and by the built-in
humanoid maps. Both files are posed with an independent forward kinematics (scipy).
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pygltflib
import pytest
from gltf_tools import issue_summary, require_blender, validate_glb
from scipy.spatial.transform import Rotation

from retargetd.daemon.cli.main import main
from retargetd.daemon.post.pivot import ShiftingPivot
from retargetd.daemon.retarget.bvh_retarget import rig_bone_humanoid_map
from retargetd.daemon.retarget.skeleton import DEFAULT_BVH_NAME_MAP
from retargetd.replay.bvh import (
    BvhSkeleton,
    bvh_motion,
    bvh_skeleton,
    read_bvh_hierarchy,
    split_bvh_motion,
    write_bvh,
)

ORDERS = ("YXZ", "XZY", "ZYX", "YZX", "XYZ")


@pytest.fixture(scope="module")
def source_bvh(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A BVH written by ``retargetd solve`` (synthetic Plug-in Gait take, ZXY)."""
    d = tmp_path_factory.mktemp("src")
    take, bvh = d / "s.c3d", d / "s.bvh"
    assert main(["synth", "--markers", "plug-in-gait", "--seconds", "3", "--rate",
                 "50", "--base-pose-s", "1", "--out", str(take)]) == 0  # fmt: skip
    args = ["solve", str(take), "--rig", "plug-in-gait", "--calibrate-frames", "0:50"]
    assert main([*args, "--out", str(bvh)]) == 0
    return bvh


def _fk(sk: BvhSkeleton) -> list[Rotation]:
    """Global rotation per joint (T frames each): parent * R_1 R_2 R_3 (scipy)."""
    assert sk.frames is not None
    angles, _ = split_bvh_motion(sk, sk.frames)
    glob: list[Rotation] = []
    for j, p in enumerate(sk.parents):
        local = Rotation.from_euler(sk.rotation_orders[j], angles[:, j], degrees=True)
        glob.append(local if p < 0 else glob[p] * local)
    return glob


def _directions(sk: BvhSkeleton) -> dict[tuple[str, str], np.ndarray]:
    """(joint, child or "end") -> (T, 3) unit world direction of that bone."""
    glob = _fk(sk)
    out = {}
    for c, p in enumerate(sk.parents):
        if p >= 0:
            d = glob[p].apply(np.array(sk.offsets[c]))
            out[(sk.joint_names[p], sk.joint_names[c])] = d
    for j, end in enumerate(sk.end_sites):
        if np.isfinite(end).all():
            out[(sk.joint_names[j], "end")] = glob[j].apply(np.array(end))
    return {k: v / np.linalg.norm(v, axis=-1, keepdims=True) for k, v in out.items()}


def _posed_target(
    src: BvhSkeleton, path: Path, *, names: list[str] | None = None, seed: int = 3
) -> BvhSkeleton:
    """The source hierarchy with another rest pose: each joint turned by a random
    rotation (up to ~60°), lengths x1.1, a root OFFSET, other rotation orders."""
    rng = np.random.default_rng(seed)
    n = len(src.joint_names)
    local = Rotation.from_rotvec(rng.normal(scale=0.6, size=(n, 3)))
    glob: list[Rotation] = []
    for j, p in enumerate(src.parents):
        glob.append(local[j] if p < 0 else glob[p] * local[j])
    offsets = np.array(src.offsets, dtype=np.float64)
    for c, p in enumerate(src.parents):
        if p >= 0:
            offsets[c] = 1.1 * glob[p].apply(np.array(src.offsets[c]))
    offsets[0] = [3.0, 95.0, -2.0]
    ends = np.array(src.end_sites, dtype=np.float64)
    for j in range(n):
        if np.isfinite(ends[j]).all():
            ends[j] = 1.1 * glob[j].apply(np.array(ends[j]))
    orders = ["XZY"] + [ORDERS[j % len(ORDERS)] for j in range(1, n)]
    sk = bvh_skeleton(
        joint_names=names or src.joint_names,
        parents=src.parents,
        offsets=offsets,
        rotation_orders=orders,
        end_sites=ends,
    )
    frames = bvh_motion(sk, np.zeros((1, n, 3)), np.zeros((1, n, 3)))
    write_bvh(path, sk, frames, 0.02)
    return sk


def _check_same_directions(
    src: BvhSkeleton, out: BvhSkeleton, rename: dict[str, str] | None = None
) -> int:
    """Every bone of ``out`` whose joints map (by ``rename``: target -> source)
    points where the source's does; returns how many bones were compared."""
    back = rename or {n: n for n in out.joint_names}
    d_src = _directions(src)
    d_out = _directions(out)
    compared = 0
    for (a, b), d in d_out.items():
        key = (back.get(a), "end" if b == "end" else back.get(b))
        if key not in d_src:
            continue
        cos = np.clip(np.sum(d * d_src[key], axis=-1), -1.0, 1.0)
        assert np.degrees(np.arccos(cos)).max() < 0.1, (a, b)
        compared += 1
    return compared


def test_retarget_onto_another_rest_pose_and_orders(
    source_bvh: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    src = read_bvh_hierarchy(source_bvh, read_motion=True)
    tgt_path, out_path = tmp_path / "target.bvh", tmp_path / "out.bvh"
    tgt = _posed_target(src, tgt_path)
    assert main(["retarget", str(source_bvh), "--target", str(tgt_path),
                 "--out", str(out_path)]) == 0  # fmt: skip
    assert "19 of 19 target joints driven" in capsys.readouterr().out
    out = read_bvh_hierarchy(out_path, read_motion=True)
    assert out.rotation_orders == tgt.rotation_orders  # written in the target's
    np.testing.assert_allclose(out.offsets, tgt.offsets, atol=1e-6)
    assert out.n_frames == src.n_frames
    # Sanity: the rest poses really differ (a naive copy of angles would fail).
    d0 = _directions(src)
    tgt_rest = {k: v for k, v in _directions_rest(tgt).items()}
    assert (
        max(
            np.degrees(np.arccos(np.clip(np.dot(d0[k][0], tgt_rest[k]), -1, 1)))
            for k in tgt_rest
            if k in d0
        )
        > 20.0
    )
    # Every bone, including the pelvis -> hip and leaf End Site ones.
    assert _check_same_directions(src, out) == 18 + 5  # bones and leaf End Sites


def _directions_rest(sk: BvhSkeleton) -> dict[tuple[str, str], np.ndarray]:
    out = {}
    for c, p in enumerate(sk.parents):
        if p >= 0:
            out[(sk.joint_names[p], sk.joint_names[c])] = sk.offsets[c]
    for j, end in enumerate(sk.end_sites):
        if np.isfinite(end).all():
            out[(sk.joint_names[j], "end")] = end
    return {k: v / np.linalg.norm(v) for k, v in out.items()}


def test_root_position_scaled(source_bvh: Path, tmp_path: Path) -> None:
    src = read_bvh_hierarchy(source_bvh, read_motion=True)
    tgt_path, out_path = tmp_path / "target.bvh", tmp_path / "out.bvh"
    tgt = _posed_target(src, tgt_path, seed=5)
    assert main(["retarget", str(source_bvh), "--target", str(tgt_path),
                 "--root-scale", "1.1", "--out", str(out_path)]) == 0  # fmt: skip
    out = read_bvh_hierarchy(out_path, read_motion=True)
    assert src.frames is not None and out.frames is not None
    _, p_src = split_bvh_motion(src, src.frames)
    _, p_out = split_bvh_motion(out, out.frames)
    # Root position = OFFSET + channels, on both sides.
    np.testing.assert_allclose(
        tgt.offsets[0] + p_out[:, 0], 1.1 * (src.offsets[0] + p_src[:, 0]), atol=2e-6
    )


def test_retarget_with_a_map_file(
    source_bvh: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    src = read_bvh_hierarchy(source_bvh, read_motion=True)
    names = [f"J{k:02d}" for k in range(len(src.joint_names))]
    tgt_path, out_path = tmp_path / "target.bvh", tmp_path / "out.bvh"
    _posed_target(src, tgt_path, names=names, seed=7)
    map_path = tmp_path / "map.toml"
    map_path.write_text(
        "[joints]\n"
        + "".join(
            f'"{s}" = "{t}"\n' for s, t in zip(src.joint_names, names, strict=True)
        )
    )
    base = ["retarget", str(source_bvh), "--target", str(tgt_path), "--out"]
    # Without the map nothing matches: the root is unmapped.
    assert main([*base, str(out_path)]) == 2
    assert "maps to no source joint" in capsys.readouterr().err
    assert main([*base, str(out_path), "--map", str(map_path)]) == 0
    out = read_bvh_hierarchy(out_path, read_motion=True)
    rename = dict(zip(names, src.joint_names, strict=True))
    assert (
        _check_same_directions(src, out, rename) == 18 + 5
    )  # bones and leaf End Sites
    map_path.write_text('[joints]\n"pelvis" = "nope"\n')
    assert main([*base, str(out_path), "--map", str(map_path)]) == 2
    assert "the target has no joint 'nope'" in capsys.readouterr().err


def test_retarget_onto_mixamo_names_by_the_builtin_maps(
    source_bvh: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    src = read_bvh_hierarchy(source_bvh, read_motion=True)
    humanoid = rig_bone_humanoid_map()
    mixamo: dict[str, str] = {}
    for bvh_name, h in DEFAULT_BVH_NAME_MAP.items():
        mixamo.setdefault(h, bvh_name)
    names = [
        f"mixamorig:{mixamo[humanoid[n]]}" if humanoid.get(n) in mixamo else f"x_{n}"
        for n in src.joint_names
    ]
    assert names[0] == "mixamorig:Hips"
    tgt_path, out_path = tmp_path / "target.bvh", tmp_path / "out.glb"
    _posed_target(src, tgt_path, names=names, seed=11)
    bvh_out = tmp_path / "out.bvh"
    assert main(["retarget", str(source_bvh), "--target", str(tgt_path),
                 "--out", str(bvh_out)]) == 0  # fmt: skip
    text = capsys.readouterr().out
    assert "mixamorig:LeftForeArm<-llowerarm" in text
    out = read_bvh_hierarchy(bvh_out, read_motion=True)
    rename = dict(zip(names, src.joint_names, strict=True))
    n_mapped = sum(not n.startswith("x_") for n in names)
    assert n_mapped >= 15
    assert _check_same_directions(src, out, rename) >= 15
    # The same take as glTF: node rotations are the BVH's local rotations, on a
    # skin of the target's joints (named as in the target) with a capsule per
    # joint-to-child segment; no validator error or warning.
    assert main(["retarget", str(source_bvh), "--target", str(tgt_path),
                 "--glb-mesh", "capsules", "--out", str(out_path)]) == 0  # fmt: skip
    report = validate_glb(out_path)
    assert report["issues"]["numErrors"] == 0, issue_summary(report)
    assert report["issues"]["numWarnings"] == 0, issue_summary(report)
    gltf = pygltflib.GLTF2().load(str(out_path))
    assert [n.name for n in gltf.nodes] == [*names, "body"]
    assert gltf.skins[0].joints == list(range(len(names)))
    assert gltf.skins[0].skeleton == 0  # the root joint: no scene root node
    assert len(gltf.meshes) == 1 and gltf.nodes[-1].skin == 0
    assert out.frames is not None
    angles, _ = split_bvh_motion(out, out.frames)
    blob = gltf.binary_blob()
    anim = gltf.animations[0]
    checked = 0
    for ch in anim.channels:
        if ch.target.path != "rotation":
            continue
        j = out.joint_names.index(gltf.nodes[ch.target.node].name)
        acc = gltf.accessors[anim.samplers[ch.sampler].output]
        view = gltf.bufferViews[acc.bufferView]
        start = (view.byteOffset or 0) + (acc.byteOffset or 0)
        xyzw = np.frombuffer(blob, np.float32, acc.count * 4, start).reshape(-1, 4)
        local = Rotation.from_euler(out.rotation_orders[j], angles[:, j], degrees=True)
        err = (Rotation.from_quat(xyzw.astype(np.float64)).inv() * local).magnitude()
        assert np.degrees(err).max() < 1e-3
        checked += 1
    assert checked == len(names)


def _with_extra_spine(src: BvhSkeleton, path: Path) -> BvhSkeleton:
    """The source hierarchy with two joints inserted between chest and neck (in
    thirds of the chest -> neck offset) and one between spine and chest: a target
    with more spine bones than the rig solves."""
    inserts = {"neck": ["chest_a", "chest_b"], "chest": ["spine_a"]}
    names: list[str] = []
    parents: list[int] = []
    offsets: list[np.ndarray] = []
    ends: list[np.ndarray] = []
    index: dict[str, int] = {}
    for j, name in enumerate(src.joint_names):
        p = src.parents[j]
        parent = -1 if p < 0 else index[src.joint_names[p]]
        extra = inserts.get(name, [])
        step = np.array(src.offsets[j]) / (len(extra) + 1)
        for e in extra:
            index[e] = len(names)
            names.append(e)
            parents.append(parent)
            offsets.append(step if parent >= 0 else np.zeros(3))
            ends.append(np.full(3, np.nan))
            parent = index[e]
        index[name] = len(names)
        names.append(name)
        parents.append(parent)
        offsets.append(step if extra else np.array(src.offsets[j]))
        ends.append(np.array(src.end_sites[j]))
    n = len(names)
    sk = bvh_skeleton(
        joint_names=names,
        parents=parents,
        offsets=np.array(offsets),
        rotation_orders=["YXZ"] * n,
        end_sites=np.array(ends),
    )
    write_bvh(path, sk, bvh_motion(sk, np.zeros((1, n, 3)), np.zeros((1, n, 3))), 0.02)
    return sk


@pytest.mark.parametrize("spread", [False, True])
def test_more_spine_bones_than_the_source(
    source_bvh: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], spread: bool
) -> None:
    src = read_bvh_hierarchy(source_bvh, read_motion=True)
    tgt_path, out_path = tmp_path / "target.bvh", tmp_path / "out.bvh"
    _with_extra_spine(src, tgt_path)
    args = ["retarget", str(source_bvh), "--target", str(tgt_path), "--out",
            str(out_path)] + (["--spread"] if spread else [])  # fmt: skip
    assert main(args) == 0
    text = capsys.readouterr().out
    assert "unmapped (keep their rest): spine_a chest_a chest_b" in text
    out = read_bvh_hierarchy(out_path, read_motion=True)
    assert out.frames is not None
    # The mapped bones still point where the source's do (neck -> head, arms, legs).
    assert _check_same_directions(src, out) >= 18 + 5 - 2
    angles, _ = split_bvh_motion(out, out.frames)
    local = {
        name: Rotation.from_euler("YXZ", angles[:, j], degrees=True)
        for j, name in enumerate(out.joint_names)
    }
    moved = np.degrees(local["neck"].magnitude()).max()
    assert moved > 5.0  # the take bends the neck against the chest
    if not spread:
        for e in ("spine_a", "chest_a", "chest_b"):
            assert np.degrees(local[e].magnitude()).max() < 1e-6
        return
    assert "sharing a chain's rotation: spine_a chest_a chest_b" in text
    # chest -> chest_a -> chest_b -> neck: three equal shares of one rotation.
    for a, b in (("chest_a", "chest_b"), ("chest_b", "neck")):
        assert np.degrees((local[a].inv() * local[b]).magnitude()).max() < 1e-4
    whole = local["chest_a"] * local["chest_b"] * local["neck"]
    src_angles, _ = split_bvh_motion(src, src.frames)
    k = src.joint_names.index("neck")
    neck_src = Rotation.from_euler(
        src.rotation_orders[k], src_angles[:, k], degrees=True
    )
    # The source's rest and the target's are the same here: the product is the
    # source's chest -> neck rotation.
    assert np.degrees((whole.inv() * neck_src).magnitude()).max() < 1e-4
    for a, b in (("spine_a", "chest"),):
        assert np.degrees((local[a].inv() * local[b]).magnitude()).max() < 1e-4


def test_spread_pivot_emits_the_chain_by_the_shifting_pivot(
    source_bvh: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--spread pivot``: the rotation between two mapped joints (chest -> neck, and
    spine -> chest) goes over the chain's joints by the chapter's shifting pivot
    (rx, rz doubled, 15 deg a joint, carry-over; ry shared), the listing applied to
    each frame's whole rotation; the mapped joints below keep their world rotation."""
    src = read_bvh_hierarchy(source_bvh, read_motion=True)
    tgt_path = tmp_path / "target.bvh"
    _with_extra_spine(src, tgt_path)
    outs = {}
    for how in ("equal", "pivot"):
        out_path = tmp_path / f"{how}.bvh"
        argv = ["retarget", str(source_bvh), "--target", str(tgt_path), "--out",
                str(out_path), "--spread", how]  # fmt: skip
        assert main(argv) == 0
        text = capsys.readouterr().out
        out = read_bvh_hierarchy(out_path, read_motion=True)
        assert out.frames is not None
        angles, _ = split_bvh_motion(out, out.frames)
        outs[how] = {
            name: Rotation.from_euler("YXZ", angles[:, j], degrees=True)
            for j, name in enumerate(out.joint_names)
        }
    assert "sharing a chain's rotation (shifting pivot, 15 deg a joint)" in text
    eq, pv = outs["equal"], outs["pivot"]
    worst = 0.0
    # Spine -> chest first (the equal shares multiply back to the whole rotation),
    # then chest -> neck from the chest the pivot made: conj(G_chest') G_neck.
    lower = eq["spine_a"] * eq["chest"]
    upper = (pv["spine_a"] * pv["chest"]).inv() * lower
    upper = upper * eq["chest_a"] * eq["chest_b"] * eq["neck"]
    for chain, group in ((("spine_a", "chest"), lower),
                         (("chest_a", "chest_b", "neck"), upper)):  # fmt: skip
        stage = ShiftingPivot(len(chain), 15.0)
        shares = np.empty((len(chain), 4))
        for t in range(len(group)):
            stage.apply(group[t].as_quat(scalar_first=True), shares)
            for k, j in enumerate(chain):
                want = Rotation.from_quat(shares[k], scalar_first=True)
                err = np.degrees((pv[j][t].inv() * want).magnitude())
                worst = max(worst, float(err))
    assert worst < 1e-3, worst
    # Where a chain's rotation exceeds one joint's limit the shares differ from the
    # equal ones (the test sees the pivot, not the equal spread).
    diff = np.degrees((pv["chest_a"].inv() * eq["chest_a"]).magnitude()).max()
    assert diff > 0.1, diff

    # The head (mapped, below the chains) keeps its world rotation: the product
    # down from the spine is the same in both.
    def down(r: dict[str, Rotation]) -> Rotation:
        chain = ("spine_a", "chest", "chest_a", "chest_b", "neck", "head")
        out = r[chain[0]]
        for j in chain[1:]:
            out = out * r[j]
        return out

    err = np.degrees((down(pv).inv() * down(eq)).magnitude()).max()
    assert err < 1e-3, err
    print(f"\n--spread pivot: shares equal the listing's within {worst:.1e} deg")


#: The bent spine of the ``--spread hermite`` test: z = BEND_PER_CM2 * y**3 (cm), a
#: forward flexion that starts straight at the hips and bends more and more (curvature
#: 6 a y): no equal spread of one rotation, which makes a circle, can follow it.
BEND_PER_CM2 = 2e-4
SRC_BONE_CM = 16.0


def _cubic_points(n: int, bone_cm: float) -> np.ndarray:
    """n points on the cubic (y, z) with equal chords ``bone_cm`` from the origin."""
    pts = [np.zeros(2)]
    for _ in range(n - 1):
        y0 = pts[-1][0]
        lo, hi = y0, y0 + bone_cm
        for _ in range(80):  # bisection on the chord length
            mid = 0.5 * (lo + hi)
            chord = np.hypot(mid - y0, BEND_PER_CM2 * (mid**3 - y0**3))
            lo, hi = (mid, hi) if chord < bone_cm else (lo, mid)
        pts.append(np.array([lo, BEND_PER_CM2 * lo**3]))
    return np.array(pts)


def _bent_spine_bvh(path: Path, frames: int) -> BvhSkeleton:
    """Hips -> Spine -> Chest -> Neck -> Head along +Y at rest; the motion bends the
    spine from straight (frame 0) onto the cubic (last frame): each bone along its
    chord, so the solved spine joints lie on the curve. Rotations about X only."""
    names = ["Hips", "Spine", "Chest", "Neck", "Head"]
    offsets = np.zeros((5, 3))
    offsets[1:, 1] = SRC_BONE_CM
    offsets[0] = [0.0, 90.0, 0.0]
    ends = np.full((5, 3), np.nan)
    ends[4] = [0.0, 10.0, 0.0]
    sk = bvh_skeleton(joint_names=names, parents=[-1, 0, 1, 2, 3], offsets=offsets,
                      rotation_orders=["ZXY"] * 5, end_sites=ends)  # fmt: skip
    pts = _cubic_points(5, SRC_BONE_CM)
    chord = np.diff(pts, axis=0)
    # World angle about +X taking +Y onto (0, cy, cz): +X turns +Y towards +Z.
    world = np.degrees(np.arctan2(chord[:, 1], chord[:, 0]))
    world = np.append(world, world[-1])  # the head continues the neck
    local = np.diff(np.concatenate([[0.0], world]))
    s = np.linspace(0.0, 1.0, frames)[:, None]
    angles = np.zeros((frames, 5, 3))
    angles[:, :, 1] = s * local[None]  # ZXY: the X angle is the second
    positions = np.zeros((frames, 5, 3))
    positions[:, 0] = offsets[0]
    write_bvh(path, sk, bvh_motion(sk, angles, positions), 0.02)
    return sk


def _long_spine_target(path: Path, n_spine: int = 5) -> None:
    """Hips, ``n_spine`` spine joints, Neck, Head: straight, 1.3 times the source's
    spine length, names only Hips, Neck and Head map."""
    names = ["Hips", *(f"vert{k}" for k in range(1, n_spine + 1)), "Neck", "Head"]
    n = len(names)
    offsets = np.zeros((n, 3))
    offsets[0] = [0.0, 100.0, 0.0]
    offsets[1:-1, 1] = 1.3 * 3 * SRC_BONE_CM / (n_spine + 1)
    offsets[-1, 1] = 12.0
    ends = np.full((n, 3), np.nan)
    ends[-1] = [0.0, 10.0, 0.0]
    sk = bvh_skeleton(joint_names=names, parents=list(range(-1, n - 1)),
                      offsets=offsets, rotation_orders=["YXZ"] * n,
                      end_sites=ends)  # fmt: skip
    write_bvh(path, sk, bvh_motion(sk, np.zeros((1, n, 3)), np.zeros((1, n, 3))), 0.02)


def _curve_error(out: BvhSkeleton) -> tuple[float, float]:
    """On the last (fully bent) frame: the worst distance of the target's joints from
    Hips to Neck to the cubic the source's spine joints lie on, and how far the
    target's neck joint bends away from straight, both in units of the target's
    spine length (scipy FK; the target scaled to the cubic's arc length)."""
    glob = _fk(out)
    neck = out.joint_names.index("Neck")
    pos = np.zeros((neck + 1, 3))
    for j in range(1, neck + 1):
        pos[j] = pos[j - 1] + glob[j - 1][-1].apply(np.array(out.offsets[j]))
    bones = np.asarray(out.offsets[1 : neck + 1])
    length_t = float(np.linalg.norm(bones, axis=-1).sum())
    y_end = _cubic_points(4, SRC_BONE_CM)[-1, 0]
    y = np.linspace(0.0, y_end, 200001)
    curve = np.stack([np.zeros_like(y), y, BEND_PER_CM2 * y**3], axis=-1)
    arc = float(np.linalg.norm(np.diff(curve, axis=0), axis=-1).sum())
    scaled = pos * (arc / length_t)
    gaps = np.array([np.min(np.linalg.norm(curve - p, axis=-1)) for p in scaled])
    bent = float(np.hypot(*pos[-1, 1:] - [length_t, 0.0])) / length_t
    return float(gaps.max()) / arc, bent


def test_spread_hermite_puts_a_longer_spine_on_the_curve(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--spread hermite``: a 3-bone source spine bent onto a cubic (its chords at
    3, 19 and 40 deg: straight at the hips, curvature rising to 1/19 cm at the chest)
    drives a target with 5 spine joints, 1.3 times as long. The target's joints from
    Hips to Neck lie on the bend within 1 % of the spine's length (measured 0.64 %),
    against 6 % for the equal spread of the Hips -> Neck rotation (a circle: the
    wrong shape), and the mapped neck and head keep the source's world directions.

    Why 1 %: two errors add up. The curve's own, from only four points over a 40 deg
    bend (the Hermite interpolation error, third order in the spacing; bounded for an
    arc in ``tests/daemon/post/test_hermite``); and the first target bone, which hangs
    on the Hips (whose rotation also drives the legs and stays the source's), so it
    runs along the source's first chord rather than the curve; the chain below aims
    each bone from where its joint really is, so that offset is not passed on.
    """
    src_path, tgt_path = tmp_path / "bent.bvh", tmp_path / "long.bvh"
    _bent_spine_bvh(src_path, 3)
    src = read_bvh_hierarchy(src_path, read_motion=True)
    _long_spine_target(tgt_path)
    errors = {}
    outs = {}
    for how in ("equal", "hermite"):
        out_path = tmp_path / f"{how}.bvh"
        argv = ["retarget", str(src_path), "--target", str(tgt_path), "--out",
                str(out_path), "--spread", how]  # fmt: skip
        assert main(argv) == 0
        text = capsys.readouterr().out
        out = read_bvh_hierarchy(out_path, read_motion=True)
        outs[how] = out
        errors[how] = _curve_error(out)
    assert "on the Hermite spine curve: vert1 vert2 vert3 vert4 vert5" in text
    print(
        "\nspine bend followed: worst joint off the curve "
        f"{100 * errors['hermite'][0]:.2f} % of the spine (equal spread "
        f"{100 * errors['equal'][0]:.2f} %)"
    )
    assert errors["hermite"][0] < 0.01, errors
    assert errors["equal"][0] > 2 * errors["hermite"][0], errors
    assert errors["hermite"][1] > 0.2  # the target did bend
    # The mapped neck and head point where the source's do.
    d_src, d_out = _directions(src), _directions(outs["hermite"])
    for key in (("Neck", "Head"), ("Head", "end")):
        cos = np.clip(np.sum(d_src[key] * d_out[key], axis=-1), -1.0, 1.0)
        assert np.degrees(np.arccos(cos)).max() < 1e-3, key


BLENDER_SCRIPT = r"""
import json, sys
import bpy

glb, out, times = sys.argv[sys.argv.index("--") + 1:]
bpy.ops.import_scene.gltf(filepath=glb)  # every option at its default
scene = bpy.context.scene
fps = scene.render.fps / scene.render.fps_base
(arma,) = [o for o in scene.objects if o.type == "ARMATURE"]
action = arma.animation_data.action
first = min(kp.co[0] for fc in action.fcurves for kp in fc.keyframe_points)
doc = {"bones": [b.name for b in arma.data.bones],
       "keys": [len(fc.keyframe_points) for fc in action.fcurves], "heads": {}}
for t in [float(x) for x in times.split(",")]:
    f = first + t * fps
    scene.frame_set(int(f), subframe=f - int(f))
    doc["heads"][repr(t)] = {
        pb.name: list(arma.matrix_world @ pb.head) for pb in arma.pose.bones
    }
with open(out, "w") as fh:
    json.dump(doc, fh)
"""


@pytest.mark.timeout(300)
def test_blender_imports_the_retargeted_glb_as_an_armature(
    source_bvh: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``retarget --out .glb``: Blender (headless, importer defaults) builds an
    armature of the target's joints whose action keys every frame, and puts each
    bone's head where the retargeted BVH's forward kinematics puts the joint
    (centimetres to metres; BVH's +Y up is glTF's, which Blender turns to +Z up:
    ``(x, y, z) -> (x, -z, y)``), within 0.1 mm."""
    exe = require_blender()
    src = read_bvh_hierarchy(source_bvh, read_motion=True)
    tgt_path, glb, bvh = tmp_path / "t.bvh", tmp_path / "o.glb", tmp_path / "o.bvh"
    _posed_target(src, tgt_path)
    for out_path in (glb, bvh):
        assert main(["retarget", str(source_bvh), "--target", str(tgt_path),
                     "--out", str(out_path)]) == 0  # fmt: skip
    capsys.readouterr()
    out = read_bvh_hierarchy(bvh, read_motion=True)
    assert out.frames is not None
    n_frames, names = len(out.frames), list(out.joint_names)
    glob = _fk(out)
    _, positions = split_bvh_motion(out, out.frames)
    pos = np.zeros((n_frames, len(names), 3))
    for j, p in enumerate(out.parents):
        # The root's channels move it from its OFFSET; children hang at theirs.
        pos[:, j] = (
            positions[:, 0] + out.offsets[0]
            if p < 0
            else pos[:, p] + glob[p].apply(np.array(out.offsets[j]))
        )
    frames = [0, n_frames // 2, n_frames - 1]
    times = [f * out.frame_time_s for f in frames]
    script, dump = tmp_path / "dump.py", tmp_path / "blender.json"
    script.write_text(BLENDER_SCRIPT)
    cmd = [exe, "-b", "--factory-startup", "--python-exit-code", "1",
           "--python", str(script), "--", str(glb), str(dump),
           ",".join(repr(t) for t in times)]  # fmt: skip
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=240, check=False)
    assert run.returncode == 0 and dump.is_file(), run.stderr[-2000:]
    doc = json.loads(dump.read_text())
    assert doc["bones"] == names
    assert doc["keys"] == [n_frames] * (4 * len(names) + 3)
    worst = 0.0
    for f, t in zip(frames, times, strict=True):
        for j, name in enumerate(names):
            x, y, z = 0.01 * pos[f, j]
            err = 1e3 * np.linalg.norm(
                np.array(doc["heads"][repr(t)][name]) - [x, -z, y]
            )
            worst = max(worst, err)
            assert err < 0.1, (name, f, err)
    print(
        f"\nBlender: {len(names)} bones, {n_frames} keys a curve; worst {worst:.4f} mm"
    )
