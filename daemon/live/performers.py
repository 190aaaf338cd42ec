"""The performers of the daemon, one part: one performer (``[performer]``) or one per
``[[performer]]`` table, each with its own frame path and live calibration; one
performer is the N = 1 case of many, on the same path.

A frame from an input is solved for every performer reading that input, in config
order, each from what it reads of the frame (the stream itself when every label on it
is its own, else its view: its labels, prefix stripped; see ``performer.py``), with
its own pipeline, calibration, face and VMC destination; the pose messages of all of
them go out on the one pose stream, each carrying its performer id. A live
calibration, face capture, the calibration timeout and the VMC state datagrams are
per performer; control commands name one (``"performer": NAME``, ``retargetd ctl
calibrate --performer NAME``), which may be left out when there is only one.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from retargetd.daemon.live.calibrate import LiveCalibration
from retargetd.daemon.live.face_only import FacePath
from retargetd.daemon.live.performer import FrameSource, Performer
from retargetd.daemon.live.ratelog import RateLimiter
from retargetd.daemon.live.rebuild import Build
from retargetd.daemon.live.reload import ReloadRequest, ReloadResult, read_files
from retargetd.daemon.live.send import BodyPath
from retargetd.daemon.live.shared import Shared
from retargetd.daemon.live.solve_threads import SolveThreads
from retargetd.protocols.marker_input import LabelSet, MarkerStream

logger = logging.getLogger(__name__)


class Performers:
    """Every performer and what works for it.

    Args:
        performers: the performers (``performer.build_performers``); each is given
            its VMC destination from ``shared.outputs`` (same order), its frame
            path and its live calibration here.
        shared: the loop's side (config, counters, outputs, clocks).
        kind_of: the input a stream belongs to ("osc", "zmq", "source").
        streams: the inputs' streams (what a new calibration is built on).
        config_path: the config file (``reload`` re-reads its ``[[pipeline]]``).
    """

    def __init__(
        self,
        performers: list[Performer],
        shared: Shared,
        kind_of: Callable[[object], str],
        streams: Callable[[], tuple[MarkerStream, ...]],
        config_path: str | Path | None,
    ) -> None:
        self.all = performers
        self.first = performers[0]
        self.shared = shared
        self.several = bool(shared.config.performers)  # [[performer]] tables
        self._kind_of = kind_of
        self._streams = streams
        self._config_path = config_path
        self._reload_limit = RateLimiter(shared.config.control.min_interval_s)
        min_interval_s = shared.config.control.min_interval_s
        # [loop] solve_threads > 1 with several performers: the solve threads,
        # started by start_solve_threads (the daemon's open), and the frame's
        # performers, their sources and those begun (no allocation per frame).
        self._threads: SolveThreads | None = None
        n = len(performers)
        self._due: list[Any] = [None] * n
        self._sources: list[Any] = [None] * n
        self._begun = [0] * n
        for perf, vmc in zip(performers, shared.outputs.vmc, strict=True):
            perf.vmc = vmc
            perf.path = BodyPath(perf, shared) if perf.body else FacePath(perf, shared)
            perf.calib = LiveCalibration(
                perf, shared, kind_of, self._sources_of(perf), min_interval_s
            )

    # ---- per frame -------------------------------------------------------------------

    def solve(self, stream: MarkerStream, t_ns: int) -> None:
        """Solve and send the stream's current frame for every performer on it
        (with ``[loop] solve_threads`` > 1 and two or more performers on it, their
        body solves on that many threads: :meth:`_solve_threaded`)."""
        kind = self._kind_of(stream)
        if self._threads is not None:
            due, sources, n = self._due, self._sources, 0
            for perf in self.all:
                source = perf.frame_of(stream, kind)
                if source is not None:
                    due[n], sources[n] = perf, source
                    n += 1
            if n > 1:
                self._solve_threaded(n, t_ns)
            elif n:
                self._process_counted(due[0], sources[0], t_ns)
            return
        for perf in self.all:
            source = perf.frame_of(stream, kind)
            if source is None:
                continue
            if self.several:  # each its own counters (one: the loop's are its own)
                self._process_counted(perf, source, t_ns)
            else:
                perf.path.process(source, t_ns)

    def _solve_threaded(self, n: int, t_ns: int) -> None:
        """The ``n`` performers in ``self._due`` (config order) on their frames in
        ``self._sources``: each one's begin on the loop thread; the body solves
        taken by the loop and the solve threads (``solve_threads.py``); each one
        finished on the loop thread in order. A solve that raised skips its
        performer's finish; the first such exception is raised once the others
        are finished."""
        threads = self._threads
        assert threads is not None
        due, sources, begun = self._due, self._sources, self._begun
        stats = self.shared.stats
        m = 0
        for i in range(n):  # the frames with a pipeline: begun, in order
            out, unsolved, unseen = stats.frames_out, stats.unsolved, stats.unseen
            if due[i].path.begin(sources[i], t_ns):
                begun[m] = i
                m += 1
            else:  # no pipeline: counted unsolved
                self._tally(due[i], out, unsolved, unseen)
        paths = threads.paths
        for j in range(m):
            paths[j] = due[begun[j]].path
        threads.open(m)  # the workers take solves from the end
        failed: Exception | None = None
        try:
            for j in range(m):
                perf = due[begun[j]]
                turn_ns = time.monotonic_ns()  # its budget's start (path.finish)
                if threads.take(j):  # no worker took it: the loop solves it
                    try:
                        perf.path.solve_begun()
                        exc = None
                    except Exception as raised:  # the others still go out
                        exc = raised
                else:
                    exc = threads.wait(j)
                if exc is not None:
                    if failed is None:
                        failed = exc
                    continue
                out, unsolved, unseen = stats.frames_out, stats.unsolved, stats.unseen
                perf.path.finish(sources[begun[j]], t_ns, turn_ns)
                self._tally(perf, out, unsolved, unseen)
        finally:
            threads.settle()
        if failed is not None:
            raise failed

    def _process_counted(self, perf: Performer, source: FrameSource, t_ns: int) -> None:
        """``perf.path.process``, its frame counted in ``perf.stats`` too (sent,
        with its latencies; unsolved; unseen)."""
        stats = self.shared.stats
        out, unsolved, unseen = stats.frames_out, stats.unsolved, stats.unseen
        perf.path.process(source, t_ns)
        self._tally(perf, out, unsolved, unseen)

    def _tally(self, perf: Performer, out: int, unsolved: int, unseen: int) -> None:
        """Count in ``perf.stats`` what its frame added to the loop's counters
        since they read ``out``, ``unsolved`` and ``unseen``."""
        stats = self.shared.stats
        ps = perf.stats
        if stats.frames_out != out:
            ps.frames_out += 1
            ps.record(*stats.last())
        elif stats.unsolved != unsolved:
            ps.unsolved += 1
        elif stats.unseen != unseen:
            ps.unseen += 1

    def collect(self, stream: MarkerStream) -> None:
        """Hand an accepted frame to every live calibration and face capture."""
        kind = ""
        for perf in self.all:
            calib = perf.calib
            capturing = perf.face is not None and perf.face.capturing
            if not calib.target and not capturing:  # (frames wanted: 0, per frame)
                continue
            kind = kind or self._kind_of(stream)
            source = perf.frame_of(stream, kind)
            if source is None:
                continue
            if calib.pending:
                calib.collect(source)
            if capturing:
                calib.collect_face(source)

    def restart(self, stream: MarkerStream) -> None:
        """The source of ``stream`` restarted: every pipeline on it starts over."""
        for perf in self.all:
            key = perf.key_of(stream)
            if key:
                perf.path.restart(key)

    def flag(self, bits: int) -> None:
        """Set frame flags on every performer's next pose (restarted, dropped)."""
        for perf in self.all:
            perf.path.flag(bits)

    def prepare(self, stream: MarkerStream, label_set: LabelSet) -> None:
        """A label set was taken: build every performer's column index for it now
        (off the hot path), and start building its pipeline for it off the loop
        (``rebuild.py``), so its first frames find them."""
        if stream.label_set is not label_set:
            return
        kind = self._kind_of(stream)
        for perf in self.all:
            view = perf.view_of(stream, kind)
            if view is None:
                continue
            if view.whole:
                perf.path.prepare(id(stream), label_set.labels)
            else:
                perf.path.prepare(id(view), view.labels_of(label_set))

    def prepare_streams(self) -> None:
        """At the start and after a reload (:meth:`end_reload`): :meth:`prepare`
        each input's label set (configured, or the one it took last)."""
        for stream in self._streams():
            if stream.label_set is not None:
                self.prepare(stream, stream.label_set)

    def ready(self, stream: MarkerStream) -> bool:
        """Whether the next frame of ``stream``'s label set would be solved by each
        performer's own pipeline (its build started when the set was taken, and
        done). Reads only: a test waits on it from another thread."""
        label_set = stream.label_set
        if label_set is None:
            return False
        for perf in self.all:
            view = perf.views.get(id(stream), _NOT_PREPARED)
            if view is _NOT_PREPARED:
                return False  # the label set not taken yet
            if view is None:
                continue  # not its input
            if view.whole:
                key, labels = id(stream), label_set.labels
            elif not view.prepared(label_set):
                return False  # (its layout is the loop's to build)
            else:
                key, labels = id(view), view.labels_of(label_set)
            if labels and not perf.path.ready(key, labels):
                return False
        return True

    def building(self) -> int:
        """How many pipelines (and face stages) are being built off the loop now
        (``status``: ``pipelines_building``)."""
        return sum(
            not job.done() for perf in self.all for job in perf.path.builds.values()
        )

    def done_building(self, timeout_s: float = 60.0) -> bool:
        """Wait until every pipeline build under way has ended (tests that drive
        the loop one wake-up at a time); False if ``timeout_s`` passed first."""
        deadline = time.monotonic() + timeout_s
        return all(
            perf.path.done_building(max(0.0, deadline - time.monotonic()))
            for perf in self.all
        )

    def _sources_of(self, perf: Performer) -> Callable[[], list[FrameSource]]:
        """What ``perf`` reads of each input now (where a new calibration's
        pipelines are built at once)."""

        def sources() -> list[FrameSource]:
            found: list[FrameSource] = []
            for s in self._streams():
                source = perf.frame_of(s, self._kind_of(s))
                if source is not None:
                    found.append(source)
            return found

        return sources

    # ---- per tick --------------------------------------------------------------------

    def tick_calibrations(self, now_ns: int) -> None:
        """Every loop pass: a pending calibration that collects no frame expires; a
        face training set written and a live validator built off the loop are
        taken (``face.py``, ``validation.py``)."""
        for perf in self.all:
            perf.calib.tick(now_ns)
            perf.path.tick_validator()

    def tick_sends(self, now_ns: int) -> None:
        """Every loop pass: the VMC state datagrams before a calibration, and the
        resampled output ticks now due."""
        for perf in self.all:
            perf.path.send_vmc_state(now_ns, perf.calib.pending)
        now_ns = time.monotonic_ns()
        for perf in self.all:
            perf.path.send_due_ticks(now_ns)

    def next_tick_ns(self) -> int:
        """The earliest send time of a queued output tick over every performer
        (``time.monotonic_ns()``), -1 when none is queued: the loop's poll wakes up
        for it."""
        best = -1
        for perf in self.all:
            due = perf.path.next_tick_ns()
            if due >= 0 and (best < 0 or due < best):
                best = due
        return best

    # ---- control ---------------------------------------------------------------------

    def named(self, name: object) -> Performer:
        """The performer a request names; None/"" = the only one.

        Raises:
            ValueError: an unknown name, or none given with several performers.
        """
        names = ", ".join(p.name for p in self.all if p.name)
        if name is None or name == "":
            if len(self.all) == 1:
                return self.first
            raise ValueError(
                f"this daemon has {len(self.all)} performers ({names}): name "
                "one (--performer NAME)"
            )
        if not isinstance(name, str):
            raise ValueError(f"'performer' must be a name string; got {name!r}")
        for perf in self.all:
            if perf.name and perf.name == name:
                return perf
        known = f"performers: {names}" if names else "one unnamed performer"
        raise ValueError(f"unknown performer {name!r} (this daemon has {known})")

    def calibrate(self, name: object, count: object, by: str) -> str:
        """A calibration request for the performer named (show control)."""
        perf = self.named(name)
        msg: str = perf.calib.request(count, by)
        return f"{perf.name}: {msg}" if perf.name else msg

    def announce_names(self) -> None:
        """Every performer's next pose is preceded by its names message (a
        recording of the pose stream opens with them)."""
        for perf in self.all:
            perf.path.announce_names()

    def reload(self) -> str:
        """Reload the rig file, the calibration file and the config file's
        ``[[pipeline]]`` stages from disk, waiting here for the worker that reads
        them (:meth:`begin_reload`, :meth:`end_reload`: the loop's own paths, ``ctl``,
        show control and the console, never wait; this is for tests and callers off
        the loop). Returns the outcome line.

        Raises:
            ValueError: rate limited (counted).
        """
        job = self.begin_reload()
        job.wait()
        return self.end_reload(job)

    def allow_reload(self) -> None:
        """A reload's turn (at most one per ``control.min_interval_s``).

        Raises:
            ValueError: rate limited (counted).
        """
        sh = self.shared
        if not self._reload_limit.allow(time.monotonic_ns()):
            sh.stats.rate_limited += 1
            raise ValueError(
                f"rate limited: one reload per {sh.config.control.min_interval_s:g} s"
            )

    def begin_reload(self) -> Build:
        """Start a reload: every performer's files read and checked on a worker
        thread (``reload.read_files``; at most once per ``control.min_interval_s``).
        The other config keys need a restart. Finish it with :meth:`end_reload`
        once the job is done.

        Raises:
            ValueError: rate limited (counted).
        """
        self.allow_reload()
        sh = self.shared
        requests = []
        for perf in self.all:
            last = perf.reload_files
            same = (
                last is not None and last[1] is perf.rig and last[2] is perf.calibration
            )
            requests.append(
                ReloadRequest(
                    rig_path=perf.config.rig,
                    calibration_path=perf.config.calibration,
                    rig=perf.rig,
                    calibration=perf.calibration,
                    last_digest=last[0] if same and last is not None else None,
                )
            )
        reqs = tuple(requests)
        return Build(reqs, read_files, reqs, self._config_path, sh.config, sh.target)

    def end_reload(self, job: Build) -> str:
        """Swap in what the reload ``job`` (done) read, performer by performer, or
        keep what runs and say why; returns the outcome line (one per performer
        with ``[[performer]]`` tables). A file that no longer validates keeps
        everything as it was."""
        try:
            results = job.take()
        except Exception as exc:  # a fault of ours: answered, logged, never fatal
            logger.error("reload failed", exc_info=exc)
            why = f"internal error ({type(exc).__name__}): see the daemon's log"
            results = [ReloadResult(digest=b"", error=why) for _ in self.all]
        for perf in self.all:  # a build that raised is tried again
            perf.path.failed.clear()
        msgs = [
            self._apply(perf, req, res)
            for perf, req, res in zip(self.all, job.want, results, strict=True)
        ]
        # Every stream's new pipelines start building now, as at the start: left to
        # the stream's next frame, a source that sends only once its pipeline is
        # ready (``ready``) would wait forever. A pipeline already built (or being
        # built) for the rig and calibration now starts nothing (``Pipelines.prepare``).
        self.prepare_streams()
        if len(self.all) == 1:
            return msgs[0]
        return "; ".join(f"{p.name}: {m}" for p, m in zip(self.all, msgs, strict=True))

    def _apply(self, perf: Performer, req: ReloadRequest, res: ReloadResult) -> str:
        """``perf``'s part of a reload: unchanged files (nothing parsed or rebuilt;
        parsing them took 40-70 ms, measured), refused files, or the new rig,
        calibration and stages swapped in (its pipelines rebuilt off the loop from
        :meth:`end_reload` on, the old ones solving meanwhile: ``rebuild.py``)."""
        sh = self.shared
        if res.unchanged:
            msg = f"reloaded rig {perf.rig.name}: its files and the config unchanged"
            sh.recording.event("reload", ok=True, message=msg)
            return msg
        error = res.error
        if not error and (
            perf.rig is not req.rig or perf.calibration is not req.calibration
        ):
            error = (
                "the rig or calibration changed while the files were read (a live "
                "calibration): reload again"
            )
        if error:
            msg = f"reload failed, kept the running rig and calibration: {error}"
            sh.recording.event("reload", ok=False, message=msg)
            return msg
        rig, cal, stages = res.rig, res.calibration, res.stages
        perf.rig, perf.calibration = rig, cal
        perf.reload_files = (res.digest, rig, cal)
        sh.config = dataclasses.replace(sh.config, pipeline=stages)
        # The pipelines are rebuilt for the new rig and calibration, off the loop
        # (rebuild.py, started by end_reload): the old ones solve until then.
        sh.stats.set_post_stages(())  # named again as the pipelines are rebuilt
        perf.path.start_validator()
        msg = f"reloaded rig {rig.name}" + (" and calibration" if cal else "")
        if stages:
            msg += f", pipeline {' -> '.join(str(e['kind']) for e in stages)}"
        sh.recording.event("reload", ok=True, message=msg)
        return msg

    # ---- lifecycle -------------------------------------------------------------------

    def start_solve_threads(self) -> None:
        """Start the solve threads (``[loop] solve_threads`` > 1, two or more
        ``[[performer]]`` tables; ``solve_threads.py``), at the start."""
        want = min(self.shared.config.loop.solve_threads, len(self.all))
        if self._threads is None and self.several and want > 1:
            self._threads = SolveThreads(len(self.all), want)
            self._threads.start()

    @property
    def solve_threads(self) -> SolveThreads | None:
        """The running solve threads, or None (every solve on the loop thread)."""
        return self._threads

    def start_validators(self) -> None:
        """Start every performer's live validator ([validate] on), at the start:
        built on workers, all at once, and waited for."""
        for perf in self.all:
            perf.path.start_validator()
        for perf in self.all:
            perf.path.start_validator(wait=True)

    def validators_building(self) -> int:
        """How many performers' live validators are being built off the loop now
        (``status``: ``validators_building``)."""
        return sum(perf.path.validator_building() for perf in self.all)

    def hint_uncalibrated(self) -> None:
        """Tell, once at start, how to calibrate each performer without a
        calibration."""
        out = self.shared.out
        for perf in self.all:
            if perf.calibration is not None:
                continue
            if not perf.name:
                out(
                    "no calibration loaded: streaming starts after 'retargetd ctl "
                    "calibrate' (or /VMC/Ext/Set/Calib/Exec) with the performer in "
                    "the base pose"
                )
            else:
                out(
                    f"performer {perf.name}: no calibration loaded: its streaming "
                    f"starts after 'retargetd ctl calibrate --performer {perf.name}' "
                    f'(or /rtd/calibrate "{perf.name}") with it in the base pose'
                )

    def close(self) -> None:
        """Stop every performer's live validator; finish writing its calibration
        and face training set; join the solve threads."""
        if self._threads is not None:
            self._threads.close()
        for perf in self.all:
            perf.path.close()
            perf.calib.close()
            if perf.face is not None:
                perf.face.close()

    # ---- status ----------------------------------------------------------------------

    def status(self) -> list[dict[str, Any]]:
        """``status["performers"]``: one document per performer."""
        stats = self.shared.stats
        docs = []
        for perf in self.all:
            occluded, held = perf.path.occluded_and_held()
            ps = perf.stats if self.several else stats
            docs.append(
                {
                    "id": perf.index,
                    "name": perf.name,
                    "prefix": perf.prefix,
                    "input": perf.input,
                    "rig": perf.rig.name,
                    "body": perf.body,
                    # a face alone has nothing to calibrate
                    "calibrated": perf.calibration is not None or not perf.body,
                    **perf.calib.status(),
                    "calibration_match": perf.path.match_status(),
                    "vmc": f"{perf.vmc_addr[0]}:{perf.vmc_addr[1]}",
                    "frames_out": ps.frames_out,
                    "unsolved": ps.unsolved,
                    "latency_us": {
                        k: [_round(p50), _round(p99)]
                        for k, (p50, p99) in ps.latency_us().items()
                    },
                    "occluded_markers": occluded,
                    "held_bones": held,
                    "face": perf.face.status() if perf.face is not None else None,
                    "validate": perf.path.validation_status(),
                }
            )
        return docs

    def line(self, docs: list[dict[str, Any]]) -> str:
        """The stats line's per-performer part (``[[performer]]`` tables only)."""
        if not self.several:
            return ""
        parts = []
        for d in docs:
            p99 = d["latency_us"]["receive_to_sent"][1]
            state = "" if d["calibrated"] else " NOT CALIBRATED"
            parts.append(
                f"{d['name']} out {d['frames_out']} p99 "
                f"{'-' if p99 is None else f'{p99:.0f}'} us{state}"
            )
        return " | performers " + ", ".join(parts)


#: ``Performer.views`` has no entry for a stream (no label set of it taken yet).
_NOT_PREPARED: Any = object()


def _round(value: float) -> float | None:
    return round(value, 1) if math.isfinite(value) else None
