"""At volume: every decoder under mutated and random inputs, then the same fired at a
running daemon while the real walk streams at 240 Hz (issue 12, item 6).

Part 1, in process: each input kind gets ``--inputs`` (default 1,000,000) inputs:
valid messages, bit flips, truncations, splices of two valid messages, overwrites
with boundary integers (0, -1, 2^31, 2^62 ...), insertions, deletions and random
bytes. Targets: OSC compact frames, OSC simple bundles, OSC label announcements,
ZeroMQ frames, ZeroMQ label announcements (all routed as the daemon's receive loop
routes them into a :class:`MarkerStream`), the control handler
(``Daemon.control_reply``, the JSON handler of ``daemon/live/control.py``), the
show-control parse (``parse_show_control``) and recordings (mutated MCAP files read
by ``read_recording`` and ``read_mcap_take``). Pass: no exception escapes but the
documented one (``DecodeError`` inside the decoders, counted by reason; an
``ok: false`` control reply; ``TakeError`` from the recording reader), and the
decoder's own counters add up to the inputs.

Part 2, live (``--live-seconds``): a ``retargetd run`` process on loopback (the
plug-in-gait rig, calibrated on the btkdata static), the PiG walk streamed to its OSC
input at 240 Hz, and in the middle third of the run mutated OSC datagrams, ZeroMQ
messages (any number of parts), show-control datagrams and control requests over a
real REQ socket fired at it. Printed: the pose rate before, during and after the
flood, the daemon's RSS at each point, and the accounting (datagrams sent = counted
by the daemon, per input).

Run from the repository root (the long run: ~10 min for the message decoders and
control, ~50 min for the recordings at ~3 ms a file, then the live part)::

    python bench/fuzz.py
    python bench/fuzz.py --inputs 20000 --live-seconds 15       # quick
    python bench/fuzz.py --json out.json                        # figures as JSON
    python bench/fuzz.py --targets recordings --inputs 100000 --seed 7 --live-seconds 0

Exit code 0 when every check passed, 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import struct
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

DATASETS = Path(__file__).resolve().parent.parent.parent / "shared" / "datasets"
PIG_MOTION = DATASETS / "btkdata" / "PiG_Motion-FlatFoot-Full.c3d"
PIG_STATIC = DATASETS / "btkdata" / "PiG_Calibration-FlatFoot-Full.c3d"
LOCALHOST = "127.0.0.1"
RATE_HZ = 240.0
LABEL_SET_ID = 1

#: Boundary integers written over header fields (frame numbers, counts, sizes, ids).
INTERESTING = (
    0, 1, -1, 2, 0x7F, 0x80, 0xFF, 0x7FFF, 0x8000, 0xFFFF, 2**31 - 1, 2**31,
    2**32 - 1, 2**62, 2**63 - 1, -(2**63), 5_454, 5_455, 65_507,
)  # fmt: skip


# ---- mutation ------------------------------------------------------------------------


def mutate(r: random.Random, corpus: list[bytes]) -> bytes:
    """One input from ``corpus``: valid, or mutated, or random bytes."""
    a = corpus[r.randrange(len(corpus))]
    op = r.randrange(11)
    if op == 0:
        return a
    b = bytearray(a)
    n = len(b)
    if op <= 2 and n:  # 1-8 bit flips
        for _ in range(r.randint(1, 8)):
            i = r.randrange(8 * n)
            b[i >> 3] ^= 1 << (i & 7)
    elif op == 3:  # truncation
        del b[r.randrange(n + 1) :]
    elif op == 4:  # splice of two valid messages
        c = corpus[r.randrange(len(corpus))]
        return bytes(b[: r.randrange(n + 1)]) + c[r.randrange(len(c) + 1) :]
    elif op == 5:  # random bytes
        return r.randbytes(r.randrange(2 * n + 17))
    elif op in (6, 7) and n >= 8:  # a boundary integer over an aligned field
        width = 8 if r.random() < 0.5 else 4
        at = r.randrange(0, n - width + 1, 4)
        v = INTERESTING[r.randrange(len(INTERESTING))] % (1 << (8 * width))
        b[at : at + width] = v.to_bytes(width, "big" if r.random() < 0.5 else "little")
    elif op == 8:  # insertion
        at = r.randrange(n + 1)
        b[at:at] = r.randbytes(r.choice((1, 3, 4, 8, 12, 64)))
    elif op == 9 and n:  # deletion
        at = r.randrange(n)
        del b[at : at + r.choice((1, 3, 4, 8, 12, 64))]
    else:  # repetition
        b += b[: r.randrange(n + 1)]
    return bytes(b)


def mutate_parts(r: random.Random, corpus: list[list[bytes]]) -> list[bytes]:
    """A multipart ZeroMQ message from ``corpus``: parts mutated, swapped between
    messages, dropped or added."""
    parts = list(corpus[r.randrange(len(corpus))])
    op = r.randrange(8)
    if op == 0:
        return parts
    if op == 1:  # one part count off
        return parts[:1] if r.random() < 0.5 else [*parts, r.randbytes(r.randrange(9))]
    if op == 2:  # a header from one message, a payload from another
        other = corpus[r.randrange(len(corpus))]
        return [parts[0], other[-1]]
    flat = [[p] for p in parts]
    return [mutate(r, flat[i]) if r.random() < 0.6 else p for i, p in enumerate(parts)]


# ---- the walk ------------------------------------------------------------------------


@dataclass(slots=True)
class Walk:
    """The PiG walk: labels and (T, M, 3) positions, metres, world (NaN occluded)."""

    labels: tuple[str, ...]
    positions: np.ndarray
    rate_hz: float


def load_walk() -> Walk:
    from retargetd.replay.takes import load_take

    take = load_take(PIG_MOTION)
    return Walk(tuple(take.labels), np.asarray(take.positions), float(take.rate_hz))


def _rows(walk: Walk, k: int) -> list[np.ndarray]:
    """``k`` rows of the walk, some with zeros for occluded markers and NaN gaps."""
    step = max(1, len(walk.positions) // k)
    rows = [walk.positions[i].copy() for i in range(0, step * k, step)]
    for row, fault in zip(rows, range(1, 4), strict=False):
        if fault == 1:
            row[[0, 5]] = 0.0  # zeros for occluded markers
        elif fault == 2:
            row[[3]] = np.nan
        else:
            row[[1, 2]] = row[[0, 0]]  # coincident markers
    return rows


# ---- part 1: the decoders ------------------------------------------------------------


@dataclass(slots=True)
class Tally:
    """One target's run: inputs, what its own counters say, and escaped exceptions."""

    name: str
    inputs: int = 0
    counted: int = 0
    outcomes: Counter[str] = field(default_factory=Counter)
    escaped: Counter[str] = field(default_factory=Counter)
    seconds: float = 0.0

    @property
    def ok(self) -> bool:
        return not self.escaped and self.counted == self.inputs and self.inputs > 0

    def as_dict(self) -> dict[str, Any]:
        return {
            "inputs": self.inputs, "counted": self.counted, "ok": self.ok,
            "escaped": dict(self.escaped),
            "outcomes": dict(self.outcomes.most_common()),
            "seconds": round(self.seconds, 2),
        }  # fmt: skip


