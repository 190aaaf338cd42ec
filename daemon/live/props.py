"""The live daemon's props (``[[prop]]``): one part object the loop calls once per
accepted frame (:meth:`LiveProps.on_frame`), whatever the performers do.

Per prop and frame: its markers found in the frame's label set (once per label set),
a live calibration fed while one runs (``ctl calibrate --prop NAME``,
``/rtd/calibrate/prop NAME``), the rigid fit (``daemon/props``), its One Euro
smoothing (``smooth_min_cutoff_hz`` > 0; a held pose is not fed to the filter), then
out: a VMC bundle (``/VMC/Ext/Tra/Pos``, serial = its name, and ``/VMC/Ext/Cam`` for a
camera with its field of view) to its own ``vmc`` destination or to every performer's,
from a socket of its own, and a prop message (``RTDR``) on the pose stream through the
loop's pose send (so recordings carry it too). Nothing is allocated per frame but by
a running calibration; a send refused by the OS is counted, never raised.

A camera's field of view follows its ``fov_osc`` address on the show-control port: one
float (or int) argument, degrees, kept within (0, 180).
"""

from __future__ import annotations

import math
import socket
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from retargetd.daemon.live.config_props import PropConfig
from retargetd.daemon.live.config_schema import ConfigError
from retargetd.daemon.post.one_euro import OneEuroFilter
from retargetd.daemon.post.pose import PoseBuffer
from retargetd.daemon.props import kernel as pk
from retargetd.daemon.props.layout import PropError, calibrate_prop, load_layout
from retargetd.daemon.props.solve import PropParams, PropSolver
from retargetd.protocols.marker_input import LabelSet, MarkerStream
from retargetd.protocols.pose_props import (
    KIND_CAMERA,
    KIND_RIGID,
    PropEncoder,
    stamp_sent,
)
from retargetd.protocols.vmc_props import VmcPropEncoder

#: Frames a live calibration waits for before it expires: 10 s at 120 Hz (a prop
#: out of view that long is not being held still for its calibration).
CALIBRATE_EXPIRE_FRAMES = 1200


class LiveProp:
    """One prop's state: its solver (once calibrated), filter, encoders, counters."""

    def __init__(self, index: int, cfg: PropConfig) -> None:
        self.index, self.cfg, self.name = index, cfg, cfg.name
        self.params = PropParams(gate_m=cfg.gate_mm / 1000.0)
        self.solver: PropSolver | None = None
        if cfg.calibration:
            try:
                self.solver = PropSolver(load_layout(cfg.calibration), self.params)
            except PropError as exc:
                raise ConfigError(f"prop[{index}].calibration: {exc}") from None
        self.fov_deg = cfg.fov_deg
        self.filter = (
            OneEuroFilter(
                1,
                min_cutoff_hz=cfg.smooth_min_cutoff_hz,
                beta_rot=cfg.smooth_beta,
                beta_pos=cfg.smooth_beta,
            )
            if cfg.smooth_min_cutoff_hz > 0.0
            else None
        )
        self._raw = PoseBuffer.new(1)
        self.pose = PoseBuffer.new(1)  # what is sent: world_from_prop, origin
        camera = cfg.kind == "camera"
        self.vmc = VmcPropEncoder(cfg.name, camera=camera)
        self.msg = PropEncoder(index, cfg.name, KIND_CAMERA if camera else KIND_RIGID)
        self.bound: LabelSet | None = None
        self.cols = np.zeros(0, dtype=np.int64)  # calibration: its markers' rows
        self.calib_labels: tuple[str, ...] = ()
        self.calib_frames: list[np.ndarray] = []
        self.calib_times: list[float] = []
        self.calib_target = 0
        self.calib_waited = 0
        self.calib_state = "calibrated" if self.solver is not None else "uncalibrated"
        self.calib_message = ""
        self.frames = self.held = self.swaps = 0
        self.flags = pk.FLAG_NEVER | pk.FLAG_HELD

    def bind(self, label_set: LabelSet) -> None:
        """Find its markers among a new label set's (off the per-frame path)."""
        self.bound = label_set
        labels = label_set.labels
        if self.cfg.markers:
            self.calib_labels = tuple(m for m in self.cfg.markers if m in labels)
        else:
            prefix = self.cfg.prefix
            self.calib_labels = tuple(
                x for x in labels if prefix and x.startswith(prefix)
            )
        index = {name: i for i, name in enumerate(labels)}
        self.cols = np.array([index[m] for m in self.calib_labels], dtype=np.int64)
        if self.solver is not None:
            self.solver.bind(labels)
            self.solver.reset()
        if self.filter is not None:
            self.filter.reset()

    def status(self) -> dict[str, Any]:
        s = self.solver
        return {
            "name": self.name,
            "kind": self.cfg.kind,
            "calibration": self.calib_state,
            "calibration_message": self.calib_message,
            "markers": len(s.layout.labels)
            if s is not None
            else len(self.calib_labels),
            "frames": self.frames,
            "held": self.held,
            "swaps": self.swaps,
            "flags": self.flags,
            "fov_deg": self.fov_deg,
            "position_m": [round(float(v), 4) for v in self.pose.root_pos],
            "quat_wxyz": [
                round(float(v), 5) for v in self.pose.parent_from_bone_quat[0]
            ],
        }


