"""End-to-end latency of the live daemon: sender -> retargetd -> receiver, in processes.

Run from the repository root::

    python bench/bench_latency.py [--seconds S] [--rates 240,1000]
        [--transports osc,zmq] [--warmup W] [--variants body,fit,face,face+validate]

Every case runs its own processes, all bound to 127.0.0.1 and all terminated at the
end, even on error:

- the daemon, ``python -m retargetd.daemon run --config <tmp.toml>`` (the same entry
  point as ``retargetd run``), on the plug-in-gait rig with a calibration made first by
  ``retargetd calibrate PiG_Calibration-FlatFoot-Full.c3d --rig plug-in-gait``, in the
  default latest-wins mode (``process_every_frame = false``); endpoints are ephemeral
  (UDP port 0, ``tcp://127.0.0.1:*``) and read back from its "listening on" lines;
- a sender (``multiprocessing``, spawn) that paces the real walk
  ``PiG_Motion-FlatFoot-Full.c3d`` (315 frames, looped, frame numbers increasing across
  loops) at the case rate, as OSC compact frames (UDP) or ZeroMQ PUSH to the daemon's
  PULL, labels first and every second; it stamps ``time.monotonic_ns()`` just before
  each send (CLOCK_MONOTONIC is system-wide on Linux, so the processes share it);
- a receiver that listens on the daemon's VMC port (UDP) and its pose stream (SUB) and
  stamps the arrival of every ``/VMC/Ext/T`` datagram and every pose message.

Latency of a frame = arrival of its output minus the send of its input. The pose
message carries the input frame number. VMC has none, so each ``/VMC/Ext/T`` is
matched to its frame through the daemon's clock: the daemon writes T = float32 of
(solved_ns - t0) s and the same ``solved_ns`` into the pose header, so t0 is found as
the offset that lines up (almost) every T with a pose's ``solved_ns`` to within the
float32 rounding of T (a few µs; solves are >= 100s of µs apart), and each T then
takes that pose's frame number. This holds under latest wins (no assumption that the
k-th T is the k-th input) and leaves unmatched only the Ts whose pose message was
lost (counted).

Baseline, in the same run: a raw UDP sender -> receiver pair (same processes, same
pacing, same payload size as the OSC compact frame) at each rate. Daemon-added latency
= the daemon case's percentile minus the raw UDP one at the same rate (for the pose
stream that includes two ZeroMQ hops against one UDP hop). A second baseline, the
floor of any Python process in between: the same raw payload through a relay process
that polls its UDP socket with ``zmq.Poller`` (the daemon's poll, its default 100 ms
timeout), receives into a buffer and sends the datagram on to the receiver, unchanged;
its added latency is what one Python hop costs on this machine at this rate, before any
decoding or solving. One such relay per input -> output pair the daemon offers, with
the daemon's own socket options (issue 35 item 1): ``relay`` UDP -> UDP (OSC in, VMC
out), ``relay-zmq`` ZeroMQ PUSH -> the relay's PULL -> UDP (ZeroMQ in, VMC out),
``relay-pub`` UDP -> PUB -> the receiver's SUB (OSC in, pose stream out: two parts, as
the daemon's pose message), ``relay-zmq-pub`` PULL -> PUB; the ZeroMQ input's relays
run only with ``--transports zmq``. Every daemon case's added p99 is printed against
raw UDP and against its pair's relay (the ratio issue 35 bounds by 1.25; with
``--rounds``, the median of the rounds of each side). The capture inputs (NatNet,
QTM) have no relay here: their sender is an emulator the daemon connects to.

Each case first sends ``--warmup`` seconds of frames (pipeline build on the first
labelled frame) that are left out of every figure, then snapshots the daemon's
counters (``{"cmd": "status"}`` on its control socket, as ``retargetd ctl status
--json``), sends ``--seconds`` of timed frames and snapshots again. Drops = timed
frames sent that the daemon did not solve (counter deltas); with latest wins, frames
it received but skipped for a newer one are ``stale``.

Variants (``--variants``, each run for every transport and rate): ``body`` (the
skeleton only), ``face`` (the body and the face from one marker stream: 40 facial
markers of the ICT-FaceKit ARKit face, ``face_synth``, riding the walk's own head
markers LFHD RFHD LBHD RBHD with known weights and 0.5 mm noise, occluded in frames
where a head marker is; ``[face]`` on with that training set, so every frame also
stabilizes 40 markers, solves 52 weights and sends 52 VMC blendshapes and the Mug),
``validate`` (``[validate]`` on: the live validator's thread checks every frame
beside the loop), ``fit`` (``[solve] method = "fit"``: the rigid-skeleton fit instead
of the construction, README "Two ways to solve the body") and any of them joined by
``+`` (``face+validate``, ``fit+validate``, ``fit+face``); ``+cold`` turns the
fit's touch before each frame off (``[loop] prewarm_ms = 0``; otherwise the daemon's
default: ``fit`` against ``fit+cold`` measures it); ``console`` (the body
with ``[console]`` on: the browser console served on a free port, its thread drawing
every published snapshot, no browser) and ``console+browser`` (the same with a headless
Chromium, Debian's ``chromium`` driven by selenium, showing the page for the whole
case; skipped when Chromium or its driver is absent);
``pipeline`` (the body with ``[[pipeline]]`` post stages twist + One Euro between the
solve and the target mapping: the daemon's own per-stage figures, ``post.twist`` and
``post.one_euro`` from ``ctl status``, are printed after the tables; ``+pipeline``
adds them to any variant); ``+plant`` (last) plants the feet on the target
(``[target] feet = "plant"``, README "Feet that plant"): ``body`` against ``body+plant``
measures the stage in the loop; ``+spin`` (after it) has the loop poll without
sleeping around each frame's due time (``[loop] spin_us`` = :data:`SPIN_US`, README
"The hot path, per frame"): ``body`` against ``body+spin`` measures what spinning
buys on this machine (off, the daemon's default, the loop pays one ``is None`` test
a pass).

Capture-system transports (``--transports natnet,qtm``, README "Capture systems"):
the sender process is the capture system, the emulators of ``tests/protocols`` (their
encoders and command handling) driven by the same pacing. ``natnet``: a NatNet 4.1
server on a UDP command port that answers the daemon's connect and model-definition
request, then sends each frame of data unicast to it (Motive's metres, Y up); ``qtm``:
a QTM RT 1.25 server on TCP that answers ``qtm-rt``'s commands, then sends data
packets with 3D and residuals (millimetres). The daemon connects to it (``[input]
source``), so its latency includes the decoder, and for QTM the ``qtm-rt`` thread and
the socketpair hand-over. Frame numbers and source timestamps are the frame count at
the case rate.

Speed is printed, never asserted (STYLE.md section 10).
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import multiprocessing as mp
import os
import re
import select
import shutil
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np

DATASETS = Path(__file__).resolve().parent.parent.parent / "shared" / "datasets"
PIG_MOTION = DATASETS / "btkdata" / "PiG_Motion-FlatFoot-Full.c3d"
PIG_CALIBRATION = DATASETS / "btkdata" / "PiG_Calibration-FlatFoot-Full.c3d"
LOCALHOST = "127.0.0.1"
LABEL_SET_ID = 1
#: ``/VMC/Ext/T ,f`` is the last message of a frame's last datagram: its last 20 bytes
#: are the padded address and type tags, then the float32 T.
VMC_T_TAIL = b"/VMC/Ext/T\0\0,f\0\0"
_BE_F32 = struct.Struct(">f")
_RAW_FRAME = struct.Struct(">q")
#: Pose header: frame number, received / solved / sent ns (pose_stream.HEADER).
_POSE_FIELDS = struct.Struct("<8xq8xqqq")
ADDED_P99_TARGET_US = 1000.0
#: Issue 19 item 1, the hot path near the wire's floor: added p99 over raw UDP (same
#: run, either transport, 240 and 1000 Hz) on a quiet machine, by variant.
HOT_PATH_TARGETS_US = {"body": 150.0, "fit+face": 250.0, "face+fit": 250.0}


# ---- child processes -----------------------------------------------------------------


#: Transports whose sender is a capture system the daemon connects to.
CAPTURE_TRANSPORTS = ("natnet", "qtm")
#: Cases without the daemon: raw UDP sender -> receiver, and the same through the
#: Python relay (the floor of any Python process in between). One relay per input ->
#: output pair the daemon offers (issue 35 item 1): ``relay`` UDP -> UDP (OSC in, VMC
#: out), ``relay-zmq`` ZeroMQ PULL -> UDP (ZeroMQ in, VMC out), ``relay-pub`` UDP ->
#: ZeroMQ PUB (OSC in, pose stream out), ``relay-zmq-pub`` PULL -> PUB; ``relay+``
#: adds the least per-frame work to ``relay``.
BASELINES = ("raw", "relay", "relay+", "relay-zmq", "relay-pub", "relay-zmq-pub")
#: The relay whose floor each (input transport, output) pair of the daemon is judged
#: against. The capture inputs (NatNet, QTM) have no relay of their own here: their
#: sender is a capture emulator the daemon connects to (README, issue 35 note).
PAIR_RELAY = {
    ("osc", "vmc"): "relay",
    ("osc", "pose"): "relay-pub",
    ("zmq", "vmc"): "relay-zmq",
    ("zmq", "pose"): "relay-zmq-pub",
}
#: The daemon's own socket options for those pairs (live/loop.py): its ZeroMQ input
#: PULL (RCVHWM 1000, LINGER 0, MAXMSGSIZE the default max_message_bytes) and its pose
#: PUB (LINGER 0, SNDHWM the default [output.pose] sndhwm, 4).
DAEMON_PULL_RCVHWM = 1000
DAEMON_PULL_MAXMSGSIZE = 65_507
DAEMON_PUB_SNDHWM = 4
RELAY_WHAT = {
    "relay-zmq": "ZeroMQ PULL -> UDP",
    "relay-pub": "UDP -> PUB",
    "relay-zmq-pub": "PULL -> PUB",
}
#: relay+: the size of its first datagram, VMC's bones (/VMC/Ext/Bone/Pos bundle of
#: the humanoid bones at 240 Hz is 1-2 KB; the root and T come in the second).
RELAY_BONES_BYTES = 1400
#: The relay's poll timeout: the daemon's loop.poll_timeout_ms default (100 ms).
RELAY_POLL_MS = 100


def _pace(
    rate_hz: float, frames: range, prepare: Any, send: Any, out_ns: np.ndarray
) -> int:
    """Send ``frames`` at ``rate_hz``: ``prepare(frame)`` (labels, encoding), then the
    stamp ``out_ns[k]`` and at once ``send(frame)``. Never bursts to catch up after a
    stall (a capture system does not): two frames are never less than half a period
    apart, and more than a period behind, the schedule restarts. Returns the number
    of late frames."""
    period = 1e9 / rate_hz
    half = 0.5 * period
    clock = time.monotonic_ns
    t_next = float(clock())
    slips = 0
    for k, frame in enumerate(frames):
        prepare(frame)
        wait = t_next - clock()
        if wait > 0:
            time.sleep(wait * 1e-9)
        t = clock()
        out_ns[k] = t
        send(frame)
        t_next += period
        if t_next < t - period:  # far behind: restart the schedule
            t_next = float(t) + period
            slips += 1
        elif t_next < t + half:  # late: catch up, but never in a burst
            t_next = float(t) + half
            slips += 1
    return slips


def _emulator(name: str) -> Any:
    """A protocol emulator module of ``tests/protocols`` (not a package: by path)."""
    import importlib.util

    path = Path(__file__).resolve().parent.parent / "tests" / "protocols" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(f"bench_{name}", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def _capture_sender(spec: dict[str, Any], conn: Connection) -> None:
    """Sender process as a capture system (``natnet`` / ``qtm``): bind, say the port,
    answer the daemon's client until it asks for frames, then pace them as
    :func:`_sender` does."""
    mode, rate = spec["mode"], spec["rate_hz"]
    positions: np.ndarray = spec["positions"]
    labels = list(spec["labels"])
    n_take = len(positions)
    current: list[bytes] = [b""]
    if mode == "natnet":
        em = _emulator("natnet_emulator")
        motive = positions @ em.MOTIVE_FROM_WORLD.T
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind((LOCALHOST, 0))
        sock.settimeout(0.05)
        conn.send(("port", sock.getsockname()[1]))
        client = None
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:  # connect, then model definitions
            try:
                data, addr = sock.recvfrom(65536)
            except TimeoutError:
                continue
            msg_id = struct.unpack_from("<H", data)[0]
            if msg_id == em.NAT_CONNECT:
                sock.sendto(em.server_info((4, 1), sock.getsockname()[1]), addr)
            elif msg_id == em.NAT_REQUEST_MODELDEF:
                sock.sendto(em.model_defs((4, 1), labels), addr)
                client = addr
                break
        if client is None:
            raise RuntimeError("the daemon never asked for model definitions")
        sock.setblocking(False)

        def prepare(frame: int) -> None:
            with contextlib.suppress(BlockingIOError):
                while True:
                    sock.recv(65536)  # keep-alives
            row = frame % n_take
            current[0] = em.frame_of_data((4, 1), frame, motive[row], frame / rate)

        def send(_frame: int) -> None:
            sock.sendto(current[0], client)

        closer: Any = sock
    else:
        em = _emulator("qtm_emulator")
        server = em.QtmEmulator(positions, labels, rate, 0, em.Scenario(faults=False))
        conn.send(("port", server.port))
        server.listener.settimeout(60)
        tcp, _ = server.listener.accept()
        tcp.setblocking(False)
        tcp.sendall(em.rt_string(em.PACKET_COMMAND, "QTM RT Interface connected"))
        buf = bytearray()
        deadline = time.monotonic() + 60
        streaming = False
        while not streaming and time.monotonic() < deadline:
            cmd = server._read_command(tcp, buf)
            if cmd is None:
                time.sleep(0.002)
                continue
            streaming = server._answer(tcp, cmd) == "stream"
        if not streaming:
            raise RuntimeError("qtm-rt never asked for frames")
        markers_mm = positions * 1000.0

        def prepare(frame: int) -> None:
            with contextlib.suppress(BlockingIOError):
                tcp.recv(65536)  # nothing expected; never let it fill
            row = frame % n_take
            current[0] = em.data_packet(
                frame, round(frame * 1e6 / rate), markers_mm[row]
            )

        def send(_frame: int) -> None:
            tcp.sendall(current[0])

        closer = tcp
    try:
        frame0 = spec["frame0"]
        n_warm = max(1, round(spec["warmup_s"] * rate))
        gc.disable()
        warm = range(frame0, frame0 + n_warm)
        _pace(rate, warm, prepare, send, np.zeros(n_warm, np.int64))
        conn.send(("warm", warm.stop))
        if conn.recv() != "go":
            return
        n = max(1, round(spec["seconds"] * rate))
        sent_ns = np.zeros(n, np.int64)
        timed = range(warm.stop, warm.stop + n)
        slips = _pace(rate, timed, prepare, send, sent_ns)
        gc.enable()
        conn.send(("done", timed.start, sent_ns, slips))
        conn.recv()  # hold the connection until the case is over
    finally:
        closer.close()


def _sender(spec: dict[str, Any], conn: Connection) -> None:
    """Sender process: labels, warm-up frames, wait for "go", timed frames."""
    import zmq

    from retargetd.protocols import osc_in, zmq_wire
    from retargetd.protocols.marker_input import LabelSet

    mode, rate = spec["mode"], spec["rate_hz"]
    positions: np.ndarray = spec["positions"]
    n_take = len(positions)
    labels = LabelSet(LABEL_SET_ID, tuple(spec["labels"]))
    ctx = zmq.Context()
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    push = None
    udp_addr = (LOCALHOST, spec.get("port", 0))
    if mode in ("zmq", "rawzmq"):
        push = ctx.socket(zmq.PUSH)
        push.setsockopt(zmq.LINGER, 0)
        push.connect(spec["endpoint"])
    # Every take row encoded once; the frame number is patched in before each send
    # (OSC: big-endian int64 at offset 20; ZeroMQ: little-endian int64 at offset 8;
    # raw: big-endian int64 at offset 0 of a payload the size of the OSC frame).
    nan = float("nan")
    osc_frames = [
        bytearray(osc_in.encode_compact_frame(0, nan, LABEL_SET_ID, p))
        for p in positions
    ]
    zmq_frames = [
        [bytearray(h), b]
        for h, b in (
            zmq_wire.encode_zmq_frame(0, nan, LABEL_SET_ID, p) for p in positions
        )
    ]
    raw = bytearray(len(osc_frames[0]))
    labels_osc = osc_in.encode_labels(labels)
    labels_zmq = zmq_wire.encode_zmq_labels(labels)
    next_labels_ns = 0
    current: list[Any] = [None]

    def prepare(frame: int) -> None:
        nonlocal next_labels_ns
        now = time.monotonic_ns()
        if mode not in ("raw", "rawzmq") and now >= next_labels_ns:  # first, each s
            if push is not None:
                push.send_multipart(labels_zmq)
            else:
                udp.sendto(labels_osc, udp_addr)
            next_labels_ns = now + 1_000_000_000
        row = frame % n_take
        if mode == "osc":
            struct.pack_into(">q", osc_frames[row], 20, frame)
            current[0] = osc_frames[row]
        elif mode == "zmq":
            struct.pack_into("<q", zmq_frames[row][0], 8, frame)
            current[0] = zmq_frames[row]
        else:
            _RAW_FRAME.pack_into(raw, 0, frame)
            current[0] = raw

    def send(_frame: int) -> None:
        if mode == "rawzmq":
            assert push is not None
            push.send(current[0])
        elif push is not None:
            push.send_multipart(current[0])
        else:
            udp.sendto(current[0], udp_addr)

    try:
        time.sleep(0.2)  # let the PUSH connect
        frame0 = spec["frame0"]
        n_warm = max(1, round(spec["warmup_s"] * rate))
        gc.disable()
        warm = range(frame0, frame0 + n_warm)
        _pace(rate, warm, prepare, send, np.zeros(n_warm, np.int64))
        conn.send(("warm", warm.stop))
        if conn.recv() != "go":
            return
        n = max(1, round(spec["seconds"] * rate))
        sent_ns = np.zeros(n, np.int64)
        timed = range(warm.stop, warm.stop + n)
        slips = _pace(rate, timed, prepare, send, sent_ns)
        gc.enable()
        conn.send(("done", timed.start, sent_ns, slips))
    finally:
        udp.close()
        if push is not None:
            push.close()
        ctx.term()


def _relay(
    port: int,
    conn: Connection,
    work: bool = False,
    zmq_in: bool = False,
    pub_out: bool = False,
) -> None:
    """The floor of any Python daemon (``relay`` baseline): what the daemon's loop
    must do per frame at the least, and nothing else. A UDP socket polled by
    ``zmq.Poller`` (as the daemon's loop polls its inputs, same timeout), each
    datagram received into a preallocated buffer and sent on at once, unchanged, to
    the receiver's ``port`` on a connected socket, a zero-timeout poll ending the
    drain (the daemon's cheapest calls, ``bench_socket_calls.py``). Its latency over
    raw UDP is the Python process hop: wake-up, poll, one receive, one send, on this
    machine at this rate.

    ``work`` (``relay+``): less than the daemon's least per frame under the design
    (one compiled call for decode, solve and encode; two sends, where the daemon
    makes a VMC send and a two-part pose send): one numba call that copies the
    datagram into two output buffers, then a first datagram of VMC's bone size (1400
    bytes) to a socket nobody reads and the copy to the receiver. A lower bound on any
    daemon built so.

    ``zmq_in`` (``relay-zmq``): the input is a ZeroMQ PULL bound on 127.0.0.1 with the
    daemon's options, drained as the daemon drains its input (``ZMQ_EVENTS``, then
    ``recv_into`` a preallocated buffer). ``pub_out`` (``relay-pub``): the output is a
    ZeroMQ PUB with the daemon's pose-stream options, each frame sent as two parts
    (the datagram, then a VMC-bone-sized body) as the daemon sends a pose message."""
    import zmq

    copy_into = None
    bones = bytearray(RELAY_BONES_BYTES)
    frame_out = bytearray(65536)
    if work:
        import numba

        @numba.njit(cache=False, nogil=True)
        def copy_into(src: Any, n: int, a: Any, b: Any) -> None:
            for i in range(n):
                b[i] = src[i]
            for i in range(a.shape[0]):
                a[i] = src[i % n]

        src0 = np.zeros(64, np.uint8)
        copy_into(src0, 64, np.frombuffer(bones, np.uint8),
                  np.frombuffer(frame_out, np.uint8))  # fmt: skip
    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sink.bind((LOCALHOST, 0))
    sink_addr = sink.getsockname()

    zctx = zmq.Context()
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    udp.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
    udp.bind((LOCALHOST, 0))
    udp.setblocking(False)
    pull = pub = None
    if zmq_in:
        pull = zctx.socket(zmq.PULL)
        pull.setsockopt(zmq.LINGER, 0)
        pull.setsockopt(zmq.RCVHWM, DAEMON_PULL_RCVHWM)
        pull.setsockopt(zmq.MAXMSGSIZE, DAEMON_PULL_MAXMSGSIZE)
        pull.bind(f"tcp://{LOCALHOST}:*")
    if pub_out:
        pub = zctx.socket(zmq.PUB)
        pub.setsockopt(zmq.LINGER, 0)
        pub.setsockopt(zmq.SNDHWM, DAEMON_PUB_SNDHWM)
        pub.bind(f"tcp://{LOCALHOST}:*")
    out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    out.connect((LOCALHOST, port))  # the cheapest sends, as the daemon's VMC socket
    side = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    side.connect(sink_addr)
    more = select.poll()  # "another datagram waits?", as the daemon's OSC drain
    more.register(udp.fileno(), select.POLLIN)
    poller = zmq.Poller()
    poller.register(pull if pull is not None else udp, zmq.POLLIN)
    poller.register(conn.fileno(), zmq.POLLIN)
    conn.send(
        ("port", udp.getsockname()[1])
        if pull is None
        else ("endpoint", pull.getsockopt_string(zmq.LAST_ENDPOINT))
    )
    if pub is not None:
        conn.send(("pub", pub.getsockopt_string(zmq.LAST_ENDPOINT)))
    buf = bytearray(65536)
    view = memoryview(buf)
    src, a, b = (np.frombuffer(x, np.uint8) for x in (buf, bones, frame_out))
    out_view = memoryview(frame_out)
    body = bytes(RELAY_BONES_BYTES)
    fd = udp.fileno()  # zmq.Poller reports a plain socket by its descriptor

    def forward(n: int) -> None:
        if pub is not None:  # as the daemon's pose send: part by part, copied
            try:
                pub.send(view[:n], zmq.NOBLOCK | zmq.SNDMORE)
                pub.send(body, zmq.NOBLOCK)
            except zmq.Again:
                pass
        elif copy_into is None:
            out.send(view[:n])
        else:
            copy_into(src, n, a, b)
            side.send(bones)
            out.send(out_view[:n])

    gc.disable()
    try:
        while True:
            events = dict(poller.poll(RELAY_POLL_MS))
            if pull is not None and pull in events:
                while int(pull.get(zmq.EVENTS)) & zmq.POLLIN:
                    try:
                        n = pull.recv_into(buf, flags=zmq.NOBLOCK)
                    except zmq.Again:
                        break
                    forward(min(n, len(buf)))
            if fd in events:
                k = 0
                while k == 0 or more.poll(0):
                    k += 1
                    try:
                        n = udp.recv_into(buf)
                    except (BlockingIOError, InterruptedError):
                        break
                    forward(n)
            if conn.fileno() in events:
                conn.recv()
                return
    finally:
        udp.close()
        out.close()
        side.close()
        sink.close()
        for z in (pull, pub):
            if z is not None:
                z.close()
        zctx.term()


def _receiver(capacity: int, raw_mode: bool, conn: Connection) -> None:
    """Receiver process: a UDP port (VMC, or the raw baseline) and a pose SUB.

    Per UDP datagram it keeps the arrival ns and, in ``raw_mode``, the frame number
    (first 8 bytes); otherwise, for ``/VMC/Ext/T`` datagrams only, the value of T.

    Commands on ``conn``: ``("sub", endpoint)`` connects the SUB (answered "ok" after
    a short settle), ``("stop",)`` sends the arrays back.
    """
    import zmq

    ctx = zmq.Context()
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    udp.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
    udp.bind((LOCALHOST, 0))
    udp.setblocking(False)
    sub = ctx.socket(zmq.SUB)
    sub.setsockopt(zmq.LINGER, 0)
    sub.setsockopt(zmq.RCVHWM, 100_000)
    # raw_mode: a relay's PUB carries the raw payload (frame number first), no topic
    sub.setsockopt(zmq.SUBSCRIBE, b"" if raw_mode else b"RTDP")
    poller = zmq.Poller()
    poller.register(udp, zmq.POLLIN)
    poller.register(sub, zmq.POLLIN)
    poller.register(conn.fileno(), zmq.POLLIN)
    conn.send(("port", udp.getsockname()[1]))
    udp_ns = np.zeros(capacity, np.int64)
    udp_val = np.zeros(capacity, np.float64)
    raw_frame = np.zeros(capacity, np.int64)
    n_udp = n_t = 0
    pose = np.zeros((capacity, 5), np.int64)  # arrival, frame, received, solved, sent
    n_pose = 0
    buf = bytearray(65536)
    clock = time.monotonic_ns
    gc.disable()
    try:
        while True:
            events = dict(poller.poll(100))
            if udp.fileno() in events or udp in events:
                while True:
                    try:
                        n = udp.recv_into(buf)
                    except (BlockingIOError, InterruptedError):
                        break
                    t = clock()
                    n_udp += 1
                    if n_t >= capacity:
                        continue
                    if raw_mode:
                        if n >= 8:
                            udp_ns[n_t] = t
                            raw_frame[n_t] = _RAW_FRAME.unpack_from(buf, 0)[0]
                            n_t += 1
                    elif n >= 20 and buf[n - 20 : n - 4] == VMC_T_TAIL:
                        udp_ns[n_t] = t
                        udp_val[n_t] = _BE_F32.unpack_from(buf, n - 4)[0]
                        n_t += 1
            if sub in events:
                while True:
                    try:
                        parts = sub.recv_multipart(zmq.NOBLOCK)
                    except zmq.Again:
                        break
                    t = clock()
                    if raw_mode:
                        if n_t < capacity and len(parts[0]) >= 8:
                            udp_ns[n_t] = t
                            raw_frame[n_t] = _RAW_FRAME.unpack_from(parts[0], 0)[0]
                            n_t += 1
                        continue
                    if n_pose < capacity and len(parts[0]) == 68:
                        pose[n_pose, 0] = t
                        pose[n_pose, 1:] = _POSE_FIELDS.unpack_from(parts[0])
                        n_pose += 1
            if conn.fileno() in events:
                cmd = conn.recv()
                if cmd[0] == "sub":
                    sub.connect(cmd[1])
                    time.sleep(0.3)  # ZeroMQ's slow joiner: let the SUB attach
                    conn.send("ok")
                elif cmd[0] == "stop":
                    conn.send(
                        {  # t_*: the T datagrams (VMC) or all datagrams (raw)
                            "udp_datagrams": n_udp,
                            "t_ns": udp_ns[:n_t].copy(),
                            "t_val": udp_val[:n_t].copy(),
                            "raw_frame": raw_frame[:n_t].copy(),
                            "pose": pose[:n_pose].copy(),
                        }
                    )
                    return
    finally:
        udp.close()
        sub.close()
        ctx.term()


# ---- the daemon ----------------------------------------------------------------------


def _face_stream(take: Any, rng: np.random.Generator) -> tuple[Any, Any, Any]:
    """(training set, labels, positions) of the walk with a face riding its head.

    The head frame is the walk's anatomical head frame (``face_synth.pig_head_motion``:
    x right, y forward, z up at the LFHD RFHD LBHD RBHD centroid), so the ICT face
    sits the right way round on the head markers; the training head layout is the
    mean of those markers in that frame.
    """
    from scipy.spatial.transform import Rotation

    from retargetd.daemon.face.solve import TrainingSet
    from retargetd.daemon.synth import face as fs

    cols = [take.labels.index(n) for n in fs.HEAD_NAMES]
    head = take.positions[:, cols]
    complete = np.all(np.isfinite(head), axis=(1, 2))
    quat, pos = fs.pig_head_motion(DATASETS)  # complete frames, in order
    rot = Rotation.from_quat(quat, scalar_first=True).as_matrix()
    local = np.einsum("tji,tmj->tmi", rot, head[complete] - pos[:, None])
    layout = local.mean(axis=0)
    ict = fs.ict_training_set(DATASETS)
    training = TrainingSet(
        head_names=fs.HEAD_NAMES, marker_names=ict.marker_names,
        expression_names=ict.expression_names, head_layout=layout - layout.mean(0),
        neutral=ict.neutral, deltas=ict.deltas,
    )  # fmt: skip
    w = fs.synth_weights(rng, int(complete.sum()), take.rate_hz)
    face_local = training.neutral + np.einsum("tk,kmc->tmc", w, training.deltas)
    face = np.full((take.n_frames, len(ict.marker_names), 3), np.nan)
    face[complete] = np.einsum("tij,tmj->tmi", rot, face_local) + pos[:, None]
    face[complete] += rng.normal(0.0, 5e-4 / np.sqrt(3.0), face[complete].shape)
    labels = (*take.labels, *training.marker_names)
    return training, labels, np.concatenate([take.positions, face], axis=1)


#: The variants ``--variants`` takes (module docstring).


def _config_toml(
    calibration: Path,
    transport: str,
    vmc_port: int,
    variant: str,
    face_npz: Path,
    source: str = "",
) -> str:
    face = "face" in variant
    validate = "validate" in variant
    method = "fit" if "fit" in variant.split("+") else "construction"
    console = variant.startswith("console")
    stages = PIPELINE_TOML if "pipeline" in variant else ""
    # +plant: the feet planted on the target (issue 34, README "Feet that plant")
    if "plant" in variant.split("+"):
        stages += '\n[target]\nfeet = "plant"\n'

    # +cold: the fit's touch off; otherwise the daemon's default [loop] prewarm_ms
    prewarm = "prewarm_ms = 0.0" if "cold" in variant.split("+") else ""
    if "spin" in variant.split("+"):  # +spin: [loop] spin_us (off by default)
        prewarm += f"\nspin_us = {SPIN_US}"
    return f"""\
