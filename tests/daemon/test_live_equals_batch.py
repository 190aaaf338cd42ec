"""Live equals batch: a real take, played into a real daemon, solves as offline.

The btkdata Plug-in Gait walk (315 frames at 100 Hz, 35 markers, a 30-frame gap on
LFHD) is played by ``retargetd replay`` into ``retargetd run --process-every-frame``
(both subprocesses, every endpoint ephemeral on 127.0.0.1), calibrated by ``retargetd
calibrate`` on the static of the same session. The test captures the ZeroMQ pose
stream and compares every frame, matched by frame number, with the batch solve of
the same take (what ``retargetd solve`` computes) on positions rounded to float32 as
on the wire: each quaternion's angle to its batch twin is within 1e-6 rad (the wire
carries float32 quaternions, ~1e-7 relative), root positions within float32
rounding, bone flags equal.

Two paths: ZeroMQ (the player's PUSH to the daemon's PULL, unpaced: PUSH/PULL has
back-pressure, so nothing is lost however fast the player goes) and compact OSC over
UDP at twice the recorded speed (unpaced UDP can overflow the daemon's receive
buffer when the kernel caps it, e.g. 208 KB with the default ``rmem_max``: ~100
datagrams; at 200 frames/s that is half a second of slack).

ZeroMQ's slow joiner (a SUB misses what was published before its subscription
reached the PUB) is handled without touching the stream under test: frames are sent
through the daemon's *other* input until the SUB sees a pose. Each input has its own
marker stream and solver, so the played input's solver starts fresh, as the batch
solve does; its poses carry their own names id. Run with ``pytest -s`` for figures.
"""

from __future__ import annotations

import functools
import subprocess
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

# Fixtures and helpers from tests/daemon/conftest.py (pytest loads it; tests can't
# import it by name under --import-mode=importlib, so the paths are repeated here).
from paths import DATASETS

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.calibration import load_calibration
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.body.solve import BodySolve, BodySolver
from retargetd.daemon.cli.main import main
from retargetd.daemon.post.stance import foot_contact
from retargetd.daemon.rotations import quat_angle, quat_conj, quat_mul
from retargetd.protocols import pose_stream as ps
from retargetd.replay.take import Take
from retargetd.replay.takes import load_take

WALK = DATASETS / "btkdata/PiG_Motion-FlatFoot-Full.c3d"
TOL_RAD = 1e-6


@functools.cache
def _walk() -> Take:
    return load_take(WALK)


def _f32(a: np.ndarray) -> np.ndarray:
    """What the daemon decodes: float32 on the wire, float64 inside."""
    return np.asarray(a, dtype=np.float32).astype(np.float64)


@functools.cache
def _batch(calibration: Path, rounded: bool) -> BodySolve:
    """What ``retargetd solve`` computes, on the take's positions (optionally rounded
    to float32 first, as the player sends them)."""
    take = _walk()
    solver = BodySolver(
        load_rig("plug-in-gait"), load_calibration(calibration), take.labels
    )
    positions = _f32(take.positions) if rounded else take.positions
    return solver.solve_take(positions)


def _angles(live_quat: np.ndarray, batch_quat: np.ndarray) -> np.ndarray:
    """Angle (rad) of ``conj(q_live) * q_batch`` per quaternion (sign-free, and free of
    the live quaternion's float32 norm error: the angle is a ratio)."""
    live = np.asarray(live_quat, dtype=np.float64)
    return quat_angle(quat_mul(quat_conj(live), batch_quat))


