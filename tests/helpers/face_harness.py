"""The exact synthetic performer wearing a face (importable: ``tests/helpers`` is on
pytest's ``pythonpath``): the ICT-FaceKit ARKit training set in the performer's own
head frame (its four head markers, shared with the body rig) and marker frames of body
plus 40 facial markers with known weights, float32 as the wire carries them."""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
from live_harness import _f32, _take

from retargetd.daemon.face.solve import TrainingSet
from retargetd.daemon.synth import face as fs

HEAD = ("LFHD", "RFHD", "LBHD", "RBHD")


@functools.cache
def _face(datasets: Path) -> tuple[TrainingSet, np.ndarray, np.ndarray]:
    """(training set in the performer's head frame, world_from_head rotations (T,3,3),
    head positions (T,3)) for every frame of the synthetic take."""
    take = _take()
    cols = [take.labels.index(n) for n in HEAD]
    head = take.markers_world[:, cols]  # (T, 4, 3), exact rigid head
    layout = head[0] - head[0].mean(axis=0)  # head frame = world axes at frame 0
    ict = fs.ict_training_set(datasets)
    # ICT head coordinates are x right, y forward, z up: the T-posed performer faces
    # world +Y with +Z up, so they are the world axes of frame 0 too.
    training = TrainingSet(
        head_names=HEAD, marker_names=ict.marker_names,
        expression_names=ict.expression_names, head_layout=layout,
        neutral=ict.neutral, deltas=ict.deltas,
    )  # fmt: skip
    rots = np.empty((len(head), 3, 3))
    for t, f in enumerate(head):
        c = f - f.mean(axis=0)
        u, _, vt = np.linalg.svd(layout.T @ c)
        d = np.sign(np.linalg.det(vt.T @ u.T))
        rots[t] = vt.T @ np.diag([1.0, 1.0, d]) @ u.T  # c ~ layout @ rot.T
    return training, rots, head.mean(axis=1)


def _stream(
    training: TrainingSet, rots: np.ndarray, pos: np.ndarray, rows: np.ndarray,
    weights: np.ndarray,
) -> tuple[tuple[str, ...], np.ndarray]:  # fmt: skip
    """Stream labels (body, then facial) and float32 frames (len(rows), N, 3)."""
    take = _take()
    local = training.neutral + np.einsum("tk,kmc->tmc", weights, training.deltas)
    face = np.einsum("tij,tmj->tmi", rots[rows], local) + pos[rows, None]
    frames = np.concatenate([take.markers_world[rows], face], axis=1)
    return (*take.labels, *training.marker_names), _f32(frames)
