"""The numpy version of :meth:`Retargeter.apply` (the compiled kernel replaced it): the
tests' oracle, kept here, beside the tests, rather than in the package."""

from __future__ import annotations

import numpy as np

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.kernel import FLAG_HELD
from retargetd.daemon.body.solve import BodyPose
from retargetd.daemon.retarget.kernel import FLAG_SOURCE_HELD
from retargetd.daemon.retarget.retarget import Retargeter, TargetPose
from retargetd.protocols.frames import F64Array

_IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


def _quat_product_tensor(conj_left: bool) -> F64Array:
    """(4, 4, 4) ``T`` with ``(p ⊗ q)_i = Σ T_ijk p_j q_k`` (``p̄ ⊗ q`` if asked)."""
    t = np.zeros((4, 4, 4))
    # Hamilton: w = pw qw - pv.qv, v = pw qv + qw pv + pv x qv.
    t[0, 0, 0] = 1.0
    for a in range(3):
        t[0, a + 1, a + 1] = -1.0
        t[a + 1, 0, a + 1] = 1.0
        t[a + 1, a + 1, 0] = 1.0
    for a, b, c in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):  # e_a x e_b = e_c
        t[c + 1, a + 1, b + 1] = 1.0
        t[c + 1, b + 1, a + 1] = -1.0
    if conj_left:
        t[:, 1:, :] *= -1.0
    t.flags.writeable = False
    return t


_MUL = _quat_product_tensor(False)

_CONJ_MUL = _quat_product_tensor(True)


class _ReferenceScratch:
    """Buffers of :func:`_reference_apply` (built once per retargeter)."""

    def __init__(self, rt: Retargeter) -> None:
        n, m, ni = len(rt.bone_names), len(rt._src), len(rt._i_t)
        self.w = np.zeros((m, 4))
        self.em = np.zeros((m, 4))
        self.e = np.tile(_IDENTITY, (n + 1, 1))  # row n: identity, Hips' "parent"
        self.e_n = self.e[:n]
        self.ep = np.zeros((n, 4))
        self.q0 = np.zeros((ni, 4))
        self.q1 = np.zeros((ni, 4))
        self.qi = np.zeros((ni, 4))
        self.tmp4 = np.zeros((ni, 4))
        self.dot = np.zeros(ni)
        self.theta = np.zeros(ni)
        self.sin = np.zeros(ni)
        self.tmp = np.zeros(ni)
        self.w0 = np.zeros(ni)
        self.w1 = np.zeros(ni)
        self.mask = np.zeros(ni, dtype=bool)
        self.sgn = np.zeros(ni)
        self.sgn_col = self.sgn[:, None]
        self.norm_col = self.tmp[:, None]
        self.w0_col = self.w0[:, None]
        self.w1_col = self.w1[:, None]
        self.ec = np.zeros((len(rt._c_t), 4))
        self.fsrc = np.zeros(m, dtype=np.uint8)


def _reference_apply(
    rt: Retargeter, pose: BodyPose, out: TargetPose, s: _ReferenceScratch
) -> TargetPose:
    """:meth:`Retargeter.apply` in vectorized numpy (~41 calls): the test oracle of
    the compiled kernel and the baseline of ``bench/bench_retarget.py``; not hot."""
    e = s.e
    # E_h = W_b(t) ⊗ K_h for the mapped bones.
    np.take(pose.world_from_bone_quat, rt._src, axis=0, out=s.w)
    np.einsum("ijk,nj,nk->ni", _MUL, s.w, rt._k, out=s.em)
    e[rt._mapped_t] = s.em
    if rt._i_t.size:
        _reference_slerp_filled(rt, s)
        e[rt._i_t] = s.qi
    if rt._c_t.size:
        np.take(e, rt._c_s, axis=0, out=s.ec)
        e[rt._c_t] = s.ec
    # L_h = Ē_parent ⊗ E_h (Hips' parent row is identity); G_h = E_h ⊗ T_h.
    np.take(e, rt._parent, axis=0, out=s.ep)
    np.einsum("ijk,nj,nk->ni", _CONJ_MUL, s.ep, s.e_n,
              out=out.rest_from_bone_quat)  # fmt: skip
    np.einsum("ijk,nj,nk->ni", _MUL, s.e_n, rt._rest_t,
              out=out.world_from_bone_quat)  # fmt: skip
    np.subtract(pose.root_pos, rt._root_rest, out=out.root_pos)
    np.multiply(out.root_pos, rt.root_scale, out=out.root_pos)
    np.add(out.root_pos, out.rest_offsets[0], out=out.hips_pos)
    np.copyto(out.flags, rt._base_flags)
    np.take(pose.bone_flags, rt._src, out=s.fsrc)
    np.bitwise_and(s.fsrc, FLAG_HELD, out=s.fsrc)
    np.minimum(s.fsrc, 1, out=s.fsrc)
    np.multiply(s.fsrc, FLAG_SOURCE_HELD, out=s.fsrc)
    out.flags[rt._mapped_t] = s.fsrc
    return out


def _reference_slerp_filled(rt: Retargeter, s: _ReferenceScratch) -> None:
    """``s.qi = slerp(E[a], E[d], u)`` per filled bone, short arc, into buffers."""
    q0, q1 = s.q0, s.q1
    np.take(s.e, rt._i_a, axis=0, out=q0)
    np.take(s.e, rt._i_d, axis=0, out=q1)
    np.einsum("ij,ij->i", q0, q1, out=s.dot)
    np.copysign(1.0, s.dot, out=s.sgn)  # short arc: q1 -> -q1 if dot < 0
    np.multiply(q1, s.sgn_col, out=q1)
    np.abs(s.dot, out=s.dot)
    np.minimum(s.dot, 1.0, out=s.dot)
    np.arccos(s.dot, out=s.theta)  # half the angle between the ends
    np.sin(s.theta, out=s.sin)
    np.greater(s.theta, 0.5 * rot.SLERP_LINEAR_BELOW_RAD, out=s.mask)
    np.copyto(s.w0, rt._i_1mu)
    np.copyto(s.w1, rt._i_u)
    np.multiply(rt._i_1mu, s.theta, out=s.tmp)
    np.sin(s.tmp, out=s.tmp)
    np.divide(s.tmp, s.sin, out=s.w0, where=s.mask)
    np.multiply(rt._i_u, s.theta, out=s.tmp)
    np.sin(s.tmp, out=s.tmp)
    np.divide(s.tmp, s.sin, out=s.w1, where=s.mask)
    np.multiply(q0, s.w0_col, out=s.qi)
    np.multiply(q1, s.w1_col, out=s.tmp4)
    np.add(s.qi, s.tmp4, out=s.qi)
    np.einsum("ij,ij->i", s.qi, s.qi, out=s.tmp)
    np.sqrt(s.tmp, out=s.tmp)
    np.divide(s.qi, s.norm_col, out=s.qi)
