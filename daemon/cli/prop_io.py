"""Props on the command line (shared by ``calibrate --prop`` and ``solve --props``;
not a command itself): a prop's definition from ``--config``'s ``[[prop]]`` table or
from the options, its markers found in a take, its calibration written and its
summary printed.

A take's labels are the stream's: a C3D that holds several subjects is read subject
by subject (``load_take`` strips the ``Name:`` prefix), so a prop named by prefix
(``boite:``) is read as the subject ``boite`` and its labels get the prefix back,
the labels the live stream carries and the layout file records.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

import numpy as np

from retargetd.daemon.errors import UsageError


def add_prop_arguments(parser: argparse.ArgumentParser) -> None:
    """``--prop`` and the options that define a prop without a config."""
    parser.add_argument(
        "--prop",
        metavar="NAME",
        help="calibrate a prop (a rigid body) instead of a performer: its layout from "
        "still frames (README 'Props and a virtual camera')",
    )
    parser.add_argument(
        "--config",
        metavar="FILE",
        help="--prop: the daemon config whose [[prop]] table NAME defines it",
    )
    parser.add_argument(
        "--markers", metavar="A,B,C", help="--prop: its marker labels (3 at least)"
    )
    parser.add_argument(
        "--prefix", metavar="P", help="--prop: its labels start with P (default NAME:)"
    )
    parser.add_argument(
        "--kind", choices=("rigid", "camera"), help="--prop: its kind (default rigid)"
    )
    parser.add_argument(
        "--pivot-mm",
        metavar="X,Y,Z",
        help="--prop: its origin from the markers' centroid, mm, world axes",
    )


def prop_definition(args: argparse.Namespace) -> dict[str, Any]:
    """The prop's name, markers, prefix, kind and pivot (metres), from ``--config``
    and the options (an option wins). Raises UsageError."""
    from retargetd.daemon.live.config import ConfigError, DaemonConfig

    name = args.prop
    spec: dict[str, Any] = {"markers": (), "prefix": f"{name}:", "kind": "rigid"}
    spec["pivot_m"] = (0.0, 0.0, 0.0)
    if args.config:
        try:
            config = DaemonConfig.from_toml(args.config)
        except ConfigError as exc:
            raise UsageError(str(exc)) from None
        table = next((p for p in config.props if p.name == name), None)
        if table is None:
            have = ", ".join(p.name for p in config.props) or "none"
            raise UsageError(
                f"--prop {name}: no [[prop]] of that name in {args.config}"
                f" (its props: {have})"
            )
        spec.update(markers=table.markers, prefix=table.prefix, kind=table.kind)
        spec["pivot_m"] = (
            table.pivot_x_mm / 1000,
            table.pivot_y_mm / 1000,
            table.pivot_z_mm / 1000,
        )
    if args.markers:
        spec["markers"] = tuple(m for m in args.markers.split(",") if m)
        if len(spec["markers"]) < 3:
            raise UsageError("--markers: a rigid fit needs 3 markers at least")
    if args.prefix is not None:
        spec["prefix"] = args.prefix
    if args.kind:
        spec["kind"] = args.kind
    if args.pivot_mm:
        try:
            xyz = tuple(float(v) / 1000 for v in args.pivot_mm.split(","))
        except ValueError:
            xyz = ()
        if len(xyz) != 3 or not all(np.isfinite(xyz)):
            raise UsageError(f"--pivot-mm: expected X,Y,Z in mm; got {args.pivot_mm!r}")
        spec["pivot_m"] = xyz
    return spec


def load_prop_take(
    path: str, markers: tuple[str, ...], prefix: str, **overrides: Any
) -> tuple[Any, list[str], np.ndarray]:
    """(take, labels as the stream names them, column of each prop marker): the take
    read whole, or as the subject its prefix names. Raises UsageError when the prop's
    markers are not in it."""
    from retargetd.replay.takes import load_take

    subject = overrides.pop("subject", None)
    stem = prefix[:-1] if prefix.endswith(":") else None
    heads = {m.split(":", 1)[0] for m in markers if ":" in m}
    if markers and len(heads) == 1:
        stem = heads.pop()  # listed markers of one subject: "boite:gauche_ext" ...
    try:
        take = load_take(path, subject=subject, **overrides)
        labels = list(take.labels)
    except ValueError:
        if subject is not None or not stem:
            raise
        take = None
    if take is None or (stem and stem in take.subjects and take.subject != stem):
        take = load_take(path, subject=stem, **overrides)
    if take.subject:
        labels = [f"{take.subject}:{label}" for label in take.labels]
    else:
        labels = list(take.labels)
    wanted = list(markers) or [x for x in labels if prefix and x.startswith(prefix)]
    missing = [m for m in wanted if m not in labels]
    if missing or len(wanted) < 3:
        said = f"missing {', '.join(missing)}" if missing else f"{len(wanted)} found"
        more = " ..." if len(labels) > 12 else ""
        raise UsageError(
            f"{path}: the prop's markers are not in the take ({said}; its labels: "
            f"{', '.join(labels[:12])}{more})"
        )
    cols = np.array([labels.index(m) for m in wanted], dtype=np.int64)
    return take, labels, cols


def calibrate_prop_command(args: argparse.Namespace) -> int:
    """``calibrate STATIC --prop NAME --out FILE.json``: the layout from the rows."""
    from retargetd.daemon.cli.args import parse_frames, take_overrides
    from retargetd.daemon.props.layout import PropError, ambiguous_pairs, calibrate_prop
    from retargetd.daemon.props.solve import DEFAULT_GATE_M

    spec = prop_definition(args)
    take, labels, cols = load_prop_take(
        args.static, spec["markers"], spec["prefix"], **take_overrides(args)
    )
    rows = parse_frames(args.frames, take.n_frames, option="--frames")
    names = [labels[c] for c in cols]
    try:
        layout = calibrate_prop(
            take.positions[rows][:, cols],
            names,
            name=args.prop,
            kind=spec["kind"],
            rate_hz=take.rate_hz,
            pivot_m=spec["pivot_m"],
            max_speed_m_s=np.inf if args.allow_moving_base_pose else 0.05,
        )
    except PropError as exc:
        raise UsageError(str(exc)) from None
    layout.save(args.out)
    out = sys.stdout.write
    out(
        f"wrote {args.out}: prop {args.prop} ({layout.kind}), {len(names)} markers, "
        f"{take.path} rows {rows.start}:{rows.stop}\n"
    )
    for label, p, s in zip(names, layout.layout_prop_m, layout.spread_mm, strict=True):
        out(
            f"  {label}: {p[0] * 1000:+8.1f} {p[1] * 1000:+8.1f} {p[2] * 1000:+8.1f} mm"
            f" (scatter {s:.2f} mm)\n"
        )
    pairs = ambiguous_pairs(layout.layout_prop_m, DEFAULT_GATE_M, names)
    if pairs:
        out(
            "warning: a swap of these pairs keeps every distance (a symmetric layout: "
            "move a marker): " + ", ".join(f"{a}/{b}" for a, b in pairs) + "\n"
        )
    return 0


def add_solve_prop_arguments(parser: argparse.ArgumentParser) -> None:
    """``solve --prop FILE.json`` (repeatable)."""
    parser.add_argument(
        "--prop",
        action="append",
        default=[],
        metavar="FILE.json",
        help="also solve this calibrated prop (calibrate --prop) on every frame "
        "(repeatable); NPZ: prop_NAME_* arrays",
    )


def solve_props_for_take(args: argparse.Namespace) -> tuple[dict[str, Any], list[str]]:
    """Each ``--prop`` layout solved on the take's rows (``--frames``): the NPZ
    arrays ``prop_NAME_world_from_prop_quat`` (T, 4) w x y z, ``prop_NAME_pos_world``
    (T, 3) metres, ``prop_NAME_flags`` (T,) (the pose stream's prop flags),
    ``prop_NAME_rms_m`` (T,) (NaN when held), ``prop_NAME_labels``; and one summary
    line per prop. Raises UsageError."""
    from retargetd.daemon.cli.args import parse_frames, take_overrides
    from retargetd.daemon.props import kernel as pk
    from retargetd.daemon.props.layout import PropError, load_layout
    from retargetd.daemon.props.solve import solve_take

    arrays: dict[str, Any] = {}
    lines: list[str] = []
    for path in args.prop:
        try:
            layout = load_layout(path)
        except PropError as exc:
            raise UsageError(f"--prop: {exc}") from None
        heads = {m.split(":", 1)[0] for m in layout.labels if ":" in m}
        prefix = f"{heads.pop()}:" if len(heads) == 1 else ""
        overrides = take_overrides(args)
        overrides["subject"] = None
        take, labels, _ = load_prop_take(args.take, layout.labels, prefix, **overrides)
        frames = getattr(args, "solve_frames", None)
        rows = parse_frames(frames, take.n_frames, option="--frames")
        track = solve_take(layout, labels, take.positions[rows], take.valid[rows])
        key = f"prop_{layout.name}_"
        arrays[key + "world_from_prop_quat"] = track.world_from_prop_quat
        arrays[key + "pos_world"] = track.prop_pos_world
        arrays[key + "flags"] = track.flags
        arrays[key + "rms_m"] = track.rms_m
        arrays[key + "labels"] = np.asarray(layout.labels, dtype=str)
        rms = track.rms_m[np.isfinite(track.rms_m)] * 1e3
        held = int(np.count_nonzero(track.flags & pk.FLAG_HELD))
        swaps = int(np.count_nonzero(track.flags & pk.FLAG_SWAP))
        stats = (
            f"residual RMS median {np.median(rms):.2f} mm, p95 "
            f"{np.percentile(rms, 95):.2f} mm, max {rms.max():.2f} mm"
            if len(rms)
            else "never solved"
        )
        lines.append(
            f"prop {layout.name}: {len(layout.labels)} markers, {len(track.flags)} "
            f"frames, {stats}; held {held} frames, swaps seen on {swaps}\n"
        )
    return arrays, lines
