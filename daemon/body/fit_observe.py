"""Which rotations a rig's markers determine, decided per bone by the code.

At the calibration pose the fit's model (every marker at its place on its bone, every
joint with the freedom its joint model gives it) is linearized: a rotation ``e`` of
bone ``b`` (a unit direction in the bone's rest axes, a radian of rotation about it)
moves each marker ``i`` that bone ``b`` carries by ``(W_b e) x (p_i - o_b)`` metres,
and the root's translation moves its markers one for one. With ``J`` those columns for
every free rotation and translation (rows scaled by each marker's weight),
``H = J^T J`` is the fit's information at unit marker noise. What the markers tell
about bone ``b`` alone, every other joint free to make up for it, is the Schur
complement of the other unknowns in ``H``:

    S_b = H_bb - H_bo pinv(H_oo) H_ob          (H_oo singular: exact, since H is a Gram
                                                matrix: null(H_oo) lies in null(H_bo))

Its eigenvectors are the bone's rotations, its eigenvalues' square roots how many
metres of marker displacement one radian of each makes when everything else moves to
hide it: the lever, here in mm per radian. At marker noise ``sigma_m`` a rotation with
lever ``L`` is measured to ``sigma_m / L`` radians; it is **observed** when that is at
most :data:`RESOLUTION_RAD`, i.e. ``L >= MIN_LEVER_M``.

A rotation that is not observed gets a **prior** automatically: a pull of the joint
towards its calibration pose in that direction only, of stiffness
:data:`PRIOR_STIFFNESS` (``MIN_LEVER_M^2``, m^2 / rad^2: the information of the weakest
rotation the markers count as measuring, so the prior decides exactly where the
markers cannot). Bones are decided parents first, each with the priors already given
to the bones before it: when two joints turn about one axis that no marker between
them sees (a spine bone without markers under the chest, a neck under a head) the
proximal one is held first. The distal one, whose markers see the sum, is then told
apart from it by that prior alone: its lever comes out ``sqrt(M k / (M + k))`` with
``k = PRIOR_STIFFNESS`` and ``M`` what its markers see of the sum, just under
``MIN_LEVER_M`` however large ``M`` is, so it is held too and the fit splits the sum
between the two by their equal priors (Plug-in Gait's chest twist: 11.44 mm/rad under
a spine twist of 0, its head twist 11.43 under a neck of 0; on the synthetic
performer's default motions the fit's spine takes a median 0.55 of the trunk's twist
on the pelvis, the performer's abdomen 0.41).

Joint models (``rig_fit``: ball, hinge, hinge_twist, swing, fixed) set which rotations
a joint has at all; a root has three rotations and three translations.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from retargetd.daemon import rotations as rot
from retargetd.protocols.frames import BoolArray, F64Array, IntArray

__all__ = [
    "HOLD_TABLE_BEND_RAD",
    "HOLD_TABLE_STRAIGHT_RAD",
    "MIN_LEVER_M",
    "NOISE_M",
    "PRIOR_STIFFNESS",
    "RESOLUTION_RAD",
    "BoneObservation",
    "Chain",
    "hidden_information",
    "hinges_at_right_angles",
    "joint_basis",
    "marker_hinges",
    "observe",
]

#: Marker noise, metres: optical systems' residuals are under 1 mm (Merriaux et al.,
#: "A study of Vicon system positioning performance", Sensors 17(7):1591, 2017).
NOISE_M = 1e-3
#: The largest standard error of a joint angle that counts as measured: 5 degrees,
#: the bound of McGinley et al.'s "reasonable" band ("The reliability of
#: three-dimensional kinematic gait measurements: a systematic review", Gait Posture
#: 29(3):360-369, 2009: errors of 2-5 degrees reasonable, above 5 a concern).
RESOLUTION_RAD = math.radians(5.0)
#: A rotation is observed when one radian of it moves the markers by at least this
#: (metres per radian): NOISE_M / RESOLUTION_RAD = 11.5 mm/rad.
MIN_LEVER_M = NOISE_M / RESOLUTION_RAD
#: Stiffness of the prior on a rotation the markers do not observe, m^2 / rad^2.
PRIOR_STIFFNESS = MIN_LEVER_M**2
#: Relative cut of the pseudo-inverse in the Schur complement (the information spans
#: ~ (1e-6 .. 10) m^2 / rad^2; what is below 1e-12 of the largest is a null space).
_RCOND = 1e-12

_EYE = np.eye(3)


@dataclass(frozen=True, slots=True)
class BoneObservation:
    """What the markers determine of one bone's rotation relative to its parent.

    Attributes:
        bone: the bone's name.
        dof: its joint model: "root", "ball", "hinge", "hinge_twist", "swing" or
            "fixed".
        axes: (d, 3) unit directions in the bone's rest axes (+Y along the bone),
            the joint's free rotations, weakest first (d = 0 for a fixed joint).
        lever_mm: (d,) mm of marker displacement per radian of each, every other
            joint free to hide it.
        observed: (d,) lever_mm >= MIN_LEVER_M in mm.
        prior: (3, 3) m^2 / rad^2, the automatic prior the unobserved directions got
            (in the bone's rest axes; zeros when none).
        explicit: the rig's own ``[fit]`` prior on the bone made the automatic one
            needless for some direction (``stiffness_mm`` or a fixed joint).
        hinge: (3,) a hinge's axis in the bone's rest axes (None: no hinge).
    """

    bone: str
    dof: str
    axes: F64Array
    lever_mm: F64Array
    observed: BoolArray
    prior: F64Array
    explicit: bool
    hinge: F64Array | None = None

    def describe(self) -> str:
        """One line: each rotation, its lever and whether it is observed."""
        if self.dof == "fixed":
            return "fixed to its parent (no rotation)"
        parts = []
        for axis, lever, seen in zip(
            self.axes, self.lever_mm, self.observed, strict=True
        ):
            name = _axis_name(axis)
            state = "observed" if seen else "held at the calibration pose"
            parts.append(f"{name} {lever:.0f} mm/rad {state}")
        return "; ".join(parts)


def _axis_name(axis: F64Array) -> str:
    """A readable name of a direction in bone axes (+Y: the bone's twist)."""
    a = np.abs(axis)
    k = int(np.argmax(a))
    if a[k] > math.cos(math.radians(20.0)):
        return ("swing x", "twist", "swing z")[k]
    return "[" + ", ".join(f"{v:+.2f}" for v in axis) + "]"


def joint_basis(
    dof: str, hinge_axis: F64Array, twist_axis: F64Array | None = None
) -> F64Array:
    """The rotations a joint model allows at its calibration pose.

    Args:
        dof: "root", "ball", "hinge", "hinge_twist", "swing" or "fixed".
        hinge_axis: (3,) the hinge axis in the bone's rest axes (hinges only).
        twist_axis: (3,) a hinge_twist's twist axis, or the one a swing forbids, in
            the bone's rest axes (None: the bone's own +Y).

    Returns:
        (3, d) orthonormal columns in the bone's rest axes.
    """
    if dof in ("root", "ball"):
        return _EYE.copy()
    if dof == "fixed":
        return np.zeros((3, 0))
    if dof == "swing":  # perpendicular to the twist it forbids (+Y or twist_to's)
        if twist_axis is None or (twist_axis[0] == 0.0 and twist_axis[2] == 0.0):
            return _EYE[:, [0, 2]].copy()
        a = np.asarray(twist_axis, dtype=np.float64)
        q, _ = np.linalg.qr(np.stack([a / np.linalg.norm(a), _EYE[0], _EYE[2]], 1))
        return np.asarray(q[:, 1:])
    h = np.asarray(hinge_axis, dtype=np.float64)
    h = h / np.linalg.norm(h)
    if dof == "hinge":
        return h[:, None]
    if dof == "hinge_twist":  # the hinge, then the twist (the bone's own +Y default)
        a = _EYE[1] if twist_axis is None else np.asarray(twist_axis, dtype=np.float64)
        q, _ = np.linalg.qr(np.stack([h, a], axis=1))
        return np.asarray(q)
    raise ValueError(f"unknown joint model {dof!r}")


def _rest_pose(
    parent: IntArray,
    root_of: IntArray,
    off_parent: F64Array,
    rest_pfb: F64Array,
    root_rest_pos: F64Array,
) -> tuple[F64Array, F64Array]:
    """World rotation matrices (B, 3, 3) and origins (B, 3) at the calibration pose."""
    n = len(parent)
    wq = np.zeros((n, 4))
    org = np.zeros((n, 3))
    for b in range(n):
        p = int(parent[b])
        if p < 0:
            wq[b] = rest_pfb[b]
            org[b] = root_rest_pos[root_of[b]]
        else:
            wq[b] = rot.quat_mul(wq[p], rest_pfb[b])
            org[b] = org[p] + rot.quat_rotate(wq[p], off_parent[b])
    return rot.mat_from_quat(wq), org


@dataclass(frozen=True, slots=True, kw_only=True)
class Chain:
    """The fit's chain at its calibration pose, as ``fit_model`` builds it.

    Attributes:
        parent: (B,) parent index, -1 for a root; ``root_of`` (B,) each bone's root
            ordinal.
        off_parent: (B, 3) metres, each origin in its parent's bone frame.
        rest_pfb: (B, 4) calibrated parent_from_bone (roots: world_from_bone),
            w x y z.
        root_rest_pos: (R, 3) metres, world, the roots' calibrated origins.
        marker_bone: (Mr,) the bone each marker rides; ``marker_local`` (Mr, 3)
            metres in its frame; ``marker_weight`` (Mr,) (0: not used).
        dof: (B,) each joint's model ("root" for roots).
        hinge_axis: (B, 3) hinge axes in the bones' rest axes (hinges).
        twist_axis: (B, 3) a ``hinge_twist``'s twist axis in the bone's rest axes
            (None: every bone's own +Y).
    """

    parent: IntArray
    root_of: IntArray
    off_parent: F64Array
    rest_pfb: F64Array
    root_rest_pos: F64Array
    marker_bone: IntArray
    marker_local: F64Array
    marker_weight: F64Array
    dof: Sequence[str]
    hinge_axis: F64Array
    twist_axis: F64Array | None = None


@dataclass(frozen=True, slots=True)
class _Linearized:
    """The model linearized at its calibration pose (rows: 3 per used marker)."""

    jac: F64Array  # (3 U, n) metres per radian / per metre, rows scaled by sqrt(w)
    used: IntArray  # (U,) rig marker of each row triple
    bases: list[F64Array]  # per bone (3, d) its free rotations, bone rest axes
    col0: IntArray  # (B + 1,) first column of each bone; translations after


def _linearize(chain: Chain) -> _Linearized:
    ch = chain
    parent, root_of, dof, hinge_axis = ch.parent, ch.root_of, ch.dof, ch.hinge_axis
    marker_bone, marker_local, marker_weight = (
        ch.marker_bone,
        ch.marker_local,
        ch.marker_weight,
    )
    root_rest_pos = ch.root_rest_pos
    n_b = len(parent)
    wm, org = _rest_pose(parent, root_of, ch.off_parent, ch.rest_pfb, root_rest_pos)
    used = np.flatnonzero(np.asarray(marker_weight) > 0.0)
    pm = org[marker_bone[used]] + np.einsum(
        "mij,mj->mi", wm[marker_bone[used]], marker_local[used]
    )
    # Columns: each bone's free rotations (world directions), then each root's
    # translation.
    tw = ch.twist_axis
    bases = [
        joint_basis(dof[b], hinge_axis[b], None if tw is None else tw[b])
        for b in range(n_b)
    ]
    col0 = np.cumsum([0] + [B.shape[1] for B in bases])
    n_roots = int(root_rest_pos.shape[0])
    n_col = int(col0[-1]) + 3 * n_roots
    jac = np.zeros((3 * len(used), n_col))
    for r, i in enumerate(used):
        s = int(marker_bone[i])
        rows = slice(3 * r, 3 * r + 3)
        sw = math.sqrt(float(marker_weight[i]))
        k = s
        while k >= 0:
            lever = pm[r] - org[k]
            for c in range(bases[k].shape[1]):
                a = wm[k] @ bases[k][:, c]
                jac[rows, col0[k] + c] = sw * np.cross(a, lever)
            k = int(parent[k])
        t0 = int(col0[-1]) + 3 * int(root_of[s])
        jac[rows, t0 : t0 + 3] = sw * _EYE
    return _Linearized(jac=jac, used=used, bases=bases, col0=col0)


def observe(
    chain: Chain, *, bone_names: Sequence[str], explicit_prior: F64Array
) -> tuple[BoneObservation, ...]:
    """Decide, bone by bone (parents first), which rotations the markers observe, and
    give the others the automatic prior (module docstring).

    Args:
        chain: the chain at its calibration pose.
        bone_names: (B,) the rig's bones, parents first.
        explicit_prior: (B, 3, 3) m^2 / rad^2, the rig's own priors (bone axes).

    Returns:
        One :class:`BoneObservation` per bone, in rig order.
    """
    n_b = len(bone_names)
    parent, dof, hinge_axis = chain.parent, chain.dof, chain.hinge_axis
    lin = _linearize(chain)
    jac, bases, col0 = lin.jac, lin.bases, lin.col0
    n_col = jac.shape[1]
    info = jac.T @ jac
    # The rig's own priors on every bone (removed from a bone's own block while it is
    # decided: the report says what the markers determine).
    own = [bases[b].T @ explicit_prior[b] @ bases[b] for b in range(n_b)]
    for b in range(n_b):
        blk = slice(col0[b], col0[b + 1])
        info[blk, blk] += own[b]
    out = []
    for b in range(n_b):
        d = bases[b].shape[1]
        blk = slice(col0[b], col0[b + 1])
        if d == 0:
            out.append(
                BoneObservation(
                    bone=bone_names[b],
                    dof=dof[b],
                    axes=np.zeros((0, 3)),
                    lever_mm=np.zeros(0),
                    observed=np.zeros(0, dtype=bool),
                    prior=np.zeros((3, 3)),
                    explicit=True,
                )
            )
            continue
        sel = np.zeros(n_col, dtype=bool)
        sel[blk] = True
        h_bb = info[np.ix_(sel, sel)] - own[b]
        h_bo = info[np.ix_(sel, ~sel)]
        h_oo = info[np.ix_(~sel, ~sel)]
        schur = (
            h_bb - h_bo @ np.linalg.pinv(h_oo, rcond=_RCOND, hermitian=True) @ h_bo.T
        )
        lam, vec = np.linalg.eigh(0.5 * (schur + schur.T))
        lever = np.sqrt(np.maximum(lam, 0.0))
        axes = (bases[b] @ vec).T  # (d, 3) bone axes
        observed = lever >= MIN_LEVER_M
        prior = np.zeros((3, 3))
        explicit = False
        for u in axes[~observed]:
            if u @ explicit_prior[b] @ u >= PRIOR_STIFFNESS:
                explicit = True
                continue
            prior += PRIOR_STIFFNESS * np.outer(u, u)
        if parent[b] >= 0:  # a root is free: its prior would pin the performer
            info[blk, blk] += bases[b].T @ prior @ bases[b]
        else:
            prior[:] = 0.0
        out.append(
            BoneObservation(
                bone=bone_names[b],
                dof=dof[b],
                axes=axes,
                lever_mm=1e3 * lever,
                observed=observed,
                prior=prior,
                explicit=explicit,
                hinge=hinge_axis[b] if dof[b] in ("hinge", "hinge_twist") else None,
            )
        )
    return tuple(out)


#: The bend at which a hinge's two twists are told apart best: sin(bend) scales what
#: the child's markers tell about the parent's twist apart from the child's own, and
#: is largest at a right angle.
HOLD_TABLE_BEND_RAD = math.pi / 2.0
#: A hinge the calibration pose holds straighter than this gets its hold tables at
#: :data:`HOLD_TABLE_BEND_RAD`: below 30 deg its two twists are told apart by less
#: than half (sin 30 deg) of what a right angle gives. (Plug-in Gait's static bends
#: the elbows 47 deg and keeps its tables; measured on its hides, bending those to a
#: right angle changed no case's pass or fail.)
HOLD_TABLE_STRAIGHT_RAD = math.radians(30.0)


def hinges_at_right_angles(chain: Chain) -> Chain:
    """The chain with every hinge the calibration pose holds straighter than
    :data:`HOLD_TABLE_STRAIGHT_RAD` turned about its axis to a right angle between its
    bone and its parent's (+Y to +Y), in the sense the calibration pose bends it (a
    straight one: the positive sense), everything else as calibrated.

    Args:
        chain: the chain at its calibration pose.

    Returns:
        A copy whose ``rest_pfb`` has each such hinge (``hinge``, ``hinge_twist``)
        bent to :data:`HOLD_TABLE_BEND_RAD`.
    """
    pfb = np.array(chain.rest_pfb, dtype=np.float64, copy=True)
    y = np.array([0.0, 1.0, 0.0])
    for b, dof in enumerate(chain.dof):
        if dof not in ("hinge", "hinge_twist") or chain.parent[b] < 0:
            continue
        axis = np.asarray(chain.hinge_axis[b], dtype=np.float64)
        # pfb R_h(t) turns the bone's +Y (in its parent's axes) about pfb h by t: the
        # bend is the signed angle from the parent's +Y to it about that axis (both
        # +Y's in the plane normal to the axis, as a hinge's two bones are)
        axis_p = rot.quat_rotate(pfb[b], axis)
        bone_y = rot.quat_rotate(pfb[b], y)
        bend = math.atan2(float(np.cross(y, bone_y) @ axis_p), float(y @ bone_y))
        target = HOLD_TABLE_BEND_RAD if bend >= 0.0 else -HOLD_TABLE_BEND_RAD
        if abs(bend) >= HOLD_TABLE_STRAIGHT_RAD:
            continue  # bent enough at calibration: its tables stand as they are
        turn = rot.quat_from_axis_angle(axis, target - bend)
        pfb[b] = rot.quat_mul(pfb[b], turn)
    return Chain(
        parent=chain.parent, root_of=chain.root_of, off_parent=chain.off_parent,
        rest_pfb=pfb, root_rest_pos=chain.root_rest_pos,
        marker_bone=chain.marker_bone, marker_local=chain.marker_local,
        marker_weight=chain.marker_weight, dof=chain.dof, hinge_axis=chain.hinge_axis,
        twist_axis=chain.twist_axis,
    )  # fmt: skip


def hidden_information(
    chain: Chain, *, prior: F64Array
) -> tuple[F64Array, F64Array, F64Array]:
    """What each bone loses when one marker hides, for the fit's hold prior.

    With marker ``k`` hidden (its rows out of ``J``) each bone's marginal information
    ``S_b`` (module docstring; every prior of the model in) is decomposed into its
    eigen-directions ``u`` (bone rest axes) with their information ``lam`` (m^2 /
    rad^2), and the information the marker gave along each, ``u^T (S_b - S_b^-k) u``
    (``lost``). The kernel (``kernel_fit``) holds, while ``k`` is hidden, each
    direction that falls below what the take's residual level resolves, at its last
    seen value, with the information lost (``FitParams``, "hold").

    Two tables: at the calibration pose, and with every nearly straight hinge at a
    right angle (:func:`hinges_at_right_angles`). A hinge held straight makes its
    parent's twist and its own one direction, which no marker of either separates:
    with a marker of the parent hidden, the first table holds the child's twist too,
    which the child's own markers see as soon as the hinge bends. The kernel blends
    the two for a hidden marker by how far its limb's hinge (:func:`marker_hinges`) is
    bent at the last explained frame (``FitParams.hold_straight_deg``). Measured on
    ``menache``'s synthetic performer (straight elbows at calibration), each
    epicondyle marker hidden 1 s: 106-128 deg off the intact solve with the first
    table alone; with both, 2.8-4.3 deg hidden from 3 s, 2.3-4.5 (left) and 77-78
    (right, whose wrist markers leave the forearm another turn) from 4 s. The second
    table alone turned a thigh 59 deg with a knee marker hidden while the leg stood
    straight.

    Args:
        chain: the chain at its calibration pose.
        prior: (B, 3, 3) m^2 / rad^2, every prior the model has (bone axes).

    Returns:
        ``axes`` (2 Mr B, 9): row ``k * B + b`` the three directions (rows of a
        3 x 3, bone rest axes; zero rows past the joint's freedom), ``lam``
        (2 Mr B, 3) and ``lost`` (2 Mr B, 3); zeros for markers not used. Rows from
        ``Mr * B`` on: the same with the nearly straight hinges at a right angle.
    """
    straight = _tables(chain, prior)
    bent = _tables(hinges_at_right_angles(chain), prior)
    return (
        np.concatenate([straight[0], bent[0]]),
        np.concatenate([straight[1], bent[1]]),
        np.concatenate([straight[2], bent[2]]),
    )


def marker_hinges(chain: Chain) -> IntArray:
    """Per marker, the hinge whose bend picks its hold table
    (:func:`hidden_information`): the nearly straight hinge
    (:data:`HOLD_TABLE_STRAIGHT_RAD` at calibration) on its limb: its own bone, else
    the nearest such below it along a limb (bones with one child), else the nearest
    above it; -1 when none.

    Args:
        chain: the chain at its calibration pose.

    Returns:
        (Mr,) int64 bone indices.
    """
    bent = hinges_at_right_angles(chain).rest_pfb
    moved = [
        dof in ("hinge", "hinge_twist")
        and not np.allclose(bent[b], chain.rest_pfb[b], atol=1e-12)
        for b, dof in enumerate(chain.dof)
    ]
    children: dict[int, list[int]] = {}
    for b, p in enumerate(chain.parent):
        children.setdefault(int(p), []).append(b)
    out = np.full(len(chain.marker_bone), -1, dtype=np.int64)
    for k, b0 in enumerate(chain.marker_bone):
        b = int(b0)
        while b >= 0 and not moved[b]:  # down the limb (a bone with one child)
            below = children.get(b, [])
            b = below[0] if len(below) == 1 else -1
        if b < 0:
            b = int(chain.parent[int(b0)])
            while b >= 0 and not moved[b]:  # else up the ancestors
                b = int(chain.parent[b])
        out[k] = b
    return out


def _tables(chain: Chain, prior: F64Array) -> tuple[F64Array, F64Array, F64Array]:
    """:func:`hidden_information`'s tables at ``chain``'s pose."""
    parent = chain.parent
    n_b = len(parent)
    n_m = len(chain.marker_bone)
    lin = _linearize(chain)
    jac, bases, col0 = lin.jac, lin.bases, lin.col0
    n_col = jac.shape[1]
    info = jac.T @ jac
    for b in range(n_b):
        blk = slice(col0[b], col0[b + 1])
        info[blk, blk] += bases[b].T @ prior[b] @ bases[b]
    # S_b^-1 is the b block of H^-1; a tiny ridge makes H invertible where the
    # markers and priors leave a direction free (a root's nothing, a fixed joint's
    # zero columns): (1e-5 m/rad)^2, far under any threshold here.
    ridge = 1e-10 * np.eye(n_col)

    def marginals(h: F64Array) -> list[F64Array]:
        cov = np.linalg.inv(h + ridge)
        out = []
        for b in range(n_b):
            blk = slice(col0[b], col0[b + 1])
            if col0[b + 1] == col0[b]:
                out.append(np.zeros((0, 0)))
                continue
            sb = np.linalg.inv(cov[blk, blk]) - 1e-10 * np.eye(col0[b + 1] - col0[b])
            out.append(0.5 * (sb + sb.T))
        return out

    full = marginals(info)
    axes = np.zeros((n_m * n_b, 9))
    lam_out = np.zeros((n_m * n_b, 3))
    lost_out = np.zeros((n_m * n_b, 3))
    for r, k in enumerate(lin.used):
        rows = jac[3 * r : 3 * r + 3]
        part = marginals(info - rows.T @ rows)
        for b in range(n_b):
            d = col0[b + 1] - col0[b]
            if d == 0 or parent[b] < 0:
                continue
            lam, vec = np.linalg.eigh(part[b])
            lost = np.einsum("ij,ik,kj->j", vec, full[b] - part[b], vec)
            row = int(k) * n_b + b
            ax = (bases[b] @ vec).T  # (d, 3)
            axes[row, : 3 * d] = ax.reshape(-1)
            lam_out[row, :d] = np.maximum(lam, 0.0)
            lost_out[row, :d] = np.maximum(lost, 0.0)
    return axes, lam_out, lost_out
