"""What the loop's socket calls (and its emit call) cost, paced as a live source
paces them.

Run from the repository root::

    python bench/bench_socket_calls.py [--calls N] [--rates 240,1000,0]

The live loop sleeps in its poll between frames, and on this shared VM a call made
4 ms after the last one finds the code, the data and the kernel's paths cold: it costs
several times the same call back to back. This times, in process over loopback, each
way the loop can make the same per-frame calls, paced at each ``--rates`` (0: back to
back), the cases of a group alternated call by call so that they see the same machine:

- **receive** one datagram and learn that no other waits: ``recvfrom_into`` until it
  raises (the baseline: what the loop did), ``recv_into`` until it raises, and
  ``recv_into`` then a zero-timeout ``select.poll`` (what it does now, with no allow
  list);
- **VMC** a humanoid frame of the 22 bones (``VmcEncoder``): in datagrams of at most
  1472 bytes with ``sendto`` (the baseline), the same with ``send`` on a connected
  socket, and one datagram of at most 8192 bytes on the connected socket (what the
  loop does to a loopback receiver);
- **emit call** the loop's one compiled call per frame (``live/emit.py``, 27
  arguments): through numba's dispatcher (the baseline) and as its compiled function
  (``compiled.direct``, what ``EmitPlan.call`` holds).

Median and p99 per call in µs and the ratio of each median to its group's baseline.
Printed, never asserted (STYLE.md section 10).
"""

from __future__ import annotations

import argparse
import os
import select
import socket
import time
from collections.abc import Callable

import numpy as np

from retargetd.protocols import vmc_out

LOCALHOST = "127.0.0.1"


def _udp_pair() -> tuple[socket.socket, socket.socket]:
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
    rx.bind((LOCALHOST, 0))
    rx.setblocking(False)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx.setblocking(False)
    return rx, tx


def _drain(sock: socket.socket, buf: bytearray) -> int:
    n = 0
    while True:
        try:
            sock.recv_into(buf)
        except BlockingIOError:
            return n
        n += 1


