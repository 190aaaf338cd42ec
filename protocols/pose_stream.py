"""ZeroMQ pose stream (PUB): one binary data message per solved frame, plus names.

Byte layout in ``protocols/PROTOCOLS.md`` (section 6). All little-endian.

Data message, two parts:

- header, 68 bytes ``<4sHHqdqqqIHH3f``: magic ``RTDP``, version 2, names id uint16,
  frame number int64, source time float64 s (NaN = unknown), received / solved / sent
  ``time.monotonic_ns()`` of this host (int64), frame flags uint32 (bits 16-23, byte
  50: the performer id, 0 with one performer), n_bones uint16,
  n_weights uint16, root position float32 x 3 (metres, world);
- body: world_from_bone float32 (B, 4) (w, x, y, z); parent_from_bone float32 (B, 4),
  the rotation relative to the parent bone (the world for the root), so
  ``world_from_parent * parent_from_bone = world_from_bone``; rest_from_bone float32
  (B, 4), the same relative to the calibration pose (``conj(rest_parent_from_bone) *
  parent_from_bone``, identity in the calibration pose); weights float32 (K,) in
  [0, 1]; bone flags uint8 (B,), NUL-padded to a multiple of 4. Bones in the rig's
  (solve NPZ) order; rotations in the internal world (right-handed, +Z up).
  (Version 1 had no rest_from_bone and sent it under the name parent_from_bone.)

A third part follows when the daemon solves a face (the stabilized "Mug"):
``<HHI7f`` n_face_markers uint16, reserved uint16, face flags uint32, world_from_head
float32 (w, x, y, z) and head position float32 x 3 (metres, world), then the
stabilized facial markers float32 (M, 3), metres, head coordinates, NaN = occluded.

Validation message, two parts (topic ``RTDV``), one per frame the live validator
checked, sent after that frame's pose: header ``<4sHHqqqIHH`` (40 bytes) magic,
version 1, names id, the checked frame's number, its received_ns, validated_ns,
frame flags (validation bits 8-15 only), n_bones, n_values; body: one float32 value
per check (``VALIDATION_CHECKS`` order), bone flags uint8 (B,) (bits 4-7 only),
NUL-padded to a multiple of 4.

The names id says which names message describes this data (it changes whenever the
names do, e.g. after a rig reload), so a client that joins mid-stream can tell.

Names message, two parts: ``RTDN`` + version uint16 + names id uint16 (8 bytes), then
UTF-8 JSON (rig, bones, parents, weights, flag bits). Sent on change and at least once
a second. The magic doubles as the topic: subscribe to ``b"RTDP"``, ``b"RTDN"`` or
``b"RTD"`` for all.

``sent_ns`` is patched in by :func:`stamp_sent` just before the send.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from retargetd.protocols.errors import DecodeError
from retargetd.protocols.frames import F32Array, F64Array, U8Array

DATA_MAGIC = b"RTDP"
NAMES_MAGIC = b"RTDN"
VALIDATION_MAGIC = b"RTDV"
VERSION = 1  #: names and validation messages
#: The data message (2: parent_from_bone is the true parent-relative rotation and
#: rest_from_bone the calibration-relative one; version 1 sent only the latter).
DATA_VERSION = 2
HEADER = struct.Struct("<4sHHqdqqqIHH3f")  # 68 bytes
NAMES_HEADER = struct.Struct("<4sHH")  # 8 bytes
FACE_HEADER = struct.Struct("<HHI7f")  # 36 bytes, then (M, 3) float32
VALIDATION_HEADER = struct.Struct("<4sHHqqqIHH")  # 40 bytes
SENT_NS_OFFSET = 40
#: The performer id: byte 50 of the header, bits 16-23 of the uint32 at offset 48
#: (reserved before several performers shared a stream; 0 with one performer).
PERFORMER_OFFSET = 50
PERFORMER_SHIFT = 16
PERFORMER_MASK = 0x00FF_0000
MAX_PERFORMERS = 256
_SENT_NS = struct.Struct("<q")
#: The header's flags word (uint32).
FLAGS_OFFSET = 48
_FLAGS_WORD = struct.Struct("<I")
_LE_F32 = np.dtype("<f4")

# Frame flag bits (uint32 in the header).
FRAME_LATE = 1 << 0  # the solve overran its budget; sent late
FRAME_HELD = 1 << 1  # at least one bone holds its last good value
FRAME_RESTARTED = 1 << 2  # the marker source restarted (frame numbers reset)
FRAME_INPUT_DROPPED = 1 << 3  # input frames were dropped since the last pose
FRAME_SOURCE_LOST = 1 << 4  # the capture system is gone: the last good pose, resent
FRAME_RESEEDED = 1 << 5  # the fit lost track and was reseeded from the construction
FRAME_UNEXPLAINED = 1 << 6  # the markers fit no pose: the last explained pose, held
FRAME_UNSEEN = 1 << 7  # the performer's markers not seen: no pose (held or rest)
FRAME_VALIDATION_MASK = 0x0000_FF00  # bits 8-15: validation results (below)
# bits 16-23: the performer id (PERFORMER_SHIFT)
FRAME_CALIBRATION_MISMATCH = 1 << 24  # the calibration does not fit these markers
FRAME_FLAG_BITS = {
    "late": 0, "held": 1, "restarted": 2, "input_dropped": 3, "source_lost": 4,
    "reseeded": 5, "unexplained": 6, "unseen": 7, "calibration_mismatch": 24,
}  # fmt: skip

# Foot contact (issue 34), bits 25-27: stance detected from the solve, per foot
# (daemon/post/stance.py); CONTACT_KNOWN says the detector runs (the rig maps
# LeftFoot and RightFoot): without it bits 25-26 are 0 and mean nothing.
FRAME_CONTACT_LEFT = 1 << 25  # the left foot is on the ground (or on a step)
FRAME_CONTACT_RIGHT = 1 << 26  # the right foot is on the ground (or on a step)
FRAME_CONTACT_KNOWN = 1 << 27  # contact detected for this frame (bits 25-26 valid)
FRAME_FLAG_BITS.update(contact_left=25, contact_right=26, contact_known=27)
# Feet planted on the target (issue 34, ``[target] feet = "plant"``;
# daemon/post/plant.py): a stance foot's hold was out of the target leg's reach this
# frame, so the leg is straightened (or at the knee's most flexion) toward it.
FRAME_PLANT_UNREACHED = 1 << 28
FRAME_FLAG_BITS.update(plant_unreached=28)

# Validation frame bits (8-15), set by the daemon's live validator (``[validate]``):
# one per check, in this order; VALIDATION_CHECKS names them.
FRAME_V_CONVENTION = 1 << 8  # model posed from the chain != streamed skeleton
FRAME_V_FIT = 1 << 9  # streamed skeleton far from the solved joint centres
FRAME_V_QUAT_NORM = 1 << 10  # a rotation is not a unit quaternion
FRAME_V_LIMITS = 1 << 11  # a joint beyond its anatomical swing/twist limits
FRAME_V_SELF_PENETRATION = 1 << 12  # two non-excluded segments overlap
FRAME_V_FLOOR_PENETRATION = 1 << 13  # a segment below the floor
FRAME_V_SPEED = 1 << 14  # root or an end effector faster than a human can move
FRAME_V_FLOATING = 1 << 15  # no foot support for longer than a jump's flight
VALIDATION_CHECKS = (
    "convention",
    "fit",
    "quat_norm",
    "limits",
    "self_penetration",
    "floor_penetration",
    "speed",
    "floating",
)
#: The unit of each check's value in the validation message (PROTOCOLS.md §6).
VALIDATION_UNITS = ("mm", "mm", "", "deg beyond limit", "mm", "mm", "m/s", "s")

# Bone flag bits (one uint8 per bone).
BONE_HELD = 1 << 0  # too little data: last good rotation held
BONE_REBUILT = 1 << 1  # a defining point rebuilt from its rigid segment's other markers
BONE_PARTIAL = 1 << 2  # solved with some defining markers missing
BONE_NEVER = 1 << 3  # never solved since the stream started (rest pose sent)
BONE_VALIDATION_MASK = 0xF0  # bits 4-7: validation results (below)
BONE_FLAG_BITS = {"held": 0, "rebuilt": 1, "partial": 2, "never": 3}
BONE_V_LIMIT = 1 << 4  # this bone's joint is beyond its limits
BONE_V_PENETRATION = 1 << 5  # this bone's segment penetrates another or the floor
BONE_V_FIT = 1 << 6  # this bone's origin/aim is far from its solved joint centre
BONE_V_SPEED = 1 << 7  # this bone (root or end effector) moves impossibly fast
BONE_VALIDATION_BITS = {"limit": 4, "penetration": 5, "fit": 6, "speed": 7}

# Face flag bits (uint32 in the face part).
FACE_HEAD_PARTIAL = 1 << 0  # a head marker was missing (pose fitted from the others)
FACE_HEAD_LOST = 1 << 1  # < 3 head markers: head pose and weights held, markers NaN
FACE_NOT_CONVERGED = 1 << 2  # the weight solve hit its iteration cap (best kept)
FACE_PARTIAL = 1 << 3  # some facial marker occluded (left out of that frame's solve)
FACE_NEVER = 1 << 4  # no good frame yet: identity head pose and zero weights
FACE_SHAPE_HELD = 1 << 5  # a shape's key markers hidden: that shape held (RTDF says)
FACE_FLAG_BITS = {
    "head_partial": 0,
    "head_lost": 1,
    "not_converged": 2,
    "face_partial": 3,
    "never": 4,
    "shape_held": 5,
}

# Shape state bits (one uint8 per solved expression, in the shape-state message).
SHAPE_UNOBSERVED = 1 << 0  # the layout cannot observe it: left out of the solve, 0
SHAPE_HIDDEN = 1 << 1  # a key marker hidden this frame: the last weight held
SHAPE_STATE_BITS = {"unobserved": 0, "hidden": 1}
SHAPE_MAGIC = b"RTDF"
#: Shape-state message: magic, version 1, names id, frame number, K, reserved; then
#: K uint8 states, NUL-padded to a multiple of 4 (one part).
SHAPE_HEADER = struct.Struct("<4sHHqHH")  # 20 bytes


def body_size(n_bones: int, n_weights: int) -> int:
    """Bytes in the body of a data message for ``n_bones`` bones and ``n_weights``."""
    return 48 * n_bones + 4 * n_weights + ((n_bones + 3) & ~3)


def face_size(n_face_markers: int) -> int:
    """Bytes in the face part for ``n_face_markers`` stabilized markers."""
    return FACE_HEADER.size + 12 * n_face_markers


def stamp_sent(header: bytearray | memoryview, t_ns: int) -> None:
    """Write ``sent_ns`` (``time.monotonic_ns()`` just before sending) into a header."""
    _SENT_NS.pack_into(header, SENT_NS_OFFSET, t_ns)


def stamp_flags(header: bytearray | memoryview, flags_word: int) -> None:
    """Overwrite a header's flags word (frame flags, the performer id in bits 16-23),
    e.g. to add ``FRAME_LATE`` to a message packed before the budget ran out."""
    _FLAGS_WORD.pack_into(header, FLAGS_OFFSET, flags_word)


class PoseEncoder:
    """Encodes pose data messages into two preallocated buffers.

    Args:
        n_bones: bones in the rig (the solve's NPZ order), <= 65535.
        n_weights: blendshape weights, <= 65535.
        names_id: the id of the names message describing these bones (0-65535).
        n_face_markers: stabilized facial markers in the face part; None = no face
            part (two-part messages).
        performer: the performer id written at byte 50 (0-255; 0 with one
            performer).

    Attributes:
        parts: ``[header, body]`` (``[header, body, face]`` with a face) memoryviews,
            reused by every :meth:`encode`.
        header_bytes, body_bytes: the first two parts as uint8 arrays (the same
            memory), for ``kernels.pose_pack``.
        performer_bits: the performer id as it sits in the flags word.
    """

    def __init__(
        self,
        n_bones: int,
        n_weights: int,
        names_id: int = 0,
        n_face_markers: int | None = None,
        performer: int = 0,
    ) -> None:
        if not 0 <= performer < MAX_PERFORMERS:
            raise ValueError(
                f"performer must be in [0, {MAX_PERFORMERS - 1}]; got {performer}"
            )
        self.performer = performer
        self._performer_bits = performer << PERFORMER_SHIFT
        if not (0 <= n_bones <= 0xFFFF and 0 <= n_weights <= 0xFFFF):
            raise ValueError(
                "n_bones and n_weights must be in [0, 65535]; "
                f"got {n_bones}, {n_weights}"
            )
        if not 0 <= names_id <= 0xFFFF:
            raise ValueError(f"names_id must be in [0, 65535]; got {names_id}")
        self.n_bones = n_bones
        self.n_weights = n_weights
        self.names_id = names_id
        self._header = bytearray(HEADER.size)
        self._body = bytearray(body_size(n_bones, n_weights))
        b, k = n_bones, n_weights
        self._world = np.frombuffer(self._body, _LE_F32, 4 * b, 0).reshape(b, 4)
        self._parent = np.frombuffer(self._body, _LE_F32, 4 * b, 16 * b).reshape(b, 4)
        self._rest = np.frombuffer(self._body, _LE_F32, 4 * b, 32 * b).reshape(b, 4)
        self._weights = np.frombuffer(self._body, _LE_F32, k, 48 * b)
        self._bone_flags = np.frombuffer(self._body, np.uint8, b, 48 * b + 4 * k)
        self.parts = [memoryview(self._header), memoryview(self._body)]
        # The same bytes as uint8 arrays, for a compiled pack (``kernels.pose_pack``);
        # the header's constant fields are written now, once.
        self.header_bytes = np.frombuffer(self._header, np.uint8)
        self.body_bytes = np.frombuffer(self._body, np.uint8)
        #: The performer id in the bits of the header's flags word (16-23).
        self.performer_bits = self._performer_bits
        HEADER.pack_into(
            self._header, 0, DATA_MAGIC, DATA_VERSION, names_id, 0, 0.0, 0, 0, 0,
            self._performer_bits, n_bones, n_weights, 0.0, 0.0, 0.0,
        )  # fmt: skip
        self.n_face_markers = n_face_markers
        if n_face_markers is not None:
            if not 0 <= n_face_markers <= 0xFFFF:
                raise ValueError(
                    f"n_face_markers must be in [0, 65535]; got {n_face_markers}"
                )
            self._face = bytearray(face_size(n_face_markers))
            self._face_markers = np.frombuffer(
                self._face, _LE_F32, 3 * n_face_markers, FACE_HEADER.size
            ).reshape(n_face_markers, 3)
            self.parts.append(memoryview(self._face))

    def encode(
        self,
        frame_id: int,
        source_time_s: float,
        received_ns: int,
        solved_ns: int,
        flags: int,
        root_pos_world: F64Array,
        world_from_bone_quat: F64Array,
        parent_from_bone_quat: F64Array,
        rest_from_bone_quat: F64Array,
        weights: F64Array,
        bone_flags: U8Array,
    ) -> list[memoryview]:
        """Write one frame; ``sent_ns`` is 0 until :func:`stamp_sent`.

        Args:
            frame_id: the source's frame number.
            source_time_s: the source's timestamp, seconds (NaN when unknown).
            received_ns: ``time.monotonic_ns()`` when the marker frame arrived.
            solved_ns: ``time.monotonic_ns()`` when the solve finished.
            flags: frame flag bits (``FRAME_*``).
            root_pos_world: (3,) float, metres, world frame.
            world_from_bone_quat: (n_bones, 4) float, (w, x, y, z), world frame.
            parent_from_bone_quat: (n_bones, 4) float, (w, x, y, z), relative to the
                parent bone (the world for the root).
            rest_from_bone_quat: (n_bones, 4) float, (w, x, y, z), relative to the
                calibration pose.
            weights: (n_weights,) float in [0, 1].
            bone_flags: (n_bones,) uint8 bone flag bits (``BONE_*``).

        Returns:
            :attr:`parts` (``[header, body]``).
        """
        HEADER.pack_into(
            self._header, 0, DATA_MAGIC, DATA_VERSION, self.names_id, frame_id,
            source_time_s, received_ns, solved_ns, 0,
            (flags & ~PERFORMER_MASK) | self._performer_bits, self.n_bones,
            self.n_weights,
            root_pos_world[0], root_pos_world[1], root_pos_world[2],
        )  # fmt: skip
        self._world[:] = world_from_bone_quat
        self._parent[:] = parent_from_bone_quat
        self._rest[:] = rest_from_bone_quat
        self._weights[:] = weights
        self._bone_flags[:] = bone_flags
        return self.parts

    def encode_face(
        self,
        flags: int,
        world_from_head_quat: F64Array,
        head_pos_world: F64Array,
        markers_head: F64Array,
    ) -> None:
        """Write the face part (this frame's stabilized markers) before sending.

        Args:
            flags: face flag bits (``FACE_*``).
            world_from_head_quat: (4,) (w, x, y, z).
            head_pos_world: (3,) metres, world.
            markers_head: (n_face_markers, 3) metres, head coordinates, NaN = occluded.
        """
        q, p = world_from_head_quat, head_pos_world
        FACE_HEADER.pack_into(
            self._face, 0, self.n_face_markers, 0, flags,
            q[0], q[1], q[2], q[3], p[0], p[1], p[2],
        )  # fmt: skip
        self._face_markers[:] = markers_head


@dataclass(slots=True, eq=False)
class PoseMessage:
    """A decoded pose data message (clients and tests; arrays are copies).

    Attributes:
        frame_id: the source's frame number.
        source_time_s: the source's timestamp, seconds (NaN when unknown).
        received_ns, solved_ns, sent_ns: the sender's ``time.monotonic_ns()`` stamps.
        flags: frame flag bits.
        root_pos_world: (3,) float32, metres, world.
        world_from_bone_quat: (n_bones, 4) float32, (w, x, y, z).
        parent_from_bone_quat: (n_bones, 4) float32, (w, x, y, z), relative to the
            parent bone.
        rest_from_bone_quat: (n_bones, 4) float32, (w, x, y, z), relative to the
            calibration pose.
        weights: (n_weights,) float32.
        bone_flags: (n_bones,) uint8.
        names_id: the names message these bones are described by.
        performer: the performer id (byte 50; 0 with one performer).
        face_flags: face flag bits (``FACE_*``); 0 without a face part.
        world_from_head_quat: (4,) float32 (w, x, y, z), or None without a face.
        head_pos_world: (3,) float32 metres, or None without a face.
        face_markers: (M, 3) float32, metres, head coordinates (NaN = occluded), or
            None without a face part.
    """

    frame_id: int
    source_time_s: float
    received_ns: int
    solved_ns: int
    sent_ns: int
    flags: int
    root_pos_world: F32Array
    world_from_bone_quat: F32Array
    parent_from_bone_quat: F32Array
    rest_from_bone_quat: F32Array
    weights: F32Array
    bone_flags: U8Array
    names_id: int = 0
    performer: int = 0
    face_flags: int = 0
    world_from_head_quat: F32Array | None = None
    head_pos_world: F32Array | None = None
    face_markers: F32Array | None = None


def decode_pose(parts: Sequence[bytes | bytearray | memoryview]) -> PoseMessage:
    """Decode a pose data message.

    Raises:
        DecodeError: ``bad_parts`` (not two or three parts), ``bad_length``,
            ``bad_magic``, ``bad_version``.
    """
    if len(parts) not in (2, 3):
        raise DecodeError("bad_parts", f"{len(parts)} parts, expected 2 or 3")
    header, body = parts[0], parts[1]
    if len(header) != HEADER.size:
        raise DecodeError("bad_length", f"header of {len(header)} bytes, expected 68")
    (magic, version, names_id, frame_id, time_s, received, solved, sent, flags, b, k,
     x, y, z) = HEADER.unpack_from(header)  # fmt: skip
    if magic != DATA_MAGIC:
        raise DecodeError("bad_magic", f"expected {DATA_MAGIC!r}; got {magic!r}")
    if version != DATA_VERSION:
        raise DecodeError("bad_version", f"version {version}, expected {DATA_VERSION}")
    if len(body) != body_size(b, k):
        raise DecodeError("bad_length", f"body of {len(body)} bytes for {b} bones, {k}")
    data = bytes(body)
    face: dict[str, Any] = {}
    if len(parts) == 3:
        face = _decode_face(parts[2])
    return PoseMessage(
        frame_id=frame_id,
        source_time_s=time_s,
        received_ns=received,
        solved_ns=solved,
        sent_ns=sent,
        flags=flags & ~PERFORMER_MASK,
        root_pos_world=np.array([x, y, z], dtype=np.float32),
        world_from_bone_quat=np.frombuffer(data, _LE_F32, 4 * b, 0)
        .reshape(b, 4)
        .copy(),
        parent_from_bone_quat=np.frombuffer(data, _LE_F32, 4 * b, 16 * b)
        .reshape(b, 4)
        .copy(),
        rest_from_bone_quat=np.frombuffer(data, _LE_F32, 4 * b, 32 * b)
        .reshape(b, 4)
        .copy(),
        weights=np.frombuffer(data, _LE_F32, k, 48 * b).copy(),
        bone_flags=np.frombuffer(data, np.uint8, b, 48 * b + 4 * k).copy(),
        names_id=names_id,
        performer=(flags & PERFORMER_MASK) >> PERFORMER_SHIFT,
        **face,
    )


def _decode_face(part: bytes | bytearray | memoryview) -> dict[str, Any]:
    if len(part) < FACE_HEADER.size:
        raise DecodeError("bad_length", f"face part of {len(part)} bytes, < 36")
    m, _reserved, flags, *vals = FACE_HEADER.unpack_from(part)
    if len(part) != face_size(m):
        raise DecodeError("bad_length", f"face part of {len(part)} bytes for {m}")
    data = bytes(part)
    return {
        "face_flags": flags,
        "world_from_head_quat": np.array(vals[:4], dtype=np.float32),
        "head_pos_world": np.array(vals[4:], dtype=np.float32),
        "face_markers": np.frombuffer(data, _LE_F32, 3 * m, FACE_HEADER.size)
        .reshape(m, 3)
        .copy(),
    }


@dataclass(frozen=True, slots=True, kw_only=True)
class PoseNames:
    """What the numbers of a data message mean: sent in the names message.

    Attributes:
        rig: the rig's name.
        bone_names: bone names, in body order.
        bone_parents: parent index per bone, -1 for the root.
        weight_names: blendshape names, in body order.
        names_id: echoed in every data message these names describe (0-65535).
        face_markers: the face part's stabilized marker names, in order (empty
            without a face).
        performer: the performer's name ("" with one performer: then the JSON
            has no ``performer`` keys).
        performer_id: its id, as at byte 50 of the data header.
        bone_humanoid: per bone, its humanoid (Unity ``HumanBodyBones``) name, ""
            for a bone the rig maps to none (empty: not sent, an older sender).
        unobserved: the weights the marker layout cannot observe: left out of the
            solve and sent as 0 (sent with a face; empty from an older sender).
    """

    rig: str
    bone_names: tuple[str, ...]
    bone_parents: tuple[int, ...]
    weight_names: tuple[str, ...]
    names_id: int = 0
    face_markers: tuple[str, ...] = ()
    performer: str = ""
    performer_id: int = 0
    bone_humanoid: tuple[str, ...] = ()
    unobserved: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        n = len(self.bone_names)
        if len(self.bone_parents) != n or any(
            not -1 <= p < n for p in self.bone_parents
        ):
            raise ValueError(
                f"bone_parents must hold one index in [-1, {n}) per bone; "
                f"got {self.bone_parents}"
            )
        if self.bone_humanoid and len(self.bone_humanoid) != n:
            raise ValueError(
                f"bone_humanoid must hold one name per bone ({n}); "
                f"got {len(self.bone_humanoid)}"
            )


def encode_pose_names(names: PoseNames) -> list[bytes]:
    """Encode the names message ``[header, json]`` (sent on change and >= 1 Hz)."""
    doc = {
        "schema": "retargetd.pose_names",
        "version": VERSION,
        "names_id": names.names_id,
        "rig": names.rig,
        "bones": list(names.bone_names),
        "humanoid": list(names.bone_humanoid),
        "parents": list(names.bone_parents),
        "weights": list(names.weight_names),
        "quat_order": "wxyz",
        "frame": "world: right-handed, +Z up, metres",
        "frame_flag_bits": FRAME_FLAG_BITS,
        "bone_flag_bits": BONE_FLAG_BITS,
        "validation_bits": {"frame": [8, 15], "bone": [4, 7]},
        "validation_checks": list(VALIDATION_CHECKS),
        "bone_validation_bits": BONE_VALIDATION_BITS,
        "face_markers": list(names.face_markers),
        "face_flag_bits": FACE_FLAG_BITS,
    }
    if names.face_markers:  # with a face: the shape states (RTDF) and what is unseen
        doc["shape_state_bits"] = SHAPE_STATE_BITS
        doc["unobserved"] = list(names.unobserved)
    if names.performer:  # several performers share the stream
        doc["performer"] = names.performer
        doc["performer_id"] = names.performer_id
    body = json.dumps(doc, separators=(",", ":"), ensure_ascii=False).encode()
    return [NAMES_HEADER.pack(NAMES_MAGIC, VERSION, names.names_id), body]


def _str_list(doc: dict[str, Any], key: str) -> tuple[str, ...]:
    value = doc.get(key)
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise DecodeError("bad_json", f"{key!r} must be a list of strings")
    return tuple(value)


def decode_pose_names(parts: Sequence[bytes | bytearray | memoryview]) -> PoseNames:
    """Decode a names message.

    Raises:
        DecodeError: ``bad_parts``, ``bad_length``, ``bad_magic``, ``bad_version``,
            ``bad_json`` (not UTF-8 JSON, or fields of the wrong type or length).
    """
    if len(parts) != 2:
        raise DecodeError("bad_parts", f"{len(parts)} parts, expected 2")
    header, body = parts
    if len(header) != NAMES_HEADER.size:
        raise DecodeError("bad_length", f"header of {len(header)} bytes, expected 8")
    magic, version, names_id = NAMES_HEADER.unpack_from(header)
    if magic != NAMES_MAGIC:
        raise DecodeError("bad_magic", f"expected {NAMES_MAGIC!r}; got {magic!r}")
    if version != VERSION:
        raise DecodeError("bad_version", f"version {version}, expected {VERSION}")
    try:
        doc = json.loads(bytes(body).decode())
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise DecodeError("bad_json", "names message is not UTF-8 JSON") from exc
    if not isinstance(doc, dict) or not isinstance(doc.get("rig"), str):
        raise DecodeError("bad_json", "expected an object with a 'rig' string")
    parents = doc.get("parents")
    if not isinstance(parents, list) or not all(
        isinstance(p, int) and not isinstance(p, bool) for p in parents
    ):
        raise DecodeError("bad_json", "'parents' must be a list of integers")
    has_face = "face_markers" in doc
    humanoid = _str_list(doc, "humanoid") if "humanoid" in doc else ()
    performer = doc.get("performer", "")
    performer_id = doc.get("performer_id", 0)
    if not isinstance(performer, str) or type(performer_id) is not int:
        raise DecodeError("bad_json", "'performer' must be a string, its id an int")
    try:
        return PoseNames(
            rig=doc["rig"],
            bone_names=_str_list(doc, "bones"),
            bone_parents=tuple(parents),
            weight_names=_str_list(doc, "weights"),
            names_id=names_id,
            face_markers=_str_list(doc, "face_markers") if has_face else (),
            performer=performer,
            performer_id=performer_id,
            bone_humanoid=humanoid,
            unobserved=_str_list(doc, "unobserved") if "unobserved" in doc else (),
        )
    except ValueError as exc:
        if isinstance(exc, DecodeError):
            raise
        raise DecodeError("bad_json", str(exc)) from exc


# ---- validation messages -----------------------------------------------------------


@dataclass(slots=True, eq=False)
class ValidationMessage:
    """A decoded validation message (one checked frame).

    Attributes:
        names_id: the names message describing the bones.
        frame_id: the checked frame's number (as in its data message).
        received_ns: that frame's received_ns (matches its data message).
        validated_ns: the sender's ``time.monotonic_ns()`` when the checks finished.
        flags: validation frame bits (8-15).
        values: (n_values,) float32, one measured value per check
            (``VALIDATION_CHECKS`` order).
        bone_flags: (n_bones,) uint8, validation bone bits (4-7).
    """

    names_id: int
    frame_id: int
    received_ns: int
    validated_ns: int
    flags: int
    values: F32Array
    bone_flags: U8Array


def validation_body_size(n_bones: int, n_values: int) -> int:
    """Bytes in the body of a validation message."""
    return 4 * n_values + ((n_bones + 3) & ~3)


class ValidationEncoder:
    """Writes validation messages (``RTDV``) into preallocated buffers: no
    allocation per message (the loop publishes one per validated frame).

    Args:
        n_bones: bones per message (B).
        n_values: measured values per message (K; ``len(VALIDATION_CHECKS)``).
    """

    def __init__(self, n_bones: int, n_values: int = len(VALIDATION_CHECKS)) -> None:
        self.n_bones = n_bones
        self.n_values = n_values
        self._header = bytearray(VALIDATION_HEADER.size)
        self._body = bytearray(validation_body_size(n_bones, n_values))
        self._values = np.frombuffer(self._body, _LE_F32, n_values, 0)
        self._bones = np.frombuffer(self._body, np.uint8, n_bones, 4 * n_values)
        self.parts = [memoryview(self._header), memoryview(self._body)]

    def encode(
        self,
        names_id: int,
        frame_id: int,
        received_ns: int,
        validated_ns: int,
        flags: int,
        values: F64Array | F32Array,
        bone_flags: U8Array,
    ) -> list[memoryview]:
        """Write one message; returns ``parts`` (valid until the next call)."""
        VALIDATION_HEADER.pack_into(
            self._header, 0, VALIDATION_MAGIC, VERSION, names_id, frame_id,
            received_ns, validated_ns, flags, self.n_bones, self.n_values,
        )  # fmt: skip
        self._values[:] = values
        self._bones[:] = bone_flags
        return self.parts


def encode_validation(
    names_id: int,
    frame_id: int,
    received_ns: int,
    validated_ns: int,
    flags: int,
    values: F64Array | F32Array,
    bone_flags: U8Array,
) -> list[bytes]:
    """Encode one validation message ``[header, body]`` as new bytes
    (:class:`ValidationEncoder` without reuse)."""
    enc = ValidationEncoder(len(bone_flags), len(values))
    parts = enc.encode(
        names_id, frame_id, received_ns, validated_ns, flags, values, bone_flags
    )
    return [bytes(x) for x in parts]


def decode_validation(
    parts: Sequence[bytes | bytearray | memoryview],
) -> ValidationMessage:
    """Decode a validation message.

    Raises:
        DecodeError: ``bad_parts``, ``bad_length``, ``bad_magic``, ``bad_version``.
    """
    if len(parts) != 2:
        raise DecodeError("bad_parts", f"{len(parts)} parts, expected 2")
    header, body = parts
    if len(header) != VALIDATION_HEADER.size:
        raise DecodeError("bad_length", f"header of {len(header)} bytes, expected 40")
    (magic, version, names_id, frame_id, received, validated, flags, b,
     k) = VALIDATION_HEADER.unpack_from(header)  # fmt: skip
    if magic != VALIDATION_MAGIC:
        raise DecodeError("bad_magic", f"expected {VALIDATION_MAGIC!r}; got {magic!r}")
    if version != VERSION:
        raise DecodeError("bad_version", f"version {version}, expected {VERSION}")
    if len(body) != validation_body_size(b, k):
        raise DecodeError("bad_length", f"body of {len(body)} bytes for {b} bones, {k}")
    data = bytes(body)
    return ValidationMessage(
        names_id=names_id,
        frame_id=frame_id,
        received_ns=received,
        validated_ns=validated,
        flags=flags,
        values=np.frombuffer(data, _LE_F32, k, 0).copy(),
        bone_flags=np.frombuffer(data, np.uint8, b, 4 * k).copy(),
    )


def shape_size(n_weights: int) -> int:
    """Bytes in a shape-state message for ``n_weights`` expressions."""
    return SHAPE_HEADER.size + ((n_weights + 3) & ~3)


class ShapeStateEncoder:
    """Encodes shape-state messages (``RTDF``, one part) into one reused buffer.

    Args:
        n_weights: solved expressions (the data message's K), <= 65535.
        names_id: the names message's id.

    Attributes:
        part: the message (a memoryview of the buffer).
    """

    def __init__(self, n_weights: int, names_id: int = 0) -> None:
        if not (0 <= n_weights <= 0xFFFF and 0 <= names_id <= 0xFFFF):
            raise ValueError(
                f"n_weights and names_id must be in [0, 65535]; "
                f"got {n_weights}, {names_id}"
            )
        self.n_weights, self.names_id = n_weights, names_id
        self._buf = bytearray(shape_size(n_weights))
        self._states = np.frombuffer(self._buf, np.uint8, n_weights, SHAPE_HEADER.size)
        self.part = memoryview(self._buf)

    def encode(self, frame_id: int, states: U8Array) -> memoryview:
        """Write one frame's states, (n_weights,) uint8 ``SHAPE_*`` bits."""
        SHAPE_HEADER.pack_into(
            self._buf, 0, SHAPE_MAGIC, VERSION, self.names_id, frame_id,
            self.n_weights, 0,
        )  # fmt: skip
        self._states[:] = states
        return self.part


@dataclass(slots=True, eq=False)
class ShapeStateMessage:
    """A decoded shape-state message.

    Attributes:
        names_id: the names message describing the weights.
        frame_id: the frame number of the data message it follows.
        states: (K,) uint8 ``SHAPE_*`` bits, in the names message's weight order.
    """

    names_id: int
    frame_id: int
    states: U8Array


def decode_shape_state(part: bytes | bytearray | memoryview) -> ShapeStateMessage:
    """Decode a shape-state message (one part).

    Raises:
        DecodeError: ``bad_length``, ``bad_magic``, ``bad_version``.
    """
    if len(part) < SHAPE_HEADER.size:
        raise DecodeError("bad_length", f"shape state of {len(part)} bytes, < 20")
    magic, version, names_id, frame_id, k, _ = SHAPE_HEADER.unpack_from(part)
    if magic != SHAPE_MAGIC:
        raise DecodeError("bad_magic", f"expected {SHAPE_MAGIC!r}; got {magic!r}")
    if version != VERSION:
        raise DecodeError("bad_version", f"version {version}, expected {VERSION}")
    if len(part) != shape_size(k):
        raise DecodeError("bad_length", f"shape state of {len(part)} bytes for {k}")
    states = np.frombuffer(bytes(part), np.uint8, k, SHAPE_HEADER.size).copy()
    return ShapeStateMessage(names_id=names_id, frame_id=frame_id, states=states)
