"""The body solve by fitting a rigid skeleton to every visible marker.

:class:`FitSolver` has the interface of :class:`~retargetd.daemon.solve_body.BodySolver`
(``new_pose``, ``solve_frame``, ``solve_take``, ``reset``) and the same outputs, plus
per-frame marker residuals: it runs ``kernel_fit`` on the model of ``fit_model`` and
keeps a construction solver (``kernel.solve_one``) to seed the first frame and reseed
when the fit loses track. One frame at a time and the batch run the same compiled code.

Flags (``bone_flags`` bits, the construction's, same meaning): ``FLAG_HELD`` no
marker of the bone's own seen (the bone is carried by its neighbours and the pull to
the last frame); ``FLAG_PARTIAL`` some not seen. Per frame, ``FitPose.stats`` says
whether the frame was reseeded from the construction and how many markers the gate
rejected; ``marker_rejected`` says which; ``frame_flags`` carries
``pose_stream.FRAME_RESEEDED`` to the pose stream when the frame was reseeded.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from retargetd.daemon.body import fit_pack
from retargetd.daemon.body import fit_terms as ft
from retargetd.daemon.body import kernel_fit as kf
from retargetd.daemon.body.calibration import Calibration, calibrate
from retargetd.daemon.body.fit_model import (
    FitModel,
    FitOptions,
    JointLimitLike,
    build_fit_model,
)
from retargetd.daemon.body.rig import Rig, parse_rig
from retargetd.daemon.body.solve import (
    _WARM_RIG,
    FLAG_HELD,
    FLAG_PARTIAL,
    BodyPose,
    BodySolve,
    BodySolver,
)
from retargetd.protocols.frames import F64Array
from retargetd.protocols.pose_stream import FRAME_RESEEDED


def _empty() -> np.ndarray:
    return np.zeros(0)


__all__ = [
    "FLAG_HELD",
    "FLAG_PARTIAL",
    "FitParams",
    "FitPose",
    "FitSolve",
    "FitSolver",
]


@dataclass(frozen=True, slots=True, kw_only=True)
class FitParams:
    """The fit's weights and tests (SI units; see ``kernel_fit`` for the cost).

    Attributes:
        lambda_rot: m^2 / rad^2, pull of each joint to the last frame: the ratio of
            variances sigma_marker^2 / sigma_joint^2 with sigma_marker = 1 mm (optical
            systems' marker residuals; Merriaux et al., "A study of Vicon system
            positioning performance", Sensors 17(7):1591, 2017: < 1 mm) and
            sigma_joint = 0.1 rad per frame (12 rad/s at 120 Hz, above the peak joint
            speeds of walking and running, e.g. the knee's ~7 rad/s in sprinting,
            Novacheck, "The biomechanics of running", Gait Posture 7(1):77-95, 1998).
            A joint its markers determine has a marker curvature >= ~1e-2 m^2 (three
            markers 0.06 m or more from it), so the pull lags it by < 1 % of its
            frame-to-frame motion even when that is far faster (a serve's humeral
            rotation); what the markers leave undetermined, it holds.
        lambda_trans: m^2 / m^2, the same for each root's position with
            sigma = 0.08 m per frame (10 m/s, sprinting, at 120 Hz).
        kappa_limit: m^2 / rad^2, soft penalty past the validator's limits: 10 mm of
            residual per radian beyond, weaker than one marker on a 0.1 m lever, so
            markers that put a joint past its limit win and ``validate`` still sees it.
        kappa_hinge: m^2 / rad^2, a hinge's rotation off its axis: 1 m per radian,
            far above any marker residual, so the joint is a hinge in effect.
        cauchy_m: Cauchy scale of the marker residuals: 20 mm, the order of skin
            artefact on limb segments (Leardini et al., "Human movement analysis
            using stereophotogrammetry, part 3: soft tissue artifact", Gait Posture
            21(2):212-225, 2005: 10-30 mm), so artefact is down-weighted mildly and a
            swapped label (residual >= marker spacing) strongly.
        gate_m: a visible marker whose residual exceeds max(gate_m, gate_k x the
            frame's median residual) after the ungated fit is rejected for the frame
            (unless it moved less than that since its last accepted frame, see
            gate_memory):
            40 mm, past the largest soft-tissue artefact in the same review, below
            the 50-100 mm spacing of markers on one segment. (A Cauchy scale as
            large as the gate halves the iterations on the real walk but lets a
            marker the model fits poorly pull the skeleton: the Plug-in Gait rig on
            the synthetic performer, whose T10 sits 30-40 mm off its chest, moved
            the root 38 mm with an ASIS hidden.)
        gate_k: see gate_m (5: a factor that keeps the gate above the fit's own
            residual level when the model fits a performer loosely).
        gate_memory: frames. A marker past the gate is rejected only if its residual
            has also moved by more than the gate since its last accepted frame, when
            that frame is at most this many frames old (else on the level alone): a
            swapped label or a ghost jumps by a marker spacing, while skin sliding
            over a joint grows a residual over many frames (the acromion marker of
            the tennis serve as the arm rises: rejected on its level, the clavicle
            lost its only marker and drifted). 30 frames
            (0.125-0.5 s at 240-60 Hz); past it a swap is still caught on its
            level, since its residual is a marker spacing.
        reseed_rms_m: inlier RMS above which the fit has lost track: 25 mm, beyond
            the artefact level above.
        reseed_reject_frac: the fit has lost track when more than this fraction of
            the visible markers is rejected (a quarter: more than an occasional
            swap or ghost).
        max_iter: iteration cap per phase (the worst case is 4 phases: two fits, each
            ungated then gated).
        tol: step size (rad, m) at which the fit has converged: 1e-4 (0.1 mm,
            0.006 deg, a tenth of the marker noise floor above; Gauss-Newton's next
            step would be smaller still).
        ftol: or when an accepted step lowers the cost by less than this fraction
            (1e-5: what is left is a direction the markers hardly see).
    """

    lambda_rot: float = 1e-4
    lambda_trans: float = (1e-3 / 0.08) ** 2
    kappa_limit: float = 0.01**2
    kappa_hinge: float = 1.0
    cauchy_m: float = 0.020
    gate_m: float = 0.040
    gate_k: float = 5.0
    gate_memory: int = 30
    reseed_rms_m: float = 0.025
    reseed_reject_frac: float = 0.25
    max_iter: int = 10
    tol: float = 1e-4
    ftol: float = 1e-5

    def array(self) -> F64Array:
        """The kernel's params array (``fit_terms.P_*`` slots)."""
        out = np.zeros(ft.N_PARAMS)
        out[ft.P_LAM_ROT] = self.lambda_rot
        out[ft.P_LAM_TRANS] = self.lambda_trans
        out[ft.P_KAPPA_LIMIT] = self.kappa_limit
        out[ft.P_KAPPA_HINGE] = self.kappa_hinge
        out[ft.P_CAUCHY_M] = self.cauchy_m
        out[ft.P_GATE_M] = self.gate_m
        out[ft.P_GATE_K] = self.gate_k
        out[ft.P_GATE_MEMORY] = self.gate_memory
        out[ft.P_RESEED_RMS_M] = self.reseed_rms_m
        out[ft.P_MAX_ITER] = self.max_iter
        out[ft.P_TOL] = self.tol
        out[ft.P_RESEED_REJECT_FRAC] = self.reseed_reject_frac
        out[ft.P_FTOL] = self.ftol
        return out


@dataclass(slots=True, eq=False)
class FitPose(BodyPose):
    """One frame of the fit: :class:`BodyPose` plus the markers' residuals.

    Attributes:
        marker_residual: (Mr,) float64, metres, |model - measured| per rig marker,
            NaN where not seen.
        marker_rejected: (Mr,) bool, rejected by the gate this frame.
        stats: (6,) float64: inlier residual RMS (m), markers rejected, iterations,
            reseeded (0/1), final cost, linear solves (``fit_terms.S_*``).
    """

    marker_residual: F64Array = field(default_factory=_empty)
    marker_rejected: np.ndarray = field(default_factory=_empty)
    stats: F64Array = field(default_factory=_empty)
    #: The flat float64, float32, uint8 and bool buffers the fields are views of,
    #: when :meth:`FitSolver.new_pose` made them (the packed call, ``fit_pack``).
    fit_buffers: tuple[np.ndarray, ...] | None = None


@dataclass(frozen=True, slots=True, kw_only=True)
class FitSolve(BodySolve):
    """A take solved by the fit: :class:`BodySolve` plus residuals.

    Attributes:
        marker_names: (Mr,) rig markers.
        marker_rms: (T,) float64, metres, inlier marker residual RMS per frame.
        marker_residual: (T, Mr) float64, metres, NaN where not seen.
        marker_rejected: (T, Mr) bool.
        iterations: (T,) int, LM iterations per frame.
        reseeded: (T,) bool.
    """

    marker_names: tuple[str, ...] = ()
    marker_rms: F64Array = field(default_factory=_empty)
    marker_residual: F64Array = field(default_factory=_empty)
    marker_rejected: np.ndarray = field(default_factory=_empty)
    iterations: np.ndarray = field(default_factory=_empty)
    reseeded: np.ndarray = field(default_factory=_empty)

    @property
    def outliers_rejected(self) -> int:
        """Marker samples rejected by the gate over the take."""
        return int(self.marker_rejected.sum())


class FitSolver:
    """A rig + calibration + base pose compiled into the fit, for one marker layout.

    Args:
        rig: the rig.
        calibration: its calibrated skeleton.
        labels: (M,) the marker labels of the frames to solve.
        base_positions: (F, M0, 3) float64, metres, world, the base-pose frames the
            calibration was made from; ``base_labels`` (M0,) their labels (default
            ``labels``).
        options: the rig's ``[fit]`` keys (``fit_model.load_fit_rig``).
        joint_limits, segment_kind: the validator's limit table and humanoid ->
            segment kind map (``validate.limits.JOINT_LIMITS_DEG``,
            ``validate.model.SEGMENT_KIND``), for the soft limit penalty; a higher
            layer passes them (``body`` may not import ``validate``).
        params: weights and tests.
        model: a model already built (then base_positions is not needed).
    """

    def __init__(
        self,
        rig: Rig,
        calibration: Calibration,
        labels: Sequence[str],
        *,
        base_positions: F64Array | None = None,
        base_labels: Sequence[str] | None = None,
        options: FitOptions | None = None,
        params: FitParams | None = None,
        model: FitModel | None = None,
        joint_limits: Mapping[str, JointLimitLike] | None = None,
        segment_kind: Mapping[str, str] | None = None,
    ) -> None:
        if model is None:
            if base_positions is None:
                raise ValueError("FitSolver needs base_positions or a model")
            model = build_fit_model(
                rig,
                calibration,
                base_positions,
                tuple(base_labels if base_labels is not None else labels),
                options,
                joint_limits=joint_limits,
                segment_kind=segment_kind,
            )
        self.model = model
        self.params = params or FitParams()
        self.construction = BodySolver(rig, calibration, labels)
        con = self.construction
        self.rig = rig
        self.calibration = calibration
        self.labels = tuple(labels)
        self.n_stream = len(self.labels)
        self.marker_cols = con.marker_cols
        self.missing_markers = con.missing_markers
        self.joint_names = model.joint_names
        self.bone_names = model.bone_names
        self.marker_names = model.marker_names
        n_b = len(model.bone_names)
        n_r = model.n_roots
        n_m = len(model.marker_names)
        n = model.n_dof
        # H and its factor as 3 x 3 blocks: one per Cholesky node and one per
        # (node, ancestor) entry (fit_normal.solve_step)
        n_blk = len(model.node_ptr) - 1 + len(model.node_idx)
        self._params_arr = self.params.array()
        self._params_arr.flags.writeable = False
        model_arrays = (
            model.bone_parent, model.bone_root, model.off_parent, model.rest_pfb,
            con.marker_cols, model.marker_bone, model.marker_local,
            model.marker_weight, model.joint_bone, model.joint_local,
            model.hinge_axis, model.limits, model.limit_left, model.limit_forward,
            model.anc_ptr, model.anc_idx, model.node_ptr, model.node_idx,
            self._params_arr, model.penalty_cos, model.twist_lock, model.rest_pull,
        )  # fmt: skip
        # packed (fit_pack): the kernel gets one buffer per dtype; self._model keeps
        # the same memory as a tuple of views (for fit_many and hand-made poses)
        mbuf, mrows, self._model = fit_pack.pack(model_arrays, fit_pack.M_KINDS)
        self._mf, self._mi = mbuf["f8"], mbuf["i8"]

        def z(*shape: int) -> np.ndarray:
            return np.zeros(shape)

        state_arrays = (
            z(n_b, 4), z(n_r, 3), z(n_b, 4), z(n_r, 3), np.zeros(1, dtype=np.int64),
            z(n_b, 4),
            z(n_b, 4), z(n_r, 3), z(n_b, 3, 3), z(n_b, 3), z(n_m, 3), z(1),
            z(n_m, 3), np.zeros(n_m, dtype=bool), z(n_m, 3), z(n_m),
            z(n_b), z(n_b, 3), z(n_b, 3, 3), z(n_b, 3), z(n_b, 3),
            z(n_blk, 3, 3), z(n_blk, 3, 3), z(n), z(n), z(n_m), z(6), z(6), z(6, 3),
            z(n_b, 4), z(n_b, 4), z(n_b, 3, 3), z(n_b, 3), z(n_m, 3), z(n_m, 3),
            z(n_m), z(3), z(n_b, 4), z(n_r, 3),
            np.zeros(n_b, dtype=np.int64), np.zeros(n_b, dtype=np.int64),
            z(n_b, 4), z(n_r, 3), z(n_b, 4), z(n_r, 3),
            np.zeros(n_m, dtype=bool), np.zeros(n_m, dtype=bool), z(n_m, 3), z(n_m),
        )  # fmt: skip
        sbuf, srows, self._state = fit_pack.pack(state_arrays, fit_pack.S_KINDS)
        self._sf, self._si, self._sb = sbuf["f8"], sbuf["i8"], sbuf["b1"]
        self._q, self._t, self._qprev, self._tprev, self._have, self._prev_out = (
            self._state[:6]
        )
        # the outputs' rows: every pose of this solver has the same layout
        _, orows, _ = fit_pack.pack(self._out_arrays(), fit_pack.O_KINDS)
        self._layout = np.ascontiguousarray(np.concatenate([mrows, srows, orows]))
        self._gate_age = self._state[48]
        self._lm_scalars = self._state[36]  # gate, linear solves, damping carried
        self._con_pose = con.new_pose()
        assert self._con_pose.kernel_buffers is not None
        # The construction's packed buffers (``body.kernel.solve_one``): a NamedTuple
        # argument costs Python allocations at every dispatch, each array ~80 ns.
        self._con = con.packed_buffers(self._con_pose)
        self.reset()

    def reset(self) -> None:
        """Forget the last frame (a new source or take): the next frame is seeded
        from the construction."""
        self.construction.reset()
        self._q[:] = self.model.rest_pfb
        self._t[:] = self.model.root_rest_pos
        self._qprev[:] = self._q
        self._tprev[:] = self._t
        self._prev_out[:] = 0.0
        self._have[0] = 0
        self._gate_age[:] = math.inf  # no marker has a gate reference yet
        self._lm_scalars[2] = 0.0

    def _out_arrays(self) -> tuple[np.ndarray, ...]:
        n_b = len(self.bone_names)
        n_m = len(self.marker_names)
        return (
            np.zeros((len(self.joint_names), 3)), np.zeros((n_b, 4)),
            np.zeros((n_b, 4)), np.zeros((n_b, 4)), np.zeros(3),
            np.zeros(n_b, dtype=np.float32), np.zeros(n_b, dtype=np.uint8),
            np.zeros(n_m), np.zeros(n_m, dtype=bool), np.zeros(ft.N_STATS),
        )  # fmt: skip

    def new_pose(self) -> FitPose:
        """Allocate the buffers of one frame's output (once per stream): the fields
        are views of four flat buffers (``fit_buffers``, the packed call)."""
        bufs, _, v = fit_pack.pack(self._out_arrays(), fit_pack.O_KINDS)
        return FitPose(
            joint_centres=v[0],
            world_from_bone_quat=v[1],
            parent_from_bone_quat=v[2],
            rest_from_bone_quat=v[3],
            root_pos=v[4],
            bone_quality=v[5],
            bone_flags=v[6],
            marker_residual=v[7],
            marker_rejected=v[8],
            stats=v[9],
            fit_buffers=(bufs["f8"], bufs["f4"], bufs["u1"], bufs["b1"]),
        )

    def solve_frame(self, markers_world: F64Array, out: FitPose) -> FitPose:
        """Fit one frame into ``out`` (no allocation).

        Args:
            markers_world: (M, 3) float64, metres, world, in this solver's label
                order; NaN rows = occluded.
            out: buffers from :meth:`new_pose`, overwritten.

        Returns:
            ``out``.
        """
        fb = out.fit_buffers
        if fb is not None:
            out.n_held = kf.fit_one(
                markers_world, self._mf, self._mi, self._sf, self._si, self._sb,
                self._layout, self._con, fb[0], fb[1], fb[2], fb[3],
            )  # fmt: skip
        else:  # a FitPose made by hand: its arrays one by one (a slower dispatch)
            out.n_held = kf.fit_one_t(
                markers_world, self._model, self._state, self._con,
                out.joint_centres, out.world_from_bone_quat, out.parent_from_bone_quat,
                out.rest_from_bone_quat, out.root_pos, out.bone_quality,
                out.bone_flags, out.marker_residual, out.marker_rejected, out.stats,
            )  # fmt: skip
        out.frame_flags = FRAME_RESEEDED if out.stats[ft.S_RESEEDED] else 0
        # Rig markers not seen this frame (their residual is NaN): the loop counts
        # them as occluded samples.
        out.n_occluded = len(out.marker_residual) - int(
            np.count_nonzero(out.marker_residual == out.marker_residual)
        )
        return out

    def solve_take(self, positions: F64Array) -> FitSolve:
        """Fit every frame of a take in order (the same kernel as
        :meth:`solve_frame`, continuing from the solver's current state).

        Args:
            positions: (T, M, 3) float64, metres, world, NaN rows = occluded.

        Returns:
            The solved arrays with residuals.
        """
        positions = np.ascontiguousarray(positions, dtype=np.float64)
        if positions.ndim != 3 or positions.shape[1:] != (self.n_stream, 3):
            raise ValueError(
                f"positions must be (frames, {self.n_stream}, 3); got {positions.shape}"
            )
        n = positions.shape[0]
        n_b = len(self.bone_names)
        n_m = len(self.marker_names)
        joints = np.zeros((n, len(self.joint_names), 3))
        wfb = np.zeros((n, n_b, 4))
        pfb = np.zeros((n, n_b, 4))
        rfb = np.zeros((n, n_b, 4))
        root = np.zeros((n, 3))
        quality = np.zeros((n, n_b), dtype=np.float32)
        flags = np.zeros((n, n_b), dtype=np.uint8)
        resid = np.zeros((n, n_m))
        rejected = np.zeros((n, n_m), dtype=bool)
        stats = np.zeros((n, ft.N_STATS))
        kf.fit_many(
            positions, self._model, self._state, self._con, joints, wfb, pfb, rfb,
            root, quality, flags, resid, rejected, stats,
        )  # fmt: skip
        return FitSolve(
            joint_names=self.joint_names,
            bone_names=self.bone_names,
            bone_parents=tuple(int(p) for p in self.model.bone_parent),
            joint_centres=joints,
            world_from_bone_quat=wfb,
            parent_from_bone_quat=pfb,
            rest_from_bone_quat=rfb,
            root_pos=root,
            bone_lengths=np.asarray(self.calibration.bone_lengths, dtype=np.float64),
            bone_quality=quality,
            bone_flags=flags,
            marker_names=self.marker_names,
            marker_rms=stats[:, ft.S_RMS].copy(),
            marker_residual=resid,
            marker_rejected=rejected,
            iterations=stats[:, ft.S_ITER].astype(np.int64),
            reseeded=stats[:, ft.S_RESEEDED] > 0.5,
        )


def warm_up() -> FitPose:
    """Load (or compile) the fit kernel through the same code paths as a real frame
    (``FitSolver.solve_frame`` and ``solve_take``, with a hidden marker), so the first
    live frame does not pay numba's cache load or compile.

    Returns:
        The last warm-up frame's pose (finite; a check for the caller's tests).
    """
    rig = parse_rig(_WARM_RIG, source="warm-up")
    labels = ("A", "B", "C", "D")
    frame = np.array(
        [[0.0, 0.0, 0.0], [0.0, 0.2, 0.0], [0.0, 0.1, 0.3], [0.1, 0.1, 0.1]]
    )
    cal = calibrate(rig, frame[None], labels)
    solver = FitSolver(rig, cal, labels, base_positions=frame[None])
    solver.solve_take(frame[None])
    frame[3] = np.nan
    return solver.solve_frame(frame, solver.new_pose())
