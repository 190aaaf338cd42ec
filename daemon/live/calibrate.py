"""Live calibration and face capture, one per performer (:class:`LiveCalibration`,
its own state): average the next N accepted frames while the
stream goes on with the old calibration, swap the new one in atomically (the loop
thread is its only reader) and save it; face training poses captured the same way
(the reload of the rig and calibration files is ``performers.Performers.reload``).

A calibration is taken only from a still performer: the markers' drift over the
averaged frames (:func:`marker_drift_speeds_m_s`) must stay under
``performer.calibrate_max_speed_m_s``; then the frames pass the offline calibrate's own
checks (``body.sanity.calibrate_checked``: up axis, units, stillness, left/right labels,
then stature and symmetry of the result). Otherwise it is refused: one line says why
(to the ``ctl`` client too: the status' ``calibration_state`` / ``_message``), it is
counted (``calibrations_refused``) and the old calibration is kept (its file untouched).
Anything else ``calibrate_checked`` raises is a fault of ours, not the performer's: it
is counted (``calibration_failures``), said in one line (its traceback in the log),
``calibration_state`` "failed", the old calibration kept; the loop serves on.
With a range of motion (``ctl calibrate --rom --seconds S``) the still base pose is
kept and the next S seconds of frames are collected as the performer moves each joint
through its range; the rig's functional joints are then placed from them
(``calibrate --rom`` offline: the same ``calibrate_checked``), a joint they do not
determine named in a warning line and left at its base-pose estimate.
A request with a bad count is refused; one that collects no frame for
``performer.calibrate_timeout_s`` expires. Calibration requests and reloads are rate
limited (``control.min_interval_s``). A calibration is saved atomically
(``Calibration.save``: a temporary file fsynced, then renamed over the old one) on a
worker thread (``rebuild.Build``, one write at a time, the newest waiting): the write
and its fsync took 12-16 ms in the loop, and a slow or stalled disk held every frame
for as long as it took. Meanwhile ``calibration_state`` is "saving" (``ctl calibrate``
waits through it) and the new calibration is already in use; the loop pass that finds
the write ended says so in one line: "calibrated", or "not_saved" with the reason
(counted ``calibration_save_failures``, the old file whole). The daemon's close waits
for the write under way and writes the one waiting.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from retargetd.daemon.body.calibration import CalibrationError
from retargetd.daemon.body.sanity import (
    BasePoseSource,
    SanityError,
    calibrate_checked,
)
from retargetd.daemon.live.config_schema import (
    CALIBRATE_MAX_FRAMES,
    CALIBRATE_ROM_MAX_S,
)
from retargetd.daemon.live.performer import FrameSource, Performer
from retargetd.daemon.live.ratelog import RateLimiter
from retargetd.daemon.live.rebuild import Build
from retargetd.daemon.live.shared import Shared
from retargetd.protocols.conventions import world_from_capture_mat

logger = logging.getLogger(__name__)


class LiveCalibration:
    """One performer's live calibration and face capture: the request, the frames
    collected, how the last one ended.

    Args:
        perf: the performer (its rig, config, face; a new calibration goes in
            through ``perf.use_calibration``).
        shared: the loop's side (config, counters, recording, out).
        kind_of: the input a stream belongs to ("osc", "zmq", "source").
        sources: what the performer reads of each input now (a new calibration's
            pipelines are built on them at once).
        min_interval_s: the least time between two calibration requests.
    """

    def __init__(
        self,
        perf: Performer,
        shared: Shared,
        kind_of: Callable[[object], str],
        sources: Callable[[], list[FrameSource]],
        min_interval_s: float,
    ) -> None:
        self.perf = perf
        self.shared = shared
        self._kind_of = kind_of
        self._sources = sources
        self.target = 0  # frames still wanted (0: nothing pending)
        self.frames: list[np.ndarray] = []
        self.labels: tuple[str, ...] = ()
        self.requested_by = ""
        self.times: list[tuple[float, int, int]] = []  # (source s, frame id, t_ns)
        self.last_ns = 0  # the request or the last collected frame (timeout)
        self.message = ""  # how the last calibration ended ("" = none yet)
        # Requests so far (the ctl reply and status name the one they are about) and
        # how the last one stands: "", "pending", "rom" (the base pose held, the range
        # of motion under way), "saving" (in use, its file being written off the
        # loop), "calibrated", "not_saved" (in use, its file not written),
        # "refused", "failed" (an internal error: the old one kept), "expired".
        self.id = 0
        self.state = ""
        self.stream: Any = None  # where the frames come from (its input)
        # A range of motion after the base pose (``ctl calibrate --rom``): seconds
        # wanted (0: none), the base pose held while it is collected, its frames.
        self.rom_s = 0.0
        self.base: Any = None  # (frames, labels, times_s) once still
        self.rom_frames: list[np.ndarray] = []
        self.rom_times: list[tuple[float, int, int]] = []
        self.limit = RateLimiter(min_interval_s)
        # The calibration file being written off the loop, and the newest waiting
        # for it: (request id, calibration, path, what it was calibrated on).
        self._save: Build | None = None
        self._next_save: tuple[int, Any, str, str] | None = None

    @property
    def pending(self) -> bool:
        """A calibration request is collecting frames."""
        return self.target > 0

    def status(self) -> dict[str, Any]:
        """The performer's calibration state (status)."""
        return {
            "calibrating": self.target > 0,
            "calibration_message": self.message,
            "calibration_id": self.id,
            "calibration_state": self.state,
            "calibration_saving": self._save is not None,
        }

    def request(self, count: object = None, by: str = "", rom_s: object = None) -> str:
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
        perf, sh = self.perf, self.shared
        if not perf.body:
            raise ValueError(
                f"{perf.label} has no body (body = false): nothing to calibrate"
            )
        if count is None:
            n = perf.config.calibrate_frames
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
            if not perf.rig.functional:
                raise ValueError(
                    f"rig {perf.rig.name} has no [functional] joints: a range of "
                    "motion has nothing to place"
                )
        now = time.monotonic_ns()
        if not self.limit.allow(now):
            sh.stats.rate_limited += 1
            raise ValueError(
                "rate limited: one calibration request per "
                f"{sh.config.control.min_interval_s:g} s"
            )
        self.target = n
        self.shared.bump()  # its frames wanted: the one-call path disarmed
        self.frames = []
        self.times = []
        self.labels = ()
        self.requested_by = by
        self.last_ns = now
        self.id += 1
        self.state = "pending"
        self.stream = None
        self.rom_s = rom
        self._end_rom()
        sh.recording.event("calibration_requested", count=n, by=by, rom_s=self.rom_s)
        logger.info("calibration requested (%s): averaging %d frames", by, n)
        if rom_s is None:
            return f"calibrating over the next {n} frames: hold the base pose"
        return (
            f"calibrating over the next {n} frames: hold the base pose, then move "
            f"each joint through its range for {self.rom_s:g} s"
        )

    def collect(self, stream: FrameSource) -> None:
        """One accepted frame of the performer's (its view of the input's)."""
        if self.base is not None:
            self._collect_rom_frame(stream)
            return
        labels = stream.current.label_set.labels
        if self.labels and labels != self.labels:
            self.frames = []  # the marker layout changed: start again
            self.times = []
        self.labels = labels
        self.stream = stream
        frame = stream.current.frame
        self.frames.append(frame.markers_world.copy())
        self.times.append(
            (frame.source_time_s, frame.frame_id, frame.t_ns)
        )  # fmt: skip
        self.last_ns = time.monotonic_ns()
        if len(self.frames) >= self.target:
            self._finish_calibration()

    def _collect_rom_frame(self, stream: FrameSource) -> None:
        """One frame of the range of motion; the last one calibrates."""
        frame = stream.current.frame
        base: tuple[np.ndarray, tuple[str, ...], np.ndarray] = self.base
        if stream.current.label_set.labels != base[1]:
            self._refuse_calibration(
                "the marker labels changed during the range of motion"
            )
            return
        self.rom_frames.append(frame.markers_world.copy())
        self.rom_times.append((frame.source_time_s, frame.frame_id, frame.t_ns))
        self.last_ns = time.monotonic_ns()
        span = _window_times_s(
            [self.rom_times[0], self.rom_times[-1]],
            self.shared.config.validate.rate_hz,
        )
        if span[1] - span[0] >= self.rom_s:
            frames, labels, times_s = base
            rom = (
                np.stack(self.rom_frames), labels,
                {"live": True, "seconds": self.rom_s,
                 "frames": len(self.rom_frames)},
            )  # fmt: skip
            self._calibrate_on(frames, labels, times_s, rom)

    def tick(self, now_ns: int) -> None:
        """Expire a pending calibration that has collected no frame for
        ``performer.calibrate_timeout_s`` (nothing changes; one line says so); say
        how a calibration file's or a face training set's save (off the loop)
        ended."""
        if self._save is not None and self._save.done():
            self._saved(self._save)
        face = self.perf.face
        if face is not None and face.averaging:
            self._face_captured(face.take_captured())
        if face is not None and face.saving:
            self._face_saved(face.take_saved())
        if not self.target:
            return
        timeout_s = self.perf.config.calibrate_timeout_s
        if now_ns - self.last_ns < int(timeout_s * 1e9):
            return
        got, wanted = len(self.frames), self.target
        self._end_calibration_request()
        self.shared.stats.calibrations_expired += 1
        self.state = "expired"
        msg = (
            f"calibration expired: no marker frames for {timeout_s:g} s "
            f"({got} of {wanted} collected); the old calibration is kept"
        )
        self.message = msg
        self.shared.recording.event("calibration_expired", collected=got, count=wanted)
        self.shared.out(self._named(msg))

    def collect_face(self, stream: FrameSource) -> None:
        """One accepted frame for the face capture under way."""
        face = self.perf.face
        assert face is not None
        labels = stream.current.label_set.labels
        done = face.collect(stream.current.frame.markers_world, labels)
        if done is not None:  # refused at once
            self._face_captured((*done, labels))
        elif face.averaging and self.shared.config.loop.process_every_frame:
            face.wait_averaged()  # offline replay: in use from the next frame
            self._face_captured(face.take_captured())
        # (else averaged off the loop: taken by tick)

    def _face_captured(self, outcome: tuple[bool, str, tuple[str, ...]] | None) -> None:
        """A face capture ended (its averaging done off the loop, or refused): its
        training set in use, one line, recorded."""
        if outcome is None:
            return
        ok, msg, labels = outcome
        if ok:
            # The next frame solves with the new training set; pipelines rebuilt now,
            # off the frame that completed the capture.
            self.shared.stats.face_captures += 1
            self.perf.use_face(labels, self._sources())
        self.shared.recording.event("face_capture", ok=ok, message=msg)
        self.shared.out(self._named(msg))

    def _face_saved(self, outcome: tuple[bool, str] | None) -> None:
        """A face training set's save ended: one line; a failure counted."""
        if outcome is None:
            return
        ok, msg = outcome
        if not ok:
            self.shared.stats.face_save_failures += 1
        self.shared.out(self._named(msg))

    def request_face(self, name: str, count: int | None = None, by: str = "") -> str:
        """Start capturing face pose ``name`` over the next ``count`` frames."""
        face = self.perf.face
        if face is None:
            raise ValueError("the face is off: set [face] enabled = true")
        msg = face.request_capture(name, count)
        self.shared.recording.event("face_capture_requested", name=name, by=by)
        return msg

    def _end_calibration_request(self) -> None:
        """Nothing pending any more (the frames collected let go)."""
        self.target = 0
        self.shared.bump()  # (the one-call path may arm again)
        self.frames = []
        self.times = []
        self._end_rom()

    def _end_rom(self) -> None:
        """No range of motion under way."""
        self.base = None
        self.rom_frames = []
        self.rom_times = []

    def _finish_calibration(self) -> None:
        """The base pose is collected: still, it calibrates, or holds for the range
        of motion when one was asked for."""
        frames = np.stack(self.frames)
        labels = self.labels
        times = self.times
        self.frames = []
        self.times = []
        limit = self.perf.config.calibrate_max_speed_m_s
        times_s = _window_times_s(times, self.shared.config.validate.rate_hz)
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
        if self.rom_s > 0.0:
            self.base = (frames, labels, times_s)
            self.state = "rom"
            self.last_ns = time.monotonic_ns()
            msg = (
                f"base pose held ({frames.shape[0]} frames): move each joint "
                f"through its range for {self.rom_s:g} s"
            )
            self.message = msg
            self.shared.out(self._named(msg))
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
                self.perf.rig, frames, labels, self._base_pose_source(times_s),
                base_pose={"live": True, "frames": int(frames.shape[0]),
                           "requested_by": self.requested_by},
                rom=rom, up_levers=self.shared.config.solve.method == "construction",
            )  # fmt: skip
        except (SanityError, CalibrationError) as exc:
            self._refuse_calibration(str(exc))
            return
        except Exception as exc:  # a fault of ours: counted, said, never fatal
            self._calibration_failed(exc)
            return
        for note in notes:
            self.shared.out(self._named(f"calibration warning: {note}"))
        # Atomic: the loop thread is the only reader; the next frame uses the new one,
        # with its pipeline built now rather than on the next frame.
        self.perf.use_calibration(cal, labels, self._sources())
        self.shared.stats.calibrations += 1
        self.state = "calibrated"  # "saving" below while its file is written
        path = self.perf.config.save_calibration or self.perf.config.calibration
        self.shared.recording.event(
            "calibrated", frames=int(frames.shape[0]), by=self.requested_by,
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
        if path:  # written off the loop; its line when the write ends (tick)
            self.state = "saving"
            self.message = f"calibrated on {what}; saving {path}"
            self._save_later((self.id, cal, path, what))
            return
        msg = f"calibrated on {what} (not saved: no path)"
        self.message = msg
        self.shared.out(self._named(msg))

    # ---- the calibration file, written off the loop ----------------------------------

    def _save_later(self, want: tuple[int, Any, str, str]) -> None:
        """Write ``want``'s calibration (request id, calibration, path, what it was
        calibrated on) on a worker: now, or after the one being written (only the
        newest waits)."""
        if self._save is None:
            _, cal, path, _ = want
            self._save = Build(want, cal.save, path)
        else:
            self._next_save = want

    def _saved(self, job: Build) -> None:
        """A calibration file's write ended (every loop pass, ``tick``): the next
        one started; its line said; a failure counted; the request's state and
        message, when it is still the latest, "calibrated" or "not_saved"."""
        self._save = None
        if self._next_save is not None:
            self._save_later(self._next_save)
            self._next_save = None
        ident, _, path, what = job.want
        try:
            job.take()
        except Exception as exc:  # OSError: the disk; any other: said, never fatal
            why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            msg, state = f"calibrated on {what}; NOT saved: {why}", "not_saved"
            self.shared.stats.calibration_save_failures += 1
            logger.warning("%s", self._named(msg))
        else:
            msg, state = f"calibrated on {what}; saved {path}", "calibrated"
        if ident == self.id and self.state == "saving":
            self.state = state
            self.message = msg
        self.shared.out(self._named(msg))

    def close(self) -> None:
        """Finish writing (the daemon's close, never in the loop): the write under
        way waited for, the one waiting written here; a failure logged."""
        job, self._save = self._save, None
        if job is not None:
            job.wait()
            if job.error is not None:
                logger.warning("calibration NOT saved: %s", job.error)
        pending, self._next_save = self._next_save, None
        if pending is not None:
            _, cal, path, _ = pending
            try:
                cal.save(path)
            except Exception as exc:  # the old file is whole (an atomic save)
                logger.warning("calibration NOT saved: %s", exc)

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
        self.shared.stats.calibrations_refused += 1
        self.state = "refused"
        self.message = msg
        self.shared.recording.event("calibration_refused", message=msg)
        self.shared.out(self._named(msg))

    def _calibration_failed(self, exc: Exception) -> None:
        """``calibrate_checked`` raised something other than a refusal (a fault of
        ours, not the performer's): counted (``calibration_failures``), one line
        (its traceback in the log), recorded; the old calibration keeps streaming,
        its file untouched, and the loop serves on."""
        why = str(exc).splitlines()[0] if str(exc) else ""
        msg = (
            f"calibration failed: internal error ({type(exc).__name__}: {why}); the "
            "old calibration is kept: see the daemon's log"
        )
        logger.error("%s", self._named(msg), exc_info=exc)
        self.shared.stats.calibration_failures += 1
        self.state = "failed"
        self.message = msg
        self.shared.recording.event("calibration_failed", message=msg)
        self.shared.out(self._named(msg))

    def _base_pose_source(self, times_s: np.ndarray) -> BasePoseSource:
        """How the calibration frames were read: the unit and up axis of the input
        they came from (``[input.osc]`` / ``[input.zmq]``), the frame rate of the
        window; a refusal names the config key to change."""
        stream = getattr(self.stream, "stream", self.stream)  # a view's
        kind = self._kind_of(stream)
        key = f"input.{kind}" if kind != "source" else ""
        cfg = getattr(self.shared.config.input, key.split(".")[-1]) if key else None
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
        return f"{self.perf.name}: {msg}" if self.perf.name else msg


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
