"""Occlusion: a real take with markers entering and leaving the volume, and synthetic
dropouts.

``opensim-core/walking2.c3d`` (250 Hz, 1249 frames, 47.5 % of samples occluded) solved
with ``tests/data/walking2-rig.toml``: every flag is accounted for by the take's
visibility, held bones hold their value, a bone with all its markers seen is solved as
if nothing else were missing, and our joint centres are compared with Vicon's.
Figures are printed (``pytest -s``).
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pytest

from retargetd.daemon.body.calibration import Calibration, calibrate, match_markers
from retargetd.daemon.body.rig import Rig, load_rig
from retargetd.daemon.body.solve import (
    FLAG_HELD,
    FLAG_NEVER,
    FLAG_PARTIAL,
    FLAG_REBUILT,
    BodySolve,
    BodySolver,
)
from retargetd.daemon.synth.performer import synthesize
from retargetd.replay.take import Take
from retargetd.replay.takes import load_take

RIG = Path(__file__).resolve().parent.parent / "data" / "walking2-rig.toml"
CAL_WINDOW = 10  # frames (40 ms at 250 Hz)


def _bone_markers(rig: Rig) -> list[np.ndarray]:
    """Per bone, the rig-marker indices of its defining markers (the core's rule)."""
    index = {m: i for i, m in enumerate(rig.markers)}
    out = []
    for bone in rig.bones:
        names: list[str] = []
        for p in bone.inputs:
            names.extend(m for m in rig.markers_of(p) if m not in names)
        out.append(np.array([index[m] for m in names]))
    return out


def _availability(rig: Rig, cal: Calibration, seen: np.ndarray) -> np.ndarray:
    """(T, Mr) markers seen, or rebuilt from a calibrated segment with >= 3 seen."""
    index = {m: i for i, m in enumerate(rig.markers)}
    avail = seen.copy()
    for names, _layout in cal.segment_layouts.values():
        idx = np.array([index[m] for m in names])
        enough = seen[:, idx].sum(axis=1) >= 3
        avail[:, idx] |= enough[:, None]
    return avail


def _rig_seen(rig: Rig, labels: tuple[str, ...], positions: np.ndarray) -> np.ndarray:
    cols = np.asarray(match_markers(rig, labels))
    seen = np.zeros((positions.shape[0], len(cols)), dtype=bool)
    have = cols >= 0
    seen[:, have] = np.isfinite(positions[:, cols[have]]).all(axis=-1)
    return seen


def _check_accounting(
    rig: Rig, cal: Calibration, res: BodySolve, seen: np.ndarray
) -> None:
    """Every flag, quality and held value explained by the markers' visibility."""
    avail = _availability(rig, cal, seen)
    flags = res.bone_flags
    for b, idx in enumerate(_bone_markers(rig)):
        quality = seen[:, idx].mean(axis=1)
        np.testing.assert_allclose(res.bone_quality[:, b], quality, atol=1e-6)
        partial = (flags[:, b] & FLAG_PARTIAL) != 0
        np.testing.assert_array_equal(partial, quality < 1.0)
        rebuilt = (~seen[:, idx] & avail[:, idx]).any(axis=1)
        np.testing.assert_array_equal((flags[:, b] & FLAG_REBUILT) != 0, rebuilt)
        held = (flags[:, b] & FLAG_HELD) != 0
        np.testing.assert_array_equal(held, ~avail[:, idx].all(axis=1))
        # A held bone keeps its last good parent-relative rotation (identity, i.e. the
        # calibrated rest, before any good frame).
        never = (flags[:, b] & FLAG_NEVER) != 0
        pfb = res.rest_from_bone_quat[:, b]
        np.testing.assert_allclose(
            pfb[never], np.tile([1.0, 0, 0, 0], (never.sum(), 1)), atol=1e-12
        )
        kept = np.flatnonzero(held & ~never)
        kept = kept[kept > 0]
        dots = np.abs(np.sum(pfb[kept] * pfb[kept - 1], axis=-1))
        np.testing.assert_allclose(dots, 1.0, atol=1e-9)


@functools.cache
def _walking2(path: Path) -> tuple[Take, Rig, Calibration, BodySolve]:
    take = load_take(path)
    rig = load_rig(RIG)
    cal = _calibrate(rig, take)
    return take, rig, cal, BodySolver(rig, cal, take.labels).solve_take(take.positions)


@pytest.fixture
def walking2(datasets: Path) -> Take:
    return _walking2(datasets / "opensim-core" / "walking2.c3d")[0]


@pytest.fixture
def rig(datasets: Path) -> Rig:
    return _walking2(datasets / "opensim-core" / "walking2.c3d")[1]


@pytest.fixture
def calibrated(datasets: Path) -> Calibration:
    return _walking2(datasets / "opensim-core" / "walking2.c3d")[2]


@pytest.fixture
def solved(datasets: Path) -> BodySolve:
    return _walking2(datasets / "opensim-core" / "walking2.c3d")[3]


def _calibration_window(rig: Rig, take: Take) -> slice:
    """The stillest CAL_WINDOW frames among those where every rig marker is seen.

    A walking take has no static pose: segment layouts are averaged over the window, so
    it must be short and where the markers move least relative to the body (RMS of
    marker positions about their window mean, after removing the per-frame centroid).
    """
    seen = _rig_seen(rig, take.labels, take.positions)
    cols = np.asarray(match_markers(rig, take.labels))
    pos = take.positions[:, cols]
    rel = np.zeros_like(pos)
    ok = seen.all(axis=1)
    rel[ok] = pos[ok] - pos[ok].mean(axis=1, keepdims=True)
    best, start = np.inf, -1
    for i in range(take.n_frames - CAL_WINDOW + 1):
        if not ok[i : i + CAL_WINDOW].all():
            continue
        w = rel[i : i + CAL_WINDOW]
        score = float(np.sqrt(np.mean((w - w.mean(axis=0)) ** 2)))
        if score < best:
            best, start = score, i
    assert start >= 0
    print(
        f"\ncalibration window {start}:{start + CAL_WINDOW} "
        f"(all {len(cols)} rig markers seen; RMS motion {1000 * best:.1f} mm)"
    )
    return slice(start, start + CAL_WINDOW)


def _calibrate(rig: Rig, walking2: Take) -> Calibration:
    window = _calibration_window(rig, walking2)
    pos = walking2.positions[window]

    def mean(label: str) -> np.ndarray:
        return pos[:, walking2.labels.index(label)].mean(axis=0)

    # The subject's pelvis width and depth, measured on the calibration frames.
    pw = 1000 * np.linalg.norm(mean("LASI") - mean("RASI"))
    pd = 1000 * np.linalg.norm(
        (mean("LASI") + mean("RASI")) / 2 - (mean("LPSI") + mean("RPSI")) / 2
    )
    print(f"pelvis width {pw:.1f} mm, depth {pd:.1f} mm")
    return calibrate(
        rig,
        pos,
        walking2.labels,
        overrides={"InterAsisDistance": pw, "PelvisDepth": pd},
    )


def test_walking2_whole_take(
    rig: Rig, calibrated: Calibration, walking2: Take, solved: BodySolve
) -> None:
    res = solved
    assert np.isfinite(res.world_from_bone_quat).all()
    assert np.isfinite(res.rest_from_bone_quat).all()
    assert np.isfinite(res.root_pos).all()
    seen = _rig_seen(rig, walking2.labels, walking2.positions)
    _check_accounting(rig, calibrated, res, seen)
    held = (res.bone_flags & FLAG_HELD) != 0
    rebuilt = (res.bone_flags & FLAG_REBUILT) != 0
    print(
        f"walking2: {walking2.n_frames} frames, rig markers occluded "
        f"{100 * (1 - seen.mean()):.1f} %"
    )
    for b, name in enumerate(res.bone_names):
        print(
            f"  {name:10s} held {100 * held[:, b].mean():5.1f} %  rebuilt "
            f"{100 * rebuilt[:, b].mean():5.1f} %  mean quality "
            f"{res.bone_quality[:, b].mean():.2f}"
        )


def test_walking2_root_holds(solved: BodySolve) -> None:
    """The root position is never NaN: it holds its last good value (the calibrated
    rest before any) while the pelvis is lost."""
    assert np.isfinite(solved.root_pos).all()
    lost = (solved.bone_flags[:, 0] & FLAG_HELD) != 0
    steps = np.flatnonzero(lost[1:]) + 1
    np.testing.assert_array_equal(solved.root_pos[steps], solved.root_pos[steps - 1])


#: Median distance bounds to Vicon's joint centres (mm). Knee and ankle: Vicon's are
#: the condyle and malleolus midpoints, as ours: equal to rounding when the markers are
#: seen; rebuilt from the clusters (markers hidden on purpose) they may move by the
#: clusters' soft-tissue deformation, the brief's 20 mm. Hip: Vicon uses another
#: regression (leg-length based, Davis); this pelvis is narrow (ASIS 199 mm apart) and
#: deep (186 mm), where Harrington's PW-based offset is ~40 mm less inferior and ~25 mm
#: less lateral than Vicon's: 60 mm bounds two regressions, not an error.
VICON_BOUNDS = {"KJC": 20.0, "AJC": 20.0, "HJC": 60.0}


def test_walking2_against_vicon(
    rig: Rig, calibrated: Calibration, walking2: Take, solved: BodySolve
) -> None:
    refs = walking2.references
    # The same take with the condyles and malleoli hidden everywhere: knee and ankle
    # centres come from markers rebuilt from the thigh and shank clusters.
    hidden = walking2.positions.copy()
    for label in ("LLFC", "LMFC", "RLFC", "RMFC", "LLMAL", "LMMAL", "RLMAL", "RMMAL"):
        hidden[:, walking2.labels.index(label)] = np.nan
    rebuilt = BodySolver(rig, calibrated, walking2.labels).solve_take(hidden)
    print("\ndistance to Vicon's joint centres (median / 95th percentile, mm):")
    for joint in ("LHJC", "RHJC", "LKJC", "RKJC", "LAJC", "RAJC"):
        ref = refs.get(joint)
        for tag, res in (("markers", solved), ("rebuilt", rebuilt)):
            ours = res.joint_centres[:, res.joint_names.index(joint)]
            d = 1000 * np.linalg.norm(ours - ref, axis=-1)
            d = d[np.isfinite(d)]
            assert d.size > 100
            med, p95 = float(np.median(d)), float(np.percentile(d, 95))
            print(f"  {joint} {tag:8s} {med:6.1f} / {p95:6.1f}  ({d.size} frames)")
            assert med <= VICON_BOUNDS[joint[1:]], (joint, tag, med)


def test_walking2_locality(rig: Rig, calibrated: Calibration, walking2: Take) -> None:
    """A bone whose defining markers are all seen is solved as if nothing else were
    missing: gaps punched into the fully visible middle of the take change no such
    bone's world rotation."""
    seen = _rig_seen(rig, walking2.labels, walking2.positions)
    full = np.flatnonzero(seen.all(axis=1))
    clean = walking2.positions[full[0] : full[-1] + 1]
    assert np.isfinite(clean[:, np.asarray(match_markers(rig, walking2.labels))]).all()
    rng = np.random.default_rng(7)
    gappy = clean.copy()
    n, m = gappy.shape[:2]
    for _ in range(4 * m):  # runs of 5-60 frames on random markers
        col, start = rng.integers(m), rng.integers(n)
        gappy[start : start + rng.integers(5, 60), col] = np.nan
    a = BodySolver(rig, calibrated, walking2.labels).solve_take(clean)
    b = BodySolver(rig, calibrated, walking2.labels).solve_take(gappy)
    gseen = _rig_seen(rig, walking2.labels, gappy)
    checked = 0
    for k, idx in enumerate(_bone_markers(rig)):
        whole = gseen[:, idx].all(axis=1)
        assert 0 < whole.sum() < n
        qa, qb = a.world_from_bone_quat[whole, k], b.world_from_bone_quat[whole, k]
        np.testing.assert_allclose(np.abs(np.sum(qa * qb, axis=-1)), 1.0, atol=1e-12)
        checked += int(whole.sum())
    print(f"\nlocality: {checked} bone-frames with all markers seen, identical")


def test_synthetic_dropouts() -> None:
    rig = load_rig("menache")
    base = synthesize(seconds=6, rate_hz=120, markerset="menache", seed=3)
    take = synthesize(seconds=6, rate_hz=120, markerset="menache", dropout=0.2, seed=3)
    cal = calibrate(rig, base.markers_world[base.base_pose_frames], base.labels)
    res = BodySolver(rig, cal, take.labels).solve_take(take.markers_world)
    assert np.isfinite(res.world_from_bone_quat).all()
    assert np.isfinite(res.rest_from_bone_quat).all()
    seen = _rig_seen(rig, take.labels, take.markers_world)
    _check_accounting(rig, cal, res, seen)
    missing = ~seen
    for k, idx in enumerate(_bone_markers(rig)):
        assert (res.bone_quality[missing[:, idx].any(axis=1), k] < 1.0).all()
    held = (res.bone_flags & FLAG_HELD) != 0
    print(
        f"\nsynthetic menache, 20 % dropout: {100 * missing.mean():.1f} % occluded, "
        f"bones held {100 * held.mean():.1f} % of bone-frames, mean quality "
        f"{res.bone_quality.mean():.2f}"
    )
    assert held.any()
