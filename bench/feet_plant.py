"""Feet that plant (issue 34, item 3): stance-foot skate and penetration on targets
whose legs are 0.8x, 1.0x and 1.25x the performer's, without and with
``[target] feet = "plant"``; the knee at the blend edges; the swing paths.

    python bench/feet_plant.py --out docs/feet.md [--seconds 8] [--rate 120]
        [--no-real] [--no-rom] [--live]

The synthetic performer (``daemon/synth``, Plug-in Gait markers: its TOE marker rides
on the foot, so the solved foot is the foot while the toes extend at push-off; noise
0) walks straight (``level_walk``), runs (``run``, with a flight phase), climbs and
descends 0.17 m stairs (``stair_ascent``, ``stair_descent``): gaits placed from their
stance feet, which neither slide nor sink (``synth/gait.py``). It is calibrated
on its own T-pose hold, solved with the construction, retargeted onto a humanoid
target (the default humanoid's torso and arms) whose leg segments (thigh, shank,
ankle height, foot) are k times the calibrated performer's, and run through three
ways:

- ``free``: the rotations alone (the retarget's root scaled by the hips-height ratio);
- ``scaled``: the root scaled by the leg-length ratio, no foot held (the plant stage
  with no contact): the unplanted path the swing is compared with;
- ``plant``: ``feet = "plant"`` (``daemon/post/plant.py``), the stance detector's
  contact (``daemon/post/stance.py``) on the solve.

Measured on the target (forward kinematics of the emitted pose), per foot, over the
frames the detector marks in contact (its contact is the performer's):

- **skate**: per frame, the horizontal travel of the foot's floor points (the heel,
  and the floor point under the MTP joint: the target's Toes joint less its rest
  height, the ball on a target without toes; those within 1 cm of the lowest), the
  least of them; summed over each contact run. Columns: the p95 over contact frames
  and the p95 over runs of that sum, mm. From heel-off the foot rolls about its MTP
  joint, the toes flat on the floor: the floor point under the joint stays put, the
  ball (a point of the foot under it at rest) rises and moves back. On the synthetic
  performer's own body (the truth), the ball travels 12.6 mm a contact on the walk
  and 10.8-12.3 on the run, the point under the MTP 0.00;
- **sink**: the foot's lowest point (heel, ball, toe tip) below its support level (the
  detector's, times the leg ratio; for a synthetic gait the truth's floor or step,
  times the leg ratio, over the frames both the truth and the detector call contact),
  max over contact frames, mm;
- **float**: the same point above that level, max, mm: ``scaled`` (the unplanted
  foot, the root scaled by the leg ratio: where the solve stands it) and ``plant``;
- **knee**: at the blend edges (the frame before each contact onset through the
  blend-in, the frame before each release through the blend-out), the most the plant
  adds to the knee's frame-to-frame change (|d flex plant - d flex scaled|), deg;
- **swing**: in swing once the release has blended out, the largest distance of the
  planted ankle from the scaled one, mm;
- **unreached**: frames flagged ``plant_unreached``;
- **events** (synthetic gaits): each contact onset and release of the truth
  (``synth --truth``'s ``foot_contact``) from its first heel strike on, the frames to
  the detector's nearest of the same kind: median / max (count).

The synthetic performer is calibrated twice: on its base pose alone (Plug-in Gait's
hip centres by Davis's regression, 12 mm below the performer's and 7 mm ahead), and
on its base pose and its range of motion (``calibrate --rom``: the hip centres from
how the thigh markers move; ``--no-rom`` leaves these rows out). The regression's hip
leaves the solved thigh 12 mm short, so a flexed thigh puts the solved foot low: on a
stair it lands up to 2.3 mm below the step (legs 1x), which the plant, live, cannot
tell from the step (docs/feet.md).

With ``--no-real`` the real takes are left out; else the takes in
``../shared/datasets`` (the PiG walk, OpenSim's subject01 walk, the MOTEK ballet, the
tennis serve), each calibrated as in ``bench/batch_datasets.toml``, on the default
humanoid, ``free`` against ``plant``.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.calibration import calibrate
from retargetd.daemon.body.method import make_body_solver
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.post import plant as plant_mod
from retargetd.daemon.post.plant import PLANT, FootPlant, foot_points, performer_leg_m
from retargetd.daemon.post.stance import (
    CONTACT_COLUMN,
    SUPPORT_COLUMN,
    StanceDetector,
    take_stance_states,
)
from retargetd.daemon.retarget.retarget import Retargeter, default_humanoid
from retargetd.daemon.retarget.skeleton import TargetSkeleton
from retargetd.daemon.synth import performer as pf
from retargetd.daemon.synth.motion import GAIT_MOTIONS
from retargetd.daemon.synth.skeleton import make_skeleton
from retargetd.daemon.validate.limits import JOINT_LIMITS_DEG
from retargetd.daemon.validate.model import SEGMENT_KIND

REPO = Path(__file__).resolve().parent.parent
DATASETS = REPO.parent / "shared" / "datasets"
ACTIVITIES = ("level_walk", "run", "stair_ascent", "stair_descent")
LEG_SCALES = (0.8, 1.0, 1.25)
#: The synthetic performer's marker set and rig: Plug-in Gait's TOE marker rides on
#: the foot (the 2nd metatarsal head), so the solved foot is the foot when the toes
#: extend at push-off (menache's toe marker rides on the toes).
SYNTH_RIG = "plug-in-gait"
#: The range of motion's length for ``--rom`` (:func:`synthetic`): its ramp and one
#: period of ``synth.motion.ROM_PERIOD_S`` (12 s: each leg circles its hip for 6 s),
#: as ``tests/daemon/test_functional.py`` takes it.
ROM_SECONDS = 25.0
#: A floor point: within this of the foot's lowest (the plant's pivot_switch_m).
ON_FLOOR_M = PLANT["pivot_switch_m"]
_SIDES = ("Left", "Right")
#: The skate's forefoot point (module docstring): the floor point under the MTP joint.
BALL = "under_mtp"


def leg_target(
    rig: Any, calibration: Any, k: float, take: Any = None
) -> TargetSkeleton:
    """The default humanoid with legs k times the calibrated performer's: each leg
    segment (hip to knee, knee to ankle, ankle to the foot bone's aim) the
    performer's calibrated one, scaled by k and pointing where it points in the
    calibration pose (so the calibration pose maps onto the target's rest, feet on
    its floor); the torso and arms the default's, the hips raised or lowered with the
    legs. Target axes: x to the right, y forward, z up (the performer faces +x).

    With the synthetic ``take``, the target's Toes joint is the performer's MTP joint
    and its toes reach the performer's toe tip (the truth's skeleton, times k), so
    the target's foot rolls where the performer's does: the calibrated foot's aim is
    Plug-in Gait's TOE marker, on the dorsum over the 2nd metatarsal head, 21 mm above
    the joint and 7.5 mm behind it on the synthetic performer (1x)."""
    base = default_humanoid()
    origins = np.asarray(calibration.rest_bone_origin_pos)
    names = list(calibration.bone_names)
    rest = np.asarray(calibration.rest_world_from_bone_quat)
    lengths = np.asarray(calibration.bone_lengths)

    def bone(h: str) -> int:
        return names.index(rig.humanoid[h])

    def joint(h: str) -> np.ndarray:
        return origins[bone(h)]

    def to_target(v: np.ndarray) -> np.ndarray:
        return np.array([-v[1], v[0], v[2]])  # world (fwd, left, up) -> target

    hip_drop = 0.05  # the default's UpperLeg below its Hips
    hip_z = float(np.mean([joint(s + "UpperLeg")[2] for s in _SIDES]))
    offsets = np.array(base.rest_offsets)
    aims = np.array(base.aim_offsets)
    hips = hip_drop + k * hip_z
    offsets[0] = (0.0, 0.0, hips)
    for s, sx in (("Left", -1.0), ("Right", 1.0)):
        i = {b: base.index(s + b) for b in ("UpperLeg", "LowerLeg", "Foot", "Toes")}
        f = bone(s + "Foot")
        toe = origins[f] + rot.quat_rotate(rest[f], np.array([0.0, lengths[f], 0.0]))
        offsets[i["UpperLeg"]] = (sx * 0.09, 0.0, -hip_drop)
        offsets[i["LowerLeg"]] = k * to_target(
            joint(s + "LowerLeg") - joint(s + "UpperLeg")
        )
        offsets[i["Foot"]] = k * to_target(joint(s + "Foot") - joint(s + "LowerLeg"))
        offsets[i["Toes"]] = k * to_target(toe - joint(s + "Foot"))
        aims[i["UpperLeg"]] = offsets[i["LowerLeg"]]
        aims[i["LowerLeg"]] = offsets[i["Foot"]]
        aims[i["Foot"]] = offsets[i["Toes"]]
        aims[i["Toes"]] = k * np.array([0.0, 0.05, 0.0])  # flat toes ahead
        if take is not None:
            names_t = list(take.segment_names)
            side = s[0].lower()
            mtp = np.asarray(take.rest_offsets)[names_t.index(f"{side}_toes")]
            offsets[i["Toes"]] = k * to_target(mtp)
            aims[i["Foot"]] = offsets[i["Toes"]]
            sk = make_skeleton(take.height_m)
            toes = sk.names.index(f"{side}_toes")
            tip = [p for g, p in zip(sk.sole_segments, sk.sole_points, strict=True)
                   if g == toes]  # fmt: skip
            aims[i["Toes"]] = k * to_target(np.asarray(tip[0]))
    return dataclasses.replace(
        base,
        name=f"humanoid, legs {k:g}x",
        rest_offsets=offsets,
        aim_offsets=aims,
        hips_height=float(hips),
    )


def run_modes(
    res: Any,
    rig: Any,
    cal: Any,
    target: TargetSkeleton,
    rate_hz: float,
    live: bool = False,
) -> dict[str, Any]:
    """The solve through ``free``, ``scaled`` and ``plant`` (module docstring): each
    way's target ``wfb`` (T, N, 4) and ``root`` (T, 3); the detector's ``contact``
    (T, 2) and ``support`` (T, 2) (the performer's, metres; offline, a contact off
    the floor the plant's own settled level over the leg ratio); ``flags`` (T,);
    ``leg_ratio``. ``live``: the plant fed the detector's state frame by frame, as
    the daemon's (``live/send.py``), instead of the offline settled support."""
    rt = Retargeter(rig, cal, target)
    leg = performer_leg_m(rig, cal)
    plant = FootPlant(target, rt.root_scale, leg)
    scaled = FootPlant(target, rt.root_scale, leg)
    no_contact = np.zeros((2, 4))
    # As ``solve --plant-feet`` (cli/post_io.retarget_solve): the detector over the
    # whole take, each contact's support the level it settled on; live, the
    # detector's state of each frame.
    take_args = (
        rig, cal, np.ascontiguousarray(res.root_pos, dtype=np.float64),
        np.ascontiguousarray(res.world_from_bone_quat, dtype=np.float64), rate_hz,
    )  # fmt: skip
    states = live_stance_states(*take_args) if live else take_stance_states(*take_args)
    n_frames, n = len(res.root_pos), len(target.bone_names)
    out: dict[str, Any] = {
        m: {"wfb": np.empty((n_frames, n, 4)), "root": np.empty((n_frames, 3))}
        for m in ("free", "scaled", "plant")
    }
    pre = {k: np.empty((n_frames, *a.shape)) for k, a in (
        ("wfb", np.zeros((n, 4))), ("rfb", np.zeros((n, 4))), ("root", np.zeros(3)),
        ("hips", np.zeros(3)))}  # fmt: skip
    pose = rt.new_pose()
    for t in range(n_frames):
        rt.apply(_Frame(res, t), pose)  # type: ignore[arg-type]
        pre["wfb"][t], pre["rfb"][t] = (
            pose.world_from_bone_quat,
            pose.rest_from_bone_quat,
        )
        pre["root"][t], pre["hips"][t] = pose.root_pos, pose.hips_pos
    if not live:  # as cli/post_io.retarget_solve: each level settled per contact
        states = plant.hold_settled(
            pre["wfb"], pre["rfb"], pre["root"], pre["hips"], states, rate_hz
        )
    contact = np.zeros((n_frames, 2), bool)
    support = np.zeros((n_frames, 2))
    flags = np.zeros(n_frames, np.uint32)
    for t in range(n_frames):
        contact[t] = states[t, :, CONTACT_COLUMN] != 0.0
        support[t] = states[t, :, SUPPORT_COLUMN]
        for mode in ("free", "scaled", "plant"):
            wfb, rfb = pre["wfb"][t].copy(), pre["rfb"][t].copy()
            root, hips = pre["root"][t].copy(), pre["hips"][t].copy()
            if mode == "scaled":
                scaled.apply(wfb, rfb, root, hips, no_contact, t / rate_hz)
            elif mode == "plant":
                flags[t] = plant.apply(wfb, rfb, root, hips, states[t], t / rate_hz)
            out[mode]["wfb"][t] = wfb
            out[mode]["root"][t] = root
    out.update(contact=contact, support=support, flags=flags,
               leg_ratio=plant.leg_ratio)  # fmt: skip
    return out


def live_stance_states(
    rig: Any, cal: Any, root_pos: np.ndarray, wfb: np.ndarray, rate_hz: float
) -> np.ndarray:
    """(T, 2, 5) the live detector's state after each frame (what the daemon's plant
    reads: ``live/send.py``)."""
    det = StanceDetector(rig, cal)
    out = np.zeros((len(root_pos), 2, 5))
    for t in range(len(root_pos)):
        det.update(root_pos[t], wfb[t], 1.0 / rate_hz if t else 0.0)
        out[t] = det.state
    return out


class _Frame:
    """One solved frame as ``Retargeter.apply`` reads it."""

    def __init__(self, res: Any, t: int) -> None:
        self.world_from_bone_quat = np.ascontiguousarray(
            res.world_from_bone_quat[t], dtype=np.float64
        )
        self.root_pos = np.ascontiguousarray(res.root_pos[t], dtype=np.float64)
        self.bone_flags = np.ascontiguousarray(res.bone_flags[t])


def foot_geometry(target: TargetSkeleton, wfb: np.ndarray, root: np.ndarray) -> dict:
    """Forward kinematics of a target take (T frames): per side (2,) ``heel``,
    ``ball``, ``tip``, ``ankle``, ``under_mtp`` (the floor point under the Toes joint:
    the joint less its rest height, :func:`~retargetd.daemon.post.plant.roll_radius`)
    (T, 2, 3) and the knee flexion ``knee_deg`` (T, 2)."""
    delta = rot.quat_mul(wfb, rot.quat_conj(target.rest_world_from_bone_quat))
    n_frames, n = wfb.shape[:2]
    x = np.zeros((n_frames, n, 3))
    x[:, 0] = root + target.rest_offsets[0]
    for i in range(1, n):
        p = target.parents[i]
        x[:, i] = x[:, p] + rot.quat_rotate(delta[:, p], target.rest_offsets[i])
    heel_v, ball_v = foot_points(target)
    roll_r = plant_mod.roll_radius(target)
    g: dict[str, np.ndarray] = {
        k: np.zeros((n_frames, 2, 3))
        for k in ("heel", "ball", "tip", "ankle", "under_mtp")
    }
    g["knee_deg"] = np.zeros((n_frames, 2))
    for s, side in enumerate(_SIDES):
        ul, ll, ft, to = (
            target.index(side + b) for b in ("UpperLeg", "LowerLeg", "Foot", "Toes")
        )
        g["ankle"][:, s] = x[:, ft]
        g["heel"][:, s] = x[:, ft] + rot.quat_rotate(delta[:, ft], heel_v[s])
        g["ball"][:, s] = x[:, ft] + rot.quat_rotate(delta[:, ft], ball_v[s])
        up = np.array([0.0, 0.0, roll_r[s]])
        g["under_mtp"][:, s] = (
            x[:, ft] + rot.quat_rotate(delta[:, ft], ball_v[s] + up) - up
        )
        g["tip"][:, s] = x[:, to] + rot.quat_rotate(
            delta[:, to], target.aim_offsets[to]
        )
        a, b = x[:, ll] - x[:, ul], x[:, ft] - x[:, ll]
        cos = (
            np.sum(a * b, -1) / np.linalg.norm(a, axis=-1) / np.linalg.norm(b, axis=-1)
        )
        g["knee_deg"][:, s] = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return g


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, stop) of each run of True."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1), strict=True))


