"""Issue 34 item 3's evidence as tests: the synthetic gaits whose stance feet stay put
(``synth/gait.py``: the level walk, the run, stair ascent and descent, 8 s at 120 Hz,
Plug-in Gait markers) retargeted onto legs 0.8x, 1x and 1.25x the performer's with
``feet = "plant"`` (``bench/feet_plant.py``'s measures, the table in
``docs/feet.md``), offline as ``solve --plant-feet`` runs it (each contact's support
settled over the whole contact, ``post/stance.py``). Each criterion of the issue is
one test per gait; where the plant or the detector does not meet one, mark the case
an expected failure (strict, so the mark follows the code) with the measured figure
in its reason.

Live (``[target] feet = "plant"`` in the daemon, ``live/send.py``) the plant reads the
detector's state of each frame, a support not yet settled: the no-sink and the knee
criteria are checked that way too (``feet_plant.measure(..., live=True)``)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from bench_scripts import bench_module

RATE_HZ = 120.0
SECONDS = 8.0
GAITS = ("level_walk", "run", "stair_ascent", "stair_descent")


@pytest.fixture(scope="module")
def solved() -> dict[str, tuple[Any, ...]]:
    """Per gait, ``feet_plant.synthetic``'s (solve, rig, calibration, take)."""
    fp = bench_module("feet_plant")
    return {gait: fp.synthetic(gait, SECONDS, RATE_HZ) for gait in GAITS}


def _measure(solved: dict[str, tuple[Any, ...]], live: bool) -> dict[str, Any]:
    fp = bench_module("feet_plant")
    out = {}
    for gait, (res, rig, cal, take) in solved.items():
        out[gait] = [
            fp.measure(
                res, rig, cal, fp.leg_target(rig, cal, k, take), RATE_HZ, take, live
            )
            for k in fp.LEG_SCALES
        ]
    return out


@pytest.fixture(scope="module")
def measured(solved: dict[str, tuple[Any, ...]]) -> dict[str, list[dict[str, Any]]]:
    """Per gait, ``feet_plant.measure`` on each leg scale (0.8, 1, 1.25), offline."""
    return _measure(solved, live=False)


@pytest.fixture(scope="module")
def measured_live(
    solved: dict[str, tuple[Any, ...]],
) -> dict[str, list[dict[str, Any]]]:
    """As :func:`measured`, the plant fed the detector's state frame by frame."""
    return _measure(solved, live=True)


@pytest.fixture(scope="module")
def solved_rom() -> dict[str, tuple[Any, ...]]:
    """As :func:`solved`, the performer calibrated with its range of motion too
    (``calibrate --rom``: functional hip centres; ``feet_plant.synthetic``'s
    ``rom``)."""
    fp = bench_module("feet_plant")
    return {gait: fp.synthetic(gait, SECONDS, RATE_HZ, rom=True) for gait in GAITS}


@pytest.fixture(scope="module")
def measured_rom(solved_rom: dict[str, tuple[Any, ...]]) -> dict[str, Any]:
    """As :func:`measured` on :func:`solved_rom`."""
    return _measure(solved_rom, live=False)


@pytest.fixture(scope="module")
def measured_live_rom(solved_rom: dict[str, tuple[Any, ...]]) -> dict[str, Any]:
    """As :func:`measured_live` on :func:`solved_rom`."""
    return _measure(solved_rom, live=True)


def _xfail(gait: str, reason: str) -> Any:
    """``gait`` as a parameter expected to fail (strict), for the measured reason."""
    return pytest.param(gait, marks=pytest.mark.xfail(strict=True, reason=reason))


#: Live, a step contact is held at the level the target's own sole came down to,
#: raised as it rises until heel-off (``post/plant_level.py``): measured
#: (``bench/feet_plant.py --live``).
LIVE_ASCENT_SINK = _xfail(
    "stair_ascent",
    "live, the ascent sinks 1.66 / 2.27 / 3.03 mm (legs 0.8 / 1 / 1.25x; "
    "2.36 / 2.94 / 3.68 held on the detector's landing level): the solved "
    "target's sole lands that far below the step (Plug-in Gait's hip centre, "
    "the thigh flexed) in each step contact's first frame; no causal rule sees "
    "the step above it there (docs/feet.md); on hips from a range of motion "
    "0.00 (test_on_functional_hips_planted_feet_do_not_sink)",
)
#: As the ascent, the solve's foot at landing: within 1 mm but at 1.25x.
LIVE_DESCENT_SINK = _xfail(
    "stair_descent",
    "live, the descent sinks 0.39 / 0.67 / 1.03 mm (legs 0.8 / 1 / "
    "1.25x): the solved target's toe tip lands that far below the step; held on "
    "the detector's level instead it sank 0 and floated 28-44 mm (p95) above "
    "the step (the detector's foot points, pitched on the toe tip, read high); "
    "on hips from a range of motion 0.00",
)


