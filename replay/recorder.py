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
writer finishes the chunk in progress and flushes the file, so a recorder killed at
any moment leaves a file whose data section is whole up to the last flush; only the
footer and summary (indexes, statistics) are missing, and
:func:`~retargetd.replay.recording.read_recording` reads it. ``fsync`` is not called:
a killed process loses nothing that reached the kernel; a power cut may lose more.
"""

from __future__ import annotations

import json
import logging
import os
import queue
import threading
import time
from dataclasses import dataclass, field
from typing import Any, BinaryIO, Protocol

from retargetd.protocols import osc_in, zmq_wire
from retargetd.protocols.errors import DecodeError
from retargetd.replay import recording as rf

logger = logging.getLogger(__name__)

#: Queue length: ~34 s of 120 Hz packets; a stalled disk drops beyond it.
DEFAULT_QUEUE_SIZE = 4096
DEFAULT_FLUSH_INTERVAL_S = 0.25
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
    """What was written (counted on the writer thread) and dropped (producer side:
    ``dropped`` when the queue was full, ``unrecordable`` for a ZeroMQ message of more
    than 255 parts, which the envelope cannot hold)."""

    frames: int = 0
    label_packets: int = 0
    other_packets: int = 0
    label_sets: int = 0
    poses: int = 0
    events: int = 0
    dropped: int = 0
    unrecordable: int = 0
    write_errors: int = 0
    first_t_ns: int = 0
    last_t_ns: int = 0
    per_input: dict[str, int] = field(default_factory=dict)

    @property
    def seconds(self) -> float:
        """Receive time from the first to the last recorded packet."""
        return max(0, self.last_t_ns - self.first_t_ns) * 1e-9


class Sink(Protocol):
    """The writer thread's side (an MCAP file, or a fake in tests)."""

    def write(self, item: tuple[Any, ...]) -> None:
        """Write one queue item."""

    def flush(self) -> None:
        """Make what was written so far readable after a crash."""

    def close(self) -> None:
        """Finish the file (footer, summary) and close it."""


