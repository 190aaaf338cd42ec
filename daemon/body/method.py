"""Which body solve to use: the chapter's construction or the rigid-skeleton fit.

``method = "construction"`` builds each bone from its own markers' points
(:class:`~retargetd.daemon.body.solve.BodySolver`: exact on clean data, ~5 us a
frame); ``method = "fit"`` fits the calibrated skeleton as a rigid chain to every
visible marker (:class:`~retargetd.daemon.body.solve_fit.FitSolver`: no freezes or
jumps when a marker hides, outliers gated, ~40-50 us a frame). Both take the same
calibration file: the fit attaches the markers to their bones from the base pose's
mean marker positions the calibration stores (``base_marker_pos``). The README
("Two ways to solve the body") says when each is right.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from retargetd.daemon.body.calibration import Calibration, CalibrationError
from retargetd.daemon.body.fit_model import build_fit_model
from retargetd.daemon.body.rig import Rig
from retargetd.daemon.body.solve import BodySolver
from retargetd.daemon.body.solve_fit import FitSolver

#: The methods, the default first (README "Two ways to solve the body").
METHODS = ("fit", "construction")


def make_body_solver(
    method: str,
    rig: Rig,
    calibration: Calibration,
    labels: Sequence[str],
    *,
    joint_limits: Mapping[str, Any] | None = None,
    segment_kind: Mapping[str, str] | None = None,
    rate_hz: float = 120.0,
) -> BodySolver | FitSolver:
    """A solver of ``method`` for this marker layout (same interface either way).

    Args:
        method: ``"construction"`` or ``"fit"``.
        rig, calibration: the rig and its calibration.
        labels: (M,) the stream's or take's marker labels.
        joint_limits: the validator's joint-limit table (the fit's soft penalty;
            ``validate.limits.JOINT_LIMITS_DEG``), None for no penalty.
        segment_kind: humanoid bone -> segment kind (``validate.model.SEGMENT_KIND``).
        rate_hz: the frames' rate (the fit's continuity prior; the construction
            has none).

    Raises:
        ValueError: an unknown method.
        CalibrationError: the fit with a calibration that has no base-pose marker
            positions (made before they were stored: recalibrate).
    """
    if method == "construction":
        return BodySolver(rig, calibration, labels)
    if method != "fit":
        raise ValueError(f"method must be one of {METHODS}; got {method!r}")
    base = calibration.base_marker_pos
    if base is None or not np.isfinite(base).all(axis=1).any():
        raise CalibrationError(
            f"calibration of rig {calibration.rig_name} has no base-pose marker "
            "positions (it predates the fit): recalibrate to use method 'fit'"
        )
    if calibration.rest_bone_origin_pos is None:
        raise CalibrationError(
            f"calibration of rig {calibration.rig_name} has no bone rest origins "
            "(it predates them): recalibrate to use method 'fit'"
        )
    # The calibration's base-pose means are already in rig-marker order: the model
    # takes them as they are. Matching the rig's own marker names as if they were
    # take labels lost every marker whose name is not also one of its aliases.
    model = build_fit_model(
        rig,
        calibration,
        base[None],
        None,
        joint_limits=joint_limits,
        segment_kind=segment_kind,
        layout_positions=calibration.layout_marker_pos,
    )
    return FitSolver(rig, calibration, labels, model=model, rate_hz=rate_hz)