def _stream_counted(stream: Any) -> int:
    """Packets a :class:`MarkerStream` has counted: every reason but
    ``unknown_label`` (markers inside kept frames), plus the announcements taken."""
    from retargetd.protocols.marker_input import UNKNOWN_LABEL

    counts = stream.counters.counts
    return int(counts.sum() - counts[UNKNOWN_LABEL]) + int(stream.labels_taken)


def _stream_outcomes(stream: Any) -> Counter[str]:
    out = Counter(stream.counters.as_dict())
    out.pop("unknown_label", None)
    if stream.labels_taken:
        out["labels_taken"] = stream.labels_taken
    return out


def feed_osc(stream: Any, data: bytes, t_ns: int, simple: bool = False) -> None:
    """One datagram into ``stream`` as ``Inputs.drain_osc`` routes it."""
    from retargetd.protocols import osc_in
    from retargetd.protocols.errors import DecodeError

    if simple:
        stream.feed(osc_in.decode_simple_bundle, data, t_ns=t_ns)
    elif len(data) >= 12 and data.startswith(b"/rtd/labels\0"):
        try:
            label_set = osc_in.decode_labels(data)
        except DecodeError as exc:
            stream.counters.add_reason(exc.reason)
            return
        stream.set_labels(label_set, t_ns)
    else:
        stream.feed(osc_in.decode_compact_frame, data, t_ns=t_ns)


