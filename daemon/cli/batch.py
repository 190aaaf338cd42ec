"""``retargetd batch solve|validate TAKES... --out DIR``: many takes, all cores.

TAKES are files (``.c3d``, ``.trc``, ``.mcap``), folders (searched recursively for
those suffixes) or globs (``'lib/**/*.c3d'``, quoted so the shell leaves them). Each
take is one job: the same ``retargetd solve`` or ``retargetd validate`` command line a
user would type (after ``retargetd calibrate`` for a static trial), run in a worker
process:

* default: a process pool on every core (``--workers N`` to choose);
* ``--scheduler dask``: an embedded Dask ``LocalCluster`` (``--workers`` processes of
  one thread each, on 127.0.0.1);
* ``--scheduler tcp://HOST:PORT``: an existing Dask cluster (its workers must have
  retargetd installed, see the take paths and ``--out`` under the same names, and run
  one thread each, ``dask worker --nthreads 1``: a job redirects its process's stdout
  and stderr into its log);
* ``--scheduler serial``: in this process, one take after the other.

Rig and calibration per take come from ``--rig`` / ``--calibrate-frames`` /
``--calibration`` / ``--static`` (defaults for every take) and a manifest
(``--manifest FILE.toml``)::

    [defaults]                       # every take (overrides the options above)
    rig = "cmu41"
    calibrate_frames = "0:10"        # or calibration = "x.json", or static = "s.c3d"

    [[takes]]                        # rules, in order; each matching rule overrides
    match = "btkdata/PiG_*.c3d"      # glob or folder, relative to the manifest's folder
    rig = "plug-in-gait"
    static = "btkdata/PiG_Calibration-FlatFoot-Full.c3d"
    static_frames = "0:"             # rows of the static (default: all)
    measure = { LKneeWidth = 105.0 } # mm, as --measure
    # also: subject, take_units, take_up, take_rate, body_mass_kg (validate)

Setting one of ``calibration``, ``calibrate_frames``, ``static`` in a rule replaces
the others. Paths in the manifest are relative to its folder; a ``match`` glob is
matched (``fnmatch``: its ``*`` also crosses ``/``) against the take's path relative
to that folder, a ``match`` without wildcards names a folder (every take under it) or
one take.

Output, per take ``DIR/<take id>/`` (the take's path relative to the manifest folder,
else to the takes' common folder, ``/`` written ``__``): ``solve.npz`` (solve) or the
``validate`` report files, ``calibration.json`` (static trials), ``log.txt`` (the
commands run and their output) and ``result.json`` (status, timings, the checks). A
job writes into a fresh hidden folder beside it that replaces ``DIR/<take id>/`` only
when complete. A take whose ``result.json`` says it ran to the end (``ok`` or
``fail``) with the same job (take file size and mtime, rig, calibration rule, options)
is skipped unless ``--force``; an ``error`` is retried. One take's error is reported
and the rest go on. Summary: ``DIR/summary.json``, ``DIR/summary.txt`` (a table),
``DIR/summary.png``.

Exit code: 0 every take ok, 1 a take failed a check or errored, 2 bad usage.

``validate`` renders its worst-frame snapshots only with ``--snapshots`` (at library
scale they dominate: ~0.8 s start plus ~0.2 s a frame in a GL subprocess); without,
each take runs ``retargetd validate --no-snapshots``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any


def add_parser(subparsers: Any) -> None:
    """Register ``batch``."""
    from retargetd.daemon.cli.batch_jobs import MODES

    parser = subparsers.add_parser(
        "batch",
        help="solve or validate many takes on all cores or a Dask cluster",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("mode", choices=MODES, help="what to run on every take")
    parser.add_argument(
        "takes", nargs="+", metavar="TAKES", help="files, folders, globs"
    )
    parser.add_argument(
        "--out", required=True, metavar="DIR",
        help="folder for the outputs (one set per take) and the summary",
    )  # fmt: skip
    parser.add_argument("--manifest", metavar="FILE.toml", help="per-take rules")
    parser.add_argument("--rig", metavar="RIG", help="default rig for every take")
    group = parser.add_mutually_exclusive_group()
    group.add_argument(
        "--calibration", metavar="FILE.json", help="one calibration for every take"
    )
    group.add_argument(
        "--calibrate-frames", metavar="a:b",
        help="calibrate each take on these rows of itself (0-based, half-open)",
    )  # fmt: skip
    group.add_argument("--static", metavar="TAKE", help="static trial to calibrate on")
    parser.add_argument(
        "--scheduler",
        metavar="WHERE",
        help="processes (default), serial, dask (embedded local cluster) or "
        "tcp://HOST:PORT (a Dask scheduler)",
    )
    parser.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="pool or local-cluster size (all cores)",
    )
    parser.add_argument("--force", action="store_true", help="rerun takes already done")
    parser.add_argument(
        "--snapshots", action="store_true", help="validate: render worst frames"
    )
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Run ``batch``; a bad manifest or take list raises UsageError (exit 2)."""
    from retargetd.daemon.cli import batch_jobs as bj

    cwd = Path.cwd()
    cli = {
        "rig": args.rig,
        "calibration": args.calibration,
        "calibrate_frames": args.calibrate_frames,
        "static": args.static,
    }
    defaults = bj.check_settings(
        {k: v for k, v in cli.items() if v is not None}, "options", cwd
    )
    rules: list[bj.Rule] = []
    base = None
    if args.manifest:
        m_defaults, rules = bj.load_manifest(args.manifest)
        if any(k in m_defaults for k in bj.CAL_KEYS):
            for k in bj.CAL_KEYS:
                defaults.pop(k, None)
        defaults.update(m_defaults)
        base = bj.abs_path(args.manifest).parent
    if args.workers is not None and args.workers < 1:
        raise bj.BatchError(f"--workers: expected >= 1; got {args.workers}")
    takes = bj.expand_takes(args.takes)
    jobs = bj.make_jobs(
        args.mode, takes, args.out, defaults, rules,
        base=base, snapshots=args.snapshots,
    )  # fmt: skip
    summary = run_batch(
        jobs,
        scheduler=args.scheduler,
        workers=args.workers,
        force=args.force,
        progress=sys.stderr,
    )
    write_summary(summary, args.out)
    sys.stdout.write(summary_text(summary))
    t = summary["totals"]
    return 0 if t["fail"] == 0 and t["error"] == 0 else 1


