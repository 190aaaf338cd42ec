"""Recording inside the live daemon (``retargetd ctl record start FILE`` / ``stop``).

The loop thread never touches the disk beyond creating the file: :meth:`start` opens
``FILE`` exclusively (one ``open`` call, so a bad path or an existing file is refused
in the control reply), and everything else (the MCAP header, chunks, the summary and
footer, closing the file) happens on the :class:`~retargetd.replay.recorder.Recorder`'s
writer thread. While a recording runs, the loop hands the recorder every marker packet
it receives (raw bytes, receive time, input name and form), every pose-stream message
it publishes (unless started with ``poses = False``) and the control events
(``record_start``, ``record_stop``, calibrations, reloads), each with a
``put_nowait``: a full queue drops the item and counts it, never waits.

:meth:`stop` queues ``record_stop`` and tells the writer to finish (``Recorder.stop``:
an event, no join) and returns at once; the writer drains its queue, writes the
footer and exits on its own, and :meth:`status` reports it under ``finishing`` until
then. Daemon shutdown (:meth:`close`) stops an active recording the same way and then
waits, bounded, for every writer.

A recording started mid-stream would otherwise hold frames whose label set was
announced before it began (compact OSC and ZeroMQ announce on change; a capture system
may never repeat it). So :meth:`start` first records, per input, the label set the
daemon is using, encoded as that input's announcement and stamped with the start time:
the file is self-contained (``read_recording``, ``load_take``, ``retargetd replay``).
The format is that of ``retargetd record``: ``protocols/PROTOCOLS.md`` section 7.

Beside those, the recording carries the Foxglove channels (``/foxglove/scene``,
``/foxglove/tf``, ``/foxglove/health``; ``retargetd.replay.foxglove``): while it runs,
the loop queues a copy of each solved frame (:meth:`LiveRecording.record_skeleton`:
joint centres, bone rotations, root, flags, markers) and the writer thread places the
bones (:class:`BoneEnds`, the console's skeleton program) and encodes them, so
Foxglove shows the performer in 3D with no layout work.

A write error (full disk, read-only or vanished file system) stops the recording on the
writer thread (``Recorder.failed``; one error line in the log, from the recorder): from
then on the recorder accepts nothing, and the next :meth:`status` (the periodic stats
line, ``ctl status``) or control command ends it here, so ``record.active`` turns false
and ``record.last`` holds the error and the counts of what the file holds. The counts
(``frames``, ``poses_written``, ``events``) are what reached the file, never what was
queued: ``queued`` is what is on its way, ``dropped`` what a full queue refused,
``write_errors`` what a write error lost.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from retargetd.daemon.console.snapshot import SkeletonProgram, bone_endpoints
from retargetd.daemon.version import package_version
from retargetd.protocols.conventions import normalize_units, normalize_up_axis
from retargetd.protocols.natnet_client import parse_natnet_url
from retargetd.replay import recording as rf
from retargetd.replay.foxglove_recorder import SkeletonRecorder, open_skeleton_recorder
from retargetd.replay.recorder import (
    DEFAULT_QUEUE_SIZE,
    InputInfo,
    Recorder,
    RecorderStats,
)

logger = logging.getLogger(__name__)

#: Writer queue length (items: packets, poses, skeleton frames, health, events): ~5.7 s
#: of 240 Hz frames (three items each) before a stalled disk drops.
QUEUE_SIZE = DEFAULT_QUEUE_SIZE
#: Health samples on ``/foxglove/health`` every 0.5 s (the stats line's figures; a
#: plot is read by eye).
HEALTH_INTERVAL_NS = 500_000_000
#: Shutdown waits this long, in all, for the writers to finish their files.
CLOSE_TIMEOUT_S = 5.0
#: How often a running recording checks the folder's size and the disk's free space,
#: nanoseconds (a stat of the file and a statvfs: microseconds, once a second).
LIMIT_CHECK_NS = 1_000_000_000


def folder_mb(folder: str | Path) -> float:
    """MB of the ``*.mcap`` files under ``folder`` (recursively; 0 when missing)."""
    total = 0
    for root, _dirs, files in os.walk(folder):
        for name in files:
            if name.lower().endswith(".mcap"):
                with contextlib.suppress(OSError):  # removed while we walk
                    total += os.stat(os.path.join(root, name)).st_size
    return total / 1e6


def free_mb(folder: str | Path) -> float:
    """MB free on the disk holding ``folder`` for an unprivileged writer."""
    return shutil.disk_usage(folder).free / 1e6


class BoneEnds:
    """Both ends of every bone from a solved frame, for the recording's writer thread.

    Follows the daemon's current pipeline: :meth:`follow` (loop thread, only when
    the solver changes) swaps in the skeleton program and the calibrated bone
    lengths as one tuple; :meth:`__call__` (writer thread) reads that tuple once.

    Args:
        rig: the rig (``body.rig.Rig``) whose bones are recorded.
    """

    def __init__(self, rig: Any) -> None:
        self.rig = rig
        self._solver_id = 0
        self._state: tuple[SkeletonProgram, np.ndarray, int] | None = None

    def follow(self, solver: Any) -> None:
        """Use ``solver``'s joint names and calibration (a no-op for the same one)."""
        if id(solver) == self._solver_id:
            return
        self._solver_id = id(solver)
        program = SkeletonProgram.from_rig(self.rig, solver.joint_names)
        lengths = np.asarray(solver.calibration.bone_lengths, dtype=np.float64)
        self._state = (program, lengths, len(solver.joint_names))

    def __call__(
        self, joints: np.ndarray, quats: np.ndarray, root: np.ndarray
    ) -> np.ndarray:
        """(B, 2, 3) metres world (NaN where undetermined)."""
        state = self._state
        if state is None or joints.shape[0] != state[2]:
            return np.full((len(self.rig.bones), 2, 3), np.nan)
        program, lengths, _ = state
        return bone_endpoints(program, joints, quats, root, lengths)


