"""``retargetd record --listen URL --out FILE.mcap``: record a marker input, no solving.

``--listen`` takes ``osc://HOST:PORT`` (a UDP socket bound there; ``--form compact`` or
``simple``), ``zmq://HOST:PORT`` (a PULL bound there: a player's or bridge's PUSH
connects) or ``zmq+sub://HOST:PORT`` (a SUB connecting to a publisher). Port 0 binds an
ephemeral port; the "listening on" line names it. ``qtm://HOST[:PORT]`` and
``natnet://HOST[:PORT][?...]`` connect to a capture system (QTM through ``qtm-rt``,
Motive over NatNet) and record its packets as they came, control packets included
(envelope forms ``qtm`` / ``natnet``); replay decodes them with the live decoders. Every
packet is recorded as received, with its receive time, on a writer thread that never
holds up the receive loop (``/markers/raw``; label sets on ``/markers/labels``).
``--poses zmq+sub://HOST:PORT`` also records a daemon's pose stream (``/poses``).
SIGINT, SIGTERM, SIGHUP or ``--seconds`` stop it cleanly: the file is finished (footer
and index) and a summary is printed. A killed recorder leaves a readable file (all but
the last ~0.25 s). A write error (a full disk ...) stops the recording: the file keeps
every whole chunk, the summary counts what it holds, and the exit code is 1.
Layout: ``protocols/PROTOCOLS.md``, "Recordings (MCAP)".

``--key-file FILE.hmac`` (OSC): only datagrams signed with the key, each newer than
the last, are recorded, without their trailers (what a daemon with ``[input.osc]
key_file`` decodes); the others are refused and counted in the summary (unsigned or
a bad tag; replayed). PROTOCOLS.md section 13.
"""

from __future__ import annotations

import argparse
import math
import socket
import sys
import threading
import time
from typing import Any

from retargetd.daemon.cli.args import add_force_argument, refuse_existing
from retargetd.daemon.cli.launch import stop_on_signals
from retargetd.daemon.errors import UsageError
from retargetd.daemon.version import package_version

_UDP_MAX = 65536
_POLL_MS = 50