def skate_sink(
    g: dict, contact: np.ndarray, floor: np.ndarray, sink_on: np.ndarray | None = None
) -> dict[str, float]:
    """Skate (per contact frame and per contact run, mm) and sink (mm; over the
    frames ``sink_on``, default ``contact``) of one way, both feet pooled (module
    docstring)."""
    per_frame, per_run, sink, above = [], [], [], []
    on_ = contact if sink_on is None else sink_on
    for s in range(2):
        pts = np.stack([g["heel"][:, s], g[BALL][:, s]], axis=1)  # (T, 2, 3)
        low = np.minimum(
            np.minimum(g["heel"][:, s, 2], g["ball"][:, s, 2]), g["tip"][:, s, 2]
        )
        below = np.maximum(floor[:, s] - low, 0.0)[on_[:, s]]
        sink.extend(below)
        above.extend(np.maximum(low - floor[:, s], 0.0)[on_[:, s]])
        for a, b in _runs(contact[:, s]):
            if b - a < 2:
                continue
            step = np.linalg.norm(np.diff(pts[a:b, :, :2], axis=0), axis=-1)  # (n, 2)
            on = (
                pts[a + 1 : b, :, 2]
                <= pts[a + 1 : b, :, 2].min(-1, keepdims=True) + ON_FLOOR_M
            )
            d = np.where(on, step, np.inf).min(axis=1)
            per_frame.extend(d)
            per_run.append(d.sum())
    pf_ = np.asarray(per_frame) * 1e3
    pr = np.asarray(per_run) * 1e3
    return {
        "frames": int(contact.sum()),
        "runs": len(per_run),
        "skate_frame_p95_mm": float(np.percentile(pf_, 95)) if pf_.size else np.nan,
        "skate_run_p95_mm": float(np.percentile(pr, 95)) if pr.size else np.nan,
        "skate_run_max_mm": float(pr.max()) if pr.size else np.nan,
        "sink_max_mm": float(np.max(sink) * 1e3) if sink else 0.0,
        "float_p95_mm": float(np.percentile(above, 95) * 1e3) if above else 0.0,
    }


