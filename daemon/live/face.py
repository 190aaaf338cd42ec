"""The face in the live daemon: training set, live captures, per-stream solve stage.

``[face]`` in the daemon config names a face config (``face_config``: head markers,
facial markers, expressions, output map) and a training set (``face.npz`` from
``retargetd face-train``). The face is solved from the same marker stream as the
body: the stream's labels must include the head and facial markers.

**Live training** (``retargetd ctl face-capture NAME --count N``): the next N
accepted frames are averaged after stabilization, like ``face-train`` does offline.
The head frame is defined once, by the first neutral capture (or the loaded training
set): every later capture, a new neutral included, is stabilized against that head
layout, so the expressions already captured stay valid. A new neutral replaces the
neutral markers and keeps the expression deltas; a captured expression replaces its
delta (``mean - neutral``). Expressions are kept in the face config's order; those
not yet captured are simply absent (their output terms contribute nothing). Each
capture rebuilds the solver and saves the training set (``face.save_training`` or
``face.training``) on a worker thread (``rebuild.Build``; issue 30 item 6: a write
and its fsync in the loop held every frame behind it for as long as the disk took):
one save at a time, the newest set waiting while one is written, its outcome said
when the loop finds it done (:meth:`LiveFace.take_saved`; a failure is counted
``face_save_failures``, the file kept whole by the atomic write). ``ctl status``'s
``face.saving`` is true meanwhile; the daemon's close waits for the last one.
The capture's averaging (:func:`capture_into`: a rigid fit per frame, twice for the
first neutral) runs on a worker thread too: 1.7 ms for 24 frames, 7.9 ms for the
default 60 and 31 ms for 240 (a second at 240 Hz) at a load of 5 on the 2-core dev
machine, past a frame's 4.2 ms at 240 Hz; ``face.averaging`` is true meanwhile, a new
capture is refused until it ends, and the loop pass that finds it done takes the new
set (:meth:`LiveFace.take_captured`).

Facial markers (``face.markers``): the face config's list, refused at the start (a
config error, exit 2) when a body rig names one of them: the daemon's rig or the
config's ``body_rig``. When the config lists none, they are every stream label that
is not a head marker and that no body rig matches (``body.calibration.match_markers``:
its aliases, prefixes, case; a rig marker's name is not a label unless listed), and
the first neutral capture keeps only those on the head's side of the neck.

Shapes the training set's markers cannot observe (``face.observability`` at its
``noise_rms_m``) are left out of the solve and sent as 0, flagged per shape
(``FaceOutput.shape_state``; the pose stream's ``RTDF`` message, PROTOCOLS.md §6);
``ctl status --json`` lists them (``face.unobserved``).

With a neutral but no expression captured yet, the stabilized markers (the "Mug")
are streamed and no weights are sent (the solver stabilizes; with no expression
there is nothing to solve).
"""

from __future__ import annotations

import logging
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from retargetd.daemon.body.rig import Rig, RigError, load_rig
from retargetd.daemon.face.config import FaceConfig, load_face_config
from retargetd.daemon.face.markers import (
    FacialMarkerError,
    check_listed,
    on_head_side,
    select_facial,
)
from retargetd.daemon.face.solve import (
    FaceOutput,
    FaceSolver,
    TrainingSet,
    head_layout_from_frames,
    mean_pose,
    observability,
)
from retargetd.daemon.face.take import face_solver
from retargetd.daemon.live.config import ConfigError, FaceSectionConfig
from retargetd.daemon.live.rebuild import Build
from retargetd.protocols.frames import F64Array

logger = logging.getLogger(__name__)