def add_parser(subparsers: Any) -> None:
    """Register ``record``."""
    parser = subparsers.add_parser(
        "record",
        help="record a marker input (OSC or ZeroMQ) to MCAP, without solving",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--listen", required=True, metavar="URL",
        help="osc://HOST:PORT, zmq://HOST:PORT (bind a PULL), zmq+sub://HOST:PORT, "
        "qtm://HOST[:PORT] or natnet://HOST[:PORT][?...] (connect to a capture system)",
    )  # fmt: skip
    parser.add_argument(
        "--out", required=True, metavar="FILE.mcap", help="the recording to write"
    )
    add_force_argument(parser)
    parser.add_argument(
        "--form", choices=("compact", "simple"), default="compact",
        help="OSC form of the input (default compact)",
    )  # fmt: skip
    parser.add_argument("--seconds", type=float, help="stop after this long")
    parser.add_argument(
        "--units", default="m", help="the sender's length unit (stored; default m)"
    )
    parser.add_argument(
        "--up", default="+Z", help="the sender's up axis (stored; default +Z)"
    )
    parser.add_argument(
        "--poses", metavar="URL", help="also record a pose stream: zmq+sub://HOST:PORT"
    )
    parser.add_argument(
        "--key-file", metavar="FILE.hmac",
        help="OSC: record only datagrams signed with this key (retargetd keys --hmac)",
    )  # fmt: skip
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Record until stopped; returns the exit code."""
    import zmq

    from retargetd.daemon.live import sources
    from retargetd.protocols import conventions as cv
    from retargetd.replay import recording as rf
    from retargetd.replay.player import parse_endpoint
    from retargetd.replay.recorder import InputInfo, open_recorder

    capture_url = args.listen if args.listen.startswith(("qtm://", "natnet://")) else ""
    try:
        if capture_url:
            system, opts = sources.parse_source(capture_url)
            capture_up = opts.up_axis if system == "natnet" else "+Z"
            ep = None
        else:
            ep = parse_endpoint(
                args.listen, ("osc", "zmq", "zmq+sub"), allow_port_0=True
            )
        poses_ep = (
            parse_endpoint(args.poses, ("zmq+sub",)) if args.poses is not None else None
        )
        units = cv.normalize_units(args.units)
        up = cv.normalize_up_axis(args.up)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if args.seconds is not None and not args.seconds > 0:
        raise UsageError(f"--seconds must be > 0; got {args.seconds:g}")
    verifier = _verifier(args.key_file, ep)
    refuse_existing(args.out, force=args.force)

    ctx = zmq.Context()
    poller = zmq.Poller()
    udp: socket.socket | None = None
    zin: Any = None
    zposes: Any = None
    cap: Any = None
    try:
        if ep is None:
            cap = sources.open_capture(capture_url, _say)
            for fd, _ in cap.readers:
                poller.register(fd, zmq.POLLIN)
            where = f"{capture_url} ({cap.system})"
            info = InputInfo(
                name=cap.system, form=cap.system,
                units="m" if cap.system == "natnet" else "mm",
                up=capture_up, endpoint=capture_url,
            )  # fmt: skip
            form = cap.form
        elif ep.scheme == "osc":
            udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            udp.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
            udp.bind((ep.host, ep.port))
            udp.setblocking(False)
            poller.register(udp, zmq.POLLIN)
            host, port = udp.getsockname()[:2]
            where = f"udp://{host}:{port} (osc {args.form})"
            info = InputInfo(
                name="osc", form=f"osc-{args.form}", units=units, up=up,
                endpoint=f"udp://{host}:{port}",
            )  # fmt: skip
            form = rf.FORM_CODES[info.form]
        else:
            zin = ctx.socket(zmq.PULL if ep.scheme == "zmq" else zmq.SUB)
            zin.setsockopt(zmq.LINGER, 0)
            zin.setsockopt(zmq.RCVHWM, 10_000)
            if ep.scheme == "zmq":
                zin.bind(ep.tcp)
            else:
                zin.setsockopt(zmq.SUBSCRIBE, b"RTD")
                zin.connect(ep.tcp)
            poller.register(zin, zmq.POLLIN)
            last = zin.getsockopt(zmq.LAST_ENDPOINT).decode() or ep.tcp
            mode = "pull" if ep.scheme == "zmq" else "sub"
            where = f"{last} (zmq {mode})"
            info = InputInfo(name="zmq", form="zmq", units=units, up=up, endpoint=last)
            form = rf.FORM_ZMQ
        if poses_ep is not None:
            zposes = ctx.socket(zmq.SUB)
            zposes.setsockopt(zmq.LINGER, 0)
            zposes.setsockopt(zmq.SUBSCRIBE, b"RTDP")
            zposes.setsockopt(zmq.SUBSCRIBE, b"RTDN")
            zposes.connect(poses_ep.tcp)
            poller.register(zposes, zmq.POLLIN)
    except (OSError, zmq.ZMQError) as exc:
        for s in (udp, zin, zposes, cap):
            if s is not None:
                s.close()
        ctx.term()
        raise UsageError(f"cannot open {args.listen}: {exc}") from None

    try:
        recorder = open_recorder(
            args.out, (info,), software=f"retargetd {package_version()}"
        )
    except OSError:
        for s in (udp, zin, zposes, cap):
            if s is not None:
                s.close()
        ctx.term()
        raise
    recorder.record_event("record_start", listen=where, form=info.form)
    verb = "connecting to" if cap is not None else "listening on"
    print(f"{verb} {where}: recording to {args.out}", flush=True)
    stop = threading.Event()
    deadline = math.inf if args.seconds is None else time.monotonic() + args.seconds
    buf = bytearray(_UDP_MAX)
    view = memoryview(buf)
    refused: dict[int, int] = {}  # osc_auth refusal code -> datagrams
    with stop_on_signals(stop):  # also during the close: a second signal waits
        try:
            while not stop.is_set() and time.monotonic() < deadline:
                if recorder.failed:
                    break  # a write error stopped the recording (logged, reported)
                events = dict(poller.poll(_POLL_MS))
                if cap is not None:
                    _drain_capture(cap, events, recorder)
                if udp is not None and udp.fileno() in events:
                    while True:
                        try:
                            n = udp.recv_into(buf)
                        except (BlockingIOError, InterruptedError):
                            break
                        if verifier is not None:
                            n = verifier.check(view, n)
                            if n < 0:
                                refused[n] = refused.get(n, 0) + 1
                                continue
                        recorder.record_packet(
                            "osc", form, time.monotonic_ns(), view[:n]
                        )
                if zin is not None and zin in events:
                    _drain_zmq(
                        zin, lambda t, p: recorder.record_packet("zmq", form, t, *p)
                    )
                if zposes is not None and zposes in events:
                    _drain_zmq(zposes, lambda t, p: recorder.record_pose(t, *p))
        finally:
            recorder.record_event("record_stop")
            for s in (udp, zin, zposes, cap):
                if s is not None:
                    s.close()
            ctx.term()
            st = recorder.close()
    print(
        f"recorded {st.frames} marker frames, {st.label_packets} label packets, "
        f"{st.other_packets} other packets ({st.label_sets} label sets"
        + (f", {st.poses} pose messages" if zposes is not None else "")
        + f") over {st.seconds:.2f} s to {args.out}; dropped {st.dropped} "
        f"(recorder queue full)" + _refused_text(verifier, refused),
        flush=True,
    )
    if recorder.failed or st.write_errors:
        sys.stderr.write(
            f"retargetd record: the recording stopped early ({recorder.error}); "
            f"{st.write_errors} packets not written\n"
        )
        return 1
    return 0


def _verifier(key_file: str | None, ep: Any) -> Any:
    """The HMAC verifier of ``--key-file`` (None without it)."""
    if key_file is None:
        return None
    from retargetd.daemon.live.surface import KeyFileError, load_hmac_key
    from retargetd.protocols.osc_auth import DatagramVerifier

    if ep is None or ep.scheme != "osc":
        raise UsageError("--key-file checks OSC datagrams; ZeroMQ uses CURVE")
    try:
        return DatagramVerifier(load_hmac_key(key_file))
    except KeyFileError as exc:
        raise UsageError(f"--key-file: {exc}") from None


def _refused_text(verifier: Any, refused: dict[int, int]) -> str:
    """The summary's refusals under ``--key-file`` ("" without it)."""
    if verifier is None:
        return ""
    from retargetd.protocols import osc_auth

    failed = refused.get(osc_auth.UNSIGNED, 0) + refused.get(osc_auth.BAD_TAG, 0)
    replayed = refused.get(osc_auth.REPLAYED, 0)
    return f"; refused {failed} unsigned or bad tag (auth_failed), {replayed} replayed"


def _drain_zmq(sock: Any, record: Any) -> None:
    import zmq

    while True:
        try:
            parts = sock.recv_multipart(zmq.NOBLOCK, copy=False)
        except zmq.Again:
            return
        record(time.monotonic_ns(), [p.buffer for p in parts])


def _drain_capture(cap: Any, events: dict[Any, int], recorder: Any) -> None:
    """Record every waiting capture-system packet as it came, then hand it to the
    input (the NatNet client asks for the model definitions once the server
    answered); the NatNet client's requests are sent on every wake-up."""
    if cap.client is not None:
        cap.client.tick()
    for fd, read in cap.readers:
        if fd not in events:
            continue
        while (pkt := read()) is not None:
            t_ns = time.monotonic_ns()
            recorder.record_packet(cap.system, cap.form, t_ns, pkt)
            cap.inp.feed(pkt, t_ns)


def _say(line: str) -> None:
    print(line, flush=True)