def edges_and_swing(
    gp: dict, gs: dict, contact: np.ndarray, rate_hz: float
) -> dict[str, float]:
    """The knee at the blend edges and the swing paths (module docstring)."""
    n_in = int(np.ceil(PLANT["blend_in_s"] * rate_hz))
    n_out = int(np.ceil(PLANT["blend_out_s"] * rate_hz))
    n_frames = len(contact)
    added, raw = [0.0], [0.0]
    swing = [0.0]
    for s in range(2):
        dp = np.abs(np.diff(gp["knee_deg"][:, s]))
        ds = np.abs(np.diff(gs["knee_deg"][:, s]))
        extra = np.abs(np.diff(gp["knee_deg"][:, s]) - np.diff(gs["knee_deg"][:, s]))
        edge = np.zeros(n_frames - 1, bool)
        free = ~contact[:, s].copy()
        for a, b in _runs(contact[:, s]):
            edge[max(a - 1, 0) : min(a + n_in, n_frames - 1)] = True
            edge[max(b - 1, 0) : min(b + n_out, n_frames - 1)] = True
            free[b : b + n_out] = False
        if edge.any():
            added.append(float(extra[edge].max()))
            raw.append(float(dp[edge].max()))
        del ds
        d = np.linalg.norm(gp["ankle"][:, s] - gs["ankle"][:, s], axis=-1)[free]
        if d.size:
            swing.append(float(d.max() * 1e3))
    return {
        "knee_added_deg": max(added),
        "knee_edge_deg": max(raw),
        "swing_max_mm": max(swing),
    }


