"""The live validator (``validate_live``): real MuJoCo, real takes, a real thread.

Per-frame values equal the offline ``validate_take`` on the PiG walk (calibrated on
its static) and on the synthetic defects of ``test_validate.py`` (same constructions:
teleport, floating, knee bent backwards, legs crossing, x y z w quaternions, norms),
each flagged by its own bit; floating, causal live, equals a causal reference built
here from scipy's ``lfilter``. The thread gives the same results as the synchronous
path; ``submit`` drops (and counts) instead of blocking when the ring is full, whether
the thread is not started or stuck. Every validator is closed at teardown.
"""

from __future__ import annotations

import dataclasses
import os
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
from paths import DATASETS
from scipy.signal import butter, lfilter, lfilter_zi

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.solve import BodySolve
from retargetd.daemon.validate import dynamics as vd
from retargetd.daemon.validate import live as vl
from retargetd.daemon.validate.checks import (
    THRESHOLDS,
    TakeReport,
    fit_pairs,
    pose_skeleton,
    validate_take,
)
from retargetd.daemon.validate.model import skeleton_from_arrays
from retargetd.protocols import pose_stream as ps

pytestmark = [pytest.mark.usefixtures("mujoco_cwd"), pytest.mark.timeout(60)]

CHECKS = ps.VALIDATION_CHECKS
DEFECT = slice(20, 110)  # test_validate.py's frames of the T-pose hold with a defect
T0_NS = 10**12  # an arbitrary receive clock origin
#: ``../shared/datasets`` (as in ``tests/conftest.py``; a conftest can't be imported).

# ---- fixtures and helpers ----------------------------------------------------------


@pytest.fixture
def make_validator() -> Iterator[Callable[..., vl.LiveValidator]]:
    """``make(rig, cal, **kwargs)``: a :class:`LiveValidator`, closed at teardown."""
    made: list[vl.LiveValidator] = []

    def make(rig: Any, cal: Any, **kwargs: Any) -> vl.LiveValidator:
        v = vl.LiveValidator(rig, cal, **kwargs)
        made.append(v)
        return v

    yield make
    for v in made:
        v.close(timeout=5.0)
        assert not v.running


@dataclasses.dataclass(frozen=True)
class Pig:
    rig: Any
    cal: Any
    solve: BodySolve
    rate_hz: float


@pytest.fixture(scope="module")
def pig() -> Pig:
    """The PiG walk solved with the plug-in-gait rig on its static calibration."""
    from retargetd.daemon.body.calibration import calibrate
    from retargetd.daemon.body.rig import load_rig
    from retargetd.daemon.body.solve import BodySolver
    from retargetd.replay.takes import load_take

    if not DATASETS.is_dir():
        reason = f"shared datasets folder not found at {DATASETS}"
        if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
            pytest.fail(f"{reason} (CI=true: nothing may skip)")
        pytest.skip(reason)
    rig = load_rig("plug-in-gait")
    static = load_take(DATASETS / "btkdata/PiG_Calibration-FlatFoot-Full.c3d")
    cal = calibrate(
        rig, static.positions, static.labels, take_measurements=static.measurements
    )
    walk = load_take(DATASETS / "btkdata/PiG_Motion-FlatFoot-Full.c3d")
    solve = BodySolver(rig, cal, walk.labels).solve_take(walk.positions)
    return Pig(rig, cal, solve, walk.rate_hz)


def _t_ns(frame: int, rate_hz: float) -> int:
    return T0_NS + round(frame * 1e9 / rate_hz)


@dataclasses.dataclass
class Live:
    """Per-frame results of one take."""

    values: np.ndarray  # (T, 8) float32
    flags: np.ndarray  # (T,) int
    bones: np.ndarray  # (T, B) uint8


def _collect(results: list[vl.ValidationResult]) -> Live:
    return Live(
        np.stack([r.values for r in results]),
        np.array([r.frame_flags for r in results]),
        np.stack([r.bone_flags for r in results]),
    )


