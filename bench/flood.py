"""Refusal is cheap (issue 30 item 1): the VMC output rate while a sender without the
show-control token floods the show-control port.

A ``retargetd run`` process on loopback (the plug-in-gait rig calibrated on the
btkdata static, ``show_control.token`` set), the PiG walk streamed to its OSC input
at ``--rate-hz`` (100 by default, the issue's), its VMC datagrams counted on a
socket of ours. Phases of ``--seconds`` each: quiet; the amplification flood (bundles
of ``--messages`` tiny token-less messages, 60 KB each, at ``--bundles-hz``, from
another process); quiet; single token-less datagrams at ``--singles-hz``; quiet.
Printed: the VMC rate of each phase, its ratio to the first quiet phase, what the
flooder sent and what the daemon counted refused (per reason). Issue 30 asks each
flood phase within 2 % of the quiet rate; before the per-datagram refusal the
amplification flood cut 100/s to 0.

Run from the repository root (``../shared`` beside it)::

    python bench/flood.py                  # 5 s phases
    python bench/flood.py --seconds 10 --rate-hz 240
"""

from __future__ import annotations

import argparse
import contextlib
import multiprocessing as mp
import os
import socket
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import fuzz  # bench/ on the path
import soak

LOCALHOST = "127.0.0.1"
TOKEN = "bench-flood-token-0123456789"


def tiny_message() -> bytes:
    """The smallest OSC message: address "/x", no arguments (8 bytes)."""
    return b"/x\0\0,\0\0\0"


def amplification_bundle(n: int) -> bytes:
    """An OSC bundle of ``n`` tiny token-less messages (5,000: 60 KB)."""
    m = tiny_message()
    head = b"#bundle\0" + (1).to_bytes(8, "big")
    return head + (len(m).to_bytes(4, "big") + m) * n


def _flooder(addr: tuple[str, int], data: bytes, rate_hz: float, seconds: float,
             sent: Any) -> None:  # fmt: skip
    """Send ``data`` to ``addr`` at ``rate_hz`` for ``seconds`` (its own process)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 << 20)
    period = 1.0 / rate_hz
    t0 = time.perf_counter()
    n = 0
    while (now := time.perf_counter()) - t0 < seconds:
        due = int((now - t0) / period) + 1
        while n < due:
            with contextlib.suppress(OSError):  # ENOBUFS in a burst: the next goes
                sock.sendto(data, addr)
            n += 1
        time.sleep(max(0.0, t0 + n * period - time.perf_counter()))
    sent.value = n
    sock.close()


class VmcCounter(threading.Thread):
    """Counts the daemon's VMC datagrams (each frame's ``/VMC/Ext/OK``)."""

    def __init__(self) -> None:
        super().__init__(name="vmc-counter", daemon=True)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((LOCALHOST, 0))
        self.sock.settimeout(0.2)
        self.port = self.sock.getsockname()[1]
        self.frames = 0
        self.stop_event = threading.Event()

    def run(self) -> None:
        while not self.stop_event.is_set():
            try:
                data = self.sock.recv(65536)
            except TimeoutError:
                continue
            self.frames += data.count(b"/VMC/Ext/OK")

    def stop(self) -> None:
        self.stop_event.set()
        self.join(5.0)
        self.sock.close()


class WalkStreamer(threading.Thread):
    """The PiG walk over OSC (compact frames) at ``rate_hz``, looping."""

    def __init__(self, addr: tuple[str, int], rate_hz: float) -> None:
        super().__init__(name="walk", daemon=True)
        from retargetd.protocols import osc_in
        from retargetd.protocols.marker_input import LabelSet

        walk = fuzz.load_walk()
        self.addr, self.rate_hz = addr, rate_hz
        self.labels = osc_in.encode_labels(LabelSet(1, walk.labels))
        self.frames = [
            osc_in.encode_compact_frame(i, i / rate_hz, 1, row)
            for i, row in enumerate(walk.positions)
        ]
        self.encode = osc_in.encode_compact_frame
        self.rows = walk.positions
        self.stop_event = threading.Event()

    def run(self) -> None:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        t0 = time.perf_counter()
        i = 0
        while not self.stop_event.is_set():
            if i % int(self.rate_hz) == 0:
                sock.sendto(self.labels, self.addr)
            row = self.rows[i % len(self.rows)]
            sock.sendto(self.encode(i, i / self.rate_hz, 1, row), self.addr)
            i += 1
            time.sleep(max(0.0, t0 + i / self.rate_hz - time.perf_counter()))
        sock.close()

    def stop(self) -> None:
        self.stop_event.set()
        self.join(5.0)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=5.0, help="per phase")
    ap.add_argument("--rate-hz", type=float, default=100.0)
    ap.add_argument("--messages", type=int, default=5000)
    ap.add_argument("--bundles-hz", type=float, default=200.0)
    ap.add_argument("--singles-hz", type=float, default=10000.0)
    args = ap.parse_args(argv)
    bundle = amplification_bundle(args.messages)
    with tempfile.TemporaryDirectory(prefix="flood-") as tmp:
        folder = Path(tmp)
        counter = VmcCounter()
        config = soak._config(fuzz.calibrate_pig(folder), counter.port, None).replace(
            "[show_control]\nport = 0", f'[show_control]\nport = 0\ntoken = "{TOKEN}"'
        )
        (folder / "flood.toml").write_text(config)
        daemon = soak.DaemonProcess(folder / "flood.toml", folder)
        try:
            counter.start()
            walk = WalkStreamer(daemon.udp("osc markers"), args.rate_hz)
            walk.start()
            time.sleep(2.0)  # the first frames: calibration match, warm-up
            show = daemon.udp("show control")
            phases = [
                ("quiet", None, 0.0),
                (f"{args.messages}-message bundles at {args.bundles_hz:g}/s "
                 f"({len(bundle)} B)", bundle, args.bundles_hz),
                ("quiet", None, 0.0),
                (f"single messages at {args.singles_hz:g}/s", tiny_message(),
                 args.singles_hz),
                ("quiet", None, 0.0),
            ]  # fmt: skip
            print(
                f"flood bench: walk at {args.rate_hz:g} Hz over OSC; load "
                f"{os.getloadavg()[0]:.2f} (1 min); {os.cpu_count()} cores"
            )
            quiet_rate = None
            for name, data, hz in phases:
                before = daemon.status()["show_control"]["refused"]
                sent = mp.Value("q", 0)
                proc = None
                if data is not None:
                    proc = mp.Process(
                        target=_flooder, args=(show, data, hz, args.seconds, sent)
                    )
                    proc.start()
                f0, t0 = counter.frames, time.perf_counter()
                time.sleep(args.seconds)
                rate = (counter.frames - f0) / (time.perf_counter() - t0)
                if proc is not None:
                    proc.join(10.0)
                time.sleep(0.5)  # the daemon drains what the flood left queued
                after = daemon.status()["show_control"]["refused"]
                refused = {k: v - before.get(k, 0) for k, v in after.items()
                           if v - before.get(k, 0)}  # fmt: skip
                quiet_rate = quiet_rate or rate
                print(
                    f"  {name}: VMC {rate:.1f}/s ({rate / quiet_rate:.3f} of quiet)"
                    + (f"; sent {sent.value}, refused {refused}" if data else "")
                )
            walk.stop()
            print(f"load after: {os.getloadavg()[0]:.2f} (1 min)")
        finally:
            counter.stop()
            daemon.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
