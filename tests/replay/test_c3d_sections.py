"""C3D parameter sections other readers open (issue 31, item 9): each fault made from a
clean file written by :func:`write_c3d`, at ``POINT:LABELS`` where the real files had
it, read as BTK reads it, the repair named by ``take info``.

- a description length (211) longer than the bytes left before the next entry;
- a next-entry offset pointing inside its own entry;
- a next-entry offset pointing past the parameter section (past the file, or into the
  data section).

A fault with nothing safe to read on from fails in one line, exit 2.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest

from retargetd.daemon.cli.main import main
from retargetd.replay.c3d import read_c3d, write_c3d
from retargetd.replay.c3d_fallback import READER_NAME
from retargetd.replay.take import Take, TakeError

LABELS = ("LFHD", "RFHD", "LKNE", "RKNE", "LHEE", "RHEE")
#: The description the clean file gives POINT:LABELS (the fault overstates it).
DESCRIPTION = b"marker names"


def _entries(data: bytes) -> dict[str, tuple[int, int, int]]:
    """``GROUP:NAME`` -> (entry start, offset word position, next entry), Intel."""
    pos = (data[0] - 1) * 512 + 4
    groups: dict[int, str] = {}
    out: dict[str, tuple[int, int, int]] = {}
    while (n_name := struct.unpack_from("b", data, pos)[0]) != 0:
        gid = struct.unpack_from("b", data, pos + 1)[0]
        name = data[pos + 2 : pos + 2 + abs(n_name)].decode()
        at = pos + 2 + abs(n_name)
        offset = struct.unpack_from("<H", data, at)[0]
        if gid < 0:
            groups[-gid] = name
        else:
            name = f"{groups[gid]}:{name}"
        out[name] = (pos, at, at + offset)
        if offset == 0:
            break
        pos = at + offset
    return out


def _clean(tmp_path: Path) -> tuple[Path, bytearray]:
    """A clean file whose POINT:LABELS carries a 12-character description."""
    rng = np.random.default_rng(3)
    pos = rng.uniform([-1.0, -1.0, 0.0], [1.0, 1.0, 1.8], (30, len(LABELS), 3))
    pos[4:9, 2] = np.nan
    path = tmp_path / "clean.c3d"
    write_c3d(path, LABELS, pos, 100.0)
    data = bytearray(path.read_bytes())
    _, at, following = _entries(data)["POINT:LABELS"]
    assert data[following - 1] == 0  # ezc3d writes no description
    # Insert the description; take as many bytes of the section's zero padding
    # (before the data block) so that the data stays where the header says.
    data[following - 1 : following] = bytes([len(DESCRIPTION)]) + DESCRIPTION
    struct.pack_into("<H", data, at, following + len(DESCRIPTION) - at)
    data_at = (struct.unpack_from("<H", data, 16)[0] - 1) * 512
    padding = data[data_at : data_at + len(DESCRIPTION)]
    assert padding == bytes(len(DESCRIPTION))
    del data[data_at : data_at + len(DESCRIPTION)]
    path.write_bytes(bytes(data))
    take = read_c3d(path)
    assert take.repairs == () and take.labels == LABELS
    return path, data


def _faulty(tmp_path: Path, name: str, data: bytearray) -> Path:
    path = tmp_path / f"{name}.c3d"
    path.write_bytes(bytes(data))
    return path


def _same_take(got: Take, clean: Take) -> None:
    assert got.reader == READER_NAME
    assert got.labels == clean.labels
    assert (got.rate_hz, got.units, got.up_axis) == (
        clean.rate_hz,
        clean.units,
        clean.up_axis,
    )
    np.testing.assert_array_equal(got.valid, clean.valid)
    np.testing.assert_array_equal(got.positions, clean.positions)


def _info(path: Path, capsys: pytest.CaptureFixture[str]) -> tuple[str, dict]:
    assert main(["take", "info", str(path)]) == 0
    text = capsys.readouterr().out
    assert main(["take", "info", str(path), "--json"]) == 0
    return text, json.loads(capsys.readouterr().out)


def test_description_longer_than_the_bytes_left(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A 211-character description with 12 bytes before the next entry: BTK reads on
    from where the offset points; so do we, and the description is the 12 bytes."""
    path, data = _clean(tmp_path)
    _, _, following = _entries(data)["POINT:LABELS"]
    data[following - 1 - len(DESCRIPTION)] = 211
    faulty = _faulty(tmp_path, "desc211", data)
    take = read_c3d(faulty)
    _same_take(take, read_c3d(path))
    repair = (
        "POINT:LABELS description length 211 overstates the 12 bytes left before "
        "the next entry; read as 12"
    )
    assert repair in take.repairs
    text, info = _info(faulty, capsys)
    assert f"  {repair}\n" in text
    assert repair in info["repairs"]
    assert info["repairs"][0].startswith("ezc3d not used: ")


