"""``retargetd retarget IN.bvh --target T.bvh --plant-feet`` (issue 34 item 2): a BVH
take's stance feet planted on a BVH target (``cli/retarget_plant.py``,
``retarget/bvh_legs.py``).

The source: the synthetic performer's level walk (``synth/gait.py``: stance feet that
neither slide nor sink, 8 s at 120 Hz) written as BVH from its true skeleton and
rotations (``bench/feet_plant_bvh.py`` ``truth_bvh``: Mixamo joint names, a toe joint
at the MTP, the toe tip its End Site, the floor at y = 0). The targets: that
hierarchy with every offset below the hip joints times 0.8 and 1.25 (legs 0.8x and
1.25x). Measured on the written take's forward kinematics with
``bench/feet_plant_bvh.py``'s ``measure`` (``bench/feet_plant.py``'s measures: skate,
per contact frame the horizontal travel of the foot's floor point that moved least,
p95; sink, the lowest foot point below the floor; the knee's added change at the
blend edges), without and with ``--plant-feet``; the table is in ``docs/feet.md``."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from bench_scripts import bench_module

from retargetd.daemon.cli.retarget_plant import plant_retarget
from retargetd.daemon.retarget.bvh_retarget import retarget_bvh
from retargetd.daemon.synth import performer as pf
from retargetd.replay.bvh import (
    read_bvh_hierarchy,
    write_bvh,
)

RATE_HZ = 120.0
SECONDS = 8.0
CM = 0.01
CLI = [sys.executable, "-m", "retargetd.daemon"]


@pytest.fixture(scope="module")
def walk(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Any]:
    """The walk's BVH and the synthetic take (its truth)."""
    take = pf.synthesize(
        seconds=SECONDS, rate_hz=RATE_HZ, markerset="plug-in-gait",
        motions=("level_walk",), seed=0,
    )  # fmt: skip
    path = tmp_path_factory.mktemp("retarget_plant") / "walk.bvh"
    bench_module("feet_plant_bvh").truth_bvh(take, path)
    return path, take


def _measure(
    walk: tuple[Path, Any], k: float, toes: float = 1.0, up_cm: float = 0.0
) -> dict[str, Any]:
    """``feet_plant_bvh.measure`` on legs ``k``x (toes ``toes`` more), the take's
    floor ``up_cm`` above the file's origin."""
    fb = bench_module("feet_plant_bvh")
    path = fb.raised(walk[0], up_cm) if up_cm else walk[0]
    return fb.measure(path, walk[1], k, toes, truth_floor_m=up_cm * CM)


@pytest.mark.timeout(600)
@pytest.mark.parametrize(("k", "up_cm"), [(0.8, 0.0), (1.25, 0.0), (1.25, 10.0)])
def test_planted_feet_neither_skate_nor_sink(
    walk: tuple[Path, Any], k: float, up_cm: float
) -> None:
    """Legs 0.8x and 1.25x: the floor found where the truth's is (0.1 mm; also with
    the take raised 10 cm, the target's floor then k times as high), the leg ratio
    k; the stance detector's contact events within 2 frames of the truth's; with
    ``--plant-feet`` a contact frame's skate p95 within the issue's 2 mm and below
    the rotations alone, no foot below the floor (0.01 mm), the knee's added change
    at the blend edges within 3 deg a frame, no frame unreached."""
    m = _measure(walk, k, up_cm=up_cm)
    pl, free, plant = m["planted"], m["free"], m["plant"]
    print(k, "skate p95 free / plant", free["skate_frame_p95_mm"],
          plant["skate_frame_p95_mm"], "sink", free["sink_max_mm"],
          plant["sink_max_mm"], "knee", m["knee_added_deg"], "events",
          m["events"].max(), "floor", pl.floor_m)  # fmt: skip
    assert abs(pl.floor_m - up_cm * CM) < 1e-4
    assert pl.leg_ratio == pytest.approx(k, rel=1e-9)
    assert m["events"].size >= 20 and m["events"].max() <= 2
    assert plant["skate_frame_p95_mm"] <= 2.0
    assert plant["skate_frame_p95_mm"] < free["skate_frame_p95_mm"]
    assert plant["skate_run_p95_mm"] < free["skate_run_p95_mm"]
    assert plant["sink_max_mm"] <= 0.01
    assert m["knee_added_deg"] <= 3.0
    assert not pl.flags.any()


