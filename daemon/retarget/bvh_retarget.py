"""Rotational data in (the chapter's first section): a BVH take mapped onto another
BVH skeleton, ``retargetd retarget IN.bvh --target TARGET.bvh --out OUT.bvh|OUT.glb``.

Both files are read in their own axes, taken to be the same axes (BVH does not say;
usually +Y up): only rotations are mapped, so the length units may differ. A BVH
rest pose has every joint at identity, its axes parallel to the file's, so two files
whose rest poses differ (a T-pose and an A-pose, bones along other axes) need the
rest-pose offset compensated (the chapter's "negative of the offset"):

    G_j(t)   = G_parent(t) R_j(t)            source FK, R_j from its channels in its
                                             own rotation order (R = R_1 R_2 R_3)
    G'_j(t)  = G_{s(j)}(t) C_j               target joint j driven by source joint s(j)
    R'_j(t)  = conj(G'_parent(t)) G'_j(t)
             = conj(C_parent) R^{s}_j(t) C_j  (when the parents map onto each other:
                                             the offset's negative on the left, the
                                             offset on the right)

``C_j`` turns the target's rest bone directions onto the source's: for each pair of
a target child ``c`` of ``j`` (through unmapped joints) and its source joint,
``C_j d'_c ≈ d_c`` with ``d`` the unit rest direction from the joint to the child (a
leaf: to its End Site). Two or more non-parallel pairs: the least-squares rotation
(Kabsch / Wahba, an SVD); one pair: the shortest arc. So every mapped bone points, in
the world, where its source bone points, whatever the two rest poses are; with one
child the twist about the bone is the source's. A target joint that maps to nothing
keeps its rest (local identity: it follows its parent), or with ``spread`` (``retarget
--spread``), when it sits on a plain chain between two mapped joints (a target with
more spine bones than the source), takes an equal share of the rotation between them
(:func:`spread_chains`), or shares given by a ``distribute`` function (``retarget
--spread pivot``: the chapter's shifting pivot,
:func:`retargetd.daemon.post.pivot.pivot_chains`). With a ``spine_curve`` function
(``retarget --spread hermite``) the whole spine, from the target joint mapped to the
source's Hips to the one mapped to its Neck (else Head), is placed along a curve
through the source's spine joints (:func:`spine_paths`; the chapter's Hermite spine,
:func:`retargetd.daemon.post.hermite.hermite_chain`): a target with more spine bones
than the source gets a smooth bend, not the source's corners.

The target root must map to a source joint; its position is that joint's, scaled by
the ratio of the two rest root heights above the lowest rest point (joints and End
Sites) along +Y (1 when either is 0), written as the root's position channels minus
its OFFSET (FK: root position = OFFSET + channels). Output channels: the root's
``Xposition Yposition Zposition`` and every joint's rotation channels in the target's
own order (a joint without rotation channels gets ``ZXY``); non-root position channels
are not written.

Joint names (:func:`match_joints`): an explicit map first (``--map FILE.toml``,
``[joints]`` table ``"source name" = "target name"``), then equal names (ignoring a
``prefix:``), then both names through the humanoid bone maps (the BVH maps of
:mod:`retargetd.daemon.retarget.skeleton` and the shipped rigs' bone names).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.rig import load_rig, shipped_rigs
from retargetd.daemon.retarget.skeleton import CMU_BVH_NAME_MAP, DEFAULT_BVH_NAME_MAP
from retargetd.protocols.frames import F64Array
from retargetd.replay.bvh import (
    BvhSkeleton,
    bvh_motion,
    bvh_skeleton,
    split_bvh_motion,
)
from retargetd.replay.gltf import GltfChannel, write_glb
from retargetd.replay.gltf_mesh import Capsule, bone_capsule, check_mesh

_IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])
#: Rotation order given to target joints that have no rotation channels.
FALLBACK_ORDER = "ZXY"
#: Below this |sin| two rest directions count as parallel (Kabsch then degenerates).
_PARALLEL_SIN = 1e-6


def _short(name: str) -> str:
    return name.rsplit(":", 1)[-1]


@functools.cache
def rig_bone_humanoid_map() -> dict[str, str]:
    """Bone name -> humanoid bone over the shipped rigs (names two rigs disagree on
    are left out), so a BVH written by ``retargetd solve`` maps onto humanoid BVHs."""
    out: dict[str, str] = {}
    clash: set[str] = set()
    for name in shipped_rigs():
        for bone in load_rig(name).bones:
            if not bone.humanoid:
                continue
            if out.get(bone.name, bone.humanoid) != bone.humanoid:
                clash.add(bone.name)
            out[bone.name] = bone.humanoid
    return {k: v for k, v in out.items() if k not in clash}


def _humanoid_names(names: tuple[str, ...]) -> list[str | None]:
    short = [_short(n) for n in names]
    bvh = CMU_BVH_NAME_MAP if "LowerBack" in short else DEFAULT_BVH_NAME_MAP
    rig = rig_bone_humanoid_map()
    out: list[str | None] = []
    for full, s in zip(names, short, strict=True):
        out.append(bvh.get(full, bvh.get(s, rig.get(full, rig.get(s)))))
    return out


def match_joints(
    source: BvhSkeleton,
    target: BvhSkeleton,
    explicit: Mapping[str, str] | None = None,
) -> list[int]:
    """The source joint driving each target joint (module docstring).

    Args:
        source: the take's hierarchy.
        target: the skeleton mapped onto.
        explicit: source joint name -> target joint name, tried first.

    Returns:
        (J',) source joint index per target joint, -1 where none.

    Raises:
        ValueError: a map naming a joint neither file has, or two source joints
            mapped onto one target joint.
    """
    src_index = {n: i for i, n in enumerate(source.joint_names)}
    tgt_index = {n: i for i, n in enumerate(target.joint_names)}
    out = [-1] * len(target.joint_names)
    for s_name, t_name in (explicit or {}).items():
        if s_name not in src_index:
            raise ValueError(f"map: the source has no joint {s_name!r}")
        if t_name not in tgt_index:
            raise ValueError(f"map: the target has no joint {t_name!r}")
        if out[tgt_index[t_name]] >= 0:
            raise ValueError(f"map: two source joints map onto {t_name!r}")
        out[tgt_index[t_name]] = src_index[s_name]
    used = {s for s in out if s >= 0}
    by_short: dict[str, int] = {}
    for i, n in enumerate(source.joint_names):
        by_short.setdefault(_short(n), i)
    for j, n in enumerate(target.joint_names):
        s = by_short.get(_short(n), -1)
        if out[j] < 0 and s >= 0 and s not in used:
            out[j] = s
            used.add(s)
    src_h = _humanoid_names(source.joint_names)
    tgt_h = _humanoid_names(target.joint_names)
    by_h = {h: i for i, h in enumerate(src_h) if h is not None}
    for j, h in enumerate(tgt_h):
        s = by_h.get(h, -1) if h is not None else -1
        if out[j] < 0 and s >= 0 and s not in used:
            out[j] = s
            used.add(s)
    return out


def _aim_pairs(
    target: BvhSkeleton, source: BvhSkeleton, mapping: list[int], j: int
) -> tuple[list[F64Array], list[F64Array]]:
    """Unit rest directions (target, source) from joint j to its mapped children."""
    t_rest = target.rest_positions()
    s_rest = source.rest_positions()
    s0 = mapping[j]
    children: list[list[int]] = [[] for _ in target.parents]
    for c, p in enumerate(target.parents):
        if p >= 0:
            children[p].append(c)
    dt: list[F64Array] = []
    ds: list[F64Array] = []
    stack = list(children[j])
    while stack:
        c = stack.pop()
        if mapping[c] < 0:
            stack.extend(children[c])
            continue
        a = t_rest[c] - t_rest[j]
        b = s_rest[mapping[c]] - s_rest[s0]
        if np.linalg.norm(a) > 0.0 and np.linalg.norm(b) > 0.0:
            dt.append(a / np.linalg.norm(a))
            ds.append(b / np.linalg.norm(b))
    if not dt:  # a leaf: End Sites
        a, b = target.end_sites[j], source.end_sites[s0]
        finite = np.isfinite(a).all() and np.isfinite(b).all()
        if finite and np.linalg.norm(a) > 0.0 and np.linalg.norm(b) > 0.0:
            dt.append(a / np.linalg.norm(a))
            ds.append(b / np.linalg.norm(b))
    return dt, ds


def _arc(a: F64Array, b: F64Array) -> F64Array:
    """Shortest-arc rotation taking unit a onto unit b (w, x, y, z)."""
    c = float(np.dot(a, b))
    axis = np.cross(a, b)
    s = float(np.linalg.norm(axis))
    if s < _PARALLEL_SIN:
        if c > 0.0:
            return _IDENTITY.copy()
        # Opposite: half a turn about any axis perpendicular to a.
        perp = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(perp) < 0.1:
            perp = np.cross(a, [0.0, 1.0, 0.0])
        return rot.quat_from_axis_angle(perp / np.linalg.norm(perp), math.pi)
    return rot.quat_from_axis_angle(axis / s, math.atan2(s, c))


def rest_compensation(dt: list[F64Array], ds: list[F64Array]) -> F64Array:
    """``C`` with ``C dt_i ≈ ds_i`` (module docstring).

    Args:
        dt: unit target rest directions, (3,) float64 each.
        ds: the matching unit source rest directions.

    Returns:
        (4,) float64 (w, x, y, z); identity for no pairs.
    """
    if not dt:
        return _IDENTITY.copy()
    a, b = np.asarray(dt), np.asarray(ds)
    spread = any(
        np.linalg.norm(np.cross(a[0], x)) > _PARALLEL_SIN for x in a[1:]
    ) and any(np.linalg.norm(np.cross(b[0], x)) > _PARALLEL_SIN for x in b[1:])
    if len(a) == 1 or not spread:
        return _arc(a[0], b[0])
    h = a.T @ b
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    m = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return rot.quat_from_mat(m)


def _rest_height(sk: BvhSkeleton, root: int) -> float:
    pos = sk.rest_positions()
    tips = pos + sk.end_sites
    floor = min(float(pos[:, 1].min()), float(np.nanmin(tips[:, 1], initial=np.inf)))
    return float(pos[root, 1] - floor)


def spread_chains(
    parents: tuple[int, ...], mapping: list[int]
) -> dict[int, tuple[int, int, float]]:
    """Unmapped joints that sit on a plain chain between two mapped joints.

    A chain ``top -> u_1 -> ... -> u_k -> bottom``: ``top`` and ``bottom`` mapped,
    every ``u_i`` unmapped with ``bottom``'s path as its only child (a target with
    more spine bones than the source: Spine2, Spine3 between Chest and Neck). With
    ``Q = conj(G'_top) G'_bottom``, joint ``u_i`` gets ``G'_top slerp(1, Q, i/(k+1))``:
    the k + 1 joints share Q equally (each local rotation is ``Q^(1/(k+1))``), the
    mapped joints' world rotations are unchanged.

    Args:
        parents: (J',) the target's parent indices.
        mapping: (J',) source joint per target joint, -1 where none.

    Returns:
        ``{u: (top, bottom, i / (k + 1))}``.
    """
    children: list[list[int]] = [[] for _ in parents]
    for c, p in enumerate(parents):
        if p >= 0:
            children[p].append(c)
    out: dict[int, tuple[int, int, float]] = {}
    for bottom, _ in enumerate(parents):
        if mapping[bottom] < 0:
            continue
        path: list[int] = []
        j = parents[bottom]
        while j >= 0 and mapping[j] < 0 and len(children[j]) == 1:
            path.append(j)
            j = parents[j]
        if not path or j < 0 or mapping[j] < 0:
            continue
        k = len(path)
        for i, u in enumerate(reversed(path), start=1):
            out[u] = (j, bottom, i / (k + 1))
    return out


def spine_paths(
    source: BvhSkeleton, target: BvhSkeleton, mapping: list[int]
) -> tuple[list[int], list[int]] | None:
    """The spine in both skeletons: from the joint mapped to Hips to the one mapped
    to Neck (else Head), by the source's humanoid names (:func:`match_joints`' maps).

    Args:
        source: the take's hierarchy.
        target: the skeleton mapped onto.
        mapping: (J',) source joint per target joint, -1 where none.

    Returns:
        ``(source_path, target_path)``, each lowest first, ends included; None when
        either end is missing or the target's upper end is not below its lower one.
    """
    names = _humanoid_names(source.joint_names)
    ends: list[int] = []
    for wanted in (("Hips",), ("Neck", "Head")):
        found = [i for w in wanted for i, h in enumerate(names) if h == w]
        if not found or found[0] not in mapping:
            return None
        ends.append(found[0])

    def path(parents: tuple[int, ...], top: int, bottom: int) -> list[int] | None:
        out = [bottom]
        while out[-1] != top:
            if parents[out[-1]] < 0:
                return None
            out.append(parents[out[-1]])
        return out[::-1]

    tgt = path(target.parents, mapping.index(ends[0]), mapping.index(ends[1]))
    src = path(source.parents, ends[0], ends[1])
    return None if tgt is None or src is None else (src, tgt)


#: ``spine_curve(glob, source_pos, source_path, target_path, target_rest_pos)``.
SpineCurve = Callable[[F64Array, F64Array, list[int], list[int], F64Array], object]


@dataclass(frozen=True, slots=True, kw_only=True)
class BvhRetarget:
    """A retargeted take on the target's hierarchy.

    Attributes:
        skeleton: the output hierarchy (the target's joints, offsets, End Sites,
            rotation orders; position channels on the root only).
        frames: (T, n_channels) float64 motion lines (degrees, the target's unit).
        parent_from_joint_quat: (T, J', 4) float64 (w, x, y, z), the target's local
            rotations ``R'_j`` in file axes.
        root_pos: (T, 3) float64, the target root's world position, its unit.
        mapping: (J',) source joint per target joint, -1 where none.
        root_scale: the factor applied to the source root's position.
        frame_time_s: seconds per frame (the source's).
        spine: the target chain placed along the spine curve (``spine_curve``),
            ends included; empty without.
    """

    skeleton: BvhSkeleton
    frames: F64Array
    parent_from_joint_quat: F64Array
    root_pos: F64Array
    mapping: tuple[int, ...]
    root_scale: float
    frame_time_s: float
    spine: tuple[int, ...] = ()


def global_rotations(sk: BvhSkeleton) -> tuple[F64Array, F64Array]:
    """Forward kinematics of a BVH take's rotations and root.

    Args:
        sk: read with motion.

    Returns:
        ``(world_from_joint, root_pos)``: (T, J, 4) float64 (w, x, y, z) in file
        axes, and (T, J, 3) float64 joint positions, the file's unit (root: OFFSET
        plus its position channels).
    """
    if sk.frames is None:
        raise ValueError(f"{sk.source}: no motion read")
    angles, positions = split_bvh_motion(sk, sk.frames)
    n_frames, n = angles.shape[:2]
    glob = np.empty((n_frames, n, 4))
    pos = np.zeros((n_frames, n, 3))
    for j, p in enumerate(sk.parents):
        order = sk.rotation_orders[j]
        local = (
            rot.quat_from_euler(np.radians(angles[:, j]), order)
            if order
            else np.tile(_IDENTITY, (n_frames, 1))
        )
        if p < 0:
            glob[:, j] = local
            # No position channels: NaN, read as 0 (the root stays at its OFFSET).
            pos[:, j] = sk.offsets[j] + np.nan_to_num(positions[:, j])
        else:
            glob[:, j] = rot.quat_mul(glob[:, p], local)
            pos[:, j] = pos[:, p] + rot.quat_rotate(glob[:, p], sk.offsets[j])
    return glob, pos


def retarget_bvh(
    source: BvhSkeleton,
    target: BvhSkeleton,
    *,
    name_map: Mapping[str, str] | None = None,
    root_scale: float | None = None,
    spread: bool = False,
    distribute: Callable[[F64Array, dict[int, tuple[int, int, float]]], object]
    | None = None,
    spine_curve: SpineCurve | None = None,
) -> BvhRetarget:
    """Map a BVH take onto another BVH skeleton (module docstring).

    Args:
        source: the take, read with ``read_motion=True``.
        target: the hierarchy to drive (its motion, if any, is ignored).
        name_map: explicit source -> target joint names, tried first.
        root_scale: factor on the root's position (default: the rest height ratio).
        spread: share the rotation between two mapped joints over the unmapped
            chain joints between them (:func:`spread_chains`) instead of leaving
            them at their rest, in equal shares unless ``distribute`` is given.
        distribute: with ``spread``, ``distribute(glob, chains)`` writes the world
            rotations of every chain joint between the mapped ends (``glob`` (T,
            J', 4) with the mapped joints set, ``chains`` from
            :func:`spread_chains`), e.g. the shifting pivot
            (:func:`retargetd.daemon.post.pivot.pivot_chains`).
        spine_curve: places the target's spine (:func:`spine_paths`, inner joints
            mapped or not) from the source's spine joint positions, e.g.
            :func:`retargetd.daemon.post.hermite.hermite_chain`; other chains are
            spread as ``spread`` says.

    Returns:
        The retargeted take.

    Raises:
        ValueError: no motion, a bad map, a target root that maps to nothing, or a
            ``spine_curve`` with no spine of at least one inner joint.
    """
    if source.frames is None or len(source.frames) == 0:
        raise ValueError(f"{source.source}: the take has no motion frames")
    mapping = match_joints(source, target, name_map)
    if mapping[0] < 0:
        raise ValueError(
            f"target root {target.joint_names[0]!r} maps to no source joint: name it "
            "in --map"
        )
    if not any(m >= 0 for m in mapping[1:]) and len(mapping) > 1:
        raise ValueError("no target joint below the root maps to a source joint")
    src_glob, src_pos = global_rotations(source)
    n_frames = len(src_glob)
    n = len(target.joint_names)
    comp = np.tile(_IDENTITY, (n, 1))
    for j in range(n):
        if mapping[j] >= 0:
            comp[j] = rest_compensation(*_aim_pairs(target, source, mapping, j))
    glob = np.empty((n_frames, n, 4))
    local = np.empty((n_frames, n, 4))
    for j in range(n):
        if mapping[j] >= 0:
            glob[:, j] = rot.quat_mul(src_glob[:, mapping[j]], comp[j])
    chains = spread_chains(target.parents, mapping) if spread else {}
    placed: set[int] = set()
    spine: tuple[int, ...] = ()
    if spine_curve is not None:
        paths = spine_paths(source, target, mapping)
        if paths is None or len(paths[1]) < 3:
            raise ValueError(
                "spine curve: the target has no joint between the ones mapped to the "
                "source's Hips and Neck (or Head)"
            )
        spine = tuple(paths[1])
        placed = set(spine[1:-1])
        chains = {u: c for u, c in chains.items() if u not in placed}
        spine_curve(glob, src_pos, paths[0], paths[1], target.rest_positions())
    pivot = bool(chains) and distribute is not None
    if pivot:
        assert distribute is not None
        distribute(glob, chains)
    for j, p in enumerate(target.parents):
        if j in placed or mapping[j] >= 0 or (pivot and j in chains):
            pass
        elif j in chains:
            top, bottom, u = chains[j]
            rel = rot.quat_mul(rot.quat_conj(glob[:, top]), glob[:, bottom])
            glob[:, j] = rot.quat_mul(
                glob[:, top], rot.slerp(np.tile(_IDENTITY, (n_frames, 1)), rel, u)
            )
        else:
            glob[:, j] = glob[:, p] if p >= 0 else _IDENTITY
        if p < 0:
            local[:, j] = glob[:, j]
        else:
            local[:, j] = rot.quat_mul(rot.quat_conj(glob[:, p]), glob[:, j])
    if root_scale is None:
        h_s = _rest_height(source, mapping[0])
        h_t = _rest_height(target, 0)
        root_scale = h_t / h_s if h_s > 0.0 and h_t > 0.0 else 1.0
    root_pos = root_scale * src_pos[:, mapping[0]]
    out_sk = output_skeleton(target)
    frame_time = source.frame_time_s
    if not (math.isfinite(frame_time) and frame_time > 0.0):
        raise ValueError(f"{source.source}: no valid Frame Time")
    return BvhRetarget(
        skeleton=out_sk,
        frames=motion_lines(out_sk, local, root_pos),
        parent_from_joint_quat=local,
        root_pos=root_pos,
        mapping=tuple(mapping),
        root_scale=float(root_scale),
        frame_time_s=float(frame_time),
        spine=spine,
    )


def output_skeleton(target: BvhSkeleton) -> BvhSkeleton:
    """The hierarchy a retarget writes: the target's joints, offsets and End Sites,
    its rotation orders (:data:`FALLBACK_ORDER` for a joint without rotation
    channels), position channels on the root only."""
    return bvh_skeleton(
        joint_names=target.joint_names,
        parents=target.parents,
        offsets=target.offsets,
        rotation_orders=[o or FALLBACK_ORDER for o in target.rotation_orders],
        end_sites=target.end_sites,
    )


def motion_lines(
    skeleton: BvhSkeleton, parent_from_joint_quat: F64Array, root_pos: F64Array
) -> F64Array:
    """The motion lines of a retargeted take on ``skeleton``
    (:func:`output_skeleton`'s).

    Args:
        skeleton: the output hierarchy (its rotation orders and root OFFSET).
        parent_from_joint_quat: (T, J, 4) float64 (w, x, y, z), file axes.
        root_pos: (T, 3) float64, the root's position, file unit and axes.

    Returns:
        (T, n_channels) float64: each joint's angles (degrees, unwrapped over time)
        in its order, the root's position channels (its position less its OFFSET).
    """
    orders = skeleton.rotation_orders
    angles = np.zeros((*parent_from_joint_quat.shape[:2], 3))
    for order in set(orders):
        cols = [j for j, o in enumerate(orders) if o == order]
        angles[:, cols] = rot.euler_from_quat(parent_from_joint_quat[:, cols], order)
    angles_deg = np.unwrap(np.degrees(angles), period=360.0, axis=0)
    positions = np.full_like(angles_deg, np.nan)
    positions[:, 0] = root_pos - skeleton.offsets[0]
    return bvh_motion(skeleton, angles_deg, positions)


def write_retarget_glb(
    path: str | Path, result: BvhRetarget, m_per_unit: float, *, mesh: str = "none"
) -> None:
    """Write a retargeted take as glTF 2.0 binary (every frame), as a skin.

    BVH's +Y-up axes are glTF's, so no scene rotation: joint nodes are the target's
    joints (named as in the target BVH) at their OFFSETs (times ``m_per_unit``),
    identity rest rotations (BVH's rest pose, also the skin's bind pose), LINEAR
    rotation channels ``R'_j`` and the root's translation.

    ``mesh="capsules"``: a capsule from each joint to each child's OFFSET and End Site
    (:func:`retargetd.replay.gltf_mesh.bone_capsule`), weighted 1 to the joint;
    segments under 1 mm (coincident joints) get none.

    Args:
        path: the ``.glb`` file.
        result: from :func:`retarget_bvh`.
        m_per_unit: metres per file unit (0.01 for centimetres).
        mesh: ``"none"`` (the skin alone) or ``"capsules"``.

    Raises:
        ValueError: an unknown mesh.
    """
    check_mesh(mesh)
    sk = result.skeleton
    n = len(sk.joint_names)
    times = np.asarray(np.arange(len(result.frames)) * result.frame_time_s, np.float64)
    channels = [
        GltfChannel(
            node=j,
            path="rotation",
            times_s=times,
            values=result.parent_from_joint_quat[:, j],
        )
        for j in range(n)
    ]
    channels.append(
        GltfChannel(
            node=0,
            path="translation",
            times_s=times,
            values=m_per_unit * result.root_pos,
        )
    )
    rest_t = m_per_unit * np.asarray(sk.offsets, dtype=np.float64)
    write_glb(
        path,
        names=sk.joint_names,
        parents=sk.parents,
        rest_translation=rest_t,
        rest_rotation_quat=np.tile(_IDENTITY, (n, 1)),
        channels=channels,
        capsules=_segment_capsules(sk.parents, rest_t, m_per_unit * sk.end_sites)
        if mesh == "capsules"
        else (),
    )


#: Shorter joint-to-child segments get no capsule (coincident joints), metres.
_MIN_SEGMENT_M = 1e-3


def _segment_capsules(
    parents: tuple[int, ...], offsets_m: F64Array, end_sites_m: F64Array
) -> list[Capsule]:
    """A capsule per joint-to-child segment and per End Site, in the joint's frame
    (identity rest rotations: a child's OFFSET is its origin in the joint's frame)."""
    capsules = []
    for j in range(len(parents)):
        ends = [offsets_m[c] for c in range(len(parents)) if parents[c] == j]
        if np.isfinite(end_sites_m[j]).all():
            ends.append(end_sites_m[j])
        capsules += [
            bone_capsule(j, e) for e in ends if np.linalg.norm(e) >= _MIN_SEGMENT_M
        ]
    return capsules
