"""Argument, take and rig helpers shared by the commands: frame selections ``a:b``
(0-based, half-open row indices), the take options (``--subject``, ``--take-units``,
``--take-up``), ``--rig``/``--measure``, and loading a rig, a take and its calibration
into a solver. Heavy modules are imported inside the helpers so that ``retargetd
--help`` stays fast (the CLI is the only layer that imports lazily)."""

from __future__ import annotations

import argparse
import contextlib
import logging
import sys
from collections.abc import Iterator
from typing import Any

from retargetd.daemon.errors import UsageError


def parse_frames(text: str | None, n_frames: int, *, option: str) -> slice:
    """Parse ``a:b`` (0-based, half-open rows of the take as loaded; either side may be
    omitted; negative counts from the end) into a slice of ``n_frames`` rows.

    Raises:
        UsageError: naming the option when the text is malformed or selects nothing.
    """
    if text is None:
        return slice(0, n_frames)
    parts = text.split(":")
    if len(parts) != 2:
        raise UsageError(f"{option}: expected a:b (0-based, half-open); got {text!r}")
    try:
        a = int(parts[0]) if parts[0].strip() else 0
        b = int(parts[1]) if parts[1].strip() else n_frames
    except ValueError:
        raise UsageError(f"{option}: expected integers a:b; got {text!r}") from None
    start, stop, _ = slice(a, b).indices(n_frames)
    if stop <= start:
        raise UsageError(
            f"{option}: {text!r} selects no frames of a take with {n_frames} frames"
        )
    return slice(start, stop)


def add_take_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``--subject``, ``--take-units``, ``--take-up`` and ``--take-rate``.

    Shared by commands; pass :func:`take_overrides` to ``load_take``.
    """
    parser.add_argument("--subject", metavar="NAME", help="subject to load")
    parser.add_argument(
        "--take-units", metavar="U", help="override the file's length unit (mm, m ...)"
    )
    parser.add_argument(
        "--take-up", metavar="AXIS", help="override the file's up axis (+Z, +Y ...)"
    )
    parser.add_argument(
        "--take-rate",
        metavar="HZ",
        type=float,
        help="override the file's frame rate (needed when the file says 0 Hz)",
    )


def take_overrides(args: argparse.Namespace) -> dict[str, Any]:
    """``load_take`` keyword arguments from :func:`add_take_arguments`' options."""
    return {
        "subject": args.subject,
        "units": args.take_units,
        "up_axis": args.take_up,
        "rate_hz": getattr(args, "take_rate", None),
    }


def add_rig_arguments(
    parser: argparse.ArgumentParser,
    required: bool = True,
    rig_help: str = "shipped rig name or a rig file",
) -> None:
    """``--rig``, ``--measure`` and ``--allow-moving-base-pose`` (shared by calibrate,
    solve and view, where the rig is optional)."""
    parser.add_argument("--rig", required=required, metavar="RIG", help=rig_help)
    parser.add_argument(
        "--measure",
        action="append",
        default=[],
        metavar="NAME=MM",
        help="override a subject measurement in mm (repeatable)",
    )
    parser.add_argument(
        "--allow-moving-base-pose",
        action="store_true",
        help="calibrate even when the markers move over the base-pose frames",
    )


def parse_measures(items: list[str]) -> dict[str, float]:
    """``["LKneeWidth=105", ...]`` -> {name: mm}. Raises UsageError naming the item."""
    out: dict[str, float] = {}
    for item in items:
        name, sep, value = item.partition("=")
        try:
            if not sep or not name:
                raise ValueError
            out[name.strip()] = float(value)
        except ValueError:
            raise UsageError(f"--measure: expected NAME=MM; got {item!r}") from None
    return out


