"""One performer of the live daemon: its rig, calibration, face, VMC destination and
counters, its view of a marker stream, and the parts that work for it: its frame path
(``send.BodyPath``, or ``face_only.FacePath`` for a face alone) and its live
calibration (``calibrate.LiveCalibration``), each owning its own state.

With no ``[[performer]]`` in the config the daemon has one performer (``[performer]``)
that takes every marker of every input, and its "view" of a stream is the stream
itself: nothing is copied. With ``[[performer]]`` tables each performer owns the
labels that start with its ``prefix`` (``"A:LASI"``; the longest matching prefix
wins, ``""`` takes those no other prefix claims) on its ``input``: a
:class:`StreamView` holds, per label set, the column index of those labels and a
frame of its own, built when the label set is announced (off the hot path); per
frame it copies its rows into it (two slice copies when its labels are one run, the
usual case, else two ``take(..., out=)`` calls), no array allocated.
The solve, calibration and face see the view exactly as they see a stream:
``current.frame`` and ``current.label_set`` (the labels with the prefix stripped).
"""

from __future__ import annotations

import logging
from dataclasses import replace
from typing import Any, Protocol

import numpy as np

from retargetd.daemon.body.calibration import Calibration, load_calibration
from retargetd.daemon.body.rig import Rig, load_rig
from retargetd.daemon.live.config import DaemonConfig, PerformerConfig
from retargetd.daemon.live.face import LiveFace
from retargetd.daemon.live.outputs import VmcOut
from retargetd.daemon.live.stats import LoopStats
from retargetd.daemon.live.surface import is_loopback_host
from retargetd.protocols.frames import IntArray, MarkerFrame
from retargetd.protocols.marker_input import LabelSet, MarkerStream
from retargetd.protocols.vmc_out import datagram_limit

logger = logging.getLogger(__name__)

#: Label sets whose column index a view keeps (a sender alternating between a few
#: sets finds each built; more are rebuilt when they come back).
_LAYOUTS_KEPT = 8


class PacketLike(Protocol):
    """A stream's current packet as the solve reads it."""

    @property
    def frame(self) -> MarkerFrame: ...

    @property
    def label_set(self) -> LabelSet: ...


class FrameSource(Protocol):
    """What the solve, calibration and face read: a :class:`MarkerStream` or a
    performer's :class:`StreamView` of one."""

    @property
    def current(self) -> PacketLike: ...


class FramePath(Protocol):
    """A performer's frame path (``send.BodyPath``, ``face_only.FacePath``): what
    the loop and the other parts call on it."""

    pipelines: dict[int, Any]
    builds: dict[int, Any]  # its next pipelines (or stages), built off the loop
    # the streams whose last build raised -> what it was for (a reload clears it)
    failed: dict[int, Any]

    @property
    def validator(self) -> Any: ...  # its running live validator, or None

    def process(self, stream: FrameSource, received_ns: int) -> None: ...

    # process() in three steps (send.BodyPath): only solve_begun() may run on
    # another thread, between the loop's begin() and finish() of the same frame.
    def begin(self, stream: FrameSource, received_ns: int) -> bool: ...

    def solve_begun(self) -> None: ...

    def finish(
        self, stream: FrameSource, received_ns: int, turn_ns: int = 0
    ) -> None: ...

    def flag(self, bits: int) -> None: ...

    def announce_names(self) -> None: ...

    def match_status(self) -> dict[str, Any] | None: ...

    def resend_held(self, key: int, now_ns: int) -> tuple[bool, bool]: ...

    def warm_up(self) -> None: ...

    def restart(self, key: int) -> None: ...

    def prepare(self, key: int, labels: tuple[str, ...]) -> None: ...

    def ready(self, key: int, labels: tuple[str, ...]) -> bool: ...

    def done_building(self, timeout_s: float) -> bool: ...

    def rebuild(self, labels: tuple[str, ...], sources: list[FrameSource]) -> None: ...

    def renew(self, labels: tuple[str, ...], sources: list[FrameSource]) -> None: ...

    def send_due_ticks(self, now_ns: int) -> None: ...

    def next_tick_ns(self) -> int: ...

    def send_vmc_state(self, now_ns: int, calibrating: bool) -> None: ...

    def start_validator(self, wait: bool = False) -> None: ...

    def tick_validator(self) -> None: ...

    def validator_building(self) -> bool: ...

    def validation_status(self) -> dict[str, Any] | None: ...

    def close(self) -> None: ...

    def occluded_and_held(self) -> tuple[list[str], list[str]]: ...