def _run_sync(v: vl.LiveValidator, s: BodySolve, rate_hz: float) -> Live:
    """Every frame through ``check_frame`` (the thread's code, on this thread)."""
    v.reset_history()
    return _collect(
        [
            v.check_frame(
                t,
                _t_ns(t, rate_hz),
                s.root_pos[t],
                s.world_from_bone_quat[t],
                s.rest_from_bone_quat[t],
                s.joint_centres[t],
                s.bone_lengths,
            )
            for t in range(s.root_pos.shape[0])
        ]
    )


def _offline(v: vl.LiveValidator, s: BodySolve, rate_hz: float, rig: Any) -> TakeReport:
    fit = fit_pairs(rig, s.joint_names)
    return validate_take(
        v.vm, s, rate_hz, fit=fit, thresholds=v.thresholds, dynamics=False
    )


def _causal_floating(v: vl.LiveValidator, s: BodySolve, rate_hz: float) -> np.ndarray:
    """(T,) running unsupported seconds, the live rule written with scipy: feet near
    the floor, or a causal 2nd-order Butterworth speed below the stillness speed for
    ``still_min_s`` so far."""
    th, contact, vm = v.thresholds, vd.CONTACT, v.vm
    skel = skeleton_from_arrays(vm.skeleton, s.bone_lengths)
    origins, aims = pose_skeleton(skel, s.root_pos, s.world_from_bone_quat)
    pts, _, _ = vd.foot_points(vm.skeleton, origins, aims)  # (T, P, 3)
    near = pts[..., 2] - vm.floor_z < 1e-3 * th["airborne_clearance_mm"]
    b, a = butter(2, contact["cutoff_hz"] / (0.5 * rate_hz))
    zi = lfilter_zi(b, a)[:, None, None] * pts[0][None]
    y, _ = lfilter(b, a, pts, axis=0, zi=zi)
    speed = np.full(near.shape, np.inf)
    speed[1:] = np.linalg.norm(np.diff(y, axis=0), axis=-1) * rate_hz
    run = np.zeros(near.shape)
    for t in range(1, run.shape[0]):
        run[t] = np.where(speed[t] < contact["still_speed_m_s"], run[t - 1] + 1, 0)
    still = run >= max(1, round(contact["still_min_s"] * rate_hz))
    unsupported = ~(near | still).any(axis=1)
    air = np.zeros(unsupported.shape[0])
    for t in range(air.shape[0]):
        air[t] = (air[t - 1] + 1) * unsupported[t] if t else float(unsupported[0])
    return air / rate_hz


def _offline_values(rep: TakeReport) -> np.ndarray:
    """(T, 8) the offline per-frame values in VALIDATION_CHECKS order (floating: the
    offline whole-run value)."""
    c = rep.checks
    speed = np.maximum(c["root_speed"].values, c["effector_speed"].values)
    cols = ["convention", "fit_max", "quat_norm", "limits", "self_penetration"]
    cols += ["floor_penetration"]
    return np.stack([*(c[n].values for n in cols), speed, c["floating"].values], 1)


def _offline_bits(rep: TakeReport) -> np.ndarray:
    """(T,) frame bits from the offline flags (speed = root or effector)."""
    c = rep.checks
    names = {
        "convention": ["convention"],
        "fit": ["fit_max"],
        "quat_norm": ["quat_norm"],
        "limits": ["limits"],
        "self_penetration": ["self_penetration"],
        "floor_penetration": ["floor_penetration"],
        "speed": ["root_speed", "effector_speed"],
        "floating": ["floating"],
    }
    bits = np.zeros(rep.n_frames, dtype=np.int64)
    for bit, check in zip(vl.CHECK_BITS, CHECKS, strict=True):
        for n in names[check]:
            bits[c[n].flagged] |= bit
    return bits


