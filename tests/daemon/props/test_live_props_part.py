"""The props part alone (``daemon/live/props.py``), driven frame by frame without
sockets: One Euro smoothing per prop, the held pose not fed to the filter, and the
steady state's allocations per frame."""

from __future__ import annotations

import gc
import tracemalloc
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from retargetd.daemon.live.config_props import PropConfig
from retargetd.daemon.live.props import LiveProps
from retargetd.daemon.props import kernel as pk
from retargetd.daemon.props.layout import calibrate_prop
from retargetd.protocols import pose_props
from retargetd.protocols.marker_input import LabelSet

CAMERA = np.array(
    [[-0.17, 0.0, 0.0], [0.15, 0.02, 0.0], [0.02, 0.14, 0.12],
     [0.06, -0.08, 0.15], [-0.08, 0.16, -0.06]]
)  # fmt: skip
LABELS = tuple(f"cam:{i}" for i in range(5))


class _Stream:
    """What the part reads of a marker stream: its label set and current frame."""

    def __init__(self) -> None:
        self.label_set = LabelSet(1, LABELS)
        frame = SimpleNamespace(
            frame_id=0, source_time_s=0.0, markers_world=np.zeros((5, 3)),
            valid=np.ones(5, dtype=np.bool_),
        )  # fmt: skip
        self.current = SimpleNamespace(frame=frame)


def _part(tmp_path: Path, **keys: Any) -> tuple[LiveProps, list[Any]]:
    layout = calibrate_prop(np.repeat(CAMERA[None], 3, 0), LABELS, name="cam",
                            kind="camera", rate_hz=100.0)  # fmt: skip
    path = tmp_path / "cam.json"
    layout.save(path)
    cfg = replace(PropConfig(name="cam", kind="camera", calibration=str(path)), **keys)
    sent: list[Any] = []
    return LiveProps((cfg,), (), lambda parts, t: sent.append(bytes(parts[0])),
                     lambda line: None), sent  # fmt: skip


def _drive(props: LiveProps, n: int, noise_m: float, seed: int = 0) -> None:
    rng = np.random.default_rng(seed)
    stream = _Stream()
    frame = stream.current.frame
    for i in range(n):
        frame.frame_id = i
        frame.markers_world[:] = CAMERA + np.array([0.0, 0.0, 1.0])
        frame.markers_world += rng.normal(0.0, noise_m, (5, 3))
        props.on_frame(stream, int(i * 1e9 / 120))  # type: ignore[arg-type]


def test_one_euro_smooths_a_still_prop(tmp_path: Path) -> None:
    raw, raw_sent = _part(tmp_path)
    smooth, smooth_sent = _part(tmp_path, smooth_min_cutoff_hz=1.0)
    for part in (raw, smooth):
        _drive(part, 600, 0.0005)

    def jitter(sent: list[bytes]) -> tuple[float, float]:
        msgs = [pose_props.decode_prop(b) for b in sent[120:]]
        pos = np.array([m.pos_world for m in msgs])
        rot = Rotation.from_quat([m.world_from_prop_quat for m in msgs],
                                 scalar_first=True)  # fmt: skip
        return float(pos.std(axis=0).max()), float(rot.magnitude().std())

    (p_raw, r_raw), (p_s, r_s) = jitter(raw_sent), jitter(smooth_sent)
    # a 1 Hz cutoff at 120 Hz passes ~5 % of white jitter's amplitude
    assert p_s < 0.3 * p_raw and r_s < 0.3 * r_raw, (p_raw, p_s, r_raw, r_s)


def test_held_pose_is_not_fed_to_the_filter(tmp_path: Path) -> None:
    part, sent = _part(tmp_path, smooth_min_cutoff_hz=1.0)
    _drive(part, 10, 0.0)
    stream = _Stream()
    stream.current.frame.valid[:3] = False
    part.on_frame(stream, int(1e9))  # type: ignore[arg-type]
    last = pose_props.decode_prop(sent[-1])
    assert last.flags & pk.FLAG_HELD
    np.testing.assert_allclose(
        last.pos_world, pose_props.decode_prop(sent[-2]).pos_world, atol=1e-6
    )


def test_steady_state_allocates_little(tmp_path: Path) -> None:
    part, sent = _part(tmp_path)
    _drive(part, 200, 0.0005)
    sent.clear()
    stream = _Stream()
    frame = stream.current.frame
    frame.markers_world[:] = CAMERA
    peaks = []
    gc.collect()
    tracemalloc.start()
    try:
        for i in range(200):
            frame.frame_id = 1000 + i
            tracemalloc.reset_peak()
            before = tracemalloc.get_traced_memory()[0]
            part.on_frame(stream, 10**10 + i)  # type: ignore[arg-type]
            peaks.append(tracemalloc.get_traced_memory()[1] - before)
    finally:
        tracemalloc.stop()
    # the compiled call's boxing of its arguments, the memoryviews handed to the
    # sends and the parts list, freed at once: measured 972 B median per frame
    assert np.median(peaks) < 2048, np.median(peaks)
