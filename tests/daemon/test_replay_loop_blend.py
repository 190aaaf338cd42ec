"""``retargetd replay TAKE --loop --blend-frames N`` (issue 15 item 6, live): a cyclic
take looped over loopback OSC into a receiver has no jump at the seam.

The take is the synthetic performer walking round its circle (``retargetd synth
--motions walk``; 1 m/s, a 1.1 m stride: one gait cycle every 1.1 s, 110 frames at
100 Hz). The window holds two whole cycles plus the N fade frames. Received frame by
frame (compact OSC, decoded with python-osc, an independent reader), every marker's
step across each seam is at most its own largest frame-to-frame step over the take
plus :data:`MARGIN_M`; every frame is finite; frame numbers and source times run on
without a break. Without ``--blend-frames`` the same loop jumps back at the seam by
metres (so the check can fail).
"""

from __future__ import annotations

import socket
import threading
from pathlib import Path

import numpy as np
import pytest
from pythonosc.osc_message import OscMessage

from retargetd.daemon.cli.main import main
from retargetd.daemon.post.marker_loop import fade_weights, loop_markers
from retargetd.replay.takes import load_take

RATE_HZ = 100.0
CYCLE_FRAMES = 110  # WALK_STRIDE_M / WALK_SPEED_M_S = 1.1 s at 100 Hz
N = 20
START = 100  # past the 0.5 s ramp of the walk's speed
#: Allowed beyond a marker's own largest step: 1 mm, the order of an optical
#: system's dynamic marker error (Merriaux et al. 2017, Sensors 17(7):1591: Vicon
#: dynamic position errors under 2 mm, static ~0.15 mm), i.e. below what a capture
#: of the same motion would itself show.
MARGIN_M = 1e-3


def _receive(sock: socket.socket, stop: threading.Event, got: list[bytes]) -> None:
    while not stop.is_set():
        try:
            got.append(sock.recv(65536))
        except TimeoutError:
            continue


def _replay(
    take: Path, extra: list[str], seconds: float
) -> list[tuple[int, float, np.ndarray]]:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 21)
        sock.bind(("127.0.0.1", 0))
        sock.settimeout(0.05)
        port = sock.getsockname()[1]
        stop, got = threading.Event(), []
        rx = threading.Thread(target=_receive, args=(sock, stop, got), daemon=True)
        rx.start()
        argv = ["replay", str(take), "--to", f"osc://127.0.0.1:{port}", "--loop",
                "--frames", f"{START}:{START + 2 * CYCLE_FRAMES + N}",
                "--seconds", str(seconds), "--speed", "4", *extra]  # fmt: skip
        try:
            assert main(argv) == 0
        finally:
            threading.Event().wait(0.2)  # the last datagrams
            stop.set()
            rx.join(timeout=5.0)
        assert not rx.is_alive()
    finally:
        sock.close()
    frames = []
    for data in got:
        msg = OscMessage(data)
        if msg.address != "/rtd/frame":
            continue
        fid, t_s, _set_id, count, blob = msg.params
        frames.append(
            (fid, t_s, np.frombuffer(blob, ">f4").reshape(count, 3).astype(float))
        )
    return frames