def calibrate_from_take(
    take: Any,
    rig: Any,
    frames: slice,
    overrides: dict[str, float],
    *,
    allow_moving: bool = False,
    rom: Any = None,
    method: str = "fit",
) -> Any:
    """Calibrate ``rig`` on ``take.positions[frames]`` after the base-pose sanity
    checks (``body.sanity.calibrate_checked``: up axis, units, stillness, left/right
    labels; then stature, left/right symmetry and, for ``method`` "construction",
    each bone's up lever of the result; the live calibration runs the same).
    Warnings go to stderr, one line
    each, only once the calibration succeeded (a wrong rig gives its one error line
    alone).

    Raises:
        UsageError: a calibration error or a base pose that would give garbage.
    """
    from retargetd.daemon.body import sanity
    from retargetd.daemon.body.calibration import CalibrationError

    source = sanity.BasePoseSource(
        units=take.units, units_source=take.units_source, up_axis=take.up_axis,
        up_source=take.up_source, world_from_capture=take.world_from_capture,
        rate_hz=take.rate_hz,
    )  # fmt: skip
    try:
        with held_log_warnings("retargetd.daemon.body") as held:
            cal, notes = sanity.calibrate_checked(
                rig,
                take.positions[frames],
                take.labels,
                source,
                allow_moving=allow_moving,
                take_measurements=take.measurements,
                overrides=overrides,
                base_pose={
                    "take": str(take.path),
                    "subject": take.subject,
                    "frames": f"{frames.start}:{frames.stop}",
                    "rate_hz": take.rate_hz,
                },
                rom=rom,
                up_levers=method == "construction",
            )
    except (CalibrationError, sanity.SanityError) as exc:
        raise UsageError(str(exc)) from None
    held.pass_on()
    for note in notes:
        sys.stderr.write(f"warning: {note}\n")
    return cal


class _HeldRecords(logging.Handler):
    """Keeps log records back until :meth:`pass_on` (dropped if never passed on)."""

    def __init__(self, target: logging.Logger) -> None:
        super().__init__(logging.NOTSET)
        self.target = target
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)

    def pass_on(self) -> None:
        """Pass the held records on to the handlers above the logger (not named
        ``release``: that is ``logging.Handler``'s lock release)."""
        records, self.records = self.records, []
        parent = self.target.parent
        for record in records:
            if parent is not None and record.levelno >= parent.getEffectiveLevel():
                parent.handle(record)


@contextlib.contextmanager
def held_log_warnings(name: str) -> Iterator[_HeldRecords]:
    """Hold back what logger ``name`` (and its children) logs inside the block;
    call ``pass_on()`` on the result to let it through (after the block)."""
    target = logging.getLogger(name)
    handler = _HeldRecords(target)
    propagate = target.propagate
    target.addHandler(handler)
    target.propagate = False
    try:
        yield handler
    finally:
        target.removeHandler(handler)
        target.propagate = propagate


def load_rig_or_fail(name: str) -> Any:
    """Load a rig; a bad rig is a UsageError (one line, exit 2)."""
    from retargetd.daemon.body.rig import RigError, load_rig

    try:
        return load_rig(name)
    except RigError as exc:
        raise UsageError(str(exc)) from None


def add_solve_arguments(
    parser: argparse.ArgumentParser, *, body_optional: bool = False
) -> None:
    """TAKE, ``--rig``/``--measure``, ``--calibration FILE | --calibrate-frames a:b``
    and the take options: what every command that solves a take accepts
    (``body_optional``: the rig and calibration may be left out, for ``solve
    --face-only``; the command checks them)."""
    parser.add_argument("take", metavar="TAKE", help="a .c3d, .trc or .mcap take")
    add_rig_arguments(parser, required=not body_optional)
    group = parser.add_mutually_exclusive_group(required=not body_optional)
    group.add_argument("--calibration", metavar="FILE.json", help="calibrated skeleton")
    group.add_argument(
        "--calibrate-frames",
        metavar="a:b",
        help="calibrate on these rows of the take itself (0-based, half-open)",
    )
    add_method_argument(parser)
    add_take_arguments(parser)
    parser.add_argument(
        "--strict-calibration",
        action="store_true",
        help="exit 2 when the calibration does not match the take (a segment's "
        "markers off their calibrated layout: README 'Does the calibration fit "
        "the take?'); else a warning",
    )
    parser.add_argument(
        "--refine-layout",
        action="store_true",
        help="re-place each marker on its bone from this take's frames before "
        "solving (a wand re-seated since the static; the joint model kept; the "
        "fit only): says per marker how far it moved (README 'Re-seated markers')",
    )


