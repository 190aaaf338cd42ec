"""The face of a whole take, offline: the same solver, frame by frame, as the daemon.

:func:`face_solver` builds what the daemon builds for a stream (the shapes the
training set's markers cannot observe left out, ``face.observability``; the config's
head weights when its head markers are the training set's), and :func:`solve_take`
runs it over every frame of a take in order, so ``retargetd solve --face`` writes what
the live daemon streams for the same frames (its ``FaceStage``, ``daemon/live/face.py``,
builds its solver with :func:`face_solver` too).

Labels: the take's labels are matched to the training set's marker names exactly, or,
when that finds none of a name, by the part after a ``Subject:`` prefix (C3D and Vicon
takes name markers ``Subject:LFHD``); a marker absent from the take is occluded on
every frame.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from retargetd.daemon.face.observability import Observability, observability
from retargetd.daemon.face.solve import FaceSolver
from retargetd.daemon.face.training import TrainingSet
from retargetd.protocols.frames import F64Array

logger = logging.getLogger(__name__)

#: The daemon's default ``[face] regularization`` (``observability.ridge``).
DEFAULT_REGULARIZATION = 1.0


def face_solver(
    training: TrainingSet,
    labels: Sequence[str],
    *,
    regularization: float = DEFAULT_REGULARIZATION,
    head_weights: Sequence[float] | None = None,
) -> tuple[FaceSolver, Observability]:
    """The solver the daemon runs for a stream with ``labels`` (and what it judged
    observable): the unobservable shapes left out (sent as 0)."""
    obs = observability(
        training,
        regularization=regularization,
        head_weights=None if head_weights is None else np.asarray(head_weights),
    )
    solver = FaceSolver(
        training,
        labels=tuple(labels),
        regularization=regularization,
        head_weights=head_weights,
        solved=obs.observable,
    )
    return solver, obs


def match_labels(training: TrainingSet, labels: Sequence[str]) -> tuple[str, ...]:
    """``labels`` renamed so that the training set's marker names find them: a label
    whose name after the last ``:`` is a head or facial marker the labels do not
    hold exactly becomes that name (the first such label)."""
    wanted = {*training.head_names, *training.marker_names}
    present = set(labels)
    out = list(labels)
    taken: set[str] = set()
    for i, lb in enumerate(labels):
        bare = lb.rsplit(":", 1)[-1]
        if bare != lb and bare in wanted and bare not in present and bare not in taken:
            out[i] = bare
            taken.add(bare)
    return tuple(out)


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class FaceTake:
    """A take's face, frame by frame (``retargetd solve --face``'s ``face_*`` arrays).

    Attributes:
        shapes: (K,) expression names (the training set's order).
        weights: (T, K) float32 in [0, 1], as the pose stream carries them; an
            unobserved shape is 0 on every frame.
        shape_state: (T, K) uint8 ``SHAPE_*`` bits per frame (unobserved, hidden).
        flags: (T,) uint8 ``FACE_*`` bits per frame (PROTOCOLS.md section 6).
        world_from_head_quat: (T, 4) float64 (w, x, y, z).
        head_pos: (T, 3) float64, metres, world.
        marker_names: (M,) stabilized facial marker names.
        markers_head: (T, M, 3) float32, metres, head coordinates; NaN = occluded.
        unobserved: the shapes left out of the solve.
        key_markers: each solved shape's key markers.
        iterations: (T,) int64 Cholesky solves of each frame's QP.
    """

    shapes: tuple[str, ...]
    weights: npt.NDArray[np.float32]
    shape_state: npt.NDArray[np.uint8]
    flags: npt.NDArray[np.uint8]
    world_from_head_quat: F64Array
    head_pos: F64Array
    marker_names: tuple[str, ...]
    markers_head: npt.NDArray[np.float32]
    unobserved: tuple[str, ...]
    key_markers: dict[str, tuple[str, ...]]
    iterations: npt.NDArray[np.int64]


def solve_take(
    training: TrainingSet,
    labels: Sequence[str],
    positions: F64Array,
    valid: npt.NDArray[np.bool_],
    *,
    regularization: float = DEFAULT_REGULARIZATION,
    head_weights: Sequence[float] | None = None,
) -> FaceTake:
    """Solve the face on every frame of a take, in order (the warm start and the
    held shapes carry from frame to frame, as live).

    Args:
        training: the performer's training set.
        labels: (N,) the take's labels (:func:`match_labels` applied).
        positions: (T, N, 3) float64, metres, world; NaN = occluded.
        valid: (T, N) bool.
        regularization / head_weights: as the daemon's ``[face]`` and face config.

    Raises:
        ValueError: fewer than 3 of the training set's head markers in the take.
    """
    names = match_labels(training, labels)
    found = [n for n in training.head_names if n in names]
    if len(found) < 3:
        raise ValueError(
            f"the take holds {len(found)} of the face's head markers "
            f"{list(training.head_names)}: a face needs 3"
        )
    missing = [n for n in training.marker_names if n not in names]
    if missing:
        logger.warning("facial markers not in the take (occluded): %s", missing)
    solver, obs = face_solver(
        training, names, regularization=regularization, head_weights=head_weights
    )
    out = solver.new_output()
    n, m, k = len(positions), len(training.marker_names), training.k
    weights = np.zeros((n, k), np.float32)
    state = np.zeros((n, k), np.uint8)
    flags = np.zeros(n, np.uint8)
    quat = np.zeros((n, 4))
    pos = np.zeros((n, 3))
    markers = np.zeros((n, m, 3), np.float32)
    iters = np.zeros(n, np.int64)
    frame = np.empty(positions.shape[1:])
    for t in range(n):
        np.copyto(frame, positions[t])
        frame[~valid[t]] = np.nan
        solver.solve_frame(frame, valid[t], out)
        weights[t] = out.weights
        state[t] = out.shape_state
        flags[t] = out.flags
        quat[t] = out.world_from_head_quat
        pos[t] = out.world_from_head_pos
        markers[t] = out.markers_head
        iters[t] = out.status[1]
    return FaceTake(
        shapes=training.expression_names,
        weights=weights,
        shape_state=state,
        flags=flags,
        world_from_head_quat=quat,
        head_pos=pos,
        marker_names=training.marker_names,
        markers_head=markers,
        unobserved=obs.unobservable,
        key_markers=solver.key_markers(),
        iterations=iters,
    )
