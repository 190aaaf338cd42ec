"""``[[pipeline]]`` entries: stages built for a skeleton, applied in the listed order,
timed per stage, no allocation; bad entries named."""

from __future__ import annotations

import tomllib
import tracemalloc

import numpy as np
import pytest

from retargetd.daemon.post.one_euro import OneEuroFilter
from retargetd.daemon.post.pipeline import build_pipeline
from retargetd.daemon.post.pose import PoseBuffer
from retargetd.daemon.post.twist import TwistDistribution, arm_chains
from retargetd.daemon.synth import performer as pf

CONFIG = """
[[pipeline]]
kind = "twist"
fractions = [0.2, 0.3, 0.5]

[[pipeline]]
kind = "one_euro"
min_cutoff_hz = 1.5
beta_rot = 0.5
"""


def test_stages_in_order_equal_the_stages_by_hand(forearm_twist: pf.SynthTake) -> None:
    take = forearm_twist
    names, parents = take.segment_names, take.segment_parents
    entries = tomllib.loads(CONFIG)["pipeline"]
    pipe = build_pipeline(entries, bone_names=names, bone_parents=parents)
    assert pipe.kinds == ("twist", "one_euro")
    twist = TwistDistribution(parents, arm_chains(names), (0.2, 0.3, 0.5))
    euro = OneEuroFilter(len(names), min_cutoff_hz=1.5, beta_rot=0.5)
    pose, out, ref = (PoseBuffer.new(len(names)) for _ in range(3))
    for t in range(200):
        pose.t_s = float(take.times_s[t])
        pose.parent_from_bone_quat[:] = take.parent_from_segment_quat[t]
        pose.root_pos[:] = take.joint_pos_world[t, 0]
        assert pipe.apply(pose, out) is out
        euro.apply(twist.apply(pose, ref), ref)
        np.testing.assert_array_equal(
            out.parent_from_bone_quat, ref.parent_from_bone_quat
        )
        np.testing.assert_array_equal(out.root_pos, ref.root_pos)
    assert np.all(pipe.stage_ns > 0)
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        start, _ = tracemalloc.get_traced_memory()
        for _ in range(1000):
            pose.t_s += 0.01
            pipe.apply(pose, out)
        end, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert end - start < 1024
    assert peak - start < 3072, peak - start  # numba's argument boxing, per call


def test_empty_pipeline_copies() -> None:
    pipe = build_pipeline([], bone_names=["a", "b"], bone_parents=[-1, 0])
    pose, out = PoseBuffer.new(2), PoseBuffer.new(2)
    pose.root_pos[:] = [1.0, 2.0, 3.0]
    np.testing.assert_array_equal(pipe.apply(pose, out).root_pos, [1.0, 2.0, 3.0])


def test_bad_entries_are_named() -> None:
    kw = {"bone_names": pf.SEGMENT_NAMES, "bone_parents": pf.make_skeleton().parents}
    with pytest.raises(ValueError, match=r"pipeline\[0\]: kind must be one of"):
        build_pipeline([{"kind": "blur"}], **kw)  # type: ignore[arg-type]
    with pytest.raises(
        ValueError, match=r"pipeline\[1\] \(one_euro\): unknown keys \['beta'\]"
    ):
        build_pipeline([{"kind": "twist"}, {"kind": "one_euro", "beta": 1}], **kw)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"pipeline\[0\] \(twist\): fractions"):
        build_pipeline([{"kind": "twist", "fractions": [1, 1, 1]}], **kw)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="no arm chains"):
        build_pipeline([{"kind": "twist"}], bone_names=["a"], bone_parents=[-1])
