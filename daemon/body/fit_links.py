"""Links: bones no marker rides, between two that markers see; their rotation spread.

A **link** is a ball-jointed bone that carries no marker (nor does any bone fixed to
it), whose one child is a ball-jointed bone that does (itself or a bone fixed to it):
Plug-in Gait's ``spine`` (pelvis -> chest, its markers all on the pelvis and the
thorax) and ``neck`` (chest -> head). The fit places such a bone as a rigid rod from
a point of its parent to its child's joint, so its direction is the chord between
the two observed segments. That chord says where they are, not how the trunk between
them bends: Plug-in Gait's spine rod starts at the sacrum's height, below the lumbar
spine, and ends at T10 / the xiphoid, so a trunk flexion of 30 deg (15 in the lumbar
spine, 15 in the thoracic, the synthetic performer's ``deep_squat``) turns it 4 deg
backwards while the chest takes 34 (``bench/fit_truth.py``: the spine 19.1 deg p95
from its truth segment, the chest 3.5).

So the fit's output gives a link the share of the chain's rotation that its length
is of the chain (the link and its child): with ``E`` the child's rotation on the
link's parent since the calibration pose (in the parent's frame), the link turns
``E^f`` on its parent and the child the rest, ``f = L_link / (L_link + L_child)``
with the calibrated bone lengths. That is the chapter's distribution of rotations
(``character-setup-chapter.txt``, "Distribution of Rotations": a rotation spread
over the joints of a spine whose vertebrae are evenly spaced and each turn alike, so
a bone's share is the number of vertebrae it spans, i.e. its length), with no number
of its own. World rotations of the child and everything below it, joint centres and
the fit's own state (the next frame's seed) do not change: only the split of the
chain's rotation between the link and its child does.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from retargetd.daemon.compiled import kernel, qmul
from retargetd.protocols.frames import F64Array, IntArray

__all__ = ["link_spread", "spread_link"]


def link_spread(
    bone_parent: IntArray,
    marker_bone: IntArray,
    marker_weight: F64Array,
    joint_dof: Sequence[str],
    bone_lengths: F64Array,
) -> tuple[F64Array, IntArray]:
    """Which bones are links (module docstring) and each one's share.

    Args:
        bone_parent: (B,) parent index, -1 for a root (parents first).
        marker_bone: (M,) the bone each marker rides (-1: unused).
        marker_weight: (M,) residual weights (0: the fit ignores the marker).
        joint_dof: (B,) each joint's model ("root", "ball", "hinge", "fixed", ...).
        bone_lengths: (B,) metres, calibrated.

    Returns:
        ``frac`` (B,) float64: a link's share ``f`` in (0, 1), 0 for any other bone;
        ``child`` (B,) int64: a link's child, -1 for any other bone.
    """
    n = len(bone_parent)
    frac = np.zeros(n)
    child = np.full(n, -1, dtype=np.int64)
    if len(joint_dof) != n:  # a model without joint models: no links
        return frac, child
    # a bone fixed to its parent is one body with it: its markers are the parent's
    body = np.arange(n)
    for b in range(n):
        if joint_dof[b] == "fixed" and bone_parent[b] >= 0:
            body[b] = body[bone_parent[b]]
    seen = np.zeros(n, dtype=bool)
    for b, w in zip(marker_bone, marker_weight, strict=True):
        if b >= 0 and w > 0.0:
            seen[body[b]] = True
    for b in range(n):
        if joint_dof[b] != "ball" or bone_parent[b] < 0 or seen[body[b]]:
            continue
        kids = [k for k in range(n) if bone_parent[k] == b and joint_dof[k] != "fixed"]
        if len(kids) != 1 or joint_dof[kids[0]] != "ball" or not seen[body[kids[0]]]:
            continue
        length, child_length = float(bone_lengths[b]), float(bone_lengths[kids[0]])
        if length > 0.0 and child_length > 0.0:
            frac[b] = length / (length + child_length)
            child[b] = kids[0]
    return frac, child


@kernel
def spread_link(
    wq: np.ndarray, rest_pfb: np.ndarray, p: int, b: int, c: int, f: float
) -> tuple[float, float, float, float]:
    """Link ``b``'s world rotation (w x y z) when it takes the share ``f`` of the
    rotation of its child ``c`` on its parent ``p`` since the calibration pose.

    Args:
        wq: (B, 4) the fit's world rotations (w x y z).
        rest_pfb: (B, 4) calibrated parent_from_bone.
        p, b, c: the parent, the link and its child.
        f: the link's share (``link_spread``).
    """
    wp, wc, rb, rc = wq[p], wq[c], rest_pfb[b], rest_pfb[c]
    # the chain (child on parent) now and at the calibration pose, and E = now * rest^-1
    nw, nx, ny, nz = qmul(wp[0], -wp[1], -wp[2], -wp[3], wc[0], wc[1], wc[2], wc[3])
    rw, rx, ry, rz = qmul(rb[0], rb[1], rb[2], rb[3], rc[0], rc[1], rc[2], rc[3])
    ew, ex, ey, ez = qmul(nw, nx, ny, nz, rw, -rx, -ry, -rz)
    if ew < 0.0:  # the shorter way round
        ew, ex, ey, ez = -ew, -ex, -ey, -ez
    s = math.sqrt(ex * ex + ey * ey + ez * ez)
    half = f * math.atan2(s, ew)  # f of the half angle
    k = math.sin(half) / s if s > 1e-12 else f
    aw, ax, ay, az = qmul(math.cos(half), k * ex, k * ey, k * ez, rb[0], rb[1],
                          rb[2], rb[3])  # fmt: skip
    return qmul(wp[0], wp[1], wp[2], wp[3], aw, ax, ay, az)
