"""A MuJoCo model of a calibrated skeleton, for validating solved poses.

One body per rig bone (parents first), its frame the bone's calibrated rest rotation
(``rest_world_from_bone_quat``: +Y along the bone) at the bone's calibrated origin; a
free joint at the root and a ball joint elsewhere. With these body frames the model's
``qpos`` is the solve's output as streamed (derived in ``validate.checks``):
root position and ``world_from_bone_quat`` of the root, then each bone's streamed
``rest_from_bone_quat`` (identity in the calibration pose) as its ball quaternion.

Segments: a capsule from the bone's origin to its aim (``fromto`` (0,0,0)-(0,L,0) in the
body frame), a site ``<bone>_aim`` at the aim. Capsule radius = a per-segment factor
(:data:`RADIUS_FACTOR`) times the bone's length for limbs, times the leg length (thigh +
shank) for trunk, neck and head (their "bone" lengths depend on where a rig puts the
markers). Masses: de Leva (1996) segment fractions (:data:`MASS_FRACTION`) of the body
mass, renormalised over the segments the rig has.

Floor: a plane at the calibrated ground height, the lowest foot-capsule point in the
calibration pose (so the feet just touch it at rest). Collision excludes: parent/child
pairs are excluded by MuJoCo; every other pair of body geoms that touches in the
calibration pose is excluded explicitly (:func:`build_model`). Bones with no humanoid
mapping (rig-internal links) do not collide.

Models are cached by a SHA-256 of the skeleton (rig bones + calibrated arrays + mass).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.calibration import Calibration
from retargetd.daemon.body.neutral import neutral_from_rest, performer_left
from retargetd.daemon.body.rig import Rig
from retargetd.protocols.frames import F64Array

DEFAULT_BODY_MASS_KG = 70.0
FLOOR_NAME = "floor"
_Y_AXIS = np.array([0.0, 1.0, 0.0])

#: Humanoid bone name -> segment kind (mass, radius and limit tables).
SEGMENT_KIND: dict[str, str] = {
    "Hips": "pelvis",
    "Spine": "abdomen",
    "Chest": "thorax",
    "UpperChest": "thorax",
    "Neck": "neck",
    "Head": "head",
    **{
        f"{side}{part}": kind
        for side in ("Left", "Right")
        for part, kind in (
            ("Shoulder", "clavicle"),
            ("UpperArm", "upper_arm"),
            ("LowerArm", "forearm"),
            ("Hand", "hand"),
            ("UpperLeg", "thigh"),
            ("LowerLeg", "shank"),
            ("Foot", "foot"),
            ("Toes", "toes"),
        )
    },
}

#: Segment mass as a fraction of body mass, de Leva P. (1996) "Adjustments to
#: Zatsiorsky-Seluyanov's segment inertia parameters", J Biomech 29(9):1223-1230,
#: Table 4 (male): head+neck 6.94 % (split here head 5.94 %, neck 1.00 %), trunk
#: 43.46 % = upper 15.96 % (thorax) + middle 16.33 % (abdomen) + lower 11.17 %
#: (pelvis), upper arm 2.71 %, forearm 1.62 %, hand 0.61 %, thigh 14.16 %, shank
#: 4.33 %, foot 1.37 % (split foot 1.17 %, toes 0.20 %). De Leva has no clavicle:
#: 0.50 % each, and 0.20 % for a bone with no humanoid mapping ("link"); all
#: renormalised to the rig's bones.
MASS_FRACTION: dict[str, float] = {
    "pelvis": 0.1117,
    "abdomen": 0.1633,
    "thorax": 0.1596,
    "neck": 0.0100,
    "head": 0.0594,
    "clavicle": 0.0050,
    "upper_arm": 0.0271,
    "forearm": 0.0162,
    "hand": 0.0061,
    "thigh": 0.1416,
    "shank": 0.0433,
    "foot": 0.0117,
    "toes": 0.0020,
    "link": 0.0020,
}

#: Capsule radius: kind -> (factor, reference) with reference "bone" (the bone's own
#: length) or "leg" (thigh + shank length, a body-size proxy for the trunk and head).
#: Set below the segments' mean girth / (2 pi) (Winter D.A., "Biomechanics and Motor
#: Control of Human Movement", 4th ed. 2009, ch. 4 proportions; e.g. thigh mid girth
#: ~0.55 m -> 8.8 cm): capsules are deliberately lean so that only real interpenetration
#: (not soft tissue) collides.
RADIUS_FACTOR: dict[str, tuple[float, str]] = {
    "pelvis": (0.13, "leg"),
    "abdomen": (0.12, "leg"),
    "thorax": (0.12, "leg"),
    "neck": (0.05, "leg"),
    "head": (0.10, "leg"),
    "clavicle": (0.03, "leg"),
    "upper_arm": (0.13, "bone"),
    "forearm": (0.12, "bone"),
    "hand": (0.22, "bone"),
    "thigh": (0.12, "bone"),
    "shank": (0.10, "bone"),
    "foot": (0.20, "bone"),
    "toes": (0.30, "bone"),
    "link": (0.02, "leg"),
}

FOOT_KINDS = ("foot", "toes")


@dataclass(frozen=True, slots=True, kw_only=True)
class Skeleton:
    """The rigid skeleton the model and the checks share.

    Attributes:
        bone_names, bone_parents (-1 root), bone_kinds: (B,) in rig order.
        bone_lengths: (B,) metres.
        offset_parent: (B, 3) metres, each bone's origin in its parent's rest bone
            frame (root: zeros).
        rest_world_from_bone_quat: (B, 4) w x y z, the calibration pose.
        rest_origin_world: (B, 3) metres, bone origins in the calibration pose.
        left_world: (3,) the performer's left in the calibration pose (horizontal).
        neutral_from_rest_quat: (B, 4) w x y z, each bone's rotation from anatomical
            neutral to the calibration pose, in its axes (``body.neutral``): the
            joint limits apply to ``neutral_from_rest * rest_from_bone``; None:
            identity (the calibration pose taken as neutral).
    """

    bone_names: tuple[str, ...]
    bone_parents: tuple[int, ...]
    bone_kinds: tuple[str, ...]
    bone_lengths: F64Array
    offset_parent: F64Array
    rest_world_from_bone_quat: F64Array
    rest_origin_world: F64Array
    left_world: F64Array
    neutral_from_rest_quat: F64Array | None = None

    def digest(self, body_mass_kg: float) -> str:
        """SHA-256 of everything the model is built from."""
        h = hashlib.sha256()
        h.update(repr((self.bone_names, self.bone_parents, self.bone_kinds)).encode())
        arrays = [self.bone_lengths, self.offset_parent]
        arrays += [self.rest_world_from_bone_quat, self.rest_origin_world]
        for arr in arrays:
            h.update(np.ascontiguousarray(arr, dtype=np.float64).tobytes())
        h.update(np.float64(body_mass_kg).tobytes())
        return h.hexdigest()


def skeleton_from_calibration(
    rig: Rig, calibration: Calibration, bone_lengths: F64Array | None = None
) -> Skeleton:
    """The skeleton of a calibration, optionally with other bone lengths.

    A bone's offset from its parent's origin is its calibrated rest offset expressed in
    the parent's rest frame, scaled by ``bone_lengths[parent] / calibrated length``
    (a segment scales as a whole). With ``bone_lengths`` None the calibrated lengths.
    """
    if calibration.rest_bone_origin_pos is None:
        raise ValueError("calibration has no rest bone origins: recalibrate")
    cal_len = np.asarray(calibration.bone_lengths, dtype=np.float64)
    lengths = (
        cal_len.copy() if bone_lengths is None else np.asarray(bone_lengths, float)
    )
    parents = tuple(int(p) for p in calibration.bone_parents)
    rest_wfb = np.asarray(calibration.rest_world_from_bone_quat, dtype=np.float64)
    origins = np.asarray(calibration.rest_bone_origin_pos, dtype=np.float64)
    offsets = np.zeros_like(origins)
    for b, p in enumerate(parents):
        if p >= 0:
            offsets[b] = rot.quat_rotate(
                rot.quat_conj(rest_wfb[p]), origins[b] - origins[p]
            )
            offsets[b] *= lengths[p] / cal_len[p]
    kinds = tuple(SEGMENT_KIND.get(b.humanoid or "", "link") for b in rig.bones)
    left = performer_left(rig, calibration)
    return Skeleton(
        bone_names=tuple(calibration.bone_names),
        bone_parents=parents,
        bone_kinds=kinds,
        bone_lengths=lengths,
        offset_parent=offsets,
        rest_world_from_bone_quat=rest_wfb,
        rest_origin_world=origins,
        left_world=left,
        neutral_from_rest_quat=neutral_from_rest(rig, calibration, SEGMENT_KIND),
    )


def capsule_radii(skel: Skeleton) -> F64Array:
    """(B,) capsule radius per bone, metres (see :data:`RADIUS_FACTOR`)."""
    leg = sum(
        float(skel.bone_lengths[i])
        for i, k in enumerate(skel.bone_kinds)
        if k in ("thigh", "shank")
    ) / max(sum(k == "thigh" for k in skel.bone_kinds), 1)
    if leg <= 0.0:
        leg = float(np.sum(skel.bone_lengths)) / 4.0
    out = np.empty(len(skel.bone_names))
    for b, kind in enumerate(skel.bone_kinds):
        factor, ref = RADIUS_FACTOR[kind]
        out[b] = factor * (leg if ref == "leg" else float(skel.bone_lengths[b]))
    return out


def segment_masses(skel: Skeleton, body_mass_kg: float) -> F64Array:
    """(B,) kg: :data:`MASS_FRACTION` renormalised over the rig's bones."""
    frac = np.array([MASS_FRACTION[k] for k in skel.bone_kinds])
    return body_mass_kg * frac / frac.sum()


