"""Authenticated marker input (issue 30 item 5), at a daemon on loopback (the live
harness: daemons in threads, ephemeral ports, every wait bounded):

- ``[input.osc] key_file``: signed datagrams are solved; unsigned ones, a tag of
  another key and a datagram sent again are refused before parsing and counted in
  ``ctl status --json`` (``drops.osc``); a restarted sender is taken at once;
  ``retargetd replay --key-file`` feeds such a daemon, an unsigned replay does not;
- ``[input.zmq]`` CURVE, as the control socket's: a listed client's frames go
  through, a plain or unlisted client's do not; a SUB as a CURVE client;
- a marker input off loopback without a key prints one warning line;
- the keys' config rules and ``retargetd keys --hmac``.

The trailer itself, byte for byte: ``tests/protocols/test_osc_auth.py`` and
``test_protocols_md.py``; ``retargetd record --key-file``:
``test_cmd_record_replay.py``.
"""

from __future__ import annotations

import contextlib
import os
import stat
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import live_harness as _live
import numpy as np
import pytest
import zmq

from retargetd.daemon.cli.main import main as cli_main
from retargetd.daemon.live.config import ConfigError, DaemonConfig
from retargetd.daemon.live.surface import CurveGuard, curve_client, load_hmac_key
from retargetd.protocols import pose_stream, zmq_wire
from retargetd.protocols.marker_input import LabelSet
from retargetd.protocols.osc_auth import DatagramSigner
from retargetd.replay.c3d import write_c3d

PoseSub, _take, _wait_until = _live.PoseSub, _live._take, _live._wait_until


@pytest.fixture
def keys(tmp_path: Path) -> Path:
    """HMAC keys ``bridge.hmac`` and ``intruder.hmac``; CURVE pairs ``daemon``,
    ``bridge`` and ``intruder``."""
    folder = tmp_path / "keys"
    folder.mkdir()
    for name in ("bridge", "intruder"):
        assert cli_main(["keys", "--hmac", name, "--dir", str(folder)]) == 0
    for name in ("daemon", "bridge", "intruder"):
        assert cli_main(["keys", name, "--dir", str(folder)]) == 0
    return folder


def _hold() -> np.ndarray:
    return np.asarray(_take().markers_world[_take().base_pose_frames][0])


def _drops(live: Any, name: str = "osc") -> dict[str, int]:
    drops: dict[str, int] = live.ctl({"cmd": "status"})["status"]["drops"][name]
    return drops


def test_signed_frames_are_solved_the_rest_refused_and_counted(
    start_daemon: Callable[..., Any],
    osc_source: Callable[..., Any],
    zmq_socket: Callable[[int], Any],
    exact_calibration: Path,
    keys: Path,
) -> None:
    live = start_daemon(
        {
            "performer": {"calibration": str(exact_calibration)},
            "input": {"osc": {"key_file": str(keys / "bridge.hmac")}},
        }
    )
    assert "signed only (HMAC-SHA256)" in live.daemon.endpoints["osc markers"]
    assert not [ln for ln in live.lines if ln.startswith("warning")]
    key = load_hmac_key(keys / "bridge.hmac")
    signer = DatagramSigner(key)
    sent: list[bytes] = []  # every signed datagram, as sent

    def sign(data: bytes) -> bytes:
        sent.append(signer.sign(data))
        return sent[-1]

    src = osc_source(live)
    src.sign = sign
    sub = PoseSub(zmq_socket(zmq.SUB), live.tcp("zmq poses"))
    src.announce()
    _live._prime(sub, lambda: src.send(_hold()))
    good = _drops(live)["accepted"]

    # Unsigned: an announcement and a spoofed frame 2^62 far off; another key's tag.
    plain = osc_source(live)
    plain.announce()
    plain.send(_hold() + 3.0, frame_id=2**62)
    forged = osc_source(live)
    forged.sign = DatagramSigner(load_hmac_key(keys / "intruder.hmac")).sign
    forged.send(_hold() + 3.0, frame_id=2**62)
    # Replays: the last signed datagram again, and the first (the announcement).
    src.sock.sendto(sent[-1], src.addr)
    src.sock.sendto(sent[0], src.addr)
    _wait_until(
        lambda: (
            _drops(live).get("auth_failed") == 3
            and _drops(live).get("auth_replayed") == 2
        ),
        "the refusals counted",
    )
    last = src.send(_hold())  # the genuine stream goes on, unharmed
    sub.wait(lambda: bool(sub.poses) and sub.poses[-1].frame_id == last, "a pose")
    assert [p.frame_id for p in sub.poses] == [last]  # nothing spoofed got through
    drops = _drops(live)
    assert drops["accepted"] == good + 1 and drops.get("restart", 0) == 0
    assert live.daemon.osc_stream.labels_taken == 1  # the refused ones not taken

    # The bridge restarts: a new session, frame numbers from 0, taken at once as a
    # restarted source (unsigned numbers going back need 3 frames to be believed).
    src.sign = DatagramSigner(key, session=signer.session + 1).sign
    src.next_id = 0
    first = src.send(_hold())
    sub.wait(lambda: sub.poses[-1].frame_id == first, "the restarted bridge's pose")
    assert sub.poses[-1].flags & pose_stream.FRAME_RESTARTED
    assert _drops(live)["restart"] == 1


