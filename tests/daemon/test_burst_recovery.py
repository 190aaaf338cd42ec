"""``bench/burst_recovery.py``: the soak's bursts of bad frames replayed offline
(issue 28 item 3, issue 30 item 6), its short version."""

from __future__ import annotations

import random
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from bench_scripts import bench_module

from retargetd.daemon.body.calibration import calibrate
from retargetd.daemon.body.method import make_body_solver
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.synth.damage import bone_deviation_deg
from retargetd.daemon.validate.limits import JOINT_LIMITS_DEG
from retargetd.daemon.validate.model import SEGMENT_KIND
from retargetd.replay.takes import load_take


def _pig_walk(datasets: Path) -> tuple[Any, Callable[[float], Any]]:
    """The btkdata PiG walk ``bench/burst_recovery.py`` replays, and a maker of the
    plug-in-gait fit (calibrated on the walk's static) at a rate."""
    br = bench_module("burst_recovery")
    static, walk = load_take(datasets / br.STATIC), load_take(datasets / br.WALK)
    rig = load_rig("plug-in-gait")
    cal = calibrate(rig, static.positions, static.labels,
                    take_measurements=static.measurements)  # fmt: skip

    def fit(rate: float) -> Any:
        return make_body_solver(
            "fit", rig, cal, walk.labels, joint_limits=JOINT_LIMITS_DEG,
            segment_kind=SEGMENT_KIND, rate_hz=rate,
        )  # fmt: skip

    return walk, fit


def test_the_bad_frames_are_the_soaks() -> None:
    """Each kind of bad frame as the soak's source makes it, as the solver gets it
    (zeros and 1e30 occluded by the live decoder: not seen)."""
    br = bench_module("burst_recovery")
    labels = ["LASI", "RASI", "T10", "LKNE", "RKNE"]
    swap = br._swap(labels)
    assert swap.tolist() == [1, 0, 2, 4, 3]
    row = np.arange(15, dtype=float).reshape(5, 3)
    row[2] = np.nan
    assert np.isnan(br._bad("zeros", row, swap)).all()
    assert np.isnan(br._bad("far", row, swap)).all()
    assert np.array_equal(br._bad("swapped", row, swap), row[swap], equal_nan=True)
    collapsed = br._bad("collapsed", row, swap)
    seen = [0, 1, 3, 4]
    assert np.allclose(collapsed[seen], row[seen].mean(axis=0))
    assert np.isnan(collapsed[2]).all()


@pytest.mark.timeout(300)
def test_short_run_measures_every_burst(datasets: Path) -> None:
    """Eight bursts, two of each kind, 1, 2, 10 and 50 frames long in turn: each
    measured, and every one back within the issue's 0.25 s of the solve without the
    bursts (before the first frame after a gap stopped measuring hidden markers on
    the held pose, and a frame kept while suspect stopped raising the level, the 50
    frames at 1e30 took 0.467 s, the head 109 deg off). The soak's random lengths,
    where a few are still late: bench/burst_recovery.py, README "What is not right
    yet"."""
    br = bench_module("burst_recovery")
    result = br.run(datasets, bursts=8, seed=1, method="fit", every_s=1.0,
                    rate_hz=240.0, dropout=0.10, lengths=(1, 2, 10, 50))  # fmt: skip
    rows = result["bursts"]
    assert [b["kind"] for b in rows] == list(br.soak.BURSTS) * 2
    assert [b["frames"] for b in rows] == [1, 2, 10, 50] * 2
    assert all(b["recovery_s"] > 0.0 for b in rows)
    assert all(b["recovery_s"] <= br.soak.MAX_RECOVERY_S for b in rows), rows
    # the second measure (against the solve with nothing hidden) is the weaker one
    assert all(b["no_worse_s"] <= b["recovery_s"] for b in rows), rows
    lines = br.report(result)
    print("\n" + "\n".join(lines))
    assert any(line.startswith("late (over 0.25 s):") for line in lines)


