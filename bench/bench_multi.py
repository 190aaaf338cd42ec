"""Several performers on one daemon, end to end: N performers x 240 Hz, in processes.

Run from the repository root::

    python bench/bench_multi.py [--performers 4] [--rate 240] [--seconds S]
        [--warmup W] [--no-single] [--method fit|construction]
        [--solve-threads 1,2] [--rounds R]

Issue 35 item 4 on a quiet machine: ``--seconds 60 --rounds 3 --solve-threads 2
--no-single`` (the default threads; ``--solve-threads 1,2`` puts the serial run beside
each); on a shared machine shorter rounds, e.g. ``--seconds 15 --rounds 3``.

What runs (issue 19 item 2), all on 127.0.0.1, every process ended at the end even on
error, with the machinery of ``bench_latency.py`` (its sender, pacing, daemon process
and VMC matching):

- the daemon, ``python -m retargetd.daemon run --config <tmp.toml>`` with N
  ``[[performer]]`` tables ``P0`` ... ``P{N-1}`` (prefixes ``P0:`` ...), each on the
  plug-in-gait rig with the calibration ``retargetd calibrate`` makes from
  ``PiG_Calibration-FlatFoot-Full.c3d``, each streaming VMC to its own port; latest
  wins (``process_every_frame = false``);
- one sender paces the real walk ``PiG_Motion-FlatFoot-Full.c3d`` (looped) at the
  rate as OSC compact frames on the one OSC input, each frame carrying all N
  performers: performer k is the walk moved k x 2 m along world +X, its labels
  prefixed ``Pk:`` (the C3D / Vicon subject convention); it stamps
  ``time.monotonic_ns()`` before each send;
- one receiver process listens on the N VMC ports and the pose stream, stamping the
  arrival of every ``/VMC/Ext/T`` datagram (per port) and of every pose message (its
  performer id from byte 50 of the header).

Latency of a performer's frame = arrival of its output minus the send of the input
frame (VMC Ts matched to the performer's pose messages through the daemon's clock, as
in ``bench_latency.match_vmc_t``). Baseline, in the same run: raw UDP one way, same
pacing and payload size as the N-performer frame. Added = the performer's percentile
minus raw UDP's. Drops per performer = timed frames sent minus that performer's poses
sent (``frames_out`` in ``ctl status --json`` ``performers``, deltas over the timed
phase); ``stale`` (latest wins), ``unsolved`` and ``unseen`` are the daemon's, and
each performer's ``unsolved`` is printed beside its drops. The timed phase starts once
the daemon has built every performer's pipeline (off its loop, from the first label
set: 3-9 s at load 4-6 here), so its drops are the steady stream's. With
``--no-single`` left out, the single-performer daemon (``[performer]``) on the plain
walk runs too, for scale. Performers are finished and sent in config order for each
frame, so performer k's latency includes the work of performers 0..k-1 of the same
frame; with ``[loop] solve_threads`` 2 some of their body solves run on the second
thread meanwhile (``daemon/live/solve_threads.py``). Each round runs a raw UDP
baseline, then the N-performer daemon once per ``--solve-threads`` setting (their
order turned every other round), each run's table with the load average after it,
and a summary line per run at the end.

In process first, for the figures the machine's scheduling does not blur: the label
split per performer and frame (``StreamView.refresh``) against fancy indexing, a
per-performer attribute read against a plain one, and the loop's own work per frame
(``Daemon._solve``) with 1 performer against N.

Speed is printed, never asserted (STYLE.md section 10).
"""

from __future__ import annotations

import argparse
import contextlib
import multiprocessing as mp
import os
import socket
import sys
import tempfile
import time
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np
from bench_latency import (
    _BE_F32,
    _POSE_FIELDS,
    LOCALHOST,
    PIG_CALIBRATION,
    PIG_MOTION,
    VMC_T_TAIL,
    Daemon,
    _calibrate,
    _load,
    _pct,
    _sender,
    _terminate,
    match_vmc_t,
    run_case,
    summarize,
)

