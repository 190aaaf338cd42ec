"""Low-poly capsules, one per bone, for a skinned glTF mesh (:mod:`.gltf`).

A capsule is a cylinder of radius ``r`` from ``start`` to ``end`` closed by two
hemispheres (so it reaches ``r`` past each end). Each is built from rings around its
axis ``a = (end - start) / |end - start|``: ``cap_rings`` rings per hemisphere at
polar angles ``θ_k = (π/2) k / cap_rings`` from the pole, ``segments`` vertices per
ring, and one vertex at each pole, so

    vertices  = 2 + 2 * cap_rings * segments
    triangles = 2 * segments + 2 * (2 * cap_rings - 1) * segments

(8 segments, 2 rings: 34 vertices and 64 triangles). A vertex on a hemisphere of
centre ``c`` is ``c + r n`` with its unit normal ``n = ±cos θ a + sin θ (cos φ u +
sin φ v)``; the cylinder is the band between the two equators. Triangles wind
counter-clockwise seen from outside (glTF's front face).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from retargetd.protocols.frames import F64Array

#: Vertices around each ring, and rings per hemisphere (low poly: 34 vertices).
CAPSULE_SEGMENTS = 8
CAPSULE_CAP_RINGS = 2
#: ``--glb-mesh`` choices: the skin alone, or a capsule per bone.
MESHES = ("none", "capsules")
#: A capsule's radius per unit of bone length: a choice, not a body measurement.
#: Limbs are long and thin, so a fixed fraction of the bone's length gives them a
#: plausible girth from the skeleton alone, with no body measurements (with 0.15 a
#: Blender render of the Plug-in Gait walk reads as a walking figure). Trunk and head
#: bones come out thinner than the body (their bulk is not along one bone): a figure
#: that shows the pose, not a body model. The caps reach 0.15 L past each end, so
#: neighbouring capsules overlap at the joints and the figure reads as connected.
CAPSULE_RADIUS_PER_LENGTH = 0.15
#: ... and no thinner than 1 cm, so short bones (hands, a short pelvis) stay visible.
CAPSULE_MIN_RADIUS_M = 0.01


@dataclass(frozen=True, slots=True, kw_only=True)
class Capsule:
    """One capsule, bound with weight 1 to one joint.

    Attributes:
        joint: the joint (node) index that moves it.
        start: (3,) float64, the axis' first end, in the joint's frame (file units).
        end: (3,) float64, its other end (may equal ``start``: a sphere).
        radius: > 0, same units.
    """

    joint: int
    start: F64Array
    end: F64Array
    radius: float


@dataclass(frozen=True, slots=True, kw_only=True)
class CapsuleMesh:
    """Capsules as one triangle list.

    Attributes:
        positions: (V, 3) float64, in each capsule's joint frame.
        normals: (V, 3) float64, unit, same frames.
        joints: (V,) int64, the joint of each vertex.
        indices: (3 F,) int64, triangles, counter-clockwise from outside.
    """

    positions: F64Array
    normals: F64Array
    joints: npt.NDArray[np.int64]
    indices: npt.NDArray[np.int64]


def bone_capsule(joint: int, end: F64Array) -> Capsule:
    """The capsule of one bone from its origin to ``end`` (bone frame, metres), radius
    :data:`CAPSULE_RADIUS_PER_LENGTH` of the length, at least
    :data:`CAPSULE_MIN_RADIUS_M`."""
    end = np.asarray(end, dtype=np.float64)
    length = float(np.linalg.norm(end))
    radius = max(CAPSULE_RADIUS_PER_LENGTH * length, CAPSULE_MIN_RADIUS_M)
    return Capsule(joint=joint, start=np.zeros(3), end=end, radius=radius)


def check_mesh(mesh: str) -> None:
    """Raise ValueError unless ``mesh`` is one of :data:`MESHES`."""
    if mesh not in MESHES:
        raise ValueError(f"mesh must be one of {', '.join(MESHES)}; got {mesh!r}")


def _perpendicular(a: F64Array) -> tuple[F64Array, F64Array]:
    """Two unit vectors ``u, v`` with ``(u, v, a)`` right-handed and orthonormal."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(helper, a)
    u /= np.linalg.norm(u)
    return u, np.cross(a, u)


