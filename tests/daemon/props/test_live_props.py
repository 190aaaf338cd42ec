"""Props in the live daemon (``daemon/live/props.py``): a camera rig streamed over OSC
beside a performer's markers, received as VMC (parsed with python-osc and read by the
VMC spec's own words, not with our encoder) and as ``RTDR`` messages on the pose
stream; its field of view set live by an OSC fader; ``ctl calibrate --prop``.
"""

from __future__ import annotations

import math
import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zmq
from pythonosc.osc_bundle import OscBundle
from pythonosc.osc_message import OscMessage
from scipy.spatial.transform import Rotation

from retargetd.daemon.cli.main import main
from retargetd.daemon.props.layout import calibrate_prop, load_layout
from retargetd.protocols import osc_in, pose_props
from retargetd.protocols.marker_input import LabelSet
from retargetd.protocols.osc_wire import build_message

CAMERA = np.array(
    [
        [0.00, 0.00, 0.00],
        [0.16, 0.02, 0.00],
        [-0.12, 0.05, 0.03],
        [0.02, 0.21, 0.06],
        [0.05, -0.04, 0.14],
    ]
)
LABELS = ("cam:0", "cam:1", "cam:2", "cam:3", "cam:4", "other")
WAIT_S = 20.0


def _vmc_messages(sock: socket.socket, until: float) -> list[tuple[str, list[Any]]]:
    """Every OSC message received before ``until`` (bundles opened: python-osc's
    parser, independent of ours)."""
    out: list[tuple[str, list[Any]]] = []
    while time.monotonic() < until:
        try:
            data = sock.recv(65536)
        except TimeoutError:
            continue
        if OscBundle.dgram_is_bundle(data):
            for item in OscBundle(data):
                if isinstance(item, OscMessage):
                    out.append((item.address, list(item.params)))
        else:
            m = OscMessage(data)
            out.append((m.address, list(m.params)))
        if any(a == "/VMC/Ext/Cam" for a, _ in out):
            break
    return out


def _world_from_unity_pos(p: list[float]) -> np.ndarray:
    # VMC poses are Unity's: left-handed, +Y up, metres. The lab's (x, y, z) with +Z
    # up is Unity's (x, z, y) (shared/reference/engines.md, "Coordinate systems").
    return np.array([p[0], p[2], p[1]])


def _unity_forward_in_world(q_xyzw: list[float]) -> np.ndarray:
    # Unity's camera looks along its local +Z; rotate it by the received quaternion
    # (x y z w, Unity's frame) with the plain quaternion-to-matrix formula, then
    # read the Unity vector in the lab's axes.
    x, y, z, w = q_xyzw
    fwd = np.array([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)])
    return _world_from_unity_pos(list(fwd))


@pytest.fixture
def camera_layout(tmp_path: Path) -> Path:
    still = np.repeat(CAMERA[None] + [0.0, 0.0, 1.5], 5, 0)
    layout = calibrate_prop(still, LABELS[:5], name="cam", kind="camera", rate_hz=100.0)
    path = tmp_path / "cam.json"
    layout.save(path)
    return path