def feed_zmq(stream: Any, parts: list[bytes], t_ns: int) -> None:
    """One ZeroMQ message into ``stream`` as ``Inputs.drain_zmq`` routes it."""
    from retargetd.protocols import zmq_wire
    from retargetd.protocols.errors import DecodeError

    if len(parts) != 2:
        stream.counters.add_reason("bad_length")
        return
    header, payload = parts
    if header[:4] == zmq_wire.LABELS_MAGIC:
        try:
            label_set = zmq_wire.decode_zmq_labels(header, payload, stream.max_markers)
        except DecodeError as exc:
            stream.counters.add_reason(exc.reason)
            return
        stream.set_labels(label_set, t_ns)
        return
    stream.feed(zmq_wire.decode_zmq_frame, header, payload, t_ns=t_ns)


def _run(tally: Tally, n: int, one: Callable[[int], None]) -> None:
    t0 = time.perf_counter()
    for i in range(n):
        tally.inputs += 1
        try:
            one(i)
        except Exception as exc:  # the finding: anything escaping is reported
            key = f"{type(exc).__name__}: {str(exc)[:80]}"
            tally.escaped[key] += 1
    tally.seconds = time.perf_counter() - t0


def _label_variants(labels: tuple[str, ...]) -> list[tuple[int, tuple[str, ...]]]:
    rotated = labels[1:] + labels[:1]
    return [
        (LABEL_SET_ID, labels), (LABEL_SET_ID, rotated), (2, labels),
        (LABEL_SET_ID, labels[:-1]), (3, tuple(f"M{i}" for i in range(5_455))),
    ]  # fmt: skip


def fuzz_osc(walk: Walk, n: int, seed: int, kind: str) -> Tally:
    """``kind``: ``compact`` (frames), ``labels`` (announcements and frames) or
    ``simple`` (bundles)."""
    from retargetd.protocols import osc_in
    from retargetd.protocols.marker_input import LabelSet, MarkerStream

    r = random.Random(seed)
    labels = walk.labels
    rows = _rows(walk, 8)
    simple = kind == "simple"
    stream = MarkerStream(LabelSet(LABEL_SET_ID, labels) if simple else None)
    frames: list[Any] = []
    for i, row in enumerate(rows):
        if simple:
            frames.append(osc_in.encode_simple_bundle(labels, row, frame_id=i))
            frames.append(osc_in.encode_simple_bundle(labels[:10], row[:10]))
        else:
            frames.append(
                bytearray(osc_in.encode_compact_frame(i, i / RATE_HZ, 1, row))
            )
    announce = [
        osc_in.encode_labels(LabelSet(i, ls)) for i, ls in _label_variants(labels)
    ]
    if not simple:
        stream.set_labels(LabelSet(LABEL_SET_ID, labels), 0)
    corpus = frames + announce if kind == "labels" else frames
    tally = Tally(f"osc {kind}")
    period_ns = int(1e9 / RATE_HZ)
    before = _stream_counted(stream)

    def one(i: int) -> None:
        if not simple:  # the valid frames count on, as a source's do
            for frame in frames:
                struct.pack_into(">q", frame, 20, i)
        feed_osc(stream, mutate(r, corpus), i * period_ns, simple)

    _run(tally, n, one)
    tally.counted = _stream_counted(stream) - before
    tally.outcomes = _stream_outcomes(stream)
    return tally


def fuzz_zmq(walk: Walk, n: int, seed: int, kind: str) -> Tally:
    """``kind``: ``frames`` or ``labels`` (announcements and frames)."""
    from retargetd.protocols import zmq_wire
    from retargetd.protocols.marker_input import LabelSet, MarkerStream

    r = random.Random(seed)
    labels = walk.labels
    stream = MarkerStream()
    stream.set_labels(LabelSet(LABEL_SET_ID, labels), 0)
    frames: list[list[Any]] = [
        [bytearray(h), p]
        for h, p in (
            zmq_wire.encode_zmq_frame(i, i / RATE_HZ, LABEL_SET_ID, row)
            for i, row in enumerate(_rows(walk, 8))
        )
    ]
    announce = [
        zmq_wire.encode_zmq_labels(LabelSet(i, ls)) for i, ls in _label_variants(labels)
    ]
    corpus = frames + announce if kind == "labels" else frames
    tally = Tally(f"zmq {kind}")
    period_ns = int(1e9 / RATE_HZ)
    before = _stream_counted(stream)

    def one(i: int) -> None:
        for frame in frames:  # the valid frames count on, as a source's do
            struct.pack_into("<q", frame[0], 8, i)
        feed_zmq(stream, mutate_parts(r, corpus), i * period_ns)

    _run(tally, n, one)
    tally.counted = _stream_counted(stream) - before
    tally.outcomes = _stream_outcomes(stream)
    return tally


