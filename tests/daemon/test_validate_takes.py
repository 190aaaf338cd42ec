"""The real takes validate clean: the MOTEK ballet and the tennis serve (rig cmu41)
solved in process, and all three (with the PiG walk) as recorded replays; with the fit
(the default), every check but the marker residual one, which fails on the ballet's
right arm and the serve's acromion markers and names them (:data:`RESIDUAL_MISFITS`).

Thresholds and the joint table were set on these takes and the literature
(``validate.THRESHOLDS``, ``validate_limits``); the figures each check reaches are
printed (``pytest -s``). Recorded replays: a real ``retargetd replay`` (ZeroMQ, as fast
as possible) into a real ``retargetd record`` subprocess over 127.0.0.1, once per
session, then ``retargetd validate RECORDING.mcap --calibration ...``; the recording
holds the markers as sent (float32 metres, world frame) and not the take's subject
measurements, so the calibrations are made from the original files.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import selectors
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from paths import DATASETS

from retargetd.daemon.body.calibration import calibrate
from retargetd.daemon.body.method import make_body_solver
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.cli.main import main
from retargetd.daemon.validate.checks import (
    THRESHOLDS,
    THRESHOLDS_BASIS,
    TakeReport,
    fit_pairs,
    validate_take,
)
from retargetd.daemon.validate.limits import JOINT_LIMITS_DEG
from retargetd.daemon.validate.model import (
    SEGMENT_KIND,
    build_model,
    skeleton_from_calibration,
)
from retargetd.replay import recording as rf
from retargetd.replay.takes import load_take

pytestmark = pytest.mark.usefixtures("mujoco_cwd")


PIG_STATIC = "btkdata/PiG_Calibration-FlatFoot-Full.c3d"
PIG_WALK = "btkdata/PiG_Motion-FlatFoot-Full.c3d"
BALLET = "btkdata/MOTEK_ballet_reduced.trc"
MOTEK_T = "btkdata/MOTEK_T.trc"
TENNIS = "kineticstoolkit/kinematics_tennis_serve.c3d"
#: The tennis serve's one-frame labelling glitches: 400 (LWRA and LWRB on one marker),
#: 744 (the wrist bar 119 mm long against 101 mm either side). Since the roll hold
#: (issue 14 item 3) frame 400 is no transient: the forearm's and hand's up direction
#: (LWRB->LWRA) collapses there, so they keep their roll (flagged partial).
TENNIS_GLITCHES = [744]
#: The fit validates the serve since the elbows are hinges with the forearm's twist,
#: the upper-arm wands are down-weighted and the feet have a pull towards the
#: calibration pose (cmu41.toml [fit], each key's reasons and what it did on both
#: takes there). Before, 7 frames were past a limit: the left forearm's twist at
#: 173.7 deg (the humerus's axial rotation put into the elbow as a sideways bend) and
#: the right foot's 1.9 deg past its 55.


#: Takes whose fit fails the marker residual check (validate.residual, issue 28 item
#: 4: what the fit cannot match shows as residual, flagged and named), and the two
#: markers it must name first. Thresholds from the literature, not these takes
#: (THRESHOLDS "marker_residual_*"); these are true misfits, not noise:
#: - the ballet on MOTEK_T (another session: its right arm SHO-ELB 35 mm shorter than
#:   the ballet's): the right upper-arm wand and elbow marker sit 46 / 36 mm (median)
#:   from where the calibrated arm can put them, past 40 mm in 0.6-0.7 s runs (and
#:   RBAC, on the scapula, at 43 mm for 8 frames); every other marker stays under;
#: - the serve: the acromion markers 100-140 mm from the fitted clavicles in every
#:   serve's arm elevation (runs of 1.3-2 s), far past the skin motion measured there
#:   (median 30 mm at the acromial angle, Sensors 22(17):6502, 2022); freeing the
#:   clavicles' [fit] prior did not bring LSHO under 120 mm (p90): the rig's model, not
#:   the prior, cannot follow the serve's shoulder (the other issue 28 items).
#: When the fit or the rigs come to match them, these become passes: update this.
RESIDUAL_MISFITS = {"motek-ballet": ("RUPA", "RELB"), "tennis-serve": ("RSHO", "LSHO")}


def _expected_failures(case: str, method: str) -> list[str]:
    """The checks a case fails with ``method`` (the fit: the residual misfits)."""
    misfit = method == "fit" and case in RESIDUAL_MISFITS
    return ["marker_residual_max"] if misfit else []


def _check_misfit(case: str, markers: dict[str, Any]) -> None:
    """The residual check names the case's two misfit markers first."""
    assert tuple(list(markers)[:2]) == RESIDUAL_MISFITS[case], markers


