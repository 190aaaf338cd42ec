"""Damaged recordings found by ``bench/fuzz.py`` (issue 12 item 6): the tolerant
reader raised ``MemoryError``/``OverflowError`` on a record length past the end of
the file, and ``read_mcap_take`` let ``JSONDecodeError`` and ``ValueError`` out of
damaged metadata and envelopes; both now stop cleanly or raise ``TakeError``."""

from __future__ import annotations

import struct
import time
from pathlib import Path

import numpy as np
import pytest

from retargetd.protocols import osc_in
from retargetd.protocols.marker_input import LabelSet
from retargetd.replay import recording as rf
from retargetd.replay.recorder import InputInfo, open_recorder
from retargetd.replay.take import TakeError

LABELS = LabelSet(1, ("LASI", "RASI", "LPSI"))


def _recording(path: Path, n: int = 20) -> bytes:
    rec = open_recorder(path, (InputInfo(name="osc", form="osc-compact"),))
    t0 = time.monotonic_ns()
    rec.record_packet("osc", rf.FORM_OSC_COMPACT, t0, osc_in.encode_labels(LABELS))
    rng = np.random.default_rng(0)
    for i in range(n):
        frame = osc_in.encode_compact_frame(i, i / 100, 1, rng.uniform(0, 1, (3, 3)))
        rec.record_packet("osc", rf.FORM_OSC_COMPACT, t0 + i * 10_000_000, frame)
    rec.close()
    return path.read_bytes()


@pytest.mark.parametrize("length", [2**63, 2**64 - 1, 1 << 40])
def test_a_record_length_past_the_end_stops_the_read(
    tmp_path: Path, length: int
) -> None:
    data = _recording(tmp_path / "good.mcap")
    half = tmp_path / "half.mcap"
    half.write_bytes(data[: len(data) // 2])
    cut = rf.read_recording(half).bytes_read
    assert cut > 0
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(data[:cut] + struct.pack("<BQ", 0x05, length) + b"x" * 64)
    rec = rf.read_recording(bad)
    assert not rec.complete
    assert rec.stop_reason == f"record cut short at byte {cut}"
    assert rec.bytes_read == cut


def test_damaged_inputs_metadata_is_a_take_error(tmp_path: Path) -> None:
    data = _recording(tmp_path / "good.mcap")
    key = b'[{"name"'
    assert data.count(key) >= 1
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(data.replace(key, b'[{"name' + b"\x00", 1))  # same length
    rec = rf.read_recording(bad)
    with pytest.raises(TakeError, match="inputs metadata"):
        rec.inputs()
    with pytest.raises(TakeError, match="inputs metadata"):
        rf.read_mcap_take(bad)


def test_inputs_metadata_of_the_wrong_shape_is_a_take_error(tmp_path: Path) -> None:
    data = _recording(tmp_path / "good.mcap")
    key = b'[{"name"'
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(data.replace(key, b'"{"name"', 1))  # a string, not a list
    with pytest.raises(TakeError):
        rf.read_mcap_take(bad)


def test_a_damaged_declared_up_axis_is_a_take_error(tmp_path: Path) -> None:
    data = _recording(tmp_path / "good.mcap")
    key = b'"up": "+Z"'
    assert key in data, data[:400]
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(data.replace(key, b'"up": "+["', 1))
    with pytest.raises(TakeError, match="damaged"):
        rf.read_mcap_take(bad)
