"""The body solve against the synthetic performer's truth, intact and damaged: the
tables of issue 28 item 6, written as markdown (``docs/fit-truth.md``).

Run from the repository root::

    python bench/fit_truth.py --out docs/fit-truth.md        # the whole document
    python bench/fit_truth.py --rigs menache --motions default --seconds 4 \
        --no-damage                                          # quick: seconds

Every case synthesizes the performer (``synth.performer.synthesize``, ``--seconds``
at ``--rate-hz``, ``--noise-mm``, ``--seed``) wearing a shipped marker set
(``daemon/synth/markersets/``) doing one motion set: the default motions, or one
activity alone (``synth.motion.ACTIVITY_MOTIONS``). The rig of the same name is
calibrated on the take's first ``--calibrate-frames`` frames (the T-pose hold) and
the take is solved with ``body.method.make_body_solver(method, rig, cal, labels,
joint_limits=JOINT_LIMITS_DEG, segment_kind=SEGMENT_KIND)``, once per method;
``fit+rom`` (rigs with a ``[functional]`` table) is the fit on a calibration that
adds the same performer's range of motion (``synth --motions rom``, two cycles:
``calibrate --rom``, issue 29), in the truth tables only.

**Truth table.** ``synth.truth.compare_with_truth``: per rig bone with a humanoid
name, the angle between its rotation change since frame 0 and its performer
segment's; statistics over the frames after the calibration window. Bones past p95
5 deg or max 10 deg (issue 28 item 6) are bold; a bone whose rig's markers leave a
rotation unobserved (``fit_observe``'s decision for the rig and its calibration,
issue 28 item 1), or whose ancestors' markers do, is judged on its error less the
truth's own excursion in those rotations. ``--unobserved FILE`` adds axes (JSON:
``{rig: {bone: [[x, y, z], ...]}}``, axes in the bone's rest axes that no marker
determines) the marks judge the error less the truth's own excursion in those axes.

**Damage table** (the default motions; ``synth.damage``): each marker hidden for
each ``--hide-s`` window, and bursts of ``--bursts`` frames of each kind (every
marker collapsed onto the take's first marker, all zeros, left/right labels
swapped), all starting at ``--damage-at-s``; each damaged take solved with the same
calibration and method and compared with the intact take's solve
(``synth.damage.damage_metrics``): the largest joint-centre distance and bone angle,
steps over 5 deg the intact solve does not have, NaN, the recovery time (every bone
back within ``--recovery-tol-deg`` and every joint within ``--recovery-tol-mm`` of the
intact solve for good) and the damaged solve's worst bone against the truth. Hides
show the worst marker; bold marks what issue 28 item 6 forbids (a hide: a joint past
20 mm, a bone past 10 deg, a new step, NaN; a burst: recovery over 0.25 s, NaN).

**Beyond the hold** (hides; ``synth.hold``): a marker that alone sees a rotation
(Plug-in Gait's LFIN: the hand's flexion) leaves it unobserved while hidden; the fit
holds it at its last seen value (``fit_track.hold_priors``), and the best any solve
can do is then off by the truth's own motion in it. Beside the plain figures (kept:
they are the issue's letter), each hide is judged against the truth: per compared
bone, its rotation change since the hide's start against its truth segment's, less
the intact take's solve's same error, less the truth's excursion since the hide's
start in the rotations the fit holds for that marker (decided as the kernel decides:
``fit_observe.hidden_information``'s tables and the threshold ``(max(noise, residual
level) / resolution)^2`` at the frame before the hide, and the local floor; the
excursion is the length of the truth joint's swing-twist coordinates in the bone's
axes, the hold prior's own, projected on the held directions, summed over the bone
and its ancestors), over the hidden frames and ``synth.hold.TAIL_S`` (0.25 s) after
them. Its largest over the bones, past ``HIDE_BONE_DEG`` (10 deg), is a runaway: a
bone turned further than the hold can explain; within it, a failure of the plain
columns is the unavoidable hold. The construction is judged with the fit's held
rotations (what the marker alone resolved does not depend on the method).

Cases run in ``--jobs`` processes (default: every core); the output is the same
whatever the number. Nothing is timed: the document is a function of the code and
the arguments (its header names both). The machine's load is printed, not written.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from functools import lru_cache
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import numpy as np

from retargetd.daemon.body.calibration import Calibration, calibrate
from retargetd.daemon.body.method import METHODS, make_body_solver
from retargetd.daemon.body.rig import Rig, load_rig
from retargetd.daemon.body.solve import BodySolve, BodySolver
from retargetd.daemon.body.solve_fit import FitSolve, FitSolver
from retargetd.daemon.synth import performer as pf
from retargetd.daemon.synth.damage import DamageMetrics, damage, damage_metrics
from retargetd.daemon.synth.hold import (
    TAIL_S,
    HideTruth,
    held_directions,
    hide_truth_excess,
)
from retargetd.daemon.synth.motion import ROM_PERIOD_S
from retargetd.daemon.synth.truth import compare_with_truth, truth_map
from retargetd.daemon.validate.limits import JOINT_LIMITS_DEG
from retargetd.daemon.validate.model import SEGMENT_KIND

REPO = Path(__file__).resolve().parent.parent
RIGS = ("menache", "plug-in-gait")
#: Motion set name -> the components synthesized.
MOTION_SETS: dict[str, tuple[str, ...]] = {
    "default": pf.DEFAULT_MOTIONS,
    **{name: (name,) for name in pf.ACTIVITY_MOTIONS},
}
BURST_KINDS = ("collapse", "zeros", "swap")
#: The fit on a calibration that adds a range of motion (issue 29): rigs with a
#: ``[functional]`` table only, truth tables only (no damage).
ROM_METHOD = "fit+rom"
#: Seconds of the synthetic range of motion after its 1 s hold: two cycles of
#: ``synth.motion`` ``rom`` (``ROM_PERIOD_S`` 12 s), the live ``ctl calibrate --rom``
#: default.
ROM_SECONDS = 2.0 * ROM_PERIOD_S
#: Issue 28 item 6's thresholds.
P95_DEG = 5.0
MAX_DEG = 10.0
HIDE_JOINT_MM = 20.0
HIDE_BONE_DEG = 10.0
STEP_DEG = 5.0
RECOVERY_S = 0.25


@dataclass(frozen=True, slots=True)
class Settings:
    """What every case shares (hashable: the per-process caches key on it)."""

    seconds: float
    rate_hz: float
    noise_mm: float
    seed: int
    calibrate_frames: int
    damage_at_s: float
    recovery_tol_deg: float
    recovery_tol_mm: float
    unobserved: str  # JSON text of --unobserved ("" for none)


@dataclass(frozen=True, slots=True)
class TruthCase:
    rig: str
    motions: str
    method: str


@dataclass(frozen=True, slots=True)
class DamageCase:
    """One task: one kind of damage, every marker (hide) or every length (burst)."""

    rig: str
    method: str
    kind: str
    lengths: tuple[int, ...]  # frames; a hide task has one


@dataclass(frozen=True, slots=True)
class TruthRow:
    case: TruthCase
    bone_names: tuple[str, ...]
    p95_deg: tuple[float, ...]
    max_deg: tuple[float, ...]
    past: tuple[str, ...]
    held: tuple[str, ...]  # bones judged less the truth's unobserved excursion
    excess_p95_deg: tuple[float, ...]
    excess_max_deg: tuple[float, ...]
    n_nan: int
    joint: str
    joint_p95_mm: float
    joint_max_mm: float


@dataclass(frozen=True, slots=True)
class DamageRow:
    case: DamageCase
    length: int
    marker: str  # hidden marker ("" for a burst)
    metrics: DamageMetrics
    hold: HideTruth | None = None  # a hide: against the truth less the hold's share


# --- work (in the worker processes) ----------------------------------------------


@lru_cache(maxsize=4)
def _take(rig_name: str, motions: str, settings: Settings) -> pf.SynthTake:
    return pf.synthesize(
        seconds=settings.seconds,
        rate_hz=settings.rate_hz,
        markerset=rig_name,
        motions=MOTION_SETS[motions],
        noise_mm=settings.noise_mm,
        seed=settings.seed,
    )


@lru_cache(maxsize=4)
def _calibrated(
    rig_name: str, motions: str, settings: Settings, rom: bool = False
) -> tuple[Rig, Calibration]:
    rig = load_rig(rig_name)
    take = _take(rig_name, motions, settings)
    base = take.markers_world[: settings.calibrate_frames]
    if not rom:
        return rig, calibrate(rig, base, take.labels)
    # the same performer (seed, height, marker set) through its range of motion
    moves = pf.synthesize(
        seconds=1.0 + ROM_SECONDS, rate_hz=settings.rate_hz, markerset=rig_name,
        motions=("rom",), noise_mm=settings.noise_mm, seed=settings.seed,
    )  # fmt: skip
    frames = (moves.markers_world[moves.base_pose_frames.stop :], moves.labels, {})
    return rig, calibrate(rig, base, take.labels, rom=frames)


@lru_cache(maxsize=4)
def _solver(
    rig_name: str, motions: str, method: str, settings: Settings
) -> BodySolver | FitSolver:
    rig, cal = _calibrated(rig_name, motions, settings, method == ROM_METHOD)
    take = _take(rig_name, motions, settings)
    return make_body_solver(
        method.removesuffix("+rom"), rig, cal, take.labels,
        joint_limits=JOINT_LIMITS_DEG, segment_kind=SEGMENT_KIND,
        rate_hz=take.rate_hz,
    )  # fmt: skip


def _solve(
    rig_name: str,
    motions: str,
    method: str,
    settings: Settings,
    positions: np.ndarray | None = None,
) -> BodySolve:
    """The take (or ``positions``) solved from a fresh state (``reset``: a new
    take), with one solver per case made once."""
    solver = _solver(rig_name, motions, method, settings)
    solver.reset()
    take = _take(rig_name, motions, settings)
    return solver.solve_take(take.markers_world if positions is None else positions)


def _unobserved(
    rig_name: str, motions: str, settings: Settings
) -> dict[str, list[list[float]]]:
    """Per compared bone, the rotations (bone rest axes) its rig's markers do not
    observe (``fit_observe``, issue 28 item 1: decided from the rig and its
    calibration, the same for both methods), then ``--unobserved``'s per bone."""
    rig, _ = _calibrated(rig_name, motions, settings)
    model = _solver(rig_name, motions, "fit", settings).model
    compared = set(truth_map(rig, _take(rig_name, motions, settings).segment_names)
                   .bone_names)  # fmt: skip
    out = {
        o.bone: o.axes[~o.observed].tolist()
        for o in model.observation
        if o.bone in compared and not o.observed.all()
    }
    out.update(json.loads(settings.unobserved or "{}").get(rig_name, {}))
    return out


