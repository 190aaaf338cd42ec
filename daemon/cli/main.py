"""The ``retargetd`` console script: argparse subcommands, one module per subcommand.

Each subcommand module exposes ``add_parser(subparsers)`` (cheap: heavy imports happen
inside ``run``) and ``run(args) -> int``. ``main(argv)`` returns the exit code:
0 success, 1 a failure the command reports (or a crash), 2 a usage, config or input
error (one clear line on stderr, no traceback).
"""

from __future__ import annotations

import argparse
import functools
import importlib
import logging
import os
import sys
from collections.abc import Sequence

from retargetd.daemon.cli.help import tidy
from retargetd.daemon.errors import UsageError
from retargetd.daemon.version import package_version
from retargetd.replay.take import TakeError

logger = logging.getLogger(__name__)

#: Subcommand modules, in ``--help`` order.
SUBCOMMAND_MODULES: tuple[str, ...] = (
    "retargetd.daemon.cli.synth",
    "retargetd.daemon.cli.take",
    "retargetd.daemon.cli.rig",
    "retargetd.daemon.cli.calibrate",
    "retargetd.daemon.cli.face_train",
    "retargetd.daemon.cli.solve",
    "retargetd.daemon.cli.reduce",
    "retargetd.daemon.cli.blend",
    "retargetd.daemon.cli.loop",
    "retargetd.daemon.cli.retarget",
    "retargetd.daemon.cli.export_c3d",
    "retargetd.daemon.cli.run",
    "retargetd.daemon.cli.ctl",
    "retargetd.daemon.cli.keys",
    "retargetd.daemon.cli.demo",
    "retargetd.daemon.cli.record",
    "retargetd.daemon.cli.replay",
    "retargetd.daemon.cli.validate",
    "retargetd.daemon.cli.view",
    "retargetd.daemon.cli.batch",
)


#: Exit code after a broken pipe on stdout (128 + SIGPIPE, as a shell reports it).
EXIT_BROKEN_PIPE = 141


def _quiet_stdout() -> None:
    """Replace stdout's descriptor with /dev/null (after a broken pipe)."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):
        pass


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
    tidy(parser)  # usage, summary and options first; the manual after, plain
    return parser


@functools.cache
def _parser() -> argparse.ArgumentParser:
    """The parser :func:`main` parses with, built once a process: building it (every
    subcommand's options and manual) costs 85 ms, and a process that calls
    :func:`main` again (the test suite, 1,000s of times) parsed with an equal one.
    Parsing leaves it as it was (``append`` copies its default list)."""
    return build_parser()


def main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI; returns the process exit code."""
    parser = _parser()
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
    except BrokenPipeError:
        # The reader went away (``retargetd take info X | head``): stop quietly, and
        # point stdout at /dev/null so the interpreter's final flush does not raise
        # again. 141 = 128 + SIGPIPE, what a shell reports for a killed writer.
        _quiet_stdout()
        return EXIT_BROKEN_PIPE
    except (UsageError, TakeError, OSError) as exc:
        # Input problems (bad file, bad value, ambiguous subject) are the user's to fix:
        # one line, exit 2. Anything else is a bug and crashes with a traceback (1).
        sys.stderr.write(f"retargetd {args.command}: error: {exc}\n")
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