[solve]
method = "{method}"
[performer]
rig = "plug-in-gait"
calibration = "{calibration}"
[input]
source = "{source}"
[input.osc]
enabled = {str(transport == "osc").lower()}
port = 0
[input.zmq]
enabled = {str(transport == "zmq").lower()}
mode = "pull"
endpoint = "tcp://{LOCALHOST}:*"
[output.vmc]
host = "{LOCALHOST}"
port = {vmc_port}
[output.pose]
endpoint = "tcp://{LOCALHOST}:*"
[control]
endpoint = "tcp://{LOCALHOST}:*"
[show_control]
enabled = false
[loop]
process_every_frame = false
{prewarm}
[face]
enabled = {str(face).lower()}
config = "arkit52"
training = "{face_npz}"
[validate]
enabled = {str(validate).lower()}
[console]
enabled = {str(console).lower()}
port = 0
{stages}"""


#: ``+spin``'s window, us either side of a frame's due time: twice the p99 of a
#: sleeping Python relay's wake-up on this VM (140-245 us at 240 Hz, issue 35), so a
#: frame that the scheduler would have delivered late still lands in the window.
SPIN_US = 500.0


#: The ``pipeline`` variant's post stages (README "Post stages").
PIPELINE_TOML = """
[[pipeline]]
kind = "twist"
[[pipeline]]
kind = "one_euro"
min_cutoff_hz = 1.0
beta_rot = 2.0
beta_pos = 20.0
"""


_LISTENING = re.compile(r"^listening on (\S+) \(.*\): (.+)$")


class Daemon:
    """``retargetd run --config FILE`` as a subprocess, stdout into a log file."""

    def __init__(self, config: Path, log: Path) -> None:
        self.log = log
        self._log_file = log.open("w")
        cmd = [sys.executable, "-m", "retargetd.daemon", "run", "--config", str(config)]
        self.proc = subprocess.Popen(
            cmd, stdout=self._log_file, stderr=subprocess.STDOUT, start_new_session=True
        )
        self.endpoints: dict[str, str] = {}

    def wait_ready(self, timeout_s: float = 60.0) -> None:
        """Wait for the control endpoint, then for a status reply (after warm-up)."""
        deadline = time.monotonic() + timeout_s
        while "control" not in self.endpoints:
            self._check_alive(deadline)
            for line in self.log.read_text().splitlines():
                m = _LISTENING.match(line)
                if m:
                    self.endpoints[m.group(2)] = m.group(1)
            time.sleep(0.05)
        while self.status(timeout_ms=500) is None:
            self._check_alive(deadline)
        for line in self.log.read_text().splitlines():  # the endpoints after control
            m = _LISTENING.match(line)
            if m:
                self.endpoints[m.group(2)] = m.group(1)

    def _check_alive(self, deadline: float) -> None:
        if self.proc.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError(
                f"daemon not ready (exit code {self.proc.returncode}):\n"
                + self.log.read_text()
            )

    def status(self, timeout_ms: int = 2000) -> dict[str, Any] | None:
        """``retargetd ctl status --json`` (the same request, in process)."""
        from retargetd.daemon.cli.ctl import request

        reply = request(self.endpoints["control"], {"cmd": "status"}, timeout_ms)
        return None if reply is None else reply["status"]

    def stop(self) -> None:
        """SIGTERM, then SIGKILL if it does not exit within 5 s."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self._log_file.close()