def control_corpus() -> list[bytes]:
    """Valid and near-valid control requests (JSON bytes)."""
    reqs: list[Any] = [
        {"cmd": "status"}, {"cmd": "calibrate"}, {"cmd": "calibrate", "count": 5},
        {"cmd": "reload"}, {"cmd": "record", "action": "stop"},
        {"cmd": "record", "action": "start", "poses": False},
        {"cmd": "face-capture", "name": "smile", "count": 3},
        {"cmd": "calibrate", "count": 2**31}, {"cmd": "calibrate", "count": -5},
        {"cmd": "calibrate", "count": "x"}, {"cmd": ["status"]}, [], "status", None,
        1e308,
    ]  # fmt: skip
    # No path in what is mutated: a mutated path could name any file the user may
    # write (recordings are confined to a folder only by issue 12 item 4's check).
    out = [json.dumps(q).encode() for q in reqs]
    out += [b"[" * 1024, b"{" * 64, b'{"cmd": "status"' + b", " * 100, b"\xff\xfe"]
    return out


def fuzz_control(n: int, seed: int, daemon: Any, folder: Path) -> Tally:
    """``daemon.control_reply`` called directly with mutated requests (0-3 parts);
    every 500th request a valid ``record start`` into ``folder``."""
    r = random.Random(seed)
    corpus = control_corpus()
    start = json.dumps(
        {"cmd": "record", "action": "start", "path": str(folder / "control.mcap")}
    ).encode()
    tally = Tally("control (direct)")
    before = daemon.stats.control_requests

    def one(i: int) -> None:
        k = r.choice((1, 1, 1, 1, 1, 1, 1, 2, 3, 0))
        parts = [mutate(r, corpus) for _ in range(k)] if i % 500 else [start]
        reply = daemon.control_reply(parts)
        json.dumps(reply, allow_nan=False)  # the reply must go out as strict JSON
        if not isinstance(reply, dict) or type(reply.get("ok")) is not bool:
            raise AssertionError(f"not a control reply: {reply!r}")
        if not reply["ok"] and not isinstance(reply.get("error"), str):
            raise AssertionError(f"error reply without an error: {reply!r}")
        tally.outcomes["ok" if reply["ok"] else "error"] += 1
        if daemon.recording.status()["active"]:  # one at a time
            daemon.recording.stop("fuzz")

    _run(tally, n, one)
    tally.counted = daemon.stats.control_requests - before
    return tally


def fuzz_control_req(n: int, seed: int, daemon: Any, folder: Path) -> Tally:
    """The same requests as :func:`fuzz_control`, over a real REQ socket to
    ``daemon`` serving in a thread: every request answered with strict JSON, and
    the daemon's ``control_requests`` counts them all."""
    import zmq

    r = random.Random(seed)
    corpus = control_corpus()
    tally = Tally("control (REQ)")
    stop = threading.Event()
    errors: list[BaseException] = []

    def serve() -> None:
        try:
            daemon.run(stop.is_set)
        except BaseException as exc:  # reported as escaped below
            errors.append(exc)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    ctx = zmq.Context()
    req = ctx.socket(zmq.REQ)
    req.setsockopt(zmq.LINGER, 0)
    req.setsockopt(zmq.RCVTIMEO, 5000)
    req.connect(daemon.endpoints["control"].split()[0])
    before = daemon.stats.control_requests
    try:

        def one(_i: int) -> None:
            k = r.choice((1, 1, 1, 1, 1, 1, 1, 2, 3))
            req.send_multipart([mutate(r, corpus) for _ in range(k)])
            reply = json.loads(req.recv(), parse_constant=_no_constant)
            if not isinstance(reply, dict) or type(reply.get("ok")) is not bool:
                raise AssertionError(f"not a control reply: {reply!r}")
            tally.outcomes["ok" if reply["ok"] else "error"] += 1

        _run(tally, n, one)
    finally:
        stop.set()
        thread.join(timeout=10.0)
        req.close()
        ctx.term()
        if daemon.recording.status()["active"]:
            daemon.recording.stop("fuzz")
    for exc in errors:
        tally.escaped[f"daemon loop: {type(exc).__name__}: {exc}"] += 1
    tally.counted = daemon.stats.control_requests - before
    return tally


