"""``retargetd replay TAKE --to URL``: send a take (MCAP, C3D, TRC) to a live input.

``--to osc://HOST:PORT`` sends UDP datagrams (``--form compact``, the default, or
``simple``); ``--to zmq://HOST:PORT`` connects a PUSH to the daemon's bound PULL.
``--speed 1`` (the default) keeps the recorded timing, ``2`` doubles it, ``0`` sends
as fast as possible. ``--loop`` starts over at the end (frame numbers keep
increasing) until Ctrl-C or ``--seconds``. ``--frames a:b`` picks rows (0-based,
half-open; for a recording, its marker frames).

``--loop --blend-frames N`` makes the loop seamless: the window's last N frames are
cross-faded into its first N (the loop N frames shorter), per marker, after the tail
is carried onto the head by one rigid motion of the floor (a turn about +Z and a
shift); each pass is sent moved on by that motion, so a walk walks on instead of
jumping back (``retargetd.daemon.post.marker_loop``). Pick a window that holds whole
cycles plus N frames (``--frames a:b``). A recording is decoded to a take for it.

C3D and TRC takes are sent in world metres (the daemon input's default ``units = "m"``,
``up = "+Z"``), frame number = row, source timestamp = row / rate, labels announced
first and every second. An MCAP recording is re-sent as recorded: the same bytes, at
the recorded inter-arrival times (scaled by ``--speed``), when ``--to`` uses the
recorded transport and ``--form`` (if given) the recorded form; otherwise (or with
``--subject``, ``--take-units``, ``--take-up``) it is decoded to a take and sent as one.
At the end the player prints its own timing jitter (send time - due time).

``--key-file FILE.hmac`` signs every OSC datagram (a daemon with ``[input.osc]
key_file`` takes only signed ones): a trailer with a session (now, in Unix µs), a
counter and the truncated HMAC-SHA256 (PROTOCOLS.md section 13). A recording made
from a signed input holds the datagrams without their trailers, so it is signed
afresh when sent.
"""

from __future__ import annotations

import argparse
import math
import sys
import threading
from typing import Any

from retargetd.daemon.cli.args import add_take_arguments, take_overrides
from retargetd.daemon.errors import UsageError