def _run_truth(case: TruthCase, settings: Settings) -> TruthRow:
    take = _take(case.rig, case.motions, settings)
    rig, _ = _calibrated(case.rig, case.motions, settings)
    unobserved = _unobserved(case.rig, case.motions, settings)
    cmp = compare_with_truth(
        _solve(case.rig, case.motions, case.method, settings),
        take,
        rig,
        frames=slice(settings.calibrate_frames, None),
        unobserved=unobserved,
    )
    j = int(np.argmax(cmp.joint_max_mm)) if cmp.joint_names else 0
    return TruthRow(
        case=case,
        bone_names=cmp.bone_names,
        p95_deg=tuple(float(v) for v in cmp.p95_deg),
        max_deg=tuple(float(v) for v in cmp.max_deg),
        past=cmp.bones_past(P95_DEG, MAX_DEG),
        held=tuple(
            n
            for n, ex in zip(cmp.bone_names, cmp.excursion_deg.T, strict=True)
            if ex.any()
        ),
        excess_p95_deg=tuple(float(v) for v in cmp.excess_p95_deg),
        excess_max_deg=tuple(float(v) for v in cmp.excess_max_deg),
        n_nan=int(cmp.n_nan.max()) if cmp.n_nan.size else 0,
        joint=cmp.joint_names[j] if cmp.joint_names else "",
        joint_p95_mm=float(cmp.joint_p95_mm[j]) if cmp.joint_names else 0.0,
        joint_max_mm=float(cmp.joint_max_mm[j]) if cmp.joint_names else 0.0,
    )


