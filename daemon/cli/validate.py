"""``retargetd validate TAKE --rig RIG (--calibration FILE | --calibrate-frames a:b)
--report DIR [--frames a:b]``: check every solved frame of a take (or of the rows
``--frames`` selects) against a MuJoCo model of the calibrated skeleton.

``--frames a:b``: solve and check only rows a..b-1 of the take (0-based, half-open);
``--calibrate-frames`` still counts rows of the whole take. The report's frame
numbers count from row a (the header says so; report.json ``frames_selected``,
``first_frame`` = the take's number of row a). The joint-limit detail names the bone
and angle at the worst flagged frames (by degrees beyond the limit), and the first
flagged frame when it is not among them.

Writes ``DIR/report.json`` (per check: threshold, frames flagged, worst frames and
values), ``DIR/report.txt`` (the same, readable) and ``DIR/model.xml`` (the model
checked against), ``DIR/checks.png`` (every check over time) and
``DIR/snapshot_*.png`` (the worst frames rendered headless: EGL, else OSMesa; skipped,
with the reason in the report, when neither works; ``validate.render``).
``--no-snapshots`` renders none (no GL subprocess; the report says ``snapshots off``):
the checks, report and plot are unchanged.
Body mass: the take's ``Bodymass`` when it has one, else 70 kg (``--body-mass-kg``
overrides). With the fit (the default), the marker residual checks
(``marker_residual_median``, ``marker_residual_max``: ``validate.residual``) read the
fit's own residuals and name the markers the calibrated skeleton cannot match
(report.json ``markers`` per such check; report.txt a line per flagged run). Checks
and thresholds: ``validate.checks``; the report's header
says how each threshold was set (the literature and the PiG walk, the MOTEK ballet and
the tennis serve). A joint-limit excursion of a single frame is listed as a transient
(a marker glitch), not failed.

``--json`` prints a summary as one JSON object instead of the text (README
"Machine-readable output"); ``--quiet`` prints nothing (the files are written as
always). On a terminal, progress bars (solve, checks) run on stderr.

Exit code: 0 every check passes, 1 a check fails, 2 bad input, 3 internal error.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from retargetd.daemon.errors import UsageError

if TYPE_CHECKING:
    import numpy as np

logger = logging.getLogger(__name__)

EXIT_PASS, EXIT_FAIL, EXIT_INTERNAL = 0, 1, 3

#: The report header's account of the thresholds (report.json "thresholds_note").
THRESHOLDS_NOTE = (
    "from the literature and three real takes that must pass: the PiG walk (rig "
    "plug-in-gait, calibrated on PiG_Calibration), the MOTEK ballet (rig cmu41, "
    "calibrated on MOTEK_T, another session) and the tennis serve (rig cmu41, "
    "calibrated on its first second); each limit sits above the takes' worst frame "
    "and below the synthetic defects it must catch (per check below; values and "
    "sources: validate.checks.THRESHOLDS, joint table: validate.limits). The fit's "
    "marker residual limits come from the literature alone, not from a take: the "
    "real takes confirm them, and the ballet's right arm and the serve's acromion "
    "markers fail them as the misfits they are (README)"
)


def add_parser(subparsers: Any) -> None:
    """Register ``validate``."""
    from retargetd.daemon.cli.args import (
        add_force_argument,
        add_frames_argument,
        add_output_arguments,
        add_solve_arguments,
    )

    parser = subparsers.add_parser(
        "validate",
        help="check a take's solved poses against a physical model (report)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_solve_arguments(parser)
    add_frames_argument(parser)
    parser.add_argument(
        "--report", required=True, metavar="DIR",
        help="folder for report.json, report.txt, model.xml and the snapshots",
    )  # fmt: skip
    add_output_arguments(parser, json=True)
    add_force_argument(parser)
    parser.add_argument(
        "--body-mass-kg", type=float, metavar="KG", help="override the body mass"
    )
    parser.add_argument(
        "--no-snapshots",
        action="store_true",
        help="render no worst-frame snapshots (checks, report and plot unchanged)",
    )
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Run ``validate``."""
    from retargetd.daemon.cli.args import refuse_existing, solver_for_take

    refuse_existing(args.report, force=args.force, option="--report")
    rig, take, cal, solver = solver_for_take(args)
    if cal.rest_bone_origin_pos is None:
        raise UsageError("calibration has no rest bone origins: recalibrate")
    mass = args.body_mass_kg
    if mass is None:
        mass = float(take.measurements.get("Bodymass", 0.0) or 0.0)
        mass = mass if mass > 0.0 else None
    if mass is not None and not mass > 0.0:
        raise UsageError(f"--body-mass-kg must be > 0; got {mass}")
    report_dir = Path(args.report)
    report_dir.mkdir(parents=True, exist_ok=True)
    try:
        return _validate(args, rig, cal, solver, take, mass, report_dir)
    except Exception as exc:  # a bug, not the user's input: exit 3, with traceback
        logger.exception("validate: internal error")
        sys.stderr.write(f"retargetd validate: internal error: {exc!r}\n")
        return EXIT_INTERNAL


