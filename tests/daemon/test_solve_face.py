"""The face solve: stabilization and bounded weights against known truth and scipy.

Ground truth (``face_synth``), for each of two real face models (the scanned ICT-FaceKit
and the artist-made MakeHuman mesh with TalkingHead's ARKit targets): the face as ARKit
52 shapes at 40 facial marker sites (eyelids, cheeks, forehead, brows, nose, lips, jaw)
with known, asymmetric weights and 0.5 mm noise (3-D RMS, per-axis sigma 0.29 mm) on
every marker, under the Plug-in Gait walk's own four head markers and carried by their
motion. "Stabilization residual" is the error the fitted head pose adds (stabilized
marker minus the same observed marker mapped by the true pose), not the markers' own
noise, which is reported beside it (``test_face_stabilization_and_weights``). A small
random face (no datasets) checks exactness and the kernel contract;
``scipy.optimize.lsq_linear`` is the oracle of the weights.
"""

from __future__ import annotations

import dataclasses
import math
import os
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from paths import DATASETS
from scipy.optimize import lsq_linear
from scipy.spatial.transform import Rotation

from retargetd.daemon.face import solve as sf
from retargetd.daemon.face.observability import pose_jacobian
from retargetd.daemon.synth import face as fs


def _random_training(
    rng: np.random.Generator, m: int = 12, k: int = 6
) -> sf.TrainingSet:
    head = rng.normal(0.0, 0.06, (4, 3))
    return sf.TrainingSet(
        head_names=("H0", "H1", "H2", "H3"),
        marker_names=tuple(f"M{i}" for i in range(m)),
        expression_names=tuple(f"E{i}" for i in range(k)),
        head_layout=head - head.mean(axis=0),
        neutral=rng.normal(0.0, 0.05, (m, 3)) + np.array([0.0, 0.08, -0.05]),
        deltas=rng.normal(0.0, 0.005, (k, m, 3)),
    )