@dataclass(slots=True, eq=False)
class FaceStage:
    """The face solve of one marker stream (built off the hot path).

    Attributes:
        solver: the face solver bound to the stream's labels.
        out: its output buffers.
        marker_names: (M,) stabilized marker names (the face part's order).
        weight_names: (K,) solved expression names sent in the pose stream.
        output_names: VMC blendshape names (the face config's outputs).
        out_matrix: (n_out, K) the output map.
        blend: (n_out,) the output values of the last frame, in [0, 1].
        weights: (K,) view of the solved weights sent in the pose stream.
        unobserved: the expressions left out of the solve (sent as 0).
    """

    solver: FaceSolver
    out: FaceOutput
    marker_names: tuple[str, ...]
    weight_names: tuple[str, ...]
    output_names: tuple[str, ...]
    out_matrix: F64Array
    blend: F64Array
    weights: F64Array
    unobserved: tuple[str, ...] = ()

    def solve(self, markers_world: F64Array, valid: np.ndarray) -> FaceOutput:
        """Solve one frame (no allocation): ``out`` and ``blend`` updated."""
        fo = self.solver.solve_frame(markers_world, valid, self.out)
        if self.blend.size:
            np.dot(self.out_matrix, fo.weights, out=self.blend)
            np.clip(self.blend, 0.0, 1.0, out=self.blend)
        return fo