#: Performer k stands k times this far along world +X (metres): apart on a stage.
SPACING_M = 2.0
#: Byte 50 of the pose header: the performer id (protocols/PROTOCOLS.md section 6).
PERFORMER_BYTE = 50


def _multi_receiver(n: int, capacity: int, conn: Connection) -> None:
    """Receiver process: ``n`` UDP ports (VMC, one per performer) and a pose SUB.

    Commands on ``conn``: ``("sub", endpoint)`` (answered "ok"), ``("stop",)`` sends
    the arrays back: per port the arrival ns and T of each ``/VMC/Ext/T``; per pose
    message its arrival, performer id and header stamps.
    """
    import zmq

    ctx = zmq.Context()
    socks = []
    for _ in range(n):
        udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        udp.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        udp.bind((LOCALHOST, 0))
        udp.setblocking(False)
        socks.append(udp)
    sub = ctx.socket(zmq.SUB)
    sub.setsockopt(zmq.LINGER, 0)
    sub.setsockopt(zmq.RCVHWM, 100_000)
    sub.setsockopt(zmq.SUBSCRIBE, b"RTDP")
    poller = zmq.Poller()
    for udp in socks:
        poller.register(udp, zmq.POLLIN)
    poller.register(sub, zmq.POLLIN)
    poller.register(conn.fileno(), zmq.POLLIN)
    conn.send(("ports", [s.getsockname()[1] for s in socks]))
    t_ns = np.zeros((n, capacity), np.int64)
    t_val = np.zeros((n, capacity), np.float64)
    n_t = [0] * n
    # arrival, performer, frame, received, solved, sent
    pose = np.zeros((capacity * n, 6), np.int64)
    n_pose = 0
    fds = {s.fileno(): i for i, s in enumerate(socks)}
    buf = bytearray(65536)
    clock = time.monotonic_ns
    try:
        while True:
            for sock, _ in poller.poll(100):
                i = fds.get(sock) if isinstance(sock, int) else None
                if i is not None:
                    udp = socks[i]
                    while True:
                        try:
                            k = udp.recv_into(buf)
                        except (BlockingIOError, InterruptedError):
                            break
                        t = clock()
                        j = n_t[i]
                        if (
                            j < capacity
                            and k >= 20
                            and buf[k - 20 : k - 4] == VMC_T_TAIL
                        ):
                            t_ns[i, j] = t
                            t_val[i, j] = _BE_F32.unpack_from(buf, k - 4)[0]
                            n_t[i] = j + 1
                elif sock is sub:
                    while True:
                        try:
                            parts = sub.recv_multipart(zmq.NOBLOCK)
                        except zmq.Again:
                            break
                        t = clock()
                        if n_pose < len(pose) and len(parts[0]) == 68:
                            pose[n_pose, 0] = t
                            pose[n_pose, 1] = parts[0][PERFORMER_BYTE]
                            pose[n_pose, 2:] = _POSE_FIELDS.unpack_from(parts[0])
                            n_pose += 1
                elif sock == conn.fileno():
                    cmd = conn.recv()
                    if cmd[0] == "sub":
                        sub.connect(cmd[1])
                        time.sleep(0.3)  # ZeroMQ's slow joiner
                        conn.send("ok")
                    elif cmd[0] == "stop":
                        conn.send(
                            {
                                "t_ns": [t_ns[i, : n_t[i]].copy() for i in range(n)],
                                "t_val": [t_val[i, : n_t[i]].copy() for i in range(n)],
                                "pose": pose[:n_pose].copy(),
                            }
                        )
                        return
    finally:
        for udp in socks:
            udp.close()
        sub.close()
        ctx.term()


