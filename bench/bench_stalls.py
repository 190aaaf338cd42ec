"""The loop stalls of issue 30 item 6, event by event: what a pose stream sees when a
stream starts, a reload reads changed files (and rebuilds the pipeline and the live
validator), a new label set comes, and a face capture changes the training set (and
writes it) (``daemon/live/rebuild.py``, ``reload.py``, ``validation.py``, ``face.py``).

A ``retargetd run`` process (the soak's config: the PiG walk's calibration, the fit,
the validator on, the face on when the ICT training set is in ``../shared/datasets``)
is sent the walk at 240 Hz over OSC; at set times the driver

- ``first``: announces the walk's labels (the stream's first pipeline);
- ``reload``: appends a newline to the calibration file, then ``ctl reload`` (the
  files parsed, the pipeline rebuilt, the live validator rebuilt: its MuJoCo model
  for the new calibration object);
- ``labels_kept``: announces a new label set (a new id) with one marker added at the
  end: the old pipeline's columns keep their markers (sent as NaN: occluded);
- ``labels_moved``: a new id with the walk's labels rotated by one: every column
  another marker, so the old pipeline cannot solve it (no pose until its own is
  built: the gap is the build's, caused by the source; the loop's stall is not);
- ``face``: ``ctl face-capture neutral --count 24`` (a new training set, written to
  ``face.training``; face on only).

Per event it prints the longest gap between two poses at a SUB on the pose stream in
the 2 s after the event (``first``: from the announcement to the first pose), the
median and p99 of the pose intervals there, the sender's own longest gap there (the
bench process not scheduled: a pose gap that long is the source's), the loop stalls
(phases over 50 ms, ``stalls.py``) counted in that window by phase, and what the
status showed in flight off the loop meanwhile (read every 0.25 s:
``pipelines_building``, ``validators_building``, ``face.averaging``, ``face.saving``,
``calibration_saving``; work that ended
between two reads is not seen); at the end the daemon's ``loop_stalls``, the median
and p99 of the pose intervals over the run and the load (``os.getloadavg``) before
and after.
With ``--baseline DIR`` (a folder holding ``retargetd/{daemon,protocols,replay}``, as
``PYTHONPATH`` would name it: another tree, e.g. ``git archive`` of main) the same run
is made first with that tree's daemon, in the same invocation, and the ratios printed.

Run from the repository root::

    python bench/bench_stalls.py
    python bench/bench_stalls.py --baseline /tmp/rtd_main
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import sys
import tempfile
import threading
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import zmq

sys.path.insert(0, str(Path(__file__).resolve().parent))
import fuzz
import soak

RATE_HZ = 240.0
#: Seconds from the start of streaming to each event, and after the last one.
EVENTS = (("first", 0.5), ("reload", 4.0), ("labels_kept", 7.5),
          ("labels_moved", 11.0), ("face", 14.5))  # fmt: skip
TAIL_S = 3.5
#: The window after an event in which its gap is looked for.
WINDOW_S = 2.0
#: How often the status is read in a window (what is in flight off the loop).
POLL_S = 0.25


class _Sender(threading.Thread):
    """The walk at 240 Hz under the current label set (columns mapped by name)."""

    def __init__(self, addr: tuple[str, int], walk: Any) -> None:
        super().__init__(name="bench-stalls-sender", daemon=True)
        from retargetd.protocols.marker_input import LabelSet

        self.addr = addr
        self.walk = walk
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.stop = threading.Event()
        self.label_set = LabelSet(1, tuple(walk.labels))
        self.cols = np.arange(len(walk.labels))
        self.streaming = threading.Event()
        self.sent: list[float] = []  # each frame's send time (monotonic s)

    def announce(self, label_set: Any) -> None:
        from retargetd.protocols import osc_in

        col = {name: k for k, name in enumerate(self.walk.labels)}
        self.cols = np.array([col.get(n, -1) for n in label_set.labels])
        self.label_set = label_set
        self.sock.sendto(osc_in.encode_labels(label_set), self.addr)

    def run(self) -> None:
        from retargetd.protocols import osc_in

        self.streaming.wait()
        t0, i = time.monotonic(), 0
        positions = np.asarray(self.walk.positions, dtype=np.float32)
        while not self.stop.is_set():
            cols = self.cols
            row = positions[i % len(positions)][np.maximum(cols, 0)]
            row[cols < 0] = np.nan  # a marker the walk lacks: occluded
            data = osc_in.encode_compact_frame(i, i / RATE_HZ, self.label_set.id, row)
            self.sock.sendto(data, self.addr)
            self.sent.append(time.monotonic())
            i += 1
            wait = t0 + i / RATE_HZ - time.monotonic()
            if wait > 0:
                time.sleep(wait)


class _Sub(threading.Thread):
    """Every pose message's arrival time (monotonic s) at a SUB."""

    def __init__(self, endpoint: str) -> None:
        super().__init__(name="bench-stalls-sub", daemon=True)
        self.sock = zmq.Context.instance().socket(zmq.SUB)
        self.sock.setsockopt(zmq.SUBSCRIBE, b"RTDP")  # pose data messages only
        self.sock.setsockopt(zmq.RCVHWM, 100_000)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.connect(endpoint)
        self.times: list[float] = []
        self.stop = threading.Event()

    def run(self) -> None:
        while not self.stop.is_set():
            if self.sock.poll(50):
                while True:
                    try:
                        self.sock.recv_multipart(zmq.NOBLOCK)
                    except zmq.Again:
                        break
                    self.times.append(time.monotonic())
        self.sock.close()