def _play(
    retargetd: list[str], daemon: Any, transport: str, speed: str, cwd: Path
) -> str:
    """``retargetd replay WALK --to ... --speed S`` to the input under test (bounded);
    its stdout."""
    if transport == "zmq":
        to = daemon.endpoints["zmq markers"].replace("tcp://", "zmq://")
    else:
        host, port = daemon.udp("osc markers")
        to = f"osc://{host}:{port}"
    argv = [*retargetd, "replay", str(WALK), "--to", to, "--speed", speed]
    done = subprocess.run(argv, cwd=cwd, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, (done.stdout, done.stderr)
    return done.stdout


def test_batch_oracle_is_retargetd_solve(pig_calibration: Path, tmp_path: Path) -> None:
    """The in-process batch solve used below is exactly what ``retargetd solve``
    writes for the walk."""
    out = tmp_path / "walk.npz"
    # The construction: the oracle of this file's live tests (conftest.daemon_config).
    argv = ["solve", str(WALK), "--rig", "plug-in-gait", "--method", "construction"]
    assert main([*argv, "--calibration", str(pig_calibration), "--out", str(out)]) == 0
    res = _batch(pig_calibration, rounded=False)
    with np.load(out, allow_pickle=False) as npz:
        for key in ("world_from_bone_quat", "rest_from_bone_quat", "root_pos"):
            np.testing.assert_array_equal(npz[key], getattr(res, key), err_msg=key)
        np.testing.assert_array_equal(npz["bone_flags"], res.bone_flags)


@pytest.mark.parametrize(
    ("transport", "speed"),
    [("zmq", "0"), ("osc", "2")],
    ids=["zmq-push-unpaced", "osc-compact-speed2"],
)
def test_live_pose_stream_equals_batch_solve(
    pig_calibration: Path,
    run_daemon: Callable[..., Any],
    retargetd: list[str],
    pose_capture: Callable[[str], Any],
    tmp_path: Path,
    transport: str,
    speed: str,
) -> None:
    take = _walk()
    n = take.n_frames
    daemon = run_daemon(pig_calibration, "--process-every-frame")
    cap = pose_capture(daemon.endpoints["zmq poses"])
    other = "zmq" if transport == "osc" else "osc"
    priming_ids = cap.prime(daemon, other, take.labels, take.positions[0])
    primed = daemon.counters()["frames_out"]

    report = _play(retargetd, daemon, transport, speed, tmp_path)
    cap.wait_for(n, timeout_s=30.0)
    cap.pump(200)  # anything beyond the take would be a bug: collect it too

    poses = [m for m in cap.poses if m.names_id not in priming_ids]
    counters = daemon.counters()
    assert len(poses) == n, (len(poses), n, counters, report)
    assert counters["frames_out"] - primed == n and counters["stale"] == 0, counters
    assert counters["send_drops"] == 0, counters
    assert [m.frame_id for m in poses] == list(range(n))
    # The names message for the played stream's names id comes before its first data.
    names_id = poses[0].names_id
    assert {m.names_id for m in poses} == {names_id}
    first_data = cap.order.index(("data", names_id))
    assert ("names", names_id) in cap.order[:first_data]
    names = next(m for m in cap.names if m.names_id == names_id)
    batch = _batch(pig_calibration, rounded=True)
    assert names.bone_names == batch.bone_names

    live_wfb = np.stack([m.world_from_bone_quat for m in poses])
    live_pfb = np.stack([m.rest_from_bone_quat for m in poses])
    live_root = np.stack([m.root_pos_world for m in poses])
    live_flags = np.stack([m.bone_flags for m in poses])
    wfb_rad = _angles(live_wfb, batch.world_from_bone_quat)
    pfb_rad = _angles(live_pfb, batch.rest_from_bone_quat)
    # How far float32 rounding alone moves the batch quaternions (the floor).
    f32_wfb_rad = _angles(_f32(batch.world_from_bone_quat), batch.world_from_bone_quat)
    f32_pfb_rad = _angles(_f32(batch.rest_from_bone_quat), batch.rest_from_bone_quat)
    bitwise = np.array_equal(
        live_wfb, batch.world_from_bone_quat.astype(np.float32)
    ) and np.array_equal(live_pfb, batch.rest_from_bone_quat.astype(np.float32))
    print(
        f"\n{transport}: {len(poses)} frames x {live_wfb.shape[1]} bones; max angle "
        f"live vs batch: world_from_bone {wfb_rad.max():.3g} rad, parent_from_bone "
        f"{pfb_rad.max():.3g} rad; float32 rounding of the batch alone: "
        f"{f32_wfb_rad.max():.3g} / {f32_pfb_rad.max():.3g} rad; live == "
        f"float32(batch) bit for bit: {bitwise}; root max "
        f"{np.abs(live_root - batch.root_pos).max():.3g} m"
    )
    assert wfb_rad.max() <= TOL_RAD and pfb_rad.max() <= TOL_RAD
    # The true parent-relative rotation too, and its frames cancel on the wire
    # (world_from_parent * parent_from_bone = world_from_bone, to float32 rounding).
    live_par = np.stack([m.parent_from_bone_quat for m in poses]).astype(np.float64)
    assert _angles(live_par, batch.parent_from_bone_quat).max() <= TOL_RAD
    for b, par in enumerate(names.bone_parents):
        if par < 0:
            continue
        composed = rot.quat_mul(live_wfb[:, par].astype(np.float64), live_par[:, b])
        assert _angles(composed, live_wfb[:, b].astype(np.float64)).max() <= 2e-6
    # Same hemisphere too (the stream promises sign continuity, as the batch has).
    dots = np.sum(live_wfb * batch.world_from_bone_quat, axis=-1)
    assert (dots > 0).all()
    np.testing.assert_allclose(live_root, batch.root_pos, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(live_flags, batch.bone_flags)
    # Foot contact (issue 34): the stream's bits are solve's foot_contact, frame for
    # frame (the same detector on the same solve, at the take's clock).
    assert all(m.flags & ps.FRAME_CONTACT_KNOWN for m in poses)
    live_contact = np.array(
        [
            [
                m.flags & ps.FRAME_CONTACT_LEFT != 0,
                m.flags & ps.FRAME_CONTACT_RIGHT != 0,
            ]
            for m in poses
        ]
    )
    contact = foot_contact(
        load_rig("plug-in-gait"), load_calibration(pig_calibration),
        batch.root_pos, batch.world_from_bone_quat, take.rate_hz,
    )  # fmt: skip
    np.testing.assert_array_equal(live_contact, contact)