def _no_constant(name: str) -> Any:
    raise ValueError(f"not strict JSON: {name}")


def show_control_corpus() -> list[bytes]:
    from retargetd.protocols.osc_wire import build_bundle, build_message

    msgs = [
        build_message("/VMC/Ext/Set/Calib/Ready", "", []),
        build_message("/VMC/Ext/Set/Calib/Exec", "", []),
        build_message("/rtd/calibrate", ",i", [5]),
        build_message("/rtd/calibrate", ",s", ["x"]),
        build_message("/rtd/reload", "", []),
        build_message("/VMC/Ext/OK", ",i", [1]),
    ]
    return [*msgs, build_bundle(msgs[:3]), build_bundle([build_bundle(msgs[3:])])]


def fuzz_show_control(n: int, seed: int) -> Tally:
    from retargetd.daemon.live.control import parse_show_control

    r = random.Random(seed)
    corpus = show_control_corpus()
    tally = Tally("show control")

    def one(_i: int) -> None:
        parsed = parse_show_control(mutate(r, corpus))
        outcome = parsed.refused or ("malformed" if parsed.malformed else "good")
        tally.outcomes[outcome] += 1
        tally.counted += 1
        for address, args in parsed.messages:
            if not isinstance(address, str) or not isinstance(args, list):
                raise AssertionError(f"bad parse {address!r} {args!r}")

    _run(tally, n, one)
    return tally


def recording_bytes(walk: Walk, folder: Path) -> bytes:
    """A small valid recording: labels, 24 compact frames, 2 ZeroMQ frames, an event."""
    from retargetd.protocols import osc_in, zmq_wire
    from retargetd.protocols.marker_input import LabelSet
    from retargetd.replay import recording as rf
    from retargetd.replay.recorder import InputInfo, open_recorder

    path = folder / "seed.mcap"
    inputs = (
        InputInfo(name="osc", form="osc-compact"),
        InputInfo(name="zmq", form="zmq"),
    )
    rec = open_recorder(path, inputs, chunk_size=2048)
    t0 = time.monotonic_ns()
    ls = LabelSet(LABEL_SET_ID, walk.labels)
    rec.record_packet("osc", rf.FORM_OSC_COMPACT, t0, osc_in.encode_labels(ls))
    for i, row in enumerate(_rows(walk, 24)):
        frame = osc_in.encode_compact_frame(i, i / RATE_HZ, LABEL_SET_ID, row)
        rec.record_packet("osc", rf.FORM_OSC_COMPACT, t0 + i * 4_166_667, frame)
    rec.record_packet("zmq", rf.FORM_ZMQ, t0, *zmq_wire.encode_zmq_labels(ls))
    for i, row in enumerate(_rows(walk, 2)):
        parts = zmq_wire.encode_zmq_frame(i, math.nan, LABEL_SET_ID, row)
        rec.record_packet("zmq", rf.FORM_ZMQ, t0 + i, *parts)
    rec.record_event("calibrate", count=5, by="fuzz")
    rec.close()
    return path.read_bytes()