def test_offset_pointing_inside_its_entry(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """BTK seeks to the target, into the labels; we read on from the entry's end,
    where the next entry starts."""
    path, data = _clean(tmp_path)
    start, at, following = _entries(data)["POINT:LABELS"]
    struct.pack_into("<H", data, at, 10)
    faulty = _faulty(tmp_path, "inside", data)
    take = read_c3d(faulty)
    _same_take(take, read_c3d(path))
    section = (data[0] - 1) * 512
    repair = (
        f"POINT:LABELS next-entry offset points inside the entry (section byte "
        f"{at + 10 - section}; it ends at {following - section}); read on from the "
        f"entry's end (byte {following - section})"
    )
    assert repair in take.repairs
    text, _ = _info(faulty, capsys)
    assert f"  {repair}\n" in text
    assert start < at + 10 < following


@pytest.mark.parametrize("where", ["past_file", "into_data"])
def test_offset_pointing_past_the_section(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], where: str
) -> None:
    path, data = _clean(tmp_path)
    _, at, following = _entries(data)["POINT:LABELS"]
    data_at = (struct.unpack_from("<H", data, 16)[0] - 1) * 512
    offset = 0xFFF0 if where == "past_file" else data_at + 40 - at
    struct.pack_into("<H", data, at, offset)
    faulty = _faulty(tmp_path, where, data)
    take = read_c3d(faulty)
    _same_take(take, read_c3d(path))
    section = (data[0] - 1) * 512
    repair = (
        f"POINT:LABELS next-entry offset points past the parameter section (section "
        f"byte {at + offset - section}; it ends at {data_at - section}); read on "
        f"from the entry's end (byte {following - section})"
    )
    assert repair in take.repairs
    text, _ = _info(faulty, capsys)
    assert f"  {repair}\n" in text


def test_offset_past_the_section_with_no_entry_after_stops_the_walk(
    tmp_path: Path,
) -> None:
    """BTK stops reading parameters at an offset into the data section; so do we
    when no entry starts at the entry's end either: what follows is not read."""
    path, data = _clean(tmp_path)
    entries = _entries(data)
    _, at, following = entries["POINT:LABELS"]
    struct.pack_into("<H", data, at, 0xFFF0)
    data[following + 1] = 0  # the next entry's group id: no entry starts there
    take = read_c3d(_faulty(tmp_path, "stop", data))
    clean = read_c3d(path)
    assert any("the parameters after it are not read" in r for r in take.repairs)
    # POINT:USED and LABELS come first; the rate comes from the header, the scale
    # from the header's too.
    assert take.labels == clean.labels
    np.testing.assert_array_equal(take.valid, clean.valid)
    np.testing.assert_array_equal(take.positions, clean.positions)


def test_offset_inside_with_nothing_to_read_on_from_fails_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _, data = _clean(tmp_path)
    _, at, following = _entries(data)["POINT:LABELS"]
    struct.pack_into("<H", data, at, 10)
    data[following + 1] = 0  # no entry at the entry's end either
    faulty = _faulty(tmp_path, "hopeless", data)
    with pytest.raises(TakeError, match="POINT:LABELS next-entry offset points inside"):
        read_c3d(faulty)
    assert main(["take", "info", str(faulty)]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and "no entry starts at its end" in err[0]