def _assert_matches_offline(
    v: vl.LiveValidator, s: BodySolve, rate_hz: float, rig: Any, live: Live
) -> TakeReport:
    """Live values and bits = offline (floating = the causal reference)."""
    rep = _offline(v, s, rate_hz, rig)
    off = _offline_values(rep).astype(np.float32)
    off[:, 7] = _causal_floating(v, s, rate_hz).astype(np.float32)
    for k, name in enumerate(CHECKS):
        np.testing.assert_allclose(
            live.values[:, k], off[:, k], rtol=2e-6, atol=1e-6, err_msg=name
        )
    # Bits: every check but floating as offline; floating flags only inside an
    # offline-flagged run (live counts the run so far, offline the whole run).
    float_bit = ps.FRAME_V_FLOATING
    expect = _offline_bits(rep)
    assert ((live.flags & ~float_bit) == (expect & ~float_bit)).all()
    assert not (live.flags & float_bit & ~expect).any()
    assert not (live.flags & ~ps.FRAME_VALIDATION_MASK).any()
    assert not (live.bones & (0xFF ^ ps.BONE_VALIDATION_MASK)).any()
    return rep


def _bits(flags: np.ndarray) -> set[str]:
    """Names of the checks flagged in any frame."""
    anyf = int(np.bitwise_or.reduce(flags)) if flags.size else 0
    return {n for n, b in zip(CHECKS, vl.CHECK_BITS, strict=True) if anyf & b}


def _wait(pred: Callable[[], bool], timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not pred():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.002)


# ---- the PiG walk ------------------------------------------------------------------


def test_pig_walk_equals_offline(
    pig: Pig, make_validator: Callable[..., vl.LiveValidator]
) -> None:
    v = make_validator(pig.rig, pig.cal, rate_hz=pig.rate_hz)
    live = _run_sync(v, pig.solve, pig.rate_hz)
    rep = _assert_matches_offline(v, pig.solve, pig.rate_hz, pig.rig, live)
    assert rep.passed and not live.flags.any() and not live.bones.any()
    # Not trivially zero: the real walk's values.
    assert np.nanmax(live.values[:, CHECKS.index("fit")]) > 10.0  # mm
    assert np.nanmax(live.values[:, CHECKS.index("speed")]) > 1.0  # m/s


def test_thread_equals_synchronous(
    pig: Pig, make_validator: Callable[..., vl.LiveValidator]
) -> None:
    s, n = pig.solve, pig.solve.root_pos.shape[0]
    sync = make_validator(pig.rig, pig.cal, rate_hz=pig.rate_hz)
    expect = _run_sync(sync, s, pig.rate_hz)
    v = make_validator(pig.rig, pig.cal, rate_hz=pig.rate_hz, queue_size=n)
    v.start()
    assert any(t.name == "retargetd-validator" for t in threading.enumerate())
    with pytest.raises(RuntimeError):
        v.start()
    with pytest.raises(RuntimeError):
        v.check_frame(
            0,
            0,
            s.root_pos[0],
            s.world_from_bone_quat[0],
            s.rest_from_bone_quat[0],
            s.joint_centres[0],
        )
    got: list[vl.ValidationResult] = []
    before_ns = time.monotonic_ns()
    for t in range(n):
        assert v.submit(
            t,
            _t_ns(t, pig.rate_hz),
            s.root_pos[t],
            s.world_from_bone_quat[t],
            s.rest_from_bone_quat[t],
            s.joint_centres[t],
        )
        got += v.results()
    _wait(lambda: v.validated == n)
    got += v.results()
    assert [r.frame_id for r in got] == list(range(n))
    assert all(r.t_ns == _t_ns(r.frame_id, pig.rate_hz) for r in got)
    # validated_ns is the checker's own monotonic clock (t_ns is the caller's stamp).
    assert all(before_ns <= r.validated_ns <= time.monotonic_ns() for r in got)
    live = _collect(got)
    assert live.values.dtype == np.float32 and live.bones.dtype == np.uint8
    np.testing.assert_array_equal(live.values, expect.values)
    np.testing.assert_array_equal(live.flags, expect.flags)
    np.testing.assert_array_equal(live.bones, expect.bones)
    c = v.counters()
    assert (c["submitted"], c["validated"], c["dropped"], c["errors"]) == (n, n, 0, 0)
    assert c["flagged"] == dict.fromkeys(CHECKS, 0)
    assert 0.0 < c["check_us_p50"] <= c["check_us_p99"]
    st = v.status()
    assert st["running"] and st["pending"] == 0 and st["queue_size"] == n
    assert v.results() == ()
    v.close(timeout=5.0)
    assert not v.running
    v.close()  # idempotent
    assert not v.submit(
        n,
        0,
        s.root_pos[0],
        s.world_from_bone_quat[0],
        s.rest_from_bone_quat[0],
        s.joint_centres[0],
    )
    assert v.dropped == 1


