"""ZeroMQ pose stream: golden header, round trips, sent stamp, names, fuzzing."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from retargetd.protocols import pose_stream as ps
from retargetd.protocols.errors import DecodeError

NAMES_HEAD = b"RTDN\x01\x00\x00\x00"
NAMES = ps.PoseNames(
    rig="menache",
    bone_names=("pelvis", "lumbar", "torso"),
    bone_parents=(-1, 0, 1),
    weight_names=("A", "Blink"),
    bone_humanoid=("Hips", "Spine", ""),
)


def _encode(rng: np.random.Generator, enc: ps.PoseEncoder) -> tuple[list, dict]:
    b, k = enc.n_bones, enc.n_weights
    args = {
        "frame_id": 41,
        "source_time_s": 1.25,
        "received_ns": 1_000,
        "solved_ns": 2_000,
        "flags": ps.FRAME_HELD | ps.FRAME_LATE,
        "root_pos_world": np.array([0.1, -0.2, 0.95]),
        "world_from_bone_quat": rng.normal(size=(b, 4)),
        "parent_from_bone_quat": rng.normal(size=(b, 4)),
        "rest_from_bone_quat": rng.normal(size=(b, 4)),
        "weights": rng.uniform(size=k),
        "bone_flags": np.array([ps.BONE_HELD, 0, ps.BONE_NEVER][:b], dtype=np.uint8),
    }
    return enc.encode(**args), args


def test_header_layout_is_pinned(rng: np.random.Generator) -> None:
    enc = ps.PoseEncoder(3, 2)
    parts, _ = _encode(rng, enc)
    assert parts is enc.parts
    header = bytes(parts[0])
    assert ps.HEADER.size == 68 and len(header) == 68
    assert header[:8] == b"RTDP\x02\x00\x00\x00"
    assert struct.unpack_from("<q", header, 8) == (41,)
    assert struct.unpack_from("<3q", header, 24) == (1_000, 2_000, 0)
    assert struct.unpack_from("<IHH", header, 48) == (3, 3, 2)
    assert len(parts[1]) == ps.body_size(3, 2) == 48 * 3 + 4 * 2 + 4


def test_round_trip_and_sent_stamp(rng: np.random.Generator) -> None:
    enc = ps.PoseEncoder(3, 2)
    parts, args = _encode(rng, enc)
    ps.stamp_sent(parts[0], 3_000)
    msg = ps.decode_pose([bytes(p) for p in parts])
    assert (msg.frame_id, msg.source_time_s) == (41, 1.25)
    assert (msg.received_ns, msg.solved_ns, msg.sent_ns) == (1_000, 2_000, 3_000)
    assert msg.flags == ps.FRAME_HELD | ps.FRAME_LATE
    np.testing.assert_array_equal(
        msg.root_pos_world, np.float32(args["root_pos_world"])
    )
    for key in (
        "world_from_bone_quat",
        "parent_from_bone_quat",
        "rest_from_bone_quat",
        "weights",
    ):
        np.testing.assert_array_equal(getattr(msg, key), np.float32(args[key]))
    np.testing.assert_array_equal(msg.bone_flags, args["bone_flags"])


def test_flag_bits_do_not_overlap_validation() -> None:
    frame_bits = (
        ps.FRAME_LATE | ps.FRAME_HELD | ps.FRAME_RESTARTED | ps.FRAME_INPUT_DROPPED
        | ps.FRAME_SOURCE_LOST | ps.FRAME_RESEEDED | ps.FRAME_UNEXPLAINED
        | ps.FRAME_UNSEEN
    )  # fmt: skip
    assert frame_bits & ps.FRAME_VALIDATION_MASK == 0
    bone_bits = ps.BONE_HELD | ps.BONE_REBUILT | ps.BONE_PARTIAL | ps.BONE_NEVER
    assert bone_bits & ps.BONE_VALIDATION_MASK == 0
    assert {1 << b for b in ps.FRAME_FLAG_BITS.values()} == {
        1, 2, 4, 8, 16, 32, 64, 128, 1 << 24, 1 << 25, 1 << 26, 1 << 27, 1 << 28
    }  # fmt: skip
    assert (
        ps.FRAME_CALIBRATION_MISMATCH & (ps.FRAME_VALIDATION_MASK | ps.PERFORMER_MASK)
        == 0
    )
    assert ps.FRAME_FLAG_BITS["calibration_mismatch"] == 24
    assert ps.FRAME_FLAG_BITS["reseeded"] == ps.FRAME_RESEEDED.bit_length() - 1
    assert ps.FRAME_FLAG_BITS["unexplained"] == ps.FRAME_UNEXPLAINED.bit_length() - 1
    assert ps.FRAME_FLAG_BITS["unseen"] == ps.FRAME_UNSEEN.bit_length() - 1


def test_names_round_trip() -> None:
    parts = ps.encode_pose_names(NAMES)
    assert parts[0] == b"RTDN\x01\x00\x00\x00"
    assert ps.decode_pose_names(parts) == NAMES
    doc = json.loads(parts[1])
    assert doc["humanoid"] == ["Hips", "Spine", ""]  # beside the rig's names
    # a sender without the key (an older one): unknown, not an error
    del doc["humanoid"]
    old = ps.decode_pose_names([parts[0], json.dumps(doc).encode()])
    assert old.bone_humanoid == () and old.bone_names == NAMES.bone_names
    with pytest.raises(DecodeError):  # one name per bone
        doc["humanoid"] = ["Hips"]
        ps.decode_pose_names([parts[0], json.dumps(doc).encode()])


@pytest.mark.parametrize(
    ("parts", "reason"),
    [
        ([b"RTDN\x01\x00\x00\x00"], "bad_parts"),
        ([b"RTDN\x01\x00\x00", b"{}"], "bad_length"),
        ([b"RTDP\x01\x00\x00\x00", b"{}"], "bad_magic"),
        ([b"RTDN\x02\x00\x00\x00", b"{}"], "bad_version"),
        ([b"RTDN\x01\x00\x00\x00", b"{"], "bad_json"),
        ([b"RTDN\x01\x00\x00\x00", b"[]"], "bad_json"),
        (
            [NAMES_HEAD, b'{"rig":"r","bones":["a"],"parents":[3],"weights":[]}'],
            "bad_json",
        ),
        (
            [NAMES_HEAD, b'{"rig":"r","bones":[1],"parents":[-1],"weights":[]}'],
            "bad_json",
        ),
    ],
)
def test_malformed_names(parts: list[bytes], reason: str) -> None:
    with pytest.raises(DecodeError) as info:
        ps.decode_pose_names(parts)
    assert info.value.reason == reason


@settings(max_examples=300)
@given(
    st.binary(max_size=80),
    st.binary(max_size=120),
    st.integers(0, 67),
    st.integers(0, 255),
)
def test_decoders_raise_only_decode_error(
    head: bytes, body: bytes, i: int, v: int
) -> None:
    enc = ps.PoseEncoder(3, 2)
    good = bytearray(enc.parts[0])
    good[i] = v
    for parts in (
        [head, body],
        [bytes(good), body],
        [bytes(good), bytes(enc.parts[1])],
    ):
        for decode in (ps.decode_pose, ps.decode_pose_names):
            with contextlib.suppress(DecodeError):
                decode(parts)


def test_names_id_travels_in_data_and_names_messages() -> None:
    from retargetd.protocols.pose_stream import (
        PoseEncoder,
        PoseNames,
        decode_pose,
        decode_pose_names,
        encode_pose_names,
    )

    names = PoseNames(rig="r", bone_names=("a", "b"), bone_parents=(-1, 0),
                      weight_names=(), names_id=7)  # fmt: skip
    assert decode_pose_names(encode_pose_names(names)).names_id == 7
    enc = PoseEncoder(2, 0, names_id=7)
    q = np.tile([1.0, 0.0, 0.0, 0.0], (2, 1))
    parts = enc.encode(1, 0.0, 1, 2, 0, np.zeros(3), q, q, q, np.zeros(0),
                       np.zeros(2, dtype=np.uint8))  # fmt: skip
    assert decode_pose([bytes(p) for p in parts]).names_id == 7


def test_face_part_round_trip_and_layout(rng: np.random.Generator) -> None:
    enc = ps.PoseEncoder(3, 2, n_face_markers=4)
    parts, _ = _encode(rng, enc)
    assert len(parts) == 3 and len(parts[2]) == ps.face_size(4) == 36 + 48
    markers = rng.normal(size=(4, 3))
    markers[2] = np.nan
    quat = np.array([0.5, 0.5, -0.5, 0.5])
    enc.encode_face(
        ps.FACE_PARTIAL | ps.FACE_HEAD_PARTIAL, quat, [0.1, 0.2, 1.6], markers
    )
    raw = bytes(parts[2])
    assert struct.unpack_from("<HHI", raw) == (4, 0, ps.FACE_PARTIAL | 1)
    assert struct.unpack_from("<4f", raw, 8) == tuple(np.float32(quat))
    msg = ps.decode_pose([bytes(p) for p in parts])
    assert msg.face_flags == ps.FACE_PARTIAL | ps.FACE_HEAD_PARTIAL
    np.testing.assert_array_equal(msg.world_from_head_quat, np.float32(quat))
    np.testing.assert_array_equal(msg.head_pos_world, np.float32([0.1, 0.2, 1.6]))
    np.testing.assert_array_equal(msg.face_markers, np.float32(markers))
    # Without a face the message keeps two parts and decodes with no face fields.
    plain = ps.decode_pose([bytes(p) for p in parts[:2]])
    assert plain.face_markers is None and plain.face_flags == 0
    with pytest.raises(DecodeError) as info:
        ps.decode_pose([bytes(p) for p in parts[:2]] + [raw[:-4]])
    assert info.value.reason == "bad_length"
    # The flag names match the face solver's bits.
    from retargetd.daemon.face import kernel as kf

    assert (kf.FLAG_HEAD_PARTIAL, kf.FLAG_HEAD_LOST, kf.FLAG_NOT_CONVERGED,
            kf.FLAG_FACE_PARTIAL, kf.FLAG_NEVER) == (
        ps.FACE_HEAD_PARTIAL, ps.FACE_HEAD_LOST, ps.FACE_NOT_CONVERGED,
        ps.FACE_PARTIAL, ps.FACE_NEVER,
    )  # fmt: skip


def test_names_carry_face_markers() -> None:
    names = ps.PoseNames(
        rig="r",
        bone_names=("a",),
        bone_parents=(-1,),
        weight_names=("jawOpen",),
        face_markers=("CHIN", "LLIP"),
    )
    assert ps.decode_pose_names(ps.encode_pose_names(names)) == names


def test_validation_message_round_trip() -> None:
    values = np.arange(len(ps.VALIDATION_CHECKS), dtype=np.float64) * 0.5
    flags = ps.FRAME_V_LIMITS | ps.FRAME_V_SPEED
    bones = np.array([0, ps.BONE_V_LIMIT, ps.BONE_V_SPEED | ps.BONE_V_FIT, 0, 0],
                     dtype=np.uint8)  # fmt: skip
    parts = ps.encode_validation(9, 1234, 5_000, 6_000, flags, values, bones)
    assert len(parts[0]) == ps.VALIDATION_HEADER.size == 40
    assert parts[0][:8] == b"RTDV\x01\x00\x09\x00"
    assert len(parts[1]) == 4 * 8 + 8
    msg = ps.decode_validation(parts)
    assert (msg.names_id, msg.frame_id, msg.received_ns, msg.validated_ns) == (
        9, 1234, 5_000, 6_000,
    )  # fmt: skip
    assert msg.flags == flags
    np.testing.assert_array_equal(msg.values, np.float32(values))
    np.testing.assert_array_equal(msg.bone_flags, bones)
    for bad, reason in (
        ([parts[0]], "bad_parts"),
        ([parts[0][:-1], parts[1]], "bad_length"),
        ([b"RTDX" + parts[0][4:], parts[1]], "bad_magic"),
        ([parts[0][:4] + b"\x02" + parts[0][5:], parts[1]], "bad_version"),
        ([parts[0], parts[1][:-4]], "bad_length"),
    ):
        with pytest.raises(DecodeError) as info:
            ps.decode_validation(bad)
        assert info.value.reason == reason


def test_validation_bits_fill_the_reserved_ranges() -> None:
    frame = [getattr(ps, f"FRAME_V_{c.upper()}") for c in ps.VALIDATION_CHECKS]
    assert sum(frame) == ps.FRAME_VALIDATION_MASK and len(set(frame)) == 8
    assert len(ps.VALIDATION_UNITS) == len(ps.VALIDATION_CHECKS)  # one unit each
    bone = [1 << b for b in ps.BONE_VALIDATION_BITS.values()]
    assert sum(bone) == ps.BONE_VALIDATION_MASK


@settings(max_examples=300)
@given(st.binary(max_size=100), st.integers(0, 10_000), st.integers(0, 255))
def test_face_and_validation_decoders_raise_only_decode_error(
    junk: bytes, i: int, v: int
) -> None:
    # Valid pose and validation headers, so the face-part and RTDV body decoders are
    # reached: random bytes as the face part or the RTDV body, and one byte of a
    # valid face part or RTDV body changed.
    enc = ps.PoseEncoder(2, 1, n_face_markers=4)
    parts, _ = _encode(np.random.default_rng(0), enc)
    enc.encode_face(0, np.array([1.0, 0.0, 0.0, 0.0]), np.zeros(3), np.zeros((4, 3)))
    head, body, face = (bytes(p) for p in parts)
    rtdv_head, rtdv_body = (
        bytes(p)
        for p in ps.encode_validation(0, 5, 1, 2, 0, np.zeros(8), np.zeros(2, np.uint8))
    )
    for decode, msg in (
        (ps.decode_pose, [head, body, junk]),
        (ps.decode_validation, [rtdv_head, junk]),
    ):
        try:
            decode(msg)
        except DecodeError as exc:
            assert exc.reason == "bad_length", exc.reason
    # One byte changed inside a well-formed part: only the face part's marker count
    # (bytes 0-1) can make it wrong; anything else decodes.
    bad = bytearray(face)
    bad[i % len(face)] = v
    try:
        msg = ps.decode_pose([head, body, bytes(bad)])
        assert msg.face_markers is not None and msg.face_markers.shape == (4, 3)
    except DecodeError as exc:
        assert exc.reason == "bad_length" and i % len(face) < 2
    bad = bytearray(rtdv_body)
    bad[i % len(bad)] = v
    assert ps.decode_validation([rtdv_head, bytes(bad)]).frame_id == 5


def test_validation_encoder_reuses_its_buffers(rng: np.random.Generator) -> None:
    enc = ps.ValidationEncoder(3)
    for frame in (7, 8):
        values = rng.normal(size=8)
        bones = np.array([0, ps.BONE_VALIDATION_MASK & 0x30, 0x80], dtype=np.uint8)
        parts = enc.encode(2, frame, 10, 20, ps.FRAME_V_SPEED, values, bones)
        assert parts is enc.parts
        assert [bytes(p) for p in parts] == ps.encode_validation(
            2, frame, 10, 20, ps.FRAME_V_SPEED, values, bones
        )
        msg = ps.decode_validation([bytes(p) for p in parts])
        assert (msg.frame_id, msg.flags) == (frame, ps.FRAME_V_SPEED)
        np.testing.assert_array_equal(msg.values, np.float32(values))
        np.testing.assert_array_equal(msg.bone_flags, bones)


def test_shape_state_message_round_trip_and_layout() -> None:
    # Issue 32: per-shape states in their own message; the data message unchanged.
    enc = ps.ShapeStateEncoder(5, names_id=9)
    states = np.array([0, ps.SHAPE_UNOBSERVED, ps.SHAPE_HIDDEN, 0, 1], dtype=np.uint8)
    part = enc.encode(42, states)
    assert part is enc.part and len(part) == 20 + 8  # 5 states, NUL-padded to 8
    assert bytes(part[:4]) == ps.SHAPE_MAGIC and bytes(part[25:]) == b"\x00" * 3
    msg = ps.decode_shape_state(bytes(part))
    assert (msg.names_id, msg.frame_id) == (9, 42)
    np.testing.assert_array_equal(msg.states, states)
    assert ps.FACE_FLAG_BITS["shape_held"] == ps.FACE_SHAPE_HELD.bit_length() - 1
    assert ps.SHAPE_STATE_BITS == {"unobserved": 0, "hidden": 1}
    for bad, reason in (
        (bytes(part)[:-4], "bad_length"),
        (b"RTDX" + bytes(part)[4:], "bad_magic"),
        (bytes(part)[:4] + b"\x02\x00" + bytes(part)[6:], "bad_version"),
        (b"RTDF", "bad_length"),
    ):
        with pytest.raises(DecodeError) as info:
            ps.decode_shape_state(bad)
        assert info.value.reason == reason


def test_names_list_the_unobserved_weights_only_with_a_face() -> None:
    face = dataclasses.replace(
        NAMES, face_markers=("F1",), unobserved=("eyeLookUpLeft",)
    )
    parts = ps.encode_pose_names(face)
    doc = json.loads(parts[1])
    assert doc["unobserved"] == ["eyeLookUpLeft"]
    assert doc["shape_state_bits"] == {"unobserved": 0, "hidden": 1}
    assert ps.decode_pose_names(parts) == face
    assert "unobserved" not in json.loads(ps.encode_pose_names(NAMES)[1])
    del doc["unobserved"]  # an older sender: nothing unobserved known
    old = ps.decode_pose_names([parts[0], json.dumps(doc).encode()])
    assert old.unobserved == () and old.face_markers == ("F1",)


@given(st.binary(max_size=100))
def test_shape_state_decoder_raises_only_decode_error(junk: bytes) -> None:
    for data in (junk, b"RTDF\x01\x00\x00\x00" + junk):
        with contextlib.suppress(DecodeError):
            ps.decode_shape_state(data)


def test_foot_contact_bits_ride_the_flags_word(rng: np.random.Generator) -> None:
    """Issue 34: bits 25-27 of the flags word at byte 48 (byte 51, bits 1-3) carry the
    foot contact; the performer id (byte 50) and the older bits are untouched, and a
    decoder that predates them reads the rest as before."""
    assert (ps.FRAME_CONTACT_LEFT, ps.FRAME_CONTACT_RIGHT, ps.FRAME_CONTACT_KNOWN) == (
        0x0200_0000,
        0x0400_0000,
        0x0800_0000,
    )
    enc = ps.PoseEncoder(3, 2, performer=5)
    _, args = _encode(rng, enc)
    contact = ps.FRAME_CONTACT_KNOWN | ps.FRAME_CONTACT_RIGHT
    enc.encode(**{**args, "flags": args["flags"] | contact})
    header = bytes(enc.parts[0])
    assert header[50] == 5 and header[51] == 0b1100  # performer id; bits 26, 27
    (word,) = struct.unpack_from("<I", header, 48)
    assert word & ps.FRAME_CONTACT_RIGHT and not word & ps.FRAME_CONTACT_LEFT
    msg = ps.decode_pose(enc.parts)
    assert msg.flags == args["flags"] | contact and msg.performer == 5
    # an old decoder: the pre-34 bits alone, as before
    assert msg.flags & 0xFF == args["flags"]
    names = json.loads(ps.encode_pose_names(NAMES)[1])
    bits = names["frame_flag_bits"]
    assert (bits["contact_left"], bits["contact_right"], bits["contact_known"]) == (
        25,
        26,
        27,
    )


def test_plant_unreached_bit_rides_the_flags_word(rng: np.random.Generator) -> None:
    """Issue 34 item 2: bit 28 ``plant_unreached`` (``0x1000_0000``, byte 51 bit 4),
    PROTOCOLS.md's vector: left foot in contact and out of reach, performer 0, the
    flags word ``0x1A00_0000`` (bytes 48-51 ``00 00 00 1A``); named in the names
    message's ``frame_flag_bits``."""
    assert ps.FRAME_PLANT_UNREACHED == 0x1000_0000
    enc = ps.PoseEncoder(3, 2, performer=0)
    _, args = _encode(rng, enc)
    word = ps.FRAME_CONTACT_LEFT | ps.FRAME_CONTACT_KNOWN | ps.FRAME_PLANT_UNREACHED
    enc.encode(**{**args, "flags": word})
    header = bytes(enc.parts[0])
    assert header[48:52] == bytes([0x00, 0x00, 0x00, 0x1A])
    assert ps.decode_pose(enc.parts).flags == 0x1A00_0000
    names = json.loads(ps.encode_pose_names(NAMES)[1])
    assert names["frame_flag_bits"]["plant_unreached"] == 28
