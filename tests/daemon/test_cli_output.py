"""Machine-readable and terminal output (issue 18, items 4 and 5): ``solve --out
take.mcap`` decoded with the schemas the file declares, ``--json`` summaries parsed,
``--quiet``, and the progress bar: drawn on a terminal (a pty), never into a pipe."""

from __future__ import annotations

import json
import os
import pty
import select
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from scipy.spatial.transform import Rotation

from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.body.solve import BodySolver
from retargetd.daemon.cli.main import main

CAL = ["--rig", "menache", "--calibrate-frames", "0:60"]


def _no_warnings(err: str) -> str:
    """stderr without calibration warnings (``warning: bone ...``: the rig's short up
    levers, which calibrate reports whatever the output options)."""
    return "".join(
        line
        for line in err.splitlines(keepends=True)
        if not line.startswith("warning:")
    )


def _synth(d: Path, dropout: float) -> Path:
    path = d / f"s{dropout:g}.c3d"
    argv = ["synth", "--seconds", "4", "--rate", "60", "--dropout", str(dropout)]
    assert main([*argv, "--out", str(path)]) == 0
    return path


@pytest.fixture(scope="module")
def take(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The synthetic performer, every marker seen."""
    return _synth(tmp_path_factory.mktemp("out"), 0.0)


@pytest.fixture(scope="module")
def gappy(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The same with 5 % of marker samples occluded (bones held)."""
    return _synth(tmp_path_factory.mktemp("gappy"), 0.05)


@pytest.fixture(scope="module")
def npz(take: Path) -> Path:
    out = take.with_suffix(".npz")
    assert main(["solve", str(take), *CAL, "--out", str(out), "--quiet"]) == 0
    return out


def _run(*argv: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "retargetd.daemon", *argv],
        capture_output=True, text=True, cwd=cwd, timeout=240,
    )  # fmt: skip


def _world(frames: dict[str, Any], frame: str) -> tuple[Rotation, np.ndarray]:
    """A frame's world pose, composed from ``world`` down the transform tree."""
    t = frames[frame]
    r = Rotation.from_quat([t.rotation.x, t.rotation.y, t.rotation.z, t.rotation.w])
    v = np.array([t.translation.x, t.translation.y, t.translation.z])
    if t.parent_frame_id == "world":
        return r, v
    pr, pv = _world(frames, t.parent_frame_id)
    return pr * r, pv + pr.apply(v)


