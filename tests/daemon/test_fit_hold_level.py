"""A hidden marker's hold keeps the threshold of the level where the marker was last
accepted (issue 28 item 6): the level rises with the misfit the hold itself leaves,
and a threshold that followed it tightened the hold while the performer turned the
held rotation, so that the parent took the turn.

``menache``'s RIWRIST sits on the ulna's twist axis; hidden 1 s from 4 s, REWRIST,
its one marker left on the ulna, sees the twist only through its lever off that
axis, so the ulna's twist is held. The performer pronates 112 deg in that second;
the seen wrist and hand markers report it, the level rose 2.22 -> 3.54 mm (the
intact solve's 2.22 -> 3.16), the ulna's hold 3.5e-4 -> 8.1e-4 m^2/rad^2 with it,
and the upper arm's twist took the pronation (29.6 deg off the intact solve, the
epicondyles 21 mm off; 27.2 deg beyond the hold against the truth). The hold's
threshold is now the level at the marker's last accepted frame, or the level now
where lower (``fit_track.hold_priors``), as the hide tables' allowance
(``synth.hold.held_directions``) is made. ``pytest -s`` prints the figures.
"""

from __future__ import annotations

import numpy as np
from hide_truth import BONE_DEG, hidden_beyond_hold


def test_a_wrist_marker_on_the_twist_axis_hidden_a_second_leaves_the_upper_arm() -> (
    None
):
    """RIWRIST hidden 1 s from 4 s: the upper arm, the parent that took the
    pronation, within 10 deg beyond the hold against the truth (27.2 deg before: 28.4
    off the truth since the hide, the intact solve 1.2; 9.3 measured). The ulna and
    the hand stay 14-15 deg beyond the hold, reached in the hide's first 0.25 s (the
    hidden marker's stand-in on the damped prediction, docs/fit-open.md), not
    asserted here."""
    solve, ht = hidden_beyond_hold("menache", "RIWRIST", 1.0)
    arm = [ht.bone_names.index(b) for b in ("rupperarm", "rulna", "rhand")]
    print(
        "\nmenache RIWRIST hidden 1 s, beyond the hold: "
        + ", ".join(f"{ht.bone_names[k]} {ht.excess_deg[k]:.1f}" for k in arm)
        + " deg"
    )
    assert not np.isnan(np.asarray(solve.world_from_bone_quat)).any()
    k = arm[0]
    assert ht.excess_deg[k] <= BONE_DEG, ht.excess_deg[k]


def test_a_head_marker_hidden_a_second_leaves_the_neck() -> None:
    """LHEAD hidden 1 s from 4 s (a case the rule was not read from): the head is
    held relative to the neck while the performer turns it, and the rising level
    gave the neck (loneck) a hold too from frame 535, so the neck turned 8 -> 24 deg
    instead (13.2 deg beyond the hold before; 7.0 measured): within 10."""
    solve, ht = hidden_beyond_hold("menache", "LHEAD", 1.0)
    k = ht.bone_names.index("loneck")
    print(
        f"\nmenache LHEAD hidden 1 s: the neck {ht.excess_deg[k]:.1f} deg "
        "beyond the hold"
    )
    assert not np.isnan(np.asarray(solve.world_from_bone_quat)).any()
    assert ht.excess_deg[k] <= BONE_DEG, ht.excess_deg[k]
