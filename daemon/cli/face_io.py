"""``retargetd solve --face``: the face of a take solved offline and written beside (or
instead of) the body, in every format ``solve`` writes but BVH.

The face is solved as the daemon solves it (``face.take.solve_take``: the shapes the
training set's markers cannot observe left out and written as 0, a shape held while
a key marker is hidden), from the take's head and facial markers alone: with
``--face-only`` no rig and no calibration are needed (a head-mounted or seated facial
capture). What each format holds (README "Face output"):

- ``.npz``: ``face_shapes`` (K,) names; ``face_weights`` (T, K) float32 in [0, 1];
  ``face_shape_state`` (T, K) uint8 (1 unobserved, 2 hidden: the pose stream's
  ``RTDF`` bits); ``face_flags`` (T,) uint8 (its face flags); ``face_head_quat`` (T, 4)
  w x y z ``world_from_head`` and ``face_head_pos`` (T, 3) metres, from the head
  markers; ``face_marker_names`` (M,) and ``face_markers`` (T, M, 3) float32 metres,
  head coordinates (the stabilized markers, NaN occluded); ``face_unobserved``
  names. With ``--face-only`` also ``rate_hz``, ``first_frame``,
  ``world_from_capture``.
- ``.csv``: after the body's columns (or ``frame, time_s`` alone) ``face_flags``, one
  column per shape (its weight) then ``state_<shape>`` per shape.
- ``.glb``: a morph-target mesh (``replay.gltf.MorphFace``): the facial markers'
  neutral points, one morph target per shape, the weights animated, the node moved
  by the head pose; beside the skeleton, or alone.
- ``.mcap``: ``/face/weights`` (JSON) beside the Foxglove channels
  (``replay.foxglove``).
"""

from __future__ import annotations

import argparse
import csv
import logging
from typing import Any

import numpy as np

from retargetd.daemon.errors import UsageError
from retargetd.protocols.pose_stream import FACE_HEAD_LOST, SHAPE_HIDDEN

logger = logging.getLogger(__name__)


def add_face_arguments(parser: argparse.ArgumentParser) -> None:
    """``--face``, ``--face-only`` and ``--face-config``."""
    parser.add_argument(
        "--face", metavar="FACE.npz",
        help="also solve the face with this training set (retargetd face-train)",
    )  # fmt: skip
    parser.add_argument(
        "--face-only", action="store_true",
        help="solve the face alone (no rig, no calibration): a facial capture",
    )  # fmt: skip
    parser.add_argument(
        "--face-config", metavar="FACECONFIG",
        help="the face config whose head_weights the daemon uses (default: equal "
        "weights, as every preset)",
    )  # fmt: skip


def check_face_arguments(args: argparse.Namespace, out_format: str) -> Any:
    """Check the face options against the body's; load the training set.

    Returns:
        ``(training, head_weights)`` or None without ``--face``.

    Raises:
        UsageError: one line: ``--face-only`` without ``--face`` or with a rig or a
            calibration; no rig without ``--face-only``; ``.bvh`` with a face; an
            unreadable training set or face config.
    """
    if args.face is None:
        if args.face_only or args.face_config is not None:
            raise UsageError("--face-only and --face-config need --face FACE.npz")
        if args.rig is None or (args.calibration is None and not args.calibrate_frames):
            raise UsageError(
                "solve needs --rig and --calibration FILE or --calibrate-frames a:b "
                "(or --face FACE.npz --face-only for a face alone)"
            )
        return None
    if args.face_only:
        given = [
            o
            for o, v in (
                ("--rig", args.rig),
                ("--calibration", args.calibration),
                ("--calibrate-frames", args.calibrate_frames),
                ("--pipeline", getattr(args, "pipeline", None)),
                ("--fill-gaps", getattr(args, "fill_gaps", None)),
            )
            if v is not None
        ]
        if given:
            raise UsageError(f"--face-only solves no body: leave out {' '.join(given)}")
    elif args.rig is None or (args.calibration is None and not args.calibrate_frames):
        raise UsageError(
            "--face with a body needs --rig and --calibration or --calibrate-frames; "
            "--face-only solves the face alone"
        )
    if out_format == "bvh":
        raise UsageError(
            f"--face: BVH carries no blendshapes; write .npz, .csv, .glb or .mcap "
            f"(got --out {args.out})"
        )
    from retargetd.daemon.face.training import TrainingSet

    try:
        training = TrainingSet.load(args.face)
    except ValueError as exc:
        raise UsageError(f"--face: {exc}") from None
    if training.k == 0:
        raise UsageError(f"--face {args.face}: a neutral alone, no expression to solve")
    head_weights = None
    if args.face_config is not None:
        from retargetd.daemon.face.config import FaceConfigError, load_face_config

        try:
            cfg = load_face_config(args.face_config)
        except FaceConfigError as exc:
            raise UsageError(str(exc)) from None
        if cfg.head_markers == training.head_names:
            head_weights = cfg.head_weights
    return training, head_weights


def solve_face_of_take(face: Any, take: Any) -> Any:
    """The take's face (``face.take.FaceTake``), as the daemon solves it."""
    from retargetd.daemon.face.take import solve_take

    training, head_weights = face
    try:
        return solve_take(
            training, take.labels, take.positions, take.valid,
            head_weights=head_weights,
        )  # fmt: skip
    except ValueError as exc:
        raise UsageError(f"--face: {exc}") from None


