"""``[loop] solve_threads`` (daemon/live/solve_threads.py): several performers' body
solves spread over threads. The same frames give the same pose messages, byte for
byte but their clock stamps, in the same order, with the same counters, as with
every solve on the loop thread; a performer whose solve raises leaves the others'
frames sent; the daemon's close joins the threads."""

from __future__ import annotations

import gc
import sys
import threading
import time
import tracemalloc
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import live_harness as lh
import numpy as np
import pytest
from live_harness import EXACT_RIG, WAIT_S, _take

from retargetd.daemon.live.config import DaemonConfig
from retargetd.daemon.live.loop import Daemon
from retargetd.daemon.live.solve_threads import SolveThreads
from retargetd.protocols import osc_in, pose_stream
from retargetd.protocols.marker_input import LabelSet

pytestmark = pytest.mark.timeout(180)

NAMES = ("A", "B", "C")
#: Performer k stands k times this far along world +X (metres).
SPACING = np.array([2.0, 0.0, 0.0])
FRAMES = range(100, 160)


def _daemon(calibration: Path, solve_threads: int, method: str) -> Daemon:
    doc = lh._ephemeral_doc(lh._unused_udp_port())
    doc["performer"] = [
        {"name": n, "rig": str(EXACT_RIG), "calibration": str(calibration),
         "vmc": f"127.0.0.1:{lh._unused_udp_port()}"}
        for n in NAMES
    ]  # fmt: skip
    doc["solve"] = {"method": method}
    doc["loop"] = {"solve_threads": solve_threads}
    return Daemon(DaemonConfig.from_dict(doc, source="test"), out=lambda _line: None)


def _packet(take: Any, row: int, hide: int = -1) -> bytes:
    """Row ``row`` of the take for every performer (performer ``hide``'s markers
    all NaN), as one OSC compact frame."""
    parts = [take.markers_world[row] + k * SPACING for k in range(len(NAMES))]
    if hide >= 0:
        parts[hide] = np.full_like(parts[hide], np.nan)
    packet: bytes = osc_in.encode_compact_frame(
        row, row / 100, 1, np.concatenate(parts)
    )
    return packet


class _Sent:
    """The pose stream's messages as the daemon hands them to its PUB socket:
    (magic, frame id, flags, performer, every part after the header), the clock
    stamps left out, and the clock's one flag (``FRAME_LATE``: solve and send over
    ``solve_budget_ms``, which a loaded machine decides frame by frame)."""

    def __init__(self) -> None:
        self.messages: list[tuple[Any, ...]] = []

    def __call__(self, parts: list[Any], t_ns: int) -> None:
        head = bytes(parts[0])
        if head[:4] == pose_stream.DATA_MAGIC:
            fields = pose_stream.HEADER.unpack_from(head)
            frame_id, flags = fields[3], fields[8] & ~pose_stream.FRAME_LATE
            key: tuple[Any, ...] = (head[:4], frame_id, flags, head[50])
            key += (head[pose_stream.HEADER.size :],)
        else:
            key = (head,)
        self.messages.append(key + tuple(bytes(p) for p in parts[1:]))


def _take_labels(d: Daemon, take: Any) -> Any:
    """``d``'s OSC stream, announced the three performers' labels of ``take``, their
    pipelines built."""
    stream = d.osc_stream
    labels = tuple(f"{n}:{label}" for n in NAMES for label in take.labels)
    label_set = LabelSet(1, labels)
    stream.set_labels(label_set)
    d.performers.prepare(stream, label_set)
    assert d.performers.done_building(60.0), "the pipelines were never built"
    return stream


def _hold_for_the_worker(d: Daemon) -> None:
    """Make the loop's first solve of each frame (performer A's) wait until a worker
    has solved the last one (C's, the first a worker takes), so every frame has a
    solve on a worker whatever the machine's scheduling."""
    a, c = d.performers.all[0].path, d.performers.all[-1].path
    solve_a, solve_c = a.solve_begun, c.solve_begun
    solved = threading.Event()

    def first() -> None:
        if not solved.wait(WAIT_S):
            raise AssertionError("no worker took C's solve")
        solved.clear()
        solve_a()

    def last() -> None:
        solve_c()
        solved.set()

    a.solve_begun = first  # type: ignore[method-assign]
    c.solve_begun = last  # type: ignore[method-assign]


def _run(
    calibration: Path, solve_threads: int, method: str, hide: int = -1
) -> tuple[_Sent, dict[str, Any], Daemon]:
    """Feed FRAMES (performer ``hide``'s markers all NaN on every 5th frame: unseen)
    to a daemon of three performers and solve each; closed on return. With solve
    threads, C's solve always on a worker (:func:`_hold_for_the_worker`)."""
    take = _take()
    d = _daemon(calibration, solve_threads, method)
    sent = _Sent()
    d.outputs.send_pub = sent  # type: ignore[method-assign]
    try:
        d.open()
        if solve_threads > 1:
            _hold_for_the_worker(d)
        stream = _take_labels(d, take)
        for row in FRAMES:
            packet = _packet(take, row, hide if row % 5 == 0 else -1)
            t_ns = time.monotonic_ns()
            stream.feed(osc_in.decode_compact_frame, packet, t_ns=t_ns)
            d.performers.solve(stream, t_ns)
        status = d.status()
    finally:
        d.close()
    return sent, status, d


