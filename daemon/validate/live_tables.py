"""The live validator's tables (the calibrated model flattened for the kernel: per-bone
limits, offsets, frames; thresholds as a parameter vector) and the per-frame
:class:`Checker` that poses the MuJoCo model and runs the kernel (validator thread)."""

from __future__ import annotations

import logging
import math

import mujoco
import numpy as np
from scipy.signal import butter

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.rig import Rig
from retargetd.daemon.validate import dynamics as vd
from retargetd.daemon.validate.checks import fit_pairs
from retargetd.daemon.validate.limits import JOINT_LIMITS_DEG, neutral_frame
from retargetd.daemon.validate.live_kernel import (
    _C_CONE,
    _C_FRO,
    _C_FWD,
    _C_LEFT,
    _C_LEN,
    _C_OFF,
    _C_REF,
    _C_SAG,
    _C_TW,
    _I_BODY,
    _I_LIMITED,
    _I_PARENT,
    _I_SITE,
    _N_BONE_F,
    _N_PARAMS,
    _P_A1,
    _P_A2,
    _P_AIR_S,
    _P_B0,
    _P_B2,
    _P_CONV,
    _P_EFF_V,
    _P_FIT,
    _P_FLOOR,
    _P_FLOOR_Z,
    _P_LIM,
    _P_NEAR,
    _P_NORM,
    _P_RATE,
    _P_ROOT_V,
    _P_SELF,
    _P_STILL_N,
    _P_STILL_V,
    N_CHECKS,
    _check_frame,
    _write_qpos,
)
from retargetd.daemon.validate.model import (
    ValidationModel,
    capsule_radii,
)
from retargetd.protocols.frames import F64Array

logger = logging.getLogger(__name__)

# ---- per-frame checker (validator thread) ------------------------------------------


class Tables:
    """Everything the kernels need, resolved once from the model."""

    def __init__(
        self, vm: ValidationModel, rig: Rig, th: dict[str, float], rate_hz: float
    ) -> None:
        skel = vm.skeleton
        n_bones = len(skel.bone_names)
        parents = np.asarray(skel.bone_parents, dtype=np.int64)
        self.root = int(np.flatnonzero(parents < 0)[0])
        self.root_adr = int(vm.model.jnt_qposadr[0])  # the free joint comes first
        self.ball_adr = np.ascontiguousarray(vm.ball_qpos_idx[:, 0], dtype=np.int64)
        self.ball_bones = np.ascontiguousarray(vm.ball_bones, dtype=np.int64)
        bone_f = np.full((n_bones, _N_BONE_F), np.nan)
        bone_i = np.zeros((n_bones, 4), dtype=np.int64)
        bone_f[:, _C_LEN] = skel.bone_lengths
        bone_f[:, _C_OFF : _C_OFF + 3] = skel.offset_parent
        bone_i[:, _I_PARENT] = parents
        bone_i[:, _I_BODY] = vm.body_ids
        bone_i[:, _I_SITE] = vm.site_ids
        forward_world = np.cross(skel.left_world, [0.0, 0.0, 1.0])
        for b, kind in enumerate(skel.bone_kinds):
            lim = JOINT_LIMITS_DEG.get(kind)
            if lim is None or parents[b] < 0:
                continue
            bone_i[b, _I_LIMITED] = 1
            ref, bone_from_world = neutral_frame(skel, b)
            bone_f[b, _C_REF : _C_REF + 4] = ref
            bone_f[b, _C_TW : _C_TW + 2] = lim.twist
            if lim.sagittal is not None:
                bone_f[b, _C_SAG : _C_SAG + 2] = lim.sagittal
            if lim.frontal is not None:
                bone_f[b, _C_FRO] = lim.frontal
            if lim.cone is not None:
                bone_f[b, _C_CONE] = lim.cone
            bone_f[b, _C_LEFT : _C_LEFT + 3] = rot.quat_rotate(
                bone_from_world, skel.left_world
            )
            bone_f[b, _C_FWD : _C_FWD + 3] = rot.quat_rotate(
                bone_from_world, forward_world
            )
        self.bone_f, self.bone_i = bone_f, bone_i
        self.fit_j, self.fit_p = fit_pairs(rig, tuple(rig.joints))
        self.n_joints = len(rig.joints)
        leaves = [b for b in range(n_bones) if b not in set(skel.bone_parents)]
        self.eff = np.asarray(leaves, dtype=np.int64)
        zeros = np.zeros((1, n_bones, 3))
        _, feet, at_aim = vd.foot_points(skel, zeros, zeros)
        self.foot = np.zeros((len(feet), 3), dtype=np.int64)
        self.foot[:, 0] = feet
        self.foot[:, 1] = at_aim
        self.foot_r = np.ascontiguousarray(capsule_radii(skel)[feet])
        self.geom_bone = np.ascontiguousarray(vm.geom_bone, dtype=np.int64)
        self.floor_geom = int(vm.floor_geom)
        contact = vd.CONTACT
        wn = contact["cutoff_hz"] / (0.5 * rate_hz)
        if wn < 1.0:
            bq, aq = butter(2, wn)
        else:  # the offline lowpass leaves data unfiltered too
            bq, aq = np.array([1.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0])
        p = np.zeros(_N_PARAMS)
        p[_P_RATE] = rate_hz
        p[_P_CONV] = th["convention_mm"]
        p[_P_FIT] = th["fit_max_mm"]
        p[_P_NORM] = th["quat_norm"]
        p[_P_LIM] = th["limit_deg"]
        p[_P_SELF] = th["self_penetration_mm"]
        p[_P_FLOOR] = th["floor_penetration_mm"]
        p[_P_ROOT_V] = th["root_speed_m_s"]
        p[_P_EFF_V] = th["effector_speed_m_s"]
        p[_P_AIR_S] = th["max_airborne_s"]
        p[_P_NEAR] = 1e-3 * th["airborne_clearance_mm"]
        p[_P_FLOOR_Z] = vm.floor_z
        p[_P_STILL_V] = contact["still_speed_m_s"]
        p[_P_STILL_N] = max(1, round(contact["still_min_s"] * rate_hz))
        p[_P_B0 : _P_B2 + 1] = bq / aq[0]
        p[_P_A1 : _P_A2 + 1] = aq[1:] / aq[0]
        self.params = p
        for arr in (self.bone_f, self.bone_i, self.eff, self.foot, self.params):
            arr.flags.writeable = False


