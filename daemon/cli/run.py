"""``retargetd run [--config FILE]``: the live daemon, in the foreground.

The config is validated before any socket opens (a bad key: one line, exit 2). SIGINT
or SIGTERM ends it cleanly (sockets closed, exit 0, within the poll timeout); a second
SIGINT forces the exit. Endpoints and their defaults: README "Live daemon".
``--listen qtm://HOST[:PORT]`` or ``--listen natnet://HOST[:PORT][?...]`` connects to a
capture system (overrides ``[input] source``; README "Capture systems").
"""

from __future__ import annotations

import argparse
import logging
import threading
from typing import Any

from retargetd.daemon.cli.launch import (
    add_console_argument,
    install_signal_handlers,
    load_config,
    make_daemon,
    open_or_fail,
)
from retargetd.daemon.errors import UsageError

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
    parser.add_argument(
        "--listen",
        metavar="URL",
        help="a capture system to connect to: qtm://HOST[:PORT] or "
        "natnet://HOST[:PORT][?data_port=N&multicast=1&up=+Z...] (overrides "
        "[input] source)",
    )
    add_console_argument(parser, None)
    parser.add_argument(
        "--method",
        choices=("construction", "fit"),
        default=None,
        help="override solve.method: the chapter's construction or the fit",
    )
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Run the daemon until SIGINT/SIGTERM."""
    config = load_config(args)
    if getattr(args, "listen", None):
        import dataclasses

        from retargetd.daemon.live.sources import parse_source

        try:
            parse_source(args.listen)
        except ValueError as exc:
            raise UsageError(f"--listen: {exc}") from None
        config = dataclasses.replace(
            config, input=dataclasses.replace(config.input, source=args.listen)
        )
    daemon = make_daemon(config, args.config)
    stop = threading.Event()
    install_signal_handlers(stop)
    open_or_fail(daemon)
    try:
        daemon.run(stop.is_set)
    finally:
        daemon.close()
        print("retargetd: stopped", flush=True)
    return 0