def add_frames_argument(parser: argparse.ArgumentParser) -> None:
    """``--frames a:b`` (``solve``, ``validate``): the rows of the take to solve.

    Stored as ``args.solve_frames`` (``blend`` and ``loop`` have an integer
    ``--frames`` of their own). ``--calibrate-frames`` still counts rows of the whole
    take; the output keeps the take's frame numbers (``first_frame`` moved on by a).
    """
    parser.add_argument(
        "--frames",
        dest="solve_frames",
        metavar="a:b",
        help="solve only these rows of the take (0-based, half-open, as "
        "--calibrate-frames, which still counts rows of the whole take); the "
        "output's first_frame is the take's number of row a",
    )


def add_method_argument(
    parser: argparse.ArgumentParser, default: str | None = None
) -> None:
    """``--method construction|fit`` (README "Two ways to solve the body")."""
    parser.add_argument(
        "--method",
        choices=("construction", "fit"),
        default=default or "fit",
        help="the body solve: the rigid-skeleton fit to every visible marker "
        "(default) or the chapter's construction",
    )
    parser.add_argument(
        "--causal",
        action="store_true",
        help="the fit as the live daemon solves it, each frame from the ones before "
        "it alone; by default an offline take is also solved backwards and each "
        "hidden marker's span filled from both sides (README 'Two ways to solve "
        "the body')",
    )


def solver_for_take(args: argparse.Namespace) -> tuple[Any, Any, Any, Any]:
    """Load the rig and the take, load or make the calibration, build the solver,
    and check that the calibration fits the take (:func:`check_calibration_match`;
    its result is left in ``args.calibration_match`` for the command's summary).
    With ``--frames a:b`` (``args.solve_frames``) the take returned is cut to those
    rows after calibrating (``args.solve_rows`` = ``"a:b"``, else None).

    Returns:
        ``(rig, take, calibration, solver)``.

    Raises:
        UsageError: a bad rig, calibration or frame selection, or with
            ``--strict-calibration`` a calibration that does not match the take
            (one line, exit 2).
    """
    from retargetd.daemon.body.calibration import (
        CalibrationError,
        load_calibration,
    )
    from retargetd.daemon.cli.args import parse_frames
    from retargetd.replay.takes import load_take

    rig = load_rig_or_fail(args.rig)
    take = load_take(args.take, **take_overrides(args))
    rows = None  # --frames: checked before calibrating, applied after
    if getattr(args, "solve_frames", None) is not None:
        rows = parse_frames(args.solve_frames, take.n_frames, option="--frames")
    args.solve_rows = None if rows is None else f"{rows.start}:{rows.stop}"
    try:
        if args.calibration is not None:
            cal = load_calibration(args.calibration)
        else:
            frames = parse_frames(
                args.calibrate_frames, take.n_frames, option="--calibrate-frames"
            )
            cal = calibrate_from_take(
                take, rig, frames, parse_measures(args.measure),
                allow_moving=args.allow_moving_base_pose,
                method=getattr(args, "method", "fit"),
            )  # fmt: skip
        # Calibrated on the whole take's rows; solved (and checked) on --frames.
        if rows is not None:
            take = take.select_rows(rows)
        args.layout_refined = None
        if getattr(args, "refine_layout", False):
            if getattr(args, "method", "fit") != "fit":
                raise UsageError(
                    "--refine-layout re-places the fit's markers: it does nothing "
                    "for --method construction, which builds its points from the "
                    "markers themselves"
                )
            args.layout_refined = refine_from_take(
                rig, cal, take, slice(0, take.n_frames)
            )
            cal = args.layout_refined.calibration
        solver = solver_of_method(args, rig, cal, take.labels, take.rate_hz)
    except CalibrationError as exc:
        raise UsageError(str(exc)) from None
    args.calibration_match = check_calibration_match(
        take, rig, cal, solver, strict=getattr(args, "strict_calibration", False)
    )
    return rig, take, cal, solver