@dataclass(slots=True)
class _Active:
    recorder: Recorder
    path: str
    poses: bool
    started_ns: int
    stopped: str = ""
    stopped_ns: int = 0


class LiveRecording:
    """The daemon's recording state: at most one active recording, plus the ones
    whose writers are still finishing. Used by the loop thread only.

    Attributes:
        packets: the active recorder while recording (the loop's hot-path check),
            else None.
        poses: the active recorder when it records poses, else None.
    """

    def __init__(
        self,
        folder: str | Path = "recordings",
        max_total_mb: float = 20_000.0,
        min_free_mb: float = 1024.0,
        min_interval_s: float = 1.0,
    ) -> None:
        #: ``[record]``'s limits (``config_schema.RecordConfig``).
        self.folder, self.max_total_mb = Path(folder), float(max_total_mb)
        self.min_free_mb, self.min_interval_ns = (
            float(min_free_mb),
            int(min_interval_s * 1e9),
        )
        self._last_start_ns: int | None = None
        self._next_check_ns = 0
        self._base_mb = 0.0  # MB of the folder's recordings when the last began
        self.packets: Recorder | None = None
        self.poses: Recorder | None = None
        #: The active recorder while recording (Foxglove channels), else None.
        self.skeleton: SkeletonRecorder | None = None
        self._bone_ends: BoneEnds | None = None
        self._health_ns = 0
        self._active: _Active | None = None
        self._finishing: list[_Active] = []
        self._last: dict[str, Any] | None = None
        #: The last recording, when a write error ended it (for ``stop``'s reply).
        self._failed: _Active | None = None

    @property
    def active(self) -> bool:
        """True while a recording runs."""
        return self._active is not None

    def start(
        self,
        path: str,
        poses: bool,
        inputs: tuple[InputInfo, ...],
        announcements: list[tuple[str, int, tuple[bytes, ...]]],
        force: bool = False,
        rig: Any = None,
    ) -> str:
        """Start recording to ``path`` (absolute, ``.mcap``; an existing file is
        refused unless ``force``).

        Args:
            path: the file to create.
            poses: also record the pose stream.
            force: replace an existing file (``ctl record start --force``).
            inputs: the marker inputs (stored in the file's metadata).
            announcements: (input name, form code, parts) of each input's current
                label-set announcement, recorded first.
            rig: the daemon's rig: its bones go out on the Foxglove channels
                (:meth:`record_skeleton`); None: no skeleton channels.

        Returns:
            A one-line message for the control reply.

        Raises:
            ValueError: already recording, or a bad path (the message says why).
        """
        self._end_failed()
        if self._active is not None:
            raise ValueError(f"already recording to {self._active.path}")
        now = time.monotonic_ns()
        if (
            self._last_start_ns is not None
            and now - self._last_start_ns < self.min_interval_ns
        ):
            raise ValueError(
                f"rate limited: one record start per {self.min_interval_ns / 1e9:g} s "
                "(record.min_interval_s)"
            )
        if not os.path.isabs(path):
            raise ValueError(
                f"path must be absolute (the daemon's working directory is not the "
                f"client's); got {path!r}"
            )
        if Path(path).suffix.lower() != ".mcap":
            raise ValueError(f"path must end in .mcap; got {path!r}")
        if os.path.exists(path) and not force:
            raise ValueError(f"{path} exists: record start --force replaces it")
        full = self._over_limits()
        if full:
            raise ValueError(f"record start refused: {full}")
        bone_ends = BoneEnds(rig) if rig is not None else None
        try:
            recorder = open_skeleton_recorder(
                path, inputs, software=f"retargetd {package_version()}",
                queue_size=QUEUE_SIZE, exclusive=not force, open_in_writer=True,
                bone_names=rig.bone_names if rig is not None else (),
                bone_parents=rig.bone_parent_indices() if rig is not None else (),
                bone_ends_fn=bone_ends if bone_ends is not None else _no_bones,
            )  # fmt: skip
        except OSError as exc:
            raise ValueError(
                f"cannot record to {path}: {exc.strerror or exc}"
            ) from None
        self._last_start_ns = now  # only a start that made a file counts
        self._next_check_ns = now + LIMIT_CHECK_NS
        self._active = _Active(recorder, path, poses, now)
        self._failed = None
        self.packets = recorder
        self.poses = recorder if poses else None
        self.skeleton = recorder if bone_ends is not None else None
        self._bone_ends = bone_ends
        recorder.record_event(
            "record_start", now, path=path, poses=poses,
            inputs=[i.name for i in inputs],
        )  # fmt: skip
        for name, form, parts in announcements:
            recorder.record_packet(name, form, now, *parts)
        logger.info("recording to %s (poses %s)", path, "on" if poses else "off")
        return f"recording to {path}" + ("" if poses else " (no poses)")

    def record_skeleton(
        self,
        solver: Any,
        t_ns: int,
        pose: Any,
        bone_flags: np.ndarray,
        markers: np.ndarray,
        marker_valid: np.ndarray,
    ) -> None:
        """Queue one solved frame for the Foxglove channels (copies; never blocks;
        a full queue drops and counts it). Call only while :attr:`skeleton` is set.

        Args:
            solver: the pipeline's body solver (its joint names and calibration).
            t_ns: ``time.monotonic_ns()`` of the frame.
            pose: the solve's ``BodyPose``.
            bone_flags: (B,) uint8.
            markers: (M, 3) metres world; marker_valid: (M,) bool.
        """
        rec, ends = self.skeleton, self._bone_ends
        if rec is None or ends is None:
            return
        ends.follow(solver)
        rec.record_skeleton(
            t_ns, pose.joint_centres, pose.world_from_bone_quat, pose.root_pos,
            bone_flags, markers, marker_valid,
        )  # fmt: skip

    def record_health(
        self,
        t_ns: int,
        status_fn: Any,
        occluded: int,
        validation_flags: int,
    ) -> None:
        """Queue a ``/foxglove/health`` sample when one is due (every
        :data:`HEALTH_INTERVAL_NS`; ``status_fn()``, the status document, is called
        only then). Call only while :attr:`skeleton` is set."""
        rec = self.skeleton
        if rec is None or t_ns - self._health_ns < HEALTH_INTERVAL_NS:
            return
        self._health_ns = t_ns
        rec.record_health(t_ns, health_figures(status_fn(), occluded, validation_flags))

    def _over_limits(self, active: _Active | None = None) -> str:
        """Why ``[record]``'s limits are reached (one line), else "": the folder's
        recordings at ``max_total_mb``, or the disk under ``min_free_mb`` free.
        Without ``active`` the folder is walked (at a start; its total kept); with
        it, that total plus the active file's size now (a stat and a statvfs: the
        loop thread never walks a folder while recording)."""
        with contextlib.suppress(OSError):
            self.folder.mkdir(parents=True, exist_ok=True)
        try:
            if active is None:
                used = self._base_mb = folder_mb(self.folder)
            else:
                used = self._base_mb + os.stat(active.path).st_size / 1e6
            free = free_mb(self.folder)
        except OSError as exc:
            return f"cannot measure the recordings folder {self.folder}: {exc.strerror}"
        if used >= self.max_total_mb:
            return (
                f"the recordings folder {self.folder} holds {used:.0f} MB "
                f"(record.max_total_mb = {self.max_total_mb:g})"
            )
        if free < self.min_free_mb:
            return (
                f"{free:.0f} MB free on the disk of {self.folder} "
                f"(record.min_free_mb = {self.min_free_mb:g})"
            )
        return ""

    def check_limits(self, now_ns: int) -> str:
        """Stop the active recording when the folder or the disk reached
        ``[record]``'s limits (checked at most every :data:`LIMIT_CHECK_NS`; the
        loop calls it every iteration). Returns the stop's message, else ""."""
        if self._active is None or now_ns < self._next_check_ns:
            return ""
        self._next_check_ns = now_ns + LIMIT_CHECK_NS
        full = self._over_limits(self._active)
        if not full:
            return ""
        msg = self.stop(f"limit: {full}")
        return f"recording stopped at a limit: {full}; {msg}"

    def event(self, event: str, **fields: Any) -> None:
        """Queue a control event when recording (never blocks)."""
        self._end_failed()
        if self.packets is not None:
            self.packets.record_event(event, **fields)

    def stop(self, reason: str = "ctl") -> str:
        """Stop the active recording without waiting for the writer.

        Returns:
            A one-line message for the control reply.

        Raises:
            ValueError: nothing is being recorded.
        """
        self._end_failed()
        active = self._active
        if active is None:
            failed = self._failed
            if failed is not None:
                raise ValueError(
                    f"not recording: the recording to {failed.path} stopped on a "
                    f"write error ({failed.recorder.error})"
                )
            raise ValueError("not recording")
        active.recorder.record_event("record_stop", reason=reason)
        active.recorder.stop()  # the writer finishes the file and exits on its own
        self._retire(active, reason)
        st = active.recorder.stats
        seconds = (active.stopped_ns - active.started_ns) * 1e-9
        logger.info("recording to %s stopped (%s)", active.path, reason)
        return (
            f"stopped recording {active.path} after {seconds:.2f} s; dropped "
            f"{st.dropped + st.unrecordable} so far; the file is finished in the "
            f"background"
        )

    def _retire(self, active: _Active, reason: str) -> None:
        active.stopped = reason
        active.stopped_ns = time.monotonic_ns()
        self._active = None
        self.packets = self.poses = None
        self.skeleton = None
        self._bone_ends = None
        self._finishing.append(active)

    def _end_failed(self) -> _Active | None:
        """End the active recording if a write error stopped its writer (the
        recorder logged it); returns it, else None."""
        a = self._active
        if a is None or not a.recorder.failed:
            return None
        self._retire(a, "write error")
        a.stopped_ns = a.recorder.failed_ns or a.stopped_ns  # when it failed
        self._failed = a
        return a

    def status(self) -> dict[str, Any]:
        """The ``record`` part of the status document (JSON-ready)."""
        self._end_failed()
        self._reap()
        a = self._active
        doc: dict[str, Any] = {
            "active": a is not None,
            "finishing": [f.path for f in self._finishing],
            "last": self._last,
        }
        if a is not None:
            doc.update(
                path=a.path,
                poses=a.poses,
                seconds=round((time.monotonic_ns() - a.started_ns) * 1e-9, 3),
                **_counts(a.recorder),
                error=a.recorder.error,
            )
        return doc

    def _reap(self) -> None:
        still = []
        for f in self._finishing:
            if f.recorder.finished:
                self._last = {
                    "path": f.path, "stopped": f.stopped,
                    "seconds": round((f.stopped_ns - f.started_ns) * 1e-9, 3),
                    **_counts(f.recorder), "error": f.recorder.error,
                }  # fmt: skip
            else:
                still.append(f)
        self._finishing = still

    def close(self, timeout_s: float = CLOSE_TIMEOUT_S) -> None:
        """Stop an active recording and wait (bounded, ``timeout_s`` in all) for
        every writer to finish its file. For shutdown, when the loop has stopped."""
        self._end_failed()
        if self._active is not None:
            self.stop("shutdown")
        deadline = time.monotonic() + timeout_s
        for f in self._finishing:
            f.recorder.close(max(0.0, deadline - time.monotonic()))
        self._reap()


