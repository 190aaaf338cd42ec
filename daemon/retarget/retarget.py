"""Retargeting: the solved rig re-expressed on a target humanoid (the engine skeleton).

Notation (quaternions ``(w, x, y, z)``, Hamilton, active; ``a ⊗ b`` applies ``b``
first; ``q̄`` = conjugate). Per frame the body solve gives ``W_b(t)``
(``world_from_bone`` of rig bone ``b``); the calibration gives ``W_b^cal``. The target
has, per humanoid bone ``h``, a rest world rotation ``T_h`` (``world_from_bone`` at
rest; identity for the default humanoid), a rest offset ``o_h`` (its joint in the
parent's frame at rest, along world axes) and an aim vector ``a_h`` (joint -> first
child joint, or the tip for a leaf, at rest, world axes).

1. **World delta since calibration**: ``D_b(t) = W_b(t) ⊗ W̄_b^cal`` (a world-frame
   rotation; identity in the calibration pose). Bone ``b`` is ``rig.humanoid[h]``.
2. **Heading** ``H``: the rotation about world +Z taking the target's forward onto the
   performer's forward at calibration, so the avatar faces the way the performer
   faced in the lab (DESIGN: no heading change). Forward = left x up (up = +Z), the
   rig convention (``calibration.body_axes``: depth = width x height). The performer's
   left comes from :func:`performer_left_from_calibration`.
3. **Base-pose compensation** ``C_h``: the minimal (swing) rotation taking the
   heading-aligned target rest aim ``H a_h`` onto the performer's calibrated bone
   direction ``W_b^cal ŷ`` (rig bones point +Y from origin to aim). In the calibration
   pose the avatar then shows the performer's real pose (an A-pose stays an A-pose),
   and a T-pose calibration gives ``C ≈ I``. Measured by default only on the long
   limb bones (:data:`COMPENSATED_BONES`: upper/lower arm and leg), whose rig axis is
   the joint-to-joint line; every other bone takes its target parent's ``C`` (Hips:
   ``I``), so a hand stays straight on its forearm. The other bones' rig axes follow
   markers, not anatomy: on the synthetic performer's exact T-pose, ``menache`` gives
   hand 18°, foot 15°, clavicle 31°, spine 19°, head 65° between the rig axis and the
   target's bone, offsets of construction, not of pose. Configurable.
4. **Target world delta** ``E_h(t) = D_b(t) ⊗ C_h ⊗ H = W_b(t) ⊗ K_h`` with the
   constant ``K_h = W̄_b^cal ⊗ C_h ⊗ H`` (one product per bone per frame). The
   target bone's world rotation is ``G_h = E_h ⊗ T_h``; its aim points along
   ``E_h a_h``, which is ``W_b(t) ŷ`` exactly when compensated: the avatar's limbs
   point where the performer's do.
5. **Rotation relative to rest, along world axes** (what VMC sends as the bone's
   rotation): ``L_h = Ē_p ⊗ E_h`` (``p`` = target parent); Hips: ``L = E_hips``. This
   is ``T_p ⊗ Ḡ_p ⊗ G_h ⊗ T̄_h``: the parent-relative rotation ``P_h = Ḡ_p ⊗ G_h``
   taken relative to its rest value ``P_h^rest = T̄_p ⊗ T_h`` (``P̄_h^rest ⊗ P_h``, in
   the bone's rest axes) and carried to world axes by ``T_h``. For the default
   humanoid (all ``T = I``) the three agree. For a BVH target ``T_h = A``
   (``world_from_capture`` of the file, since a BVH rest pose has every joint frame
   parallel to the file's axes), ``P^rest = I``, and the BVH channel rotation (file
   axes) is ``Ā ⊗ L_h ⊗ A`` (:func:`bone_axes_from_world_axes`). VMC receivers hold
   VRM-normalized models (rest frames parallel to the model's axes), so ``L`` in world
   axes is what the engine adapter converts (``R' = M R Mᵀ``, ``engine_unity``).
6. **Bones the rig does not solve** (e.g. UpperChest, Toes) are filled: slerp of
   ``E`` between the nearest mapped ancestor and the nearest mapped descendant down
   the chain (Hips -> Spine -> Chest -> UpperChest -> Neck -> Head, Shoulder ->
   UpperArm -> LowerArm -> Hand, UpperLeg -> LowerLeg -> Foot -> Toes) at
   ``u = k / n`` (``k`` steps from the ancestor out of ``n``); with no mapped
   descendant the rotation relative to the parent is identity (``E_h = E_parent``).
   Flagged :data:`FLAG_FILLED`.
7. **Root**: ``root_pos = (r(t) - r^cal) s`` with ``s = hips_height_target /
   hips_height_performer`` (the performer's is ``r^cal_z``, the calibrated root's
   height above the lab floor z = 0); the model root (floor point under the hips),
   sent in ``/VMC/Ext/Root/Pos`` with identity rotation. The Hips joint sits at
   ``hips_pos = root_pos + o_hips`` (``o_hips = (0, 0, hips_height)``, sent as the
   Hips' Bone/Pos position), so the hips move by the scaled displacement.

Everything is in the internal world (+Z up, metres); ``protocols/engine_unity``
converts for VMC. :meth:`Retargeter.apply` is one call of the compiled kernel
(``retargetd.daemon.retarget.kernel``) and allocates nothing in steady state; the numpy
version it replaced is the tests' oracle (``tests/helpers/retarget_oracle.py``).
"""

