"""What the loop shares with every performer's parts: the configuration and the
target skeleton (read), the loop's counters (counted into), the outputs and the
recording (called), the clocks, and the two values the loop keeps for all of them
(the pose stream's names id, the latest frame's receive time). One object, passed
in: a performer's part never reaches into the loop.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from retargetd.daemon.live.config import DaemonConfig
from retargetd.daemon.live.outputs import Outputs
from retargetd.daemon.live.prewarm import Prewarm
from retargetd.daemon.live.recording import LiveRecording
from retargetd.daemon.live.stats import LoopStats


@dataclass(slots=True, eq=False)
class Shared:
    """The loop's side of every performer's parts (the loop thread only).

    Attributes:
        config: the running configuration (``reload`` replaces its pipeline).
        target: the target skeleton (``retarget.TargetSkeleton``).
        stats: the loop's counters, every performer together.
        outputs: the pose stream and the VMC destinations.
        recording: the live recording (events, skeleton and health channels).
        prewarm: keeps the fit warm between frames (``[loop] prewarm_ms``).
        out: where lines for the operator go.
        status: the status document (the console draws from it).
        t0_ns: the daemon's start (``time.monotonic_ns()``): the pose stream's t.
        budget_ns: ``solve_budget_ms``: solve + send of one frame.
        names_id: the id of the latest pose-stream names message (16 bits).
        last_frame_ns: the receive time of the latest accepted frame.
        fast_ok: the loop may solve a frame in one compiled call with its
            packet's feed (one performer, no ``[[prop]]``: ``one_call.FastFrame``).
        epoch: counts the changes that may end a stream's armed one-call path
            (:meth:`bump`): a path armed at another epoch is not used.
    """

    config: DaemonConfig
    target: Any
    stats: LoopStats
    outputs: Outputs
    recording: LiveRecording
    prewarm: Prewarm
    out: Callable[[str], None]
    status: Callable[[], dict[str, Any]]
    t0_ns: int
    budget_ns: int
    names_id: int = 0
    last_frame_ns: int = 0
    fast_ok: bool = False
    epoch: int = 0

    def bump(self) -> None:
        """Something a frame's one-call path was armed on changed (a label set, a
        pipeline build, the validator, a live calibration, the calibration-match
        window's end): every armed path is off until a frame's two calls arm it
        again (``one_call.arm``)."""
        self.epoch += 1

    def next_names_id(self) -> int:
        """A new names id (a pipeline announces new names)."""
        self.names_id = (self.names_id + 1) % 65536
        return self.names_id