def _run_damage(case: DamageCase, settings: Settings) -> list[DamageRow]:
    take = _take(case.rig, "default", settings)
    rig, _ = _calibrated(case.rig, "default", settings)
    intact = _solve(case.rig, "default", case.method, settings)
    start = round(settings.damage_at_s * settings.rate_hz)
    rows = []
    markers = range(len(take.labels)) if case.kind == "hide" else (0,)
    # what each hidden marker alone resolved, the fit's decision at the hide's start
    # (synth.hold; the same directions judge the construction: the markers' loss)
    fit = _solver(case.rig, "default", "fit", settings)
    assert isinstance(fit, FitSolver)
    fit_intact = (
        intact if case.method == "fit" else _solve(case.rig, "default", "fit", settings)
    )
    level = (
        fit_intact.residual_level[start - 1]
        if isinstance(fit_intact, FitSolve)
        else 0.0
    )
    for length in case.lengths:
        window = slice(start, start + length)
        for marker in markers:
            pos = damage(take.markers_world, take.labels, case.kind, window,  # type: ignore[arg-type]
                         marker=marker)  # fmt: skip
            damaged = _solve(case.rig, "default", case.method, settings, pos)
            metrics = damage_metrics(
                intact, damaged, window, settings.rate_hz,
                tol_deg=settings.recovery_tol_deg, tol_mm=settings.recovery_tol_mm,
                step_deg=STEP_DEG, truth=take, rig=rig,
            )  # fmt: skip
            name = take.labels[marker] if case.kind == "hide" else ""
            hold = None
            rig_marker = np.flatnonzero(fit.marker_cols == marker)
            if case.kind == "hide" and rig_marker.size:
                held = held_directions(
                    fit.model, fit.params, int(rig_marker[0]),
                    fit_intact.parent_from_bone_quat[start - 1],
                    float(level),
                )  # fmt: skip
                hold = hide_truth_excess(take, rig, intact, damaged, held, window,
                                         settings.rate_hz)  # fmt: skip
            rows.append(DamageRow(case, length, name, metrics, hold))
    again = _solve(case.rig, "default", case.method, settings)
    if not np.array_equal(
        again.world_from_bone_quat, intact.world_from_bone_quat, equal_nan=True
    ):
        raise RuntimeError(
            f"{case.rig} {case.method}: the intact take solved after reset() differs "
            "from its first solve: reset() leaves state behind"
        )
    return rows