def test_fit_bits_per_bone(
    pig: Pig, make_validator: Callable[..., vl.LiveValidator]
) -> None:
    """A fit threshold the walk exceeds: frame and bone bits as the offline distances
    (a bone's bit when its origin or aim is beyond)."""
    th = {"fit_max_mm": 20.0}
    v = make_validator(pig.rig, pig.cal, rate_hz=pig.rate_hz, thresholds=th)
    live = _run_sync(v, pig.solve, pig.rate_hz)
    _assert_matches_offline(v, pig.solve, pig.rate_hz, pig.rig, live)
    assert _bits(live.flags) == {"fit"}
    s = pig.solve
    joints, points = fit_pairs(pig.rig, s.joint_names)
    origins, aims = pose_skeleton(v.vm.skeleton, s.root_pos, s.world_from_bone_quat)
    pts = np.concatenate([origins, aims], axis=1)
    d = 1e3 * np.linalg.norm(pts[:, points] - s.joint_centres[:, joints], axis=-1)
    expect = np.zeros_like(live.bones)
    for k, p in enumerate(points):
        expect[d[:, k] > 20.0, p % v.n_bones] |= ps.BONE_V_FIT
    assert expect.any() and not expect.all()
    np.testing.assert_array_equal(live.bones, expect)


# ---- drop, don't block -------------------------------------------------------------


def _submit_frame(v: vl.LiveValidator, s: BodySolve, t: int) -> tuple[bool, float]:
    t0 = time.perf_counter()
    ok = v.submit(
        t,
        T0_NS + t,
        s.root_pos[t],
        s.world_from_bone_quat[t],
        s.rest_from_bone_quat[t],
        s.joint_centres[t],
    )
    return ok, time.perf_counter() - t0


def test_full_ring_drops_when_not_started(
    pig: Pig, make_validator: Callable[..., vl.LiveValidator]
) -> None:
    v = make_validator(pig.rig, pig.cal, rate_hz=pig.rate_hz, queue_size=2)
    sent = [_submit_frame(v, pig.solve, t) for t in range(5)]
    assert [ok for ok, _ in sent] == [True, True, False, False, False]
    assert max(dt for _, dt in sent) < 0.5  # returned at once (no wait for a slot)
    assert (v.submitted, v.dropped, v.pending) == (2, 3, 2)
    assert v.results() == ()
    v.start()  # the two queued frames are checked; the ring frees
    _wait(lambda: v.validated == 2)
    assert [r.frame_id for r in v.results()] == [0, 1]
    assert _submit_frame(v, pig.solve, 5)[0]
    _wait(lambda: v.validated == 3)