class LiveFace:
    """The daemon's face state (config, training set, a live capture in progress).

    Args:
        settings: the ``[face]`` section.
        body_rig: the body's rig: the labels it matches are not facial markers.

    Raises:
        FaceConfigError / ValueError: a bad face config or training file;
            ConfigError: a body marker listed as facial (one line naming it).
    """

    def __init__(
        self, settings: FaceSectionConfig, body_rig: Rig | None = None
    ) -> None:
        self.settings = settings
        self.face: FaceConfig = load_face_config(settings.config)
        self.body_rig = body_rig
        rigs = [body_rig] if body_rig is not None else []
        if self.face.body_rig and (
            body_rig is None or self.face.body_rig != body_rig.name
        ):
            try:
                rigs.append(load_rig(self.face.body_rig))
            except RigError as exc:
                raise ConfigError(f"face {self.face.name}: body_rig: {exc}") from None
        #: The body rigs whose markers are never facial.
        self.body_rigs: tuple[Rig, ...] = tuple(rigs)
        try:
            check_listed(self.face.facial_markers, self.face.head_markers, rigs)
        except FacialMarkerError as exc:
            raise ConfigError(f"face {self.face.name}: {exc}") from None
        self.training: TrainingSet | None = None
        if settings.training and Path(settings.training).exists():
            self.training = TrainingSet.load(settings.training)
            self._check_training(self.training)
        self._capture_name = ""
        self._capture_target = 0
        self._capture_head: list[F64Array] = []
        self._capture_face: list[F64Array] = []
        self._capture_labels: tuple[str, ...] = ()
        self.captures = 0
        self.last_message = ""
        self._save: Build | None = None  # the training set being written
        # the capture being averaged off the loop (capture_into); its want: (name,
        # the stream's labels, frames)
        self._averaging: Build | None = None
        # the newest set to write next: (set, path, its capture's line)
        self._next_save: tuple[TrainingSet, str, str] | None = None
        self._unobserved_cache: tuple[TrainingSet | None, tuple[str, ...]] = (None, ())

    def _check_training(self, t: TrainingSet) -> None:
        if tuple(t.head_names) != self.face.head_markers:
            logger.warning(
                "face training set head markers %s differ from face config %s's %s",
                t.head_names,
                self.face.name,
                self.face.head_markers,
            )

    # ---- the solve stage -------------------------------------------------------------

    def facial_markers(self, labels: Sequence[str]) -> tuple[str, ...]:
        """The facial markers for a stream with ``labels`` (training set's when one
        exists, else the config's, else every label that is not a head marker and
        that no body rig matches: ``face.markers.select_facial`` by names; the
        neck test follows on the first neutral capture)."""
        if self.training is not None:
            return self.training.marker_names
        try:
            return select_facial(
                labels, self.face.head_markers, self.face.facial_markers,
                self.body_rigs, None,
            )  # fmt: skip
        except FacialMarkerError:
            return ()

    def stage(
        self, labels: Sequence[str], training: TrainingSet | None = None
    ) -> FaceStage | None:
        """The solve stage for a stream (None without a training set): of
        ``training`` when given (a build off the loop: the set when it was asked
        for), else of the current one. Reads only the face config and settings
        besides, never the capture state: any thread may call it."""
        t = self.training if training is None else training
        if t is None:
            return None
        head_w = None
        if tuple(t.head_names) == self.face.head_markers:
            head_w = self.face.head_weights
        solver, obs = face_solver(  # as ``retargetd solve --face`` builds it
            t, labels, regularization=self.settings.regularization,
            head_weights=head_w,
        )  # fmt: skip
        out = solver.new_output()
        names = t.expression_names
        outputs = self.face.outputs if t.k else ()
        missing = [n for n in (*t.head_names, *t.marker_names) if n not in labels]
        if missing:
            logger.warning("face markers not in the stream (occluded): %s", missing)
        return FaceStage(
            solver=solver,
            out=out,
            marker_names=t.marker_names,
            weight_names=names,
            output_names=outputs,
            out_matrix=self.face.output_matrix(names) if t.k else np.zeros((0, 0)),
            blend=np.zeros(len(outputs)),
            weights=out.weights,
            unobserved=obs.unobservable,
        )

    # ---- live capture ----------------------------------------------------------------

    @property
    def capturing(self) -> bool:
        """True while a capture collects frames."""
        return self._capture_target > 0

    def request_capture(self, name: str, count: int | None = None) -> str:
        """Start capturing pose ``name`` over the next ``count`` accepted frames.

        Raises:
            ValueError: an unknown name, a bad count, or an expression before any
                neutral.
        """
        n = count or self.settings.capture_frames
        if type(n) is not int or n < 1:
            raise ValueError(f"count must be a positive integer; got {n!r}")
        if name != "neutral" and name not in self.face.expressions:
            raise ValueError(
                f"face-capture: {name!r} is not 'neutral' nor an expression of face "
                f"config {self.face.name} ({', '.join(self.face.expressions[:6])}, ...)"
            )
        if self._averaging is not None:
            raise ValueError(
                "face-capture: the last capture is still being averaged; ask again"
            )
        if name != "neutral" and self.training is None:
            raise ValueError(
                "face-capture: capture 'neutral' first (it defines the head)"
            )
        self._capture_name = name
        self._capture_target = n
        self._capture_head = []
        self._capture_face = []
        self._capture_labels = ()
        return f"capturing face pose {name!r} over the next {n} frames: hold it"

    def collect(
        self, markers_world: F64Array, labels: tuple[str, ...]
    ) -> tuple[bool, str] | None:
        """Add one accepted frame to the capture; when its frames are in and it
        cannot be averaged (no facial markers), returns (False, message); else None
        (its averaging, off the loop, ends in :meth:`take_captured`)."""
        if labels != self._capture_labels:
            self._capture_head = []  # the marker layout changed: start again
            self._capture_face = []
            self._capture_labels = labels
            col = {lb: i for i, lb in enumerate(labels)}
            head = self.face.head_markers
            if self.training is not None:
                head = self.training.head_names
            self._head_cols = [col.get(n, -1) for n in head]
            self._face_names = self.facial_markers(labels)
            self._face_cols = [col.get(n, -1) for n in self._face_names]
        self._capture_head.append(_take_cols(markers_world, self._head_cols))
        self._capture_face.append(_take_cols(markers_world, self._face_cols))
        if len(self._capture_head) < self._capture_target:
            return None
        return self._finish(labels)

    def _finish(self, labels: tuple[str, ...]) -> tuple[bool, str] | None:
        name = self._capture_name
        head = np.stack(self._capture_head)
        face = np.stack(self._capture_face)
        self._capture_target = 0
        self._capture_head, self._capture_face = [], []
        names = self._face_names
        if self.training is None and not self.face.facial_markers and len(names):
            # The first neutral: keep the markers on the head's side of the neck.
            with np.errstate(all="ignore"), warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                up = on_head_side(np.nanmean(head, 0), np.nanmean(face, 0))
            names = tuple(n for n, k in zip(names, up, strict=True) if k)
            face = face[:, up]
        if not names:
            self.last_message = (
                f"face capture {name!r} failed: no facial markers (every label a "
                "head marker, a body rig's or below the neck)"
            )
            return False, self.last_message
        self._averaging = Build(
            (name, labels, head.shape[0]), capture_into, self.training, name, head,
            face, self.face, names,
        )  # fmt: skip
        return None

    @property
    def averaging(self) -> bool:
        """A capture's frames are being averaged off the loop."""
        return self._averaging is not None

    def wait_averaged(self) -> None:
        """Wait for the capture being averaged (offline replay, never live)."""
        if self._averaging is not None:
            self._averaging.wait()

    def take_captured(self) -> tuple[bool, str, tuple[str, ...]] | None:
        """Every loop pass: the capture whose averaging has ended, (captured, one
        line, the stream's labels), its training set in use and its save started;
        None while none has ended."""
        job = self._averaging
        if job is None or not job.done():
            return None
        self._averaging = None
        name, labels, n_frames = job.want
        try:
            training: TrainingSet = job.take()
        except Exception as exc:  # ValueError: the frames; any other: never fatal
            why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            self.last_message = f"face capture {name!r} failed: {why}"
            return False, self.last_message, labels
        self.training = training
        self.captures += 1
        path = self.settings.save_training or self.settings.training
        msg = (
            f"face pose {name!r} captured on {n_frames} frames "
            f"({training.k} expressions)"
        )
        if path:
            self._save_later(training, path, msg)
            msg += f"; saving {path}"
        else:
            msg += " (not saved: no face.training path)"
        self.last_message = msg
        return True, msg, labels

    # ---- the training set's file, written off the loop -------------------------------

    def _save_later(self, training: TrainingSet, path: str, captured: str) -> None:
        """Write ``training`` to ``path`` on a worker: now, or after the one being
        written (only the newest waits); ``captured``: its capture's line."""
        if self._save is None:
            self._save = Build((training, path, captured), training.save, path)
        else:
            self._next_save = (training, path, captured)

    @property
    def saving(self) -> bool:
        """A training set is being written (or waits to be)."""
        return self._save is not None

    def take_saved(self) -> tuple[bool, str] | None:
        """Every loop pass: the outcome of a save that has ended, (written, one
        line), the next one started; None while none has ended."""
        job = self._save
        if job is None or not job.done():
            return None
        training, path, captured = job.want
        self._save = None
        if self._next_save is not None:
            self._save_later(*self._next_save)
            self._next_save = None
        try:
            job.take()
        except Exception as exc:  # OSError: the disk; any other: said, never fatal
            outcome, ok = f"NOT saved: {exc}", False
        else:
            outcome, ok = f"saved {path}", True
        if self.last_message == f"{captured}; saving {path}":  # (no later capture)
            self.last_message = f"{captured}; {outcome}"
        return ok, f"face training set ({training.k} expressions) {outcome}"

    def close(self) -> None:
        """Finish writing (the daemon's close, never in the loop): a capture being
        averaged waited for and its set saved, the save under way waited for, the
        one waiting written here."""
        if self._averaging is not None:
            self._averaging.wait()
            self.take_captured()  # (its save started: waited for below)
        job, self._save = self._save, None
        if job is not None:
            job.wait()
            if job.error is not None:
                logger.warning("face training set NOT saved: %s", job.error)
        pending, self._next_save = self._next_save, None
        if pending is not None:
            training, path, _ = pending
            try:
                training.save(path)
            except OSError as exc:
                logger.warning("face training set NOT saved: %s", exc)

    def status(self) -> dict[str, object]:
        """The face part of ``ctl status --json``."""
        t = self.training
        return {
            "config": self.face.name,
            "trained": t is not None,
            "expressions": list(t.expression_names) if t is not None else [],
            "facial_markers": len(t.marker_names) if t is not None else 0,
            "unobserved": list(self._unobserved(t)),
            "noise_mm": 1e3 * t.noise_rms_m if t is not None else None,
            "capturing": self._capture_name if self.capturing else "",
            "captures": self.captures,
            "averaging": self.averaging,  # a capture averaged (off the loop)
            "saving": self.saving,  # its training set being written (off the loop)
            "last_capture": self.last_message,
        }

    def _unobserved(self, t: TrainingSet | None) -> tuple[str, ...]:
        # Judged once per training set (a few ms of linear algebra), not per status.
        if t is None:
            return ()
        if self._unobserved_cache[0] is not t:
            reg = self.settings.regularization
            head_w = None
            if tuple(t.head_names) == self.face.head_markers:
                head_w = np.asarray(self.face.head_weights)
            self._unobserved_cache = (
                t,
                observability(t, regularization=reg, head_weights=head_w).unobservable,
            )
        return self._unobserved_cache[1]


