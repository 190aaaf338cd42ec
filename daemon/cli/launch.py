"""Start-up and shutdown helpers shared by the commands that run a daemon or a
recorder in the foreground: the config with CLI overrides, building and opening a
daemon, and the signal handlers."""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
import threading
from collections.abc import Iterator
from typing import Any

from retargetd.daemon.errors import UsageError


def add_console_argument(parser: argparse.ArgumentParser, default: str | None) -> None:
    """``--console [HOST:]PORT`` (the browser console; ``default`` None = off)."""
    parser.add_argument(
        "--console",
        metavar="[HOST:]PORT",
        default=default,
        help="serve the browser console there (viser; 127.0.0.1 unless a host is "
        "given, which then needs --allow-remote)"
        + (f"; default {default}" if default else "; off unless given"),
    )
    parser.add_argument(
        "--allow-remote", action="store_true",
        help="let --console serve off loopback (the page has no login; as view's "
        "--allow-remote and the config's console.allow_remote)",
    )  # fmt: skip
    if default:
        parser.add_argument(
            "--no-console", action="store_true", help="run without the console"
        )


def parse_console(text: str) -> tuple[str, int]:
    """``"[HOST:]PORT"`` -> (host, port); UsageError naming ``--console``."""
    host, sep, port = text.rpartition(":")
    host = host if sep else "127.0.0.1"
    try:
        number = int(port)
    except ValueError:
        raise UsageError(f"--console: expected [HOST:]PORT; got {text!r}") from None
    if not 0 <= number <= 65535:
        raise UsageError(f"--console: port must be in [0, 65535]; got {number}")
    return host or "127.0.0.1", number


def load_config(args: argparse.Namespace) -> Any:
    """The validated config with CLI overrides applied (ConfigError -> UsageError)."""
    import dataclasses

    from retargetd.daemon.live.config import ConfigError, DaemonConfig

    try:
        config = DaemonConfig.from_toml(args.config) if args.config else DaemonConfig()
    except ConfigError as exc:
        raise UsageError(str(exc)) from None
    performer = config.performer
    if config.performers and (getattr(args, "rig", None) or
                              getattr(args, "calibration", None)):  # fmt: skip
        raise UsageError(
            "--rig and --calibration set [performer]'s; with [[performer]] tables "
            "give each performer its rig and calibration in the config"
        )
    if getattr(args, "rig", None):
        performer = dataclasses.replace(performer, rig=args.rig)
    if getattr(args, "calibration", None):
        performer = dataclasses.replace(performer, calibration=args.calibration)
    loop = config.loop
    if getattr(args, "process_every_frame", False):
        loop = dataclasses.replace(loop, process_every_frame=True)
    solve = config.solve
    if getattr(args, "method", None):
        solve = dataclasses.replace(solve, method=args.method)
    console = config.console
    if getattr(args, "allow_remote", False):
        console = dataclasses.replace(console, allow_remote=True)
    if getattr(args, "console", None) and not getattr(args, "no_console", False):
        host, port = parse_console(args.console)
        console = dataclasses.replace(console, enabled=True, host=host, port=port)
        try:  # the same checks as the file's (a host off loopback, say)
            DaemonConfig.from_dict(
                {"console": {"host": host, "port": port,
                             "allow_remote": console.allow_remote}},
                source="--console",
            )  # fmt: skip
        except ConfigError as exc:
            raise UsageError(str(exc)) from None
    return dataclasses.replace(
        config, performer=performer, loop=loop, console=console, solve=solve
    )


def make_daemon(config: Any, config_path: str | None = None) -> Any:
    """Build a Daemon, turning rig/calibration/pipeline problems into UsageError
    (``config_path``: the file ``reload`` re-reads the ``[[pipeline]]`` of)."""
    from retargetd.daemon.body.calibration import CalibrationError
    from retargetd.daemon.body.rig import RigError
    from retargetd.daemon.live.config import ConfigError
    from retargetd.daemon.live.loop import Daemon

    try:
        return Daemon(config, config_path=config_path)
    except (RigError, CalibrationError, ConfigError) as exc:
        raise UsageError(str(exc)) from None


def open_or_fail(daemon: Any, hint: str = "") -> None:
    """Open every endpoint; a port in use (or any bind error) closes what was opened
    and becomes one UsageError line (exit 2)."""
    import zmq

    try:
        daemon.open()
    except (OSError, zmq.ZMQError) as exc:
        daemon.close()
        where = _failed_endpoint(daemon)
        what = f"the {where[0]} endpoint {where[1]}" if where else "an endpoint"
        raise UsageError(f"cannot open {what}{hint}: {exc}") from None


def _failed_endpoint(daemon: Any) -> tuple[str, str] | None:
    """(name, address) of the endpoint ``daemon.open()`` failed on: the first, in the
    order it binds them, not announced in ``daemon.endpoints``."""
    c = getattr(daemon, "config", None)
    done = getattr(daemon, "endpoints", {})
    if c is None:
        return None
    order: list[tuple[str, str]] = []
    try:
        if c.input.osc.enabled:
            order.append(
                ("osc markers", f"udp://{c.input.osc.host}:{c.input.osc.port}")
            )
        if c.show_control.enabled:
            order.append(
                ("show control", f"udp://{c.show_control.host}:{c.show_control.port}")
            )
        if c.input.zmq.enabled:
            order.append(("zmq markers", str(c.input.zmq.endpoint)))
        if c.output.pose.enabled:
            order.append(("zmq poses", str(c.output.pose.endpoint)))
        order.append(("control", str(c.control.endpoint)))
    except AttributeError:
        return None
    return next(((n, a) for n, a in order if n not in done), None)


#: The signals that stop a foreground command cleanly (the recording is finished,
#: sockets closed): Ctrl-C, ``kill``/systemd/docker stop, and a closed terminal or
#: SSH session (SIGHUP's default action would end the process with nothing closed).
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def install_signal_handlers(stop: threading.Event) -> None:
    """SIGINT, SIGTERM and SIGHUP set ``stop``; a second SIGINT exits at once."""

    def handler(signum: int, _frame: Any) -> None:
        if stop.is_set() and signum == signal.SIGINT:
            sys.stderr.write("retargetd: forced exit\n")
            os._exit(130)
        stop.set()

    for s in STOP_SIGNALS:
        signal.signal(s, handler)


@contextlib.contextmanager
def stop_on_signals(stop: threading.Event) -> Iterator[None]:
    """SIGINT, SIGTERM and SIGHUP set ``stop`` (a second SIGINT raises
    KeyboardInterrupt); the previous handlers are restored on exit. Main thread
    only."""

    def handler(signum: int, _frame: Any) -> None:
        if stop.is_set() and signum == signal.SIGINT:
            raise KeyboardInterrupt
        stop.set()

    old = {s: signal.signal(s, handler) for s in STOP_SIGNALS}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)