# ---- one case ------------------------------------------------------------------------


@dataclass(slots=True)
class Result:
    """One case's raw observations (ns, this host's monotonic clock)."""

    name: str
    rate_hz: float
    sent_ns: np.ndarray  # per timed frame, frame number = frame0 + index
    frame0: int
    slips: int
    recv: dict[str, Any]
    counters0: dict[str, Any] = field(default_factory=dict)
    counters1: dict[str, Any] = field(default_factory=dict)
    seconds: float = 0.0


def _terminate(procs: list[Any]) -> None:
    for p in procs:
        if p.is_alive():
            p.terminate()
        p.join(5)
        if p.is_alive():
            p.kill()
            p.join(5)


def run_case(
    ctx: Any,
    transport: str,
    rate_hz: float,
    args: argparse.Namespace,
    take: Any,
    calibration: Path | None,
    tmp: Path,
    variant: str = "body",
    stream: tuple[tuple[str, ...], np.ndarray] | None = None,
) -> Result:
    """One case: transport "raw" (baseline, no daemon), "osc" or "zmq"; variant
    "body", "face", "validate" or "face+validate" (``stream``: its labels and
    positions)."""
    name = f"{transport} {rate_hz:g} Hz" + ("" if variant == "body" else f" {variant}")
    labels, positions = stream or (take.labels, take.positions)
    capacity = int(rate_hz * (args.seconds + args.warmup + 5)) + 1000
    recv_conn, recv_child = ctx.Pipe()
    send_conn, send_child = ctx.Pipe()
    procs: list[Any] = []
    daemon: Daemon | None = None
    browser: Any = None
    try:
        receiver = ctx.Process(
            target=_receiver, args=(capacity, transport in BASELINES, recv_child)
        )
        receiver.start()
        procs.append(receiver)
        if not recv_conn.poll(30):
            raise RuntimeError("receiver did not start")
        _, port = recv_conn.recv()
        spec: dict[str, Any] = {
            "mode": "raw" if transport in BASELINES else transport,
            "rate_hz": rate_hz,
            "seconds": args.seconds,
            "warmup_s": args.warmup,
            "positions": positions,
            "labels": labels,
            "raw_size": 48 + 12 * len(labels),  # the OSC compact frame's size
            "frame0": 0,
        }
        capture = transport in CAPTURE_TRANSPORTS
        source = ""
        if capture:  # the capture system runs first; the daemon connects to it
            sender = ctx.Process(target=_capture_sender, args=(spec, send_child))
            sender.start()
            procs.append(sender)
            if not send_conn.poll(30):
                raise RuntimeError("capture sender did not bind")
            _, server_port = send_conn.recv()
            source = (
                f"natnet://{LOCALHOST}:{server_port}?local={LOCALHOST}"
                if transport == "natnet"
                else f"qtm://{LOCALHOST}:{server_port}"
            )
        if transport == "raw":
            spec["port"] = port
        elif transport.startswith("relay"):
            relay_conn, relay_child = ctx.Pipe()
            zmq_in = transport.startswith("relay-zmq")
            pub_out = transport.endswith("-pub")
            relay = ctx.Process(
                target=_relay,
                args=(port, relay_child, transport == "relay+", zmq_in, pub_out),
            )
            relay.start()
            procs.append(relay)
            if not relay_conn.poll(30):
                raise RuntimeError("relay did not start")
            kind, where = relay_conn.recv()
            if kind == "endpoint":
                spec["mode"], spec["endpoint"] = "rawzmq", where
            else:
                spec["port"] = where
            if pub_out:
                if not relay_conn.poll(30):
                    raise RuntimeError("relay did not say its PUB")
                recv_conn.send(("sub", relay_conn.recv()[1]))
                recv_conn.recv()
        else:
            assert calibration is not None
            stem = f"{transport}_{rate_hz:g}_{variant}"
            config = tmp / f"{stem}.toml"
            config.write_text(
                _config_toml(
                    calibration, transport, port, variant, tmp / "face.npz", source
                )
            )
            daemon = Daemon(config, tmp / f"{stem}.log")
            daemon.wait_ready()
            if variant == "console+browser":
                browser = _open_browser(daemon.endpoints["console"], tmp)
            recv_conn.send(("sub", daemon.endpoints["zmq poses"]))
            recv_conn.recv()
            if transport == "osc":
                spec["port"] = int(daemon.endpoints["osc markers"].rsplit(":", 1)[1])
            elif transport == "zmq":
                spec["endpoint"] = daemon.endpoints["zmq markers"]
        if not capture:
            sender = ctx.Process(target=_sender, args=(spec, send_child))
            sender.start()
            procs.append(sender)
        if not send_conn.poll(60):
            raise RuntimeError("sender did not finish its warm-up")
        send_conn.recv()
        time.sleep(0.2)  # let the daemon drain the warm-up
        counters0 = daemon.status() if daemon else None
        send_conn.send("go")
        if not send_conn.poll(args.seconds * 3 + 30):
            raise RuntimeError("sender did not finish")
        _, frame0, sent_ns, slips = send_conn.recv()
        time.sleep(0.3)  # stragglers
        counters1 = daemon.status() if daemon else None
        if capture:
            send_conn.send("end")
        recv_conn.send(("stop",))
        if not recv_conn.poll(30):
            raise RuntimeError("receiver did not answer")
        recv = recv_conn.recv()
        return Result(
            name, rate_hz, sent_ns, frame0, slips, recv,
            counters0 or {}, counters1 or {}, args.seconds,
        )  # fmt: skip
    finally:
        _terminate(procs)
        if browser is not None:
            browser.quit()
        if daemon is not None:
            daemon.stop()