def one_run(tree: str | None, face: bool) -> dict[str, Any]:
    """One daemon (``tree``: its PYTHONPATH; None: this one's), the events sent."""
    old_path = os.environ.get("PYTHONPATH")
    if tree is not None:
        os.environ["PYTHONPATH"] = tree
    try:
        with tempfile.TemporaryDirectory(prefix="stalls_") as tmp_name:
            tmp = Path(tmp_name)
            calibration = fuzz.calibrate_pig(tmp)
            walk = fuzz.load_walk()
            face_npz = None
            if face:
                got = soak.face_training(walk, tmp)
                if got is not None:
                    face_npz, walk = got
            config = tmp / "stalls.toml"
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
                probe.bind((soak.LOCALHOST, 0))  # a port nobody listens on
                vmc_port = int(probe.getsockname()[1])
            config.write_text(soak._config(calibration, vmc_port, face_npz))
            daemon = soak.DaemonProcess(config, tmp)
            try:
                result = _drive(daemon, walk, calibration, face_npz is not None)
            finally:
                daemon.stop()
            if tree is None:  # (this tree's code; the daemon stopped: no contention)
                load = os.getloadavg()
                result["op_costs"] = op_costs(calibration, face_npz)
                result["op_costs"]["load"] = (load, os.getloadavg())
            return result
    finally:
        if old_path is None:
            os.environ.pop("PYTHONPATH", None)
        else:
            os.environ["PYTHONPATH"] = old_path


#: The live-calibration run: seconds from the start of streaming the static to
#: ``ctl calibrate``, and how long after it the loop is watched.
CALIBRATE_AT_S = 1.5
CALIBRATE_WINDOW_S = 4.0


