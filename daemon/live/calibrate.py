"""Live calibration and face capture: average the next N accepted frames while the
stream goes on with the old calibration, swap the new one in atomically (the loop
thread is its only reader) and save it; face training poses captured the same way;
reload of the rig and calibration files.

A calibration is taken only from a still performer: the markers' drift over the
averaged frames (:func:`marker_drift_speeds_m_s`) must stay under
``performer.calibrate_max_speed_m_s``; then the frames pass the offline calibrate's own
checks (``body.sanity.calibrate_checked``: up axis, units, stillness, left/right labels,
then stature and symmetry of the result). Otherwise it is refused: one line says why
(to the ``ctl`` client too: the status' ``calibration_state`` / ``_message``), it is
counted (``calibrations_refused``) and the old calibration is kept (its file untouched).
With a range of motion (``ctl calibrate --rom --seconds S``) the still base pose is
kept and the next S seconds of frames are collected as the performer moves each joint
through its range; the rig's functional joints are then placed from them
(``calibrate --rom`` offline: the same ``calibrate_checked``), a joint they do not
determine named in a warning line and left at its base-pose estimate.
A request with a bad count is refused; one that collects no frame for
``performer.calibrate_timeout_s`` expires. Calibration requests and reloads are rate
limited (``control.min_interval_s``). A calibration is saved atomically
(``Calibration.save``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import logging
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from retargetd.daemon.body.calibration import CalibrationError, load_calibration
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.body.sanity import (
    BasePoseSource,
    SanityError,
    calibrate_checked,
)
from retargetd.daemon.body.solve import BodySolver
from retargetd.daemon.files import MAX_TEXT_BYTES
from retargetd.daemon.live.config import DaemonConfig, check_pipeline
from retargetd.daemon.live.config_schema import (
    CALIBRATE_MAX_FRAMES,
    CALIBRATE_ROM_MAX_S,
)
from retargetd.daemon.live.performer import FrameSource
from retargetd.daemon.live.send import spine_stage
from retargetd.daemon.live.state import DaemonState
from retargetd.protocols.conventions import world_from_capture_mat

logger = logging.getLogger(__name__)


class CalibrationMixin(DaemonState):
    """Live calibration, live face capture and reload."""

    def _hint_uncalibrated(self) -> None:
        """Tell, once at start, how to calibrate each performer without a
        calibration."""
        for perf in self.performers:
            if perf.calibration is not None:
                continue
            if not perf.name:
                self.out(
                    "no calibration loaded: streaming starts after 'retargetd ctl "
                    "calibrate' (or /VMC/Ext/Set/Calib/Exec) with the performer in "
                    "the base pose"
                )
            else:
                self.out(
                    f"performer {perf.name}: no calibration loaded: its streaming "
                    f"starts after 'retargetd ctl calibrate --performer {perf.name}' "
                    f'(or /rtd/calibrate "{perf.name}") with it in the base pose'
                )

    def request_calibration(
        self, count: object = None, by: str = "", rom_s: object = None
    ) -> str:
        """Start a live calibration over the next ``count`` accepted frames.

        Args:
            count: frames to average (an int in [3, CALIBRATE_MAX_FRAMES]); None =
                ``performer.calibrate_frames``.
            by: who asked (logged, recorded, saved in the calibration).
            rom_s: then this many seconds of range of motion for the rig's
                functional joints (a number in [1, CALIBRATE_ROM_MAX_S]); None =
                none.

        Raises:
            ValueError: a bad count, or rate limited (the message says which); the
                pending calibration, if any, goes on untouched.
        """
        if not self._perf.body:
            raise ValueError(
                f"{self._perf.label} has no body (body = false): nothing to calibrate"
            )
        if count is None:
            n = self._perf.config.calibrate_frames
        elif type(count) is not int or not 3 <= count <= CALIBRATE_MAX_FRAMES:
            raise ValueError(
                f"count must be an integer in [3, {CALIBRATE_MAX_FRAMES}]; "
                f"got {count!r}"
            )
        else:
            n = count
        rom = 0.0
        if rom_s is not None:
            if isinstance(rom_s, int | float) and not isinstance(rom_s, bool):
                rom = float(rom_s)
            if not 1.0 <= rom <= CALIBRATE_ROM_MAX_S:
                raise ValueError(
                    f"seconds of range of motion must be a number in [1, "
                    f"{CALIBRATE_ROM_MAX_S:g}]; got {rom_s!r}"
                )
            if not self.rig.functional:
                raise ValueError(
                    f"rig {self.rig.name} has no [functional] joints: a range of "
                    "motion has nothing to place"
                )
        now = time.monotonic_ns()
        if not self._calibrate_limit.allow(now):
            self.stats.rate_limited += 1
            raise ValueError(
                "rate limited: one calibration request per "
                f"{self.config.control.min_interval_s:g} s"
            )
        self._calib_target = n
        self._calib_frames = []
        self._calib_times = []
        self._calib_labels = ()
        self._calib_requested_by = by
        self._calib_last_ns = now
        self._calib_id += 1
        self._calib_state = "pending"
        self._calib_stream = None
        self._calib_rom_s = rom
        self._end_rom()
        self.recording.event(
            "calibration_requested", count=n, by=by, rom_s=self._calib_rom_s
        )
        logger.info("calibration requested (%s): averaging %d frames", by, n)
        if rom_s is None:
            return f"calibrating over the next {n} frames: hold the base pose"
        return (
            f"calibrating over the next {n} frames: hold the base pose, then move "
            f"each joint through its range for {self._calib_rom_s:g} s"
        )

    def _collect_calibration_frame(self, stream: FrameSource) -> None:
        if self._calib_base is not None:
            self._collect_rom_frame(stream)
            return
        labels = stream.current.label_set.labels
        if self._calib_labels and labels != self._calib_labels:
            self._calib_frames = []  # the marker layout changed: start again
            self._calib_times = []
        self._calib_labels = labels
        self._calib_stream = stream
        frame = stream.current.frame
        self._calib_frames.append(frame.markers_world.copy())
        self._calib_times.append(
            (frame.source_time_s, frame.frame_id, frame.t_ns)
        )  # fmt: skip
        self._calib_last_ns = time.monotonic_ns()
        if len(self._calib_frames) >= self._calib_target:
            self._finish_calibration()

    def _collect_rom_frame(self, stream: FrameSource) -> None:
        """One frame of the range of motion; the last one calibrates."""
        frame = stream.current.frame
        base: tuple[np.ndarray, tuple[str, ...], np.ndarray] = self._calib_base
        if stream.current.label_set.labels != base[1]:
            self._refuse_calibration(
                "the marker labels changed during the range of motion"
            )
            return
        self._calib_rom_frames.append(frame.markers_world.copy())
        self._calib_rom_times.append((frame.source_time_s, frame.frame_id, frame.t_ns))
        self._calib_last_ns = time.monotonic_ns()
        span = _window_times_s(
            [self._calib_rom_times[0], self._calib_rom_times[-1]],
            self.config.validate.rate_hz,
        )
        if span[1] - span[0] >= self._calib_rom_s:
            frames, labels, times_s = base
            rom = (
                np.stack(self._calib_rom_frames), labels,
                {"live": True, "seconds": self._calib_rom_s,
                 "frames": len(self._calib_rom_frames)},
            )  # fmt: skip
            self._calibrate_on(frames, labels, times_s, rom)

    def _calibration_tick(self, now_ns: int) -> None:
        """Expire a pending calibration that has collected no frame for
        ``performer.calibrate_timeout_s`` (nothing changes; one line says so)."""
        if not self._calib_target:
            return
        timeout_s = self._perf.config.calibrate_timeout_s
        if now_ns - self._calib_last_ns < int(timeout_s * 1e9):
            return
        got, wanted = len(self._calib_frames), self._calib_target
        self._end_calibration_request()
        self.stats.calibrations_expired += 1
        self._calib_state = "expired"
        msg = (
            f"calibration expired: no marker frames for {timeout_s:g} s "
            f"({got} of {wanted} collected); the old calibration is kept"
        )
        self._calib_message = msg
        self.recording.event("calibration_expired", collected=got, count=wanted)
        self.out(self._named(msg))

    def _collect_face_frame(self, stream: FrameSource) -> None:
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
            for s in self._own_streams():
                if s.current.label_set.labels == labels:
                    self._pipeline(s)
        self.recording.event("face_capture", ok=ok, message=msg)
        self.out(self._named(msg))

    def request_face_capture(
        self, name: str, count: int | None = None, by: str = ""
    ) -> str:
        """Start capturing face pose ``name`` over the next ``count`` frames."""
        if self.face is None:
            raise ValueError("the face is off: set [face] enabled = true")
        msg = self.face.request_capture(name, count)
        self.recording.event("face_capture_requested", name=name, by=by)
        return msg

    def _end_calibration_request(self) -> None:
        """Nothing pending any more (the frames collected let go)."""
        self._calib_target = 0
        self._calib_frames = []
        self._calib_times = []
        self._end_rom()

    def _end_rom(self) -> None:
        """No range of motion under way."""
        self._calib_base = None
        self._calib_rom_frames = []
        self._calib_rom_times = []

    def _finish_calibration(self) -> None:
        """The base pose is collected: still, it calibrates, or holds for the range
        of motion when one was asked for."""
        frames = np.stack(self._calib_frames)
        labels = self._calib_labels
        times = self._calib_times
        self._calib_frames = []
        self._calib_times = []
        limit = self._perf.config.calibrate_max_speed_m_s
        times_s = _window_times_s(times, self.config.validate.rate_hz)
        if not times_s[-1] > times_s[0]:  # no speed can be told: never "still"
            self._refuse_calibration(
                f"the {frames.shape[0]} frames span no time (source, frame number "
                "and receive times alike), so stillness cannot be judged"
            )
            return
        speeds = marker_drift_speeds_m_s(frames, times_s)
        if np.any(speeds > limit):
            worst = int(np.nanargmax(speeds))
            name = labels[worst] if worst < len(labels) else f"#{worst}"
            self._refuse_calibration(
                f"the performer is not still (marker {name} moving at "
                f"{speeds[worst]:.3f} m/s > {limit:g} m/s over the {frames.shape[0]} "
                "frames)"
            )
            return
        if self._calib_rom_s > 0.0:
            self._calib_base = (frames, labels, times_s)
            self._calib_state = "rom"
            self._calib_last_ns = time.monotonic_ns()
            msg = (
                f"base pose held ({frames.shape[0]} frames): move each joint "
                f"through its range for {self._calib_rom_s:g} s"
            )
            self._calib_message = msg
            self.out(self._named(msg))
            return
        self._calibrate_on(frames, labels, times_s, None)

    def _calibrate_on(
        self,
        frames: np.ndarray,
        labels: tuple[str, ...],
        times_s: np.ndarray,
        rom: tuple[np.ndarray, tuple[str, ...], dict[str, Any]] | None,
    ) -> None:
        """Calibrate on a still base pose (and a range of motion) with every
        offline check; take the result, or refuse it."""
        self._end_calibration_request()
        try:
            cal, notes = calibrate_checked(
                self.rig, frames, labels, self._base_pose_source(times_s),
                base_pose={"live": True, "frames": int(frames.shape[0]),
                           "requested_by": self._calib_requested_by},
                rom=rom, up_levers=self.config.solve.method == "construction",
            )  # fmt: skip
        except (SanityError, CalibrationError) as exc:
            self._refuse_calibration(str(exc))
            return
        for note in notes:
            self.out(self._named(f"calibration warning: {note}"))
        # Atomic: the loop thread is the only reader. Each stream's new body solver
        # is built off the loop from now (rebuild.py), its old pipeline solving
        # meanwhile; a stream without one gets it built now, not on its next frame.
        self.calibration = cal
        for stream in self._own_streams():
            if stream.current.label_set.labels == labels:
                self._pipeline(stream)
        self._start_validator()
        self.stats.calibrations += 1
        self._calib_state = "calibrated"  # "not_saved" below when the save fails
        path = self._perf.config.save_calibration or self._perf.config.calibration
        self.recording.event(
            "calibrated", frames=int(frames.shape[0]), by=self._calib_requested_by,
            path=path or "", warnings=notes,
        )  # fmt: skip
        what = f"{frames.shape[0]} frames"
        if rom is not None:
            placed = [
                n for n, j in cal.functional.get("joints", {}).items() if j.get("used")
            ]
            what += (
                f" and {rom[0].shape[0]} frames of range of motion (placed: "
                f"{', '.join(placed) or 'none'})"
            )
        if path:
            try:
                cal.save(path)
                msg = f"calibrated on {what}; saved {path}"
            except OSError as exc:  # the old file is whole (an atomic save)
                msg = f"calibrated on {what}; NOT saved: {exc}"
                self._calib_state = "not_saved"
        else:
            msg = f"calibrated on {what} (not saved: no path)"
        self._calib_message = msg
        self.out(self._named(msg))

    def _refuse_calibration(self, why: str) -> None:
        """A live calibration refused: counted, said in one line (to the log and,
        through the status, to the ``ctl`` client), recorded; the old calibration
        keeps streaming and its file is not written."""
        msg = (
            f"calibration refused: {why}; the old calibration is kept: hold the "
            "base pose and ask again"
        )
        logger.warning("%s", self._named(msg))
        self._end_calibration_request()
        self.stats.calibrations_refused += 1
        self._calib_state = "refused"
        self._calib_message = msg
        self.recording.event("calibration_refused", message=msg)
        self.out(self._named(msg))

    def _base_pose_source(self, times_s: np.ndarray) -> BasePoseSource:
        """How the calibration frames were read: the unit and up axis of the input
        they came from (``[input.osc]`` / ``[input.zmq]``), the frame rate of the
        window; a refusal names the config key to change."""
        stream = getattr(self._calib_stream, "stream", self._calib_stream)  # a view's
        key = (
            "input.osc" if stream is self.osc_stream
            else "input.zmq" if stream is self.zmq_stream
            else ""
        )  # fmt: skip
        cfg = getattr(self.config.input, key.split(".")[-1]) if key else None
        units = cfg.units if cfg is not None else "m"
        up = cfg.up if cfg is not None else "+Z"
        where = f"config {key}" if key else "the capture input"
        span = float(times_s[-1] - times_s[0]) if len(times_s) > 1 else 0.0
        rate = (len(times_s) - 1) / span if span > 0 else math.nan
        return BasePoseSource(
            units=units, units_source=where, up_axis=up, up_source=where,
            world_from_capture=world_from_capture_mat(up),
            rate_hz=rate, units_override=f"[{key or 'input'}] units =",
            up_override=f"[{key or 'input'}] up =",
            moving_override="nothing (hold the base pose)",
        )  # fmt: skip

    def _named(self, msg: str) -> str:
        """A calibration line, naming the performer when there are several."""
        return f"{self._perf.name}: {msg}" if self._perf.name else msg

    def reload(self) -> str:
        """Reload the rig file, the calibration file and the config file's
        ``[[pipeline]]`` stages from disk (at most once per ``control.min_interval_s``:
        it blocks the loop while it parses; the body solvers are rebuilt off it,
        ``rebuild.py``). The other config keys need a restart; a file that no longer
        validates keeps everything as it was.

        Raises:
            ValueError: rate limited (counted).
        """
        if not self._reload_limit.allow(time.monotonic_ns()):
            self.stats.rate_limited += 1
            raise ValueError(
                f"rate limited: one reload per {self.config.control.min_interval_s:g} s"
            )
        if len(self.performers) == 1:
            return self._reload_performer()
        first = self.performers[0]
        msgs = []
        try:
            for perf in self.performers:  # each its own rig and calibration
                self._perf = perf
                msgs.append(f"{perf.name}: {self._reload_performer()}")
        finally:
            self._perf = first
        return "; ".join(msgs)

    def _reload_performer(self) -> str:
        """Reload the current performer's rig and calibration files (files unchanged
        since the last reload, and the rig and calibration still theirs: nothing to
        parse or rebuild; parsing them took 40-70 ms of the loop, measured)."""
        perf = self._perf
        files = files_digest(perf.config.rig, perf.config.calibration, self.config_path)
        last = perf.reload_files
        if (
            last
            and last[0] == files
            and last[1] is self.rig
            and last[2] is self.calibration
        ):
            msg = f"reloaded rig {self.rig.name}: its files and the config unchanged"
            self.recording.event("reload", ok=True, message=msg)
            return msg
        try:
            rig = load_rig(self._perf.config.rig)
            cal = (
                load_calibration(self._perf.config.calibration)
                if self._perf.config.calibration
                else self.calibration
            )
            if cal is not None:
                BodySolver(rig, cal, ())  # checks the calibration fits the rig
            stages = self.config.pipeline
            if self.config_path:  # the file's [[pipeline]] as it is now
                stages = DaemonConfig.from_toml(self.config_path).pipeline
            check_pipeline(stages, rig, str(self.config_path or "config"))
            spine_stage(self.config.target, self.target, rig)  # its spine fits
        except ValueError as exc:
            msg = f"reload failed, kept the running rig and calibration: {exc}"
            self.recording.event("reload", ok=False, message=msg)
            return msg
        self.rig, self.calibration = rig, cal
        perf.reload_files = (files, rig, cal)
        self.config = dataclasses.replace(self.config, pipeline=stages)
        # The pipelines are rebuilt for the new rig and calibration, their body
        # solvers off the loop (rebuild.py): the old ones solve until then.
        self.stats.set_post_stages(())  # named again as the pipelines are rebuilt
        self._start_validator()
        msg = f"reloaded rig {rig.name}" + (" and calibration" if cal else "")
        if stages:
            msg += f", pipeline {' -> '.join(str(e['kind']) for e in stages)}"

        self.recording.event("reload", ok=True, message=msg)
        return msg


def marker_drift_speeds_m_s(frames: np.ndarray, times_s: np.ndarray) -> np.ndarray:
    """Each marker's drift speed over a window: the distance between its mean
    position over the first and over the last third of the frames, over the time
    between their mean times. Averaging a third of the window cancels measurement
    noise (at 0.3 mm RMS and 60 frames at 240 Hz, under 1 mm/s) where a
    frame-to-frame speed would be dominated by it.

    Args:
        frames: (n, m, 3) float64 marker positions, metres, world frame; NaN =
            occluded. n >= 2.
        times_s: (n,) float64 frame times, seconds, increasing.

    Returns:
        (m,) float64 speeds in m/s; NaN for a marker unseen in either third (it
        does not count as moving); all NaN when the window spans no time.
    """
    n = frames.shape[0]
    k = max(1, n // 3)
    first, last = frames[:k], frames[n - k :]
    dt = float(np.mean(times_s[n - k :]) - np.mean(times_s[:k]))
    out = np.full(frames.shape[1], np.nan)
    if not dt > 0.0:
        return out
    mean_a = _finite_mean(first)
    mean_b = _finite_mean(last)
    dist = np.sqrt(np.sum((mean_b - mean_a) ** 2, axis=1))
    ok = np.isfinite(dist)
    out[ok] = dist[ok] / dt
    return out


def _finite_mean(frames: np.ndarray) -> np.ndarray:
    """(k, m, 3) -> (m, 3) mean over the frames where each marker is finite (NaN
    where it never is), without NumPy's empty-slice warning."""
    finite = np.isfinite(frames).all(axis=2)  # (k, m)
    count = finite.sum(axis=0)  # (m,)
    total = np.where(finite[:, :, None], frames, 0.0).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = total / count[:, None]
    mean[count == 0] = np.nan
    return mean


def _window_times_s(times: list[tuple[float, int, int]], rate_hz: float) -> np.ndarray:
    """The frames' times in seconds: the source's timestamps when every frame has one
    and they span time, else frame numbers at ``rate_hz``, else receive times."""
    source = np.array([t[0] for t in times], dtype=np.float64)
    if np.all(np.isfinite(source)) and source[-1] > source[0]:
        return source
    ids = np.array([t[1] for t in times], dtype=np.float64)
    if np.all(ids >= 0) and ids[-1] > ids[0] and math.isfinite(rate_hz):
        return ids / rate_hz
    return np.array([t[2] for t in times], dtype=np.float64) * 1e-9


def files_digest(*paths: Any) -> bytes:
    """SHA-256 over the bytes of every file named (a shipped rig's name, an empty or
    None path, and a file that cannot be read count as their names: the reload that
    follows then parses and says what is wrong)."""
    h = hashlib.sha256()
    for p in paths:
        h.update(str(p).encode() + b"\0")
        with contextlib.suppress(OSError, ValueError):
            if p and Path(p).is_file():  # (at most MAX_TEXT_BYTES: as the readers)
                with open(p, "rb") as fh:
                    h.update(fh.read(MAX_TEXT_BYTES + 1))
    return h.digest()
