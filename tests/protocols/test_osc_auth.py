"""Signed OSC marker datagrams (issue 30 item 5, PROTOCOLS.md §13): the verifier
takes a datagram only with the key's tag and a (session, counter) past the last one
taken; anything else is refused before any OSC in it is read. The byte-exact test
vector and the documented sender: ``test_protocols_md.py``; the daemon:
``tests/daemon/test_marker_auth.py``."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from retargetd.protocols import osc_in
from retargetd.protocols.marker_input import LabelSet
from retargetd.protocols.osc_auth import (
    BAD_TAG,
    REPLAYED,
    TRAILER_BYTES,
    UNSIGNED,
    DatagramSigner,
    DatagramVerifier,
    sign_datagram,
)

KEY = bytes(range(32))
OTHER_KEY = bytes(range(1, 33))
FRAME = osc_in.encode_compact_frame(7, 0.5, 3, np.array([[1.0, 2.0, 3.0]]))
LABELS = osc_in.encode_labels(LabelSet(3, ("LASI",)))


def _check(v: DatagramVerifier, data: bytes) -> int:
    return v.check(memoryview(data), len(data))


def test_signed_datagrams_in_order_are_taken_and_stripped() -> None:
    signer, v = DatagramSigner(KEY, session=10), DatagramVerifier(KEY)
    for datagram in (LABELS, FRAME, FRAME):  # the same bytes, a new counter: fine
        signed = signer.sign(datagram)
        assert len(signed) == len(datagram) + TRAILER_BYTES
        assert _check(v, signed) == len(datagram)
        assert signed[: len(datagram)] == datagram  # the datagram, untouched
    assert (v.session, v.counter, v.new_session) == (10, 2, False)


def test_replays_are_refused_and_a_new_session_taken() -> None:
    v = DatagramVerifier(KEY)
    first = sign_datagram(KEY, FRAME, 10, 5)
    assert _check(v, first) >= 0
    assert _check(v, first) == REPLAYED  # the same datagram again
    assert _check(v, sign_datagram(KEY, FRAME, 10, 4)) == REPLAYED  # older counter
    assert _check(v, sign_datagram(KEY, FRAME, 9, 99)) == REPLAYED  # older session
    assert (v.session, v.counter) == (10, 5)  # refusals change nothing
    assert _check(v, sign_datagram(KEY, FRAME, 10, 6)) >= 0
    assert not v.new_session
    # A restarted sender: a larger session, counter from 0, taken at once.
    assert _check(v, sign_datagram(KEY, FRAME, 11, 0)) >= 0
    assert v.new_session and (v.session, v.counter) == (11, 0)
    assert _check(v, sign_datagram(KEY, FRAME, 10, 7)) == REPLAYED


def test_unsigned_altered_and_other_keys_are_refused() -> None:
    v = DatagramVerifier(KEY)
    assert _check(v, FRAME) == UNSIGNED  # a plain compact frame
    assert _check(v, b"") == UNSIGNED
    assert _check(v, b"RTDS" + bytes(31)) == UNSIGNED  # one byte short of a trailer
    assert _check(v, sign_datagram(OTHER_KEY, FRAME, 1, 0)) == BAD_TAG
    signed = sign_datagram(KEY, FRAME, 1, 0)
    for i in range(len(signed)):  # any byte flipped: datagram, trailer or tag
        altered = bytearray(signed)
        altered[i] ^= 0x01
        got = _check(v, bytes(altered))
        magic = len(signed) - TRAILER_BYTES
        assert got == (UNSIGNED if magic <= i < magic + 4 else BAD_TAG), i
    assert _check(v, signed) >= 0  # still the first taken
    assert _check(v, signed + b"\0") == UNSIGNED  # trailing bytes: no trailer


@pytest.mark.parametrize("n_key", [32, 33, 48, 63, 64])
def test_the_verifiers_hmac_is_the_hmac_modules(n_key: int) -> None:
    # The verifier builds HMAC from two keyed SHA-256 states; the signer calls
    # hmac.digest: every key length agrees.
    key = bytes(range(7, 7 + n_key))
    v = DatagramVerifier(key)
    for counter in range(3):
        assert _check(v, sign_datagram(key, FRAME, 1, counter)) == len(FRAME)


def test_keys_outside_32_to_64_bytes_are_refused() -> None:
    for n in (0, 16, 31, 65):
        with pytest.raises(ValueError, match="32-64 bytes"):
            DatagramVerifier(bytes(n))
    DatagramSigner(bytes(64))


@given(st.binary(max_size=200))
def test_arbitrary_bytes_are_refused_never_raise(data: bytes) -> None:
    v = DatagramVerifier(KEY)
    assert _check(v, data) in (UNSIGNED, BAD_TAG)
    # ... a forged trailer after them too
    assert _check(v, data + b"RTDS" + bytes(32)) == BAD_TAG
