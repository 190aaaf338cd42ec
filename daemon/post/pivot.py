"""Distributed rotations with a shifting pivot point (the chapter's spine pseudocode).

A vertebra turns only so far; the spine's rotation starts at the lowest one and, once
it reaches its limit, carries over (rotation and pivot) to the next. One rotation
group ``(rx, ry, rz)`` (intrinsic XYZ, y the longitudinal axis, as the listing
assumes) becomes ``num_joints`` groups:

- rx and rz are doubled "to approximate the result to a single pivot" (the prose:
  spreading 36° over the vertebrae gives about half the single-pivot displacement),
  then spread bottom-up, at most ``limit`` per joint, the rest carried over; what is
  left after the last joint is dropped. A doubled rotation within the limit goes to
  the first joint whole.
- ry (the longitudinal twist) is split equally over the joints, undoubled.

Reading of the listing. Its typesetting printed ``>`` as ``]`` and ``<`` as ``[``
(``abs(rot_vector[0]) ] rot_joint_limit``, ``i [ num_joints``, ``rot_residual[0] [
0``) and the minus of ``rot_joint_vector[i][0] - rot_joint_limit`` as an en dash
(U+2013); we read them as ``>``, ``<`` and ``-``. ``rot_joint_vector`` is taken
to start at 0 (the listing declares it without initializing it). The negative
branch's over-limit correction ``rot_residual -= (rot_joint_vector[i] -
rot_joint_limit)`` has the sign of the positive branch; its mirror is ``rot_residual
+= rot_joint_vector[i] + rot_joint_limit``, which is what :func:`_spread` does. With
joints starting at 0 neither over-limit correction can fire (a joint receives at most
one ``limit``), so the reading changes no result. The prose example (10° vertebrae,
36° -> 10, 10, 10, 6) is :func:`distribute` without the doubling.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Sequence
from typing import Any

import numpy as np

from retargetd.daemon import rotations as rot
from retargetd.daemon.compiled import kernel, qmul
from retargetd.protocols.frames import F64Array, IntArray

#: The listing's ``num_joints`` and ``rot_joint_limit`` (degrees): 3 joints, 15°.
DEFAULT_JOINTS = 3
DEFAULT_LIMIT_DEG = 15.0


@kernel
def _spread(
    v: float, limit: float, out: F64Array, col: int
) -> None:  # pragma: no cover - compiled
    """The listing's distribution loop for one axis, into ``out[:, col]`` (zeroed)."""
    n = out.shape[0]
    if abs(v) > limit:
        residual = v
        i = 0
        while abs(residual) > 0.0 and i < n:
            if v > 0.0:
                if abs(residual) < limit:
                    out[i, col] += residual
                else:
                    out[i, col] += limit
                if out[i, col] > limit:
                    residual += out[i, col] - limit
                    out[i, col] = limit
                residual -= limit
                if residual < 0.0:
                    residual = 0.0
            else:
                if abs(residual) < limit:
                    out[i, col] += residual
                else:
                    out[i, col] -= limit
                if abs(out[i, col]) > limit:
                    residual += out[i, col] + limit
                    out[i, col] = -limit
                residual += limit
                if residual > 0.0:
                    residual = 0.0
            i += 1
    else:
        out[0, col] = v


@kernel
def _pivot(
    rx: float, ry: float, rz: float, limit: float, double: bool, out: F64Array
) -> None:  # pragma: no cover - compiled
    n = out.shape[0]
    scale = 2.0 if double else 1.0
    for i in range(n):
        out[i, 0] = 0.0
        out[i, 1] = ry / n
        out[i, 2] = 0.0
    _spread(rx * scale, limit, out, 0)
    _spread(rz * scale, limit, out, 2)


