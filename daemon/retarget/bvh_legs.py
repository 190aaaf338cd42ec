"""The legs of two BVH skeletons, for ``retargetd retarget --plant-feet`` (issue 34
item 2): a BVH has no rig and no calibration, which the stance detector
(``post/stance.py``) and the plant's leg lengths (``post/plant_target.py``) are built
from, so both are made from its joints here; ``cli/retarget_plant.py`` runs the
detector and the plant on them.

Both files are read in the retarget's axes (+Y up, :mod:`bvh_retarget`) and turned
into the internal world (Z up, metres: ``world_from_capture_mat("+Y")``, the file's
unit in metres given). Joints are named by the humanoid maps the retarget matches
with (:func:`~retargetd.daemon.retarget.bvh_retarget.match_joints`).

- **The source as a rig** (:func:`source_rig`): one bone per joint; the humanoid bone
  ``h`` of the rig is the joint the maps name ``h``. Its rest pose (every joint at
  identity) is the calibration pose, standing on the floor: its lowest foot point
  (ankle, forefoot, toe tip: the detector's points) at z = 0. A Foot bone aims (+Y)
  at its Toes joint when that is its child, else at its first child, else at its
  End Site; a Toes bone at its End Site (else its first child): the detector's
  forefoot and toe tip; the detector's heel is under the ankle at the foot's lowest
  rest point, as on a marker rig. The leg length (``performer_leg_m``) is the mean
  height of the UpperLeg joints over that floor.
- **Its motion** (:func:`source_motion`): the BVH's forward kinematics; each bone's
  ``world_from_bone = A G Ā R`` (``G`` its global rotation in file axes, which is its
  rotation from rest; ``A`` file to world; ``R`` its rest rotation above).
- **The floor** (:func:`take_floor`): a BVH does not say where its floor is (one
  written by ``retargetd solve`` stands its lowest foot point, Plug-in Gait's toe
  marker, 3.5 cm above the lab floor). It is taken as the lowest the detector's heels
  come over the take, each less its rest height: a foot standing flat holds its heel
  there, and no foot goes below the floor. The heel (under the ankle) rises whichever
  way the foot rolls off the flat, about the real heel at a strike or the ball at
  heel-off, where a point above the sole dips below its rest height (by ``r (1 - cos
  θ)``, ``r`` its height over the roll's contact: the lowest of all the foot points
  read the floor 5.3 mm low on a Plug-in Gait walk, the heels 0.0). A take whose feet
  never stand flat (tiptoe) puts the floor as high as its heels come.
- **The target** (:class:`PlantTarget`): every joint, named by its humanoid bone (the
  source joint that drives it through the retarget's joint map, else its own name
  through the maps), offsets in world metres, rest rotations the file's axes (as
  ``TargetSkeleton.from_bvh``), its root ``h_t`` above its floor (its lowest foot
  point at rest, as the source's).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.calibration import Calibration
from retargetd.daemon.body.rig_model import Bone, Rig
from retargetd.daemon.retarget.bvh import world_from_parent_chain
from retargetd.daemon.retarget.bvh_retarget import (
    _arc,
    _humanoid_names,
    global_rotations,
)
from retargetd.daemon.retarget.skeleton import CHAIN_CHILD
from retargetd.protocols.conventions import world_from_capture_mat
from retargetd.protocols.frames import F64Array
from retargetd.replay.bvh import BvhSkeleton

_SIDES = ("Left", "Right")
#: The humanoid bones the stance detector and the leg length need of the source.
SOURCE_LEGS = tuple(s + b for s in _SIDES for b in ("UpperLeg", "Foot"))
#: The bones the plant's two-bone IK needs of the target.
TARGET_LEGS = tuple(s + b for s in _SIDES for b in ("UpperLeg", "LowerLeg", "Foot"))
_Y = np.array([0.0, 1.0, 0.0])
_IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


def _file_to_world() -> tuple[F64Array, F64Array]:
    """``(A (3, 3), A as (w, x, y, z))``: the retarget's +Y-up file axes to world."""
    a = world_from_capture_mat("+Y")
    return a, rot.quat_from_mat(a)


