"""The compiled per-frame body-solve kernel (numba): one implementation for live
one-frame solves and offline batches.

The rig is flattened by ``solve_body`` into index arrays (a small "program"); the
kernel walks it once per frame with no allocation:

1. gather the rig's markers from the frame's columns (missing column or non-finite =
   occluded);
2. rebuild occluded markers of a rigid segment from its visible ones (>= 3) by a
   Kabsch fit of the calibrated layout;
3. derived points in dependency order: ``line`` p = a + u (b - a); ``rigid``
   p = a + R_abc @ offset with the three-point frame x = unit(b - a),
   z = unit(x x (c - a)), y = z x x;
4. bones: +Y = unit(aim - origin), +X = the up reference made orthogonal to Y,
   +Z = X x Y; a bone whose up reference lies within ``bone_up_min`` of its axis
   keeps the new +Y and takes its roll from the previous frame relative to its
   parent (the parent's axes now, times the last good parent-relative rotation,
   turned by the least rotation onto the new +Y), flagged ``FLAG_PARTIAL``; a bone
   whose points are missing holds its last good rotation and is flagged held;
5. parent-relative rotations, and the same relative to the calibration pose; joint
   centres; root.

Why numba: a vectorized numpy version costs ~1-2 us per numpy call and a rig needs
~150 of them per frame; the compiled walk is one call (figures in bench/).

The kernel reads three records (:class:`BodyPlan`: the rig program, read-only;
:class:`BodyState`: scratch and what carries over between frames; :class:`BodyOut`:
this frame's outputs), built once per stream by ``body.solve.BodySolver`` as views of a
few flat buffers, which is how the live call passes them (:func:`solve_one`). Its flag
bits are the pose stream's bone flags (``protocols.pose_stream.BONE_*``), imported, not
copied.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from retargetd.daemon.compiled import (
    horn_fit,
    kernel,
    qmul,
    quat_conj_mul_into,
    quat_mul_into,
)
from retargetd.protocols import pose_stream

OP_LINE = 0
OP_RIGID = 1

FLAG_HELD = pose_stream.BONE_HELD  #: rotation held from the last good frame
FLAG_REBUILT = pose_stream.BONE_REBUILT  #: a defining marker rebuilt from its segment
#: some defining marker not seen (quality < 1), or, with quality 1, the up reference
#: too near the bone's axis: the roll taken from the previous frame
FLAG_PARTIAL = pose_stream.BONE_PARTIAL
FLAG_NEVER = pose_stream.BONE_NEVER  #: no good value yet: the rest rotation is sent


class BodyPlan(NamedTuple):
    """The rig compiled for one marker layout (read-only arrays; int64 indices)."""

    marker_cols: np.ndarray  # (Mr,) stream column per rig marker, -1 absent
    op_kind: np.ndarray  # (P,) OP_LINE / OP_RIGID
    op_idx: np.ndarray  # (P, 3) indices into pts
    op_u: np.ndarray  # (P,) float64 line parameter
    op_off: np.ndarray  # (P, 3) float64 local offset (rigid)
    seg_ptr: np.ndarray  # (S+1,)
    seg_idx: np.ndarray  # (K,) marker indices
    seg_layout: np.ndarray  # (K, 3) float64 calibrated layout
    seg_w: np.ndarray  # (K,) float64 fit weights (1)
    bone_pts: np.ndarray  # (B, 4) origin, aim, up1, up2 (-1: single point)
    bone_parent: np.ndarray  # (B,) parents before children
    bone_def_ptr: np.ndarray  # (B+1,)
    bone_def_idx: np.ndarray  # (D,) defining marker indices
    rest_pfb: np.ndarray  # (B, 4) calibrated parent_from_bone (w x y z)
    joint_idx: np.ndarray  # (J,) indices into pts
    root_point: int
    bone_up_min: np.ndarray  # (B,) float64 m: roll from the last frame under this


class BodyState(NamedTuple):
    """Scratch and the state carried between frames (preallocated)."""

    pts: np.ndarray  # (Mr + P, 3)
    seen: np.ndarray  # (Mr + P,) bool
    filled: np.ndarray  # (Mr + P,) bool
    last_pfb: np.ndarray  # (B, 4) last good parent_from_bone (init: rest_pfb)
    have_good: np.ndarray  # (B,) bool, a good value was seen
    prev_wfb: np.ndarray  # (B, 4) previous frame's output; w = NaN: none
    tmp4: np.ndarray  # (4,)
    n44: np.ndarray  # (4, 4)
    v44: np.ndarray  # (4, 4)
    cen: np.ndarray  # (6,) fit centroids
    last_root: np.ndarray  # (3,) last good root position (init: calibrated rest)
    counts: np.ndarray  # (1,) int64 out: rig markers occluded this frame


class BodyOut(NamedTuple):
    """One frame's outputs (or, for :func:`solve_many`, a take's: a leading T)."""

    joints: np.ndarray  # (J, 3)
    wfb: np.ndarray  # (B, 4) world_from_bone
    pfb: np.ndarray  # (B, 4) parent_from_bone (the root's parent: the world)
    rfb: np.ndarray  # (B, 4) rest_from_bone: relative to the calibration pose
    root: np.ndarray  # (3,)
    quality: np.ndarray  # (B,) float32
    flags: np.ndarray  # (B,) uint8


@kernel
def _quat_from_axes(
    xx: float, xy: float, xz: float,
    yx: float, yy: float, yz: float,
    zx: float, zy: float, zz: float,
    out: np.ndarray,
) -> None:  # fmt: skip
    # Rotation matrix columns are the bone axes X, Y, Z in world coordinates:
    # m = [[xx, yx, zx], [xy, yy, zy], [xz, yz, zz]]. Trace method, branch on the
    # largest diagonal (Shepperd) for accuracy near 180 degrees.
    m00, m01, m02 = xx, yx, zx
    m10, m11, m12 = xy, yy, zy
    m20, m21, m22 = xz, yz, zz
    tr = m00 + m11 + m22
    if tr > 0.0:
        s = math.sqrt(tr + 1.0) * 2.0
        w = 0.25 * s
        x = (m21 - m12) / s
        y = (m02 - m20) / s
        z = (m10 - m01) / s
    elif m00 > m11 and m00 > m22:
        s = math.sqrt(1.0 + m00 - m11 - m22) * 2.0
        w = (m21 - m12) / s
        x = 0.25 * s
        y = (m01 + m10) / s
        z = (m02 + m20) / s
    elif m11 > m22:
        s = math.sqrt(1.0 + m11 - m00 - m22) * 2.0
        w = (m02 - m20) / s
        x = (m01 + m10) / s
        y = 0.25 * s
        z = (m12 + m21) / s
    else:
        s = math.sqrt(1.0 + m22 - m00 - m11) * 2.0
        w = (m10 - m01) / s
        x = (m02 + m20) / s
        y = (m12 + m21) / s
        z = 0.25 * s
    n = math.sqrt(w * w + x * x + y * y + z * z)
    out[0] = w / n
    out[1] = x / n
    out[2] = y / n
    out[3] = z / n


@kernel
def _kabsch_fill(
    pts: np.ndarray,
    seen: np.ndarray,
    idx: np.ndarray,
    layout: np.ndarray,
    weights: np.ndarray,
    filled: np.ndarray,
    n44: np.ndarray,
    v44: np.ndarray,
    q4: np.ndarray,
    cen: np.ndarray,
) -> None:
    # Fit the calibrated layout of one rigid segment to its visible markers (the
    # shared Horn fit) and put the missing ones where the fit says. Needs >= 3
    # visible markers not on one line.
    k = idx.shape[0]
    n = 0
    for i in range(k):
        if seen[idx[i]]:
            n += 1
    if n < 3 or n == k:
        return
    if horn_fit(layout, pts, idx, seen, weights, n44, v44, q4, cen) == 0:
        return
    clx, cly, clz, ccx, ccy, ccz = cen[0], cen[1], cen[2], cen[3], cen[4], cen[5]
    r00, r01, r02 = n44[0, 0], n44[0, 1], n44[0, 2]
    r10, r11, r12 = n44[1, 0], n44[1, 1], n44[1, 2]
    r20, r21, r22 = n44[2, 0], n44[2, 1], n44[2, 2]
    for i in range(k):
        m = idx[i]
        if not seen[m]:
            lx, ly, lz = layout[i, 0] - clx, layout[i, 1] - cly, layout[i, 2] - clz
            pts[m, 0] = ccx + r00 * lx + r01 * ly + r02 * lz
            pts[m, 1] = ccy + r10 * lx + r11 * ly + r12 * lz
            pts[m, 2] = ccz + r20 * lx + r21 * ly + r22 * lz
            filled[m] = True


@kernel
def solve_one_nt(
    markers: np.ndarray, plan: BodyPlan, st: BodyState, out: BodyOut
) -> int:
    """Solve one frame. ``markers``: (M_stream, 3) world metres, NaN = occluded.
    Writes ``out``; returns the number of bones held."""
    marker_cols, op_kind, op_idx, op_u = (
        plan.marker_cols,
        plan.op_kind,
        plan.op_idx,
        plan.op_u,
    )
    op_off, seg_ptr, seg_idx, seg_layout = (
        plan.op_off,
        plan.seg_ptr,
        plan.seg_idx,
        plan.seg_layout,
    )
    bone_pts, bone_parent, bone_def_ptr, bone_def_idx = (
        plan.bone_pts,
        plan.bone_parent,
        plan.bone_def_ptr,
        plan.bone_def_idx,
    )
    rest_pfb, joint_idx, root_point = plan.rest_pfb, plan.joint_idx, plan.root_point
    pts, seen, filled, last_pfb = st.pts, st.seen, st.filled, st.last_pfb
    have_good, prev_wfb, tmp4, n44, v44 = (
        st.have_good,
        st.prev_wfb,
        st.tmp4,
        st.n44,
        st.v44,
    )
    last_root = st.last_root
    out_joints, out_wfb, out_pfb = out.joints, out.wfb, out.pfb
    out_root, out_quality, out_flags = out.root, out.quality, out.flags
    n_markers = marker_cols.shape[0]
    nan = math.nan
    # 1. gather
    n_occluded = 0
    for i in range(n_markers):
        col = marker_cols[i]
        ok = False
        if col >= 0:
            x = markers[col, 0]
            y = markers[col, 1]
            z = markers[col, 2]
            if math.isfinite(x) and math.isfinite(y) and math.isfinite(z):
                ok = True
                pts[i, 0] = x
                pts[i, 1] = y
                pts[i, 2] = z
        if not ok:
            pts[i, 0] = nan
            pts[i, 1] = nan
            pts[i, 2] = nan
            n_occluded += 1
        seen[i] = ok
        filled[i] = False
    st.counts[0] = n_occluded
    # 2. rebuild occluded markers from their rigid segment
    for s in range(seg_ptr.shape[0] - 1):
        a, b = seg_ptr[s], seg_ptr[s + 1]
        _kabsch_fill(
            pts, seen, seg_idx[a:b], seg_layout[a:b], plan.seg_w[a:b], filled,
            n44, v44, tmp4, st.cen,
        )  # fmt: skip
    # 3. derived points (NaN propagates through the arithmetic)
    for p in range(op_kind.shape[0]):
        dst = n_markers + p
        ia, ib, ic = op_idx[p, 0], op_idx[p, 1], op_idx[p, 2]
        if op_kind[p] == 0:
            u = op_u[p]
            for j in range(3):
                pts[dst, j] = pts[ia, j] + u * (pts[ib, j] - pts[ia, j])
        else:
            ax, ay, az = pts[ia, 0], pts[ia, 1], pts[ia, 2]
            xx, xy, xz = pts[ib, 0] - ax, pts[ib, 1] - ay, pts[ib, 2] - az
            n = math.sqrt(xx * xx + xy * xy + xz * xz)
            xx, xy, xz = xx / n, xy / n, xz / n
            cx, cy, cz = pts[ic, 0] - ax, pts[ic, 1] - ay, pts[ic, 2] - az
            zx = xy * cz - xz * cy
            zy = xz * cx - xx * cz
            zz = xx * cy - xy * cx
            n = math.sqrt(zx * zx + zy * zy + zz * zz)
            zx, zy, zz = zx / n, zy / n, zz / n
            yx = zy * xz - zz * xy
            yy = zz * xx - zx * xz
            yz = zx * xy - zy * xx
            ox, oy, oz = op_off[p, 0], op_off[p, 1], op_off[p, 2]
            pts[dst, 0] = ax + xx * ox + yx * oy + zx * oz
            pts[dst, 1] = ay + xy * ox + yy * oy + zy * oz
            pts[dst, 2] = az + xz * ox + yz * oy + zz * oz
    # 4. bones
    n_held = 0
    for b in range(bone_pts.shape[0]):
        io, ia, iu1, iu2 = (
            bone_pts[b, 0],
            bone_pts[b, 1],
            bone_pts[b, 2],
            bone_pts[b, 3],
        )
        flags = 0
        d0, d1 = bone_def_ptr[b], bone_def_ptr[b + 1]
        n_seen = 0
        for k in range(d0, d1):
            m = bone_def_idx[k]
            if seen[m]:
                n_seen += 1
            elif filled[m]:
                flags |= FLAG_REBUILT
        out_quality[b] = n_seen / max(d1 - d0, 1)
        if n_seen < d1 - d0:
            flags |= FLAG_PARTIAL
        yx = pts[ia, 0] - pts[io, 0]
        yy = pts[ia, 1] - pts[io, 1]
        yz = pts[ia, 2] - pts[io, 2]
        ny = math.sqrt(yx * yx + yy * yy + yz * yz)
        if iu2 >= 0:
            ux = pts[iu2, 0] - pts[iu1, 0]
            uy = pts[iu2, 1] - pts[iu1, 1]
            uz = pts[iu2, 2] - pts[iu1, 2]
        else:
            ux = pts[iu1, 0] - pts[io, 0]
            uy = pts[iu1, 1] - pts[io, 1]
            uz = pts[iu1, 2] - pts[io, 2]
        good = math.isfinite(ny) and ny > 1e-9
        near = False
        if good:
            yx, yy, yz = yx / ny, yy / ny, yz / ny
            dot = ux * yx + uy * yy + uz * yz
            xx, xy, xz = ux - dot * yx, uy - dot * yy, uz - dot * yz
            nx = math.sqrt(xx * xx + xy * xy + xz * xz)
            nu = math.sqrt(ux * ux + uy * uy + uz * uz)
            if not math.isfinite(nx):
                good = False
            elif nx < plan.bone_up_min[b] or not (nx > 1e-2 * nu and nx > 1e-9):
                # The up reference is seen but too near the axis (within the rig's
                # up_min_mm, or closer than ~0.6 deg): its roll is noise.
                good = False
                near = True
        par = bone_parent[b]
        if near:
            # Keep the new axis; the roll is the previous frame's relative to the
            # parent (its last good parent_from_bone, the calibrated one before any;
            # a root's: its last world rotation), carried by the parent's motion and
            # turned by the least rotation that takes its +Y onto the new +Y. (The
            # previous frame's world axes turned the same way would drift: a least
            # rotation never turns about the axis, so a foot held that way for 0.4 s
            # of walking missed the shank's 14 deg of axial turn and jumped by it
            # when the heel came back.)
            if par < 0:
                for j in range(4):
                    tmp4[j] = last_pfb[b, j]
            else:
                quat_mul_into(out_wfb[par], last_pfb[b], tmp4)
            rw, rx, ry, rz = tmp4[0], tmp4[1], tmp4[2], tmp4[3]
            # the reference's +Y: the middle column of its rotation matrix
            px = 2.0 * (rx * ry - rw * rz)
            py = 1.0 - 2.0 * (rx * rx + rz * rz)
            pz = 2.0 * (ry * rz + rw * rx)
            # swing (1 + p.y, p x y), normalized, is the least rotation p -> y
            sw = 1.0 + px * yx + py * yy + pz * yz
            sx = py * yz - pz * yy
            sy = pz * yx - px * yz
            sz = px * yy - py * yx
            ns = math.sqrt(sw * sw + sx * sx + sy * sy + sz * sz)
            if sw > 1e-6 and math.isfinite(ns):
                sw, sx, sy, sz = sw / ns, sx / ns, sy / ns, sz / ns
                ow, ox, oy, oz = qmul(sw, sx, sy, sz, rw, rx, ry, rz)
                no = math.sqrt(ow * ow + ox * ox + oy * oy + oz * oz)
                out_wfb[b, 0] = ow / no
                out_wfb[b, 1] = ox / no
                out_wfb[b, 2] = oy / no
                out_wfb[b, 3] = oz / no
                flags |= FLAG_PARTIAL
                if par < 0:
                    for j in range(4):
                        last_pfb[b, j] = out_wfb[b, j]
                else:
                    quat_conj_mul_into(out_wfb[par], out_wfb[b], last_pfb[b])
                have_good[b] = True
            else:  # the axis turned half a turn in one frame: no roll to carry
                near = False
        if good:
            xx, xy, xz = xx / nx, xy / nx, xz / nx
            zx = xy * yz - xz * yy
            zy = xz * yx - xx * yz
            zz = xx * yy - xy * yx
            _quat_from_axes(xx, xy, xz, yx, yy, yz, zx, zy, zz, out_wfb[b])
            if par < 0:
                for j in range(4):
                    last_pfb[b, j] = out_wfb[b, j]
            else:
                quat_conj_mul_into(out_wfb[par], out_wfb[b], last_pfb[b])
            have_good[b] = True
        elif not near:
            # Too little data: hold the last good parent-relative rotation (the
            # calibrated rest one before any), so the bone follows its parent.
            flags |= FLAG_HELD
            n_held += 1
            if not have_good[b]:
                flags |= FLAG_NEVER
            if par < 0:
                for j in range(4):
                    out_wfb[b, j] = last_pfb[b, j]
            else:
                quat_mul_into(out_wfb[par], last_pfb[b], out_wfb[b])
        # Keep the sign continuous with the previous frame's (engines blend).
        if math.isfinite(prev_wfb[b, 0]):
            d = (
                out_wfb[b, 0] * prev_wfb[b, 0]
                + out_wfb[b, 1] * prev_wfb[b, 1]
                + out_wfb[b, 2] * prev_wfb[b, 2]
                + out_wfb[b, 3] * prev_wfb[b, 3]
            )
            if d < 0.0:
                for j in range(4):
                    out_wfb[b, j] = -out_wfb[b, j]
        for j in range(4):
            prev_wfb[b, j] = out_wfb[b, j]
        out_flags[b] = flags
    # 5. parent_from_bone = conj(world_from_parent) * world_from_bone (the root's
    #    parent is the world), and relative to the calibration pose
    #    rest_from_bone = conj(rest_parent_from_bone) * parent_from_bone.
    out_rfb = out.rfb
    for b in range(bone_pts.shape[0]):
        par = bone_parent[b]
        if par < 0:
            for j in range(4):
                out_pfb[b, j] = out_wfb[b, j]
        else:
            quat_conj_mul_into(out_wfb[par], out_wfb[b], out_pfb[b])
        quat_conj_mul_into(rest_pfb[b], out_pfb[b], out_rfb[b])
        # The rotation from rest is near identity in normal use: keep w >= 0 so that
        # it reads as the short way round.
        if out_rfb[b, 0] < 0.0:
            for j in range(4):
                out_rfb[b, j] = -out_rfb[b, j]
    for j in range(joint_idx.shape[0]):
        for c in range(3):
            out_joints[j, c] = pts[joint_idx[j], c]
    # The root position holds its last good value when its point is missing.
    rx, ry, rz = pts[root_point, 0], pts[root_point, 1], pts[root_point, 2]
    if math.isfinite(rx) and math.isfinite(ry) and math.isfinite(rz):
        last_root[0] = rx
        last_root[1] = ry
        last_root[2] = rz
    for c in range(3):
        out_root[c] = last_root[c]
    return n_held


# -- The packed form: a handful of flat buffers instead of 35 arrays. -------------
#
# numba's dispatcher types and unboxes every array of an argument, ~60-100 ns each, so
# passing the plan, state and output as 35 arrays cost ~2 us a call, half of a frame's
# solve (bench/bench_solve.py). The live path passes them as nine flat buffers instead;
# the functions below are the one definition of how the fields tile those buffers,
# used by the kernel and, from Python, by ``BodySolver`` to fill them (the NamedTuples
# Python holds are views of the same memory).
#
# ``plan_i`` starts with the sizes header ``PLAN_HEADER`` (Mr, P, S, K, B, D, J,
# root_point); every other size follows from it.

PLAN_HEADER = 8


@kernel
def plan_sizes(h: np.ndarray) -> tuple[int, int]:
    """Lengths of the int64 and float64 plan buffers for the sizes header ``h``."""
    mr, p, s, k, b, d, j = h[0], h[1], h[2], h[3], h[4], h[5], h[6]
    n_i = PLAN_HEADER + mr + p + 3 * p + (s + 1) + k + 4 * b + b + (b + 1) + d + j
    n_f = p + 3 * p + 3 * k + k + 4 * b + b
    return n_i, n_f


@kernel
def plan_views(pi: np.ndarray, pf: np.ndarray) -> BodyPlan:
    """The :class:`BodyPlan` fields as views of the packed buffers."""
    mr, p, s, k, b, d, j = pi[0], pi[1], pi[2], pi[3], pi[4], pi[5], pi[6]
    o = PLAN_HEADER
    marker_cols = pi[o : o + mr]
    o += mr
    op_kind = pi[o : o + p]
    o += p
    op_idx = pi[o : o + 3 * p].reshape((p, 3))
    o += 3 * p
    seg_ptr = pi[o : o + s + 1]
    o += s + 1
    seg_idx = pi[o : o + k]
    o += k
    bone_pts = pi[o : o + 4 * b].reshape((b, 4))
    o += 4 * b
    bone_parent = pi[o : o + b]
    o += b
    bone_def_ptr = pi[o : o + b + 1]
    o += b + 1
    bone_def_idx = pi[o : o + d]
    o += d
    joint_idx = pi[o : o + j]
    f = 0
    op_u = pf[f : f + p]
    f += p
    op_off = pf[f : f + 3 * p].reshape((p, 3))
    f += 3 * p
    seg_layout = pf[f : f + 3 * k].reshape((k, 3))
    f += 3 * k
    seg_w = pf[f : f + k]
    f += k
    rest_pfb = pf[f : f + 4 * b].reshape((b, 4))
    f += 4 * b
    bone_up_min = pf[f : f + b]
    return BodyPlan(
        marker_cols, op_kind, op_idx, op_u, op_off, seg_ptr, seg_idx, seg_layout,
        seg_w, bone_pts, bone_parent, bone_def_ptr, bone_def_idx, rest_pfb,
        joint_idx, pi[7], bone_up_min,
    )  # fmt: skip


@kernel
def state_sizes(pi: np.ndarray) -> tuple[int, int, int]:
    """Lengths of the float64, bool and int64 state buffers."""
    n_pts, b = pi[0] + pi[1], pi[4]
    return 3 * n_pts + 4 * b + 4 * b + 4 + 16 + 16 + 6 + 3, 2 * n_pts + b, 1


@kernel
def state_views(
    pi: np.ndarray, sf: np.ndarray, sb: np.ndarray, si: np.ndarray
) -> BodyState:
    """The :class:`BodyState` fields as views of the packed buffers."""
    n_pts, b = pi[0] + pi[1], pi[4]
    f = 0
    pts = sf[f : f + 3 * n_pts].reshape((n_pts, 3))
    f += 3 * n_pts
    last_pfb = sf[f : f + 4 * b].reshape((b, 4))
    f += 4 * b
    prev_wfb = sf[f : f + 4 * b].reshape((b, 4))
    f += 4 * b
    tmp4 = sf[f : f + 4]
    f += 4
    n44 = sf[f : f + 16].reshape((4, 4))
    f += 16
    v44 = sf[f : f + 16].reshape((4, 4))
    f += 16
    cen = sf[f : f + 6]
    f += 6
    last_root = sf[f : f + 3]
    return BodyState(
        pts, sb[:n_pts], sb[n_pts : 2 * n_pts], last_pfb, sb[2 * n_pts : 2 * n_pts + b],
        prev_wfb, tmp4, n44, v44, cen, last_root, si[:1],
    )  # fmt: skip


@kernel
def out_size(pi: np.ndarray) -> int:
    """Length of the float64 output buffer (the float32 quality and uint8 flags
    buffers are (B,))."""
    return 3 * pi[6] + 3 * 4 * pi[4] + 3


@kernel
def out_views(
    pi: np.ndarray, of: np.ndarray, oq: np.ndarray, ofl: np.ndarray
) -> BodyOut:
    """The :class:`BodyOut` fields as views of the packed buffers."""
    b, j = pi[4], pi[6]
    f = 0
    joints = of[f : f + 3 * j].reshape((j, 3))
    f += 3 * j
    wfb = of[f : f + 4 * b].reshape((b, 4))
    f += 4 * b
    pfb = of[f : f + 4 * b].reshape((b, 4))
    f += 4 * b
    rfb = of[f : f + 4 * b].reshape((b, 4))
    f += 4 * b
    return BodyOut(joints, wfb, pfb, rfb, of[f : f + 3], oq, ofl)


@kernel
def solve_one(
    markers: np.ndarray,
    pi: np.ndarray, pf: np.ndarray,
    sf: np.ndarray, sb: np.ndarray, si: np.ndarray,
    of: np.ndarray, oq: np.ndarray, ofl: np.ndarray,
) -> int:  # fmt: skip
    """Solve one frame: the plan, state and output packed (see :func:`plan_views`,
    :func:`state_views`, :func:`out_views`). Returns the number of bones held in the
    low 32 bits and of rig markers occluded above them (no numpy read in Python)."""
    held = solve_one_nt(
        markers, plan_views(pi, pf), state_views(pi, sf, sb, si),
        out_views(pi, of, oq, ofl),
    )  # fmt: skip
    return held | (si[0] << 32)


@kernel
def solve_one_t(markers: np.ndarray, plan: tuple, st: tuple, out: tuple) -> int:
    """:func:`solve_one` for outputs that are not views of one buffer (a ``BodyPose``
    built by hand): the fields as plain tuples (numba types a plain tuple in C; a
    NamedTuple argument goes through Python)."""
    held = solve_one_nt(markers, BodyPlan(*plan), BodyState(*st), BodyOut(*out))
    return held | (st[11][0] << 32)


@kernel
def solve_many(markers: np.ndarray, plan_t: tuple, st_t: tuple, out_t: tuple) -> int:
    """Solve a take: ``markers`` (T, M_stream, 3); the output arrays with a leading
    T; plain tuples as :func:`solve_one`. Returns the number of held bone-frames."""
    plan, st, out = BodyPlan(*plan_t), BodyState(*st_t), BodyOut(*out_t)
    held = 0
    for t in range(markers.shape[0]):
        frame = BodyOut(
            out.joints[t], out.wfb[t], out.pfb[t], out.rfb[t], out.root[t],
            out.quality[t], out.flags[t],
        )  # fmt: skip
        held += solve_one_nt(markers[t], plan, st, frame)
    return held