@kernel
def _pivot_quat(
    q: F64Array, limit: float, double: bool, angles: F64Array, out: F64Array
) -> None:  # pragma: no cover - compiled
    w, x, y, z = q[0], q[1], q[2], q[3]
    # Intrinsic XYZ, R = Rx(a) Ry(b) Rz(c): R02 = sin b, R12 = -sin a cos b,
    # R22 = cos a cos b, R01 = -cos b sin c, R00 = cos b cos c.
    r02 = 2.0 * (x * z + w * y)
    r12 = 2.0 * (y * z - w * x)
    r22 = 1.0 - 2.0 * (x * x + y * y)
    r01 = 2.0 * (x * y - w * z)
    r00 = 1.0 - 2.0 * (y * y + z * z)
    a = math.atan2(-r12, r22)
    b = math.asin(min(1.0, max(-1.0, r02)))
    c = math.atan2(-r01, r00)
    _pivot(a, b, c, limit, double, angles)
    for i in range(out.shape[0]):
        ca, sa = math.cos(0.5 * angles[i, 0]), math.sin(0.5 * angles[i, 0])
        cb, sb = math.cos(0.5 * angles[i, 1]), math.sin(0.5 * angles[i, 1])
        cc, sc = math.cos(0.5 * angles[i, 2]), math.sin(0.5 * angles[i, 2])
        # qx(a) ⊗ qy(b) ⊗ qz(c), expanded.
        out[i, 0] = ca * cb * cc - sa * sb * sc
        out[i, 1] = sa * cb * cc + ca * sb * sc
        out[i, 2] = ca * sb * cc - sa * cb * sc
        out[i, 3] = ca * cb * sc + sa * sb * cc


def _check_limit(limit: float) -> float:
    limit = float(limit)
    if not limit > 0.0 or not math.isfinite(limit):
        raise ValueError(f"limit must be a positive finite angle; got {limit!r}")
    return limit


def distribute(total: float, limit: float, out: F64Array) -> F64Array:
    """Spread one rotation bottom-up over ``len(out)`` joints with carry-over.

    Args:
        total: the rotation to spread (any unit, e.g. degrees).
        limit: the most one joint takes, same unit (> 0).
        out: (N,) float64 destination, one value per joint, lowest first.

    Returns:
        ``out``: ``min(limit, rest)`` per joint in turn while any rotation is left
        (sign of ``total``); ``total`` whole on the first joint if within ``limit``.

    Raises:
        ValueError: a bad ``limit`` or ``out``.
    """
    limit = _check_limit(limit)
    if out.ndim != 1 or out.shape[0] < 1:
        raise ValueError(f"out must have shape (N,), N >= 1; got {out.shape}")
    out[:] = 0.0
    _spread(float(total), limit, out.reshape(-1, 1), 0)
    return out


def shifting_pivot(
    rx: float, ry: float, rz: float, limit: float, out: F64Array, *, double: bool = True
) -> F64Array:
    """The listing: one rotation group into ``len(out)`` groups (module docstring).

    Args:
        rx: rotation about x (any angle unit, e.g. degrees).
        ry: rotation about y, the longitudinal axis.
        rz: rotation about z.
        limit: most rotation per joint about x and z, same unit (> 0).
        out: (N, 3) float64 destination, (rx, ry, rz) per joint, lowest first.
        double: double rx and rz first, as the listing does.

    Returns:
        ``out``.

    Raises:
        ValueError: a bad ``limit`` or ``out``.
    """
    limit = _check_limit(limit)
    if out.ndim != 2 or out.shape[1] != 3 or out.shape[0] < 1:
        raise ValueError(f"out must have shape (N, 3), N >= 1; got {out.shape}")
    _pivot(float(rx), float(ry), float(rz), limit, double, out)
    return out


class ShiftingPivot:
    """Per-frame stage: a solved rotation group onto N spine joints.

    E.g. the solved lumbar-to-thorax rotation onto a target's Spine, Chest and
    UpperChest. Angles are the intrinsic XYZ Euler angles of the group (y the long
    axis, the listing's order); each joint's rotation is built back in the same order.

    Args:
        n_joints: number of output joints N (>= 1), lowest first.
        limit_deg: most rotation per joint about x and z, degrees.
        double: double rx and rz (the listing's single-pivot approximation).

    Raises:
        ValueError: a bad ``n_joints`` or ``limit_deg``.
    """

    def __init__(
        self,
        n_joints: int = DEFAULT_JOINTS,
        limit_deg: float = DEFAULT_LIMIT_DEG,
        *,
        double: bool = True,
    ) -> None:
        if int(n_joints) != n_joints or n_joints < 1:
            raise ValueError(f"n_joints must be an integer >= 1; got {n_joints!r}")
        self.n_joints = int(n_joints)
        self.limit_rad = math.radians(_check_limit(limit_deg))
        self.double = bool(double)
        self._angles = np.zeros((self.n_joints, 3))

    def apply(self, group_quat: F64Array, out: F64Array) -> F64Array:
        """Distribute one rotation.

        Args:
            group_quat: (4,) float64 (w, x, y, z), unit: the group's rotation, e.g.
                ``lumbar_from_thorax``.
            out: (N, 4) float64 destination: ``parent_from_joint`` (w, x, y, z) per
                joint, lowest first; their product approximates the group's rotation
                (with the doubling: its single-pivot displacement).

        Returns:
            ``out``.
        """
        _pivot_quat(group_quat, self.limit_rad, self.double, self._angles, out)
        return out

    @property
    def angles_rad(self) -> F64Array:
        """(N, 3) float64: the last call's per-joint XYZ angles, radians."""
        return self._angles