def rest_aim_world(skel: Skeleton) -> F64Array:
    """(B, 3) each bone's aim point in the calibration pose."""
    return skel.rest_origin_world + rot.quat_rotate(
        skel.rest_world_from_bone_quat, skel.bone_lengths[:, None] * _Y_AXIS
    )


def ground_height(skel: Skeleton) -> float:
    """Lowest foot-capsule point in the calibration pose (the floor), metres."""
    radii = capsule_radii(skel)
    feet = [i for i, k in enumerate(skel.bone_kinds) if k in FOOT_KINDS]
    if not feet:  # no feet: the lowest capsule of all
        feet = list(range(len(skel.bone_names)))
    aims = rest_aim_world(skel)
    z = np.minimum(skel.rest_origin_world[feet, 2], aims[feet, 2]) - radii[feet]
    return float(z.min())


@dataclass(frozen=True, slots=True, kw_only=True)
class ValidationModel:
    """A compiled model with what the checks need to address it."""

    skeleton: Skeleton
    model: Any  # mujoco.MjModel
    xml: str
    digest: str
    body_mass_kg: float
    floor_z: float
    body_ids: np.ndarray  # (B,) MuJoCo body id per bone
    site_ids: np.ndarray  # (B,) aim site id per bone
    ball_qpos_idx: np.ndarray  # (B-1, 4) qpos addresses of the non-root bones
    ball_bones: np.ndarray  # (B-1,) which bones those are
    geom_bone: np.ndarray  # (ngeom,) bone index of each geom, -1 for the floor
    floor_geom: int
    excluded_pairs: tuple[tuple[str, str], ...]