def test_camera_streams_as_vmc_and_pose_stream(
    start_daemon: Callable[..., Any],
    udp_socket: Callable[..., socket.socket],
    camera_layout: Path,
) -> None:
    vmc = udp_socket(bind=True, timeout_s=0.05)
    live = start_daemon(
        {
            "prop": [
                {
                    "name": "cam",
                    "kind": "camera",
                    "calibration": str(camera_layout),
                    "fov_deg": 50.0,
                    "fov_osc": "/lens/fov",
                }
            ]
        },
        vmc_port=vmc.getsockname()[1],
    )
    ctx = zmq.Context.instance()
    sub = ctx.socket(zmq.SUB)
    sub.setsockopt(zmq.LINGER, 0)
    sub.setsockopt(zmq.SUBSCRIBE, pose_props.PROP_MAGIC)
    sub.connect(live.tcp("zmq poses"))
    src = udp_socket()
    osc = live.udp("osc markers")
    label_set = LabelSet(7, LABELS)
    # The camera yawed +90 deg about world +Z and 1.5 m up: at calibration it
    # looked along world +Y, so now along world -X.
    turn = Rotation.from_euler("z", 90, degrees=True)
    origin = np.array([0.3, -0.2, 1.6])
    centred = CAMERA - CAMERA.mean(axis=0)
    markers = np.vstack([turn.apply(centred) + origin, [[9.0, 9.0, 9.0]]])
    fid = 0
    msgs: list[tuple[str, list[Any]]] = []
    got = None
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline and (got is None or not msgs):
        src.sendto(osc_in.encode_labels(label_set), osc)
        src.sendto(osc_in.encode_compact_frame(fid, fid / 120, 7, markers), osc)
        fid += 1
        if not msgs:
            msgs = [
                m
                for m in _vmc_messages(vmc, time.monotonic() + 0.1)
                if m[0] in ("/VMC/Ext/Tra/Pos", "/VMC/Ext/Cam")
            ]
        if got is None and sub.poll(50):
            got = pose_props.decode_prop(sub.recv())
    assert got is not None and msgs, "no prop message or no VMC prop datagram"
    # the pose stream: the prop message, world frame, w x y z
    assert got.name == "cam" and got.kind == pose_props.KIND_CAMERA
    assert got.flags == 0 and got.used == 5 and got.seen == 5
    np.testing.assert_allclose(got.pos_world, origin, atol=1e-5)
    q = Rotation.from_quat(got.world_from_prop_quat, scalar_first=True)
    assert np.degrees((q * turn.inv()).magnitude()) < 0.01
    assert got.fov_deg == pytest.approx(50.0)
    # VMC, by the spec: /VMC/Ext/Tra/Pos s fff ffff and /VMC/Ext/Cam s fff ffff f
    tra = next(args for addr, args in msgs if addr == "/VMC/Ext/Tra/Pos")
    cam = next(args for addr, args in msgs if addr == "/VMC/Ext/Cam")
    assert (
        tra[0] == "cam" and len(tra) == 8 and all(isinstance(v, float) for v in tra[1:])
    )
    assert cam[0] == "cam" and len(cam) == 9
    np.testing.assert_allclose(_world_from_unity_pos(cam[1:4]), origin, atol=1e-5)
    # hand-worked: +90 deg about world +Z is -90 deg about Unity +Y:
    # x y z w = (0, -sin 45, 0, cos 45), and Unity's forward turns to world -X
    s = math.sqrt(0.5)
    np.testing.assert_allclose(cam[4:8], [0.0, -s, 0.0, s], atol=1e-5)
    np.testing.assert_allclose(_unity_forward_in_world(cam[4:8]), [-1, 0, 0], atol=1e-5)
    assert cam[8] == pytest.approx(50.0)
    np.testing.assert_allclose(tra[1:8], cam[1:8], atol=0)
    # a lens fader on the show-control port moves the field of view
    show = live.udp("show control")
    src.sendto(build_message("/lens/fov", "f", [35.0]), show)
    src.sendto(build_message("/lens/fov", "f", [500.0]), show)  # refused, counted
    fov = None
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline and fov != pytest.approx(35.0):
        src.sendto(osc_in.encode_compact_frame(fid, fid / 120, 7, markers), osc)
        fid += 1
        for addr, args in _vmc_messages(vmc, time.monotonic() + 0.05):
            if addr == "/VMC/Ext/Cam":
                fov = args[8]
    assert fov == pytest.approx(35.0)
    status = live.ctl({"cmd": "status"})["status"]
    (doc,) = status["props"]
    assert doc["name"] == "cam" and doc["frames"] > 0 and doc["fov_deg"] == 35.0
    assert status["show_control"]["refused"].get("bad_argument", 0) >= 1
    sub.close()