def test_replay_with_the_key_file_feeds_a_signed_daemon(
    start_daemon: Callable[..., Any],
    exact_calibration: Path,
    keys: Path,
    tmp_path: Path,
) -> None:
    take = _take()
    path = tmp_path / "exact.c3d"
    write_c3d(path, take.labels, take.markers_world[:40], take.rate_hz, units="m")
    live = start_daemon(
        {
            "performer": {"calibration": str(exact_calibration)},
            "input": {"osc": {"key_file": str(keys / "bridge.hmac")}},
            "loop": {"process_every_frame": True},
        }
    )
    host, port = live.udp("osc markers")
    to = ["--to", f"osc://{host}:{port}", "--speed", "0"]
    assert cli_main(["replay", str(path), *to]) == 0  # unsigned: all refused
    signed = ["--key-file", str(keys / "bridge.hmac")]
    assert cli_main(["replay", str(path), *to, *signed]) == 0
    _wait_until(lambda: live.daemon.stats.frames_out == 40, "40 poses")
    drops = _drops(live)
    assert drops["accepted"] == 40 and drops["auth_failed"] == 41  # 40 + the labels
    assert live.daemon.osc_stream.labels_taken == 1
    assert cli_main(["replay", str(path), "--to", "zmq://127.0.0.1:1", *signed]) == 2


def _zmq_labels_and_frames(n: int) -> list[list[bytes]]:
    labels = LabelSet(1, _take().labels)
    msgs = [zmq_wire.encode_zmq_labels(labels)]
    msgs += [zmq_wire.encode_zmq_frame(k, k / 100, 1, _hold()) for k in range(n)]
    return msgs


def _push(sock: Any, msgs: list[list[bytes]]) -> None:
    for parts in msgs:
        # nobody connected (a refused handshake): nothing queued
        with contextlib.suppress(zmq.Again):
            sock.send_multipart(parts, zmq.NOBLOCK)


def test_zmq_marker_input_under_curve_takes_only_the_listed_key(
    start_daemon: Callable[..., Any], zmq_socket: Callable[[int], Any], keys: Path
) -> None:
    live = start_daemon(
        {
            "input": {
                "zmq": {
                    "secret_key": str(keys / "daemon.key_secret"),
                    "client_keys": [str(keys / "bridge.key")],
                }
            }
        }
    )
    assert "CURVE: 1 client key(s)" in live.daemon.endpoints["zmq markers"]
    ep = live.tcp("zmq markers")
    plain = zmq_socket(zmq.PUSH)
    intruder = zmq_socket(zmq.PUSH)
    curve_client(intruder, keys / "intruder.key_secret", keys / "daemon.key")
    bridge = zmq_socket(zmq.PUSH)
    curve_client(bridge, keys / "bridge.key_secret", keys / "daemon.key")
    for sock in (plain, intruder, bridge):
        sock.connect(ep)
    _push(plain, _zmq_labels_and_frames(20))
    _push(intruder, _zmq_labels_and_frames(20))
    time.sleep(0.5)  # their handshakes fail meanwhile
    _push(bridge, _zmq_labels_and_frames(10))
    _wait_until(lambda: _drops(live, "zmq").get("accepted") == 10, "10 frames")
    time.sleep(0.3)
    assert _drops(live, "zmq") == {"accepted": 10}
    assert live.daemon.zmq_stream.labels_taken == 1


