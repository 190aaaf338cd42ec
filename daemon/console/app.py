"""The console page and its thread: a ``viser`` server fed from a :class:`SnapshotSlot`.

:class:`Console` starts a ``viser`` server (its own asyncio thread; the page is the
client ``viser`` ships, nothing is downloaded at run time) and a render thread that
copies the latest snapshot out of the slot at :data:`RENDER_HZ` and updates the scene:
markers (seen: orange; occluded: grey at their last seen position), the solved
skeleton (bones blue, flagged bones red), the retargeted humanoid beside it (green),
the face weights as bars when the face is live, and rolling plots of the health
figures against the seconds since the run started (``Snapshot.t_s``). Buttons queue
:class:`Command` items (calibrate after a countdown, record start/stop with a file
name, face capture under a pose name when a face is configured, reload); nothing here
calls into the loop.

At a frame a validation check flags (``Snapshot.check_flags``: the live validator's
latest result, or ``retargetd view --report``'s report), the status names each check
with its value and the bones it flags (their validation bits, drawn red).

"Follow performer" (on by default) keeps the performer in every client's view: each
render moves the camera (position and look-at together, so the operator's orbit and
zoom stay) by the performer's displacement in the floor plane since the view was
taken; height is not followed, so a walk's bob does not shake the view.

Offline (:mod:`retargetd.daemon.console.offline`) the same page runs with
``commands=None`` (no buttons, no plots) and a timeline added by the player.
"""

from __future__ import annotations

import html
import logging
import threading
import time
from typing import Any

import numpy as np

from retargetd.daemon.console.snapshot import (
    CMD_CALIBRATE,
    CMD_FACE_CAPTURE,
    CMD_RECORD_START,
    CMD_RECORD_STOP,
    CMD_RELOAD,
    CommandQueue,
    ConsoleLayout,
    Snapshot,
    SnapshotSlot,
    bone_endpoints,
    humanoid_positions,
)
from retargetd.protocols import pose_stream
from retargetd.protocols.pose_props import PROP_HELD, PROP_NEVER

logger = logging.getLogger(__name__)

#: The render thread's rate: the publish rate (``DEFAULT_PUBLISH_HZ``); faster only
#: re-reads the same snapshot.
RENDER_HZ = 30.0
#: Plots redraw at this rate: a plot is read by eye, 4 Hz is smooth enough and keeps
#: the websocket traffic small.
PLOT_HZ = 4.0
#: Seconds of history in the plots.
PLOT_WINDOW_S = 20.0
#: Default calibration countdown: time for the performer to take and hold the base
#: pose after the operator presses (an operator's choice, not a physical limit).
DEFAULT_CALIBRATE_COUNTDOWN_S = 3.0

#: Colours (RGB 0-255).
BONE_RGB = (40, 90, 230)
FLAGGED_RGB = (230, 30, 30)
HUMANOID_RGB = (30, 170, 80)
MARKER_RGB = (255, 160, 0)
OCCLUDED_RGB = (150, 150, 150)
#: Drawn sizes, metres: bones as 25 mm tubes, markers as 20 mm points (optical
#: markers are 9.5-25 mm spheres, Vicon and OptiTrack catalogues).
BONE_THICKNESS_M = 0.025
MARKER_SIZE_M = 0.02
#: A prop's axes (``[[prop]]``), metres: the size of a hand-held camera rig.
PROP_AXES_M = 0.2
#: Follow: the view moves once the performer is this far (metres, floor plane) from
#: where the view follows it, so a standing performer's sway does not move it.
FOLLOW_DEADBAND_M = 0.01
#: Follow: a page's camera report this long after the console last moved that
#: camera is the operator's (or the page's first view), not an echo of the move:
#: the view is followed from there (a pan while the performer stands stays).
FOLLOW_ECHO_S = 0.5
#: The validation bone bits each check sets (``pose_stream.BONE_V_*``): the bones a
#: flagged check names on the page. Live checks (``VALIDATION_CHECKS``) and the
#: offline report's (``validate.checks``) alike.
CHECK_BONE_BITS = {
    "limits": pose_stream.BONE_V_LIMIT,
    "self_penetration": pose_stream.BONE_V_PENETRATION,
    "floor_penetration": pose_stream.BONE_V_PENETRATION,
    "fit": pose_stream.BONE_V_FIT,
    "fit_max": pose_stream.BONE_V_FIT,
    "fit_median": pose_stream.BONE_V_FIT,
    "speed": pose_stream.BONE_V_SPEED,
    "root_speed": pose_stream.BONE_V_SPEED,
    "effector_speed": pose_stream.BONE_V_SPEED,
}
#: Bones named per flagged check on the page (then "+N").
MAX_BONES_NAMED = 4


