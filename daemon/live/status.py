"""Health, one part (:class:`Health`): the status document (``retargetd ctl status
--json``) and the one-line stats summary printed every ``stats_interval_s``, read from
the other parts' counters.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from typing import Any

from retargetd.daemon.live.inputs import Inputs
from retargetd.daemon.live.performers import Performers
from retargetd.daemon.live.prewarm import Prewarm
from retargetd.daemon.live.props import LiveProps
from retargetd.daemon.live.recording import LiveRecording
from retargetd.daemon.live.sources import capture_stats
from retargetd.daemon.live.spin import Spin, spin_counters
from retargetd.daemon.live.stalls import LoopStalls
from retargetd.daemon.live.stats import POST_PREFIX, LoopStats
from retargetd.daemon.live.watch import SocketWatch

logger = logging.getLogger(__name__)


class Health:
    """The status document and the periodic stats line, read from the parts'
    counters (it changes none of them).

    Args:
        stats: the loop's counters.
        performers: every performer (their status, the first's calibration).
        inputs: the marker inputs (drops by reason, label sets taken).
        recording: the live recording.
        props: the ``[[prop]]`` part.
        watch: the bound ZeroMQ sockets' monitors (CURVE refusals, descriptors).
        stalls: the loop's phases over 50 ms.
        prewarm: the fit's warm touches.
        spin: the loop's spins before a frame (None: ``[loop] spin_us`` off).
        endpoints: what is listening where (``open`` fills it).
        t0_ns: the daemon's start.
        capture: the capture input's status (None: no ``[input] source``).
        control: the control part's status (show control refused, its kernel
            drops).
    """

    def __init__(
        self,
        stats: LoopStats,
        performers: Performers,
        inputs: Inputs,
        recording: LiveRecording,
        props: LiveProps,
        watch: SocketWatch,
        stalls: LoopStalls,
        prewarm: Prewarm,
        spin: Spin | None,
        endpoints: dict[str, str],
        t0_ns: int,
        capture: Callable[[], dict[str, Any] | None],
        control: Callable[[], dict[str, Any]],
    ) -> None:
        self.stats = stats
        self.performers = performers
        self.inputs = inputs
        self.recording = recording
        self.props = props
        self.watch = watch
        self.stalls = stalls
        self.prewarm = prewarm
        self.spin = spin
        self.endpoints = endpoints
        self.t0_ns = t0_ns
        self._capture = capture
        self._control = control
        # (t_ns, frames_in, frames_out) at the last stats line: fps over that window.
        self._window = (t0_ns, 0, 0)

    def roll(self, now_ns: int) -> None:
        """A stats line was printed: the fps window starts again."""
        self._window = (now_ns, self.stats.frames_in, self.stats.frames_out)

    def document(self) -> dict[str, Any]:
        """The status document (``retargetd ctl status --json``)."""
        # None until the first frame: NaN is not JSON (jq and browsers refuse it).
        latency = {
            k: [_round_or_none(p50), _round_or_none(p99)]
            for k, (p50, p99) in self.stats.latency_us().items()
        }
        up_s = (time.monotonic_ns() - self.t0_ns) * 1e-9
        first = self.performers.first
        occluded, flagged = first.path.occluded_and_held()
        calib = first.calib.status()
        performers = self.performers.status()
        inputs = self.inputs.status()
        control = self._control()
        return {
            "uptime_s": round(up_s, 3),
            "rig": first.rig.name,  # the first performer's (all: "performers")
            "calibrated": all(p["calibrated"] for p in performers),
            "calibrating": any(p["calibrating"] for p in performers),
            "calibration_message": calib["calibration_message"],
            "calibration_id": calib["calibration_id"],
            "calibration_state": calib["calibration_state"],
            "performers": performers,
            "endpoints": self.endpoints,
            "counters": {
                **self.stats.counters(),
                "prewarm": self.prewarm.touches,
                "prewarm_resets": self.prewarm.resets,  # after a flagged/slow touch
                # [loop] spin_us: windows spun in, and those a frame ended
                **spin_counters(self.spin),
                # markers occluded for a coordinate past max_coordinate_m, all inputs
                "implausible_markers": inputs["implausible_markers"],
                # episodes of descriptor exhaustion, and the failed accepts seen
                "fd_episodes": self.watch.fd_episodes,
                "fd_accept_failures": self.watch.fd_accept_failures,
            },
            # phases of a loop iteration over 50 ms, by name (stalls.py)
            "loop_stalls": self.stalls.status(),
            # pipelines (and face stages) being built off the loop (rebuild.py)
            "pipelines_building": self.performers.building(),
            # live validators being built off the loop (validation.py)
            "validators_building": self.performers.validators_building(),
            # [loop] solve_threads: the threads solving (the loop's included), the
            # solve threads alive and the solves they ran (solve_threads.py)
            "solve_threads": self._solve_threads(),
            "fd_exhausted": self.watch.exhausted,  # an episode is going on
            # CURVE handshakes refused, by socket and reason (sockets with a key)
            "curve_refused": self.watch.status(),
            "fps_in": self._fps(self.stats.frames_in, 1),
            "fps_out": self._fps(self.stats.frames_out, 2),
            "fps_window_s": round((time.monotonic_ns() - self._window[0]) * 1e-9, 3),
            "drops": inputs["drops"],
            # Label announcements adopted or confirming (not in "drops"), per input.
            "labels_taken": inputs["labels_taken"],
            # Datagrams the kernel dropped (receive buffer full), per UDP input;
            # None where unknown (not Linux) or the input is off.
            "kernel_drops": {
                "osc": inputs["kernel_drops_osc"],
                "show_control": control["kernel_drops"],
            },
            "latency_us": latency,
            "occluded_markers": occluded,
            "held_bones": flagged,
            "show_control": {"refused": control["refused"]},
            "record": self.recording.status(),
            "face": first.face.status() if first.face is not None else None,
            "validate": self.performers.first.path.validation_status(),
            "capture": self._capture(),
            "props": self.props.status(),  # [[prop]] (live/props.py)
        }

    def _solve_threads(self) -> dict[str, int]:
        """``[loop] solve_threads`` as running: 1 thread, none alive, no solves when
        every solve is on the loop thread (one performer, or ``solve_threads`` 1)."""
        t = self.performers.solve_threads
        if t is None:
            return {"threads": 1, "alive": 0, "worker_solves": 0}
        return {"threads": t.n_threads, "alive": t.alive(), "worker_solves": t.solves}

    def _fps(self, count: int, which: int) -> float:
        """Frames per second since the last stats line (the recent rate, not the
        lifetime average: it falls to 0 when a source stops)."""
        dt = (time.monotonic_ns() - self._window[0]) * 1e-9
        return round((count - self._window[which]) / dt, 2) if dt > 0 else 0.0

    def line(self) -> str:
        """The periodic one-line health summary."""
        s = self.document()
        lat = s["latency_us"]
        drops = {
            **s["drops"]["osc"],
            **{f"zmq.{k}": v for k, v in s["drops"]["zmq"].items()},
        }
        drops.pop("accepted", None)
        drops.pop("zmq.accepted", None)
        c = s["counters"]
        return (
            f"fps in {s['fps_in']:.1f} out {s['fps_out']:.1f} | latency us p50/p99 "
            f"solve {_us(lat['solve'][0])}/{_us(lat['solve'][1])} "
            f"recv->sent {_us(lat['receive_to_sent'][0])}/"
            f"{_us(lat['receive_to_sent'][1])}"
            + _post_stages(lat)
            + f" | stale {c['stale']} overruns {c['overruns']} send drops "
            f"{c['send_drops']} | drops {drops or 0} | occluded "
            f"{len(s['occluded_markers'])} held {len(s['held_bones'])}"
            f" | kernel_drops {sum(v for v in s['kernel_drops'].values() if v)}"
            + capture_stats(s["capture"])
            + self.performers.line(s["performers"])
            + (
                ""
                if s["calibrated"] or self.performers.several
                else " | NOT CALIBRATED"
            )
            + (
                f" | REC {s['record']['path']} dropped {s['record']['dropped']}"
                if s["record"]["active"]
                else ""
            )
            + (
                f" | face head lost {c['face_head_lost']}/{c['face_solved']}"
                + _unobserved(s["face"])
                if s["face"] is not None
                else ""
            )
            + (
                f" | validated {c['validated']} flagged {c['validation_flagged']} "
                f"dropped {c['validation_drops']}"
                if s["validate"] is not None
                else ""
            )
        )


NOT_CALIBRATED = " | NOT CALIBRATED"


def _unobserved(face: dict[str, Any]) -> str:
    """`` unobserved 2 (eyeLookUpLeft eyeWideLeft)``: the shapes left out (issue 32)."""
    names = face.get("unobserved") or []
    return f" unobserved {len(names)} ({' '.join(names)})" if names else ""


def _post_stages(latency: dict[str, Any]) -> str:
    """`` | post twist 2/3 one_euro 3/4``: each ``[[pipeline]]`` stage's p50/p99 µs."""
    parts = [
        f"{k[len(POST_PREFIX) :]} {_us(v[0])}/{_us(v[1])}"
        for k, v in latency.items()
        if k.startswith(POST_PREFIX)
    ]
    return f" | post {' '.join(parts)}" if parts else ""


def _round_or_none(value: float) -> float | None:
    return round(value, 1) if math.isfinite(value) else None


def _us(value: float | None) -> str:
    return "-" if value is None else f"{value:.0f}"
