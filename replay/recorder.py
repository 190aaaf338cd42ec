"""Recording to MCAP on a thread of its own: the live loop never waits for the disk.

The producer (the live loop, or ``retargetd record``) calls
:meth:`Recorder.record_packet`, :meth:`~Recorder.record_pose` or
:meth:`~Recorder.record_event`. Each copies its arguments into a tuple and does a
``put_nowait`` on a bounded queue; when the queue is full the item is dropped and
counted (``RecorderStats.dropped``), never waited for.
The writer thread classifies each packet by its header (frame, labels, other), wraps
it in the envelope (``retargetd.replay.recording``), tracks label sets and writes
MCAP. Layout: ``protocols/PROTOCOLS.md``, "Recordings (MCAP)".

Crash safety: chunks are small and closed every ``flush_interval_s`` (0.25 s): the
writer finishes the chunk in progress and hands it to the kernel, so a recorder killed
at any moment leaves a file whose data section is whole up to the last flush; only the
footer and summary (indexes, statistics) are missing, and
:func:`~retargetd.replay.recording.read_recording` reads it. The file is written with
``os.write`` (no user-space buffer, :class:`RecordingFile`), so what a flush wrote has
reached the kernel; ``fsync`` is not called: a killed process loses nothing that reached
the kernel, a power cut may lose more.

Truthful counts: :class:`RecorderStats` counts what reached the file, not what was
queued. A message is counted when the chunk holding it has been written whole (with its
message indexes); until then it is pending. A write error of any kind (a full disk, a
read-only or vanished file system, any ``OSError`` on the writer thread) stops the
recording at once: the file is cut back (``ftruncate``) to the end of the last whole
chunk, so it ends on a record boundary and holds exactly the counted messages; the
pending messages and whatever was still queued are counted in ``write_errors``;
:attr:`Recorder.error` says what failed and one error line is logged; nothing more is
accepted (``record_*`` return False).
"""

from __future__ import annotations

import errno
import json
import logging
import os
import queue
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Protocol

from retargetd.protocols import osc_in, zmq_wire
from retargetd.protocols.errors import DecodeError
from retargetd.replay import recording as rf

logger = logging.getLogger(__name__)

#: Queue length: ~34 s of 120 Hz packets; a stalled disk drops beyond it.
DEFAULT_QUEUE_SIZE = 4096
DEFAULT_FLUSH_INTERVAL_S = 0.25
#: The longest flush interval allowed: a killed recorder may lose at most 1 s (issue
#: 12's requirement for crash loss), so the file is made crash-readable at least once
#: a second.
MAX_FLUSH_INTERVAL_S = 1.0
#: Chunks close at this size even between flushes (bytes, uncompressed).
DEFAULT_CHUNK_SIZE = 256 * 1024

_LABELS_SCHEMA = {
    "title": "retargetd.label_set",
    "type": "object",
    "properties": {
        "input": {"type": "string"},
        "form": {"type": "string"},
        "t_ns": {"type": "integer"},
        "label_set_id": {"type": "integer"},
        "labels": {"type": "array", "items": {"type": "string"}},
    },
    "required": ["input", "form", "t_ns", "label_set_id", "labels"],
}
_CONTROL_SCHEMA = {
    "title": "retargetd.control_event",
    "type": "object",
    "properties": {"event": {"type": "string"}, "t_ns": {"type": "integer"}},
    "required": ["event", "t_ns"],
}

# Queue item tags.
_PACKET, _POSE, _EVENT = 0, 1, 2


@dataclass(frozen=True, slots=True, kw_only=True)
class InputInfo:
    """A recorded marker input, stored in the recording's metadata.

    Attributes:
        name: the input's name, as in the envelope (``"osc"``, ``"zmq"``).
        form: ``"osc-compact"``, ``"osc-simple"`` or ``"zmq"``.
        units: the sender's declared length unit (used to load the take).
        up: the sender's declared up axis.
        endpoint: where it listened (for people).
        labels: configured labels (simple form), or empty.
    """

    name: str
    form: str
    units: str = "m"
    up: str = "+Z"
    endpoint: str = ""
    labels: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.form not in rf.FORM_CODES or self.form == "pose-stream":
            raise ValueError(
                f"form must be osc-compact, osc-simple or zmq; got {self.form!r}"
            )

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {
            "name": self.name, "form": self.form, "units": self.units, "up": self.up,
            "endpoint": self.endpoint, "labels": list(self.labels),
        }  # fmt: skip


