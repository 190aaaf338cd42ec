"""The compiled primitives and the kernels' cache design (issue 13, item 4).

numba keys a function's on-disk cache on its own source file only, so a kernel that
calls a primitive from another module would keep stale machine code after that
primitive changed. Every kernel compiles with :func:`compiled.kernel`, which caches
under a folder named by the digest of every kernel module's source: these tests show
that every compiled function of the package is placed there, that the digest covers
every module that compiles, and that editing any one of them moves the folder.
"""

from __future__ import annotations

import importlib
import pkgutil
import shutil
from pathlib import Path

import numba
import numpy as np
from numba.core.registry import CPUDispatcher
from scipy.spatial.transform import Rotation

import retargetd.daemon
from retargetd.daemon import compiled, rotations
from retargetd.daemon.body import kernel as body_kernel
from retargetd.daemon.face import kernel as face_kernel
from retargetd.protocols import pose_stream


def _dispatchers() -> list[tuple[str, CPUDispatcher]]:
    found = []
    for info in pkgutil.walk_packages(retargetd.daemon.__path__, "retargetd.daemon."):
        if info.name.endswith("__main__"):
            continue
        module = importlib.import_module(info.name)
        for name, obj in vars(module).items():
            if isinstance(obj, CPUDispatcher) and obj.__module__ == module.__name__:
                found.append((f"{info.name}.{name}", obj))
    return found


def test_every_kernel_caches_under_the_digest_folder() -> None:
    dispatchers = _dispatchers()
    assert len(dispatchers) >= 12  # body, face, target, validator kernels, primitives
    sources = {p.resolve() for p in compiled.kernel_sources()}
    for name, disp in dispatchers:
        cache = disp._cache  # FunctionCache: set by cache=True
        assert cache is not None, f"{name}: not cached"
        path = Path(cache._cache_path)
        assert path.is_relative_to(compiled.CACHE_DIR), f"{name}: caches in {path}"
        src = Path(disp.py_func.__code__.co_filename).resolve()
        assert src in sources, f"{name}: {src} is not in the digest's sources"
    assert str(compiled.CACHE_DIR) != numba.config.CACHE_DIR  # restored after use


def test_editing_any_kernel_source_moves_the_cache_folder(tmp_path: Path) -> None:
    sources = compiled.kernel_sources()
    assert len(sources) >= 5
    copies = []
    for i, path in enumerate(sources):
        dst = tmp_path / f"{i}_{path.name}"
        shutil.copy(path, dst)
        copies.append(dst)
    base = compiled.sources_digest(tuple(copies))
    assert base == compiled.sources_digest(tuple(copies))  # deterministic
    for dst in copies:
        text = dst.read_text()
        dst.write_text(text + "\n# an edit\n")
        assert compiled.sources_digest(tuple(copies)) != base, dst.name
        dst.write_text(text)
    assert compiled.sources_digest(tuple(copies)) == base


def test_qmul_is_the_hamilton_product(rng: np.random.Generator) -> None:
    a = rotations.quat_normalize(rng.normal(size=(50, 4)))
    b = rotations.quat_normalize(rng.normal(size=(50, 4)))
    want = rotations.quat_mul(a, b)
    out = np.zeros(4)
    for i in range(50):
        compiled.quat_mul_into(a[i], b[i], out)
        np.testing.assert_allclose(out, want[i], atol=1e-15)
        compiled.quat_conj_mul_into(a[i], b[i], out)
        np.testing.assert_allclose(
            out, rotations.quat_mul(rotations.quat_conj(a[i]), b[i]), atol=1e-15
        )


def test_horn_fit_recovers_a_weighted_rigid_motion(rng: np.random.Generator) -> None:
    layout = rng.normal(0.0, 0.1, (6, 3))
    rot = Rotation.random(random_state=3)
    pts = rot.apply(layout) + np.array([0.3, -1.0, 1.2])
    rows = np.arange(6, dtype=np.int64)
    rows[2] = -1  # absent
    use = np.ones(6, dtype=bool)
    use[4] = False  # not to be used
    weights = np.array([1.0, 2.0, 1.0, 0.5, 1.0, 3.0])
    n44, v44, q4, cen = np.zeros((4, 4)), np.zeros((4, 4)), np.zeros(4), np.zeros(6)
    n = compiled.horn_fit(layout, pts, rows, use, weights, n44, v44, q4, cen)
    assert n == 4
    np.testing.assert_allclose(n44[:3, :3], rot.as_matrix(), atol=1e-12)
    np.testing.assert_allclose(
        abs(q4 @ rot.as_quat(scalar_first=True)), 1.0, atol=1e-12
    )
    # Collinear points leave the rotation about their line unknown: not determined.
    line = np.outer(np.linspace(0.0, 0.3, 6), [1.0, 0.5, 0.2])
    assert compiled.horn_fit(line, line, rows, use, weights, n44, v44, q4, cen) == 0


def test_kernel_flags_are_the_wire_flags() -> None:
    assert (
        body_kernel.FLAG_HELD,
        body_kernel.FLAG_REBUILT,
        body_kernel.FLAG_PARTIAL,
        body_kernel.FLAG_NEVER,
    ) == (
        pose_stream.BONE_HELD,
        pose_stream.BONE_REBUILT,
        pose_stream.BONE_PARTIAL,
        pose_stream.BONE_NEVER,
    )
    bits = {1 << b for b in pose_stream.BONE_FLAG_BITS.values()}
    assert bits == {
        body_kernel.FLAG_HELD,
        body_kernel.FLAG_REBUILT,
        body_kernel.FLAG_PARTIAL,
        body_kernel.FLAG_NEVER,
    }
    assert {1 << b for b in pose_stream.FACE_FLAG_BITS.values()} == {
        face_kernel.FLAG_HEAD_PARTIAL,
        face_kernel.FLAG_HEAD_LOST,
        face_kernel.FLAG_NOT_CONVERGED,
        face_kernel.FLAG_FACE_PARTIAL,
        face_kernel.FLAG_NEVER,
        face_kernel.FLAG_SHAPE_HELD,
    }


def test_direct_is_the_compiled_function_for_those_types_only() -> None:
    """``direct``: the overload compiled for the arguments' types (it computes the
    same), or the dispatcher itself when none has those types (it then compiles)."""
    a, out = np.array([1.0, 2.0, 3.0, 4.0]), np.zeros(4)
    b = np.array([0.5, 0.5, 0.5, 0.5])
    compiled.quat_mul_into(a, b, out)
    fn = compiled.direct(compiled.quat_mul_into, a, b, out)
    assert fn is not compiled.quat_mul_into
    got = np.zeros(4)
    fn(a, b, got)
    np.testing.assert_array_equal(got, out)
    f32 = np.zeros(4, np.float32)  # never compiled for float32: the dispatcher
    assert compiled.direct(compiled.quat_mul_into, f32, f32, f32) is (
        compiled.quat_mul_into
    )
    assert compiled.direct(len, a) is len  # not a numba dispatcher at all