def calibrate_run(tree: str | None) -> dict[str, Any]:
    """A daemon started without a calibration (the soak's config otherwise: the
    fit, the validator on, no face) is sent the PiG static at 240 Hz, then ``ctl
    calibrate``: the live calibration (``calibrate_checked`` and its file's write,
    in the loop), the stream's first pipeline (off the loop) and the first live
    validator of the process (its kernels loaded from numba's cache: in the loop
    before, off it now). The loop stalls over the window after the request, by
    phase, and the frames counted ``stale`` (left behind while the loop was busy)
    are the measure: no pose comes before a calibration to measure a gap on."""
    from retargetd.protocols.marker_input import LabelSet
    from retargetd.replay.takes import load_take

    old_path = os.environ.get("PYTHONPATH")
    if tree is not None:
        os.environ["PYTHONPATH"] = tree
    try:
        with tempfile.TemporaryDirectory(prefix="stalls_cal_") as tmp_name:
            tmp = Path(tmp_name)
            static = load_take(fuzz.PIG_STATIC)
            # its base pose (rows 0:94, as ``calibrate_pig``), held perfectly still:
            # the take's own sway fails the live stillness check (LFIN 0.13 m/s)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # (all-NaN markers)
                hold = np.nanmedian(np.asarray(static.positions)[:94], axis=0)
            still = fuzz.Walk(tuple(static.labels), hold[None], RATE_HZ)
            config = tmp / "stalls.toml"
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
                probe.bind((soak.LOCALHOST, 0))
                vmc_port = int(probe.getsockname()[1])
            live = tmp / "live_calibration.json"
            text = soak._config(live, vmc_port, None)
            text = text.replace(
                f"calibration = {json.dumps(str(live))}",
                f"save_calibration = {json.dumps(str(live))}",
            )
            config.write_text(text)
            daemon = soak.DaemonProcess(config, tmp)
            try:
                sender = _Sender(daemon.udp("osc markers"), still)
                sender.start()
                load_before = os.getloadavg()
                sender.announce(LabelSet(1, still.labels))
                sender.streaming.set()
                time.sleep(CALIBRATE_AT_S)
                before = daemon.status()
                reply = daemon.ctl({"cmd": "calibrate"}, 10_000)
                time.sleep(CALIBRATE_WINDOW_S)
                after = daemon.status()
                sender.stop.set()
                sender.join(5.0)
                load_after = os.getloadavg()
            finally:
                daemon.stop()
            lines = [  # each stall's own line: its CPU time (own work or waiting)
                ln.strip()
                for ln in daemon.log.read_text(errors="replace").splitlines()
                if "held the frame path" in ln
            ]
            ls0, ls1 = before["loop_stalls"], after["loop_stalls"]
            phases = {
                p: n - ls0["by_phase"].get(p, 0)
                for p, n in ls1["by_phase"].items()
                if n != ls0["by_phase"].get(p, 0)
            }
            return {
                "reply": (reply or {}).get("message"),
                "calibration_message": after.get("calibration_message"),
                "stalls": ls1["count"] - ls0["count"],
                "stall_phases": phases,
                "longest_ms": ls1["longest_ms"],
                "longest_phase": ls1["longest_phase"],
                "stale": after["counters"]["stale"] - before["counters"]["stale"],
                "frames_out": after["counters"]["frames_out"],
                "validating": after.get("validate") is not None,
                "stall_lines": lines,
                "load": (load_before, load_after),
            }
    finally:
        if old_path is None:
            os.environ.pop("PYTHONPATH", None)
        else:
            os.environ["PYTHONPATH"] = old_path


def _calibrate_line(tag: str, r: dict[str, Any]) -> str:
    lb, la = r["load"]
    return (
        f"{tag}: live calibration without one at the start: {r['stalls']} loop "
        f"stalls {json.dumps(r['stall_phases'])} (the run's longest "
        f"{r['longest_ms']} ms in {r['longest_phase']}), stale {r['stale']}, "
        f"frames out after it {r['frames_out']}, validating {r['validating']}; "
        f"load {lb[0]:.2f} -> {la[0]:.2f}\n  {r['calibration_message']}"
        + "".join(f"\n  {ln}" for ln in r["stall_lines"])
    )


def op_costs(calibration: Path, face_npz: Path | None, n: int = 6) -> dict[str, Any]:
    """What the loop waited for, before, per operation now moved off it (issue 30
    item 6: ``validation.py``, ``face.py``), timed here in this process (ms): a
    live validator of the run's calibration built ``n`` times (the first one in a
    process loads its kernels from numba's cache: a daemon started without a
    calibration paid it on its first live calibration), and its face training set
    written ``n`` times to a temporary folder (atomically: the write and its fsync,
    as the daemon does now; disk and load dependent)."""
    from retargetd.daemon.body.calibration import load_calibration
    from retargetd.daemon.body.rig import load_rig
    from retargetd.daemon.face.training import TrainingSet
    from retargetd.daemon.live.config_schema import ValidateSectionConfig
    from retargetd.daemon.live.validation import new_validator

    cal = load_calibration(calibration)
    rig = load_rig("plug-in-gait")
    settings = ValidateSectionConfig()
    builds = []
    for _ in range(n):
        t = time.perf_counter()
        v = new_validator(rig, cal, settings)
        builds.append((time.perf_counter() - t) * 1e3)
        v.close()
    out: dict[str, Any] = {"validator_build_ms": builds}
    if face_npz is not None:
        training = TrainingSet.load(face_npz)
        writes = []
        with tempfile.TemporaryDirectory(prefix="stalls_save_") as tmp:
            for k in range(n):
                t = time.perf_counter()
                training.save(Path(tmp) / f"face{k}.npz")
                writes.append((time.perf_counter() - t) * 1e3)
        out["face_save_ms"] = writes
    return out


