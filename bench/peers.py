"""retargetd and its peers side by side, one frame at a time, on the peers' own data.

Run from the repository root (optional extra ``peers``: ``pip install -e '.[peers]'``)::

    python bench/peers.py [--frames a:b] [--method construction|fit|all]
                          [--json OUT.json] [--plot OUT.png]
    python bench/peers.py --hinge-axes   # gait2354's knee / ankle axes in the rig

Two problems, each solved frame by frame as a live loop would call the solver (the
previous frame's answer kept as the start of the next where the solver has one):

* **biorbd** (its bioptim whole-body model ``wholebody_model_nomesh.bioMod``, 34 DoF,
  75 markers, and its gait take ``bioptim_gait_wholebody.c3d``, 100 Hz): biorbd's
  extended Kalman filter (``KalmanReconsMarkers.reconstructFrame``) and its
  least-squares inverse kinematics (``InverseKinematics``'s own residual and Jacobian
  under ``scipy.optimize.least_squares``, its per-frame step: ``trf`` within the
  model's ranges on the first frame, then ``lm`` warm-started, ``xtol`` 1e-6); against
  retargetd with ``daemon/body/rigs/bioptim-wholebody.toml`` calibrated on the take's
  first ``--calibrate-frames`` rows (the take has no static trial).
* **OpenSim** (gait2354 scaled to subject01, ``subject01_simbody.osim``;
  ``subject01_walk1.trc``, 60 Hz): ``InverseKinematicsSolver.track`` with the marker and
  coordinate tasks of ``subject01_Setup_IK.xml``, constraint weight 20, at accuracy 1e-5
  and 1e-3 (``assemble`` on the first frame); against retargetd with
  ``daemon/body/rigs/opensim-gait2354.toml`` calibrated on
  ``opensim-core/subject01_static.trc``.

retargetd: ``BodySolver.solve_frame`` (``--method construction``) and the rigid-skeleton
fit ``FitSolver.solve_frame`` (``--method fit``; built as ``bench/bench_fit.py`` builds
it: the validator's joint limits and segment kinds for its soft limit penalty, the
rig's ``[fit]`` tables). Timing: ``time.perf_counter_ns`` around each solver call only;
the first frame is reported apart (filter start, assembly; numba's cache load is done
before by a warm-up frame). Per solver: median and p99 per frame over the frames after
the first, the ratio of its median to each retargetd solver's median (same run), the
marker residual RMS and, per joint centre and per corresponding segment, the agreement
with each retargetd solver.

Marker residual RMS, per solver, over every frame after the first and over the
**peer's markers** (like for like): biorbd's 75 model markers; the 31 markers of
OpenSim's IK tasks (``subject01_Setup_IK.xml``; not the temples, knee and ankle
markers; also without the two acromions, :data:`OSIM_ACROMIONS`). Every sample where
the marker was seen counts, a marker the fit's gate rejected included:

* biorbd: distance of each model marker, placed by the solved q, to the measured one;
* OpenSim: ``computeCurrentMarkerErrors`` (the markers in use by the IK tasks);
* retargetd fit: its own distance from the fitted model to the measured marker
  (``FitPose.marker_residual``), on the same markers;
* retargetd construction: the construction puts bones through points built from the
  markers and has no model that predicts every marker, so its residual is the distance
  of each marker of a rigid segment (``[segments]``) to where the segment's calibrated
  layout, fitted rigidly (Kabsch) to that frame's markers of the segment, places it:
  how far the markers are from moving as the rigid bodies the solve assumes. Markers
  in no segment are not counted (bioptim: RA LA RTT2 LTT2; OpenSim: the sternum and
  acromions), and three-marker segments (every OpenSim one) fit nearly exactly, so
  this is **not** like for like; the fit's residual is.

Segment axes: for each retargetd bone with a corresponding peer body (biorbd and
OpenSim segment frames, listed in :data:`BIORBD_SEGMENTS`, :data:`OSIM_SEGMENTS`), the
rotation between the two frames per frame, ``R_rel(t) = R_ours(t)^T R_peer(t)``. The
frames are defined differently (a bone's +Y runs from its origin to its aim, the
peer's from its generic model), so the mean of ``R_rel`` is a convention, printed as
``offset``; what says whether the two solvers turn the segment alike is the angle of
each ``R_rel(t)`` from that mean (median and p95, degrees).

Joint centres compared: biorbd segment origins (femur = hip, tibia = knee, talus =
ankle, humerus = shoulder, ulna = elbow, hand = wrist); OpenSim joint child frames
(hip, knee, ankle), in the take's world (+Z up) as retargetd has them. OpenSim writes
``opensim.log`` into the working directory: it runs in a temporary one.
Speed is printed, never asserted; state the machine's load beside any figure
(``uptime`` is printed).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from retargetd.daemon.body.calibration import Calibration, calibrate, match_markers
from retargetd.daemon.body.rig import Rig, load_rig
from retargetd.daemon.body.solve import BodySolver, warm_up
from retargetd.daemon.body.solve_fit import FitSolver
from retargetd.daemon.body.solve_fit import warm_up as warm_up_fit
from retargetd.daemon.cli.args import parse_frames
from retargetd.daemon.validate.limits import JOINT_LIMITS_DEG
from retargetd.daemon.validate.model import SEGMENT_KIND
from retargetd.replay.takes import load_take

REPO = Path(__file__).resolve().parent.parent
DATASETS = REPO.parent / "shared" / "datasets"
PEERS = DATASETS / "peers"
BIOMOD = PEERS / "wholebody_model_nomesh.bioMod"
BIOPTIM_TAKE = PEERS / "bioptim_gait_wholebody.c3d"
OSIM = PEERS / "subject01_simbody.osim"
OSIM_SETUP = PEERS / "subject01_Setup_IK.xml"
OSIM_WALK = PEERS / "subject01_walk1.trc"
OSIM_STATIC = DATASETS / "opensim-core" / "subject01_static.trc"
RIG_BIOPTIM = REPO / "daemon" / "body" / "rigs" / "bioptim-wholebody.toml"
RIG_OPENSIM = REPO / "daemon" / "body" / "rigs" / "opensim-gait2354.toml"
#: OpenSim's constraint weight from subject01_Setup_IK.xml.
OSIM_CONSTRAINT_WEIGHT = 20.0
#: Accuracies asked for by issue 19 (1e-5 is subject01_Setup_IK.xml's own).
OSIM_ACCURACIES = (1e-5, 1e-3)
#: biorbd segment whose origin is the joint centre -> retargetd joint name (R side;
#: the L side mirrors it).
BIORBD_CENTRES = {
    "femur": "HJC",
    "tibia": "KJC",
    "talus": "AJC",
    "humerus": "SJC",
    "ulna": "EJC",
    "hand": "WJC",
}
#: OpenSim joint (child frame origin) -> retargetd joint name.
OSIM_CENTRES = {"hip": "HJC", "knee": "KJC", "ankle": "AJC"}
#: OpenSim's acromion markers: gait2354 carries them on its rigid torso, the
#: opensim-gait2354 rig's fit on clavicles (swing joints): the residual is also given
#: without them, where both models put the markers on the same segments.
OSIM_ACROMIONS = ("R.Acromium", "L.Acromium")
#: retargetd bone (bioptim-wholebody.toml) -> biorbd segment whose frame it is
#: compared with; ``{s}`` is the side (r, l). The forearm's roll comes from the
#: styloids, so it is the radius (which carries pronation), not the ulna.
BIORBD_SEGMENTS = {
    "pelvis": "pelvis",
    "thorax": "torso",
    "head": "head_and_neck",
    "{s}thigh": "femur_{s}",
    "{s}shank": "tibia_{s}",
    "{s}foot": "calcn_{s}",
    "{s}toes": "toes_{s}",
    "{s}upperarm": "humerus_{s}",
    "{s}forearm": "radius_{s}",
    "{s}hand": "hand_{s}",
}
#: retargetd bone (opensim-gait2354.toml) -> OpenSim body (gait2354 has no head or
#: arms: its torso carries them).
OSIM_SEGMENTS = {
    "pelvis": "pelvis",
    "torso": "torso",
    "{s}thigh": "femur_{s}",
    "{s}shank": "tibia_{s}",
    "{s}foot": "calcn_{s}",
    "{s}toes": "toes_{s}",
}


def sided(table: dict[str, str]) -> dict[str, str]:
    """Expand ``{s}`` into the two sides (r, l)."""
    out = {}
    for ours, peer in table.items():
        for side in ("r", "l") if "{s}" in ours else ("",):
            out[ours.format(s=side)] = peer.format(s=side)
    return out


@dataclass
class Run:
    """One solver over the selected frames."""

    name: str
    problem: str
    ns: list[int] = field(default_factory=list)  # per-frame solve time, ns
    # take label -> (T,) m, distance per frame (NaN: not seen, or no residual)
    residual_m: dict[str, np.ndarray] = field(default_factory=dict)
    centres: dict[str, np.ndarray] = field(default_factory=dict)  # joint -> (T, 3) m
    # segment (the retargetd bone it corresponds to) -> (T, 3, 3) world_from_segment
    frames: dict[str, np.ndarray] = field(default_factory=dict)

    def residuals(self, markers: tuple[str, ...] | None = None) -> np.ndarray:
        """The finite residual samples (m) of ``markers`` (all when None), frames
        after the first."""
        parts = [
            r[1:]
            for name, r in self.residual_m.items()
            if markers is None or name in markers
        ]
        res = np.concatenate(parts) if parts else np.zeros(0)
        return res[np.isfinite(res)]

    def stats(self, markers: tuple[str, ...] | None = None) -> dict[str, float]:
        """first / median / p99 per frame (ms) and the residual RMS (mm) over
        ``markers``."""
        steady = np.asarray(self.ns[1:], dtype=np.float64) / 1e6
        res = self.residuals(markers)
        return {
            "first_ms": self.ns[0] / 1e6,
            "median_ms": float(np.median(steady)),
            "p99_ms": float(np.percentile(steady, 99)),
            "residual_rms_mm": float(1000 * np.sqrt(np.mean(res**2))),
            "residual_samples": int(res.size),
            "frames": len(self.ns),
        }

    def marker_rms_mm(self) -> dict[str, float]:
        """Per marker, its residual RMS (mm), frames after the first."""
        out = {}
        for name, r in self.residual_m.items():
            r = r[1:][np.isfinite(r[1:])]
            if r.size:
                out[name] = float(1000 * np.sqrt(np.mean(r**2)))
        return out


@contextlib.contextmanager
def in_temp_dir() -> Iterator[None]:
    """Run in a temporary working directory (OpenSim writes opensim.log there)."""
    cwd = os.getcwd()
    with tempfile.TemporaryDirectory(prefix="retargetd-peers-") as tmp:
        os.chdir(tmp)
        try:
            yield
        finally:
            os.chdir(cwd)


# ---- retargetd ----------------------------------------------------------------------


def pelvis_measurements(
    positions: np.ndarray,
    labels: tuple[str, ...],
    asis: tuple[str, str],
    psis: tuple[str, ...],
) -> dict[str, float]:
    """Harrington's PW and PD (mm) measured on base-pose frames (medians).

    Args:
        positions: (F, M, 3) metres.
        labels: (M,) take labels.
        asis: (right, left) ASIS labels.
        psis: PSIS labels (their midpoint) or the one sacral marker.
    """
    col = {n: i for i, n in enumerate(labels)}
    r, lft = positions[:, col[asis[0]]], positions[:, col[asis[1]]]
    back = np.mean([positions[:, col[p]] for p in psis], axis=0)
    pw = np.linalg.norm(lft - r, axis=-1)
    pd = np.linalg.norm(0.5 * (lft + r) - back, axis=-1)
    return {
        "PelvisWidth": float(1000 * np.nanmedian(pw)),
        "PelvisDepth": float(1000 * np.nanmedian(pd)),
    }


def segment_residuals(
    cal: Calibration, col_of: dict[str, int], frame: np.ndarray
) -> dict[str, float]:
    """Distance (m) of each seen marker of each rigid segment to its calibrated layout
    fitted rigidly (Kabsch) to the segment's seen markers in ``frame``.

    Args:
        cal: the calibration (its ``segment_layouts``).
        col_of: rig marker -> column of ``frame`` (absent: not in the take).
        frame: (M, 3) float64, metres, world; NaN rows occluded.

    Returns:
        rig marker -> distance, for the markers of segments with >= 3 seen.
    """
    out: dict[str, float] = {}
    for names, layout in cal.segment_layouts.values():
        pts = np.array(
            [frame[col_of[n]] if n in col_of else np.full(3, np.nan) for n in names]
        )
        ok = np.isfinite(pts).all(axis=1)
        if ok.sum() < 3:
            continue
        a, b = np.asarray(layout)[ok], pts[ok]
        ca, cb = a.mean(axis=0), b.mean(axis=0)
        u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
        d = np.sign(np.linalg.det(u @ vt))
        rot = u @ np.diag([1.0, 1.0, d]) @ vt  # layout -> frame, row vectors
        fitted = (a - ca) @ rot + cb
        dist = np.linalg.norm(fitted - b, axis=1)
        for n, di in zip(np.asarray(names)[ok], dist, strict=True):
            out[str(n)] = float(di)
    return out


def mat_from_quat(q: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices from (..., 4) unit quaternions (w, x, y, z)."""
    from scipy.spatial.transform import Rotation

    flat = Rotation.from_quat(q.reshape(-1, 4), scalar_first=True).as_matrix()
    return flat.reshape(*q.shape[:-1], 3, 3)