def stance_by_bone(
    rig: Any, cal: Any, solve: Any, rate_hz: float, support: np.ndarray | None = None
) -> dict[str, np.ndarray]:
    """Foot bone name -> (T,) bool: the stance the detector of ``post/stance.py``
    finds on the solve (the NPZ's ``foot_contact``), for the skate check
    (``validate.skate``: validate may not import post, the command line hands it
    over); empty when the rig maps no LeftFoot/RightFoot. With ``support`` ((T,)),
    also the lowest level under the feet per frame from the detector's supports
    (``validate.checks.lowest_support``: the floor check's floor where it is below
    the calibration's, a stair down; 0 without feet)."""
    import numpy as np

    from retargetd.daemon.post.stance import foot_contact

    feet = [rig.humanoid.get(f) for f in ("LeftFoot", "RightFoot")]
    if None in feet or cal.rest_bone_origin_pos is None:
        if support is not None:
            support[:] = 0.0
        return {}
    levels = np.zeros((len(solve.root_pos), 2))
    contact = foot_contact(
        rig, cal, solve.root_pos, solve.world_from_bone_quat, rate_hz, levels
    )
    if support is not None:
        from retargetd.daemon.validate.checks import lowest_support

        support[:] = lowest_support(contact, levels)
    return {str(name): contact[:, k] for k, name in enumerate(feet)}