def target_humanoid(
    source: BvhSkeleton, target: BvhSkeleton, mapping: Sequence[int]
) -> list[str | None]:
    """(J',) the humanoid bone of each target joint: the humanoid name of the source
    joint that drives it (the retarget's joint map), else its own name's through
    the maps; None where neither names one (or another joint has it already)."""
    src = _humanoid_names(source.joint_names)
    out: list[str | None] = [src[s] if s >= 0 else None for s in mapping]
    seen: set[str] = set()
    for j, h in enumerate(out):
        out[j] = None if h in seen else h
        seen.add(h or "")
    for j, h in enumerate(_humanoid_names(target.joint_names)):
        if out[j] is None and h is not None and h not in seen:
            out[j] = h
            seen.add(h)
    return out


def source_humanoid(source: BvhSkeleton) -> list[str | None]:
    """(J,) the humanoid bone of each source joint (the retarget's maps)."""
    return _humanoid_names(source.joint_names)


def missing_legs(humanoid: Sequence[str | None], wanted: Sequence[str]) -> list[str]:
    """The bones of ``wanted`` that no joint is named as."""
    have = set(humanoid)
    return [w for w in wanted if w not in have]


def _aims(sk: BvhSkeleton, humanoid: Sequence[str | None]) -> F64Array:
    """(J, 3) file unit and axes: each joint to its humanoid chain child when that is
    its child, else its first child, else its End Site, else zeros."""
    children: list[list[int]] = [[] for _ in sk.parents]
    for c, p in enumerate(sk.parents):
        if p >= 0:
            children[p].append(c)
    out = np.zeros((len(sk.parents), 3))
    for j, kids in enumerate(children):
        chain = CHAIN_CHILD.get(humanoid[j] or "")
        pick = [c for c in kids if chain is not None and humanoid[c] == chain]
        if pick or kids:
            out[j] = sk.offsets[(pick or kids)[0]]
        elif np.isfinite(sk.end_sites[j]).all():
            out[j] = sk.end_sites[j]
    return out


def _foot_bones(
    humanoid: Sequence[str | None], parents: Sequence[int]
) -> list[list[int]]:
    """Per side, ``[foot]`` or ``[foot, toes]`` (the Toes joint when the foot's child:
    the stance detector's rule)."""
    out = []
    for side in _SIDES:
        f = list(humanoid).index(side + "Foot")
        toes = [j for j, h in enumerate(humanoid) if h == side + "Toes"]
        out.append([f, toes[0]] if toes and parents[toes[0]] == f else [f])
    return out


def _rest_world(
    sk: BvhSkeleton, humanoid: Sequence[str | None], m_per_unit: float
) -> tuple[F64Array, F64Array, float]:
    """``(joints (J, 3), aims (J, 3), floor)`` at rest, world metres; ``floor`` the
    lowest foot point's height (ankle, forefoot, toe tip, both feet)."""
    a, _ = _file_to_world()
    pos = m_per_unit * sk.rest_positions() @ a.T
    aims = m_per_unit * _aims(sk, humanoid) @ a.T
    feet = _foot_bones(humanoid, sk.parents)
    low = min(min(pos[b[0], 2], *(pos[j, 2] + aims[j, 2] for j in b)) for b in feet)
    return pos, aims, float(low)


