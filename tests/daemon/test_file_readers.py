"""Every file reader is total (issue 30 item 2): a config, rig, face config,
calibration, batch manifest, pipeline, retarget map or marker set file of any depth,
size or encoding gives one line of the reader's own error (the CLI's exit 2), never a
traceback; and a daemon whose rig file turns into one keeps running through a show
control ``/rtd/reload`` and answers ``ctl reload`` with the file's reason.

Property tests (hypothesis) generate nested arrays and inline tables of any depth
from just past :data:`files.MAX_DEPTH` to far past Python's recursion limit,
non-UTF-8 bytes anywhere, and a file past :data:`files.MAX_TEXT_BYTES`.
"""

from __future__ import annotations

import shutil
import socket
import time
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import zmq
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from live_harness import EXACT_RIG, PoseSub, _wait_until
from pythonosc.osc_message_builder import OscMessageBuilder

from retargetd.daemon import files
from retargetd.daemon.body.calibration import CalibrationError, load_calibration
from retargetd.daemon.body.rig import RigError, load_rig
from retargetd.daemon.cli.batch_jobs import BatchError, load_manifest
from retargetd.daemon.cli.main import main
from retargetd.daemon.cli.post_io import load_pipeline_entries
from retargetd.daemon.errors import UsageError
from retargetd.daemon.face.config import FaceConfigError, load_face_config
from retargetd.daemon.face.training import TrainingSet
from retargetd.daemon.live.config import DaemonConfig
from retargetd.daemon.live.config_schema import ConfigError
from retargetd.daemon.synth.markerset import load_markerset

pytestmark = pytest.mark.timeout(120)

#: reader name -> (suffix, read(path), the error it raises)
READERS: dict[str, tuple[str, Callable[[Path], Any], type[Exception]]] = {
    "config": (".toml", DaemonConfig.from_toml, ConfigError),
    "rig": (".toml", load_rig, RigError),
    "face config": (".toml", load_face_config, FaceConfigError),
    "calibration": (".json", load_calibration, CalibrationError),
    "batch manifest": (".toml", load_manifest, BatchError),
    "pipeline": (".toml", load_pipeline_entries, UsageError),
    "marker set": (".toml", load_markerset, ValueError),
}


def _nested(kind: str, depth: int, json: bool) -> str:
    """A document nesting ``depth`` arrays or inline tables (objects) deep."""
    if kind == "array":
        inner = "[" * depth + "]" * depth
    else:
        key = '"a"' if json else "a"
        sep = ":" if json else " ="
        inner = f"{{{key}{sep} " * depth + "1" + "}" * depth
    return f'{{"x": {inner}}}' if json else f"x = {inner}\n"


def _one_line(exc: BaseException, path: Path) -> str:
    text = str(exc)
    assert "\n" not in text, text
    assert str(path) in text, text
    return text


@settings(max_examples=25, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])  # fmt: skip
@given(
    reader=st.sampled_from(sorted(READERS)),
    kind=st.sampled_from(["array", "table"]),
    depth=st.integers(min_value=files.MAX_DEPTH + 1, max_value=5000),
)
def test_nesting_of_any_depth_is_one_line(
    tmp_path: Path, reader: str, kind: str, depth: int
) -> None:
    suffix, read, error = READERS[reader]
    path = tmp_path / f"nested{suffix}"
    path.write_text(_nested(kind, depth, json=suffix == ".json"))
    with pytest.raises(error) as caught:
        read(path)
    assert "nested more than 32 levels" in _one_line(caught.value, path)


@settings(max_examples=25, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])  # fmt: skip
@given(
    reader=st.sampled_from(sorted(READERS)),
    head=st.text(st.characters(min_codepoint=32, max_codepoint=126), max_size=40),
    bad=st.sampled_from([b"\xff", b"\xc3\x28", b"\xe2\x82", b"\x80"]),
)
def test_bytes_that_are_not_utf8_are_one_line(
    tmp_path: Path, reader: str, head: str, bad: bytes
) -> None:
    # ASCII before the bad bytes, so nothing before them completes a character
    suffix, read, error = READERS[reader]
    path = tmp_path / f"binary{suffix}"
    path.write_bytes(b"x = 1\n# " + head.encode() + bad + b"\n")
    with pytest.raises(error) as caught:
        read(path)
    text = _one_line(caught.value, path)
    assert "not UTF-8" in text or "not valid" in text, text


