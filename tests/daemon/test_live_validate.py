"""The live validator in the daemon, over real loopback sockets: validation bits in the
ZeroMQ pose stream, one ``RTDV`` message per checked frame, counters in the status,
and drop-don't-block when the validator's queue is full (every pose still sent).

The performer is the exact synthetic one of ``test_live.py`` (ZeroMQ PUSH input,
process-every-frame). A 30 cm teleport of every marker for a few frames is the
defect: the speed check must flag it, live, with the bone bits of the root.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import live_harness as _live
import numpy as np
import zmq

from retargetd.daemon.body.calibration import load_calibration
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.body.solve import BodySolver
from retargetd.daemon.validate.live import LiveValidator
from retargetd.protocols import pose_stream as ps
from retargetd.protocols import zmq_wire
from retargetd.protocols.marker_input import LabelSet

Live = _live.Live
_f32, _take, _wait_until = _live._f32, _live._take, _live._wait_until
RATE_HZ = _live.RATE_HZ
EXACT_RIG = _live.EXACT_RIG


class Stream:
    """ZeroMQ PUSH into the daemon, a SUB on its pose stream (data, validation)."""

    def __init__(self, live: Live, zmq_socket: Callable[[int], Any]) -> None:
        self.push = zmq_socket(zmq.PUSH)
        self.push.connect(live.tcp("zmq markers"))
        self.sub = zmq_socket(zmq.SUB)
        self.sub.setsockopt(zmq.SUBSCRIBE, b"RTD")
        self.sub.setsockopt(zmq.RCVHWM, 100_000)
        self.sub.connect(live.tcp("zmq poses"))
        self.poses: list[ps.PoseMessage] = []
        self.checks: list[ps.ValidationMessage] = []
        self.order: list[tuple[str, int]] = []  # ("pose"|"check", frame) as received
        labels = LabelSet(5, _take().labels)
        self.push.send_multipart(zmq_wire.encode_zmq_labels(labels))

    def send(self, fid: int, markers: np.ndarray) -> None:
        self.push.send_multipart(
            zmq_wire.encode_zmq_frame(fid, fid / RATE_HZ, 5, markers)
        )

    def pump(self, timeout_ms: int = 0) -> None:
        while self.sub.poll(timeout_ms):
            timeout_ms = 0
            parts = self.sub.recv_multipart()
            magic = parts[0][:4]
            if magic == ps.DATA_MAGIC:
                msg = ps.decode_pose(parts)
                self.poses.append(msg)
                self.order.append(("pose", msg.frame_id))
            elif magic == ps.VALIDATION_MAGIC:
                check = ps.decode_validation(parts)
                self.checks.append(check)
                self.order.append(("check", check.frame_id))

    def prime(self, markers: np.ndarray) -> int:
        """Frames until the SUB hears the daemon (slow joiner); returns the next id."""
        deadline = time.monotonic() + 10.0
        fid = 0
        while not self.poses:
            assert time.monotonic() < deadline, "pose stream never reached the SUB"
            self.send(fid, markers)
            fid += 1
            self.pump(20)
        return fid


def _frames() -> tuple[np.ndarray, list[int]]:
    """Rows 100-299 of the exact take (float32), every marker 30 cm up +X for rows
    150-152 (a teleport there and back)."""
    take = _take()
    frames = _f32(take.markers_world[100:300]).copy()
    jump = [50, 51, 52]
    frames[jump] += np.float32(0.3) * np.array([1, 0, 0], dtype=np.float32)
    return frames, jump


def test_validation_bits_and_messages_flag_a_teleport(
    start_daemon: Callable[..., Live],
    zmq_socket: Callable[[int], Any],
    exact_calibration: Path,
) -> None:
    live = start_daemon(
        {
            "performer": {"calibration": str(exact_calibration)},
            "loop": {"process_every_frame": True},
            "validate": {"enabled": True, "rate_hz": RATE_HZ, "queue": 64},
        }
    )
    assert live.daemon.validator is not None and live.daemon.validator.running
    assert any(line.startswith("live validator on") for line in live.lines)
    s = Stream(live, zmq_socket)
    frames, jump = _frames()
    fid0 = s.prime(frames[0]) + 1000  # a jump in frame numbers: history restarts
    for i, f in enumerate(frames):
        s.send(fid0 + i, f)
        time.sleep(0.002)  # ~ a live rate: the validator keeps up, nothing dropped
    last = fid0 + len(frames) - 1
    deadline = time.monotonic() + 10.0
    while not any(c.frame_id == last for c in s.checks):
        assert time.monotonic() < deadline, "validation of the last frame never came"
        s.send(last + 1 + len(s.poses), frames[-1])  # later poses carry the results
        s.pump(20)
    checks = {c.frame_id: c for c in s.checks if fid0 <= c.frame_id <= last}
    assert len(checks) == len(frames), "every frame checked (queue 64, paced)"
    assert live.daemon.stats.validation_drops == 0
    # Each check equals a synchronous LiveValidator on the same solve of the same
    # float32 frames (the daemon's pose buffers are float64 of these).
    rig = load_rig(EXACT_RIG)
    solver = BodySolver(rig, load_calibration(exact_calibration), _take().labels)
    oracle = LiveValidator(rig, solver.calibration, rate_hz=RATE_HZ)
    pose = solver.new_pose()
    solver.solve_frame(frames[0].astype(np.float64), pose)  # the priming frames
    flagged = []
    for i, f in enumerate(frames):
        solver.solve_frame(f.astype(np.float64), pose)
        want = oracle.check_frame(
            fid0 + i, 0, pose.root_pos, pose.world_from_bone_quat,
            pose.rest_from_bone_quat, pose.joint_centres,
        )  # fmt: skip
        got = checks[fid0 + i]
        np.testing.assert_allclose(got.values, want.values, rtol=1e-5, atol=1e-4)
        assert got.flags == want.frame_flags, i
        np.testing.assert_array_equal(got.bone_flags, want.bone_flags)
        if got.flags:
            flagged.append(i)
    # The teleport (there and back) is flagged by speed, at its edges, and only there.
    speed = [i for i in flagged if checks[fid0 + i].flags & ps.FRAME_V_SPEED]
    assert speed == [jump[0], jump[-1] + 1], flagged
    for i in speed:
        c = checks[fid0 + i]
        assert c.values[ps.VALIDATION_CHECKS.index("speed")] > 13.0
        assert c.bone_flags.any()
    # Elsewhere only self-penetration: the synthetic motions (rows 197+) bring two
    # lean capsules ~14 mm into each other, as the offline check says too.
    others = {checks[fid0 + i].flags for i in flagged if i not in speed}
    assert others <= {ps.FRAME_V_SELF_PENETRATION}, others
    # In the pose stream a result shows on a LATER frame's pose (the validator runs
    # after the send), and its RTDV message follows that pose: the loop takes the
    # finished results before encoding a pose, ORs in the newest one's bits, sends
    # the pose, then publishes those results. So each pose carries the bits of the
    # last check published before the next pose, from an earlier frame; and every
    # check arrives after the pose of its own frame.
    arrival = {(kind, frame): k for k, (kind, frame) in enumerate(s.order)}
    flags_of = {c.frame_id: c.flags for c in s.checks}
    bits_of = {m.frame_id: m.flags & ps.FRAME_VALIDATION_MASK for m in s.poses}
    expect, pending, compared = 0, None, 0
    for kind, frame in [*s.order, ("pose", None)]:
        if kind == "check":
            assert pending is None or frame < pending, (frame, pending)
            expect = flags_of[frame]
            continue
        if pending is not None:
            assert bits_of[pending] == expect, (pending, bits_of[pending], expect)
            compared += 1
        pending = frame
    assert compared == len(s.poses)
    for c in s.checks:
        if ("pose", c.frame_id) in arrival:
            assert arrival[("check", c.frame_id)] > arrival[("pose", c.frame_id)]
    shown = [p for p in s.poses if p.flags & ps.FRAME_V_SPEED]
    assert shown and all(p.frame_id > fid0 + jump[0] for p in shown)
    status = live.ctl({"cmd": "status"})["status"]
    v = status["validate"]
    assert v["running"] and v["thresholds"]["root_speed_m_s"] == 13.0
    assert v["flagged"]["speed"] >= 2
    c = status["counters"]
    assert c["validated"] >= len(frames) and c["validation_flagged"] >= 2
    assert "validated" in live.daemon.stats_line()


def test_validator_queue_full_drops_never_blocks(
    start_daemon: Callable[..., Live],
    zmq_socket: Callable[[int], Any],
    exact_calibration: Path,
) -> None:
    """A queue of one and a burst as fast as ZeroMQ delivers: every frame is solved
    and sent; what the validator had no room for is dropped and counted."""
    live = start_daemon(
        {
            "performer": {"calibration": str(exact_calibration)},
            "loop": {"process_every_frame": True},
            "validate": {"enabled": True, "rate_hz": RATE_HZ, "queue": 1},
        }
    )
    s = Stream(live, zmq_socket)
    frames, _ = _frames()
    fid0 = s.prime(frames[0])
    n0 = live.daemon.stats.frames_out
    for i in range(3):
        for j, f in enumerate(frames):
            s.send(fid0 + i * len(frames) + j, f)
    n = 3 * len(frames)
    _wait_until(lambda: live.daemon.stats.frames_out >= n0 + n, "every frame sent")
    st = live.daemon.stats
    assert st.validation_drops > 0
    v = live.daemon.validator
    assert v is not None
    assert v.submitted + v.dropped == st.frames_out
    assert st.validation_drops == v.dropped