def make_solver(
    kind: str,
    rig: Rig,
    cal: Calibration,
    labels: tuple[str, ...],
    base: tuple[np.ndarray, tuple[str, ...]],
    rate_hz: float = 120.0,
) -> BodySolver | FitSolver:
    """The construction, or the fit built as ``bench/bench_fit.py`` builds it (the
    validator's joint limits and segment kinds; ``base``: the base-pose frames
    ((F, M0, 3) metres) and labels the calibration was made from)."""
    if kind == "construction":
        return BodySolver(rig, cal, labels)
    return FitSolver(
        rig,
        cal,
        labels,
        base_positions=base[0],
        base_labels=base[1],
        joint_limits=JOINT_LIMITS_DEG,
        segment_kind=SEGMENT_KIND,
        rate_hz=rate_hz,
    )


def run_retargetd(
    kind: str,
    problem: str,
    rig: Rig,
    cal: Calibration,
    take: Any,
    frames: slice,
    base: tuple[np.ndarray, tuple[str, ...]],
) -> Run:
    """One retargetd solver (``kind``: construction or fit) over the frames, one
    ``solve_frame`` call per frame. Residuals are keyed by the take's labels."""
    cols = match_markers(rig, take.labels)
    col_of = {m: int(c) for m, c in zip(rig.marker_names, cols, strict=True) if c >= 0}
    label_of = {m: take.labels[c] for m, c in col_of.items()}
    solver = make_solver(kind, rig, cal, take.labels, base, take.rate_hz)
    pose = solver.new_pose()
    pos = np.ascontiguousarray(take.positions[frames], dtype=np.float64)
    solver.solve_frame(pos[0], pose)  # warm-up: the kernel loaded, then reset
    solver.reset()
    run = Run(f"retargetd {kind}", problem)
    n = pos.shape[0]
    joints = np.zeros((n, len(solver.joint_names), 3))
    wfb = np.zeros((n, len(solver.bone_names), 4))
    res = {label_of[m]: np.full(n, np.nan) for m in col_of}
    fit_markers = getattr(solver, "marker_names", None) if kind == "fit" else None
    clock = time.perf_counter_ns
    for t in range(n):
        t0 = clock()
        solver.solve_frame(pos[t], pose)
        run.ns.append(clock() - t0)
        joints[t] = pose.joint_centres
        wfb[t] = pose.world_from_bone_quat
        if fit_markers is not None:  # the fit's own residual per rig marker
            for m, r in zip(fit_markers, pose.marker_residual, strict=True):
                if m in label_of:
                    res[label_of[m]][t] = r
        else:
            for m, r in segment_residuals(cal, col_of, pos[t]).items():
                res[label_of[m]][t] = r
    run.residual_m = res
    run.centres = {j: joints[:, k] for k, j in enumerate(solver.joint_names)}
    mats = mat_from_quat(wfb)
    run.frames = {b: mats[:, k] for k, b in enumerate(solver.bone_names)}
    return run