def _frames(
    tr: sf.TrainingSet, rng: np.random.Generator, w: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    n = len(w)
    quat = Rotation.random(n, random_state=1).as_quat(scalar_first=True)
    pos = rng.normal(0.0, 0.5, (n, 3)) + np.array([0.0, 0.0, 1.6])
    face = tr.neutral + np.einsum("tk,kmc->tmc", w, tr.deltas)
    local = np.concatenate([np.broadcast_to(tr.head_layout, (n, 4, 3)), face], axis=1)
    rot = Rotation.from_quat(quat, scalar_first=True).as_matrix()
    return np.einsum("tij,tmj->tmi", rot, local) + pos[:, None], quat, pos


def _oracle(
    solver: sf.FaceSolver,
    markers_head: np.ndarray,
    seen: np.ndarray,
    held: np.ndarray | None = None,
    head_seen: np.ndarray | None = None,
) -> np.ndarray:
    # min |B_v w + J_v delta - d_v|^2 + delta^T G delta + lambda |w|^2, 0 <= w <= 1,
    # delta (the head pose's correction, 6) free, as one stacked least squares over
    # the solver's solved shapes (the others are 0); G's rows are the head markers'
    # Jacobians (``head_seen``, default all). ``held`` (K,) weights, NaN where free:
    # shapes held at a value (their key markers hidden) are fixed there.
    tr = solver.training
    rows = np.repeat(seen, 3)
    d = (markers_head - tr.neutral).reshape(-1)[rows]
    w = np.zeros(tr.k)
    fixed = np.zeros(tr.k, bool) if held is None else np.isfinite(held)
    free = solver.solved & ~fixed
    if fixed.any():
        w[fixed] = held[fixed]
        d = d - tr.basis[rows][:, fixed] @ held[fixed]
    basis = tr.basis[:, free]
    k = basis.shape[1]
    jac = pose_jacobian(tr.neutral).reshape(-1, 6)[rows]
    hs = np.ones(len(tr.head_names), bool) if head_seen is None else head_seen
    jh = pose_jacobian(tr.head_layout[hs]).reshape(-1, 6)
    a = np.block(
        [
            [basis[rows], jac],
            [math.sqrt(solver.lambda_) * np.eye(k), np.zeros((k, 6))],
            [np.zeros((len(jh), k)), jh],
        ]
    )
    rhs = np.concatenate([d, np.zeros(k + len(jh))])
    lo = np.r_[np.zeros(k), np.full(6, -np.inf)]
    hi = np.r_[np.ones(k), np.full(6, np.inf)]
    w[free] = lsq_linear(a, rhs, bounds=(lo, hi), method="bvls", tol=1e-14).x[:k]
    return w


def test_noise_free_random_face_is_exact(rng: np.random.Generator) -> None:
    tr = _random_training(rng)
    w = rng.uniform(0.0, 1.0, (30, tr.k)) * (rng.uniform(size=(30, tr.k)) > 0.3)
    markers, quat, pos = _frames(tr, rng, w)
    solver = sf.FaceSolver(tr, regularization=0.0)
    out = solver.new_output()
    valid = np.ones(markers.shape[1], dtype=bool)
    for t in range(len(w)):
        assert solver.solve_frame(markers[t], valid, out) is out
        assert out.flags == 0
        np.testing.assert_allclose(out.world_from_head_pos, pos[t], atol=1e-9)
        dot = abs(float(np.dot(out.world_from_head_quat, quat[t])))
        assert dot == pytest.approx(1.0, abs=1e-12)
        expect = tr.neutral + np.einsum("k,kmc->mc", w[t], tr.deltas)
        np.testing.assert_allclose(out.markers_head, expect, atol=1e-9)
        np.testing.assert_allclose(out.weights, w[t], atol=1e-7)


def test_weights_equal_scipy_oracle_with_occlusion(rng: np.random.Generator) -> None:
    tr = _random_training(rng, m=20, k=10)
    # Weights partly outside [0, 1] and noise: many bounds active.
    w = rng.uniform(-0.5, 1.5, (60, tr.k))
    markers, _, _ = _frames(tr, rng, w)
    markers += rng.normal(0.0, 3e-4, markers.shape)
    solver = sf.FaceSolver(tr, regularization=1e-2)
    out = solver.new_output()
    for t in range(len(w)):
        valid = np.ones(markers.shape[1], dtype=bool)
        if t % 3:
            valid[4 + rng.choice(tr.neutral.shape[0], 4, replace=False)] = False
        frame = markers[t].copy()
        frame[~valid] = np.nan
        solver.solve_frame(frame, valid, out)
        assert out.status[1] > 0, "not converged"
        seen = valid[4:]
        assert np.array_equal(np.isfinite(out.markers_head[:, 0]), seen)
        assert bool(out.flags & sf.FLAG_FACE_PARTIAL) == (not seen.all())
        np.testing.assert_allclose(
            out.weights, _oracle(solver, out.markers_head, seen), atol=1e-6
        )


def test_head_lost_holds_pose_and_weights(rng: np.random.Generator) -> None:
    tr = _random_training(rng)
    w = rng.uniform(0.0, 1.0, (2, tr.k))
    markers, _, _ = _frames(tr, rng, w)
    solver = sf.FaceSolver(tr)
    out = solver.new_output()
    valid = np.ones(markers.shape[1], dtype=bool)
    solver.solve_frame(markers[0], np.zeros_like(valid), out)
    assert out.flags & sf.FLAG_NEVER and out.flags & sf.FLAG_HEAD_LOST
    np.testing.assert_array_equal(out.world_from_head_quat, [1.0, 0.0, 0.0, 0.0])
    solver.solve_frame(markers[0], valid, out)
    quat, pos, wts = (
        out.world_from_head_quat.copy(),
        out.world_from_head_pos.copy(),
        out.weights.copy(),
    )
    lost = valid.copy()
    lost[:2] = False  # two head markers left: not enough
    solver.solve_frame(markers[1], lost, out)
    assert out.flags & sf.FLAG_HEAD_LOST and not out.flags & sf.FLAG_NEVER
    np.testing.assert_array_equal(out.world_from_head_quat, quat)
    np.testing.assert_array_equal(out.world_from_head_pos, pos)
    np.testing.assert_array_equal(out.weights, wts)
    assert np.isnan(out.markers_head).all()


def test_training_set_round_trip(tmp_path: Path, rng: np.random.Generator) -> None:
    tr = _random_training(rng)
    tr.save(tmp_path / "face.npz")
    back = sf.TrainingSet.load(tmp_path / "face.npz")
    assert back.marker_names == tr.marker_names
    assert back.head_names == tr.head_names
    assert back.expression_names == tr.expression_names
    np.testing.assert_array_equal(back.deltas, tr.deltas)
    np.testing.assert_array_equal(back.neutral, tr.neutral)
    np.testing.assert_array_equal(back.head_layout, tr.head_layout)
    np.savez(tmp_path / "other.npz", x=np.zeros(3))
    with pytest.raises(ValueError, match="not a"):
        sf.TrainingSet.load(tmp_path / "other.npz")


def test_a_training_set_is_written_atomically_npz_appended(
    tmp_path: Path, rng: np.random.Generator, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A live capture's save runs on a worker thread (``live/face.py``): a write cut
    short (a full disk, the process ending) must leave the file that was there
    whole. A name without ``.npz`` gets it, as ``numpy.savez`` did."""
    tr = _random_training(rng)
    tr.save(tmp_path / "face")
    assert sf.TrainingSet.load(tmp_path / "face.npz").k == tr.k
    before = (tmp_path / "face.npz").read_bytes()

    def full(*args: object, **kwargs: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", full)
    with pytest.raises(OSError, match=r"cannot write .*face\.npz"):
        dataclasses.replace(tr, noise_rms_m=1e-3).save(tmp_path / "face.npz")
    assert (tmp_path / "face.npz").read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["face.npz"]


def test_bad_training_shapes_are_rejected(rng: np.random.Generator) -> None:
    tr = _random_training(rng)
    with pytest.raises(ValueError, match="deltas"):
        sf.TrainingSet(
            head_names=tr.head_names, marker_names=tr.marker_names,
            expression_names=tr.expression_names, head_layout=tr.head_layout,
            neutral=tr.neutral, deltas=tr.deltas[:, :3],
        )  # fmt: skip


def test_neutral_only_training_set_stabilizes_without_weights(
    rng: np.random.Generator,
) -> None:
    # No expression captured yet: the solver still stabilizes, with zero weights.
    full = _random_training(rng, m=5, k=1)
    tr = dataclasses.replace(full, expression_names=(), deltas=np.zeros((0, 5, 3)))
    assert tr.basis.shape == (15, 0)
    markers, _, _ = _frames(tr, rng, np.zeros((3, 0)))
    solver = sf.FaceSolver(tr)
    out = solver.new_output()
    for frame in markers:
        solver.solve_frame(frame, np.ones(len(frame), dtype=bool), out)
        assert out.weights.shape == (0,) and out.status[0] == 0
        np.testing.assert_allclose(out.markers_head, tr.neutral, atol=1e-12)


def test_solve_frame_allocates_nothing(rng: np.random.Generator) -> None:
    tr = _random_training(rng, m=40, k=52)
    w = rng.uniform(-0.2, 1.2, (200, tr.k))
    markers, _, _ = _frames(tr, rng, w)
    markers = np.ascontiguousarray(markers)
    solver = sf.FaceSolver(tr)
    out = solver.new_output()
    valid = np.ones(markers.shape[1], dtype=bool)
    occluded = valid.copy()
    occluded[[1, 7, 9]] = False
    for t in range(20):  # warm-up: compilation
        solver.solve_frame(markers[t], valid if t % 2 else occluded, out)
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        start, _ = tracemalloc.get_traced_memory()
        for t in range(1000):
            res = solver.solve_frame(
                markers[t % 200], valid if t % 7 else occluded, out
            )
        end, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert res is out
    assert out.weights.dtype == np.float64 and out.markers_head.dtype == np.float64
    assert end - start < 1024, f"{end - start} bytes kept over 1000 solve_frame calls"
    # Nothing allocated per call either: the peak, not just what is kept. numba's
    # dispatch of one call (argument boxing) peaks at ~2.2 KB here; a (40, 3) float64
    # array more (1.1 KB) would cross the line.
    assert peak - start < 3072, f"peak {peak - start} bytes above the start"


def test_stabilization_error_matches_monte_carlo(rng: np.random.Generator) -> None:
    tr = _random_training(rng)
    noise = 5e-4
    n = 3000
    local = np.concatenate([tr.head_layout, tr.neutral])
    rots = Rotation.random(n, random_state=2).as_matrix()
    for weights, seen in (
        (None, None),
        ([3.0, 1.0, 1.0, 0.5], None),
        (None, [True, False, True, True]),
    ):
        solver = sf.FaceSolver(tr, head_weights=weights)
        out = solver.new_output()
        valid = np.ones(len(local), dtype=bool)
        if seen is not None:
            valid[:4] = seen
        err = np.empty((n, len(tr.neutral), 3))
        for t in range(n):
            pos = rng.normal(0.0, 1.0, 3)
            noisy = local @ rots[t].T + pos
            noisy += rng.normal(0.0, noise / math.sqrt(3.0), noisy.shape)
            solver.solve_frame(np.where(valid[:, None], noisy, np.nan), valid, out)
            err[t] = out.markers_head - (noisy[4:] - pos) @ rots[t]
        got = np.sqrt(np.mean(np.sum(err**2, axis=-1), axis=0))
        want = sf.stabilization_error(
            tr, noise_rms_m=noise, head_weights=weights, head_seen=seen
        )
        np.testing.assert_allclose(got, want, rtol=0.05)
    # Equal weights are the best for equal noise (Gauss-Markov).
    equal = sf.stabilization_error(tr)
    for _ in range(5):
        other = sf.stabilization_error(tr, head_weights=rng.uniform(0.2, 2.0, 4))
        assert np.mean(other**2) >= np.mean(equal**2)
    with pytest.raises(ValueError, match="3"):
        sf.stabilization_error(tr, head_seen=[True, True, False, False])


# ---- ICT-FaceKit and MakeHuman on the Plug-in Gait head motion ------------------


#: Same place as ``tests/conftest.py``'s DATASETS (a conftest can't be imported).


@pytest.fixture(scope="module", params=sorted(fs.MODELS))
def face_take(request: pytest.FixtureRequest) -> fs.SynthFace:
    """A synthetic face on the PiG walk's head motion, once per face model: the
    scanned ICT-FaceKit and the artist-made MakeHuman/TalkingHead ARKit targets
    (module-wide: ~1 s each)."""
    folder = DATASETS / fs.MODEL_DIRS[request.param]
    if not folder.is_dir():
        reason = f"face dataset not found at {folder}"
        if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
            pytest.fail(f"{reason} (CI=true: nothing may skip)")
        pytest.skip(reason)
    # The performer moves the shapes the 40 markers can see; the others stay at 0
    # (issue 32's scenario): a shape no marker tells apart is left out of the solve,
    # so a motion of it would leak into the seen shapes (README "Face").
    return fs.synth_face_take(
        DATASETS, np.random.default_rng(0), model=request.param,
        unobservable_still=True,
    )  # fmt: skip


def _solve_take(
    take: fs.SynthFace, valid: np.ndarray | None = None
) -> tuple[sf.FaceSolver, dict[str, np.ndarray]]:
    # As the daemon solves: the shapes the layout cannot observe left out (issue 32).
    solver = sf.FaceSolver(
        take.training, solved=sf.observability(take.training).observable
    )
    out = solver.new_output()
    n, m = take.markers_world.shape[:2]
    if valid is None:
        valid = np.ones((n, m), dtype=bool)
    markers = np.where(valid[..., None], take.markers_world, np.nan)
    got: dict[str, list[np.ndarray]] = {k: [] for k in ("w", "s", "q", "p", "f", "st")}
    for t in range(n):
        solver.solve_frame(markers[t], valid[t], out)
        got["w"].append(out.weights.copy())
        got["s"].append(out.markers_head.copy())
        got["q"].append(out.world_from_head_quat.copy())
        got["p"].append(out.world_from_head_pos.copy())
        got["f"].append(out.status.copy())
        got["st"].append(out.shape_state.copy())
    return solver, {k: np.array(v) for k, v in got.items()}


def _head_truth(take: fs.SynthFace, clean: bool = False) -> np.ndarray:
    # The observed facial markers (noisy, or the noise-free ones) taken to head
    # coordinates by the TRUE head pose: what a perfect stabilizer would output.
    rot = Rotation.from_quat(take.world_from_head_quat, scalar_first=True).as_matrix()
    world = take.markers_clean_world if clean else take.markers_world
    rel = world[:, len(take.training.head_names) :] - take.world_from_head_pos[:, None]
    return np.einsum("tji,tmj->tmi", rot, rel)


def _rms_mm(err: np.ndarray) -> float:
    # 3-D RMS over every finite (frame, marker), millimetres.
    return 1e3 * float(np.sqrt(np.nanmean(np.sum(err**2, axis=-1))))


def _fit_residual_mm(
    take: fs.SynthFace, got: dict[str, np.ndarray], used: np.ndarray | None = None
) -> float:
    # RMS distance of the head markers used in the fit from the fitted layout.
    h = len(take.training.head_names)
    rot = Rotation.from_quat(got["q"], scalar_first=True).as_matrix()
    fitted = (
        np.einsum("tij,mj->tmi", rot, take.training.head_layout) + got["p"][:, None]
    )
    res = np.sum((take.markers_world[:, :h] - fitted) ** 2, axis=-1)
    if used is not None:
        res = res[:, used]
    return 1e3 * float(np.sqrt(np.mean(res)))


def _predicted_mm(take: fs.SynthFace, seen: np.ndarray | None = None) -> float:
    e = sf.stabilization_error(
        take.training, noise_rms_m=take.noise_rms_m, head_seen=seen
    )
    return 1e3 * float(np.sqrt(np.mean(e**2)))


#: Per model: how many of the 52 shapes its 40 markers must see, and shapes that
#: must be reported unobservable (ICT has no tongue shape; MakeHuman's moves only
#: the tongue, under the skin; gaze shapes look like lid shapes in both).
EXPECTED_OBSERVABILITY = {
    "ict": (30, {"tongueOut", "eyeLookUpLeft", "eyeLookDownLeft"}),
    "makehuman": (25, {"tongueOut", "eyeLookUpLeft", "eyeLookDownLeft"}),
}


def test_face_layout_and_observability(face_take: fs.SynthFace) -> None:
    tr = face_take.training
    assert len(tr.marker_names) >= 40 and tr.k == 52
    assert face_take.markers_world.shape[0] > 200  # every complete frame of the walk
    # The head markers are the take's own four, in their measured layout.
    layout = fs.pig_head_layout(DATASETS)
    np.testing.assert_allclose(tr.head_layout, layout - layout.mean(axis=0))
    # The face sits under the band: facial markers below and in front of it,
    # spread over a face-sized area (eyelids and brows to the chin).
    assert (tr.neutral[:, 2] < 0.0).all()
    assert 0.09 <= float(np.ptp(tr.neutral[:, 2])) <= 0.16
    assert 0.08 <= float(np.ptp(tr.neutral[:, 0])) <= 0.14
    obs = sf.observability(tr)
    n_observable, must_be_unobservable = EXPECTED_OBSERVABILITY[face_take.model]
    # Reported, not pretended.
    assert must_be_unobservable <= set(obs.unobservable)
    assert obs.observable.sum() >= n_observable
    for name in ("jawOpen", "mouthSmileLeft", "browInnerUp", "cheekPuff"):
        assert obs.observable[tr.expression_names.index(name)], name


def test_face_stabilization_and_weights(face_take: fs.SynthFace) -> None:
    """Issue 7 item 5 on the synthetic face (0.5 mm 3-D RMS noise on every marker).

    The stabilization residual is the error the fitted head pose puts on the facial
    markers: stabilized marker minus the SAME observed marker mapped by the true
    head pose (``_head_truth``). Against the noise-free face the stabilized markers
    also hold their own noise, which no stabilizer removes; both parts are measured
    here, and the residual is checked against its first-order prediction
    (``solve_face.stabilization_error``), so the figure is the fit's, not luck's.
    """
    solver, got = _solve_take(face_take)
    assert (got["f"][:, 0] == 0).all()
    noise_mm = 1e3 * face_take.noise_rms_m
    # Head-marker fit residual: 4 markers, 6 pose dof -> noise * sqrt(1 - 6/12).
    assert _fit_residual_mm(face_take, got) == pytest.approx(
        noise_mm * math.sqrt(0.5), rel=0.1
    )
    # Stabilization residual (issue: <= 0.5 mm RMS), expected value and measured.
    stab = _rms_mm(got["s"] - _head_truth(face_take))
    predicted = _predicted_mm(face_take)
    assert predicted <= 0.5
    assert stab <= 0.5
    assert stab == pytest.approx(predicted, rel=0.1)
    # The same with noise-free facial markers and noisy head markers.
    clean = face_take.markers_clean_world.copy()
    clean[:, :4] = face_take.markers_world[:, :4]
    _, got_clean = _solve_take(dataclasses.replace(face_take, markers_world=clean))
    stab_clean = _rms_mm(got_clean["s"] - _head_truth(face_take, clean=True))
    assert stab_clean == pytest.approx(stab, rel=0.01)
    # The markers' own noise, and the total against the noise-free face.
    own = _rms_mm(_head_truth(face_take) - _head_truth(face_take, clean=True))
    assert own == pytest.approx(noise_mm, rel=0.05)
    total = _rms_mm(got["s"] - _head_truth(face_take, clean=True))
    assert total == pytest.approx(math.hypot(stab, own), rel=0.05)
    # Weights: median error on the observable shapes; and the report does not
    # pretend: every shape recovered worse than 0.1 (median) is reported.
    obs = sf.observability(face_take.training)
    w_err = np.abs(got["w"] - face_take.weights)
    assert np.median(w_err[:, obs.observable]) <= 0.05
    per_shape = np.median(w_err, axis=0)
    assert (per_shape[obs.observable] <= 0.1).all()
    bad = {
        face_take.training.expression_names[k] for k in np.flatnonzero(per_shape > 0.1)
    }
    assert bad <= set(obs.unobservable)
    # The oracle on a sample of frames.
    seen = np.ones(len(face_take.training.marker_names), dtype=bool)
    for t in range(0, len(w_err), 40):
        np.testing.assert_allclose(
            got["w"][t], _oracle(solver, got["s"][t], seen), atol=1e-6
        )


def test_face_noise_free_stabilization_is_exact(face_take: fs.SynthFace) -> None:
    clean = fs.synth_face_take(
        DATASETS, np.random.default_rng(0), noise_rms_m=0.0, model=face_take.model
    )
    _, got = _solve_take(clean)
    np.testing.assert_allclose(got["s"], _head_truth(clean), atol=1e-9)
    # Any three head markers fit the rigid head exactly.
    n, m = clean.markers_world.shape[:2]
    for lost in range(4):
        valid = np.ones((n, m), dtype=bool)
        valid[:, lost] = False
        _, got = _solve_take(clean, valid)
        np.testing.assert_allclose(got["s"], _head_truth(clean), atol=1e-9)


def test_face_missing_head_marker(face_take: fs.SynthFace) -> None:
    n, m = face_take.markers_world.shape[:2]
    obs = sf.observability(face_take.training)
    for lost in range(4):
        valid = np.ones((n, m), dtype=bool)
        valid[:, lost] = False
        _, got = _solve_take(face_take, valid)
        assert (got["f"][:, 0] == sf.FLAG_HEAD_PARTIAL).all()
        # 3 markers: noise * sqrt(1 - 6/9).
        assert _fit_residual_mm(face_take, got, valid[0, :4]) == pytest.approx(
            1e3 * face_take.noise_rms_m / math.sqrt(3.0), rel=0.1
        )
        # Three markers are a weaker fit (0.55-0.79 mm here), as predicted.
        stab = _rms_mm(got["s"] - _head_truth(face_take))
        assert stab == pytest.approx(_predicted_mm(face_take, valid[0, :4]), rel=0.1)
        assert stab <= 1.0
        w_err = np.abs(got["w"] - face_take.weights)
        assert np.median(w_err[:, obs.observable]) <= 0.05
    # A head marker that drops out now and then: flagged on exactly those frames.
    valid = np.ones((n, m), dtype=bool)
    valid[:, 2] = np.random.default_rng(4).uniform(size=n) > 0.2
    _, got = _solve_take(face_take, valid)
    partial = got["f"][:, 0] == sf.FLAG_HEAD_PARTIAL
    assert np.array_equal(partial, ~valid[:, 2])
    assert (got["f"][valid[:, 2], 0] == 0).all()


def test_face_occluded_facial_markers(face_take: fs.SynthFace) -> None:
    rng = np.random.default_rng(3)
    n, m = face_take.markers_world.shape[:2]
    valid = np.ones((n, m), dtype=bool)
    valid[:, 4:] = rng.uniform(size=(n, m - 4)) > 0.1  # 10 % of facial markers
    solver, got = _solve_take(face_take, valid)
    assert (got["f"][:, 0] & sf.FLAG_FACE_PARTIAL).any()
    assert (got["f"][:, 2] == valid[:, 4:].sum(axis=1)).all()
    assert np.array_equal(np.isfinite(got["s"][..., 0]), valid[:, 4:])
    # Facial occlusion does not touch the head fit: the seen markers are stabilized
    # exactly as with every marker seen.
    _, full = _solve_take(face_take)
    np.testing.assert_allclose(got["s"][valid[:, 4:]], full["s"][valid[:, 4:]])
    obs = sf.observability(face_take.training)
    assert np.median(np.abs(got["w"] - face_take.weights)[:, obs.observable]) <= 0.05
    for t in range(0, n, 40):
        # A shape whose key marker is hidden holds its last weight (0 at the start).
        hidden = (got["st"][t] & sf.SHAPE_HIDDEN) > 0
        last = got["w"][t - 1] if t else np.zeros(face_take.training.k)
        held = np.where(hidden, last, np.nan)
        np.testing.assert_allclose(
            got["w"][t], _oracle(solver, got["s"][t], valid[t, 4:], held), atol=1e-6
        )


# ---- issue 32: what the layout cannot see is not streamed as seen -------------------


def test_unobservable_shapes_are_left_out_and_sent_as_zero(
    face_take: fs.SynthFace,
) -> None:
    """The shapes the 40 markers cannot observe (at 0.5 mm) are not solved: their
    weight is exactly 0 on every frame and their state says ``unobserved``; each is
    reported with the shape it is confused with. A performer who moved them would
    leak their motion into the seen shapes, so here (as in the issue) they are
    still, and the truth of the unobserved ones is 0 whatever the solver says."""
    tr = face_take.training
    obs = sf.observability(tr)
    unseen = ~obs.observable
    assert unseen.sum() >= 10 and obs.observable.sum() >= 30
    # Every shape kept is observable in the solve that runs (std at 0.5 mm).
    assert (obs.weight_std[obs.observable] <= sf.MAX_WEIGHT_STD).all()
    assert (obs.weight_std[unseen] > sf.MAX_WEIGHT_STD).all()
    # Each unobservable shape: nothing moved, or confused with a kept shape.
    for k in np.flatnonzero(unseen):
        if obs.peak_m[k] >= obs.min_peak_m:
            partner = tr.expression_names.index(obs.confused_with[k])
            assert obs.observable[partner] and abs(obs.correlation[k]) > 0.3
    lines = obs.describe()
    assert len(lines) == unseen.sum()
    assert any(
        line.startswith("eyeLookUpLeft: confused with eyeBlinkLeft") for line in lines
    )
    assert any(line.startswith("tongueOut: moves no marker") for line in lines)
    _, got = _solve_take(face_take)
    assert (got["w"][:, unseen] == 0.0).all()
    assert (got["st"][:, unseen] == sf.SHAPE_UNOBSERVED).all()
    assert (got["st"][:, obs.observable] == 0).all()
    err = np.abs(got["w"] - face_take.weights)
    # Median 0.019 (ICT) / 0.016 (MakeHuman); p95 0.102 / 0.080: 38 / 32 shapes move
    # at once, each with a noise std up to MAX_WEIGHT_STD. The solver before issue 32's
    # item 4 (the ridge 1e-3 mean(diag B^T B), the head pose from the head markers
    # alone) gave ICT 0.13, which fails here.
    assert np.median(err[:, obs.observable]) <= 0.05
    assert np.percentile(err[:, obs.observable], 95) <= 0.11
    # A larger noise level leaves more shapes out, never fewer.
    noisier = sf.observability(tr, noise_rms_m=1e-3)
    assert set(obs.unobservable) <= set(noisier.unobservable)
    assert noisier.observable.sum() < obs.observable.sum()


def test_a_hidden_key_marker_holds_and_flags_its_shape(
    face_take: fs.SynthFace,
) -> None:
    """A solved shape's key markers are those whose loss alone makes it
    unobservable. While one is hidden, that shape (and only the shapes it is key to)
    holds its last weight, flagged ``hidden`` per shape; the frame says
    ``shape_held``; the other shapes go on being solved."""
    tr = face_take.training
    obs = sf.observability(tr)
    solver = sf.FaceSolver(tr, solved=obs.observable)
    keys = solver.key_markers()
    shape, markers = next((s, m) for s, m in keys.items() if m)
    marker = tr.marker_names.index(markers[0])
    owners = {s for s, m in keys.items() if markers[0] in m}
    k_owned = np.array([tr.expression_names.index(s) for s in owners])
    n, m = face_take.markers_world.shape[:2]
    k0 = tr.expression_names.index(shape)
    # Hidden for 60 frames from a frame where the shape is well on.
    start = 20 + int(np.argmax(face_take.weights[20 : n - 80, k0] > 0.3))
    hide = slice(start, start + 60)
    valid = np.ones((n, m), dtype=bool)
    valid[hide, 4 + marker] = False
    _, got = _solve_take(face_take, valid)
    hidden = (got["st"] & sf.SHAPE_HIDDEN) > 0
    expect = np.zeros(n, bool)
    expect[hide] = True
    for k in range(tr.k):
        want = expect if k in k_owned else np.zeros(n, bool)
        assert np.array_equal(hidden[:, k], want), tr.expression_names[k]
    held_flag = (got["f"][:, 0] & sf.FLAG_SHAPE_HELD) > 0
    assert np.array_equal(held_flag, expect)
    # Held, not decayed: the weight of the frame before, on every hidden frame.
    assert got["w"][hide.start - 1, k0] > 0.1
    assert (got["w"][hide, k0] == got["w"][hide.start - 1, k0]).all()
    # Released: solved again from the next frame.
    after = slice(hide.stop, hide.stop + 20)
    assert np.median(np.abs(got["w"][after, k0] - face_take.weights[after, k0])) < 0.1
    # The other seen shapes stay as right as with every marker.
    others = obs.observable.copy()
    others[k_owned] = False
    err = np.abs(got["w"] - face_take.weights)[hide][:, others]
    assert np.median(err) <= 0.05
