"""Live calibration and face capture: average the next N accepted frames while the
stream goes on with the old calibration, swap the new one in atomically (the loop
thread is its only reader) and save it; face training poses captured the same way;
reload of the rig and calibration files.
"""

from __future__ import annotations

import logging

import numpy as np

from retargetd.daemon.body.calibration import calibrate, load_calibration
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.body.solve import BodySolver
from retargetd.daemon.live.state import DaemonState
from retargetd.protocols.marker_input import MarkerStream

logger = logging.getLogger(__name__)


class CalibrationMixin(DaemonState):
    """Live calibration, live face capture and reload."""

    def request_calibration(self, count: int | None = None, by: str = "") -> str:
        """Start a live calibration over the next ``count`` accepted frames."""
        n = count or self.config.performer.calibrate_frames
        if n < 1:
            raise ValueError(f"count must be >= 1; got {n}")
        self._calib_target = n
        self._calib_frames = []
        self._calib_labels = ()
        self._calib_requested_by = by
        self.recording.event("calibration_requested", count=n, by=by)
        logger.info("calibration requested (%s): averaging %d frames", by, n)
        return f"calibrating over the next {n} frames: hold the base pose"

    def _collect_calibration_frame(self, stream: MarkerStream) -> None:
        labels = stream.current.label_set.labels
        if self._calib_labels and labels != self._calib_labels:
            self._calib_frames = []  # the marker layout changed: start again
        self._calib_labels = labels
        self._calib_frames.append(stream.current.frame.markers_world.copy())
        if len(self._calib_frames) >= self._calib_target:
            self._finish_calibration()

    def _collect_face_frame(self, stream: MarkerStream) -> None:
        assert self.face is not None
        labels = stream.current.label_set.labels
        done = self.face.collect(stream.current.frame.markers_world, labels)
        if done is None:
            return
        ok, msg = done
        if ok:
            # The next frame solves with the new training set; pipelines rebuilt now,
            # off the frame that completed the capture.
            self.stats.face_captures += 1
            self._pipelines.clear()
            self._labels_of.clear()
            for s in (self.osc_stream, self.zmq_stream):
                if s.current.label_set.labels == labels:
                    self._pipeline(s)
        self.recording.event("face_capture", ok=ok, message=msg)
        self.out(msg)

    def request_face_capture(
        self, name: str, count: int | None = None, by: str = ""
    ) -> str:
        """Start capturing face pose ``name`` over the next ``count`` frames."""
        if self.face is None:
            raise ValueError("the face is off: set [face] enabled = true")
        msg = self.face.request_capture(name, count)
        self.recording.event("face_capture_requested", name=name, by=by)
        return msg

    def _finish_calibration(self) -> None:
        frames = np.stack(self._calib_frames)
        labels = self._calib_labels
        self._calib_target = 0
        self._calib_frames = []
        try:
            cal = calibrate(
                self.rig,
                frames,
                labels,
                base_pose={"live": True, "frames": int(frames.shape[0]),
                           "requested_by": self._calib_requested_by},
            )  # fmt: skip
        except ValueError as exc:
            logger.warning("live calibration failed: %s", exc)
            self.recording.event("calibration_failed", error=str(exc))
            self.out(f"calibration failed: {exc}")
            return
        # Atomic: the loop thread is the only reader; the next frame uses the new one,
        # with its pipeline built now rather than on the next frame.
        self.calibration = cal
        self._pipelines.clear()
        self._labels_of.clear()
        for stream in (self.osc_stream, self.zmq_stream):
            if stream.current.label_set.labels == labels:
                self._pipeline(stream)
        self._start_validator()
        self.stats.calibrations += 1
        path = (
            self.config.performer.save_calibration or self.config.performer.calibration
        )
        self.recording.event(
            "calibrated", frames=int(frames.shape[0]), by=self._calib_requested_by,
            path=path or "",
        )  # fmt: skip
        if path:
            try:
                cal.save(path)
                self.out(f"calibrated on {frames.shape[0]} frames; saved {path}")
            except OSError as exc:
                self.out(f"calibrated on {frames.shape[0]} frames; NOT saved: {exc}")
        else:
            self.out(f"calibrated on {frames.shape[0]} frames (not saved: no path)")

    def reload(self) -> str:
        """Reload the rig file and the calibration file from disk."""
        try:
            rig = load_rig(self.config.performer.rig)
            cal = (
                load_calibration(self.config.performer.calibration)
                if self.config.performer.calibration
                else self.calibration
            )
            if cal is not None:
                BodySolver(rig, cal, ())  # checks the calibration fits the rig
        except ValueError as exc:
            msg = f"reload failed, kept the running rig and calibration: {exc}"
            self.recording.event("reload", ok=False, message=msg)
            return msg
        self.rig, self.calibration = rig, cal
        self._pipelines.clear()
        self._labels_of.clear()
        self._start_validator()
        msg = f"reloaded rig {rig.name}" + (" and calibration" if cal else "")
        self.recording.event("reload", ok=True, message=msg)
        return msg
