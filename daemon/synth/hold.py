"""A hidden marker's damage judged against the truth's own motion in what it alone saw.

Issue 28 item 6: "where a rotation is not observed, off by no more than the truth's own
excursion in it from the prior". While one marker is hidden, the rotations that it
alone resolved are not observed: the fit holds them at their last seen value
(``fit_track.hold_priors``), as a Kalman filter or a commercial solver does, and the
best any solve can then be is off by as much as the truth turned in them since. This
module says which rotations those are and how far the truth turned in them.

**Which rotations are held** (:func:`held_directions`): the fit's own decision, read
from the same tables and threshold as ``fit_track.hold_priors`` uses, at the last
frame before the hide (``t0``). With ``sigma = max(noise_m, residual level at t0) /
resolution`` (``FitParams``; the level is ``FitSolve.residual_level[t0]``), for the
hidden rig marker ``k`` and each bone ``b``, each direction ``u`` of the
``fit_observe.hidden_information`` row ``k B + b`` with information ``lam < sigma^2``
that the marker gave (``lost > 0``) a hold of at least 1 % of ``sigma^2`` is held;
the straight and the bent table are read with the kernel's shares (the bend of the
marker's hinge, ``fit_observe.marker_hinges``, at ``t0``: ``sin(bend) /
sin(hold_straight)``, at most 1). The tables hold only the hidden marker's bone and
its ancestors (the bones whose rotations move it). The kernel's local floor
(``fit_track.local_floor``) adds nothing for one marker hidden: it holds a bone only
while two or more hidden markers ride it or hang below it. Nor is the share of a
``hinge_twist``'s held twist that the kernel passes to the joint's parent
(``fit_track.twist_to_parent``) counted: the parent's allowance stays its own
table's (a stricter figure: the parent's turn about that axis counts against it).
A ``hinge_twist`` below the bones the marker rides, whose parent's own markers left
resolve the parent's turn about its twist axis or whose parent the marker does not
ride, has its twist taken off the hold by the kernel (the marker never moved with
it); a held direction of such a bone with any twist in it is left out here whole
(the kernel holds what is left of it off the twist: a stricter figure, which never
counts a hinge's flexion excursion as held).
The directions are unit vectors in each bone's own axes.

**The truth's excursion in them** (:func:`hold_excursion_deg`): the hold pulls the
fit's joint towards its anchor in swing-twist coordinates of the bone's axes
(``fit_terms.prior_chart``: swing about x, twist about +Y, swing about z). The truth's
joint, its segment relative to the carrier segment (``truth.truth_map``), turned since
``t0`` and expressed in the bone's axes (the bone's rotation in its segment as at
frame 0, the calibration pose, as ``truth``'s excursion reads them), is put in the
same coordinates ``c(t)``; its excursion in the held directions ``U`` of that
bone is ``|P_U c(t)|`` (the length of ``c``'s projection onto their span, radians,
here degrees). A bone's allowance is the sum of that over itself and its ancestors
(the bones whose held rotations move it: the triangle inequality bounds the world
error of several holds by their sum). Held bones with no truth segment add nothing
(their truth is unknown; their rotation shows up in their mapped child's carrier).

**The figure** (:func:`hide_truth_excess`): per compared bone and frame, the angle
between the damaged solve's rotation change since ``t0`` and its truth segment's
(``truth.rotation_change_error_deg`` with the reference at ``t0``: the standing error
the solve already had at ``t0`` is not the hide's), less the same for the intact
take's solve (what the rig and solve get wrong with every marker seen is not the
hide's either), less the allowance; its maximum per bone over the hidden frames and a
tail after them (:data:`TAIL_S`, in which the allowance is the last hidden frame's;
after it, none), degrees. A solve that holds exactly what the marker alone saw is
within it (``|e_i + h| <= |e_i| + |h|``: the intact solve's error ``e_i`` and a hold's
``h``, no bigger than the truth's excursion in the held rotations, to first order);
one that turns a bone further, a runaway, is not.

**What it does not tell.** "Held" is the kernel's rule: a prior of at most ``sigma^2``
against what the markers still seen give (``lam``, under ``sigma^2``). Where ``lam`` is
close to the threshold the fit still follows the remaining markers in that direction,
and the allowance there is the truth's whole excursion all the same: generous. On the
synthetic performer's default motions (10 s, seed 0, each marker hidden 1 s from 4 s,
residual level 7.2 mm, so ``sigma^2`` is a lever of 82 mm/rad), Plug-in Gait's LKNE
hidden: the damaged solve's lower leg turned 49.3 deg in the directions called held,
as the intact solve's did; LFIN hidden: the forearm 4.7 deg, the intact's 30.4 (a real
hold). A bone within its allowance is therefore no proof that the fit held it; one
past it is a runaway.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.fit_model import FitModel
from retargetd.daemon.body.rig import Rig
from retargetd.daemon.body.solve import BodySolve
from retargetd.daemon.body.solve_fit import FitParams
from retargetd.daemon.synth.performer import SynthTake
from retargetd.daemon.synth.truth import rotation_change_error_deg, truth_map
from retargetd.protocols.frames import F64Array

__all__ = [
    "TAIL_S",
    "HideTruth",
    "chart",
    "held_directions",
    "hide_truth_excess",
    "hold_excursion_deg",
]

#: Seconds after a hide in which its error is still judged against the truth's
#: excursion at the hide's last frame: issue 28 item 3's recovery time (a solve
#: returns to the answer within 0.25 s), so a hold may take as long to let go.
TAIL_S = 0.25
#: A hold under this share of the threshold is not made (``fit_track.hold_priors``).
_MIN_SHARE = 0.01


def chart(q: F64Array) -> F64Array:
    """Swing-twist coordinates of rotations ``q`` (..., 4) (w, x, y, z) in their own
    axes: (swing about x, twist about +Y, swing about z), radians, as
    ``fit_terms.prior_chart`` (the hold prior's coordinates).

    Returns:
        (..., 3) float64.
    """
    q = np.asarray(q, dtype=np.float64)
    q = np.where(q[..., :1] < 0.0, -q, q)
    w, y = q[..., 0], q[..., 2]
    tw = 2.0 * np.arctan2(y, w)
    h = 0.5 * tw
    untwist = np.stack(
        [np.cos(h), np.zeros_like(h), -np.sin(h), np.zeros_like(h)], axis=-1
    )
    swing = rot.rotvec_from_quat(rot.quat_mul(q, untwist))
    return np.stack([swing[..., 0], tw, swing[..., 2]], axis=-1)


def held_directions(
    model: FitModel,
    params: FitParams,
    marker: int,
    pfb_t0: F64Array,
    level_m: float,
) -> dict[int, F64Array]:
    """The rotations the fit holds while rig marker ``marker`` alone is hidden (the
    module docstring: ``fit_track.hold_priors``; its local floor needs two hidden).

    Args:
        model: the fit's model (``FitSolver.model``).
        params: the fit's parameters (``FitSolver.params``).
        marker: the hidden rig marker (``model.marker_names`` index).
        pfb_t0: (B, 4) float64 (w, x, y, z), each joint's ``parent_from_bone`` at the
            last frame before the hide.
        level_m: the take's running residual level there, metres.

    Returns:
        Bone index -> (n, 3) unit directions in its axes (bones with none left out).
    """
    n_b = len(model.bone_names)
    wt = model.marker_weight
    if wt[marker] <= 0.0:
        return {}
    sig = max(params.noise_m, level_m) / math.radians(params.resolution_deg)
    thr = sig * sig
    found: dict[int, list[F64Array]] = {}
    # the two tables, shared by the bend of the marker's hinge
    hinge = int(model.hide_hinge[marker])
    bent = 0.0
    if hinge >= 0:
        y_of = rot.quat_rotate(pfb_t0[hinge], np.array([0.0, 1.0, 0.0]))
        cos = float(y_of[1])
        bent = min(1.0, math.sqrt(max(0.0, 1.0 - cos * cos))
                   / math.sin(math.radians(params.hold_straight_deg)))  # fmt: skip
    n_tab = len(wt) * n_b
    # the bones the marker rides (its own and its ancestors): a hinge_twist below
    # them has its twist taken off the hold (fit_track.hold_priors)
    rides = set()
    kb = int(model.marker_bone[marker])
    while kb >= 0:
        rides.add(kb)
        kb = int(model.bone_parent[kb])
    for half, share in enumerate((1.0 - bent, bent)):
        if share <= 0.0:
            continue
        for b in range(n_b):
            row = marker * n_b + b + half * n_tab
            for j in range(3):
                lost, lam = model.hide_lost[row, j], model.hide_lam[row, j]
                if lost <= 0.0 or lam >= thr:
                    continue
                if share * min(lost, thr - lam) < _MIN_SHARE * thr:
                    continue
                u = np.array(model.hide_axes[row, 3 * j : 3 * j + 3], dtype=np.float64)
                if (
                    model.twist_lock[b] == 2.0
                    and b not in rides
                    and (
                        int(model.bone_parent[b]) not in rides
                        or _parent_turn_info(model, marker, b, pfb_t0[b]) >= thr
                    )
                    and abs(float(u @ model.twist_axis[b])) > 0.0
                ):
                    continue
                found.setdefault(b, []).append(u)
    return {b: np.asarray(v, dtype=np.float64) for b, v in found.items()}


def _parent_turn_info(model: FitModel, hidden: int, b: int, pfb_b: F64Array) -> float:
    """What the markers on bone ``b``'s parent, all but ``hidden`` seen, tell of the
    parent's turn about ``b``'s twist axis through its hinge (m^2 / rad^2, every
    other joint fixed; ``fit_track.parent_turn_info``)."""
    p = int(model.bone_parent[b])
    a = rot.quat_rotate(pfb_b, model.twist_axis[b])
    info = 0.0
    for i in np.flatnonzero(model.marker_bone == p):
        if i == hidden or model.marker_weight[i] <= 0.0:
            continue
        c = np.cross(a, model.marker_local[i] - model.off_parent[b])
        info += float(model.marker_weight[i] * (c @ c))
    return info


def _span(directions: F64Array) -> F64Array:
    """(r, 3) an orthonormal basis of the directions' span."""
    _, s, vt = np.linalg.svd(np.asarray(directions).reshape(-1, 3))
    return np.asarray(vt[: int((s > 1e-6 * max(s[0], 1e-300)).sum())])


def hold_excursion_deg(
    take: SynthTake,
    rig: Rig,
    solve: BodySolve,
    held: dict[int, F64Array],
    t0: int,
) -> F64Array:
    """Per compared bone (``truth_map(rig, ...)`` order) and frame, the truth's
    excursion since ``t0`` in the held rotations of itself and its ancestors
    (module docstring), degrees.

    Args:
        take: the synthetic take (its truth).
        rig: the rig solved.
        solve: a solve of it (its bones at frame 0, the calibration pose, give each
            bone's axes in its segment).
        held: rig bone index -> (n, 3) unit directions in its axes.
        t0: the last frame before the hide.

    Returns:
        (T, K) float64 degrees.
    """
    tmap = truth_map(rig, take.segment_names)
    wfs = np.asarray(take.world_from_segment_quat, dtype=np.float64)
    wfb = np.asarray(solve.world_from_bone_quat, dtype=np.float64)
    own = np.zeros((wfs.shape[0], len(rig.bones)))
    for b, dirs in held.items():
        hits = np.flatnonzero(tmap.bones == b)
        if hits.size == 0 or len(dirs) == 0:
            continue  # no truth segment: unknown
        k = int(hits[0])
        seg, carrier = tmap.segments[k], tmap.carriers[k]
        s = wfs[:, seg]
        rel = s if carrier < 0 else rot.quat_mul(rot.quat_conj(wfs[:, carrier]), s)
        change = rot.quat_mul(rot.quat_conj(rel[t0]), rel)  # segment axes at t0
        # the bone's axes in its segment's, as calibrated (frame 0): a standing
        # error of the solve at t0 does not turn the axes the truth is read in
        seg_from_bone = rot.quat_mul(rot.quat_conj(s[0]), wfb[0, b])
        in_bone = rot.quat_mul(
            rot.quat_mul(rot.quat_conj(seg_from_bone), change), seg_from_bone
        )
        c = chart(in_bone)  # (T, 3)
        basis = _span(dirs)
        own[:, b] = np.degrees(np.linalg.norm(c @ basis.T, axis=-1))
    return np.stack([own[:, list(chain)].sum(axis=1) for chain in tmap.ancestors], 1)


@dataclass(frozen=True, slots=True, kw_only=True)
class HideTruth:
    """A hidden marker's damaged solve against the truth, less the truth's
    excursion in what the fit held (module docstring).

    Attributes:
        bone_names: (K,) the compared bones.
        error_deg: (K,) the damaged solve's error since ``t0`` at the frame of the
            largest excess.
        intact_deg: (K,) the intact solve's there.
        allowance_deg: (K,) the allowance there.
        excess_deg: (K,) the largest ``error - intact - allowance`` over the judged
            frames.
        held_bones: the rig bones the fit holds (with a truth segment or not).
    """

    bone_names: tuple[str, ...]
    error_deg: F64Array
    intact_deg: F64Array
    allowance_deg: F64Array
    excess_deg: F64Array
    held_bones: tuple[str, ...]

    @property
    def worst(self) -> int:
        """The bone with the largest excess."""
        return int(np.argmax(self.excess_deg)) if self.excess_deg.size else 0


def hide_truth_excess(
    take: SynthTake,
    rig: Rig,
    intact: BodySolve,
    damaged: BodySolve,
    held: dict[int, F64Array],
    window: slice,
    rate_hz: float,
) -> HideTruth:
    """The figure of the module docstring for one hidden marker.

    Args:
        take: the synthetic take (its truth).
        rig: the rig solved.
        intact: the intact take's solve (same rig, calibration, method).
        damaged: the solve of the take with the marker hidden over ``window``.
        held: :func:`held_directions`'s answer for that marker.
        window: the hidden frames (contiguous, starting after frame 0).
        rate_hz: frame rate (the tail, :data:`TAIL_S`).

    Returns:
        The :class:`HideTruth`.
    """
    n = take.n_frames
    span = range(*window.indices(n))
    if len(span) == 0 or span.start < 1:
        raise ValueError(f"window must be non-empty and start after frame 0: {window}")
    t0 = span.start - 1
    stop = min(n, span.stop + round(TAIL_S * rate_hz))
    tmap = truth_map(rig, take.segment_names)
    wfs = np.asarray(take.world_from_segment_quat, dtype=np.float64)[:, tmap.segments]
    frames = slice(span.start, stop)

    def error(solve: BodySolve) -> F64Array:
        wfb = np.asarray(solve.world_from_bone_quat, dtype=np.float64)
        if wfb.shape[0] != n:
            raise ValueError(f"a solve has {wfb.shape[0]} frames, the take {n}")
        return rotation_change_error_deg(wfb[:, tmap.bones], wfs, t0)[frames]

    err, base = error(damaged), error(intact)
    allow = hold_excursion_deg(take, rig, damaged, held, t0)
    allow[span.stop : stop] = allow[span.stop - 1]  # the tail: the last hidden frame's
    allow = allow[frames]
    excess = err - base - allow
    at = np.argmax(excess, axis=0)
    cols = np.arange(excess.shape[1])
    return HideTruth(
        bone_names=tmap.bone_names,
        error_deg=err[at, cols],
        intact_deg=base[at, cols],
        allowance_deg=allow[at, cols],
        excess_deg=excess[at, cols],
        held_bones=tuple(rig.bones[b].name for b in sorted(held)),
    )