class _Progress:
    """A one-line progress bar on a terminal, one line per take otherwise."""

    def __init__(self, total: int, stream: Any) -> None:
        self.total, self.done, self.stream = total, 0, stream
        self.tty = bool(getattr(stream, "isatty", lambda: False)())

    def step(self, res: dict[str, Any]) -> None:
        self.done += 1
        mark = "skipped" if res.get("skipped") else res["status"]
        if self.tty:
            n = 30 * self.done // max(self.total, 1)
            self.stream.write(
                f"\r[{'#' * n}{'.' * (30 - n)}] {self.done}/{self.total} "
                f"{mark:7s} {res['id'][:40]:40s}"
            )
            if self.done == self.total:
                self.stream.write("\n")
        else:
            self.stream.write(
                f"[{self.done}/{self.total}] {mark:7s} {res['id']} "
                f"{res.get('seconds', 0.0):.2f} s\n"
            )
        self.stream.flush()


def run_batch(
    jobs: list[dict[str, Any]],
    *,
    scheduler: str | None = None,
    workers: int | None = None,
    force: bool = False,
    progress: Any = None,
) -> dict[str, Any]:
    """Run the jobs; returns the summary (not written: see :func:`write_summary`).

    Args:
        jobs: from ``batch_jobs.make_jobs``.
        scheduler: None or ``"processes"`` (a process pool), ``"serial"``,
            ``"dask"`` (an embedded local Dask cluster on 127.0.0.1) or a Dask
            scheduler address ``"tcp://HOST:PORT"``.
        workers: pool / local cluster size (default: every core).
        force: rerun takes already done.
        progress: a text stream for progress (None: silent).

    Raises:
        UsageError: an unknown scheduler.
    """
    from retargetd.daemon.cli import batch_jobs as bj

    scheduler = bj.check_scheduler(scheduler or "processes")
    n_workers = workers or os.cpu_count() or 1
    results: dict[str, dict[str, Any]] = {}
    todo = []
    bar = _Progress(len(jobs), progress) if progress is not None else None
    for job in jobs:
        prev = None if force else bj.previous_result(job)
        if prev is not None:
            results[job["id"]] = {**prev, "skipped": True}
            if bar:
                bar.step(results[job["id"]])
        else:
            todo.append(job)

    def collect(job: dict[str, Any], get: Callable[[], dict[str, Any]]) -> None:
        try:
            res = {**get(), "skipped": False}
        except Exception as exc:  # the worker died (killed, out of memory)
            res = {**bj.crashed(job, exc), "skipped": False}
        results[job["id"]] = res
        if bar:
            bar.step(res)

    t0 = time.perf_counter()
    if todo:
        n_workers = bj.schedule(todo, scheduler, n_workers, collect)
    wall = time.perf_counter() - t0
    ordered = [results[j["id"]] for j in jobs]
    ran = [r for r in ordered if not r["skipped"]]
    frames = sum(int(r["checks"].get("frames", 0)) for r in ran)
    counts = {
        s: sum(r["status"] == s for r in ordered) for s in ("ok", "fail", "error")
    }
    fps = frames / wall if ran and wall > 0 else None
    return {
        "mode": jobs[0]["mode"] if jobs else None,
        "scheduler": scheduler,
        "workers": n_workers,
        "wall_seconds": wall,
        "takes": ordered,
        "totals": {
            "takes": len(ordered),
            "ran": len(ran),
            "skipped": len(ordered) - len(ran),
            **counts,
            "frames_ran": frames,
            "frames_per_second": fps,
            "frames_per_second_per_worker": fps / n_workers if fps else None,
        },
    }