@pytest.mark.timeout(300)
def test_soak_seed_1_bursts(datasets: Path) -> None:
    """The soak's 40 bursts of seed 1 (``bench/burst_recovery.py --seed 1``): the
    collapse of 50 frames came back in 0.271 s while the second frame after a gap
    still measured the hidden markers on the first one held (T10 and LTOE hidden
    across the burst's end: the spine 4.5 deg off the solve without the burst and
    4.7 off the one with nothing hidden, where that solve is 1.1 off). One burst is
    late still (1e30 for 38 frames, 0.271 s), where the solve without the bursts is
    the one off (LFIN and LWRA hidden there: its forearm 14 deg from the solve with
    nothing hidden, the burst's 3): by the second measure none is late. With the
    local floor for two hidden markers only (helper h28a) the solve without the
    bursts became the better one there and that burst was late by the second
    measure too (0.267 s); with a hidden marker on a bone none of whose markers is
    seen fading with its age (helper h28b) as well, 0.267 s, no worse after 0.087 s
    (measured on the merged tree, 2026-12-06)."""
    br = bench_module("burst_recovery")
    result = br.run(datasets, bursts=40, seed=1, method="fit", every_s=2.5,
                    rate_hz=240.0, dropout=0.10)  # fmt: skip
    rows = result["bursts"]
    limit = br.soak.MAX_RECOVERY_S
    late = [b for b in rows if b["recovery_s"] > limit]
    assert len(late) <= 1, late
    assert all(b["no_worse_s"] <= limit for b in rows), rows


@pytest.mark.timeout(300)
@pytest.mark.parametrize("kind", ["collapsed", "swapped"])
def test_a_burst_at_a_restart_leaves_nothing(datasets: Path, kind: str) -> None:
    """A source that restarts into a burst (the soak, 120 s at seed 1: a collapse as
    the first 24 frames after a restart left the arms 150-180 deg off the intact solve
    for 1.3 s and the next burst 1 s): the walk at 240 Hz with the soak's occlusions,
    the solver reset as the daemon resets it, the first 10 frames after it bad, and
    a second burst 1.2 s later (inside the residual level's 1 s). The bad first
    frames are unexplained, so from the first good frame on the solve is exactly
    that of a solver started there, and the second burst is back within 0.25 s.
    Before: the first bad frame, taken as the first pose, became the take's level
    (5 of the 10 collapsed frames and 7 of the swapped ones were then explained; the
    level before the second burst 155 and 88 mm, the intact solve's 6.1), and at 4x
    that little was unexplained or suspect: the second burst came back after 0.84
    and 0.76 s (170 and 132 deg off); after, 0.033 s."""
    br = bench_module("burst_recovery")
    soak = br.soak
    walk, fit = _pig_walk(datasets)
    rate, restart, n_bad, second = 240.0, 240, 10, 290
    n = restart + second + n_bad + 240
    pos = walk.positions
    rows = np.array([soak.walk_row(k, pos.shape[0]) for k in range(n)])
    clean = pos[rows].copy()
    rng = np.random.default_rng(1)
    clean[soak.occlusion_mask(rng, n, pos.shape[1], 0.10)] = np.nan
    bad = clean.copy()
    swap = br._swap(list(walk.labels))
    for f in (*range(restart, restart + n_bad),
              *range(restart + second, restart + second + n_bad)):  # fmt: skip
        bad[f] = br._bad(kind, clean[f], swap)

    def solve(markers: np.ndarray, reset_at: int) -> Any:
        solver = fit(rate)
        solver.solve_take(markers[:reset_at])
        solver.reset()  # the source restarted (frame numbers from 0)
        return solver.solve_take(markers[reset_at:])

    hit, twin = solve(bad, restart), solve(clean, restart)
    fresh = solve(clean, restart + n_bad)
    assert hit.unexplained[:n_bad].all()
    # from the first good frame to the second burst: a solver started there
    span, k = slice(n_bad, second), second - n_bad
    assert np.array_equal(hit.unexplained[span], fresh.unexplained[:k])
    dot = np.sum(hit.world_from_bone_quat[span] * fresh.world_from_bone_quat[:k], -1)
    assert np.abs(np.abs(dot) - 1.0).max() < 1e-9
    level = hit.residual_level[second - 1]
    assert level < 2.0 * twin.residual_level[second - 1], level
    rec_s = _recovery_s(hit, twin, second + n_bad, rate)
    print(f"{kind}: level {level * 1e3:.1f} mm, second burst back in {rec_s:.3f} s")
    assert rec_s <= soak.MAX_RECOVERY_S


