"""What checking a signed OSC marker datagram adds per datagram (issue 30 item 5,
PROTOCOLS.md section 13), beside the compact frame's decode in the same run.

Run from the repository root::

    python bench/bench_auth.py [--calls N] [--rates 240,0] [--markers 41,200]

Per frame size (a compact frame of ``--markers`` markers, 48 + 12 n bytes, plus the
36-byte trailer), the cases of a group alternated call by call (bench_socket_calls'
``_time``), paced at each ``--rates`` (0: back to back), each call on a datagram
signed afresh before it (untimed), as the loop meets them:

- **decode** the unsigned frame: ``osc_in.decode_compact_into``, the loop's one
  compiled call from its receive buffer (the baseline);
- **verify**: ``DatagramVerifier.check`` (read the trailer, HMAC-SHA256 over the
  datagram with ``hmac.digest``, constant-time compare, the order check): what a
  key adds;
- **verify + decode**: what the loop does per signed datagram;
- **verify with hmac.digest**: the same check with the standard library's one-shot
  HMAC (the key set up on every call), which the verifier does not use: it keeps two
  keyed SHA-256 states and copies them (``osc_auth.DatagramVerifier``).

Median and p99 per call in µs and the ratio of each median to the decode's. Printed,
never asserted (STYLE.md section 10).
"""

from __future__ import annotations

import argparse
import hmac
import os
import struct

import numpy as np
from bench_socket_calls import _time

from retargetd.protocols import osc_in
from retargetd.protocols.marker_input import LabelSet, MarkerPacket
from retargetd.protocols.osc_auth import (
    TAG_BYTES,
    TRAILER_BYTES,
    DatagramSigner,
    DatagramVerifier,
)

_HEAD = struct.Struct(">4sQQ")  # PROTOCOLS.md 13: magic, session, counter


def _cases(n_markers: int, calls: int, rate_hz: float) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    key = bytes(range(32))
    labels = LabelSet(1, tuple(f"M{i}" for i in range(n_markers)))
    packet = MarkerPacket.create(labels)
    signer, verifier = DatagramSigner(key, session=1), DatagramVerifier(key)
    buf = bytearray(65536)
    view, wire = memoryview(buf), np.frombuffer(buf, dtype=np.uint8)
    frame_id = 0
    size = {"n": 0}

    def fresh() -> None:  # untimed: the next datagram, signed, in the buffer
        nonlocal frame_id
        frame_id += 1
        pos = rng.uniform(-1.0, 2.0, (n_markers, 3))
        signed = signer.sign(osc_in.encode_compact_frame(frame_id, 0.0, 1, pos))
        buf[: len(signed)] = signed
        size["n"] = len(signed)

    body = 48 + 12 * n_markers

    def decode() -> None:
        osc_in.decode_compact_into(wire, body, packet)

    def verify() -> None:
        assert verifier.check(view, size["n"]) == body

    def both() -> None:
        m = verifier.check(view, size["n"])
        osc_in.decode_compact_into(wire, m, packet)

    def one_shot() -> None:  # the check, with hmac.digest instead of the states
        n = size["n"]
        _, session, counter = _HEAD.unpack_from(view, n - TRAILER_BYTES)
        assert session >= 0 and counter >= 0
        tag = hmac.digest(key, view[: n - TAG_BYTES], "sha256")[:TAG_BYTES]
        assert hmac.compare_digest(tag, view[n - TAG_BYTES : n])

    # Each case meets a datagram signed afresh (the verifier refuses a repeat).
    return _time(
        {
            "decode, unsigned (baseline)": decode,
            "verify the trailer (what a key adds)": verify,
            "verify + decode (the signed loop)": both,
            "verify with hmac.digest (not used)": one_shot,
        },
        fresh,
        lambda: None,
        calls,
        rate_hz,
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--calls", type=int, default=2000, help="timed calls per case")
    ap.add_argument("--rates", default="240,0", help="Hz, 0: back to back")
    ap.add_argument("--markers", default="41,200", help="markers per frame")
    args = ap.parse_args(argv)
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    print(f"bench_auth  [load average {load} ({os.cpu_count()} cpus)]")
    for n in (int(m) for m in args.markers.split(",")):
        for rate in (float(r) for r in args.rates.split(",")):
            got = _cases(n, args.calls, rate)
            paced = f"paced at {rate:g} Hz" if rate else "back to back"
            print(
                f"\n== {n} markers ({48 + 12 * n} B + 36 B trailer), {paced}, "
                f"{args.calls} calls per case"
            )
            print(f"{'case':40s} {'median µs':>10s} {'p99 µs':>8s} {'ratio':>6s}")
            base = None
            for name, ns in got.items():
                med, p99 = np.median(ns) / 1e3, np.percentile(ns, 99) / 1e3
                base = med if base is None else base
                print(f"{name:40s} {med:10.2f} {p99:8.2f} {med / base:6.2f}")
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    print(f"\nload average at the end: {load}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