def pivot_chains(
    glob: F64Array,
    chains: dict[int, tuple[int, int, float]],
    limit_deg: float = DEFAULT_LIMIT_DEG,
) -> list[tuple[int, ...]]:
    """The shifting pivot on every spread chain, into ``glob`` in place.

    For a chain ``top -> u_1 .. u_k -> bottom`` the whole rotation between the two
    mapped joints, ``Q = conj(G'_top) G'_bottom`` (in ``top``'s frame: for a BVH
    spine, at rest parallel to the file's axes, +Y along the spine, the listing's
    longitudinal y), is spread bottom-up over the k + 1 joints ``u_1 .. u_k,
    bottom`` by :class:`ShiftingPivot` (rx and rz doubled, at most ``limit_deg`` a
    joint, the rest carried to the next; ry shared equally): ``G'_{u_i} = G'_top p_1
    .. p_i``. ``bottom`` takes the last share, so its
    world rotation becomes the distributed approximation of the single pivot (its
    mapped children keep their own, their local rotations absorb the difference).
    This is how the chapter emits Spine, Chest and UpperChest from one solved
    lumbar-to-thorax rotation.

    Args:
        glob: (T, J', 4) float64 (w, x, y, z) world rotations of the target joints,
            the mapped ones set; the chains' joints are written.
        chains: from :func:`retargetd.daemon.retarget.bvh_retarget.spread_chains`.
        limit_deg: the most rotation per joint about x and z, degrees.

    Returns:
        The chains, each ``(top, u_1, .., u_k, bottom)``.
    """
    by_ends: dict[tuple[int, int], list[tuple[float, int]]] = {}
    for u, (top, bottom, frac) in chains.items():
        by_ends.setdefault((top, bottom), []).append((frac, u))
    out: list[tuple[int, ...]] = []
    for (top, bottom), members in sorted(by_ends.items()):
        joints = [u for _, u in sorted(members)] + [bottom]
        stage = ShiftingPivot(len(joints), limit_deg)
        group = rot.quat_mul(rot.quat_conj(glob[:, top]), glob[:, bottom])
        shares = np.empty((len(joints), 4))
        for t in range(len(glob)):
            stage.apply(np.ascontiguousarray(group[t]), shares)
            acc = glob[t, top]
            for j, share in zip(joints, shares, strict=True):
                acc = rot.quat_mul(acc, share)
                glob[t, j] = acc
        out.append((top, *joints))
    return out


#: The target bones the spine pivot writes, lowest first (VMC / VRM humanoid names),
#: and the bone below them that the group is measured from.
SPINE_BONES = ("Spine", "Chest", "UpperChest")
SPINE_BASE = "Hips"


