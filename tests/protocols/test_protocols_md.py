"""PROTOCOLS.md cannot rot: its hex examples equal the encoders' bytes, and its
senders, run as written (only the port changed), are decoded by our decoders."""

from __future__ import annotations

import math
import re
import socket
from pathlib import Path

import numpy as np
import pytest
import zmq

from retargetd.protocols import marker_input as mi
from retargetd.protocols import osc_auth, osc_in, pose_stream, zmq_wire
from retargetd.protocols.osc_wire import build_message

DOC = (Path(__file__).resolve().parents[2] / "protocols" / "PROTOCOLS.md").read_text()
NAN = float("nan")
LABELS = mi.LabelSet(3, ("LASI", "RASI"))
POS = np.array([[1.0, 2.0, 3.0], [NAN, NAN, NAN]])


def _block(kind: str, name: str) -> str:
    match = re.search(rf"<!-- {kind}: {name} -->\n```[a-z]*\n(.*?)```", DOC, re.DOTALL)
    assert match, f"no {kind} block {name!r} in PROTOCOLS.md"
    return match.group(1)


def _hex(name: str) -> bytes:
    data = bytearray()
    for line in _block("hex", name).splitlines():
        data += bytes.fromhex(line[6:].split("|")[0])
    return bytes(data)


def _pose_parts(performer: int = 0) -> list[bytes]:
    # PROTOCOLS.md's worked example: the root (Hips) yawed +90 deg about world +Z,
    # its child (Spine) bent +90 deg about its parent's x: world_from_spine =
    # world_from_hips * hips_from_spine. The calibration had the Spine already bent
    # so, so its rest_from_bone is the identity while its parent_from_bone is the bend.
    c = s = math.sqrt(0.5)
    wfb = np.array([[c, 0.0, 0.0, s], [0.5, 0.5, 0.5, 0.5]])
    pfb = np.array([[c, 0.0, 0.0, s], [c, s, 0.0, 0.0]])
    rfb = np.array([[c, 0.0, 0.0, s], [1.0, 0.0, 0.0, 0.0]])
    enc = pose_stream.PoseEncoder(2, 1, performer=performer)
    parts = enc.encode(
        7, 0.5, 1000, 2000, pose_stream.FRAME_HELD, np.array([0.0, 0.0, 1.0]),
        wfb, pfb, rfb, np.array([0.5]),
        np.array([0, pose_stream.BONE_HELD], dtype=np.uint8),
    )  # fmt: skip
    pose_stream.stamp_sent(parts[0], 3000)
    return [bytes(p) for p in parts]


def _face_part() -> bytes:
    enc = pose_stream.PoseEncoder(1, 1, n_face_markers=2)
    nan3 = [np.nan] * 3
    enc.encode_face(
        pose_stream.FACE_PARTIAL, np.array([1.0, 0, 0, 0]), np.array([0, 0, 1.5]),
        np.array([[0.0, 0.1, 0.0], nan3]),
    )  # fmt: skip
    return bytes(enc.parts[2])


def _validation_parts() -> list[bytes]:
    values = np.array([0, 1.5, 0, 12.5, 0, 0, 0, 0.0])
    bones = np.array([pose_stream.BONE_V_LIMIT], dtype=np.uint8)
    return pose_stream.encode_validation(
        0, 7, 1000, 5000, pose_stream.FRAME_V_LIMITS, values, bones
    )


def test_hex_examples_match_the_encoders() -> None:
    zmq_frame = zmq_wire.encode_zmq_frame(7, 0.5, 3, POS)
    zmq_labels = zmq_wire.encode_zmq_labels(LABELS)
    expected = {
        "osc_compact": osc_in.encode_compact_frame(7, 0.5, 3, POS),
        "osc_labels": osc_in.encode_labels(LABELS),
        "osc_simple": osc_in.encode_simple_bundle(LABELS.labels, POS, 7),
        "zmq_frame_header": zmq_frame[0],
        "zmq_frame_payload": zmq_frame[1],
        "zmq_labels_header": zmq_labels[0],
        "zmq_labels_payload": zmq_labels[1],
        "vmc_bone": build_message(
            "/VMC/Ext/Bone/Pos", ",sfffffff", ["Spine", 0.0, 0.1, 0, 0, 0, 0, 1.0]
        ),
        "pose_header": _pose_parts()[0],
        "pose_body": _pose_parts()[1],
        "pose_header_performer": _pose_parts(performer=1)[0],
        "pose_face": _face_part(),
        "shape_state": bytes(
            pose_stream.ShapeStateEncoder(3).encode(
                7,
                np.array(
                    [0, pose_stream.SHAPE_UNOBSERVED, pose_stream.SHAPE_HIDDEN],
                    dtype=np.uint8,
                ),
            )
        ),
        "validation_header": _validation_parts()[0],
        "validation_body": _validation_parts()[1],
        "osc_signed_trailer": osc_auth.sign_datagram(
            bytes(range(32)),
            osc_in.encode_compact_frame(7, 0.5, 3, POS),
            1_750_000_000_000_000,
            41,
        )[-osc_auth.TRAILER_BYTES :],
    }
    for name, data in expected.items():
        assert _hex(name) == data, name


