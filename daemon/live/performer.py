"""One performer of the live daemon: its rig, calibration, face, VMC destination,
pipelines, live-calibration state and counters, and its view of a marker stream.

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
from retargetd.daemon.body.match import MatchWindow
from retargetd.daemon.body.rig import Rig, load_rig
from retargetd.daemon.live.config import DaemonConfig, PerformerConfig
from retargetd.daemon.live.face import LiveFace
from retargetd.daemon.live.ratelog import RateLimiter
from retargetd.daemon.live.stats import LoopStats
from retargetd.daemon.live.surface import is_loopback_host
from retargetd.protocols import pose_stream
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
    )  # fmt: skip

    def __init__(
        self, stream: MarkerStream, prefix: str, rivals: tuple[str, ...]
    ) -> None:
        self.stream = stream
        self.prefix = prefix
        self.rivals = rivals
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
        min_interval_s: the least time between two calibration requests.
    """

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
        min_interval_s: float,
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
        self.face_stages: dict[int, Any] = {}  # id(stream or view) -> FaceOnlyStage
        self.calibration: Calibration | None = (
            load_calibration(config.calibration) if config.calibration else None
        )
        self.face: LiveFace | None = (
            LiveFace(face, self.rig) if face is not None else None
        )
        self.vmc_addr = vmc_addr
        self.vmc_max_datagram = vmc_max_datagram
        # Its VMC socket (``Daemon.open``), connected to vmc_addr when the route is
        # there: send() skips sendto's per-call address parse and route lookup.
        self.vmc_sock: Any = None
        self.vmc_connected = False
        self.validator: Any = None
        self.console: Any = None
        self.pipelines: dict[int, Any] = {}  # id(stream or view) -> Pipeline
        self.labels_of: dict[int, tuple[str, ...]] = {}
        # (digest of its rig, calibration and config files, the rig, the calibration)
        # at the last reload: a reload of the same files and objects does nothing
        self.reload_files: tuple[bytes, Any, Any] | None = None
        self.views: dict[int, StreamView | None] = {}  # id(stream) -> view
        self.last_names_ns = 0
        self.frame_flags = 0
        self.next_vmc_state_ns = 0
        self.calib_target = 0
        self.calib_frames: list[np.ndarray] = []
        self.calib_labels: tuple[str, ...] = ()
        self.calib_requested_by = ""
        self.calib_times: list[tuple[float, int, int]] = []
        self.calib_last_ns = 0
        self.calib_message = ""
        # Requests so far (the ctl reply and status name the one they are about) and
        # how the last one stands: "", "pending", "rom" (the base pose held, the range
        # of motion under way), "calibrated", "not_saved" (in use,
        # its file not written), "refused", "expired".
        self.calib_id = 0
        self.calib_state = ""
        self.calib_stream: Any = None  # where the frames come from (its input)
        # A range of motion after the base pose (``ctl calibrate --rom``): seconds
        # wanted (0: none), the base pose held while it is collected, its frames.
        self.calib_rom_s = 0.0
        self.calib_base: Any = None  # (frames, labels, times_s) once still
        self.calib_rom_frames: list[np.ndarray] = []
        self.calib_rom_times: list[tuple[float, int, int]] = []
        self.calibrate_limit = RateLimiter(min_interval_s)
        self.validation_bits = 0
        # The calibration-match check over the stream's first second
        # (``body.match.MatchWindow``; ``send._check_calibration_match``) and the
        # frame flag it leaves on every later pose (``calibration_mismatch``).
        self.match_window: MatchWindow | None = None
        self.match_flags = 0
        self.validation_bones: np.ndarray | None = None
        # the latest result's values (VALIDATION_CHECKS order), for the console
        self.validation_values = np.full(len(pose_stream.VALIDATION_CHECKS), np.nan)
        self.validation_enc: pose_stream.ValidationEncoder | None = None
        self.validation_results: list[Any] = []
        # This performer's frames out, unsolved frames and latency rings (the
        # daemon's LoopStats counts every performer together).
        self.stats = LoopStats()
        # The prefixes of the performers on each input (build_performers).
        self.rivals_by_input: dict[str, tuple[str, ...]] = {}

    @property
    def label(self) -> str:
        """How messages name it: ``performer A`` (or ``the performer``)."""
        return f"performer {self.name}" if self.name else "the performer"

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


def build_performers(config: DaemonConfig) -> list[Performer]:
    """The daemon's performers: one from ``[performer]``, or one per
    ``[[performer]]`` table (index = its order in the file).

    Raises:
        ValueError: a rig, calibration or face file that cannot be used.
    """
    vmc = config.output.vmc
    min_interval_s = config.control.min_interval_s
    if not config.performers:
        face = config.face if config.face.enabled else None
        one = Performer(
            0, "", config.performer, prefix="", input="any",
            vmc_addr=(vmc.host, vmc.port),
            vmc_max_datagram=datagram_limit(
                is_loopback_host(vmc.host), vmc.max_datagram_bytes
            ),
            face=face, min_interval_s=min_interval_s,
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
                min_interval_s=min_interval_s,
            )
        )
    for perf in out:
        perf.rivals_by_input = {
            kind: tuple(q.prefix for q in out if q.input in ("any", kind))
            for kind in ("osc", "zmq", "source")
        }
    return out
