"""The fit's model, state and output arrays packed into a few flat buffers.

Why: numba unboxes every array argument at every call, and a tuple of arrays element
by element. The fit's model (26 arrays), state (59) and output (10) cost 9.6 µs of
dispatch back to back and 94 µs median when calls come 4 ms apart (240 Hz: the
arrays' Python objects are out of the caches by then; measured on the project
machine, 2026-12-03). Packed, a frame's call passes one buffer per dtype and a
layout: the kernel rebuilds the same views (:func:`model_views`, :func:`state_views`,
:func:`out_views`) at a few ns each.

Layout: one int64 row per array, ``[offset, d0, d1, d2]`` (offset into the buffer
of its dtype; unused dimensions 1), rows in the order of ``m``, then ``s``, then the
outputs (``ROW_*``). The element kinds (dtype, ndim) are fixed by the kernel code
below; :func:`pack` checks the arrays it is given against them.

The views are built by ``_view`` (a numba intrinsic), not by slicing and
``reshape``: numba's ``reshape`` normalizes the shape and checks the size through an
out-of-line helper at every call, ~32 ns a view, and a frame's call builds 102 of them
(3.3 µs of the fit's ~90 µs a frame on the PiG walk; ``_view`` ~1 ns). The layout is
trusted: it is :func:`pack`'s own.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numba import types
from numba.extending import intrinsic

from retargetd.daemon.compiled import kernel

try:  # numba's array-struct helpers (there since numba 0.4x, not its public API)
    from numba.core import cgutils
    from numba.core.imputils import impl_ret_borrowed
    from numba.np.arrayobj import make_array, populate_array

    VIEW_INTRINSIC = True
except ImportError:  # pragma: no cover (a numba that moved them: the reshape views)
    VIEW_INTRINSIC = False

#: (dtype, ndim) of each element of the model tuple ``m`` (``kernel_fit``).
M_KINDS: tuple[tuple[str, int], ...] = (
    ("i8", 1), ("i8", 1), ("f8", 2), ("f8", 2), ("i8", 1), ("i8", 1), ("f8", 2),
    ("f8", 1), ("i8", 1), ("f8", 2), ("f8", 2), ("f8", 2), ("f8", 2), ("f8", 2),
    ("i8", 1), ("i8", 1), ("i8", 1), ("i8", 1), ("f8", 1), ("f8", 1), ("f8", 1),
    ("f8", 3), ("f8", 2), ("f8", 2), ("f8", 2), ("i8", 1), ("i8", 2),
)  # fmt: skip
#: (dtype, ndim) of each element of the state tuple ``s``.
S_KINDS: tuple[tuple[str, int], ...] = (
    ("f8", 2), ("f8", 2), ("f8", 2), ("f8", 2), ("i8", 1), ("f8", 2), ("f8", 2),
    ("f8", 2), ("f8", 3), ("f8", 2), ("f8", 2), ("f8", 1), ("f8", 2), ("b1", 1),
    ("f8", 2), ("f8", 1), ("f8", 1), ("f8", 2), ("f8", 3), ("f8", 2), ("f8", 2),
    ("f8", 3), ("f8", 3), ("f8", 1), ("f8", 1), ("f8", 1), ("f8", 1), ("f8", 1),
    ("f8", 2), ("f8", 2), ("f8", 2), ("f8", 3), ("f8", 2), ("f8", 2), ("f8", 2),
    ("f8", 1), ("f8", 1), ("f8", 2), ("f8", 2), ("i8", 1), ("i8", 1), ("f8", 2),
    ("f8", 2), ("f8", 2), ("f8", 2), ("b1", 1), ("b1", 1), ("f8", 2), ("f8", 1),
    ("f8", 2), ("f8", 2), ("f8", 1), ("f8", 2), ("f8", 3), ("f8", 2), ("f8", 1),
    ("f8", 2), ("f8", 2), ("f8", 1), ("f8", 1), ("f8", 3), ("i8", 2), ("f8", 3),
    ("f8", 2), ("f8", 1), ("f8", 2), ("f8", 2), ("f8", 1), ("f8", 1), ("f8", 3),
)  # fmt: skip
#: (dtype, ndim) of the outputs: joint centres, world / parent / rest rotations, root,
#: quality, flags, residuals, rejected, stats (``kernel_fit.fit_one_t``'s order).
O_KINDS: tuple[tuple[str, int], ...] = (
    ("f8", 2), ("f8", 2), ("f8", 2), ("f8", 2), ("f8", 1), ("f4", 1), ("u1", 1),
    ("f8", 1), ("b1", 1), ("f8", 1),
)  # fmt: skip
ROW_S = len(M_KINDS)  #: first state row
ROW_O = ROW_S + len(S_KINDS)  #: first output row
N_ROWS = ROW_O + len(O_KINDS)
if (ROW_S, ROW_O) != (27, 97):  # the literals of state_views and out_views
    raise ImportError("fit_pack: the kinds and the view functions disagree")


def pack(
    arrays: Sequence[np.ndarray], kinds: Sequence[tuple[str, int]]
) -> tuple[dict[str, np.ndarray], np.ndarray, tuple[np.ndarray, ...]]:
    """Copy ``arrays`` into one flat buffer per dtype.

    Returns:
        the buffers by dtype code (``"f8"``, ``"i8"``, ``"b1"``, ``"f4"``, ``"u1"``;
        every code of ``kinds``, at least one element each), the layout rows
        ``(len(arrays), 4)`` and the arrays' views into the buffers (C-contiguous,
        writable, equal to the arrays).
    """
    if len(arrays) != len(kinds):
        raise ValueError(f"expected {len(kinds)} arrays, got {len(arrays)}")
    sizes: dict[str, int] = {code: 0 for code, _ in kinds}
    rows = np.ones((len(arrays), 4), dtype=np.int64)
    for r, (a, (code, ndim)) in enumerate(zip(arrays, kinds, strict=True)):
        if a.dtype != np.dtype(code) or a.ndim != ndim:
            raise ValueError(
                f"array {r}: {a.dtype} {a.ndim}-d, expected {code} {ndim}-d"
            )
        rows[r, 0] = sizes[code]
        rows[r, 1 : 1 + ndim] = a.shape
        sizes[code] += a.size
    bufs = {code: np.zeros(max(n, 1), dtype=code) for code, n in sizes.items()}
    views = []
    for r, (a, (code, _)) in enumerate(zip(arrays, kinds, strict=True)):
        o = int(rows[r, 0])
        v = bufs[code][o : o + a.size].reshape(a.shape)
        v[...] = a
        views.append(v)
    return bufs, rows, tuple(views)


def _view_typing(
    typingctx: object, buf: types.Array, off: types.Integer, shape: types.UniTuple
) -> tuple:
    # A C-contiguous view of ``buf`` (1-d, C) from element ``off`` with ``shape``:
    # the array struct filled in directly (data pointer, shape, C strides, and the
    # buffer's meminfo and parent, so the view keeps it alive as a slice does),
    # with no size check (the layout is pack's).
    nd = shape.count
    ret = types.Array(buf.dtype, nd, "C")

    def codegen(context: Any, builder: Any, sig: Any, args: Any) -> Any:
        bufv, offv, shapev = args
        src = make_array(sig.args[0])(context, builder, bufv)
        dst = make_array(ret)(context, builder)
        shapes = cgutils.unpack_tuple(builder, shapev, nd)
        strides = [src.itemsize] * nd
        for k in range(nd - 2, -1, -1):
            strides[k] = builder.mul(strides[k + 1], shapes[k + 1])
        populate_array(
            dst, data=builder.gep(src.data, [offv]), shape=shapes, strides=strides,
            itemsize=src.itemsize, meminfo=src.meminfo, parent=src.parent,
        )  # fmt: skip
        return impl_ret_borrowed(context, builder, ret, dst._getvalue())

    return ret(buf, off, shape), codegen


@kernel
def view_by_reshape(b: np.ndarray, off: int, shape: tuple) -> np.ndarray:
    """``_view`` by slicing and ``reshape``: the same view, at ~32 ns (numba's size
    check); used where numba lacks the helpers the intrinsic needs, and as the
    intrinsic's reference (``tests/daemon/test_fit.py``)."""
    n = 1
    for d in shape:
        n *= d
    return b[off : off + n].reshape(shape)