def _unit_capsule(segments: int, cap_rings: int) -> tuple[F64Array, F64Array, F64Array]:
    """Rings of a capsule along +z: per vertex ``(end_flag, normal)``, and triangles.

    ``end_flag`` is 0 for the ``start`` hemisphere, 1 for the ``end`` one.
    """
    theta = (math.pi / 2) * np.arange(1, cap_rings + 1) / cap_rings
    phi = 2 * math.pi * np.arange(segments) / segments
    # Rings from the start pole to the end pole: (end flag, axial, radial) per ring.
    rings = [(0.0, -math.cos(t), math.sin(t)) for t in theta]
    rings += [(1.0, math.cos(t), math.sin(t)) for t in theta[::-1]]
    flags = [0.0]
    normals = [np.array([0.0, 0.0, -1.0])]
    for flag, axial, radial in rings:
        ring = np.stack(
            [radial * np.cos(phi), radial * np.sin(phi), np.full(segments, axial)], -1
        )
        normals.extend(ring)
        flags.extend([flag] * segments)
    normals.append(np.array([0.0, 0.0, 1.0]))
    flags.append(1.0)
    top = 1 + len(rings) * segments
    tris: list[tuple[int, int, int]] = []
    j_next = [(j + 1) % segments for j in range(segments)]
    for j in range(segments):  # start pole: seen from -z, counter-clockwise
        tris.append((0, 1 + j_next[j], 1 + j))
    for r in range(len(rings) - 1):
        a, b = 1 + r * segments, 1 + (r + 1) * segments
        for j in range(segments):
            tris.append((a + j, a + j_next[j], b + j_next[j]))
            tris.append((a + j, b + j_next[j], b + j))
    last = 1 + (len(rings) - 1) * segments
    for j in range(segments):
        tris.append((top, last + j, last + j_next[j]))
    return np.array(flags), np.array(normals), np.array(tris, dtype=np.int64)


def capsule_mesh(
    capsules: list[Capsule] | tuple[Capsule, ...],
    *,
    segments: int = CAPSULE_SEGMENTS,
    cap_rings: int = CAPSULE_CAP_RINGS,
) -> CapsuleMesh:
    """Every capsule's vertices and triangles, in its joint's frame (module docstring).

    Args:
        capsules: the capsules.
        segments: vertices per ring (>= 3).
        cap_rings: rings per hemisphere (>= 1).

    Returns:
        The mesh (empty arrays for no capsules).

    Raises:
        ValueError: a capsule with a non-positive or non-finite radius or ends.
    """
    if segments < 3 or cap_rings < 1:
        raise ValueError(
            f"need segments >= 3 and cap_rings >= 1; got {segments}, {cap_rings}"
        )
    flags, unit_normals, tris = _unit_capsule(segments, cap_rings)
    positions, normals, joints, indices = [], [], [], []
    n_vertices = 0
    for c in capsules:
        start = np.asarray(c.start, dtype=np.float64)
        end = np.asarray(c.end, dtype=np.float64)
        if not (
            math.isfinite(c.radius)
            and c.radius > 0.0
            and np.isfinite(start).all()
            and np.isfinite(end).all()
        ):
            raise ValueError(
                f"capsule of joint {c.joint}: needs finite ends and a positive radius; "
                f"got {start}, {end}, {c.radius}"
            )
        axis = end - start
        length = float(np.linalg.norm(axis))
        a = axis / length if length > 0.0 else np.array([0.0, 0.0, 1.0])
        u, v = _perpendicular(a)
        frame = np.stack([u, v, a], -1)  # columns: the unit capsule's x, y, z
        n = unit_normals @ frame.T
        centre = start + flags[:, None] * axis
        positions.append(centre + c.radius * n)
        normals.append(n)
        joints.append(np.full(len(n), c.joint, dtype=np.int64))
        indices.append(tris.reshape(-1) + n_vertices)
        n_vertices += len(n)
    if not positions:
        empty = np.zeros((0, 3))
        return CapsuleMesh(
            positions=empty,
            normals=empty.copy(),
            joints=np.zeros(0, dtype=np.int64),
            indices=np.zeros(0, dtype=np.int64),
        )
    return CapsuleMesh(
        positions=np.concatenate(positions),
        normals=np.concatenate(normals),
        joints=np.concatenate(joints),
        indices=np.concatenate(indices),
    )