def _validate(
    static: Path, frames: slice, take_path: Path, method: str = "construction"
) -> tuple[TakeReport, np.ndarray]:
    rig = load_rig("cmu41")
    base = load_take(static)
    cal = calibrate(
        rig, base.positions[frames], base.labels, take_measurements=base.measurements
    )
    take = base if take_path == static else load_take(take_path)
    solver = make_body_solver(
        method, rig, cal, take.labels,
        joint_limits=JOINT_LIMITS_DEG, segment_kind=SEGMENT_KIND,
        rate_hz=take.rate_hz,
    )  # fmt: skip
    solve = solver.solve_take(take.positions)
    vm = build_model(skeleton_from_calibration(rig, cal))
    rep = validate_take(vm, solve, take.rate_hz, fit=fit_pairs(rig, solve.joint_names))
    print(f"\n{take_path.name} ({method})")
    if method == "fit":
        rms = 1e3 * solve.marker_rms[np.isfinite(solve.marker_rms)]
        print(
            f"  marker RMS median {np.median(rms):.1f} p95 {np.percentile(rms, 95):.1f}"
            f" mm, {solve.outliers_rejected} samples rejected, "
            f"{int(solve.reseeded.sum())} frames reseeded"
        )
    else:
        rms = np.full(0, np.nan)
    for name, c in rep.checks.items():
        v = c.values[np.isfinite(c.values)]
        print(
            f"  {name:18s} median {np.median(v):9.3g} max {v.max():9.3g} {c.unit}"
            f" (threshold {c.threshold:g}) transients {c.transients.tolist()}"
        )
    return rep, rms


@pytest.mark.parametrize("method", ["construction", "fit"])
def test_motek_ballet_validates(datasets: Path, method: str) -> None:
    rep, rms = _validate(datasets / MOTEK_T, slice(None), datasets / BALLET, method)
    failed = {n: c.summary() for n, c in rep.checks.items() if c.n_flagged}
    assert rep.failed() == _expected_failures("motek-ballet", method), failed
    if method == "fit":
        _check_misfit("motek-ballet", rep.checks["marker_residual_max"].markers or {})
    assert rep.checks["limits"].transients.size == 0
    if method == "construction":
        # The checks the ballet came closest to (see THRESHOLDS): MOTEK_T is another
        # session, the right arm's SHO-ELB 35 mm longer in the ballet.
        assert 40.0 < rep.checks["fit_max"].values.max() < 70.0  # mm
    else:
        # The fit's skeleton is rigid, so its joint centres are the skeleton's; the
        # session mismatch shows in the marker residuals instead, which stay under
        # the gate (40 mm, the largest soft-tissue artefact: FitParams.gate_m).
        assert rep.checks["fit_max"].values.max() < 1e-6
        assert np.median(rms) < 40.0