class LiveProps:
    """The daemon's props (see the module docstring).

    Args:
        props: the ``[[prop]]`` tables.
        vmc_destinations: every performer's VMC (host, port), used by a prop
            without its own ``vmc`` ([output.vmc] off: empty, and no prop sends VMC).
        send_pub: the loop's pose send (``parts, t_ns``): the pose stream and the
            recording.
        out: where lines go (a calibration's outcome).
    """

    def __init__(
        self,
        props: tuple[PropConfig, ...],
        vmc_destinations: tuple[tuple[str, int], ...],
        send_pub: Callable[[list[Any], int], None],
        out: Callable[[str], None],
    ) -> None:
        self.props = [LiveProp(i, cfg) for i, cfg in enumerate(props)]
        self._send_pub = send_pub
        self._out = out
        self.vmc_drops = 0
        self._dests: list[tuple[tuple[str, int], ...]] = []
        for p in self.props:
            if p.cfg.vmc:
                host, _, port = p.cfg.vmc.rpartition(":")
                self._dests.append(((host, int(port)),))
            else:
                self._dests.append(vmc_destinations)
        self._fov_by_address = {p.cfg.fov_osc: p for p in self.props if p.cfg.fov_osc}
        self._sock: socket.socket | None = None
        if any(self._dests):
            self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self._sock.setblocking(False)

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    # ---- per frame -------------------------------------------------------------------

    def on_frame(self, stream: MarkerStream, t_ns: int) -> None:
        """Solve and send every prop on the stream's current frame."""
        labels = stream.label_set
        if labels is None or not self.props:
            return
        frame = stream.current.frame
        pts, valid = frame.markers_world, frame.valid
        for i, p in enumerate(self.props):
            if p.bound is not labels:
                if p.bound is not None and p.bound.labels == labels.labels:
                    p.bound = labels  # the same names re-announced: no restart
                else:
                    p.bind(labels)
            if p.calib_target:
                self._collect(p, pts, valid, frame.source_time_s, t_ns)
            solver = p.solver
            if solver is None:
                continue
            flags = solver.solve(pts, valid)
            p.frames += 1
            p.flags = flags
            if flags & pk.FLAG_HELD:
                p.held += 1
            if flags & pk.FLAG_SWAP:
                p.swaps += 1
            if flags & pk.FLAG_NEVER:
                continue  # no pose yet: nothing to send
            raw = p._raw
            raw.parent_from_bone_quat[0] = solver.quat
            raw.root_pos[:] = solver.pos
            raw.t_s = t_ns * 1e-9
            if p.filter is not None and not flags & pk.FLAG_HELD:
                p.filter.apply(raw, p.pose)
            elif p.filter is None:
                p.pose.copy_from(raw)
            q, pos = p.pose.parent_from_bone_quat[0], p.pose.root_pos
            self._send_vmc(i, p.vmc.encode(pos, q, p.fov_deg))
            st = solver.stats
            part = p.msg.encode(
                frame.frame_id, frame.source_time_s, t_ns, flags,
                int(st[pk.S_USED]), int(st[pk.S_SEEN]), q, pos,
                p.fov_deg if p.cfg.kind == "camera" else 0.0, st[pk.S_RMS_M],
            )  # fmt: skip
            stamp_sent(part, time.monotonic_ns())
            self._send_pub([part], t_ns)

    def _send_vmc(self, i: int, datagram: memoryview) -> None:
        sock = self._sock
        if sock is None:
            return
        for dest in self._dests[i]:
            try:
                sock.sendto(datagram, dest)
            except OSError:  # receiver absent, buffer full, no route: counted
                self.vmc_drops += 1

    # ---- control ---------------------------------------------------------------------

    def named(self, name: object) -> LiveProp:
        for p in self.props:
            if p.name == name:
                return p
        have = ", ".join(p.name for p in self.props) or "none configured"
        raise ValueError(f"no prop named {name!r} (props: {have})")

    def request_calibration(self, name: object, count: object, by: str) -> str:
        """Start a live calibration of a prop over its next ``count`` frames."""
        p = self.named(name)
        if count is None:
            count = p.cfg.calibrate_frames
        if type(count) is not int or not 3 <= count <= 10_000:
            raise ValueError(f"count must be an integer in [3, 10000]; got {count!r}")
        p.calib_target = count
        p.calib_waited = 0
        p.calib_frames = []
        p.calib_times = []
        p.calib_state = "calibrating"
        p.calib_message = (
            f"prop {p.name}: calibrating on the next {count} frames ({by})"
        )
        return p.calib_message

    def _collect(
        self, p: LiveProp, pts: np.ndarray, valid: np.ndarray, t_s: float, t_ns: int
    ) -> None:
        p.calib_waited += 1
        if len(p.cols) >= 3:
            rows = pts[p.cols].copy()
            rows[~valid[p.cols]] = np.nan
            p.calib_frames.append(rows)
            p.calib_times.append(t_s if math.isfinite(t_s) else t_ns * 1e-9)
        if len(p.calib_frames) >= p.calib_target:
            self._finish_calibration(p)
        elif p.calib_waited >= CALIBRATE_EXPIRE_FRAMES:
            p.calib_state = "expired"
            found = len(p.calib_labels)
            p.calib_message = (
                f"prop {p.name}: calibration expired: {len(p.calib_frames)} of "
                f"{p.calib_target} frames with its markers ({found} in the stream)"
            )
            p.calib_target = 0
            self._out(p.calib_message)

    def _finish_calibration(self, p: LiveProp) -> None:
        frames = np.stack(p.calib_frames)
        span = p.calib_times[-1] - p.calib_times[0]
        rate = (len(p.calib_times) - 1) / span if span > 0 else 120.0
        cfg = p.cfg
        pivot = (cfg.pivot_x_mm / 1000, cfg.pivot_y_mm / 1000, cfg.pivot_z_mm / 1000)
        p.calib_target = 0
        try:
            layout = calibrate_prop(
                frames, p.calib_labels, name=p.name, kind=cfg.kind, rate_hz=rate,
                pivot_m=pivot,
            )  # fmt: skip
        except PropError as exc:
            p.calib_state = "refused"
            p.calib_message = f"prop {p.name}: calibration refused: {exc}"
            self._out(p.calib_message)
            return
        path = cfg.save_calibration or cfg.calibration or f"{p.name}.prop.json"
        saved, state = f", saved to {path}", "calibrated"
        try:
            layout.save(path)
        except OSError as exc:  # used all the same; ctl exits 1 on it
            saved, state = f", not saved ({exc})", "not saved"
        p.solver = PropSolver(layout, p.params)
        if p.bound is not None:
            p.solver.bind(p.bound.labels)
        if p.filter is not None:
            p.filter.reset()
        p.calib_state = state
        p.calib_message = (
            f"prop {p.name}: calibrated on {len(frames)} frames, "
            f"{len(p.calib_labels)} markers{saved}"
        )
        self._out(p.calib_message)

    def set_fov(self, address: str, args: list[Any]) -> bool:
        """A show-control message for a camera's ``fov_osc``: True when it was one
        (taken, or refused by ValueError naming the problem)."""
        p = self._fov_by_address.get(address)
        if p is None:
            return False
        if len(args) != 1 or type(args[0]) not in (int, float):
            raise ValueError(f"{address}: expected one number (degrees); got {args!r}")
        value = float(args[0])
        if not 0.0 < value < 180.0:
            raise ValueError(f"{address}: a field of view in (0, 180) deg; got {value}")
        p.fov_deg = value
        return True

    def status(self) -> list[dict[str, Any]]:
        return [p.status() for p in self.props]


def vmc_destinations(config: Any) -> tuple[tuple[str, int], ...]:
    """Every performer's VMC (host, port) (``performer.vmc`` or ``[output.vmc]``)."""
    vmc = config.output.vmc
    if not vmc.enabled:
        return ()
    out = []
    for perf in config.performers or (config.performer,):
        dest = getattr(perf, "vmc", "")
        if dest:
            host, _, port = dest.rpartition(":")
            out.append((host, int(port)))
        else:
            out.append((vmc.host, vmc.port))
    return tuple(dict.fromkeys(out))