def summary_text(summary: dict[str, Any]) -> str:
    """The summary as a readable table."""
    t = summary["totals"]
    lines = [
        f"retargetd batch {summary['mode']}: {t['takes']} takes ({t['ran']} ran, "
        f"{t['skipped']} skipped as done), {t['ok']} ok, {t['fail']} failed a check, "
        f"{t['error']} errors; scheduler {summary['scheduler']}, "
        f"{summary['workers']} workers, {summary['wall_seconds']:.2f} s wall",
    ]
    if t["frames_per_second"]:
        lines.append(
            f"frames solved: {t['frames_ran']}, {t['frames_per_second']:.1f} frames/s, "
            f"{t['frames_per_second_per_worker']:.1f} frames/s per worker"
        )
    lines.append("")
    lines.append(
        f"{'take':48s} {'status':7s} {'frames':>7s} {'s':>8s} {'frames/s':>9s}  checks"
    )
    for r in summary["takes"]:
        c = r["checks"]
        fr = int(c.get("frames", 0))
        fps = fr / r["seconds"] if r["seconds"] and fr else 0.0
        if r["error"]:
            note = r["error"]
        elif "flagged" in c:
            note = "PASS" if c["passed"] else "FAIL " + ", ".join(c["failed"])
        else:
            note = f"bones held {100 * c.get('held_fraction', 0.0):.1f} % of samples"
        status = r["status"] + ("*" if r["skipped"] else "")
        lines.append(
            f"{r['id'][:48]:48s} {status:7s} {fr:7d} {r['seconds']:8.2f} "
            f"{fps:9.1f}  {note}"
        )
    lines.append("(* done in an earlier run, skipped; seconds from that run)")
    return "\n".join(lines) + "\n"


def plot_summary(summary: dict[str, Any], path: Path) -> None:
    """Frames/s per take (bars coloured by status) and, for validate, the fraction
    of frames each check flagged."""
    import numpy as np
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    takes = summary["takes"]
    checks = sorted({n for r in takes for n in r["checks"].get("flagged", {})})
    fig = Figure(figsize=(10, (2.0 + 0.35 * len(takes)) * (2 if checks else 1)))
    FigureCanvasAgg(fig)
    axes = fig.subplots(2 if checks else 1, 1, squeeze=False)[:, 0]
    colour = {"ok": "tab:green", "fail": "tab:orange", "error": "tab:red"}
    names = [r["id"] for r in takes]
    fps = [
        r["checks"].get("frames", 0) / r["seconds"] if r["seconds"] else 0.0
        for r in takes
    ]
    ax = axes[0]
    ax.barh(names, fps, color=[colour[r["status"]] for r in takes])
    for i, r in enumerate(takes):
        if r["status"] == "error":
            ax.text(0.0, i, " error", color=colour["error"], va="center")
    ax.invert_yaxis()
    ax.set_xlabel("frames per second in one worker (green ok, orange fail, red error)")
    ax.set_title(
        f"retargetd batch {summary['mode']}: {len(takes)} takes, "
        f"{summary['workers']} workers ({summary['scheduler']})"
    )
    if checks:
        grid = np.array(
            [
                [
                    r["checks"].get("flagged", {}).get(n, 0)
                    / max(r["checks"].get("frames", 1), 1)
                    for n in checks
                ]
                for r in takes
            ]
        )
        im = axes[1].imshow(grid, aspect="auto", cmap="Reds", vmin=0.0, vmax=1.0)
        axes[1].set_yticks(range(len(names)), names)
        axes[1].set_xticks(range(len(checks)), checks, rotation=30, ha="right")
        fig.colorbar(im, ax=axes[1], label="fraction of frames flagged")
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def write_summary(summary: dict[str, Any], out_dir: str | Path) -> None:
    """``summary.json``, ``summary.txt`` and ``summary.png`` into ``out_dir``."""
    import json

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    (out_dir / "summary.txt").write_text(summary_text(summary))
    plot_summary(summary, out_dir / "summary.png")
