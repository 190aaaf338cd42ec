"""Health: the status document (``retargetd ctl status --json``) and the one-line stats
summary printed every ``stats_interval_s``.
"""

from __future__ import annotations

import logging
import math
import time
from typing import Any

import numpy as np

from retargetd.daemon.body.solve import FLAG_HELD
from retargetd.daemon.live.kernel_drops import udp_kernel_drops
from retargetd.daemon.live.sources import capture_stats
from retargetd.daemon.live.state import DaemonState
from retargetd.daemon.live.stats import POST_PREFIX

logger = logging.getLogger(__name__)


class StatusMixin(DaemonState):
    """The status document and the periodic stats line."""

    def status(self) -> dict[str, Any]:
        """The status document (``retargetd ctl status --json``)."""
        # None until the first frame: NaN is not JSON (jq and browsers refuse it).
        latency = {
            k: [_round_or_none(p50), _round_or_none(p99)]
            for k, (p50, p99) in self.stats.latency_us().items()
        }
        up_s = (time.monotonic_ns() - self._t0_ns) * 1e-9
        occluded, flagged = self._occluded_and_held()
        performers = self.performers_status()
        return {
            "uptime_s": round(up_s, 3),
            "rig": self.rig.name,  # the first performer's (all: "performers")
            "calibrated": all(p["calibrated"] for p in performers),
            "calibrating": any(p["calibrating"] for p in performers),
            "calibration_message": self._calib_message,
            "calibration_id": self._calib_id,
            "calibration_state": self._calib_state,
            "performers": performers,
            "endpoints": self.endpoints,
            "counters": {
                **self.stats.counters(),
                "prewarm": self._prewarm.touches,
                "prewarm_resets": self._prewarm.resets,  # after a flagged/slow touch
                # markers occluded for a coordinate past max_coordinate_m, all inputs
                "implausible_markers": int(
                    self.osc_stream.implausible[0] + self.zmq_stream.implausible[0]
                ),
                # episodes of descriptor exhaustion, and the failed accepts seen
                "fd_episodes": self._watch.fd_episodes,
                "fd_accept_failures": self._watch.fd_accept_failures,
            },
            # phases of a loop iteration over 50 ms, by name (stalls.py)
            "loop_stalls": self._stalls.status(),
            "fd_exhausted": self._watch.exhausted,  # an episode is going on
            # CURVE handshakes refused, by socket and reason (sockets with a key)
            "curve_refused": self._watch.status(),
            "fps_in": self._fps(self.stats.frames_in, 1),
            "fps_out": self._fps(self.stats.frames_out, 2),
            "fps_window_s": round((time.monotonic_ns() - self._window[0]) * 1e-9, 3),
            "drops": {
                "osc": self.osc_stream.counters.as_dict(),
                "zmq": self.zmq_stream.counters.as_dict(),
            },
            # Label announcements adopted or confirming (not in "drops"), per input.
            "labels_taken": {
                "osc": self.osc_stream.labels_taken,
                "zmq": self.zmq_stream.labels_taken,
            },
            # Datagrams the kernel dropped (receive buffer full), per UDP input;
            # None where unknown (not Linux) or the input is off.
            "kernel_drops": {
                "osc": udp_kernel_drops(self._osc),
                "show_control": udp_kernel_drops(self._show),
            },
            "latency_us": latency,
            "occluded_markers": occluded,
            "held_bones": flagged,
            "show_control": {"refused": dict(self._show_counters)},
            "record": self.recording.status(),
            "face": self.face.status() if self.face is not None else None,
            "validate": self._validate_status(),
            "capture": self._capture_status(),
            "props": self.props.status(),  # [[prop]] (live/props.py)
        }

    def _occluded_and_held(self) -> tuple[list[str], list[str]]:
        """The current performer's occluded rig markers and held bones, from the
        last frame its (first) pipeline solved."""
        pipe = next(iter(self._pipelines.values()), None)
        occluded: list[str] = []
        flagged: list[str] = []
        if pipe is not None:
            seen = getattr(pipe.solver, "_seen", None)  # the construction's markers
            pts_seen = (
                seen[: len(self.rig.markers)]
                if seen is not None
                else np.isfinite(pipe.pose.marker_residual)  # the fit's
            )
            occluded = [
                m for m, s in zip(self.rig.marker_names, pts_seen, strict=True) if not s
            ]
            flags = pipe.pose.bone_flags
            names = self.rig.bone_names
            flagged = [b for b, f in zip(names, flags, strict=True) if f & FLAG_HELD]
        return occluded, flagged

    def _validate_status(self) -> dict[str, Any] | None:
        v = self.validator
        if v is None:
            return None
        status: dict[str, Any] = v.status()
        return status

    def _fps(self, count: int, which: int) -> float:
        """Frames per second since the last stats line (the recent rate, not the
        lifetime average: it falls to 0 when a source stops)."""
        dt = (time.monotonic_ns() - self._window[0]) * 1e-9
        return round((count - self._window[which]) / dt, 2) if dt > 0 else 0.0

    def stats_line(self) -> str:
        """The periodic one-line health summary."""
        s = self.status()
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
            + self.performers_line(s["performers"])
            + ("" if s["calibrated"] or self._multi else " | NOT CALIBRATED")
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