#: ``_view(b, off, shape)``: the intrinsic, or :func:`view_by_reshape` where this
#: numba lacks its helpers. (Any: mypy reads the typing function's signature.)
_view: Any = intrinsic(_view_typing) if VIEW_INTRINSIC else view_by_reshape


@kernel
def _v1(b: np.ndarray, lay: np.ndarray, k: int) -> np.ndarray:
    return _view(b, lay[k, 0], (lay[k, 1],))


@kernel
def _v2(b: np.ndarray, lay: np.ndarray, k: int) -> np.ndarray:
    return _view(b, lay[k, 0], (lay[k, 1], lay[k, 2]))


@kernel
def _v3(b: np.ndarray, lay: np.ndarray, k: int) -> np.ndarray:
    return _view(b, lay[k, 0], (lay[k, 1], lay[k, 2], lay[k, 3]))


@kernel
def model_views(f: np.ndarray, i: np.ndarray, lay: np.ndarray) -> tuple:
    """The model tuple ``m`` (:data:`M_KINDS`) as views of its buffers."""
    return (
        _v1(i, lay, 0), _v1(i, lay, 1), _v2(f, lay, 2), _v2(f, lay, 3),
        _v1(i, lay, 4), _v1(i, lay, 5), _v2(f, lay, 6), _v1(f, lay, 7),
        _v1(i, lay, 8), _v2(f, lay, 9), _v2(f, lay, 10), _v2(f, lay, 11),
        _v2(f, lay, 12), _v2(f, lay, 13), _v1(i, lay, 14), _v1(i, lay, 15),
        _v1(i, lay, 16), _v1(i, lay, 17), _v1(f, lay, 18), _v1(f, lay, 19),
        _v1(f, lay, 20), _v3(f, lay, 21), _v2(f, lay, 22), _v2(f, lay, 23),
        _v2(f, lay, 24), _v1(i, lay, 25), _v2(i, lay, 26),
    )  # fmt: skip


