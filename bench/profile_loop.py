"""Where a frame's time goes inside the live loop: a per-stage CPU profile, in process.

Run from the repository root::

    python bench/profile_loop.py [--frames N] [--warmup W] [--transports osc,zmq]
        [--method construction|fit] [--validate] [--cprofile] [--rate-hz R]

The daemon (``Daemon`` of ``daemon/live``, the object ``retargetd run`` serves) is
opened on the ``menache`` rig calibrated on the synthetic performer's T-pose hold,
with ephemeral endpoints on 127.0.0.1: compact OSC and ZeroMQ marker inputs, VMC out
to a UDP socket this script drains, the ZeroMQ pose stream to a SUB this script drains.
It is then driven one wake-up at a time, exactly as ``Daemon.run`` does (``poll`` then
``_service``), one frame per wake-up: each frame is sent, then the loop wakes for it,
0.2 ms later, or paced at ``--rate-hz`` as a live source sends (on this shared VM a
frame every 4 ms finds the code and data it touches colder than one every 0.5 ms, and
every stage costs more: compare the two). The script runs against whichever tree is
installed (an older one, without ``live/emit.py``, shows its separate stages).

Each stage of the frame is timed by a wrapper put around the call on the live objects
(``time.perf_counter_ns`` before and after): the poll, the decode and book-keeping of
the input (``_service`` minus the performer's ``path.process``), the body solve, the
emit call (``live/emit.py``: the retarget, the engine-frame conversion, the VMC and pose
packs in one compiled call), or the two in one (``solve + emit call``,
``live/solve_emit.py``: the default pipeline without a live validator), or the
packet's feed with them (``feed + solve + emit call``: the one compiled call per frame
of ``one_call.FastFrame``, where the stream's is armed; its ``run`` is
then the frame's ``solve_and_send``, and the decode and book-keeping row is the
drain's Python and the wake-up's around it), the VMC sends
(``send`` on the connected socket), the pose send, the validator's submit (stages a
configuration never calls are left out of the table: the separate retarget, engine
frame, VMC and pose encode rows appear only where the loop still makes them, the
retarget with ``[target] spine = "pivot"``); "glue" is
``path.process`` minus the stages inside it (attribute reads, flags, the budget checks,
the stats record, which is also timed alone on the same object after the run: a
slotted object cannot be wrapped in place). The wrapper's own cost (measured on an empty
call, same run) is subtracted from each stage and printed. Medians and p99 per stage in
µs, and what share of the median frame each one is.

This is CPU time on the loop's thread: the wake-up latency of the scheduler, which
dominates the end-to-end p99 on a loaded machine, is measured by
``bench/bench_latency.py``, not here. Printed, never asserted (STYLE.md section 10).
"""

from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import socket
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import zmq

from retargetd.daemon.body.calibration import calibrate
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.live import send as live_send
from retargetd.daemon.live.config import DaemonConfig
from retargetd.daemon.live.loop import Daemon
from retargetd.daemon.synth import performer as pf
from retargetd.protocols import engine_unity, osc_in, zmq_wire
from retargetd.protocols.marker_input import LabelSet


class Timer:
    """perf_counter_ns intervals of one stage, preallocated."""

    def __init__(self, n: int) -> None:
        self.ns = np.zeros(n, dtype=np.int64)
        self.calls = np.zeros(n, dtype=np.int64)
        self.k = 0  # the frame being filled (set by the driver)

    def wrap(self, fn: Callable[..., Any]) -> Callable[..., Any]:
        clock = time.perf_counter_ns

        def timed(*args: Any, **kwargs: Any) -> Any:
            t0 = clock()
            try:
                return fn(*args, **kwargs)
            finally:
                self.ns[self.k] += clock() - t0
                self.calls[self.k] += 1

        return timed


class SocketProxy:
    """The daemon's VMC socket with its ``send`` and ``sendto`` timed."""

    def __init__(self, sock: socket.socket, timer: Timer) -> None:
        self._sock = sock
        self.send = timer.wrap(sock.send)
        self.sendto = timer.wrap(sock.sendto)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._sock, name)


def _config(tmp: Path, method: str, validate: bool, vmc_port: int) -> DaemonConfig:
    take = pf.synthesize(seconds=2.0, rate_hz=240.0)
    rig = load_rig("menache")
    cal = calibrate(rig, take.markers_world[take.base_pose_frames], take.labels)
    cal.save(tmp / "menache.json")
    doc = {
        "performer": {"rig": "menache", "calibration": str(tmp / "menache.json")},
        "solve": {"method": method},
        "input": {"osc": {"port": 0}, "zmq": {"endpoint": "tcp://127.0.0.1:*"}},
        "output": {
            "vmc": {"port": vmc_port},
            "pose": {"endpoint": "tcp://127.0.0.1:*", "sndhwm": 100_000},
        },
        "control": {"endpoint": "tcp://127.0.0.1:*"},
        "show_control": {"port": 0},
        "validate": {"enabled": validate},
        "loop": {"poll_timeout_ms": 20, "stats_interval_s": 3600},
    }
    return DaemonConfig.from_dict(doc, source="profile_loop")