def retargetd_runs(
    problem: str,
    rig: Rig,
    cal: Calibration,
    take: Any,
    frames: slice,
    method: str,
    base: tuple[np.ndarray, tuple[str, ...]],
) -> list[Run]:
    kinds = ("construction", "fit") if method == "all" else (method,)
    return [run_retargetd(k, problem, rig, cal, take, frames, base) for k in kinds]


# ---- biorbd -------------------------------------------------------------------------


def biorbd_runs(frames: slice) -> tuple[list[Run], dict[str, Any]]:
    """biorbd's Kalman filter and least-squares IK on its model and take."""
    import biorbd
    from scipy import optimize

    model = biorbd.Model(str(BIOMOD))
    names = [n.to_string() for n in model.technicalMarkerNames()]
    take = load_take(BIOPTIM_TAKE)  # metres, +Z up already (world = capture)
    col = {n: i for i, n in enumerate(take.labels)}
    markers = take.positions[frames][:, [col[n] for n in names]]  # (T, 75, 3) m
    seg = {model.segment(i).name().to_string(): i for i in range(model.nbSegment())}
    centre_seg = {
        f"{s}{j}": seg[f"{b}_{s.lower()}"]
        for b, j in BIORBD_CENTRES.items()
        for s in "RL"
    }
    frame_seg = {ours: seg[peer] for ours, peer in sided(BIORBD_SEGMENTS).items()}
    info = {
        "dof": model.nbQ(),
        "markers": model.nbMarkers(),
        "rate_hz": take.rate_hz,
        "frames": markers.shape[0],
        "biorbd": biorbd.__version__,
    }

    def start(name: str) -> Run:
        run = Run(name, "biorbd")
        run.centres = {j: np.zeros((n, 3)) for j in centre_seg}
        run.frames = {b: np.zeros((n, 3, 3)) for b in frame_seg}
        run.residual_m = {m: np.full(n, np.nan) for m in names}
        return run

    def record(run: Run, q: np.ndarray, t: int) -> None:
        placed = np.array([m.to_array() for m in model.technicalMarkers(q)])
        dist = np.linalg.norm(placed - markers[t], axis=1)  # NaN where not seen
        for m, d in zip(names, dist, strict=True):
            run.residual_m[m][t] = d
        for j, s in centre_seg.items():
            run.centres[j][t] = model.globalJCS(q, s).trans().to_array()
        for b, s in frame_seg.items():
            run.frames[b][t] = model.globalJCS(q, s).rot().to_array()

    clock = time.perf_counter_ns
    n = markers.shape[0]
    kal = start("biorbd Kalman (EKF)")
    kalman = biorbd.KalmanReconsMarkers(model, biorbd.KalmanParam(take.rate_hz))
    q = biorbd.GeneralizedCoordinates(model)
    qd = biorbd.GeneralizedVelocity(model)
    qdd = biorbd.GeneralizedAcceleration(model)
    flat = np.ascontiguousarray(markers.reshape(n, -1))  # x y z per marker
    for t in range(n):
        t0 = clock()
        kalman.reconstructFrame(model, flat[t], q, qd, qdd)
        kal.ns.append(clock() - t0)
        record(kal, q.to_array(), t)

    lsq = start("biorbd least-squares IK")
    # (3, markers, frames) as biorbd wants; only its residual, Jacobian and ranges used.
    ik = biorbd.InverseKinematics(model, np.transpose(markers[:1], (2, 1, 0)))
    lo, hi = (np.asarray(b, dtype=np.float64) for b in ik.bounds)
    qv = 0.5 * (lo + hi)

    def fun(x: np.ndarray, real: np.ndarray, keep: np.ndarray) -> np.ndarray:
        return ik._marker_diff(np.array(model.technicalMarkers(x))[keep], real)

    def jac(x: np.ndarray, real: np.ndarray, keep: np.ndarray) -> np.ndarray:
        return ik._marker_jacobian(np.array(model.technicalMarkersJacobian(x))[keep])

    for t in range(n):
        keep = np.flatnonzero(np.isfinite(markers[t]).all(axis=1))
        real = markers[t, keep].T
        t0 = clock()
        sol = optimize.least_squares(
            fun,
            qv,
            jac=jac,
            args=(real, keep),
            xtol=1e-6,
            method="trf" if t == 0 else "lm",
            bounds=(lo, hi) if t == 0 else (-np.inf, np.inf),
        )
        lsq.ns.append(clock() - t0)
        qv = sol.x
        record(lsq, qv, t)
    return [kal, lsq], info


