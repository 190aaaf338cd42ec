"""VMC protocol output (OSC over UDP, default 127.0.0.1:39539), encoded from templates.

Per frame, in this order (``shared/reference/engines.md``, PROTOCOLS.md section 5)::

    /VMC/Ext/Root/Pos  ,sfffffff  "root" px py pz qx qy qz qw
    /VMC/Ext/Bone/Pos  ,sfffffff  NAME   px py pz qx qy qz qw     (every bone)
    /VMC/Ext/Blend/Val ,sf        NAME   value                     (every blendshape)
    /VMC/Ext/Blend/Apply ,
    /VMC/Ext/OK        ,iiii      1 3 0 1  (VMC 2.7: model loaded, calibrated,
                                           normal calibration mode, tracking ok)
    /VMC/Ext/T         ,f         t  (sender time, seconds)

A face-only performer (no body: README "A face alone") sends
:class:`BlendEncoder`'s frames: the same messages without ``Root/Pos`` and
``Bone/Pos`` (the avatar's body is someone else's to move)::

    /VMC/Ext/Blend/Val ,sf NAME value   (every blendshape), /VMC/Ext/Blend/Apply ,
    /VMC/Ext/OK ,iiii 1 3 0 1, /VMC/Ext/T ,f t

Before a calibration (nothing to stream yet) and while one collects frames, the
daemon sends :meth:`VmcEncoder.encode_state` instead, about twice a second: a bundle
of ``/VMC/Ext/OK ,iiii 1 S 0 K`` (S = 1 waiting for calibration, 2 calibrating;
K = 1 while markers arrive, else 0) and ``/VMC/Ext/T``, so receivers (EVMC4U, VSeeFace)
show the state rather than silence.

All values in Unity's frame (left-handed, +Y up, metres, x y z w; see
``engine_unity``). The messages are packed in order into bundles (time tag
"immediately"), each datagram at most ``max_datagram`` bytes: :data:`MAX_DATAGRAM`
to another machine, so nothing is IP-fragmented, :data:`LOOPBACK_MAX_DATAGRAM` to
this one, where a frame is one datagram and one send (:func:`datagram_limit`);
``/VMC/Ext/T`` is the last message of the last datagram.

Every message is prebuilt once; the float slots of all datagrams are one big-endian
float32 view over one buffer, so a frame is encoded by a handful of array writes and
one scatter (no per-message Python objects).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import numpy as np

from retargetd.protocols import kernels
from retargetd.protocols.frames import F64Array, IntArray
from retargetd.protocols.humanoid import HUMANOID_BONES
from retargetd.protocols.marker_input import MAX_MESSAGE_BYTES
from retargetd.protocols.osc_wire import (
    BUNDLE_HEADER,
    ELEMENT_SIZE_PREFIX,
    build_message,
)

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 39539
#: Largest UDP payload sent off this machine: a 1500-byte Ethernet MTU minus IPv4 (20)
#: and UDP (8), so nothing is IP-fragmented (one lost fragment loses the datagram).
MAX_DATAGRAM = 1472
#: Largest UDP payload sent to a loopback receiver. Loopback never fragments below its
#: 64 KiB MTU, so the limit is the receivers' buffers: python-osc's UDP servers read
#: with ``socketserver.UDPServer.max_packet_size`` = 8192 bytes (CPython's
#: ``socketserver``; a longer datagram is cut there), the smallest of the VMC
#: receivers we know (uOSC, under EVMC4U, reads whole datagrams). A frame of the
#: 22 humanoid bones is 1.9 KB, 4.8 KB with 52 blendshapes: one datagram, one send.
LOOPBACK_MAX_DATAGRAM = 8192
#: The least ``max_datagram``: every IPv4 host accepts a 576-byte datagram (RFC 791),
#: minus IPv4 (20) and UDP (8).
MIN_DATAGRAM = 548


def datagram_limit(loopback: bool, configured: int = 0) -> int:
    """The largest datagram sent to a receiver: ``configured`` when not 0, else
    :data:`LOOPBACK_MAX_DATAGRAM` to a loopback one and :data:`MAX_DATAGRAM` to any
    other."""
    if configured:
        return configured
    return LOOPBACK_MAX_DATAGRAM if loopback else MAX_DATAGRAM


ROOT_ADDRESS = "/VMC/Ext/Root/Pos"
BONE_ADDRESS = "/VMC/Ext/Bone/Pos"
BLEND_VAL_ADDRESS = "/VMC/Ext/Blend/Val"
BLEND_APPLY_ADDRESS = "/VMC/Ext/Blend/Apply"
OK_ADDRESS = "/VMC/Ext/OK"
#: ``/VMC/Ext/OK`` calibration states (VMC protocol 2.5+).
CALIBRATION_UNCALIBRATED = 0
CALIBRATION_WAITING = 1
CALIBRATION_CALIBRATING = 2
CALIBRATION_CALIBRATED = 3
TIME_ADDRESS = "/VMC/Ext/T"
_NAN7 = [float("nan")] * 7


def _pack(
    messages: list[tuple[bytes, int]], max_datagram: int
) -> tuple[bytearray, list[int], IntArray]:
    """Pack ``(message, n_trailing_floats)`` in order into bundles <= max_datagram.

    Returns the buffer (datagrams back to back), the datagram boundaries and the
    float32 index (into the buffer viewed as 4-byte words) of every float slot.
    """
    buf = bytearray()
    bounds = [0]
    slots: list[int] = []
    for msg, n_floats in messages:
        element = ELEMENT_SIZE_PREFIX + len(msg)
        if len(BUNDLE_HEADER) + element > max_datagram:
            raise ValueError(f"a {len(msg)}-byte VMC message cannot fit one datagram")
        if len(buf) == bounds[-1] or len(buf) - bounds[-1] + element > max_datagram:
            if len(buf) != bounds[-1]:
                bounds.append(len(buf))
            buf += BUNDLE_HEADER
        buf += len(msg).to_bytes(4, "big")
        end = len(buf) + len(msg)
        buf += msg
        # Float slots are the message's last n_floats words (all offsets are 4-aligned).
        slots.extend(range(end // 4 - n_floats, end // 4))
    bounds.append(len(buf))
    return buf, bounds, np.array(slots, dtype=np.intp)


class VmcEncoder:
    """Encodes one frame of VMC into prebuilt datagrams.

    Args:
        bone_names: bone names, in the order of the ``bone_*`` arrays given to
            :meth:`encode` (default :data:`HUMANOID_BONES`; add any others you send).
        blend_names: blendshape clip names, in the order of ``blend``; may be empty.
        max_datagram: the largest datagram, bytes (:func:`datagram_limit`; at least
            :data:`MIN_DATAGRAM`): the messages are packed in order, greedily.

    Attributes:
        datagrams: the datagrams of a frame, in send order (memoryviews into one
            reused buffer: send them before the next :meth:`encode`).
    """

    def __init__(
        self,
        bone_names: Sequence[str] = HUMANOID_BONES,
        blend_names: Sequence[str] = (),
        max_datagram: int = MAX_DATAGRAM,
    ) -> None:
        if not MIN_DATAGRAM <= max_datagram <= MAX_MESSAGE_BYTES:  # UDP payload
            raise ValueError(
                f"max_datagram must be {MIN_DATAGRAM}-{MAX_MESSAGE_BYTES} bytes; got "
                f"{max_datagram}"
            )
        names = tuple(bone_names)
        blends = tuple(blend_names)
        for kind, seq in (("bone", names), ("blendshape", blends)):
            if len(set(seq)) != len(seq) or not all(seq):
                raise ValueError(
                    f"{kind} names must be unique and non-empty; got {seq}"
                )
        self.bone_names = names
        self.blend_names = blends
        n_pose = 1 + len(names)
        messages = [(build_message(ROOT_ADDRESS, ",sfffffff", ["root", *_NAN7]), 7)]
        messages += [
            (build_message(BONE_ADDRESS, ",sfffffff", [name, *_NAN7]), 7)
            for name in names
        ]
        messages += [
            (build_message(BLEND_VAL_ADDRESS, ",sf", [name, 0.0]), 1) for name in blends
        ]
        messages += [
            (build_message(BLEND_APPLY_ADDRESS, ",", []), 0),
            (build_message(OK_ADDRESS, ",iiii", [1, CALIBRATION_CALIBRATED, 0, 1]), 0),
            (build_message(TIME_ADDRESS, ",f", [0.0]), 1),
        ]
        self._buf, bounds, self._slots = _pack(messages, max_datagram)
        view = memoryview(self._buf)
        self.datagrams = [view[a:b] for a, b in itertools.pairwise(bounds)]
        # One compiled call writes a frame (``kernels.vmc_pack``): the floats staged
        # as float32 in slot order ((root + bones) x 7, the blend values, T), each
        # written big-endian at its byte offset in the datagrams.
        self._wire = np.frombuffer(self._buf, dtype=np.uint8)
        self._offsets = np.ascontiguousarray(self._slots * 4, dtype=np.int64)
        self._stage32 = np.zeros(len(self._slots), dtype=np.float32)
        self._stage_bits = self._stage32.view(np.uint32)
        self._last_quat: F64Array = np.zeros((n_pose, 4))
        # The state bundle (before and during a calibration): OK + T, prebuilt; the
        # calibration state, the tracking flag and the time are patched in place.
        state_ok = build_message(OK_ADDRESS, ",iiii", [1, 0, 0, 0])
        state_t = build_message(TIME_ADDRESS, ",f", [0.0])
        self._state = bytearray(
            BUNDLE_HEADER
            + (len(state_ok)).to_bytes(4, "big") + state_ok
            + (len(state_t)).to_bytes(4, "big") + state_t
        )  # fmt: skip
        base = len(BUNDLE_HEADER) + 4
        self._state_ints = np.frombuffer(
            self._state, dtype=">i4", count=4, offset=base + len(state_ok) - 16
        )
        self._state_time = np.frombuffer(
            self._state, dtype=">f4", count=1, offset=len(self._state) - 4
        )
        self.state_datagram = memoryview(self._state)
        self.reset_continuity()

    def pack_buffers(
        self,
    ) -> tuple[F64Array, np.ndarray, IntArray, np.ndarray]:
        """``(last_quat, stage32, offsets, wire)`` as :func:`kernels.vmc_pack` takes
        them (its stage bits are ``stage32.view(np.uint32)``), for a kernel that packs
        a frame inside its own call (``daemon/live/emit.py``): the same state as
        :meth:`encode`, so the two can be mixed and :meth:`reset_continuity` holds."""
        return self._last_quat, self._stage32, self._offsets, self._wire

    def encode_state(
        self, calibration_state: int, tracking_ok: bool, t_s: float
    ) -> memoryview:
        """The state datagram: ``/VMC/Ext/OK ,iiii 1 calibration_state 0 tracking``
        then ``/VMC/Ext/T``, in one bundle (written in place; returns
        :attr:`state_datagram`).

        Args:
            calibration_state: ``CALIBRATION_*`` (0-3).
            tracking_ok: markers are arriving.
            t_s: sender time in seconds.
        """
        if not 0 <= calibration_state <= 3:
            raise ValueError(f"calibration_state must be 0-3; got {calibration_state}")
        self._state_ints[1] = calibration_state
        self._state_ints[3] = 1 if tracking_ok else 0
        self._state_time[0] = t_s
        return self.state_datagram

    def reset_continuity(self) -> None:
        """Forget the last quaternions sent (e.g. after a receiver restart): the next
        frame is kept on the hemisphere of the identity (w >= 0), so the first frame's
        signs are deterministic too."""
        self._last_quat[:] = (0.0, 0.0, 0.0, 1.0)  # x y z w identity

    def encode(
        self,
        root_pos_unity: F64Array,
        root_quat_xyzw: F64Array,
        bone_pos_unity: F64Array,
        bone_quat_xyzw: F64Array,
        blend: F64Array,
        t_s: float,
    ) -> list[memoryview]:
        """Write one frame into the datagrams and return them.

        Each quaternion (the root's and every bone's) is negated when its dot product
        with the one sent last frame is < 0 (with the identity for the first frame),
        so receivers that blend never take the long way round.

        Args:
            root_pos_unity: (3,) float, metres, Unity frame: the model root's position.
            root_quat_xyzw: (4,) float, (x, y, z, w), Unity frame.
            bone_pos_unity: (n_bones, 3) float, metres: each bone's position in its
                parent (the target rest pose's offsets; never zeros).
            bone_quat_xyzw: (n_bones, 4) float, (x, y, z, w): parent_from_bone.
            blend: (n_blend,) float in [0, 1], in ``blend_names`` order.
            t_s: sender time in seconds (``/VMC/Ext/T``; float32 on the wire, so keep
                it small, e.g. seconds since the stream started).

        Returns:
            :attr:`datagrams`, in send order.
        """
        kernels.vmc_pack(
            root_pos_unity, root_quat_xyzw, bone_pos_unity, bone_quat_xyzw, blend,
            t_s, self._last_quat, self._stage32, self._stage_bits, self._offsets,
            self._wire,
        )  # fmt: skip
        return self.datagrams


class BlendEncoder:
    """Encodes the blendshapes of a face alone into prebuilt datagrams (no root, no
    bones: module docstring).

    Args:
        blend_names: blendshape clip names, in the order of ``blend``.
        max_datagram: the largest datagram, bytes (:func:`datagram_limit`).

    Attributes:
        datagrams: the datagrams of a frame, in send order (views into one reused
            buffer: send them before the next :meth:`encode`).
    """

    def __init__(
        self, blend_names: Sequence[str], max_datagram: int = MAX_DATAGRAM
    ) -> None:
        if not MIN_DATAGRAM <= max_datagram <= MAX_MESSAGE_BYTES:
            raise ValueError(
                f"max_datagram must be {MIN_DATAGRAM}-{MAX_MESSAGE_BYTES} bytes; got "
                f"{max_datagram}"
            )
        blends = tuple(blend_names)
        if len(set(blends)) != len(blends) or not all(blends):
            raise ValueError(f"blendshape names must be unique and non-empty; {blends}")
        self.blend_names = blends
        messages = [
            (build_message(BLEND_VAL_ADDRESS, ",sf", [name, 0.0]), 1) for name in blends
        ]
        messages += [
            (build_message(BLEND_APPLY_ADDRESS, ",", []), 0),
            (build_message(OK_ADDRESS, ",iiii", [1, CALIBRATION_CALIBRATED, 0, 1]), 0),
            (build_message(TIME_ADDRESS, ",f", [0.0]), 1),
        ]
        self._buf, bounds, slots = _pack(messages, max_datagram)
        view = memoryview(self._buf)
        self.datagrams = [view[a:b] for a, b in itertools.pairwise(bounds)]
        self._wire = np.frombuffer(self._buf, dtype=">f4")
        self._slots = np.ascontiguousarray(slots, dtype=np.intp)
        self._stage = np.zeros(len(slots), dtype=">f4")

    def encode(self, blend: F64Array, t_s: float) -> list[memoryview]:
        """Write one frame (``blend`` (n,) in [0, 1], ``t_s`` the sender time in
        seconds) and return :attr:`datagrams`."""
        n = len(self.blend_names)
        self._stage[:n] = blend
        self._stage[n] = t_s
        self._wire[self._slots] = self._stage
        return self.datagrams