from __future__ import annotations

import logging
from collections.abc import Collection
from dataclasses import dataclass

import numpy as np

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.calibration import Calibration, check_calibration_fits
from retargetd.daemon.body.rig import HUMANOID_BONES, Rig
from retargetd.daemon.body.solve import BodyPose
from retargetd.daemon.body.solve import warm_up as warm_up_body
from retargetd.daemon.retarget import kernel as kt
from retargetd.daemon.retarget.kernel import FLAG_FILLED
from retargetd.daemon.retarget.skeleton import (
    _UP,
    CHAIN_CHILD,
    CMU_BVH_NAME_MAP,
    DEFAULT_BVH_NAME_MAP,
    TargetSkeleton,
    _horizontal_unit,
    _readonly,
    bone_axes_from_world_axes,
    default_humanoid,
)
from retargetd.protocols.frames import F64Array, U8Array

__all__ = [
    "CHAIN_CHILD",
    "CMU_BVH_NAME_MAP",
    "COMPENSATED_BONES",
    "DEFAULT_BVH_NAME_MAP",
    "Retargeter",
    "TargetPose",
    "TargetSkeleton",
    "bone_axes_from_world_axes",
    "default_humanoid",
    "joint_positions_world",
    "performer_left_from_calibration",
    "warm_up",
]

logger = logging.getLogger(__name__)

#: Bones whose own calibrated direction sets the base-pose compensation by default
#: (module docstring, step 3); the others inherit their parent's.
COMPENSATED_BONES = tuple(
    f"{s}{b}"
    for s in ("Left", "Right")
    for b in ("UpperArm", "LowerArm", "UpperLeg", "LowerLeg")
)


_IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