def health_figures(
    status: dict[str, Any], occluded: int, validation_flags: int
) -> dict[str, Any]:
    """The ``/foxglove/health`` figures from the status document (JSON-ready:
    unknown latencies are None)."""
    drops = 0
    for counts in status.get("drops", {}).values():
        drops += sum(v for k, v in counts.items() if k not in ("accepted", "restart"))

    def ms(us: Any) -> float | None:
        return None if us is None else round(float(us) * 1e-3, 4)

    lat = status.get("latency_us", {})
    return {
        "input_rate_hz": float(status.get("fps_in") or 0.0),
        "drops": int(drops),
        "occluded": int(occluded),
        "validation_flags": int(validation_flags),
        "latency_p50_ms": {k: ms(v[0]) for k, v in lat.items()},
        "latency_p99_ms": {k: ms(v[1]) for k, v in lat.items()},
    }


def _no_bones(joints: np.ndarray, quats: np.ndarray, root: np.ndarray) -> np.ndarray:
    return np.zeros((0, 2, 3))


def _counts(recorder: Recorder) -> dict[str, int | float]:
    """What the file holds (``frames``, ``poses_written``, ``events``: written whole,
    counted by the writer), what is on its way (``queued``), what a full queue refused
    (``dropped_queue_full``) or the envelope cannot hold (``unrecordable``; both in
    ``dropped``), what a write error lost (``write_errors``), and the receive-time
    span of the packets in the file (``seconds_in_file``)."""
    st: RecorderStats = recorder.stats
    return {
        "frames": st.frames, "poses_written": st.poses, "events": st.events,
        "queued": recorder.queued, "dropped": st.dropped + st.unrecordable,
        "dropped_queue_full": st.dropped, "unrecordable": st.unrecordable,
        "write_errors": st.write_errors, "seconds_in_file": round(st.seconds, 3),
    }  # fmt: skip


