"""The fit's Newton matrix (issue 28 item 7): ``fit_newton.add_curvature`` gives the
normal equations the markers' own curvature, the Cauchy loss's along each residual
and the skeleton's (its rotations' second derivative), which the Gauss-Newton matrix
of ``fit_normal.build_normal`` leaves out. Checked against the marker cost's
curvature measured by finite differences along random steps, at a pose whose
markers sit 0-19 mm off (inside the 20 mm Cauchy scale, where the loss is convex
along each residual and the Newton matrix is exact; past it add_curvature keeps the
matrix positive semi-definite instead).
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np

from retargetd.daemon.body import fit_terms as ft
from retargetd.daemon.body.calibration import calibrate
from retargetd.daemon.body.fit_newton import add_curvature
from retargetd.daemon.body.fit_normal import apply_step, build_normal
from retargetd.daemon.body.method import make_body_solver
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.synth import performer as pf
from retargetd.daemon.validate.limits import JOINT_LIMITS_DEG
from retargetd.daemon.validate.model import SEGMENT_KIND

RATE_HZ = 120.0


@functools.cache
def _solved() -> Any:
    """Plug-in Gait on the synthetic performer, 1 s solved: the solver's state."""
    take = pf.synthesize(seconds=1.0, rate_hz=RATE_HZ, markerset="plug-in-gait")
    rig = load_rig("plug-in-gait")
    cal = calibrate(rig, take.markers_world[take.base_pose_frames], take.labels)
    fit = make_body_solver(
        "fit", rig, cal, take.labels,
        joint_limits=JOINT_LIMITS_DEG, segment_kind=SEGMENT_KIND, rate_hz=RATE_HZ,
    )  # fmt: skip
    fit.solve_take(take.markers_world)
    return fit


def _dense(m: tuple, hh: np.ndarray) -> np.ndarray:
    """H from its 3 x 3 blocks (``fit_model``: node_ptr, node_idx)."""
    node_ptr, node_idx = m[16], m[17]
    n_nodes = len(node_ptr) - 1
    h = np.zeros((3 * n_nodes, 3 * n_nodes))
    for nd in range(n_nodes):
        h[3 * nd : 3 * nd + 3, 3 * nd : 3 * nd + 3] = hh[nd]
        for e in range(node_ptr[nd], node_ptr[nd + 1]):
            a = node_idx[e]
            blk = hh[n_nodes + e]  # rows: the ancestor a, cols: nd
            h[3 * a : 3 * a + 3, 3 * nd : 3 * nd + 3] = blk
            h[3 * nd : 3 * nd + 3, 3 * a : 3 * a + 3] = blk.T
    return h


def _markers_at(m: tuple, s: tuple, x: np.ndarray) -> tuple[float, np.ndarray]:
    """The marker cost and the model's marker positions after the step x."""
    s[24][:] = x
    apply_step(m, s)
    ft.fk(m[0], m[1], m[2], s[6], s[7], s[30], s[31], s[32])
    c = ft.marker_cost(m, s, s[31], s[32], s[33], s[34], s[35], False)
    return c, s[33].copy()


def test_newton_matrix_has_the_marker_costs_curvature() -> None:
    """Along random steps, the curvature add_curvature adds to the Gauss-Newton
    matrix is the marker cost's (finite differences) less the Gauss-Newton part
    (IRLS weight x |J x|^2), within 1 % of the Gauss-Newton part (the Gauss-Newton
    matrix alone misses it by more than 10 %)."""
    fit = _solved()
    m, s = fit._model, fit._state
    rng = np.random.default_rng(1)
    vis = s[13]
    s[45][:] = False  # none gated out
    s[58][:] = 0.0  # no stand-in
    ft.fk(m[0], m[1], m[2], s[0], s[1], s[29], s[8], s[9])
    ft.marker_cost(m, s, s[8], s[9], s[10], s[14], s[15], False)
    off = rng.normal(size=(len(vis), 3))
    c = float(m[18][ft.P_CAUCHY_M])
    off *= (rng.uniform(0.0, 0.95 * c, len(vis)) / np.linalg.norm(off, axis=1))[:, None]
    s[12][:] = np.where(vis[:, None], s[10] + off, np.nan)
    ft.marker_cost(m, s, s[8], s[9], s[10], s[14], s[15], False)
    wrob = s[15].copy()
    assert (np.linalg.norm(s[14][vis], axis=1) > 0.5 * c).sum() >= 10
    ft.reg_cost(m, s, s[0], s[1], s[65])
    build_normal(m, s)
    h_gn = _dense(m, s[21])
    add_curvature(m, s)
    h_newton = _dense(m, s[21])
    a = 1e-3
    for _ in range(5):
        x = rng.normal(size=h_gn.shape[0])
        x *= 1.0 / np.abs(x).max()
        c0, _p0 = _markers_at(m, s, 0.0 * x)
        cp, pp = _markers_at(m, s, a * x)
        cn, pn = _markers_at(m, s, -a * x)
        true = (cp - 2.0 * c0 + cn) / a**2
        jx = (pp - pn) / (2.0 * a)
        gn = float(np.sum(wrob * np.sum(jx * jx, axis=1)))
        added = float(x @ (h_newton - h_gn) @ x)
        print(f"\ncurvature along x: true {true:.4e}, Gauss-Newton {gn:.4e}, "
              f"Gauss-Newton + added {gn + added:.4e}")  # fmt: skip
        assert abs(true - gn) > 0.1 * gn
        assert abs(gn + added - true) < 0.01 * gn