def _swing(a: F64Array, b: F64Array) -> F64Array:
    """(4,) the minimal rotation taking direction ``a`` onto direction ``b``."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    d = float(a @ b)
    if d < -1.0 + 1e-12:  # opposite: 180° about any axis normal to a
        axis = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(a, [0.0, 1.0, 0.0])
        return np.array([0.0, *(axis / np.linalg.norm(axis))])
    q = np.array([1.0 + d, *np.cross(a, b)])
    return q / np.linalg.norm(q)


def performer_left_from_calibration(rig: Rig, calibration: Calibration) -> F64Array:
    """The performer's left in the calibration pose, (3,) unit, horizontal, world.

    In order, the first that applies:

    1. a bone whose up reference is the rig's ``lateral`` pair as a direction
       (``up = [RIGHT, LEFT]``: its +X points left; reversed: -X), the one mapped to
       Hips first. All shipped rigs build their pelvis this way (menache
       ``[RHIP, LHIP]``, plug-in-gait ``[RASI, LASI]``, cmu41 ``[RFWT, LFWT]``), and the
       calibration averaged exactly this axis over the base pose;
    2. the feet (mapped LeftFoot and RightFoot, +Y heel/ankle -> toe): forward = the
       mean of their horizontal directions (toe-out cancels), left = up x forward;
    3. the upper arms (T- or A-pose): left = horizontal(LeftUpperArm +Y - RightUpperArm
       +Y).

    Raises:
        ValueError: when none applies (pass ``performer_left_world`` instead).
    """
    mats = rot.mat_from_quat(np.asarray(calibration.rest_world_from_bone_quat))
    index = {n: i for i, n in enumerate(rig.bone_names)}
    lateral = tuple(rig.lateral)
    hips = rig.humanoid.get("Hips")
    bones = sorted(rig.bones, key=lambda b: b.name != hips)
    for bone in bones:
        if len(bone.up) == 2 and set(bone.up) == set(lateral):
            sign = 1.0 if tuple(bone.up) == lateral else -1.0
            return _horizontal_unit(sign * mats[index[bone.name]][:, 0], bone.name)
    feet = [rig.humanoid.get(s + "Foot") for s in ("Left", "Right")]
    if all(feet):
        fwd = np.sum(
            [_horizontal_unit(mats[index[f]][:, 1], f) for f in feet if f is not None],
            axis=0,
        )
        return np.cross(_UP, _horizontal_unit(fwd, "mean foot direction"))
    arms = [rig.humanoid.get(s + "UpperArm") for s in ("Left", "Right")]
    if arms[0] is not None and arms[1] is not None:
        lat = mats[index[arms[0]]][:, 1] - mats[index[arms[1]]][:, 1]
        return _horizontal_unit(lat, "LeftUpperArm - RightUpperArm")
    raise ValueError(
        f"rig {rig.name}: cannot tell the performer's left from the calibration "
        "(no bone with up = rig.lateral, no mapped feet or upper arms); pass "
        "performer_left_world"
    )


@dataclass(slots=True, eq=False)
class TargetPose:
    """One frame on the target (buffers reused frame after frame).

    Attributes:
        world_from_bone_quat: (N, 4) float64, w x y z: ``world_from_bone`` of each
            target bone, ``G_h = E_h ⊗ T_h``.
        rest_from_bone_quat: (N, 4) float64, w x y z, world axes: each bone's rotation
            relative to its parent and its rest (``L_h = Ē_p ⊗ E_h``; Hips: its world
            rotation relative to rest). What VMC sends (after ``engine_unity``).
        root_pos: (3,) float64, metres, world: the model root (floor point under the
            hips), the performer's scaled displacement since calibration; sent as
            ``/VMC/Ext/Root/Pos`` with identity rotation.
        hips_pos: (3,) float64, metres, world: the Hips joint (``root_pos +
            rest_offsets[0]``).
        rest_offsets: (N, 3) float64, metres, world axes: the target's rest offsets
            (constant, read-only; Bone/Pos positions).
        flags: (N,) uint8, :data:`FLAG_FILLED` | :data:`FLAG_SOURCE_HELD`.
    """

    world_from_bone_quat: F64Array
    rest_from_bone_quat: F64Array
    root_pos: F64Array
    hips_pos: F64Array
    rest_offsets: F64Array
    flags: U8Array


class Retargeter:
    """Rig + calibration -> target humanoid, one frame at a time (module docstring).

    Args:
        rig: the rig the poses come from.
        calibration: its calibration (the base pose compensation is measured on).
        target: the target skeleton (default: :func:`default_humanoid`).
        compensate_base_pose: True (:data:`COMPENSATED_BONES`), False (none) or the
            humanoid bones whose own direction is matched (the rest inherit their
            parent's compensation).
        performer_left_world: (3,) the performer's left at calibration, world; default
            from :func:`performer_left_from_calibration`.
        performer_hips_height: metres; default the calibrated root's height
            (``calibration.root_rest_pos[2]``, lab floor at z = 0).

    Raises:
        ValueError: the rig maps no Hips, a bad direction or height.
    """

    def __init__(
        self,
        rig: Rig,
        calibration: Calibration,
        target: TargetSkeleton | None = None,
        *,
        compensate_base_pose: bool | Collection[str] = True,
        performer_left_world: F64Array | None = None,
        performer_hips_height: float | None = None,
    ) -> None:
        check_calibration_fits(rig, calibration)
        self.target = target = default_humanoid() if target is None else target
        names = target.bone_names
        n = len(names)
        rig_index = {b: i for i, b in enumerate(rig.bone_names)}
        src = [rig_index[rig.humanoid[h]] if h in rig.humanoid else -1 for h in names]
        if src[0] < 0:
            raise ValueError(f"rig {rig.name} maps no bone to Hips")
        if compensate_base_pose is True:
            comp = set(COMPENSATED_BONES)
        elif compensate_base_pose is False:
            comp = set()
        else:
            comp = set(compensate_base_pose)
            unknown = comp - set(HUMANOID_BONES)
            if unknown:
                raise ValueError(f"compensate_base_pose: unknown bones {unknown}")
        self.compensated = tuple(h for h in names if h in comp)

        left = (
            performer_left_from_calibration(rig, calibration)
            if performer_left_world is None
            else _horizontal_unit(np.asarray(performer_left_world, float), "left")
        )
        self.performer_forward_world = np.cross(left, _UP)
        f_t = target.forward_world
        f_p = self.performer_forward_world
        yaw = np.arctan2(np.cross(f_t, f_p) @ _UP, f_t @ f_p)
        self.heading_quat = rot.quat_from_axis_angle(_UP, yaw)
        self.heading_deg = float(np.degrees(yaw))

        rest_w = np.asarray(calibration.rest_world_from_bone_quat, dtype=np.float64)
        comp_q = np.tile(_IDENTITY, (n, 1))
        for i in range(n):  # parents first: inherit, or match the own direction
            if src[i] >= 0 and names[i] in comp:
                aim = rot.quat_rotate(self.heading_quat, target.aim_offsets[i])
                performer_dir = rot.quat_rotate(
                    rest_w[src[i]], np.array([0.0, 1.0, 0.0])
                )
                comp_q[i] = _swing(aim, performer_dir)
            elif i > 0:
                comp_q[i] = comp_q[target.parents[i]]
        mapped = [i for i in range(n) if src[i] >= 0]
        k = np.zeros((len(mapped), 4))
        for m, i in enumerate(mapped):
            c_h = rot.quat_mul(comp_q[i], self.heading_quat)
            k[m] = rot.quat_mul(rot.quat_conj(rest_w[src[i]]), c_h)
        self.compensation_quat = _readonly(comp_q)

        # Filling: interpolate between mapped ancestor and mapped chain descendant,
        # else copy the parent's (mapped or interpolated) world delta.
        by_name = {h: i for i, h in enumerate(names)}
        interp, copy = [], []
        for i in range(n):
            if src[i] >= 0:
                continue
            anc, k_up = target.parents[i], 1
            while src[anc] < 0:
                anc, k_up = target.parents[anc], k_up + 1
            desc, k_down = by_name.get(CHAIN_CHILD.get(names[i], "")), 1
            while desc is not None and src[desc] < 0:
                desc = by_name.get(CHAIN_CHILD.get(names[desc], ""))
                k_down += 1
            if desc is not None:
                interp.append((i, anc, desc, k_up / (k_up + k_down)))
            else:
                copy.append(i)
        interp_set = {t[0] for t in interp}
        copy_src = []
        for i in copy:
            s = target.parents[i]
            while src[s] < 0 and s not in interp_set:
                s = target.parents[s]
            copy_src.append(s)

        def idx(values: list[int]) -> np.ndarray:
            a = np.asarray(values, dtype=np.intp)
            a.flags.writeable = False
            return a

        self.bone_names = names
        self.source_bones = tuple(rig.bone_names[s] if s >= 0 else "" for s in src)
        self._src = idx([src[i] for i in mapped])
        self._mapped_t = idx(mapped)
        self._k = _readonly(k)
        self._i_t = idx([t[0] for t in interp])
        self._i_a = idx([t[1] for t in interp])
        self._i_d = idx([t[2] for t in interp])
        self._i_u = _readonly(np.array([t[3] for t in interp]))
        self._i_1mu = _readonly(1.0 - self._i_u)
        self._c_t = idx(copy)
        self._c_s = idx(copy_src)
        self._parent = idx([p if p >= 0 else n for p in target.parents])
        self._rest_t = target.rest_world_from_bone_quat
        flags = np.zeros(n, dtype=np.uint8)
        flags[[t[0] for t in interp] + copy] = FLAG_FILLED
        flags.flags.writeable = False
        self._base_flags = flags
        self.filled = tuple(names[i] for i in range(n) if flags[i])

        self.performer_hips_height = float(
            calibration.root_rest_pos[2]
            if performer_hips_height is None
            else performer_hips_height
        )
        if not self.performer_hips_height > 0.1:
            raise ValueError(
                "performer hips height must be > 0.1 m (calibrated root height above "
                f"the lab floor z = 0); got {self.performer_hips_height} m: pass "
                "performer_hips_height"
            )
        self.root_scale = target.hips_height / self.performer_hips_height
        self._root_rest = _readonly(calibration.root_rest_pos)

        # The compiled kernel's program (kernel_target), read-only, and its scratch.
        prog = np.zeros((n, 4), dtype=np.int64)
        prog[:, 3] = target.parents
        cst = np.zeros((n, kt.N_CST))
        cst[:, kt.C_REST : kt.C_REST + 4] = target.rest_world_from_bone_quat
        for m, i in enumerate(mapped):
            prog[i, :3] = (kt.KIND_MAPPED, src[i], -1)
            cst[i, kt.C_K : kt.C_K + 4] = k[m]
        for (i, a, d, _), u, one_minus_u in zip(
            interp, self._i_u, self._i_1mu, strict=True
        ):
            prog[i, :3] = (kt.KIND_SLERP, a, d)
            cst[i, kt.C_U] = u
            cst[i, kt.C_1MU] = one_minus_u
        for i, c in zip(copy, copy_src, strict=True):
            prog[i, :3] = (kt.KIND_COPY, c, -1)
        params = np.zeros(kt.N_PARAMS)
        params[kt.P_ROOT : kt.P_ROOT + 3] = self._root_rest
        params[kt.P_SCALE] = self.root_scale
        params[kt.P_HALF_LINEAR] = 0.5 * rot.SLERP_LINEAR_BELOW_RAD
        prog.flags.writeable = False
        self._prog = prog
        self._cst = _readonly(cst)
        self._params = _readonly(params)
        self._e = np.tile(_IDENTITY, (n, 1))  # E_h, scratch (steady state: no alloc)

    def program(self) -> tuple[np.ndarray, F64Array, F64Array]:
        """``(prog, cst, params)`` of the compiled kernel (read-only), for a kernel
        that runs this retarget inside its own call (``live/emit.py``)."""
        return self._prog, self._cst, self._params

    def new_pose(self) -> TargetPose:
        """Allocate one frame's output buffers (once per stream)."""
        n = len(self.bone_names)
        return TargetPose(
            world_from_bone_quat=np.tile(_IDENTITY, (n, 1)),
            rest_from_bone_quat=np.tile(_IDENTITY, (n, 1)),
            root_pos=np.zeros(3),
            hips_pos=np.zeros(3),
            rest_offsets=self.target.rest_offsets,
            flags=np.zeros(n, dtype=np.uint8),
        )

    def apply(self, pose: BodyPose, out: TargetPose) -> TargetPose:
        """Retarget one solved frame into ``out`` (no allocation).

        Args:
            pose: the body solve's frame for this rig (``world_from_bone_quat`` (B, 4)
                w x y z, ``root_pos`` (3,) metres world, ``bone_flags`` (B,)).
            out: buffers from :meth:`new_pose`, overwritten.

        Returns:
            ``out``.
        """
        kt.retarget_one(
            pose.world_from_bone_quat, pose.root_pos, pose.bone_flags, self._prog,
            self._cst, self._params, self._e, out.rest_from_bone_quat,
            out.world_from_bone_quat, out.root_pos, out.hips_pos, out.rest_offsets,
            out.flags,
        )  # fmt: skip
        return out


def warm_up() -> None:
    """Load (or compile) the body-solve and retarget kernels through the same code
    paths as a real frame (``BodySolver.solve_frame``, ``Retargeter.apply``), so the
    first live frame pays neither numba's cache load (~0.3 s) nor a compile."""
    solver, pose = warm_up_body()
    rt = Retargeter(
        solver.rig,
        solver.calibration,
        performer_left_world=np.array([0.0, 1.0, 0.0]),
        performer_hips_height=1.0,
    )
    rt.apply(pose, rt.new_pose())


def joint_positions_world(
    target: TargetSkeleton, pose: TargetPose, out: F64Array | None = None
) -> F64Array:
    """Forward kinematics of a retargeted frame (tests, validation; not hot).

    ``x_h = x_p + E_p o_h`` with ``E_p = G_p ⊗ T̄_p`` (the parent's world delta from
    rest) and ``x_hips = hips_pos``.

    Returns:
        (N, 3) float64, metres, world: each target joint.
    """
    n = len(target.bone_names)
    res = np.zeros((n, 3)) if out is None else out
    delta = rot.quat_mul(
        pose.world_from_bone_quat, rot.quat_conj(target.rest_world_from_bone_quat)
    )
    res[0] = pose.hips_pos
    for i in range(1, n):
        p = target.parents[i]
        res[i] = res[p] + rot.quat_rotate(delta[p], target.rest_offsets[i])
    return res
