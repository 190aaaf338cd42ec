"""The engine of ``retargetd batch``: manifest rules, the take list, one job per take,
running a job (the take's own ``retargetd`` command line in a worker) and the pool,
Dask or serial scheduling. Not a command: ``cli/batch.py`` is.

A job runs exactly what a user's shell would run for that take
(``retargetd [calibrate ...;] solve|validate ...``) through the CLI entry point
:func:`retargetd.daemon.cli.main.main`, so a job never imports another command's
module. Each job writes into a fresh temporary folder beside ``--out DIR/<take id>``
and replaces that folder only when it is complete: no command ever sees an earlier
run's outputs (whatever its overwrite policy), and an interrupted run leaves the
previous result whole.
"""

from __future__ import annotations

import contextlib
import fnmatch
import functools
import glob
import hashlib
import io
import json
import logging
import os
import shlex
import shutil
import tempfile
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

from retargetd.daemon.errors import UsageError

MODES = ("solve", "validate")
TAKE_SUFFIXES = (".c3d", ".trc", ".mcap")
#: Keys a rule may set (manifest ``[defaults]`` and ``[[takes]]``).
RULE_KEYS = (
    "rig",
    "calibration",
    "calibrate_frames",
    "static",
    "static_frames",
    "measure",
    "subject",
    "take_units",
    "take_up",
    "take_rate",
    "body_mass_kg",
)
#: Mutually exclusive ways of getting the calibration.
CAL_KEYS = ("calibration", "calibrate_frames", "static")
#: Keys holding a path (resolved against the manifest's folder).
PATH_KEYS = ("calibration", "static")
#: Keys holding a positive number.
NUMBER_KEYS = ("body_mass_kg", "take_rate")
RESULT_NAME = "result.json"
LOG_NAME = "log.txt"
#: ``retargetd``'s exit code after Ctrl-C (``cli.main``: 128 + SIGINT).
EXIT_INTERRUPTED = 130
#: Statuses that mean "ran to the end" (skipped on resume).
DONE = ("ok", "fail")


class BatchError(UsageError):
    """A bad manifest, take list or option (one line, exit 2)."""


@dataclass(frozen=True, slots=True)
class Rule:
    """One manifest rule: a glob or folder (relative to ``base``) and its settings."""

    match: str
    settings: dict[str, Any]
    base: Path = field(default_factory=Path.cwd)

    def matches(self, take: Path) -> bool:
        """Whether ``take`` (an absolute path) falls under this rule: as named, else
        with the folders on both sides resolved (a take named through a symlinked
        folder, e.g. ``../shared``, matches a rule written through the other name)."""
        base = abs_path(self.base)
        return self._matches(take, base, abs_path(base / self.match)) or self._matches(
            _real(take), _real(base), _real(base / self.match)
        )

    def _matches(self, take: Path, base: Path, target: Path) -> bool:
        if not any(c in self.match for c in "*?["):
            return take == target or target in take.parents
        try:
            rel = take.relative_to(base).as_posix()
        except ValueError:
            return fnmatch.fnmatchcase(take.as_posix(), target.as_posix())
        return fnmatch.fnmatchcase(rel, self.match)


def _real(path: Path) -> Path:
    """``path`` with its folders' symlinks resolved (not its last part: a take that
    is a link keeps its own name)."""
    return Path(os.path.realpath(abs_path(path).parent)) / abs_path(path).name


def abs_path(path: str | Path) -> Path:
    """Absolute and normalised, symlinks kept (a take's id is its path as named)."""
    return Path(os.path.abspath(path))