def _time(
    cases: dict[str, Callable[[], None]],
    before: Callable[[], None],
    after: Callable[[], None],
    calls: int,
    rate_hz: float,
) -> dict[str, np.ndarray]:
    """Each case ``calls`` times, alternated, ``1/rate_hz`` after the last call of
    the group (0: back to back); ``before`` runs untimed before each call (a
    datagram to receive), ``after`` after it (drain what was sent)."""
    clock = time.perf_counter_ns
    out = {name: np.zeros(calls, np.int64) for name in cases}
    period = 1.0 / rate_hz if rate_hz else 0.0
    warm = max(calls // 10, 20)
    for k in range(-warm, calls):
        for name, call in cases.items():
            before()
            if period:
                time.sleep(period)
            t0 = clock()
            call()
            t1 = clock()
            after()
            if k >= 0:
                out[name][k] = t1 - t0
    return out


def _receive(calls: int, rate_hz: float) -> dict[str, np.ndarray]:
    rx, tx = _udp_pair()
    tx.connect(rx.getsockname())
    buf = bytearray(65536)
    more = select.poll()
    more.register(rx.fileno(), select.POLLIN)
    payload = bytes(48 + 12 * 41)  # a compact OSC frame of the walk's 41 markers

    def until_raise(recv: Callable[..., object]) -> Callable[[], None]:
        def call() -> None:
            while True:
                try:
                    recv(buf, 65536)
                except BlockingIOError:
                    return

        return call

    def recv_then_poll() -> None:
        k = 0
        while k == 0 or more.poll(0):
            k += 1
            try:
                rx.recv_into(buf, 65536)
            except BlockingIOError:
                return

    try:
        return _time(
            {
                "recvfrom_into until it raises (baseline)": until_raise(
                    rx.recvfrom_into
                ),
                "recv_into until it raises": until_raise(rx.recv_into),
                "recv_into, then poll(0) (the loop)": recv_then_poll,
            },
            lambda: tx.send(payload),
            lambda: None,
            calls,
            rate_hz,
        )
    finally:
        rx.close()
        tx.close()


def _vmc(calls: int, rate_hz: float) -> dict[str, np.ndarray]:
    rx, tx = _udp_pair()
    dest = rx.getsockname()
    conn = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    conn.setblocking(False)
    conn.connect(dest)
    lan = vmc_out.VmcEncoder(vmc_out.HUMANOID_BONES).datagrams
    one = vmc_out.VmcEncoder(
        vmc_out.HUMANOID_BONES, max_datagram=vmc_out.LOOPBACK_MAX_DATAGRAM
    ).datagrams
    buf = bytearray(65536)

    def sendto_split() -> None:
        for d in lan:
            tx.sendto(d, dest)

    def send_split() -> None:
        for d in lan:
            conn.send(d)

    def send_one() -> None:
        for d in one:
            conn.send(d)

    try:
        return _time(
            {
                f"sendto, {len(lan)} datagrams <= 1472 B (baseline)": sendto_split,
                f"send connected, {len(lan)} datagrams <= 1472 B": send_split,
                f"send connected, {len(one)} datagram <= 8192 B (the loop)": send_one,
            },
            lambda: None,
            lambda: _drain(rx, buf) and None,
            calls,
            rate_hz,
        )
    finally:
        for s in (rx, tx, conn):
            s.close()


def _emit(calls: int, rate_hz: float) -> dict[str, np.ndarray]:
    """The live loop's emit call (27 arguments; the foot contact's two off) on the
    real PiG-sized arrays of a warm-up plan: through numba's dispatcher and as
    ``EmitPlan.call`` makes it."""
    from retargetd.daemon.compiled import direct
    from retargetd.daemon.live import emit

    n, b = 22, 20
    ei, at = emit._arenas(n)
    ei[emit.N_HEAD + 3 :: 4] = -1  # every bone a root: nothing to walk
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (b, 1))
    stage = np.zeros(7 * (n + 1) + 1, dtype=np.float32)
    args = (
        emit.DO_RETARGET | emit.DO_VMC | emit.DO_POSE, quat, quat.copy(), quat.copy(),
        np.zeros(3), np.zeros(b, np.uint8), ei, np.zeros(at), np.zeros(n, np.uint8),
        np.zeros((n + 1, 4)), stage, np.arange(len(stage), dtype=np.int64) * 4,
        np.zeros(4 * len(stage), np.uint8), np.zeros(68, np.uint8),
        np.zeros(52 + 60 * b, np.uint8), np.zeros(0), np.zeros(0), *emit._NO_STANCE,
        np.zeros(0, np.uint8), 0.0, 0, 0.0, 0, 0, 0, 0.0,
    )  # fmt: skip
    emit.emit_frame(*args)
    fn = direct(emit.emit_frame, *args)
    assert fn is not emit.emit_frame
    return _time(
        {
            "emit_frame through the dispatcher (baseline)": lambda: emit.emit_frame(
                *args
            ),
            "its compiled function, EmitPlan.call (the loop)": lambda: fn(*args),
        },
        lambda: None,
        lambda: None,
        calls,
        rate_hz,
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--calls", type=int, default=1000, help="timed calls per case")
    ap.add_argument("--rates", default="240,1000,0", help="Hz, 0: back to back")
    args = ap.parse_args(argv)
    rates = [float(r) for r in args.rates.split(",")]
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    print(f"bench_socket_calls  [load average {load} ({os.cpu_count()} cpus)]")
    groups = (("receive", _receive), ("VMC", _vmc), ("emit call", _emit))
    for group, run in groups:
        for rate in rates:
            got = run(args.calls, rate)
            paced = f"paced at {rate:g} Hz" if rate else "back to back"
            print(f"\n== {group}, {paced}, {args.calls} calls per case")
            print(f"{'case':58s} {'median µs':>10s} {'p99 µs':>8s} {'ratio':>6s}")
            base = None
            for name, ns in got.items():
                med, p99 = np.median(ns) / 1e3, np.percentile(ns, 99) / 1e3
                base = med if base is None else base
                print(f"{name:58s} {med:10.1f} {p99:8.1f} {med / base:6.2f}")
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    print(f"\nload average at the end: {load}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