@kernel
def _spine_pivot(
    g: F64Array,
    rfb: F64Array,
    rest: F64Array,
    plan: IntArray,
    m: F64Array,
    limit: float,
    double: bool,
    angles: F64Array,
    shares: F64Array,
    e_chain: F64Array,
) -> None:  # pragma: no cover - compiled
    """``plan``: row 0 (hips, end, n_chain, n_kids), rows 1..n_chain (chain bone),
    then n_kids rows (kid bone, its parent's chain position)."""
    hips, end, n_chain, n_kids = plan[0, 0], plan[0, 1], plan[0, 2], plan[0, 3]
    # E_h = G_h ⊗ conj(T_h), the world delta since calibration.
    hw, hx, hy, hz = qmul(
        g[hips, 0], g[hips, 1], g[hips, 2], g[hips, 3],
        rest[hips, 0], -rest[hips, 1], -rest[hips, 2], -rest[hips, 3],
    )  # fmt: skip
    ew, ex, ey, ez = qmul(
        g[end, 0], g[end, 1], g[end, 2], g[end, 3],
        rest[end, 0], -rest[end, 1], -rest[end, 2], -rest[end, 3],
    )  # fmt: skip
    # The group conj(E_hips) ⊗ E_end, in the spine frame S: conj(m) ⊗ . ⊗ m.
    qw, qx, qy, qz = qmul(hw, -hx, -hy, -hz, ew, ex, ey, ez)
    qw, qx, qy, qz = qmul(m[0], -m[1], -m[2], -m[3], qw, qx, qy, qz)
    qw, qx, qy, qz = qmul(qw, qx, qy, qz, m[0], m[1], m[2], m[3])
    group = e_chain[n_chain]  # scratch row
    group[0], group[1], group[2], group[3] = qw, qx, qy, qz
    _pivot_quat(group, limit, double, angles, shares)
    aw, ax, ay, az = hw, hx, hy, hz
    for i in range(n_chain):
        j = plan[1 + i, 0]
        s = shares[i]
        # The share back in world axes: m ⊗ p ⊗ conj(m).
        pw, px, py, pz = qmul(m[0], m[1], m[2], m[3], s[0], s[1], s[2], s[3])
        pw, px, py, pz = qmul(pw, px, py, pz, m[0], -m[1], -m[2], -m[3])
        bw, bx, by, bz = qmul(aw, ax, ay, az, pw, px, py, pz)
        # L_j = conj(E_parent) ⊗ E_j = the share; G_j = E_j ⊗ T_j.
        rfb[j, 0], rfb[j, 1], rfb[j, 2], rfb[j, 3] = pw, px, py, pz
        r = qmul(bw, bx, by, bz, rest[j, 0], rest[j, 1], rest[j, 2], rest[j, 3])
        g[j, 0], g[j, 1], g[j, 2], g[j, 3] = r
        e_chain[i, 0], e_chain[i, 1], e_chain[i, 2], e_chain[i, 3] = bw, bx, by, bz
        aw, ax, ay, az = bw, bx, by, bz
    for k in range(n_kids):
        c, pos = plan[1 + n_chain + k, 0], plan[1 + n_chain + k, 1]
        cw, cx, cy, cz = qmul(
            g[c, 0], g[c, 1], g[c, 2], g[c, 3],
            rest[c, 0], -rest[c, 1], -rest[c, 2], -rest[c, 3],
        )  # fmt: skip
        p = e_chain[pos]
        r = qmul(p[0], -p[1], -p[2], -p[3], cw, cx, cy, cz)
        rfb[c, 0], rfb[c, 1], rfb[c, 2], rfb[c, 3] = r


