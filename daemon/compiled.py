"""The compiled primitives every kernel shares, and the one decorator they compile with.

:func:`kernel` is ``numba.njit(cache=True, nogil=True, error_model="numpy")``:
``nogil`` so the validator thread and the loop thread run kernels side by side;
NumPy's error model so a zero-length axis gives NaN or inf (the bone holds, flagged)
instead of raising ``ZeroDivisionError`` in the live loop (issue 12).

**Caching that cannot go stale.** numba keys a function's on-disk cache on its own
source file only: a kernel that calls a primitive from another module (the
quaternion product below, say) keeps loading its old machine code after that
primitive changes. So every kernel here caches under a folder named by the digest of
the sources of *every* module that compiles with :func:`kernel` (this one included,
found by scanning the package for its import): edit any of them and every kernel
recompiles into a fresh folder; nothing needs deleting by hand. The wire codecs'
kernels (``retargetd.protocols.kernels``) are among those sources too: the live loop's
emit kernel calls them. The folder lives under
``$NUMBA_CACHE_DIR`` when set, else ``$XDG_CACHE_HOME/retargetd/numba`` (default
``~/.cache``), else the temporary directory.

Primitives (quaternions ``(w, x, y, z)``, Hamilton): :func:`qmul` (the one compiled
quaternion product; the array forms :func:`quat_mul_into`, :func:`quat_conj_mul_into`
wrap it) and :func:`horn_fit` (the one weighted Horn rigid fit: centroids, the
cross-covariance and the top eigenvector of Horn's 4x4 matrix), used by the body
kernel's rigid-segment rebuild and the face kernel's head stabilization.
"""

from __future__ import annotations

import hashlib
import importlib.util
import math
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numba
import numpy as np

from retargetd.protocols import kernels as protocol_kernels

_PACKAGE = Path(__file__).resolve().parent
_MARKERS = (
    "from retargetd.daemon.compiled import",
    "from retargetd.daemon import compiled",
)


def kernel_sources() -> tuple[Path, ...]:
    """Every module of the package that compiles with :func:`kernel` (and this one),
    and the wire codecs' kernels (``retargetd.protocols.kernels``), which the live
    loop's one call per frame runs inside its own (``live/emit.py``)."""
    found = [Path(__file__).resolve()]
    for path in sorted(_PACKAGE.rglob("*.py")):
        if path == found[0] or "__pycache__" in path.parts:
            continue
        text = path.read_text(encoding="utf-8")
        if any(m in text for m in _MARKERS):
            found.append(path)
    spec = importlib.util.find_spec("retargetd.protocols.kernels")
    if spec is not None and spec.origin:
        found.append(Path(spec.origin).resolve())
    return tuple(found)