@pytest.mark.parametrize("reader", sorted(READERS))
def test_a_huge_file_is_one_line_without_reading_it_all(
    tmp_path: Path, reader: str
) -> None:
    suffix, read, error = READERS[reader]
    path = tmp_path / f"huge{suffix}"
    with path.open("wb") as fh:  # a sparse file: 1 GiB that costs nothing
        fh.truncate(1 << 30)
    t0 = time.perf_counter()
    with pytest.raises(error) as caught:
        read(path)
    assert "larger than 16 MiB" in _one_line(caught.value, path)
    print(f"{reader}: refused a 1 GiB file in {time.perf_counter() - t0:.3f} s")


def test_the_cli_exits_2_with_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    nested = _nested("array", 500, json=False)  # the 1 KB config
    config, rig = tmp_path / "deep.toml", tmp_path / "deep-rig.toml"
    config.write_text(nested)
    rig.write_text(nested)
    for argv in (
        ["run", "--config", str(config)],
        [
            "calibrate",
            str(config),
            "--rig",
            str(rig),
            "--out",
            str(tmp_path / "c.json"),
        ],
    ):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "nested more than 32 levels" in err, err


def _osc(address: str) -> bytes:
    return OscMessageBuilder(address=address).build().dgram


def test_a_running_daemon_survives_a_nested_rig_on_reload(
    tmp_path: Path,
    start_daemon: Callable[..., Any],
    osc_source: Callable[..., Any],
    udp_socket: Callable[..., socket.socket],
    zmq_socket: Callable[[int], Any],
    streamer: Callable[[Any], Any],
    exact_calibration: Path,
) -> None:
    """The rig file becomes 500 nested arrays while the daemon streams: show
    control's ``/rtd/reload`` and ``ctl reload`` both refuse it with the file's
    reason, the daemon keeps its rig and the pose stream goes on."""
    rig = tmp_path / "rig.toml"
    shutil.copyfile(EXACT_RIG, rig)
    live = start_daemon(
        {
            "performer": {"rig": str(rig), "calibration": str(exact_calibration)},
            "control": {"min_interval_s": 0.05},
        }
    )
    sub = PoseSub(zmq_socket(zmq.SUB), live.tcp("zmq poses"))
    feed = streamer(osc_source(live))
    sub.wait(lambda: len(sub.poses) > 20, "the stream")
    rig.write_text(_nested("array", 500, json=False))
    sock = udp_socket()
    sock.sendto(_osc("/rtd/reload"), live.udp("show control"))
    _wait_until(
        lambda: any("reload failed" in ln and "nested" in ln for ln in live.lines),
        "the show-control reload's refusal",
    )
    n = len(sub.poses)
    sub.wait(lambda: len(sub.poses) > n + 20, "poses after the reload")
    time.sleep(0.06)  # control.min_interval_s
    reply = live.ctl({"cmd": "reload"})
    feed.stop()
    message = str(reply.get("message", reply.get("error", "")))
    assert "reload failed" in message and "nested more than 32 levels" in message, reply
    assert str(rig) in message and "request" not in message
    assert live.daemon.rig.name  # the running rig kept


@settings(max_examples=25, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])  # fmt: skip
@given(data=st.binary(max_size=2000), zip_head=st.booleans())
def test_a_face_training_file_of_any_bytes_is_one_line(
    tmp_path: Path, data: bytes, zip_head: bool
) -> None:
    # any bytes (a zip's signature first or not: a broken archive) read as a training
    # set are one ValueError line naming the file
    path = tmp_path / "training.npz"
    path.write_bytes((b"PK\x03\x04" if zip_head else b"") + data)
    with pytest.raises(ValueError) as caught:
        TrainingSet.load(path)
    assert "not a face training set" in _one_line(caught.value, path)


def test_a_zip_bomb_training_file_is_refused_before_it_unpacks(tmp_path: Path) -> None:
    path = tmp_path / "bomb.npz"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("deltas.npy", b"\0" * (65 << 20))  # 65 MiB of zeros, ~65 KB
    assert path.stat().st_size < 1 << 20
    with pytest.raises(ValueError) as caught:
        TrainingSet.load(path)
    assert "65 MiB unpacked" in _one_line(caught.value, path)
    # and a run's config that names it: one line, exit 2
    config = tmp_path / "face.toml"
    config.write_text(f"[face]\ntraining = {str(path)!r}\n")
    with pytest.raises(ConfigError) as refused:
        DaemonConfig.from_toml(config)
    assert "65 MiB unpacked" in _one_line(refused.value, path)