class Console:
    """The browser console: a ``viser`` server and a render thread.

    Args:
        slot: where the loop (or the offline player) publishes snapshots.
        commands: where button presses go; None for a view-only page (offline).
        host / port: where to listen (port 0: any free port; :attr:`port` tells).
        calibrate_countdown_s: seconds between the Calibrate press and the
            ``calibrate`` command (0: at once); pressing again during the countdown
            cancels it.
        title: the page's heading.
        face_capture: show the "Face pose" field and "Face capture" button (only
            when a face is configured: ``[face]`` or the performer's ``face``).
        follow: "Follow performer" at start.
    """

    def __init__(
        self,
        slot: SnapshotSlot,
        commands: CommandQueue | None = None,
        *,
        host: str = "127.0.0.1",
        port: int = 8080,
        calibrate_countdown_s: float = DEFAULT_CALIBRATE_COUNTDOWN_S,
        title: str = "retargetd",
        face_capture: bool = False,
        follow: bool = True,
    ) -> None:
        if calibrate_countdown_s < 0:
            raise ValueError(
                f"calibrate_countdown_s must be >= 0; got {calibrate_countdown_s}"
            )
        self.slot = slot
        self.commands = commands
        self._host, self._port = host, port
        self._countdown_s = calibrate_countdown_s
        self._title = title
        self._face_capture = face_capture
        self._follow_initial = follow
        # client id -> the view's look-at minus the performer's anchor (x, y), taken
        # when following starts for that client, and the look-at (x, y) it was last
        # moved to (or taken at) with time.monotonic() of that move
        self._follow_base: dict[int, np.ndarray] = {}
        self._follow_look: dict[int, tuple[np.ndarray, float]] = {}
        self._anchor_source = ""
        # client id -> time.monotonic() of its latest camera report
        self._camera_reported: dict[int, float] = {}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self._calibrate_at = 0.0  # time.monotonic() of the pending calibrate, or 0
        self._recording = False  # as last published by the loop
        self.server: Any = None
        #: Snapshots drawn (render thread).
        self.frames_drawn = 0

    # ---- lifecycle -------------------------------------------------------------------

    def start(self) -> None:
        """Start the server and the render thread (returns once listening)."""
        import viser

        self.server = viser.ViserServer(host=self._host, port=self._port, verbose=False)
        self.server.scene.set_up_direction("+z")
        self.server.scene.add_grid("/floor", width=8.0, height=8.0, cell_size=0.5)
        self._build_gui()
        self.server.on_client_connect(self._client_connected)
        self.server.on_client_disconnect(
            lambda c: self._camera_reported.pop(c.client_id, None)
        )
        self._thread = threading.Thread(target=self._run, name="console", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop the render thread and the server (bounded wait)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
        if self.server is not None:
            self.server.stop()
            self.server = None

    @property
    def port(self) -> int:
        """The port the page is served on."""
        return int(self.server.get_port()) if self.server is not None else self._port

    @property
    def url(self) -> str:
        """The page's address."""
        return f"http://{self._host}:{self.port}/"

    # ---- page ------------------------------------------------------------------------

    def _build_gui(self) -> None:
        from viser import uplot

        gui = self.server.gui
        # No share button: it would open a tunnel through viser's public relay; the
        # console stays on the network it is served on.
        gui.configure_theme(control_width="medium", show_share_button=False)
        self._status = gui.add_markdown(f"**{html.escape(self._title)}**: waiting")
        self.follow = gui.add_checkbox(
            "Follow performer", self._follow_initial,
            hint="the camera moves with the performer (orbit and zoom stay)",
        )  # fmt: skip
        self._buttons: dict[str, Any] = {}
        if self.commands is not None:
            with gui.add_folder("Controls"):
                b = gui.add_button("Calibrate", hint="calibrate after a countdown")
                b.on_click(lambda _e: self._press_calibrate())
                self._buttons["calibrate"] = b
                self._record_name = gui.add_text("Record file", "take.mcap")
                b = gui.add_button("Record start")
                b.on_click(lambda _e: self._press_record())
                self._buttons["record"] = b
                if self._face_capture:
                    # The training set's order: neutral first, then each expression.
                    self._face_name = gui.add_text("Face pose", "neutral")
                    b = gui.add_button("Face capture", hint="average the next frames")
                    b.on_click(
                        lambda _e: self._put(
                            CMD_FACE_CAPTURE,
                            self._face_name.value.strip() or "neutral",
                        )
                    )
                    self._buttons["face"] = b
                b = gui.add_button("Reload")
                b.on_click(lambda _e: self._put(CMD_RELOAD))
                self._buttons["reload"] = b
        self._face_folder = gui.add_folder("Face", visible=False)
        with self._face_folder:
            self._face_html = gui.add_html("")
        self._plots: dict[str, Any] = {}
        self._history: dict[str, list[list[float]]] = {}
        self._plot_series: dict[str, tuple[str, ...]] = {}
        if self.commands is not None:
            stages = self.slot.layout.stage_names or ("loop",)
            specs = {
                "input rate (Hz)": ("rate",),
                "drops (per s)": ("drops",),
                "latency p50 (ms)": stages,
                "latency p99 (ms)": stages,
                "occluded markers": ("occluded",),
                "validation flags": ("flags",),
            }
            palette = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b")
            with gui.add_folder("Health"):
                for title, names in specs.items():
                    series = (
                        uplot.Series(label="t (s)"),
                        *(
                            uplot.Series(
                                label=n, stroke=palette[i % len(palette)], width=2
                            )
                            for i, n in enumerate(names)
                        ),
                    )
                    empty = tuple(np.zeros(0) for _ in range(len(names) + 1))
                    self._plots[title] = gui.add_uplot(
                        empty, series, title=title, aspect=2.0,
                        scales={"x": uplot.Scale(time=False)},
                    )  # fmt: skip
                    self._history[title] = [[] for _ in range(len(names) + 1)]
                    self._plot_series[title] = names
        self._markers = self._bones = self._humanoid = None
        self._props: dict[str, Any] = {}  # [[prop]] name -> its axes' handle
        self._last_marker_pos: np.ndarray | None = None

    # ---- buttons (viser's threads): queue only -----------------------------------

    def _put(self, kind: str, arg: str = "") -> None:
        if self.commands is not None and not self.commands.put(kind, arg):
            logger.warning("console: command queue full, %s dropped", kind)

    def _press_calibrate(self) -> None:
        with self._lock:
            if self._calibrate_at:
                self._calibrate_at = 0.0  # a second press cancels the countdown
                return
            if self._countdown_s == 0:
                self._put(CMD_CALIBRATE)
                return
            self._calibrate_at = time.monotonic() + self._countdown_s

    def _press_record(self) -> None:
        # The loop's state decides (the snapshot's ``recording``), not the label:
        # a start the loop refused leaves the button at "Record start".
        if self._recording:
            self._put(CMD_RECORD_STOP)
        else:
            self._put(CMD_RECORD_START, self._record_name.value.strip())

    # ---- render thread ---------------------------------------------------------------

    def _run(self) -> None:
        period = 1.0 / RENDER_HZ
        layout, layout_id = self.slot.current_layout()
        snap = Snapshot.for_layout(layout, layout_id)
        seq = 0
        last_plot = 0.0
        last_drops, last_t = 0, 0.0
        while not self._stop.wait(period):
            try:
                self._tick_countdown()
                got = self.slot.read(snap, seq)
                if got < 0:  # new layout
                    layout, layout_id = self.slot.current_layout()
                    snap = Snapshot.for_layout(layout, layout_id)
                    self._last_marker_pos = None
                    seq = -1
                    continue
                if got == seq:
                    continue
                seq = got
                self._draw(layout, snap)
                self._follow_performer(snap)
                self.frames_drawn += 1
                if self._plots:
                    dt = snap.t_s - last_t
                    rate = (snap.drops - last_drops) / dt if dt > 0 else 0.0
                    last_drops, last_t = snap.drops, snap.t_s
                    self._append_health(snap, rate)
                    now = time.monotonic()
                    if now - last_plot >= 1.0 / PLOT_HZ:
                        last_plot = now
                        self._draw_plots()
            except Exception:  # keep the page alive; the loop is not affected
                logger.exception("console: render failed")

    def _tick_countdown(self) -> None:
        with self._lock:
            at = self._calibrate_at
            if at and time.monotonic() >= at:
                self._calibrate_at = 0.0
                self._put(CMD_CALIBRATE)
                at = 0.0
        button = self._buttons.get("calibrate")
        if button is not None:
            left = max(0.0, at - time.monotonic()) if at else 0.0
            label = (
                f"Calibrating in {left:.0f} s (press to cancel)" if at else "Calibrate"
            )
            if button.label != label:
                button.label = label

    def _draw(self, layout: ConsoleLayout, s: Snapshot) -> None:
        scene = self.server.scene
        with self.server.atomic():
            # Markers: last seen position for occluded ones (greyed).
            if self._last_marker_pos is None:
                self._last_marker_pos = np.full_like(s.marker_pos, np.nan)
            seen = s.marker_valid & np.isfinite(s.marker_pos).all(axis=1)
            self._last_marker_pos[seen] = s.marker_pos[seen]
            known = np.isfinite(self._last_marker_pos).all(axis=1)
            pts = self._last_marker_pos[known].astype(np.float32)
            colors = np.where(seen[known, None], MARKER_RGB, OCCLUDED_RGB).astype(
                np.uint8
            )
            if len(pts) and self._markers is not None:
                self._markers.points, self._markers.colors = pts, colors
                self._markers.visible = True
            elif len(pts):
                self._markers = scene.add_point_cloud(
                    "/markers", pts, colors, point_size=MARKER_SIZE_M,
                    point_shape="circle",
                )  # fmt: skip
            elif self._markers is not None:
                self._markers.visible = False
            # Solved skeleton.
            ends = bone_endpoints(
                layout.skeleton, s.joint_pos, s.world_from_bone_quat, s.root_pos,
                layout.bone_lengths,
            )  # fmt: skip
            ok = np.isfinite(ends).all(axis=(1, 2))
            flagged = s.bone_flags[ok] != 0
            bone_colors = np.where(flagged[:, None, None], FLAGGED_RGB, BONE_RGB)
            self._bones = self._segments(
                "/skeleton", ends[ok], np.broadcast_to(bone_colors, (ok.sum(), 2, 3)),
                self._bones,
            )  # fmt: skip
            # The retargeted humanoid, beside the performer.
            if len(layout.humanoid_pairs):
                if len(layout.humanoid_parents):  # posed here, off the loop
                    humanoid_positions(
                        layout, s.humanoid_quat, s.humanoid_hips, s.humanoid_pos
                    )
                h = s.humanoid_pos[layout.humanoid_pairs] + layout.humanoid_offset_m
                hok = np.isfinite(h).all(axis=(1, 2))
                colors = np.broadcast_to(HUMANOID_RGB, (int(hok.sum()), 2, 3))
                self._humanoid = self._segments(
                    "/humanoid", h[hok], colors, self._humanoid
                )
            self._draw_props(layout, s)
            if layout.face_names:
                self._face_folder.visible = s.face_on
                if s.face_on:
                    self._face_html.content = _face_bars(layout.face_names, s)
            self._status.content = _status_text(
                self._title, s, live=self.commands is not None
            ) + _check_text(layout, s)
            self._recording = s.recording
            button = self._buttons.get("record")
            label = "Record stop" if s.recording else "Record start"
            if button is not None and button.label != label:
                button.label = label

    def _draw_props(self, layout: ConsoleLayout, s: Snapshot) -> None:
        # Each [[prop]] as a frame of axes at its pose (x red, y green, z blue);
        # hidden until its first pose, shrunk while held.
        for i, name in enumerate(layout.prop_names):
            handle = self._props.get(name)
            if handle is None:
                handle = self.server.scene.add_frame(
                    f"/props/{name}", axes_length=PROP_AXES_M,
                    axes_radius=PROP_AXES_M / 25,
                )  # fmt: skip
                self._props[name] = handle
            flags = int(s.prop_flags[i])
            handle.visible = not flags & PROP_NEVER
            handle.wxyz = s.prop_quat[i]
            handle.position = s.prop_pos[i]
            handle.axes_length = PROP_AXES_M * (0.5 if flags & PROP_HELD else 1.0)

    # ---- camera follow (render thread) -------------------------------------------

    def _client_connected(self, client: Any) -> None:
        # A client's camera is known once it reports one (before that, viser's
        # handle holds placeholders).
        cid = client.client_id

        def reported(_cam: Any) -> None:
            self._camera_reported[cid] = time.monotonic()

        client.camera.on_update(reported)

    def _follow_performer(self, s: Snapshot) -> None:
        """Move each client's camera with the performer (floor plane); see the
        module docstring."""
        if not self.follow.value:
            self._follow_base.clear()  # re-taken from the view when turned on
            self._follow_look.clear()
            return
        anchor, source = performer_anchor(s, self._last_marker_pos)
        if anchor is None:
            return
        if source != self._anchor_source:  # e.g. markers -> solved root: no jump
            self._follow_base.clear()
            self._follow_look.clear()
            self._anchor_source = source
        clients = self.server.get_clients()
        for cid in [c for c in self._follow_base if c not in clients]:
            del self._follow_base[cid]
            self._follow_look.pop(cid, None)
        now = time.monotonic()
        for cid, client in clients.items():
            reported = self._camera_reported.get(cid)
            if reported is None:  # no camera from the page yet
                continue
            cam = client.camera
            look = np.asarray(cam.look_at, np.float64)[:2]
            base = self._follow_base.get(cid)
            moved_to, moved_at = self._follow_look.get(cid, (look, 0.0))
            if base is None or (
                reported > moved_at + FOLLOW_ECHO_S
                and float(np.hypot(*(look - moved_to))) > 1e-3
            ):  # the page's own view (its first, or the operator's): from here
                self._follow_base[cid] = look - anchor
                self._follow_look[cid] = (look, 0.0)  # not a move of ours
                continue
            # Absolute, not incremental: a camera report that crosses a move in
            # flight is corrected on the next render instead of losing the step.
            shift = anchor + base - look
            if float(np.hypot(shift[0], shift[1])) > FOLLOW_DEADBAND_M:
                pos = np.asarray(cam.position, np.float64)
                cam.position = pos + np.array([shift[0], shift[1], 0.0])
                self._follow_look[cid] = (anchor + base, now)

    def _segments(
        self, name: str, points: np.ndarray, colors: np.ndarray, handle: Any
    ) -> Any:
        if len(points) == 0:
            if handle is not None:
                handle.visible = False
            return handle
        if handle is not None:
            handle.points = points.astype(np.float32)
            handle.colors = np.ascontiguousarray(colors, np.uint8)
            handle.visible = True
            return handle
        return self.server.scene.add_line_segments(
            name, points.astype(np.float32), np.ascontiguousarray(colors, np.uint8),
            thickness=BONE_THICKNESS_M,
        )  # fmt: skip

    def _append_health(self, s: Snapshot, drop_rate: float) -> None:
        n_keep = int(PLOT_WINDOW_S * RENDER_HZ)
        values: dict[str, tuple[float, ...]] = {
            "input rate (Hz)": (s.input_rate_hz,),
            "drops (per s)": (drop_rate,),
            "latency p50 (ms)": tuple(s.latency_p50_ms) or (np.nan,),
            "latency p99 (ms)": tuple(s.latency_p99_ms) or (np.nan,),
            "occluded markers": (float(s.occluded),),
            "validation flags": (float(s.validation_flags),),
        }
        for title, cols in self._history.items():
            row = (s.t_s, *values[title])
            for col, v in zip(cols, row, strict=False):
                col.append(float(v))
                if len(col) > n_keep:
                    del col[0]

    def _draw_plots(self) -> None:
        for title, handle in self._plots.items():
            handle.data = tuple(np.asarray(c, np.float64) for c in self._history[title])


def _status_text(title: str, s: Snapshot, *, live: bool = True) -> str:
    state = "calibrated" if s.calibrated else "not calibrated"
    rec = ", recording" if s.recording else ""
    rate = f"input {s.input_rate_hz:.0f} Hz, " if live else ""
    return (
        f"**{html.escape(title)}**: frame {s.frame}, t = {s.t_s:.2f} s, {state}{rec}"
        f"  \n{rate}{s.occluded} occluded, "
        f"{int(np.count_nonzero(s.bone_flags))} bones flagged"
    )


def performer_anchor(
    s: Snapshot, last_marker_pos: np.ndarray | None = None
) -> tuple[np.ndarray | None, str]:
    """Where the performer stands, (x, y) metres world, and what it was taken from:
    the solved root, else the mean solved joint centre, else (before a calibration)
    the mean of the markers at their last seen places (``last_marker_pos``, (M, 3),
    NaN where never seen: a marker's dropout does not move it), else of the markers
    seen now; (None, "") when nothing is known."""
    if np.isfinite(s.root_pos).all():
        return s.root_pos[:2].copy(), "root"
    ok = np.isfinite(s.joint_pos).all(axis=1)
    if ok.any():
        return s.joint_pos[ok, :2].mean(axis=0), "joints"
    if last_marker_pos is not None and len(last_marker_pos) == len(s.marker_pos):
        known = np.isfinite(last_marker_pos).all(axis=1)
        if known.any():
            return last_marker_pos[known, :2].mean(axis=0), "markers"
    seen = s.marker_valid & np.isfinite(s.marker_pos).all(axis=1)
    if seen.any():
        return s.marker_pos[seen, :2].mean(axis=0), "markers"
    return None, ""


def _check_text(layout: ConsoleLayout, s: Snapshot) -> str:
    """One line per check flagging this frame: its name, the bones it flags and
    its value ("limits: lupleg 12.3 deg beyond limit"); "" when none does."""
    if not s.check_flags:
        return ""
    lines = []
    for k, name in enumerate(layout.check_names):
        if not (s.check_flags >> k) & 1:
            continue
        bit = CHECK_BONE_BITS.get(name, 0)
        bones = [layout.bone_names[b] for b in np.flatnonzero(s.bone_flags & bit)]
        who = ", ".join(bones[:MAX_BONES_NAMED])
        if len(bones) > MAX_BONES_NAMED:
            who += f" +{len(bones) - MAX_BONES_NAMED}"
        v = float(s.check_values[k])
        unit = layout.check_units[k] if layout.check_units else ""
        value = f"{v:.3g} {unit}".rstrip() if np.isfinite(v) else "flagged"
        lines.append(html.escape(f"{name}: {who} {value}".replace("  ", " ")))
    return "  \n**flagged**: " + "; ".join(lines)


def _face_bars(names: tuple[str, ...], s: Snapshot) -> str:
    rows = []
    for name, w in zip(names, s.face_weights, strict=True):
        pct = 100.0 * float(np.clip(w, 0.0, 1.0)) if np.isfinite(w) else 0.0
        rows.append(
            '<div style="display:flex;align-items:center;font-size:11px">'
            f'<span style="width:45%;overflow:hidden">{html.escape(name)}</span>'
            '<span style="flex:1;background:#eee;height:8px">'
            f'<span style="display:block;width:{pct:.0f}%;height:8px;'
            'background:#1f77b4"></span></span></div>'
        )
    return "".join(rows)