def source_rig(
    source: BvhSkeleton, humanoid: Sequence[str | None], m_per_unit: float
) -> tuple[Rig, Calibration]:
    """The source BVH as a rig and its calibration (module docstring): what the
    stance detector and ``performer_leg_m`` read.

    Args:
        source: the take's hierarchy.
        humanoid: (J,) :func:`source_humanoid`; Left/RightFoot named.
        m_per_unit: metres per file unit.

    Returns:
        ``(rig, calibration)``: bones the joints, parents first; world metres, Z up,
        the rest pose's lowest foot point on z = 0.
    """
    names = tuple(source.joint_names)
    pos, aims, low = _rest_world(source, humanoid, m_per_unit)
    n = len(names)
    rest = np.tile(_IDENTITY, (n, 1))
    lengths = np.zeros(n)
    for foot in _foot_bones(humanoid, source.parents):
        for b in foot:
            lengths[b] = float(np.linalg.norm(aims[b]))
            if lengths[b] > 0.0:  # the bone's +Y along its aim (rig convention)
                rest[b] = _arc(_Y, aims[b] / lengths[b])
    origins = pos - np.array([0.0, 0.0, low])
    parents = tuple(int(p) for p in source.parents)
    rest_parent = np.array(rest)
    for j, p in enumerate(parents):
        if p >= 0:
            rest_parent[j] = rot.quat_mul(rot.quat_conj(rest[p]), rest[j])
    label = f"bvh {source.source}"
    bones = tuple(
        Bone(
            name=nm,
            parent=None if p < 0 else names[p],
            origin=nm,
            aim=nm,
            up=(),
            humanoid=h,
        )
        for nm, p, h in zip(names, parents, humanoid, strict=True)
    )
    rig = Rig(
        name=label, source=source.source, description="a BVH take's joints",
        lateral=("", ""), measurements={}, markers={}, segments={}, points=(),
        bones=bones, joints={},
        humanoid={h: nm for nm, h in zip(names, humanoid, strict=True) if h},
    )  # fmt: skip
    cal = Calibration(
        rig_name=label, rig_source=source.source, rig_sha256="", marker_names=(),
        markers_seen=(), point_names=(), point_offsets=np.zeros((0, 3)),
        segment_layouts={}, bone_names=names, bone_parents=parents,
        bone_lengths=lengths, rest_world_from_bone_quat=rest,
        rest_parent_from_bone_quat=rest_parent, root_rest_pos=origins[0].copy(),
        rest_bone_origin_pos=origins,
    )  # fmt: skip
    return rig, cal


def source_motion(
    source: BvhSkeleton, calibration: Calibration, m_per_unit: float
) -> tuple[F64Array, F64Array]:
    """The take's frames as a solve of :func:`source_rig`'s bones.

    Returns:
        ``(world_from_bone_quat (T, J, 4) w x y z, joints (T, J, 3))``: world, metres,
        the file's origin (the floor not yet taken off).
    """
    a, aq = _file_to_world()
    glob, pos = global_rotations(source)
    delta = rot.quat_mul(rot.quat_mul(aq, glob), rot.quat_conj(aq))
    wfb = rot.quat_mul(delta, calibration.rest_world_from_bone_quat)
    return np.ascontiguousarray(wfb), m_per_unit * pos @ a.T


def take_floor(
    rig: Rig, calibration: Calibration, world_from_bone_quat: F64Array,
    joints: F64Array,
) -> float:  # fmt: skip
    """The floor's height in :func:`source_motion`'s world, metres (module
    docstring): the lowest the heels come over the take, each heel the stance
    detector's (under the ankle at the foot's lowest rest point, fixed in the
    foot), less its rest height."""
    names = list(calibration.bone_names)
    origins = np.asarray(calibration.rest_bone_origin_pos)
    rest = calibration.rest_world_from_bone_quat
    low = np.inf
    for side in _SIDES:
        f = names.index(rig.humanoid[side + "Foot"])
        toes = rig.humanoid.get(side + "Toes")
        bones = [f] + (
            [names.index(toes)]
            if toes is not None and calibration.bone_parents[names.index(toes)] == f
            else []
        )
        rest_z = [origins[f, 2]] + [
            origins[b, 2]
            + rot.quat_rotate(rest[b], np.array([0.0, calibration.bone_lengths[b], 0]))[
                2
            ]
            for b in bones
        ]
        delta = rot.quat_mul(world_from_bone_quat[:, f], rot.quat_conj(rest[f]))
        drop = np.array([0.0, 0.0, min(rest_z) - origins[f, 2]])
        heel = joints[:, f] + rot.quat_rotate(delta, drop)
        low = min(low, float(np.min(heel[:, 2])) - min(rest_z))
    return low