def _run(task: tuple[Any, Settings]) -> Any:
    case, settings = task
    if isinstance(case, TruthCase):
        return _run_truth(case, settings)
    return _run_damage(case, settings)


# --- the document -----------------------------------------------------------------


def _deg(value: float) -> str:
    return "NaN" if np.isnan(value) else f"{value:.1f}"


def _mm(value: float) -> str:
    """Millimetres; inf (a NaN joint centre, ``synth.damage``) reads NaN."""
    return "NaN" if not np.isfinite(value) else f"{value:.1f}"


def _bold(text: str, flag: bool) -> str:
    return f"**{text}**" if flag else text


def _recovery(m: DamageMetrics, rate_hz: float) -> str:
    if m.recovery_frames is None:
        return "never"
    return f"{m.recovery_frames} ({m.recovery_frames / rate_hz:.3f} s)"


def _truth_section(rows: Sequence[TruthRow], settings: Settings) -> list[str]:
    out = [
        "## Against the truth",
        "",
        f"Per rig bone with a humanoid name: p95 / max over frames "
        f"{settings.calibrate_frames}-{round(settings.seconds * settings.rate_hz) - 1} "
        "of the angle between its rotation change since frame 0 and its performer "
        "segment's, degrees (`synth.truth.compare_with_truth`). **Bold**: past "
        f"p95 {P95_DEG:g} deg or max {MAX_DEG:g} deg; for a bone whose rig's markers "
        "leave a rotation unobserved (`fit_observe`, issue 28 item 1: held at the "
        "calibration pose by the fit's prior) or whose ancestors' do, judged on the "
        "error less the truth's own excursion in those rotations (shown as \"less "
        'excursion"), as item 6 asks; the worst columns of the first table stay the '
        "plain error. Joints: the worst rig joint "
        "centre that stands for a performer joint, mm, after a constant offset "
        "carried by either adjacent segment.",
        "",
        "| rig | motions | method | bones past / compared | worst p95 | worst max "
        "| worst joint p95 / max mm | NaN frames |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        p95, top = np.array(r.p95_deg), np.array(r.max_deg)
        i, k = int(np.argmax(p95)), int(np.argmax(top))
        out.append(
            f"| {r.case.rig} | {r.case.motions} | {r.case.method} | "
            f"{_bold(str(len(r.past)), bool(r.past))} / {len(r.bone_names)} | "
            f"{_deg(p95[i])} ({r.bone_names[i]}) | {_deg(top[k])} ({r.bone_names[k]}) "
            f"| {r.joint_p95_mm:.1f} / {r.joint_max_mm:.1f} ({r.joint}) | {r.n_nan} |"
        )
    out.append("")
    for rig in dict.fromkeys(r.case.rig for r in rows):
        for method in dict.fromkeys(r.case.method for r in rows):
            block = [r for r in rows if r.case.rig == rig and r.case.method == method]
            if not block:
                continue
            out += [
                f"### {rig}, {method}: p95 / max, degrees",
                "",
                "| bone | " + " | ".join(r.case.motions for r in block) + " |",
                "|---|" + "---|" * len(block),
            ]
            for b, bone in enumerate(block[0].bone_names):
                cells = [
                    _bold(
                        f"{_deg(r.p95_deg[b])} / {_deg(r.max_deg[b])}"
                        + (
                            f" (less excursion {_deg(r.excess_p95_deg[b])} / "
                            f"{_deg(r.excess_max_deg[b])})"
                            if bone in r.held
                            else ""
                        ),
                        bone in r.past,
                    )
                    for r in block
                ]
                out.append(f"| {bone} | " + " | ".join(cells) + " |")
            out.append("")
    return out


def _damage_section(rows: Sequence[DamageRow], settings: Settings) -> list[str]:
    rate = settings.rate_hz
    out = [
        "## Damage (default motions)",
        "",
        f"Damage starts at {settings.damage_at_s:g} s (frame "
        f"{round(settings.damage_at_s * rate)}); each damaged take is solved with the "
        "same calibration and method and compared with the intact take's solve "
        "(`synth.damage.damage_metrics`), every frame. Columns: largest joint-centre "
        "distance (mm; NaN: a joint centre was NaN) and bone angle (deg) from the "
        "intact solve; (frame, bone) steps "
        f"over {STEP_DEG:g} deg between frames that the intact solve does not have; "
        "frames with NaN (the most of any marker hidden); recovery = frames "
        "(seconds) from the damage's end until "
        f"every bone is within {settings.recovery_tol_deg:g} deg and every joint "
        f"within {settings.recovery_tol_mm:g} mm of the intact solve for good; the "
        "damaged solve's worst bone against the truth (the intact solve's in "
        "brackets). A hide row is the worst over every marker hidden in turn, the "
        "marker named, and says how many of the markers hidden passed a limit "
        "below. **Bold**: what issue 28 item 6 forbids (hide: a joint past "
        f"{HIDE_JOINT_MM:g} mm, a bone past {HIDE_BONE_DEG:g} deg, a new step, NaN; "
        f"burst: recovery over {RECOVERY_S:g} s, NaN). The collapse is onto the "
        "take's first marker.",
        "",
        "Beyond the hold (hides): when a marker alone sees a rotation (a hand's "
        "flexion seen by one marker on the hand), hiding it leaves that rotation "
        "unobserved; the fit holds it at its last seen value, and no solve can do "
        "better than the truth's own motion in it, so the plain columns cannot tell "
        "such a hold from a runaway. This column judges each hide against the "
        "truth: per bone, its rotation change since the hide's start against its "
        "truth segment's, less the intact solve's same error, less the truth's own "
        "excursion since the hide's start in the rotations the fit holds for that "
        "marker (`synth.hold`: the fit's own tables and threshold at the frame "
        "before the hide; the excursion in the hold prior's swing-twist coordinates "
        "of the bone's axes, projected on the held directions, summed over the bone "
        "and its ancestors), over the hidden frames and "
        f"{TAIL_S:g} s after them; the largest over the bones, **bold** past "
        f"{HIDE_BONE_DEG:g} deg: a runaway. A marker past a limit in the plain "
        "columns but within this one is a hold no solve can avoid. The "
        "construction is judged on the fit's held rotations.",
        "",
    ]
    for rig in dict.fromkeys(r.case.rig for r in rows):
        for method in dict.fromkeys(r.case.method for r in rows):
            block = [r for r in rows if r.case.rig == rig and r.case.method == method]
            if not block:
                continue
            out += [
                f"### {rig}, {method}",
                "",
                "| damage | joint mm | bone deg | new steps | NaN | recovery "
                "| truth max deg | beyond the hold deg |",
                "|---|---|---|---|---|---|---|---|",
            ]
            groups: dict[tuple[str, int], list[DamageRow]] = {}
            for r in block:
                groups.setdefault((r.case.kind, r.length), []).append(r)
            for (kind, length), group in groups.items():
                out.append(_damage_line(kind, length, group, rate))
            out.append("")
            out += _hidden_markers(groups, rate)
    return out


def _beyond(r: DamageRow) -> float:
    """A hide's largest bone error against the truth beyond the intact solve's and
    the hold's share (``synth.hold``); 0 for a burst."""
    return float(r.hold.excess_deg.max()) if r.hold and r.hold.excess_deg.size else 0.0


def _beyond_cell(r: DamageRow | None) -> str:
    """The figure with its bone, bold past the bone limit."""
    if r is None or r.hold is None or not r.hold.excess_deg.size:
        return ""
    h = r.hold
    w = h.worst
    parts = (h.excess_deg[w], h.error_deg[w], h.intact_deg[w], h.allowance_deg[w])
    ex, err, base, allow = (_deg(float(v)) for v in parts)
    return _bold(
        f"{ex} ({h.bone_names[w]}: {err} - {base} - {allow})",
        _beyond(r) > HIDE_BONE_DEG,
    )


def _past(m: DamageMetrics) -> bool:
    """What issue 28 item 6 forbids of a hidden marker."""
    return (
        m.max_joint_mm > HIDE_JOINT_MM
        or m.max_bone_deg > HIDE_BONE_DEG
        or m.new_steps > 0
        or m.nan_frames > 0
    )


def _hidden_markers(
    groups: dict[tuple[str, int], list[DamageRow]], rate: float
) -> list[str]:
    """Per hidden marker that passes a limit in any hide window: its joint, bone
    (the bone named) and new steps in each window, so each failure is traceable."""
    hides = {length: {r.marker: r for r in group}
             for (kind, length), group in groups.items() if kind == "hide"}  # fmt: skip
    if not hides:
        return []
    markers = list(dict.fromkeys(k for by in hides.values() for k in by))
    failing = [
        k for k in markers
        if any(_past(by[k].metrics) or _beyond(by[k]) > HIDE_BONE_DEG
               for by in hides.values() if k in by)
    ]  # fmt: skip
    if not failing:
        return []
    head = " | ".join(
        f"hide {length / rate:g} s | beyond the hold, {length / rate:g} s"
        for length in hides
    )
    out = [
        "Hidden markers past a limit (joint mm / bone deg (bone) / new steps against "
        "the intact solve; beyond the hold: deg (bone: damaged - intact - the "
        "truth's excursion in what the fit held, each since the hide's start, "
        "against the truth), bold past "
        f"{HIDE_BONE_DEG:g} deg: a runaway, not a hold):",
        "",
        f"| marker | {head} |",
        "|---|" + "---|---|" * len(hides),
    ]
    for k in failing:
        cells = []
        for by in hides.values():
            r = by.get(k)
            m = None if r is None else r.metrics
            cells.append(
                "" if m is None else _bold(
                    f"{_mm(m.max_joint_mm)} / {_deg(m.max_bone_deg)} "
                    f"({m.max_bone}) / {m.new_steps}",
                    _past(m),
                )
            )  # fmt: skip
            cells.append(_beyond_cell(r))
        out.append(f"| {k} | " + " | ".join(cells) + " |")
    return [*out, ""]


def _damage_line(kind: str, length: int, group: list[DamageRow], rate: float) -> str:
    def worst(key: Callable[[DamageMetrics], float]) -> DamageRow:
        return max(group, key=lambda r: key(r.metrics))

    hide = kind == "hide"
    j = worst(lambda m: m.max_joint_mm)
    b = worst(lambda m: m.max_bone_deg)
    s = worst(lambda m: m.new_steps)
    rec = worst(
        lambda m: np.inf if m.recovery_frames is None else float(m.recovery_frames)
    )
    t = worst(lambda m: m.truth_max_deg or 0.0)
    n = worst(lambda m: m.nan_frames)
    n_nan = n.metrics.nan_frames

    def at(r: DamageRow, value: float | None = 1.0) -> str:
        """The hidden marker behind a worst figure (none for a zero)."""
        return f" ({r.marker})" if hide and value != 0 else ""

    late = rec.metrics.recovery_frames is None or (
        rec.metrics.recovery_frames / rate > RECOVERY_S
    )
    past = sum(_past(r.metrics) for r in group)
    beyond = sum(_beyond(r) > HIDE_BONE_DEG for r in group)
    label = (
        f"hide {length / rate:g} s ({len(group)} markers, {past} past a limit, "
        f"{beyond} beyond the hold)"
        if hide
        else f"{kind} {length} frame{'s' if length > 1 else ''}"
    )
    cells = [
        label,
        _bold(
            f"{_mm(j.metrics.max_joint_mm)}{at(j)}",
            hide and j.metrics.max_joint_mm > HIDE_JOINT_MM,
        ),
        _bold(
            f"{_deg(b.metrics.max_bone_deg)}{at(b)}",
            hide and b.metrics.max_bone_deg > HIDE_BONE_DEG,
        ),
        _bold(
            f"{s.metrics.new_steps}{at(s, s.metrics.new_steps)}",
            hide and s.metrics.new_steps > 0,
        ),
        _bold(f"{n_nan}{at(n, n_nan)}", n_nan > 0),
        _bold(
            f"{_recovery(rec.metrics, rate)}{at(rec, rec.metrics.recovery_frames)}",
            not hide and late,
        ),
        f"{_deg(t.metrics.truth_max_deg or 0.0)}{at(t)} "
        f"[{_deg(t.metrics.intact_truth_max_deg or 0.0)}]",
    ]
    if hide:
        h = max(group, key=_beyond)
        cells.append(_bold(f"{_deg(_beyond(h))}{at(h)}", _beyond(h) > HIDE_BONE_DEG))
    else:
        cells.append("")
    return "| " + " | ".join(cells) + " |"


def _commit() -> str:
    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=REPO, check=True,
            capture_output=True, text=True,
        ).stdout.strip()  # fmt: skip
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"], cwd=REPO,
            check=True, capture_output=True, text=True,
        ).stdout.strip()  # fmt: skip
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + (" with uncommitted changes" if dirty else "")