@pytest.mark.timeout(900)
@pytest.mark.parametrize(
    "gait", ["level_walk", "run", LIVE_ASCENT_SINK, LIVE_DESCENT_SINK]
)
def test_live_planted_feet_do_not_sink(measured_live: Any, gait: str) -> None:
    """Live, as :func:`test_planted_feet_do_not_sink`: a contact foot's lowest point
    never more than 1 mm below the truth's floor or step (times the leg ratio)."""
    for m in measured_live[gait]:
        print(gait, m["leg_ratio"], m["plant"]["sink_max_mm"])
        assert m["plant"]["sink_max_mm"] <= 1.0


@pytest.mark.timeout(600)
@pytest.mark.parametrize("gait", GAITS)
def test_planted_stance_skates_at_most_2_mm(measured: Any, gait: str) -> None:
    """Skate on the target with the plant: the p95 over contact frames of the
    horizontal travel of the foot's floor point that moved least, <= 2 mm (at
    120 Hz)."""
    for m in measured[gait]:
        print(gait, m["leg_ratio"], m["plant"]["skate_frame_p95_mm"])
        assert m["plant"]["skate_frame_p95_mm"] <= 2.0


def _per_contact(gait: str, k: float) -> Any:
    return pytest.param(gait, k, id=f"{gait}-{k:g}x")


@pytest.mark.timeout(600)
@pytest.mark.parametrize(
    ("gait", "k"),
    [
        *(_per_contact("level_walk", k) for k in (0.8, 1.0, 1.25)),
        _per_contact("run", 0.8),
        # Failed before the run started from both legs in mid-stance
        # (``synth.motion.RUN_START_LAG``): 2.01 mm, its first contact 3.71 mm.
        _per_contact("run", 1.0),
        # Failed before the plant lagged a knee-limited leg straight up and
        # anchored the ball at heel-off where it stood (``post/plant.py``):
        # 2.26 mm, the toe-off frame (the detector's release 1 frame late).
        _per_contact("run", 1.25),
        _per_contact("stair_ascent", 0.8),
        _per_contact("stair_ascent", 1.0),
        # Failed likewise: 2.31 mm, the gait initiation's first swing held (the
        # heel-to-ball switch moved the ball with the solve's foot, 3.59 mm).
        _per_contact("stair_ascent", 1.25),
        *(_per_contact("stair_descent", k) for k in (0.8, 1.0, 1.25)),
    ],
)
def test_planted_stance_skates_at_most_2_mm_per_contact(
    measured: Any, gait: str, k: float
) -> None:
    """Skate summed over each contact (the least-moving floor point's horizontal
    travel from onset to release), p95 over the contacts, <= 2 mm: the issue's
    2 mm held over a whole stance, not only frame by frame."""
    (m,) = [m for m in measured[gait] if m["leg_ratio"] == pytest.approx(k)]
    print(gait, k, m["plant"]["skate_run_p95_mm"])
    assert m["plant"]["skate_run_p95_mm"] <= 2.0


@pytest.mark.timeout(600)
def test_the_run_starts_within_the_legs_reach(measured: Any) -> None:
    """The run's start from standing holds no stance foot out of the target's leg's
    reach (``plant_unreached``): its first swing is slow and low no more, so the
    detector does not hold a swinging foot (84 frames before, on every target)."""
    for m in measured["run"]:
        assert m["unreached"] == 0, (m["leg_ratio"], m["unreached"])


#: Offline each contact off the floor is held at its own level settled by heel-off;
#: the take ends on the first frame of a contact, whose only level is its landing.
def _take_end(gait: str, figures: str, whole: str) -> Any:
    return _xfail(
        gait,
        f"offline, the {gait} sinks {figures} mm (legs 0.8 / 1 / 1.25x) "
        "in one frame: the take's last, the first of a right-foot step contact, "
        "its level the landing's (the solved target's sole there); the contacts "
        f"the take holds whole sink {whole} mm; on hips from a range of motion, "
        "0.00 (the landing's level is the step's)",
    )


@pytest.mark.timeout(600)
@pytest.mark.parametrize(
    "gait",
    [
        "level_walk",
        "run",
        _take_end("stair_ascent", "1.65 / 2.26 / 3.01", "0.03 / 0.23 / 0.48"),
        _take_end("stair_descent", "0.39 / 0.67 / 1.03", "0.00"),
    ],
)
def test_planted_feet_do_not_sink(measured: Any, gait: str) -> None:
    """No penetration: a contact foot's lowest point (heel, ball, toe tip) never
    more than 1 mm below the truth's floor or step (times the leg ratio)."""
    for m in measured[gait]:
        assert m["plant"]["sink_max_mm"] <= 1.0