def _config(
    calibration: Path, ports: list[int], method: str = "fit", solve_threads: int = 1
) -> str:
    tables = "".join(
        f"""
[[performer]]
name = "P{k}"
rig = "plug-in-gait"
calibration = "{calibration}"
vmc = "{LOCALHOST}:{port}"
"""
        for k, port in enumerate(ports)
    )
    return f"""\
{tables}
[input.osc]
port = 0
[input.zmq]
enabled = false
[output.pose]
endpoint = "tcp://{LOCALHOST}:*"
[control]
endpoint = "tcp://{LOCALHOST}:*"
[show_control]
enabled = false
[loop]
process_every_frame = false
solve_threads = {solve_threads}
[solve]
method = "{method}"
"""


def _stream(take: Any, n: int) -> tuple[tuple[str, ...], np.ndarray]:
    """The N-performer frames: labels ``Pk:NAME``, performer k moved k x 2 m on X."""
    labels = tuple(f"P{k}:{name}" for k in range(n) for name in take.labels)
    shift = np.zeros(3)
    parts = []
    for k in range(n):
        shift[0] = k * SPACING_M
        parts.append(take.positions + shift)  # NaN (occluded) rows stay NaN
    return labels, np.concatenate(parts, axis=1)


def run_multi(
    ctx: Any,
    args: argparse.Namespace,
    take: Any,
    calibration: Path,
    tmp: Path,
    solve_threads: int = 1,
) -> dict[str, Any]:
    """The N-performer case (``[loop] solve_threads``): observations and the
    daemon's counters."""
    n, rate = args.performers, args.rate
    labels, positions = _stream(take, n)
    capacity = int(rate * (args.seconds + args.warmup + 5)) + 1000
    recv_conn, recv_child = ctx.Pipe()
    send_conn, send_child = ctx.Pipe()
    procs: list[Any] = []
    daemon: Daemon | None = None
    try:
        receiver = ctx.Process(target=_multi_receiver, args=(n, capacity, recv_child))
        receiver.start()
        procs.append(receiver)
        if not recv_conn.poll(30):
            raise RuntimeError("receiver did not start")
        _, ports = recv_conn.recv()
        config = tmp / "multi.toml"
        config.write_text(_config(calibration, ports, args.method, solve_threads))
        daemon = Daemon(config, tmp / "multi.log")
        daemon.wait_ready()
        recv_conn.send(("sub", daemon.endpoints["zmq poses"]))
        recv_conn.recv()
        spec = {
            "mode": "osc", "rate_hz": rate, "seconds": args.seconds,
            "warmup_s": args.warmup, "positions": positions, "labels": labels,
            "raw_size": 48 + 12 * len(labels), "frame0": 0,
            "port": int(daemon.endpoints["osc markers"].rsplit(":", 1)[1]),
        }  # fmt: skip
        sender = ctx.Process(target=_sender, args=(spec, send_child))
        sender.start()
        procs.append(sender)
        if not send_conn.poll(60):
            raise RuntimeError("sender did not finish its warm-up")
        send_conn.recv()
        time.sleep(0.2)
        # The performers' pipelines are built off the loop once the labels arrive
        # (live/rebuild.py); a frame before is unsolved. Timed once they are built,
        # so the drops are the steady stream's (the wait is printed).
        t_wait = time.monotonic()
        status0 = daemon.status()
        while status0 is None or status0.get("pipelines_building", 0):
            if time.monotonic() - t_wait > 120.0:
                raise RuntimeError("the pipelines were not built in 120 s")
            time.sleep(0.1)
            status0 = daemon.status()
        built_s = time.monotonic() - t_wait
        send_conn.send("go")
        if not send_conn.poll(args.seconds * 3 + 30):
            raise RuntimeError("sender did not finish")
        _, frame0, sent_ns, slips = send_conn.recv()
        time.sleep(0.3)
        status1 = daemon.status()
        recv_conn.send(("stop",))
        if not recv_conn.poll(30):
            raise RuntimeError("receiver did not answer")
        recv = recv_conn.recv()
        return {
            "sent_ns": sent_ns, "frame0": frame0, "slips": slips, "recv": recv,
            "status0": status0 or {}, "status1": status1 or {}, "built_s": built_s,
            "frame_bytes": 48 + 12 * len(labels), "stream": (labels, positions),
        }  # fmt: skip
    finally:
        _terminate(procs)
        if daemon is not None:
            daemon.stop()