@kernel
def state_views(f: np.ndarray, i: np.ndarray, b: np.ndarray, lay: np.ndarray) -> tuple:
    """The state tuple ``s`` (:data:`S_KINDS`) as views of its buffers."""
    r = 27  # ROW_S
    return (
        _v2(f, lay, r), _v2(f, lay, r + 1), _v2(f, lay, r + 2), _v2(f, lay, r + 3),
        _v1(i, lay, r + 4), _v2(f, lay, r + 5), _v2(f, lay, r + 6),
        _v2(f, lay, r + 7), _v3(f, lay, r + 8), _v2(f, lay, r + 9),
        _v2(f, lay, r + 10), _v1(f, lay, r + 11), _v2(f, lay, r + 12),
        _v1(b, lay, r + 13), _v2(f, lay, r + 14), _v1(f, lay, r + 15),
        _v1(f, lay, r + 16), _v2(f, lay, r + 17), _v3(f, lay, r + 18),
        _v2(f, lay, r + 19), _v2(f, lay, r + 20), _v3(f, lay, r + 21),
        _v3(f, lay, r + 22), _v1(f, lay, r + 23), _v1(f, lay, r + 24),
        _v1(f, lay, r + 25), _v1(f, lay, r + 26), _v1(f, lay, r + 27),
        _v2(f, lay, r + 28), _v2(f, lay, r + 29), _v2(f, lay, r + 30),
        _v3(f, lay, r + 31), _v2(f, lay, r + 32), _v2(f, lay, r + 33),
        _v2(f, lay, r + 34), _v1(f, lay, r + 35), _v1(f, lay, r + 36),
        _v2(f, lay, r + 37), _v2(f, lay, r + 38), _v1(i, lay, r + 39),
        _v1(i, lay, r + 40), _v2(f, lay, r + 41), _v2(f, lay, r + 42),
        _v2(f, lay, r + 43), _v2(f, lay, r + 44), _v1(b, lay, r + 45),
        _v1(b, lay, r + 46), _v2(f, lay, r + 47), _v1(f, lay, r + 48),
        _v2(f, lay, r + 49), _v2(f, lay, r + 50), _v1(f, lay, r + 51),
        _v2(f, lay, r + 52), _v3(f, lay, r + 53), _v2(f, lay, r + 54),
        _v1(f, lay, r + 55), _v2(f, lay, r + 56), _v2(f, lay, r + 57),
        _v1(f, lay, r + 58), _v1(f, lay, r + 59), _v3(f, lay, r + 60),
        _v2(i, lay, r + 61), _v3(f, lay, r + 62), _v2(f, lay, r + 63),
        _v1(f, lay, r + 64), _v2(f, lay, r + 65), _v2(f, lay, r + 66),
        _v1(f, lay, r + 67), _v1(f, lay, r + 68), _v3(f, lay, r + 69),
    )  # fmt: skip


@kernel
def out_views(
    f: np.ndarray, f4: np.ndarray, u1: np.ndarray, b: np.ndarray, lay: np.ndarray
) -> tuple:
    """The outputs (:data:`O_KINDS`) as views of a pose's buffers."""
    r = 97  # ROW_O
    return (
        _v2(f, lay, r), _v2(f, lay, r + 1), _v2(f, lay, r + 2), _v2(f, lay, r + 3),
        _v1(f, lay, r + 4), _v1(f4, lay, r + 5), _v1(u1, lay, r + 6),
        _v1(f, lay, r + 7), _v1(b, lay, r + 8), _v1(f, lay, r + 9),
    )  # fmt: skip
