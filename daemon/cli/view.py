"""``retargetd view TAKE|RECORDING|SOLVE.npz [--report REPORT.json] [--console
HOST:PORT]``: the browser console's page over a recorded sequence, with a timeline to
scrub, play and loop.

``SOLVE.npz`` (``retargetd solve --out``): the solved skeleton (its rig's bones when
the rig is a shipped one or ``--rig`` names it, else the joint centres), flagged bones
red; ``--take`` adds the take's markers. A take (``.c3d``, ``.trc``) or a recording
(``.mcap``) with ``--rig`` and ``--calibration FILE`` or ``--calibrate-frames a:b`` is
solved first, exactly as ``retargetd solve`` does (``--method`` too), and shown with
its markers; without ``--rig`` its markers alone are shown.

``--report`` (``retargetd validate``'s ``report.json``, or its folder): every frame a
check flags is marked on the timeline ("Next flagged" steps through them), and at such
a frame the page names each check with its value (where the report holds one) and
draws the bones the report names in red; without it, the frames where the solve
flagged a bone are marked.

Serves ``--console`` (default 127.0.0.1:8080; port 0 picks a free one), prints the
page's address, and runs until Ctrl-C (SIGINT) or SIGTERM. A host other than loopback
needs ``--allow-remote`` (the page has no login).
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from pathlib import Path
from typing import Any

from retargetd.daemon.cli.args import (
    add_method_argument,
    add_rig_arguments,
    add_take_arguments,
    take_overrides,
)
from retargetd.daemon.cli.launch import parse_console
from retargetd.daemon.errors import UsageError

DEFAULT_CONSOLE = "127.0.0.1:8080"


def add_parser(subparsers: Any) -> None:
    """Register ``view``."""
    parser = subparsers.add_parser(
        "view",
        help="open a take, recording or solve in the browser console (timeline)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("path", metavar="TAKE|RECORDING|SOLVE.npz", help="what to show")
    add_rig_arguments(
        parser, required=False,
        rig_help="solve a take with this rig (shipped name or file)",
    )  # fmt: skip
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--calibration", metavar="FILE.json", help="calibrated skeleton")
    group.add_argument(
        "--calibrate-frames",
        metavar="a:b",
        help="calibrate on these rows of the take itself (0-based, half-open)",
    )
    add_method_argument(parser)
    add_take_arguments(parser)
    parser.add_argument(
        "--take", metavar="TAKE", help="with a SOLVE.npz: the take, to show its markers"
    )
    parser.add_argument(
        "--report",
        metavar="REPORT.json",
        help="validate's report.json (or its folder): mark its flagged frames",
    )
    parser.add_argument(
        "--console",
        metavar="[HOST:]PORT",
        default=DEFAULT_CONSOLE,
        help=f"where to serve the page (default {DEFAULT_CONSOLE}; port 0: any free)",
    )
    parser.add_argument(
        "--allow-remote",
        action="store_true",
        help="serve on a host other than loopback (anyone who reaches it sees it)",
    )
    parser.set_defaults(run=run)


def _read_report(text: str) -> dict[str, Any]:
    p = Path(text)
    if p.is_dir():
        p = p / "report.json"
    try:
        doc = json.loads(p.read_text())
    except (OSError, ValueError) as exc:
        raise UsageError(f"--report: cannot read {p}: {exc}") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("checks"), dict):
        raise UsageError(f"--report: {p} is not a validate report (no 'checks')")
    return doc


def _sequence(args: argparse.Namespace, flagged: list[int] | None) -> Any:
    import numpy as np

    from retargetd.daemon.console.offline import (
        load_sequence,
        sequence_from_solve,
        sequence_from_take,
    )
    from retargetd.replay.takes import load_take

    is_npz = Path(args.path).suffix.lower() == ".npz"
    if is_npz:
        if args.calibration or args.calibrate_frames:
            raise UsageError(
                "--calibration/--calibrate-frames apply to a take, not an NPZ"
            )
        if not Path(args.path).is_file():
            raise UsageError(f"{args.path}: no such file")
        rig = None
        if args.rig:
            from retargetd.daemon.cli.args import load_rig_or_fail

            rig = load_rig_or_fail(args.rig)
        if rig is None:
            return load_sequence(args.path, take=args.take, flagged_frames=flagged)
        with np.load(args.path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        take = None if args.take is None else load_take(args.take)
        return sequence_from_solve(arrays, rig=rig, take=take, flagged_frames=flagged)
    if args.take:
        raise UsageError("--take applies to a SOLVE.npz; give the take as the path")
    if args.rig is None:
        if args.calibration or args.calibrate_frames:
            raise UsageError("--calibration/--calibrate-frames need --rig")
        return sequence_from_take(
            load_take(args.path, **take_overrides(args)), flagged_frames=flagged
        )
    if not (args.calibration or args.calibrate_frames):
        raise UsageError("--rig needs --calibration FILE or --calibrate-frames a:b")
    from retargetd.daemon.cli.args import solver_for_take

    args.take = args.path
    rig, take, _cal, solver = solver_for_take(args)
    from retargetd.daemon.cli.args import solve_take_progress

    res = solve_take_progress(solver, take.positions, causal=args.causal)
    arrays = {
        "joint_names": res.joint_names, "joint_centres": res.joint_centres,
        "bone_names": res.bone_names, "world_from_bone_quat": res.world_from_bone_quat,
        "root_pos": res.root_pos, "bone_flags": res.bone_flags,
        "bone_lengths": res.bone_lengths, "bone_parents": res.bone_parents,
        "rate_hz": take.rate_hz, "rig_name": rig.name,
    }  # fmt: skip
    return sequence_from_solve(arrays, rig=rig, take=take, flagged_frames=flagged)


def run(args: argparse.Namespace) -> int:
    """Run ``view``: serve until SIGINT or SIGTERM."""
    from retargetd.daemon.console.offline import OfflineViewer
    from retargetd.daemon.live.surface import is_loopback_host

    host, port = parse_console(args.console)
    if not is_loopback_host(host) and not args.allow_remote:
        raise UsageError(
            f"--console: {host} is not loopback; pass --allow-remote to serve there"
        )
    from retargetd.daemon.console.offline import (
        flagged_frames_from_report,
        with_report,
    )

    report = _read_report(args.report) if args.report else None
    flagged = None if report is None else flagged_frames_from_report(report)
    seq = _sequence(args, flagged)
    if report is not None:  # each flagged frame's checks, values and bones
        seq = with_report(seq, report)
    viewer = OfflineViewer(seq, host=host, port=port)
    stop = threading.Event()
    previous = signal.signal(signal.SIGTERM, lambda *_: stop.set())
    viewer.start()
    try:
        sys.stdout.write(
            f"view: {viewer.url} ({seq.n_frames} frames at {seq.rate_hz:g} Hz, "
            f"{len(seq.flagged_frames)} flagged; Ctrl-C stops)\n"
        )
        sys.stdout.flush()
        while not stop.wait(0.5):
            pass
    except KeyboardInterrupt:
        pass
    finally:
        viewer.stop()
        signal.signal(signal.SIGTERM, previous)
    return 0