def _open_browser(url: str, tmp: Path) -> Any:
    """A headless Chromium showing ``url`` (the console) until ``quit()``."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support import expected_conditions as ec
    from selenium.webdriver.support.ui import WebDriverWait

    opts = webdriver.ChromeOptions()
    opts.binary_location = shutil.which("chromium") or "/usr/bin/chromium"
    for flag in (
        "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run",
        "--enable-unsafe-swiftshader", "--window-size=1000,640",
        f"--user-data-dir={tmp / 'chromium'}",
    ):  # fmt: skip
        opts.add_argument(flag)
    driver = webdriver.Chrome(
        options=opts,
        service=Service(shutil.which("chromedriver") or "/usr/bin/chromedriver"),
    )
    driver.get(url)
    WebDriverWait(driver, 60).until(
        ec.presence_of_element_located((By.TAG_NAME, "canvas"))
    )
    return driver


# ---- analysis ------------------------------------------------------------------------


def match_vmc_t(t_s: np.ndarray, solved_ns: np.ndarray) -> np.ndarray:
    """Index into ``solved_ns`` of the pose each ``/VMC/Ext/T`` belongs to, -1 if none.

    The daemon sends T = float32((solved_ns - t0) * 1e-9) with an unknown t0. The
    right t0 makes T * 1e9 + t0 land on a ``solved_ns`` within T's float32 rounding
    for nearly every T; a wrong one (a pairing off by k frames) only where the solve
    intervals happen to agree to a few µs. Candidates come from pairing the first Ts
    with the first poses; the one matching the most Ts wins.
    """
    out = np.full(len(t_s), -1, np.int64)
    if len(t_s) == 0 or len(solved_ns) == 0:
        return out
    x_ns = t_s.astype(np.float64) * 1e9
    half_ulp_ns = 0.5 * float(np.spacing(np.float32(np.abs(t_s).max()))) * 1e9
    tol_ns = half_ulp_ns + 1000.0
    order = np.argsort(solved_ns, kind="stable")
    s = solved_ns[order].astype(np.float64)

    def nearest(c: float) -> tuple[np.ndarray, np.ndarray]:
        want = x_ns + c
        i = np.clip(np.searchsorted(s, want), 1, len(s) - 1) if len(s) > 1 else None
        if i is None:
            return np.zeros(len(want), np.int64), np.abs(s[0] - want)
        left = np.abs(s[i - 1] - want) <= np.abs(s[i] - want)
        j = np.where(left, i - 1, i)
        return j, np.abs(s[j] - want)

    k = min(40, len(t_s), len(s))
    cands = (solved_ns[:k, None].astype(np.float64) - x_ns[None, :k]).ravel()
    best_c, best_n = 0.0, -1
    for c in cands:
        n = int(np.count_nonzero(nearest(c)[1] <= tol_ns))
        if n > best_n:
            best_c, best_n = c, n
    j, d = nearest(best_c)
    ok = d <= tol_ns
    best_c += float(np.median(s[j[ok]] - (x_ns[ok] + best_c)))  # refine
    j, d = nearest(best_c)
    ok = d <= tol_ns
    out[ok] = order[j[ok]]
    return out


def _pct(values_ns: np.ndarray) -> tuple[float, float]:
    if len(values_ns) == 0:
        return float("nan"), float("nan")
    p = np.percentile(values_ns / 1e3, [50.0, 99.0])
    return float(p[0]), float(p[1])


@dataclass(slots=True)
class Summary:
    """One case's figures (µs, counts)."""

    name: str
    rate_hz: float
    sent: int
    send_rate_hz: float
    slips: int
    raw_recv: int = 0
    raw: tuple[float, float] = (float("nan"), float("nan"))
    pose_recv: int = 0
    pose: tuple[float, float] = (float("nan"), float("nan"))
    vmc_recv: int = 0
    vmc_unmatched: int = 0
    vmc: tuple[float, float] = (float("nan"), float("nan"))
    stages: dict[str, tuple[float, float]] = field(default_factory=dict)
    # The daemon's own latency_us (ctl status) at the end: its post.<kind> stages.
    daemon_latency: dict[str, Any] = field(default_factory=dict)
    counters: dict[str, int] = field(default_factory=dict)
    input_drops: dict[str, int] = field(default_factory=dict)

    @property
    def drops(self) -> int:
        """Timed input frames the daemon did not solve."""
        return self.sent - self.counters.get("frames_solved", 0)