def per_performer(m: dict[str, Any], n: int) -> list[dict[str, Any]]:
    """Per performer: drops, poses and VMC Ts received, latency percentiles (µs)."""
    sent_ns, frame0 = m["sent_ns"], m["frame0"]
    n_sent = len(sent_ns)
    pose = m["recv"]["pose"]
    p0 = {p["name"]: p for p in m["status0"].get("performers", [])}
    p1 = {p["name"]: p for p in m["status1"].get("performers", [])}
    out = []
    for k in range(n):
        mine = pose[pose[:, 1] == k]
        arrival, _, frame, received, solved, sent = mine.T
        idx = frame - frame0
        timed = (idx >= 0) & (idx < n_sent)
        send = sent_ns[idx[timed]]
        j = match_vmc_t(m["recv"]["t_val"][k], solved)
        ok = j >= 0
        vidx = frame[j[ok]] - frame0
        vt = (vidx >= 0) & (vidx < n_sent)
        vmc_lat = m["recv"]["t_ns"][k][ok][vt] - sent_ns[vidx[vt]]
        name = f"P{k}"
        out_delta = p1.get(name, {}).get("frames_out", 0) - p0.get(name, {}).get(
            "frames_out", 0
        )
        unsolved = p1.get(name, {}).get("unsolved", 0) - p0.get(name, {}).get(
            "unsolved", 0
        )
        out.append(
            {
                "name": name,
                "drops": n_sent - out_delta,
                "frames_out": out_delta,
                "unsolved": unsolved,
                "pose_rx": int(np.count_nonzero(timed)),
                "vmc_rx": int(np.count_nonzero(vt)),
                "vmc_unmatched": int(np.count_nonzero(~ok)),
                "pose": _pct(arrival[timed] - send),
                "vmc": _pct(vmc_lat),
                "solve": _pct(solved[timed] - received[timed]),
                "send": _pct(sent[timed] - solved[timed]),
            }
        )
    return out


def micro(take: Any, n: int, calls: int = 20_000) -> None:
    """In process: what the split adds per performer and frame
    (``StreamView.refresh``: two slice copies, the labels being one run) against
    fancy indexing of the same rows (allocating), same run."""
    from retargetd.daemon.live.performer import StreamView
    from retargetd.protocols.marker_input import LabelSet, MarkerStream

    labels, positions = _stream(take, n)
    stream = MarkerStream(LabelSet(1, labels))
    stream.current.frame.markers_world[:] = np.nan_to_num(positions[0])
    rivals = tuple(f"P{k}:" for k in range(n))
    view = StreamView(stream, rivals[-1], rivals)
    view.refresh()
    cols = view.cols
    src = stream.current.frame

    def fancy() -> None:
        src.markers_world[cols]
        src.valid[cols]

    clock = time.perf_counter_ns
    figures = {}
    cases = (("refresh", view.refresh), ("fancy", fancy))
    for name, fn in cases:
        t = np.zeros(calls, np.int64)
        for i in range(calls):
            t0 = clock()
            fn()
            t[i] = clock() - t0
        figures[name] = (float(np.median(t)), float(np.percentile(t, 99)))
    r, f = figures["refresh"], figures["fancy"]
    print(
        f"split of one performer ({len(cols)} of {len(labels)} markers), ns per call "
        f"median / p99: refresh {r[0]:.0f} / {r[1]:.0f}, fancy indexing (allocates) "
        f"{f[0]:.0f} / {f[1]:.0f}, ratio of medians {r[0] / f[0]:.2f}"
    )