@pytest.fixture(scope="module")
def walk(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("walk") / "walk.c3d"
    argv = ["synth", "--seconds", "4", "--rate", str(RATE_HZ), "--motions", "walk",
            "--base-pose-s", "0", "--out", str(path)]  # fmt: skip
    assert main(argv) == 0
    return path


def _own_steps(walk: Path) -> np.ndarray:
    """(M,) each marker's largest frame-to-frame step over the window, metres."""
    pos = load_take(walk).positions[START : START + 2 * CYCLE_FRAMES + N]
    return np.linalg.norm(np.diff(pos, axis=0), axis=-1).max(axis=0)


@pytest.mark.timeout(60)
def test_blended_loop_has_no_jump_at_the_seam(walk: Path) -> None:
    loop_len = 2 * CYCLE_FRAMES  # the window minus the N fade frames
    # 4 passes at speed 4: 8.8 s of take in 2.2 s.
    frames = _replay(walk, ["--blend-frames", str(N)], seconds=2.3)
    ids = np.array([f for f, _, _ in frames])
    assert len(frames) >= 3 * loop_len, len(frames)
    np.testing.assert_array_equal(ids, np.arange(len(ids)))  # none lost, in order
    times = np.array([t for _, t, _ in frames])
    np.testing.assert_allclose(np.diff(times), 1.0 / RATE_HZ, rtol=1e-9)
    pos = np.stack([m for _, _, m in frames])
    assert np.isfinite(pos).all()
    steps = np.linalg.norm(np.diff(pos, axis=0), axis=-1)  # (F-1, M)
    own = _own_steps(walk)
    seams = np.arange(loop_len, len(frames), loop_len)  # first frame of a pass
    # Every step of the fade and of the seam into it, each marker against its own.
    for s in seams:
        window = steps[s - 2 : s + N + 1]
        excess = (window - own).max()
        assert excess <= MARGIN_M, (s, excess, window.max(), own.max())
    worst = max(float(steps[s - 1].max()) for s in seams)
    print(
        f"\nblended loop: {len(seams)} seams, worst marker step at a seam "
        f"{1e3 * worst:.1f} mm; the take's own largest step {1e3 * own.max():.1f} mm"
    )
    # The walk walks on: each pass turned round the circle by one loop's heading.
    centroid = pos.mean(axis=1)
    travelled = np.linalg.norm(centroid[seams[0]] - centroid[0])
    assert travelled > 0.5


@pytest.mark.timeout(60)
def test_plain_loop_jumps_back_at_the_seam(walk: Path) -> None:
    frames = _replay(walk, [], seconds=0.8)
    pos = np.stack([m for _, _, m in frames])
    loop_len = 2 * CYCLE_FRAMES + N
    step = np.linalg.norm(pos[loop_len] - pos[loop_len - 1], axis=-1)
    assert step.min() > 10 * _own_steps(walk).max()  # the walk jumps back
    print(f"\nplain loop: the seam moves every marker by >= {step.min():.2f} m")


def test_loop_markers_fade_and_alignment() -> None:
    """The fade on a rigid walk straight along +X: after the alignment the blend is
    the head exactly (the tail is the head moved); the motion is the cycle's travel."""
    rng = np.random.default_rng(0)
    body = rng.normal(0, 0.2, (12, 3))
    t = np.arange(60)
    cycle = 50  # the loop's length: T - N
    sway = 0.05 * np.sin(2 * np.pi * t / cycle)
    m = body[None] + np.stack([0.03 * t, sway, 0 * t], axis=1)[:, None]
    out, mat, pos = loop_markers(m, 10)
    assert out.shape == (50, 12, 3)
    np.testing.assert_allclose(mat, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(pos, [-0.03 * 50, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(out[:10], m[:10], atol=1e-12)
    np.testing.assert_array_equal(out[10:], m[10:50])
    u = fade_weights(3)
    np.testing.assert_allclose(u, [0.25, 0.5, 0.75])
    # Occluded on either side: occluded in the blend.
    m[55, 3] = np.nan
    out, _, _ = loop_markers(m, 10)
    assert np.isnan(out[5, 3]).all() and np.isfinite(np.delete(out, 3, 1)).all()
    with pytest.raises(ValueError, match=r"--blend-frames must be in 1 \.\. 29"):
        loop_markers(m, 30)


def test_blend_frames_needs_loop(
    walk: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["replay", str(walk), "--to", "osc://127.0.0.1:9", "--blend-frames", "5"]
    assert main(argv) == 2
    assert "--blend-frames needs --loop" in capsys.readouterr().err
    argv = [*argv, "--loop", "--frames", "0:8"]
    assert main(argv) == 2
    assert "--blend-frames must be in 1 .. 3 for 8 frames" in capsys.readouterr().err
