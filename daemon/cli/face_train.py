"""``retargetd face-train TAKE --face FACECONFIG --poses neutral=a:b,jawOpen=c:d,...
--out face.npz``: build a face training set from a take.

Each pose is averaged over its frame range (rows of the take as loaded, 0-based,
half-open, as ``--frames`` elsewhere) after stabilization against the neutral head
layout (:func:`retargetd.daemon.face.solve.train`). ``neutral`` is required; every
other name must be one of the face config's ``expressions`` and the training set
keeps the config's expression order. ``--face`` is a shipped preset (``arkit52``,
``vrm0``, ``vrm1``) or a face config TOML (``retargetd.daemon.face.config``).

Facial markers are the config's ``facial_markers``; when it lists none, every take
marker that is not a head marker, not a marker of the body rig (``--rig``, default
the config's ``body_rig``) and on the head's side of the neck in the neutral range
(``retargetd.daemon.face.markers``). A listed marker the rig names is refused (exit
2, naming it). The command prints the facial markers it used.

The output is ``face.npz`` (:class:`~retargetd.daemon.face.solve.TrainingSet`, no
pickle); the command prints the expressions this marker layout cannot see or separate
at ``--noise-mm`` (3-D RMS, default 0.5 mm, stored in the file: the daemon leaves the
same shapes out), each with the shape it is confused with and by how much
(:func:`~retargetd.daemon.face.solve.observability`). Reference:
``daemon/face/faces/FACES.md``.
"""

from __future__ import annotations

import argparse
import logging
from typing import Any

from retargetd.daemon.cli.args import add_force_argument, take_overrides
from retargetd.daemon.errors import UsageError

logger = logging.getLogger(__name__)