def check_settings(settings: dict[str, Any], where: str, base: Path) -> dict[str, Any]:
    """Validate one rule's settings; paths resolved against ``base``.

    Raises:
        BatchError: naming ``where`` and the key.
    """
    out: dict[str, Any] = {}
    for key, value in settings.items():
        if key not in RULE_KEYS:
            raise BatchError(f"{where}: unknown key {key!r} (one of {RULE_KEYS})")
        if key == "measure":
            if not isinstance(value, dict) or not all(
                isinstance(v, int | float) for v in value.values()
            ):
                raise BatchError(f"{where}.measure: expected a table NAME = mm")
            value = {str(k): float(v) for k, v in value.items()}
        elif key in NUMBER_KEYS:
            if not isinstance(value, int | float) or not value > 0:
                raise BatchError(f"{where}.{key}: expected > 0; got {value!r}")
            value = float(value)
        elif not isinstance(value, str):
            raise BatchError(f"{where}.{key}: expected a string; got {value!r}")
        elif key in PATH_KEYS or (key == "rig" and value.endswith(".toml")):
            value = str(abs_path(base / value))
        out[key] = value
    if sum(k in out for k in CAL_KEYS) > 1:
        raise BatchError(f"{where}: at most one of {', '.join(CAL_KEYS)}")
    return out


def load_manifest(path: str | Path) -> tuple[dict[str, Any], list[Rule]]:
    """Read a batch manifest.

    Returns:
        ``(defaults, rules)``; paths resolved against the manifest's folder.

    Raises:
        BatchError: naming the file and key.
    """
    path = Path(path)
    from retargetd.daemon.files import FileFormatError, loads_toml, read_text

    try:
        doc = loads_toml(read_text(path, "batch manifest"))
    except FileFormatError as exc:
        raise BatchError(f"{path}: {exc}") from None
    base = abs_path(path).parent
    unknown = set(doc) - {"defaults", "takes"}
    if unknown:
        raise BatchError(f"{path.name}: unknown section(s) {sorted(unknown)}")
    defaults = check_settings(doc.get("defaults", {}), f"{path.name}: defaults", base)
    rules = []
    for i, entry in enumerate(doc.get("takes", [])):
        where = f"{path.name}: takes[{i}]"
        entry = dict(entry)
        match = entry.pop("match", None)
        if not isinstance(match, str) or not match:
            raise BatchError(f"{where}.match: expected a glob or folder")
        rules.append(Rule(match, check_settings(entry, where, base), base))
    return defaults, rules


def expand_takes(items: Sequence[str]) -> list[Path]:
    """Files, folders (searched recursively) and globs (matching takes or folders)
    -> sorted unique absolute take paths. A file named outright is taken whatever
    its suffix; folders and globs yield ``TAKE_SUFFIXES`` files only.

    Raises:
        BatchError: an item that names nothing.
    """
    found: list[Path] = []
    for item in items:
        explicit = Path(item).exists()
        named = [Path(item)] if explicit else []
        named = named or [Path(p) for p in sorted(glob.glob(item, recursive=True))]
        hits: list[Path] = []
        for path in named:
            if path.is_dir():
                hits.extend(
                    p
                    for p in sorted(path.rglob("*"))
                    if p.suffix.lower() in TAKE_SUFFIXES and p.is_file()
                )
            elif path.is_file() and (explicit or path.suffix.lower() in TAKE_SUFFIXES):
                hits.append(path)
        if not hits:
            raise BatchError(f"TAKES: {item!r} names no take")
        found.extend(abs_path(p) for p in hits)
    return sorted(dict.fromkeys(found))


def settings_for(
    take: Path, defaults: dict[str, Any], rules: Sequence[Rule]
) -> dict[str, Any]:
    """The settings of one take: ``defaults`` then every matching rule in order (a
    rule naming a calibration replaces the others)."""
    out = dict(defaults)
    for rule in rules:
        if rule.matches(take):
            if any(k in rule.settings for k in CAL_KEYS):
                for k in (*CAL_KEYS, "static_frames"):
                    out.pop(k, None)
            out.update(rule.settings)
    return out


def _take_ids(takes: Sequence[Path], base: Path | None) -> list[str]:
    if not takes:
        return []
    root = base
    if root is None or not all(root in t.parents for t in takes):
        root = Path(os.path.commonpath([t.parent for t in takes]))
    return [t.relative_to(root).as_posix().replace("/", "__") for t in takes]