@pytest.mark.timeout(900)
@pytest.mark.parametrize("source", ["measured", "measured_live"])
@pytest.mark.parametrize("gait", GAITS)
def test_planted_feet_stand_no_higher_than_the_solve(
    request: pytest.FixtureRequest, source: str, gait: str
) -> None:
    """The plant holds a contact foot no higher above the truth's floor or step than
    the solve stands it (the unplanted foot, root scaled): p95 over contact frames,
    to the truth's own stillness (a contact foot moves at most 0.05 mm a frame,
    ``tests/daemon/test_synth_gait.py``). Held on the detector's level, the descent's
    foot floated 5-8 mm (offline) and 28-44 mm (live) above the step."""
    for m in request.getfixturevalue(source)[gait]:
        print(gait, m["leg_ratio"], m["scaled"]["float_p95_mm"],
              m["plant"]["float_p95_mm"])  # fmt: skip
        assert m["plant"]["float_p95_mm"] <= m["scaled"]["float_p95_mm"] + 0.05


@pytest.mark.timeout(900)
@pytest.mark.parametrize("source", ["measured", "measured_live"])
@pytest.mark.parametrize("gait", GAITS)
def test_the_knee_never_pops_at_the_blend_edges(
    request: pytest.FixtureRequest, source: str, gait: str
) -> None:
    """The plant adds at most 3 deg to the knee's frame-to-frame change at the
    blend edges, offline and live (``measured_live``: frame by frame)."""
    for m in request.getfixturevalue(source)[gait]:
        assert m["knee_added_deg"] <= 3.0


@pytest.mark.timeout(600)
@pytest.mark.parametrize("gait", GAITS)
def test_swing_stays_on_the_unplanted_path(measured: Any, gait: str) -> None:
    """Once the release has blended out, the planted ankle is within 10 mm of the
    unplanted one (root scaled by the leg ratio)."""
    for m in measured[gait]:
        assert m["swing_max_mm"] <= 10.0


@pytest.mark.timeout(600)
@pytest.mark.parametrize("gait", GAITS)
def test_contact_events_within_2_frames_of_the_truth(measured: Any, gait: str) -> None:
    """The stance detector's contact onsets and releases within 2 frames (17 ms)
    of the synthetic truth's, from the first heel strike on."""
    ev = measured[gait][0]["events_frames"]
    print(gait, np.bincount(ev))
    assert ev.size >= 10
    assert ev.max() <= 2


@pytest.mark.timeout(900)
@pytest.mark.parametrize("source", ["measured_rom", "measured_live_rom"])
@pytest.mark.parametrize("gait", GAITS)
def test_on_functional_hips_planted_feet_do_not_sink(
    request: pytest.FixtureRequest, source: str, gait: str
) -> None:
    """The stairs' sink, live and at the take's end offline, is the calibration's
    hip: with the hip centres from a range of motion (``calibrate --rom``) the solved
    foot lands on the step, and the plant holds every contact foot within 1 mm of the
    truth's floor or step, live and offline, every gait and leg ratio; the other
    criteria hold there too (skate per frame and per contact, the knee at the blend
    edges, the swing). On the regression's hip (the tests above) the live ascent
    sank 1.66 / 2.27 / 3.03 mm and the descent 0.39 / 0.67 / 1.03 (legs 0.8 / 1 /
    1.25x): the solved foot's own level at landing (docs/feet.md)."""
    for m in request.getfixturevalue(source)[gait]:
        p = m["plant"]
        print(gait, m["leg_ratio"], p["sink_max_mm"], p["skate_frame_p95_mm"],
              p["skate_run_p95_mm"], m["knee_added_deg"])  # fmt: skip
        assert p["sink_max_mm"] <= 1.0
        assert p["skate_frame_p95_mm"] <= 2.0
        assert p["skate_run_p95_mm"] <= 2.0
        assert m["knee_added_deg"] <= 3.0
        assert m["swing_max_mm"] <= 10.0
        assert p["float_p95_mm"] <= m["scaled"]["float_p95_mm"] + 0.05


@pytest.mark.timeout(600)
@pytest.mark.parametrize("gait", GAITS)
def test_every_detected_contact_holds_a_truth_contact(
    solved: dict[str, tuple[Any, ...]], gait: str
) -> None:
    """Each contact the detector finds (``post/stance.py``, causal, as live) overlaps
    one of the truth's: a foot the lift-off rule let go is not back on by the near
    rule until it comes down. Before, the run's first swing (its start-up ramp: the
    forefoot 10-25 mm up, rising at 0.14-0.22 m/s, slower than the on-speed) was let
    go and struck again by turns, frame by frame (188, 190), then held 192-198."""
    from retargetd.daemon.post.stance import CONTACT_COLUMN, take_stance_states

    res, rig, cal, take = solved[gait]
    states = take_stance_states(
        rig, cal, np.ascontiguousarray(res.root_pos, dtype=np.float64),
        np.ascontiguousarray(res.world_from_bone_quat, dtype=np.float64), RATE_HZ,
    )  # fmt: skip
    found = states[:, :, CONTACT_COLUMN] != 0.0
    truth = np.asarray(take.foot_contact, dtype=bool)
    stray = []
    for s in range(2):
        on = np.concatenate([[0], found[:, s].astype(np.int8), [0]])
        d = np.diff(on)
        for a, b in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1), strict=True):
            if not truth[a:b, s].any():
                stray.append((s, int(a), int(b)))
    assert not stray, stray
