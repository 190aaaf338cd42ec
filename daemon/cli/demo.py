"""``retargetd demo [--seconds N] [--rate HZ]``: the whole product on one machine.

The synthetic performer (wearing the ``menache`` markers) is sent over real loopback
OSC (the compact form, labels announced every second) into a live daemon, which
calibrates on the performer's opening T-pose hold, then streams VMC to 127.0.0.1:39539
(point Unity EVMC4U, VMC4UE or VMC4B at it) and the ZeroMQ pose stream, printing a
status line every second. ``--seconds`` stops it; so does Ctrl-C.
"""

from __future__ import annotations

import argparse
import dataclasses
import socket
import threading
import time
from typing import Any

from retargetd.daemon.cli.launch import add_console_argument
from retargetd.daemon.errors import UsageError


def add_parser(subparsers: Any) -> None:
    """Register ``demo``."""
    parser = subparsers.add_parser(
        "demo",
        help="synthetic performer -> loopback OSC -> daemon -> VMC + ZeroMQ",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--seconds", type=float, default=30.0, help="run time (s)")
    parser.add_argument("--rate", type=float, default=120.0, help="marker rate (Hz)")
    parser.add_argument("--config", metavar="FILE.toml", help="daemon config (TOML)")
    parser.add_argument(
        "--noise-mm", type=float, default=0.5,
        help="marker noise of the synthetic performer, mm (default %(default)s)",
    )  # fmt: skip
    add_console_argument(parser, "127.0.0.1:8080")
    parser.set_defaults(run=run)


class _Sender(threading.Thread):
    """Paces compact OSC frames of a synthetic take to the daemon (real UDP)."""

    def __init__(
        self, take: Any, address: tuple[str, int], stop: threading.Event
    ) -> None:
        super().__init__(name="demo-sender", daemon=True)
        self.take = take
        self.address = address
        self.stop = stop
        self.sent = 0

    def run(self) -> None:
        import numpy as np

        from retargetd.protocols import osc_in
        from retargetd.protocols.marker_input import LabelSet

        take = self.take
        labels = LabelSet(1, tuple(take.labels))
        label_msg = osc_in.encode_labels(labels)
        period = 1.0 / take.rate_hz
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            start = time.perf_counter()
            next_labels = 0.0
            frame = 0
            n = take.markers_world.shape[0]
            markers = np.asarray(take.markers_world, dtype=np.float32)
            while not self.stop.is_set():
                now = time.perf_counter() - start
                if now >= next_labels:
                    sock.sendto(label_msg, self.address)
                    next_labels = now + 1.0
                row = frame % n
                packet = osc_in.encode_compact_frame(
                    frame, now, labels.id, markers[row]
                )
                sock.sendto(packet, self.address)
                self.sent += 1
                frame += 1
                delay = start + frame * period - time.perf_counter()
                if delay > 0:
                    time.sleep(delay)
        finally:
            sock.close()


def run(args: argparse.Namespace) -> int:
    """Run the demo."""

    from retargetd.daemon.cli.launch import (
        install_signal_handlers,
        load_config,
        make_daemon,
        open_or_fail,
    )
    from retargetd.daemon.synth.performer import synthesize

    if not 60.0 <= args.rate <= 1000.0:
        raise UsageError(f"--rate must be in [60, 1000] Hz; got {args.rate:g}")
    if not args.seconds > 0:
        raise UsageError(f"--seconds must be > 0; got {args.seconds:g}")
    args.rig = "menache"
    args.calibration = None
    args.process_every_frame = False
    config = load_config(args)
    config = dataclasses.replace(
        config,
        loop=dataclasses.replace(config.loop, stats_interval_s=1.0),
        input=dataclasses.replace(
            config.input,
            osc=dataclasses.replace(
                config.input.osc, form="compact", units="m", up="+Z"
            ),
        ),
        performer=dataclasses.replace(config.performer, calibration=""),
    )
    length = min(args.seconds + 1.0, 60.0)
    take = synthesize(
        seconds=length, rate_hz=args.rate, markerset="menache",
        noise_mm=args.noise_mm, seed=1,
    )  # fmt: skip
    daemon = make_daemon(config)
    daemon.hint_uncalibrated = False  # the demo calibrates on the opening hold itself
    stop = threading.Event()
    install_signal_handlers(stop)
    open_or_fail(daemon, " (another daemon?)")
    hold = take.base_pose_frames
    daemon.out(
        daemon.request_calibration(max(1, (hold.stop - hold.start) // 2), "demo")
    )
    sender = _Sender(take, (config.input.osc.host, _osc_port(daemon)), stop)
    sender.start()
    deadline = time.monotonic() + args.seconds
    try:
        daemon.run(lambda: stop.is_set() or time.monotonic() >= deadline)
    finally:
        stop.set()
        sender.join(timeout=2.0)
        daemon.close()
    s = daemon.stats
    print(
        f"demo: sent {sender.sent} frames at {args.rate:g} Hz; daemon accepted "
        f"{s.frames_in}, solved {s.frames_solved}, streamed {s.frames_out}",
        flush=True,
    )
    return 0 if s.frames_out > 0 else 1


def _osc_port(daemon: Any) -> int:
    where = daemon.endpoints["osc markers"]  # "udp://host:port (compact)"
    return int(where.split()[0].rsplit(":", 1)[1])