def _validate(
    args: argparse.Namespace,
    rig: Any,
    cal: Any,
    solver: Any,
    take: Any,
    mass: float | None,
    report_dir: Path,
) -> int:
    import numpy

    from retargetd.daemon.cli.args import print_json, solve_take_progress
    from retargetd.daemon.progress import Progress
    from retargetd.daemon.validate.checks import (
        THRESHOLDS,
        THRESHOLDS_BASIS,
        fit_pairs,
        validate_take,
    )
    from retargetd.daemon.validate.limits import LIMITS_SOURCES
    from retargetd.daemon.validate.model import (
        DEFAULT_BODY_MASS_KG,
        build_model,
        skeleton_from_calibration,
    )

    res = solve_take_progress(
        solver, take.positions, quiet=args.quiet, causal=args.causal
    )
    body_mass = DEFAULT_BODY_MASS_KG if mass is None else mass
    vm = build_model(skeleton_from_calibration(rig, cal), body_mass)
    (report_dir / "model.xml").write_text(vm.xml)
    with Progress(
        take.n_frames, "checks", unit="frames", enabled=False if args.quiet else None
    ) as bar:
        support = numpy.zeros(len(res.root_pos))
        stance = stance_by_bone(rig, cal, res, take.rate_hz, support)
        rep = validate_take(
            vm, res, take.rate_hz, fit=fit_pairs(rig, res.joint_names),
            progress=bar.update, stance=stance, support_m=support,
        )  # fmt: skip
    doc = {
        "take": str(take.path),
        "rig": rig.name,
        "method": getattr(args, "method", "fit"),
        "frames": rep.n_frames,
        "frames_selected": args.solve_rows,
        "first_frame": int(take.first_frame),
        "rate_hz": take.rate_hz,
        "body_mass_kg": body_mass,
        "body_mass_source": "default" if mass is None else "take or --body-mass-kg",
        "model": {"xml": "model.xml", "sha256": vm.digest, "floor_z_m": vm.floor_z},
        "thresholds_note": THRESHOLDS_NOTE,
        "limits_note": f"joint limits: {LIMITS_SOURCES}",
        "thresholds": THRESHOLDS,
        "thresholds_basis": THRESHOLDS_BASIS,
        "seconds_per_frame": rep.seconds_per_frame,
        "passed": rep.passed,
        "failed": rep.failed(),
        "calibration_match": args.calibration_match.to_json(),
        "layout_refined": (
            None
            if args.layout_refined is None
            else args.layout_refined.calibration.layout_refined
        ),
        "checks": {
            n: {**c.summary(), "detail": c.detail} for n, c in rep.checks.items()
        },
    }
    (report_dir / "report.json").write_text(json.dumps(doc, indent=1) + "\n")
    from retargetd.daemon.validate.render import visuals_text, write_visuals

    doc["visuals"] = write_visuals(
        report_dir, vm, res, rep, take.rate_hz,
        snapshots=not getattr(args, "no_snapshots", False),
    )  # fmt: skip
    (report_dir / "report.json").write_text(json.dumps(doc, indent=1) + "\n")
    rows = (
        f", rows {args.solve_rows} of the take: frame f below is take row "
        f"{args.solve_rows.split(':')[0]} + f"
        if args.solve_rows
        else ""
    )
    lines = [
        f"retargetd validate: {take.path} (rig {rig.name}, {rep.n_frames} frames at "
        f"{take.rate_hz:g} Hz{rows}, body mass {body_mass:g} kg)",
        f"Result: {'PASS' if rep.passed else 'FAIL: ' + ', '.join(rep.failed())}",
        args.calibration_match.summary(),
        "",
        f"How the thresholds were set: {THRESHOLDS_NOTE}",
        f"Joint limits: {LIMITS_SOURCES}",
        *(
            f"    {name}: {rep.checks[name].threshold:g} {rep.checks[name].unit}"
            f" - {basis}"
            for name, basis in THRESHOLDS_BASIS.items()
            if name in rep.checks
        ),
        "",
    ]
    width = max(18, *(len(name) for name in rep.checks))
    for name, c in rep.checks.items():
        s = c.summary(3)
        worst = ", ".join(
            f"{f} ({v:.3g})"
            for f, v in zip(s["worst_frames"], s["worst_values"], strict=True)
        )
        transients = f"  transients {c.transients.size}" if c.transients.size else ""
        lines.append(
            f"{name:{width}s} {'FAIL' if c.n_flagged else 'ok  '} flagged "
            f"{c.n_flagged:6d}"
            f"  max {s['max']:.4g} {c.unit} (threshold {c.threshold:g})"
            f"  worst frames: {worst}{transients}"
        )
        lines.extend(f"    {d}" for d in c.detail)
        lines.extend(f"    {w}" for w in c.warnings)
    lines.extend(["", *visuals_text(doc["visuals"])])
    text = "\n".join(lines) + "\n"
    (report_dir / "report.txt").write_text(text)
    if args.json:
        print_json(
            {
                "command": "validate",
                "take": str(take.path),
                "rig": rig.name,
                "report": str(report_dir / "report.json"),
                "frames": rep.n_frames,
                "frames_selected": args.solve_rows,
                "rate_hz": float(take.rate_hz),
                "body_mass_kg": body_mass,
                "passed": rep.passed,
                "failed": rep.failed(),
                "calibration_match": args.calibration_match.to_json(),
                "checks": {
                    n: {
                        "frames_flagged": c.n_flagged,
                        "threshold": c.threshold,
                        "unit": c.unit,
                        "max": doc["checks"][n]["max"],
                        "first_flagged": doc["checks"][n]["first_flagged"],
                    }
                    for n, c in rep.checks.items()
                },
            }
        )
    elif not args.quiet:
        sys.stdout.write(text)
    return EXIT_PASS if rep.passed else EXIT_FAIL
