"""A hidden marker above a hinge_twist's hinge does not hold the twist below it where
the parent's own markers seen resolve the parent's turn about the twist axis (issue
28 items 1 and 6): ``menache``'s right upper arm on the synthetic performer, RIELBOW
or REELBOW hidden (the other epicondyle marker left on it).

The hold tables (``fit_observe.hidden_information``) count a hinge_twist's twist as
lost with a marker above its hinge: that marker fixed the parent's turn about the
same axis, which the markers below the hinge see as they see the twist. Held on the
child relative to its parent, that twist refused the forearm's real pronation
(the performer pronates ~50 deg in the last 0.3 s of the hide), which the seen wrist
markers report, and the upper arm took it: 24.6 deg (RIELBOW) and 14.2 (REELBOW)
beyond the hold against the truth before. The child's twist is now taken off the
hold (``fit_track.hold_priors``), and for a marker above the parent whatever the
parent's markers see (``plug-in-gait``'s RSHO: 20.6 deg before, -0.3 measured).
``pytest -s`` prints the figures.
"""

from __future__ import annotations

import numpy as np
import pytest
from hide_truth import BONE_DEG, hidden_beyond_hold


@pytest.mark.parametrize(
    ("markerset", "marker"),
    [("menache", "RIELBOW"), ("menache", "REELBOW"), ("plug-in-gait", "RSHO")],
)
def test_an_arm_marker_hidden_a_second_leaves_the_upper_arm(
    markerset: str, marker: str
) -> None:
    """Hidden 1 s from 4 s: the upper arm no more than 10 deg beyond what the fit
    holds against the truth (the damaged solve's error since the hide, less the
    intact solve's and the truth's own turn in the held rotations; before: 24.6 and
    14.2 deg for the epicondyles, 20.6 for RSHO). Plug-in Gait's RSHO sits alone on
    the clavicle, two bones above the elbow: neither the forearm's twist nor the
    upper arm's turn about the same axis moves it; its table counted that twist lost
    only through the clavicle's freedom, and held on the forearm relative to the
    upper arm it refused the pronation the wrist markers report (81 deg in that
    second), which the upper arm took, its one marker RELB resolving its turn about
    the forearm's axis under the hold threshold."""
    solve, ht = hidden_beyond_hold(markerset, marker, 1.0)
    k = ht.bone_names.index("rupperarm")
    print(f"\n{markerset} {marker} hidden 1 s: the upper arm "
          f"{ht.excess_deg[k]:.1f} deg beyond the hold")  # fmt: skip
    assert not np.isnan(np.asarray(solve.world_from_bone_quat)).any()
    assert ht.excess_deg[k] <= BONE_DEG, ht.excess_deg[k]