def make_jobs(
    mode: str,
    takes: Sequence[Path],
    out_dir: str | Path,
    defaults: dict[str, Any],
    rules: Sequence[Rule] = (),
    *,
    base: Path | None = None,
    snapshots: bool = False,
) -> list[dict[str, Any]]:
    """One JSON-ready job per take (a worker needs nothing else).

    Raises:
        BatchError: a take without a rig or a calibration rule.
    """
    if mode not in MODES:
        raise BatchError(f"mode: expected one of {MODES}; got {mode!r}")
    out_dir = abs_path(out_dir)
    jobs = []
    for take, take_id in zip(takes, _take_ids(takes, base), strict=True):
        s = settings_for(take, defaults, rules)
        if "rig" not in s:
            raise BatchError(f"{take}: no rig (--rig or a manifest rule)")
        if not any(k in s for k in CAL_KEYS):
            raise BatchError(
                f"{take}: no calibration rule (--calibration, --calibrate-frames, "
                "--static or a manifest rule)"
            )
        stat = take.stat()
        job = {
            "id": take_id,
            "mode": mode,
            "take": str(take),
            "take_size": stat.st_size,
            "take_mtime_ns": stat.st_mtime_ns,
            "snapshots": bool(snapshots) if mode == "validate" else False,
            **{k: s[k] for k in RULE_KEYS if k in s},
        }
        job["fingerprint"] = hashlib.sha256(
            json.dumps(job, sort_keys=True).encode()
        ).hexdigest()[:16]
        job["out_dir"] = str(out_dir / take_id)
        jobs.append(job)
    return jobs


def _common_argv(job: dict[str, Any]) -> list[str]:
    """``--rig``, ``--measure`` and the take options (``--opt=value``: a value may
    start with ``-``)."""
    argv = [f"--rig={job['rig']}"]
    argv += [f"--measure={k}={v:g}" for k, v in job.get("measure", {}).items()]
    for key, option in (
        ("subject", "--subject"),
        ("take_units", "--take-units"),
        ("take_up", "--take-up"),
        ("take_rate", "--take-rate"),
    ):
        if key in job:
            argv.append(f"{option}={job[key]}")
    return argv


def job_commands(job: dict[str, Any], work: Path, scratch: Path) -> list[list[str]]:
    """The ``retargetd`` command lines of one job, in order.

    Args:
        job: from :func:`make_jobs`.
        work: the take's output folder (does not exist yet for ``validate``).
        scratch: an existing folder for the static trial's calibration.
    """
    common = _common_argv(job)
    cmds = []
    calibration = job.get("calibration")
    if "static" in job:
        calibration = str(scratch / "calibration.json")
        cmd = ["calibrate", job["static"], *common, f"--out={calibration}"]
        if "static_frames" in job:
            cmd.append(f"--frames={job['static_frames']}")
        cmds.append(cmd)
    cal = (
        [f"--calibration={calibration}"]
        if calibration
        else [f"--calibrate-frames={job['calibrate_frames']}"]
    )
    cmd = [job["mode"], job["take"], *common, *cal]
    if job["mode"] == "solve":
        cmd.append(f"--out={work / 'solve.npz'}")
    else:
        cmd.append(f"--report={work}")
        if not job["snapshots"]:
            cmd.append("--no-snapshots")
        if "body_mass_kg" in job:
            cmd.append(f"--body-mass-kg={job['body_mass_kg']}")
    cmds.append(cmd)
    return cmds


def _retargetd(argv: list[str], log: TextIO) -> tuple[int, str | None]:
    """Run one ``retargetd`` command line in this process, its stdout, stderr and
    logging into ``log``; (exit code, the command's own error line or None)."""
    from retargetd.daemon.cli.main import main

    err = io.StringIO()
    handler = logging.StreamHandler(log)
    root = logging.getLogger()
    root.addHandler(handler)  # main()'s basicConfig is then a no-op: no stale stream
    log.write("$ retargetd " + shlex.join(argv) + "\n")
    log.flush()
    try:
        with contextlib.redirect_stdout(log), contextlib.redirect_stderr(err):
            try:
                code = int(main(argv))
            except SystemExit as exc:  # argparse: bad usage
                code = exc.code if isinstance(exc.code, int) else 2
    finally:
        root.removeHandler(handler)
        log.write(err.getvalue())
    lines = [ln for ln in err.getvalue().splitlines() if " error: " in ln]
    return code, (lines[-1].strip() if lines else None)