@pytest.mark.parametrize("method", ["fit", "construction"])
def test_threads_send_the_serial_poses_in_the_serial_order(
    exact_calibration: Path, method: str
) -> None:
    serial, s1, d1 = _run(exact_calibration, 1, method, hide=1)
    threaded, s2, d2 = _run(exact_calibration, 2, method, hide=1)
    assert d1.performers.solve_threads is None
    threads = d2.performers.solve_threads
    assert threads is not None and threads.n_threads == 2
    assert threads.solves >= len(FRAMES)  # C's at least, every frame
    assert s2["solve_threads"] == {  # ctl status --json
        "threads": 2,
        "alive": 1,
        "worker_solves": threads.solves,
    }
    assert s1["solve_threads"] == {"threads": 1, "alive": 0, "worker_solves": 0}
    assert threaded.messages == serial.messages  # bytes, order, frame ids, flags
    data = [m for m in threaded.messages if m[0] == pose_stream.DATA_MAGIC]
    assert [m[3] for m in data if m[1] == FRAMES[1]] == [0, 1, 2]  # config order
    keys = ("frames_in", "frames_out", "frames_solved", "unsolved", "unseen")
    c1, c2 = s1["counters"], s2["counters"]
    assert {k: c2[k] for k in keys} == {k: c1[k] for k in keys}
    per = [(p["frames_out"], p["unsolved"]) for p in s2["performers"]]
    assert per == [(p["frames_out"], p["unsolved"]) for p in s1["performers"]]
    if method == "fit":  # B's markers all hidden: unseen, no pose (the construction
        # holds the last pose, flagged)
        unseen = len(FRAMES) // 5
        assert len(data) == 3 * len(FRAMES) - unseen and c2["unseen"] == unseen
        assert [m[3] for m in data if m[1] == FRAMES[0]] == [0, 2]
        assert per[1][0] == len(FRAMES) - unseen


@pytest.fixture
def threaded(exact_calibration: Path) -> Iterator[tuple[Daemon, Any, list[Any]]]:
    """An open three-performer daemon with a solve thread, its stream taking the
    three performers' labels, and one frame's packet per call of ``feed``."""
    take = _take()
    d = _daemon(exact_calibration, 2, "construction")
    try:
        d.open()
        stream = _take_labels(d, take)
        rows = iter(FRAMES)

        def feed() -> int:
            row = next(rows)
            packet = _packet(take, row)
            t_ns = time.monotonic_ns()
            stream.feed(osc_in.decode_compact_frame, packet, t_ns=t_ns)
            return t_ns

        yield d, stream, [feed]
    finally:
        d.close()


class _Boom(RuntimeError):
    pass


@pytest.mark.parametrize("broken", [0, 1])  # the loop's own solve; the worker's
def test_a_solve_that_raises_leaves_the_others_sent(
    threaded: tuple[Daemon, Any, list[Any]],
    monkeypatch: pytest.MonkeyPatch,
    broken: int,
) -> None:
    d, stream, (feed,) = threaded
    d.performers.solve(stream, feed())  # the built pipelines taken
    perfs = d.performers.all
    victim = next(iter(perfs[broken].path.pipelines.values()))

    def boom(*_args: Any) -> Any:
        raise _Boom(f"performer {broken}")

    out0 = [p.stats.frames_out for p in perfs]
    with monkeypatch.context() as m:
        m.setattr(victim.solver, "solve_frame", boom)
        t_ns = feed()
        with pytest.raises(_Boom, match=f"performer {broken}"):
            d.performers.solve(stream, t_ns)
    got = [p.stats.frames_out - n for p, n in zip(perfs, out0, strict=True)]
    assert got == [int(k != broken) for k in range(len(NAMES))]
    threads = d.performers.solve_threads
    assert threads is not None and threads.alive() == 1
    t_ns = feed()  # the next frame: every performer again, the worker still serving
    d.performers.solve(stream, t_ns)
    got = [p.stats.frames_out - n for p, n in zip(perfs, out0, strict=True)]
    assert got == [1 + int(k != broken) for k in range(len(NAMES))]


def test_close_joins_the_solve_thread(
    threaded: tuple[Daemon, Any, list[Any]],
) -> None:
    d, stream, (feed,) = threaded
    threads = d.performers.solve_threads
    assert threads is not None
    d.performers.solve(stream, feed())
    workers = [w.thread for w in threads.workers]
    assert len(workers) == 1 and workers[0].is_alive()
    assert workers[0] in threading.enumerate()
    d.close()
    assert not workers[0].is_alive() and threads.alive() == 0
    d.close()  # idempotent