@dataclass(frozen=True, slots=True, kw_only=True)
class PlantTarget:
    """A BVH target as the plant stage reads it (``post/plant.py`` ``FootPlant``'s
    ``target``; the fields of ``TargetSkeleton``'s it reads), every joint kept.

    Attributes:
        name: the file.
        bone_names: (J',) each joint's humanoid bone (:func:`target_humanoid`), else
            ``"joint NAME"``.
        parents: (J',) parent index, -1 for the root.
        rest_offsets: (J', 3) float64, metres, world axes: each joint from its parent
            at rest; the root's ``(0, 0, h_t)``, its height above its floor.
        aim_offsets: (J', 3) float64, metres, world axes: to its chain child (or
            first child, or End Site).
        rest_world_from_bone_quat: (J', 4) w x y z: the file's axes, ``A``.
        left_world: (3,) unit, horizontal: LeftUpperLeg less RightUpperLeg at rest.
    """

    name: str
    bone_names: tuple[str, ...]
    parents: tuple[int, ...]
    rest_offsets: F64Array
    aim_offsets: F64Array
    rest_world_from_bone_quat: F64Array
    left_world: F64Array

    def index(self, name: str) -> int:
        """Index of a joint's name (ValueError naming it when absent)."""
        try:
            return self.bone_names.index(name)
        except ValueError:
            raise ValueError(f"target {self.name!r} has no {name} joint") from None

    @classmethod
    def from_bvh(
        cls, target: BvhSkeleton, humanoid: Sequence[str | None], m_per_unit: float
    ) -> PlantTarget:
        """The target at rest (class docstring); ``humanoid`` names Left/Right
        UpperLeg and Foot."""
        a, aq = _file_to_world()
        pos, aims, low = _rest_world(target, humanoid, m_per_unit)
        offsets = m_per_unit * np.asarray(target.offsets) @ a.T
        offsets[0] = (0.0, 0.0, pos[0, 2] - low)
        hum = list(humanoid)
        lat = pos[hum.index("LeftUpperLeg")] - pos[hum.index("RightUpperLeg")]
        lat[2] = 0.0
        return cls(
            name=target.source,
            bone_names=tuple(
                h or f"joint {n}"
                for h, n in zip(humanoid, target.joint_names, strict=True)
            ),
            parents=tuple(int(p) for p in target.parents),
            rest_offsets=offsets,
            aim_offsets=aims,
            rest_world_from_bone_quat=np.tile(aq, (len(hum), 1)),
            left_world=lat / np.linalg.norm(lat),
        )

    def pose_world(self, parent_from_joint_quat: F64Array) -> tuple[F64Array, F64Array]:
        """A retarget's rotations (file axes, (T, J', 4)) as the plant's pose:
        ``(G, L)``, (T, J', 4) each, world axes: ``G = A G_file`` (``G_file`` the
        forward kinematics; rest ``A``), ``L = A R Ā``."""
        aq = self.rest_world_from_bone_quat[0]
        glob = world_from_parent_chain(self.parents, parent_from_joint_quat)
        g = rot.quat_mul(aq, glob)
        lq = rot.quat_mul(rot.quat_mul(aq, parent_from_joint_quat), rot.quat_conj(aq))
        return np.ascontiguousarray(g), np.ascontiguousarray(lq)

    def file_rotations(self, rest_from_bone_quat: F64Array) -> F64Array:
        """:meth:`pose_world`'s ``L`` back to file-axes parent-relative rotations,
        ``Ā L A``."""
        aq = self.rest_world_from_bone_quat[0]
        return rot.quat_mul(rot.quat_mul(rot.quat_conj(aq), rest_from_bone_quat), aq)