def _solve_checks(npz_path: Path) -> dict[str, Any]:
    import numpy as np

    from retargetd.daemon.body.solve import FLAG_HELD

    with np.load(npz_path, allow_pickle=False) as npz:
        held = (npz["bone_flags"] & FLAG_HELD) != 0
        keys = ("joint_centres", "parent_from_bone_quat", "rest_from_bone_quat")
        return {
            "frames": int(held.shape[0]),
            "rate_hz": float(npz["rate_hz"]),
            "bones": int(held.shape[1]),
            "held_fraction": float(held.mean()) if held.size else 0.0,
            "digest": hashlib.sha256(
                b"".join(
                    np.ascontiguousarray(npz[k]).tobytes() for k in (*keys, "root_pos")
                )
            ).hexdigest()[:16],
        }


def _validate_checks(report: Path) -> tuple[dict[str, Any], float]:
    doc = json.loads(report.read_text())
    render = doc.get("visuals", {}).get("render", {})
    checks = {
        "frames": int(doc["frames"]),
        "rate_hz": float(doc["rate_hz"]),
        "passed": bool(doc["passed"]),
        "failed": list(doc["failed"]),
        "flagged": {n: int(c["frames_flagged"]) for n, c in doc["checks"].items()},
        "max": {n: float(c["max"]) for n, c in doc["checks"].items()},
    }
    return checks, float(render.get("seconds_total") or 0.0)


def _job_body(
    job: dict[str, Any], work: Path, scratch: Path, log: TextIO
) -> tuple[int, str | None, dict[str, Any], float]:
    """(exit code, error, the checks, seconds rendering) of one job's commands."""
    if job["mode"] == "solve":
        work.mkdir()
    for argv in job_commands(job, work, scratch):
        code, error = _retargetd(argv, log)
        if code == EXIT_INTERRUPTED:  # Ctrl-C in a serial run: stop the batch
            raise KeyboardInterrupt
        if code not in (0, 1) or (argv[0] == "calibrate" and code != 0):
            return code, error or f"retargetd {argv[0]}: exit code {code}", {}, 0.0
    if job["mode"] == "solve":
        return code, None, _solve_checks(work / "solve.npz"), 0.0
    checks, render_s = _validate_checks(work / "report.json")
    return code, None, checks, render_s


def run_job(job: dict[str, Any]) -> dict[str, Any]:
    """Run one take (in a worker): never raises; writes and returns its result.

    The outputs go to a fresh folder beside ``job["out_dir"]`` that replaces it
    once ``result.json`` is written.

    Returns:
        ``{"id", "take", "mode", "fingerprint", "status": "ok"|"fail"|"error",
        "exit_code", "error", "checks", "seconds", "cpu_seconds",
        "render_seconds", "worker"}``; ``seconds`` is the job's wall time in the
        worker, ``render_seconds`` the part of it spent rendering snapshots.
    """
    final = Path(job["out_dir"])
    final.parent.mkdir(parents=True, exist_ok=True)
    scratch = Path(tempfile.mkdtemp(prefix=f".{final.name}.", dir=final.parent))
    work = scratch / "out"
    t0, c0 = time.perf_counter(), time.process_time()
    checks: dict[str, Any] = {}
    render_s = 0.0
    with (scratch / LOG_NAME).open("w") as log:
        try:
            code, error, checks, render_s = _job_body(job, work, scratch, log)
        except Exception as exc:  # a bug in one take must not stop the library
            code, error = 3, f"{type(exc).__name__}: {exc}"
            log.write(traceback.format_exc())
        except BaseException:  # interrupted: no half-made folder left behind
            shutil.rmtree(scratch, ignore_errors=True)
            raise
    result = {
        "id": job["id"],
        "take": job["take"],
        "mode": job["mode"],
        "fingerprint": job["fingerprint"],
        "status": "ok" if code == 0 else "fail" if code == 1 else "error",
        "exit_code": code,
        "error": error,
        "checks": checks,
        "seconds": time.perf_counter() - t0,
        "cpu_seconds": time.process_time() - c0,
        "render_seconds": render_s,
        "worker": f"{os.uname().nodename}:{os.getpid()}",
    }
    work.mkdir(exist_ok=True)
    for name in (LOG_NAME, "calibration.json"):
        if (scratch / name).exists():
            (scratch / name).replace(work / name)
    (work / RESULT_NAME).write_text(json.dumps(result, indent=1) + "\n")
    if final.exists():
        final.replace(scratch / "previous")
    work.replace(final)
    shutil.rmtree(scratch, ignore_errors=True)
    return result


