""":class:`SolvePost`: the pipeline on a body-solve pose in place, as the live loop
runs it: equal to the offline command's per-frame pipeline plus forward kinematics,
restarts on a clock step back or a gap, passes a non-finite pose unprocessed, no
allocation per frame."""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from live_harness import EXACT_RIG, RATE_HZ, _f32, _take

from retargetd.daemon.body.calibration import calibrate
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.body.solve import BodySolver
from retargetd.daemon.cli.post_io import apply_pipeline_to_solve
from retargetd.daemon.post.pipeline import build_pipeline
from retargetd.daemon.post.solve_post import RESTART_GAP_S, SolvePost

STAGES = [{"kind": "twist"}, {"kind": "one_euro", "beta_rot": 2.0, "beta_pos": 20.0}]
TOML = """
[[pipeline]]
kind = "twist"
[[pipeline]]
kind = "one_euro"
beta_rot = 2.0
beta_pos = 20.0
"""


def _setup() -> tuple[BodySolver, SolvePost, np.ndarray, object]:
    take = _take()
    rig = load_rig(EXACT_RIG)
    cal = calibrate(rig, _f32(take.markers_world[take.base_pose_frames]), take.labels)
    solver = BodySolver(rig, cal, take.labels)
    parents = rig.bone_parent_indices()
    post = SolvePost(
        build_pipeline(
            STAGES,
            bone_names=rig.bone_names,
            bone_parents=parents,
            rest_parent_from_bone_quat=cal.rest_parent_from_bone_quat,
        ),
        parents,
        cal.rest_parent_from_bone_quat,
    )
    return solver, post, _f32(take.markers_world), cal


def test_frame_by_frame_equals_the_offline_pipeline(tmp_path: Path) -> None:
    solver, post, markers, cal = _setup()
    frames = markers[60:200]
    path = tmp_path / "p.toml"
    path.write_text(TOML)
    offline, _ = apply_pipeline_to_solve(path, solver.solve_take(frames), cal, RATE_HZ)
    pose = solver.new_pose()
    solver_live = BodySolver(solver.rig, cal, solver.labels)
    for t, m in enumerate(frames):
        assert post.apply(solver_live.solve_frame(m, pose), t / RATE_HZ) is True
        for key in ("parent_from_bone_quat", "world_from_bone_quat",
                    "rest_from_bone_quat", "root_pos"):  # fmt: skip
            np.testing.assert_allclose(
                getattr(pose, key), getattr(offline, key)[t], rtol=0, atol=1e-12,
                err_msg=f"{key} frame {t}",
            )  # fmt: skip
    assert post.stage_names == ("twist", "one_euro")
    assert (post.stage_ns > 0).all()


def test_restarts_on_a_clock_step_back_or_a_gap_and_skips_non_finite() -> None:
    solver, post, markers, _cal = _setup()
    pose = solver.new_pose()
    for t in range(20):
        post.apply(solver.solve_frame(markers[60 + t], pose), t / RATE_HZ)
    assert post.restarts == 0
    # A still repeat (same time) is no restart.
    post.apply(solver.solve_frame(markers[79], pose), 19 / RATE_HZ)
    assert post.restarts == 0
    # Clock back (a looped take): the filter restarts, so the pose passes as solved
    # (twist only), not dragged from the old estimate.
    solver.solve_frame(markers[60], pose)
    twisted_only = pose.parent_from_bone_quat.copy()
    post.pipeline.stages[0].apply_quat(twisted_only, twisted_only)
    post.apply(pose, 0.0)
    assert post.restarts == 1
    np.testing.assert_allclose(pose.parent_from_bone_quat, twisted_only, atol=1e-12)
    post.apply(solver.solve_frame(markers[61], pose), 0.0 + RESTART_GAP_S + 0.5)
    assert post.restarts == 2
    # Not finite: passed through untouched, the filter restarted, counted.
    pose.parent_from_bone_quat[3, 0] = np.nan
    before = pose.parent_from_bone_quat.copy()
    post.apply(pose, 2.0)
    assert post.non_finite == 1 and post.restarts == 3
    np.testing.assert_array_equal(pose.parent_from_bone_quat, before)


@pytest.mark.timeout(60)
def test_no_allocation_per_frame() -> None:
    solver, post, markers, _cal = _setup()
    pose = solver.new_pose()
    solved = []
    for t in range(60, 100):
        solver.solve_frame(markers[t], pose)
        solved.append((pose.parent_from_bone_quat.copy(), pose.root_pos.copy()))
    for t in range(200):  # warm-up (compiles, caches)
        q, p = solved[t % len(solved)]
        pose.parent_from_bone_quat[:] = q
        post.apply(pose, t / RATE_HZ)
    tracemalloc.start()
    try:
        start, _ = tracemalloc.get_traced_memory()
        tracemalloc.reset_peak()
        for t in range(200, 1200):
            q, p = solved[t % len(solved)]
            np.copyto(pose.parent_from_bone_quat, q)
            np.copyto(pose.root_pos, p)
            post.apply(pose, t / RATE_HZ)
        end, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    print(f"\nSolvePost over 1000 frames: kept {end - start} B, peak {peak - start} B")
    assert end - start < 1024  # nothing kept per frame (1000 frames)
    # The kernels' argument boxing only (freed on return), never a pose-sized copy
    # per frame accumulating.
    assert peak - start < 4096