def test_solve_mcap_holds_the_solve_under_foxglove_schemas(
    take: Path, npz: Path, tmp_path: Path
) -> None:
    out = tmp_path / "take.mcap"
    assert main(["solve", str(take), *CAL, "--out", str(out), "--quiet"]) == 0
    with np.load(npz, allow_pickle=False) as z:
        joints, names = z["joint_centres"], [str(n) for n in z["joint_names"]]
        bone_names = [str(n) for n in z["bone_names"]]
    rig = load_rig("menache")
    # Oracle: the NPZ's joint centres at the ends of the bones between two of them.
    point_joint = {p: names.index(j) for j, p in rig.joints.items() if j in names}
    both = [
        (b, point_joint[bone.origin], point_joint[bone.aim])
        for b, bone in enumerate(rig.bones)
        if bone.origin in point_joint and bone.aim in point_joint
    ]
    assert len(both) >= 8
    with open(out, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None
        schemas = {s.name for s in summary.schemas.values()}
        assert {"foxglove.SceneUpdate", "foxglove.FrameTransforms"} <= schemas
        scene, tf = [], []
        topics = ["/foxglove/scene", "/foxglove/tf"]
        for _, channel, _, msg in reader.iter_decoded_messages(topics=topics):
            if channel.topic == "/foxglove/scene":
                scene.append(msg)
            else:
                tf.append(msg)
        health = [
            (message.log_time, json.loads(message.data))
            for _, _, message in reader.iter_messages(topics=["/foxglove/health"])
        ]
        declared = {c.topic for c in summary.channels.values()}
        counts = summary.statistics.channel_message_counts
        # every declared channel carries messages (issue 31 item 8)
        assert all(counts.get(cid, 0) > 0 for cid in summary.channels), counts
    n = joints.shape[0]
    assert len(scene) == len(tf) == len(health) == n
    assert "/foxglove/health" in declared
    # the health per frame: the fit's residual and the held bones of the NPZ
    with np.load(npz, allow_pickle=False) as z:
        rms, flags = z["marker_rms"], z["bone_flags"]
    for i, (log_ns, h) in enumerate(health):
        assert h["t_ns"] == log_ns
        assert h["held_bones"] == int((flags[i] != 0).sum())
        if np.isfinite(rms[i]):
            assert h["marker_rms_mm"] == pytest.approx(1e3 * rms[i], abs=1e-3)
    for i in (10, n // 2, n - 1):
        ents = {e.id: e for e in scene[i].entities}
        pts = np.array([[p.x, p.y, p.z] for p in ents["skeleton"].lines[0].points])
        pairs = pts.reshape(-1, 2, 3)
        for _, a, b in both:  # each such bone is one drawn line, ends at the centres
            want = np.stack([joints[i, a], joints[i, b]])
            if not np.isfinite(want).all():
                continue
            d = np.abs(pairs - want).max(axis=(1, 2))
            assert d.min() < 1e-9, (i, a, b, d.min())
        # The bone frames: composed from world down, each bone's origin lands on its
        # joint centre.
        frames = {t.child_frame_id: t for t in tf[i].transforms}

        checked = 0
        for b, a, _ in both:  # every marker seen: every bone determined
            key = f"bone/{bone_names[b]}"
            if not np.isfinite(joints[i, a]).all():
                continue
            np.testing.assert_allclose(_world(frames, key)[1], joints[i, a], atol=1e-6)
            checked += 1
        assert checked == len(both)


def test_solve_json_summary(gappy: Path, tmp_path: Path) -> None:
    out = tmp_path / "s.npz"
    p = _run("solve", str(gappy), *CAL, "--out", str(out), "--json", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    doc = json.loads(p.stdout)  # one object, nothing else on stdout
    with np.load(out, allow_pickle=False) as z:
        t, n_bones = z["bone_flags"].shape
        n_joints = len(z["joint_names"])
    assert doc["command"] == "solve" and doc["format"] == "npz"
    assert (doc["frames"], doc["bones"], doc["joint_centres"]) == (t, n_bones, n_joints)
    assert doc["rate_hz"] == 60.0 and doc["rig"] == "menache"
    assert 0 < doc["occluded_samples"] < doc["rig_marker_samples"]
    assert _no_warnings(p.stderr) == ""  # no bar: stderr is a pipe


def test_validate_rig_check_calibrate_json(take: Path, tmp_path: Path) -> None:
    p = _run(
        "validate", str(take), *CAL, "--report", str(tmp_path / "r"), "--json",
        "--no-snapshots", cwd=tmp_path,
    )  # fmt: skip
    assert p.returncode in (0, 1), p.stderr
    doc = json.loads(p.stdout)
    report = json.loads((tmp_path / "r" / "report.json").read_text())
    assert doc["command"] == "validate"
    assert doc["passed"] == report["passed"] == (p.returncode == 0)
    assert doc["frames"] == report["frames"]
    assert set(doc["checks"]) == set(report["checks"])
    for name, c in doc["checks"].items():
        assert c["frames_flagged"] == report["checks"][name]["frames_flagged"]
    p = _run("rig", "check", "menache", str(take), "--json", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    doc = json.loads(p.stdout)
    assert doc["command"] == "rig check" and doc["rig"] == "menache"
    assert doc["valid"] is True and doc["bones_without_data"] == []
    assert len(doc["bones"]) == len(load_rig("menache").bones)
    cal = tmp_path / "cal.json"
    p = _run(
        "calibrate", str(take), "--rig", "menache", "--frames", "0:60",
        "--out", str(cal), "--json", cwd=tmp_path,
    )  # fmt: skip
    assert p.returncode == 0, p.stderr
    doc = json.loads(p.stdout)
    saved = json.loads(cal.read_text())
    assert doc["command"] == "calibrate" and doc["frames"] == [0, 60]
    lengths = {name: b["length_m"] for name, b in saved["bones"].items()}
    assert doc["bone_lengths_m"] == lengths


def test_quiet_prints_nothing(take: Path, tmp_path: Path) -> None:
    out = tmp_path / "q.npz"
    p = _run("solve", str(take), *CAL, "--out", str(out), "--quiet", cwd=tmp_path)
    assert p.returncode == 0 and out.is_file()
    assert p.stdout == "" and _no_warnings(p.stderr) == ""


def _pty_run(argv: list[str], cwd: Path, timeout_s: float = 240.0) -> tuple[int, str]:
    """Run with stderr on a pty (stdout a pipe); (exit code, what the pty saw)."""
    master, slave = pty.openpty()
    proc = subprocess.Popen(
        [sys.executable, "-m", "retargetd.daemon", *argv],
        stdout=subprocess.DEVNULL, stderr=slave, stdin=subprocess.DEVNULL, cwd=cwd,
    )  # fmt: skip
    os.close(slave)
    seen = b""
    t_end = time.monotonic() + timeout_s
    try:
        while time.monotonic() < t_end:
            r, _, _ = select.select([master], [], [], 0.2)
            if r:
                try:
                    chunk = os.read(master, 4096)
                except OSError:  # the child closed its end
                    break
                if not chunk:
                    break
                seen += chunk
            elif proc.poll() is not None:
                break
        rc = proc.wait(timeout=max(1.0, t_end - time.monotonic()))
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
        os.close(master)
    return rc, seen.decode(errors="replace")


def test_progress_bar_on_a_terminal_only(take: Path, tmp_path: Path) -> None:
    argv = ["solve", str(take), *CAL]
    rc, seen = _pty_run([*argv, "--out", str(tmp_path / "a.npz")], tmp_path)
    assert rc == 0
    n = 240
    assert f"solve [{'#' * 30}] {n}/{n} frames" in seen, seen
    assert "\r" in seen
    rc, seen = _pty_run([*argv, "--out", str(tmp_path / "b.npz"), "--quiet"], tmp_path)
    assert rc == 0 and "frames" not in seen, seen
    p = _run(*argv, "--out", str(tmp_path / "c.npz"), cwd=tmp_path)
    assert p.returncode == 0 and _no_warnings(p.stderr) == ""


@pytest.mark.parametrize("step", [32, 77])
def test_chunked_solve_equals_one_call(gappy: Path, step: int) -> None:
    from retargetd.daemon.cli.args import calibrate_from_take, solve_take_chunked
    from retargetd.replay.takes import load_take

    tk = load_take(gappy)
    rig = load_rig("menache")
    cal = calibrate_from_take(tk, rig, slice(0, 60), {})
    whole = BodySolver(rig, cal, tk.labels).solve_take(tk.positions)
    seen: list[int] = []
    parts = solve_take_chunked(
        BodySolver(rig, cal, tk.labels), tk.positions, step, seen.append
    )
    assert sum(seen) == tk.n_frames and len(seen) == -(-tk.n_frames // step)
    assert np.count_nonzero(whole.bone_flags)  # the dropout holds bones: state matters
    for name in ("joint_centres", "world_from_bone_quat", "rest_from_bone_quat",
                 "root_pos", "bone_flags", "bone_quality"):  # fmt: skip
        np.testing.assert_array_equal(getattr(parts, name), getattr(whole, name))