def test_a_zmq_sub_input_is_a_curve_client_of_the_publisher(
    start_daemon: Callable[..., Any], keys: Path
) -> None:
    guard = CurveGuard("test publisher")
    pub = guard.server_socket(
        zmq.PUB, str(keys / "bridge.key_secret"), (str(keys / "daemon.key"),)
    )
    try:
        port = pub.bind_to_random_port("tcp://127.0.0.1")
        live = start_daemon(
            {
                "input": {
                    "zmq": {
                        "mode": "sub",
                        "endpoint": f"tcp://127.0.0.1:{port}",
                        "secret_key": str(keys / "daemon.key_secret"),
                        "server_key": str(keys / "bridge.key"),
                    }
                }
            }
        )
        assert "(sub; " in live.daemon.endpoints["zmq markers"]
        assert "CURVE" in live.daemon.endpoints["zmq markers"]
        msgs = _zmq_labels_and_frames(1000)
        deadline = time.monotonic() + _live.WAIT_S
        k = 0
        while not _drops(live, "zmq").get("accepted"):  # slow joiner: publish on
            assert time.monotonic() < deadline, "no frame reached the SUB"
            pub.send_multipart(msgs[0] if k % 10 == 0 else msgs[1 + k % 1000])
            k += 1
            time.sleep(0.01)
    finally:
        pub.close()
        guard.close()


def test_marker_inputs_off_loopback_without_keys_print_one_warning_each(
    start_daemon: Callable[..., Any],
    monkeypatch: pytest.MonkeyPatch,
    keys: Path,
) -> None:
    # Taken as off loopback without binding anything but 127.0.0.1.
    from retargetd.daemon.live import inputs

    monkeypatch.setattr(inputs, "is_loopback_host", lambda host: False)
    monkeypatch.setattr(inputs, "endpoint_is_local", lambda ep: False)
    live = start_daemon()
    warnings = [ln for ln in live.lines if ln.startswith("warning")]
    assert len(warnings) == 2, warnings
    assert "osc markers" in warnings[0] and "key_file" in warnings[0]
    assert "zmq markers" in warnings[1] and "secret_key" in warnings[1]
    keyed = start_daemon(
        {
            "input": {
                "osc": {"key_file": str(keys / "bridge.hmac")},
                "zmq": {
                    "secret_key": str(keys / "daemon.key_secret"),
                    "client_keys": [str(keys / "bridge.key")],
                },
            }
        }
    )
    assert not [ln for ln in keyed.lines if ln.startswith("warning")]


def test_keys_hmac_writes_0600_and_never_overwrites(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert cli_main(["keys", "--hmac", "bridge", "--dir", str(tmp_path)]) == 0
    path = tmp_path / "bridge.hmac"
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert len(load_hmac_key(path)) == 32
    before = path.read_bytes()
    capsys.readouterr()
    assert cli_main(["keys", "--hmac", "bridge", "--dir", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "exists already" in err
    assert path.read_bytes() == before


def _key_file(tmp_path: Path, text: str, mode: int = 0o600) -> str:
    path = tmp_path / "k.hmac"
    path.write_text(text)
    os.chmod(path, mode)
    return str(path)


@pytest.mark.parametrize(
    ("make", "key", "text"),
    [
        (lambda t, k: {"osc": {"key_file": _key_file(t, "00" * 32, 0o644)}},
         "input.osc.key_file", "chmod 600"),
        (lambda t, k: {"osc": {"key_file": _key_file(t, "00" * 16)}},
         "input.osc.key_file", "64-128 hex digits"),
        (lambda t, k: {"osc": {"key_file": _key_file(t, "zz" * 32)}},
         "input.osc.key_file", "hex digits"),
        (lambda t, k: {"osc": {"key_file": _key_file(t, "# only a comment\n")}},
         "input.osc.key_file", "found 0 lines"),
        (lambda t, k: {"zmq": {"server_key": str(k / "bridge.key")}},
         "input.zmq.server_key", 'mode = "sub"'),
        (lambda t, k: {"zmq": {"secret_key": str(k / "daemon.key_secret")}},
         "input.zmq.client_keys", "public keys of the allowed clients"),
        (lambda t, k: {"zmq": {"mode": "sub", "client_keys": [str(k / "bridge.key")]}},
         "input.zmq.client_keys", 'mode = "pull"'),
        (lambda t, k: {"zmq": {"mode": "sub",
                               "secret_key": str(k / "daemon.key_secret")}},
         "input.zmq.server_key", "publisher's server_key"),
    ],
)  # fmt: skip
def test_key_config_errors_name_the_key(
    tmp_path: Path, keys: Path, make: Callable[..., Any], key: str, text: str
) -> None:
    with pytest.raises(ConfigError) as info:
        DaemonConfig.from_dict({"input": make(tmp_path, keys)}, source="test")
    message = str(info.value)
    assert f"test: {key}: " in message and text in message, message
    assert "\n" not in message
