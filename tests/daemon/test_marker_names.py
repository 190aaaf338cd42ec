"""Every marker the rig names is used, whatever the take calls it (issue 28 item 5).

A rig written from RIGS.md for a lab's own marker set names its markers and lists the
take's labels as aliases. Before the fix, the fit re-matched the calibration's rig
marker names as if they were take labels (``method.make_body_solver`` passed
``base_labels=calibration.marker_names``), so every marker whose name is not also one
of its own aliases was dropped ("never seen in the base pose: unused"), and the
construction's roll-hold levels (``sanity.roll_hold_levels_m``) were worked out from
no markers at all. Here each shipped rig is rewritten with every marker renamed to a
name no take uses (the take's label kept as its alias, the rest of the file renamed
to match), and the take is also relabelled as the matcher accepts (a ``Subject:``
prefix, another alias, another case); both methods must give the same solve as the
original rig on the original take, and the fit must use every marker the base pose
saw.

Takes: the synthetic performer wearing ``menache`` and ``plug-in-gait``, and the
real takes of the other rigs (``../shared/datasets``): the btkdata Plug-in Gait pair,
``cmu41`` on the MOTEK ballet calibrated on ``MOTEK_T``, ``opensim-gait2354`` on
subject01's static and walk, ``bioptim-wholebody`` on its gait (calibrated on its
first 10 frames).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from importlib import resources
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pytest
from paths import DATASETS, require
from renamed_rig import write_renamed_rig

from retargetd.daemon.body.calibration import Calibration, calibrate, match_markers
from retargetd.daemon.body.fit_model import build_fit_model
from retargetd.daemon.body.method import make_body_solver
from retargetd.daemon.body.rig import Rig, load_rig
from retargetd.daemon.body.solve import BodySolve
from retargetd.daemon.body.solve_fit import FitSolve, FitSolver
from retargetd.daemon.synth import performer as pf
from retargetd.daemon.validate.limits import JOINT_LIMITS_DEG
from retargetd.daemon.validate.model import SEGMENT_KIND
from retargetd.replay.takes import load_take


class Case(NamedTuple):
    """A rig and a take it fits: base-pose frames and the frames solved."""

    base: np.ndarray  # (F, M, 3) metres, world
    base_labels: tuple[str, ...]
    positions: np.ndarray  # (T, M, 3) metres, world
    labels: tuple[str, ...]
    measurements: dict[str, float]


def _synthetic(markerset: str) -> Case:
    take = pf.synthesize(seconds=2.0, rate_hz=60.0, markerset=markerset, noise_mm=1.0)
    base = take.markers_world[take.base_pose_frames]
    return Case(base, take.labels, take.markers_world, take.labels, {})


def _real(static: str, frames: slice, motion: str, rows: slice) -> Case:
    base = load_take(require(DATASETS / static, static))
    take = base if motion == static else load_take(require(DATASETS / motion, motion))
    return Case(
        base.positions[frames],
        base.labels,
        take.positions[rows],
        take.labels,
        dict(base.measurements),
    )


_PIG = (
    "btkdata/PiG_Calibration-FlatFoot-Full.c3d",
    "btkdata/PiG_Motion-FlatFoot-Full.c3d",
)
#: name -> (rig, how to load its case). Real takes are cut to ~1-2 s: the solve of
#: every frame is compared, so more frames add time and no evidence.
CASES: dict[str, tuple[str, Callable[[], Case]]] = {
    "menache-synthetic": ("menache", lambda: _synthetic("menache")),
    "pig-synthetic": ("plug-in-gait", lambda: _synthetic("plug-in-gait")),
    "pig-btkdata": (
        "plug-in-gait",
        lambda: _real(_PIG[0], slice(None), _PIG[1], slice(0, 150)),
    ),
    "cmu41-ballet": (
        "cmu41",
        lambda: _real(
            "btkdata/MOTEK_T.trc",
            slice(None),
            "btkdata/MOTEK_ballet_reduced.trc",
            slice(None),
        ),
    ),
    "opensim-walk": (
        "opensim-gait2354",
        lambda: _real(
            "opensim-core/subject01_static.trc",
            slice(None),
            "opensim-core/subject01_walk1.trc",
            slice(0, 120),
        ),
    ),
    "bioptim-gait": (
        "bioptim-wholebody",
        lambda: _real(
            "peers/bioptim_gait_wholebody.c3d",
            slice(0, 10),
            "peers/bioptim_gait_wholebody.c3d",
            slice(0, 120),
        ),
    ),
}

_cached_case = functools.cache(lambda name: CASES[name][1]())


# --- how the take is relabelled ------------------------------------------------------

#: mode -> (extra alias the rig gets, how a take label is renamed). "rig": the take
#: as recorded; "prefix": a subject prefix (``Sub01:LASI``, stripped by the
#: matcher); "alias": every label replaced by a second alias the rig lists; "case":
#: every label in another case (the matcher's case-insensitive fallback).
RELABEL: dict[str, tuple[Callable[[str], str] | None, Callable[[str], str]]] = {
    "rig": (None, lambda label: label),
    "prefix": (None, lambda label: f"Sub01:{label}"),
    "alias": (lambda label: f"{label}_alt", lambda label: f"{label}_alt"),
    "case": (None, lambda label: label.swapcase()),
}


def _relabel(
    rig: Rig, labels: tuple[str, ...], how: Callable[[str], str]
) -> tuple[str, ...]:
    """Rename the labels the rig matches (others are kept: extra labels)."""
    matched = {a for aliases in rig.markers.values() for a in aliases}
    return tuple(
        how(lab) if lab.rsplit(":", 1)[-1] in matched else lab for lab in labels
    )


def _solve(
    method: str,
    rig: Rig,
    case: Case,
    base_labels: tuple[str, ...],
    labels: tuple[str, ...],
) -> BodySolve:
    """Calibrate ``rig`` on the case's base pose and solve its frames; the fit must
    use every marker the base pose saw."""
    cal = calibrate(rig, case.base, base_labels, take_measurements=case.measurements)
    solver = make_body_solver(
        method, rig, cal, labels,
        joint_limits=JOINT_LIMITS_DEG, segment_kind=SEGMENT_KIND,
    )  # fmt: skip
    res = solver.solve_take(case.positions)
    if isinstance(solver, FitSolver):
        _check_every_seen_marker_used(solver, cal)
    return res


def _check_every_seen_marker_used(solver: FitSolver, cal: Calibration) -> None:
    """Every rig marker seen in the base pose rides a bone with a weight > 0 (unless
    the rig's ``[fit.markers.M] weight`` is 0)."""
    model = solver.model
    seen = np.asarray(cal.markers_seen) > 0.0
    want = np.array(
        [
            (opt.weight if (opt := solver.rig.fit.markers.get(m)) else 1.0) > 0.0
            for m in model.marker_names
        ]
    )
    dropped = [
        m
        for m, s, w, used in zip(
            model.marker_names, seen, want, model.marker_weight > 0.0, strict=True
        )
        if s and w and not used
    ]
    assert not dropped, f"{len(dropped)}/{len(seen)} seen markers dropped: {dropped}"


_ARRAYS = (
    "joint_centres", "world_from_bone_quat", "parent_from_bone_quat",
    "rest_from_bone_quat", "root_pos", "bone_lengths", "bone_quality", "bone_flags",
)  # fmt: skip
_FIT_ARRAYS = ("marker_rms", "marker_residual", "marker_rejected", "iterations")


def _assert_same(got: BodySolve, want: BodySolve) -> None:
    names = _ARRAYS + (_FIT_ARRAYS if isinstance(want, FitSolve) else ())
    for name in names:
        np.testing.assert_allclose(
            np.asarray(getattr(got, name), dtype=np.float64),
            np.asarray(getattr(want, name), dtype=np.float64),
            rtol=0.0, atol=1e-9, equal_nan=True, err_msg=name,
        )  # fmt: skip


@pytest.mark.parametrize("mode", list(RELABEL))
@pytest.mark.parametrize("method", ["fit", "construction"])
@pytest.mark.parametrize("case_name", list(CASES))
def test_renamed_rig_gives_the_same_solve(
    case_name: str, method: str, mode: str, tmp_path: Path
) -> None:
    rig_name, _ = CASES[case_name]
    case = _cached_case(case_name)
    original = load_rig(rig_name)
    want = _reference(case_name, method)
    extra, how = RELABEL[mode]
    rig, _ = write_renamed_rig(rig_name, tmp_path / f"{rig_name}-renamed.toml", extra)
    labels = _relabel(rig, case.labels, how)
    base_labels = _relabel(rig, case.base_labels, how)
    assert not set(rig.marker_names) & set(labels)  # no name is a take label
    got = _solve(method, rig, case, base_labels, labels)
    _assert_same(got, want)
    # The same markers are found (and missed) as with the shipped rig.
    assert [c < 0 for c in match_markers(rig, labels)] == [
        c < 0 for c in match_markers(original, case.labels)
    ]


@functools.cache
def _reference(case_name: str, method: str) -> BodySolve:
    """The shipped rig on the take as recorded."""
    rig_name, _ = CASES[case_name]
    case = _cached_case(case_name)
    rig = load_rig(rig_name)
    return _solve(method, rig, case, case.base_labels, case.labels)


def test_renamed_rig_from_the_command_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The user's path: ``rig check`` matches every marker, and ``retargetd solve``
    with the renamed rig file writes the shipped rig's solve and residuals (the
    calibration made on the way, saved and read back)."""
    from retargetd.daemon.cli.main import main

    take = tmp_path / "take.c3d"
    argv = ["synth", "--seconds", "2", "--rate", "60", "--noise-mm", "1"]
    assert main([*argv, "--out", str(take), "--markers", "menache"]) == 0
    rig, _ = write_renamed_rig("menache", tmp_path / "renamed.toml")
    capsys.readouterr()
    assert main(["rig", "check", str(tmp_path / "renamed.toml"), str(take)]) == 0
    assert f"matched {len(rig.markers)}/{len(rig.markers)}" in capsys.readouterr().out
    out = {}
    for name, path in (("shipped", "menache"), ("renamed", tmp_path / "renamed.toml")):
        cal = tmp_path / f"{name}.json"
        assert main(["calibrate", str(take), "--rig", str(path), "--frames", "0:60",
                     "--out", str(cal)]) == 0  # fmt: skip
        out[name] = tmp_path / f"{name}.npz"
        assert main(["solve", str(take), "--rig", str(path), "--calibration",
                     str(cal), "--out", str(out[name]), "--quiet"]) == 0  # fmt: skip
    with np.load(out["shipped"]) as a, np.load(out["renamed"]) as b:
        # Residuals of a real fit: the synthetic noise (1 mm), not 0.
        assert np.nanmedian(a["marker_rms"]) > 0.5e-3
        for key in (
            "world_from_bone_quat",
            "root_pos",
            "marker_residual",
            "marker_rms",
        ):
            np.testing.assert_allclose(b[key], a[key], rtol=0, atol=1e-9, err_msg=key)


def test_rig_order_base_positions_need_one_column_per_rig_marker() -> None:
    rig = load_rig("menache")
    case = _cached_case("menache-synthetic")
    cal = calibrate(rig, case.base, case.base_labels)
    assert cal.base_marker_pos is not None
    with pytest.raises(ValueError, match=r"must be \(F, 37, 3\) for rig menache"):
        build_fit_model(rig, cal, cal.base_marker_pos[None, :-1], None)
    model = build_fit_model(rig, cal, cal.base_marker_pos[None], None)
    assert (model.marker_weight > 0.0).all()


def test_case_fallback_takes_only_an_unambiguous_free_label() -> None:
    """A label in another case is taken only by a marker none of whose aliases is
    a label exactly, when that spelling is the only one and no marker took it."""
    from retargetd.daemon.body.rig import parse_rig

    rig = load_rig("menache")
    names = list(rig.markers)
    lower = [n.lower() for n in names]
    assert match_markers(rig, lower) == tuple(range(len(names)))
    # Exact first: the exact label wins over another case of it, anywhere.
    assert match_markers(rig, ["sacrum", *lower[1:], "SACRUM"])[0] == len(names)
    # Two other-case spellings of one alias: ambiguous, left unmatched.
    assert match_markers(rig, ["sacrum", *lower[1:], "Sacrum"])[0] == -1
    # A label another marker matched exactly is not taken again by case.
    text = (resources.files("retargetd.daemon.body.rigs") / "menache.toml").read_text()
    assert '\nLHIP = "LHIP"\n' in text
    text = text.replace('\nLHIP = "LHIP"\n', '\nLHIP = ["LHIP", "sacrum"]\n')
    both = parse_rig(text, source="menache with LHIP also 'sacrum'")
    cols = match_markers(both, [n for n in names if n != "LHIP"])
    assert cols[names.index("SACRUM")] == 0 and cols[names.index("LHIP")] == -1
