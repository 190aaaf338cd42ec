"""The wire codecs' compiled loops (``protocols/kernels.py``) against their numpy
references (the code they replaced, kept here as the oracle), and the rule that keeps
their on-disk cache from going stale: they call nothing outside their own module."""

from __future__ import annotations

import ast
from pathlib import Path
from typing import Any

import numba
import numpy as np
import pytest

from retargetd.protocols import cache_lock, kernels, osc_in, zmq_wire
from retargetd.protocols.errors import DecodeError
from retargetd.protocols.marker_input import MAX_COORDINATE_M, LabelSet, MarkerPacket
from retargetd.protocols.vmc_out import VmcEncoder

KERNELS = Path(kernels.__file__)


def _store_reference(
    raw: np.ndarray, mat: np.ndarray, zero_is_occluded: bool
) -> tuple[np.ndarray, np.ndarray]:
    """The numpy form of ``MarkerPacket.store``: (markers_world, valid); a row with
    a world coordinate past ``MAX_COORDINATE_M`` is occluded too."""
    raw32 = np.asarray(raw, dtype=np.float32)
    if np.isinf(raw32).any():
        raise DecodeError("non_finite", "inf")
    occluded = np.isnan(raw32).any(axis=1)
    if zero_is_occluded:
        occluded |= (raw32 == 0.0).all(axis=1)
    rows = raw32.astype(np.float64)
    with np.errstate(invalid="ignore"):
        occluded |= (np.abs(rows @ mat.T) > MAX_COORDINATE_M).any(axis=1)
    rows[occluded] = np.nan
    return rows @ mat.T, ~occluded


@pytest.mark.parametrize("up, units", [("+Z", "m"), ("+Y", "mm"), ("-X", "cm")])
@pytest.mark.parametrize("zero_is_occluded", [True, False])
def test_store_rows_equals_the_numpy_form(
    up: str, units: str, zero_is_occluded: bool
) -> None:
    rng = np.random.default_rng(7)
    n = 40
    labels = LabelSet(1, tuple(f"M{i}" for i in range(n)))
    packet = MarkerPacket.create(labels, up, units, zero_is_occluded)
    mat = packet.world_from_capture_scaled_mat
    for trial in range(50):
        raw = rng.normal(scale=500.0, size=(n, 3)).astype(">f4")  # the wire's order
        raw[rng.random(n) < 0.2, rng.integers(0, 3)] = np.nan  # one value: occluded
        raw[rng.random(n) < 0.1] = 0.0
        raw[rng.random(n) < 0.05] = -0.0
        raw[rng.random(n) < 0.05, 1] = 0.0  # a zero in one axis only: visible
        packet.store(raw)  # scale 500: in metres, a row in ten past 1 km
        want_world, want_valid = _store_reference(raw, mat, zero_is_occluded)
        np.testing.assert_array_equal(
            packet.frame.valid, want_valid, err_msg=str(trial)
        )
        np.testing.assert_array_equal(packet.frame.markers_world, want_world)
        np.testing.assert_array_equal(packet._occluded, ~want_valid)


def test_store_rows_refuses_inf_and_writes_nothing() -> None:
    n = 5
    packet = MarkerPacket.create(LabelSet(1, tuple("ABCDE")), "+Z", "m")
    good = np.arange(15, dtype=np.float32).reshape(n, 3) + 1
    packet.store(good)
    before = packet.frame.markers_world.copy(), packet.frame.valid.copy()
    bad = good.copy()
    bad[3, 2] = -np.inf
    with pytest.raises(DecodeError) as err:
        packet.store(bad)
    assert err.value.reason == "non_finite"
    np.testing.assert_array_equal(packet.frame.markers_world, before[0])
    np.testing.assert_array_equal(packet.frame.valid, before[1])


def _vmc_reference(enc: VmcEncoder, last: np.ndarray, *args: object) -> bytes:
    """The numpy form of ``VmcEncoder.encode``: stage in float64, flip each quaternion
    onto the last one's hemisphere, cast to big-endian float32, scatter into slots."""
    root_pos, root_quat, bone_pos, bone_quat, blend, t_s = args
    n_pose = 1 + len(enc.bone_names)
    buf, slots = bytearray(enc._buf), enc._slots  # the floats are all overwritten
    stage = np.zeros(len(slots))
    pose = stage[: 7 * n_pose].reshape(n_pose, 7)
    pose[0, :3], pose[0, 3:] = root_pos, root_quat
    pose[1:, :3], pose[1:, 3:] = bone_pos, bone_quat
    quat = pose[:, 3:]
    flip = np.sum(quat * last, axis=1) < 0
    quat[flip] *= -1
    last[:] = quat
    stage[7 * n_pose : 7 * n_pose + len(enc.blend_names)] = blend
    stage[-1] = t_s
    floats = np.frombuffer(buf, dtype=">f4")
    floats[slots] = stage.astype(">f4")
    return bytes(buf)