# ---- OpenSim ------------------------------------------------------------------------


def opensim_runs(
    frames: slice, world_from_capture: np.ndarray
) -> tuple[list[Run], dict[str, Any]]:
    """OpenSim's IK solver at each accuracy on subject01's model and walk."""
    import opensim as osim

    osim.Logger.setLevelString("error")  # not the missing-mesh warnings
    runs = []
    info: dict[str, Any] = {"opensim": osim.GetVersion()}
    with in_temp_dir():
        for accuracy in OSIM_ACCURACIES:
            model = osim.Model(str(OSIM))
            tasks = osim.InverseKinematicsTool(str(OSIM_SETUP)).getIKTaskSet()
            weights = osim.SetMarkerWeights()
            coords = osim.SimTKArrayCoordinateReference()
            for i in range(tasks.getSize()):
                task = tasks.get(i)
                if not task.getApply():
                    continue
                if osim.IKMarkerTask.safeDownCast(task) is not None:
                    weights.cloneAndAppend(
                        osim.MarkerWeight(task.getName(), task.getWeight())
                    )
                else:  # the setup's coordinate tasks hold the model's default value
                    c = model.getCoordinateSet().get(task.getName())
                    ref = osim.CoordinateReference(
                        task.getName(), osim.Constant(c.getDefaultValue())
                    )
                    ref.setWeight(task.getWeight())
                    coords.push_back(ref)
            table = osim.TimeSeriesTableVec3(str(OSIM_WALK))
            mref = osim.MarkersReference(table, weights)
            state = model.initSystem()
            solver = osim.InverseKinematicsSolver(
                model, mref, coords, OSIM_CONSTRAINT_WEIGHT
            )
            solver.setAccuracy(accuracy)
            times = list(table.getIndependentColumn())[frames]
            joints = {
                f"{s}{j}": model.getJointSet().get(f"{b}_{s.lower()}").getChildFrame()
                for b, j in OSIM_CENTRES.items()
                for s in "RL"
            }
            bodies = {
                ours: model.getBodySet().get(peer)
                for ours, peer in sided(OSIM_SEGMENTS).items()
            }
            n = len(times)
            run = Run(f"OpenSim IK {accuracy:g}", "opensim")
            run.centres = {j: np.zeros((n, 3)) for j in joints}
            run.frames = {b: np.zeros((n, 3, 3)) for b in bodies}
            errors = osim.SimTKArrayDouble()
            clock = time.perf_counter_ns
            for t, tm in enumerate(times):
                state.setTime(tm)
                t0 = clock()
                if t == 0:
                    solver.assemble(state)
                else:
                    solver.track(state)
                run.ns.append(clock() - t0)
                solver.computeCurrentMarkerErrors(errors)
                for i in range(errors.size()):
                    name = solver.getMarkerNameForIndex(i)
                    run.residual_m.setdefault(name, np.full(n, np.nan))
                    run.residual_m[name][t] = errors.getElt(i)
                model.realizePosition(state)
                for j, frame in joints.items():
                    p = frame.getPositionInGround(state)
                    run.centres[j][t] = world_from_capture @ np.array(
                        [p.get(k) for k in range(3)]
                    )
                for b, body in bodies.items():
                    rot = body.getTransformInGround(state).R()
                    run.frames[b][t] = world_from_capture @ np.array(
                        [[rot.get(r, c) for c in range(3)] for r in range(3)]
                    )
            info["markers_in_use"] = solver.getNumMarkersInUse()
            info["ik_markers"] = list(run.residual_m)
            info["frames"] = len(times)
            runs.append(run)
    return runs, info