@dataclass(slots=True)
class RecorderStats:
    """What reached the file (counted on the writer thread once the chunk holding it was
    written whole), what was lost to a write error, and what was dropped on the
    producer side (``dropped`` when the queue was full, ``unrecordable`` for a ZeroMQ
    message of more than 255 parts, which the envelope cannot hold).

    Attributes:
        write_errors: items accepted into the queue but not in the file because a write
            failed (those of the chunk being written, and those still queued).
        accepted: items the producer queued (producer side).
    """

    frames: int = 0
    label_packets: int = 0
    other_packets: int = 0
    label_sets: int = 0
    poses: int = 0
    events: int = 0
    dropped: int = 0
    unrecordable: int = 0
    write_errors: int = 0
    accepted: int = 0
    first_t_ns: int = 0
    last_t_ns: int = 0
    per_input: dict[str, int] = field(default_factory=dict)

    @property
    def seconds(self) -> float:
        """Receive time from the first to the last recorded packet."""
        return max(0, self.last_t_ns - self.first_t_ns) * 1e-9

    @property
    def items_written(self) -> int:
        """Queue items (packets, poses, events) in the file."""
        return sum((self.frames, self.label_packets, self.other_packets, self.poses,
                    self.events))  # fmt: skip

    def add(self, other: RecorderStats) -> None:
        """Add ``other``'s written counts (a committed chunk) to these."""
        self.frames += other.frames
        self.label_packets += other.label_packets
        self.other_packets += other.other_packets
        self.label_sets += other.label_sets
        self.poses += other.poses
        self.events += other.events
        if other.first_t_ns:
            self.first_t_ns = min(self.first_t_ns or other.first_t_ns, other.first_t_ns)
        self.last_t_ns = max(self.last_t_ns, other.last_t_ns)
        for name, n in other.per_input.items():
            self.per_input[name] = self.per_input.get(name, 0) + n


class Sink(Protocol):
    """The writer thread's side (an MCAP file, or a fake in tests)."""

    def write(self, item: tuple[Any, ...]) -> None:
        """Write one queue item."""

    def flush(self) -> None:
        """Make what was written so far readable after a crash."""

    def close(self) -> None:
        """Finish the file (footer, summary) and close it."""

    def abort(self) -> int:
        """After a write error: cut the file back to what is counted, close it and
        return how many written-but-uncounted items were lost."""


class RecordingFile:
    """The recording's file descriptor at the OS boundary: every :meth:`write` goes
    straight to ``os.write`` (looping over short writes), so :attr:`position` is the
    number of bytes the kernel accepted, and a full disk raises ``OSError`` here, in
    the call that wrote the data, never later in a buffer flush.

    Args:
        fd: a file descriptor open for writing (closed by :meth:`close`).
        name: the path, for messages.
    """

    def __init__(self, fd: int, name: str = "") -> None:
        self.fd = fd
        self.name = name
        self.position = 0
        self._closed = False

    def write(self, data: Any) -> int:
        """Write all of ``data`` (bytes-like); raises OSError on failure."""
        view = memoryview(data).cast("B")
        done = 0
        while done < len(view):
            n = os.write(self.fd, view[done:])
            if n <= 0:  # a regular file never does this; be safe rather than spin
                raise OSError(errno.EIO, f"os.write wrote {n} bytes")
            done += n
            self.position += n
        return done

    def tell(self) -> int:
        """Bytes written so far (the mcap writer's offsets)."""
        return self.position

    def flush(self) -> None:
        """Nothing is buffered here."""

    def truncate(self, size: int) -> None:
        """Cut the file to ``size`` bytes (shrinking needs no free space)."""
        os.ftruncate(self.fd, size)
        self.position = size

    def close(self) -> None:
        """Close the descriptor (idempotent)."""
        if not self._closed:
            self._closed = True
            os.close(self.fd)


