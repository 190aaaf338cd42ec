"""The prop's rigid fit (``daemon/props``): against scipy's Kabsch as the oracle, the
hold below 3 markers, the consensus that rejects swapped labels, the gate, the
calibration and its file, and the hot-path contract (results in the same buffers)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from retargetd.daemon.props import kernel as pk
from retargetd.daemon.props.layout import (
    PropError,
    ambiguous_pairs,
    calibrate_prop,
    load_layout,
)
from retargetd.daemon.props.solve import PropSolver, solve_take

#: A virtual camera rig's 5 markers, metres (an asymmetric cluster, ~30 cm across).
CAMERA = np.array(
    [
        [0.00, 0.00, 0.00],
        [0.16, 0.02, 0.00],
        [-0.12, 0.05, 0.03],
        [0.02, 0.21, 0.06],
        [0.05, -0.04, 0.14],
    ]
)
LABELS = [f"cam:{i}" for i in range(5)]


def _layout(rng: np.random.Generator, noise_m: float = 0.0):
    still = np.repeat(CAMERA[None] + [0.5, 1.0, 1.4], 40, 0)
    still = still + rng.normal(0.0, noise_m, still.shape)
    return calibrate_prop(still, LABELS, name="cam", kind="camera", rate_hz=100.0)


def _frames(layout, rng, n=120, noise_m=0.0005):
    rots = Rotation.random(n, random_state=rng.integers(1 << 30))
    pos = rng.normal(0.0, 1.0, (n, 3))
    lp = np.array(layout.layout_prop_m)
    pts = np.stack([rots[i].apply(lp) + pos[i] for i in range(n)])
    return rots, pos, pts + rng.normal(0.0, noise_m, pts.shape)


def _rot_err_deg(quat: np.ndarray, rots: Rotation) -> np.ndarray:
    return np.degrees(
        (Rotation.from_quat(quat, scalar_first=True) * rots.inv()).magnitude()
    )


@pytest.mark.parametrize(("noise_m", "tol_deg"), [(0.0, 1e-6), (0.0005, 0.1)])
def test_fit_matches_scipy_kabsch(
    rng: np.random.Generator, noise_m: float, tol_deg: float
) -> None:
    # Exact data: the fit is the least-squares rotation. Noisy: the Cauchy weights
    # move it from the unweighted oracle by a fraction of the noise's own error.
    layout = _layout(rng)
    _rots, _pos, pts = _frames(layout, rng, n=30, noise_m=noise_m)
    track = solve_take(layout, LABELS, pts, np.ones(pts.shape[:2], bool))
    lp = np.array(layout.layout_prop_m)
    for f in range(30):
        c = pts[f].mean(axis=0)
        oracle, _ = Rotation.align_vectors(pts[f] - c, lp - lp.mean(axis=0))
        ours = Rotation.from_quat(track.world_from_prop_quat[f], scalar_first=True)
        assert np.degrees((ours * oracle.inv()).magnitude()) < tol_deg
        np.testing.assert_allclose(
            track.prop_pos_world[f],
            c - oracle.apply(lp.mean(axis=0)),
            atol=1e-9 if noise_m == 0 else 1e-3,
        )
    assert np.all(track.flags == 0) and np.all(track.used == 5)


def test_solver_writes_into_its_own_buffers(rng: np.random.Generator) -> None:
    layout = _layout(rng)
    _rots, _pos, pts = _frames(layout, rng, n=3)
    solver = PropSolver(layout)
    assert solver.bind(["x", *LABELS]) == 5
    quat, pos, stats = solver.quat, solver.pos, solver.stats
    frame = np.concatenate([np.full((1, 3), 9.0), pts[0]])
    valid = np.ones(6, bool)
    assert solver.solve(frame, valid) == 0
    assert solver.quat is quat and solver.pos is pos and solver.stats is stats
    assert quat.dtype == np.float64 and stats[pk.S_USED] == 5


def test_fewer_than_three_holds_and_flags(rng: np.random.Generator) -> None:
    layout = _layout(rng)
    _rots, _pos, pts = _frames(layout, rng, n=2)
    solver = PropSolver(layout)
    solver.bind(LABELS)
    valid = np.zeros(5, bool)
    valid[:2] = True
    flags = solver.solve(pts[0], valid)
    assert flags & pk.FLAG_HELD and flags & pk.FLAG_NEVER
    np.testing.assert_array_equal(solver.quat, [1.0, 0.0, 0.0, 0.0])
    assert solver.solve(pts[0], np.ones(5, bool)) == 0
    good_q, good_p = solver.quat.copy(), solver.pos.copy()
    flags = solver.solve(pts[1], valid)
    assert flags == pk.FLAG_HELD
    np.testing.assert_array_equal(solver.quat, good_q)
    np.testing.assert_array_equal(solver.pos, good_p)
    assert np.isnan(solver.stats[pk.S_RMS_M])


def test_one_hidden_marker_keeps_the_pose(rng: np.random.Generator) -> None:
    layout = _layout(rng)
    rots, _pos, pts = _frames(layout, rng)
    valid = np.ones(pts.shape[:2], bool)
    full = solve_take(layout, LABELS, pts, valid)
    for hidden in range(5):
        v = valid.copy()
        v[:, hidden] = False
        part = solve_take(layout, LABELS, pts, v)
        assert np.all(part.flags == pk.FLAG_PARTIAL) and np.all(part.used == 4)
        d = _rot_err_deg(
            part.world_from_prop_quat,
            Rotation.from_quat(full.world_from_prop_quat, scalar_first=True),
        )
        # 0.5 mm noise on a ~25 cm cluster: one marker fewer moves the fit by
        # under 0.5 deg on 95 % of frames (the bound) and under 1 deg on all
        assert np.percentile(d, 95) < 0.5 and d.max() < 1.0, (hidden, d.max())
        assert np.percentile(_rot_err_deg(part.world_from_prop_quat, rots), 95) < 1.0


@pytest.mark.parametrize(("a", "b"), [(0, 1), (1, 3), (2, 4), (0, 4)])
def test_two_swapped_labels_are_rejected(
    rng: np.random.Generator, a: int, b: int
) -> None:
    layout = _layout(rng)
    rots, _pos, pts = _frames(layout, rng, n=40)
    pts[:, [a, b]] = pts[:, [b, a]]
    track = solve_take(layout, LABELS, pts, np.ones(pts.shape[:2], bool))
    # 3 of 5 agree: solved from them, the swap seen and left out
    assert np.all(track.flags == pk.FLAG_PARTIAL | pk.FLAG_SWAP)
    assert np.all(track.used == 3) and np.all(track.swaps == 1)
    assert _rot_err_deg(track.world_from_prop_quat, rots).max() < 1.5


def test_a_swap_leaving_two_holds(rng: np.random.Generator) -> None:
    layout = _layout(rng)
    _rots, _pos, pts = _frames(layout, rng, n=2)
    solver = PropSolver(layout)
    solver.bind(LABELS)
    solver.solve(pts[0], np.ones(5, bool))
    held_q = solver.quat.copy()
    frame = pts[1].copy()
    frame[[0, 1]] = frame[[1, 0]]
    valid = np.array([True, True, True, True, False])
    frame[[2]] = frame[[2]] + 0.3  # a ghost: one of the other two is wrong too
    flags = solver.solve(frame, valid)
    assert flags & pk.FLAG_HELD
    np.testing.assert_array_equal(solver.quat, held_q)


def test_a_ghost_beyond_the_gate_is_gated(rng: np.random.Generator) -> None:
    layout = _layout(rng)
    rots, _pos, pts = _frames(layout, rng, n=20)
    pts[:, 3] += [0.0, 0.0, 0.03]  # 30 mm off: a ghost or a bent mount
    track = solve_take(layout, LABELS, pts, np.ones(pts.shape[:2], bool))
    assert np.all(track.used == 4) and np.all(track.flags == pk.FLAG_PARTIAL)
    assert _rot_err_deg(track.world_from_prop_quat, rots).max() < 1.0


def test_calibration_file_round_trip_and_errors(
    rng: np.random.Generator, tmp_path: Path
) -> None:
    layout = _layout(rng)
    np.testing.assert_allclose(layout.layout_prop_m.mean(axis=0), 0.0, atol=1e-12)
    path = tmp_path / "cam.json"
    layout.save(path)
    back = load_layout(path)
    assert back.labels == layout.labels and back.kind == "camera"
    np.testing.assert_array_equal(back.layout_prop_m, layout.layout_prop_m)
    doc = json.loads(path.read_text())
    doc["layout_prop_m"] = doc["layout_prop_m"][:2]
    path.write_text(json.dumps(doc))
    with pytest.raises(PropError, match="shape"):
        load_layout(path)
    line = np.stack([np.linspace(0, 1, 4), np.zeros(4), np.zeros(4)], axis=1)
    with pytest.raises(PropError, match="one line"):
        calibrate_prop(np.repeat(line[None], 5, 0), list("abcd"), name="x", rate_hz=100)
    moving = np.repeat(CAMERA[None], 30, 0) + np.linspace(0, 0.3, 30)[:, None, None]
    with pytest.raises(PropError, match="not still"):
        calibrate_prop(moving, LABELS, name="x", rate_hz=100)
    hidden = np.repeat(CAMERA[None], 5, 0)
    hidden[:, 2] = np.nan
    with pytest.raises(PropError, match="never seen"):
        calibrate_prop(hidden, LABELS, name="x", rate_hz=100)


def test_pivot_moves_the_origin(rng: np.random.Generator) -> None:
    still = np.repeat(CAMERA[None] + [0.5, 1.0, 1.4], 10, 0)
    base = calibrate_prop(still, LABELS, name="c", rate_hz=100)
    moved = calibrate_prop(still, LABELS, name="c", rate_hz=100, pivot_m=(0, 0, -0.1))
    np.testing.assert_allclose(
        moved.layout_prop_m - base.layout_prop_m, [[0, 0, 0.1]] * 5
    )
    track = solve_take(moved, LABELS, still[:1], np.ones((1, 5), bool))
    np.testing.assert_allclose(
        track.prop_pos_world[0],
        CAMERA.mean(0) + np.array([0.5, 1.0, 1.4 - 0.1]),
        atol=1e-12,
    )


def test_symmetric_pairs_are_named() -> None:
    # a and b mirror each other through the plane holding c and d
    kite = np.array([[-0.1, 0, 0], [0.1, 0, 0], [0, 0.15, 0], [0, 0, 0.2]])
    assert ambiguous_pairs(kite, 0.01, list("abcd")) == [("a", "b")]
    assert ambiguous_pairs(CAMERA, 0.01, LABELS) == []