def _run(name: str, port: int) -> None:
    code = re.sub(r"^PORT = \d+", f"PORT = {port}", _block("sender", name), flags=re.M)
    namespace: dict[str, object] = {}
    try:
        exec(compile(code, f"PROTOCOLS.md:{name}", "exec"), namespace)
    finally:  # the snippets leave their sockets to the interpreter's exit
        for value in namespace.values():
            if isinstance(value, socket.socket):
                value.close()


def _udp_receiver() -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(2.0)
    return sock


@pytest.mark.timeout(30)
def test_osc_compact_sender() -> None:
    with _udp_receiver() as rx:
        _run("osc_compact", rx.getsockname()[1])
        stream = mi.MarkerStream(up_axis="+Y", units="mm")
        for t in range(122):
            data = rx.recv(65536)
            if data.startswith(b"/rtd/labels"):
                stream.set_labels(osc_in.decode_labels(data))
            else:
                assert (
                    stream.feed(osc_in.decode_compact_frame, data, t_ns=t)
                    == mi.ACCEPTED
                )
    frame = stream.current.frame
    assert frame.frame_id == 119 and stream.counters["accepted"] == 120
    np.testing.assert_allclose(frame.markers_world[0], [0.219, -0.25, 1.7], rtol=1e-6)
    np.testing.assert_array_equal(frame.valid, [True, False, True])


@pytest.mark.timeout(30)
def test_osc_simple_sender() -> None:
    with _udp_receiver() as rx:
        _run("osc_simple", rx.getsockname()[1])
        stream = mi.MarkerStream(mi.LabelSet(0, ("LASI", "RASI", "LPSI")))
        for t in range(120):
            assert stream.feed(osc_in.decode_simple_bundle, rx.recv(65536), t_ns=t) == 0
    frame = stream.current.frame
    assert frame.frame_id == 119
    np.testing.assert_array_equal(frame.valid, [True, False, False])
    np.testing.assert_allclose(frame.markers_world[0], [0.1, 0.2, 1.0], rtol=1e-6)


@pytest.mark.timeout(30)
def test_zmq_sender_speaks_zmtp_to_a_pull_socket() -> None:
    ctx = zmq.Context()
    pull = ctx.socket(zmq.PULL)
    pull.linger = 0
    pull.rcvtimeo = 5000
    try:
        port = pull.bind_to_random_port("tcp://127.0.0.1")
        _run("zmq_push", port)
        stream = mi.MarkerStream()
        stream.set_labels(zmq_wire.decode_zmq_labels(*pull.recv_multipart()))
        for t in range(120):
            code = stream.feed(
                zmq_wire.decode_zmq_frame, *pull.recv_multipart(), t_ns=t
            )
            assert code == mi.ACCEPTED
    finally:
        pull.close()
        ctx.term()
    frame = stream.current.frame
    assert frame.frame_id == 119
    np.testing.assert_allclose(frame.markers_world[0], [0.1, 0.2, 1.119], rtol=1e-6)


@pytest.mark.timeout(30)
def test_osc_signed_sender_is_verified_and_decoded() -> None:
    verifier = osc_auth.DatagramVerifier(bytes(range(32)))
    with _udp_receiver() as rx:
        _run("osc_signed", rx.getsockname()[1])
        stream = mi.MarkerStream()
        for t in range(122):
            data = rx.recv(65536)
            n = verifier.check(memoryview(data), len(data))
            assert n >= 0, n
            if data.startswith(b"/rtd/labels"):
                stream.set_labels(osc_in.decode_labels(data[:n]))
            else:
                code = stream.feed(osc_in.decode_compact_frame, data[:n], t_ns=t)
                assert code == mi.ACCEPTED
    assert verifier.counter == 121 and stream.current.frame.frame_id == 119


def test_signed_trailer_vector_computed_from_the_text_alone() -> None:
    # Written from §13's words, not our encoder: HMAC-SHA256 over the datagram, the
    # magic, session and counter (uint64 BE), truncated to 16 bytes.
    import hashlib
    import hmac
    import struct

    section = DOC[DOC.index("## 13. Signed marker datagrams") :]

    def find(pattern: str) -> str:
        match = re.search(pattern, section)
        assert match, pattern
        return match.group(1)

    key = bytes.fromhex(find(r"`([0-9a-f]{64})`"))
    session = int(find(r"session (\d+) \("))
    counter = int(find(r"counter (\d+)\. The trailer"))
    datagram = _hex("osc_compact")
    trailer = _hex("osc_signed_trailer")
    head = b"RTDS" + struct.pack(">QQ", session, counter)
    tag = hmac.new(key, datagram + head, hashlib.sha256).digest()[:16]
    assert len(datagram) == 72 and key == bytes(range(32))
    assert trailer == head + tag