@pytest.mark.timeout(300)
@pytest.mark.parametrize(("n_mask", "t0"), [(480, 230), (240 * 97, 120)])
def test_a_swapped_burst_is_not_let_in_across_its_gap(
    datasets: Path, n_mask: int, t0: int
) -> None:
    """Left and right labels swapped for 8 frames of the walk at 240 Hz (the soak's
    occlusions, drawn for ``n_mask`` frames): every swapped frame is unexplained, and
    the solve is back within 0.25 s. Before, after a gap the prediction was held and
    bounded by the peak acceleration alone (3 x 1/2 8000 rad/s^2 h^2: 191 deg after 4
    frames), so a swapped frame came in, fitted at 5-6 mm RMS with the pelvis turned
    50 deg from its prediction: the fourth at gap 4 (52 deg off the intact solve, a
    leg 62 deg), the last at gap 8 (a shank 67 deg from its prediction), and the
    true frames after it were judged against it. A root turns at most 3 rev/s (the
    top of a pirouette; ``FitParams.omega_root``): 18 and 36 deg in those 4 and 8
    frames."""
    br = bench_module("burst_recovery")
    soak = br.soak
    walk, fit = _pig_walk(datasets)
    rate, n, n_bad = 240.0, t0 + 250, 8
    pos = walk.positions
    rows = np.array([soak.walk_row(k, pos.shape[0]) for k in range(n)])
    clean = pos[rows].copy()
    hide = soak.occlusion_mask(np.random.default_rng(1), n_mask, pos.shape[1], 0.10)
    clean[hide[:n]] = np.nan
    bad = clean.copy()
    swap = br._swap(list(walk.labels))
    for f in range(t0, t0 + n_bad):
        bad[f] = br._bad("swapped", clean[f], swap)

    def solve(markers: np.ndarray) -> Any:
        return fit(rate).solve_take(markers)

    hit, intact = solve(bad), solve(clean)
    assert not hit.unexplained[:t0].any()
    assert hit.unexplained[t0 : t0 + n_bad].all(), hit.unexplained[t0 : t0 + n_bad]
    rec_s = _recovery_s(hit, intact, t0 + n_bad, rate)
    print(f"swapped {n_bad} frames: back in {rec_s:.3f} s")
    assert rec_s <= soak.MAX_RECOVERY_S


def _soak_burst_replay(
    datasets: Path, seed: int, index: int, after: int
) -> tuple[Any, Any, str, int, int]:
    """``bench/burst_recovery.py --seed SEED``'s take up to ``after`` frames past its
    burst ``index`` (the bursts before it and the soak's occlusions as the full run
    of 40 draws them), solved with and without the bursts: (hit, intact, kind, first
    bad frame, first frame after)."""
    br = bench_module("burst_recovery")
    soak = br.soak
    walk, fit = _pig_walk(datasets)
    rate, n_bursts = 240.0, 40
    every = round(2.5 * rate)
    pos = walk.positions
    rng = np.random.default_rng(seed)
    hide = soak.occlusion_mask(rng, every * (n_bursts + 1), pos.shape[1], 0.10)
    pick = random.Random(seed)
    spans = []
    for i in range(index + 1):
        t0 = every * (i + 1) - every // 2
        spans.append((soak.BURSTS[i % len(soak.BURSTS)], t0, t0 + pick.randint(1, 50)))
    kind, t0, t1 = spans[-1]
    n = t1 + after
    rows = np.array([soak.walk_row(k, pos.shape[0]) for k in range(n)])
    clean = pos[rows].copy()
    clean[hide[:n]] = np.nan
    bad = clean.copy()
    swap = br._swap(list(walk.labels))
    for k, a, b in spans:
        for f in range(a, b):
            bad[f] = br._bad(k, clean[f], swap)

    def solve(markers: np.ndarray) -> Any:
        return fit(rate).solve_take(markers)

    return solve(bad), solve(clean), kind, t0, t1


def _recovery_s(hit: Any, intact: Any, t1: int, rate: float) -> float:
    """Seconds from the burst's last frame to the first after it within the soak's
    degrees and metres of the solve without the bursts, neither held nor unseen."""
    soak = bench_module("burst_recovery").soak
    deg = bone_deviation_deg(
        np.asarray(hit.world_from_bone_quat), np.asarray(intact.world_from_bone_quat)
    ).max(axis=1)
    root = np.linalg.norm(hit.root_pos - intact.root_pos, axis=1)
    back = (deg <= soak.RECOVERED_DEG) & (root <= soak.RECOVERED_M)
    back &= ~hit.unexplained & ~hit.unseen
    after = np.flatnonzero(back[t1:])
    assert after.size, f"never back: {np.nanmax(deg[t1:]):.1f} deg"
    return float((after[0] + 1) / rate)


