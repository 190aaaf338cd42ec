"""The live daemon's side of the browser console (``[console]``, ``run --console``).

The console (``retargetd.daemon.console``: a ``viser`` page on its own thread) never
touches the loop's state. The loop publishes a decimated copy (``publish_hz``, 30 by
default) into the console's two-buffer :class:`SnapshotSlot` with a non-blocking
commit (a publish the console is reading at that instant is skipped and counted), and
drains the console's bounded :class:`CommandQueue` once per pass of the loop (a
``get_nowait`` that allocates nothing when it is empty). Button presses become the
same requests as ``retargetd ctl``: calibrate (after the page's countdown; the
stillness check runs on the frames as for any calibration), record start/stop (under
the configured recordings folder), face capture, reload.

The page shows the markers, the solved skeleton with flagged bones in red, the
retargeted humanoid beside it (the loop copies the target's bone rotations and hips
position, ``TargetPose``; the console thread poses the joints,
``console.snapshot.humanoid_positions``), face weights when the face is on, and the
health plots. Its ``t`` counts from the daemon's start (the pose stream's ``t``), not
the machine's uptime. With ``[validate]`` on, the latest validation result goes with
each snapshot: its frame bits name the checks (``VALIDATION_CHECKS``), its values
and bone bits (ORed into the drawn bone flags: red) say where and by how much. The
"Face capture" button is on the page only when the performer has a face configured.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from retargetd.daemon.body.rig import Rig
from retargetd.daemon.body.solve import BodyPose, BodySolver
from retargetd.daemon.console.app import Console
from retargetd.daemon.console.snapshot import (
    CMD_CALIBRATE,
    CMD_FACE_CAPTURE,
    CMD_RECORD_START,
    CMD_RECORD_STOP,
    CMD_RELOAD,
    CommandQueue,
    ConsoleLayout,
    SkeletonProgram,
    SnapshotSlot,
)
from retargetd.daemon.live.config import ConsoleConfig
from retargetd.daemon.live.stats import STAGES, LoopStats
from retargetd.daemon.retarget.retarget import performer_left_from_calibration
from retargetd.protocols import pose_stream
from retargetd.protocols.frames import MarkerFrame

logger = logging.getLogger(__name__)

#: How far to the performer's right the retargeted humanoid is drawn, metres: two
#: T-poses side by side clear each other (half arm spans of ~0.9 m each for 1.8 m
#: figures: arm span is about body height, Vitruvian proportion).
HUMANOID_BESIDE_M = 2.0
#: The health plots' refresh (0.5 s): the stats line's figures, not per frame.
HEALTH_INTERVAL_NS = 500_000_000
_VALIDATION_SHIFT = pose_stream.FRAME_V_CONVENTION.bit_length() - 1  # first check


def _health(status: dict[str, Any]) -> dict[str, Any]:
    drops = 0
    for counts in status.get("drops", {}).values():
        drops += sum(v for k, v in counts.items() if k not in ("accepted", "restart"))
    return {
        "recording": bool(status.get("record", {}).get("active")),
        "fps_in": float(status.get("fps_in") or 0.0),
        "drops": drops,
        "latency_us": {
            k: tuple(float("nan") if x is None else float(x) for x in v)
            for k, v in status.get("latency_us", {}).items()
        },
    }


def _layout(
    rig: Rig,
    solver: BodySolver,
    labels: tuple[str, ...],
    face_names: tuple[str, ...],
    target: Any = None,
) -> ConsoleLayout:
    humanoid: dict[str, Any] = {}
    if target is not None:  # a TargetSkeleton: its bones joint to joint
        par = np.asarray(target.parents, dtype=np.int64)
        # The humanoid's root moves by the performer's displacement since
        # calibration (TargetPose.root_pos): put it where the performer stood then,
        # and beside it, to its right.
        cal = solver.calibration
        at = np.array([cal.root_rest_pos[0], cal.root_rest_pos[1], 0.0])
        try:
            left = performer_left_from_calibration(rig, cal)
            humanoid["humanoid_offset_m"] = at - HUMANOID_BESIDE_M * left
        except ValueError:
            pass  # the layout's default offset
        humanoid |= {
            "humanoid_names": tuple(target.bone_names),
            "humanoid_pairs": np.array(
                [(p, i) for i, p in enumerate(par.tolist()) if p >= 0], np.int64
            ).reshape(-1, 2),
            "humanoid_parents": par,
            "humanoid_rest_offsets": np.asarray(target.rest_offsets, np.float64),
            "humanoid_rest_quat": np.asarray(
                target.rest_world_from_bone_quat, np.float64
            ),
        }
    return ConsoleLayout(
        marker_names=labels,
        joint_names=solver.joint_names,
        bone_names=rig.bone_names,
        bone_parents=np.asarray(rig.bone_parent_indices(), dtype=np.int64),
        skeleton=SkeletonProgram.from_rig(rig, solver.joint_names),
        bone_lengths=np.asarray(solver.calibration.bone_lengths, dtype=np.float64),
        face_names=face_names,
        stage_names=STAGES,
        check_names=pose_stream.VALIDATION_CHECKS,
        check_units=pose_stream.VALIDATION_UNITS,
        **humanoid,
    )


def _markers_layout(labels: tuple[str, ...]) -> ConsoleLayout:
    """A layout of markers alone (before a calibration, or empty at start)."""
    return ConsoleLayout(
        marker_names=labels,
        joint_names=(),
        bone_names=(),
        bone_parents=np.zeros(0, np.int64),
        skeleton=SkeletonProgram.from_joint_pairs([], 0),
        bone_lengths=np.zeros(0),
        stage_names=STAGES,
    )


class ConsoleFeed:
    """The console server plus what the loop publishes to it.

    Args:
        config: the ``[console]`` section (host, port, publish rate).
        out: where the daemon's lines go (the console's URL is printed there).
        t0_ns: ``time.monotonic_ns()`` when the daemon started: the page's ``t`` and
            plots count from it.
        face_capture: a face is configured (the page offers Face capture).
    """

    def __init__(
        self,
        config: ConsoleConfig,
        out: Callable[[str], None],
        *,
        t0_ns: int = 0,
        face_capture: bool = False,
    ) -> None:
        self.config = config
        self.out = out
        self.t0_ns = t0_ns
        self.face_capture = face_capture
        self.commands = CommandQueue()
        self.slot: SnapshotSlot | None = None
        self.console: Console | None = None
        self._layout_key: tuple[int, tuple[str, ...]] | None = None
        self._p50 = np.zeros(len(STAGES))
        self._p99 = np.zeros(len(STAGES))
        self._health: dict[str, Any] = {}
        self._health_ns = 0
        self.published = 0
        #: the daemon's props (``live/props.LiveProps``), drawn as axes when set
        self.props: Any = None

    def start(self, rig: Rig) -> str:
        """Start the page (an empty layout until the first solved frame); its URL."""
        empty = _markers_layout(())
        del rig
        self.slot = SnapshotSlot(empty, publish_hz=self.config.publish_hz)
        self.console = Console(
            self.slot, self.commands, host=self.config.host, port=self.config.port,
            face_capture=self.face_capture,
        )  # fmt: skip
        self.console.start()
        return self.console.url

    def stop(self) -> None:
        """Stop the page (bounded)."""
        if self.console is not None:
            self.console.stop()
            self.console = None

    def publish(
        self,
        now_ns: int,
        rig: Rig,
        solver: BodySolver,
        frame: MarkerFrame,
        labels: tuple[str, ...],
        pose: BodyPose,
        bone_flags: np.ndarray,
        face_names: tuple[str, ...],
        face_weights: np.ndarray | None,
        stats: LoopStats,
        status_fn: Callable[[], dict[str, Any]],
        target: Any = None,
        target_pose: Any = None,
        validation_bits: int = 0,
        validation_values: np.ndarray | None = None,
        validation_bones: np.ndarray | None = None,
    ) -> None:
        """Publish this frame when one is due (``publish_hz``); never waits. The
        health figures (``status_fn``, the status document) are refreshed at most
        every :data:`HEALTH_INTERVAL_NS`: their percentiles are not per-frame work.
        ``target`` (``TargetSkeleton``) and ``target_pose`` (``TargetPose``): the
        retargeted humanoid, copied as rotations (posed on the console thread).
        ``validation_bits`` (frame bits 8-15), ``validation_values`` ((8,) in
        ``VALIDATION_CHECKS`` order) and ``validation_bones`` ((B,) uint8 bits 4-7):
        the live validator's latest result ([validate] on)."""
        slot = self.slot
        if slot is None or not slot.due(now_ns):
            return
        if now_ns - self._health_ns >= HEALTH_INTERVAL_NS:
            self._health, self._health_ns = _health(status_fn()), now_ns
        status = self._health
        key = (id(solver), labels)
        if key != self._layout_key:  # a new pipeline: the page's layout (not hot)
            slot.set_layout(self._with_props(_layout(rig, solver, labels, face_names,
                                                     target)))  # fmt: skip
            self._layout_key = key
        s = slot.begin()
        if s.marker_pos.shape != frame.markers_world.shape:
            return  # the layout is being swapped
        s.frame = frame.frame_id
        s.t_s = (now_ns - self.t0_ns) * 1e-9
        np.copyto(s.marker_pos, frame.markers_world)
        np.copyto(s.marker_valid, frame.valid)
        np.copyto(s.joint_pos, pose.joint_centres)
        np.copyto(s.world_from_bone_quat, pose.world_from_bone_quat)
        np.copyto(s.root_pos, pose.root_pos)
        np.copyto(s.bone_flags, bone_flags)
        s.check_flags = (validation_bits & pose_stream.FRAME_VALIDATION_MASK) >> (
            _VALIDATION_SHIFT
        )
        if validation_values is not None:
            np.copyto(s.check_values, validation_values)
        if validation_bones is not None and len(validation_bones) == len(bone_flags):
            np.bitwise_or(s.bone_flags, validation_bones, out=s.bone_flags)
        if target_pose is not None and s.humanoid_quat.shape[0]:
            np.copyto(s.humanoid_quat, target_pose.world_from_bone_quat)
            np.copyto(s.humanoid_hips, target_pose.hips_pos)
        s.face_on = face_weights is not None and len(face_weights) > 0
        if s.face_on and face_weights is not None:
            np.copyto(s.face_weights, face_weights, casting="same_kind")
        s.calibrated = True
        self._commit_health(slot, s, status, frame, stats)

    def publish_markers(
        self,
        now_ns: int,
        frame: MarkerFrame,
        labels: tuple[str, ...],
        stats: LoopStats,
        status_fn: Callable[[], dict[str, Any]],
    ) -> None:
        """Before a calibration: publish the markers alone when one is due (the
        operator sees the performer take the base pose); never waits."""
        slot = self.slot
        if slot is None or not slot.due(now_ns):
            return
        if now_ns - self._health_ns >= HEALTH_INTERVAL_NS:
            self._health, self._health_ns = _health(status_fn()), now_ns
        key = (0, labels)
        if key != self._layout_key:  # markers only, until a pipeline exists
            slot.set_layout(self._with_props(_markers_layout(labels)))
            self._layout_key = key
        s = slot.begin()
        if s.marker_pos.shape != frame.markers_world.shape:
            return
        s.frame = frame.frame_id
        s.t_s = (now_ns - self.t0_ns) * 1e-9
        np.copyto(s.marker_pos, frame.markers_world)
        np.copyto(s.marker_valid, frame.valid)
        s.check_flags = 0
        s.face_on = False
        s.calibrated = False
        self._commit_health(slot, s, self._health, frame, stats)

    def _with_props(self, layout: ConsoleLayout) -> ConsoleLayout:
        props = self.props.props if self.props is not None else ()
        return replace(layout, prop_names=tuple(p.name for p in props))

    def _commit_health(
        self,
        slot: SnapshotSlot,
        s: Any,
        status: dict[str, Any],
        frame: MarkerFrame,
        stats: LoopStats,
    ) -> None:
        if self.props is not None and len(s.prop_flags) == len(self.props.props):
            for i, p in enumerate(self.props.props):  # each prop's last sent pose
                s.prop_quat[i] = p.pose.parent_from_bone_quat[0]
                s.prop_pos[i] = p.pose.root_pos
                s.prop_flags[i] = p.flags
        s.recording = bool(status.get("recording"))
        s.input_rate_hz = float(status.get("fps_in", 0.0))
        s.drops = int(status.get("drops", 0))
        for k, name in enumerate(STAGES):
            lat = status.get("latency_us", {})
            p50, p99 = lat.get(name, (float("nan"), float("nan")))
            self._p50[k], self._p99[k] = p50 * 1e-3, p99 * 1e-3
        np.copyto(s.latency_p50_ms, self._p50)
        np.copyto(s.latency_p99_ms, self._p99)
        s.occluded = int(len(frame.valid) - np.count_nonzero(frame.valid))
        s.validation_flags = stats.validation_flagged
        if slot.commit():
            self.published += 1


def dispatch(daemon: Any, cmd: Any) -> None:
    """Turn one console command into the daemon request it stands for; a refused one
    is printed (the page shows the stats line), never raised."""
    try:
        if cmd.kind == CMD_CALIBRATE:
            msg = daemon.request_calibration(None, "console")
        elif cmd.kind == CMD_RECORD_START:
            msg = daemon._record_control(
                {"cmd": "record", "action": "start", "path": cmd.arg or "console.mcap"}
            )
        elif cmd.kind == CMD_RECORD_STOP:
            msg = daemon._record_control({"cmd": "record", "action": "stop"})
        elif cmd.kind == CMD_FACE_CAPTURE:
            msg = daemon.request_face_capture(cmd.arg or "neutral", None, "console")
        elif cmd.kind == CMD_RELOAD:  # its files read off the loop: printed then
            daemon.control.reload_later("out")
            return
        else:
            msg = f"console: unknown command {cmd.kind!r}"
    except (ValueError, TypeError, OSError) as exc:
        msg = f"console {cmd.kind}: {exc}"
    daemon.out(str(msg))
