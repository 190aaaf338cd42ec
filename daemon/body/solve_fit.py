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
from typing import Any

import numpy as np

from retargetd.daemon.body import fit_fill, fit_observe, fit_pack
from retargetd.daemon.body import fit_terms as ft
from retargetd.daemon.body import kernel_fit as kf
from retargetd.daemon.body.calibration import Calibration, calibrate
from retargetd.daemon.body.fit_model import (
    N_LIM,
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
from retargetd.protocols import kernels
from retargetd.protocols.frames import F64Array
from retargetd.protocols.pose_stream import (
    FRAME_RESEEDED,
    FRAME_UNEXPLAINED,
    FRAME_UNSEEN,
)

#: float64 (native byte order): a frame's dtype for ``FitSolver._fit_entry``.
_F8 = np.dtype(np.float64)


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


if N_LIM != ft.L_TWIST_AXIS:  # the kernel's penalty row: the limits, then the axis
    raise ImportError("solve_fit: fit_model.N_LIM and fit_terms.L_TWIST_AXIS differ")


@dataclass(frozen=True, slots=True, kw_only=True)
class FitParams:
    """The fit's weights and tests (SI units; see ``kernel_fit`` for the cost and the
    per-frame rules). Every number is physics or a published figure; README ("The
    fit's rules") lists them with the takes that confirmed them.

    Attributes:
        noise_m: marker noise sigma_m, the unit the other weights are relative to: 1 mm
            (optical systems' residuals; Merriaux et al., "A study of Vicon system
            positioning performance", Sensors 17(7):1591, 2017: < 1 mm).
        alpha_max: rad/s^2, the peak angular acceleration of any segment: 8000, the
            throwing arm's internal rotation (about 7000 deg/s reached in the ~30 ms
            from maximum external rotation to ball release; Fleisig et al., "Kinetics of
            baseball pitching with implications about injury mechanisms", Am J Sports
            Med 23(2):233-239, 1995: a mean of ~4000 rad/s^2, twice that at the peak).
            The pull to the pose predicted from the last two frames has sigma =
            alpha_max (n dt)^2 / 2 after n frames of dt seconds, weight (noise_m /
            sigma)^2: at 120 Hz sigma is 16 deg, so the pull never holds back a real
            motion, and what the markers leave undetermined it carries from frame to
            frame. A held prediction (no velocity known: after a gap, and the frame
            after the first one explained) misses by up to the peak speed x n dt
            instead (omega_max, speed_max; as ``fit_track.jump_bound``): 29 deg a
            frame at 240 Hz, where alpha_max gave 4 (seed 6 of
            ``bench/burst_recovery.py``: 10 frames at 1e30 back in 0.212 s, was
            0.308; with the hidden markers' offsets fading as their hinges bend,
            merged after it, 0.346; 0.229 since the local floor needs two hidden
            markers, 0.113 once a hidden marker on a bone with no marker seen fades
            (velocity_tau_s below), each alone; both: 0.113).
        acc_max: m/s^2, the same for a root's position: 100 (about 10 g, the body's
            centre of mass under a landing's peak ground reaction force of up to ~11
            body weights; Dufek & Bates, "Biomechanical factors associated with injury
            during landing in jump sports", Sports Med 12(5):326-337, 1991).
        kappa_limit: m^2 / rad^2, penalty past the validator's joint limits: 1 m of
            residual per radian (as a hinge's off-axis stiffness), above the pull of
            every marker a bone carries (a few markers at 0.1-0.5 m levers: < 0.5 m^2 /
            rad^2), so a fitted pose stays within ~2 deg of the table and markers that
            ask for more show as residual, not as a bent joint.
        kappa_hinge: m^2 / rad^2, a hinge's rotation off its axis: 1 m per radian, far
            above any marker residual, so the joint is a hinge in effect.
        cauchy_m: Cauchy scale of the marker residuals: 20 mm, the order of skin
            artefact on limb segments (Leardini et al., "Human movement analysis using
            stereophotogrammetry, part 3: soft tissue artifact", Gait Posture
            21(2):212-225, 2005: 10-30 mm), so artefact is down-weighted mildly and a
            swapped label (residual >= marker spacing) strongly.
        gate_m: a visible marker whose residual exceeds max(gate_m, gate_k x the frame's
            median residual) after the ungated fit is rejected for the frame when its
            residual also moved by more than that since its last accepted frame (at most
            gate_memory frames ago; older: on the level alone): a swapped label or a
            ghost jumps by a marker spacing, while skin sliding over a joint grows a
            residual over many frames. 40 mm, past the largest soft-tissue artefact in
            the same review, below the 50-100 mm spacing of markers on one segment. A
            marker never accepted since the take began (beyond the gate from its first
            frame: a steady misfit) is not gated; the Cauchy loss weighs it down.
            The same bound judges a first frame (the take's first, or the first
            after a reset: a source that restarts), which has neither a level of
            its own nor a past to jump from: its pose is unexplained when its
            residual RMS exceeds gate_m (every marker, on average, beyond the
            largest soft-tissue artefact), and the next frame is seeded afresh.
            A collapse onto one point or mirrored labels as a restart's first
            frame fit at 370-430 mm RMS on the PiG walk (its own first frame:
            4.6 mm; README's loosest real take, the ``cmu41`` tennis serve: p95
            31 mm); taken as the first pose, such a frame became the take's level,
            and at 4x ~0.4 m nothing was unexplained or suspect for seconds (the
            soak: the arms 150-180 deg off for 1.3 s after a collapse at a
            restart, and the next burst 1 s). 100 mm (the marker spacing below)
            let a mirrored frame of 99 mm in on an occluded walk.
        gate_k: see gate_m (5: a factor that keeps the gate above the fit's own residual
            level when the model fits a performer loosely).
        gate_memory: frames, see gate_m (30: 0.125-0.5 s at 240-60 Hz).
        lost_floor_m, lost_k: the fit is suspect when its residual RMS (each marker the
            gate rejected counted at the gate) exceeds max(lost_floor_m, lost_k x the
            take's own running level): then a second candidate is seeded from the
            construction and the better of the two on the whole cost (markers,
            continuity, priors, limits) is kept. 10 mm (the low end of skin artefact: a
            misfit below it is never a lost track) and 2 (the running level doubled).
            The take's own is the running level, or the last explained frame's RMS
            where higher (a misfit that grows with the motion), and a frame's RMS
            becomes that last one only under max(lost_floor_m, lost_k x the running
            level): the same factor, so that no frame the running level alone would
            call suspect vouches for the next. Judged against the frame before it
            alone, a misfit growing by under 2x a frame raised its own reference
            (the walk's LKNE hidden from row 30: 5.7 -> 43 mm over 20 rows, the
            thigh run 58 deg off and nothing suspect).
        reject_frac: suspect too when more than this fraction of the visible markers is
            rejected (a quarter: more than an occasional swap or ghost).
        persist_s: a marker rejected this long (seconds) makes the fit try that
            candidate again, at most once per persist_s: a wrong basin (a limb turned
            half round) shows as its markers rejected frame after frame. 0.1 s, under
            half the 0.25 s the fit has to recover in.
        unexplained_k, unexplained_frac: a frame is unexplained when the kept
            candidate's residual RMS (as above) exceeds max(lost_floor_m, unexplained_k
            x the running level) or more than unexplained_frac of its markers are
            rejected: no skeleton pose accounts for the markers (a collapse, a burst of
            garbage, mirrored labels). Its pose is the last explained one, flagged, and
            the fit carries on from that. 4 (twice the suspect level) and one half.
            After a gap (the prediction held: no track to tell a marker the pose
            rejects from one it has wrong) a frame is unexplained too while it is
            still suspect with the better candidate (lost_k, reject_frac): a
            swapped burst's frame came in at gap 11 with 14 of 29 markers rejected,
            the hidden markers' holds were anchored on it, and the true frames after
            the burst kept it (``tests/daemon/test_burst_recovery.py``). Only
            while the gap is shorter than level_tau_s: past it the level before
            the gap no longer speaks for the take, and without that bound a
            performer whose markers fit worse after a gap was held for good (the
            PiG walk, every marker 20 mm further off after a 0.2 s gap: the rest
            of the take, 1.95 s, unexplained; now 0.8 s). The far rule is bounded
            the same way (``fit_track.far_at``): past level_tau_s a frame is judged
            as a first frame is (past gate_m), and the level starts again from the
            first one explained (the walk 35 mm further off: held for good before,
            now 0.8 s).
        resolution_deg: while a marker is hidden, what the markers still seen observe of
            a joint under (max(noise_m, the running residual level) / this)^2 m^2 /
            rad^2 is held at its last seen value with the information the hidden marker
            gave it (``kernel_fit._hold_priors``): on a real take the model's misfit,
            not the 1 mm noise, is what would turn it. 5 deg,
            ``fit_observe.RESOLUTION_RAD``.
        hold_straight_deg: a hidden marker's hold reads the tables made with the
            nearly straight hinges at a right angle once its limb's hinge
            (``fit_observe.marker_hinges``) bends past this at the last explained
            frame, else those made at the calibration pose
            (``fit_observe.hidden_information``): 30 deg,
            ``fit_observe.HOLD_TABLE_STRAIGHT_RAD``, below which the hinge's two twists
            are told apart by less than half what a right angle gives. The same
            angle fades a hidden marker's virtual offset (its last residual) by
            exp(-change / this) as the hinge where its segment ends (its own bone's or
            its child's) bends away from where that residual was measured
            (``fit_track.virtual_markers``): soft-tissue artefact follows the joint's
            motion, not the clock.
        velocity_tau_s: a hidden marker is measured on the pose whose joints move on
            from their last explained values with their last velocity damped by
            exp(-dt / velocity_tau_s) per frame (Singer's manoeuvre model): the
            velocity is known for about the duration of the fastest voluntary
            movement phases (0.03 s, a pitch's arm acceleration, to 0.1 s, a step's
            push-off), not longer; a velocity carried on undamped fed the fit its
            own prediction and ran away (menache's neck, C1 hidden). 0.1 s; 0.05 and
            0.3 s gave the same hide sweeps within one case. The same time fades a
            hidden marker measured on a bone none of whose markers is seen, by
            exp(-age / velocity_tau_s): that bone's pose is its prediction alone
            (``fit_track.virtual_markers``).
        jump_z, jump_floor_deg: a frame is unexplained too when its pose moves a joint
            further from its prediction than max(jump_z x what a body can,
            jump_floor_deg) (a root's position: max(jump_z x that, gate_m)): a body
            cannot, mirrored or permuted labels can (the rigid skeleton turned half
            round fits a left-right swap with a small residual). What a body can,
            h seconds after the last explained frame (``fit_track.jump_bound``):
            with the velocity known (the prediction extrapolated) min(jump_z x
            alpha_max h^2 / 2, 2 omega h); with the prediction held (after a gap,
            and the frame after the first one explained: no velocity is known
            across a gap) omega h, the speed never passing omega whatever it was
            when the markers went (acc_max and speed_max for a root's position).
            3 (thrice the peak acceleration: the extrapolation's miss; a peak speed
            is a bound as it stands, the fastest the body turns or runs) and 10 deg
            (twice RESOLUTION_RAD of ``fit_observe``: noise on a short lever
            jitters a few degrees a frame at any rate).
            Before, the held prediction was bounded by alpha_max alone, past pi
            after 4 frames at 240 Hz: a swapped burst's frame came in at gap 3-8
            with the pelvis turned 44-50 deg from its prediction
            (``tests/daemon/test_burst_recovery.py``). The real takes' fastest
            frames (README "The fit's rules") stay under the bound.
        omega_max: rad/s, the peak angular velocity of a joint (parent-relative): the
            throwing arm's internal rotation, about 7000 deg/s (Fleisig et al. 1995,
            above; the fastest joint rotation measured in sport), for every joint.
        omega_root: rad/s, the peak angular velocity of a root's rotation in the
            world (the whole body turning): 3 rev/s, the top of a ballet dancer's
            pirouette (2-3 rev/s; Kim et al., "Generation of vertical angular
            momentum in single, double, and triple-turn pirouette en dehors in
            ballet", Sports Biomech 13(3):215-229, 2014), about the pitcher's upper
            trunk (~1170 deg/s) and far above the pitcher's pelvis (~660 deg/s;
            Fleisig et al., "Kinematic and kinetic comparison of baseball pitching
            among various levels of development", J Biomech 32(12):1371-1375,
            1999).
        speed_max: m/s, the peak speed of a root: 12.3, a world-record sprinter's
            top speed (Graubner & Nixdorf, "Biomechanical analysis of the sprint
            and hurdles events at the 2009 IAAF World Championships in Athletics",
            New Studies in Athletics 26(1/2):19-53, 2011).
        level_tau_s: time constant of the running residual level (that RMS) over
            explained frames: 1 s, a gait cycle (its artefact pattern), long against a
            burst.
        max_iter: iteration cap per phase (the worst case is 4 phases: two fits, each
            ungated then gated).
        tol: step size (rad, m) at which the fit has converged: 1e-4 (0.1 mm, 0.006 deg,
            a tenth of the marker noise floor above; Gauss-Newton's next step would be
            smaller still).
        ftol: or when an accepted step lowers the cost by less than this fraction (1e-5:
            what is left is a direction the markers hardly see), or the next step's
            predicted decrease does (tested before its evaluation is paid for: from
            the second iteration the model is Newton's, ``fit_newton``, and its
            prediction is the decrease to within a few per cent near the optimum).
    """

    noise_m: float = 1e-3
    alpha_max: float = 8000.0
    acc_max: float = 100.0
    kappa_limit: float = 1.0
    kappa_hinge: float = 1.0
    cauchy_m: float = 0.020
    gate_m: float = 0.040
    gate_k: float = 5.0
    gate_memory: int = 30
    lost_floor_m: float = 0.010
    lost_k: float = 2.0
    reject_frac: float = 0.25
    persist_s: float = 0.1
    unexplained_k: float = 4.0
    unexplained_frac: float = 0.5
    resolution_deg: float = math.degrees(fit_observe.RESOLUTION_RAD)
    hold_straight_deg: float = math.degrees(fit_observe.HOLD_TABLE_STRAIGHT_RAD)
    velocity_tau_s: float = 0.1
    jump_z: float = 3.0
    jump_floor_deg: float = 10.0
    omega_max: float = math.radians(7000.0)
    omega_root: float = 6.0 * math.pi
    speed_max: float = 12.3
    level_tau_s: float = 1.0
    max_iter: int = 10
    tol: float = 1e-4
    ftol: float = 1e-5

    def array(self) -> F64Array:
        """The kernel's params array (``fit_terms.P_*`` slots)."""
        out = np.zeros(ft.N_PARAMS)
        out[ft.P_NOISE_M] = self.noise_m
        out[ft.P_ALPHA_MAX] = self.alpha_max
        out[ft.P_ACC_MAX] = self.acc_max
        out[ft.P_KAPPA_LIMIT] = self.kappa_limit
        out[ft.P_KAPPA_HINGE] = self.kappa_hinge
        out[ft.P_CAUCHY_M] = self.cauchy_m
        out[ft.P_GATE_M] = self.gate_m
        out[ft.P_GATE_K] = self.gate_k
        out[ft.P_GATE_MEMORY] = self.gate_memory
        out[ft.P_LOST_FLOOR_M] = self.lost_floor_m
        out[ft.P_LOST_K] = self.lost_k
        out[ft.P_REJECT_FRAC] = self.reject_frac
        out[ft.P_PERSIST] = self.persist_s
        out[ft.P_UNEXPLAINED_K] = self.unexplained_k
        out[ft.P_UNEXPLAINED_FRAC] = self.unexplained_frac
        out[ft.P_LEVEL_TAU_S] = self.level_tau_s
        out[ft.P_JUMP_Z] = self.jump_z
        out[ft.P_VELOCITY_TAU_S] = self.velocity_tau_s
        out[ft.P_RESOLUTION_RAD] = math.radians(self.resolution_deg)
        out[ft.P_HOLD_STRAIGHT_RAD] = math.radians(self.hold_straight_deg)
        out[ft.P_JUMP_FLOOR_RAD] = math.radians(self.jump_floor_deg)
        out[ft.P_OMEGA_MAX] = self.omega_max
        out[ft.P_OMEGA_ROOT] = self.omega_root
        out[ft.P_SPEED_MAX] = self.speed_max
        out[ft.P_MAX_ITER] = self.max_iter
        out[ft.P_TOL] = self.tol
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
        unexplained: (T,) bool, the markers fit no pose (``FRAME_UNEXPLAINED``):
            the last explained pose held.
        unseen: (T,) bool, too few of the performer's markers (``FRAME_UNSEEN``):
            no pose (before the first seen frame: that frame's pose).
        residual_level: (T,) float64, metres, the take's running inlier residual
            RMS after each frame (what "unexplained" is judged against).
    """

    marker_names: tuple[str, ...] = ()
    marker_rms: F64Array = field(default_factory=_empty)
    marker_residual: F64Array = field(default_factory=_empty)
    marker_rejected: np.ndarray = field(default_factory=_empty)
    iterations: np.ndarray = field(default_factory=_empty)
    reseeded: np.ndarray = field(default_factory=_empty)
    unexplained: np.ndarray = field(default_factory=_empty)
    unseen: np.ndarray = field(default_factory=_empty)
    residual_level: F64Array = field(default_factory=_empty)

    @property
    def frame_flags(self) -> np.ndarray:
        """(T,) uint32 ``pose_stream.FRAME_*`` bits the fit sets per frame."""
        return (
            np.where(self.reseeded, FRAME_RESEEDED, 0)
            | np.where(self.unexplained, FRAME_UNEXPLAINED, 0)
            | np.where(self.unseen, FRAME_UNSEEN, 0)
        ).astype(np.uint32)

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
        rate_hz: the frame rate of the frames to solve (the continuity prior's
            time step; :meth:`solve_frame` may pass each frame's own ``dt_s``).
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
        rate_hz: float = 120.0,
    ) -> None:
        if not (math.isfinite(rate_hz) and rate_hz > 0.0):
            raise ValueError(f"rate_hz must be a positive number; got {rate_hz}")
        self.rate_hz = float(rate_hz)
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
            model.hinge_axis, np.hstack([model.limits, model.twist_axis]),
            model.limit_left, model.limit_forward,
            model.anc_ptr, model.anc_idx, model.node_ptr, model.node_idx,
            self._params_arr, model.penalty_cos, model.twist_lock, model.prior_mat,
            model.hide_axes, model.hide_lam, model.hide_lost, model.hide_hinge,
            fit_fill.chain_pairs(model.bone_parent, model.marker_bone),
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
            z(n_m), z(ft.N_SCALARS), z(n_b, 4), z(n_r, 3),
            np.zeros(n_b, dtype=np.int64), np.zeros(n_b, dtype=np.int64),
            z(n_b, 4), z(n_r, 3), z(n_b, 4), z(n_r, 3),
            np.zeros(n_m, dtype=bool), np.zeros(n_m, dtype=bool), z(n_m, 3), z(n_m),
            z(n_b, 4), z(n_r, 3), z(n_m), z(self.n_stream, 3),
            z(n_b, 3, 3), z(n_b, 4), z(n_b), z(n_m, 3), z(n_m, 3), z(n_m), z(n_m),
            *fit_fill.new_fill_state(n_m),
            z(n_b, ft.N_REG), z(n_b, ft.N_REG), z(n_m), z(n_m), z(n_b, 3, 12),
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
        self._scalars = self._state[36]  # fit_terms.C_* slots
        self._qlast, self._tlast, self._rej_run = self._state[49:52]
        self._hold_active = self._state[55]
        self._con_pose = con.new_pose()
        assert self._con_pose.kernel_buffers is not None
        # The construction's packed buffers (``body.kernel.solve_one``): a NamedTuple
        # argument costs Python allocations at every dispatch, each array ~80 ns.
        # Three more: a copy of its state, kept before a frame's reseed candidate and
        # restored when the frame turns out unexplained (kernel_fit.fit_one_t).
        packed = con.packed_buffers(self._con_pose)
        self._con = (*packed, packed[2].copy(), packed[3].copy(), packed[4].copy())
        # kernel_fit.fit_one's compiled function for a frame's usual types, bound at
        # the first such call (solve_frame): called without numba's dispatcher, which
        # resolves the types of the 12 arguments at every call
        self._fit_entry: Any = None
        self.reset()

    def reset(self) -> None:
        """Forget the last frame (a new source or take): the next frame is seeded
        from the construction."""
        self.construction.reset()
        self._q[:] = self.model.rest_pfb
        self._t[:] = self.model.root_rest_pos
        self._qprev[:] = self._q
        self._tprev[:] = self._t
        # the pose held before the performer is first seen: the calibration pose
        self._qlast[:] = self._q
        self._tlast[:] = self._t
        self._rej_run[:] = 0.0
        self._hold_active[:] = 0.0
        self._state[58][:] = 0.0  # no misfit carried
        self._state[67][:] = 0.0  # no level at any marker's last accepted frame
        self._state[68][:] = 0.0  # no robust share taken at a hide (fit_hold_robust)
        for dst, src in zip(  # no pair statistics, no donors (fit_fill)
            self._state[60:65],
            fit_fill.new_fill_state(len(self.marker_names)),
            strict=True,
        ):
            dst[...] = src
        self._prev_out[:] = 0.0
        self._have[0] = 0
        self._gate_age[:] = math.inf  # no marker has a gate reference yet
        self._scalars[:] = 0.0
        self._scalars[ft.C_DT] = 1.0 / self.rate_hz
        self._scalars[ft.C_GAP] = 1.0

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

    def packed_buffers(self, pose: FitPose) -> tuple[Any, ...]:
        """``kernel_fit.fit_one``'s arguments after the markers for ``pose``, then
        what :meth:`solve_frame` does around that call: the scalars whose ``C_DT``
        slot it sets, the pose's stats (its frame flags) and the interval used
        when none is given (for a kernel that runs this solve inside its own call,
        ``live/solve_emit.py``)."""
        if pose.fit_buffers is None:
            raise ValueError("the pose was not made by new_pose()")
        return (
            self._mf, self._mi, self._sf, self._si, self._sb, self._layout, self._con,
            *pose.fit_buffers, self._scalars, pose.stats,
            1.0 / self.rate_hz,
        )  # fmt: skip

    def solve_frame(
        self, markers_world: F64Array, out: FitPose, dt_s: float = 0.0
    ) -> FitPose:
        """Fit one frame into ``out`` (no allocation).

        Args:
            markers_world: (M, 3) float64, metres, world, in this solver's label
                order; NaN rows = occluded.
            out: buffers from :meth:`new_pose`, overwritten.
            dt_s: seconds since the last frame (0: ``1 / rate_hz``).

        Returns:
            ``out``.
        """
        self._scalars[ft.C_DT] = dt_s if dt_s > 0.0 else 1.0 / self.rate_hz
        fb = out.fit_buffers
        if fb is not None:
            # The compiled function takes its arguments as the types it was compiled
            # for, unchecked: only a frame of those types (float64, 2-d, C-contiguous,
            # aligned) goes to it, anything else to the dispatcher. Every other
            # argument is this solver's or a pose's from new_pose: the same types at
            # every call. Same compiled code either way: the same answers.
            fl = markers_world.flags
            usual = (
                markers_world.dtype is _F8
                and markers_world.ndim == 2
                and fl.c_contiguous
                and fl.aligned
            )
            entry = self._fit_entry if usual else None
            args = (
                markers_world, self._mf, self._mi, self._sf, self._si, self._sb,
                self._layout, self._con, fb[0], fb[1], fb[2], fb[3],
            )  # fmt: skip
            if entry is None:
                both = kf.fit_one(*args)
                if usual:
                    self._fit_entry = kernels.direct(kf.fit_one, *args)
            else:
                both = entry(*args)
            out.n_held = both & 0xFFFFFFFF
            # rig markers not seen this frame (their residual is NaN): the loop
            # counts them as occluded samples
            out.n_occluded = both >> 32
        else:  # a FitPose made by hand: its arrays one by one (a slower dispatch)
            out.n_held = kf.fit_one_t(
                markers_world, self._model, self._state, self._con,
                out.joint_centres, out.world_from_bone_quat, out.parent_from_bone_quat,
                out.rest_from_bone_quat, out.root_pos, out.bone_quality,
                out.bone_flags, out.marker_residual, out.marker_rejected, out.stats,
            )  # fmt: skip
            out.n_occluded = len(out.marker_residual) - int(
                np.count_nonzero(out.marker_residual == out.marker_residual)
            )
        st = out.stats
        out.frame_flags = (
            (FRAME_RESEEDED if st[ft.S_RESEEDED] else 0)
            | (FRAME_UNEXPLAINED if st[ft.S_UNEXPLAINED] else 0)
            | (FRAME_UNSEEN if st[ft.S_UNSEEN] else 0)
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
        if not positions.flags.writeable:
            # One compiled type per kernel: a read-only take (a synthetic one, a
            # memory map) would compile the whole batch kernel a second time
            # (numba types read-only arrays apart); copied here, off the hot path.
            positions = positions.copy()
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
        self._scalars[ft.C_DT] = 1.0 / self.rate_hz
        kf.fit_many(
            positions, self._model, self._state, self._con, joints, wfb, pfb, rfb,
            root, quality, flags, resid, rejected, stats,
        )  # fmt: skip
        unseen = stats[:, ft.S_UNSEEN] > 0.5
        unexplained = stats[:, ft.S_UNEXPLAINED] > 0.5
        seen = np.flatnonzero(~unseen & ~unexplained)
        if seen.size and seen[0] > 0:
            # Before the performer is first seen (or first explained: FitParams.gate_m
            # on a first frame) there is no pose: those frames (flagged) take the first
            # one, so a file has no jump from the calibration spot.
            lead = slice(0, int(seen[0]))
            for arr in (joints, wfb, pfb, rfb, root):
                arr[lead] = arr[seen[0]]
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
            unexplained=unexplained,
            unseen=unseen,
            residual_level=stats[:, ft.S_LEVEL].copy(),
        )


def warm_up() -> FitPose:
    """Load (or compile) the fit kernel through the same code paths as a real frame
    (``FitSolver.solve_frame`` and ``solve_take``, with a hidden marker), so the first
    live frame does not pay numba's cache load or compile.

    Returns:
        The last warm-up frame's pose (finite; a check for the caller's tests).
    """
    return warm_up_solver()[1]


def warm_up_solver() -> tuple[FitSolver, FitPose]:
    """:func:`warm_up`'s solver and its last pose (for a kernel that runs the fit
    inside its own call to warm up on: ``live/solve_emit.py``)."""
    rig = parse_rig(_WARM_RIG, source="warm-up")
    labels = ("A", "B", "C", "D")
    frame = (
        np.array([[0.0, 0.0, 0.0], [0.0, 0.2, 0.0], [0.0, 0.1, 0.3], [0.1, 0.1, 0.1]])
        + 0.5
    )  # (a marker at exactly 0, 0, 0 is one the capture system lost)
    cal = calibrate(rig, frame[None], labels)
    solver = FitSolver(rig, cal, labels, base_positions=frame[None])
    solver.solve_take(frame[None])
    frame[3] = np.nan
    return solver, solver.solve_frame(frame, solver.new_pose())