class SpinePivot:
    """Per-frame target stage: a target's Spine, Chest and UpperChest from the solved
    lumbar-to-thorax rotation by the shifting pivot (``[target] spine = "pivot"``).

    On a retargeted frame (``retargetd.daemon.retarget.retarget``: world deltas since
    calibration ``E_h = G_h ⊗ conj(T_h)``, rotations relative to rest along world axes
    ``L_h = conj(E_parent) ⊗ E_h``), the group is the whole bend from the Hips to the
    highest spine bone the rig solves (the thorax on the shipped rigs: ``Q =
    conj(E_Hips) ⊗ E_end``). It is expressed in the spine frame S (x the target's
    left, y world up: the listing's longitudinal axis, z = x cross y: forward), spread
    by :class:`ShiftingPivot` over the target's spine bones present (lowest first: rx
    and rz doubled, at most ``limit_deg`` a joint, the rest carried up; ry shared)
    and written back: each joint's ``L`` is its share (in world axes), ``E``
    accumulates from the Hips, ``G = E ⊗ T``. Every other bone keeps its world
    rotation; the children of the spine bones (Neck, the shoulders) get their ``L``
    recomputed against their new parent. The flags are left as the mapping set them.

    Args:
        bone_names: (N,) the target's humanoid bone names (Hips first).
        parents: (N,) parent index per bone, -1 for Hips.
        rest_world_from_bone_quat: (N, 4) float64 (w, x, y, z), ``T_h``.
        mapped: the target bones the rig drives (the group's end: the highest of
            :data:`SPINE_BONES` among them).
        left_world: (3,) the target's left, world (its forward is left x up).
        limit_deg: the most rotation a joint takes about x and z, degrees.
        double: double rx and rz (the listing's single-pivot approximation).

    Raises:
        ValueError: the target has no spine bone on a chain from Hips, or the rig maps
            none of them.
    """

    def __init__(
        self,
        bone_names: Sequence[str],
        parents: Sequence[int],
        rest_world_from_bone_quat: F64Array,
        mapped: Collection[str],
        left_world: F64Array,
        limit_deg: float = DEFAULT_LIMIT_DEG,
        *,
        double: bool = True,
    ) -> None:
        index = {n: i for i, n in enumerate(bone_names)}
        if SPINE_BASE not in index:
            raise ValueError(f"spine pivot: the target has no {SPINE_BASE}")
        chain = [index[n] for n in SPINE_BONES if n in index]
        below = index[SPINE_BASE]
        for j in chain:
            if parents[j] != below:
                raise ValueError(
                    f"spine pivot: {bone_names[j]} is not the child of "
                    f"{bone_names[below]} (the target's spine bones "
                    f"{[bone_names[c] for c in chain]} must be a chain from Hips)"
                )
            below = j
        ends = [j for j in chain if bone_names[j] in mapped]
        if not chain or not ends:
            raise ValueError(
                f"spine pivot: the target needs {' / '.join(SPINE_BONES)} bones and "
                f"the rig must drive one of them; target has "
                f"{[bone_names[c] for c in chain]}, the rig drives "
                f"{sorted(set(mapped) & set(SPINE_BONES))}"
            )
        in_chain = {j: i for i, j in enumerate(chain)}
        kids = [
            (c, in_chain[p])
            for c, p in enumerate(parents)
            if p in in_chain and c not in in_chain
        ]
        plan = np.zeros((1 + len(chain) + len(kids), 2 + 2), dtype=np.int64)
        plan[0] = (index[SPINE_BASE], ends[-1], len(chain), len(kids))
        for i, j in enumerate(chain):
            plan[1 + i, 0] = j
        for k, (c, pos) in enumerate(kids):
            plan[1 + len(chain) + k, :2] = (c, pos)
        plan.flags.writeable = False
        left = np.asarray(left_world, dtype=np.float64)
        left = left / np.linalg.norm(left)
        up = np.array([0.0, 0.0, 1.0])
        world_from_s = np.stack([left, up, np.cross(left, up)], axis=1)
        self.bones = tuple(bone_names[j] for j in chain)
        self.end = bone_names[ends[-1]]
        self.stage = ShiftingPivot(len(chain), limit_deg, double=double)
        self._plan = plan
        self._m = rot.quat_from_mat(world_from_s)
        self._rest = np.ascontiguousarray(rest_world_from_bone_quat, dtype=np.float64)
        self._shares = np.zeros((len(chain), 4))
        self._e = np.zeros((len(chain) + 1, 4))

    def apply(
        self, world_from_bone_quat: F64Array, rest_from_bone_quat: F64Array
    ) -> None:
        """Rewrite one retargeted frame's spine, in place.

        Args:
            world_from_bone_quat: (N, 4) float64 (w, x, y, z), ``G_h``.
            rest_from_bone_quat: (N, 4) float64 (w, x, y, z), ``L_h`` (world axes).
        """
        st = self.stage
        _spine_pivot(
            world_from_bone_quat, rest_from_bone_quat, self._rest, self._plan,
            self._m, st.limit_rad, st.double, st._angles, self._shares, self._e,
        )  # fmt: skip


def spine_stage(config: Any, target: Any, rig: Any) -> SpinePivot | None:
    """The ``[target] spine = "pivot"`` stage for ``target`` driven by ``rig`` (None
    for ``"mapped"``); ``config`` is the ``[target]`` table (``TargetConfig``:
    ``spine``, ``spine_pivot_limit_deg``).

    Why a target option and not a ``[[pipeline]]`` kind: the pipeline's stages act
    on the solved rig's pose (``PoseBuffer``, the rig's B bones), and the bones the
    pivot writes are the target's: UpperChest exists on no shipped rig (the rigs
    solve pelvis, lumbar, thorax), so the shares can only be written once the pose
    is mapped onto the target, after ``Retargeter.apply``.

    Raises:
        ValueError: the target has no spine chain or the rig drives none of it.
    """
    if config.spine != "pivot":
        return None
    return SpinePivot(
        target.bone_names, target.parents, target.rest_world_from_bone_quat,
        set(rig.humanoid), target.left_world, config.spine_pivot_limit_deg,
    )  # fmt: skip