def face_arrays(ft: Any) -> dict[str, Any]:
    """The NPZ's ``face_*`` arrays (module docstring)."""
    return {
        "face_shapes": np.asarray(ft.shapes, dtype=str),
        "face_weights": ft.weights,
        "face_shape_state": ft.shape_state,
        "face_flags": ft.flags,
        "face_head_quat": ft.world_from_head_quat,
        "face_head_pos": ft.head_pos,
        "face_marker_names": np.asarray(ft.marker_names, dtype=str),
        "face_markers": ft.markers_head,
        "face_unobserved": np.asarray(ft.unobserved, dtype=str),
    }


def write_face_csv(path: str, ft: Any, rate_hz: float, *, append: bool) -> None:
    """The face's columns (module docstring): appended to the body's CSV rows
    (``append``), else a CSV of ``frame, time_s`` and the face."""
    head = ["face_flags", *ft.shapes, *(f"state_{s}" for s in ft.shapes)]
    n = len(ft.weights)
    rows: list[list[str]]
    if append:
        with open(path, newline="", encoding="utf-8") as fh:
            rows = list(csv.reader(fh))
        if len(rows) != n + 1:
            raise ValueError(f"{path}: {len(rows) - 1} body rows, {n} face frames")
    else:
        rows = [["frame", "time_s"]] + [
            [str(t), f"{t / rate_hz:.9g}"] for t in range(n)
        ]
    rows[0] += head
    for t in range(n):
        rows[t + 1] += [
            str(int(ft.flags[t])),
            *(f"{float(w):.9g}" for w in ft.weights[t]),
            *(str(int(s)) for s in ft.shape_state[t]),
        ]
    with open(path, "w", newline="", encoding="utf-8") as fh:
        csv.writer(fh).writerows(rows)


def morph_face(face: Any, ft: Any, rate_hz: float) -> Any:
    """The glTF morph-target face (``replay.gltf.MorphFace``); a frame with the head
    lost keeps the last pose (NaN never goes into glTF)."""
    from retargetd.replay.gltf import MorphFace

    training = face[0]
    quat = ft.world_from_head_quat
    return MorphFace(
        name="face",
        neutral=training.neutral,
        targets=training.deltas,
        target_names=ft.shapes,
        times_s=np.arange(len(ft.weights)) / rate_hz,
        weights=ft.weights,
        world_from_head_quat=quat,
        head_pos=ft.head_pos,
    )


def write_face_only(
    args: argparse.Namespace, face: Any, take: Any, ft: Any, out_format: str
) -> None:
    """Write a face-only solve in ``out_format`` (npz, csv, glb or mcap)."""
    if out_format == "csv":
        write_face_csv(args.out, ft, take.rate_hz, append=False)
        return
    if out_format == "glb":
        from retargetd.daemon.post.export_gltf import GLTF_FROM_WORLD_QUAT
        from retargetd.replay.gltf import write_glb

        write_glb(
            args.out, names=[], parents=[], rest_translation=np.zeros((0, 3)),
            rest_rotation_quat=np.zeros((0, 4)), channels=[],
            scene_root_quat=GLTF_FROM_WORLD_QUAT,
            face=morph_face(face, ft, take.rate_hz),
        )  # fmt: skip
        return
    arrays = {
        **face_arrays(ft),
        "rate_hz": np.float64(take.rate_hz),
        "world_from_capture": np.asarray(take.world_from_capture, dtype=np.float64),
        "first_frame": np.int64(take.first_frame),
    }
    if out_format == "mcap":
        from retargetd.daemon.version import package_version
        from retargetd.replay.foxglove import write_solve_mcap

        n = take.n_frames
        write_solve_mcap(
            args.out, bone_names=[], bone_parents=[],
            bone_ends=np.zeros((n, 0, 2, 3)), world_from_bone_quat=np.zeros((n, 0, 4)),
            rate_hz=take.rate_hz, markers=take.positions, marker_valid=take.valid,
            library=f"retargetd {package_version()}", face=arrays,
        )  # fmt: skip
        return
    np.savez(args.out, **arrays)


def face_summary(ft: Any) -> list[str]:
    """The summary's face lines."""
    n = max(len(ft.weights), 1)
    held = (ft.shape_state & SHAPE_HIDDEN) != 0
    held_names = [
        f"{s} {100.0 * held[:, k].mean():.1f} %"
        for k, s in enumerate(ft.shapes)
        if held[:, k].any()
    ]
    lost = int(np.count_nonzero(ft.flags & FACE_HEAD_LOST))
    return [
        f"face: {len(ft.shapes)} shapes, {len(ft.shapes) - len(ft.unobserved)} solved; "
        f"unobserved (sent as 0): {', '.join(ft.unobserved) or 'none'}",
        f"face: head lost on {lost} of {n} frames; shapes held (a key marker "
        f"hidden): {', '.join(held_names) or 'none'}",
    ]


def face_json(ft: Any) -> dict[str, Any]:
    """The ``--json`` summary's ``face`` object."""
    held = (ft.shape_state & SHAPE_HIDDEN) != 0
    return {
        "shapes": list(ft.shapes),
        "unobserved": list(ft.unobserved),
        "head_lost_frames": int(np.count_nonzero(ft.flags & FACE_HEAD_LOST)),
        "held_fraction": {
            s: float(held[:, k].mean())
            for k, s in enumerate(ft.shapes)
            if held[:, k].any()
        },
    }
