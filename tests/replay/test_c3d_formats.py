"""C3D and TRC variants labs write (``../shared/formats``), the fallback reader, and
crafted files that declare more than they hold (memory bombs).

Every file in ``../shared/formats`` either loads, with the reader and its repairs
reported, or (when it holds no data) fails with one line and exit 2. Each is read in a
child process whose peak resident memory is measured (``VmHWM``, else
``resource.getrusage``; ezc3d allocates in C++, out of tracemalloc's sight). A file
ezc3d reads loads exactly as ezc3d gives it, and the fallback reads the same numbers
from every file both read.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import struct
import subprocess
import sys
from pathlib import Path
from typing import Any

import ezc3d
import numpy as np
import pytest
from paths import DATASETS, FORMATS, IN_CI, REPO_ROOT, SHARED

from retargetd.daemon.cli.main import main
from retargetd.protocols import conventions as cv
from retargetd.replay.c3d import EZC3D_READER, _file_rate, _read_ezc3d, read_c3d
from retargetd.replay.c3d_fallback import READER_NAME, layout_params, read_fallback
from retargetd.replay.c3d_layout import inspect_c3d
from retargetd.replay.take import TakeError
from retargetd.replay.takes import load_take

#: Peak resident memory allowed to read or reject a file under 1 MB (issue 16).
MAX_RSS_MB = 300
#: Hang guard for a child process, s. Not a speed assertion: a regression to the
#: memory-bomb behaviour (46 s, 12.6 GB for BKINtechnologies.c3d) trips it.
CHILD_TIMEOUT_S = 60
#: Files in ../shared/formats that hold no data: one line, exit 2.
NO_DATA = {"others__Empty.c3d", "trc__Truncated.trc"}


def require_formats() -> Path:
    """The shared formats folder; skip (outside CI) or fail (in CI) if absent."""
    if FORMATS.is_dir():
        return FORMATS
    reason = f"shared formats folder not found at {FORMATS}"
    if IN_CI:
        pytest.fail(f"{reason} (CI=true: nothing may skip)")
    pytest.skip(reason)


def require_file(path: Path) -> Path:
    """A shared file; skip (outside CI) or fail (in CI) if absent."""
    if path.is_file():
        return path
    reason = f"{path} not found"
    if IN_CI:
        pytest.fail(f"{reason} (CI=true: nothing may skip)")
    pytest.skip(reason)


def _format_files() -> list[str]:
    if not FORMATS.is_dir():
        return ["(formats folder absent)"]
    return sorted(
        p.name for p in FORMATS.iterdir() if p.suffix.lower() in (".c3d", ".trc")
    )


_CHILD = r"""
import json, resource, sys, time
t0 = time.perf_counter()
from retargetd.replay.takes import load_take
from retargetd.replay.take import TakeError
out = {}
try:
    rate = float(sys.argv[2]) if len(sys.argv) > 2 else None
    take = load_take(sys.argv[1], rate_hz=rate)
    out.update(ok=True, reader=take.reader, repairs=list(take.repairs),
               frames=take.n_frames, markers=take.n_markers, rate_hz=take.rate_hz,
               finite=int(take.valid.sum()))
except TakeError as exc:
    out.update(ok=False, error=str(exc))
out["seconds"] = time.perf_counter() - t0
# Peak RSS of this interpreter: VmHWM (Linux) belongs to the process image; ru_maxrss
# would also count the parent's pages from before exec.
try:
    with open("/proc/self/status") as fh:
        hwm = [l for l in fh if l.startswith("VmHWM:")][0]
    out["maxrss_mb"] = int(hwm.split()[1]) / 1024