class Calibrating(Protocol):
    """A performer's live calibration (``calibrate.LiveCalibration``): what the
    loop and the other parts call on it."""

    id: int  # the last request's id
    target: int  # frames still wanted (0: nothing pending)

    @property
    def pending(self) -> bool: ...

    def status(self) -> dict[str, Any]: ...

    def request(
        self, count: object = None, by: str = "", rom_s: object = None
    ) -> str: ...

    def request_face(
        self, name: str, count: int | None = None, by: str = ""
    ) -> str: ...

    def tick(self, now_ns: int) -> None: ...

    def collect(self, stream: FrameSource) -> None: ...

    def collect_face(self, stream: FrameSource) -> None: ...

    def close(self) -> None: ...  # its file's write under way finished


class _NoPath:
    """The path of a performer before ``Performers`` gives it one."""

    pipelines: dict[int, Any] = {}  # noqa: RUF012 (never written)
    builds: dict[int, Any] = {}  # noqa: RUF012 (never written)
    failed: dict[int, Any] = {}  # noqa: RUF012 (never written)
    validator: Any = None

    def process(self, stream: FrameSource, received_ns: int) -> None:
        raise RuntimeError("a performer without its frame path")

    def begin(self, stream: FrameSource, received_ns: int) -> bool:
        raise RuntimeError("a performer without its frame path")

    def solve_begun(self) -> None:
        raise RuntimeError("a performer without its frame path")

    def finish(self, stream: FrameSource, received_ns: int, turn_ns: int = 0) -> None:
        raise RuntimeError("a performer without its frame path")

    def flag(self, bits: int) -> None:
        pass

    def announce_names(self) -> None:
        pass

    def match_status(self) -> dict[str, Any] | None:
        return None

    def resend_held(self, key: int, now_ns: int) -> tuple[bool, bool]:
        return False, False

    def warm_up(self) -> None:
        pass

    def restart(self, key: int) -> None:
        pass

    def prepare(self, key: int, labels: tuple[str, ...]) -> None:
        pass

    def ready(self, key: int, labels: tuple[str, ...]) -> bool:
        return True

    def done_building(self, timeout_s: float) -> bool:
        return True

    def rebuild(self, labels: tuple[str, ...], sources: list[FrameSource]) -> None:
        pass

    def renew(self, labels: tuple[str, ...], sources: list[FrameSource]) -> None:
        pass

    def send_due_ticks(self, now_ns: int) -> None:
        pass

    def next_tick_ns(self) -> int:
        return -1

    def send_vmc_state(self, now_ns: int, calibrating: bool) -> None:
        pass

    def start_validator(self, wait: bool = False) -> None:
        pass

    def tick_validator(self) -> None:
        pass

    def validator_building(self) -> bool:
        return False

    def validation_status(self) -> dict[str, Any] | None:
        return None

    def close(self) -> None:
        pass

    def occluded_and_held(self) -> tuple[list[str], list[str]]:
        return [], []


_NO_PATH = _NoPath()


class ViewPacket:
    """What the solve reads of a stream's current packet: ``frame`` and
    ``label_set`` (this performer's rows and names)."""

    __slots__ = ("frame", "label_set")

    def __init__(self, frame: MarkerFrame, label_set: LabelSet) -> None:
        self.frame = frame
        self.label_set = label_set