def event_errors(detected: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """|frames| from each truth contact event (onset or release, either foot) to the
    nearest detected event of the same kind and foot, from the truth's first onset
    on (gait initiation, when a foot is let go while it still stands, is left out);
    a truth event with no detected one gets the take's length."""
    out = []
    for s in range(2):
        d = np.diff(detected[:, s].astype(np.int8))
        g = np.diff(truth[:, s].astype(np.int8))
        first = np.flatnonzero(g == 1)
        if not first.size:
            continue
        for kind in (1, -1):
            det = np.flatnonzero(d == kind)
            for e in np.flatnonzero(g == kind):
                if e < first[0]:
                    continue
                near = np.abs(det - e).min() if det.size else len(truth)
                out.append(int(near))
    return np.asarray(out, dtype=np.int64)


def measure(
    res: Any,
    rig: Any,
    cal: Any,
    target: TargetSkeleton,
    rate_hz: float,
    truth: Any = None,
    live: bool = False,
) -> dict[str, Any]:
    """Every figure of one take on one target (module docstring). With ``truth``
    (the synthetic take of a gait, ``synth.motion.GAIT_MOTIONS``): the contact
    events against its ``foot_contact``, and the sink against its supports (floor or
    step, times the leg ratio) over the frames both it and the detector call
    contact. ``live``: as :func:`run_modes`."""
    ways = run_modes(res, rig, cal, target, rate_hz, live)
    contact, k = ways["contact"], ways["leg_ratio"]
    floor = ways["support"] * k
    sink_on = contact
    events = np.zeros(0, dtype=np.int64)
    if truth is not None and set(truth.motions) & set(GAIT_MOTIONS):
        floor = (np.asarray(truth.foot_support_m) - truth.origin_world[2]) * k
        sink_on = contact & np.asarray(truth.foot_contact)
        events = event_errors(contact, np.asarray(truth.foot_contact))
    geo = {m: foot_geometry(target, ways[m]["wfb"], ways[m]["root"])
           for m in ("free", "scaled", "plant")}  # fmt: skip
    out = {
        "leg_ratio": k,
        "free": skate_sink(geo["free"], contact, floor, sink_on),
        "scaled": skate_sink(geo["scaled"], contact, floor, sink_on),
        "plant": skate_sink(geo["plant"], contact, floor, sink_on),
        **edges_and_swing(geo["plant"], geo["scaled"], contact, rate_hz),
        "unreached": int(np.count_nonzero(ways["flags"])),
        "n_frames": len(contact),
        "events_frames": events,
    }
    return out


def synthetic(
    activity: str,
    seconds: float,
    rate_hz: float,
    rig_name: str = SYNTH_RIG,
    rom: bool = False,
) -> tuple[Any, ...]:
    """(solve, rig, calibration, take) of the synthetic performer doing
    ``activity``, wearing ``rig_name``'s marker set. ``rom``: calibrated as
    ``calibrate --rom`` does, its base pose and its range of motion (``synth
    --motions rom``, :data:`ROM_SECONDS`, the same performer): the rig's functional
    joints (Plug-in Gait's hip centres and knee axes) from how the markers move, not
    from the regression (README "Functional joints")."""
    take = pf.synthesize(
        seconds=seconds,
        rate_hz=rate_hz,
        markerset=rig_name,
        motions=(activity,),
        seed=0,
    )
    rig = load_rig(rig_name)
    motion = None
    if rom:
        r = pf.synthesize(seconds=ROM_SECONDS, rate_hz=rate_hz, markerset=rig_name,
                          motions=("rom",), seed=0)  # fmt: skip
        motion = (r.markers_world, r.labels, {"take": "synth --motions rom"})
    cal = calibrate(
        rig, take.markers_world[: int(0.5 * rate_hz)], take.labels, rom=motion
    )
    solver = make_body_solver(
        "construction", rig, cal, take.labels,
        joint_limits=JOINT_LIMITS_DEG, segment_kind=SEGMENT_KIND,
    )  # fmt: skip
    return solver.solve_take(take.markers_world), rig, cal, take


#: The real takes, calibrated as ``bench/batch_datasets.toml`` does: (label, take,
#: rig, static take or None, base-pose rows, measurements).
REAL = (
    ("PiG walk", "btkdata/PiG_Motion-FlatFoot-Full.c3d", "plug-in-gait",
     "btkdata/PiG_Calibration-FlatFoot-Full.c3d", None, ()),
    ("OpenSim subject01 walk", "opensim-core/subject01_walk1.trc", "opensim-gait2354",
     "opensim-core/subject01_static.trc", None,
     ("PelvisWidth=262.3", "PelvisDepth=198.6")),
    ("MOTEK ballet", "btkdata/MOTEK_ballet_reduced.trc", "cmu41",
     "btkdata/MOTEK_T.trc", None, ()),
    ("tennis serve", "kineticstoolkit/kinematics_tennis_serve.c3d", "cmu41", None,
     "0:50", ()),
)  # fmt: skip


def real(
    take_rel: str,
    rig_name: str,
    static_rel: str | None,
    rows: str | None,
    measures: tuple[str, ...],
    work: Path,
) -> tuple[Any, ...]:
    """(solve, rig, calibration, rate) of a real take: ``retargetd calibrate`` and
    ``retargetd solve`` (NPZ), as a user runs them."""
    import subprocess
    from types import SimpleNamespace

    from retargetd.daemon.body.calibration import load_calibration

    stem = Path(take_rel).stem
    cal_path, npz = work / f"{stem}.json", work / f"{stem}.npz"
    cli = [sys.executable, "-m", "retargetd.daemon"]
    static = DATASETS / (static_rel or take_rel)
    cmd = [*cli, "calibrate", str(static), "--rig", rig_name, "--out", str(cal_path)]
    if rows is not None:
        cmd += ["--frames", rows]
    for m in measures:
        cmd += ["--measure", m]
    subprocess.run(cmd, check=True, capture_output=True)
    subprocess.run(
        [*cli, "solve", str(DATASETS / take_rel), "--rig", rig_name, "--calibration",
         str(cal_path), "--out", str(npz), "--quiet"],
        check=True, capture_output=True,
    )  # fmt: skip
    d = np.load(npz)
    res = SimpleNamespace(
        world_from_bone_quat=d["world_from_bone_quat"],
        root_pos=d["root_pos"],
        bone_flags=d["bone_flags"],
    )
    return res, load_rig(rig_name), load_calibration(cal_path), float(d["rate_hz"])


def _row(label: str, m: dict[str, Any], *, synthetic_row: bool) -> str:
    f, s, p = m["free"], m["scaled"], m["plant"]
    cells = [
        label,
        f"{m['leg_ratio']:.2f}",
        f"{p['frames']} / {p['runs']}",
        f"{f['skate_frame_p95_mm']:.1f} / {f['skate_run_p95_mm']:.1f}",
        f"{p['skate_frame_p95_mm']:.2f} / {p['skate_run_p95_mm']:.2f}",
        f"{f['sink_max_mm']:.1f}",
        f"{p['sink_max_mm']:.2f}",
        f"{s['float_p95_mm']:.2f} / {p['float_p95_mm']:.2f}",
        f"{m['knee_added_deg']:.2f} ({m['knee_edge_deg']:.1f})",
        f"{m['swing_max_mm']:.2f}",
        str(m["unreached"]),
    ]
    if synthetic_row:
        ev = m["events_frames"]
        cells.append(f"{int(np.median(ev))} / {int(ev.max())} ({ev.size})"
                     if ev.size else "-")  # fmt: skip
    return "| " + " | ".join(cells) + " |"


HEADER = (
    "| take | leg ratio | contact frames / runs | skate free, mm (p95 frame / p95 "
    "run) | skate plant, mm | sink free, mm (max) | sink plant, mm | float, mm (p95): "
    "scaled / plant | knee at blend edges, deg: added (raw) | swing off path, mm "
    "(max) | unreached frames |\n"
    "|---|---|---|---|---|---|---|---|---|---|---|"
)
#: The synthetic sections' titles: the base pose alone (Plug-in Gait's regression hip
#: centres), and with the range of motion (``--rom``: functional hip centres).
SYNTH_TITLE = {
    False: "### Synthetic performer",
    True: "### Synthetic performer, hips from a range of motion (`calibrate --rom`)",
}
SYNTH_HEADER = (
    HEADER.split("\n")[0]
    + " contact events off the truth, frames: median / max (events) |\n"
    + HEADER.split("\n")[1]
    + "---|"
)


def main(argv: list[str] | None = None) -> int:
    """Measure and write the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, help="write the Markdown here")
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--rate", type=float, default=120.0)
    ap.add_argument("--activities", default=",".join(ACTIVITIES))
    ap.add_argument("--no-real", action="store_true")
    ap.add_argument(
        "--no-rom",
        action="store_true",
        help="leave out the synthetic rows calibrated with a range of motion",
    )
    ap.add_argument(
        "--live",
        action="store_true",
        help="feed the plant the detector's state frame by frame (the daemon's)",
    )
    args = ap.parse_args(argv)
    started = time.perf_counter()
    lines: list[str] = []
    results: dict[str, Any] = {}
    for rom in (False,) if args.no_rom else (False, True):
        lines += [SYNTH_TITLE[rom], "", SYNTH_HEADER]
        for activity in args.activities.split(","):
            res, rig, cal, take = synthetic(activity, args.seconds, args.rate, rom=rom)
            for k in LEG_SCALES:
                target = leg_target(rig, cal, k, take)
                m = measure(res, rig, cal, target, args.rate, take, args.live)
                results[f"{activity} {k:g}x{' rom' if rom else ''}"] = m
                lines.append(_row(f"{activity}, legs {k:g}x", m, synthetic_row=True))
                print(lines[-1], flush=True)
        lines.append("")
    lines.pop()
    if not args.no_real:
        lines += ["", "### Real takes (default humanoid)", "", HEADER]
        import tempfile

        work = Path(tempfile.mkdtemp(prefix="feet_plant_"))
        for label, take_rel, rig_name, static_rel, rows, measures in REAL:
            if not (DATASETS / take_rel).exists():
                lines.append(f"| {label} | (not in ../shared/datasets) |")
                continue
            res, rig, cal, rate = real(
                take_rel, rig_name, static_rel, rows, measures, work
            )
            m = measure(res, rig, cal, default_humanoid(), rate, live=args.live)
            results[label] = m
            lines.append(_row(f"{label} ({rig_name}, {rate:g} Hz)", m,
                              synthetic_row=False))  # fmt: skip
            print(lines[-1], flush=True)
    took = time.perf_counter() - started
    lines += [
        "",
        f"(measured in {took:.0f} s: `python bench/feet_plant.py --out docs/feet.md "
        f"--seconds {args.seconds:g} --rate {args.rate:g}`)",
    ]
    if args.out is not None:
        write_between(args.out, "\n".join(lines) + "\n", "feet_plant.py")
    return 0


def write_between(path: Path, table: str, script: str) -> None:
    """Replace the part of ``path`` that ``script`` generated (between its markers),
    else append it."""
    start, end = f"<!-- {script}: begin -->", f"<!-- {script}: end -->"
    text = path.read_text(encoding="utf-8") if path.exists() else ""
    if start in text and end in text:
        head, rest = text.split(start, 1)
        _, tail = rest.split(end, 1)
        text = f"{head}{start}\n{table}{end}{tail}"
    else:
        text = f"{text}{start}\n{table}{end}\n"
    path.write_text(text, encoding="utf-8")


if __name__ == "__main__":
    sys.exit(main())
