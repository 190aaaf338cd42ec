"""Signed OSC marker datagrams (PROTOCOLS.md §13): a 36-byte trailer after the
datagram's own bytes carries a session, a counter and a truncated HMAC-SHA256 of
everything before the tag, so a daemon with ``[input.osc] key_file`` accepts only
datagrams from a holder of the key, and never the same one twice.

Trailer (big-endian, as OSC), appended to any OSC datagram (a compact frame, a label
announcement, a simple bundle):

| offset in the trailer | size | type | field |
|---|---|---|---|
| 0 | 4 | bytes | magic ``RTDS`` |
| 4 | 8 | uint64 BE | session: above the sender's earlier ones (its start, Unix µs) |
| 12 | 8 | uint64 BE | counter: 0, 1, 2 ... per datagram within the session |
| 20 | 16 | bytes | tag = HMAC-SHA256(key, datagram ‖ magic ‖ session ‖ counter)[:16] |

Replay rule: a datagram is accepted only when its (session, counter) is larger, in
that order, than the last accepted one's: the same datagram sent again, or any older
one, is refused (``auth_replayed``); a restarted sender starts a larger session and is
accepted at once (its frame numbers may start over: the input treats its first frame
as a restarted source). The frame number inside a compact frame is signed with the
rest, but the order is the trailer's: label announcements and simple bundles carry
no frame number, and a restarted bridge's frame numbers start over.
"""

from __future__ import annotations

import hashlib
import hmac
import struct
import time

#: The trailer's first four bytes.
MAGIC = b"RTDS"
#: HMAC-SHA256 truncated to its first 16 bytes (128 bits; RFC 2104 section 5 allows
#: truncation to half the hash output and no fewer than 80 bits).
TAG_BYTES = 16
_HEAD = struct.Struct(">4sQQ")  # magic, session, counter
#: Bytes a signature adds to a datagram.
TRAILER_BYTES = _HEAD.size + TAG_BYTES
#: Key length, bytes: at least SHA-256's output (RFC 2104 section 3: less weakens the
#: MAC), at most its block (a longer key is hashed first, gaining nothing).
KEY_MIN_BYTES = 32
KEY_MAX_BYTES = 64
_BLOCK_BYTES = 64  # SHA-256's block

#: :meth:`DatagramVerifier.check` refusals.
UNSIGNED = -1  # too short for a trailer, or no ``RTDS`` where it belongs
BAD_TAG = -2  # a trailer whose tag is not the key's for these bytes
REPLAYED = -3  # a valid tag, but (session, counter) not past the last accepted


def check_key(key: bytes) -> None:
    """Raise ValueError unless ``key`` has ``KEY_MIN_BYTES``-``KEY_MAX_BYTES`` bytes."""
    if not KEY_MIN_BYTES <= len(key) <= KEY_MAX_BYTES:
        raise ValueError(
            f"an HMAC key has {KEY_MIN_BYTES}-{KEY_MAX_BYTES} bytes; got {len(key)}"
        )


def sign_datagram(key: bytes, datagram: bytes, session: int, counter: int) -> bytes:
    """``datagram`` with its trailer: the bytes a signing sender sends.

    Args:
        key: the shared key (the bytes, not their hex).
        datagram: any OSC datagram (compact frame, labels, simple bundle).
        session: uint64, larger than the sender's earlier sessions.
        counter: uint64, larger than the last one sent in this session.
    """
    signed = bytes(datagram) + _HEAD.pack(MAGIC, session, counter)
    return signed + hmac.digest(key, signed, "sha256")[:TAG_BYTES]


class DatagramSigner:
    """Signs a sender's datagrams: one session, the counter counting up from 0.

    Args:
        key: the shared key.
        session: the session number (default: now in Unix microseconds, so a
            restarted sender's session is larger unless the clock went back).
    """

    __slots__ = ("_key", "counter", "session")

    def __init__(self, key: bytes, session: int | None = None) -> None:
        check_key(key)
        self._key = key
        self.session = time.time_ns() // 1000 if session is None else session
        self.counter = 0

    def sign(self, datagram: bytes | memoryview) -> bytes:
        """``datagram`` signed with the next counter."""
        out = sign_datagram(self._key, bytes(datagram), self.session, self.counter)
        self.counter += 1
        return out


class DatagramVerifier:
    """Checks signed datagrams of one input in arrival order (the replay rule above).

    Args:
        key: the shared key.

    Attributes:
        session: the last accepted datagram's session (-1: none yet).
        counter: ... and its counter.
        new_session: the last accepted datagram started a session after an earlier
            one (the sender restarted).
    """

    __slots__ = ("_inner", "_outer", "counter", "new_session", "session")

    def __init__(self, key: bytes) -> None:
        check_key(key)
        # HMAC as RFC 2104 writes it, H((K ^ opad) || H((K ^ ipad) || m)), with the
        # two keyed SHA-256 states made once and copied per datagram: hmac.digest
        # sets the key up on every call, measured slower (bench/bench_auth.py times
        # both; the whole check of a 41-marker frame, median: 21.0 against 28.7 us
        # paced at 240 Hz, 1.7 against 2.4 us back to back, load 1.4-2.3 on 2
        # cores). A key of at most the 64-byte block is zero-padded to it (RFC 2104
        # section 2).
        padded = key.ljust(_BLOCK_BYTES, b"\0")
        self._inner = hashlib.sha256(bytes(b ^ 0x36 for b in padded))
        self._outer = hashlib.sha256(bytes(b ^ 0x5C for b in padded))
        self.session = -1
        self.counter = -1
        self.new_session = False

    def check(self, view: memoryview, n: int) -> int:
        """Check the datagram in ``view[:n]``; on success, remember its order.

        Returns:
            The length of the datagram without its trailer (>= 0; the bytes to
            decode), or ``UNSIGNED``, ``BAD_TAG`` or ``REPLAYED``. Nothing but the
            trailer is read before the tag is checked: the OSC inside is not parsed.
        """
        body = n - TAG_BYTES
        start = body - _HEAD.size
        if start < 0:
            return UNSIGNED
        magic, session, counter = _HEAD.unpack_from(view, start)
        if magic != MAGIC:
            return UNSIGNED
        inner = self._inner.copy()
        inner.update(view[:body])
        outer = self._outer.copy()
        outer.update(inner.digest())
        if not hmac.compare_digest(outer.digest()[:TAG_BYTES], view[body:n]):
            return BAD_TAG
        last = self.session
        if session < last or (session == last and counter <= self.counter):
            return REPLAYED
        self.new_session = 0 <= last < session
        self.session, self.counter = session, counter
        return start