def previous_result(job: dict[str, Any]) -> dict[str, Any] | None:
    """The result of an earlier run of the same job that ran to the end, or None."""
    path = Path(job["out_dir"]) / RESULT_NAME
    try:
        res = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if res.get("fingerprint") == job["fingerprint"] and res.get("status") in DONE:
        return dict(res)
    return None


def crashed(job: dict[str, Any], exc: BaseException) -> dict[str, Any]:
    """The result of a job whose worker died (killed, out of memory)."""
    return {
        "id": job["id"],
        "take": job["take"],
        "mode": job["mode"],
        "fingerprint": job["fingerprint"],
        "status": "error",
        "exit_code": 3,
        "error": f"worker lost: {type(exc).__name__}: {exc}",
        "checks": {},
        "seconds": 0.0,
        "cpu_seconds": 0.0,
        "render_seconds": 0.0,
        "worker": None,
    }


Collect = Callable[[dict[str, Any], Callable[[], dict[str, Any]]], None]


def check_scheduler(scheduler: str) -> str:
    """``scheduler`` if it is one :func:`schedule` knows.

    Raises:
        BatchError: naming the option.
    """
    if scheduler in ("serial", "processes", "dask") or scheduler.startswith(
        ("tcp://", "tls://")
    ):
        return scheduler
    raise BatchError(
        f"--scheduler: expected processes, serial, dask or tcp://HOST:PORT; "
        f"got {scheduler!r}"
    )


def schedule(
    todo: Sequence[dict[str, Any]], scheduler: str, n_workers: int, collect: Collect
) -> int:
    """Run ``todo`` on ``scheduler``; ``collect(job, get_result)`` as each ends.

    Returns:
        The number of workers used.

    Raises:
        BatchError: an unknown scheduler.
    """
    check_scheduler(scheduler)
    if scheduler == "serial":
        for job in todo:
            collect(job, functools.partial(run_job, job))
        return 1
    if scheduler == "processes":
        # Imported here: ``retargetd --help`` registers this command's parser.
        from concurrent.futures import Future, ProcessPoolExecutor
        from concurrent.futures import as_completed as futures_as_completed
        from multiprocessing import get_context

        ctx = get_context("spawn")  # no fork of a process holding threads
        with ProcessPoolExecutor(min(n_workers, len(todo)), mp_context=ctx) as pool:
            futs: dict[Future[dict[str, Any]], dict[str, Any]] = {
                pool.submit(run_job, job): job for job in todo
            }
            for fut in futures_as_completed(futs):
                collect(futs[fut], fut.result)
        return n_workers
    return _run_dask(todo, scheduler, n_workers, collect)


def _run_dask(
    todo: Sequence[dict[str, Any]], scheduler: str, n_workers: int, collect: Collect
) -> int:
    from distributed import Client, LocalCluster, as_completed

    with contextlib.ExitStack() as stack:
        if scheduler == "dask":
            cluster = stack.enter_context(
                LocalCluster(
                    n_workers=n_workers,
                    threads_per_worker=1,  # one job per process (stdout redirected)
                    processes=True,
                    host="127.0.0.1",
                    dashboard_address="127.0.0.1:0",  # a free loopback port, not 8787
                )
            )
            client = stack.enter_context(Client(cluster))
        else:
            client = stack.enter_context(Client(scheduler))
        n_workers = len(client.scheduler_info().get("workers", {})) or n_workers
        futs = {
            client.submit(
                run_job, job, key=f"retargetd-batch-{job['fingerprint']}", pure=False
            ): job
            for job in todo
        }
        for fut in as_completed(list(futs)):
            collect(futs[fut], fut.result)
            fut.release()
    return n_workers
