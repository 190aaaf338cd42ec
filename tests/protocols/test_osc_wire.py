"""OSC primitives: padding, message building against python-osc, bundle splitting."""

from __future__ import annotations

import contextlib

import pytest
from hypothesis import given
from hypothesis import strategies as st
from pythonosc.osc_bundle import OscBundle
from pythonosc.osc_message import OscMessage

from retargetd.protocols import osc_wire as ow
from retargetd.protocols.errors import DecodeError


def test_strings_are_nul_terminated_and_padded() -> None:
    assert ow.osc_string("") == b"\0\0\0\0"
    assert ow.osc_string("abc") == b"abc\0"
    assert ow.osc_string("abcd") == b"abcd\0\0\0\0"
    assert ow.osc_string_size("/rtd/frame") == 12
    assert ow.osc_blob(b"\x01\x02") == b"\0\0\0\x02\x01\x02\0\0"
    with pytest.raises(ValueError, match="NUL"):
        ow.osc_string("a\0b")


def test_bundle_header_is_immediately() -> None:
    assert ow.BUNDLE_HEADER == b"#bundle\0" + b"\0" * 7 + b"\x01"
    assert len(ow.BUNDLE_HEADER) == ow.BUNDLE_HEADER_SIZE


def test_build_message_matches_python_osc() -> None:
    msg = ow.build_message("/a/b", ",ihfdsbTF", [1, -(2**40), 0.5, 0.25, "x", b"yz"])
    parsed = OscMessage(msg)
    assert parsed.address == "/a/b"
    assert parsed.params == [1, -(2**40), 0.5, 0.25, "x", b"yz", True, False]
    assert ow.parse_message(msg) == (
        "/a/b",
        ",ihfdsbTF",
        [1, -(2**40), 0.5, 0.25, "x", b"yz", True, False],
    )


def test_build_message_checks_arguments() -> None:
    with pytest.raises(ValueError, match="take 1 arguments"):
        ow.build_message("/a", ",i", [])
    with pytest.raises(ValueError, match="does not fit"):
        ow.build_message("/a", ",i", [2**40])
    with pytest.raises(ValueError, match="unsupported"):
        ow.build_message("/a", ",r", [1])


def test_bundle_elements_round_trip() -> None:
    one = ow.build_message("/x", ",i", [1])
    two = ow.build_message("/y", ",s", ["hello"])
    bundle = ow.build_bundle([one, two])
    assert [bytes(e) for e in ow.iter_bundle_elements(bundle)] == [one, two]
    parsed = OscBundle(bundle)
    assert [m.address for m in parsed] == ["/x", "/y"]


@pytest.mark.parametrize(
    ("packet", "reason"),
    [
        (b"#bundle\0", "bad_length"),
        (b"/not/a/bundle\0\0\0,\0\0\0", "not_bundle"),
        (ow.BUNDLE_HEADER + b"\0\0\0", "bad_bundle"),
        (ow.BUNDLE_HEADER + b"\0\0\0\x08abcd", "bad_bundle"),
        (ow.BUNDLE_HEADER + b"\0\0\0\x03abcd", "bad_bundle"),
        (ow.BUNDLE_HEADER + b"\xff\xff\xff\xfc", "bad_bundle"),
    ],
)
def test_bad_bundles(packet: bytes, reason: str) -> None:
    with pytest.raises(DecodeError) as info:
        list(ow.iter_bundle_elements(packet))
    assert info.value.reason == reason


@given(st.binary(max_size=200))
def test_parsers_raise_only_decode_error(data: bytes) -> None:
    for parse in (ow.parse_message, lambda b: list(ow.iter_bundle_elements(b))):
        with contextlib.suppress(DecodeError):
            parse(data)