def warm_up() -> None:
    """Load the compiled face kernel (numba's cache, ~0.3 s) before the first frame,
    through the same path as a live frame."""
    layout = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0]])
    t = TrainingSet(
        head_names=("H1", "H2", "H3"), marker_names=("F1", "F2"),
        expression_names=("e",), head_layout=layout,
        neutral=np.array([[0.0, 0.05, -0.05], [0.05, 0.0, -0.05]]),
        deltas=np.array([[[0.0, 0.0, 0.01], [0.0, 0.01, 0.0]]]),
    )  # fmt: skip
    solver = FaceSolver(t)
    frame = np.vstack([layout, t.neutral + t.deltas[0]])
    valid = np.ones(len(frame), dtype=bool)
    solver.solve_frame(frame, valid, solver.new_output())
    valid[0] = False
    frame[0] = np.nan
    solver.solve_frame(frame, valid, solver.new_output())


def _take_cols(markers: F64Array, cols: Sequence[int]) -> F64Array:
    out = np.full((len(cols), 3), np.nan)
    for i, c in enumerate(cols):
        if c >= 0:
            out[i] = markers[c]
    return out


def capture_into(
    training: TrainingSet | None,
    name: str,
    head_world: F64Array,
    face_world: F64Array,
    face: FaceConfig,
    marker_names: Sequence[str],
) -> TrainingSet:
    """A training set with pose ``name`` (averaged over the frames) put in.

    Args:
        training: the current set (None: ``name`` must be ``"neutral"``).
        name: ``"neutral"`` or an expression of ``face``.
        head_world: (T, H, 3) metres, world, the config's head markers.
        face_world: (T, M, 3) metres, world, ``marker_names``' markers.
        face: the face config (expression order, head marker names).
        marker_names: (M,) facial marker names (the training set's when it exists).

    Raises:
        ValueError: no neutral yet, no frame with the head seen, a marker never seen.
    """
    if training is None:
        if name != "neutral":
            raise ValueError("capture 'neutral' first")
        layout = head_layout_from_frames(head_world)
    else:
        layout = training.head_layout
    mean = mean_pose(head_world, face_world, layout, marker_names)
    if training is None:
        return TrainingSet(
            head_names=face.head_markers, marker_names=tuple(marker_names),
            expression_names=(), head_layout=layout, neutral=mean,
            deltas=np.zeros((0, len(marker_names), 3)),
        )  # fmt: skip
    deltas = dict(zip(training.expression_names, training.deltas, strict=True))
    neutral = training.neutral
    if name == "neutral":
        neutral = mean
    else:
        deltas[name] = mean - neutral
    order = [e for e in face.expressions if e in deltas]
    order += [e for e in deltas if e not in order]  # from a file, not in the config
    m = len(training.marker_names)
    return TrainingSet(
        head_names=training.head_names,
        marker_names=training.marker_names,
        expression_names=tuple(order),
        head_layout=layout,
        neutral=neutral,
        deltas=np.array([deltas[e] for e in order]).reshape(len(order), m, 3),
        noise_rms_m=training.noise_rms_m,
    )