def in_process(
    take: Any,
    n: int,
    calibration: Path,
    frames: int = 3000,
    threads: tuple[int, ...] = (1,),
) -> None:
    """The loop's own work per frame, in process (no scheduling between processes):
    ``Performers.solve`` of an OSC frame fed to the stream (the decode not timed):
    every performer's solve, retarget, VMC and pose encode and send; 1 performer
    ([performer]) against N ([[performer]]) with each ``[loop] solve_threads`` of
    ``threads``, in the same run, after 500 frames of warm-up."""
    from retargetd.daemon.live.config import DaemonConfig
    from retargetd.daemon.live.loop import Daemon
    from retargetd.protocols import osc_in
    from retargetd.protocols.marker_input import LabelSet

    figures = []
    for count, solve_threads in [(0, 1)] + [(n, t) for t in threads]:
        if count == 0:
            doc: dict[str, Any] = {
                "performer": {"rig": "plug-in-gait", "calibration": str(calibration)}
            }
            labels, positions = take.labels, take.positions
        else:
            sinks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(n)]
            for sink in sinks:
                sink.bind((LOCALHOST, 0))
            doc = {"performer": [
                {"name": f"P{k}", "rig": "plug-in-gait",
                 "calibration": str(calibration),
                 "vmc": f"{LOCALHOST}:{sinks[k].getsockname()[1]}"}
                for k in range(n)
            ]}  # fmt: skip
            labels, positions = _stream(take, n)
        doc.update(
            {
                "input": {"osc": {"port": 0}, "zmq": {"enabled": False}},
                "output": {"pose": {"endpoint": f"tcp://{LOCALHOST}:*"}},
                "control": {"endpoint": f"tcp://{LOCALHOST}:*"},
                "show_control": {"enabled": False},
                "loop": {"solve_threads": solve_threads},
            }
        )
        d = Daemon(DaemonConfig.from_dict(doc, source="bench"), out=lambda _: None)
        try:
            d.open()
            stream = d.osc_stream
            label_set = LabelSet(1, tuple(labels))
            stream.set_labels(label_set)
            d.performers.prepare(stream, label_set)
            # its pipelines are built off the loop (live/rebuild.py): timed once built
            if not d.performers.done_building(120.0):
                raise RuntimeError("the performers' pipelines were not built in 120 s")
            packets = [
                osc_in.encode_compact_frame(
                    i, i / 240, 1, positions[i % len(positions)]
                )
                for i in range(frames)
            ]
            cost = np.zeros(frames, np.int64)
            for i, packet in enumerate(packets):
                t_ns = time.monotonic_ns()
                stream.feed(osc_in.decode_compact_frame, packet, t_ns=t_ns)
                t0 = time.perf_counter_ns()
                d.performers.solve(stream, t_ns)
                cost[i] = time.perf_counter_ns() - t0
        finally:
            d.close()
            if count:
                for sink in sinks:
                    sink.close()
        us = cost[500:] / 1e3
        figures.append((float(np.median(us)), float(np.percentile(us, 99))))
    (m1, p1), *several = figures
    cases = ", ".join(
        f"{n} performers solve_threads {t}: {mn:.0f} / {pn:.0f} (ratio of medians "
        f"{mn / m1:.2f})"
        for t, (mn, pn) in zip(threads, several, strict=True)
    )
    print(
        f"in process, the loop's work per frame (solve, retarget, VMC + pose send of "
        f"every performer), µs median / p99: 1 performer {m1:.0f} / {p1:.0f}, "
        f"{cases}; the 240 Hz frame period is 4167 µs; load average {_load()}"
    )