def _drive(
    daemon: soak.DaemonProcess, walk: Any, calibration: Path, face: bool
) -> dict[str, Any]:
    from retargetd.protocols.marker_input import LabelSet

    sub = _Sub(daemon.endpoints["zmq poses"])
    sub.start()
    sender = _Sender(daemon.udp("osc markers"), walk)
    sender.start()
    time.sleep(0.5)  # the SUB joined
    load_before = os.getloadavg()
    t0 = time.monotonic()
    at: dict[str, float] = {}
    replies: dict[str, Any] = {}
    stalls: dict[str, int] = {}
    phases: dict[str, dict[str, int]] = {}  # stalls per phase in each window
    phases_before: dict[str, int] = {}
    in_flight: dict[str, dict[str, Any]] = {}
    counted = 0
    for k, (name, t_s) in enumerate(EVENTS):
        if name == "face" and not face:
            continue
        wait = t0 + t_s - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        at[name] = time.monotonic()
        if name == "first":
            sender.announce(sender.label_set)
            sender.streaming.set()
        elif name == "reload":
            with calibration.open("a") as fh:
                fh.write("\n")
            replies[name] = daemon.ctl({"cmd": "reload"}, 10_000)
        elif name == "labels_kept":
            sender.announce(LabelSet(2, (*walk.labels, "EXTRA")))
        elif name == "labels_moved":
            labels = tuple(walk.labels)
            sender.announce(LabelSet(3, labels[1:] + labels[:1]))
        elif name == "face":
            req = {"cmd": "face-capture", "name": "neutral", "count": 24}
            replies[name] = daemon.ctl(req, 10_000)
        # the stalls counted in this event's window (read at its end), and what
        # was in flight off the loop meanwhile
        end = at[name] + WINDOW_S
        nxt = EVENTS[k + 1][1] + t0 if k + 1 < len(EVENTS) else end
        stop = min(end, nxt - 0.05)
        seen = in_flight[name] = {"pipelines_building": 0, "validators_building": 0,
                                  "face_averaging": False, "face_saving": False,
                                  "calibration_saving": False}  # fmt: skip
        while True:
            st = daemon.status()
            for key in ("pipelines_building", "validators_building"):
                seen[key] = max(seen[key], int(st.get(key) or 0))
            seen["face_averaging"] |= bool((st.get("face") or {}).get("averaging"))
            seen["face_saving"] |= bool((st.get("face") or {}).get("saving"))
            seen["calibration_saving"] |= any(
                p.get("calibration_saving") for p in st.get("performers") or []
            )
            if time.monotonic() + POLL_S >= stop:
                break
            time.sleep(POLL_S)
        time.sleep(max(0.0, stop - time.monotonic()))
        ls = daemon.status().get("loop_stalls") or {}
        total = int(ls.get("count", 0))
        stalls[name], counted = total - counted, total
        by_phase = dict(ls.get("by_phase") or {})
        phases[name] = {
            p: n - phases_before.get(p, 0)
            for p, n in by_phase.items()
            if n != phases_before.get(p, 0)
        }
        phases_before = by_phase
    time.sleep(TAIL_S)
    status = daemon.status()
    load_after = os.getloadavg()
    sender.stop.set()
    sub.stop.set()
    sender.join(5.0)
    sub.join(5.0)
    times = np.asarray(sub.times)
    sent = np.asarray(sender.sent)
    gaps, source, window_ms = {}, {}, {}
    for name, t in at.items():
        after = np.diff(times[(times > t) & (times < t + WINDOW_S)])
        window_ms[name] = (
            (float(np.median(after) * 1e3), float(np.percentile(after, 99) * 1e3))
            if len(after)
            else (float("nan"), float("nan"))
        )
        # the sender's own longest gap in the window (the bench process not
        # scheduled: a pose gap that long is the source's, not the daemon's)
        d_sent = np.diff(sent[(sent > t - 1.0) & (sent < t + WINDOW_S)])
        source[name] = float(d_sent.max()) if len(d_sent) else float("nan")
        # from the last pose before the event to the last within the window
        inside = times[(times > t - 1.0) & (times < t + WINDOW_S)]
        if name == "first":  # from the announcement to the first pose
            later = times[times > t]
            gaps[name] = float(later[0] - t) if len(later) else float("nan")
        else:
            d = np.diff(inside)
            gaps[name] = float(d.max()) if len(d) else float("nan")
    steady = np.diff(times[times > at["first"] + 0.5]) if len(times) else np.zeros(0)
    return {
        "gaps_s": gaps,
        "source_gaps_s": source,
        "interval_ms": (
            float(np.median(steady) * 1e3),
            float(np.percentile(steady, 99) * 1e3),
        )
        if len(steady)
        else (float("nan"), float("nan")),
        "poses": len(times),
        "loop_stalls": status.get("loop_stalls"),
        "stalls_by_event": stalls,
        "stall_phases_by_event": phases,
        "interval_ms_by_event": window_ms,
        "in_flight_by_event": in_flight,
        "unsolved": status["counters"].get("unsolved"),
        "replies": {k: (v or {}).get("message") for k, v in replies.items()},
        "load": (load_before, load_after),
    }