@pytest.mark.timeout(600)
def test_a_foot_that_cannot_reach_is_flagged(walk: tuple[Path, Any]) -> None:
    """Toes half as long on legs 1x: rolling about a nearer MTP joint, the target's
    ankle rises less than the performer's at heel-off, so the hold is past the
    straight leg. Every flagged frame has a foot in contact and a planted leg
    straighter than the unplanted one (straightened toward its hold); the
    proportional targets above flag none."""
    m = _measure(walk, 1.0, toes=0.5)
    flags = m["planted"].flags != 0
    print("unreached", flags.sum())
    assert flags.sum() > 10
    assert m["planted"].contact[flags].any(axis=1).all()
    straighter = (m["knee_plant"] - m["knee_free"]).min(axis=1)
    assert (straighter[flags] < 0.0).all()


def _run(*argv: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*CLI, *argv], capture_output=True, text=True, timeout=300, check=False
    )


@pytest.mark.timeout(600)
def test_cli_writes_the_planted_take(walk: tuple[Path, Any], tmp_path: Path) -> None:
    """``retarget --plant-feet`` (real files): the BVH it writes is the planted take
    (1e-5, the file's precision), its summary line the plant's figures; ``.glb``
    is written too."""
    src = read_bvh_hierarchy(walk[0], read_motion=True)
    tgt_sk = bench_module("feet_plant_bvh").scaled_target(src, 1.25, toes=0.5)
    target = tmp_path / "avatar.bvh"
    write_bvh(target, tgt_sk, src.frames[:1], src.frame_time_s)
    out = tmp_path / "out.bvh"
    done = _run("retarget", str(walk[0]), "--target", str(target), "--out", str(out),
                "--plant-feet")  # fmt: skip
    assert done.returncode == 0, done.stderr
    tgt = read_bvh_hierarchy(target)
    pl = plant_retarget(src, tgt, retarget_bvh(src, tgt), source_m_per_unit=CM,
                        target_m_per_unit=CM)  # fmt: skip
    written = read_bvh_hierarchy(out, read_motion=True)
    assert written.frames is not None
    np.testing.assert_allclose(written.frames, pl.result.frames, atol=1e-5)
    line = next(x for x in done.stdout.splitlines() if x.startswith("planted feet"))
    n = int(np.count_nonzero(pl.flags))
    assert n > 0 and f"plant_unreached {n} frames" in line
    assert f"leg ratio {pl.leg_ratio:.4g} " in line
    left, right = pl.contact.sum(axis=0)
    assert f"contact frames left {left} right {right}" in line
    glb = tmp_path / "out.glb"
    done = _run("retarget", str(walk[0]), "--target", str(target), "--out", str(glb),
                "--plant-feet")  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert glb.stat().st_size > 0 and line in done.stdout