def test_ctl_calibrate_prop_live(
    start_daemon: Callable[..., Any],
    udp_socket: Callable[..., socket.socket],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    out = tmp_path / "cam.json"
    live = start_daemon(
        {
            "prop": [
                {"name": "cam", "save_calibration": str(out), "calibrate_frames": 10}
            ]
        }
    )
    reply = live.ctl({"cmd": "calibrate", "prop": "nope"})
    assert reply["ok"] is False and "no prop named 'nope'" in reply["error"]
    src = udp_socket()
    osc = live.udp("osc markers")
    label_set = LabelSet(3, LABELS)
    markers = np.vstack([CAMERA + np.array([1.0, 2.0, 0.9]), [[9.0, 9.0, 9.0]]])
    rng = np.random.default_rng(0)
    stop = threading.Event()

    def stream() -> None:  # the prop lies still, markers jittering by 0.2 mm
        fid = 0
        while not stop.is_set():
            src.sendto(osc_in.encode_labels(label_set), osc)
            noisy = markers + rng.normal(0.0, 2e-4, markers.shape)
            src.sendto(osc_in.encode_compact_frame(fid, fid / 120, 3, noisy), osc)
            fid += 1
            time.sleep(1 / 120)

    sender = threading.Thread(target=stream, daemon=True)
    sender.start()
    try:
        ep = live.tcp("control")
        assert main(["ctl", "--endpoint", ep, "calibrate", "--prop", "cam"]) == 0
    finally:
        stop.set()
        sender.join(timeout=5)
    said = capsys.readouterr().out
    assert "prop cam: calibrating on the next 10 frames (ctl)" in said
    assert "prop cam: calibrated on 10 frames, 5 markers, saved to" in said
    layout = load_layout(out)
    assert layout.labels == LABELS[:5]
    np.testing.assert_allclose(
        layout.layout_prop_m, CAMERA - CAMERA.mean(axis=0), atol=1e-3
    )
    (doc,) = live.ctl({"cmd": "status"})["status"]["props"]
    assert doc["calibration"] == "calibrated"
    assert main(["ctl", "--endpoint", ep, "calibrate", "--prop", "cam", "--rom"]) == 2


def test_recordings_carry_props_and_replay_solves_them_again(
    start_daemon: Callable[..., Any],
    udp_socket: Callable[..., socket.socket],
    camera_layout: Path,
    tmp_path: Path,
) -> None:
    # A recording holds the prop's markers as received (/markers/raw) and its RTDR
    # messages (/poses); read back as a take and solved offline, it gives the poses
    # the daemon sent, frame for frame.
    from retargetd.daemon.cli.prop_io import load_prop_take
    from retargetd.daemon.props.solve import solve_take
    from retargetd.replay import recording as rf

    live = start_daemon(
        {
            "prop": [
                {"name": "cam", "kind": "camera", "calibration": str(camera_layout)}
            ],
            "record": {"folder": str(tmp_path)},
        }
    )
    src = udp_socket()
    osc = live.udp("osc markers")
    label_set = LabelSet(5, LABELS)
    src.sendto(osc_in.encode_labels(label_set), osc)
    rec_path = tmp_path / "props.mcap"
    reply = live.ctl({"cmd": "record", "action": "start", "path": str(rec_path)})
    assert reply["ok"], reply
    rng = np.random.default_rng(1)
    centred = CAMERA - CAMERA.mean(axis=0)
    turns = Rotation.from_rotvec(rng.normal(0.0, 0.5, (60, 3)))
    for fid in range(60):
        pos = np.array([0.01 * fid, 0.0, 1.5])
        markers = np.vstack([turns[fid].apply(centred) + pos, [[9.0, 9.0, 9.0]]])
        markers += rng.normal(0.0, 5e-4, markers.shape)
        src.sendto(osc_in.encode_compact_frame(fid, fid / 120, 5, markers), osc)
        time.sleep(0.004)
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        (doc,) = live.ctl({"cmd": "status"})["status"]["props"]
        if doc["frames"] >= 60:
            break
        time.sleep(0.02)
    assert live.ctl({"cmd": "record", "action": "stop"})["ok"]
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        rec_status = live.ctl({"cmd": "status"})["status"]["record"]
        if not rec_status["active"] and not rec_status["finishing"]:
            break
        time.sleep(0.02)
    rec = rf.read_recording(rec_path)
    assert rec.complete
    sent = [
        pose_props.decode_prop(p.parts[0])
        for p in rec.packets(rf.POSES_TOPIC)
        if p.parts[0][:4] == pose_props.PROP_MAGIC
    ]
    assert [m.frame_id for m in sent] == list(range(60))
    for m in sent:
        q = Rotation.from_quat(m.world_from_prop_quat, scalar_first=True)
        assert np.degrees((q * turns[m.frame_id].inv()).magnitude()) < 0.5
    take, labels, _ = load_prop_take(str(rec_path), LABELS[:5], "cam:")
    assert take.n_frames == 60
    track = solve_take(load_layout(camera_layout), labels, take.positions, take.valid)
    wire = np.array([m.world_from_prop_quat for m in sent])
    np.testing.assert_allclose(track.world_from_prop_quat, wire, atol=2e-7)
    np.testing.assert_allclose(
        track.prop_pos_world, np.array([m.pos_world for m in sent]), atol=2e-7
    )


def test_console_draws_the_prop(
    start_daemon: Callable[..., Any],
    udp_socket: Callable[..., socket.socket],
    camera_layout: Path,
) -> None:
    # The browser console's scene holds an axes frame per prop at its pose (the
    # viser handle the page renders; no browser needed to read it).
    live = start_daemon(
        {
            "prop": [
                {"name": "cam", "kind": "camera", "calibration": str(camera_layout)}
            ],
            "console": {"enabled": True, "port": 0},
        }
    )
    feed = live.daemon.console
    assert feed is not None and feed.console is not None
    src = udp_socket()
    osc = live.udp("osc markers")
    label_set = LabelSet(9, LABELS)
    turn = Rotation.from_euler("x", 30, degrees=True)
    origin = np.array([-0.4, 0.7, 1.2])
    markers = np.vstack(
        [turn.apply(CAMERA - CAMERA.mean(axis=0)) + origin, [[9.0, 9.0, 9.0]]]
    )
    deadline = time.monotonic() + WAIT_S
    fid = 0
    handle = None
    while time.monotonic() < deadline:
        src.sendto(osc_in.encode_labels(label_set), osc)
        src.sendto(osc_in.encode_compact_frame(fid, fid / 120, 9, markers), osc)
        fid += 1
        time.sleep(0.01)
        handle = feed.console._props.get("cam")
        if handle is not None and np.allclose(handle.position, origin, atol=1e-4):
            break
    assert handle is not None and handle.visible
    np.testing.assert_allclose(handle.position, origin, atol=1e-4)
    drawn = Rotation.from_quat(np.asarray(handle.wxyz), scalar_first=True)
    assert np.degrees((drawn * turn.inv()).magnitude()) < 0.05


def test_replay_of_a_recording_streams_the_same_props(
    start_daemon: Callable[..., Any],
    udp_socket: Callable[..., socket.socket],
    camera_layout: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    # ``retargetd replay`` sends a recording's marker packets as they came: a daemon
    # with the same [[prop]] sends the same RTDR poses the recorded one did.
    from retargetd.replay import recording as rf

    prop = {"name": "cam", "kind": "camera", "calibration": str(camera_layout)}
    first = start_daemon({"prop": [prop], "record": {"folder": str(tmp_path)}})
    src = udp_socket()
    osc = first.udp("osc markers")
    src.sendto(osc_in.encode_labels(LabelSet(5, LABELS)), osc)
    rec_path = tmp_path / "r.mcap"
    assert first.ctl({"cmd": "record", "action": "start", "path": str(rec_path)})["ok"]
    rng = np.random.default_rng(2)
    centred = CAMERA - CAMERA.mean(axis=0)
    turns = Rotation.from_rotvec(rng.normal(0.0, 0.5, (40, 3)))
    for fid in range(40):
        up = np.array([0.0, 0.0, 1.5])
        markers = np.vstack([turns[fid].apply(centred) + up, [[9, 9, 9.0]]])
        src.sendto(osc_in.encode_compact_frame(fid, fid / 120, 5, markers), osc)
        time.sleep(0.004)
    deadline = time.monotonic() + WAIT_S
    while first.ctl({"cmd": "status"})["status"]["props"][0]["frames"] < 40:
        assert time.monotonic() < deadline
        time.sleep(0.02)
    assert first.ctl({"cmd": "record", "action": "stop"})["ok"]
    while (
        first.ctl({"cmd": "status"})["status"]["record"]["active"]
        or (first.ctl({"cmd": "status"})["status"]["record"]["finishing"])
    ):
        assert time.monotonic() < deadline
        time.sleep(0.02)
    recorded = [
        pose_props.decode_prop(p.parts[0])
        for p in rf.read_recording(rec_path).packets(rf.POSES_TOPIC)
        if p.parts[0][:4] == pose_props.PROP_MAGIC
    ]
    assert len(recorded) == 40
    second = start_daemon({"prop": [prop]})
    sub = zmq.Context.instance().socket(zmq.SUB)
    sub.setsockopt(zmq.LINGER, 0)
    sub.setsockopt(zmq.SUBSCRIBE, pose_props.PROP_MAGIC)
    osc2 = second.udp("osc markers")
    # past ZeroMQ's slow joiner: the handshake done, the subscription on its way
    monitor = sub.get_monitor_socket(zmq.EVENT_HANDSHAKE_SUCCEEDED)
    sub.connect(second.tcp("zmq poses"))
    assert monitor.poll(int(WAIT_S * 1000)), "no handshake with the pose stream"
    sub.disable_monitor()
    monitor.close()
    time.sleep(0.2)
    to = f"osc://{osc2[0]}:{osc2[1]}"
    assert main(["replay", str(rec_path), "--to", to]) == 0
    capsys.readouterr()
    replayed = []
    while len(replayed) < 40 and sub.poll(int(WAIT_S * 1000)):
        replayed.append(pose_props.decode_prop(sub.recv()))
    sub.close()
    assert [m.frame_id for m in replayed] == [m.frame_id for m in recorded]
    for live, again in zip(recorded, replayed, strict=True):
        np.testing.assert_array_equal(
            again.world_from_prop_quat, live.world_from_prop_quat
        )
        np.testing.assert_array_equal(again.pos_world, live.pos_world)
        assert again.flags == live.flags and again.used == live.used