def fuzz_recordings(walk: Walk, n: int, seed: int, folder: Path) -> Tally:
    """Mutated MCAP files through ``read_recording`` and ``read_mcap_take``."""
    import logging

    from retargetd.replay.recording import read_mcap_take, read_recording
    from retargetd.replay.take import TakeError

    logging.getLogger("retargetd.replay.recording").setLevel(logging.ERROR)
    r = random.Random(seed)
    seed_file = recording_bytes(walk, folder)
    corpus = [seed_file, seed_file[: len(seed_file) // 2]]
    path = folder / "fuzz.mcap"
    tally = Tally("recordings")

    def one(_i: int) -> None:
        path.write_bytes(mutate(r, corpus))
        try:
            rec = read_recording(path)
        except TakeError:
            tally.outcomes["TakeError"] += 1
            tally.counted += 1
            return
        tally.outcomes["complete" if rec.complete else "partial"] += 1
        tally.counted += 1
        try:
            take = read_mcap_take(path)
        except TakeError:
            tally.outcomes["take: TakeError"] += 1
            return
        tally.outcomes[f"take: {take.n_frames > 0}"] += 1

    _run(tally, n, one)
    return tally


def in_process_daemon(calibration: Path, folder: Path) -> Any:
    """An opened (not running) daemon: the plug-in-gait rig, every endpoint ephemeral
    on loopback, VMC off; working directory ``folder`` (recordings land there)."""
    from retargetd.daemon.live.config import DaemonConfig
    from retargetd.daemon.live.loop import Daemon

    doc = {
        "performer": {"rig": "plug-in-gait", "calibration": str(calibration)},
        "input": {"osc": {"port": 0}, "zmq": {"endpoint": "tcp://127.0.0.1:*"}},
        "output": {
            "vmc": {"enabled": False},
            "pose": {"endpoint": "tcp://127.0.0.1:*"},
        },
        "control": {"endpoint": "tcp://127.0.0.1:*"},
        "show_control": {"port": 0},
    }
    os.chdir(folder)
    daemon = Daemon(DaemonConfig.from_dict(doc, source="fuzz"), out=lambda _s: None)
    daemon.open()
    return daemon


def calibrate_pig(folder: Path) -> Path:
    """``retargetd calibrate`` of the plug-in-gait rig on the btkdata static."""
    from retargetd.daemon.cli.main import main

    out = folder / "pig_calibration.json"
    argv = ["calibrate", str(PIG_STATIC), "--rig", "plug-in-gait", "--out", str(out)]
    if main(argv) != 0:
        raise RuntimeError("calibration of the PiG static failed")
    return out


TARGETS = (
    "osc-compact", "osc-simple", "osc-labels", "zmq-frames", "zmq-labels",
    "show-control", "recordings", "control", "control-req",
)  # fmt: skip


def fuzz_decoders(
    n: int,
    seed: int,
    folder: Path,
    calibration: Path,
    targets: tuple[str, ...] = TARGETS,
    n_recordings: int | None = None,
) -> list[Tally]:
    """Part 1: every target, ``n`` inputs each (``n_recordings`` for recordings)."""
    walk = load_walk()
    runs: dict[str, Callable[[], Tally]] = {
        "osc-compact": lambda: fuzz_osc(walk, n, seed, "compact"),
        "osc-simple": lambda: fuzz_osc(walk, n, seed + 1, "simple"),
        "osc-labels": lambda: fuzz_osc(walk, n, seed + 2, "labels"),
        "zmq-frames": lambda: fuzz_zmq(walk, n, seed + 3, "frames"),
        "zmq-labels": lambda: fuzz_zmq(walk, n, seed + 4, "labels"),
        "show-control": lambda: fuzz_show_control(n, seed + 5),
        "recordings": lambda: fuzz_recordings(
            walk, n if n_recordings is None else n_recordings, seed + 6, folder
        ),
    }
    tallies = []
    for name in targets:
        if name in ("control", "control-req"):
            cwd = os.getcwd()
            daemon = in_process_daemon(calibration, folder)
            try:
                if name == "control":
                    tallies.append(fuzz_control(n, seed + 7, daemon, folder))
                else:
                    tallies.append(fuzz_control_req(n, seed + 8, daemon, folder))
            finally:
                daemon.close()
                os.chdir(cwd)
        else:
            tallies.append(runs[name]())
        print_tallies(tallies[-1:], header=len(tallies) == 1)
        sys.stdout.flush()
    return tallies


def print_tallies(tallies: list[Tally], header: bool = True) -> None:
    if header:
        head = f"{'target':<18} {'inputs':>9} {'counted':>9} {'escaped':>8}"
        print(f"{head} {'s':>7}  outcomes")
    for t in tallies:
        top = ", ".join(f"{k} {v}" for k, v in t.outcomes.most_common(6))
        print(
            f"{t.name:<18} {t.inputs:>9,} {t.counted:>9,} {sum(t.escaped.values()):>8}"
            f" {t.seconds:>7.1f}  {top}"
        )
        for key, count in t.escaped.most_common(5):
            print(f"    ESCAPED x{count}: {key}")


# ---- part 2: at a running daemon -----------------------------------------------------


def fuzz_live(
    seconds: float, flood_hz: float, seed: int, labels: bool = True
) -> dict[str, Any]:
    """The walk at 240 Hz, clean, to a daemon; the middle third of the run a flood of
    mutated inputs at ``flood_hz`` on each of OSC, ZeroMQ and show control (control
    requests over a REQ socket at a tenth of that); ``labels``: label announcements
    among the mutated marker inputs."""
    import soak

    faults = soak.Faults(
        malformed=0.0, dropout=0.0, restart_every_s=1e9, spoof_every_s=1e9,
        flood_hz=flood_hz, flood_window=(1 / 3, 2 / 3), flood_labels=labels,
    )  # fmt: skip
    return soak.run(seconds, faults, face=False, record=False, seed=seed)


def print_live(result: dict[str, Any], flood_hz: float) -> None:
    a = result["accounting"]
    print(
        f"\nlive: {result['seconds']:.0f} s, walk at 240 Hz over OSC; flood "
        f"{flood_hz:.0f}/s each on OSC, ZeroMQ, show control (+ control REQ) in the "
        f"middle third; load {result['load_before']} -> {result['load_after']}"
    )
    print(f"pose rate Hz: {result['pose_rate_phases']}")
    print(f"RSS MB: {result['rss_phases_mb']} (growth after warm-up "
          f"{result['rss_mb']['growth']:.2f})")  # fmt: skip
    print(
        f"osc sent {a['osc_sent']} = counted {a['osc_counted']} + kernel "
        f"{a['osc_kernel_drops']}: {a['osc_ok']}; zmq sent {a['zmq_sent']} = counted "
        f"{a['zmq_counted']}: {a['zmq_ok']} (disconnects {a['zmq_disconnects']}); show "
        f"sent {a['show_sent']} = counted {a['show_counted']} + kernel "
        f"{a['show_kernel_drops']}: {a['show_ok']}; control {result['control_sent']} "
        f"sent, {result['control_replies']} answered"
    )
    print(
        f"frames in {a['frames_in']} = solved {a['frames_solved']} + stale "
        f"{a['stale']} + unsolved {a['unsolved']}: {a['frames_ok']}; alive "
        f"{result['alive']}, exit {result['rc']}"
    )
    print(f"drops by reason: {a['drops']}")
    print(f"zmq drops by reason: {a['zmq_drops']}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--inputs", type=int, default=1_000_000, help="per target")
    parser.add_argument(
        "--recording-inputs", type=int, help="for recordings (default: --inputs)"
    )
    parser.add_argument(
        "--targets",
        default=",".join(TARGETS),
        help="comma-separated: " + ", ".join(TARGETS),
    )
    parser.add_argument("--live-seconds", type=float, default=60.0, help="0: skip")
    parser.add_argument("--flood-hz", type=float, default=1000.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--no-flood-labels", action="store_true",
        help="no label announcements among the flood's marker inputs",
    )  # fmt: skip
    parser.add_argument("--json", type=Path, help="write the figures here")
    args = parser.parse_args(argv)
    targets = tuple(t for t in args.targets.split(",") if t)
    if args.inputs < 0 or args.live_seconds < 0 or args.flood_hz <= 0:
        parser.error("--inputs, --live-seconds >= 0 and --flood-hz > 0")
    if any(t not in TARGETS for t in targets):
        parser.error(f"--targets: choose from {', '.join(TARGETS)}")
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    print(f"fuzz: {args.inputs:,} inputs per target, seed {args.seed}; load {load}")
    doc: dict[str, Any] = {}
    ok = True
    if args.inputs:
        with tempfile.TemporaryDirectory(prefix="fuzz_") as tmp_name:
            tmp = Path(tmp_name)
            calibration = calibrate_pig(tmp)
            tallies = fuzz_decoders(
                args.inputs, args.seed, tmp, calibration, targets,
                args.recording_inputs,
            )  # fmt: skip
        doc["decoders"] = {t.name: t.as_dict() for t in tallies}
        ok = all(t.ok for t in tallies)
    if args.live_seconds:
        result = fuzz_live(
            args.live_seconds, args.flood_hz, args.seed, not args.no_flood_labels
        )
        print_live(result, args.flood_hz)
        doc["live"] = result
        p = result["pass"]  # RSS is printed: a flood's buffers raise it once
        ok = ok and p["up"] and p["accounting"]
        ok = ok and result["pose_rate_phases"].get("during", 0.0) > 0.0
    if args.json:
        args.json.write_text(json.dumps(doc, indent=1, default=str))
    print("pass" if ok else "FAIL")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