def add_parser(subparsers: Any) -> None:
    """Register ``face-train``."""
    from retargetd.daemon.cli.args import add_take_arguments

    parser = subparsers.add_parser(
        "face-train",
        help="build a face training set (neutral + a pose per expression) from a take",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("take", metavar="TAKE", help="a .c3d, .trc or .mcap take")
    parser.add_argument(
        "--face", required=True, metavar="FACECONFIG",
        help="face config: a shipped preset name or a TOML file (FACES.md)",
    )  # fmt: skip
    parser.add_argument(
        "--poses", required=True, metavar="neutral=a:b,NAME=c:d,...",
        help="frame range of each pose (0-based, half-open rows)",
    )  # fmt: skip
    parser.add_argument(
        "--out", required=True, metavar="face.npz", help="the training set to write"
    )
    parser.add_argument(
        "--rig", metavar="RIG", default=None,
        help="body rig whose markers are never facial (default: the face config's "
        "body_rig; 'none' for a face-only take)",
    )  # fmt: skip
    parser.add_argument(
        "--noise-mm", type=float, default=None, metavar="MM",
        help="3-D RMS marker noise at which observability is judged (default 0.5 "
        "mm, face.training.DEFAULT_NOISE_RMS_M: between a Vicon's 0.15 mm static "
        "and < 2 mm moving error, Merriaux et al. 2017)",
    )  # fmt: skip
    add_force_argument(parser)
    add_take_arguments(parser)
    from retargetd.daemon.cli.args import add_output_arguments

    add_output_arguments(parser, json=False)
    parser.set_defaults(run=run)


def parse_poses(text: str, n_frames: int) -> list[tuple[str, slice]]:
    """``neutral=a:b,jawOpen=c:d`` -> [(name, rows)], in the order given.

    Raises:
        UsageError: malformed entry, repeated name or an empty range.
    """
    from retargetd.daemon.cli.args import parse_frames

    out: list[tuple[str, slice]] = []
    for item in filter(None, (s.strip() for s in text.split(","))):
        name, sep, rng = item.partition("=")
        if not sep or not name.strip():
            raise UsageError(f"--poses: expected NAME=a:b, got {item!r}")
        name = name.strip()
        if any(name == n for n, _ in out):
            raise UsageError(f"--poses: {name!r} given twice")
        out.append((name, parse_frames(rng, n_frames, option=f"--poses {name}")))
    return out


def run(args: argparse.Namespace) -> int:
    """Run ``face-train``."""
    import dataclasses
    import warnings

    import numpy as np

    from retargetd.daemon.face.config import FaceConfigError, load_face_config
    from retargetd.daemon.face.markers import FacialMarkerError, select_facial
    from retargetd.daemon.face.solve import observability, train
    from retargetd.daemon.face.training import DEFAULT_NOISE_RMS_M
    from retargetd.daemon.progress import Progress
    from retargetd.replay.takes import load_take

    if not args.out.lower().endswith(".npz"):
        raise UsageError(f"--out: expected a .npz file; got {args.out!r}")
    from retargetd.daemon.cli.args import refuse_existing

    refuse_existing(args.out, force=args.force)
    try:
        face = load_face_config(args.face)
    except FaceConfigError as exc:
        raise UsageError(str(exc)) from None
    take = load_take(args.take, **take_overrides(args))
    poses = parse_poses(args.poses, take.n_frames)
    unknown = [n for n, _ in poses if n != "neutral" and n not in face.expressions]
    if unknown:
        raise UsageError(f"--poses: not expressions of {face.name}: {unknown}")
    order = {n: i for i, n in enumerate(face.expressions)}
    poses.sort(key=lambda p: -1 if p[0] == "neutral" else order[p[0]])
    if args.noise_mm is None:
        args.noise_mm = 1e3 * DEFAULT_NOISE_RMS_M
    if not (args.noise_mm > 0.0 and np.isfinite(args.noise_mm)):
        raise UsageError(f"--noise-mm: expected a positive number; got {args.noise_mm}")
    rig_name = face.body_rig if args.rig is None else args.rig
    rig = None
    if rig_name and rig_name != "none":
        from retargetd.daemon.cli.args import load_rig_or_fail

        rig = load_rig_or_fail(rig_name)
    missing = [
        n for n in (*face.head_markers, *face.facial_markers) if n not in take.labels
    ]
    if missing:
        raise UsageError(f"take {args.take}: markers of {face.name} missing: {missing}")
    pos = np.where(take.valid[..., None], take.positions, np.nan)
    neutral_rows = (
        dict(poses)["neutral"] if any(n == "neutral" for n, _ in poses) else None
    )
    neutral_world = None
    if neutral_rows is not None:
        with warnings.catch_warnings():  # a marker never seen in the range: NaN
            warnings.simplefilter("ignore", RuntimeWarning)
            neutral_world = np.nanmean(pos[neutral_rows], axis=0)
    try:
        facial = select_facial(
            take.labels, face.head_markers, face.facial_markers,
            () if rig is None else (rig,), neutral_world,
        )  # fmt: skip
    except FacialMarkerError as exc:
        raise UsageError(f"{face.name}: {exc}") from None
    col = {n: i for i, n in enumerate(take.labels)}
    head_world = pos[:, [col[n] for n in face.head_markers]]
    face_world = pos[:, [col[n] for n in facial]]
    with Progress(3, "face-train: train", unit="steps", enabled=not args.quiet) as bar:
        try:
            training = train(
                head_world, face_world, poses,
                head_names=face.head_markers, marker_names=facial,
            )  # fmt: skip
        except ValueError as exc:
            raise UsageError(str(exc)) from None
        training = dataclasses.replace(training, noise_rms_m=1e-3 * args.noise_mm)
        bar.update()
        bar.set_description("face-train: save")
        training.save(args.out)
        bar.update()
        bar.set_description("face-train: observability")
        obs = observability(training)
        bar.update()
    if args.quiet:
        return 0
    print(
        f"wrote {args.out}: {len(training.head_names)} head markers, "
        f"{len(training.marker_names)} facial markers, {training.k} expressions"
    )
    source = (
        "listed by the face config"
        if face.facial_markers
        else (
            f"not head markers, not {rig.name}'s, above the neck"
            if rig is not None
            else "not head markers, above the neck"
        )
    )
    print(f"facial markers ({source}): {' '.join(training.marker_names)}")
    lines = obs.describe()
    print(
        f"unobservable with this marker layout ({args.noise_mm:g} mm noise): "
        f"{', '.join(obs.unobservable) or 'none'}"
    )
    for line in lines:
        print(f"  {line}")
    return 0
