"""What a performer with a body sends while no frame of its comes: its last pose again,
flagged held and source_lost (the capture system is lost), and the VMC calibration
state before and during a calibration (``send.BodyPath`` delegates here)."""

from __future__ import annotations

import struct
from typing import Any

from retargetd.daemon.live.outputs import VMC_STATE_INTERVAL_NS
from retargetd.daemon.live.performer import Performer
from retargetd.daemon.live.shared import Shared
from retargetd.protocols import pose_stream
from retargetd.protocols.vmc_out import (
    CALIBRATION_CALIBRATED,
    CALIBRATION_CALIBRATING,
    CALIBRATION_WAITING,
)

#: Byte offset of the frame flags in the pose-stream data header (PROTOCOLS.md): a
#: held pose sent again is flagged in place.
_FLAGS_OFFSET = struct.calcsize("<4sHHqdqqq")
_FLAGS = struct.Struct("<I")


def resend_held(
    pipe: Any, perf: Performer, sh: Shared, now_ns: int
) -> tuple[bool, bool]:
    """The last pose message of ``pipe`` sent again (its encoder's buffers still
    hold it), flagged held and source_lost, with a new sent time: the capture system
    is lost. Returns (VMC state sent, pose sent)."""
    vmc = perf.vmc
    outputs = sh.outputs
    if outputs.vmc_on:
        # VMC has no frame flags; its own word for this is /VMC/Ext/OK with
        # tracking 0 (VMC 2.7): the model is loaded and calibrated, tracking is
        # lost. Receivers keep the last pose they got and hear the performer is
        # still there (silence reads as "no performer" in EVMC4U and VSeeFace).
        dgram = vmc.state.encode_state(
            CALIBRATION_CALIBRATED, False, (now_ns - sh.t0_ns) * 1e-9
        )
        vmc.send((dgram,))
    if not outputs.publishing:
        return outputs.vmc_on, False
    parts = pipe.pose_enc.parts
    header = parts[0]
    (flags,) = _FLAGS.unpack_from(header, _FLAGS_OFFSET)
    flags |= pose_stream.FRAME_HELD | pose_stream.FRAME_SOURCE_LOST
    _FLAGS.pack_into(header, _FLAGS_OFFSET, flags)
    pose_stream.stamp_sent(header, now_ns)
    outputs.send_pub(parts, now_ns)
    return outputs.vmc_on, True


def send_vmc_state(perf: Performer, sh: Shared, now_ns: int, calibrating: bool) -> None:
    """Before a calibration, and while one collects frames, tell the VMC receiver
    the state (``/VMC/Ext/OK`` calibration state 1 waiting or 2 calibrating, the
    tracking flag) about twice a second: no pose is streamed then, and silence
    reads as "no performer" in EVMC4U and VSeeFace."""
    vmc = perf.vmc
    if not sh.outputs.vmc_on or now_ns < vmc.next_state_ns:
        return
    if perf.calibration is not None and not calibrating:
        return
    vmc.next_state_ns = now_ns + VMC_STATE_INTERVAL_NS
    state = CALIBRATION_CALIBRATING if calibrating else CALIBRATION_WAITING
    tracking = now_ns - sh.last_frame_ns < 1_000_000_000
    dgram = vmc.state.encode_state(state, tracking, (now_ns - sh.t0_ns) * 1e-9)
    vmc.send((dgram,))
