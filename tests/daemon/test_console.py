"""Console plumbing without a browser: the snapshot slot never blocks its writer and
never hands out a torn snapshot, the command queue is bounded, the skeleton program
places every bone of the shipped rigs, the offline viewer plays a real solve."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from retargetd.daemon.body.calibration import calibrate
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.body.solve import BodySolver
from retargetd.daemon.cli.main import main
from retargetd.daemon.console import (
    CommandQueue,
    ConsoleLayout,
    SkeletonProgram,
    Snapshot,
    SnapshotSlot,
    bone_endpoints,
)
from retargetd.daemon.synth.performer import synthesize


def _layout(m: int = 5, j: int = 4) -> ConsoleLayout:
    pairs = [(i, i + 1) for i in range(j - 1)]
    return ConsoleLayout(
        marker_names=tuple(f"M{i}" for i in range(m)),
        joint_names=tuple(f"J{i}" for i in range(j)),
        bone_names=tuple(f"B{i}" for i in range(j - 1)),
        bone_parents=np.arange(-1, j - 2, dtype=np.int64),
        skeleton=SkeletonProgram.from_joint_pairs(pairs),
        bone_lengths=np.full(j - 1, np.nan),
        stage_names=("decode", "solve"),
    )


def _fill(s: Snapshot, value: float) -> None:
    s.frame = int(value)
    s.t_s = value
    s.marker_pos[:] = value
    s.joint_pos[:] = value
    s.latency_p50_ms[:] = value
    s.latency_p99_ms[:] = value


def test_commit_returns_at_once_while_the_reader_holds_the_slot() -> None:
    slot = SnapshotSlot(_layout())
    held, release = threading.Event(), threading.Event()

    def reader() -> None:
        with slot._lock:  # what read() holds while it copies
            held.set()
            release.wait(10)

    th = threading.Thread(target=reader)
    th.start()
    try:
        assert held.wait(10)
        _fill(slot.begin(), 7.0)
        assert slot.commit() is False  # returned, without waiting for the reader
        assert slot.skipped == 1 and slot.seq == 0
    finally:
        release.set()
        th.join(10)
    back = slot.begin()
    assert back.frame == 7  # the skipped contents are still in the back buffer
    assert slot.commit() is True and slot.seq == 1
    out = Snapshot.for_layout(slot.layout)
    assert slot.read(out, 0) == 1 and out.frame == 7
    assert slot.read(out, 1) == 1  # nothing newer


def test_reads_are_never_torn_and_buffers_are_reused() -> None:
    slot = SnapshotSlot(_layout(m=200, j=60))
    bufs = {id(slot.begin())}
    arrays = {id(slot.begin().marker_pos)}
    stop = threading.Event()
    torn: list[int] = []
    reads = [0]

    def reader() -> None:
        out = Snapshot.for_layout(slot.layout)
        seq = 0
        while not stop.is_set():
            got = slot.read(out, seq)
            if got != seq:
                seq = got
                reads[0] += 1
                v = out.t_s
                same = [out.marker_pos, out.joint_pos, out.latency_p99_ms]
                if out.frame != int(v) or any((a != v).any() for a in same):
                    torn.append(seq)

    th = threading.Thread(target=reader)
    th.start()
    i = 0
    t_end = time.monotonic() + 1.0
    while time.monotonic() < t_end:
        i += 1
        s = slot.begin()
        bufs.add(id(s))
        arrays.add(id(s.marker_pos))
        _fill(s, float(i))
        slot.commit()
    stop.set()
    th.join(10)
    assert reads[0] > 10, "the reader saw too few snapshots to mean anything"
    assert not torn, f"torn snapshots at seq {torn[:5]}"
    assert len(bufs) == 2 and len(arrays) == 2  # two preallocated buffers, reused
    assert slot.seq + slot.skipped == i


def test_due_paces_publishing() -> None:
    slot = SnapshotSlot(_layout(), publish_hz=30.0)
    # 2 s of a 120 Hz loop (synthetic clock): 60 publishes, evenly every 4th frame.
    due = [slot.due(int(k * 1e9 / 120)) for k in range(240)]
    assert sum(due) == 60
    assert set(np.diff(np.flatnonzero(due))) == {4}


def test_layout_change_is_seen_by_the_reader() -> None:
    slot = SnapshotSlot(_layout())
    out = Snapshot.for_layout(slot.layout)
    slot.set_layout(_layout(m=9))
    assert slot.read(out, 0) == -1  # the reader must reallocate
    out = Snapshot.for_layout(slot.layout, slot.layout_id)
    _fill(slot.begin(), 3.0)
    slot.commit()
    assert slot.read(out, -1) == slot.seq and out.marker_pos.shape == (9, 3)


def test_command_queue_is_bounded_and_ordered() -> None:
    q = CommandQueue(maxsize=3)
    assert q.poll() is None
    assert q.put("calibrate") and q.put("record_start", "a.mcap") and q.put("reload")
    assert q.put("face_capture") is False and q.dropped == 1
    with pytest.raises(ValueError, match="unknown command"):
        q.put("format_disk")
    first = q.poll()
    assert first is not None and first.kind == "calibrate" and first.t_ns > 0
    assert [(c.kind, c.arg) for c in q.drain()] == [
        ("record_start", "a.mcap"),
        ("reload", ""),
    ]


@pytest.mark.parametrize("rig_name", ["plug-in-gait", "menache"])
def test_skeleton_program_places_every_bone_of_a_solve(rig_name: str) -> None:
    take = synthesize(seconds=2.0, rate_hz=60.0, markerset=rig_name, seed=2)
    rig = load_rig(rig_name)
    cal = calibrate(rig, take.markers_world[:60], take.labels)
    res = BodySolver(rig, cal, take.labels).solve_take(take.markers_world)
    program = SkeletonProgram.from_rig(rig, res.joint_names)
    ends = bone_endpoints(
        program, res.joint_centres, res.world_from_bone_quat, res.root_pos,
        res.bone_lengths,
    )  # fmt: skip
    assert ends.shape == (take.n_frames, len(rig.bones), 2, 3)
    assert np.isfinite(ends).all(), "some bone end was not placed"
    np.testing.assert_array_equal(ends[:, 0, 0], res.root_pos)
    jindex = {n: i for i, n in enumerate(res.joint_names)}
    joint_of_point = {p: j for j, p in rig.joints.items()}
    uses: dict[str, int] = {}
    for bone in rig.bones:
        for point in (bone.origin, bone.aim):
            uses[point] = uses.get(point, 0) + 1
    placed_alone = [0]
    for b, bone in enumerate(rig.bones):
        for k, point in enumerate((bone.origin, bone.aim)):
            if point in joint_of_point:
                np.testing.assert_array_equal(
                    ends[:, b, k], res.joint_centres[:, jindex[joint_of_point[point]]]
                )
        # An end no joint names and no other bone touches is placed through this
        # bone alone: exactly its calibrated length from the other end.
        for point in (bone.origin, bone.aim):
            if point not in joint_of_point and uses[point] == 1:
                length = np.linalg.norm(ends[:, b, 1] - ends[:, b, 0], axis=-1)
                np.testing.assert_allclose(length, res.bone_lengths[b], rtol=1e-9)
                placed_alone[0] += 1
    assert placed_alone[0] >= 3
    # One frame at a time gives the same as the whole take.
    one = bone_endpoints(
        program, res.joint_centres[30], res.world_from_bone_quat[30],
        res.root_pos[30], res.bone_lengths,
    )  # fmt: skip
    np.testing.assert_array_equal(one, ends[30])


@pytest.fixture(scope="module")
def solved(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    d = tmp_path_factory.mktemp("view")
    take, npz = d / "s.c3d", d / "s.npz"
    assert main(["synth", "--seconds", "3", "--rate", "60", "--out", str(take)]) == 0
    args = ["solve", str(take), "--rig", "menache", "--calibrate-frames", "0:60"]
    assert main([*args, "--out", str(npz)]) == 0
    return take, npz


def test_offline_viewer_scrubs_plays_and_loops(solved: tuple[Path, Path]) -> None:
    from retargetd.daemon.console.offline import load_sequence, serve_offline

    take, npz = solved
    seq = load_sequence(npz, take=take, flagged_frames=[10, 11, 12, 50])
    with np.load(npz, allow_pickle=False) as z:
        joints = z["joint_centres"]
    n = joints.shape[0]
    assert seq.n_frames == n and seq.marker_pos.shape[0] == n
    assert seq.flagged_frames == (10, 11, 12, 50)
    viewer = serve_offline(npz, take=take, port=0, block=False)
    try:
        out = Snapshot.for_layout(viewer.slot.layout)

        def shown(timeout_s: float = 10.0, want: int | None = None) -> int:
            seq_no, t_end = 0, time.monotonic() + timeout_s
            while time.monotonic() < t_end:
                seq_no = viewer.slot.read(out, 0)
                if seq_no > 0 and (want is None or out.frame == want):
                    return out.frame
                time.sleep(0.02)
            return out.frame

        viewer.frame.value = 42  # scrub
        assert shown(want=42) == 42
        np.testing.assert_array_equal(out.joint_pos, joints[42])
        viewer.speed.value = "2"
        viewer.play.value = True
        time.sleep(0.5)
        f1 = shown()
        assert f1 > 42  # playing
        viewer.frame.value = n - 3  # near the end: loops back to the start
        time.sleep(0.6)
        assert shown() < n - 3
        assert viewer.play.value is True
    finally:
        viewer.stop()


def test_solve_as_foxglove_mcap(solved: tuple[Path, Path], tmp_path: Path) -> None:
    from retargetd.daemon.console.export import solve_bone_ends, write_solve_foxglove
    from retargetd.replay import foxglove as fg
    from retargetd.replay.takes import load_take

    take_path, npz = solved
    take = load_take(take_path)
    rig = load_rig("menache")
    out = tmp_path / "s.mcap"
    with np.load(npz, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    n = write_solve_foxglove(
        out, arrays, rig, markers=take.positions, marker_valid=take.valid
    )
    ends = solve_bone_ends(arrays, rig)
    with open(out, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        lines = [
            msg.entities[0].lines[0]
            for _, _, _, msg in reader.iter_decoded_messages(topics=[fg.SCENE_TOPIC])
        ]
    assert len(lines) == n == take.n_frames
    got = np.array([[p.x, p.y, p.z] for p in lines[100].points]).reshape(-1, 2, 3)
    ok = np.isfinite(ends[100]).all(axis=(1, 2))
    np.testing.assert_allclose(got, ends[100][ok], atol=1e-9)
    assert len(got) == len(rig.bones)  # every bone drawn


def test_offline_viewer_shows_a_take_alone(solved: tuple[Path, Path]) -> None:
    from retargetd.daemon.console.offline import serve_offline
    from retargetd.replay.takes import load_take

    take_path, _ = solved
    take = load_take(take_path)
    viewer = serve_offline(take_path, port=0, block=False)
    try:
        assert viewer.seq.layout.joint_names == ()
        out = Snapshot.for_layout(viewer.slot.layout)

        def drawn(n: int) -> int:  # the page's render thread drew n snapshots
            t_end = time.monotonic() + 10
            while viewer.console.frames_drawn < n and time.monotonic() < t_end:
                time.sleep(0.02)
            return viewer.console.frames_drawn

        assert drawn(1) == 1  # frame 0
        viewer.frame.value = 17
        t_end = time.monotonic() + 10
        while time.monotonic() < t_end:
            if viewer.slot.read(out, 0) > 0 and out.frame == 17:
                break
            time.sleep(0.02)
        assert out.frame == 17
        np.testing.assert_array_equal(out.marker_pos, take.positions[17])
        assert drawn(2) == 2
    finally:
        viewer.stop()


def test_humanoid_posed_on_the_console_thread_matches_the_target() -> None:
    """The console's forward kinematics of the retargeted humanoid equals the
    target's own (``target.retarget.joint_positions_world``) on a real solve."""
    from retargetd.daemon.console.snapshot import humanoid_positions
    from retargetd.daemon.live.console_feed import _layout
    from retargetd.daemon.retarget.retarget import Retargeter, joint_positions_world
    from retargetd.daemon.retarget.skeleton import default_humanoid

    take = synthesize(seconds=2.0, rate_hz=60.0, seed=1)
    rig = load_rig("menache")
    hold = take.base_pose_frames
    cal = calibrate(rig, take.markers_world[hold], take.labels)
    solver = BodySolver(rig, cal, take.labels)
    target = default_humanoid()
    rt = Retargeter(rig, cal, target)
    layout = _layout(rig, solver, take.labels, (), target)
    assert len(layout.humanoid_pairs) == len(target.bone_names) - 1
    # Drawn 2 m to the right of where the performer stood at calibration (left =
    # RHIP -> LHIP in the base pose; the humanoid's root is the displacement since).
    hips = take.markers_world[
        hold.start, [take.labels.index("LHIP"), take.labels.index("RHIP")]
    ]
    left = hips[0] - hips[1]
    left[2] = 0.0
    left /= np.linalg.norm(left)
    at = np.array([*cal.root_rest_pos[:2], 0.0])
    np.testing.assert_allclose(layout.humanoid_offset_m, at - 2.0 * left, atol=0.02)
    pose, tp = solver.new_pose(), rt.new_pose()
    out = np.zeros((len(target.bone_names), 3))
    moved = 0.0
    for f in (hold.stop + 10, take.n_frames - 1):
        solver.solve_frame(np.array(take.markers_world[f]), pose)  # writable, as live
        rt.apply(pose, tp)
        want = joint_positions_world(target, tp)
        got = humanoid_positions(layout, tp.world_from_bone_quat, tp.hips_pos, out)
        assert got is out
        np.testing.assert_allclose(got, want, atol=1e-12)
        rest = humanoid_positions(
            layout, layout.humanoid_rest_quat, tp.hips_pos, np.zeros_like(out)
        )
        moved = max(moved, float(np.abs(got - rest).max()))
    assert moved > 0.05  # the performer moved the humanoid off its rest pose