_CACHE: dict[str, ValidationModel] = {}


def build_model(
    skel: Skeleton, body_mass_kg: float = DEFAULT_BODY_MASS_KG
) -> ValidationModel:
    """Build (or fetch from the cache) the model of a skeleton."""
    digest = skel.digest(body_mass_kg)
    hit = _CACHE.get(digest)
    if hit is not None:
        return hit
    radii = capsule_radii(skel)
    masses = segment_masses(skel, body_mass_kg)
    floor_z = ground_height(skel)
    spec = _spec(skel, radii, masses, floor_z, excludes=())
    model = spec.compile()
    # Rest-pose collision excludes: pose the calibration pose (qpos0), collide, and
    # exclude every touching pair of body geoms (parent/child already are).
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    mujoco.mj_collision(model, data)
    geom_bone = _geom_bone(model, skel.bone_names)
    pairs: set[tuple[int, int]] = set()
    for c in range(data.ncon):
        a, b = (int(geom_bone[g]) for g in data.contact.geom[c])
        if a >= 0 and b >= 0:
            pairs.add((min(a, b), max(a, b)))
    excludes = tuple((skel.bone_names[a], skel.bone_names[b]) for a, b in sorted(pairs))
    if excludes:
        spec = _spec(skel, radii, masses, floor_z, excludes=excludes)
        model = spec.compile()
    names = skel.bone_names
    body_ids = np.array(
        [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, n) for n in names]
    )
    site_ids = np.array(
        [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, f"{n}_aim") for n in names]
    )
    ball = np.array([b for b, p in enumerate(skel.bone_parents) if p >= 0])
    adr = np.array(
        [
            model.jnt_qposadr[
                mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, names[b])
            ]
            for b in ball
        ]
    )
    out = ValidationModel(
        skeleton=skel,
        model=model,
        xml=spec.to_xml(),
        digest=digest,
        body_mass_kg=body_mass_kg,
        floor_z=floor_z,
        body_ids=body_ids,
        site_ids=site_ids,
        ball_qpos_idx=adr[:, None] + np.arange(4),
        ball_bones=ball,
        geom_bone=_geom_bone(model, names),
        floor_geom=mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, FLOOR_NAME),
        excluded_pairs=excludes,
    )
    _CACHE[digest] = out
    return out


