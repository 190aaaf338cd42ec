"""Per-frame physical checks of a solved take against its MuJoCo model.

Convention (what ``qpos`` is). Body ``b``'s frame in its parent body's frame is
``rest_pfb_b = conj(rest_wfb_p) * rest_wfb_b`` (``validate_model``), and a ball joint
rotates the body in its own frame, so the model poses

    wfb_b = wfb_p * rest_pfb_b * q_b  =>  q_b = conj(rest_pfb_b) * conj(wfb_p) * wfb_b,

which is exactly the streamed ``rest_from_bone_quat`` (README "Solve output": the
parent-relative rotation composed with the inverse of its calibrated value, in the
bone's own axes). The root's free joint takes ``root_pos`` and the root's
``world_from_bone_quat`` (w x y z). The check poses the model from the parent-relative
chain and compares its body origins and aim sites with the skeleton posed directly from
each bone's streamed ``world_from_bone_quat`` and the calibrated offsets
(:func:`pose_skeleton`): any disagreement between the two streamed rotation sets, a
component order or a model/stream length mismatch shows up as distance.

Checks (thresholds: :data:`THRESHOLDS`; how they were set: ``validate_limits`` and the
report header): convention, fit (posed skeleton vs solved joint centres), quaternion
norms, anatomical limits (swing/twist about each bone's +Y, :mod:`validate_limits`),
self-penetration, floor penetration, floating (no foot support for longer than a jump's
flight; support = a foot near the floor or stationary at any height, inferred by
:mod:`validate_dynamics`), impossible speeds of the root and the end effectors, and
offline the ghost force (:mod:`validate_dynamics`: the inverse-dynamics root wrench the
inferred foot contacts cannot explain, in body weights). A solve that carries marker
residuals (the fit) also gets the marker residual checks (:mod:`validate.residual`):
for the fit, whose joint centres are its rigid skeleton's own, "fit" reads ~1e-12 mm
and measures nothing; what the fit cannot match is in its residuals. Given the stance
the detector found (``stance``), also the stance-foot skate (:mod:`validate.skate`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import mujoco
import numpy as np

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.rig import Rig
from retargetd.daemon.body.solve import BodySolve
from retargetd.daemon.validate import dynamics as vd
from retargetd.daemon.validate import residual as vr
from retargetd.daemon.validate import skate as vs
from retargetd.daemon.validate.limits import TYPICAL_LIMITS_DEG, limit_violation_deg
from retargetd.daemon.validate.model import (
    Skeleton,
    ValidationModel,
    skeleton_from_arrays,
)
from retargetd.protocols.frames import F64Array

_Y_AXIS = np.array([0.0, 1.0, 0.0])

#: Check thresholds (SI unless suffixed), set from the literature and three real takes
#: (``THRESHOLDS_BASIS`` says how, per check; the report header repeats it):
#: the PiG walk (rig plug-in-gait, calibrated on PiG_Calibration, 315 frames at
#: 100 Hz), the MOTEK ballet (rig cmu41, calibrated on MOTEK_T, another session, 100
#: frames at 30 Hz) and the tennis serve (rig cmu41, calibrated on its first second,
#: 1092 frames at 50 Hz): ``retargetd validate TAKE --rig RIG (--calibration FILE |
#: --calibrate-frames 0:50) --report DIR``. "median / max": over a take's frames.
#: The synthetic defects (tests/daemon/test_validate*.py) must stay beyond them.
THRESHOLDS: dict[str, float] = {
    # Model posed from the chain vs skeleton posed from world rotations: numerical
    # agreement (max 1.7e-12 / 1.6e-12 / 2.4e-12 mm on the three takes); any
    # convention error is >= millimetres (a bone 3 % longer: 12.9 mm; x y z w: 651).
    "convention_mm": 0.1,
    # Streamed skeleton (calibrated lengths, streamed rotations, from the root) vs the
    # solved joint centres: a rigid chain against soft-tissue-borne centres, so the
    # error accumulates along the chain. Per-frame median over the joints: PiG 4.7 /
    # 7.2 mm, ballet 11.3 / 26.4, tennis 16.4 / 51.1; per-frame max: PiG 13.1 / 31.3,
    # ballet 45.4 / 56.2 (MOTEK_T is another session: its RSHO-RELB is 293 mm, the
    # ballet's 328 mm median), tennis 36.6 / 106.5 (the serve bends the thorax the
    # rig holds rigid: C7-T10 173-221 mm, hips to shoulder centre 476-651 mm; the knee
    # marker slides in the knee bend: shank 357 mm against 392 calibrated; SHO-ELB CV
    # 7.8 %). Limits ~1.2x the tennis maxima; gross solve failures stay far beyond
    # (x y z w quaternions: 651 mm median; a swapped or flipped limb: >= 300 mm).
    "fit_median_mm": 60.0,
    "fit_max_mm": 130.0,
    # |q| - 1: the solve writes unit quaternions to ~1e-15 (max 6.7e-16 on all three).
    "quat_norm": 1e-6,
    # Degrees beyond the per-joint table (validate_limits: literature ranges, widened
    # for dancers, overhead athletes and skin-marker artefact, with the takes' values);
    # all three takes: 0. An excursion must last limit_min_frames consecutive frames:
    # a single-frame one that returns is a marker glitch, reported as a transient
    # (tennis frames 400 and 744: labelling glitches, forearm / hand twist jumping by
    # 120-160 deg for one frame, 6000-8000 deg/s, beyond any joint's speed).
    "limit_deg": 0.0,
    "limit_min_frames": 2,
    # Penetration depth (contact.dist < -x) between non-excluded segments: capsules are
    # lean, so any overlap beyond the contact noise is real. Max 3.3 / 0 / 0 mm; the
    # legs crossing: far beyond.
    "self_penetration_mm": 10.0,
    # Segments below the calibrated floor (the lowest foot capsule of the calibration
    # pose). Median / max: PiG 6.4 / 19.2 mm (heel strike), ballet 2.2 / 28.7, tennis
    # 10.9 / 53.1 (frame 575: the model's rigid shank is longer than the sliding knee
    # marker's, and the toe marker sits 16 mm lower than in the calibration window).
    # A body sunk 15 cm reads 163 mm.
    "floor_penetration_mm": 60.0,
    # A foot point (capsule bottom) within this of the floor, or stationary at any
    # height (validate_dynamics.CONTACT: a box, a step, a riser), supports the body;
    # unsupported longer than a jump's flight (a 1 m vertical jump flies 0.9 s) is
    # floating. All three takes: never unsupported.
    "airborne_clearance_mm": 100.0,
    "max_airborne_s": 1.0,
    # Sprint peak ~12.4 m/s (Bolt 2009): the root (max 1.5 / 1.1 / 1.6 m/s); end
    # effectors (hands, feet, head): a pitcher's or server's hand reaches ~20-25 m/s
    # (max 4.0 / 8.9 / 15.9). A 30 cm one-frame teleport at 120 Hz: 37 m/s.
    "root_speed_m_s": 13.0,
    # Ghost force (validate_dynamics): root wrench no inferred foot contact explains,
    # in body weights, 6 Hz zero-phase low-pass. Reference: filtered walking median
    # ~0.02, p95 ~0.1 BW; floating 30 cm ~1 BW; a 30 cm teleport 6-12 BW. Median / p95
    # / max: PiG 0.006 / 0.022 / 0.025, ballet 0 / 0.069 / 0.125, tennis 0 / 0.122 /
    # 0.57 (frames 377 and 553, the end of each serve's flight: the rigid-chain model's
    # centre of mass falls at 1.3 g, its trunk being the one the serve bends, see
    # fit); the same takes on a 35 cm riser: the same; synthetic walk (not dynamically
    # consistent) 0.03 / 0.15 / 0.26; a synthetic step down from a 35 cm platform max
    # 0.15. Defects: floating 30 cm 0.92 median once the feet have left the spots
    # they stood on, a 30 cm teleport 5.5 peak. 0.75: above the tennis serve's
    # flight, below floating.
    "ghost_force_bw": 0.75,
    "effector_speed_m_s": 30.0,
    # The fit's marker residuals (validate.residual; a solve that carries them: the
    # fit), gate-rejected markers included. Set from the literature and the fit's own
    # reasoning, not from a take; the synthetic performer checks they tell a misfit
    # from an intact take, and every real take with a shipped rig is the confirmation
    # (README "Validation against MuJoCo", figures in THRESHOLDS_BASIS).
    # Median over a frame's markers: soft-tissue artefact is 10-30 mm on limb segments,
    # the thigh worst (Leardini et al., "Human movement analysis using
    # stereophotogrammetry, part 3: soft tissue artifact", Gait Posture 21(2):212-225,
    # 2005), less on trunk, pelvis, head and bony distal landmarks, and marker noise
    # ~1 mm (Merriaux et al., Sensors 17(7):1591, 2017): the typical marker beyond
    # 20 mm, the middle of the limb range (the fit's own Cauchy scale,
    # FitParams.cauchy_m), says the skeleton, not soft tissue, is off.
    "marker_residual_median_mm": 20.0,
    # Max over a frame's markers: 40 mm, past the largest soft-tissue artefact of the
    # same review and below the 50-100 mm spacing of markers on one segment (the
    # reasoning of the fit's gate, FitParams.gate_m, not read from it: validation
    # stays independent of the solver's settings). Skin markers over the scapula move
    # further on their bone in arm elevation (median 30 mm at the acromial angle, 53 at
    # the root of the spine, 70 at the inferior angle: "Three-dimensional
    # quantitative evaluation of the scapular skin marker movements in the upright
    # posture", Sensors 22(17):6502, 2022, upright CT), so a sustained excursion
    # there is named, not excused.
    "marker_residual_max_mm": 40.0,
    # Sustained: an excursion must last this long (the same marker, for the max) to
    # fail: the 0.25 s within which issue 28 asks the fit to recover from any burst of
    # bad frames; shorter ones are transients (swaps, ghosts, glitches), reported.
    "marker_residual_min_s": 0.25,
    # Stance-foot skate (validate.skate; the stance the detector of post/stance.py
    # found, handed over by the caller): the horizontal speed of the foot's slowest
    # floor point (heel, ball, toe tip). A stance foot that does not slip has one of
    # them at rest (Perry & Burnfield 2010, the three rockers); the gait-event
    # methods call a heel or forefoot landed below 0.5 m/s (Ghoussayni et al. 2004,
    # Gait Posture 20:266-272; Bonci et al. 2022, Front Bioeng Biotechnol
    # 10:868928, M5) and off above 1.0 m/s (Bonci M5): a foot the detector holds in
    # stance that keeps one fifth of the landing speed, 0.1 m/s, for the length of
    # a loading response (0.1 s: 1 cm of travel) slides. The stance's first and last
    # 0.1 s are left out (loading response and pre-swing, ~10 % of the cycle each,
    # Perry & Burnfield: the heel still braking, the foot already leaving).
    # Measured after the choice: README "Stance-foot skate" (every real take).
    "foot_skate_m_s": 0.1,
    "foot_skate_min_s": 0.1,
    "foot_skate_edge_s": 0.1,
    # ... and only while the foot's lowest sole point is within 1 cm of the stance's
    # support (its median over the stance core): above it the foot is off the
    # floor (swing toe clearance 1.29 +- 0.45 cm, Winter 1992, Phys Ther 72:45-53),
    # so a detected stance that lifts is the detector's, not a slide.
    "foot_skate_support_m": 0.01,
}

#: How each threshold was set, one line per check (the report header prints these).
THRESHOLDS_BASIS: dict[str, str] = {
    "convention": "numerical agreement: takes <= 2.4e-12 mm; any convention error "
    ">= mm (bone 3 % longer 12.9, x y z w 651)",
    "fit_median": "rigid chain vs soft-tissue joint centres, per-frame median: "
    "max PiG 7.2, ballet 26.4, tennis 51.1 mm; x y z w 651",
    "fit_max": "per-frame max: PiG 31.3, ballet 56.2 (other-session calibration), "
    "tennis 106.5 mm (the serve bends the rigid thorax, knee marker slides)",
    "quat_norm": "solve writes unit quaternions to ~1e-15",
    "limits": "per-joint table (validate.limits: the widest published range across "
    "activities - stairs, running, landing, deep squat, kicking, dance, throwing - "
    "+ skin-marker margin; beyond the clinical norms AAOS, Norkin & White, Soucie "
    "2011 + 10 deg: a warning only): 0 deg beyond on all three takes and the "
    "synthetic activities; >= 2 consecutive frames (tennis 400, 744: one-frame "
    "marker glitches, reported as transients)",
    "self_penetration": "lean capsules: max PiG 3.3, ballet 0, tennis 0 mm",
    "floor_penetration": "max PiG 19.2, ballet 28.7, tennis 53.1 mm (rigid shank vs "
    "sliding knee marker); body sunk 15 cm: 163",
    "floating": "unsupported longer than a 1 m jump's flight (0.9 s); support = foot "
    "near the floor or stationary at any height; takes: 0 s",
    "ghost_force": "max PiG 0.025, ballet 0.125, tennis 0.57 BW (serve flight), "
    "the same on a 35 cm riser; floating 30 cm ~0.9, teleport 30 cm 5.5",
    "root_speed": "sprint peak 12.4 m/s (Bolt 2009); takes <= 1.6",
    "effector_speed": "server's / pitcher's hand 20-25 m/s; takes <= 15.9",
    "marker_residual_median": "the fit's marker residual, per-frame median over the "
    "seen markers (gate-rejected included): soft-tissue artefact 10-30 mm on limb "
    "segments (Leardini 2005), less elsewhere; sustained >= 0.25 s",
    "marker_residual_max": "the fit's marker residual, per-frame max: 40 mm, past the "
    "largest soft-tissue artefact (Leardini 2005), under the 50-100 mm marker "
    "spacing on a segment; the same marker for >= 0.25 s",
    "foot_skate": "stance foot's least-moving sole point horizontally (the whole sole "
    "region, so a roll or a pivot on the floor is no skate), detected stance less "
    "0.1 s at either end, on its support (within 1 cm), >= 0.1 s: one fifth of the "
    "0.5 m/s landing speed of Ghoussayni 2004 / Bonci 2022",
}


def pose_skeleton(
    skel: Skeleton, root_pos: F64Array, world_from_bone_quat: F64Array
) -> tuple[F64Array, F64Array]:
    """Bone origins and aims from world rotations and the skeleton's offsets.

    ``origin_b = origin_p + wfb_p · offset_b`` (offset in the parent's bone frame),
    ``aim_b = origin_b + wfb_b · (0, L_b, 0)``.

    Args:
        skel: the skeleton (lengths, offsets).
        root_pos: (T, 3) metres.
        world_from_bone_quat: (T, B, 4) w x y z.

    Returns:
        origins (T, B, 3) and aims (T, B, 3), metres, world.
    """
    wfb = world_from_bone_quat
    n = wfb.shape[0]
    origins = np.empty((n, len(skel.bone_names), 3))
    for b, p in enumerate(skel.bone_parents):
        if p < 0:
            origins[:, b] = root_pos
        else:
            origins[:, b] = origins[:, p] + rot.quat_rotate(
                wfb[:, p], skel.offset_parent[b]
            )
    aims = origins + rot.quat_rotate(wfb, skel.bone_lengths[:, None] * _Y_AXIS)
    return origins, aims


def fit_pairs(rig: Rig, joint_names: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Joint centres that are skeleton points: (joint index, point index) arrays.

    Point index ``b`` is bone ``b``'s origin, ``B + b`` its aim.
    """
    n_bones = len(rig.bones)
    where: dict[str, int] = {}
    for b, bone in enumerate(rig.bones):
        where.setdefault(bone.origin, b)
    for b, bone in enumerate(rig.bones):
        where.setdefault(bone.aim, n_bones + b)
    joints, points = [], []
    for j, name in enumerate(joint_names):
        point = rig.joints.get(name)
        if point in where:
            joints.append(j)
            points.append(where[point])
    return np.asarray(joints, dtype=np.int64), np.asarray(points, dtype=np.int64)


@dataclass(slots=True, eq=False)
class FrameContacts:
    """One frame's MuJoCo results (buffers reused)."""

    points: F64Array  # (2B, 3) body origins then aim sites, world
    self_depth: float = 0.0  # deepest segment/segment penetration, metres (>= 0)
    self_pair: tuple[int, int] = (-1, -1)
    floor_depth: float = 0.0  # deepest penetration of the floor, metres (>= 0)


class FrameChecker:
    """Writes one frame into the model and reads positions and contacts.

    Index arrays are resolved once; per frame: a qpos write, ``mj_kinematics``,
    ``mj_collision`` and a vectorised read of the contacts.
    """

    def __init__(self, vm: ValidationModel) -> None:
        self.vm = vm
        self.data = mujoco.MjData(vm.model)
        self._root = next(b for b, p in enumerate(vm.skeleton.bone_parents) if p < 0)
        adr = int(vm.model.jnt_qposadr[0])  # the free joint is the first joint
        self._root_pos_idx = adr + np.arange(3)
        self._root_quat_idx = adr + 3 + np.arange(4)
        self._ball_idx = vm.ball_qpos_idx.reshape(-1)
        self._ball_bones = vm.ball_bones
        self.out = FrameContacts(points=np.zeros((2 * len(vm.body_ids), 3)))

    def check(
        self, root_pos: F64Array, world_from_root_quat: F64Array, pfb: F64Array
    ) -> FrameContacts:
        """Pose one frame and collide it; returns the reused :class:`FrameContacts`."""
        m, d, vm, out = self.vm.model, self.data, self.vm, self.out
        d.qpos[self._root_pos_idx] = root_pos
        d.qpos[self._root_quat_idx] = world_from_root_quat
        d.qpos[self._ball_idx] = pfb[self._ball_bones].reshape(-1)
        mujoco.mj_kinematics(m, d)
        mujoco.mj_collision(m, d)
        n_bones = len(vm.body_ids)
        out.points[:n_bones] = d.xpos[vm.body_ids]
        out.points[n_bones:] = d.site_xpos[vm.site_ids]
        out.self_depth = 0.0
        out.floor_depth = 0.0
        out.self_pair = (-1, -1)
        if d.ncon:
            dist = d.contact.dist[: d.ncon]
            geoms = d.contact.geom[: d.ncon]
            floor = (geoms == vm.floor_geom).any(axis=1)
            if floor.any():
                out.floor_depth = max(0.0, -float(dist[floor].min()))
            if (~floor).any():
                k = int(np.argmin(np.where(floor, np.inf, dist)))
                out.self_depth = max(0.0, -float(dist[k]))
                g0, g1 = geoms[k]
                out.self_pair = (int(vm.geom_bone[g0]), int(vm.geom_bone[g1]))
        return out


@dataclass(slots=True)
class CheckResult:
    """One check over a take: per-frame values, a threshold, the flagged frames."""

    name: str
    values: F64Array  # (T,)
    threshold: float
    unit: str
    flagged: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    detail: list[str] = field(default_factory=list)  # per worst frame
    # Frames beyond the threshold that do not fail the check (too short: limits).
    transients: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    # Warnings that do not fail the check (limits: beyond the typical range).
    warnings: list[str] = field(default_factory=list)
    # The markers it blames (the residual checks; None for the others): marker ->
    # {"frames": flagged frames it is blamed for, "max_mm": its largest residual there}.
    markers: dict[str, dict[str, float]] | None = None

    @property
    def n_flagged(self) -> int:
        return int(self.flagged.sum())

    def summary(self, n_worst: int = 5) -> dict[str, Any]:
        """JSON-ready: frames flagged, worst frames and values, threshold (and the
        markers blamed, for the residual checks)."""
        v = np.where(np.isfinite(self.values), self.values, -np.inf)
        worst = np.argsort(-v)[:n_worst]
        # NaN: a frame the check does not apply to (a foot in no contact, say); one
        # with none it applies to reads as an empty check, not as a NaN.
        known = self.values[~np.isnan(self.values)]
        blamed = {} if self.markers is None else {"markers": dict(self.markers)}
        return blamed | {
            "threshold": self.threshold,
            "unit": self.unit,
            "frames_flagged": self.n_flagged,
            "first_flagged": (
                int(np.flatnonzero(self.flagged)[0]) if self.n_flagged else None
            ),
            "max": float(known.max()) if known.size else 0.0,
            "median": float(np.median(known)) if known.size else 0.0,
            "worst_frames": [int(i) for i in worst],
            "worst_values": [float(self.values[i]) for i in worst],
            "transient_frames": [int(i) for i in self.transients],
            "flagged_runs": _runs(self.flagged),
            "warnings": list(self.warnings),
        }


def _runs(mask: np.ndarray) -> list[list[int]]:
    """[[start, stop), ...] of the True runs of a (T,) bool mask (0-based frames)."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    edges = np.flatnonzero(m[1:] != m[:-1])
    return [[int(a), int(b)] for a, b in zip(edges[::2], edges[1::2], strict=True)]


@dataclass(slots=True)
class TakeReport:
    """All checks of a take."""

    checks: dict[str, CheckResult]
    n_frames: int
    seconds_per_frame: float  # the MuJoCo per-frame loop (qpos, kinematics, collision)

    @property
    def passed(self) -> bool:
        return all(c.n_flagged == 0 for c in self.checks.values())

    def failed(self) -> list[str]:
        return [n for n, c in self.checks.items() if c.n_flagged]


#: Frames between two ``progress`` calls of :func:`validate_take`.
PROGRESS_FRAMES = 64


def lowest_support(contact: np.ndarray, support: np.ndarray) -> np.ndarray:
    """(T,) the lowest level under the feet per frame, metres above the
    calibration's floor, for :func:`validate_take`'s ``support_m``: per foot, the
    lower of the support it stands on (or last left) and the one its next contact
    is on (a swing foot reaching down a stair is over the step it lands on); then
    the lower foot's. Offline only (it looks ahead to the next contact).

    Args:
        contact: (T, 2) bool, each foot in contact.
        support: (T, 2) each foot's support level (the stance detector's, or a
            synthetic take's truth), metres above the calibration's floor.
    """
    n = len(contact)
    out = np.array(support, dtype=np.float64)
    for s in range(contact.shape[1]):
        nxt = np.inf
        for t in range(n - 1, -1, -1):
            if contact[t, s]:
                nxt = support[t, s]
            out[t, s] = min(out[t, s], nxt)
    return out.min(axis=1) if out.shape[1] else np.zeros(n)


def validate_take(
    vm: ValidationModel,
    solve: BodySolve,
    rate_hz: float,
    *,
    fit: tuple[np.ndarray, np.ndarray] | None = None,
    thresholds: dict[str, float] | None = None,
    dynamics: bool = True,
    progress: Callable[[int], None] | None = None,
    stance: dict[str, np.ndarray] | None = None,
    support_m: np.ndarray | None = None,
) -> TakeReport:
    """Run every check on a solved take.

    Args:
        vm: the model (its skeleton = the calibration the model was built from).
        solve: the solved take; its ``bone_lengths`` pose the streamed skeleton.
        rate_hz: frame rate.
        fit: (joint index, point index) from :func:`fit_pairs`; None skips "fit".
        thresholds: overrides of :data:`THRESHOLDS`.
        dynamics: run the ghost-force check (offline inverse dynamics).
        progress: called with the number of frames checked since the last call
            (every :data:`PROGRESS_FRAMES` frames of the per-frame MuJoCo loop;
            a progress bar).
        stance: foot bone name -> (T,) bool, the stance the detector found
            (``post.stance.foot_contact``, handed over by the caller:
            :mod:`validate.skate`); None skips the skate check.
        support_m: (T,) metres above the calibration's floor, the lowest support
            under the feet per frame (the stance detector's, or a synthetic take's
            truth): where it is below the floor (a stair down), floor penetration
            is measured below it; None: the calibration's floor alone.

    Returns:
        The report.
    """
    th = {**THRESHOLDS, **(thresholds or {})}
    skel_model = vm.skeleton
    skel_stream = skeleton_from_arrays(skel_model, solve.bone_lengths)
    wfb, pfb, root_pos = (
        solve.world_from_bone_quat,
        solve.rest_from_bone_quat,
        solve.root_pos,
    )
    n, n_bones = wfb.shape[:2]
    root = next(b for b, p in enumerate(skel_model.bone_parents) if p < 0)
    origins, aims = pose_skeleton(skel_stream, root_pos, wfb)
    points = np.concatenate([origins, aims], axis=1)  # (T, 2B, 3)

    checker = FrameChecker(vm)
    conv = np.empty(n)
    self_depth = np.empty(n)
    self_pairs = np.empty((n, 2), dtype=np.int64)
    floor_depth = np.empty(n)
    t0 = time.perf_counter()
    for t in range(n):
        fc = checker.check(root_pos[t], wfb[t, root], pfb[t])
        conv[t] = np.sqrt(((fc.points - points[t]) ** 2).sum(axis=1).max())
        self_depth[t] = fc.self_depth
        self_pairs[t] = fc.self_pair
        floor_depth[t] = fc.floor_depth
        if support_m is not None and support_m[t] < 0.0:  # standing below the floor
            floor_depth[t] = max(0.0, fc.floor_depth + float(support_m[t]))
        if progress is not None and (t + 1) % PROGRESS_FRAMES == 0:
            progress(PROGRESS_FRAMES)
    if progress is not None and n % PROGRESS_FRAMES:
        progress(n % PROGRESS_FRAMES)
    per_frame = (time.perf_counter() - t0) / max(n, 1)

    checks: dict[str, CheckResult] = {}
    checks["convention"] = CheckResult(
        "convention", 1e3 * conv, th["convention_mm"], "mm"
    )
    if fit is not None and fit[0].size:
        d = 1e3 * np.linalg.norm(
            points[:, fit[1]] - solve.joint_centres[:, fit[0]], axis=-1
        )
        ok = np.isfinite(d).any(axis=1)
        med = np.full(n, np.nan)
        mx = np.full(n, np.nan)
        med[ok] = np.nanmedian(d[ok], axis=1)
        mx[ok] = np.nanmax(d[ok], axis=1)
        checks["fit_median"] = CheckResult("fit_median", med, th["fit_median_mm"], "mm")
        checks["fit_max"] = CheckResult("fit_max", mx, th["fit_max_mm"], "mm")
    norms = np.maximum(
        np.abs(np.linalg.norm(wfb, axis=-1) - 1.0).max(axis=1),
        np.abs(np.linalg.norm(pfb, axis=-1) - 1.0).max(axis=1),
    )
    checks["quat_norm"] = CheckResult("quat_norm", norms, th["quat_norm"], "")
    viol, which = limit_violation_deg(skel_model, pfb)
    worst_bone = np.argmax(viol, axis=1)
    checks["limits"] = CheckResult(
        "limits", viol.max(axis=1), th["limit_deg"], "deg beyond limit"
    )
    checks["self_penetration"] = CheckResult(
        "self_penetration", 1e3 * self_depth, th["self_penetration_mm"], "mm"
    )
    checks["floor_penetration"] = CheckResult(
        "floor_penetration", 1e3 * floor_depth, th["floor_penetration_mm"], "mm"
    )
    # Support from the feet: near the floor or stationary at any height
    # (validate_dynamics); unsupported longer than a jump's flight is floating.
    feet_pts, _, _ = vd.foot_points(skel_model, origins, aims)
    near = {"near_floor_m": 1e-3 * th["airborne_clearance_mm"]}
    supported = vd.infer_contacts(feet_pts, vm.floor_z, rate_hz, near, surfaces=False)
    airborne = np.asarray(
        ~supported.any(axis=1) if supported.shape[1] else np.zeros(n, bool),
        dtype=bool,
    )
    # The ghost force's contacts add the surfaces where a foot stood (a platform).
    contacts = vd.infer_contacts(feet_pts, vm.floor_z, rate_hz, near)
    run_s = vd.run_lengths(airborne) / rate_hz
    checks["floating"] = CheckResult("floating", run_s, th["max_airborne_s"], "s")
    if dynamics and contacts.shape[1]:
        gf = vd.ghost_force(vm, root_pos, wfb[:, root], pfb, rate_hz, contacts)
        checks["ghost_force"] = CheckResult(
            "ghost_force", gf.ghost_bw, th["ghost_force_bw"], "BW"
        )
    root_speed = _speed(root_pos, rate_hz)
    checks["root_speed"] = CheckResult(
        "root_speed", root_speed, th["root_speed_m_s"], "m/s"
    )
    leaves = [b for b in range(n_bones) if b not in set(skel_model.bone_parents)]
    eff = np.max(_speed(aims[:, leaves], rate_hz), axis=1)
    checks["effector_speed"] = CheckResult(
        "effector_speed", eff, th["effector_speed_m_s"], "m/s"
    )
    for c in checks.values():
        c.flagged = np.isfinite(c.values) & (c.values > c.threshold)
    # A limit excursion shorter than limit_min_frames is a transient (a marker
    # glitch), reported but not failed: see validate_limits "Single-frame excursions".
    lim = checks["limits"]
    beyond = lim.flagged
    lim.flagged = beyond & (vd.run_lengths(beyond) >= th["limit_min_frames"])
    lim.transients = np.flatnonzero(beyond & ~lim.flagged)
    names = skel_model.bone_names
    excess = viol[np.arange(n), worst_bone]  # (T,) degrees beyond, worst bone

    def limit_line(t: int, prefix: str = "") -> str:
        b = worst_bone[t]
        return (
            f"{prefix}frame {t}: {names[b]} {which[t, b]} ({excess[t]:.1f} deg beyond)"
        )

    flagged_frames = np.flatnonzero(lim.flagged)
    worst = _worst(flagged_frames, excess)
    lim.detail = [limit_line(t) for t in worst]
    if flagged_frames.size and flagged_frames[0] not in worst:
        lim.detail.append(limit_line(int(flagged_frames[0]), "first flagged, "))
    lim.detail += [limit_line(t, "transient, ") for t in _worst(lim.transients, excess)]
    lim.warnings = _typical_warnings(skel_model, pfb, viol, rate_hz)
    checks["self_penetration"].detail = [
        f"frame {t}: {names[self_pairs[t, 0]]} / {names[self_pairs[t, 1]]}"
        for t in np.flatnonzero(checks["self_penetration"].flagged)[:5]
    ]
    if stance:
        sk = vs.skate_check(
            skel_stream, origins, wfb, stance, rate_hz,
            speed_m_s=th["foot_skate_m_s"], min_s=th["foot_skate_min_s"],
            edge_s=th["foot_skate_edge_s"], support_m=th["foot_skate_support_m"],
        )  # fmt: skip
        checks["foot_skate"] = CheckResult(
            "foot_skate", sk.values, th["foot_skate_m_s"], "m/s", flagged=sk.flagged,
            detail=sk.detail, transients=sk.transients,
        )  # fmt: skip
    checks.update(_residual_checks(solve, th, rate_hz))
    return TakeReport(checks=checks, n_frames=n, seconds_per_frame=per_frame)


#: Frames named per check in the limit detail lines (the worst, by degrees beyond).
N_DETAIL_FRAMES = 5


def _worst(frames: np.ndarray, values: F64Array) -> list[int]:
    """The :data:`N_DETAIL_FRAMES` of ``frames`` with the largest ``values``, largest
    first (the earlier frame first on a tie)."""
    order = np.argsort(-values[frames], kind="stable")[:N_DETAIL_FRAMES]
    return [int(frames[i]) for i in order]


def _residual_checks(
    solve: BodySolve, th: dict[str, float], rate_hz: float
) -> dict[str, CheckResult]:
    """The marker residual checks (:mod:`validate.residual`) of a solve that carries
    residuals (``FitSolve.marker_residual``, (T, Mr) metres); none for the others."""
    resid = getattr(solve, "marker_residual", None)
    if resid is None or np.ndim(resid) != 2 or not np.size(resid):
        return {}
    got = vr.residual_checks(
        1e3 * np.asarray(resid, dtype=np.float64),
        tuple(getattr(solve, "marker_names", ())),
        median_mm=th["marker_residual_median_mm"],
        max_mm=th["marker_residual_max_mm"],
        n_min=vr.min_frames(th["marker_residual_min_s"], rate_hz),
        rate_hz=rate_hz,
    )
    out = {}
    for name, rc in got.items():
        out[name] = CheckResult(
            name, rc.values, th[f"{name}_mm"], "mm", flagged=rc.flagged,
            detail=rc.detail, transients=rc.transients, markers=rc.markers,
        )  # fmt: skip
    return out


def _typical_warnings(
    skel: Any, pfb: F64Array, viol: F64Array, rate_hz: float
) -> list[str]:
    """One line per bone that goes beyond the typical range
    (:data:`validate.limits.TYPICAL_LIMITS_DEG`) but not beyond the failure limits in
    the same frames: a warning, not a failure."""
    typ, which = limit_violation_deg(skel, pfb, TYPICAL_LIMITS_DEG)
    out = []
    for b, name in enumerate(skel.bone_names):
        beyond = (typ[:, b] > 0.0) & (viol[:, b] <= 0.0)
        if not beyond.any():
            continue
        t = int(np.argmax(np.where(beyond, typ[:, b], -1.0)))
        out.append(
            f"beyond the typical range (warning): {name} {which[t, b]}, "
            f"{typ[t, b]:.1f} deg past it at frame {t}, "
            f"{beyond.sum() / rate_hz:.2f} s in all"
        )
    return out


def _speed(pos: F64Array, rate_hz: float) -> F64Array:
    """(T, ...) speed by the backward difference (0 for the first frame), m/s."""
    out = np.zeros(pos.shape[:-1])
    out[1:] = np.linalg.norm(np.diff(pos, axis=0), axis=-1) * rate_hz
    return out
