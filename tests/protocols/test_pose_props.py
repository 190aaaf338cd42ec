"""The prop messages (``protocols/pose_props.py``, ``protocols/vmc_props.py``): the
PROTOCOLS.md hex examples are the encoders' bytes, the example's fields read back from
the bytes as the tables say, the decoder refuses what it must, and the wire flags are
the kernel's."""

from __future__ import annotations

import contextlib
import math
import re
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from retargetd.daemon.props import kernel as pk
from retargetd.protocols import pose_props as pp
from retargetd.protocols.errors import DecodeError
from retargetd.protocols.vmc_props import VmcPropEncoder

DOC = (Path(__file__).resolve().parents[2] / "protocols" / "PROTOCOLS.md").read_text()
C = S = math.sqrt(0.5)


def _hex(name: str) -> bytes:
    match = re.search(rf"<!-- hex: {name} -->\n```\n(.*?)```", DOC, re.DOTALL)
    assert match, name
    out = bytearray()
    for line in match.group(1).splitlines():
        out += bytes.fromhex(line[6:].split("|")[0])
    return bytes(out)


def _example() -> bytes:
    enc = pp.PropEncoder(0, "cam", pp.KIND_CAMERA)
    part = enc.encode(
        7, 0.5, 1000, pp.PROP_PARTIAL, 4, 5, np.array([C, 0.0, 0.0, S]),
        np.array([0.5, -0.25, 1.5]), 40.0, 0.0005,
    )  # fmt: skip
    pp.stamp_sent(part, 3000)
    return bytes(part)


def test_prop_message_hex_is_the_encoder_and_reads_as_the_table_says() -> None:
    data = _hex("prop_message")
    assert data == _example()
    # read with the table's offsets alone (not our decoder)
    assert data[0:4] == b"RTDR" and struct.unpack_from("<H", data, 4) == (1,)
    assert data[6] == 0 and data[7] == 1
    assert struct.unpack_from("<qdqq", data, 8) == (7, 0.5, 1000, 3000)
    assert struct.unpack_from("<I", data, 40) == (2,)  # bit 1: partial
    assert (data[44], data[45], data[46], data[47]) == (4, 5, 3, 0)
    q = struct.unpack_from("<4f", data, 48)
    np.testing.assert_allclose(q, [C, 0, 0, S], rtol=1e-7)
    np.testing.assert_allclose(struct.unpack_from("<3f", data, 64), [0.5, -0.25, 1.5])
    fov, rms = struct.unpack_from("<2f", data, 76)
    assert fov == 40.0 and rms == pytest.approx(0.0005)
    assert data[84:88] == b"cam\0" and len(data) == 88
    msg = pp.decode_prop(data)
    assert (msg.name, msg.frame_id, msg.flags, msg.used, msg.seen) == (
        "cam", 7, pp.PROP_PARTIAL, 4, 5,
    )  # fmt: skip


def test_vmc_prop_hex_is_the_encoder() -> None:
    enc = VmcPropEncoder("cam", camera=True)
    got = bytes(enc.encode(np.array([0.5, -0.25, 1.5]), np.array([C, 0, 0, S]), 40.0))
    assert _hex("vmc_prop_camera") == got
    tracker = VmcPropEncoder("sword", camera=False)
    only = bytes(tracker.encode(np.zeros(3), np.array([1.0, 0, 0, 0]), 0.0))
    assert b"/VMC/Ext/Cam" not in only and b"/VMC/Ext/Tra/Pos" in only


def test_wire_flags_are_the_kernel_flags() -> None:
    assert {1 << b for b in pp.PROP_FLAG_BITS.values()} == {
        pk.FLAG_HELD, pk.FLAG_PARTIAL, pk.FLAG_SWAP, pk.FLAG_NEVER,
    }  # fmt: skip
    assert (pp.PROP_HELD, pp.PROP_PARTIAL, pp.PROP_SWAP, pp.PROP_NEVER) == (
        pk.FLAG_HELD, pk.FLAG_PARTIAL, pk.FLAG_SWAP, pk.FLAG_NEVER,
    )  # fmt: skip


def test_decoder_refuses() -> None:
    good = bytearray(_example())
    cases = {
        "bad_length": bytes(good[:80]),
        "bad_magic": b"RTDX" + bytes(good[4:]),
        "bad_version": bytes(good[:4]) + b"\x02\x00" + bytes(good[6:]),
    }
    long = bytes(good) + b"\0\0\0\0"
    cases_len = [long]
    nonfinite = bytearray(good)
    struct.pack_into("<f", nonfinite, 64, math.nan)
    off_unit = bytearray(good)
    struct.pack_into("<f", off_unit, 48, 0.9)
    bad_name = bytearray(good)
    bad_name[84] = 0xFF
    for reason, data in cases.items():
        with pytest.raises(DecodeError) as info:
            pp.decode_prop(data)
        assert info.value.reason == reason
    for data in cases_len:
        with pytest.raises(DecodeError, match="bytes for 3"):
            pp.decode_prop(data)
    for reason, data in (
        ("non_finite", nonfinite),
        ("bad_quaternion", off_unit),
        ("bad_name", bad_name),
    ):
        with pytest.raises(DecodeError) as info:
            pp.decode_prop(bytes(data))
        assert info.value.reason == reason


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=200))
def test_arbitrary_bytes_raise_only_decode_error(data: bytes) -> None:
    with contextlib.suppress(DecodeError):
        pp.decode_prop(data)