#: gait2354 hinge -> (retargetd bone, OpenSim markers on the segment the axis is
#: carried through: the bone's own segment, then the joint's other one as a check).
OSIM_HINGES = {
    "knee_{s}": ("{s}shank", ("Shank.Upper", "Shank.Front", "Shank.Rear"),
                 ("Thigh.Upper", "Thigh.Front", "Thigh.Rear")),
    "ankle_{s}": ("{s}foot", ("Heel", "Midfoot.Sup", "Midfoot.Lat"),
                  ("Shank.Upper", "Shank.Front", "Shank.Rear")),
}  # fmt: skip


def _marker_frame(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(3, 3) world_from_frame of three markers: +Y a -> b, +X towards c."""
    y = (b - a) / np.linalg.norm(b - a)
    x = (c - b) - y * ((c - b) @ y)
    x /= np.linalg.norm(x)
    return np.stack([x, y, np.cross(x, y)], axis=1)


def hinge_axes() -> list[str]:
    """The gait2354 knee and ankle axes in opensim-gait2354.toml's bones.

    Each joint's first rotation axis (its coordinate's) is taken from
    subject01_simbody.osim at the default pose into the frame of the model's markers on
    one segment, then through the same markers in subject01_static.trc (medians) into
    the bone as the construction builds it there (calibrated on that static). The
    angle between that route and the one through the joint's other segment is printed
    as a check (the static stands at the model's default pose when it is small).
    """
    import opensim as osim
    from scipy.spatial.transform import Rotation

    def vec(v: Any) -> np.ndarray:
        return np.array([v.get(i) for i in range(3)])

    def mat(r: Any) -> np.ndarray:
        return np.array([[r.get(i, j) for j in range(3)] for i in range(3)])

    osim.Logger.setLevelString("error")
    static = load_take(OSIM_STATIC)
    col = {n: i for i, n in enumerate(static.labels)}
    rig = load_rig(RIG_OPENSIM)
    meas = pelvis_measurements(
        static.positions, static.labels, ("R.ASIS", "L.ASIS"), ("V.Sacral",)
    )
    cal = calibrate(rig, static.positions, static.labels, overrides=meas)
    solved = BodySolver(rig, cal, static.labels).solve_take(static.positions)
    lines = []
    with in_temp_dir():
        model = osim.Model(str(OSIM))
        state = model.initSystem()
        model.realizePosition(state)
        markers = model.getMarkerSet()
        for side in "rl":
            for joint, (bone, own, other) in OSIM_HINGES.items():
                j = model.getJointSet().get(joint.format(s=side))
                axis = osim.CustomJoint.safeDownCast(j).getSpatialTransform()
                axis = vec(axis.getTransformAxis(0).get_axis())
                axis_g = mat(j.getParentFrame().getTransformInGround(state).R()) @ axis
                routes = []
                for names in (own, other):
                    full = [f"{side.upper()}.{n}" for n in names]
                    in_model = _marker_frame(
                        *[vec(markers.get(n).getLocationInGround(state)) for n in full]
                    )
                    in_static = _marker_frame(
                        *[
                            np.nanmedian(static.positions[:, col[n]], axis=0)
                            for n in full
                        ]
                    )
                    routes.append(in_static @ (in_model.T @ axis_g))
                b = solved.bone_names.index(bone.format(s=side))
                q = np.median(solved.world_from_bone_quat[:, b], axis=0)
                world_from_bone = Rotation.from_quat(
                    q / np.linalg.norm(q), scalar_first=True
                ).as_matrix()
                in_bone = world_from_bone.T @ routes[0]
                check = np.degrees(np.arccos(min(1.0, abs(routes[0] @ routes[1]))))
                off_x = np.degrees(np.arccos(min(1.0, abs(in_bone[0]))))
                model_axis = np.round(axis, 3).tolist()
                lines.append(
                    f"{joint.format(s=side)} (model axis {model_axis}): "
                    f"[fit.bones.{bone.format(s=side)}] axis = "
                    f"{np.round(in_bone, 3).tolist()}  ({off_x:.1f} deg from +X; "
                    f"other segment's route {check:.1f} deg away)"
                )
    return lines


# ---- report -------------------------------------------------------------------------


def agreement(run: Run, ref: Run) -> dict[str, float]:
    """Joint -> median distance (mm) between ``run``'s and ``ref``'s centres (frames
    after the first)."""
    out = {}
    for j, c in run.centres.items():
        if j in ref.centres:
            d = np.linalg.norm(c[1:] - ref.centres[j][1:], axis=-1)
            d = d[np.isfinite(d)]
            if d.size:
                out[j] = float(1000 * np.median(d))
    return out


def _angle_deg(rot: np.ndarray) -> np.ndarray:
    """(...,) rotation angle (deg) of (..., 3, 3) rotation matrices."""
    cos = 0.5 * (np.trace(rot, axis1=-2, axis2=-1) - 1.0)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def axis_agreement(run: Run, ref: Run) -> dict[str, dict[str, float]]:
    """Segment -> how ``run``'s frame turns against ``ref``'s (frames after the first).

    ``R_rel(t) = R_ref(t)^T R_run(t)``; its mean (the rotation nearest the average
    matrix) is the two frames' fixed difference of convention, ``offset_deg``; the
    angle of each ``R_rel(t)`` from it, ``median_deg`` and ``p95_deg``, is how
    differently the two turn the segment."""
    out = {}
    for b, rot in run.frames.items():
        if b not in ref.frames:
            continue
        rel = np.swapaxes(ref.frames[b][1:], -1, -2) @ rot[1:]
        u, _, vt = np.linalg.svd(rel.mean(axis=0))
        mean = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
        dev = _angle_deg(np.swapaxes(mean, -1, -2)[None] @ rel)
        out[b] = {
            "offset_deg": float(_angle_deg(mean)),
            "median_deg": float(np.median(dev)),
            "p95_deg": float(np.percentile(dev, 95)),
        }
    return out


def table(
    runs: list[Run],
    bases: list[Run],
    markers: tuple[str, ...],
    without: tuple[str, ...] = (),
) -> list[str]:
    """Markdown rows: solver, first, median, p99, the ratio of its median to each
    retargetd solver's (``bases``), residual RMS over ``markers`` (and over them
    ``without`` some, when given)."""
    short = [b.name.removeprefix("retargetd ") for b in bases]
    rest = tuple(m for m in markers if m not in without)
    head = f" | marker residual RMS mm ({len(markers)} markers) |"
    if without:
        head += f" RMS mm without {' '.join(without)} |"
    rows = [
        "| solver | first frame ms | median ms | p99 ms | "
        + " | ".join(f"median / {n}" for n in short)
        + head,
        "|---|---|---|---|" + "---|" * len(bases) + "---|" + "---|" * bool(without),
    ]
    medians = [b.stats()["median_ms"] for b in bases]
    for r in runs:
        s = r.stats(markers)
        ratios = " | ".join(f"{s['median_ms'] / m:.3g}x" for m in medians)
        row = (
            f"| {r.name} | {s['first_ms']:.3g} | {s['median_ms']:.4g} | "
            f"{s['p99_ms']:.4g} | {ratios} | {s['residual_rms_mm']:.1f} |"
        )
        if without:
            row += f" {r.stats(rest)['residual_rms_mm']:.1f} |"
        rows.append(row)
    return rows


def plot(runs: list[Run], path: Path, load: str) -> None:
    """Per-frame time distributions (frames after the first), log scale."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 0.55 * len(runs) + 1.6))
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    data = [np.asarray(r.ns[1:]) / 1e6 for r in runs]
    ax.boxplot(
        data,
        orientation="horizontal",
        whis=(1, 99),
        showfliers=True,
        flierprops={"markersize": 2},
    )
    ax.set_yticks(range(1, len(runs) + 1), [f"{r.name} ({r.problem})" for r in runs])
    ax.set_xscale("log")
    ax.invert_yaxis()
    ax.set_xlabel("time per frame, ms (log; box: quartiles, whiskers: p1-p99)")
    ax.set_title(f"one frame at a time, same run; load {load}")
    ax.grid(True, axis="x", which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def load_average() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--frames", metavar="a:b", help="rows of both takes (default all)"
    )
    parser.add_argument(
        "--method", choices=("construction", "fit", "all"), default="all"
    )
    parser.add_argument(
        "--calibrate-frames",
        metavar="a:b",
        default="0:10",
        help="bioptim take rows to calibrate on (it has no static)",
    )
    parser.add_argument("--json", metavar="OUT.json")
    parser.add_argument("--plot", metavar="OUT.png")
    parser.add_argument(
        "--hinge-axes",
        action="store_true",
        help="print the gait2354 knee and ankle axes in opensim-gait2354.toml's bones "
        "and exit",
    )
    args = parser.parse_args(argv)
    if not PEERS.is_dir():
        print(f"peers data not found at {PEERS}")
        return 2
    if args.hinge_axes:
        print("\n".join(hinge_axes()))
        return 0
    warm_up()
    warm_up_fit()
    print(f"load before: {load_average()} ({os.cpu_count()} cores)")
    out: dict[str, Any] = {"load_before": load_average(), "problems": {}}
    all_runs: list[Run] = []
    lines: list[str] = []

    # biorbd's problem.
    take = load_take(BIOPTIM_TAKE)
    frames = parse_frames(args.frames, take.n_frames, option="--frames")
    rig = load_rig(RIG_BIOPTIM)
    base = parse_frames(
        args.calibrate_frames, take.n_frames, option="--calibrate-frames"
    )
    meas = pelvis_measurements(
        take.positions[base], take.labels, ("RASIS", "LASIS"), ("RPSIS", "LPSIS")
    )
    cal = calibrate(rig, take.positions[base], take.labels, overrides=meas)
    ours = retargetd_runs(
        "biorbd",
        rig,
        cal,
        take,
        frames,
        args.method,
        (take.positions[base], take.labels),
    )
    peers, info = biorbd_runs(frames)
    info["calibration"] = {"frames": args.calibrate_frames, **meas}
    markers = tuple(peers[0].residual_m)  # biorbd's 75 model markers
    lines += _section(
        "biorbd: bioptim whole-body model and gait take", info, ours, peers, markers
    )
    out["problems"]["biorbd"] = _doc(info, ours, peers, markers)
    all_runs += ours + peers

    # OpenSim's problem.
    take = load_take(OSIM_WALK)
    static = load_take(OSIM_STATIC)
    frames = parse_frames(args.frames, take.n_frames, option="--frames")
    rig = load_rig(RIG_OPENSIM)
    meas = pelvis_measurements(
        static.positions, static.labels, ("R.ASIS", "L.ASIS"), ("V.Sacral",)
    )
    cal = calibrate(rig, static.positions, static.labels, overrides=meas)
    ours = retargetd_runs(
        "opensim",
        rig,
        cal,
        take,
        frames,
        args.method,
        (static.positions, static.labels),
    )
    peers, info = opensim_runs(frames, np.asarray(take.world_from_capture))
    info["calibration"] = {"static": OSIM_STATIC.name, **meas}
    markers = tuple(peers[0].residual_m)  # the markers of OpenSim's IK tasks
    lines += _section(
        "OpenSim: gait2354 / subject01 walk",
        info,
        ours,
        peers,
        markers,
        OSIM_ACROMIONS,
    )
    out["problems"]["opensim"] = _doc(info, ours, peers, markers, OSIM_ACROMIONS)
    all_runs += ours + peers

    out["load_after"] = load_average()
    lines.append(
        f"load (1, 5, 15 min) before {out['load_before']}, after {out['load_after']}"
    )
    print("\n".join(lines))
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1) + "\n")
    if args.plot:
        plot(all_runs, Path(args.plot), f"{out['load_before']} -> {out['load_after']}")
    return 0