def test_one_performer_or_one_thread_starts_no_thread(exact_calibration: Path) -> None:
    doc = lh._ephemeral_doc(lh._unused_udp_port())
    doc["performer"] = {"rig": str(EXACT_RIG), "calibration": str(exact_calibration)}
    doc["loop"] = {"solve_threads": 4}
    d = Daemon(DaemonConfig.from_dict(doc, source="test"), out=lambda _line: None)
    try:
        d.open()
        assert d.performers.solve_threads is None  # one [performer]: nothing to share
    finally:
        d.close()
    d = _daemon(exact_calibration, 1, "construction")
    try:
        d.open()
        assert d.performers.solve_threads is None
    finally:
        d.close()
    d = _daemon(exact_calibration, 8, "construction")  # at most one per performer
    try:
        d.open()
        threads = d.performers.solve_threads
        assert threads is not None and threads.n_threads == len(NAMES)
        assert threads.alive() == len(NAMES) - 1
    finally:
        d.close()


class _Path:
    """A frame path stand-in: its solve records the thread it ran on."""

    def __init__(self, fail: bool = False) -> None:
        self.fail = fail
        self.threads: list[int] = []

    def solve_begun(self) -> None:
        self.threads.append(threading.get_ident())
        if self.fail:
            raise _Boom("solve")


def test_the_loop_and_a_worker_take_each_solve_once() -> None:
    t = SolveThreads(4, 2)  # the loop and one worker
    t.start()
    try:
        me = threading.get_ident()
        for frame in range(3):
            paths = [_Path(), _Path(fail=True), _Path(), _Path()]
            t.paths[:4] = paths
            t.open(4)
            # the loop takes solve 0 at once; it waits for the worker's 3, 2, 1
            # (taken from the end) rather than taking them
            assert t.take(0)
            paths[0].solve_begun()
            assert t.wait(3) is None and t.wait(2) is None
            assert isinstance(t.wait(1), _Boom)
            t.settle()
            assert [len(p.threads) for p in paths] == [1, 1, 1, 1]  # each once
            assert paths[0].threads == [me]
            assert all(p.threads[0] != me for p in paths[1:])
            assert t.solves == 3 * (frame + 1)
        # a frame the loop takes whole (the worker not scheduled yet: it takes
        # only what is open when it runs): nothing solved twice, nothing waited
        paths = [_Path(), _Path()]
        t.paths[:2] = paths
        t.open(2)
        took = [t.take(j) for j in range(2)]
        for j, mine in enumerate(took):
            if mine:
                paths[j].solve_begun()
            else:
                assert t.wait(j) is None
        t.settle()
        assert [len(p.threads) for p in paths] == [1, 1]
        # a frame left early (a finish raised): settle waits for a worker's solve
        # and takes the rest, solved by nobody
        paths = [_Path(), _Path(), _Path()]
        t.paths[:3] = paths
        t.open(3)
        assert t.take(0)
        t.settle()
        assert len(paths[0].threads) == 0 and sum(len(p.threads) for p in paths) <= 2
        assert not any(lock.acquire(False) for lock in t.claim)  # nothing left open
    finally:
        t.close()
    assert t.alive() == 0


def _frame_peaks(calibration: Path, solve_threads: int) -> float:
    """The median over 60 frames (after 40 of warm-up) of the memory a frame's
    ``Performers.solve`` holds above its start at its peak, every thread's."""
    take = _take()
    d = _daemon(calibration, solve_threads, "fit")
    try:
        d.open()
        stream = _take_labels(d, take)
        packets = [_packet(take, row) for row in range(100, 200)]
        peaks = []
        for k, packet in enumerate(packets):
            t_ns = time.monotonic_ns()
            stream.feed(osc_in.decode_compact_frame, packet, t_ns=t_ns)
            if k == 40:
                gc.collect()
                tracemalloc.start()
            if k >= 40:
                base = tracemalloc.get_traced_memory()[0]
                tracemalloc.reset_peak()
            d.performers.solve(stream, t_ns)
            if k >= 40:
                peaks.append(tracemalloc.get_traced_memory()[1] - base)
        tracemalloc.stop()
        return float(np.median(peaks))
    finally:
        d.close()


def test_threads_allocate_no_more_per_frame_than_the_loop_alone(
    exact_calibration: Path,
) -> None:
    """What the threaded path adds per frame is its loops' ``range`` objects and
    their iterators (five on the loop thread, one on the worker), each freed at
    once; the tables and locks are made once. Measured here on a loaded 2-core VM:
    3465 B against 3609 B serial (the kernels' own argument boxing, the bulk of it,
    spread over two threads)."""
    serial = _frame_peaks(exact_calibration, 1)
    threaded = _frame_peaks(exact_calibration, 2)
    ranges = 6 * (sys.getsizeof(range(4)) + sys.getsizeof(iter(range(4))))
    print(f"\nper frame, peak above its start: serial {serial:.0f} B, threads "
          f"{threaded:.0f} B (allowed {serial + ranges:.0f})")  # fmt: skip
    assert threaded <= serial + ranges