@pytest.mark.timeout(300)
def test_a_suspect_frame_after_a_gap_does_not_restart_the_track(
    datasets: Path,
) -> None:
    """``bench/burst_recovery.py --seed 5``'s swapped burst of 42 frames (its 7th
    burst, frames 3900-3941): every swapped frame is unexplained, and the solve is
    back within 0.25 s of the solve without the bursts. Before, the 11th came in at
    gap 11 (the pelvis 42.6 deg from its held prediction, under the 49.5 a root can
    turn; 14 of 29 markers rejected, one short of half) and the 12th after it; the
    hidden markers' holds were anchored on that pose, so the true frames after the
    burst kept it (the intact pose's whole cost 0.00242 against the kept one's
    0.00245, its holds 0.00198 of that), the left clavicle 45-62 deg off for 0.45 s.
    After a gap the prediction is held, and a frame still suspect with the better
    candidate (a quarter of its markers rejected, or twice the take's level) no
    longer restarts the track."""
    hit, intact, kind, t0, t1 = _soak_burst_replay(datasets, 5, 6, 120)
    assert (kind, t0, t1 - t0) == ("swapped", 3900, 42)
    assert hit.unexplained[t0:t1].all(), np.flatnonzero(~hit.unexplained[t0:t1])
    rec_s = _recovery_s(hit, intact, t1, 240.0)
    print(f"back in {rec_s:.3f} s")
    assert rec_s <= bench_module("burst_recovery").soak.MAX_RECOVERY_S, rec_s


@pytest.mark.timeout(300)
def test_the_frame_after_a_gap_is_pulled_as_a_held_prediction(datasets: Path) -> None:
    """``bench/burst_recovery.py --seed 6``'s 10 frames at 1e30 (its 8th burst,
    frames 4500-4509: not seen) are back within 0.25 s of the solve without the
    bursts. The first explained frame after a gap gives no velocity, so the next
    one's prediction holds it; its continuity was weighted as an extrapolated one,
    alpha_max dt^2 / 2 (4 deg at 240 Hz), where a joint held can be omega_max dt
    (29 deg) away (the jump bound's own physics, fit_track.jump_bound). Before:
    0.308 s, the right thigh 11.4 deg off. Then 0.346 s once hidden markers' offsets
    faded with their hinges: from two frames after the burst RTHI and RKNE are both
    hidden, and both solves' right thighs ran away on their virtual markers, each
    measured on its own prediction at full weight (43 deg with the burst, 52
    without, from the solve with nothing hidden; RTIB 76 / 96 mm off), and the
    foot stayed 2.4-5.4 deg apart after both reseeded. A hidden marker on a bone
    none of whose markers is seen now fades with its age (fit_track.virtual_markers):
    0.113 s (helper h28b); the local floor needing two hidden markers (helper h28a)
    gave 0.229 s on its own; both, merged: 0.113 s."""
    hit, intact, kind, t0, t1 = _soak_burst_replay(datasets, 6, 7, 120)
    assert (kind, t0, t1 - t0) == ("far", 4500, 10)
    rec_s = _recovery_s(hit, intact, t1, 240.0)
    print(f"back in {rec_s:.3f} s")
    assert rec_s <= bench_module("burst_recovery").soak.MAX_RECOVERY_S, rec_s


