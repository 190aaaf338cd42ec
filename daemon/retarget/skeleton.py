"""The target skeleton: the engine humanoid (or a BVH hierarchy) a solve is retargeted
onto: its bones, parents, rest offsets and aims, rest rotations and forward axis; the
default T-pose humanoid VMC receivers expect; the BVH joint-name maps onto the humanoid
(Mixamo/MotionBuilder, CMU); forward kinematics of a target pose. Notation: the
``retarget`` module docstring."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.rig import HUMANOID_BONES
from retargetd.protocols.conventions import (
    world_from_capture_mat,
    world_from_capture_pos,
)
from retargetd.protocols.frames import F64Array
from retargetd.protocols.humanoid import HUMANOID_PARENTS
from retargetd.replay.bvh import read_bvh_hierarchy

logger = logging.getLogger(__name__)

_IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])
#: The default humanoid at rest, joint positions in the world (metres): a 1.70 m adult
#: in T-pose (palms down), facing world +Y (Unity +Z), its left at world -X (Unity -X).
_DEFAULT_JOINTS: dict[str, tuple[float, float, float]] = {
    "Hips": (0.0, 0.0, 0.95),
    "Spine": (0.0, 0.0, 1.05),
    "Chest": (0.0, 0.0, 1.17),
    "UpperChest": (0.0, 0.0, 1.29),
    "Neck": (0.0, 0.0, 1.45),
    "Head": (0.0, 0.0, 1.55),
    **{
        f"{s}{b}": (sx * x, y, z)
        for s, sx in (("Left", -1.0), ("Right", 1.0))
        for b, (x, y, z) in (
            ("Shoulder", (0.03, 0.0, 1.41)),
            ("UpperArm", (0.19, 0.0, 1.41)),
            ("LowerArm", (0.46, 0.0, 1.41)),
            ("Hand", (0.71, 0.0, 1.41)),
            ("UpperLeg", (0.09, 0.0, 0.90)),
            ("LowerLeg", (0.09, 0.0, 0.48)),
            ("Foot", (0.09, 0.0, 0.08)),
            ("Toes", (0.09, 0.13, 0.02)),
        )
    },
}

#: Tips of the leaves (head top, fingertips, toe tips), world metres.
_DEFAULT_TIPS: dict[str, tuple[float, float, float]] = {
    "Head": (0.0, 0.0, 1.70),
    "LeftHand": (-0.89, 0.0, 1.41),
    "RightHand": (0.89, 0.0, 1.41),
    "LeftToes": (-0.09, 0.19, 0.0),
    "RightToes": (0.09, 0.19, 0.0),
}

#: The chain child of each bone: its aim, and the way down for filling.
CHAIN_CHILD: dict[str, str] = {
    "Hips": "Spine",
    "Spine": "Chest",
    "Chest": "UpperChest",
    "UpperChest": "Neck",
    "Neck": "Head",
    **{
        f"{s}{b}": f"{s}{c}"
        for s in ("Left", "Right")
        for b, c in (
            ("Shoulder", "UpperArm"),
            ("UpperArm", "LowerArm"),
            ("LowerArm", "Hand"),
            ("UpperLeg", "LowerLeg"),
            ("LowerLeg", "Foot"),
            ("Foot", "Toes"),
        )
    },
}

#: BVH joint name (after stripping a ``prefix:``) -> humanoid bone: Mixamo,
#: MotionBuilder and most game rigs.
DEFAULT_BVH_NAME_MAP: dict[str, str] = {
    "Hips": "Hips",
    "Spine": "Spine",
    "Spine1": "Chest",
    "Chest": "Chest",
    "Spine2": "UpperChest",
    "UpperChest": "UpperChest",
    "Neck": "Neck",
    "Head": "Head",
    **{
        f"{s}{k}": f"{s}{v}"
        for s in ("Left", "Right")
        for k, v in (
            ("Shoulder", "Shoulder"),
            ("Arm", "UpperArm"),
            ("UpperArm", "UpperArm"),
            ("ForeArm", "LowerArm"),
            ("LowerArm", "LowerArm"),
            ("Hand", "Hand"),
            ("UpLeg", "UpperLeg"),
            ("UpperLeg", "UpperLeg"),
            ("Leg", "LowerLeg"),
            ("LowerLeg", "LowerLeg"),
            ("Foot", "Foot"),
            ("ToeBase", "Toes"),
            ("Toes", "Toes"),
        )
    },
}

#: The CMU BVH conversions (LowerBack, Spine, Spine1): used when a file has LowerBack.
CMU_BVH_NAME_MAP: dict[str, str] = {
    **DEFAULT_BVH_NAME_MAP,
    "LowerBack": "Spine",
    "Spine": "Chest",
    "Spine1": "UpperChest",
}

_UP = np.array([0.0, 0.0, 1.0])


def _readonly(a: F64Array) -> F64Array:
    a = np.array(a, dtype=np.float64)
    a.flags.writeable = False
    return a


def _horizontal_unit(v: F64Array, what: str) -> F64Array:
    h = np.array([v[0], v[1], 0.0])
    n = float(np.linalg.norm(h))
    if not n > 1e-6:
        raise ValueError(f"{what} has no horizontal direction: {v}")
    return h / n


@dataclass(frozen=True, slots=True, kw_only=True)
class TargetSkeleton:
    """A target humanoid: the skeleton the engine animates (frozen, read-only arrays).

    Attributes:
        name: a label (``"default"``, or the BVH path).
        bone_names: (N,) humanoid bone names, parents first, ``"Hips"`` first.
        parents: (N,) parent index, -1 for Hips.
        rest_offsets: (N, 3) float64, metres, world axes: each joint in its parent's
            frame at rest (Hips: from the model root, the floor point under it).
        aim_offsets: (N, 3) float64, metres, world axes: joint -> chain child (or
            first child, or tip) at rest; the bone direction compensation aligns.
        rest_world_from_bone_quat: (N, 4) w x y z, ``T_h``.
        rest_parent_from_bone_quat: (N, 4) w x y z (identity for default and BVH).
        hips_height: metres, Hips above the lowest joint or tip at rest.
        forward_world: (3,) unit, horizontal: the way the target faces at rest.
        source_joints: (N,) the file's joint each bone came from (``""`` default).
    """

    name: str
    bone_names: tuple[str, ...]
    parents: tuple[int, ...]
    rest_offsets: F64Array
    aim_offsets: F64Array
    rest_world_from_bone_quat: F64Array
    rest_parent_from_bone_quat: F64Array
    hips_height: float
    forward_world: F64Array
    source_joints: tuple[str, ...] = field(default=())

    def __post_init__(self) -> None:
        n = len(self.bone_names)
        bad = [b for b in self.bone_names if b not in HUMANOID_BONES]
        if bad or len(set(self.bone_names)) != n:
            raise ValueError(f"bone_names must be distinct humanoid bones; got {bad}")
        if n == 0 or self.bone_names[0] != "Hips" or self.parents[0] != -1:
            raise ValueError("a target's first bone must be Hips, the root")
        if len(self.parents) != n or any(
            not 0 <= p < i for i, p in enumerate(self.parents) if i
        ):
            raise ValueError(f"parents must come before children; got {self.parents}")
        for arr, width, what in (
            (self.rest_offsets, 3, "rest_offsets"),
            (self.aim_offsets, 3, "aim_offsets"),
            (self.rest_world_from_bone_quat, 4, "rest_world_from_bone_quat"),
            (self.rest_parent_from_bone_quat, 4, "rest_parent_from_bone_quat"),
        ):
            if arr.shape != (n, width) or not np.isfinite(arr).all():
                raise ValueError(f"{what} must be finite ({n}, {width}); {arr.shape}")
            arr.flags.writeable = False
        if not self.hips_height > 0.0:
            raise ValueError(f"hips_height must be > 0 m; got {self.hips_height}")
        self.forward_world.flags.writeable = False

    @property
    def left_world(self) -> F64Array:
        """(3,) the target's left at rest: up x forward."""
        return np.cross(_UP, self.forward_world)

    def index(self, name: str) -> int:
        """Index of a humanoid bone (ValueError naming it when absent)."""
        try:
            return self.bone_names.index(name)
        except ValueError:
            raise ValueError(f"target {self.name!r} has no bone {name!r}") from None

    @classmethod
    def from_bvh(
        cls,
        path: str | Path,
        *,
        units: str = "cm",
        up: str = "+Y",
        name_map: Mapping[str, str] | None = None,
    ) -> TargetSkeleton:
        """A target from a BVH hierarchy (rest pose = every joint at identity).

        Positions go to world metres with ``world_from_capture_pos(p, up, units)``. The
        rest world rotation of every bone is ``A = world_from_capture`` (a BVH joint's
        rest frame is parallel to the file's axes), so rest parent-relative rotations
        are identity. Joints the map does not name are skipped (their offsets add up
        into the next mapped joint's).

        Args:
            path: the ``.bvh`` file.
            units: the file's length unit (BVH does not say; usually ``"cm"``).
            up: the file's up axis (usually ``"+Y"``).
            name_map: joint name -> humanoid bone; keys match the full name or the
                name after its last ``:`` (``mixamorig:Hips``). Default:
                :data:`DEFAULT_BVH_NAME_MAP`, or :data:`CMU_BVH_NAME_MAP` when the
                file has a ``LowerBack`` joint.

        Raises:
            ValueError: unreadable file, unknown humanoid names, duplicates, no
                Hips, no left/right pair to find the forward axis.
        """
        sk = read_bvh_hierarchy(path)
        short = [n.rsplit(":", 1)[-1] for n in sk.joint_names]
        if name_map is None:
            name_map = (
                CMU_BVH_NAME_MAP if "LowerBack" in short else DEFAULT_BVH_NAME_MAP
            )
        human: dict[int, str] = {}
        for j, (full, s) in enumerate(zip(sk.joint_names, short, strict=True)):
            h = name_map.get(full, name_map.get(s))
            if h is None:
                continue
            if h not in HUMANOID_BONES:
                raise ValueError(f"{path}: name map sends {full!r} to unknown {h!r}")
            if h in human.values():
                raise ValueError(f"{path}: two joints map to humanoid {h!r}")
            human[j] = h
        if "Hips" not in human.values():
            raise ValueError(f"{path}: no joint maps to Hips (joints: {short})")
        pos = world_from_capture_pos(sk.rest_positions(), up, units)
        ends = world_from_capture_pos(sk.end_sites, up, units)
        tips = pos + ends  # NaN where no End Site
        floor = min(pos[:, 2].min(), np.nanmin(tips[:, 2], initial=np.inf))
        hips_j = next(j for j, h in human.items() if h == "Hips")
        hips_height = float(pos[hips_j, 2] - floor)

        def mapped_ancestor(j: int) -> int:
            p = sk.parents[j]
            while p >= 0 and p not in human:
                p = sk.parents[p]
            return p

        def on_path(j: int, below: int) -> int | None:
            """The direct child of j on the way to ``below`` (None if not below)."""
            k = below
            while k >= 0 and sk.parents[k] != j:
                k = sk.parents[k]
            return None if k < 0 else k

        order = sorted(human)  # file order: parents first
        names = [human[j] for j in order]
        index = {j: i for i, j in enumerate(order)}
        parents, offsets, aims = [], [], []
        children = {j: [c for c, p in enumerate(sk.parents) if p == j] for j in order}
        by_human = {h: j for j, h in human.items()}
        for j in order:
            h = human[j]
            anc = mapped_ancestor(j)
            if h == "Hips":
                if anc >= 0:
                    raise ValueError(f"{path}: Hips ({sk.joint_names[j]}) has a mapped "
                                     "ancestor")  # fmt: skip
                parents.append(-1)
                offsets.append([0.0, 0.0, hips_height])
            else:
                if anc < 0:
                    raise ValueError(
                        f"{path}: {h} ({sk.joint_names[j]}) is not below Hips"
                    )
                parents.append(index[anc])
                offsets.append(pos[j] - pos[anc])
            chain = by_human.get(CHAIN_CHILD.get(h, ""), -1)
            via = on_path(j, chain) if chain >= 0 else None
            if via is None and children[j]:
                via = children[j][0]
            if via is not None:
                aim = pos[via] - pos[j]
            elif np.isfinite(ends[j]).all():
                aim = ends[j]
            else:
                aim = np.asarray(offsets[-1], dtype=np.float64)
            if not np.linalg.norm(aim) > 1e-9:
                aim = np.asarray(offsets[-1], dtype=np.float64)
            aims.append(aim)
        forward = _forward_from_pairs({h: pos[by_human[h]] for h in names}, f"{path}")
        a = rot.quat_from_mat(world_from_capture_mat(up))
        n = len(names)
        return cls(
            name=str(path),
            bone_names=tuple(names),
            parents=tuple(parents),
            rest_offsets=_readonly(np.asarray(offsets).reshape(n, 3)),
            aim_offsets=_readonly(np.asarray(aims).reshape(n, 3)),
            rest_world_from_bone_quat=_readonly(np.tile(a, (n, 1))),
            rest_parent_from_bone_quat=_readonly(np.tile(_IDENTITY, (n, 1))),
            hips_height=hips_height,
            forward_world=_readonly(forward),
            source_joints=tuple(sk.joint_names[j] for j in order),
        )


