"""Issue 12 item 7, the CI version of ``bench/soak.py``: 60 s of the PiG walk at
240 Hz to a ``retargetd run`` process with every fault of the soak (2 % malformed
datagrams, 10 % marker dropouts with zeros, a source restart every 30 s, spoofed
frame numbers and label announcements, the VMC receiver absent half the time,
control commands every 10 s, a recording, the validator on, the face on when the
ICT training set is in ``../shared/datasets``). Passes as the soak does: up
throughout, RSS growth <= 10 MB after warm-up, every datagram and frame accounted
for exactly, no pose gap over 100 ms but where the source paused or a conflicting
label announcement held the id, and the recording replays to the same poses. Keep
it at 60 s: two source restarts and twelve spoofs fall in it."""

from __future__ import annotations

import pytest
from bench_scripts import bench_module
from paths import require, require_datasets

SECONDS = 60.0


@pytest.mark.timeout(600)
def test_soak_with_faults() -> None:
    require_datasets()
    soak = bench_module("soak")
    require(soak.fuzz.PIG_MOTION, "the PiG walk")
    result = soak.run(SECONDS, soak.Faults(), face=True, seed=12)
    soak.print_result(result)
    sent = result["sent"]
    # The faults happened.
    assert sent["osc_malformed"] > 0 and sent["spoofed_frames"] >= 5
    assert sent["spoofed_labels"] >= 5 and len(result["gaps"]["paused"]) <= 2
    assert result["control_sent"] >= 6
    # Up throughout, every control request answered.
    assert result["alive"] and result["rc"] == 0 and not result["errors"], result
    assert result["pass"]["up"]
    # Every datagram and every frame accounted for.
    a = result["accounting"]
    assert a["osc_sent"] == a["osc_counted"] + a["osc_kernel_drops"], a
    assert a["frames_in"] == a["frames_solved"] + a["stale"] + a["unsolved"], a
    assert a["drops"]["implausible_jump"] >= sent["spoofed_frames"] - 1, a
    assert a["drops"]["conflicting_labels"] >= sent["spoofed_labels"], a
    assert a["drops"]["restart"] >= 1, a
    # Memory flat after warm-up.
    assert result["rss_mb"]["growth"] <= soak.MAX_RSS_GROWTH_MB, result["rss_mb"]
    # No unexplained gap in the pose stream (daemon side, the recorded sent_ns):
    # every gap over 100 ms is the source pausing, a conflicting announcement
    # holding the id (by design: PROTOCOLS.md "Label sets"), a restart's
    # confirmation, or the loop not scheduled on a loaded host (loop_late: timing,
    # printed with the load, never asserted).
    assert not result["gaps"]["other"], result["gaps"]
    # A conflicting announcement keeps the names in use: no gap from it.
    assert not result["gaps"]["label_conflict"], result["gaps"]
    assert result["poses"] > 0.5 * SECONDS * soak.RATE_HZ
    # The recording replays to the same poses.
    replay = result["replay"]
    assert replay["complete"] and replay["poses_unmatched"] == 0, replay
    assert replay["poses_compared"] == a["frames_solved"], replay
    assert replay["ok"], replay