class McapSink:
    """Writes queue items as MCAP (channels and schemas in PROTOCOLS.md).

    Counts go to a pending :class:`RecorderStats` and move to ``stats`` when the
    chunk holding them has been written whole (a chunk closed by size inside
    ``add_message``, or by :meth:`flush`).

    Args:
        out: the file (closed by :meth:`close` or :meth:`abort`).
        inputs: the marker inputs, stored in the metadata record.
        stats: counters to update.
        mono_anchor_ns / wall_anchor_ns: the same instant on ``time.monotonic_ns()``
            and ``time.time_ns()``: log_time = wall_anchor + (t_ns - mono_anchor).
        software: written to the metadata (``"retargetd 0.1.0"``).
        chunk_size: uncompressed bytes at which a chunk closes between flushes.
    """

    def __init__(
        self,
        out: RecordingFile,
        inputs: tuple[InputInfo, ...],
        stats: RecorderStats,
        *,
        mono_anchor_ns: int,
        wall_anchor_ns: int,
        software: str = "",
        chunk_size: int = DEFAULT_CHUNK_SIZE,
    ) -> None:
        from mcap.writer import CompressionType, Writer

        self._out = out
        self._stats = stats
        self._pending = RecorderStats()
        self._committed_pos = 0
        self._offset_ns = wall_anchor_ns - mono_anchor_ns
        self._writer = Writer(
            out,  # type: ignore[arg-type]  # write/tell/flush is all it uses
            chunk_size=chunk_size,
            compression=CompressionType.ZSTD,
        )
        w = self._writer
        w.start(profile=rf.PROFILE, library=software or "retargetd")
        doc = {"spec": "protocols/PROTOCOLS.md, Recordings (MCAP)"}
        envelope_meta = {**doc, "version": str(rf.FORMAT_VERSION)}
        self._raw = w.register_channel(
            rf.RAW_TOPIC, rf.PACKET_ENCODING, 0, envelope_meta
        )
        labels_schema = w.register_schema(
            "retargetd.label_set", "jsonschema", json.dumps(_LABELS_SCHEMA).encode()
        )
        self._labels = w.register_channel(rf.LABELS_TOPIC, "json", labels_schema, doc)
        self._poses = w.register_channel(
            rf.POSES_TOPIC, rf.PACKET_ENCODING, 0, envelope_meta
        )
        control_schema = w.register_schema(
            "retargetd.control_event",
            "jsonschema",
            json.dumps(_CONTROL_SCHEMA).encode(),
        )
        self._control = w.register_channel(
            rf.CONTROL_TOPIC, "json", control_schema, doc
        )
        w.add_metadata(
            rf.METADATA_NAME,
            {
                "version": str(rf.FORMAT_VERSION),
                "software": software,
                "monotonic_anchor_ns": str(mono_anchor_ns),
                "wall_anchor_ns": str(wall_anchor_ns),
                "inputs": json.dumps([i.as_dict() for i in inputs]),
            },
        )
        self._seq = [0] * 5
        self._forms = {i.name: rf.FORM_CODES[i.form] for i in inputs}
        # Per input: (label-set id, labels) last written to /markers/labels.
        self._label_sets: dict[str, tuple[int, tuple[str, ...]]] = {}
        for i in inputs:
            if i.labels:
                self._write_labels(i.name, mono_anchor_ns, 0, i.labels)
        self.flush()

    def _add(self, channel: int, t_ns: int, data: bytes) -> None:
        # The caller counts the message in self._pending first: a chunk closed by
        # size inside add_message holds it.
        log_time = t_ns + self._offset_ns
        self._seq[channel] += 1
        self._writer.add_message(
            channel, log_time, data, log_time, sequence=self._seq[channel]
        )
        if self._out.position != self._committed_pos:
            self._commit()

    def _commit(self) -> None:
        """Everything pending is in the file: count it."""
        self._stats.add(self._pending)
        self._pending = RecorderStats()
        self._committed_pos = self._out.position

    @property
    def pending_items(self) -> int:
        """Queue items written to the chunk in progress, not yet in the file."""
        return self._pending.items_written

    def _write_labels(
        self, name: str, t_ns: int, set_id: int, labels: tuple[str, ...]
    ) -> None:
        self._label_sets[name] = (set_id, labels)
        form = rf.FORM_NAMES.get(self._forms.get(name, 0), "")
        msg = {
            "input": name, "form": form, "t_ns": t_ns, "label_set_id": set_id,
            "labels": list(labels),
        }  # fmt: skip
        self._pending.label_sets += 1
        self._add(self._labels, t_ns, json.dumps(msg).encode())

    def write(self, item: tuple[Any, ...]) -> None:
        """Write one queue item (see :class:`Recorder`)."""
        tag, t_ns = item[0], item[1]
        st = self._pending
        if tag == _EVENT:
            st.events += 1
            self._add(self._control, t_ns, json.dumps(item[2]).encode())
            return
        if st.first_t_ns == 0:
            st.first_t_ns = t_ns
        st.last_t_ns = max(st.last_t_ns, t_ns)
        if tag == _POSE:
            parts = item[2]
            kind, frame, time_s = rf.classify(rf.FORM_POSE, parts)
            packet = rf.Packet(t_ns, frame, time_s, rf.FORM_POSE, kind, "poses", parts)
            st.poses += 1
            self._add(self._poses, t_ns, rf.encode_packet(packet))
            return
        name, form, parts = item[2], item[3], item[4]
        kind, frame, time_s = rf.classify(form, parts)
        if kind == rf.KIND_FRAME:
            st.frames += 1
            st.per_input[name] = st.per_input.get(name, 0) + 1
        elif kind == rf.KIND_LABELS:
            st.label_packets += 1
        else:
            st.other_packets += 1
        self._add(
            self._raw,
            t_ns,
            rf.encode_packet(rf.Packet(t_ns, frame, time_s, form, kind, name, parts)),
        )
        if kind == rf.KIND_FRAME and form == rf.FORM_OSC_SIMPLE:
            self._track_simple_labels(name, t_ns, parts[0])
        elif kind == rf.KIND_LABELS:
            self._track_announced_labels(name, form, t_ns, parts)

    def _track_announced_labels(
        self, name: str, form: int, t_ns: int, parts: tuple[bytes, ...]
    ) -> None:
        try:
            if form == rf.FORM_ZMQ:
                label_set = zmq_wire.decode_zmq_labels(parts[0], parts[1])
            else:
                label_set = osc_in.decode_labels(parts[0])
        except DecodeError:
            return
        if self._label_sets.get(name) != (label_set.id, label_set.labels):
            self._write_labels(name, t_ns, label_set.id, label_set.labels)

    def _track_simple_labels(self, name: str, t_ns: int, buf: bytes) -> None:
        # Simple bundles name every marker: the label set is every name seen so far,
        # in first-seen order; a new name makes a new set (id + 1).
        set_id, labels = self._label_sets.get(name, (-1, ()))
        try:
            names = rf.simple_bundle_names(buf)
        except DecodeError:
            return
        new = [n for n in dict.fromkeys(names) if n not in labels]
        if new:
            self._write_labels(name, t_ns, set_id + 1, (*labels, *new))

    def flush(self) -> None:
        """Close the chunk in progress and write it to the file; count it."""
        self._writer.flush()
        self._commit()

    def close(self) -> None:
        """Write the last chunk (counted), the summary and footer, and close the file.
        On an OSError the caller calls :meth:`abort`."""
        self.flush()
        self._writer.finish()
        self._out.close()

    def abort(self) -> int:
        """Cut the file back to the end of the last whole chunk (so it ends on a
        record boundary and holds exactly the counted messages) and close it.

        Returns:
            The queue items written to the chunk that did not make it (pending).
        """
        lost = self._pending.items_written
        self._pending = RecorderStats()
        try:
            self._out.truncate(self._committed_pos)
        except OSError as exc:
            logger.error("recorder: cannot cut %s back: %s", self._out.name, exc)
        finally:
            self._out.close()
        return lost


