"""The loop's latency rings (``live/stats.py``): what is recorded is what is read."""

from __future__ import annotations

import numpy as np

from retargetd.daemon.live.stats import RING, STAGES, LoopStats


def test_rings_record_last_and_percentiles() -> None:
    rng = np.random.default_rng(0)
    stats = LoopStats()
    assert stats.last() == (0, 0, 0, 0)
    n = RING + 37  # wraps: only the last RING frames count
    ns = rng.integers(1_000, 5_000_000, size=(n, len(STAGES)))
    for row in ns:
        stats.record(*(int(v) for v in row))
        assert stats.last() == tuple(int(v) for v in row)
    assert stats.ring_count == RING
    got = stats.latency_us()
    kept = ns[-RING:] / 1000.0
    for i, stage in enumerate(STAGES):
        want = np.percentile(kept[:, i], [50.0, 99.0])
        assert got[stage] == (float(want[0]), float(want[1])), stage
