"""``retargetd keys NAME [--dir DIR] [--hmac]``: write a ZeroMQ CURVE key pair, or
with ``--hmac`` a key for signed OSC marker datagrams.

Writes ``DIR/NAME.key`` (the public key: give it to the peer) and
``DIR/NAME.key_secret`` (public and secret key: keep it), both with mode 0600; an
existing file is never overwritten. The daemon's pair goes in its config
(``control.secret_key = "DIR/daemon.key_secret"``), each operator's public key in
``control.client_keys``; ``retargetd ctl --key DIR/operator.key_secret`` talks to it
(README "Network surface"). The same for the pose stream (``output.pose``) and the
ZeroMQ marker input (``input.zmq``).

``--hmac`` writes ``DIR/NAME.hmac`` instead: 32 random bytes as hex, mode 0600, the
shared key of ``[input.osc] key_file`` and of ``retargetd replay/record --key-file``
(a capture bridge signs with it: PROTOCOLS.md section 13).
"""

from __future__ import annotations

import argparse
from typing import Any

from retargetd.daemon.errors import UsageError


def add_parser(subparsers: Any) -> None:
    """Register ``keys``."""
    parser = subparsers.add_parser(
        "keys",
        help="write a CURVE key pair (control, pose stream, ZeroMQ markers) or, "
        "with --hmac, an OSC marker signing key",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("name", metavar="NAME", help="e.g. daemon, operator, unity")
    parser.add_argument("--dir", default=".", help="folder (default: here)")
    parser.add_argument(
        "--hmac", action="store_true",
        help="write NAME.hmac: a key for signed OSC marker datagrams",
    )  # fmt: skip
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Write the pair; print both paths."""
    from retargetd.daemon.live.surface import (
        KeyFileError,
        write_hmac_key,
        write_keypair,
    )

    if args.hmac:
        try:
            path = write_hmac_key(args.dir, args.name)
        except KeyFileError as exc:
            raise UsageError(str(exc)) from None
        print(f"hmac key {path} (mode 0600: the daemon's and the sender's, secret)")
        return 0
    try:
        public_path, secret_path = write_keypair(args.dir, args.name)
    except KeyFileError as exc:
        raise UsageError(str(exc)) from None
    print(f"public key {public_path} (give it to the peer)")
    print(f"secret key {secret_path} (mode 0600: keep it)")
    return 0