def add_parser(subparsers: Any) -> None:
    """Register ``replay``."""
    parser = subparsers.add_parser(
        "replay",
        help="send a take (MCAP, C3D, TRC) over OSC or ZeroMQ, paced",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("take", metavar="TAKE", help="a .mcap, .c3d or .trc file")
    parser.add_argument(
        "--to", required=True, metavar="URL", help="osc://HOST:PORT or zmq://HOST:PORT"
    )
    parser.add_argument(
        "--speed", type=float, default=1.0,
        help="1 = recorded speed (default), 2 = twice as fast, 0 = unpaced",
    )  # fmt: skip
    parser.add_argument("--loop", action="store_true", help="start over at the end")
    parser.add_argument("--frames", metavar="a:b", help="rows to send (0-based)")
    parser.add_argument(
        "--blend-frames", type=int, metavar="N",
        help="with --loop: cross-fade the window's last N frames into its first N "
        "(seamless loop; the loop is N frames shorter)",
    )  # fmt: skip
    parser.add_argument(
        "--form", choices=("compact", "simple"),
        help="OSC form (default compact; for a recording: as recorded)",
    )  # fmt: skip
    parser.add_argument("--seconds", type=float, help="stop after this long")
    parser.add_argument(
        "--key-file", metavar="FILE.hmac",
        help="sign each OSC datagram with this key (retargetd keys --hmac)",
    )  # fmt: skip
    add_take_arguments(parser)
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Replay; returns the exit code."""
    from retargetd.daemon.cli.args import parse_frames
    from retargetd.daemon.cli.launch import stop_on_signals
    from retargetd.replay import recording as rf
    from retargetd.replay.player import (
        RecordingSource,
        Sender,
        TakeSource,
        parse_endpoint,
        play,
    )
    from retargetd.replay.takes import load_take

    try:
        ep = parse_endpoint(args.to)
    except ValueError as exc:
        raise UsageError(f"--to: {exc}") from None
    if not (math.isfinite(args.speed) and args.speed >= 0):
        raise UsageError(f"--speed must be >= 0; got {args.speed:g}")
    if args.seconds is not None and not args.seconds > 0:
        raise UsageError(f"--seconds must be > 0; got {args.seconds:g}")
    if ep.scheme == "zmq" and args.form == "simple":
        raise UsageError("--form simple is an OSC form; ZeroMQ has one form")
    sign = None
    if args.key_file is not None:
        from retargetd.daemon.live.surface import KeyFileError, load_hmac_key
        from retargetd.protocols.osc_auth import DatagramSigner

        if ep.scheme != "osc":
            raise UsageError("--key-file signs OSC datagrams; ZeroMQ uses CURVE")
        try:
            sign = DatagramSigner(load_hmac_key(args.key_file)).sign
        except KeyFileError as exc:
            raise UsageError(f"--key-file: {exc}") from None
    blend = args.blend_frames
    if blend is not None and not args.loop:
        raise UsageError("--blend-frames needs --loop (it blends the loop's seam)")
    if blend is not None and blend < 1:
        raise UsageError(f"--blend-frames must be >= 1; got {blend}")

    source: TakeSource | RecordingSource | None = None
    overrides = args.subject or args.take_units or args.take_up or args.take_rate
    if args.take.lower().endswith(".mcap") and not overrides and blend is None:
        rec = rf.read_recording(args.take)
        name = rf.main_input(rec)
        packets = [p for p in rec.packets() if p.input == name]
        form = rf.FORM_NAMES[next(p.form for p in packets if p.kind == rf.KIND_FRAME)]
        wanted = "zmq" if ep.scheme == "zmq" else f"osc-{args.form or form[4:]}"
        if form == wanted:
            n_frames = sum(p.kind == rf.KIND_FRAME for p in packets)
            rows = parse_frames(args.frames, n_frames, option="--frames")
            source = RecordingSource(packets, rows)
            what = f"{len(range(*rows.indices(n_frames)))} recorded {form} frames"
    if source is None:
        take = load_take(args.take, **take_overrides(args))
        rows = parse_frames(args.frames, take.n_frames, option="--frames")
        motion = None
        blended = ""
        if blend is not None:
            take, motion, blended = _blended_loop(take, rows, blend)
            rows = slice(None)
        source = TakeSource(take, ep.scheme, args.form or "compact", rows, motion)
        form_text = f"osc {source.form}" if ep.scheme == "osc" else "zmq"
        what = (
            f"{len(source.rows)} frames of {take.n_markers} markers at "
            f"{take.rate_hz:g} Hz ({form_text}){blended}"
        )
    print(
        f"replaying {args.take}: {what}, {source.duration_s:.2f} s, to {ep} at speed "
        f"{args.speed:g}{' (looping)' if args.loop else ''}"
        f"{', signed' if sign is not None else ''}",
        flush=True,
    )
    try:
        sender = Sender(ep, sign=sign)
    except OSError as exc:
        raise UsageError(f"cannot send to {ep}: {exc}") from None
    stop = threading.Event()
    try:
        with stop_on_signals(stop):
            report = play(
                source, sender, speed=args.speed, loop=args.loop,
                should_stop=stop.is_set, max_seconds=args.seconds,
            )  # fmt: skip
    finally:
        sender.close()
    jitter = report.jitter_us()
    timing = (
        f"jitter (send - due) us: median {jitter['median']:.0f}, p99 "
        f"{jitter['p99']:.0f}, max {jitter['max']:.0f}"
        if report.lateness_s
        else "unpaced"
    )
    sys.stdout.write(
        f"replay: sent {report.frames} frames, {report.label_packets} label packets"
        + (f", {report.other_packets} other packets" if report.other_packets else "")
        + f" in {report.wall_s:.3f} s ({report.passes} full passes); {timing}; "
        f"dropped {report.dropped}\n"
    )
    sys.stdout.flush()
    return 0


def _blended_loop(take: Any, rows: slice, n: int) -> tuple[Any, Any, str]:
    """The take cut to ``rows`` and made a seamless loop over ``n`` frames.

    Returns:
        ``(take, (mat, pos), what)``: the loop take (``valid`` recomputed), the
        per-pass floor motion, and a phrase for the first line.
    """
    import dataclasses

    import numpy as np

    from retargetd.daemon.post.marker_loop import loop_markers

    window = np.asarray(take.positions[rows], dtype=np.float64)
    try:
        positions, mat, pos = loop_markers(window, n)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    looped = dataclasses.replace(
        take, positions=positions, valid=np.isfinite(positions).all(axis=-1)
    )
    # Each pass is moved by A^-1 (x -> mat^T (x - pos)) from the one before.
    yaw = -math.degrees(math.atan2(mat[1, 0], mat[0, 0]))
    shift = -mat.T @ pos
    what = (
        f"; looped: last {n} frames blended into the first {n}, each pass moved on "
        f"by {yaw:.1f} deg about +Z then ({shift[0]:.3f}, {shift[1]:.3f}) m"
    )
    return looped, (mat, pos), what
