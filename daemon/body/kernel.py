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
   +Z = X x Y; a bone whose points are missing or degenerate holds its last good
   rotation and is flagged;
5. parent-relative rotations, relative to the calibration pose; joint centres; root.

Why numba: a vectorized numpy version costs ~1-2 us per numpy call and a rig needs
~150 of them per frame; the compiled walk is one call (figures in bench/).
"""

from __future__ import annotations

import math

import numba
import numpy as np

OP_LINE = 0
OP_RIGID = 1

FLAG_HELD = 1  #: bone rotation held from the last good frame (too little data)
FLAG_REBUILT = 2  #: a defining marker was rebuilt from its rigid segment
FLAG_PARTIAL = 4  #: some defining marker was not seen (quality < 1)
FLAG_NEVER = 8  #: no good value yet: the calibrated rest rotation is sent


@numba.njit(cache=True, nogil=True, error_model="numpy")
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


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _conj_mul(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    # out = conj(a) * b (Hamilton), i.e. a^-1 b for unit a.
    aw, ax, ay, az = a[0], -a[1], -a[2], -a[3]
    bw, bx, by, bz = b[0], b[1], b[2], b[3]
    out[0] = aw * bw - ax * bx - ay * by - az * bz
    out[1] = aw * bx + ax * bw + ay * bz - az * by
    out[2] = aw * by - ax * bz + ay * bw + az * bx
    out[3] = aw * bz + ax * by - ay * bx + az * bw


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _mul(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    # out = a * b (Hamilton); out may not alias a or b.
    aw, ax, ay, az = a[0], a[1], a[2], a[3]
    bw, bx, by, bz = b[0], b[1], b[2], b[3]
    out[0] = aw * bw - ax * bx - ay * by - az * bz
    out[1] = aw * bx + ax * bw + ay * bz - az * by
    out[2] = aw * by - ax * bz + ay * bw + az * bx
    out[3] = aw * bz + ax * by - ay * bx + az * bw


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _jacobi_top_eigvec(a: np.ndarray, v: np.ndarray, out: np.ndarray) -> None:
    # Eigenvector of the largest eigenvalue of the symmetric 4x4 ``a`` (destroyed),
    # by cyclic Jacobi rotations on the scratch ``v`` (4, 4): no allocation.
    for i in range(4):
        for j in range(4):
            v[i, j] = 1.0 if i == j else 0.0
    for _sweep in range(30):
        off = 0.0
        for p in range(3):
            for q in range(p + 1, 4):
                off += a[p, q] * a[p, q]
        if off < 1e-30:
            break
        for p in range(3):
            for q in range(p + 1, 4):
                apq = a[p, q]
                if abs(apq) < 1e-300:
                    continue
                theta = (a[q, q] - a[p, p]) / (2.0 * apq)
                t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
                if theta < 0.0:
                    t = -t
                c = 1.0 / math.sqrt(t * t + 1.0)
                s = t * c
                for k in range(4):
                    akp = a[k, p]
                    akq = a[k, q]
                    a[k, p] = c * akp - s * akq
                    a[k, q] = s * akp + c * akq
                for k in range(4):
                    apk = a[p, k]
                    aqk = a[q, k]
                    a[p, k] = c * apk - s * aqk
                    a[q, k] = s * apk + c * aqk
                for k in range(4):
                    vkp = v[k, p]
                    vkq = v[k, q]
                    v[k, p] = c * vkp - s * vkq
                    v[k, q] = s * vkp + c * vkq
    best = 0
    for i in range(1, 4):
        if a[i, i] > a[best, best]:
            best = i
    for k in range(4):
        out[k] = v[k, best]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def horn_rotation(
    sxx: float, sxy: float, sxz: float,
    syx: float, syy: float, syz: float,
    szx: float, szy: float, szz: float,
    n44: np.ndarray,
    v44: np.ndarray,
    q4: np.ndarray,
) -> None:  # fmt: skip
    """Horn's closed-form rigid fit: from the cross-covariance S = sum l_i c_i^T of
    centred layout points l and current points c, the rotation R maximizing
    sum c_i . R l_i is the top eigenvector of a symmetric 4x4 matrix built from S.
    Writes R (3, 3) into ``n44[:3, :3]`` and its quaternion (w, x, y, z) into ``q4``
    (scratch n44, v44 (4, 4); no allocation)."""
    n44[0, 0] = sxx + syy + szz
    n44[0, 1] = n44[1, 0] = syz - szy
    n44[0, 2] = n44[2, 0] = szx - sxz
    n44[0, 3] = n44[3, 0] = sxy - syx
    n44[1, 1] = sxx - syy - szz
    n44[1, 2] = n44[2, 1] = sxy + syx
    n44[1, 3] = n44[3, 1] = szx + sxz
    n44[2, 2] = -sxx + syy - szz
    n44[2, 3] = n44[3, 2] = syz + szy
    n44[3, 3] = -sxx - syy + szz
    _jacobi_top_eigvec(n44, v44, q4)
    w, x, y, z = q4[0], q4[1], q4[2], q4[3]
    n44[0, 0] = 1.0 - 2.0 * (y * y + z * z)
    n44[0, 1] = 2.0 * (x * y - w * z)
    n44[0, 2] = 2.0 * (x * z + w * y)
    n44[1, 0] = 2.0 * (x * y + w * z)
    n44[1, 1] = 1.0 - 2.0 * (x * x + z * z)
    n44[1, 2] = 2.0 * (y * z - w * x)
    n44[2, 0] = 2.0 * (x * z - w * y)
    n44[2, 1] = 2.0 * (y * z + w * x)
    n44[2, 2] = 1.0 - 2.0 * (x * x + y * y)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _kabsch_fill(
    pts: np.ndarray,
    seen: np.ndarray,
    idx: np.ndarray,
    layout: np.ndarray,
    filled: np.ndarray,
    n44: np.ndarray,
    v44: np.ndarray,
    q4: np.ndarray,
) -> None:
    # Fit the calibrated layout of one rigid segment to its visible markers (Horn's
    # quaternion method: the rotation is the top eigenvector of a 4x4 matrix built
    # from the cross-covariance) and put the missing ones where the fit says. Needs
    # >= 3 visible markers not on one line. Scratch n44, v44 (4, 4) and q4 (4,).
    k = idx.shape[0]
    n = 0
    for i in range(k):
        if seen[idx[i]]:
            n += 1
    if n < 3 or n == k:
        return
    clx = cly = clz = ccx = ccy = ccz = 0.0
    for i in range(k):
        if seen[idx[i]]:
            m = idx[i]
            clx += layout[i, 0]
            cly += layout[i, 1]
            clz += layout[i, 2]
            ccx += pts[m, 0]
            ccy += pts[m, 1]
            ccz += pts[m, 2]
    clx /= n
    cly /= n
    clz /= n
    ccx /= n
    ccy /= n
    ccz /= n
    sxx = sxy = sxz = syx = syy = syz = szx = szy = szz = 0.0
    # Largest cross product of visible layout offsets: 0 when they are collinear.
    area = 0.0
    ref_x = ref_y = ref_z = 0.0
    have_ref = False
    for i in range(k):
        if not seen[idx[i]]:
            continue
        m = idx[i]
        lx, ly, lz = layout[i, 0] - clx, layout[i, 1] - cly, layout[i, 2] - clz
        cx, cy, cz = pts[m, 0] - ccx, pts[m, 1] - ccy, pts[m, 2] - ccz
        sxx += lx * cx
        sxy += lx * cy
        sxz += lx * cz
        syx += ly * cx
        syy += ly * cy
        syz += ly * cz
        szx += lz * cx
        szy += lz * cy
        szz += lz * cz
        if not have_ref:
            ref_x, ref_y, ref_z = lx, ly, lz
            have_ref = True
        else:
            ax = ref_y * lz - ref_z * ly
            ay = ref_z * lx - ref_x * lz
            az = ref_x * ly - ref_y * lx
            area = max(area, ax * ax + ay * ay + az * az)
    if area < 1e-12:  # (1 mm x 1 mm)^2: the fit is not determined
        return
    horn_rotation(sxx, sxy, sxz, syx, syy, syz, szx, szy, szz, n44, v44, q4)
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


@numba.njit(cache=True, nogil=True, error_model="numpy")
def solve_one(
    markers: np.ndarray,  # (M_stream, 3) world metres, NaN = occluded
    marker_cols: np.ndarray,  # (Mr,) int64, stream column per rig marker, -1 absent
    op_kind: np.ndarray,  # (P,) int64
    op_idx: np.ndarray,  # (P, 3) int64 indices into pts
    op_u: np.ndarray,  # (P,) float64
    op_off: np.ndarray,  # (P, 3) float64 local offset (rigid)
    seg_ptr: np.ndarray,  # (S+1,) int64
    seg_idx: np.ndarray,  # (K,) int64 marker indices
    seg_layout: np.ndarray,  # (K, 3) float64 calibrated layout
    bone_pts: np.ndarray,  # (B, 4) int64: origin, aim, up1, up2 (-1: single point)
    bone_parent: np.ndarray,  # (B,) int64, parents before children
    bone_def_ptr: np.ndarray,  # (B+1,) int64
    bone_def_idx: np.ndarray,  # (D,) int64 defining marker indices
    rest_pfb: np.ndarray,  # (B, 4) calibrated parent_from_bone (w x y z)
    joint_idx: np.ndarray,  # (J,) int64 indices into pts
    root_point: int,
    # scratch and state, preallocated
    pts: np.ndarray,  # (Mr + P, 3)
    seen: np.ndarray,  # (Mr + P,) bool
    filled: np.ndarray,  # (Mr + P,) bool
    last_pfb: np.ndarray,  # (B, 4) last good parent_from_bone (init: rest_pfb)
    have_good: np.ndarray,  # (B,) bool, a good value was seen
    prev_wfb: np.ndarray,  # (B, 4) previous frame's output; w = NaN: none
    tmp4: np.ndarray,  # (4,)
    n44: np.ndarray,  # (4, 4) scratch
    v44: np.ndarray,  # (4, 4) scratch
    last_root: np.ndarray,  # (3,) last good root position (init: calibrated rest)
    # outputs for this frame
    out_joints: np.ndarray,  # (J, 3)
    out_wfb: np.ndarray,  # (B, 4)
    out_pfb: np.ndarray,  # (B, 4)
    out_root: np.ndarray,  # (3,)
    out_quality: np.ndarray,  # (B,) float32
    out_flags: np.ndarray,  # (B,) uint8
) -> int:
    n_markers = marker_cols.shape[0]
    nan = math.nan
    # 1. gather
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
        seen[i] = ok
        filled[i] = False
    # 2. rebuild occluded markers from their rigid segment
    for s in range(seg_ptr.shape[0] - 1):
        a, b = seg_ptr[s], seg_ptr[s + 1]
        _kabsch_fill(pts, seen, seg_idx[a:b], seg_layout[a:b], filled, n44, v44, tmp4)
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
        if good:
            yx, yy, yz = yx / ny, yy / ny, yz / ny
            dot = ux * yx + uy * yy + uz * yz
            xx, xy, xz = ux - dot * yx, uy - dot * yy, uz - dot * yz
            nx = math.sqrt(xx * xx + xy * xy + xz * xz)
            nu = math.sqrt(ux * ux + uy * uy + uz * uz)
            # The up reference must stand off the bone axis (> ~0.6 deg).
            good = math.isfinite(nx) and nx > 1e-2 * nu and nx > 1e-9
        par = bone_parent[b]
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
                _conj_mul(out_wfb[par], out_wfb[b], last_pfb[b])
            have_good[b] = True
        else:
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
                _mul(out_wfb[par], last_pfb[b], out_wfb[b])
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
    # 5. parent-relative, relative to the calibration pose:
    #    out = conj(rest_pfb) * (conj(world_from_parent) * world_from_bone)
    for b in range(bone_pts.shape[0]):
        par = bone_parent[b]
        if par < 0:
            for j in range(4):
                tmp4[j] = out_wfb[b, j]
        else:
            _conj_mul(out_wfb[par], out_wfb[b], tmp4)
        _conj_mul(rest_pfb[b], tmp4, out_pfb[b])
        # The relative rotation is near identity in normal use: keep w >= 0 so that
        # it reads as the short way round.
        if out_pfb[b, 0] < 0.0:
            for j in range(4):
                out_pfb[b, j] = -out_pfb[b, j]
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


@numba.njit(cache=True, nogil=True, error_model="numpy")
def solve_many(
    markers: np.ndarray,  # (T, M_stream, 3)
    marker_cols: np.ndarray,
    op_kind: np.ndarray,
    op_idx: np.ndarray,
    op_u: np.ndarray,
    op_off: np.ndarray,
    seg_ptr: np.ndarray,
    seg_idx: np.ndarray,
    seg_layout: np.ndarray,
    bone_pts: np.ndarray,
    bone_parent: np.ndarray,
    bone_def_ptr: np.ndarray,
    bone_def_idx: np.ndarray,
    rest_pfb: np.ndarray,
    joint_idx: np.ndarray,
    root_point: int,
    pts: np.ndarray,
    seen: np.ndarray,
    filled: np.ndarray,
    last_pfb: np.ndarray,
    have_good: np.ndarray,
    prev_wfb: np.ndarray,
    tmp4: np.ndarray,
    n44: np.ndarray,
    v44: np.ndarray,
    last_root: np.ndarray,
    out_joints: np.ndarray,  # (T, J, 3)
    out_wfb: np.ndarray,  # (T, B, 4)
    out_pfb: np.ndarray,  # (T, B, 4)
    out_root: np.ndarray,  # (T, 3)
    out_quality: np.ndarray,  # (T, B)
    out_flags: np.ndarray,  # (T, B)
) -> int:
    held = 0
    for t in range(markers.shape[0]):
        held += solve_one(
            markers[t], marker_cols, op_kind, op_idx, op_u, op_off, seg_ptr,
            seg_idx, seg_layout, bone_pts, bone_parent, bone_def_ptr, bone_def_idx,
            rest_pfb, joint_idx, root_point, pts, seen, filled, last_pfb, have_good,
            prev_wfb, tmp4, n44, v44, last_root,
            out_joints[t], out_wfb[t], out_pfb[t], out_root[t], out_quality[t],
            out_flags[t],
        )  # fmt: skip
    return held
