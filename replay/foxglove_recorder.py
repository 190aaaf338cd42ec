"""A live recording that also carries the Foxglove channels (``/foxglove/*``).

:func:`open_skeleton_recorder` is :func:`retargetd.replay.recorder.open_recorder` plus
:meth:`SkeletonRecorder.record_skeleton`: the producer (the live loop) queues a copy
of one frame's solve (joint centres, bone rotations, root, flags, markers) with a
``put_nowait`` like every other item (a full queue drops and counts it); the writer
thread places the bones (``bone_ends_fn``, supplied by the daemon:
``retargetd.daemon.console.snapshot.bone_endpoints`` bound to the rig's program and
calibrated lengths; ``replay`` may not import the daemon) and writes them with
:class:`~retargetd.replay.foxglove.FoxgloveChannels` beside the recording's own
channels, at the same log-time clock (wall clock, as ``McapSink``).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from retargetd.replay.foxglove import FoxgloveChannels
from retargetd.replay.recorder import (
    DEFAULT_CHUNK_SIZE,
    DEFAULT_FLUSH_INTERVAL_S,
    DEFAULT_QUEUE_SIZE,
    InputInfo,
    McapSink,
    Recorder,
    RecorderStats,
    RecordingFile,
)

#: Queue item tags for a skeleton frame and a health sample (the recorder's own
#: tags are 0-2).
_SKELETON = 16
_HEALTH = 17

#: ``bone_ends_fn(joint_pos (J, 3), world_from_bone_quat (B, 4), root_pos (3,))``
#: -> (B, 2, 3) metres world.
BoneEndsFn = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]


class FoxgloveMcapSink(McapSink):
    """:class:`McapSink` with the Foxglove channels registered beside its own.

    Args:
        out / inputs / stats / kwargs: as :class:`McapSink`.
        bone_names: (B,) bone names; bone_parents: (B,) parent index, -1 root.
        bone_ends_fn: places both ends of every bone (see :data:`BoneEndsFn`).
    """

    def __init__(
        self,
        out: RecordingFile,
        inputs: tuple[InputInfo, ...],
        stats: RecorderStats,
        *,
        bone_names: Sequence[str],
        bone_parents: Sequence[int],
        bone_ends_fn: BoneEndsFn,
        **kwargs: Any,
    ) -> None:
        super().__init__(out, inputs, stats, **kwargs)
        self.foxglove = FoxgloveChannels(self._writer, bone_names, bone_parents)
        self._bone_ends_fn = bone_ends_fn
        #: Skeleton frames written.
        self.skeletons = 0

    def write(self, item: tuple[Any, ...]) -> None:
        """Write one queue item (a skeleton frame, or the recorder's own)."""
        if item[0] == _HEALTH:
            _, t_ns, figures = item
            self.foxglove.write_health(t_ns + self._offset_ns, figures)
            return
        if item[0] != _SKELETON:
            super().write(item)
            return
        _, t_ns, joints, quats, root, flags, markers, valid = item
        self.foxglove.write_frame(
            t_ns + self._offset_ns,
            bone_ends=self._bone_ends_fn(joints, quats, root),
            world_from_bone_quat=quats,
            bone_flags=flags,
            markers=markers,
            marker_valid=valid,
        )
        self.skeletons += 1


class SkeletonRecorder(Recorder):
    """:class:`Recorder` that also queues solved frames for the Foxglove channels."""

    def record_skeleton(
        self,
        t_ns: int,
        joint_pos: np.ndarray,
        world_from_bone_quat: np.ndarray,
        root_pos: np.ndarray,
        bone_flags: np.ndarray,
        markers: np.ndarray | None = None,
        marker_valid: np.ndarray | None = None,
    ) -> bool:
        """Queue one solved frame (copied; never blocks).

        Args:
            t_ns: ``time.monotonic_ns()`` of the frame (as ``record_packet``).
            joint_pos: (J, 3) float64 metres world, joint centres.
            world_from_bone_quat: (B, 4) float64 w x y z.
            root_pos: (3,) float64 metres world.
            bone_flags: (B,) uint8.
            markers: (M, 3) float64 metres world, or None.
            marker_valid: (M,) bool, or None.

        Returns:
            False when the queue was full (dropped, counted in ``stats.dropped``).
        """
        return self._put(
            (
                _SKELETON, t_ns, joint_pos.copy(), world_from_bone_quat.copy(),
                root_pos.copy(), bone_flags.copy(),
                None if markers is None else markers.copy(),
                None if marker_valid is None else marker_valid.copy(),
            )
        )  # fmt: skip

    def record_health(self, t_ns: int, figures: dict[str, Any]) -> bool:
        """Queue one health sample for ``/foxglove/health`` (never blocks).

        Args:
            t_ns: ``time.monotonic_ns()`` of the sample.
            figures: JSON-ready figures (finite numbers or None): ``input_rate_hz``,
                ``drops``, ``occluded``, ``validation_flags``, ``latency_p50_ms`` and
                ``latency_p99_ms`` (stage -> ms).

        Returns:
            False when the queue was full (dropped, counted).
        """
        return self._put((_HEALTH, t_ns, figures))


def open_skeleton_recorder(
    path: str | os.PathLike[str],
    inputs: tuple[InputInfo, ...],
    *,
    bone_names: Sequence[str],
    bone_parents: Sequence[int],
    bone_ends_fn: BoneEndsFn,
    software: str = "",
    queue_size: int = DEFAULT_QUEUE_SIZE,
    flush_interval_s: float = DEFAULT_FLUSH_INTERVAL_S,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    exclusive: bool = False,
    open_in_writer: bool = False,
) -> SkeletonRecorder:
    """A started :class:`SkeletonRecorder` writing MCAP with the Foxglove channels.

    Arguments as :func:`retargetd.replay.recorder.open_recorder`, plus the bone
    layout and ``bone_ends_fn`` of :class:`FoxgloveMcapSink`.

    Raises:
        OSError: the file cannot be created (or exists, with ``exclusive``).
    """
    flags = os.O_WRONLY | os.O_CREAT | (os.O_EXCL if exclusive else os.O_TRUNC)
    name = os.fspath(path)
    # The recorder's own file at the OS boundary (write errors raise where they
    # happen, counts are what the file holds): see ``recorder.RecordingFile``.
    out = RecordingFile(os.open(name, flags | getattr(os, "O_CLOEXEC", 0), 0o644), name)
    mono = time.monotonic_ns()
    wall = time.time_ns()

    def factory(stats: RecorderStats) -> FoxgloveMcapSink:
        try:
            return FoxgloveMcapSink(
                out, inputs, stats, bone_names=bone_names, bone_parents=bone_parents,
                bone_ends_fn=bone_ends_fn, mono_anchor_ns=mono, wall_anchor_ns=wall,
                software=software, chunk_size=chunk_size,
            )  # fmt: skip
        except BaseException:
            out.close()
            raise

    recorder = SkeletonRecorder(
        factory, queue_size=queue_size, flush_interval_s=flush_interval_s, name=name
    )
    try:
        recorder.start(open_in_writer=open_in_writer)
    except Exception:
        out.close()
        raise
    return recorder