def summarize(r: Result) -> Summary:
    """Latencies and counts of one case."""
    n = len(r.sent_ns)
    span_s = (r.sent_ns[-1] - r.sent_ns[0]) * 1e-9 if n > 1 else float("nan")
    s = Summary(r.name, r.rate_hz, n, (n - 1) / span_s, r.slips)

    def lat(frames: np.ndarray, arrival: np.ndarray) -> np.ndarray:
        k = frames - r.frame0
        timed = (k >= 0) & (k < n)
        return arrival[timed] - r.sent_ns[k[timed]]

    if r.name.startswith(BASELINES):
        d = lat(r.recv["raw_frame"], r.recv["t_ns"])
        s.raw_recv, s.raw = len(d), _pct(d)
        return s
    pose = r.recv["pose"]
    arrival, frame, received, solved, sent = pose.T
    k = frame - r.frame0
    timed = (k >= 0) & (k < n)
    d = lat(frame, arrival)
    s.pose_recv, s.pose = len(d), _pct(d)
    send = r.sent_ns[k[timed]]
    s.stages = {
        "in": _pct(received[timed] - send),
        "solve": _pct(solved[timed] - received[timed]),
        "send": _pct(sent[timed] - solved[timed]),
        "out": _pct(arrival[timed] - sent[timed]),
    }
    idx = match_vmc_t(r.recv["t_val"], solved)
    ok = idx >= 0
    s.vmc_unmatched = int(np.count_nonzero(~ok))
    d = lat(frame[idx[ok]], r.recv["t_ns"][ok])
    s.vmc_recv, s.vmc = len(d), _pct(d)
    s.daemon_latency = dict(r.counters1.get("latency_us", {}))
    c0, c1 = r.counters0.get("counters", {}), r.counters1.get("counters", {})
    s.counters = {key: c1.get(key, 0) - c0.get(key, 0) for key in c1}
    for src in ("osc", "zmq"):
        d0 = r.counters0.get("drops", {}).get(src, {})
        for reason, v in r.counters1.get("drops", {}).get(src, {}).items():
            if reason != "accepted" and v - d0.get(reason, 0):
                s.input_drops[f"{src}.{reason}"] = v - d0.get(reason, 0)
    cap0 = (r.counters0.get("capture") or {}).get("drops", {})
    cap1 = r.counters1.get("capture") or {}
    for reason, v in cap1.get("drops", {}).items():
        if reason != "accepted" and v - cap0.get(reason, 0):
            s.input_drops[f"{cap1['system']}.{reason}"] = v - cap0.get(reason, 0)
    return s


