"""Evidence with truth (issue 36): a camera rig of 5 markers and a sword of 4 carried
by the synthetic performer's hands (``daemon/synth/props.py``) through its everyday
motions (walk, arm raise, forearm twist, spine, head turn: 20 s at 120 Hz) and turned
and shifted in the grip on their own, 0.5 mm of noise per coordinate. Each prop is
calibrated on the performer's base-pose hold (the first second) and solved on every
frame; the solve's prop frame has the world's axes at calibration, so the truth it is
compared with is ``world_from_prop(t) world_from_prop(calibration)⁻¹``.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from retargetd.daemon.props import kernel as pk
from retargetd.daemon.props.layout import ambiguous_pairs, calibrate_prop
from retargetd.daemon.props.solve import DEFAULT_GATE_M, PropTrack, solve_take
from retargetd.daemon.synth.performer import synthesize
from retargetd.daemon.synth.props import SynthProp, synth_props

RATE_HZ = 120.0
BASE = slice(0, 120)  # the base-pose hold: 1 s


@functools.cache
def _props() -> dict[str, SynthProp]:
    take = synthesize(seconds=20.0, rate_hz=RATE_HZ, noise_mm=0.5, seed=3)
    return {p.name: p for p in synth_props(take, noise_mm=0.5, seed=3)}


def _solve(p: SynthProp, markers: np.ndarray, valid: np.ndarray) -> PropTrack:
    layout = calibrate_prop(
        p.markers_world[BASE], p.labels, name=p.name, rate_hz=RATE_HZ
    )
    return solve_take(layout, p.labels, markers, valid)


def _truth(p: SynthProp) -> Rotation:
    q = Rotation.from_quat(p.world_from_prop_quat, scalar_first=True)
    return q * q[BASE.stop // 2].inv()  # the prop lies still over BASE


def _deg(a: np.ndarray, b: Rotation) -> np.ndarray:
    return np.degrees((Rotation.from_quat(a, scalar_first=True) * b.inv()).magnitude())


@pytest.mark.parametrize("name", ["camera", "sword"])
def test_rotation_and_position_against_truth(name: str) -> None:
    p = _props()[name]
    truth = _truth(p)
    # the prop does move: turned through ~180 deg and carried metres by the walk
    assert np.degrees((truth * truth[0].inv()).magnitude()).max() > 150.0
    assert np.ptp(p.prop_pos_world, axis=0).max() > 2.0
    assert ambiguous_pairs(p.layout_prop_m, DEFAULT_GATE_M, p.labels) == []
    track = _solve(p, p.markers_world, p.valid)
    assert np.all(track.flags == 0) and np.all(track.used == len(p.labels))
    rot_err = _deg(track.world_from_prop_quat, truth)
    pos_err_mm = np.linalg.norm(track.prop_pos_world - p.prop_pos_world, axis=1) * 1e3
    # issue 36: <= 0.5 deg p95 at 0.5 mm noise, position <= 1 mm (p95)
    assert np.percentile(rot_err, 95) <= 0.5, np.percentile(rot_err, 95)
    assert np.percentile(pos_err_mm, 95) <= 1.0, np.percentile(pos_err_mm, 95)
    assert rot_err.max() < 1.0 and pos_err_mm.max() < 2.0


@pytest.mark.parametrize("name", ["camera", "sword"])
def test_one_marker_hidden_changes_the_pose_by_under_half_a_degree(name: str) -> None:
    p = _props()[name]
    full = _solve(p, p.markers_world, p.valid)
    full_rot = Rotation.from_quat(full.world_from_prop_quat, scalar_first=True)
    for hidden in range(len(p.labels)):
        valid = p.valid.copy()
        valid[BASE.stop :, hidden] = False
        markers = p.markers_world.copy()
        markers[~valid] = np.nan
        track = _solve(p, markers, valid)
        after = slice(BASE.stop, None)
        assert np.all(track.flags[after] == pk.FLAG_PARTIAL)
        d = _deg(track.world_from_prop_quat[after], full_rot[after])
        assert np.percentile(d, 95) <= 0.5, (name, hidden, np.percentile(d, 95))


@pytest.mark.parametrize("name", ["camera", "sword"])
def test_two_swapped_labels_are_rejected(name: str) -> None:
    p = _props()[name]
    truth = _truth(p)
    k = len(p.labels)
    window = slice(600, 900)
    for a in range(k):
        for b in range(a + 1, k):
            markers = p.markers_world.copy()
            markers[window, [a, b]] = markers[window, [b, a]]
            track = _solve(p, markers, p.valid)
            flags = track.flags[window]
            assert np.all(flags & pk.FLAG_SWAP), (name, a, b)
            if k - 2 >= 3:
                # the camera: solved from the 3 that agree, never from the swap:
                # the very pose those 3 give with the swapped two hidden
                assert np.all(flags == pk.FLAG_PARTIAL | pk.FLAG_SWAP)
                assert np.all(track.used[window] == 3)
                valid = p.valid.copy()
                valid[window, [a, b]] = False
                hidden = _solve(p, p.markers_world, valid)
                np.testing.assert_allclose(
                    track.world_from_prop_quat[window],
                    hidden.world_from_prop_quat[window],
                    atol=1e-12,
                )
                err = _deg(track.world_from_prop_quat[window], truth[window])
                assert err.max() < 1.5, (name, a, b, err.max())
            else:
                # the sword keeps 2: the last good pose is held and flagged
                assert np.all(flags == pk.FLAG_HELD | pk.FLAG_SWAP)
                held = track.world_from_prop_quat[window.start - 1]
                np.testing.assert_array_equal(
                    track.world_from_prop_quat[window], np.tile(held, (300, 1))
                )
            assert np.all(track.flags[window.stop :] == 0)  # and back after it