class Recorder:
    """A bounded queue in front of a :class:`Sink` written by a thread of its own.

    Args:
        sink_factory: builds the sink on :meth:`start`, given the stats to update.
        queue_size: items held before new ones are dropped (and counted).
        flush_interval_s: how often the writer makes the file crash-readable.
        name: the recording's path, for the log line of a write error.

    Attributes:
        stats: the counts (:class:`RecorderStats`).
        error: what stopped the recording (a write or open error), or "".
        failed: True once a write error stopped the recording.
    """

    def __init__(
        self,
        sink_factory: Any,
        *,
        queue_size: int = DEFAULT_QUEUE_SIZE,
        flush_interval_s: float = DEFAULT_FLUSH_INTERVAL_S,
        name: str = "",
    ) -> None:
        if queue_size < 1:
            raise ValueError(f"queue_size must be >= 1; got {queue_size}")
        if not 0 < flush_interval_s <= MAX_FLUSH_INTERVAL_S:
            raise ValueError(
                f"flush_interval_s must be in (0, {MAX_FLUSH_INTERVAL_S:g}] s; got "
                f"{flush_interval_s}"
            )
        self.stats = RecorderStats()
        self._queue: queue.Queue[tuple[Any, ...]] = queue.Queue(queue_size)
        self._sink_factory = sink_factory
        self._flush_interval_s = flush_interval_s
        self._name = name
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._sink: Sink | None = None
        self.error = ""
        self.failed = False
        #: ``time.monotonic_ns()`` when the write error stopped the recording, or 0.
        self.failed_ns = 0

    # ---- producer side (the live loop): never blocks --------------------------------

    def _put(self, item: tuple[Any, ...]) -> bool:
        if self.failed:  # the recording has stopped: nothing more is part of it
            return False
        try:
            self._queue.put_nowait(item)
        except queue.Full:
            self.stats.dropped += 1
            return False
        self.stats.accepted += 1
        return True

    def record_packet(self, input_name: str, form: int, t_ns: int, *parts: Any) -> bool:
        """Queue a marker packet as received (copied: receive buffers are reused).

        Args:
            input_name: the input's name (an :class:`InputInfo` name).
            form: ``recording.FORM_OSC_COMPACT``, ``FORM_OSC_SIMPLE`` or ``FORM_ZMQ``.
            t_ns: ``time.monotonic_ns()`` at receive.
            parts: the datagram, or the ZeroMQ parts (bytes-like).

        Returns:
            False when the queue was full and the packet was dropped (counted), when
            it has more than 255 parts (``unrecordable``, counted), or when a write
            error has stopped the recording (:attr:`failed`).
        """
        if self.failed:
            return False
        if not 1 <= len(parts) <= 255:  # the envelope's part count is one byte
            self.stats.unrecordable += 1
            return False
        return self._put(
            (_PACKET, t_ns, input_name, form, tuple(bytes(p) for p in parts))
        )

    def record_pose(self, t_ns: int, *parts: Any) -> bool:
        """Queue a pose-stream message (its two parts) sent at ``t_ns``."""
        if self.failed:
            return False
        return self._put((_POSE, t_ns, tuple(bytes(p) for p in parts)))

    def record_event(self, event: str, t_ns: int | None = None, **fields: Any) -> bool:
        """Queue a control event (``"calibrate"``, ``"reload"`` ...), JSON fields."""
        t = time.monotonic_ns() if t_ns is None else t_ns
        return self._put((_EVENT, t, {"event": event, "t_ns": t, **fields}))

    @property
    def queued(self) -> int:
        """Items accepted and neither in the file nor lost yet (in the queue or in
        the chunk being built)."""
        if self.failed and self.finished:
            return 0  # anything put while the writer was failing is not recorded
        st = self.stats
        return max(0, st.accepted - st.items_written - st.write_errors)

    # ---- lifecycle -------------------------------------------------------------------

    def start(self, *, open_in_writer: bool = False) -> None:
        """Start the writer thread.

        Args:
            open_in_writer: build the sink (which writes the file's header) on the
                writer thread rather than here, so the caller does no file I/O at all
                (the live loop). A sink that fails to open (``OSError``) stops the
                recording like a write error.
        """
        if not open_in_writer:
            self._sink = self._sink_factory(self.stats)
        self._thread = threading.Thread(target=self._run, name="recorder", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Ask the writer to write what is queued, finish the file and exit; returns
        at once (the live loop's way to close). Nothing may be queued after this."""
        self._stop.set()

    @property
    def finished(self) -> bool:
        """True once the writer thread has finished the file and exited."""
        return self._thread is None or not self._thread.is_alive()

    def close(self, timeout_s: float = 5.0) -> RecorderStats:
        """Write what is queued, finish the file and stop the thread (bounded wait).

        Returns:
            The stats; if the writer did not finish within ``timeout_s`` it is left
            running as a daemon thread and a warning is logged.
        """
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                logger.warning("recorder: writer still busy after %.1f s", timeout_s)
        return self.stats

    def _run(self) -> None:
        sink = self._sink
        if sink is None:
            try:
                sink = self._sink = self._sink_factory(self.stats)
            except Exception as exc:
                self._fail(None, exc, "cannot start the file")
                return
        interval = self._flush_interval_s
        next_flush = time.monotonic() + interval
        dirty = False
        try:
            while True:
                try:
                    item: tuple[Any, ...] | None = self._queue.get(
                        timeout=max(0.0, next_flush - time.monotonic())
                    )
                except queue.Empty:
                    item = None
                if item is not None:
                    sink.write(item)
                    dirty = True
                now = time.monotonic()
                if now >= next_flush:
                    if dirty:
                        sink.flush()
                    dirty = False
                    next_flush = now + interval
                if self._stop.is_set() and self._queue.empty():
                    break
            sink.close()
        except Exception as exc:
            self._fail(sink, exc, "write failed")

    def _fail(self, sink: Sink | None, exc: BaseException, what: str) -> None:
        """Stop the recording on a write error: cut the file back to what is
        counted, count what is lost, say why (one log line)."""
        self.failed_ns = time.monotonic_ns()
        self.failed = True  # producers stop queueing from here on
        lost = 0
        if sink is not None:
            try:
                lost = sink.abort()
            except Exception as abort_exc:
                logger.debug("recorder: abort: %s", abort_exc)
        while True:
            try:
                self._queue.get_nowait()
            except queue.Empty:
                break
            lost += 1
        st = self.stats
        st.write_errors += lost
        detail = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
        code = (
            f" ({errno.errorcode.get(exc.errno, exc.errno)})"
            if isinstance(exc, OSError) and exc.errno
            else ""
        )
        self.error = f"{what}: {detail}{code}"
        logger.error(
            "recorder: recording %s stopped, %s; the file keeps %d frames "
            "(%.2f s, up to the last whole chunk), %d items lost",
            self._name or "(unnamed)", self.error, st.frames, st.seconds, lost,
        )  # fmt: skip


def open_recorder(
    path: str | os.PathLike[str],
    inputs: tuple[InputInfo, ...],
    *,
    software: str = "",
    queue_size: int = DEFAULT_QUEUE_SIZE,
    flush_interval_s: float = DEFAULT_FLUSH_INTERVAL_S,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    exclusive: bool = False,
    open_in_writer: bool = False,
) -> Recorder:
    """A started :class:`Recorder` writing MCAP to ``path`` (created or truncated).

    Args:
        exclusive: refuse an existing file (``FileExistsError``) instead of
            truncating it.
        open_in_writer: only create the file here; the MCAP header is written on the
            writer thread (see :meth:`Recorder.start`).

    Raises:
        OSError: the file cannot be created (or exists, with ``exclusive``).
    """
    flags = os.O_WRONLY | os.O_CREAT | (os.O_EXCL if exclusive else os.O_TRUNC)
    name = os.fspath(path)
    out = RecordingFile(os.open(name, flags | getattr(os, "O_CLOEXEC", 0), 0o644), name)
    mono = time.monotonic_ns()
    wall = time.time_ns()

    def factory(stats: RecorderStats) -> McapSink:
        try:
            return McapSink(
                out, inputs, stats, mono_anchor_ns=mono, wall_anchor_ns=wall,
                software=software, chunk_size=chunk_size,
            )  # fmt: skip
        except BaseException:
            out.close()
            raise

    recorder = Recorder(
        factory, queue_size=queue_size, flush_interval_s=flush_interval_s, name=name
    )
    try:
        recorder.start(open_in_writer=open_in_writer)
    except Exception:
        out.close()
        raise
    return recorder