def test_full_ring_drops_while_thread_is_stuck(
    pig: Pig,
    make_validator: Callable[..., vl.LiveValidator],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    v = make_validator(pig.rig, pig.cal, rate_hz=pig.rate_hz, queue_size=2)
    entered, release = threading.Event(), threading.Event()
    real = v._check_slot

    def stuck(slot: Any) -> vl.ValidationResult:
        entered.set()
        assert release.wait(timeout=20.0)
        return real(slot)

    monkeypatch.setattr(v, "_check_slot", stuck)
    v.start()
    try:
        assert _submit_frame(v, pig.solve, 0)[0]
        assert entered.wait(timeout=10.0)  # frame 0 is being checked: its slot held
        sent = [_submit_frame(v, pig.solve, t) for t in range(1, 6)]
        assert [ok for ok, _ in sent] == [True, False, False, False, False]
        assert max(dt for _, dt in sent) < 0.5
        assert (v.submitted, v.dropped) == (2, 4)
    finally:
        release.set()
    _wait(lambda: v.validated == 2)
    assert [r.frame_id for r in v.results()] == [0, 1]


def test_check_error_is_counted_and_thread_survives(
    pig: Pig,
    make_validator: Callable[..., vl.LiveValidator],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    v = make_validator(pig.rig, pig.cal, rate_hz=pig.rate_hz, queue_size=4)
    real = v._check_slot

    def flaky(slot: Any) -> vl.ValidationResult:
        if slot.frame_id == 1:
            raise RuntimeError("boom")
        return real(slot)

    monkeypatch.setattr(v, "_check_slot", flaky)
    v.start()
    for t in range(3):
        assert _submit_frame(v, pig.solve, t)[0]
    _wait(lambda: v.validated == 2 and v.errors == 1)
    assert [r.frame_id for r in v.results()] == [0, 2]
    assert v.running


def test_arguments(pig: Pig, make_validator: Callable[..., vl.LiveValidator]) -> None:
    with pytest.raises(ValueError, match="no_such"):
        make_validator(pig.rig, pig.cal, thresholds={"no_such": 1.0})
    with pytest.raises(ValueError, match="queue_size"):
        make_validator(pig.rig, pig.cal, queue_size=0)
    with pytest.raises(ValueError, match="rate_hz"):
        make_validator(pig.rig, pig.cal, rate_hz=0.0)
    v = make_validator(pig.rig, pig.cal, thresholds={"convention_mm": -1.0})
    assert v.thresholds["convention_mm"] == -1.0
    assert v.thresholds["fit_max_mm"] == THRESHOLDS["fit_max_mm"]
    v.close()
    with pytest.raises(RuntimeError):
        v.start()


# ---- gaps and history --------------------------------------------------------------


def test_speed_over_gaps(
    pig: Pig, make_validator: Callable[..., vl.LiveValidator]
) -> None:
    s, rate = pig.solve, pig.rate_hz
    v = make_validator(pig.rig, pig.cal, rate_hz=rate, max_gap_s=0.25)
    speed = CHECKS.index("speed")

    def check(t: int, t_ns: int | None = None) -> float:
        r = v.check_frame(
            t,
            _t_ns(t, rate) if t_ns is None else t_ns,
            s.root_pos[t],
            s.world_from_bone_quat[t],
            s.rest_from_bone_quat[t],
            s.joint_centres[t],
        )
        return float(r.values[speed])

    assert check(100) == 0.0  # no history
    # A dropped frame: the mean speed over the two frame periods.
    v_gap = check(102)
    root = np.linalg.norm(s.root_pos[102] - s.root_pos[100]) * rate / 2
    assert v_gap >= root * (1 - 1e-6) and v_gap > 0.5
    assert check(102 + 40) == 0.0  # 0.4 s of frames missing: history reset
    assert check(143) > 0.0
    assert check(120) == 0.0  # frame numbers went backwards (a restarted source)
    assert check(121, _t_ns(121, rate) + 10**9) == 0.0  # 1 s receive gap: reset
    assert check(122) == 0.0  # receive clock went backwards: reset
    assert check(123) > 0.0
    # An unnumbered source (frame_id -1): frames counted from the receive clock.
    v.reset_history()
    speeds = []
    for t in (200, 201, 203):
        r = v.check_frame(
            -1,
            _t_ns(t, rate),
            s.root_pos[t],
            s.world_from_bone_quat[t],
            s.rest_from_bone_quat[t],
            s.joint_centres[t],
        )
        speeds.append(float(r.values[speed]))
    v.reset_history()
    numbered = [check(t) for t in (200, 201, 203)]
    np.testing.assert_allclose(speeds, numbered, rtol=1e-6)
    assert numbered[1] > 0.0 and numbered[2] > 0.0


# ---- synthetic defects (test_validate.py's constructions) --------------------------


@pytest.fixture(scope="module")
def synth_live(clean_synth: Any) -> Iterator[vl.LiveValidator]:
    v = vl.LiveValidator(clean_synth.rig, clean_synth.cal, rate_hz=clean_synth.rate_hz)
    yield v
    v.close()


def _rechain(c: Any, pfb: np.ndarray) -> np.ndarray:
    rest = c.skel.rest_world_from_bone_quat
    wfb = c.solve.world_from_bone_quat.copy()
    for b, p in enumerate(c.skel.bone_parents):
        if p >= 0:
            rest_pfb = rot.quat_mul(rot.quat_conj(rest[p]), rest[b])
            wfb[:, b] = rot.quat_mul(wfb[:, p], rot.quat_mul(rest_pfb, pfb[:, b]))
    return wfb


def _rotate_bone(c: Any, bone: str, axis_world: np.ndarray, deg: float) -> BodySolve:
    """test_validate._rotate_bone: a smooth bump over DEFECT, children following,
    joint centres following (only the check meant for the defect fires)."""
    b = c.skel.bone_names.index(bone)
    axis = rot.quat_rotate(
        rot.quat_conj(c.skel.rest_world_from_bone_quat[b]), axis_world
    )
    pfb = c.solve.rest_from_bone_quat.copy()
    n = DEFECT.stop - DEFECT.start
    bump = np.sin(np.pi * (np.arange(n) + 0.5) / n)
    turn = rot.quat_from_axis_angle(axis, np.radians(deg) * bump)
    pfb[DEFECT, b] = rot.quat_mul(turn, pfb[DEFECT, b])
    solve = dataclasses.replace(
        c.solve, rest_from_bone_quat=pfb, world_from_bone_quat=_rechain(c, pfb)
    )
    origins, aims = pose_skeleton(c.skel, solve.root_pos, solve.world_from_bone_quat)
    points = np.concatenate([origins, aims], axis=1)
    joints = solve.joint_centres.copy()
    joints[:, c.fit[0]] = points[:, c.fit[1]]
    return dataclasses.replace(solve, joint_centres=joints)


def _shift(s: BodySolve, offset: list[float], frames: slice) -> BodySolve:
    root, joints = s.root_pos.copy(), s.joint_centres.copy()
    root[frames] += offset
    joints[frames] += offset
    return dataclasses.replace(s, root_pos=root, joint_centres=joints)


def _defect(c: Any, v: vl.LiveValidator, s: BodySolve) -> tuple[Live, TakeReport]:
    live = _run_sync(v, s, c.rate_hz)
    return live, _assert_matches_offline(v, s, c.rate_hz, c.rig, live)


def test_clean_synthetic_take_passes(
    clean_synth: Any, synth_live: vl.LiveValidator
) -> None:
    live, _ = _defect(clean_synth, synth_live, clean_synth.solve)
    assert _bits(live.flags) == set()


def test_teleport_flags_speed(clean_synth: Any, synth_live: vl.LiveValidator) -> None:
    c = clean_synth
    live, _ = _defect(c, synth_live, _shift(c.solve, [0.3, 0.0, 0.0], slice(200, None)))
    assert _bits(live.flags) == {"speed"}
    assert np.flatnonzero(live.flags).tolist() == [200]
    root = c.skel.bone_parents.index(-1)
    assert live.bones[200, root] & ps.BONE_V_SPEED
    # The root jumps 0.3 m in one frame; a hand moves with it plus its own motion.
    assert live.values[200, CHECKS.index("speed")] >= 0.3 * c.rate_hz


def test_floating_flags_floating(
    clean_synth: Any, synth_live: vl.LiveValidator
) -> None:
    c = clean_synth
    n = c.solve.root_pos.shape[0]
    live, rep = _defect(c, synth_live, _shift(c.solve, [0.0, 0.0, 0.3], slice(0, n)))
    assert _bits(live.flags) == {"floating"}
    flagged = live.flags & ps.FRAME_V_FLOATING != 0
    # Causal: flagged from max_airborne_s into the offline-flagged run.
    first = int(np.flatnonzero(flagged)[0])
    assert rep.checks["floating"].flagged[first - round(c.rate_hz * 1.0) + 1]
    assert live.values[first, CHECKS.index("floating")] > THRESHOLDS["max_airborne_s"]


def test_knee_bent_backwards_flags_limits(
    clean_synth: Any, synth_live: vl.LiveValidator
) -> None:
    c = clean_synth
    live, _ = _defect(
        c, synth_live, _rotate_bone(c, "l_shank", c.skel.left_world, -40.0)
    )
    assert _bits(live.flags) == {"limits"}
    assert live.values[:, CHECKS.index("limits")].max() == pytest.approx(25.0, abs=0.1)
    shank = c.skel.bone_names.index("l_shank")
    limited = np.flatnonzero((live.bones & ps.BONE_V_LIMIT).any(axis=0)).tolist()
    assert limited == [shank]


def test_legs_crossing_flag_self_penetration(
    clean_synth: Any, synth_live: vl.LiveValidator
) -> None:
    c = clean_synth
    forward = np.cross(c.skel.left_world, [0.0, 0.0, 1.0])
    live, _ = _defect(c, synth_live, _rotate_bone(c, "l_thigh", forward, -30.0))
    assert _bits(live.flags) == {"self_penetration"}
    hit = (live.bones & ps.BONE_V_PENETRATION).any(axis=0)
    names = {c.skel.bone_names[b] for b in np.flatnonzero(hit)}
    assert any(n.startswith("l_") for n in names) and any(
        n.startswith("r_") for n in names
    )


def test_xyzw_and_norms_flag_convention_and_quat_norm(
    clean_synth: Any, synth_live: vl.LiveValidator
) -> None:
    c, s = clean_synth, clean_synth.solve
    xyzw = dataclasses.replace(
        s,
        world_from_bone_quat=s.world_from_bone_quat[..., [1, 2, 3, 0]],
        rest_from_bone_quat=s.rest_from_bone_quat[..., [1, 2, 3, 0]],
    )
    live, _ = _defect(c, synth_live, xyzw)
    assert {"convention", "fit"} <= _bits(live.flags)
    assert np.median(live.values[:, CHECKS.index("convention")]) > 100.0
    pfb = s.rest_from_bone_quat.copy()
    pfb[DEFECT] *= 1.01
    live, _ = _defect(c, synth_live, dataclasses.replace(s, rest_from_bone_quat=pfb))
    assert _bits(live.flags) == {"quat_norm"}


def test_thread_counts_flags(
    clean_synth: Any, make_validator: Callable[..., vl.LiveValidator]
) -> None:
    c = clean_synth
    s = _shift(c.solve, [0.3, 0.0, 0.0], slice(200, None))
    n = s.root_pos.shape[0]
    v = make_validator(c.rig, c.cal, rate_hz=c.rate_hz, queue_size=n)
    v.start()
    for t in range(n):
        assert v.submit(
            t,
            _t_ns(t, c.rate_hz),
            s.root_pos[t],
            s.world_from_bone_quat[t],
            s.rest_from_bone_quat[t],
            s.joint_centres[t],
        )
    _wait(lambda: v.validated == n)
    flagged = [r.frame_id for r in v.results() if r.frame_flags]
    assert flagged == [200]
    assert v.counters()["flagged"] == {**dict.fromkeys(CHECKS, 0), "speed": 1}