class StreamView:
    """One performer's columns of one marker stream.

    Args:
        stream: the input's stream.
        prefix: this performer's label prefix.
        rivals: the prefixes of every performer reading this input (this one's
            included): a label belongs to the longest one it starts with.
    """

    __slots__ = (
        "_layouts", "_source", "cols", "current", "prefix", "rivals", "rows", "stream",
        "whole",
    )  # fmt: skip

    def __init__(
        self, stream: MarkerStream, prefix: str, rivals: tuple[str, ...]
    ) -> None:
        self.stream = stream
        self.prefix = prefix
        self.rivals = rivals
        # Every label of the stream is this performer's, as it is (one performer,
        # no prefix): it reads the stream itself, nothing copied.
        self.whole = prefix == "" and all(r == "" for r in rivals)
        self.current = ViewPacket(MarkerFrame.empty(0), LabelSet(-1, ()))
        self.cols: IntArray = np.zeros(0, dtype=np.intp)
        # The same rows as a slice when they are one run (a subject's markers sent
        # together, the usual case): a slice copy is ~4x cheaper than a take.
        self.rows: slice | None = None
        self._source: LabelSet | None = None
        self._layouts: dict[
            int, tuple[LabelSet, IntArray, slice | None, ViewPacket]
        ] = {}

    def owns(self, label: str) -> bool:
        """Whether ``label`` is this performer's (the longest matching prefix)."""
        if not label.startswith(self.prefix) or len(label) == len(self.prefix):
            return False
        n = len(self.prefix)
        return not any(
            len(r) > n and label.startswith(r) for r in self.rivals
        )  # fmt: skip

    def prepare(self, source: LabelSet) -> None:
        """Build the column index and frame for ``source`` (off the hot path: when
        the label set is announced, or the first frame that carries it)."""
        if id(source) in self._layouts:
            return
        cols = [i for i, name in enumerate(source.labels) if self.owns(name)]
        n = len(self.prefix)
        labels = LabelSet(source.id, tuple(source.labels[i][n:] for i in cols))
        if len(self._layouts) >= _LAYOUTS_KEPT:
            self._layouts.clear()
        index = np.array(cols, dtype=np.intp)
        run = bool(cols) and cols[-1] - cols[0] == len(cols) - 1
        rows = slice(cols[0], cols[-1] + 1) if run else None
        self._layouts[id(source)] = (
            source, index, rows, ViewPacket(MarkerFrame.empty(len(cols)), labels)
        )  # fmt: skip

    def prepared(self, source: LabelSet) -> bool:
        """Whether the layout of ``source`` is built (reads only)."""
        return id(source) in self._layouts

    def labels_of(self, source: LabelSet) -> tuple[str, ...]:
        """This performer's labels of ``source`` (prefix stripped; its layout built
        now, off the hot path)."""
        self.prepare(source)
        return self._layouts[id(source)][3].label_set.labels

    def refresh(self) -> bool:
        """Copy this performer's rows of the stream's current frame into
        ``current.frame`` (no allocation); False when the frame has none of them."""
        src = self.stream.current
        if src.label_set is not self._source:
            source = src.label_set
            self.prepare(source)
            _, self.cols, self.rows, self.current = self._layouts[id(source)]
            self._source = source
        cols = self.cols
        if not len(cols):
            return False
        f, out = src.frame, self.current.frame
        rows = self.rows
        if rows is not None:
            out.markers_world[:] = f.markers_world[rows]
            out.valid[:] = f.valid[rows]
        else:  # the method (np.take's wrapper costs ~1 us more); mode "clip": the
            # indices are valid, and "raise" buffers ``out`` (a copy per call)
            f.markers_world.take(cols, axis=0, out=out.markers_world, mode="clip")
            f.valid.take(cols, out=out.valid, mode="clip")
        out.frame_id = f.frame_id
        out.t_ns = f.t_ns
        out.source_time_s = f.source_time_s
        return True


