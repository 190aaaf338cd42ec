"""``retargetd view``: the console page over a recorded sequence, with a timeline.

:func:`load_sequence` reads a solved NPZ (``retargetd solve --out x.npz``; the
skeleton drawn from its rig when the rig is a shipped one, else joint centres only)
or a take (anything ``retargetd.replay.takes.load_take`` reads: markers only), and
optionally overlays a take's markers on a solve. :func:`serve_offline` serves it: a
frame slider (scrub), Play and Loop checkboxes and a speed choice; flagged frames
(given, e.g. from a validation report, or every frame where a bone is flagged in the
solve) are marked on the slider and reachable with "Next flagged". With a report
(:func:`with_report`), each frame the report flags shows the checks that flag it,
their values where the report holds them, and the bones it names drawn red
(:func:`report_checks`).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import re
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from retargetd.daemon.body.rig import load_rig, shipped_rigs
from retargetd.daemon.console.app import CHECK_BONE_BITS, Console
from retargetd.daemon.console.snapshot import (
    ConsoleLayout,
    SkeletonProgram,
    SnapshotSlot,
)
from retargetd.protocols.frames import F64Array
from retargetd.replay.takes import load_take

logger = logging.getLogger(__name__)

#: At most this many flagged-frame marks on the slider (runs are merged first).
MAX_MARKS = 40
#: The first view's distance from the performer, metres (see :func:`camera_for`).
CAMERA_DISTANCE_M = 4.6
#: The first view's vertical field of view (viser's default is 75 degrees; 50 keeps
#: a 2 m figure large on the page).
CAMERA_FOV_DEG = 50.0


@dataclass(frozen=True, slots=True, kw_only=True)
class ViewSequence:
    """A sequence of frames to view, arrays in :class:`ConsoleLayout` order.

    Attributes:
        layout: names and the skeleton program.
        rate_hz: frame rate.
        marker_pos: (T, M, 3) float64 metres world (M may be 0).
        marker_valid: (T, M) bool.
        joint_pos: (T, J, 3) float64 metres world (J may be 0).
        world_from_bone_quat: (T, B, 4) float64 w x y z.
        root_pos: (T, 3) float64 metres world.
        bone_flags: (T, B) uint8.
        flagged_frames: sorted frame indices (0-based) to mark on the timeline.
        checks: a validation report's checks frame by frame (:func:`with_report`),
            in the layout's ``check_names`` order; None: no report.
    """

    layout: ConsoleLayout
    rate_hz: float
    marker_pos: F64Array
    marker_valid: np.ndarray
    joint_pos: F64Array
    world_from_bone_quat: F64Array
    root_pos: F64Array
    bone_flags: np.ndarray
    flagged_frames: tuple[int, ...] = ()
    checks: ReportChecks | None = None

    @property
    def n_frames(self) -> int:
        """Number of frames T."""
        return int(max(self.marker_pos.shape[0], self.joint_pos.shape[0]))


def _program_for(
    rig: Any, rig_name: str, joint_names: tuple[str, ...], n_bones: int
) -> Any:
    if rig is None and rig_name in shipped_rigs():
        rig = load_rig(rig_name)
    if rig is not None and len(rig.bones) == n_bones:
        return SkeletonProgram.from_rig(rig, joint_names)
    logger.warning("view: rig %r not shipped; drawing joint centres only", rig_name)
    return None


def sequence_from_solve(
    arrays: Mapping[str, Any],
    *,
    rig: Any = None,
    take: Any = None,
    flagged_frames: Sequence[int] | None = None,
) -> ViewSequence:
    """A solve (the NPZ keys of ``retargetd solve``, as arrays) for viewing.

    Args:
        arrays: ``joint_names``, ``joint_centres``, ``bone_names``,
            ``world_from_bone_quat``, ``root_pos``, ``bone_flags``, ``bone_lengths``,
            ``bone_parents``, ``rate_hz``, ``rig_name``.
        rig: the rig it was solved with (``body.rig.Rig``; None: the shipped rig
            named ``rig_name``, else joint centres only).
        take: the take it was solved from (``replay.take.Take``), to show its
            markers too (row ``i`` of the take is frame ``i`` of the solve).
        flagged_frames: frames to mark (0-based); None: every frame where some bone
            is flagged.
    """
    joint_names = tuple(str(n) for n in arrays["joint_names"])
    bone_names = tuple(str(n) for n in arrays["bone_names"])
    joints = np.asarray(arrays["joint_centres"], np.float64)
    quats = np.asarray(arrays["world_from_bone_quat"], np.float64)
    root = np.asarray(arrays["root_pos"], np.float64)
    flags = np.asarray(arrays["bone_flags"], np.uint8)
    lengths = np.asarray(arrays["bone_lengths"], np.float64)
    parents = np.asarray(arrays["bone_parents"], np.int64)
    rate = float(arrays["rate_hz"])
    program = _program_for(rig, str(arrays["rig_name"]), joint_names, len(bone_names))
    if program is None:
        program = SkeletonProgram.from_joint_pairs([])
        bone_names, parents, lengths = (), parents[:0], lengths[:0]
        quats, flags = quats[:, :0], flags[:, :0]
    t = joints.shape[0]
    labels: tuple[str, ...] = ()
    markers = np.zeros((t, 0, 3))
    valid = np.zeros((t, 0), bool)
    if take is not None:
        labels = take.labels
        markers = np.full((t, len(labels), 3), np.nan)
        valid = np.zeros((t, len(labels)), bool)
        n = min(t, take.positions.shape[0])
        markers[:n], valid[:n] = take.positions[:n], take.valid[:n]
    if flagged_frames is None:
        flagged_frames = np.flatnonzero(flags.any(axis=1)).tolist()
    layout = ConsoleLayout(
        marker_names=labels,
        joint_names=joint_names,
        bone_names=bone_names,
        bone_parents=parents,
        skeleton=program,
        bone_lengths=lengths,
    )
    return ViewSequence(
        layout=layout, rate_hz=rate, marker_pos=markers, marker_valid=valid,
        joint_pos=joints, world_from_bone_quat=quats, root_pos=root, bone_flags=flags,
        flagged_frames=tuple(sorted({int(f) for f in flagged_frames})),
    )  # fmt: skip


def sequence_from_take(
    take: Any, *, flagged_frames: Sequence[int] | None = None
) -> ViewSequence:
    """A take's markers alone (``replay.take.Take``) for viewing."""
    labels, markers, valid = take.labels, take.positions, take.valid
    t = markers.shape[0]
    layout = ConsoleLayout(
        marker_names=labels,
        joint_names=(),
        bone_names=(),
        bone_parents=np.zeros(0, np.int64),
        skeleton=SkeletonProgram.from_joint_pairs([]),
        bone_lengths=np.zeros(0),
    )
    return ViewSequence(
        layout=layout, rate_hz=float(take.rate_hz), marker_pos=markers,
        marker_valid=valid, joint_pos=np.zeros((t, 0, 3)),
        world_from_bone_quat=np.zeros((t, 0, 4)), root_pos=np.full((t, 3), np.nan),
        bone_flags=np.zeros((t, 0), np.uint8),
        flagged_frames=tuple(sorted({int(f) for f in (flagged_frames or ())})),
    )  # fmt: skip