def test_vmc_pack_equals_the_numpy_form_byte_for_byte() -> None:
    rng = np.random.default_rng(3)
    names = ("Hips", "Spine", "Chest", "Neck", "Head", "LeftUpperArm")
    enc = VmcEncoder(names, ("A", "B", "C"))
    last = np.zeros((1 + len(names), 4))
    last[:, 3] = 1.0  # the encoder's start: identity, x y z w
    for i in range(200):
        args = (
            rng.normal(size=3), rng.normal(size=4), rng.normal(size=(len(names), 3)),
            rng.normal(size=(len(names), 4)), rng.uniform(size=3), 0.004 * i,
        )  # fmt: skip
        got = b"".join(bytes(d) for d in enc.encode(*args))
        assert got == _vmc_reference(enc, last, *args), f"frame {i}"


def test_kernels_call_nothing_outside_their_module() -> None:
    """numba caches a kernel by its own file only: a callee from another module could
    change without the cache noticing. So this module imports only numba, numpy and
    the standard library's math, and the cache lock, which defines no kernel (nothing
    a kernel could call)."""
    tree = ast.parse(KERNELS.read_text())
    imported = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            imported |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            names = [f"{node.module}.{a.name}" for a in node.names]
            if names == ["retargetd.protocols.cache_lock"]:
                imported.add(names[0])
            else:
                imported.add((node.module or "").split(".")[0])
    allowed = {"__future__", "math", "numba", "numpy", "retargetd.protocols.cache_lock"}
    assert imported <= allowed, imported
    assert not [
        name
        for name, value in vars(cache_lock).items()
        if isinstance(value, numba.core.dispatcher.Dispatcher)
    ], "cache_lock compiles nothing"


def _outcome(decode: Any, *args: Any) -> tuple[Any, ...]:
    """(reason,) or (frame_id, time, markers, valid, label_set_id) of a decode."""
    packet = args[-1]
    try:
        decode(*args)
    except DecodeError as exc:
        return (exc.reason,)
    f = packet.frame
    return (
        f.frame_id, np.float64(f.source_time_s).tobytes(), f.markers_world.tobytes(),
        f.valid.tobytes(), packet.label_set_id, packet.unknown_labels,
    )  # fmt: skip


def _mutations(good: bytes, rng: np.random.Generator) -> list[bytes]:
    out = [good, good[:-1], good + b"\0\0\0\0", good[:20], b""]
    for _ in range(300):
        b = bytearray(good)
        for _ in range(int(rng.integers(1, 4))):
            b[int(rng.integers(0, len(b)))] = int(rng.integers(0, 256))
        out.append(bytes(b))
    return out


@pytest.mark.parametrize("form", ["osc", "zmq"])
def test_decode_frame_equals_the_python_decoders(form: str) -> None:
    """The compiled checks and store (``decode_*_into``) against the Python decoders
    on good, mutated and truncated packets: the same reason, or the same frame."""
    rng = np.random.default_rng(5)
    labels = LabelSet(3, tuple(f"M{i}" for i in range(6)))
    pos = rng.normal(scale=500.0, size=(6, 3))
    pos[1] = np.nan
    pos[2] = 0.0
    specials = [(7, 0.5), (0, float("nan")), (2**40, float("inf")), (-3, 1.0)]
    wire_a = np.zeros(512, dtype=np.uint8)
    wire_b = np.zeros(512, dtype=np.uint8)
    seen: set[str] = set()
    for frame_id, t in specials:
        inf_row = np.where(np.arange(6)[:, None] == 4, np.inf, pos)
        for p in (pos, inf_row, pos[:5]):  # good, an infinite marker, one too few
            if form == "osc":
                good = osc_in.encode_compact_frame(max(frame_id, 0), t, 3, p)
                good = good[:20] + frame_id.to_bytes(8, "big", signed=True) + good[28:]
                cases = [(m, b"") for m in _mutations(good, rng)]
            else:
                head, pay = zmq_wire.encode_zmq_frame(max(frame_id, 0), t, 3, p)
                fid = frame_id.to_bytes(8, "little", signed=True)
                head = head[:8] + fid + head[16:]
                cases = [(m, pay) for m in _mutations(head, rng)]
                cases += [(head, m) for m in _mutations(pay, rng)[:60]]
            for k, (a, b) in enumerate(cases):
                ref = MarkerPacket.create(labels, "+Y", "mm")
                got = MarkerPacket.create(labels, "+Y", "mm")
                wire_a[: len(a)] = np.frombuffer(a, np.uint8)
                wire_b[: len(b)] = np.frombuffer(b, np.uint8)
                if form == "osc":
                    want = _outcome(osc_in.decode_compact_frame, a, ref)
                    have = _outcome(osc_in.decode_compact_into, wire_a, len(a), got)
                else:
                    want = _outcome(zmq_wire.decode_zmq_frame, a, b, ref)
                    have = _outcome(
                        zmq_wire.decode_zmq_into, wire_a, len(a), wire_b, len(b), got
                    )
                assert have == want, (frame_id, t, k)
                seen.add(str(want[0]) if len(want) == 1 else "ok")
    # Every refusal the two forms share was met, and good frames.
    common = {"ok", "bad_length", "unknown_label_set", "count_mismatch",
              "bad_frame_number", "non_finite"}  # fmt: skip
    own = {"bad_address", "bad_typetags", "bad_blob_size"} if form == "osc" else {
        "bad_magic", "bad_version"}  # fmt: skip
    assert common | own <= seen, seen