class Performer:
    """Everything of one performer the loop keeps (the loop thread only).

    Args:
        index: its id in the pose stream (byte 50 of the data header) and status.
        name: its name ("" for the single performer of a config without
            ``[[performer]]``).
        config: its ``[performer]`` / ``[[performer]]`` keys.
        prefix: its label prefix ("" with one performer: every label).
        input: "any", "osc", "zmq" or "source".
        vmc_addr: its VMC destination (host, port).
        vmc_max_datagram: the largest VMC datagram sent to it, bytes
            (``vmc_out.datagram_limit``).
        face: its ``[face]`` settings, or None for no face.
    """

    #: Its live calibration (``calibrate.LiveCalibration``), given by ``Performers``
    #: right after it is built.
    calib: Calibrating

    def __init__(
        self,
        index: int,
        name: str,
        config: PerformerConfig,
        *,
        prefix: str,
        input: str,
        vmc_addr: tuple[str, int],
        vmc_max_datagram: int,
        face: Any,
    ) -> None:
        self.index = index
        self.name = name
        self.config = config
        self.prefix = prefix
        self.input = input
        self.rig: Rig = load_rig(config.rig)
        # False: a face alone (``face_only.py``): no rig calibration, no body solve.
        self.body = config.body
        if not self.body and face is None:
            raise ValueError(
                f"{self.label}: body = false needs a face ([face] enabled = true"
                f"{' and its face key' if name else ''})"
            )
        self.calibration: Calibration | None = (
            load_calibration(config.calibration) if config.calibration else None
        )
        self.face: LiveFace | None = (
            LiveFace(face, self.rig) if face is not None else None
        )
        self.vmc_addr = vmc_addr
        self.vmc_max_datagram = vmc_max_datagram
        # Its VMC destination (``outputs.VmcOut``): its socket, opened by the loop;
        # ``Performers`` gives it the loop's counters.
        self.vmc = VmcOut(vmc_addr, vmc_max_datagram, None)
        self.console: Any = None  # live.console_feed.ConsoleFeed (the first's)
        self.views: dict[int, StreamView | None] = {}  # id(stream) -> view
        # (digest of its rig, calibration and config files, the rig, the calibration)
        # at the last reload: a reload of the same files and objects does nothing
        self.reload_files: tuple[bytes, Any, Any] | None = None
        # This performer's frames out, unsolved frames and latency rings (the
        # daemon's LoopStats counts every performer together).
        self.stats = LoopStats()
        # The prefixes of the performers on each input (build_performers).
        self.rivals_by_input: dict[str, tuple[str, ...]] = {}
        # Its frame path and live calibration (``performers.Performers`` makes
        # them: ``send.BodyPath`` or ``face_only.FacePath``, and
        # ``calibrate.LiveCalibration``).
        self.path: FramePath = _NO_PATH

    def use_calibration(
        self,
        calibration: Calibration | None,
        labels: tuple[str, ...],
        sources: list[FrameSource],
    ) -> None:
        """Swap ``calibration`` in (atomically: the loop thread is the only reader):
        each stream's new body solver built off the loop from now (``rebuild.py``),
        its old pipeline solving meanwhile, a stream of the ``sources`` carrying
        ``labels`` without one getting it now; the live validator restarted on it."""
        self.calibration = calibration
        self.path.renew(labels, sources)
        self.path.start_validator()

    def use_face(self, labels: tuple[str, ...], sources: list[FrameSource]) -> None:
        """Its face has a new training set: the pipelines of the ``sources``
        carrying ``labels`` built with it off the loop from now (``rebuild.py``),
        the old ones solving meanwhile."""
        self.path.rebuild(labels, sources)

    @property
    def label(self) -> str:
        """How messages name it: ``performer A`` (or ``the performer``)."""
        return f"performer {self.name}" if self.name else "the performer"

    def frame_of(self, stream: MarkerStream, kind: str) -> FrameSource | None:
        """What this performer reads of ``stream``'s current frame: the stream
        itself when every label on it is this performer's (one performer), else its
        view with its rows copied in; None when the input (``kind``) is not its own
        or the frame carries none of its markers."""
        view = self.views.get(id(stream), _UNSEEN)  # one lookup per frame
        if view is _UNSEEN:
            view = self.view_of(stream, kind)
        if view is None:
            return None
        if view.whole:
            return stream
        return view if view.refresh() else None

    def key_of(self, stream: MarkerStream) -> int:
        """The key of this performer's pipeline on ``stream`` (``id`` of what
        :meth:`frame_of` returns), 0 when it has not read that stream."""
        view = self.views.get(id(stream))
        if view is None:
            return 0
        return id(stream) if view.whole else id(view)

    def view_of(self, stream: MarkerStream, kind: str) -> StreamView | None:
        """Its view of ``stream`` (input ``kind``: "osc", "zmq" or "source"), or
        None when that input is not its own. Built once per stream."""
        key = id(stream)
        if key in self.views:
            return self.views[key]
        view = None
        if self.input in ("any", kind):
            rivals = self.rivals_by_input.get(kind, (self.prefix,))
            view = StreamView(stream, self.prefix, rivals)
        self.views[key] = view
        return view


#: ``Performer.views`` has no entry for a stream yet (None: not its input).
_UNSEEN: Any = object()


def build_performers(config: DaemonConfig) -> list[Performer]:
    """The daemon's performers: one from ``[performer]``, or one per
    ``[[performer]]`` table (index = its order in the file).

    Raises:
        ValueError: a rig, calibration or face file that cannot be used.
    """
    vmc = config.output.vmc
    if not config.performers:
        face = config.face if config.face.enabled else None
        one = Performer(
            0, "", config.performer, prefix="", input="any",
            vmc_addr=(vmc.host, vmc.port),
            vmc_max_datagram=datagram_limit(
                is_loopback_host(vmc.host), vmc.max_datagram_bytes
            ),
            face=face,
        )  # fmt: skip
        return [one]
    out = []
    for i, p in enumerate(config.performers):
        face = None
        if config.face.enabled and p.face:
            face = replace(
                config.face, config=p.face, training=p.face_training, save_training=""
            )
        host, port = (vmc.host, vmc.port)
        if p.vmc:
            host, _, port_s = p.vmc.rpartition(":")
            port = int(port_s)
        out.append(
            Performer(
                i,
                p.name,
                p,
                prefix=p.prefix,
                input=p.input,
                vmc_addr=(host, port),
                vmc_max_datagram=datagram_limit(
                    is_loopback_host(host), vmc.max_datagram_bytes
                ),
                face=face,
            )
        )
    for perf in out:
        perf.rivals_by_input = {
            kind: tuple(q.prefix for q in out if q.input in ("any", kind))
            for kind in ("osc", "zmq", "source")
        }
    return out