@pytest.mark.parametrize("method", ["construction", "fit"])
def test_tennis_serve_validates(datasets: Path, method: str) -> None:
    """With the fit (issue 14), the serve's one-frame label glitches are gated out
    and no longer show as limit transients."""
    path = datasets / TENNIS
    rep, _ = _validate(path, slice(0, 50), path, method)
    failed = {n: c.summary() for n, c in rep.checks.items() if c.n_flagged}
    assert rep.failed() == _expected_failures("tennis-serve", method), failed
    if method == "fit":
        _check_misfit("tennis-serve", rep.checks["marker_residual_max"].markers or {})
    want = TENNIS_GLITCHES if method == "construction" else []
    assert rep.checks["limits"].transients.tolist() == want
    assert 0.3 < np.nanmax(rep.checks["ghost_force"].values) < 0.75  # serve flight


# --- recorded replays ----------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Recorded:
    """A take recorded through ``retargetd replay`` -> ``retargetd record``."""

    name: str
    rig: str
    source: Path  # the original take
    recording: Path  # the .mcap
    calibration: Path  # made from the original files
    n_frames: int
    rate_hz: float
    extra: tuple[str, ...] = ()  # more validate arguments


#: name -> (rig, take, calibration take, calibration frames or None, validate extras).
#: The stance-foot skate check (``retargetd validate`` hands it the detected stance):
#: the serve's feet slide on the floor (the heel pivoting with the toes up, the back
#: foot dragged: LHEE, LTOE and LANK translate together 4-30 cm with the foot on its
#: support; README "Stance-foot skate"), so it fails there.
SKATES: dict[str, list[str]] = {"tennis-serve": ["foot_skate"]}
CASES: dict[str, tuple[str, str, str, str | None, tuple[str, ...]]] = {
    # The walk's Bodymass, from its C3D (a recording carries no measurements).
    "pig-walk": (
        "plug-in-gait",
        PIG_WALK,
        PIG_STATIC,
        None,
        ("--body-mass-kg", "47.5"),
    ),
    "motek-ballet": ("cmu41", BALLET, MOTEK_T, None, ()),
    "tennis-serve": ("cmu41", TENNIS, TENNIS, "0:50", ()),
}