def input_infos(config: Any, endpoints: dict[str, str]) -> tuple[InputInfo, ...]:
    """The daemon's enabled marker inputs as recording metadata."""
    out = []
    osc, zin = config.input.osc, config.input.zmq
    if osc.enabled:
        out.append(
            InputInfo(
                name="osc", form=f"osc-{osc.form}", units=normalize_units(osc.units),
                up=normalize_up_axis(osc.up),
                endpoint=endpoints.get("osc markers", "").split(" ")[0],
                labels=tuple(osc.labels) if osc.form == "simple" else (),
            )
        )  # fmt: skip
    if zin.enabled:
        out.append(
            InputInfo(
                name="zmq", form="zmq", units=normalize_units(zin.units),
                up=normalize_up_axis(zin.up),
                endpoint=endpoints.get("zmq markers", "").split(" ")[0],
            )
        )  # fmt: skip
    source = config.input.source
    if source.startswith("natnet://"):  # Motive: metres, the configured up axis
        up = parse_natnet_url(source).up_axis
        out.append(
            InputInfo(name="natnet", form="natnet", units="m", up=up, endpoint=source)
        )
    elif source.startswith("qtm://"):  # QTM: millimetres; its XML holds the axis
        out.append(
            InputInfo(name="qtm", form="qtm", units="mm", up="+Z", endpoint=source)
        )
    return tuple(out)


#: Envelope form codes of the daemon's inputs.
FORM_OSC = {"compact": rf.FORM_OSC_COMPACT, "simple": rf.FORM_OSC_SIMPLE}
FORM_ZMQ = rf.FORM_ZMQ