def _line(tag: str, r: dict[str, Any]) -> str:
    def one(k: str, v: float) -> str:
        med, p99 = r["interval_ms_by_event"][k]
        flight = r["in_flight_by_event"].get(k, {})
        busy = [f"{n} {m}" for n, m in flight.items() if m]
        return (
            f"\n  {k}: longest {v * 1e3:.0f} ms, interval median {med:.2f} p99 "
            f"{p99:.2f} ms (source's longest {r['source_gaps_s'][k] * 1e3:.0f} ms); "
            f"{r['stalls_by_event'].get(k, 0)} stalls "
            f"{json.dumps(r['stall_phases_by_event'].get(k, {}))}; in flight: "
            f"{', '.join(busy) or 'nothing seen'}"
        )

    gaps = "".join(one(k, v) for k, v in r["gaps_s"].items())
    med, p99 = r["interval_ms"]
    lb, la = r["load"]
    costs = r.get("op_costs")
    if costs:  # what the loop waited for before, per operation moved off it
        lb, la = costs["load"]
        gaps += (
            "\n  off the loop now, timed in this process (ms, each): "
            + "; ".join(
                f"{k} {' '.join(f'{x:.1f}' for x in costs[k])}"
                for k in ("validator_build_ms", "face_save_ms")
                if k in costs
            )
            + f" (load {lb[0]:.2f} -> {la[0]:.2f})"
        )
    return (
        f"{tag}: after each event (2 s):{gaps}\n  whole run: pose interval median "
        f"{med:.2f} ms, p99 {p99:.2f} ms; {r['poses']} poses, unsolved {r['unsolved']};"
        f" load {lb[0]:.2f} -> {la[0]:.2f}\n  loop_stalls "
        f"{json.dumps(r['loop_stalls'])}\n  replies {r['replies']}"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", help="PYTHONPATH of the tree to compare with")
    parser.add_argument("--no-face", action="store_true", help="face off")
    parser.add_argument("--json", type=Path, help="write the figures here")
    parser.add_argument(
        "--no-calibrate", action="store_true", help="no live-calibration run"
    )
    args = parser.parse_args(argv)
    results: dict[str, Any] = {}
    if args.baseline:
        results["baseline"] = one_run(args.baseline, not args.no_face)
        print(_line("baseline", results["baseline"]), flush=True)
        if not args.no_calibrate:
            results["baseline_calibrate"] = calibrate_run(args.baseline)
            print(_calibrate_line("baseline", results["baseline_calibrate"]))
    results["this"] = one_run(None, not args.no_face)
    print(_line("this tree", results["this"]))
    if not args.no_calibrate:
        results["this_calibrate"] = calibrate_run(None)
        print(_calibrate_line("this tree", results["this_calibrate"]), flush=True)
    if args.baseline:
        b, t = results["baseline"], results["this"]
        ratios = {
            k: t["gaps_s"][k] / b["gaps_s"][k]
            for k in t["gaps_s"]
            if k in b["gaps_s"] and b["gaps_s"][k] > 0
        }
        print(
            "ratio this / baseline, longest gap per event: "
            + ", ".join(f"{k} {v:.2f}" for k, v in ratios.items())
            + f"; pose interval p99 {t['interval_ms'][1] / b['interval_ms'][1]:.2f}"
        )
    if args.json:
        args.json.write_text(json.dumps(results, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