def _forward_from_pairs(pos: Mapping[str, F64Array], what: str) -> F64Array:
    """Forward = left x up, left from the upper legs (else shoulders, upper arms)."""
    for pair in ("UpperLeg", "Shoulder", "UpperArm"):
        left, right = pos.get("Left" + pair), pos.get("Right" + pair)
        if left is not None and right is not None:
            lat = _horizontal_unit(left - right, f"{what}: Left{pair} - Right{pair}")
            return np.cross(lat, _UP)
    raise ValueError(f"{what}: no Left/Right UpperLeg, Shoulder or UpperArm pair")


def default_humanoid() -> TargetSkeleton:
    """The standard humanoid in T-pose, all rest rotations identity (VRM-normalized).

    A 1.70 m adult (hips 0.95 m, shoulders 0.38 m apart, arm span 1.78 m) facing
    world +Y, which Unity_from_world maps to Unity +Z, Unity's forward; its left is
    world -X (Unity -X), arms along ±X, palms down. Bone order: :data:`HUMANOID_BONES`.
    """
    names = HUMANOID_BONES
    pos = {k: np.asarray(v) for k, v in _DEFAULT_JOINTS.items()}
    parents, offsets, aims = [], [], []
    for h in names:
        p = HUMANOID_PARENTS[h]
        parents.append(-1 if p is None else names.index(p))
        offsets.append(pos[h] if p is None else pos[h] - pos[p])
        child = CHAIN_CHILD.get(h)
        aims.append((pos[child] if child else np.asarray(_DEFAULT_TIPS[h])) - pos[h])
    n = len(names)
    return TargetSkeleton(
        name="default",
        bone_names=names,
        parents=tuple(parents),
        rest_offsets=_readonly(np.asarray(offsets)),
        aim_offsets=_readonly(np.asarray(aims)),
        rest_world_from_bone_quat=_readonly(np.tile(_IDENTITY, (n, 1))),
        rest_parent_from_bone_quat=_readonly(np.tile(_IDENTITY, (n, 1))),
        hips_height=0.95,
        forward_world=_readonly(np.array([0.0, 1.0, 0.0])),
        source_joints=("",) * n,
    )


def bone_axes_from_world_axes(
    target: TargetSkeleton, rest_from_bone_quat: F64Array, out: F64Array | None = None
) -> F64Array:
    """Rotations relative to rest, from world axes to each bone's rest axes.

    ``T̄_h ⊗ L_h ⊗ T_h`` = ``P̄_h^rest ⊗ Ḡ_p ⊗ G_h``: for a BVH target, the joint's
    channel rotation in the file's axes (rest = identity); for the default humanoid
    the input unchanged.

    Args:
        target: the target.
        rest_from_bone_quat: (..., N, 4) w x y z, world axes
            (``TargetPose.rest_from_bone_quat``).
        out: optional (..., N, 4) destination.

    Returns:
        (..., N, 4) w x y z, each bone's rest axes.
    """
    t = target.rest_world_from_bone_quat
    res = rot.quat_mul(rot.quat_conj(t), rot.quat_mul(rest_from_bone_quat, t))
    if out is None:
        return res
    out[...] = res
    return out
