"""load_take over every real take: labels, references, rate, frames, gaps, up axis."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

# Same place as conftest's DATASETS (tests can't import conftest): used only to list
# files at collection time; every test still takes the `datasets` fixture.
from paths import DATASETS as _DATASETS

from retargetd.replay.c3d import write_c3d
from retargetd.replay.points import reference_kind, split_subjects
from retargetd.replay.take import Take, TakeError
from retargetd.replay.takes import load_take

_FILES: list[str | None] = [
    str(p.relative_to(_DATASETS))
    for p in sorted(_DATASETS.rglob("*"))
    if p.suffix.lower() in (".c3d", ".trc")
] or [None]  # absent: one case that the fixture skips (or fails in CI)
_MANIFEST = (
    json.loads((_DATASETS / "manifest.json").read_text())
    if (_DATASETS / "manifest.json").is_file()
    else [None]
)
MULTI_SUBJECT = {
    "pyomeca/markers_analogs.c3d": ("boite", "Daphnee"),
    "kineticstoolkit/kinematics_tennis_serve_2players_SYNTHETIC.c3d": (
        "Derrick",
        "Viktor",
    ),
}
#: Full-body takes: (head markers, foot markers); the head is > 1 m above the feet.
HEAD_FOOT = {
    "btkdata/MOTEK_T.trc": (["LFHD", "RFHD"], ["LHEE", "RHEE"]),
    "btkdata/MOTEK_ballet_reduced.trc": (["LFHD", "RFHD"], ["LHEE", "RHEE"]),
    "btkdata/PiG_Calibration-FlatFoot-Full.c3d": (["LFHD", "RFHD"], ["LHEE", "RHEE"]),
    "btkdata/PiG_Motion-FlatFoot-Full.c3d": (["LFHD", "RFHD"], ["LHEE", "RHEE"]),
    "opensim-core/subject01_static.trc": (["Top.Head"], ["R.Heel", "L.Heel"]),
    "opensim-core/subject01_walk1.trc": (["Top.Head"], ["R.Heel", "L.Heel"]),
    "peers/subject01_walk1.trc": (["Top.Head"], ["R.Heel", "L.Heel"]),
    "opensim-core/walking2.c3d": (["LFHD", "RFHD"], ["LCAL", "RCAL"]),
    "kineticstoolkit/kinematics_tennis_serve.c3d": (["LFHD", "RFHD"], ["LHEE", "RHEE"]),
    "ezc3d-testfiles/Qualisys.c3d": (["L_HDF", "R_HDF"], ["L_FCC", "R_FCC"]),
    "peers/bioptim_gait_wholebody.c3d": (["HV"], ["LCAL", "RCAL"]),
}


def _load_all(path: Path, rel: str) -> list[Take]:
    """One take per subject (multi-subject files need ``subject=``)."""
    if rel in MULTI_SUBJECT:
        return [load_take(path, subject=s) for s in MULTI_SUBJECT[rel]]
    return [load_take(path)]


def _strip(label: str) -> tuple[str | None, str]:
    head, sep, tail = label.partition(":")
    return (head, tail) if sep else (None, label)


@pytest.mark.parametrize("rel", _FILES)
def test_every_take_loads(datasets: Path, rel: str) -> None:
    for take in _load_all(datasets / rel, rel):
        assert take.n_markers > 0
        assert take.n_frames > 0
        assert take.positions.shape == (take.n_frames, take.n_markers, 3)
        assert take.positions.dtype == np.float64
        np.testing.assert_array_equal(take.valid, np.isfinite(take.positions).all(-1))
        assert len(set(take.labels)) == take.n_markers
        assert take.references.values.shape[1] == len(take.references.labels)


@pytest.mark.parametrize("rel", sorted(MULTI_SUBJECT))
def test_multi_subject_files_need_a_subject(datasets: Path, rel: str) -> None:
    names = MULTI_SUBJECT[rel]
    with pytest.raises(TakeError, match=rf"holds 2 subjects \({', '.join(names)}\)"):
        load_take(datasets / rel)
    with pytest.raises(TakeError, match=rf"it holds: {', '.join(names)}"):
        load_take(datasets / rel, subject="Nobody")


@pytest.mark.parametrize(
    "entry", _MANIFEST, ids=lambda e: e["file"] if e else "no-datasets"
)
def test_matches_manifest(datasets: Path, entry: dict) -> None:
    rel = entry["file"]
    takes = _load_all(datasets / rel, rel)
    markers: dict[str | None, list[str]] = {}
    for label in entry["marker_labels"]:
        who, name = _strip(label)
        markers.setdefault(who, []).append(name)
    if set(markers) != {None}:
        assert {t.subject for t in takes} == set(markers)
    others = {_strip(label)[1] for label in entry["other_points"]}
    refs: set[str] = set()
    samples = valid = 0
    for take in takes:
        assert (
            list(take.labels) == markers[take.subject if None not in markers else None]
        )
        refs |= set(take.references.labels)
        assert take.n_frames == entry["n_frames"]
        assert take.rate_hz == pytest.approx(entry["rate"])
        assert take.units == entry["units"]
        if "first_frame" in entry:
            assert take.first_frame == entry["first_frame"]
        samples += take.valid.size
        valid += int(take.valid.sum())
    assert refs == others
    assert 1.0 - valid / samples == pytest.approx(entry["gap_fraction"], abs=1e-6)


@pytest.mark.parametrize("rel", sorted(HEAD_FOOT))
def test_world_is_z_up(datasets: Path, rel: str) -> None:
    take = load_take(datasets / rel)
    head, foot = HEAD_FOOT[rel]
    z = take.positions[..., 2]
    head_z = np.nanmean(z[:, [take.marker_index(m) for m in head]])
    foot_z = np.nanmean(z[:, [take.marker_index(m) for m in foot]])
    assert head_z - foot_z > 1.0, (head_z, foot_z)


def test_overrides_and_sources(datasets: Path) -> None:
    path = datasets / "opensim-core" / "subject01_walk1.trc"
    base = load_take(path)
    as_m = load_take(path, units="m", up_axis="y")
    assert (as_m.units, as_m.units_source) == ("m", "override")
    assert (as_m.up_axis, as_m.up_source) == ("+Y", "override")
    np.testing.assert_allclose(as_m.positions, base.positions * 1e3)
    with pytest.raises(TakeError, match=r"--take-up.*'up'"):
        load_take(path, up_axis="up")
    with pytest.raises(TakeError, match=r"--take-units.*'parsec'"):
        load_take(path, units="parsec")
    with pytest.raises(TakeError, match="no subjects"):
        load_take(path, subject="Derrick")


def test_suffix_dispatch(tmp_path: Path) -> None:
    path = tmp_path / "UPPER.C3D"
    write_c3d(path, ["a"], np.zeros((2, 1, 3)), 100.0)
    assert load_take(path).format == "c3d"
    with pytest.raises(TakeError, match=r"notes\.txt.*supported: \.c3d, \.mcap, \.trc"):
        load_take(tmp_path / "notes.txt")
    with pytest.raises(TakeError, match=r"missing\.trc: no such file"):
        load_take(tmp_path / "missing.trc")


@pytest.mark.parametrize(
    ("label", "kind"),
    [
        ("LHJC", "joint_centre"),
        ("RKJC", "joint_centre"),
        ("LAJC", "joint_centre"),
        ("LFEO", "segment_point"),
        ("PELP", "segment_point"),
        ("RTOA", "segment_point"),
        ("CentreOfMass", "model_point"),
        ("CentreOfMassFloor", "model_point"),
        ("LKNE", None),
        ("RTOE", None),
        ("LFHD", None),
        ("R.Knee.Lat", None),
        ("LFEOX", None),
    ],
)
def test_reference_kind_by_name(label: str, kind: str | None) -> None:
    assert reference_kind(label) == kind


def test_split_subjects_uses_declared_prefixes_and_names() -> None:
    subjects, owner, stripped = split_subjects(
        ["P1_C7", "P1_T10", "Other:C7", "loose"], ["P1_"], ["Alice"]
    )
    assert subjects == ("Alice", "Other")
    assert owner == ["Alice", "Alice", "Other", None]
    assert stripped == ["C7", "T10", "C7", "loose"]
    # Unprefixed single-subject Vicon file: the one declared name owns everything.
    assert split_subjects(["C7", "T10"], [], ["BELT_C"])[:2] == (
        ("BELT_C",),
        ["BELT_C", "BELT_C"],
    )