def _geom_bone(model: Any, names: tuple[str, ...]) -> np.ndarray:
    """(ngeom,) bone index of each geom (-1: the floor); MuJoCo orders bodies depth
    first, which differs from the rig's order."""
    bone_of_body = np.full(model.nbody, -1)
    for b, n in enumerate(names):
        bone_of_body[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, n)] = b
    return bone_of_body[np.asarray(model.geom_bodyid)]


def _spec(
    skel: Skeleton,
    radii: F64Array,
    masses: F64Array,
    floor_z: float,
    excludes: tuple[tuple[str, str], ...],
) -> Any:
    spec = mujoco.MjSpec()
    spec.modelname = "retargetd_validate"
    spec.compiler.degree = False
    spec.worldbody.add_geom(
        name=FLOOR_NAME,
        type=mujoco.mjtGeom.mjGEOM_PLANE,
        pos=[0.0, 0.0, floor_z],
        size=[0.0, 0.0, 1.0],
    )
    bodies: list[Any] = []
    rest = skel.rest_world_from_bone_quat
    for b, name in enumerate(skel.bone_names):
        p = skel.bone_parents[b]
        if p < 0:
            # The root body's frame is the bone frame in the world.
            body = spec.worldbody.add_body(
                name=name, pos=skel.rest_origin_world[b], quat=rest[b]
            )
            body.add_freejoint(name=name)
        else:
            # Child frame in the parent frame = rest parent_from_bone.
            quat = rot.quat_mul(rot.quat_conj(rest[p]), rest[b])
            body = bodies[p].add_body(name=name, pos=skel.offset_parent[b], quat=quat)
            body.add_joint(name=name, type=mujoco.mjtJoint.mjJNT_BALL)
        length = float(skel.bone_lengths[b])
        body.add_geom(
            name=name,
            type=mujoco.mjtGeom.mjGEOM_CAPSULE,
            fromto=[0.0, 0.0, 0.0, 0.0, length, 0.0],
            size=[float(radii[b]), 0.0, 0.0],
            mass=float(masses[b]),
            # Bones with no humanoid mapping are rig-internal links (menache's
            # scapulae, radii, torso): massless-ish and never colliding.
            contype=0 if skel.bone_kinds[b] == "link" else 1,
            conaffinity=0 if skel.bone_kinds[b] == "link" else 1,
        )
        body.add_site(name=f"{name}_aim", pos=[0.0, length, 0.0])
        bodies.append(body)
    for first, second in excludes:
        spec.add_exclude(bodyname1=first, bodyname2=second)
    return spec


def skeleton_from_arrays(skel: Skeleton, bone_lengths: F64Array) -> Skeleton:
    """``skel`` with other bone lengths (children's offsets scale with the parent)."""
    lengths = np.asarray(bone_lengths, dtype=np.float64)
    offsets = skel.offset_parent.copy()
    for b, p in enumerate(skel.bone_parents):
        if p >= 0:
            offsets[b] *= lengths[p] / skel.bone_lengths[p]
    return Skeleton(
        bone_names=skel.bone_names,
        bone_parents=skel.bone_parents,
        bone_kinds=skel.bone_kinds,
        bone_lengths=lengths,
        offset_parent=offsets,
        rest_world_from_bone_quat=skel.rest_world_from_bone_quat,
        rest_origin_world=skel.rest_origin_world,
        left_world=skel.left_world,
        neutral_from_rest_quat=skel.neutral_from_rest_quat,
    )