def _num(x: Any) -> float:
    return float("nan") if x is None else float(x)


def _f(x: float) -> str:
    return "-" if not np.isfinite(x) else f"{x:.0f}"


def print_report(summaries: list[Summary], args: argparse.Namespace) -> None:
    """Tables and verdicts."""
    raw = {s.rate_hz: s for s in summaries if s.name.startswith("raw")}
    relay = {s.name: s for s in summaries if s.name.startswith("relay")}
    cases = [s for s in summaries if not s.name.startswith(BASELINES)]
    print(
        f"\n{args.seconds:g} s timed per case after {args.warmup:g} s of warm-up; "
        "daemon in latest-wins mode; latencies in µs, send -> arrival, "
        "time.monotonic_ns in every process"
    )
    head = (
        f"{'case':<24} {'sent':>6} {'rate Hz':>8} {'solved':>6} {'stale':>5} "
        f"{'drops':>5} {'pose rx':>7} {'VMC T rx':>8} {'unmatch':>7} "
        f"{'overrun':>7} {'pub drop':>8} {'touched':>7} {'spun':>11}  input drops"
    )
    print("\nframes (timed phase; daemon counters are deltas over it)")
    print(head)
    print("-" * len(head))
    for s in summaries:
        if s.name.startswith(BASELINES):
            print(f"{s.name:<24} {s.sent:>6} {s.send_rate_hz:8.1f} {'':>6} {'':>5} "
                  f"{s.sent - s.raw_recv:>5} {'':>7} {s.raw_recv:>8}")  # fmt: skip
            continue
        c = s.counters
        print(
            f"{s.name:<24} {s.sent:>6} {s.send_rate_hz:8.1f} "
            f"{c.get('frames_solved', 0):>6} {c.get('stale', 0):>5} {s.drops:>5} "
            f"{s.pose_recv:>7} {s.vmc_recv:>8} {s.vmc_unmatched:>7} "
            f"{c.get('overruns', 0):>7} {c.get('send_drops', 0):>8} "
            f"{c.get('prewarm', 0):>7} "
            f"{c.get('spins_caught', 0):>5}/{c.get('spins', 0):<5}  "
            f"{s.input_drops or 0}"
        )
    print(
        "drops = sent - solved; stale = received but skipped for a newer frame "
        "(latest wins); unmatch = VMC Ts whose pose message never arrived; touched "
        "= the fit's touches before a frame ([loop] prewarm_ms); spun = windows a "
        "frame ended / windows spun in ([loop] spin_us): how often the paced "
        "stream was steady enough for them on this machine"
    )
    head = (
        f"{'case':<24} {'raw UDP p50/p99':>16} {'VMC T p50/p99':>14} "
        f"{'added':>12} {'pose p50/p99':>13} {'added':>12}"
    )
    print("\nlatency, µs (added = case percentile - raw UDP percentile, same rate)")
    print(head)
    print("-" * len(head))
    for s in summaries:
        b = raw.get(s.rate_hz)
        rp = b.raw if b else (float("nan"),) * 2
        if s.name.startswith("raw"):
            print(f"{s.name:<24} {_f(rp[0]):>7} / {_f(rp[1]):<6}")
            continue
        if s.name.startswith("relay"):
            print(
                f"{s.name:<24} {_f(rp[0]):>7} / {_f(rp[1]):<6} "
                f"{_f(s.raw[0]):>6} / {_f(s.raw[1]):<5} "
                f"{_f(s.raw[0] - rp[0]):>5} / {_f(s.raw[1] - rp[1]):<4}"
                "   (the relay's datagram, in the VMC columns)"
            )
            continue
        av = (s.vmc[0] - rp[0], s.vmc[1] - rp[1])
        ap = (s.pose[0] - rp[0], s.pose[1] - rp[1])
        print(
            f"{s.name:<24} {_f(rp[0]):>7} / {_f(rp[1]):<6} "
            f"{_f(s.vmc[0]):>6} / {_f(s.vmc[1]):<5} {_f(av[0]):>5} / {_f(av[1]):<4} "
            f"{_f(s.pose[0]):>5} / {_f(s.pose[1]):<5} {_f(ap[0]):>5} / {_f(ap[1]):<4}"
        )
    head = (
        f"{'case':<24} {'in p50/p99':>13} {'solve p50/p99':>14} {'send p50/p99':>13} "
        f"{'out p50/p99':>13}"
    )
    print(
        "\npose stream by stage, µs, from the pose header's stamps: in = send -> "
        "daemon received; solve = received -> solved (incl. queueing); "
        "send = solved -> sent (VMC + pose); out = sent -> arrival"
    )
    print(head)
    print("-" * len(head))
    for s in cases:
        st = s.stages
        cols = " ".join(
            f"{_f(st[k][0]):>6} / {_f(st[k][1]):<6}"
            for k in ("in", "solve", "send", "out")
        )
        print(f"{s.name:<24} {cols}")
    post = [(s, k, v) for s in cases for k, v in s.daemon_latency.items()
            if k.startswith("post.")]  # fmt: skip
    if post:
        print(
            "\n[[pipeline]] stages, µs p50 / p99, the daemon's own timing (ctl status "
            "latency_us, last 4096 frames; each a part of its solve stage)"
        )
        for s, k, v in post:
            solve = s.daemon_latency.get("solve", [None, None])
            print(
                f"{s.name:<24} {k:<16} {_f(_num(v[0])):>5} / {_f(_num(v[1])):<5} "
                f"(solve {_f(_num(solve[0]))} / {_f(_num(solve[1]))})"
            )
    print()
    for s in cases:
        b = raw.get(s.rate_hz)
        if s.rate_hz == 240 and b is not None:
            for out, p in (("VMC T", s.vmc), ("pose", s.pose)):
                print(
                    f"added p99 at 240 Hz, {s.name} -> {out}: "
                    f"{_f(p[1] - b.raw[1])} µs (target <= {ADDED_P99_TARGET_US:.0f} µs)"
                )
    for s in cases:
        if s.rate_hz == 1000:
            print(
                f"drops at 1000 Hz, {s.name}: {s.drops} of {s.sent} "
                f"(target 0; stale {s.counters.get('stale', 0)}, latest wins)"
            )
    for s in cases:
        b = raw.get(s.rate_hz)
        variant = s.name.partition(" Hz")[2].strip() or "body"
        target = HOT_PATH_TARGETS_US.get(variant)
        if b is None or target is None:
            continue
        for out, p in (("VMC T", s.vmc), ("pose", s.pose)):
            print(
                f"hot path (issue 19): added p99, {s.name} -> {out}: "
                f"{_f(p[1] - b.raw[1])} µs (target <= {target:.0f} µs, quiet machine)"
            )
    for r in relay.values():
        b = raw.get(r.rate_hz)
        what = (
            "one compiled call, two sends"
            if r.name.startswith("relay+")
            else "poll, receive, send; nothing else"
        )
        if r.name.startswith("relay-"):
            what = RELAY_WHAT[r.name.split(" ", 1)[0]]
        if b is not None:
            print(
                f"floor: a Python relay ({what}) adds "
                f"{_f(r.raw[0] - b.raw[0])} / {_f(r.raw[1] - b.raw[1])} µs "
                f"(p50 / p99) at {r.rate_hz:g} Hz"
            )