def _wake(d: Daemon, poll: Callable[[int], Any]) -> None:
    deadline = time.monotonic() + 2.0
    while True:
        events = poll(50)
        if events:
            d._service(events)
            return
        if time.monotonic() > deadline:
            raise RuntimeError("no input event within 2 s")


def profile(
    transport: str, n_frames: int, warmup: int, method: str, validate: bool,
    cprofile: bool = False, rate_hz: float = 0.0, ab: bool = False,
) -> None:  # fmt: skip
    take = pf.synthesize(seconds=(n_frames + warmup) / 240.0 + 1.0, rate_hz=240.0)
    rows = np.asarray(take.markers_world, dtype=np.float32)
    labels = LabelSet(1, take.labels)
    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sink.bind(("127.0.0.1", 0))
    sink.setblocking(False)
    ctx = zmq.Context.instance()
    with tempfile.TemporaryDirectory() as tmp_s:
        config = _config(Path(tmp_s), method, validate, sink.getsockname()[1])
        d = Daemon(config, out=lambda _line: None)
        sub = ctx.socket(zmq.SUB)
        sub.setsockopt(zmq.LINGER, 0)
        sub.setsockopt(zmq.SUBSCRIBE, b"")
        tx_udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        tx_zmq = ctx.socket(zmq.PUSH)
        tx_zmq.setsockopt(zmq.LINGER, 0)
        try:
            d.open()
            sub.connect(d.endpoints["zmq poses"].split()[0])
            if transport == "osc":
                host, port = d.endpoints["osc markers"].split()[0][6:].rsplit(":", 1)
                addr = (host, int(port))
                tx_udp.sendto(osc_in.encode_labels(labels), addr)
                pkts = [
                    osc_in.encode_compact_frame(i, i / 240.0, 1, rows[i])
                    for i in range(n_frames + warmup)
                ]

                def send(p: Any) -> None:
                    tx_udp.sendto(p, addr)
            else:
                tx_zmq.connect(d.endpoints["zmq markers"].split()[0])
                tx_zmq.send_multipart(zmq_wire.encode_zmq_labels(labels))
                pkts = [
                    zmq_wire.encode_zmq_frame(i, i / 240.0, 1, rows[i])
                    for i in range(n_frames + warmup)
                ]

                def send(p: Any) -> None:
                    tx_zmq.send_multipart(p)

            def drain() -> None:
                try:
                    while True:
                        sink.recv(65536)
                except BlockingIOError:
                    pass
                while sub.poll(0):
                    sub.recv_multipart()

            poll_fn = d._poller.poll
            path = d.performers.first.path
            for p in pkts[:warmup]:
                send(p)
                time.sleep(0.0002)
                _wake(d, poll_fn)
                drain()
                if not path.pipelines:  # built off the loop (the fit's: seconds on
                    path.done_building(120.0)  # a loaded machine): waited for
            pipe = next(iter(d.performers.first.path.pipelines.values()))
            names = (
                "poll", "service", "solve_and_send", "body solve", "retarget",
                "engine frame", "VMC encode", "emit call", "solve + emit call",
                "feed + solve + emit call", "VMC send", "pose encode",
                "pose send", "validator submit", "stats record", "empty wrapper",
            )  # fmt: skip
            t = {k: Timer(n_frames) for k in names}
            poll = t["poll"].wrap(poll_fn)
            perf = d.performers.first
            path, outputs = perf.path, d.outputs
            orig = {
                "service": d._service,
                "solve_and_send": path.process,
                "_send_pub": outputs.send_pub,
            }
            d._service = t["service"].wrap(orig["service"])  # type: ignore[method-assign]
            path.process = t["solve_and_send"].wrap(orig["solve_and_send"])  # type: ignore[method-assign]
            # One compiled call per frame (one_call.FastFrame: the packet's feed, the
            # solve and the emit), where the stream's is armed: its run is the
            # frame's solve_and_send (the feed inside it).
            stream = d.osc_stream if transport == "osc" else d.zmq_stream
            fast = getattr(stream, "fast", None)
            saved_fast = getattr(fast, "call", None)
            if fast is not None:
                saved_run = fast.run
                fast.run = t["solve_and_send"].wrap(saved_run)
                fast.call = t["feed + solve + emit call"].wrap(saved_fast)
            outputs.send_pub = t["pose send"].wrap(orig["_send_pub"])  # type: ignore[method-assign]
            pipe.solver.solve_frame = t["body solve"].wrap(pipe.solver.solve_frame)  # type: ignore[method-assign]
            pipe.retargeter.apply = t["retarget"].wrap(pipe.retargeter.apply)
            pipe.vmc.encode = t["VMC encode"].wrap(pipe.vmc.encode)  # type: ignore[method-assign]
            pipe.pose_enc.encode = t["pose encode"].wrap(pipe.pose_enc.encode)  # type: ignore[method-assign]
            if d.validator is not None:
                d.validator.submit = t["validator submit"].wrap(d.validator.submit)  # type: ignore[method-assign]
            eu = engine_unity
            saved_eu = (eu.unity_quat_xyzw_from_world, eu.unity_pos_from_world)
            eu.unity_quat_xyzw_from_world = t["engine frame"].wrap(saved_eu[0])
            eu.unity_pos_from_world = t["engine frame"].wrap(saved_eu[1])
            # The emit call: the plan's compiled function (EmitPlan.call), or the
            # module's kernel in older trees (none before live/emit.py).
            plan = getattr(pipe, "emit", None)
            saved_call = getattr(plan, "call", None)
            saved_emit = None
            if saved_call is not None:
                plan.call = t["emit call"].wrap(saved_call)
            else:
                saved_emit = getattr(live_send, "emit_frame", None)
                if saved_emit is not None:
                    live_send.emit_frame = t["emit call"].wrap(saved_emit)
            # The body solve and the emit in one call (live/solve_emit.py), where
            # the pipeline has it (none before it, nor with a stage between them).
            fused = getattr(pipe, "solve_emit", None)
            saved_fused = getattr(fused, "call", None)
            if saved_fused is not None:
                fused.call = t["solve + emit call"].wrap(saved_fused)
            real_vmc = perf.vmc.sock
            assert real_vmc is not None
            perf.vmc.sock = SocketProxy(real_vmc, t["VMC send"])  # type: ignore[assignment]
            empty = t["empty wrapper"].wrap(lambda: None)
            prof = cProfile.Profile() if cprofile else None
            period_s = 1.0 / rate_hz if rate_hz > 0 else 0.0
            next_s = time.perf_counter()
            try:
                for k, p in enumerate(pkts[warmup:]):
                    for timer in t.values():
                        timer.k = k
                    if period_s:  # paced: one frame every period, as a live source
                        next_s += period_s
                        ahead = next_s - time.perf_counter()
                        if ahead > 0:
                            time.sleep(ahead)
                    if ab and fast is not None:  # odd frames: the feed, the frame
                        stream.fast = fast if k % 2 == 0 else None
                    elif ab and saved_fused is not None:  # odd frames: two calls
                        pipe.solve_emit = fused if k % 2 == 0 else None
                    send(p)
                    time.sleep(0.0002)  # the packet is in the socket before the wake
                    if prof is not None:
                        prof.enable()
                    _wake(d, poll)
                    if prof is not None:
                        prof.disable()
                    empty()
                    drain()
            finally:
                eu.unity_quat_xyzw_from_world, eu.unity_pos_from_world = saved_eu
                if saved_call is not None:
                    plan.call = saved_call
                if saved_emit is not None:
                    live_send.emit_frame = saved_emit
                if saved_fused is not None:
                    fused.call = saved_fused
                    pipe.solve_emit = fused
                if fast is not None:
                    fast.call = saved_fast
                    fast.run = saved_run
                    stream.fast = fast
                perf.vmc.sock = real_vmc
            solved = d.stats.frames_solved
            # The stats record (a slotted object: not wrappable in place), alone on
            # the same object, same arguments' kind, as many calls.
            rec, clock = d.stats.record, time.perf_counter_ns
            for k in range(n_frames):
                t0 = clock()
                rec(1000, 2000, 3000, 4000)
                t["stats record"].ns[k] = clock() - t0
                t["stats record"].calls[k] = 1
        finally:
            d.close()
            sub.close()
            tx_zmq.close()
            tx_udp.close()
            sink.close()
    if prof is not None:  # function-level, with cProfile's own overhead (not the table)
        pstats.Stats(prof).sort_stats("tottime").print_stats(25)
    wrapper = float(np.median(t["empty wrapper"].ns))
    us: dict[str, np.ndarray] = {}
    for k, timer in t.items():
        if k == "stats record":  # timed inline, no wrapper
            us[k] = timer.ns / 1e3
        elif k != "empty wrapper":  # each call's wrapper cost out
            us[k] = (timer.ns - timer.calls * wrapper) / 1e3
    inside = (
        "body solve", "retarget", "engine frame", "VMC encode", "emit call",
        "solve + emit call", "feed + solve + emit call", "VMC send", "pose encode",
        "pose send", "validator submit",
    )  # fmt: skip
    us["glue (solve_and_send rest)"] = us["solve_and_send"] - sum(us[k] for k in inside)
    us["decode + book-keeping"] = us["service"] - us["solve_and_send"]
    sends = ("VMC send", "pose send", "validator submit")
    us["path without sends"] = us["solve_and_send"] - sum(us[k] for k in sends)
    order = (
        "poll", "decode + book-keeping", *inside, "glue (solve_and_send rest)",
        "stats record", "path without sends",
        "solve_and_send", "service",
    )  # fmt: skip
    pacing = f"paced at {rate_hz:g} Hz" if rate_hz > 0 else "unpaced"
    head = (
        f"\n== {transport}, {method}, validator {'on' if validate else 'off'}, "
        f"{pacing}: {n_frames} frames after {warmup} warm-up, {solved} solved; "
        f"wrapper cost {wrapper / 1e3:.2f} µs subtracted per call"
    )
    if ab and fast is not None:
        even = np.arange(n_frames) % 2 == 0
        _table(f"{head}\n   even frames: one call (the feed, the solve, the emit)",
               us, t, order, even)  # fmt: skip
        _table(f"{head}\n   odd frames: the feed's call, then the frame's", us, t,
               order, ~even)  # fmt: skip
        return
    if not (ab and saved_fused is not None):
        _table(head, us, t, order, np.ones(n_frames, dtype=bool))
        return
    even = np.arange(n_frames) % 2 == 0
    _table(f"{head}\n   even frames: the solve and the emit in one call", us, t,
           order, even)  # fmt: skip
    _table(f"{head}\n   odd frames: the solve's call, then the emit's", us, t,
           order, ~even)  # fmt: skip


