"""``retargetd batch``: a small library of real takes (the PiG walk with its static
trial, the MOTEK ballet calibrated on MOTEK_T, the tennis serve on its first 50 rows)
plus a deliberately corrupt take, run serially, on a process pool and on a local Dask
cluster of two worker processes over 127.0.0.1: the same results, the broken take
reported while the rest go on, done takes skipped on a second run. Every job runs its
take's own ``retargetd`` command lines (``cli/batch_jobs.py``).
"""

from __future__ import annotations

import json
import os
import re
import shlex
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from paths import require_datasets

from retargetd.daemon.cli import batch
from retargetd.daemon.cli import batch_jobs as bj
from retargetd.daemon.cli.main import main
from retargetd.daemon.validate.render import SNAPSHOTS_OFF

pytestmark = pytest.mark.usefixtures("mujoco_cwd")

MANIFEST = """
[defaults]
rig = "cmu41"
calibrate_frames = "0:10"

[[takes]]
match = "btkdata"
static = "btkdata/MOTEK_T.trc"

[[takes]]
match = "btkdata/PiG_*.c3d"
rig = "plug-in-gait"
static = "btkdata/PiG_Calibration-FlatFoot-Full.c3d"

[[takes]]
match = "kineticstoolkit/*.c3d"
calibrate_frames = "0:50"
"""
#: The tennis serve calibrates on its first 50 rows (as in test_validate_takes).
TAKES = (
    "btkdata/PiG_Motion-FlatFoot-Full.c3d",
    "btkdata/MOTEK_ballet_reduced.trc",
    "kineticstoolkit/kinematics_tennis_serve.c3d",
)
BROKEN = "broken/corrupt.trc"
#: Result fields that are timings or process identities, not results.
VOLATILE = ("seconds", "cpu_seconds", "render_seconds", "worker", "skipped")


