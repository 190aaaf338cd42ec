"""The compiled per-frame retarget kernel (numba): ``Retargeter.apply`` in one call.

``retargetd.daemon.retarget.retarget`` flattens a rig + calibration + target into a
small "program" once (:class:`~.retarget.Retargeter`); the kernel walks it
once per frame with scalar loops and no allocation (notation: the ``retarget`` module
docstring):

1. mapped bones: ``E_h = W_b(t) ⊗ K_h``;
2. every bone in order (parents first): a filled bone takes the slerp of ``E``
   between its mapped ancestor and mapped chain descendant (both done in 1), or copies
   an ancestor's ``E`` (done before it); then ``L_h = Ē_parent ⊗ E_h`` (Hips:
   ``E``), ``G_h = E_h ⊗ T_h`` and its flags;
3. root and hips positions.

Why numba: the vectorized numpy version took ~41 numpy calls per frame (~72 µs
median on the menache rig); the compiled walk is one call (``bench/bench_retarget.py``).
The numpy version stays as the test oracle (``tests/helpers/retarget_oracle.py``).
"""

from __future__ import annotations

import math

import numpy as np

from retargetd.daemon.body.kernel import FLAG_HELD
from retargetd.daemon.compiled import kernel, qmul

#: Bit 0: filled by interpolation along the chain (the rig does not solve it).
FLAG_FILLED = 1
#: Bit 1: the rig bone it follows was held this frame (solve ``FLAG_HELD``).
FLAG_SOURCE_HELD = 2

#: ``prog[h, 0]``: how bone ``h`` gets its world delta ``E_h``.
KIND_MAPPED = 0  #: ``W[prog[h, 1]] ⊗ K_h`` (``prog[h, 1]``: the rig bone)
KIND_SLERP = 1  #: slerp of ``E[prog[h, 1]]`` (ancestor) -> ``E[prog[h, 2]]``
KIND_COPY = 2  #: ``E[prog[h, 1]]`` (an ancestor, mapped or slerped)

#: ``cst`` columns per target bone.
C_K = 0  #: 0:4 ``K_h`` (mapped bones)
C_REST = 4  #: 4:8 ``T_h``, the target's rest world rotation
C_U = 8  #: slerp parameter ``u`` (slerped bones)
C_1MU = 9  #: ``1 - u``
N_CST = 10
#: ``params``: calibrated root (3), root scale, half the slerp linear threshold.
P_ROOT = 0
P_SCALE = 3
P_HALF_LINEAR = 4
N_PARAMS = 5


@kernel
def retarget_one(
    in_wfb: np.ndarray,  # (B, 4) rig world_from_bone (w x y z)
    in_root: np.ndarray,  # (3,) rig root position, metres world
    in_flags: np.ndarray,  # (B,) uint8 solve flags
    prog: np.ndarray,  # (N, 4) int64: kind, i0, i1, parent (-1: Hips)
    cst: np.ndarray,  # (N, N_CST) float64, see C_*
    params: np.ndarray,  # (N_PARAMS,) float64, see P_*
    e: np.ndarray,  # (N, 4) scratch: E_h
    out_pfb: np.ndarray,  # (N, 4) L_h
    out_wfb: np.ndarray,  # (N, 4) G_h
    out_root: np.ndarray,  # (3,)
    out_hips: np.ndarray,  # (3,)
    rest_offsets: np.ndarray,  # (N, 3) the target's (row 0: the Hips' offset)
    out_flags: np.ndarray,  # (N,) uint8
) -> None:
    n = prog.shape[0]
    # 1. E_h = W_b ⊗ K_h for the mapped bones.
    for h in range(n):
        if prog[h, 0] != KIND_MAPPED:
            continue
        b = prog[h, 1]
        e[h, 0], e[h, 1], e[h, 2], e[h, 3] = qmul(
            in_wfb[b, 0], in_wfb[b, 1], in_wfb[b, 2], in_wfb[b, 3],
            cst[h, 0], cst[h, 1], cst[h, 2], cst[h, 3],
        )  # fmt: skip
        out_flags[h] = FLAG_SOURCE_HELD if in_flags[b] & FLAG_HELD else 0
    # 2. Filled bones, then L_h = Ē_parent ⊗ E_h and G_h = E_h ⊗ T_h, parents first.
    half_linear = params[P_HALF_LINEAR]
    for h in range(n):
        kind = prog[h, 0]
        if kind == KIND_SLERP:  # short arc; normalized lerp when the ends are close
            a, d = prog[h, 1], prog[h, 2]
            q0w, q0x, q0y, q0z = e[a, 0], e[a, 1], e[a, 2], e[a, 3]
            q1w, q1x, q1y, q1z = e[d, 0], e[d, 1], e[d, 2], e[d, 3]
            dot = q0w * q1w + q0x * q1x + q0y * q1y + q0z * q1z
            sgn = math.copysign(1.0, dot)
            q1w, q1x, q1y, q1z = q1w * sgn, q1x * sgn, q1y * sgn, q1z * sgn
            dot = abs(dot)
            if dot > 1.0:  # (NaN stays NaN, as np.minimum)
                dot = 1.0
            theta = math.acos(dot)  # half the angle between the ends
            u, w0 = cst[h, C_U], cst[h, C_1MU]
            w1 = u
            if theta > half_linear:
                s = math.sin(theta)
                w0 = math.sin(w0 * theta) / s
                w1 = math.sin(u * theta) / s
            qw = q0w * w0 + q1w * w1
            qx = q0x * w0 + q1x * w1
            qy = q0y * w0 + q1y * w1
            qz = q0z * w0 + q1z * w1
            norm = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
            e[h, 0] = qw / norm
            e[h, 1] = qx / norm
            e[h, 2] = qy / norm
            e[h, 3] = qz / norm
            out_flags[h] = FLAG_FILLED
        elif kind == KIND_COPY:
            s_ = prog[h, 1]
            for j in range(4):
                e[h, j] = e[s_, j]
            out_flags[h] = FLAG_FILLED
        bw, bx, by, bz = e[h, 0], e[h, 1], e[h, 2], e[h, 3]
        p = prog[h, 3]
        if p < 0:
            for j in range(4):
                out_pfb[h, j] = e[h, j]
        else:
            out_pfb[h, 0], out_pfb[h, 1], out_pfb[h, 2], out_pfb[h, 3] = qmul(
                e[p, 0], -e[p, 1], -e[p, 2], -e[p, 3], bw, bx, by, bz
            )
        out_wfb[h, 0], out_wfb[h, 1], out_wfb[h, 2], out_wfb[h, 3] = qmul(
            bw, bx, by, bz,
            cst[h, C_REST], cst[h, C_REST + 1], cst[h, C_REST + 2], cst[h, C_REST + 3],
        )  # fmt: skip
    # 3. Root: the scaled displacement since calibration; Hips above it.
    scale = params[P_SCALE]
    for c in range(3):
        r = (in_root[c] - params[P_ROOT + c]) * scale
        out_root[c] = r
        out_hips[c] = r + rest_offsets[0, c]