def _start_recorder(out: Path) -> tuple[subprocess.Popen[str], int]:
    proc = subprocess.Popen(
        [sys.executable, "-m", "retargetd.daemon", "record",
         "--listen", "zmq://127.0.0.1:0", "--out", str(out)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    assert proc.stdout is not None
    with selectors.DefaultSelector() as sel:
        sel.register(proc.stdout, selectors.EVENT_READ)
        if not sel.select(60.0):
            proc.kill()
            raise AssertionError("recorder did not start in time")
    line = proc.stdout.readline()
    match = re.search(r"tcp://127\.0\.0\.1:(\d+)", line)
    if not match:
        proc.kill()
        raise AssertionError(f"no listening line: {line!r}")
    return proc, int(match.group(1))


@pytest.fixture(scope="session")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Recorded]:
    """The PiG walk, the MOTEK ballet and the tennis serve, each replayed at full
    speed into its own ``retargetd record`` (started together), and their
    calibrations."""
    if not DATASETS.is_dir():
        reason = f"shared datasets folder not found at {DATASETS}"
        if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
            pytest.fail(f"{reason} (CI=true: nothing may skip)")
        pytest.skip(reason)
    root = tmp_path_factory.mktemp("recorded")
    procs: dict[str, tuple[subprocess.Popen[str], int]] = {}
    out: dict[str, Recorded] = {}
    try:
        for name in CASES:
            procs[name] = _start_recorder(root / f"{name}.mcap")
        for name, (rig, take, static, frames, extra) in CASES.items():
            source = DATASETS / take
            cal = root / f"{name}-calibration.json"
            argv = [
                "calibrate",
                str(DATASETS / static),
                "--rig",
                rig,
                "--out",
                str(cal),
            ]
            if frames is not None:
                argv += ["--frames", frames]
            assert main(argv) == 0
            to = f"zmq://127.0.0.1:{procs[name][1]}"
            assert main(["replay", str(source), "--to", to, "--speed", "0"]) == 0
            original = load_take(source)
            out[name] = Recorded(
                name, rig, source, root / f"{name}.mcap", cal, original.n_frames,
                original.rate_hz, extra,
            )  # fmt: skip
        for name, rec in out.items():
            proc = procs[name][0]
            _wait_frames(rec.recording, rec.n_frames, proc)
            proc.send_signal(signal.SIGINT)
            stdout, stderr = proc.communicate(timeout=30)
            assert proc.returncode == 0, stderr
            assert f"recorded {rec.n_frames} marker frames" in stdout, stdout
    finally:
        for proc, _ in procs.values():
            if proc.poll() is None:
                proc.kill()
                proc.communicate(timeout=10)
    return out


def _wait_frames(path: Path, n: int, proc: subprocess.Popen[str]) -> None:
    """Until the recorder's (flushed) file holds ``n`` marker frames (bounded)."""
    deadline = time.monotonic() + 30.0
    while time.monotonic() < deadline:
        assert proc.poll() is None, "recorder exited early"
        if path.exists() and path.stat().st_size > 0:
            got = sum(
                p.kind == rf.KIND_FRAME for p in rf.read_recording(path).packets()
            )
            if got >= n:
                return
        time.sleep(0.1)
    raise AssertionError(f"{path.name}: recorder did not get {n} frames in 30 s")


@pytest.mark.timeout(240)
@pytest.mark.parametrize("name", list(CASES))
def test_recorded_replay_validates_clean(
    recorded: dict[str, Recorded], name: str, tmp_path: Path
) -> None:
    rec = recorded[name]
    take = load_take(rec.recording)
    source = load_take(rec.source)
    assert take.n_frames == rec.n_frames and take.labels == source.labels
    assert take.rate_hz == pytest.approx(rec.rate_hz, rel=1e-6)
    np.testing.assert_array_equal(
        take.positions, source.positions.astype(np.float32).astype(np.float64)
    )
    report = tmp_path / "report"
    argv = [
        *("validate", str(rec.recording), "--rig", rec.rig),
        *("--calibration", str(rec.calibration), "--report", str(report), *rec.extra),
    ]
    expected = SKATES.get(name, []) + _expected_failures(name, "fit")
    assert main(argv) == (1 if expected else 0)
    doc: dict[str, Any] = json.loads((report / "report.json").read_text())
    assert doc["passed"] == (not expected) and doc["failed"] == expected
    assert doc["frames"] == rec.n_frames
    assert doc["take"] == str(rec.recording)
    assert doc["thresholds"] == THRESHOLDS
    assert doc["thresholds_basis"] == THRESHOLDS_BASIS and doc["thresholds_note"]
    checks = doc["checks"]
    assert set(checks) == {*THRESHOLDS_BASIS}
    for check_name, check in checks.items():
        if check_name == "foot_skate" and check_name in expected:
            assert check["frames_flagged"] > 0 and check["detail"]
            continue
        if check_name in expected:
            _check_misfit(name, check["markers"])
            continue
        assert check["frames_flagged"] == 0
        assert check["max"] <= check["threshold"] or check["transient_frames"]
    # validate solves with the fit (the default), which gates the serve's one-frame
    # label glitches; the construction still shows them (test_tennis_serve_passes).
    assert checks["limits"]["transient_frames"] == []
    assert doc["method"] == "fit"
    assert checks["convention"]["max"] < 1e-6  # mm
    assert 0.0 < checks["ghost_force"]["max"] < THRESHOLDS["ghost_force_bw"]
    assert checks["floating"]["max"] == 0.0
    text = (report / "report.txt").read_text()
    result = f"Result: FAIL: {', '.join(expected)}" if expected else "Result: PASS"
    assert result in text and "How the thresholds were set" in text
    assert (report / "model.xml").is_file() and (report / "checks.png").is_file()
