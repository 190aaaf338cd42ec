"""The pipeline of one performer on one stream (or view): everything that depends on
(rig, calibration, label set), built off the hot path when one of them changes and
reused for every frame (``send.BodyPath``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from retargetd.daemon.body.solve import BodySolver
from retargetd.daemon.body.solve_fit import FitSolver
from retargetd.daemon.live.emit import EmitPlan
from retargetd.daemon.live.face import FaceStage
from retargetd.daemon.post.pivot import SpinePivot
from retargetd.daemon.post.plant import FootPlant
from retargetd.daemon.post.solve_post import SolvePost
from retargetd.daemon.post.stance import StanceDetector
from retargetd.protocols import pose_stream
from retargetd.protocols.vmc_out import VmcEncoder


@dataclass(slots=True)
class Pipeline:
    """Everything that depends on (rig, calibration, label set); rebuilt off the hot
    path when one of them changes."""

    solver: BodySolver | FitSolver
    retargeter: Any
    pose: Any
    target_pose: Any
    vmc: VmcEncoder
    bone_pos_unity: np.ndarray
    bone_quat_xyzw: np.ndarray
    root_pos_unity: np.ndarray
    root_quat_xyzw: np.ndarray
    blend: np.ndarray
    pose_enc: pose_stream.PoseEncoder
    names_parts: list[bytes]
    weights: np.ndarray
    bone_flags: np.ndarray  # sent bone flags: the solve's | the latest validation's
    face: FaceStage | None = None
    # the face's shape-state message (RTDF, after each pose with a face)
    shape_enc: pose_stream.ShapeStateEncoder | None = None
    post: SolvePost | None = None  # the [[pipeline]] stages (None: none configured)
    tick_source_clock: bool = True  # resampled ticks' times are the source's clock
    spine: SpinePivot | None = None  # [target] spine = "pivot", after the retarget
    emit: EmitPlan | None = None  # the one compiled call per frame (live/emit.py)
    stance: StanceDetector | None = None  # foot contact (post/stance.py)
    stance_bits: int = 0  # its FRAME_CONTACT_* bits for the latest solved frame
    plant: FootPlant | None = None  # [target] feet = "plant", after the retarget
    # the last solved frame's source time, frame number and receive time (the fit's
    # frame time, BodyPath._frame_dt_s)
    last_times: tuple[float, int, int] = (math.nan, -1, 0)
