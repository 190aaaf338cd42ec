"""``retargetd run [--config FILE]``: the live daemon, in the foreground.

The config is validated before any socket opens (a bad key: one line, exit 2). SIGINT
or SIGTERM ends it cleanly (sockets closed, exit 0, within the poll timeout); a second
SIGINT forces the exit. Endpoints and their defaults: README "Live daemon".
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
from typing import Any

from retargetd.daemon.cli import UsageError

logger = logging.getLogger(__name__)


def add_parser(subparsers: Any) -> None:
    """Register ``run``."""
    parser = subparsers.add_parser(
        "run",
        help="run the live daemon (markers in over OSC/ZeroMQ, VMC and poses out)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--config", metavar="FILE.toml", help="daemon config (TOML)")
    parser.add_argument("--rig", help="override performer.rig")
    parser.add_argument("--calibration", help="override performer.calibration")
    parser.add_argument(
        "--process-every-frame",
        action="store_true",
        help="solve every accepted frame in order (offline replay), drop none",
    )
    parser.set_defaults(run=run)


def load_config(args: argparse.Namespace) -> Any:
    """The validated config with CLI overrides applied (ConfigError -> UsageError)."""
    import dataclasses

    from retargetd.daemon.config import ConfigError, DaemonConfig

    try:
        config = DaemonConfig.from_toml(args.config) if args.config else DaemonConfig()
    except ConfigError as exc:
        raise UsageError(str(exc)) from None
    performer = config.performer
    if getattr(args, "rig", None):
        performer = dataclasses.replace(performer, rig=args.rig)
    if getattr(args, "calibration", None):
        performer = dataclasses.replace(performer, calibration=args.calibration)
    loop = config.loop
    if getattr(args, "process_every_frame", False):
        loop = dataclasses.replace(loop, process_every_frame=True)
    return dataclasses.replace(config, performer=performer, loop=loop)


def make_daemon(config: Any) -> Any:
    """Build a Daemon, turning rig/calibration problems into UsageError."""
    from retargetd.daemon.calibration import CalibrationError
    from retargetd.daemon.loop import Daemon
    from retargetd.daemon.rig import RigError

    try:
        return Daemon(config)
    except (RigError, CalibrationError) as exc:
        raise UsageError(str(exc)) from None


def open_or_fail(daemon: Any, hint: str = "") -> None:
    """Open every endpoint; a port in use (or any bind error) closes what was opened
    and becomes one UsageError line (exit 2)."""
    import zmq

    try:
        daemon.open()
    except (OSError, zmq.ZMQError) as exc:
        daemon.close()
        raise UsageError(f"cannot open an endpoint{hint}: {exc}") from None


def install_signal_handlers(stop: threading.Event) -> None:
    """SIGINT/SIGTERM set ``stop``; a second SIGINT exits at once."""

    def handler(signum: int, _frame: Any) -> None:
        if stop.is_set() and signum == signal.SIGINT:
            sys.stderr.write("retargetd: forced exit\n")
            os._exit(130)
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)


def run(args: argparse.Namespace) -> int:
    """Run the daemon until SIGINT/SIGTERM."""
    config = load_config(args)
    daemon = make_daemon(config)
    stop = threading.Event()
    install_signal_handlers(stop)
    open_or_fail(daemon)
    try:
        daemon.run(stop.is_set)
    finally:
        daemon.close()
        print("retargetd: stopped", flush=True)
    return 0
