"""Degenerate marker layouts never raise and never give a NaN rotation (issue 12).

Capture systems send zeros for occluded markers, two markers can coincide (a ghost
merged onto a real marker), three can line up, a value can be huge or NaN. numba's
default ``error_model="python"`` raised ``ZeroDivisionError`` on a zero-length axis
where the kernel expected NaN to propagate (11 of the 561 pairs of the Plug-in Gait
walk's markers at (0, 0, 0) crashed the live daemon); the kernels now use NumPy's
error model, and a bone whose points are degenerate holds and is flagged.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from paths import require_datasets

from retargetd.daemon.body.calibration import calibrate
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.body.solve import FLAG_HELD, BodyPose, BodySolver
from retargetd.daemon.face import solve as sf
from retargetd.replay.takes import load_take


@pytest.fixture(scope="module")
def pig() -> tuple[BodySolver, np.ndarray]:
    root = require_datasets()
    rig = load_rig("plug-in-gait")
    static = load_take(root / "btkdata/PiG_Calibration-FlatFoot-Full.c3d")
    cal = calibrate(rig, static.positions[:50], static.labels)
    walk = load_take(root / "btkdata/PiG_Motion-FlatFoot-Full.c3d")
    return BodySolver(rig, cal, walk.labels), walk.positions[100].copy()


def _check(pose: BodyPose) -> None:
    q = pose.world_from_bone_quat
    assert np.isfinite(q).all()
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-9)
    assert np.isfinite(pose.rest_from_bone_quat).all()
    assert np.isfinite(pose.root_pos).all()


def test_every_pair_of_markers_at_the_origin(
    pig: tuple[BodySolver, np.ndarray],
) -> None:
    solver, frame = pig
    pose = solver.new_pose()
    cols = [int(c) for c in solver.marker_cols if c >= 0]
    held_any = 0
    for a, b in itertools.combinations(cols, 2):
        f = frame.copy()
        f[a] = 0.0
        f[b] = 0.0
        solver.reset()
        solver.solve_frame(f, pose)
        _check(pose)
        held_any += bool(np.any(pose.bone_flags & FLAG_HELD))
    # Coincident zeros make some bone's axis or up lever vanish: it holds, flagged.
    assert held_any > 0


def test_coincident_collinear_huge_markers(pig: tuple[BodySolver, np.ndarray]) -> None:
    solver, frame = pig
    pose = solver.new_pose()
    cols = [int(c) for c in solver.marker_cols if c >= 0]
    for a, b, c in itertools.combinations(cols[:14], 3):
        for how in ("coincide", "collinear", "huge", "nan"):
            f = frame.copy()
            if how == "coincide":
                f[b] = f[a]
                f[c] = f[a]
            elif how == "collinear":
                f[c] = f[a] + 2.0 * (f[b] - f[a])
            elif how == "huge":
                f[a] = 1e30
                f[b] = -1e30
            else:
                f[[a, b, c]] = np.nan
            solver.solve_frame(f, pose)
            _check(pose)


@settings(
    max_examples=300,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(
    data=st.lists(
        st.tuples(
            st.integers(0, 33),
            st.sampled_from(["zero", "copy", "nan", "huge", "tiny", "line"]),
            st.integers(0, 33),
        ),
        min_size=1,
        max_size=12,
    )
)
def test_fuzzed_degenerate_frames(
    pig: tuple[BodySolver, np.ndarray], data: list[tuple[int, str, int]]
) -> None:
    solver, frame = pig
    pose = solver.new_pose()
    cols = [int(c) for c in solver.marker_cols if c >= 0]
    f = frame.copy()
    for i, how, j in data:
        a, b = cols[i % len(cols)], cols[j % len(cols)]
        if how == "zero":
            f[a] = 0.0
        elif how == "copy":
            f[a] = f[b]
        elif how == "nan":
            f[a] = np.nan
        elif how == "huge":
            f[a] = 1e300
        elif how == "tiny":
            f[a] = f[b] + 1e-300
        else:
            f[a] = 0.5 * (f[b] + f[cols[0]])
    solver.solve_frame(f, pose)
    _check(pose)


def _face_solver() -> sf.FaceSolver:
    rng = np.random.default_rng(0)
    head = rng.normal(0.0, 0.06, (4, 3))
    tr = sf.TrainingSet(
        head_names=("H0", "H1", "H2", "H3"),
        marker_names=tuple(f"M{i}" for i in range(10)),
        expression_names=tuple(f"E{i}" for i in range(5)),
        head_layout=head - head.mean(axis=0),
        neutral=rng.normal(0.0, 0.05, (10, 3)),
        deltas=rng.normal(0.0, 0.005, (5, 10, 3)),
    )
    return sf.FaceSolver(tr)


@settings(max_examples=300, deadline=None)
@given(
    how=st.lists(
        st.tuples(
            st.integers(0, 13),
            st.sampled_from(["zero", "copy0", "nan", "huge", "line"]),
        ),
        min_size=1,
        max_size=14,
    )
)
def test_face_kernel_degenerate_frames(how: list[tuple[int, str]]) -> None:
    solver = _face_solver()
    out = solver.new_output()
    tr = solver.training
    rng = np.random.default_rng(1)
    markers = np.concatenate([tr.head_layout, tr.neutral]) + rng.normal(
        0, 1e-4, (14, 3)
    )
    for i, kind in how:
        if kind == "zero":
            markers[i] = 0.0
        elif kind == "copy0":
            markers[i] = markers[0]
        elif kind == "nan":
            markers[i] = np.nan
        elif kind == "huge":
            markers[i] = 1e300
        else:
            markers[i] = markers[0] + (i + 1) * (markers[1] - markers[0])
    valid = np.isfinite(markers).all(axis=1)
    for _ in range(3):
        solver.solve_frame(markers, valid, out)
        assert np.isfinite(out.world_from_head_quat).all()
        assert np.isfinite(out.weights).all()
        assert np.all((out.weights >= 0.0) & (out.weights <= 1.0))