def _table(
    head: str,
    us: dict[str, np.ndarray],
    t: dict[str, Timer],
    order: tuple[str, ...],
    rows: np.ndarray,
) -> None:
    """The stages' medians and p99s over the frames ``rows`` selects."""
    total = float(np.median((us["service"] + us["poll"])[rows]))
    print(head)
    print(f"{'stage':30s} {'median µs':>10s} {'p99 µs':>9s} {'share':>7s}")
    for k in order:
        if k in t and not t[k].calls[rows].any():
            continue  # a stage this configuration never calls (e.g. the pivot's)
        a = us[k][rows]
        med, p99 = float(np.median(a)), float(np.percentile(a, 99))
        share = (
            ""
            if k in ("solve_and_send", "service", "stats record", "path without sends")
            else f"{100 * med / total:6.1f}%"
        )
        print(f"{k:30s} {med:10.1f} {p99:9.1f} {share:>7s}")
    print(f"{'poll + service (frame)':30s} {total:10.1f}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=3000)
    ap.add_argument("--warmup", type=int, default=600)
    ap.add_argument("--transports", default="osc,zmq")
    ap.add_argument("--method", default="construction", choices=("construction", "fit"))
    ap.add_argument("--validate", action="store_true")
    ap.add_argument(
        "--rate-hz", type=float, default=0.0,
        help="send the timed frames at this rate (0: each 0.2 ms after the last "
        "wake-up); the per-frame costs grow with the time between frames",
    )  # fmt: skip
    ap.add_argument(
        "--cprofile", action="store_true",
        help="also print cProfile's top functions of the timed wake-ups",
    )  # fmt: skip
    ap.add_argument(
        "--ab", action="store_true",
        help="where the stream's one call per frame is armed (one_call.FastFrame), "
        "make every other frame's two calls instead (the feed's, the frame's), "
        "else where the pipeline has the solve and the emit in one call "
        "(live/solve_emit.py), every other frame's solve and emit calls; the same "
        "pipeline and state; a table for each kind of frame",
    )  # fmt: skip
    args = ap.parse_args(argv)
    la = os.getloadavg()
    print(
        f"profile_loop  [load average {la[0]:.2f} {la[1]:.2f} {la[2]:.2f} "
        f"({os.cpu_count()} cpus)]"
    )
    for transport in args.transports.split(","):
        profile(
            transport.strip(), args.frames, args.warmup, args.method, args.validate,
            args.cprofile, args.rate_hz, args.ab,
        )  # fmt: skip
    la = os.getloadavg()
    print(f"load average at the end: {la[0]:.2f} {la[1]:.2f} {la[2]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
