"""``retargetd rig check RIG [TAKE]``: validate a rig and show how it is built.

Prints, for every derived point and bone, what it is built from and the markers it
finally depends on; with a take, how the take's labels match the rig (prefixes
stripped, extra labels ignored, missing rig markers occluded) and which points and
bones the missing markers leave without data. Exit 0 when the rig is valid (and, with a
take, every bone can be built from the take's labels), 1 when the take leaves bones
without data, 2 for a bad rig or take (one line naming file, key and value).
``--json`` prints one JSON object instead (README "Machine-readable output").
"""

from __future__ import annotations

import argparse
import io
import math
import sys
from typing import Any

from retargetd.daemon.body.rig import LinePoint, Rig, RigError, load_rig, shipped_rigs
from retargetd.daemon.cli.args import take_overrides
from retargetd.daemon.errors import UsageError


def add_parser(subparsers: Any) -> None:
    """Register ``rig`` and its ``check`` subcommand."""
    parser = subparsers.add_parser("rig", help="validate and inspect rig files")
    sub = parser.add_subparsers(dest="rig_command", metavar="ACTION", required=True)
    check = sub.add_parser(
        "check",
        help="validate a rig (and its fit to a take); print what each point uses",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    check.add_argument(
        "rig", metavar="RIG", help=f"shipped name ({', '.join(shipped_rigs())}) or path"
    )
    check.add_argument("take", metavar="TAKE", nargs="?", help="a take to match")
    check.add_argument(
        "--frames",
        metavar="a:b",
        help="the take's base-pose rows for the up-lever check (default: all)",
    )
    from retargetd.daemon.cli.args import add_take_arguments

    add_take_arguments(check)
    check.add_argument(
        "--calibration",
        metavar="FILE",
        help="a calibration of the rig: what the fit's markers observe is worked out "
        "on it (default: on the take's base-pose rows, else on the synthetic "
        "performer wearing the rig's marker set when one is shipped)",
    )
    check.add_argument(
        "--json",
        action="store_true",
        help="print the result as one JSON object (README: stable keys)",
    )
    check.set_defaults(run=run)


def _describe_point(rig: Rig, name: str) -> str:
    point = next(p for p in rig.points if p.name == name)
    if isinstance(point, LinePoint):
        how = f"line {point.a} -> {point.b} at u = {point.u:g}"
    elif point.rule is not None:
        rule = ", ".join(f"{k} of {v.text}" for k, v in point.rule.items())
        how = f"rigid in frame [{', '.join(point.frame)}]; base-pose rule: {rule}"
    else:
        assert point.offset_mm is not None
        off = ", ".join(e.text for e in point.offset_mm)
        how = f"rigid in frame [{', '.join(point.frame)}]; offset_mm [{off}]"
    return how


def run(args: argparse.Namespace) -> int:
    """Run ``rig check``."""
    try:
        rig = load_rig(args.rig)
    except RigError as exc:
        raise UsageError(str(exc)) from None
    doc: dict[str, Any] = {
        "command": "rig check",
        "rig": rig.name,
        "source": str(rig.source),
        "valid": True,
        "markers": list(rig.markers),
        "points": [p.name for p in rig.points],
        "bones": [
            {"name": b.name, "parent": b.parent, "humanoid": b.humanoid or None}
            for b in rig.bones
        ],
        "joint_centres": dict(rig.joints),
        "take": None,
    }
    out = io.StringIO().write if args.json else sys.stdout.write
    rc = _describe(rig, args, out, doc)
    if args.json:
        from retargetd.daemon.cli.args import print_json

        print_json(doc)
    return rc


def _describe(rig: Rig, args: argparse.Namespace, out: Any, doc: dict[str, Any]) -> int:
    out(f"rig {rig.name} ({rig.source}): valid\n")
    if rig.description:
        out(f"  {rig.description}\n")
    out(f"markers ({len(rig.markers)}):\n")
    for name, aliases in rig.markers.items():
        alias = "" if aliases == (name,) else f"  <- {' | '.join(aliases)}"
        out(f"  {name}{alias}\n")
    if rig.measurements:
        out(f"measurements ({len(rig.measurements)}, mm):\n")
        for m in rig.measurements.values():
            out(f"  {m.name} = {m.default_mm:g} (default) {m.description}\n")
    if rig.segments:
        out(f"rigid segments ({len(rig.segments)}):\n")
        for seg, names in rig.segments.items():
            out(f"  {seg}: {' '.join(names)}\n")
    out(f"derived points ({len(rig.points)}, in solve order):\n")
    for p in rig.points:
        out(f"  {p.name}: {_describe_point(rig, p.name)}\n")
        out(f"      markers: {' '.join(rig.markers_of(p.name))}\n")
        base = [m for m in rig.markers_of(p.name, base_pose=True)
                if m not in rig.markers_of(p.name)]  # fmt: skip
        if base:
            out(f"      base pose only: {' '.join(base)}\n")
    out(f"bones ({len(rig.bones)}, parents first):\n")
    for b in rig.bones:
        up = b.up[0] if len(b.up) == 1 else f"{b.up[0]} -> {b.up[1]}"
        hum = f" [{b.humanoid}]" if b.humanoid else ""
        out(
            f"  {b.name}{hum}: parent {b.parent or '(root)'}; origin {b.origin}, "
            f"aim {b.aim}, up {up}\n"
        )
        markers: list[str] = []
        for name in b.inputs:
            markers.extend(m for m in rig.markers_of(name) if m not in markers)
        out(f"      markers: {' '.join(markers)}\n")
    out(f"joint centres ({len(rig.joints)}): ")
    out(" ".join(f"{j}={p}" for j, p in rig.joints.items()) + "\n")
    unmapped = [h for h in _humanoid_order() if h not in rig.humanoid]
    out(f"humanoid: {len(rig.humanoid)} mapped; not solved: {' '.join(unmapped)}\n")
    doc["humanoid_unmapped"] = unmapped
    doc["observability"] = None
    rc = 0
    cal = None
    source = ""
    if args.take is not None:
        rc, cal = _check_take(rig, args, out, doc)
        source = f"the take's base-pose rows ({args.frames or 'all'})"
    if args.calibration is not None:
        from retargetd.daemon.body.calibration import (
            CalibrationError,
            load_calibration,
        )

        try:
            cal = load_calibration(args.calibration)
        except (CalibrationError, OSError, ValueError) as exc:
            raise UsageError(f"--calibration {args.calibration}: {exc}") from None
        source = f"calibration {args.calibration}"
    if cal is None and args.take is None:
        cal = _synthetic_calibration(rig)
        source = "the synthetic performer's T-pose"
    if cal is not None:
        _print_observability(rig, cal, source, out, doc)
    return rc


def _humanoid_order() -> tuple[str, ...]:
    from retargetd.daemon.body.rig import HUMANOID_BONES

    return HUMANOID_BONES


def _synthetic_calibration(rig: Rig) -> Any:
    """The rig calibrated on the synthetic performer wearing the shipped marker set
    of the rig's name (its T-pose hold), or None when there is none."""
    from retargetd.daemon.body.calibration import CalibrationError, calibrate
    from retargetd.daemon.cli.args import held_log_warnings
    from retargetd.daemon.synth.performer import shipped_markersets, synthesize

    if rig.name not in shipped_markersets():
        return None
    take = synthesize(seconds=0.5, rate_hz=60.0, markerset=rig.name, base_pose_s=0.5)
    try:
        with held_log_warnings("retargetd.daemon.body"):
            return calibrate(rig, take.markers_world, take.labels)
    except CalibrationError:
        return None


def _print_observability(
    rig: Rig, cal: Any, source: str, out: Any, doc: dict[str, Any]
) -> None:
    """What the fit's markers observe of each bone's rotation, and what holds the
    rest (``body.fit_observe``), on ``cal``'s base pose."""
    from retargetd.daemon.body import fit_observe
    from retargetd.daemon.body.calibration import CalibrationError
    from retargetd.daemon.body.fit_model import build_fit_model
    from retargetd.daemon.body.rig_fit import free_plane_axis
    from retargetd.daemon.cli.args import held_log_warnings

    base = cal.base_marker_pos
    if base is None or cal.rest_bone_origin_pos is None:
        out("observability: not computed (the calibration predates the fit)\n")
        return
    try:
        with held_log_warnings("retargetd.daemon.body"):
            model = build_fit_model(rig, cal, base[None], None)
    except (CalibrationError, ValueError) as exc:
        out(f"observability: not computed ({exc})\n")
        return
    lever_min = 1e3 * fit_observe.MIN_LEVER_M
    out(
        f"observability on {source} (what the fit's markers determine of each "
        f"joint; a rotation under {lever_min:.1f} mm/rad, 5 deg at 1 mm noise, is "
        "held at the calibration pose by the automatic prior):\n"
    )
    bones: dict[str, Any] = {}
    for obs in model.observation:
        riders = [
            m
            for i, m in enumerate(model.marker_names)
            if model.marker_bone[i] == rig.bone_names.index(obs.bone)
            and model.marker_weight[i] > 0.0
        ]
        explicit = rig.fit.bones.get(obs.bone)
        stiff = explicit.stiffness_mm if explicit is not None else 0.0
        note = f"; the rig's stiffness {stiff:g} mm/rad" if stiff else ""
        plane = explicit.stiffness_free_plane if explicit is not None else ()
        spared = None
        if len(plane) == 2 and all(m in model.marker_names for m in plane):
            i, k = (model.marker_names.index(m) for m in plane)
            if model.marker_weight[i] > 0.0 and model.marker_weight[k] > 0.0:
                spared = free_plane_axis(model.marker_local[i], model.marker_local[k])
        if stiff and spared is not None:
            note += (
                f" on every rotation but the one about [{spared[0]:+.2f}, "
                f"{spared[1]:+.2f}, {spared[2]:+.2f}] (the normal of the plane "
                f"through the joint, {' and '.join(plane)})"
            )
        out(f"  {obs.bone} ({obs.dof}{note}): {obs.describe()}\n")
        out(f"      markers riding it: {' '.join(riders) or '(none)'}\n")
        twist = model.twist_axis[rig.bone_names.index(obs.bone)]
        to = explicit.twist_to if explicit is not None else ""
        if obs.dof == "hinge_twist" or (obs.dof == "swing" and to):
            off = math.degrees(math.acos(min(1.0, abs(float(twist[1])))))
            what = "twist axis" if obs.dof == "hinge_twist" else "no twist about"
            out(
                f"      {what} [{twist[0]:+.3f} {twist[1]:+.3f} {twist[2]:+.3f}] "
                f"in its axes, {off:.1f} deg off its +Y "
                f"({'to ' + to if to else 'its own axis'})\n"
            )
        bones[obs.bone] = {
            "dof": obs.dof,
            "markers": riders,
            "stiffness_mm": stiff,
            "stiffness_spares_axis": (
                None if spared is None else [round(float(v), 4) for v in spared]
            ),
            "twist_axis": [round(float(v), 4) for v in twist],
            "rotations": [
                {
                    "axis": [round(float(v), 4) for v in axis],
                    "lever_mm_per_rad": round(float(lever), 2),
                    "observed": bool(seen),
                    "held_by": "markers" if seen else "automatic prior",
                }
                for axis, lever, seen in zip(
                    obs.axes, obs.lever_mm, obs.observed, strict=True
                )
            ],
        }
    doc["observability"] = {
        "source": source,
        "min_lever_mm_per_rad": round(lever_min, 3),
        "prior_stiffness_mm_per_rad": round(lever_min, 3),
        "bones": bones,
    }


def _check_take(
    rig: Rig, args: argparse.Namespace, out: Any, doc: dict[str, Any]
) -> tuple[int, Any]:
    from retargetd.daemon.body.calibration import match_markers
    from retargetd.replay.takes import load_take

    take = load_take(args.take, **take_overrides(args))
    cols = match_markers(rig, take.labels)
    missing = [m for m, c in zip(rig.markers, cols, strict=True) if c < 0]
    used = {c for c in cols if c >= 0}
    extra = [lab for i, lab in enumerate(take.labels) if i not in used]
    out(f"take {take.path}: {take.n_markers} markers, {take.n_frames} frames\n")
    out(f"  matched {len(rig.markers) - len(missing)}/{len(rig.markers)} rig markers\n")
    if missing:
        out(f"  missing (occluded in every frame): {' '.join(missing)}\n")
    if extra:
        out(f"  extra labels (ignored): {' '.join(extra)}\n")
    for m, c in zip(rig.markers, cols, strict=True):
        if c >= 0 and not take.valid[:, c].all():
            gap = 100.0 * (1.0 - take.valid[:, c].mean())
            out(f"  {m} ({take.labels[c]}): occluded in {gap:.1f} % of frames\n")
    lost_points = [
        p.name for p in rig.points if set(rig.markers_of(p.name)) & set(missing)
    ]
    segs = {m: s for s, names in rig.segments.items() for m in names}
    # A missing marker of a rigid segment with >= 3 others present is rebuilt.
    rebuildable = {
        m
        for m in missing
        if m in segs and sum(1 for n in rig.segments[segs[m]] if n not in missing) >= 3
    }
    lost = set(missing) - rebuildable
    dead_points = [p.name for p in rig.points if set(rig.markers_of(p.name)) & lost]
    dead_bones = []
    for b in rig.bones:
        need: set[str] = set()
        for p in b.inputs:
            need |= set(rig.markers_of(p))
        if need & lost:
            dead_bones.append(b.name)
    doc["take"] = str(take.path)
    doc["matched_markers"] = len(rig.markers) - len(missing)
    doc["missing_markers"] = missing
    doc["extra_labels"] = extra
    doc["rebuilt_markers"] = sorted(rebuildable)
    doc["bones_without_data"] = dead_bones
    doc["up_levers_m"] = None
    if lost_points:
        out(f"  points using missing markers: {' '.join(lost_points)}\n")
    if rebuildable:
        out(f"  rebuilt from their rigid segment: {' '.join(sorted(rebuildable))}\n")
    if dead_bones:
        out(f"  bones without data (held at rest, flagged): {' '.join(dead_bones)}\n")
        out(f"  points without data: {' '.join(dead_points)}\n")
        return 1, None
    out("  every bone can be built from this take\n")
    doc["up_levers_m"], cal = _check_levers(rig, take, args, out)
    return 0, cal


def _check_levers(
    rig: Rig, take: Any, args: argparse.Namespace, out: Any
) -> tuple[dict[str, float] | None, Any]:
    """Calibrate on the base-pose rows and print each bone's up lever; a warning
    line for each under ``body.sanity.UP_LEVER_MIN_M``. Returns the levers (metres)
    and the calibration, (None, None) when the calibration failed."""
    from retargetd.daemon.body import sanity
    from retargetd.daemon.body.calibration import CalibrationError, calibrate
    from retargetd.daemon.cli.args import held_log_warnings, parse_frames

    rows = parse_frames(args.frames, take.n_frames, option="--frames")
    base = take.positions[rows]
    try:
        with held_log_warnings("retargetd.daemon.body"):
            cal = calibrate(rig, base, take.labels, take_measurements=take.measurements)
    except CalibrationError as exc:
        out(f"  up levers: not computed (calibration failed: {exc})\n")
        return None, None
    levers = sanity.up_levers(rig, cal, base, take.labels)
    out(
        f"  up levers in the base pose (rows {rows.start}:{rows.stop}; at least "
        f"{1000 * sanity.UP_LEVER_MIN_M:.0f} mm wanted): "
        + ", ".join(f"{b} {1000 * v:.0f} mm" for b, v in levers.items())
        + "\n"
    )
    for line in sanity.check_up_levers(rig, cal, base, take.labels):
        out(f"  warning: {line}\n")
    return {b: float(v) for b, v in levers.items()}, cal