@pytest.mark.timeout(300)
@pytest.mark.parametrize("shift_m", [0.020, 0.035], ids=["suspect", "far"])
def test_a_take_that_fits_worse_after_a_gap_is_not_held_for_good(
    datasets: Path, shift_m: float
) -> None:
    """Every rule that judges a frame against the take's running level stops
    deciding from it past the level's time constant (1 s): the PiG walk with every
    marker gone for 0.2 s and back ``shift_m`` further off each (a fixed random
    direction per marker, as if the suit had shifted).

    - 20 mm: about twice the level before the gap. A frame still suspect after a gap
      is unexplained only while the gap is shorter than 1 s; without that bound every
      frame after the gap was unexplained, the pose held for the rest of the take.
    - 35 mm (a lab's stair walk fits its calibration 30-45 mm off, issue 28): about 5x
      the level (5.6 mm), the far rule's (4x), under the gate a first frame is judged
      by (40 mm). Past 1 s the frame is judged as a first frame is and the level
      starts again from it; before, the rest of the take (1.95 s) was held.

    Now the gap ends 1 s after it began and the rest is explained."""
    walk, fit = _pig_walk(datasets)
    rate = 100.0  # the take's
    pos = walk.positions.copy()
    d = np.random.default_rng(0).normal(size=(pos.shape[1], 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    g0, g1 = 100, 120
    pos[g0:g1] = np.nan
    pos[g1:] += shift_m * d
    r = fit(rate).solve_take(pos)
    held = np.asarray(r.unexplained)[g1:]
    assert held[0], "the first frame after the gap fits past the level's rules"
    back = np.flatnonzero(~held)
    assert back.size, "held for the rest of the take"
    assert g1 + back[0] - g0 <= rate * 1.0 + 1, back[0]  # the level's 1 s
    assert not held[back[0] :].any(), np.flatnonzero(held[back[0] :])


def _no_worse_s(hit: Any, intact: Any, seen_all: Any, t1: int, rate: float) -> float:
    """``bench/burst_recovery.py``'s second measure: seconds from the burst's last
    frame to the first after it whose every bone is within the soak's degrees of the
    solve without the bursts or no more than that further from the solve with
    nothing hidden than the solve without the bursts is (the root likewise), neither
    held nor unseen: the burst left nothing worse than the hides already had."""
    soak = bench_module("burst_recovery").soak

    def apart(a: Any, b: Any) -> tuple[np.ndarray, np.ndarray]:
        deg = bone_deviation_deg(
            np.asarray(a.world_from_bone_quat), np.asarray(b.world_from_bone_quat)
        )
        return deg, np.linalg.norm(a.root_pos - b.root_pos, axis=1)

    deg, root = apart(hit, intact)
    deg_all, root_all = apart(hit, seen_all)
    deg_hides, root_hides = apart(intact, seen_all)
    worse_deg = np.max(np.minimum(deg, deg_all - deg_hides), axis=1)
    worse_m = np.minimum(root, root_all - root_hides)
    ok = (worse_deg <= soak.RECOVERED_DEG) & (worse_m <= soak.RECOVERED_M)
    ok &= ~hit.unexplained & ~hit.unseen
    after = np.flatnonzero(ok[t1:])
    assert after.size, "never back"
    return float((after[0] + 1) / rate)


@pytest.mark.timeout(300)
@pytest.mark.xfail(
    strict=True,
    reason="the hold of the one marker that sees the upper arm's twist, hidden inside "
    "the burst and after it, is anchored on the last frame before the burst, when the "
    "hides had the arm 16 deg off (docs/fit-open.md 'Bursts on a take with markers "
    "missing around them'): the frames that would anchor it better are the burst's",
)
def test_a_hold_anchored_before_the_burst_leaves_the_arm_worse_than_the_hides(
    datasets: Path,
) -> None:
    """``bench/burst_recovery.py --seed 3``'s zeros of 39 frames (its 6th burst,
    frames 3300-3338), the one burst of seeds 1-9 late by both of its measures
    (0.300 s, no worse than the hides after 0.300 s): back within 0.25 s of the
    solve without the bursts, or no worse than that solve against the one with
    nothing hidden. Traced (helper h28z, 2026-12-07): LSHO hidden from frame 3248
    leaves both solves' left upper arm 12.6 deg (16.0 parent-relative) from the solve
    with nothing hidden at frame 3299; in the solve without the bursts LSHO is back at
    3305 (0.4 deg) and LELB, the upper arm's one marker, hides at 3334, its hold
    anchored there (0.1 deg); after the burst LELB is hidden until 3409, and its hold
    is anchored on frame 3299, the last explained one: the upper arm 14.8-22.7 deg from
    the solve with nothing hidden (26.5 at the first frame after) while the other's
    drifts 0.3 -> 16.3 deg, back the frame after LELB returns. With the hold dropped
    after the gap wherever the seen markers observe the rotation at all, the seen
    markers turn that arm 39-54 deg off (seeds 1-6: late 1, 0, 2, 1, 2, 2 -> 1, 2, 5,
    3, 2, 3)."""
    br = bench_module("burst_recovery")
    hit, intact, kind, t0, t1 = _soak_burst_replay(datasets, 3, 5, 90)
    assert (kind, t0, t1 - t0) == ("zeros", 3300, 39)
    walk, fit = _pig_walk(datasets)
    pos = walk.positions
    rows = np.array([br.soak.walk_row(k, pos.shape[0]) for k in range(t1 + 90)])
    seen_all = fit(240.0).solve_take(pos[rows])
    rec_s = _no_worse_s(hit, intact, seen_all, t1, 240.0)
    print(f"no worse than the hides after {rec_s:.3f} s")
    assert rec_s <= br.soak.MAX_RECOVERY_S, rec_s