# ---- main ----------------------------------------------------------------------------


def _print_pairs(summaries: list[Summary]) -> None:
    lines = pair_floor_lines(summaries)
    if lines:
        print("\nagainst the pair's relay (added p99 over raw UDP, same rate)")
        for line in lines:
            print(line)


def _load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def _calibrate(tmp: Path) -> Path:
    out = tmp / "pig_calibration.json"
    cmd = [sys.executable, "-m", "retargetd.daemon", "calibrate",
           str(PIG_CALIBRATION), "--rig", "plug-in-gait",
           "--out", str(out)]  # fmt: skip
    subprocess.run(cmd, check=True, capture_output=True, timeout=120)
    return out


def _valid_variant(variant: str) -> bool:
    """``body``, ``pipeline``, ``console``, ``console+browser``, or ``fit``, ``face``,
    ``validate`` joined by ``+``; any of them ``+pipeline``, then any ``+plant``,
    then any ``+spin``."""
    variant = variant.removesuffix("+spin").removesuffix("+plant")
    variant = variant.removesuffix("+pipeline")
    parts = variant.split("+")
    return variant in ("body", "pipeline", "console", "console+browser") or (
        len(set(parts)) == len(parts)
        and all(p in ("fit", "face", "validate", "cold") for p in parts)
        and parts != ["cold"]
    )


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; returns the exit code."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=10.0, help="timed s per case")
    parser.add_argument("--warmup", type=float, default=0.5, help="untimed s per case")
    parser.add_argument(
        "--rounds", type=int, default=1,
        help="run every case (baselines too) this many times, interleaved; the "
        "added p99 of each round against its own raw UDP, and their median",
    )  # fmt: skip
    parser.add_argument("--rates", default="240,1000", help="send rates, Hz")
    parser.add_argument(
        "--transports",
        default="osc,zmq",
        help="osc, zmq, natnet, qtm (comma-separated)",
    )
    parser.add_argument(
        "--variants", default="body,face",
        help="body, fit, face, validate, or joined by +; console, console+browser; "
        "pipeline (+pipeline adds the post stages to any; +cold turns the fit's "
        "touch off) (comma-separated)",
    )  # fmt: skip
    args = parser.parse_args(argv)
    variants = [v for v in args.variants.split(",") if v]
    rates = [float(r) for r in args.rates.split(",") if r]
    transports = [t for t in args.transports.split(",") if t]
    if (
        args.seconds <= 0
        or args.warmup < 0
        or args.rounds < 1
        or not rates
        or any(not 1 <= r <= 10_000 for r in rates)
        or any(t not in ("osc", "zmq", *CAPTURE_TRANSPORTS) for t in transports)
        or any(not _valid_variant(v) for v in variants)
    ):
        parser.error(
            "--seconds > 0, --warmup >= 0, --rounds >= 1, rates in [1, 10000], "
            "osc/zmq/natnet/qtm, variants "
            "body, or fit/face/validate/cold joined by +, console, console+browser, "
            "any +pipeline"
        )
    if "console+browser" in variants and not (
        shutil.which("chromium") and shutil.which("chromedriver")
    ):
        print("console+browser skipped: chromium / chromedriver not installed")
        variants = [v for v in variants if v != "console+browser"]
    if not (PIG_MOTION.is_file() and PIG_CALIBRATION.is_file()):
        print(f"datasets not found at {DATASETS / 'btkdata'}", file=sys.stderr)
        return 1
    from retargetd.replay.takes import load_take

    take = load_take(PIG_MOTION)
    print(
        f"take {PIG_MOTION.name}: {take.n_frames} frames at {take.rate_hz:g} Hz, "
        f"{take.n_markers} markers (compact frame {48 + 12 * take.n_markers} bytes), "
        f"looped; {os.cpu_count()} CPUs, load average {_load()}"
    )
    ctx = mp.get_context("spawn")
    summaries: list[Summary] = []
    with tempfile.TemporaryDirectory(prefix="bench_latency_") as tmp_name:
        tmp = Path(tmp_name)
        calibration = _calibrate(tmp)
        streams: dict[str, Any] = {v: None for v in variants}
        if any("face" in v for v in variants):
            training, labels, positions = _face_stream(take, np.random.default_rng(0))
            training.save(tmp / "face.npz")
            for v in variants:
                if "face" in v:
                    streams[v] = (labels, positions)
            print(
                f"face variants: {len(training.marker_names)} facial markers x "
                f"{training.k} shapes on the walk's head; {len(labels)} markers "
                f"per frame (compact frame {48 + 12 * len(labels)} bytes)"
            )
        plan = [(b, r, "body") for b in _baselines(transports) for r in rates] + [
            (t, r, v) for v in variants for t in transports for r in rates
        ]
        rounds: list[list[Summary]] = []
        for k in range(args.rounds):
            if args.rounds > 1:
                print(f"round {k + 1} of {args.rounds} (load average {_load()})")
            summaries = []
            for transport, rate, variant in plan:
                t0 = time.monotonic()
                result = run_case(
                    ctx, transport, rate, args, take, calibration, tmp, variant,
                    streams.get(variant),
                )  # fmt: skip
                summaries.append(summarize(result))
                took = time.monotonic() - t0
                print(f"  {result.name}: done in {took:.1f} s", flush=True)
            rounds.append(summaries)
    for k, summaries in enumerate(rounds):
        if args.rounds > 1:
            print(f"\n======== round {k + 1} of {args.rounds}")
        print_report(summaries, args)
        _print_pairs(summaries)
    if args.rounds > 1:
        print_rounds(rounds)
    print(f"load average at the end: {_load()}")
    return 0