def _document(
    argv: Sequence[str],
    settings: Settings,
    truth: Sequence[TruthRow],
    damaged: Sequence[DamageRow],
) -> str:
    lines = [
        "# The body solve against the synthetic performer's truth",
        "",
        "Generated by `python bench/fit_truth.py"
        + (" " + shlex.join(argv) if argv else "")
        + f"` at commit {_commit()}; regenerate, don't edit "
        "(`bench/fit_truth.py`'s docstring defines every figure).",
        "",
        f"Synthetic performer (`synth.performer.synthesize`): {settings.seconds:g} s "
        f"at {settings.rate_hz:g} Hz, noise {settings.noise_mm:g} mm, seed "
        f"{settings.seed}, wearing each rig's marker set; calibrated on frames "
        f"0-{settings.calibrate_frames - 1} (the T-pose hold); solved with "
        "`make_body_solver(method, rig, cal, labels, joint_limits=JOINT_LIMITS_DEG, "
        f"segment_kind=SEGMENT_KIND)`. `{ROM_METHOD}` (rigs with a `[functional]` "
        "table): the fit on a calibration that adds the same performer's range of "
        f"motion (`synth --motions rom`, {ROM_SECONDS:g} s after its hold; "
        "`calibrate --rom`, issue 29)."
        + (" Unobserved axes added by `--unobserved`." if settings.unobserved
           else ""),
        "",
    ]  # fmt: skip
    if truth:
        lines += _truth_section(truth, settings)
    if damaged:
        lines += _damage_section(damaged, settings)
    return "\n".join(lines).rstrip() + "\n"