@pytest.mark.parametrize(
    ("which", "renamed", "missing"),
    [
        ("target", {"LeftLeg": "LeftKnee"}, "LeftLowerLeg"),
        ("source", {"LeftFoot": "LeftAnkle", "RightUpLeg": "RightThigh"},
         "LeftFoot, RightUpperLeg"),
    ],
)  # fmt: skip
def test_cli_refuses_a_file_without_legs(
    walk: tuple[Path, Any], tmp_path: Path, which: str, renamed: dict, missing: str
) -> None:
    """A source or target whose leg joints no map names: one line naming the file
    and the joints it lacks, exit 2, nothing written; ``--root-scale`` with it
    too (the plant sets the root's scale)."""
    src = read_bvh_hierarchy(walk[0], read_motion=True)
    sk = dataclasses.replace(
        src, joint_names=tuple(renamed.get(n, n) for n in src.joint_names)
    )
    odd = tmp_path / f"{which}.bvh"
    assert src.frames is not None
    write_bvh(odd, sk, src.frames, src.frame_time_s)
    source, target = (odd, walk[0]) if which == "source" else (walk[0], odd)
    out = tmp_path / "out.bvh"
    done = _run("retarget", str(source), "--target", str(target), "--out", str(out),
                "--plant-feet")  # fmt: skip
    assert done.returncode == 2
    assert len(done.stderr.strip().splitlines()) == 1
    assert f"the {which} {odd}" in done.stderr and missing in done.stderr
    assert not out.exists()
    done = _run("retarget", str(walk[0]), "--target", str(walk[0]), "--out",
                str(out), "--plant-feet", "--root-scale", "1.1")  # fmt: skip
    assert done.returncode == 2 and "--root-scale" in done.stderr
    assert not out.exists()


def test_cli_refuses_legs_too_short_for_their_unit(
    walk: tuple[Path, Any], tmp_path: Path
) -> None:
    """Centimetre files read as millimetres: legs of 0.09 m, under the plant's
    0.2 m; one line naming the unit options, exit 2. ``--source-units`` without
    ``--plant-feet`` is refused (it applies to nothing else)."""
    out = tmp_path / "out.bvh"
    done = _run("retarget", str(walk[0]), "--target", str(walk[0]), "--out",
                str(out), "--plant-feet", "--units", "mm")  # fmt: skip
    assert done.returncode == 2
    assert len(done.stderr.strip().splitlines()) == 1
    assert "leg length must be > 0.2 m" in done.stderr and "--units" in done.stderr
    assert not out.exists()
    done = _run("retarget", str(walk[0]), "--target", str(walk[0]), "--out",
                str(out), "--source-units", "mm")  # fmt: skip
    assert done.returncode == 2 and "--source-units" in done.stderr
    assert not out.exists()


def test_target_legs_named_by_the_joint_map(
    walk: tuple[Path, Any], tmp_path: Path
) -> None:
    """A target whose leg joints no name map knows (``thigh_l`` ...), mapped from
    the source's by ``--map``: its legs are the joints the map drives, planted as
    the same skeleton with Mixamo names is (the same motion lines, 1e-9)."""
    src = read_bvh_hierarchy(walk[0], read_motion=True)
    named = bench_module("feet_plant_bvh").scaled_target(src, 1.25)
    odd_names = {
        f"{s}{b}": f"{b.lower()}_{s[0].lower()}"
        for s in ("Left", "Right")
        for b in ("UpLeg", "Leg", "Foot", "ToeBase")
    }
    odd = dataclasses.replace(
        named, joint_names=tuple(odd_names.get(n, n) for n in named.joint_names)
    )
    table = tmp_path / "map.toml"
    table.write_text(
        "[joints]\n" + "".join(f'"{a}" = "{b}"\n' for a, b in odd_names.items())
    )
    pl = {}
    for name, sk, joint_map in (("named", named, None), ("odd", odd, odd_names)):
        free = retarget_bvh(src, sk, name_map=joint_map)
        pl[name] = plant_retarget(
            src, sk, free, source_m_per_unit=CM, target_m_per_unit=CM
        )
    assert pl["named"].leg_ratio == pytest.approx(1.25)
    np.testing.assert_allclose(
        pl["odd"].result.frames, pl["named"].result.frames, atol=1e-9
    )
    target = tmp_path / "odd.bvh"
    write_bvh(target, odd, src.frames[:1], src.frame_time_s)
    out = tmp_path / "o.bvh"
    done = _run("retarget", str(walk[0]), "--target", str(target), "--map",
                str(table), "--out", str(out), "--plant-feet")  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert "planted feet: leg ratio 1.25 " in done.stdout