@pytest.fixture(scope="module")
def library(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``tmp/lib``: links to the takes, a corrupt TRC and the manifest (one for the
    module: no test writes into it)."""
    datasets = require_datasets()
    lib = tmp_path_factory.mktemp("batch") / "lib"
    for rel in (*TAKES, "btkdata/PiG_Calibration-FlatFoot-Full.c3d",
                "btkdata/MOTEK_T.trc"):  # fmt: skip
        (lib / rel).parent.mkdir(parents=True, exist_ok=True)
        (lib / rel).symlink_to(datasets / rel)
    (lib / BROKEN).parent.mkdir()
    # The ballet's TRC header, then a row that is not numbers. (Not a truncated C3D:
    # ezc3d allocates ~12 GB reading the first 3000 bytes of the PiG walk, and Dask's
    # nanny kills the worker: reported as "worker lost", but the machine is shared.)
    header = (datasets / TAKES[1]).read_text().splitlines()[:5]
    (lib / BROKEN).write_text("\n".join([*header, "1\t0.0\tnot\ta\tnumber"]) + "\n")
    (lib / "batch.toml").write_text(MANIFEST)
    return lib


@pytest.fixture(scope="module")
def serial_solve(
    library: Path, tmp_path_factory: pytest.TempPathFactory
) -> tuple[dict[str, Any], Path]:
    """The library solved serially, once for the module (the summary and its
    folder): what the Dask cluster's and the process pool's solves must equal."""
    out = tmp_path_factory.mktemp("serial") / "solve-serial"
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(out.parent)  # MuJoCo's log, as mujoco_cwd
        summary = batch.run_batch(_jobs(library, "solve", out), scheduler="serial")
    return summary, out


def _jobs(lib: Path, mode: str, out: Path, **kw: Any) -> list[dict[str, Any]]:
    defaults, rules = bj.load_manifest(lib / "batch.toml")
    paths = [lib / t for t in (*TAKES, BROKEN)]
    return bj.make_jobs(mode, paths, out, defaults, rules, base=lib, **kw)


def _stable(summary: dict[str, Any]) -> list[dict[str, Any]]:
    return [{k: v for k, v in r.items() if k not in VOLATILE} for r in summary["takes"]]


def _check_statuses(summary: dict[str, Any]) -> None:
    by_id = {r["id"]: r for r in summary["takes"]}
    broken = by_id[BROKEN.replace("/", "__")]
    assert broken["status"] == "error"
    assert "corrupt.trc" in broken["error"]
    for take in TAKES:
        res = by_id[take.replace("/", "__")]
        assert res["status"] in ("ok", "fail"), res
        assert res["checks"]["frames"] > 0


def test_manifest_rules(library: Path, tmp_path: Path) -> None:
    jobs = {j["id"]: j for j in _jobs(library, "solve", tmp_path / "out")}
    pig = jobs["btkdata__PiG_Motion-FlatFoot-Full.c3d"]
    assert pig["rig"] == "plug-in-gait"
    assert pig["static"].endswith("PiG_Calibration-FlatFoot-Full.c3d")
    ballet = jobs["btkdata__MOTEK_ballet_reduced.trc"]
    assert ballet["rig"] == "cmu41" and ballet["static"].endswith("MOTEK_T.trc")
    tennis = jobs["kineticstoolkit__kinematics_tennis_serve.c3d"]
    assert tennis["calibrate_frames"] == "0:50" and "static" not in tennis
    broken = jobs["broken__corrupt.trc"]
    assert broken["calibrate_frames"] == "0:10" and broken["rig"] == "cmu41"
    assert len({j["fingerprint"] for j in jobs.values()}) == len(jobs)
    # The same take named through a symlinked folder still matches the rules.
    (tmp_path / "alias").symlink_to(library)
    defaults, rules = bj.load_manifest(library / "batch.toml")
    walk = tmp_path / "alias" / TAKES[0]
    assert bj.settings_for(walk, defaults, rules)["rig"] == "plug-in-gait"
    outside = tmp_path / "alias" / "outside.c3d"
    assert bj.settings_for(outside, defaults, rules)["rig"] == "cmu41"


def test_manifest_errors(library: Path, tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text('[[takes]]\nmatch = "x"\nrigg = "cmu41"\n')
    with pytest.raises(bj.BatchError, match="unknown key 'rigg'"):
        bj.load_manifest(bad)
    bad.write_text('[defaults]\ncalibration = "a.json"\ncalibrate_frames = "0:1"\n')
    with pytest.raises(bj.BatchError, match="at most one of"):
        bj.load_manifest(bad)
    with pytest.raises(bj.BatchError, match="no calibration rule"):
        bj.make_jobs("solve", [library / TAKES[0]], tmp_path, {"rig": "cmu41"})
    # A glob over folders: their takes, not the manifest beside them (sorted by path:
    # broken/ before btkdata/).
    found = bj.expand_takes([str(library / "b*")])
    assert [p.name for p in found] == [
        "corrupt.trc", "MOTEK_T.trc", "MOTEK_ballet_reduced.trc",
        "PiG_Calibration-FlatFoot-Full.c3d", "PiG_Motion-FlatFoot-Full.c3d",
    ]  # fmt: skip
    with pytest.raises(bj.BatchError, match="names no take"):
        bj.expand_takes([str(tmp_path / "nothing*.c3d")])


@pytest.fixture
def dask_cluster() -> Iterator[str]:
    """A local Dask cluster of two worker processes on 127.0.0.1: its address."""
    from distributed import LocalCluster

    with LocalCluster(
        n_workers=2,
        threads_per_worker=1,
        processes=True,
        host="127.0.0.1",
        dashboard_address="127.0.0.1:0",  # a free loopback port, not 8787
    ) as cluster:
        yield str(cluster.scheduler_address)


@pytest.mark.timeout(600)
def test_dask_equals_serial_solve_and_validate(
    library: Path,
    tmp_path: Path,
    dask_cluster: str,
    serial_solve: tuple[dict[str, Any], Path],
) -> None:
    assert dask_cluster.startswith("tcp://127.0.0.1:")
    # solve on the cluster by its address, validate on an embedded local cluster.
    for mode, scheduler in (("solve", dask_cluster), ("validate", "dask")):
        if mode == "solve":
            serial, serial_out = serial_solve
        else:
            serial_out = tmp_path / f"{mode}-serial"
            serial = batch.run_batch(
                _jobs(library, mode, serial_out), scheduler="serial"
            )
        dask = batch.run_batch(
            _jobs(library, mode, tmp_path / f"{mode}-dask"),
            scheduler=scheduler,
            workers=2,
        )
        assert dask["workers"] == 2 and dask["scheduler"] == scheduler
        assert _stable(dask) == _stable(serial)
        _check_statuses(serial)
        # Worker processes did the work, none of it in this process.
        workers = {r["worker"] for r in dask["takes"]}
        assert workers and f":{os.getpid()}" not in " ".join(map(str, workers))
        assert all(w and ":" in w for w in workers)
        for take in TAKES:
            tid = take.replace("/", "__")
            if mode == "solve":
                a = np.load(serial_out / tid / "solve.npz")
                b = np.load(tmp_path / "solve-dask" / tid / "solve.npz")
                assert set(a.files) == set(b.files)
                for k in a.files:
                    np.testing.assert_array_equal(a[k], b[k], err_msg=k)
            else:
                ra = json.loads((serial_out / tid / "report.json")
                                .read_text())  # fmt: skip
                rb = json.loads((tmp_path / "validate-dask" / tid / "report.json")
                                .read_text())  # fmt: skip
                assert ra["checks"] == rb["checks"]
                assert ra["visuals"]["render"]["skipped"] == SNAPSHOTS_OFF


@pytest.mark.timeout(300)
def test_resume_and_force(
    library: Path, tmp_path: Path, serial_solve: tuple[dict[str, Any], Path]
) -> None:
    out = tmp_path / "out"
    first = batch.run_batch(_jobs(library, "solve", out), workers=2)  # process pool
    _check_statuses(first)
    assert first["totals"]["ran"] == 4 and first["totals"]["error"] == 1
    serial = serial_solve[0]
    assert _stable(first) == _stable(serial)
    stamp = {
        t: (out / t.replace("/", "__") / "result.json").stat().st_mtime_ns
        for t in TAKES
    }
    again = batch.run_batch(_jobs(library, "solve", out), scheduler="serial")
    by_id = {r["id"]: r for r in again["takes"]}
    for t in TAKES:
        assert by_id[t.replace("/", "__")]["skipped"] is True
        path = out / t.replace("/", "__") / "result.json"
        assert path.stat().st_mtime_ns == stamp[t]
    assert by_id["broken__corrupt.trc"]["skipped"] is False  # errors are retried
    assert again["totals"]["ran"] == 1 and _stable(again) == _stable(first)
    # A changed rule is a different job: that take runs again, the others skip.
    jobs = _jobs(library, "solve", out)
    changed = next(j for j in jobs if j["id"].startswith("kineticstoolkit"))
    jobs = bj.make_jobs(
        "solve",
        [Path(changed["take"])],
        out,
        {"rig": "cmu41", "calibrate_frames": "0:100"},
        base=library,
    )
    assert (
        jobs[0]["id"] == changed["id"]
        and jobs[0]["fingerprint"] != changed["fingerprint"]
    )
    rerun = batch.run_batch(jobs, scheduler="serial")
    assert rerun["totals"]["ran"] == 1
    forced = batch.run_batch(
        _jobs(library, "solve", out), scheduler="serial", force=True
    )
    assert forced["totals"]["ran"] == 4 and forced["totals"]["skipped"] == 0


def test_cli_batch_runs_the_takes_own_command_lines(
    library: Path, tmp_path: Path
) -> None:
    """``retargetd batch`` is a registered command; each job runs the ``retargetd``
    command lines its log shows, and running those by hand gives the same solve."""
    out = tmp_path / "o"
    argv = ["batch", "solve", str(library / TAKES[1]), "--rig", "cmu41",
            "--static", str(library / "btkdata/MOTEK_T.trc"),
            "--out", str(out), "--scheduler", "serial"]  # fmt: skip
    assert main(argv) == 0
    (take_dir,) = [p for p in out.iterdir() if p.is_dir()]  # no scratch folder left
    res = json.loads((take_dir / "result.json").read_text())
    assert res["status"] == "ok" and res["checks"]["frames"] == 100
    assert (take_dir / "calibration.json").is_file()
    commands = [
        shlex.split(line[len("$ retargetd ") :])
        for line in (take_dir / "log.txt").read_text().splitlines()
        if line.startswith("$ retargetd ")
    ]
    assert [c[0] for c in commands] == ["calibrate", "solve"]
    # The job ran in a scratch folder (out/.<id>.<random>/) since replaced: the same
    # command lines in another folder.
    by_hand = tmp_path / "by-hand"
    (by_hand / "out").mkdir(parents=True)
    scratch = re.compile(re.escape(str(out)) + r"/\.[^/]+")
    for cmd in commands:
        assert main([scratch.sub(str(by_hand), a) for a in cmd]) == 0, cmd
    hand = sorted(by_hand.rglob("solve.npz"))
    assert len(hand) == 1
    with np.load(take_dir / "solve.npz") as a, np.load(hand[0]) as b:
        assert set(a.files) == set(b.files)
        for k in a.files:
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def test_cli_batch_writes_summary(
    library: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "cli"
    argv = ["batch", "solve", str(library / "btkdata"), str(library / BROKEN),
            "--manifest", str(library / "batch.toml"), "--out", str(out),
            "--scheduler", "serial"]  # fmt: skip
    assert main(argv) == 1  # the broken take errors
    doc = json.loads((out / "summary.json").read_text())
    ids = [r["id"] for r in doc["takes"]]
    assert "broken__corrupt.trc" in ids and len(ids) == 5  # 4 btkdata + broken
    assert doc["totals"]["error"] == 1 and doc["totals"]["ok"] == 4
    text = (out / "summary.txt").read_text()
    assert "retargetd solve: error:" in text and "btkdata__MOTEK_T.trc" in text
    assert (out / "summary.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    capsys.readouterr()
    assert main([*argv[:-2], "--scheduler", "nowhere"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        "retargetd batch: error: --scheduler: expected processes, serial, dask or "
        "tcp://HOST:PORT; got 'nowhere'"
    ]


def test_validate_no_snapshots(library: Path, tmp_path: Path) -> None:
    """``retargetd validate --no-snapshots``: the checks, report and plot, no render
    (what every batch validate job runs without ``--snapshots``)."""
    report = tmp_path / "report"
    argv = ["validate", str(library / TAKES[2]), "--rig", "cmu41",
            "--calibrate-frames", "0:50", "--report", str(report)]  # fmt: skip
    assert main([*argv, "--no-snapshots"]) in (0, 1)
    doc = json.loads((report / "report.json").read_text())
    render = doc["visuals"]["render"]
    assert render["skipped"] == SNAPSHOTS_OFF and render["backend"] is None
    assert doc["visuals"]["snapshots"] == [] and not list(report.glob("snapshot_*"))
    assert (report / "checks.png").read_bytes()[:4] == b"\x89PNG"
    assert f"Snapshots skipped: {SNAPSHOTS_OFF}" in (report / "report.txt").read_text()
    assert doc["checks"] and doc["frames"] > 0


def test_rerun_replaces_the_take_folder_whole(library: Path, tmp_path: Path) -> None:
    """A job writes into a fresh scratch folder and swaps it in: a forced rerun meets
    none of the earlier run's files (whatever a command's overwrite policy) and
    leaves no scratch behind."""
    out = tmp_path / "out"
    jobs = [j for j in _jobs(library, "solve", out) if j["id"].startswith("kinetics")]
    first = batch.run_batch(jobs, scheduler="serial")["takes"][0]
    take_dir = Path(jobs[0]["out_dir"])
    (take_dir / "stale.txt").write_text("from an earlier run\n")
    again = batch.run_batch(jobs, scheduler="serial", force=True)["takes"][0]
    assert again["status"] == first["status"] == "ok"
    assert again["checks"]["digest"] == first["checks"]["digest"]
    assert sorted(p.name for p in take_dir.iterdir()) == [
        "log.txt", "result.json", "solve.npz"
    ]  # fmt: skip
    assert [p.name for p in out.iterdir()] == [take_dir.name]