def _section(
    title: str,
    info: dict[str, Any],
    ours: list[Run],
    peers: list[Run],
    markers: tuple[str, ...],
    without: tuple[str, ...] = (),
) -> list[str]:
    lines = ["", f"## {title}", "", "setup: " + json.dumps(info), ""]
    lines += table(ours + peers, ours, markers, without)
    lines += [
        "",
        f"residual over the peer's {len(markers)} markers: {' '.join(markers)}",
    ]
    for r in ours + peers:
        worst = sorted(r.marker_rms_mm().items(), key=lambda kv: -kv[1])
        worst = [kv for kv in worst if kv[0] in markers][:6]
        lines.append(
            f"- {r.name}, largest per-marker RMS mm: "
            + ", ".join(f"{m} {v:.0f}" for m, v in worst)
        )
    for ref in ours:
        lines += ["", f"joint-centre agreement with {ref.name}, median mm:", ""]
        for r in [*ours, *peers]:
            if r is ref:
                continue
            agree = agreement(r, ref)
            lines.append(
                f"- {r.name}: "
                + ", ".join(f"{j} {d:.0f}" for j, d in sorted(agree.items()))
            )
        lines += [
            "",
            f"segment axes against {ref.name}, deg (offset: fixed difference of "
            "convention; median / p95: angle from it per frame):",
            "",
        ]
        for r in [*ours, *peers]:
            if r is ref:
                continue
            axes = axis_agreement(r, ref)
            lines.append(
                f"- {r.name}: "
                + ", ".join(
                    f"{b} {a['offset_deg']:.0f} / {a['median_deg']:.1f} / "
                    f"{a['p95_deg']:.1f}"
                    for b, a in axes.items()
                )
            )
    return lines


def _doc(
    info: dict[str, Any],
    ours: list[Run],
    peers: list[Run],
    markers: tuple[str, ...],
    without: tuple[str, ...] = (),
) -> dict[str, Any]:
    rest = tuple(m for m in markers if m not in without)
    return {
        "setup": info,
        "residual_markers": list(markers),
        "residual_without": list(without),
        "solvers": {
            r.name: {
                **r.stats(markers),
                "residual_rms_mm_without": r.stats(rest)["residual_rms_mm"],
                "marker_rms_mm": r.marker_rms_mm(),
                "agreement_mm": {ref.name: agreement(r, ref) for ref in ours},
                "axes_deg": {ref.name: axis_agreement(r, ref) for ref in ours},
                "ns": r.ns,
            }
            for r in ours + peers
        },
    }


if __name__ == "__main__":
    sys.exit(main())
