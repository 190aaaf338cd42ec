"""The prop solver: one prop's buffers, bound to a stream's labels once, then one
compiled call per frame (:mod:`retargetd.daemon.props.kernel`); and the same over a
whole take for the offline commands.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from retargetd.daemon.body.solve_fit import FitParams
from retargetd.daemon.compiled import direct
from retargetd.daemon.props import kernel as pk
from retargetd.daemon.props.layout import PropLayout
from retargetd.protocols.frames import BoolArray, F64Array

_BODY = FitParams()

#: The gate of a rigid prop's marker, metres. A prop's markers move with it, so its
#: residual is the capture system's reconstruction error, not skin artefact (the
#: body fit's 40 mm gate): about 0.2 mm static and under 2 mm in motion for a
#: calibrated passive optical system (Merriaux et al., "A Study of Vicon System
#: Positioning Performance", Sensors 17(7):1591, 2017). 10 mm is five times that
#: worst error, and below the closest two distinct markers of a cluster may sit
#: (a marker diameter, 9.5-14 mm passive markers, apart at least). Confirmed on the
#: pyomeca box, 8 markers, 580 frames, not used to choose it
#: (``tests/daemon/props/test_props_real.py``): residual RMS median 0.27 mm, 95th
#: percentile 0.52 mm, largest 1.5 mm; no marker gated on a frame it was seen.
DEFAULT_GATE_M = 0.010
#: The body fit's gate factor (``FitParams.gate_k``): the gate stays above the fit's
#: own residual level on a noisy system.
DEFAULT_GATE_K = _BODY.gate_k
#: The Cauchy scale as a fraction of the gate, the body fit's own ratio
#: (``FitParams.cauchy_m / gate_m``, 20 / 40 mm): a marker at the gate weighs a fifth.
CAUCHY_PER_GATE = _BODY.cauchy_m / _BODY.gate_m
#: Reweighting passes after the consensus fit: the consensus has already removed
#: swaps and ghosts, so two passes settle the weights of the remaining markers.
DEFAULT_IRLS_ITER = 2


@dataclass(frozen=True, slots=True, kw_only=True)
class PropParams:
    """The fit's parameters (see the constants above for each default's grounds)."""

    gate_m: float = DEFAULT_GATE_M
    gate_k: float = DEFAULT_GATE_K
    irls_iter: int = DEFAULT_IRLS_ITER

    def array(self) -> F64Array:
        out = np.zeros(pk.N_PARAMS)
        out[pk.P_GATE_M] = self.gate_m
        out[pk.P_GATE_K] = self.gate_k
        out[pk.P_CAUCHY_M] = self.gate_m * CAUCHY_PER_GATE
        out[pk.P_IRLS_ITER] = self.irls_iter
        return out


class PropSolver:
    """One prop's per-frame fit. ``bind(labels)`` when a stream's label set is
    known, then ``solve(markers_world, valid)`` per frame: ``quat`` (w x y z,
    world_from_prop), ``pos`` (metres, world) and ``stats`` hold the result.

    Args:
        layout: the calibrated prop.
        params: the fit's parameters.
    """

    def __init__(self, layout: PropLayout, params: PropParams | None = None) -> None:
        self.layout = layout
        self.params = params or PropParams()
        k = len(layout.labels)
        self._layout = np.ascontiguousarray(layout.layout_prop_m, dtype=np.float64)
        self._layout_d = np.linalg.norm(
            self._layout[:, None] - self._layout[None], axis=2
        )
        self._weights = np.ascontiguousarray(layout.weights, dtype=np.float64)
        self._params = self.params.array()
        self.cols = np.full(k, -1, dtype=np.int64)
        self.state = np.zeros(pk.N_STATE)
        self.quat = np.array([1.0, 0.0, 0.0, 0.0])
        self.pos = np.zeros(3)
        self.stats = np.zeros(pk.N_STATS)
        self.flags = pk.FLAG_NEVER | pk.FLAG_HELD
        self._scratch = np.zeros(4 * k + 14)
        self._seen = np.zeros(k, dtype=np.bool_)
        self._keep = np.zeros(k, dtype=np.bool_)
        self._alt = np.zeros(k, dtype=np.bool_)
        self._n44 = np.zeros((4, 4))
        self._v44 = np.zeros((4, 4))
        self._call: Any = None
        self._bound: Any = None

    def bind(self, labels: Sequence[str]) -> int:
        """Find the prop's markers among a stream's labels; returns how many."""
        index = {name: i for i, name in enumerate(labels)}
        for i, name in enumerate(self.layout.labels):
            self.cols[i] = index.get(name, -1)
        return int(np.count_nonzero(self.cols >= 0))

    def reset(self) -> None:
        """Forget the last pose (a new stream)."""
        self.state[:] = 0.0

    def solve(self, markers_world: F64Array, valid: BoolArray) -> int:
        """Fit this frame; returns the flags (``kernel.FLAG_*``)."""
        args = (
            self._layout, self._layout_d, self._weights, self.cols,
            markers_world, valid, self._params, self.state,
            self.quat, self.pos, self.stats,
            self._scratch, self._seen, self._keep, self._alt, self._n44, self._v44,
        )  # fmt: skip
        key = (
            markers_world.dtype, markers_world.flags.c_contiguous, markers_world.ndim,
            valid.dtype, valid.flags.c_contiguous, valid.ndim,
        )  # fmt: skip
        if key != self._bound:
            # the compiled entry for these argument types, skipping the dispatcher's
            # per-call type resolution (compiled.direct); the other arrays are ours
            self._call = direct(pk.solve_prop, *args)
            if self._call is pk.solve_prop:  # not compiled yet: compile, then bind
                pk.solve_prop(*args)
                self._call = direct(pk.solve_prop, *args)
            self._bound = key
        self.flags = int(self._call(*args))
        return self.flags


@dataclass(frozen=True, slots=True, kw_only=True)
class PropTrack:
    """A prop solved over a take: per frame the pose, flags and residual."""

    name: str
    world_from_prop_quat: F64Array  # (T, 4) w x y z
    prop_pos_world: F64Array  # (T, 3) metres
    flags: np.ndarray  # (T,) int64
    rms_m: F64Array  # (T,) NaN when held
    used: np.ndarray  # (T,) int64 markers fitted
    swaps: np.ndarray  # (T,) int64


def solve_take(
    layout: PropLayout,
    labels: Sequence[str],
    positions: F64Array,
    valid: BoolArray,
    params: PropParams | None = None,
) -> PropTrack:
    """Solve the prop on every frame of a take (positions (T, M, 3), valid (T, M))."""
    solver = PropSolver(layout, params)
    solver.bind(labels)
    n = positions.shape[0]
    quat = np.empty((n, 4))
    pos = np.empty((n, 3))
    flags = np.empty(n, dtype=np.int64)
    rms = np.empty(n)
    used = np.empty(n, dtype=np.int64)
    swaps = np.empty(n, dtype=np.int64)
    pts = np.ascontiguousarray(positions, dtype=np.float64)
    ok = np.ascontiguousarray(valid, dtype=np.bool_)
    for f in range(n):
        flags[f] = solver.solve(pts[f], ok[f])
        quat[f] = solver.quat
        pos[f] = solver.pos
        rms[f] = solver.stats[pk.S_RMS_M]
        used[f] = solver.stats[pk.S_USED]
        swaps[f] = solver.stats[pk.S_SWAPS]
    return PropTrack(
        name=layout.name,
        world_from_prop_quat=quat,
        prop_pos_world=pos,
        flags=flags,
        rms_m=rms,
        used=used,
        swaps=swaps,
    )
