"""``bench/burst_recovery.py``: the soak's bursts of bad frames replayed offline
(issue 28 item 3, issue 30 item 6), its short version."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from bench_scripts import bench_module


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
    nothing hidden, the burst's 3): by the second measure none is late."""
    br = bench_module("burst_recovery")
    result = br.run(datasets, bursts=40, seed=1, method="fit", every_s=2.5,
                    rate_hz=240.0, dropout=0.10)  # fmt: skip
    rows = result["bursts"]
    limit = br.soak.MAX_RECOVERY_S
    late = [b for b in rows if b["recovery_s"] > limit]
    assert len(late) <= 1, late
    assert all(b["no_worse_s"] <= limit for b in rows), rows
