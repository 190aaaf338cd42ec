"""A solved frame out in one compiled call: the retarget, the engine frame, the VMC
datagrams and the pose stream's data message, written into the preallocated send
buffers by :func:`emit_frame` (numba).

Before, the loop made these steps as four kernel calls, two numpy matmuls, a struct
pack and five numpy copies, each with its own dispatch. On this shared VM a frame
every 4 ms finds every piece of code and data it touches cold (a 2-argument numba
call: 0.5 µs back to back, 18 µs at 240 Hz; STYLE.md section 6.2 counts calls for
this reason), so the loop now crosses into compiled code once for all of them.

What the call reads and writes is the same as before, byte for byte
(``tests/daemon/test_live_emit.py`` compares it with the separate calls on a real
take): ``Retargeter.apply``'s kernel (``target/kernel.py``) on the program
:meth:`Retargeter.program` gives, the target pose converted to Unity's frame as
``engine_unity`` does (each output a sum of four products, in the same order as
``np.matmul``, from +0.0), ``kernels.vmc_pack`` into the encoder's datagrams and
``kernels.pose_pack`` into the pose encoder's two parts.

When no post stage, pivot or plant runs between the solve and the send (the default
pipeline), the call also runs the stance detector's step (``post/stance.py``, the
foot contact) on the solved pose and ORs its bits into the pose header, what the loop
did as a call of its own before (``DO_STANCE``; the detector's arrays packed into two
flat arrays, ``StanceDetector.pack``, bound with the rest: :meth:`EmitPlan.bind`).

The retarget's constants and scratch, the target pose (its arrays are views of this
plan's float64 arena, :attr:`EmitPlan.target_pose`) and the engine constants live in
two arenas, one int64 and one float64, so the call takes few arguments (each costs
its unboxing, cold too). With ``[target] spine = "pivot"`` the loop runs the retarget
and the pivot itself and calls this with the retarget off.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from retargetd.daemon.compiled import direct, kernel
from retargetd.daemon.post.stance import StanceDetector, step_packed
from retargetd.daemon.retarget import kernel as kt
from retargetd.daemon.retarget.kernel import retarget_one
from retargetd.daemon.retarget.retarget import Retargeter, TargetPose
from retargetd.protocols import engine_unity
from retargetd.protocols.kernels import pose_pack, vmc_pack
from retargetd.protocols.pose_stream import PoseEncoder
from retargetd.protocols.vmc_out import VmcEncoder

#: No validation bone flags to OR in (``or_flags`` of :func:`emit_frame`).
NO_FLAGS = np.zeros(0, dtype=np.uint8)

#: ``what`` bits of :func:`emit_frame`.
DO_RETARGET = 1
DO_VMC = 2
DO_POSE = 4
DO_STANCE = 8

#: The stance arrays of a pipeline whose stance runs outside the call (none, or
#: before its post stages, pivot or plant): typed as a packed detector's, never read.
_NO_STANCE = (np.zeros(3, dtype=np.int64), np.zeros(1))

# ``ei[:N_HEAD]``: the target's bone count, then the float arena's offsets.
(I_N, I_CST, I_PARAMS, I_E, I_REST, I_WFB, I_ROOT, I_HIPS, I_OFFSETS, I_BONE_POS,
 I_ROOT_QUAT, I_BQ, I_RP, I_QRHS, I_PRHS, N_HEAD) = range(16)  # fmt: skip


@kernel
def emit_frame(
    what: int,
    wfb: np.ndarray,
    pfb: np.ndarray,
    rfb: np.ndarray,
    root: np.ndarray,
    bone_flags: np.ndarray,
    ei: np.ndarray,
    ef: np.ndarray,
    tflags: np.ndarray,
    last_quat: np.ndarray,
    stage32: np.ndarray,
    offsets: np.ndarray,
    wire: np.ndarray,
    header: np.ndarray,
    body: np.ndarray,
    blend: np.ndarray,
    weights: np.ndarray,
    stance_ints: np.ndarray,
    stance_floats: np.ndarray,
    or_flags: np.ndarray,
    t_s: float,
    frame_id: int,
    source_t: float,
    received_ns: int,
    solved_ns: int,
    flags_word: int,
    dt: float,
) -> int:
    """The foot contact (``what & DO_STANCE``), the retarget (``DO_RETARGET``), VMC
    (``DO_VMC``) and the pose message (``DO_POSE``) of one solved frame.

    Args:
        what: ``DO_*`` bits.
        wfb, pfb, rfb: (B, 4) float64 (w, x, y, z): the solved rig pose's
            world_from_bone, parent_from_bone, rest_from_bone.
        root: (3,) float64, metres, world: the rig's root.
        bone_flags: (B,) uint8, the solve's bone flags.
        ei, ef: the plan's arenas (:class:`EmitPlan`).
        tflags: (N,) uint8, the target pose's flags (written by the retarget).
        last_quat, stage32, offsets, wire: ``VmcEncoder.pack_buffers()``.
        header, body: ``PoseEncoder.header_bytes``, ``body_bytes``.
        blend: (K_vmc,) VMC blendshape values; weights: (K,) pose-stream weights.
        stance_ints, stance_floats: ``StanceDetector.pack()`` (or ``_NO_STANCE``).
        or_flags: (B,) uint8 ORed into the sent bone flags (validation), or empty.
        t_s: ``/VMC/Ext/T``, seconds.
        frame_id, source_t, received_ns, solved_ns, flags_word: the pose header's
            (the contact bits ORed into ``flags_word`` with ``DO_STANCE``).
        dt: seconds since the pipeline's last frame (the stance's step).

    Returns:
        The contact's ``FRAME_CONTACT_*`` bits with ``DO_STANCE``
        (``StanceDetector.update``'s), else 0.
    """
    contact = 0
    if what & DO_STANCE:  # StanceDetector.update, before anything reads the pose
        contact = step_packed(root, wfb, dt, stance_ints, stance_floats)
        flags_word |= contact
    n = ei[I_N]
    prog = ei[N_HEAD : N_HEAD + 4 * n].reshape((n, 4))
    cst = ef[ei[I_CST] : ei[I_CST] + n * kt.N_CST].reshape((n, kt.N_CST))
    params = ef[ei[I_PARAMS] : ei[I_PARAMS] + kt.N_PARAMS]
    e = ef[ei[I_E] : ei[I_E] + 4 * n].reshape((n, 4))
    t_rest = ef[ei[I_REST] : ei[I_REST] + 4 * n].reshape((n, 4))
    t_wfb = ef[ei[I_WFB] : ei[I_WFB] + 4 * n].reshape((n, 4))
    t_root = ef[ei[I_ROOT] : ei[I_ROOT] + 3]
    t_hips = ef[ei[I_HIPS] : ei[I_HIPS] + 3]
    t_offsets = ef[ei[I_OFFSETS] : ei[I_OFFSETS] + 3 * n].reshape((n, 3))
    if what & DO_RETARGET:
        retarget_one(
            wfb, root, bone_flags, prog, cst, params, e, t_rest, t_wfb, t_root, t_hips,
            t_offsets, tflags,
        )  # fmt: skip
    if what & DO_VMC:
        bone_pos = ef[ei[I_BONE_POS] : ei[I_BONE_POS] + 3 * n].reshape((n, 3))
        root_quat = ef[ei[I_ROOT_QUAT] : ei[I_ROOT_QUAT] + 4]
        bq = ef[ei[I_BQ] : ei[I_BQ] + 4 * n].reshape((n, 4))
        rp = ef[ei[I_RP] : ei[I_RP] + 3]
        qrhs = ef[ei[I_QRHS] : ei[I_QRHS] + 16].reshape((4, 4))
        prhs = ef[ei[I_PRHS] : ei[I_PRHS] + 9].reshape((3, 3))
        # engine_unity: q_xyzw = q_wxyz @ Q, p = p_world @ P, summed as np.matmul.
        for h in range(n):
            for j in range(4):
                acc = 0.0
                for k in range(4):
                    acc += t_rest[h, k] * qrhs[k, j]
                bq[h, j] = acc
        for j in range(3):
            acc = 0.0
            for k in range(3):
                acc += t_root[k] * prhs[k, j]
            rp[j] = acc
        vmc_pack(
            rp, root_quat, bone_pos, bq, blend, t_s, last_quat, stage32,
            stage32.view(np.uint32), offsets, wire,
        )  # fmt: skip
    if what & DO_POSE:
        pose_pack(
            header, body, frame_id, source_t, received_ns, solved_ns, flags_word, root,
            wfb, pfb, rfb, weights, bone_flags, or_flags,
        )  # fmt: skip
    return contact


def _arenas(n: int) -> tuple[np.ndarray, int]:
    """The int64 arena for ``n`` target bones (its head filled, the program not
    yet) and the float arena's size."""
    sizes = (
        (I_CST, n * kt.N_CST), (I_PARAMS, kt.N_PARAMS), (I_E, 4 * n), (I_REST, 4 * n),
        (I_WFB, 4 * n), (I_ROOT, 3), (I_HIPS, 3), (I_OFFSETS, 3 * n),
        (I_BONE_POS, 3 * n), (I_ROOT_QUAT, 4), (I_BQ, 4 * n), (I_RP, 3), (I_QRHS, 16),
        (I_PRHS, 9),
    )  # fmt: skip
    ei = np.zeros(N_HEAD + 4 * n, dtype=np.int64)
    ei[I_N] = n
    at = 0
    for slot, size in sizes:
        ei[slot] = at
        at += size
    return ei, at


class EmitPlan:
    """The arenas of :func:`emit_frame` for one pipeline (built off the hot path).

    Args:
        retargeter: the pipeline's retargeter (its program is copied).
        vmc: the pipeline's VMC encoder (its buffers are used in place).
        pose_enc: the pipeline's pose encoder (its parts are written in place).
        bone_pos_unity: (N, 3) float64, metres, Unity: each target bone's position
            in its parent (``/VMC/Ext/Bone/Pos``).

    Attributes:
        target_pose: the retargeted frame, its arrays views of the float arena
            (what ``Retargeter.apply`` fills; the pivot and the console read it).
        ei, ef: the int64 and float64 arenas.
        args: the call's per-pipeline arrays, in order (:meth:`bind`).
    """

    def __init__(
        self,
        retargeter: Retargeter,
        vmc: VmcEncoder,
        pose_enc: PoseEncoder,
        bone_pos_unity: np.ndarray,
    ) -> None:
        prog, cst, params = retargeter.program()
        proto = retargeter.new_pose()
        n = prog.shape[0]
        ei, at = _arenas(n)
        ei[N_HEAD:] = prog.ravel()
        ef = np.zeros(at)
        self.ei, self.ef = ei, ef
        self._n = n
        self.view(I_CST, (n, kt.N_CST))[:] = cst
        self.view(I_PARAMS, (kt.N_PARAMS,))[:] = params
        self.view(I_BONE_POS, (n, 3))[:] = bone_pos_unity
        self.view(I_ROOT_QUAT, (4,))[:] = (0.0, 0.0, 0.0, 1.0)  # identity, x y z w
        # The engine's matrices, as its own functions apply them (rows of I @ M).
        qrhs = engine_unity.unity_quat_xyzw_from_world(np.eye(4), np.zeros((4, 4)))
        prhs = engine_unity.unity_pos_from_world(np.eye(3), np.zeros((3, 3)))
        self.view(I_QRHS, (4, 4))[:] = qrhs
        self.view(I_PRHS, (3, 3))[:] = prhs
        offsets = self.view(I_OFFSETS, (n, 3))
        offsets[:] = proto.rest_offsets
        offsets.flags.writeable = False
        self.view(I_E, (n, 4))[:] = proto.world_from_bone_quat  # identity scratch
        pose = TargetPose(
            world_from_bone_quat=self.view(I_WFB, (n, 4)),
            rest_from_bone_quat=self.view(I_REST, (n, 4)),
            root_pos=self.view(I_ROOT, (3,)),
            hips_pos=self.view(I_HIPS, (3,)),
            rest_offsets=offsets,
            flags=proto.flags,
        )
        pose.world_from_bone_quat[:] = proto.world_from_bone_quat
        pose.rest_from_bone_quat[:] = proto.rest_from_bone_quat
        self.target_pose = pose
        self.vmc_buffers = vmc.pack_buffers()
        self.header = pose_enc.header_bytes
        self.body = pose_enc.body_bytes
        self.performer_bits = pose_enc.performer_bits
        self.args: tuple[np.ndarray, ...] = ()  # set by bind()
        self.call: Any = emit_frame  # its compiled function, once bound (bind())
        self.stance: StanceDetector | None = None  # run inside the call (bind())

    def bind(
        self,
        pose: Any,
        blend: np.ndarray,
        weights: np.ndarray,
        stance: StanceDetector | None = None,
    ) -> None:
        """Fix the pipeline's solved pose (``BodyPose`` / ``FitPose``, its arrays
        reused every frame), face outputs and, when the call runs it, its stance
        detector (``stance``: none of post stages, pivot or plant runs between the
        solve and the emit, so the contact can be found inside the call; None: the
        loop runs it, or there is none): :attr:`args` are then :func:`emit_frame`'s
        array arguments from ``wfb`` to ``stance_floats``, one tuple read per frame
        instead of eighteen attributes."""
        arrays = stance.pack() if stance is not None else None
        #: the call finds the contact (``DO_STANCE``): the loop leaves it to it
        self.stance = stance if arrays is not None else None
        self.args = (
            pose.world_from_bone_quat, pose.parent_from_bone_quat,
            pose.rest_from_bone_quat, pose.root_pos, pose.bone_flags, self.ei, self.ef,
            self.target_pose.flags, *self.vmc_buffers, self.header, self.body, blend,
            weights, *(arrays if arrays is not None else _NO_STANCE),
        )  # fmt: skip
        # The same argument types every frame: the compiled function itself, past
        # the dispatcher (the validation bone flags or NO_FLAGS: both (B,) uint8).
        self.call = direct(
            emit_frame, DO_RETARGET, *self.args, NO_FLAGS, 0.0, 0, 0.0, 0, 0, 0, 0.0
        )

    def view(self, slot: int, shape: tuple[int, ...]) -> np.ndarray:
        """The float arena's region ``slot`` (``I_*``) as an array of ``shape``."""
        a = int(self.ei[slot])
        return self.ef[a : a + int(np.prod(shape))].reshape(shape)


def warm_args() -> tuple[np.ndarray, ...]:
    """A tiny plan's arrays after the pose's five (``EmitPlan.args[5:]``: the arenas
    for one target bone, the VMC and pose buffers, no face, no contact), of the
    types a bound plan passes (``live/solve_emit.py``'s warm-up reuses them)."""
    n = 1
    ei, at = _arenas(n)
    ei[N_HEAD + 3] = -1  # the Hips: no parent
    stage = np.zeros(7 * (n + 1) + 1, dtype=np.float32)
    return (
        ei, np.zeros(at), np.zeros(n, dtype=np.uint8), np.zeros((n + 1, 4)), stage,
        np.arange(len(stage), dtype=np.int64) * 4, np.zeros(4 * len(stage), np.uint8),
        np.zeros(68, dtype=np.uint8), np.zeros(52, dtype=np.uint8), np.zeros(0),
        np.zeros(0), *_NO_STANCE,
    )  # fmt: skip


def warm_up() -> None:
    """Compile (or load from the cache) :func:`emit_frame` on a tiny plan, through
    the types the loop passes, so no streamed frame pays for it."""
    b = 1
    quat = np.array([[1.0, 0.0, 0.0, 0.0]])
    u8 = np.zeros(b, dtype=np.uint8)
    emit_frame(
        DO_RETARGET | DO_VMC | DO_POSE, quat, quat, quat, np.zeros(3), u8,
        *warm_args(), np.zeros(0, dtype=np.uint8), 0.0, 0, 0.0, 0, 0, 0, 0.0,
    )  # fmt: skip
