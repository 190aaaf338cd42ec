"""ZeroMQ pose stream: golden header, round trips, sent stamp, names, fuzzing."""

from __future__ import annotations

import contextlib
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
    bone_names=("Hips", "Spine", "Head"),
    bone_parents=(-1, 0, 1),
    weight_names=("A", "Blink"),
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
    assert header[:8] == b"RTDP\x01\x00\x00\x00"
    assert struct.unpack_from("<q", header, 8) == (41,)
    assert struct.unpack_from("<3q", header, 24) == (1_000, 2_000, 0)
    assert struct.unpack_from("<IHH", header, 48) == (3, 3, 2)
    assert len(parts[1]) == ps.body_size(3, 2) == 32 * 3 + 4 * 2 + 4


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
    for key in ("world_from_bone_quat", "parent_from_bone_quat", "weights"):
        np.testing.assert_array_equal(getattr(msg, key), np.float32(args[key]))
    np.testing.assert_array_equal(msg.bone_flags, args["bone_flags"])


def test_flag_bits_do_not_overlap_validation() -> None:
    frame_bits = (
        ps.FRAME_LATE | ps.FRAME_HELD | ps.FRAME_RESTARTED | ps.FRAME_INPUT_DROPPED
    )
    assert frame_bits & ps.FRAME_VALIDATION_MASK == 0
    bone_bits = ps.BONE_HELD | ps.BONE_REBUILT | ps.BONE_PARTIAL | ps.BONE_NEVER
    assert bone_bits & ps.BONE_VALIDATION_MASK == 0
    assert {1 << b for b in ps.FRAME_FLAG_BITS.values()} == {1, 2, 4, 8}


def test_names_round_trip() -> None:
    parts = ps.encode_pose_names(NAMES)
    assert parts[0] == b"RTDN\x01\x00\x00\x00"
    assert ps.decode_pose_names(parts) == NAMES


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
    parts = enc.encode(1, 0.0, 1, 2, 0, np.zeros(3), q, q, np.zeros(0),
                       np.zeros(2, dtype=np.uint8))  # fmt: skip
    assert decode_pose([bytes(p) for p in parts]).names_id == 7