def refine_from_take(rig: Any, calibration: Any, take: Any, rows: slice) -> Any:
    """Re-place each marker on its bone from ``take.positions[rows]``
    (``body.refine.refine_layout``, with the fit's joint limits as ``solve``'s);
    its one summary line goes to stderr.

    Returns:
        The :class:`~retargetd.daemon.body.refine.RefinedLayout`.
    """
    from retargetd.daemon.body.refine import refine_layout
    from retargetd.daemon.validate.limits import JOINT_LIMITS_DEG
    from retargetd.daemon.validate.model import SEGMENT_KIND

    refined = refine_layout(
        rig, calibration, take.positions[rows], take.labels,
        source={"take": str(take.path), "frames": f"{rows.start}:{rows.stop}"},
        rate_hz=take.rate_hz, joint_limits=JOINT_LIMITS_DEG,
        segment_kind=SEGMENT_KIND,
    )  # fmt: skip
    sys.stderr.write(f"refine-layout: {refined.summary()}\n")
    return refined


def check_calibration_match(
    take: Any, rig: Any, calibration: Any, solver: Any, *, strict: bool
) -> Any:
    """Fit each rigid segment's markers, on every frame of ``take``, to their
    calibrated layout (``body.match``); a segment past its threshold is named in
    one ``warning:`` line on stderr, or with ``strict`` a UsageError (exit 2).

    Returns:
        The :class:`~retargetd.daemon.body.match.CalibrationMatch`.
    """
    from retargetd.daemon.body.match import markers_of_calibration, match_calibration

    found = match_calibration(
        calibration,
        markers_of_calibration(
            calibration, rig.marker_names, solver.marker_cols, take.positions
        ),
    )
    line = found.warning()
    if line is not None:
        if strict:
            raise UsageError(f"{line} (--strict-calibration)")
        sys.stderr.write(f"warning: {line}\n")
    return found


def solver_of_method(
    args: argparse.Namespace,
    rig: Any,
    calibration: Any,
    labels: Any,
    rate_hz: float = 120.0,
) -> Any:
    """The body solver ``--method`` names (default: the fit), with the validator's
    joint limits as the fit's soft penalty: every command solves a take alike.
    ``rate_hz``: the take's frame rate (the fit's continuity prior).

    Raises:
        CalibrationError: a calibration the method cannot use.
    """
    from retargetd.daemon.body.method import make_body_solver
    from retargetd.daemon.validate.limits import JOINT_LIMITS_DEG
    from retargetd.daemon.validate.model import SEGMENT_KIND

    return make_body_solver(
        getattr(args, "method", "fit"), rig, calibration, labels,
        joint_limits=JOINT_LIMITS_DEG, segment_kind=SEGMENT_KIND, rate_hz=rate_hz,
    )  # fmt: skip


def add_force_argument(parser: argparse.ArgumentParser) -> None:
    """``--force``: allow the command to replace an existing output."""
    parser.add_argument(
        "--force", action="store_true", help="replace an existing output"
    )


def refuse_existing(path: str, *, force: bool, option: str = "--out") -> None:
    """Refuse to overwrite ``path`` unless ``force``: nothing is replaced silently.

    A directory output (``validate --report``) counts as existing when it holds
    anything; an empty directory is reused.

    Raises:
        UsageError: one line naming the option, the path and ``--force``.
    """
    from pathlib import Path

    if force:
        return
    p = Path(path)
    if p.is_dir():
        if any(p.iterdir()):
            raise UsageError(
                f"{option}: {path} exists and is not empty; pass --force to replace it"
            )
        return
    if p.exists() or p.is_symlink():
        raise UsageError(f"{option}: {path} exists; pass --force to replace it")