except (OSError, IndexError):
    out["maxrss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps(out))
"""


def _load_in_child(path: Path, *extra: str) -> dict[str, Any]:
    """Load a take in a fresh interpreter; its result, seconds and peak RSS (MB)."""
    proc = subprocess.run(
        [sys.executable, "-c", _CHILD, str(path), *extra],
        capture_output=True,
        text=True,
        timeout=CHILD_TIMEOUT_S,
        check=False,
        cwd=REPO_ROOT,
        env={**os.environ, "PYTHONWARNINGS": "error"},
    )
    assert proc.returncode == 0, proc.stderr
    result: dict[str, Any] = json.loads(proc.stdout.strip().splitlines()[-1])
    print(path.name, {k: result[k] for k in ("seconds", "maxrss_mb")})
    return result


@pytest.mark.parametrize("name", _format_files())
def test_every_format_file_loads_or_fails_in_one_line(
    name: str, capsys: pytest.CaptureFixture[str]
) -> None:
    path = require_formats() / name
    result = _load_in_child(path)
    assert result["maxrss_mb"] < MAX_RSS_MB
    capsys.readouterr()  # drop the child's figures printed above
    code = main(["take", "info", str(path), "--json"])
    captured = capsys.readouterr()
    if name in NO_DATA:
        assert not result["ok"]
        assert "holds no data" in result["error"]
        assert code == 2
        assert captured.out == ""
        assert len(captured.err.strip().splitlines()) == 1
        assert "holds no data" in captured.err
        return
    assert result["ok"], result
    assert result["frames"] > 0 and result["markers"] > 0 and result["finite"] > 0
    assert code == 0
    info = json.loads(captured.out)
    assert info["reader"] == result["reader"]
    assert info["repairs"] == result["repairs"]
    if info["reader"] == READER_NAME:
        # The fallback only runs for a reason, and says which.
        assert info["repairs"][0].startswith("ezc3d not used: ")
    else:
        assert info["reader"] == EZC3D_READER


def test_mips_file_reads_as_its_intel_twin() -> None:
    """c3d.org sample01 holds one capture written Intel and SGI/MIPS (big-endian)."""
    folder = require_formats()
    intel = read_c3d(folder / "c3d.org__sample01__Eb015pr.c3d")
    mips = read_c3d(folder / "c3d.org__sample01__Eb015sr.c3d")
    assert intel.reader == EZC3D_READER and intel.repairs == ()
    assert mips.reader == READER_NAME
    assert "MIPS" in mips.repairs[0]
    assert mips.labels == intel.labels
    assert (mips.rate_hz, mips.first_frame, mips.units) == (
        intel.rate_hz,
        intel.first_frame,
        intel.units,
    )
    np.testing.assert_array_equal(mips.valid, intel.valid)
    np.testing.assert_array_equal(mips.positions, intel.positions)


def test_repairs_of_the_odd_files() -> None:
    folder = require_formats()
    fp1 = read_c3d(folder / "c3d.org__sample15__FP1.C3D")
    assert fp1.reader == EZC3D_READER
    assert fp1.units == "m"
    assert any("'mete' read as m" in r for r in fp1.repairs)
    # Metres: the force-plate sample's points lie within a few metres of the origin.
    assert 0.5 < np.nanmax(np.abs(fp1.positions)) < 5.0

    phase = read_c3d(folder / "c3d.org__sample20__phasespace_sample.c3d")
    assert phase.reader == READER_NAME
    assert (phase.n_frames, phase.n_markers) == (701, 40)
    assert phase.rate_hz == 30.0
    assert phase.rate_source == "file (header; no POINT:RATE)"
    assert any("POINT:USED" in r for r in phase.repairs)

    bkin = read_c3d(folder / "c3d.org__sample22__BKINtechnologies.c3d")
    assert bkin.reader == READER_NAME
    assert bkin.labels == ("Right_Hand", "Left_Hand")
    assert (bkin.n_frames, bkin.rate_hz, bkin.units) == (5065, 1000.0, "m")
    assert any("EXPERIMENT:SESSION" in r for r in bkin.repairs)

    dance = read_c3d(folder / "c3d.org__sample13__Dance.c3d")
    assert dance.reader == READER_NAME
    assert dance.n_markers == 40
    assert any("499 of 500" in r for r in dance.repairs)


def test_take_info_text_names_reader_and_repairs(
    capsys: pytest.CaptureFixture[str],
) -> None:
    path = require_formats() / "c3d.org__sample22__BKINtechnologies.c3d"
    assert main(["take", "info", str(path)]) == 0
    out = capsys.readouterr().out
    assert f"reader:        {READER_NAME}" in out
    assert "repairs:       1\n  ezc3d not used: parameter EXPERIMENT:SESSION" in out
    assert "rate:          1000 Hz (file (POINT:RATE))" in out


def _zero_rate_copy(src: Path, dst: Path) -> Path:
    """A copy of a C3D whose header rate and POINT:RATE are both 0."""
    data = bytearray(src.read_bytes())
    data[20:24] = b"\x00\x00\x00\x00"  # header words 11-12 (Intel float)
    layout = inspect_c3d(src)
    rate = layout.params[("POINT", "RATE")]
    at = bytes(data).find(rate.data, 512)
    assert at > 0
    data[at : at + 4] = b"\x00\x00\x00\x00"
    dst.write_bytes(bytes(data))
    return dst


def test_zero_rate_needs_take_rate(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    src = require_formats() / "c3d.org__sample01__Eb015pr.c3d"
    path = _zero_rate_copy(src, tmp_path / "zero_rate.c3d")
    with pytest.raises(TakeError, match="pass --take-rate HZ"):
        load_take(path)
    assert main(["take", "info", str(path)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "--take-rate" in err
    take = load_take(path, rate_hz=50.0)
    original = load_take(src)
    assert (take.rate_hz, take.rate_source) == (50.0, "override (--take-rate)")
    np.testing.assert_array_equal(take.positions, original.positions)
    assert main(["take", "info", str(path), "--take-rate", "50", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert (info["rate_hz"], info["rate_source"]) == (50.0, "override (--take-rate)")


def test_zero_rate_trc_needs_take_rate(tmp_path: Path) -> None:
    src = require_file(DATASETS / "btkdata/MOTEK_T.trc")
    lines = src.read_text().splitlines()
    fields = lines[2].split("\t")
    fields[0] = "0"
    lines[2] = "\t".join(fields)
    path = tmp_path / "zero.trc"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(TakeError, match="pass --take-rate HZ"):
        load_take(path)
    assert load_take(path, rate_hz=60.0).rate_hz == 60.0


def _dataset_c3ds() -> list[str]:
    root = DATASETS
    if not root.is_dir():
        return ["(datasets folder absent)"]
    return sorted(
        str(p.relative_to(root)) for p in root.rglob("*") if p.suffix.lower() == ".c3d"
    )


def _ezc3d_labels(params: dict[str, Any]) -> list[str]:
    labels = [str(v) for v in params["POINT"]["LABELS"]["value"]]
    i = 2
    while f"LABELS{i}" in params["POINT"]:
        labels += [str(v) for v in params["POINT"][f"LABELS{i}"]["value"]]
        i += 1
    return [label.strip() for label in labels]


@pytest.mark.parametrize("rel", _dataset_c3ds())
def test_files_ezc3d_reads_load_unchanged(datasets: Path, rel: str) -> None:
    """Every real take: read by ezc3d, no repair, each marker exactly ezc3d's data."""
    path = datasets / rel
    raw = ezc3d.c3d(str(path))
    params = raw["parameters"]
    points = np.asarray(raw["data"]["points"], dtype=np.float64)  # (4, N, T)
    residuals = np.asarray(raw["data"]["meta_points"]["residuals"])[0]  # (N, T)
    labels = _ezc3d_labels(params)
    try:
        takes = [read_c3d(path)]
    except TakeError as exc:
        assert "--subject" in str(exc)
        takes = [read_c3d(path, subject=s) for s in load_subjects(path)]
    for take in takes:
        assert take.reader == EZC3D_READER
        assert take.repairs == ()
        assert take.rate_hz == float(params["POINT"]["RATE"]["value"][0])
        assert take.first_frame == raw["header"]["points"]["first_frame"]
        prefix = f"{take.subject}:" if take.subject else ""
        for m, label in enumerate(take.labels):
            candidates = [prefix + label, label]
            col = next(labels.index(c) for c in candidates if c in labels)
            xyz = points[:3, col, :].T
            seen = np.isfinite(xyz).all(axis=1) & (residuals[col] >= 0)
            expected = cv.world_from_capture_pos(
                np.where(seen[:, None], xyz, np.nan), take.up_axis, take.units
            )
            np.testing.assert_array_equal(take.valid[:, m], seen)
            np.testing.assert_array_equal(take.positions[:, m], expected)


def load_subjects(path: Path) -> list[str]:
    """Subjects named by the one-line error of an ambiguous file's load."""
    try:
        read_c3d(path)
    except TakeError as exc:
        text = str(exc)
    else:
        return []
    # "take PATH holds 2 subjects (A, B): pass --subject NAME"
    listed = text.rsplit(" subjects (", 1)[1].rsplit("): pass", 1)[0]
    return [s.strip() for s in listed.split(",")]


def _both_readable() -> list[str]:
    files = [f"datasets/{rel}" for rel in _dataset_c3ds()]
    files += [
        "formats/c3d.org__sample01__Eb015pr.c3d",
        "formats/c3d.org__sample02__Dec_real.c3d",
    ]
    return files


#: Files the c3d package refuses although ezc3d reads them (why the fallback comes
#: second): a parameter name repeated in another case, header analog counts that
#: disagree with the parameters.
PACKAGE_REFUSES = {
    "datasets/btkdata/PiG_Calibration-FlatFoot-Full.c3d": KeyError,
}


@pytest.mark.parametrize("rel", _both_readable())
def test_fallback_reads_what_ezc3d_reads(rel: str) -> None:
    path = require_file(SHARED / rel)
    expected = _read_ezc3d(str(path))
    layout = inspect_c3d(path)
    assert layout.ezc3d_problems == ()
    rate = _file_rate(layout_params(layout), layout.header_rate_hz)[0]
    if rel in PACKAGE_REFUSES:
        with pytest.raises(PACKAGE_REFUSES[rel]):
            read_fallback(layout, rate)
        return
    got = read_fallback(layout, rate)
    np.testing.assert_array_equal(got.valid, expected.valid)
    np.testing.assert_array_equal(
        np.where(got.valid[..., None], got.points, 0.0),
        np.where(expected.valid[..., None], expected.points, 0.0),
    )
    assert layout.first_frame == expected.first_frame
    for group, entries in got.params.items():
        for name, entry in entries.items():
            want = expected.params[group][name]["value"]
            value = entry["value"]
            if isinstance(value, list):
                assert [v.strip() for v in value] == [str(v).strip() for v in want]
            else:
                np.testing.assert_allclose(
                    value, np.ravel(want, order="F"), rtol=1e-6, err_msg=name
                )


# --- crafted files -------------------------------------------------------------


#: Byte order of each processor type (DEC integers are little-endian).
_ORDER = {84: "<", 85: "<", 86: ">"}


def _f32(value: float, proc: int = 84) -> bytes:
    """One float as the processor stores it (DEC: IEEE x 4 with halves swapped)."""
    if proc == 85:
        raw = struct.pack("<f", value * 4.0)
        return raw[2:4] + raw[0:2]
    return struct.pack(_ORDER[proc] + "f", value)


def _i16(value: int, proc: int = 84) -> bytes:
    return struct.pack(_ORDER[proc] + "h", value)


def _entry_group(gid: int, name: str, desc: bytes = b"", proc: int = 84) -> bytes:
    body = _i16(2 + 1 + len(desc), proc) + struct.pack("B", len(desc)) + desc
    return struct.pack("bb", len(name), -gid) + name.encode() + body


def _entry_param(
    gid: int,
    name: str,
    type_code: int,
    dims: tuple[int, ...],
    data: bytes,
    desc: bytes = b"",
    proc: int = 84,
) -> bytes:
    body = struct.pack("bB", type_code, len(dims)) + bytes(dims) + data
    body += struct.pack("B", len(desc)) + desc
    return (
        struct.pack("bb", len(name), gid)
        + name.encode()
        + _i16(2 + len(body), proc)
        + body
    )


def _crafted_c3d(
    path: Path,
    *,
    n_points: int,
    header_frames: int,
    frames_held: int,
    extra: bytes = b"",
    point_frames: float | None = None,
    param_blocks: int | None = None,
    terminate: bool = True,
    proc: int = 84,
    scale: float = -1.0,
) -> np.ndarray:
    """Write a C3D; returns the (T, N, 3) float64 points it holds (NaN: occluded).

    ``scale`` < 0 writes float data, > 0 16-bit integers (``value / scale``); every
    7th sample is occluded (residual word -1). ``proc`` is the processor type.
    """
    o = _ORDER[proc]
    labels = b"".join(f"M{i:03d}".encode() for i in range(n_points))
    entries = _entry_group(1, "POINT", proc=proc)
    entries += _entry_param(1, "USED", 2, (), _i16(n_points, proc), proc=proc)
    entries += _entry_param(1, "SCALE", 4, (), _f32(scale, proc), proc=proc)
    entries += _entry_param(1, "RATE", 4, (), _f32(100.0, proc), proc=proc)
    entries += _entry_param(1, "UNITS", -1, (2,), b"mm", proc=proc)
    n_labels = min(n_points, 255)  # one byte per dimension; more need LABELS2
    entries += _entry_param(
        1, "LABELS", -1, (4, n_labels), labels[: 4 * n_labels], proc=proc
    )
    if point_frames is not None:
        entries += _entry_param(1, "FRAMES", 4, (), _f32(point_frames, proc), proc=proc)
    entries += extra
    section = bytearray(bytes([1, 0x50, 0, proc]) + entries)
    if terminate:
        section += b"\x00\x00"
        blocks = -(-len(section) // 512)
        section = section.ljust(blocks * 512, b"\x00")
    else:
        # The file ends inside the section: no zero name length anywhere.
        blocks = -(-len(section) // 512)
    section[2] = blocks if param_blocks is None else param_blocks
    header = bytearray(512)
    header[0:2] = b"\x02\x50"
    struct.pack_into(o + "HHHH", header, 2, n_points, 0, 1, header_frames)
    header[12:16] = _f32(scale, proc)
    struct.pack_into(o + "HH", header, 16, 2 + blocks, 0)
    header[20:24] = _f32(100.0, proc)
    rng = np.random.default_rng(0)
    shape = (frames_held, n_points)
    occluded = (np.arange(np.prod(shape)).reshape(shape) % 7) == 3
    if scale < 0:
        xyz = rng.uniform(-1000, 1000, (*shape, 3)).astype(np.float32)
        words = np.zeros((*shape, 4), dtype=np.float32)
        words[..., :3] = xyz
        words[..., 3] = np.where(occluded, -1.0, 2.0)  # residual byte 2, camera 0
        if proc == 85:
            raw = (words * 4.0).astype("<f4").view("<u2").reshape(-1, 2)[:, ::-1]
            data = np.ascontiguousarray(raw).tobytes()
        else:
            data = words.astype(o + "f4").tobytes()
        values = xyz.astype(np.float64)
    else:
        counts = rng.integers(-20000, 20000, (*shape, 3))
        words_i = np.zeros((*shape, 4), dtype=np.int64)
        words_i[..., :3] = counts
        words_i[..., 3] = np.where(occluded, -1, 2)
        data = words_i.astype(o + "i2").tobytes()
        values = counts * np.float64(np.float32(scale))
    path.write_bytes(bytes(header) + bytes(section) + data)
    assert path.stat().st_size < 1_000_000
    values[occluded] = np.nan
    return values


@pytest.mark.parametrize("proc", [84, 85, 86])
@pytest.mark.parametrize("scale", [-1.0, 0.1])
def test_integer_and_float_data_of_every_processor(
    tmp_path: Path, proc: int, scale: float
) -> None:
    """Intel, DEC and MIPS, float and 16-bit integer data: the points as written."""
    path = tmp_path / f"p{proc}_{'float' if scale < 0 else 'int'}.c3d"
    values = _crafted_c3d(
        path, n_points=12, header_frames=40, frames_held=40, proc=proc, scale=scale
    )
    take = read_c3d(path)
    assert take.reader == (READER_NAME if proc == 86 else EZC3D_READER)
    np.testing.assert_array_equal(take.valid, np.isfinite(values[..., 0]))
    # Integers times a float32 scale are rounded to float32 by the readers:
    # 2000 mm x 2^-24 ~ 1.2e-4 mm.
    np.testing.assert_allclose(
        take.positions, values * cv.MM_TO_M, rtol=0, atol=1e-3 * cv.MM_TO_M
    )
    layout = inspect_c3d(path)
    got = read_fallback(layout, 100.0)
    np.testing.assert_array_equal(got.valid, take.valid)
    np.testing.assert_allclose(
        np.where(got.valid[..., None], got.points, np.nan),
        values,
        rtol=0,
        atol=1e-3,
    )


def test_crafted_declared_frames_far_beyond_the_file(tmp_path: Path) -> None:
    """10^9 frames declared (POINT:FRAMES), 2 held: read 2, say so, stay small."""
    path = tmp_path / "billion.c3d"
    values = _crafted_c3d(
        path, n_points=1000, header_frames=65535, frames_held=2, point_frames=1e9
    )
    layout = inspect_c3d(path)
    assert layout.frames_declared == 10**9 and layout.frames_present == 2
    assert layout.ezc3d_problems  # never handed to ezc3d
    result = _load_in_child(path)
    assert result["maxrss_mb"] < MAX_RSS_MB
    assert result["ok"] and result["reader"] == READER_NAME
    assert result["frames"] == 2 and result["markers"] == 1000
    assert any("2 of 1000000000 declared frames" in r for r in result["repairs"])
    take = read_c3d(path)
    np.testing.assert_array_equal(take.positions[..., 0], values[..., 0] * cv.MM_TO_M)


def test_crafted_declared_frames_none_held(tmp_path: Path) -> None:
    path = tmp_path / "hollow.c3d"
    _crafted_c3d(
        path, n_points=30000, header_frames=65535, frames_held=0, point_frames=1e9
    )
    with path.open("ab") as fh:
        fh.write(b"\x00" * 4096)  # part of one 480 KB frame
    result = _load_in_child(path)
    assert result["maxrss_mb"] < MAX_RSS_MB
    assert not result["ok"]
    assert "no complete frame" in result["error"]
    assert "holds no data" in result["error"]


def test_crafted_parameter_declaring_255_to_the_7_values(tmp_path: Path) -> None:
    path = tmp_path / "dims.c3d"
    bomb = _entry_param(1, "HUGE", 4, (255,) * 7, b"")
    _crafted_c3d(path, n_points=10, header_frames=5, frames_held=5, extra=bomb)
    layout = inspect_c3d(path)
    assert ("POINT", "HUGE") not in layout.params
    assert any("POINT:HUGE declares" in p for p in layout.ezc3d_problems)
    result = _load_in_child(path)
    assert result["maxrss_mb"] < MAX_RSS_MB
    # The c3d package cannot step over such an entry either: one line naming it.
    assert not result["ok"]
    assert "POINT:HUGE declares" in result["error"] and "\n" not in result["error"]


def test_crafted_description_ezc3d_reads_as_negative(tmp_path: Path) -> None:
    """A 200-character description: ezc3d's signed length would ask for ~4 GB."""
    path = tmp_path / "desc.c3d"
    long_desc = _entry_param(1, "NOTE", 2, (), b"\x01\x00", desc=b"d" * 200)
    _crafted_c3d(path, n_points=10, header_frames=5, frames_held=5, extra=long_desc)
    result = _load_in_child(path)
    assert result["maxrss_mb"] < MAX_RSS_MB
    assert result["ok"] and result["reader"] == READER_NAME
    assert any("200-character description" in r for r in result["repairs"])


def test_crafted_parameter_section_without_end(tmp_path: Path) -> None:
    """255 parameter blocks declared, one present, no end marker: one line, small."""
    path = tmp_path / "endless.c3d"
    _crafted_c3d(
        path,
        n_points=10,
        header_frames=5,
        frames_held=0,
        param_blocks=255,
        terminate=False,
    )
    result = _load_in_child(path)
    assert result["maxrss_mb"] < MAX_RSS_MB
    assert not result["ok"]
    assert "\n" not in result["error"]


def test_crafted_points_without_room(tmp_path: Path) -> None:
    """32767 points declared in a 2 KB file: no complete frame, exit 2."""
    path = tmp_path / "points.c3d"
    _crafted_c3d(path, n_points=10, header_frames=3, frames_held=3)
    data = bytearray(path.read_bytes())
    struct.pack_into("<H", data, 2, 32767)
    layout_before = inspect_c3d(path)
    at = data.find(struct.pack("<h", 10), 512)  # POINT:USED value
    struct.pack_into("<h", data, at, 32767)
    path.write_bytes(bytes(data))
    assert layout_before.n_points == 10
    result = _load_in_child(path)
    assert result["maxrss_mb"] < MAX_RSS_MB
    assert not result["ok"] and "no complete frame" in result["error"]


def test_copy_of_bkin_file_is_small_to_read(tmp_path: Path) -> None:
    """The 583 KB file that took 12.6 GB: read by the fallback in a small process."""
    src = require_formats() / "c3d.org__sample22__BKINtechnologies.c3d"
    path = shutil.copy(src, tmp_path / "bkin.c3d")
    result = _load_in_child(Path(path))
    assert result["ok"] and result["reader"] == READER_NAME
    assert result["maxrss_mb"] < MAX_RSS_MB
    assert math.isclose(result["rate_hz"], 1000.0)


def test_crafted_rotation_section_beyond_the_file(tmp_path: Path) -> None:
    """ezc3d reads ROTATION:USED x RATIO matrices per frame: declared far past EOF."""
    path = tmp_path / "rotation.c3d"
    rotation = _entry_group(2, "ROTATION")
    rotation += _entry_param(2, "USED", 2, (), struct.pack("<h", 30000))
    rotation += _entry_param(2, "RATIO", 2, (), struct.pack("<h", 255))
    rotation += _entry_param(2, "DATA_START", 2, (), struct.pack("<h", 3))
    _crafted_c3d(path, n_points=10, header_frames=5, frames_held=5, extra=rotation)
    layout = inspect_c3d(path)
    assert any("ROTATION data declares" in p for p in layout.ezc3d_problems)
    result = _load_in_child(path)
    assert result["maxrss_mb"] < MAX_RSS_MB
    assert result["ok"] and result["reader"] == READER_NAME
    assert result["frames"] == 5 and result["markers"] == 10


def test_take_info_gives_processing_units(
    datasets: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Plug-in Gait measurements: lengths in mm, body mass in kg, angles in rad."""
    path = datasets / "btkdata" / "PiG_Motion-FlatFoot-Full.c3d"
    assert main(["take", "info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "  LKneeWidth = 105 mm\n" in out
    assert "  Bodymass = 47.5 kg\n" in out
    assert "  HeadOffset = 0.353677 rad\n" in out
    assert "  RStaticPlantFlex = 0.162755 rad\n" in out
    assert main(["take", "info", str(path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    units = info["measurement_units"]
    assert set(units) == set(info["measurements"])
    assert units["InterAsisDistance"] == "mm" and units["LTibialTorsion"] == "rad"
    assert "" not in units.values()  # every PiG measurement has a known unit