def _baselines(transports: list[str]) -> list[str]:
    """The baselines a run needs: raw UDP, the UDP relays, and each pair relay of the
    transports asked for (the ZeroMQ input's only with ``zmq``)."""
    keep = ["raw", "relay", "relay+", "relay-pub"]
    if "zmq" in transports:
        keep += ["relay-zmq", "relay-zmq-pub"]
    return [b for b in BASELINES if b in keep]


def _transport(name: str) -> str:
    """A case's input transport, from its name (``"zmq 240 Hz fit"`` -> ``zmq``)."""
    return name.split(" ", 1)[0]


def pair_floor_lines(summaries: list[Summary]) -> list[str]:
    """Each daemon case's added p99 (over raw UDP, same rate) against the added p99
    of the relay of its input -> output pair (:data:`PAIR_RELAY`), same rate and
    round: the ratio issue 35 item 2 bounds by 1.25."""
    raw = {s.rate_hz: s for s in summaries if s.name.startswith("raw")}
    relays = {(s.name.split(" ", 1)[0], s.rate_hz): s for s in summaries
              if s.name.startswith("relay")}  # fmt: skip
    out = []
    for s in summaries:
        if s.name.startswith(BASELINES):
            continue
        b = raw.get(s.rate_hz)
        for what, p in (("vmc", s.vmc), ("pose", s.pose)):
            relay_name = PAIR_RELAY.get((_transport(s.name), what))
            r = relays.get((relay_name, s.rate_hz)) if relay_name else None
            if b is None:
                continue
            added = p[1] - b.raw[1]
            label = f"{s.name} -> {'VMC T' if what == 'vmc' else 'pose'}"
            if r is None:
                out.append(f"{label:<36} added p99 {_f(added):>6} µs; no pair relay")
                continue
            floor = r.raw[1] - b.raw[1]
            ratio = added / floor if floor > 0 else float("nan")
            out.append(
                f"{label:<36} added p99 {_f(added):>6} µs; {relay_name} "
                f"{_f(floor):>6} µs; ratio {ratio:5.2f} (target <= 1.25)"
            )
    return out


def print_rounds(rounds: list[list[Summary]]) -> None:
    """Each case's added p99 over the rounds (each round's raw UDP baseline), the
    median of the rounds and their range: the machine drifts between cases of a
    round, and one round's p99 against one raw p99 is one draw of that drift."""
    print(
        f"\nadded p99 over raw UDP by round (each against its round's raw), µs; "
        f"median [min, max] of {len(rounds)} rounds"
    )
    print(f"{'case':<28} {'VMC T':>22} {'pose':>22}   rounds (VMC T)")
    for j, first in enumerate(rounds[0]):
        if first.name.startswith("raw"):
            continue
        cols, per = [], []
        for out in ("vmc", "pose"):
            vals = []
            for summaries in rounds:
                s = summaries[j]
                b = next(x for x in summaries if x.name == f"raw {s.rate_hz:g} Hz")
                p = s.raw if s.name.startswith("relay") else getattr(s, out)
                vals.append(p[1] - b.raw[1])
            if out == "vmc":
                per = vals
            if first.name.startswith("relay") and out == "pose":
                cols.append("")
                continue
            v = np.array(vals)
            cols.append(f"{_f(np.median(v))} [{_f(v.min())}, {_f(v.max())}]")
        print(
            f"{first.name:<28} {cols[0]:>22} {cols[1]:>22}   "
            + " ".join(_f(x) for x in per)
        )
    # each case against its pair's relay: the median over rounds of each side
    print("\nagainst the pair's relay, median of rounds (added p99 over raw UDP), µs")
    for j, first in enumerate(rounds[0]):
        if first.name.startswith(BASELINES):
            continue
        for what in ("vmc", "pose"):
            relay_name = PAIR_RELAY.get((_transport(first.name), what))
            if relay_name is None:
                continue
            case_v, relay_v = [], []
            for summaries in rounds:
                s = summaries[j]
                b = next(x for x in summaries if x.name == f"raw {s.rate_hz:g} Hz")
                want = f"{relay_name} {s.rate_hz:g} Hz"
                r = next((x for x in summaries if x.name == want), None)
                if r is None:
                    continue
                case_v.append(getattr(s, what)[1] - b.raw[1])
                relay_v.append(r.raw[1] - b.raw[1])
            if not case_v:
                continue
            c, f = float(np.median(case_v)), float(np.median(relay_v))
            print(
                f"{first.name + (' -> VMC T' if what == 'vmc' else ' -> pose'):<36} "
                f"{_f(c):>6} vs {relay_name} {_f(f):>6}: ratio "
                f"{c / f if f > 0 else float('nan'):5.2f} (target <= 1.25)"
            )


if __name__ == "__main__":
    with contextlib.suppress(KeyboardInterrupt):
        sys.exit(main())
    sys.exit(130)