# --- command line -----------------------------------------------------------------


def _names(text: str, known: Iterable[str], what: str) -> tuple[str, ...]:
    known = tuple(known)
    names = tuple(n for n in text.split(",") if n)
    bad = [n for n in names if n not in known]
    if bad or not names:
        raise SystemExit(f"--{what}: choose from {', '.join(known)}; got {text!r}")
    return names


def _numbers(text: str, kind: Callable[[str], Any], what: str) -> tuple[Any, ...]:
    try:
        values = tuple(kind(v) for v in text.split(",") if v)
    except ValueError:
        raise SystemExit(f"--{what}: comma-separated numbers; got {text!r}") from None
    return values


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, help="write the markdown here (else stdout)")
    ap.add_argument("--rigs", default=",".join(RIGS))
    ap.add_argument("--motions", default=",".join(MOTION_SETS),
                    help="motion sets: default and activity names")  # fmt: skip
    ap.add_argument("--methods", default=",".join((*METHODS, ROM_METHOD)),
                    help=f"{', '.join(METHODS)}, {ROM_METHOD}")  # fmt: skip
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--rate-hz", type=float, default=120.0)
    ap.add_argument("--noise-mm", type=float, default=0.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--calibrate-frames", type=int, default=120)
    ap.add_argument("--no-damage", action="store_true")
    ap.add_argument("--damage-at-s", type=float, default=4.0)
    ap.add_argument("--hide-s", default="0.25,1", help="hide windows, seconds")
    ap.add_argument("--bursts", default="1,2,10,50", help="burst lengths, frames")
    ap.add_argument("--burst-kinds", default=",".join(BURST_KINDS))
    ap.add_argument("--recovery-tol-deg", type=float, default=2.0)
    ap.add_argument("--recovery-tol-mm", type=float, default=10.0)
    ap.add_argument(
        "--unobserved", type=Path, help="JSON {rig: {bone: [[x, y, z], ...]}}"
    )
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 1)
    args = ap.parse_args(argv)

    rigs = _names(args.rigs, RIGS, "rigs")
    motion_sets = _names(args.motions, MOTION_SETS, "motions")
    methods = _names(args.methods, (*METHODS, ROM_METHOD), "methods")
    kinds = _names(args.burst_kinds, BURST_KINDS, "burst-kinds")
    hides = _numbers(args.hide_s, float, "hide-s")
    bursts = _numbers(args.bursts, int, "bursts")
    n_frames = round(args.seconds * args.rate_hz)
    hold = round(1.0 * args.rate_hz)  # synthesize's base_pose_s default: 1 s
    if not 0 < args.calibrate_frames <= min(hold, n_frames):
        raise SystemExit(f"--calibrate-frames must be in [1, {min(hold, n_frames)}]")
    start = round(args.damage_at_s * args.rate_hz)
    longest = max([round(h * args.rate_hz) for h in hides] + list(bursts) + [1])
    if not args.no_damage and not (
        args.calibrate_frames <= start and start + longest < n_frames
    ):
        raise SystemExit(
            f"--damage-at-s {args.damage_at_s:g}: damage must start after the "
            f"calibration and end ({longest} frames) before the take's end "
            f"({n_frames} frames)"
        )
    settings = Settings(
        seconds=args.seconds,
        rate_hz=args.rate_hz,
        noise_mm=args.noise_mm,
        seed=args.seed,
        calibrate_frames=args.calibrate_frames,
        damage_at_s=args.damage_at_s,
        recovery_tol_deg=args.recovery_tol_deg,
        recovery_tol_mm=args.recovery_tol_mm,
        unobserved=args.unobserved.read_text() if args.unobserved else "",
    )
    functional = {r for r in rigs if load_rig(r).functional}
    tasks: list[Any] = [
        TruthCase(r, m, meth)
        for r in rigs
        for m in motion_sets
        for meth in methods
        if meth != ROM_METHOD or r in functional
    ]
    n_truth = len(tasks)
    if not args.no_damage:
        for r in rigs:
            for meth in methods:
                if meth == ROM_METHOD:
                    continue
                tasks += [
                    DamageCase(r, meth, "hide", (round(h * args.rate_hz),))
                    for h in hides
                ]
                tasks += [DamageCase(r, meth, k, tuple(bursts)) for k in kinds]
    t0 = time.perf_counter()
    print(
        f"{len(tasks)} tasks on {args.jobs} process(es); load "
        f"{os.getloadavg()[0]:.2f} (1 min)",
        flush=True,
    )
    work = [(case, settings) for case in tasks]
    if args.jobs <= 1:
        results = [_run(t) for t in work]
    else:
        with ProcessPoolExecutor(args.jobs, mp_context=get_context("spawn")) as pool:
            results = list(pool.map(_run, work))
    truth_rows: list[TruthRow] = results[:n_truth]
    damage_rows = [row for batch in results[n_truth:] for row in batch]
    text = _document(argv, settings, truth_rows, damage_rows)
    if args.out:
        args.out.write_text(text)
    else:
        print(text)
    print(
        f"done in {time.perf_counter() - t0:.1f} s; load {os.getloadavg()[0]:.2f} "
        f"(1 min){'; wrote ' + str(args.out) if args.out else ''}",
        flush=True,
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