def add_output_arguments(parser: argparse.ArgumentParser, *, json: bool) -> None:
    """``--quiet`` (no progress bar, no summary) and, when ``json``, ``--json`` (the
    summary as one JSON object on stdout; README "Machine-readable output")."""
    parser.add_argument(
        "--quiet",
        action="store_true",
        help="no progress bar on stderr and no summary on stdout (errors still)",
    )
    if json:
        parser.add_argument(
            "--json",
            action="store_true",
            help="print the summary as one JSON object (README: stable keys)",
        )


def print_json(doc: dict[str, Any]) -> None:
    """One JSON object and a newline on stdout (NaN written as null)."""
    import json
    import math
    import sys

    def clean(v: Any) -> Any:
        if isinstance(v, float) and not math.isfinite(v):
            return None
        if isinstance(v, dict):
            return {str(k): clean(x) for k, x in v.items()}
        if isinstance(v, list | tuple):
            return [clean(x) for x in v]
        return v

    sys.stdout.write(json.dumps(clean(doc), allow_nan=False) + "\n")


#: BodySolve / FitSolve fields that hold one value for the take (not per frame).
_PER_TAKE_FIELDS = frozenset({"bone_lengths"})
#: Progress: at most this many chunks per take, each at least this many frames.
_MAX_CHUNKS, _MIN_CHUNK = 100, 32


def solve_take_chunked(
    solver: Any, positions: Any, step: int, on_chunk: Any = None
) -> Any:
    """Solve a take in consecutive chunks of ``step`` frames and join the results.

    The solver carries its state from one ``solve_take`` call to the next (held
    bones, the fit's previous pose), so the joined arrays equal one call's.
    ``on_chunk(n_frames)`` is called after each chunk.
    """
    import dataclasses

    import numpy as np

    n = int(positions.shape[0])
    parts = []
    for a in range(0, n, step):
        parts.append(solver.solve_take(positions[a : a + step]))
        if on_chunk is not None:
            on_chunk(min(step, n - a))
    first = parts[0]
    joined = {}
    for f in dataclasses.fields(first):
        v = getattr(first, f.name)
        if isinstance(v, np.ndarray) and v.ndim and f.name not in _PER_TAKE_FIELDS:
            joined[f.name] = np.concatenate([getattr(p, f.name) for p in parts])
    return dataclasses.replace(first, **joined)


def solve_take_progress(
    solver: Any,
    positions: Any,
    *,
    quiet: bool = False,
    desc: str = "solve",
    causal: bool = False,
) -> Any:
    """``solver.solve_take(positions)`` with a progress bar on a terminal.

    With a bar the take is solved in up to :data:`_MAX_CHUNKS` chunks
    (:func:`solve_take_chunked`: the same arrays as one call); without one
    (``quiet``, stderr not a TTY) it is one call. The fit, unless ``causal``
    (``--causal``), then solves the take backwards (a second bar) and fills each
    hidden marker's span from both sides (``body.fit_gaps``): an offline take is
    known at both ends of a gap.
    """
    import numpy as np

    from retargetd.daemon.body import fit_gaps
    from retargetd.daemon.body.solve_fit import FitSolver
    from retargetd.daemon.progress import Progress

    n = int(positions.shape[0])

    def run(what: str, s: Any, pos: Any) -> Any:
        with Progress(n, what, unit="frames", enabled=False if quiet else None) as bar:
            if not bar.active or n <= _MIN_CHUNK:
                res = s.solve_take(pos)
                bar.update(n)
                return res
            step = max(_MIN_CHUNK, -(-n // _MAX_CHUNKS))
            return solve_take_chunked(s, pos, step, bar.update)

    forward = run(desc, solver, positions)
    if causal or not isinstance(solver, FitSolver):
        return forward
    positions = np.ascontiguousarray(positions, dtype=np.float64)
    backward = fit_gaps.backward_solve(
        solver, positions, lambda s, pos: run(f"{desc} backwards", s, pos)
    )
    return fit_gaps.fill_from_both_sides(solver, positions, forward, backward)
