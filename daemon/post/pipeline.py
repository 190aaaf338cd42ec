"""The pose pipeline: post stages in the order a config lists them.

Config (TOML), one table per stage, applied in the order listed::

    [[pipeline]]
    kind = "twist"                   # TwistDistribution
    fractions = [0.3333333333333333, 0.3333333333333333, 0.3333333333333334]

    [[pipeline]]
    kind = "one_euro"                # OneEuroFilter
    min_cutoff_hz = 1.0
    beta_rot = 0.5
    beta_pos = 5.0

Kinds and their keys (all optional; defaults as in the stage's module):

- ``twist``: ``fractions`` (shoulder, elbow, wrist), ``axis`` (+Y). Chains: the arms
  :func:`~retargetd.daemon.post.twist.arm_chains` finds in the skeleton.
- ``one_euro``: ``min_cutoff_hz``, ``beta_rot``, ``beta_pos``, ``d_cutoff_hz``.

These act on the solved skeleton's pose (:class:`PoseBuffer`, B bones) in place. The
shifting pivot and the Hermite spine write a target's spine bones (UpperChest is on no
rig), and the output rate changes the number of poses, so they are not pipeline
kinds: the pivot is the target option ``[target] spine = "pivot"``
(:class:`~retargetd.daemon.post.pivot.SpinePivot`, after the target mapping), the
Hermite spine ``retarget --spread hermite``
(:func:`~retargetd.daemon.post.hermite.hermite_chain`), the rate ``output_rate_hz``
(:class:`~retargetd.daemon.post.interp.RateResampler`).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Protocol

import numpy as np

from retargetd.daemon.post.one_euro import OneEuroFilter
from retargetd.daemon.post.pose import PoseBuffer
from retargetd.daemon.post.twist import LONG_AXIS, TwistDistribution, arm_chains
from retargetd.protocols.frames import F64Array


class PoseStage(Protocol):
    """A per-frame stage on the solved pose."""

    def apply(self, pose: PoseBuffer, out: PoseBuffer) -> PoseBuffer:
        """Process ``pose`` into ``out`` (which may be ``pose``); return ``out``."""
        ...


def _twist(
    params: Mapping[str, Any],
    names: Sequence[str],
    parents: Sequence[int],
    rest: F64Array | None,
) -> PoseStage:
    chains = arm_chains(names)
    if not chains:
        raise ValueError("pipeline kind 'twist': the skeleton has no arm chains")
    kwargs: dict[str, Any] = {"rest_parent_from_bone_quat": rest}
    if "fractions" in params:
        kwargs["fractions"] = tuple(float(f) for f in params["fractions"])
    kwargs["axis"] = tuple(float(a) for a in params.get("axis", LONG_AXIS))
    return TwistDistribution(parents, chains, **kwargs)


def _one_euro(
    params: Mapping[str, Any],
    names: Sequence[str],
    parents: Sequence[int],
    rest: F64Array | None,
) -> PoseStage:
    del parents, rest  # unused: the filter works on every bone
    return OneEuroFilter(len(names), **{k: float(v) for k, v in params.items()})


_Builder = Callable[
    [Mapping[str, Any], Sequence[str], Sequence[int], "F64Array | None"], PoseStage
]
#: kind -> (allowed keys, builder).
KINDS: dict[str, tuple[frozenset[str], _Builder]] = {
    "twist": (frozenset({"fractions", "axis"}), _twist),
    "one_euro": (
        frozenset({"min_cutoff_hz", "beta_rot", "beta_pos", "d_cutoff_hz"}),
        _one_euro,
    ),
}


class Pipeline:
    """Stages applied in order, each timed.

    Built by :func:`build_pipeline`. ``stage_ns`` holds the last call's wall time per
    stage (int64 nanoseconds, ``time.perf_counter_ns``) for the per-stage latency
    statistics.

    Args:
        kinds: (S,) the stages' kinds, in order.
        stages: (S,) the stage objects.
    """

    def __init__(self, kinds: Sequence[str], stages: Sequence[PoseStage]) -> None:
        self.kinds = tuple(kinds)
        self.stages = tuple(stages)
        self.stage_ns = np.zeros(len(self.stages), dtype=np.int64)

    def apply(self, pose: PoseBuffer, out: PoseBuffer) -> PoseBuffer:
        """Run every stage on one pose.

        Args:
            pose: the solved pose.
            out: the destination (may be ``pose``).

        Returns:
            ``out``.
        """
        if out is not pose:
            out.copy_from(pose)
        clock = time.perf_counter_ns
        for i, stage in enumerate(self.stages):
            t0 = clock()
            stage.apply(out, out)
            self.stage_ns[i] = clock() - t0
        return out


def build_pipeline(
    entries: Sequence[Mapping[str, Any]],
    *,
    bone_names: Sequence[str],
    bone_parents: Sequence[int],
    rest_parent_from_bone_quat: F64Array | None = None,
) -> Pipeline:
    """Build the stages of ``[[pipeline]]`` entries for one skeleton.

    Args:
        entries: the config's ``pipeline`` array of tables (``kind`` plus keys).
        bone_names: (B,) the solved skeleton's bones.
        bone_parents: (B,) parent index per bone, -1 for the root.
        rest_parent_from_bone_quat: (B, 4) float64 (w, x, y, z): the calibration's
            rest rotations (the pose the stages see is ``rest ⊗ solve``).

    Returns:
        The pipeline (no stages for an empty list).

    Raises:
        ValueError: naming the entry, an unknown kind or key, or a bad value.
    """
    kinds, stages = [], []
    for n, entry in enumerate(entries):
        kind = entry.get("kind")
        if kind not in KINDS:
            raise ValueError(
                f"pipeline[{n}]: kind must be one of {sorted(KINDS)}; got {kind!r}"
            )
        allowed, builder = KINDS[kind]
        params = {k: v for k, v in entry.items() if k != "kind"}
        unknown = sorted(set(params) - allowed)
        if unknown:
            raise ValueError(
                f"pipeline[{n}] ({kind}): unknown keys {unknown}; allowed "
                f"{sorted(allowed)}"
            )
        try:
            stages.append(
                builder(params, bone_names, bone_parents, rest_parent_from_bone_quat)
            )
        except (TypeError, ValueError) as exc:
            raise ValueError(f"pipeline[{n}] ({kind}): {exc}") from exc
        kinds.append(kind)
    return Pipeline(kinds, stages)
