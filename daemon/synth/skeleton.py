"""The synthetic performer's skeleton: segments, proportions, rest pose.

Skeleton (:func:`make_skeleton`): 21 segments, pelvis root. World = internal world
(right-handed, +Z up, metres). The performer faces +X at rest, its left is +Y. The rest
pose is the T-pose (arms along +-Y, palms down, feet parallel), with **every segment
frame aligned with the world axes at rest** (identity rest rotations), so a segment's
axes read x forward, y left, z up in the T-pose. Each segment's origin is its proximal
joint centre; ``rest_offsets[s]`` is that origin in the parent's frame. Proportions are
fractions of the height (Winter 2009 and de Leva 1996: hip 0.530 H, knee 0.285 H, ankle
0.039 H, upper arm 0.162 H, forearm 0.154 H, hand 0.108 H, foot 0.150 H); the spine
joints sit at the levels of the L1, T7, T1 and C1 markers of Menache's marker set, so
the chapter's constructions land on them.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from retargetd.protocols.frames import F64Array, IntArray

#: Height the marker-set offsets (and the proportions table) are written for.
REFERENCE_HEIGHT_M = 1.75

_SPINE = ("pelvis", "abdomen", "thorax", "neck", "head")
_LIMBS = ("clavicle", "upper_arm", "forearm", "hand", "thigh", "shank", "foot", "toes")
# name -> (parent, rest joint centre as a fraction of height (forward, left, up), left
# side for bilateral segments).
_REST_POS_H: dict[str, tuple[str | None, tuple[float, float, float]]] = {
    "pelvis": (None, (0.0, 0.0, 0.530)),  # midpoint of the hip joint centres
    "abdomen": ("pelvis", (-0.035, 0.0, 0.645)),  # L1 level
    "thorax": ("abdomen", (-0.0675, 0.0, 0.740)),  # T7 level
    "neck": ("thorax", (-0.050, 0.0, 0.825)),  # T1 level
    "head": ("neck", (-0.020, 0.0, 0.900)),  # C1 level (atlanto-occipital)
    "clavicle": ("thorax", (0.020, 0.012, 0.810)),  # sternoclavicular joint
    "upper_arm": ("clavicle", (-0.020, 0.100, 0.800)),  # glenohumeral joint
    "forearm": ("upper_arm", (-0.020, 0.262, 0.800)),  # elbow
    "hand": ("forearm", (-0.020, 0.416, 0.800)),  # wrist
    "thigh": ("pelvis", (0.0, 0.050, 0.530)),  # hip joint centre
    "shank": ("thigh", (0.0, 0.050, 0.285)),  # knee
    "foot": ("shank", (0.0, 0.050, 0.039)),  # ankle
    "toes": ("foot", (0.075, 0.050, 0.008)),  # 2nd metatarsophalangeal joint
}
#: The ulnar styloid in the left forearm's frame, as a fraction of height: at the
#: wrist (0.154 H along the forearm), 0.020 H (35 mm at 1.75 m) to the little-finger
#: side (backward with the palms down), where both shipped marker sets wear their
#: ulnar styloid marker. The forearm pronates and supinates about the line from the
#: elbow centre to it (:func:`pronation_axis`): the ISB's forearm axis Yf, the
#: elbow's third joint-coordinate-system axis (Wu et al., "ISB recommendation on
#: definitions of joint coordinate systems of various joints ... Part II: shoulder,
#: elbow, wrist and hand", J Biomech 38(5):981-992, 2005), near the anatomical axis
#: through the ulnar head (Hollister et al., Clin Orthop Relat Res 298:272-276,
#: 1994): the ulna stays, and the radius, with the hand, turns round it.
ULNAR_STYLOID_H = (-0.020, 0.154, 0.0)
#: Intrinsic Euler sequence per segment kind (long-axis rotation last).
EULER_ORDERS: dict[str, str] = {
    **dict.fromkeys(("pelvis", "abdomen", "thorax", "neck", "head"), "YXZ"),
    **dict.fromkeys(("thigh", "shank"), "YXZ"),
    **dict.fromkeys(("clavicle", "forearm", "hand"), "ZXY"),
    # Flexion about the parent's y last-applied-first, so a hanging arm swings fore-aft.
    "upper_arm": "YZX",
    **dict.fromkeys(("foot", "toes"), "YZX"),
}
# Sole points (segment kind, point in that segment's frame as a fraction of height):
# heel, under the MTP joint, toe tip. All at z = 0 in the rest pose.
_SOLE_H = (
    ("foot", (-0.035, 0.0, -0.039)),
    ("foot", (0.075, 0.0, -0.039)),
    ("toes", (0.040, 0.0, -0.008)),
)


def pronation_axis(side: str) -> F64Array:
    """The forearm's pronation axis, a unit vector in the ``side`` ("l" or "r")
    forearm's frame: elbow centre -> ulnar styloid (:data:`ULNAR_STYLOID_H`); the
    right one mirrors the left's through the sagittal plane as a rotation axis (x
    negated), so the same angle turns both the same anatomical way."""
    x, y, z = ULNAR_STYLOID_H
    axis = np.array([x if side == "l" else -x, y, z])
    return axis / np.linalg.norm(axis)


def _segment_names() -> tuple[str, ...]:
    names = list(_SPINE)
    for side in ("l", "r"):
        names += [f"{side}_{kind}" for kind in _LIMBS]
    return tuple(names)


#: Segment names, parents before children.
SEGMENT_NAMES: tuple[str, ...] = _segment_names()


def segment_kind(name: str) -> str:
    """Segment name without its ``l_``/``r_`` side prefix."""
    return name[2:] if name[:2] in ("l_", "r_") else name


def readonly(a: np.ndarray) -> np.ndarray:
    """Mark an array read-only (shared immutable data) and return it."""
    a.flags.writeable = False
    return a


@dataclass(frozen=True, slots=True, kw_only=True)
class Skeleton:
    """The performer's skeleton (immutable; arrays read-only).

    Attributes:
        height_m: standing height, metres.
        names: (S,) segment names, parents before children.
        parents: (S,) int64 parent index, -1 for the root (pelvis).
        rest_offsets: (S, 3) float64, metres: each origin in its parent's frame; the
            root's is the pelvis above its floor point.
        rest_pos: (S, 3) float64, metres: T-pose joint centres relative to the floor
            point under the pelvis (world axes).
        euler_orders: (S,) intrinsic sequence per segment (see :data:`EULER_ORDERS`).
        levels: index arrays of segments by depth (level 0 = root).
        sole_segments: (P,) int64 segment of each sole point.
        sole_points: (P, 3) float64, metres, sole points in their segment's frame.
    """

    height_m: float
    names: tuple[str, ...]
    parents: IntArray
    rest_offsets: F64Array
    rest_pos: F64Array
    euler_orders: tuple[str, ...]
    levels: tuple[IntArray, ...]
    sole_segments: IntArray
    sole_points: F64Array

    def index(self, name: str) -> int:
        """Index of a segment. Raises KeyError naming it."""
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"no segment named {name!r}") from None


@lru_cache(maxsize=8)
def make_skeleton(height_m: float = REFERENCE_HEIGHT_M) -> Skeleton:
    """Build the performer's skeleton scaled to ``height_m``.

    Args:
        height_m: standing height in metres (> 0).

    Returns:
        The immutable :class:`Skeleton` (cached per height).

    Raises:
        ValueError: naming ``height_m`` when it is not positive and finite.
    """
    if not (np.isfinite(height_m) and height_m > 0.0):
        raise ValueError(
            f"height_m must be a positive number of metres; got {height_m}"
        )
    names = SEGMENT_NAMES
    rest_pos = np.empty((len(names), 3))
    parents = np.empty(len(names), dtype=np.int64)
    for s, name in enumerate(names):
        parent, pos_h = _REST_POS_H[segment_kind(name)]
        sign = -1.0 if name.startswith("r_") else 1.0
        rest_pos[s] = np.array([pos_h[0], sign * pos_h[1], pos_h[2]]) * height_m
        if parent is None:
            parents[s] = -1
        else:
            parents[s] = names.index(parent if parent in _SPINE else name[:2] + parent)
    rest_offsets = rest_pos.copy()
    rest_offsets[1:] -= rest_pos[parents[1:]]
    depth = np.zeros(len(names), dtype=np.int64)
    for s in range(1, len(names)):
        depth[s] = depth[parents[s]] + 1
    levels = tuple(readonly(np.flatnonzero(depth == d)) for d in range(depth.max() + 1))
    sole_seg, sole_pts = [], []
    for side in ("l", "r"):
        for kind, pt in _SOLE_H:
            sole_seg.append(names.index(f"{side}_{kind}"))
            sole_pts.append(np.array(pt) * height_m)
    return Skeleton(
        height_m=float(height_m),
        names=names,
        parents=readonly(parents),
        rest_offsets=readonly(rest_offsets),
        rest_pos=readonly(rest_pos),
        euler_orders=tuple(EULER_ORDERS[segment_kind(n)] for n in names),
        levels=levels,
        sole_segments=readonly(np.array(sole_seg, dtype=np.int64)),
        sole_points=readonly(np.array(sole_pts)),
    )
