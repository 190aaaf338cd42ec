"""Regression suite: golden solve outputs of real takes and the synthetic performer.

Each case in ``tests/golden/`` is recomputed (calibrate + solve the whole take) and
every sampled frame compared: rotations within 1e-4 rad, joint centres and root within
0.05 mm, flags exact (README there). A failure names the case and take, the row and
source frame, and the bone or joint, worst first. Regenerate with
``python tests/golden/regenerate.py`` (prints what changed).
"""

from __future__ import annotations

import dataclasses
import importlib.util
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest

from retargetd.daemon.rotations import quat_from_axis_angle, quat_mul

GOLDEN_DIR = Path(__file__).resolve().parent.parent / "golden"


def _load_cases() -> ModuleType:
    """tests/golden/golden_cases.py (tests are not a package)."""
    name = "retargetd_tests_golden_cases"
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, GOLDEN_DIR / "golden_cases.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


g = _load_cases()
SYNTH = g.CASE_BY_NAME["synthetic-menache"]


@pytest.fixture(scope="module")
def synth_computed() -> Any:
    return g.compute(SYNTH)


def _case_datasets(case: Any, request: pytest.FixtureRequest) -> Path:
    return request.getfixturevalue("datasets") if case.needs_datasets else g.DATASETS


@pytest.mark.parametrize("name", list(g.CASE_BY_NAME))
def test_golden(name: str, request: pytest.FixtureRequest) -> None:
    case = g.CASE_BY_NAME[name]
    root = _case_datasets(case, request)
    doc = g.load_golden(case)
    cmp = g.compare(case, doc, g.compute(case, root))
    assert cmp.ok, g.failure_message(case, cmp)


def test_every_case_has_a_golden_and_no_stray_files() -> None:
    stored = {p.name for p in GOLDEN_DIR.glob("*.json")}
    assert stored == {g.golden_path(c).name for c in g.CASES}


def test_goldens_are_small() -> None:
    sizes = {p.name: p.stat().st_size for p in GOLDEN_DIR.iterdir() if p.is_file()}
    assert all(s < 30_000 for n, s in sizes.items() if n.endswith(".json")), sizes
    assert sum(sizes.values()) < 200_000, sizes


def test_stored_rounding_is_far_inside_the_tolerances(synth_computed: Any) -> None:
    """Rounding to the stored decimals costs < 1/20 of each tolerance."""
    cmp = g.compare(SYNTH, g.to_golden(SYNTH, synth_computed), synth_computed)
    assert cmp.ok
    assert max(cmp.max_angle_rad.values()) < g.TOL_ANGLE_RAD / 20
    assert max(cmp.max_mm.values()) < g.TOL_MM / 20


def test_synthesis_is_bit_reproducible(synth_computed: Any) -> None:
    again = g.compute(SYNTH)
    for f in ("world_from_bone_quat", "joint_centres_mm", "bone_flags"):
        np.testing.assert_array_equal(getattr(again, f), getattr(synth_computed, f))


def _perturbed(computed: Any, **arrays: np.ndarray) -> Any:
    return dataclasses.replace(computed, **arrays)


def _fails(computed: Any) -> tuple[str, list[str]]:
    """The failure message and every offence, described."""
    cmp = g.compare(SYNTH, g.load_golden(SYNTH), computed)
    assert not cmp.ok
    return g.failure_message(SYNTH, cmp), [o.describe() for o in cmp.offences]


def test_a_bone_rotated_beyond_tolerance_fails_naming_take_frame_bone(
    synth_computed: Any,
) -> None:
    row = int(synth_computed.rows[4])
    bone = synth_computed.bone_names.index("lupperarm")
    q = synth_computed.rest_from_bone_quat.copy()
    # 3 mrad: far past the tolerance and the stored files' rounding (~1e-6 rad), so
    # the printed value is the turn's own
    turn = quat_from_axis_angle(np.array([0.0, 0.0, 1.0]), 3e-3)
    q[row, bone] = quat_mul(q[row, bone], turn)
    message, _ = _fails(_perturbed(synth_computed, rest_from_bone_quat=q))
    assert "synthetic-menache [synthesize(" in message
    where = f"row {row} (frame {row}) rest_from_bone_quat bone lupperarm"
    assert f"{where}: 0.003 rad" in message
    assert "1 value(s) beyond tolerance" in message


def test_within_tolerance_passes(synth_computed: Any) -> None:
    q = synth_computed.world_from_bone_quat.copy()
    turn = quat_from_axis_angle(np.array([1.0, 0.0, 0.0]), 5e-5)
    q[:] = quat_mul(q, turn)
    jc = synth_computed.joint_centres_mm + 0.02
    cmp = g.compare(
        SYNTH,
        g.load_golden(SYNTH),
        _perturbed(synth_computed, world_from_bone_quat=-q, joint_centres_mm=jc),
    )
    assert cmp.ok, g.failure_message(SYNTH, cmp)


def test_a_moved_calibration_offset_fails_naming_joints(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A change upstream of the solve: the calibrated left ankle centre (a rigid
    point's offset) moves 0.2 mm; its joint centre and the left shank are named (the
    message's worst ten: the shank or the foot it carries, ~0.29 deg each)."""
    from retargetd.daemon.body import calibration
    from retargetd.daemon.body.rig import load_rig

    rig = load_rig("menache")
    point = rig.point_names.index(rig.joints["LAJC"])
    real = calibration.calibrate

    def shifted(*args: Any, **kwargs: Any) -> Any:
        cal = real(*args, **kwargs)
        offsets = cal.point_offsets.copy()
        offsets[point] += [2e-4, 0.0, 0.0]
        return dataclasses.replace(cal, point_offsets=offsets)

    monkeypatch.setattr(calibration, "calibrate", shifted)
    message, every = _fails(g.compute(SYNTH))
    assert "golden synthetic-menache [synthesize(" in message
    assert any(f"bone {b}: " in message for b in ("lloleg", "lfoot"))
    shank = "row 0 (frame 0) world_from_bone_quat bone lloleg: "
    assert any(e.startswith(shank) for e in every)
    assert "row 0 (frame 0) joint_centres_mm LAJC: 0.2 mm > 0.05 mm" in every


def test_a_flag_change_fails(synth_computed: Any) -> None:
    flags = synth_computed.bone_flags.copy()
    row = int(synth_computed.rows[-1])
    flags[row, 0] |= 1
    message, _ = _fails(_perturbed(synth_computed, bone_flags=flags))
    assert (
        f"row {row} (frame {row}) bone_flags bone pelvis: 0 (none) -> 1 (held)"
        in message
    )
    assert "flag_counts pelvis: {} -> {'held': 1}" in message


def test_worst_offenders_listed_first_and_capped(synth_computed: Any) -> None:
    jc = synth_computed.joint_centres_mm.copy()
    rows = synth_computed.rows
    jc[rows[1], 2, 0] += 0.3
    jc[rows[2], 5, 1] += 7.0
    jc[rows[3], :, 2] += 0.1
    message, _ = _fails(_perturbed(synth_computed, joint_centres_mm=jc))
    lines = message.splitlines()
    names = synth_computed.joint_names
    assert (
        f"row {rows[2]} (frame {rows[2]}) joint_centres_mm {names[5]}: 7 mm"
        in (lines[1])
    )
    assert (
        f"row {rows[1]} (frame {rows[1]}) joint_centres_mm {names[2]}: 0.3 mm"
        in (lines[2])
    )
    assert f"{2 + len(names)} value(s) beyond tolerance" in lines[0]
    assert len(lines) == 1 + 10 + 1
