"""Several performers on one daemon (``[[performer]]`` tables): the loop's work done
once per performer, each as the *current* performer (``state.OfPerformer``).

A frame from an input is solved for every performer reading that input, in config
order, each from its own view of the frame (its labels, prefix stripped; see
``performer.py``), with its own pipeline, calibration, face and VMC destination; the
pose messages of all of them go out on the one pose stream, each carrying its
performer id. A live calibration, face capture, the calibration timeout and the
VMC state datagrams are per performer; control commands name one (``"performer":
NAME``, ``retargetd ctl calibrate --performer NAME``), which may be left out when
there is only one. With one performer (no ``[[performer]]``) everything here is a
direct call of what the loop did before.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

from retargetd.daemon.live.performer import FrameSource, Performer
from retargetd.daemon.live.state import DaemonState
from retargetd.protocols.marker_input import LabelSet, MarkerStream

logger = logging.getLogger(__name__)

#: Commands that act for one performer (the others act for the daemon).
PER_PERFORMER_COMMANDS = ("calibrate", "face-capture")


class PerformersMixin(DaemonState):
    """The per-performer loop: solve, collect, restart, flags, ticks, control."""

    # ---- per frame ---------------------------------------------------------------

    def _solve(self, stream: MarkerStream, t_ns: int) -> None:
        """Solve and send the stream's current frame for every performer on it."""
        stats = self.stats
        kind = self.inputs.kind_of(stream)
        try:
            for perf in self.performers:
                source = perf.frame_of(stream, kind)
                if source is None:
                    continue
                self._perf = perf
                out, unsolved, unseen = stats.frames_out, stats.unsolved, stats.unseen
                self._solve_and_send(source, t_ns)
                ps = perf.stats
                if stats.frames_out != out:
                    ps.frames_out += 1
                    j = (stats.ring_pos - 1) % stats.rings.shape[1]
                    r = stats.rings
                    ps.record(int(r[0, j]), int(r[1, j]), int(r[2, j]), int(r[3, j]))
                elif stats.unsolved != unsolved:
                    ps.unsolved += 1
                elif stats.unseen != unseen:
                    ps.unseen += 1
        finally:
            self._perf = self.performers[0]

    def _collect(self, stream: MarkerStream) -> None:
        """Hand an accepted frame to every live calibration and face capture."""
        kind = ""
        for perf in self.performers:
            capturing = perf.face is not None and perf.face.capturing
            if not perf.calib_target and not capturing:
                continue
            kind = kind or self.inputs.kind_of(stream)
            source = perf.frame_of(stream, kind)
            if source is None:
                continue
            with self._acting_for(perf):
                if perf.calib_target:
                    self._collect_calibration_frame(source)
                if capturing:
                    self._collect_face_frame(source)

    def _restart_pipelines(self, stream: MarkerStream) -> None:
        """The source of ``stream`` restarted: every pipeline on it starts over."""
        for perf in self.performers:
            key = perf.key_of(stream)
            if not key:
                continue
            stage = perf.face_stages.get(key)  # a face alone (face_only.py)
            if stage is not None:
                stage.face.solver.reset()
            pipe = perf.pipelines.get(key)
            if pipe is not None:
                pipe.solver.reset()
                pipe.vmc.reset_continuity()
                if pipe.face is not None:
                    pipe.face.solver.reset()

    def _flag_frames(self, bits: int) -> None:
        """Set frame flags on every performer's next pose (restarted, dropped)."""
        for perf in self.performers:
            perf.frame_flags |= bits

    def _prepare_views(self, stream: MarkerStream, label_set: LabelSet) -> None:
        """A label set was announced: build every performer's column index for it
        now (off the hot path), so its first frame finds them."""
        if stream.label_set is not label_set:
            return
        kind = self.inputs.kind_of(stream)
        for perf in self.performers:
            view = perf.view_of(stream, kind)
            if view is not None and not view.whole:
                view.prepare(label_set)

    def _own_streams(self) -> list[FrameSource]:
        """What the current performer reads of each input now: where a new
        calibration's pipelines are built at once."""
        sources: list[FrameSource] = []
        for s in self.inputs.streams():
            source = self._perf.frame_of(s, self.inputs.kind_of(s))
            if source is not None:
                sources.append(source)
        return sources

    # ---- per tick ----------------------------------------------------------------

    def _each_performer(self, fn: Callable[[int], None], now_ns: int) -> None:
        """``fn(now_ns)`` once for every performer, each the current one."""
        try:
            for perf in self.performers:
                self._perf = perf
                fn(now_ns)
        finally:
            self._perf = self.performers[0]

    @contextmanager
    def _acting_for(self, perf: Performer) -> Iterator[None]:
        """Make ``perf`` the current performer (the one before again after)."""
        before, self._perf = self._perf, perf
        try:
            yield
        finally:
            self._perf = before

    # ---- control -----------------------------------------------------------------

    def performer_named(self, name: object) -> Performer:
        """The performer a request names; None/"" = the only one.

        Raises:
            ValueError: an unknown name, or none given with several performers.
        """
        names = ", ".join(p.name for p in self.performers if p.name)
        if name is None or name == "":
            if len(self.performers) == 1:
                return self.performers[0]
            raise ValueError(
                f"this daemon has {len(self.performers)} performers ({names}): name "
                "one (--performer NAME)"
            )
        if not isinstance(name, str):
            raise ValueError(f"'performer' must be a name string; got {name!r}")
        for perf in self.performers:
            if perf.name and perf.name == name:
                return perf
        known = f"performers: {names}" if names else "one unnamed performer"
        raise ValueError(f"unknown performer {name!r} (this daemon has {known})")

    def _control_for(self, req: dict[str, Any]) -> dict[str, Any]:
        """A control request acting for the performer it names (``performer``);
        commands for the daemon as a whole (status, reload, record) take none."""
        cmd = req.get("cmd")
        name = req.get("performer")
        if cmd == "calibrate" and req.get("prop") is not None:  # a [[prop]]'s
            if not self.config.control.calibrate:
                raise ValueError("calibrate is off on this path (control.calibrate)")
            msg = self.props.request_calibration(req["prop"], req.get("count"), "ctl")
            return {"ok": True, "message": msg, "prop": req["prop"]}
        if cmd not in PER_PERFORMER_COMMANDS:
            if name is not None:
                raise ValueError(
                    f"{cmd!r} acts for the whole daemon: leave out 'performer' "
                    f"(it applies to {', '.join(PER_PERFORMER_COMMANDS)})"
                )
            return self._control(req)
        perf = self.performer_named(name)
        with self._acting_for(perf):
            reply = self._control(req)
        if perf.name:
            reply["performer"] = perf.name
        return reply

    def calibrate_performer(self, name: object, count: object, by: str) -> str:
        """``request_calibration`` for the performer named (show control)."""
        perf = self.performer_named(name)
        with self._acting_for(perf):
            msg = self.request_calibration(count, by)
        return f"{perf.name}: {msg}" if perf.name else msg

    # ---- status ------------------------------------------------------------------

    def performers_status(self) -> list[dict[str, Any]]:
        """``status["performers"]``: one document per performer."""
        docs = []
        for perf in self.performers:
            with self._acting_for(perf):
                occluded, held = self._occluded_and_held()
            s = perf.stats
            lat = s.latency_us()
            docs.append(
                {
                    "id": perf.index,
                    "name": perf.name,
                    "prefix": perf.prefix,
                    "input": perf.input,
                    "rig": perf.rig.name,
                    "body": perf.body,
                    # a face alone has nothing to calibrate
                    "calibrated": perf.calibration is not None or not perf.body,
                    "calibrating": perf.calib_target > 0,
                    "calibration_message": perf.calib_message,
                    "calibration_id": perf.calib_id,
                    "calibration_state": perf.calib_state,
                    "calibration_match": _match_status(perf),
                    "vmc": f"{perf.vmc_addr[0]}:{perf.vmc_addr[1]}",
                    "frames_out": (
                        perf.stats.frames_out if self._multi else self.stats.frames_out
                    ),
                    "unsolved": (
                        perf.stats.unsolved if self._multi else self.stats.unsolved
                    ),
                    "latency_us": {
                        k: [_round(p50), _round(p99)]
                        for k, (p50, p99) in (
                            lat if self._multi else self.stats.latency_us()
                        ).items()
                    },
                    "occluded_markers": occluded,
                    "held_bones": held,
                    "face": perf.face.status() if perf.face is not None else None,
                    "validate": (
                        perf.validator.status() if perf.validator is not None else None
                    ),
                }
            )
        return docs

    def performers_line(self, docs: list[dict[str, Any]]) -> str:
        """The stats line's per-performer part (several performers only)."""
        if not self._multi:
            return ""
        parts = []
        for d in docs:
            p99 = d["latency_us"]["receive_to_sent"][1]
            state = "" if d["calibrated"] else " NOT CALIBRATED"
            parts.append(
                f"{d['name']} out {d['frames_out']} p99 "
                f"{'-' if p99 is None else f'{p99:.0f}'} us{state}"
            )
        return " | performers " + ", ".join(parts)


def _match_status(perf: Performer) -> dict[str, Any] | None:
    """``calibration_match`` of a performer's status: None before its first second
    of frames with its calibration has been checked (``body.match``)."""
    window = perf.match_window
    if window is None or window.result is None:
        return None
    found = window.result
    return {
        "matches": found.matches,
        "frames": found.frames,
        "warning": found.warning(),
        "segments": found.to_json(),
    }


def _round(value: float) -> float | None:
    return round(value, 1) if math.isfinite(value) else None
