"""Re-seated markers absorbed: each marker's place on its bone re-estimated from a
take (issue 29 item 3; ``calibrate --refine-layout TAKE``, ``solve --refine-layout``).

A calibration fixes where each marker sits on its bone from the base pose. A wand
re-seated or a marker re-stuck between the static and the take sits elsewhere on its
bone for the whole take; the fit then turns the bones to bring it as close as the other
markers allow, and the match check (``body.match``) names the segment. This module
re-places such markers and keeps the joint model: bone lengths, joint centres and axes,
rest orientations and the derived points stay the calibration's; only where each marker
sits on its bone moves.

Method: rounds of the fit and a re-placement (a block-coordinate descent on the same
least squares a bundle adjustment solves jointly). Each round solves the take with the
fit on the current layout and takes, for every marker, its offset from the model's
prediction in its bone's frame, ``R_b(t)^T (x_i(t) - o_b(t)) - l_i``, over the frames
where it is seen and the fit explained the frame (``FitSolve.unexplained`` and
``unseen`` out; a marker the gate rejected is kept: it is the one that moved). The
per-axis median of those offsets (robust to a transient, a mislabel, a gated burst)
is the marker's move this round. One marker per bone at most is re-placed: the one
with the largest move on its bone, when that move is past what noise and skin motion
explain (the match check's bound, ``body.match.marker_bound_mm``: 7.1 mm on a limb,
19.7 mm on the trunk): a moved marker pulls its bone's pose a little towards itself,
so in the first round its neighbours show offsets of their own that are the bone's
error, not theirs; re-placing the worst one first and solving again lets the bone
come back before its neighbours are judged. A marker once re-placed follows its
offset every round (the bone's pull on it shrinks each round) until it settles
(:data:`SETTLED_MM`). The other markers stay where the static put them and anchor
the bones: with more of a bone's markers free, the layout follows the pose the fit's
priors prefer round after round instead of settling (re-placing every marker past
2 mm turned subject01's torso 5 deg in 40 rounds; re-placing both markers of the
btkdata walk's wrist bar let them drift round the forearm for 40 rounds). A marker
still past its bound on a bone that already has one re-placed is named, not moved.
Rounds stop when nothing moves or after :data:`MAX_ROUNDS`.

What the take cannot tell apart: a marker whose place trades with its bone's rotation
(the one marker that turns a forearm about its axis: the wrist bar's) settles slowly,
each round moving it by nearly what the last did (the btkdata walk's LWRA: 17, 3.9,
1.9, 1.5, 1.3 ... mm, shrinking 6 % a round, 34 mm after 40 rounds, where the thigh
wand beside it settled in 7). Its place is then the fit's priors' choice, not the
take's. So when the rounds run out, a marker still moving whose remaining move (the
geometric tail of its last two rounds, Aitken's extrapolation) is past the noise
bound goes back to the static's place and is named, and the others settle again
without it. Likewise all of a bone's markers moved by one rigid motion is, to the
markers, the bone turned about its joint: one marker per bone is re-placed.

Thresholds:

- the bound a marker must move past: the match check's (module docstring of
  ``body.match``: 2 mm noise, Merriaux et al. 2017, plus the thigh cluster's 5.1 mm
  non-rigid artefact, Andersen et al. 2012; the trunk's 9.3 + 2 x 4.2 mm, Zemp et al.
  2014): a marker that has moved less is not told apart from its skin's motion;
- :data:`FRAMES_MIN` 25: the per-axis median of n samples of noise sigma has a
  standard error of about 1.25 sigma / sqrt(n) (the median's asymptotic efficiency,
  pi / 2 of the mean's variance); at the 2 mm bound, 25 frames place a marker to
  0.5 mm, a quarter of the noise bound. A marker seen in fewer explained frames
  keeps its place and is named.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.calibration import (
    Calibration,
    bone_world_quats,
    compute_points,
)
from retargetd.daemon.body.fit_model import FitModel
from retargetd.daemon.body.match import NOISE_MM, marker_bound_mm
from retargetd.daemon.body.method import make_body_solver
from retargetd.daemon.body.rig import Rig
from retargetd.daemon.body.solve_fit import FitSolve, FitSolver
from retargetd.protocols.frames import F64Array

#: Explained frames a marker must be seen in to be re-placed (module docstring).
FRAMES_MIN = 25
#: A re-placed marker settles when a round would move it less than this, mm (a
#: twentieth of the noise bound, ``body.match.NOISE_MM``).
SETTLED_MM = 0.1
#: Rounds of solve and re-placement at most, before the markers still moving are
#: judged by their tail (:func:`_tail_m`); twice, the second time without those put
#: back. A marker whose moves halve each round settles from 20 mm to
#: :data:`SETTLED_MM` in 8.
MAX_ROUNDS = 12


@dataclass(frozen=True, slots=True, kw_only=True)
class RefinedLayout:
    """What :func:`refine_layout` did.

    Attributes:
        calibration: the calibration with the refined layout (``layout_marker_pos``,
            ``layout_refined``, its segments' layouts re-placed).
        moved_mm: rig marker -> how far its place moved from the calibration's, mm
            (0 for a marker left where it was).
        frames: rig marker -> explained frames it was seen in.
        too_few: rig markers seen in fewer than :data:`FRAMES_MIN` explained frames.
        kept_off: rig markers still past their bound after the refinement, kept
            because another marker of their bone was re-placed (one per bone).
        undetermined: rig markers re-placed that did not settle in
            :data:`MAX_ROUNDS` (their place trades with their bone's rotation:
            the take does not place them), put back where the static had them.
        rounds: fit-and-re-place rounds run.
        rms_before_mm / rms_after_mm: median over the take of the fit's per-frame
            marker residual RMS with the calibration's layout and the refined one.
    """

    calibration: Calibration
    moved_mm: dict[str, float]
    frames: dict[str, int]
    too_few: tuple[str, ...]
    kept_off: tuple[str, ...]
    undetermined: tuple[str, ...]
    rounds: int
    rms_before_mm: float
    rms_after_mm: float

    def summary(self) -> str:
        """One line: residuals and the markers re-placed, furthest first."""
        moved = sorted(
            ((d, m) for m, d in self.moved_mm.items() if d > 0.0), reverse=True
        )
        text = (
            f"layout refined in {self.rounds} rounds: marker residual median "
            f"{self.rms_before_mm:.2f} -> {self.rms_after_mm:.2f} mm; "
        )
        if moved:
            text += "moved (mm): " + ", ".join(f"{m} {d:.1f}" for d, m in moved)
        else:
            text += "no marker moved past what noise and skin motion explain"
        if self.kept_off:
            text += "; still off, kept (one marker per bone is re-placed): " + " ".join(
                self.kept_off
            )
        if self.undetermined:
            text += (
                "; not placed by the take (its place trades with its bone's "
                "rotation), kept: " + " ".join(self.undetermined)
            )
        if self.too_few:
            text += (
                f"; kept (seen in fewer than {FRAMES_MIN} explained frames): "
                + " ".join(self.too_few)
            )
        return text


def bone_origins(solver: FitSolver, solved: FitSolve) -> F64Array:
    """(T, B, 3) metres, world: each bone's origin in each solved frame, from the
    chain (a child's origin rides its parent); a root other than bone 0 from a joint
    centre it carries, NaN when it carries none."""
    model = solver.model
    wfb = solved.world_from_bone_quat
    n, n_b = wfb.shape[:2]
    out = np.full((n, n_b, 3), np.nan)
    for b in range(n_b):
        p = int(model.bone_parent[b])
        if p >= 0:
            out[:, b] = out[:, p] + rot.quat_rotate(
                wfb[:, p], np.broadcast_to(model.off_parent[b], (n, 3))
            )
        elif b == 0:
            out[:, b] = solved.root_pos
        else:
            carried = np.flatnonzero(np.asarray(model.joint_bone) == b)
            if carried.size:
                j = int(carried[0])
                out[:, b] = solved.joint_centres[:, j] - rot.quat_rotate(
                    wfb[:, b], np.broadcast_to(model.joint_local[j], (n, 3))
                )
    return out


def _offsets(
    solver: FitSolver, solved: FitSolve, positions: F64Array
) -> tuple[F64Array, np.ndarray]:
    """Each rig marker's median offset from its model place in its bone frame (Mr, 3)
    metres (NaN where it has no usable frame), and the frames used per marker."""
    model = solver.model
    origins = bone_origins(solver, solved)
    ok_frame = ~(solved.unexplained | solved.unseen)
    n_m = len(model.marker_names)
    offset = np.full((n_m, 3), np.nan)
    used = np.zeros(n_m, dtype=np.int64)
    for i in range(n_m):
        col = int(solver.marker_cols[i])
        if col < 0 or model.marker_weight[i] <= 0.0:
            continue
        b = int(model.marker_bone[i])
        x = positions[:, col]
        rows = ok_frame & np.isfinite(x).all(axis=1) & np.isfinite(origins[:, b]).all(1)
        used[i] = int(rows.sum())
        if used[i] == 0:
            continue
        local = rot.quat_rotate(
            rot.quat_conj(solved.world_from_bone_quat[rows, b]),
            x[rows] - origins[rows, b],
        )
        offset[i] = np.median(local - model.marker_local[i], axis=0)
    return offset, used


def refine_layout(
    rig: Rig,
    calibration: Calibration,
    positions: F64Array,
    labels: Sequence[str],
    *,
    source: Mapping[str, Any],
    rate_hz: float = 120.0,
    joint_limits: Mapping[str, Any] | None = None,
    segment_kind: Mapping[str, str] | None = None,
) -> RefinedLayout:
    """Re-place each marker on its bone from a take's frames (module docstring).

    Args:
        rig, calibration: the rig and the calibration to refine.
        positions: (T, M, 3) float64, metres, world: the take's frames.
        labels: (M,) their labels.
        source: recorded in the result (``{"take": ..., "frames": "a:b"}``).
        rate_hz: the take's frame rate (the fit's continuity prior).
        joint_limits, segment_kind: the fit's joint-limit table (as ``solve``'s).

    Returns:
        The refined calibration and what moved.
    """
    positions = np.ascontiguousarray(positions, dtype=np.float64)

    def solve(cal: Calibration) -> tuple[FitSolver, FitSolve]:
        solver = make_body_solver(
            "fit", rig, cal, labels, joint_limits=joint_limits,
            segment_kind=segment_kind, rate_hz=rate_hz,
        )  # fmt: skip
        assert isinstance(solver, FitSolver)
        return solver, solver.solve_take(positions)

    def rms_mm(solved: FitSolve) -> float:
        ok = ~(solved.unexplained | solved.unseen) & np.isfinite(solved.marker_rms)
        return 1e3 * float(np.median(solved.marker_rms[ok])) if ok.any() else math.nan

    solver, solved = solve(calibration)
    before = rms_mm(solved)
    model0 = solver.model
    bones = np.asarray(model0.marker_bone)
    base = np.asarray(model0.marker_local)
    local = np.array(base, dtype=np.float64)
    bound_m = 1e-3 * np.asarray([marker_bound_mm(rig.bone_names[b]) for b in bones])
    re_placed = np.zeros(len(local), dtype=bool)
    undetermined = np.zeros(len(local), dtype=bool)
    steps: list[list[float]] = [[] for _ in local]
    frames = np.zeros(len(local), dtype=np.int64)
    rounds = 0
    for phase in range(2):
        for _ in range(MAX_ROUNDS):
            offset, used = _offsets(solver, solved, positions)
            if rounds == 0:
                frames = used
            dist = np.linalg.norm(offset, axis=1)
            dist[(used < FRAMES_MIN) | ~np.isfinite(dist)] = 0.0
            move = re_placed & (dist >= 1e-3 * SETTLED_MM)
            for b in np.unique(bones):
                on = np.flatnonzero((bones == b) & ~undetermined)
                if on.size == 0 or re_placed[bones == b].any():
                    continue
                worst = int(on[np.argmax(dist[on])])
                move[worst] = dist[worst] >= bound_m[worst]
            if not move.any():
                break
            rounds += 1
            re_placed |= move
            for i in np.flatnonzero(move):
                steps[i].append(float(dist[i]))
            local[move] += offset[move]
            solver, solved = solve(_with_layout(rig, calibration, model0, local))
        else:
            # Rounds ran out: a marker still moving whose geometric tail (Aitken)
            # is past the noise bound is one the take does not place: back to the
            # static's place, and the rest settle again without it.
            stuck = [
                i for i in np.flatnonzero(move)
                if _tail_m(steps[i]) > 1e-3 * NOISE_MM
            ]  # fmt: skip
            if stuck:
                local[stuck] = base[stuck]
                re_placed[stuck] = False
                undetermined[stuck] = True
                solver, solved = solve(_with_layout(rig, calibration, model0, local))
                if phase == 0:
                    continue
        break
    moved = 1e3 * np.linalg.norm(local - base, axis=1)
    offset, _ = _offsets(solver, solved, positions)
    off_mm = 1e3 * np.linalg.norm(offset, axis=1)
    kept = tuple(
        m
        for i, m in enumerate(rig.marker_names)
        if not re_placed[i] and not undetermined[i] and frames[i] >= FRAMES_MIN
        and off_mm[i] >= 1e3 * bound_m[i]
    )  # fmt: skip
    unplaced = tuple(m for i, m in enumerate(rig.marker_names) if undetermined[i])
    too_few = tuple(
        m
        for i, m in enumerate(rig.marker_names)
        if model0.marker_weight[i] > 0.0 and int(solver.marker_cols[i]) >= 0
        and frames[i] < FRAMES_MIN
    )  # fmt: skip
    record = {
        "source": dict(source),
        "rounds": rounds,
        "rms_before_mm": round(before, 3),
        "rms_after_mm": round(rms_mm(solved), 3),
        "kept_off": list(kept),
        "undetermined": list(unplaced),
        "markers": {
            m: {"moved_mm": round(float(moved[i]), 2), "frames": int(frames[i])}
            for i, m in enumerate(rig.marker_names)
        },
    }
    cal = replace(_with_layout(rig, calibration, model0, local), layout_refined=record)
    return RefinedLayout(
        calibration=cal,
        moved_mm={m: float(moved[i]) for i, m in enumerate(rig.marker_names)},
        frames={m: int(frames[i]) for i, m in enumerate(rig.marker_names)},
        too_few=too_few,
        kept_off=kept,
        undetermined=unplaced,
        rounds=rounds,
        rms_before_mm=before,
        rms_after_mm=rms_mm(solved),
    )


def _tail_m(steps: Sequence[float]) -> float:
    """What a marker still has to move, metres, from its last two rounds' moves as a
    geometric series (Aitken's extrapolation): ``d r / (1 - r)`` with ``r`` the
    last ratio; inf when its moves do not shrink; 0 once it settled."""
    if not steps or steps[-1] < 1e-3 * SETTLED_MM:
        return 0.0
    if len(steps) < 2:
        return math.inf
    r = steps[-1] / steps[-2]
    return math.inf if r >= 1.0 else steps[-1] * r / (1.0 - r)


def _with_layout(
    rig: Rig, calibration: Calibration, model: FitModel, local: F64Array
) -> Calibration:
    """``calibration`` with each marker placed at ``local`` on its bone, carried into
    the base pose by the bone frames ``model`` (``calibration``'s own) attached it
    in; the segments' layouts (the match check's and the construction's occlusion
    fill) follow."""
    base = calibration.base_marker_pos
    assert base is not None and calibration.rest_bone_origin_pos is not None
    old_local = np.asarray(model.marker_local)
    bones = np.asarray(model.marker_bone)
    # The model's local places are in the bone frames the base pose's mean markers
    # build (``fit_model.build_fit_model``), not the calibration's rest frames (the
    # mean of each frame's: up to 0.1 deg apart on the real statics): a change of
    # place turns into the base pose through those same frames, so the model built
    # from the result holds exactly ``local``.
    frames = bone_world_quats(
        rig, compute_points(rig, base[None], calibration.point_offsets)
    )[0]
    delta = rot.quat_rotate(frames[bones], local - old_local)
    place = np.array(
        base if calibration.layout_marker_pos is None else calibration.layout_marker_pos
    )
    ok = np.asarray(np.isfinite(place).all(axis=1), dtype=bool)
    place[ok] += delta[ok]
    index = {m: i for i, m in enumerate(rig.marker_names)}
    layouts = {
        seg: (names, np.asarray([place[index[n]] for n in names], dtype=np.float64))
        if all(n in index and ok[index[n]] for n in names)
        else (names, layout)
        for seg, (names, layout) in calibration.segment_layouts.items()
    }
    return replace(calibration, layout_marker_pos=place, segment_layouts=layouts)
