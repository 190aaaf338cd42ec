"""Compiled inner loops of the wire codecs (numba), each replacing a run of numpy calls
on the live path by one call.

- :func:`store_rows`: a decoded marker block into the frame (occlusion by NaN or an
  exact zero row, the inf check, the fused axis and unit conversion), what
  ``MarkerPacket.store`` did in twelve numpy calls (~1 µs each);
- :func:`vmc_pack`: one VMC frame's floats, hemisphere-continuous quaternions,
  big-endian into the datagram bytes, what ``VmcEncoder.encode`` did in ten numpy
  calls and a scatter;
- :func:`pose_pack`: one pose data message into its two parts, what
  ``PoseEncoder.encode`` does with a struct pack and five numpy copies (the live
  loop calls it inside its one compiled call per frame, ``daemon/live/emit.py``).

The numpy forms stay beside them as the reference (the tests compare both, byte for
byte). The kernels here call nothing outside this module, so numba's per-file cache
(which does not see a change in a callee from another module) cannot go stale:
``tests/protocols/test_kernels.py`` keeps it so. ``protocols`` sits below ``daemon``,
so these do not use ``daemon.compiled.kernel``; they compile with the same options.
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True, nogil=True, error_model="numpy")
def store_rows(
    raw32: np.ndarray,
    zero_is_occluded: bool,
    rhs: np.ndarray,
    occluded: np.ndarray,
    valid: np.ndarray,
    markers_world: np.ndarray,
) -> bool:
    """Convert ``raw32`` (n, 3) float32 (native order) into ``markers_world`` (n, 3)
    float64 world metres, ``markers_world[i] = raw32[i] @ rhs``; a row with a NaN (or,
    with ``zero_is_occluded``, exactly (0, 0, 0), either sign of zero) is occluded: all
    NaN, ``occluded[i]`` True, ``valid[i]`` False.

    Returns False, writing nothing, when any value is infinite."""
    n = raw32.shape[0]
    for i in range(n):
        for c in range(3):
            if math.isinf(raw32[i, c]):
                return False
    nan = math.nan
    for i in range(n):
        x = np.float64(raw32[i, 0])
        y = np.float64(raw32[i, 1])
        z = np.float64(raw32[i, 2])
        hidden = math.isnan(x) or math.isnan(y) or math.isnan(z)
        if zero_is_occluded and x == 0.0 and y == 0.0 and z == 0.0:
            hidden = True
        occluded[i] = hidden
        valid[i] = not hidden
        if hidden:
            markers_world[i, 0] = nan
            markers_world[i, 1] = nan
            markers_world[i, 2] = nan
        else:
            for c in range(3):
                markers_world[i, c] = x * rhs[0, c] + y * rhs[1, c] + z * rhs[2, c]
    return True


@numba.njit(cache=True, nogil=True, error_model="numpy")
def vmc_pack(
    root_pos: np.ndarray,
    root_quat: np.ndarray,
    bone_pos: np.ndarray,
    bone_quat: np.ndarray,
    blend: np.ndarray,
    t_s: float,
    last_quat: np.ndarray,
    stage: np.ndarray,
    stage_bits: np.ndarray,
    offsets: np.ndarray,
    wire: np.ndarray,
) -> None:
    """One VMC frame into the datagram bytes ``wire`` (uint8).

    ``stage`` is a float32 scratch of the frame's floats in slot order, ``stage_bits``
    the same memory as uint32; slot ``k`` goes big-endian to ``wire[offsets[k]:+4]``.
    Slot order: the root's position and quaternion (x y z w), each bone's position
    and quaternion, the blend values, the time. Each quaternion is negated when its
    dot product with ``last_quat`` (its row, updated) is negative."""
    n_b = bone_pos.shape[0]
    k = 0
    for r in range(n_b + 1):
        for c in range(3):
            stage[k + c] = root_pos[c] if r == 0 else bone_pos[r - 1, c]
        if r == 0:
            qx, qy, qz, qw = root_quat[0], root_quat[1], root_quat[2], root_quat[3]
        else:
            qx, qy, qz, qw = (
                bone_quat[r - 1, 0], bone_quat[r - 1, 1], bone_quat[r - 1, 2],
                bone_quat[r - 1, 3],
            )  # fmt: skip
        dot = (
            qx * last_quat[r, 0] + qy * last_quat[r, 1] + qz * last_quat[r, 2]
            + qw * last_quat[r, 3]
        )  # fmt: skip
        if dot < 0.0:
            qx, qy, qz, qw = -qx, -qy, -qz, -qw
        last_quat[r, 0] = qx
        last_quat[r, 1] = qy
        last_quat[r, 2] = qz
        last_quat[r, 3] = qw
        stage[k + 3] = qx
        stage[k + 4] = qy
        stage[k + 5] = qz
        stage[k + 6] = qw
        k += 7
    for j in range(blend.shape[0]):
        stage[k] = blend[j]
        k += 1
    stage[k] = t_s
    k += 1
    for s in range(k):
        bits = stage_bits[s]
        o = offsets[s]
        wire[o] = (bits >> 24) & 0xFF
        wire[o + 1] = (bits >> 16) & 0xFF
        wire[o + 2] = (bits >> 8) & 0xFF
        wire[o + 3] = bits & 0xFF


@numba.njit(cache=True, nogil=True, error_model="numpy")
def pose_pack(
    header: np.ndarray,
    body: np.ndarray,
    frame_id: int,
    source_time_s: float,
    received_ns: int,
    solved_ns: int,
    flags_word: int,
    root_pos: np.ndarray,
    wfb: np.ndarray,
    pfb: np.ndarray,
    rfb: np.ndarray,
    weights: np.ndarray,
    bone_flags: np.ndarray,
    or_flags: np.ndarray,
) -> None:
    """One pose data message into ``header`` (68) and ``body`` (uint8, the
    ``pose_stream`` layout, little-endian), as ``PoseEncoder.encode`` writes it.

    The header's constant fields (magic, version, names id, counts) are written once
    by the encoder; this writes the frame number, the source time, the received and
    solved stamps, ``sent_ns`` = 0, ``flags_word`` (the performer id already in bits
    16-23) and the root position. The bone flags are ``bone_flags | or_flags`` when
    ``or_flags`` has one entry per bone, else ``bone_flags``."""
    hi = header[8:48].view(np.int64)
    hi[0] = frame_id
    header[16:24].view(np.float64)[0] = source_time_s
    hi[2] = received_ns
    hi[3] = solved_ns
    hi[4] = 0
    header[48:52].view(np.uint32)[0] = flags_word
    hf = header[56:68].view(np.float32)
    for c in range(3):
        hf[c] = root_pos[c]
    b = wfb.shape[0]
    k = weights.shape[0]
    bf = body[: 48 * b + 4 * k].view(np.float32)
    for i in range(b):
        for j in range(4):
            bf[4 * i + j] = wfb[i, j]
            bf[4 * (b + i) + j] = pfb[i, j]
            bf[4 * (2 * b + i) + j] = rfb[i, j]
    for j in range(k):
        bf[12 * b + j] = weights[j]
    o = 48 * b + 4 * k
    both = or_flags.shape[0] == b
    for i in range(b):
        f = bone_flags[i]
        if both:
            f |= or_flags[i]
        body[o + i] = f


def warm_up() -> None:
    """Compile (or load from the cache) every kernel on tiny inputs, so no streamed
    frame pays for it."""
    rows = np.zeros((2, 3), dtype=np.float32)
    rows[1] = np.nan
    store_rows(
        rows, True, np.eye(3), np.zeros(2, dtype=np.bool_), np.zeros(2, dtype=np.bool_),
        np.zeros((2, 3)),
    )  # fmt: skip
    stage = np.zeros(16, dtype=np.float32)
    vmc_pack(
        np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]), np.zeros((1, 3)),
        np.array([[0.0, 0.0, 0.0, 1.0]]), np.zeros(1), 0.0, np.zeros((2, 4)), stage,
        stage.view(np.uint32), np.arange(16, dtype=np.int64) * 4,
        np.zeros(64, dtype=np.uint8),
    )  # fmt: skip
    quat = np.array([[1.0, 0.0, 0.0, 0.0]])
    pose_pack(
        np.zeros(68, dtype=np.uint8), np.zeros(56, dtype=np.uint8), 0, 0.0, 0, 0, 0,
        np.zeros(3), quat, quat, quat, np.zeros(1), np.zeros(1, dtype=np.uint8),
        np.zeros(0, dtype=np.uint8),
    )  # fmt: skip