class Checker:
    """One MjData and the causal state; used by one thread at a time."""

    def __init__(
        self, vm: ValidationModel, tables: Tables, rate_hz: float, max_gap_s: float
    ) -> None:
        self.vm, self.t = vm, tables
        n_bones = len(vm.skeleton.bone_names)
        self.model = vm.model
        self.data = mujoco.MjData(vm.model)
        # Views into MjData's buffers, taken once (an attribute read builds a view).
        self.qpos = self.data.qpos
        self.xpos = self.data.xpos
        self.site_xpos = self.data.site_xpos
        # Contacts copied into contiguous buffers (MuJoCo's fields are strided views,
        # one mjContact apart): one kernel specialisation, grown when needed.
        self.cdist = np.zeros(64)
        self.cgeom = np.zeros((64, 2), dtype=np.int32)
        self.origins = np.zeros((n_bones, 3))
        self.aims = np.zeros((n_bones, 3))
        self.prev = np.zeros((1 + tables.eff.shape[0], 3))
        self.filt = np.zeros((tables.foot.shape[0], 3, 3))
        self.slow_run = np.zeros(tables.foot.shape[0])
        self.airborne = np.zeros(1)
        self.values = np.zeros(N_CHECKS)
        self.bone_bits = np.zeros(n_bones, dtype=np.uint8)
        self.rate_hz = rate_hz
        self.max_gap_frames = max(1, math.floor(max_gap_s * rate_hz))
        self.max_gap_ns = int(max_gap_s * 1e9)
        self.has_prev = False
        self.prev_id = 0
        self.prev_t_ns = 0

    def reset(self) -> None:
        """Forget the history (speed, support)."""
        self.has_prev = False

    def check(
        self,
        frame_id: int,
        t_ns: int,
        root_pos: F64Array,
        wfb: F64Array,
        pfb: F64Array,
        joints: F64Array,
        lengths: F64Array,
    ) -> int:
        """Check one frame; values in ``self.values``, bone bits in ``self.bone_bits``.

        Returns:
            The frame bits (8-15).
        """
        t = self.t
        dt = t_ns - self.prev_t_ns
        if frame_id >= 0 and self.prev_id >= 0:
            gap = frame_id - self.prev_id
        else:  # an unnumbered source (frame_id -1): frames counted from receive time
            gap = max(1, round(dt * self.rate_hz * 1e-9))
        recent = self.has_prev and 0 < gap <= self.max_gap_frames
        dt_frames = gap if recent and 0 <= dt <= self.max_gap_ns else 0
        _write_qpos(
            self.qpos, root_pos, wfb, pfb, t.root, t.root_adr, t.ball_adr, t.ball_bones
        )
        m, d = self.model, self.data
        mujoco.mj_kinematics(m, d)
        mujoco.mj_collision(m, d)
        ncon = d.ncon
        if ncon:
            if ncon > self.cdist.shape[0]:  # rare: grow (allocates)
                self.cdist = np.zeros(2 * ncon)
                self.cgeom = np.zeros((2 * ncon, 2), dtype=np.int32)
            contact = d.contact
            self.cdist[:ncon] = contact.dist
            self.cgeom[:ncon] = contact.geom
        flags: int = _check_frame(
            root_pos,
            wfb,
            pfb,
            joints,
            lengths,
            self.xpos,
            self.site_xpos,
            self.cdist,
            self.cgeom,
            ncon,
            t.bone_f,
            t.bone_i,
            t.fit_j,
            t.fit_p,
            t.eff,
            t.foot,
            t.foot_r,
            t.geom_bone,
            t.floor_geom,
            t.params,
            dt_frames,
            self.origins,
            self.aims,
            self.prev,
            self.filt,
            self.slow_run,
            self.airborne,
            self.values,
            self.bone_bits,
        )
        self.has_prev = True
        self.prev_id = frame_id
        self.prev_t_ns = t_ns
        return flags