def _f(x: float) -> str:
    return "-" if not np.isfinite(x) else f"{x:.0f}"


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; returns the exit code."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--performers", type=int, default=4)
    parser.add_argument("--rate", type=float, default=240.0, help="send rate, Hz")
    parser.add_argument("--seconds", type=float, default=10.0, help="timed s")
    parser.add_argument("--warmup", type=float, default=0.5, help="untimed s")
    parser.add_argument(
        "--no-single", action="store_true", help="skip the 1-performer reference"
    )
    parser.add_argument(
        "--method", choices=("fit", "construction"), default="fit",
        help="the body solve (default: the daemon's default, the fit)",
    )  # fmt: skip
    parser.add_argument(
        "--solve-threads", type=_threads_list, default=(1, 2), metavar="T[,T...]",
        help="[loop] solve_threads of the N-performer daemon, each a run per round "
        "(default 1,2: the loop alone, then with one solve thread)",
    )  # fmt: skip
    parser.add_argument(
        "--rounds", type=int, default=1,
        help="rounds, each a raw UDP baseline then every --solve-threads setting "
        "(their order turned every other round)",
    )  # fmt: skip
    args = parser.parse_args(argv)
    if args.rounds < 1:
        parser.error("--rounds >= 1")
    if not 1 <= args.performers <= 64 or not 1 <= args.rate <= 10_000:
        parser.error("--performers in [1, 64], --rate in [1, 10000]")
    if args.seconds <= 0 or args.warmup < 0:
        parser.error("--seconds > 0, --warmup >= 0")
    if not (PIG_MOTION.is_file() and PIG_CALIBRATION.is_file()):
        print(f"datasets not found: {PIG_MOTION.parent}", file=sys.stderr)
        return 1
    from retargetd.replay.takes import load_take

    take = load_take(PIG_MOTION)
    n = args.performers
    print(
        f"take {PIG_MOTION.name}: {take.n_frames} frames, {take.n_markers} markers per "
        f"performer; {n} performers in one OSC frame of {48 + 12 * n * take.n_markers} "
        f"bytes at {args.rate:g} Hz; {os.cpu_count()} CPUs, load average {_load()}"
    )
    micro(take, n)
    ctx = mp.get_context("spawn")
    threads = args.solve_threads
    summary: list[tuple[int, int, int, float, str]] = []
    with tempfile.TemporaryDirectory(prefix="bench_multi_") as tmp_name:
        tmp = Path(tmp_name)
        calibration = _calibrate(tmp)
        in_process(take, n, calibration, threads=threads)
        stream = _stream(take, n)
        single = None
        for r in range(args.rounds):
            # the settings interleaved, their order turned every round; a raw UDP
            # baseline in every round
            order = threads if r % 2 == 0 else threads[::-1]
            raw = summarize(
                run_case(ctx, "raw", args.rate, args, take, None, tmp, "body", stream)
            )
            print(f"  round {r + 1}: raw UDP done (load {_load()})", flush=True)
            if r == 0 and not args.no_single:
                variant = "fit" if args.method == "fit" else "body"  # bench_latency's
                single = summarize(run_case(ctx, "osc", args.rate, args, take,
                                            calibration, tmp, variant))  # fmt: skip
                print(f"  1 performer: done (load {_load()})", flush=True)
            for t in order:
                m = run_multi(ctx, args, take, calibration, tmp, t)
                load = _load()
                print(f"  {n} performers, solve_threads {t}: done (load {load})")
                rows = per_performer(m, n)
                _report(args, m, rows, raw, single if t == order[0] else None)
                worst = max(x["vmc"][1] - raw.raw[1] for x in rows)
                drops = sum(x["drops"] for x in rows)
                summary.append((r + 1, t, drops, worst, load))
    print(
        f"\n{n} performers x {args.rate:g} Hz, {args.seconds:g} s a run: drops (target "
        f"0) and worst added VMC p99 per run"
    )
    for r, t, drops, worst, load in summary:
        print(
            f"  round {r} solve_threads {t}: drops {drops}, worst added VMC p99 "
            f"{_f(worst)} µs (load average after the run {load})"
        )
    return 0