class McapSink:
    """Writes queue items as MCAP (channels and schemas in PROTOCOLS.md).

    Args:
        out: a binary file opened for writing (closed by :meth:`close`).
        inputs: the marker inputs, stored in the metadata record.
        stats: counters to update.
        mono_anchor_ns / wall_anchor_ns: the same instant on ``time.monotonic_ns()``
            and ``time.time_ns()``: log_time = wall_anchor + (t_ns - mono_anchor).
        software: written to the metadata (``"retargetd 0.1.0"``).
        chunk_size: uncompressed bytes at which a chunk closes between flushes.
    """

    def __init__(
        self,
        out: BinaryIO,
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
        self._offset_ns = wall_anchor_ns - mono_anchor_ns
        self._writer = Writer(
            out, chunk_size=chunk_size, compression=CompressionType.ZSTD
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
        log_time = t_ns + self._offset_ns
        self._seq[channel] += 1
        self._writer.add_message(
            channel, log_time, data, log_time, sequence=self._seq[channel]
        )

    def _write_labels(
        self, name: str, t_ns: int, set_id: int, labels: tuple[str, ...]
    ) -> None:
        self._label_sets[name] = (set_id, labels)
        form = rf.FORM_NAMES.get(self._forms.get(name, 0), "")
        msg = {
            "input": name, "form": form, "t_ns": t_ns, "label_set_id": set_id,
            "labels": list(labels),
        }  # fmt: skip
        self._add(self._labels, t_ns, json.dumps(msg).encode())
        self._stats.label_sets += 1

    def write(self, item: tuple[Any, ...]) -> None:
        """Write one queue item (see :class:`Recorder`)."""
        tag, t_ns = item[0], item[1]
        st = self._stats
        if tag == _EVENT:
            self._add(self._control, t_ns, json.dumps(item[2]).encode())
            st.events += 1
            return
        if st.first_t_ns == 0:
            st.first_t_ns = t_ns
        st.last_t_ns = max(st.last_t_ns, t_ns)
        if tag == _POSE:
            parts = item[2]
            kind, frame, time_s = rf.classify(rf.FORM_POSE, parts)
            packet = rf.Packet(t_ns, frame, time_s, rf.FORM_POSE, kind, "poses", parts)
            self._add(self._poses, t_ns, rf.encode_packet(packet))
            st.poses += 1
            return
        name, form, parts = item[2], item[3], item[4]
        kind, frame, time_s = rf.classify(form, parts)
        self._add(
            self._raw,
            t_ns,
            rf.encode_packet(rf.Packet(t_ns, frame, time_s, form, kind, name, parts)),
        )
        if kind == rf.KIND_FRAME:
            st.frames += 1
            st.per_input[name] = st.per_input.get(name, 0) + 1
            if form == rf.FORM_OSC_SIMPLE:
                self._track_simple_labels(name, t_ns, parts[0])
        elif kind == rf.KIND_LABELS:
            st.label_packets += 1
            self._track_announced_labels(name, form, t_ns, parts)
        else:
            st.other_packets += 1

    def _track_announced_labels(
        self, name: str, form: int, t_ns: int, parts: tuple[bytes, ...]
    ) -> None:
        try:
            if form == rf.FORM_ZMQ:
                label_set = zmq_wire.decode_zmq_labels(*parts)
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
        """Close the chunk in progress and flush the file."""
        self._writer.flush()

    def close(self) -> None:
        """Write the summary and footer, and close the file."""
        try:
            self._writer.finish()
        finally:
            self._out.close()


class Recorder:
    """A bounded queue in front of a :class:`Sink` written by a thread of its own.

    Args:
        sink_factory: builds the sink on :meth:`start`, given the stats to update.
        queue_size: items held before new ones are dropped (and counted).
        flush_interval_s: how often the writer makes the file crash-readable.
    """

    def __init__(
        self,
        sink_factory: Any,
        *,
        queue_size: int = DEFAULT_QUEUE_SIZE,
        flush_interval_s: float = DEFAULT_FLUSH_INTERVAL_S,
    ) -> None:
        if queue_size < 1:
            raise ValueError(f"queue_size must be >= 1; got {queue_size}")
        if not flush_interval_s > 0:
            raise ValueError(f"flush_interval_s must be > 0 s; got {flush_interval_s}")
        self.stats = RecorderStats()
        self._queue: queue.Queue[tuple[Any, ...]] = queue.Queue(queue_size)
        self._sink_factory = sink_factory
        self._flush_interval_s = flush_interval_s
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._sink: Sink | None = None
        #: Why the sink could not be opened (``start(open_in_writer=True)``), or "".
        self.error = ""

    # ---- producer side (the live loop): never blocks --------------------------------

    def _put(self, item: tuple[Any, ...]) -> bool:
        try:
            self._queue.put_nowait(item)
        except queue.Full:
            self.stats.dropped += 1
            return False
        return True

    def record_packet(self, input_name: str, form: int, t_ns: int, *parts: Any) -> bool:
        """Queue a marker packet as received (copied: receive buffers are reused).

        Args:
            input_name: the input's name (an :class:`InputInfo` name).
            form: ``recording.FORM_OSC_COMPACT``, ``FORM_OSC_SIMPLE`` or ``FORM_ZMQ``.
            t_ns: ``time.monotonic_ns()`` at receive.
            parts: the datagram, or the ZeroMQ parts (bytes-like).

        Returns:
            False when the queue was full and the packet was dropped (counted), or
            when it has more than 255 parts (``unrecordable``, counted).
        """
        if not 1 <= len(parts) <= 255:  # the envelope's part count is one byte
            self.stats.unrecordable += 1
            return False
        return self._put(
            (_PACKET, t_ns, input_name, form, tuple(bytes(p) for p in parts))
        )

    def record_pose(self, t_ns: int, *parts: Any) -> bool:
        """Queue a pose-stream message (its two parts) sent at ``t_ns``."""
        return self._put((_POSE, t_ns, tuple(bytes(p) for p in parts)))

    def record_event(self, event: str, t_ns: int | None = None, **fields: Any) -> bool:
        """Queue a control event (``"calibrate"``, ``"reload"`` ...), JSON fields."""
        t = time.monotonic_ns() if t_ns is None else t_ns
        return self._put((_EVENT, t, {"event": event, "t_ns": t, **fields}))

    # ---- lifecycle -------------------------------------------------------------------

    def start(self, *, open_in_writer: bool = False) -> None:
        """Start the writer thread.

        Args:
            open_in_writer: build the sink (which writes the file's header) on the
                writer thread rather than here, so the caller does no file I/O at all
                (the live loop). A sink that fails to open (``OSError``) is then
                reported in :attr:`error` and every queued item counts as a write
                error.
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
        failed = False
        if self._sink is None:
            try:
                self._sink = self._sink_factory(self.stats)
            except OSError as exc:
                self.error = str(exc)
                logger.error("recorder: cannot open the recording: %s", exc)
                failed = True
        sink = self._sink
        interval = self._flush_interval_s
        next_flush = time.monotonic() + interval
        dirty = False
        while True:
            try:
                item: tuple[Any, ...] | None = self._queue.get(
                    timeout=max(0.0, next_flush - time.monotonic())
                )
            except queue.Empty:
                item = None
            if item is not None and not failed and sink is not None:
                try:
                    sink.write(item)
                    dirty = True
                except OSError as exc:  # disk full ...: keep draining, count
                    failed = True
                    logger.error("recorder: write failed, recording stops: %s", exc)
            if item is not None and failed:
                self.stats.write_errors += 1
            now = time.monotonic()
            if now >= next_flush:
                if dirty and not failed and sink is not None:
                    _try(sink.flush)
                dirty = False
                next_flush = now + interval
            if self._stop.is_set() and self._queue.empty():
                break
        if sink is not None and not failed:
            _try(sink.close)


def _try(call: Any) -> None:
    try:
        call()
    except OSError as exc:
        logger.error("recorder: %s", exc)


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
    out = open(path, "xb" if exclusive else "wb")  # noqa: SIM115 (the sink closes it)
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
        factory, queue_size=queue_size, flush_interval_s=flush_interval_s
    )
    try:
        recorder.start(open_in_writer=open_in_writer)
    except Exception:
        out.close()
        raise
    return recorder
