"""The body solve: labelled markers -> the rig's skeleton, one frame or a whole take.

:class:`BodySolver` flattens a rig and its calibration into index arrays once (the
"program") and runs the compiled kernel (``body.kernel``) either one frame
at a time into preallocated buffers (:meth:`BodySolver.solve_frame`, the live path:
no allocation in steady state) or over a whole take (:meth:`BodySolver.solve_take`,
the same kernel in a loop, so batch and live agree exactly).

Outputs per frame (see README "Solve output"): joint centres (J, 3) metres world;
``world_from_bone_quat`` (B, 4); ``parent_from_bone_quat`` (B, 4) = the bone's rotation
relative to its parent (``conj(world_from_parent) * world_from_bone``; the root's parent
is the world), so ``world_from_parent * parent_from_bone = world_from_bone``;
``rest_from_bone_quat`` (B, 4) = the same relative to its calibrated value
(``conj(rest_parent_from_bone) * parent_from_bone``: identity in the calibration pose,
in the bone's own axes, +Y along the bone); root position (3,); per-bone quality
(fraction of defining markers seen) and flags (``FLAG_*``).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from retargetd.daemon.body import kernel
from retargetd.daemon.body.calibration import (
    Calibration,
    bone_world_quats,
    calibrate,
    check_calibration_fits,
    match_markers,
)
from retargetd.daemon.body.kernel import (
    FLAG_HELD,
    FLAG_NEVER,
    FLAG_PARTIAL,
    FLAG_REBUILT,
)
from retargetd.daemon.body.rig import LinePoint, Rig, parse_rig
from retargetd.daemon.body.sanity import roll_hold_levels_m
from retargetd.protocols.frames import F64Array

logger = logging.getLogger(__name__)

__all__ = [
    "FLAG_HELD",
    "FLAG_NEVER",
    "FLAG_PARTIAL",
    "FLAG_REBUILT",
    "BodyPose",
    "BodySolve",
    "BodySolver",
    "bone_world_quats",
]


@dataclass(slots=True, eq=False)
class BodyPose:
    """One frame of the body solve (buffers reused frame after frame).

    Attributes:
        joint_centres: (J, 3) float64, metres, world.
        world_from_bone_quat: (B, 4) float64, w x y z.
        parent_from_bone_quat: (B, 4) float64, w x y z, relative to the parent (the
            world for the root).
        rest_from_bone_quat: (B, 4) float64, w x y z, relative to the calibration
            pose (``conj(rest_parent_from_bone) * parent_from_bone``, w >= 0).
        root_pos: (3,) float64, metres, world (the root bone's origin).
        bone_quality: (B,) float32, fraction of defining markers seen.
        bone_flags: (B,) uint8, ``FLAG_*`` bits.
        n_held: bones held this frame.
    """

    joint_centres: F64Array
    world_from_bone_quat: F64Array
    parent_from_bone_quat: F64Array
    rest_from_bone_quat: F64Array
    root_pos: F64Array
    bone_quality: np.ndarray
    bone_flags: np.ndarray
    n_held: int = 0
    #: Rig markers occluded this frame (missing from the stream or not finite).
    n_occluded: int = 0
    #: Frame flag bits the solve sets (``protocols.pose_stream.FRAME_*``): the fit's
    #: ``FRAME_RESEEDED``; 0 from the construction.
    frame_flags: int = 0
    #: The same buffers as the kernel's output tuple (built once, never per frame).
    kernel_out: tuple[np.ndarray, ...] | None = None
    #: The flat float64, float32 and uint8 buffers the fields are views of, when
    #: :meth:`BodySolver.new_pose` made them (the fast call, ``kernel.solve_one``).
    kernel_buffers: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None


@dataclass(frozen=True, slots=True, kw_only=True)
class BodySolve:
    """A solved take: the arrays of ``retargetd solve``'s NPZ (see README)."""

    joint_names: tuple[str, ...]
    bone_names: tuple[str, ...]
    bone_parents: tuple[int, ...]
    joint_centres: F64Array  # (T, J, 3)
    world_from_bone_quat: F64Array  # (T, B, 4)
    parent_from_bone_quat: F64Array  # (T, B, 4)
    rest_from_bone_quat: F64Array  # (T, B, 4)
    root_pos: F64Array  # (T, 3)
    bone_lengths: F64Array  # (B,)
    bone_quality: np.ndarray  # (T, B) float32
    bone_flags: np.ndarray  # (T, B) uint8


class BodySolver:
    """A rig + calibration compiled for one marker layout (the take's or stream's).

    Args:
        rig: the rig.
        calibration: its calibrated skeleton.
        labels: (M,) the marker labels of the frames to solve (prefixes stripped on
            match; rig markers absent are occluded; extra labels ignored).
    """

    def __init__(
        self, rig: Rig, calibration: Calibration, labels: Sequence[str]
    ) -> None:
        check_calibration_fits(rig, calibration)
        self.rig = rig
        self.calibration = calibration
        self.labels = tuple(labels)
        self.n_stream = len(self.labels)
        names = [*rig.marker_names, *rig.point_names]
        index = {n: i for i, n in enumerate(names)}
        n_markers = len(rig.marker_names)
        self.marker_cols = np.asarray(match_markers(rig, labels), dtype=np.int64)
        self.missing_markers = tuple(
            m for m, c in zip(rig.marker_names, self.marker_cols, strict=False) if c < 0
        )
        n_points = len(rig.points)
        self.op_kind = np.zeros(n_points, dtype=np.int64)
        self.op_idx = np.zeros((n_points, 3), dtype=np.int64)
        self.op_u = np.zeros(n_points)
        self.op_off = np.ascontiguousarray(calibration.point_offsets, dtype=np.float64)
        for k, p in enumerate(rig.points):
            if isinstance(p, LinePoint):
                self.op_kind[k] = kernel.OP_LINE
                self.op_idx[k] = (index[p.a], index[p.b], index[p.a])
                self.op_u[k] = p.u
            else:
                self.op_kind[k] = kernel.OP_RIGID
                self.op_idx[k] = [index[n] for n in p.frame]
        seg_ptr = [0]
        seg_idx: list[int] = []
        seg_layout: list[F64Array] = []
        for names_k, layout in calibration.segment_layouts.values():
            seg_idx.extend(index[n] for n in names_k)
            seg_layout.append(np.asarray(layout).reshape(-1, 3))
            seg_ptr.append(len(seg_idx))
        self.seg_ptr = np.asarray(seg_ptr, dtype=np.int64)
        self.seg_idx = np.asarray(seg_idx, dtype=np.int64)
        self.seg_layout = (
            np.ascontiguousarray(np.concatenate(seg_layout))
            if seg_layout
            else np.zeros((0, 3))
        )
        n_bones = len(rig.bones)
        self.bone_pts = np.full((n_bones, 4), -1, dtype=np.int64)
        def_ptr = [0]
        def_idx: list[int] = []
        for b, bone in enumerate(rig.bones):
            self.bone_pts[b, 0] = index[bone.origin]
            self.bone_pts[b, 1] = index[bone.aim]
            self.bone_pts[b, 2] = index[bone.up[0]]
            if len(bone.up) == 2:
                self.bone_pts[b, 3] = index[bone.up[1]]
            markers: list[str] = []
            for name in bone.inputs:
                markers.extend(m for m in rig.markers_of(name) if m not in markers)
            def_idx.extend(index[m] for m in markers)
            def_ptr.append(len(def_idx))
        self.bone_parent = np.asarray(rig.bone_parent_indices(), dtype=np.int64)
        self.bone_def_ptr = np.asarray(def_ptr, dtype=np.int64)
        self.bone_def_idx = np.asarray(def_idx, dtype=np.int64)
        self.rest_pfb = np.ascontiguousarray(
            calibration.rest_parent_from_bone_quat, dtype=np.float64
        )
        self.joint_names = tuple(rig.joints)
        self.joint_idx = np.asarray(
            [index[p] for p in rig.joints.values()], dtype=np.int64
        )
        self.root_point = int(index[rig.bones[0].origin])
        self.bone_names = rig.bone_names
        seg_w = np.ones(len(self.seg_idx))
        # A bone's up lever under this takes the roll from the previous frame
        # (``kernel``, step 4): the rig's up_min_mm, less for a bone whose lever is
        # short already in the base pose.
        self.bone_up_min = roll_hold_levels_m(rig, calibration)
        # The plan, state and output live in a few flat buffers (what the live call
        # passes: see ``kernel.solve_one``); the NamedTuples here are views of them.
        header = np.array(
            [n_markers, n_points, len(self.seg_ptr) - 1, len(self.seg_idx), n_bones,
             len(self.bone_def_idx), len(self.joint_idx), self.root_point],
            dtype=np.int64,
        )  # fmt: skip
        n_i, n_f = kernel.plan_sizes(header)
        self._pi = np.zeros(n_i, dtype=np.int64)
        self._pi[: kernel.PLAN_HEADER] = header
        self._pf = np.zeros(n_f)
        source = kernel.BodyPlan(
            self.marker_cols, self.op_kind, self.op_idx, self.op_u, self.op_off,
            self.seg_ptr, self.seg_idx, self.seg_layout, seg_w, self.bone_pts,
            self.bone_parent, self.bone_def_ptr, self.bone_def_idx, self.rest_pfb,
            self.joint_idx, self.root_point, self.bone_up_min,
        )  # fmt: skip
        views = kernel.plan_views(self._pi, self._pf)
        for dst, src in zip(views, source, strict=True):
            if isinstance(dst, np.ndarray):
                dst[...] = src
        self._pi.flags.writeable = False
        self._pf.flags.writeable = False
        self.plan = kernel.plan_views(self._pi, self._pf)
        for name in kernel.BodyPlan._fields:  # one copy: the attributes are the views
            if name != "seg_w" and hasattr(self, name):
                setattr(self, name, getattr(self.plan, name))
        n_sf, n_sb, n_si = kernel.state_sizes(self._pi)
        self._sf = np.zeros(n_sf)
        self._sb = np.zeros(n_sb, dtype=bool)
        self._si = np.zeros(n_si, dtype=np.int64)
        self.state = kernel.state_views(self._pi, self._sf, self._sb, self._si)
        self._pts = self.state.pts  # the kernel's scratch: rig markers, then points
        self._seen = self.state.seen  # which of them were seen this frame
        self._last_pfb = self.state.last_pfb
        self._have_good = self.state.have_good
        self._prev_wfb = self.state.prev_wfb
        self._last_root = self.state.last_root
        # Plain tuples for the batch kernel and hand-made poses (``solve_one_t``).
        self._plan_t = tuple(self.plan)
        self._state_t = tuple(self.state)
        self.reset()

    def reset(self) -> None:
        """Forget the last good pose (a new source, or a new take)."""
        self._last_pfb[:] = self.rest_pfb
        self._have_good[:] = False
        self._prev_wfb[:] = np.nan
        self._last_root[:] = self.calibration.root_rest_pos

    def new_pose(self) -> BodyPose:
        """Allocate the buffers of one frame's output (once per stream)."""
        n_bones = len(self.bone_names)
        buffers = (
            np.zeros(kernel.out_size(self._pi)),
            np.zeros(n_bones, dtype=np.float32),
            np.zeros(n_bones, dtype=np.uint8),
        )
        out = kernel.out_views(self._pi, *buffers)
        pose = BodyPose(
            joint_centres=out.joints,
            world_from_bone_quat=out.wfb,
            parent_from_bone_quat=out.pfb,
            rest_from_bone_quat=out.rfb,
            root_pos=out.root,
            bone_quality=out.quality,
            bone_flags=out.flags,
        )
        pose.kernel_out = tuple(out)
        pose.kernel_buffers = buffers
        return pose

    def packed_buffers(self, pose: BodyPose) -> tuple[np.ndarray, ...]:
        """The plan, state and ``pose``'s output buffers as ``kernel.solve_one`` takes
        them (for a kernel that runs this solve inside its own call)."""
        if pose.kernel_buffers is None:
            raise ValueError("the pose was not made by new_pose()")
        return (self._pi, self._pf, self._sf, self._sb, self._si, *pose.kernel_buffers)

    def solve_frame(
        self, markers_world: F64Array, out: BodyPose, dt_s: float = 0.0
    ) -> BodyPose:
        """Solve one frame into ``out`` (no allocation).

        Args:
            markers_world: (M, 3) float64, metres, world, in this solver's label order;
                NaN rows = occluded.
            out: buffers from :meth:`new_pose`, overwritten.
            dt_s: seconds since the last frame (unused: the construction has no
                prediction; the fit's interface).

        Returns:
            ``out``.
        """
        buffers = out.kernel_buffers
        if buffers is not None:
            of, oq, ofl = buffers
            both = kernel.solve_one(
                markers_world,
                self._pi,
                self._pf,
                self._sf,
                self._sb,
                self._si,
                of,
                oq,
                ofl,
            )  # fmt: skip (positional: the fastest dispatch)
        else:  # a BodyPose made by hand: its arrays as a plain tuple, built once
            if out.kernel_out is None:
                out.kernel_out = _kernel_out(out)
            both = kernel.solve_one_t(
                markers_world, self._plan_t, self._state_t, out.kernel_out
            )
        out.n_held = both & 0xFFFFFFFF
        out.n_occluded = both >> 32
        return out

    def solve_take(self, positions: F64Array) -> BodySolve:
        """Solve every frame of a take (the same kernel as :meth:`solve_frame`).

        Args:
            positions: (T, M, 3) float64, metres, world, NaN rows = occluded.

        Returns:
            The solved arrays.
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
        n_bones = len(self.bone_names)
        joints = np.zeros((n, len(self.joint_names), 3))
        wfb = np.zeros((n, n_bones, 4))
        pfb = np.zeros((n, n_bones, 4))
        rfb = np.zeros((n, n_bones, 4))
        root = np.zeros((n, 3))
        quality = np.zeros((n, n_bones), dtype=np.float32)
        flags = np.zeros((n, n_bones), dtype=np.uint8)
        kernel.solve_many(
            positions, self._plan_t, self._state_t,
            (joints, wfb, pfb, rfb, root, quality, flags),
        )  # fmt: skip
        return BodySolve(
            joint_names=self.joint_names,
            bone_names=self.bone_names,
            bone_parents=tuple(int(p) for p in self.bone_parent),
            joint_centres=joints,
            world_from_bone_quat=wfb,
            parent_from_bone_quat=pfb,
            rest_from_bone_quat=rfb,
            root_pos=root,
            bone_lengths=np.asarray(self.calibration.bone_lengths, dtype=np.float64),
            bone_quality=quality,
            bone_flags=flags,
        )


def _kernel_out(pose: BodyPose) -> tuple[np.ndarray, ...]:
    # The BodyOut fields as a plain tuple (see ``kernel.solve_one``).
    return (
        pose.joint_centres, pose.world_from_bone_quat, pose.parent_from_bone_quat,
        pose.rest_from_bone_quat, pose.root_pos, pose.bone_quality, pose.bone_flags,
    )  # fmt: skip


_WARM_RIG = """
[rig]
name = "warm-up"
lateral = ["A", "B"]
[markers]
A = "A"
B = "B"
C = "C"
D = "D"
[segments.s]
markers = ["A", "B", "C", "D"]
[points.M]
line = ["A", "B"]
[points.R]
rigid = ["A", "B", "C"]
rule = { height = "C", width = "M", depth = "M" }
[bones.b]
origin = "M"
aim = "C"
up = "B"
humanoid = "Hips"
[joints]
J = "R"
"""


def warm_up() -> tuple[BodySolver, BodyPose]:
    """Load (or compile) the body-solve kernel through the same code paths as a real
    frame (``BodySolver.solve_frame``, ``solve_take``), so the first live frame does not
    pay numba's cache load (~0.3 s) or compile.

    Returns:
        the warm-up solver and its last pose (for the next stage's own warm-up).
    """
    rig = parse_rig(_WARM_RIG, source="warm-up")
    labels = ("A", "B", "C", "D")
    frame = np.array(
        [[0.0, 0.0, 0.0], [0.0, 0.2, 0.0], [0.0, 0.1, 0.3], [0.1, 0.1, 0.1]]
    )
    solver = BodySolver(rig, calibrate(rig, frame[None], labels), labels)
    solver.solve_take(frame[None])
    frame[3] = np.nan  # exercise the rigid-segment rebuild as well
    return solver, solver.solve_frame(frame, solver.new_pose())