def sources_digest(paths: tuple[Path, ...]) -> str:
    """sha256 over the files' paths (relative to the package) and contents."""
    h = hashlib.sha256(numba.__version__.encode())
    for path in paths:
        rel = path.relative_to(_PACKAGE) if path.is_relative_to(_PACKAGE) else path
        h.update(str(rel).encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()


def _cache_root() -> Path:
    env = os.environ.get("NUMBA_CACHE_DIR")
    if env:
        return Path(env)
    xdg = os.environ.get("XDG_CACHE_HOME") or os.path.join(
        os.path.expanduser("~"), ".cache"
    )
    root = Path(xdg) / "retargetd" / "numba"
    try:
        root.mkdir(parents=True, exist_ok=True)
        if os.access(root, os.W_OK):
            return root
    except OSError:
        pass
    return Path(tempfile.gettempdir()) / f"retargetd-numba-{os.getuid()}"


#: The digest every kernel's cache folder is named by (module docstring).
KERNEL_DIGEST = sources_digest(kernel_sources())
#: Where the kernels' compiled code is cached.
CACHE_DIR = _cache_root() / KERNEL_DIGEST[:16]


def kernel(fn: Callable[..., Any] | None = None, **options: Any) -> Any:
    """Compile ``fn`` like every kernel here (``@kernel`` or ``@kernel(inline=...)``).

    The cache folder is chosen while numba builds the function's cache locator
    (``numba.config.CACHE_DIR`` is read then, and restored at once)."""

    def wrap(f: Callable[..., Any]) -> Any:
        cfg: Any = numba.config  # (CACHE_DIR is set at run time, untyped)
        saved = cfg.CACHE_DIR
        cfg.CACHE_DIR = str(CACHE_DIR)
        try:
            return numba.njit(cache=True, nogil=True, error_model="numpy", **options)(f)
        finally:
            cfg.CACHE_DIR = saved

    return wrap(fn) if fn is not None else wrap


def direct(dispatcher: Any, *args: Any) -> Any:
    """``dispatcher``'s compiled function for the types of ``args``, called without
    the dispatcher's per-call type resolution (paced at 240 Hz, a 24-argument call
    ~50 -> ~38 us median on this VM; 1000 Hz ~15 -> ~10), or ``dispatcher`` itself
    when no compiled overload has those types yet.

    Only for a call whose arguments keep these types on every call (the live loop's
    emit call, its arrays bound once per pipeline): the compiled function converts
    each argument to the type it was compiled for without checking it. (The wire
    codecs' ``protocols.kernels.direct``, which the marker streams use too.)"""
    return protocol_kernels.direct(dispatcher, *args)


def readonly_f64(a: Any) -> np.ndarray:
    """A C-contiguous float64 copy of ``a``, marked read-only: constant arguments
    passed to a kernel as one type whatever their source (numba compiles a read-only
    array and a writable one apart)."""
    out = np.array(a, dtype=np.float64, order="C")
    out.flags.writeable = False
    return out


@kernel(inline="always")
def qmul(
    aw: float, ax: float, ay: float, az: float,
    bw: float, bx: float, by: float, bz: float,
) -> tuple[float, float, float, float]:  # fmt: skip
    """The Hamilton product ``a ⊗ b`` of two quaternions given by components."""
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


@kernel(inline="always")
def qrot(
    w: float, x: float, y: float, z: float, vx: float, vy: float, vz: float
) -> tuple[float, float, float]:
    """The unit quaternion (w x y z) applied to v: v + 2 w (u x v) + 2 u x (u x v)."""
    cx = y * vz - z * vy
    cy = z * vx - x * vz
    cz = x * vy - y * vx
    return (
        vx + 2.0 * (w * cx + y * cz - z * cy),
        vy + 2.0 * (w * cy + z * cx - x * cz),
        vz + 2.0 * (w * cz + x * cy - y * cx),
    )


@kernel
def quat_mul_into(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    """``out = a ⊗ b`` (4,) each; ``out`` may not alias ``a`` or ``b``."""
    out[0], out[1], out[2], out[3] = qmul(
        a[0], a[1], a[2], a[3], b[0], b[1], b[2], b[3]
    )


@kernel
def quat_conj_mul_into(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    """``out = conj(a) ⊗ b`` (``a⁻¹ b`` for a unit ``a``); (4,) each, no aliasing."""
    out[0], out[1], out[2], out[3] = qmul(
        a[0], -a[1], -a[2], -a[3], b[0], b[1], b[2], b[3]
    )


@kernel
def jacobi_eigen(a: np.ndarray, v: np.ndarray) -> None:
    """Diagonalize the symmetric (n, n) ``a`` in place by cyclic Jacobi rotations:
    its diagonal becomes the eigenvalues and ``v``'s columns (n, n) the eigenvectors.
    No allocation (n = 3 for a joint's information, 4 for quaternion averaging)."""
    n = a.shape[0]
    for i in range(n):
        for j in range(n):
            v[i, j] = 1.0 if i == j else 0.0
    for _sweep in range(30):
        off = 0.0
        for p in range(n - 1):
            for q in range(p + 1, n):
                off += a[p, q] * a[p, q]
        if off < 1e-30:
            break
        for p in range(n - 1):
            for q in range(p + 1, n):
                apq = a[p, q]
                if abs(apq) < 1e-300:
                    continue
                theta = (a[q, q] - a[p, p]) / (2.0 * apq)
                t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
                if theta < 0.0:
                    t = -t
                c = 1.0 / math.sqrt(t * t + 1.0)
                s = t * c
                for k in range(n):
                    akp = a[k, p]
                    akq = a[k, q]
                    a[k, p] = c * akp - s * akq
                    a[k, q] = s * akp + c * akq
                for k in range(n):
                    apk = a[p, k]
                    aqk = a[q, k]
                    a[p, k] = c * apk - s * aqk
                    a[q, k] = s * apk + c * aqk
                for k in range(n):
                    vkp = v[k, p]
                    vkq = v[k, q]
                    v[k, p] = c * vkp - s * vkq
                    v[k, q] = s * vkp + c * vkq


@kernel
def _jacobi_top_eigvec(a: np.ndarray, v: np.ndarray, out: np.ndarray) -> None:
    # Eigenvector of the largest eigenvalue of the symmetric 4x4 ``a`` (destroyed),
    # on the scratch ``v`` (4, 4): no allocation.
    jacobi_eigen(a, v)
    best = 0
    for i in range(1, 4):
        if a[i, i] > a[best, best]:
            best = i
    for k in range(4):
        out[k] = v[k, best]


@kernel
def mat_from_unit_quat(q: np.ndarray, m: np.ndarray) -> None:
    """Rotation matrix of the unit quaternion ``q`` (w, x, y, z) into ``m[:3, :3]``
    (``v_a = M @ v_b``; ``m`` may be larger, e.g. a 4x4 scratch)."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    m[0, 0] = 1.0 - 2.0 * (y * y + z * z)
    m[0, 1] = 2.0 * (x * y - w * z)
    m[0, 2] = 2.0 * (x * z + w * y)
    m[1, 0] = 2.0 * (x * y + w * z)
    m[1, 1] = 1.0 - 2.0 * (x * x + z * z)
    m[1, 2] = 2.0 * (y * z - w * x)
    m[2, 0] = 2.0 * (x * z - w * y)
    m[2, 1] = 2.0 * (y * z + w * x)
    m[2, 2] = 1.0 - 2.0 * (x * x + y * y)


@kernel
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
    mat_from_unit_quat(q4, n44)


@kernel
def horn_fit(
    layout: np.ndarray,
    pts: np.ndarray,
    rows: np.ndarray,
    use: np.ndarray,
    weights: np.ndarray,
    n44: np.ndarray,
    v44: np.ndarray,
    q4: np.ndarray,
    cen: np.ndarray,
) -> int:
    """Weighted rigid fit of a layout to the points it sees (Horn's quaternion method).

    Point ``i`` of the layout is used when ``rows[i] >= 0``, ``use[rows[i]]``,
    ``weights[i] > 0`` and its current point is finite. Maximizes
    ``sum_i w_i c_i . R l_i`` over the centred points.

    Args:
        layout: (K, 3) float64, the layout (segment or head coordinates).
        pts: (N, 3) float64, current points (world).
        rows: (K,) int64, row of ``pts`` of each layout point; -1 = absent.
        use: (N,) bool, whether a row of ``pts`` may be used.
        weights: (K,) float64, weight of each layout point (0 = skip).
        n44, v44: (4, 4) scratch; on return ``n44[:3, :3]`` is R (world_from_layout).
        q4: (4,) out: R as a quaternion (w, x, y, z).
        cen: (6,) out: the weighted layout centroid (0:3) and points centroid (3:6).

    Returns:
        the number of points used; 0 when the fit is not determined (fewer than
        three, no weight, or all on one line: the rotation about it is unknown).
    """
    k = layout.shape[0]
    wsum = clx = cly = clz = ccx = ccy = ccz = 0.0
    n = 0
    for i in range(k):
        r = rows[i]
        if r < 0 or not use[r] or not weights[i] > 0.0:
            continue
        x, y, z = pts[r, 0], pts[r, 1], pts[r, 2]
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            continue
        w = weights[i]
        n += 1
        wsum += w
        clx += w * layout[i, 0]
        cly += w * layout[i, 1]
        clz += w * layout[i, 2]
        ccx += w * x
        ccy += w * y
        ccz += w * z
    if n < 3 or wsum <= 0.0:
        return 0
    clx /= wsum
    cly /= wsum
    clz /= wsum
    ccx /= wsum
    ccy /= wsum
    ccz /= wsum
    sxx = sxy = sxz = syx = syy = syz = szx = szy = szz = 0.0
    # Largest cross product of used layout offsets: 0 when they are collinear.
    area = 0.0
    rx = ry = rz = 0.0
    have_ref = False
    for i in range(k):
        r = rows[i]
        if r < 0 or not use[r] or not weights[i] > 0.0:
            continue
        x, y, z = pts[r, 0], pts[r, 1], pts[r, 2]
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            continue
        w = weights[i]
        lx, ly, lz = layout[i, 0] - clx, layout[i, 1] - cly, layout[i, 2] - clz
        cx, cy, cz = w * (x - ccx), w * (y - ccy), w * (z - ccz)
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
            rx, ry, rz = lx, ly, lz
            have_ref = True
        else:
            ax = ry * lz - rz * ly
            ay = rz * lx - rx * lz
            az = rx * ly - ry * lx
            area = max(area, ax * ax + ay * ay + az * az)
    if area < 1e-12:  # (1 mm x 1 mm)^2: collinear, the rotation about the line unknown
        return 0
    horn_rotation(sxx, sxy, sxz, syx, syy, syz, szx, szy, szz, n44, v44, q4)
    cen[0], cen[1], cen[2] = clx, cly, clz
    cen[3], cen[4], cen[5] = ccx, ccy, ccz
    return n
