"""The ``retargetd`` console script: argparse subcommands, one module per subcommand.

Each subcommand module exposes ``add_parser(subparsers)`` (cheap: heavy imports happen
inside ``run``) and ``run(args) -> int``. ``main(argv)`` returns the exit code:
0 success, 1 a failure the command reports (or a crash), 2 a usage, config or input
error (one clear line on stderr, no traceback).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence
from importlib.metadata import PackageNotFoundError, version

from retargetd.replay.take import TakeError

logger = logging.getLogger(__name__)

#: Subcommand modules, in ``--help`` order.
SUBCOMMAND_MODULES: tuple[str, ...] = (
    "retargetd.daemon.cmd_synth",
    "retargetd.daemon.cmd_take",
    "retargetd.daemon.cmd_rig",
    "retargetd.daemon.cmd_calibrate",
    "retargetd.daemon.cmd_face_train",
    "retargetd.daemon.cmd_solve",
    "retargetd.daemon.cmd_export_c3d",
    "retargetd.daemon.cmd_run",
    "retargetd.daemon.cmd_ctl",
    "retargetd.daemon.cmd_demo",
    "retargetd.daemon.cmd_record",
    "retargetd.daemon.cmd_replay",
    "retargetd.daemon.cmd_validate",
)


class UsageError(Exception):
    """A user error the CLI reports in one line with exit code 2."""


def package_version() -> str:
    """The installed distribution's version, ``"unknown"`` when not installed."""
    try:
        return version("mocap-retargetd")
    except PackageNotFoundError:
        return "unknown"


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # type: ignore[override]
        # One line, exit 2: the usage block is one `--help` away.
        self.exit(2, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    """Build the top-level parser with every subcommand registered."""
    parser = _Parser(
        prog="retargetd",
        description=(
            "Live motion-capture retarget daemon: labelled optical markers in, "
            "a skeleton solved, rotations streamed to engines."
        ),
    )
    parser.add_argument(
        "--version", action="version", version=f"retargetd {package_version()}"
    )
    parser.add_argument(
        "-v", "--verbose", action="count", default=0, help="more logging (-vv: debug)"
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for name in SUBCOMMAND_MODULES:
        importlib.import_module(name).add_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI; returns the process exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.WARNING - 10 * min(args.verbose, 2),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    if args.command is None:
        parser.print_help(sys.stderr)
        return 2
    try:
        return int(args.run(args))
    except (UsageError, TakeError, OSError) as exc:
        # Input problems (bad file, bad value, ambiguous subject) are the user's to fix:
        # one line, exit 2. Anything else is a bug and crashes with a traceback (1).
        sys.stderr.write(f"retargetd {args.command}: error: {exc}\n")
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
