"""``retargetd ctl [--endpoint E] status [--json] | calibrate [--count N] | reload``.

Talks to a running daemon over its local control socket (ZeroMQ REQ/REP, JSON
requests ``{"cmd": "status"}``, ``{"cmd": "calibrate", "count": N}``,
``{"cmd": "reload"}``). Exit 0 on success, 1 when the daemon refuses or does not answer
within ``--timeout-ms``, 2 for usage errors.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from retargetd.daemon.config import ControlConfig


def add_parser(subparsers: Any) -> None:
    """Register ``ctl``."""
    parser = subparsers.add_parser(
        "ctl",
        help="control a running daemon: status, calibrate, reload",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--endpoint",
        default=ControlConfig().endpoint,
        help="the daemon's control endpoint (default %(default)s)",
    )
    parser.add_argument("--timeout-ms", type=int, default=2000)
    sub = parser.add_subparsers(dest="ctl_command", metavar="ACTION", required=True)
    status = sub.add_parser("status", help="fps, drops, latency, occluded markers")
    status.add_argument("--json", action="store_true", help="the full JSON document")
    cal = sub.add_parser("calibrate", help="calibrate live on the next N frames")
    cal.add_argument("--count", type=int, default=None, metavar="N")
    sub.add_parser("reload", help="reload the rig and calibration files")
    parser.set_defaults(run=run)


def request(
    endpoint: str, req: dict[str, Any], timeout_ms: int
) -> dict[str, Any] | None:
    """Send one request; the reply, or None on timeout."""
    import zmq

    ctx = zmq.Context.instance()
    sock = ctx.socket(zmq.REQ)
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.RCVTIMEO, timeout_ms)
    sock.setsockopt(zmq.SNDTIMEO, timeout_ms)
    try:
        sock.connect(endpoint)
        sock.send(json.dumps(req).encode())
        reply: dict[str, Any] = json.loads(sock.recv())
        return reply
    except zmq.Again:
        return None
    finally:
        sock.close()


def run(args: argparse.Namespace) -> int:
    """Run ``ctl``."""
    from retargetd.daemon.cli import UsageError

    if args.ctl_command == "calibrate" and args.count is not None and args.count < 1:
        raise UsageError(f"--count must be >= 1; got {args.count}")
    req: dict[str, Any] = {"cmd": args.ctl_command}
    if args.ctl_command == "calibrate" and args.count is not None:
        req["count"] = args.count
    reply = request(args.endpoint, req, args.timeout_ms)
    if reply is None:
        sys.stderr.write(
            f"retargetd ctl: no daemon answered at {args.endpoint} "
            f"within {args.timeout_ms} ms\n"
        )
        return 1
    if not reply.get("ok"):
        sys.stderr.write(
            f"retargetd ctl: {reply.get('error') or reply.get('message')}\n"
        )
        return 1
    if args.ctl_command == "status":
        if args.json:
            sys.stdout.write(json.dumps(reply["status"], indent=1) + "\n")
        else:
            sys.stdout.write(reply["line"] + "\n")
    else:
        sys.stdout.write(reply["message"] + "\n")
    return 0