def _report(
    args: argparse.Namespace,
    m: dict[str, Any],
    rows: list[dict[str, Any]],
    raw: Any,
    single: Any,
) -> None:
    """One N-performer run's table (and the 1-performer reference above it)."""
    n = len(rows)
    c0 = m["status0"].get("counters", {})
    c1 = m["status1"].get("counters", {})
    dc = {k: c1.get(k, 0) - c0.get(k, 0) for k in c1}
    n_sent = len(m["sent_ns"])
    rp = raw.raw
    print(
        f"\n{args.seconds:g} s timed after {args.warmup:g} s warm-up; {n_sent} frames "
        f"sent ({m['slips']} late sends); latencies µs, send -> arrival; raw UDP "
        f"({m['frame_bytes']} bytes) p50/p99 {_f(rp[0])} / {_f(rp[1])}"
    )
    print(
        f"daemon counters over the timed phase (timed once its pipelines were built, "
        f"{m['built_s']:.1f} s after the warm-up): frames_in {dc.get('frames_in', 0)} "
        f"solved {dc.get('frames_solved', 0)} (per performer) stale "
        f"{dc.get('stale', 0)} (per frame: every performer's) unsolved "
        f"{dc.get('unsolved', 0)} (building {dc.get('unsolved_building', 0)}) unseen "
        f"{dc.get('unseen', 0)} overruns {dc.get('overruns', 0)} send_drops "
        f"{dc.get('send_drops', 0)} vmc_errors {dc.get('vmc_errors', 0)}"
    )
    head = (
        f"{'performer':<10} {'drops':>5} {'unsolv':>6} {'out':>6} "
        f"{'VMC T p50/p99':>14} {'added p99':>9} {'pose p50/p99':>13} {'added p99':>9} "
        f"{'solve p50/p99':>14} {'send p50/p99':>13}"
    )
    print(head)
    print("-" * len(head))
    if single is not None:
        print(
            f"{'1 alone':<10} {single.drops:>5} "
            f"{single.counters.get('unsolved', 0):>6} "
            f"{single.counters.get('frames_out', 0):>6} "
            f"{_f(single.vmc[0]):>6} / {_f(single.vmc[1]):<5} "
            f"{_f(single.vmc[1] - rp[1]):>9} "
            f"{_f(single.pose[0]):>5} / {_f(single.pose[1]):<5} "
            f"{_f(single.pose[1] - rp[1]):>9} "
            f"{_f(single.stages['solve'][0]):>6} / {_f(single.stages['solve'][1]):<6} "
            f"{_f(single.stages['send'][0]):>5} / {_f(single.stages['send'][1]):<5}"
        )
    for r in rows:
        print(
            f"{r['name']:<10} {r['drops']:>5} {r['unsolved']:>6} {r['frames_out']:>6} "
            f"{_f(r['vmc'][0]):>6} / {_f(r['vmc'][1]):<5} {_f(r['vmc'][1] - rp[1]):>9} "
            f"{_f(r['pose'][0]):>5} / {_f(r['pose'][1]):<5} "
            f"{_f(r['pose'][1] - rp[1]):>9} "
            f"{_f(r['solve'][0]):>6} / {_f(r['solve'][1]):<6} "
            f"{_f(r['send'][0]):>5} / {_f(r['send'][1]):<5}"
        )
    print(
        "drops = timed frames sent - that performer's poses sent (daemon counters: "
        "stale, unsolved, unseen); unsolv = its frames with no pipeline to solve them; "
        "solve = received -> solved, send = solved -> sent (pose header stamps; a "
        "later performer's 'received' is the frame's, so its solve includes the "
        "earlier performers' of the same frame)"
    )
    total = sum(r["drops"] for r in rows)
    worst = max(r["vmc"][1] - rp[1] for r in rows)
    print(
        f"{n} performers x {args.rate:g} Hz: drops {total} (target 0), worst added "
        f"VMC p99 {_f(worst)} µs; load average at the end: {_load()}"
    )


def _threads_list(text: str) -> tuple[int, ...]:
    """``--solve-threads 1,2``: the settings, each in [1, 64]."""
    try:
        values = tuple(int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a list of integers: {text!r}") from None
    if not values or not all(1 <= v <= 64 for v in values):
        raise argparse.ArgumentTypeError("each solve_threads in [1, 64]")
    return values


if __name__ == "__main__":
    with contextlib.suppress(KeyboardInterrupt):
        sys.exit(main())
    sys.exit(130)