def load_sequence(
    path: str | os.PathLike[str],
    *,
    take: str | os.PathLike[str] | None = None,
    flagged_frames: Sequence[int] | None = None,
) -> ViewSequence:
    """Read a solved NPZ or a take for viewing.

    Args:
        path: ``.npz`` from ``retargetd solve``, or a take file.
        take: with an NPZ, the take it was solved from, to show its markers too
            (row ``i`` of the take is frame ``i`` of the solve).
        flagged_frames: frames to mark (0-based); None: for a solve, every frame
            where some bone is flagged.
    """
    p = Path(path)
    if p.suffix.lower() != ".npz":
        return sequence_from_take(load_take(p), flagged_frames=flagged_frames)
    with np.load(p, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    return sequence_from_solve(
        arrays,
        take=None if take is None else load_take(take),
        flagged_frames=flagged_frames,
    )


def flagged_frames_from_report(doc: Mapping[str, Any]) -> list[int]:
    """Every frame a validation report (``retargetd validate``'s ``report.json``)
    flags, over all its checks: each check's ``flagged_runs`` ([start, stop) frame
    ranges); a report without them (older) gives each failing check's
    ``worst_frames``."""
    frames: set[int] = set()
    for check in doc.get("checks", {}).values():
        runs = check.get("flagged_runs")
        if runs is not None:
            for a, b in runs:
                frames.update(range(int(a), int(b)))
        elif check.get("frames_flagged"):
            frames.update(int(f) for f in check.get("worst_frames", ()))
    return sorted(frames)


#: A report's detail line about one frame ("frame 120: lupleg swing (12.3 deg
#: beyond)", "first flagged, frame 7: ...", "frame 9: lfemur / rfemur").
_DETAIL_FRAME = re.compile(r"frame (\d+): (.*)$")
#: The limits detail's value at that frame.
_DETAIL_DEG = re.compile(r"\(([-+0-9.eE]+) deg beyond\)")


@dataclass(frozen=True, slots=True, kw_only=True)
class ReportChecks:
    """A validation report's checks, frame by frame (what ``report.json`` holds).

    Attributes:
        names: (K,) check names, the report's order (at most 64).
        units: (K,) their units.
        flags: (T,) uint64, bit k set where ``names[k]`` flags the frame (its
            ``flagged_runs``).
        values: (T, K) float64, the check's value at the frame in its unit where
            the report holds one (its worst frames, its detail lines); NaN else.
        bone_bits: (T, B) uint8 ``BONE_V_*`` bits: the bones a check's detail lines
            name (limits: the joint's bone; self-penetration: both bones), over
            the whole flagged run holding the named frame.
    """

    names: tuple[str, ...]
    units: tuple[str, ...]
    flags: np.ndarray
    values: F64Array
    bone_bits: np.ndarray


def report_checks(
    doc: Mapping[str, Any], bone_names: Sequence[str], n_frames: int
) -> ReportChecks:
    """Read ``retargetd validate``'s ``report.json`` frame by frame.

    A report holds, per check, its flagged runs, its five worst frames with their
    values and detail lines naming a frame (limits: the bone, the swing or twist and
    the degrees beyond; self-penetration: the two bones). Values elsewhere are not
    in the report and stay NaN. Frames past ``n_frames`` are ignored.

    Args:
        doc: the report, parsed.
        bone_names: (B,) the view's bones (named in the detail lines).
        n_frames: T.
    """
    checks = list(doc.get("checks", {}).items())[:64]
    n, b = int(n_frames), len(bone_names)
    index = {name: i for i, name in enumerate(bone_names)}
    flags = np.zeros(n, np.uint64)
    values = np.full((n, len(checks)), np.nan)
    bone_bits = np.zeros((n, b), np.uint8)
    for k, (name, check) in enumerate(checks):
        runs = check.get("flagged_runs")
        if runs is None:  # an older report: its worst frames, when it failed
            worst = check.get("worst_frames", ()) if check.get("frames_flagged") else ()
            runs = [[int(f), int(f) + 1] for f in worst]
        runs = [(max(int(a), 0), min(int(z), n)) for a, z in runs]
        runs = [(a, z) for a, z in runs if a < z]
        flagged = np.zeros(n, bool)
        for a, z in runs:
            flagged[a:z] = True
        flags[flagged] |= np.uint64(1 << k)
        for f, v in zip(
            check.get("worst_frames", ()), check.get("worst_values", ()), strict=False
        ):
            if 0 <= int(f) < n and flagged[int(f)]:
                values[int(f), k] = float(v)
        bit = CHECK_BONE_BITS.get(name, 0)
        for line in check.get("detail", ()):
            m = _DETAIL_FRAME.search(str(line))
            if m is None or not (0 <= int(m.group(1)) < n and flagged[int(m.group(1))]):
                continue  # a transient (not flagged), or past the view
            f, body = int(m.group(1)), m.group(2)
            deg = _DETAIL_DEG.search(body)
            if deg is not None and np.isnan(values[f, k]):
                values[f, k] = float(deg.group(1))
            named = [index[w] for w in re.findall(r"[^\s/(),]+", body) if w in index]
            if bit and named:
                a, z = next((a, z) for a, z in runs if a <= f < z)
                bone_bits[a:z, named] |= np.uint8(bit)
    return ReportChecks(
        names=tuple(str(name) for name, _ in checks),
        units=tuple(str(c.get("unit", "")) for _, c in checks),
        flags=flags, values=values, bone_bits=bone_bits,
    )  # fmt: skip


def with_report(seq: ViewSequence, doc: Mapping[str, Any]) -> ViewSequence:
    """``seq`` with a validation report: its flagged frames marked, and at each
    one the checks, values and bones the report gives (:func:`report_checks`)."""
    checks = report_checks(doc, seq.layout.bone_names, seq.n_frames)
    layout = dataclasses.replace(
        seq.layout, check_names=checks.names, check_units=checks.units
    )
    return dataclasses.replace(
        seq, layout=layout, checks=checks,
        flagged_frames=tuple(flagged_frames_from_report(doc)),
    )  # fmt: skip


def camera_for(seq: ViewSequence) -> tuple[F64Array, F64Array]:
    """(position, look_at) metres world of the page's first view: level with the
    performer's mean position, 4.6 m off along -Y (a 50 degree vertical field of
    view then holds a 2 m figure with margin), so the whole take is in frame."""
    pts = [seq.joint_pos.reshape(-1, 3), seq.marker_pos.reshape(-1, 3)]
    allp = np.concatenate(pts) if any(len(p) for p in pts) else np.zeros((0, 3))
    allp = allp[np.isfinite(allp).all(axis=1)]
    centre = allp.mean(axis=0) if len(allp) else np.array([0.0, 0.0, 1.0])
    return centre + np.array([0.0, -CAMERA_DISTANCE_M, 0.0]), centre


def _marks(frames: tuple[int, ...]) -> tuple[tuple[int, str], ...]:
    """Slider marks: the first frame of each run of flagged frames, at most
    :data:`MAX_MARKS` of them (evenly thinned)."""
    starts = [f for i, f in enumerate(frames) if i == 0 or frames[i - 1] != f - 1]
    if len(starts) > MAX_MARKS:
        starts = [
            starts[i] for i in np.linspace(0, len(starts) - 1, MAX_MARKS, dtype=int)
        ]
    return tuple((f, "!") for f in starts)


class OfflineViewer:
    """A :class:`Console` (view only) and a player thread publishing the timeline's
    frame into its slot.

    Args:
        seq: what to show.
        host / port: where to listen.
    """

    def __init__(self, seq: ViewSequence, *, host: str = "127.0.0.1", port: int = 8080):
        self.seq = seq
        self.slot = SnapshotSlot(seq.layout)
        self.console = Console(self.slot, None, host=host, port=port, title="view")
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._dirty = threading.Event()

    def start(self) -> None:
        """Serve the page and start the player."""
        self.console.start()
        cam = self.console.server.initial_camera
        cam.position, cam.look_at = camera_for(self.seq)
        cam.up = (0.0, 0.0, 1.0)
        cam.fov = float(np.deg2rad(CAMERA_FOV_DEG))
        gui = self.console.server.gui
        last = max(self.seq.n_frames - 1, 1)
        with gui.add_folder("Timeline"):
            self.frame = gui.add_slider(
                "Frame", min=0, max=last, step=1, initial_value=0,
                marks=_marks(self.seq.flagged_frames) or None,
            )  # fmt: skip
            self.play = gui.add_checkbox("Play", False)
            self.loop = gui.add_checkbox("Loop", True)
            self.speed = gui.add_dropdown(
                "Speed", ("0.25", "0.5", "1", "2"), initial_value="1"
            )
            nxt = gui.add_button("Next flagged", disabled=not self.seq.flagged_frames)
            gui.add_markdown(
                f"{self.seq.n_frames} frames at {self.seq.rate_hz:g} Hz; "
                f"{len(self.seq.flagged_frames)} flagged"
            )
        self.frame.on_update(lambda _e: self._dirty.set())
        nxt.on_click(lambda _e: self._next_flagged())
        self._publish(0)
        self._thread = threading.Thread(target=self._run, name="view", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the player and the page."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
        self.console.stop()

    @property
    def url(self) -> str:
        """The page's address."""
        return self.console.url

    def _next_flagged(self) -> None:
        after = [f for f in self.seq.flagged_frames if f > int(self.frame.value)]
        if after or self.seq.flagged_frames:
            self.frame.value = (after or self.seq.flagged_frames)[0]

    def _publish(self, i: int) -> None:
        q = self.seq
        s = self.slot.begin()
        s.frame, s.t_s = i, i / q.rate_hz
        np.copyto(s.marker_pos, q.marker_pos[i])
        np.copyto(s.marker_valid, q.marker_valid[i])
        np.copyto(s.joint_pos, q.joint_pos[i])
        np.copyto(s.world_from_bone_quat, q.world_from_bone_quat[i])
        np.copyto(s.root_pos, q.root_pos[i])
        np.copyto(s.bone_flags, q.bone_flags[i])
        if q.checks is not None:  # the report's flagged bones join the solve's
            np.bitwise_or(s.bone_flags, q.checks.bone_bits[i], out=s.bone_flags)
            s.check_flags = int(q.checks.flags[i])
            np.copyto(s.check_values, q.checks.values[i])
        s.occluded = int(np.count_nonzero(~q.marker_valid[i]))
        s.calibrated = bool(q.layout.joint_names)  # a solve: a calibrated skeleton
        while not self.slot.commit() and not self._stop.is_set():
            time.sleep(0.001)  # the player may wait; only the live loop may not

    def _run(self) -> None:
        n = self.seq.n_frames
        shown = 0
        t0, f0 = time.monotonic(), 0.0
        while not self._stop.wait(1.0 / 60.0):
            cur = int(self.frame.value)
            if self.play.value:
                if self._dirty.is_set() and cur != shown:  # scrubbed while playing
                    t0, f0 = time.monotonic(), float(cur)
                self._dirty.clear()
                speed = float(self.speed.value)
                f = f0 + (time.monotonic() - t0) * self.seq.rate_hz * speed
                if f >= n:
                    if self.loop.value:
                        t0, f0, f = time.monotonic(), 0.0, 0.0
                    else:
                        self.play.value = False
                        f = n - 1
                cur = int(f)
                if cur != shown:
                    self.frame.value = cur
                    self._dirty.clear()
            else:
                t0, f0 = time.monotonic(), float(cur)
            if cur != shown:
                self._publish(cur)
                shown = cur


def serve_offline(
    path: str | os.PathLike[str],
    *,
    take: str | os.PathLike[str] | None = None,
    flagged_frames: Sequence[int] | None = None,
    host: str = "127.0.0.1",
    port: int = 8080,
    block: bool = True,
) -> OfflineViewer:
    """Serve ``path`` (solved NPZ or take) on the console page with a timeline.

    Args:
        path / take / flagged_frames: see :func:`load_sequence`.
        host / port: where to listen (port 0: any free port).
        block: serve until interrupted (Ctrl-C), then stop; False: return the
            started viewer (call ``stop()``).

    Returns:
        The viewer (stopped when ``block``).
    """
    viewer = OfflineViewer(
        load_sequence(path, take=take, flagged_frames=flagged_frames),
        host=host, port=port,
    )  # fmt: skip
    viewer.start()
    if block:
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            pass
        finally:
            viewer.stop()
    return viewer
