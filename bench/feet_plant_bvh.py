"""Feet that plant, BVH onto BVH (issue 34 item 2): ``retargetd retarget IN.bvh
--target T.bvh --plant-feet`` (``cli/retarget_plant.py``) on targets whose legs are
0.8x, 1.0x and 1.25x the source's, without and with the plant.

    python bench/feet_plant_bvh.py --out docs/feet.md [--seconds 8] [--rate 120]

Sources (BVH, Y up, cm):

- ``truth``: the synthetic performer's gaits (``synth/gait.py``: ``level_walk``,
  ``run``, ``stair_ascent``, ``stair_descent``; stance feet that neither slide nor
  sink) written from its true skeleton and rotations (:func:`truth_bvh`: Mixamo joint
  names, a toe joint at the MTP, the toe tip its End Site, the floor at y = 0);
- ``solve``: the level walk as ``retargetd solve --out take.bvh`` writes it from the
  Plug-in Gait solve (no toe joint: the foot aims at the TOE marker, on the dorsum
  3.5 cm above the sole).

Targets: the source's hierarchy with every offset and End Site below the hip joints
times k (:func:`scaled_target`). Measured on the written take's forward kinematics
(:func:`geometry`: the plant's heel, ball, floor point under the MTP joint and toe
tip, metres, the target's floor at 0) with ``feet_plant.py``'s measures, over the
stance detector's contact: skate (p95 over contact frames / p95 over contacts of
its sum, mm), sink below the truth's floor or step (times k; over frames both the
truth and the detector call contact), float (p95), the knee's added change at the
blend edges (and its own change there), the swing's distance from the unplanted
ankle; ``free`` is the retarget alone (the root by the rest root heights' ratio).
Also: the floor found (``bvh_legs.take_floor``) less the truth's (the truth
source's floor is y = 0; the solve's lowest rest foot point, the TOE marker, stands
on the lab floor 3.5 cm below it: that height is the truth there), and the contact
events against the truth's.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import feet_plant as fp
import numpy as np

from retargetd.daemon import rotations as rot
from retargetd.daemon.cli.retarget_plant import plant_retarget
from retargetd.daemon.post.plant_target import foot_points, roll_radius
from retargetd.daemon.retarget.bvh import BVH_FROM_WORLD, write_solve_bvh
from retargetd.daemon.retarget.bvh_legs import (
    PlantTarget,
    source_humanoid,
    target_humanoid,
)
from retargetd.daemon.retarget.bvh_retarget import global_rotations, retarget_bvh
from retargetd.daemon.synth import performer as pf
from retargetd.daemon.synth.skeleton import make_skeleton
from retargetd.protocols.conventions import world_from_capture_mat
from retargetd.replay.bvh import (
    BvhSkeleton,
    bvh_motion,
    bvh_skeleton,
    read_bvh_hierarchy,
    write_bvh,
)

CM = 0.01
#: The synthetic performer's segments as Mixamo joints.
NAMES = {
    "pelvis": "Hips", "abdomen": "Spine", "thorax": "Spine1", "neck": "Neck",
    "head": "Head",
    **{f"{s[0].lower()}_{a}": f"{s}{b}" for s in ("Left", "Right") for a, b in (
        ("clavicle", "Shoulder"), ("upper_arm", "Arm"), ("forearm", "ForeArm"),
        ("hand", "Hand"), ("thigh", "UpLeg"), ("shank", "Leg"), ("foot", "Foot"),
        ("toes", "ToeBase"))},
}  # fmt: skip


def truth_bvh(take: Any, path: Path) -> None:
    """The synthetic take's true skeleton and rotations as BVH (Y up, cm, ZXY):
    offsets ``100 M o``, rotations ``(w, M v)``, the root's position channels its
    true position (``M`` world to BVH axes, ``retarget/bvh.py``)."""
    m = np.asarray(BVH_FROM_WORLD)
    parents = [int(p) for p in take.segment_parents]
    offsets = 100.0 * np.asarray(take.rest_offsets) @ m.T
    offsets[0] = 0.0
    sk = make_skeleton(take.height_m)
    ends = np.full((len(parents), 3), np.nan)
    for g, p in zip(sk.sole_segments, sk.sole_points, strict=True):
        if take.segment_names[g].endswith("toes"):
            ends[g] = 100.0 * m @ p  # the toe tip
    for j in range(len(parents)):
        if j not in parents and not np.isfinite(ends[j]).all():
            ends[j] = 0.5 * offsets[j]
    q = np.array(take.parent_from_segment_quat, dtype=np.float64)
    q[..., 1:] = q[..., 1:] @ m.T
    skel = bvh_skeleton(
        joint_names=[NAMES[n] for n in take.segment_names], parents=parents,
        offsets=offsets, rotation_orders=["ZXY"] * len(parents), end_sites=ends,
    )  # fmt: skip
    ang = np.unwrap(np.degrees(rot.euler_from_quat(q, "ZXY")), period=360.0, axis=0)
    pos = np.full_like(ang, np.nan)
    pos[:, 0] = 100.0 * np.asarray(take.joint_pos_world)[:, 0] @ m.T
    write_bvh(path, skel, bvh_motion(skel, ang, pos), 1.0 / take.rate_hz)


def scaled_target(src: BvhSkeleton, k: float, toes: float = 1.0) -> BvhSkeleton:
    """``src``'s hierarchy with every offset and End Site below the hip joints (the
    joints the maps name UpperLeg) times ``k``, the Toes joints' times ``toes``
    more."""
    hum = source_humanoid(src)
    below: set[int] = set()
    for j, p in enumerate(src.parents):
        if p >= 0 and ((hum[p] or "").endswith("UpperLeg") or p in below):
            below.add(j)
    off, ends = np.array(src.offsets), np.array(src.end_sites)
    for j in below:
        f = k * (toes if (hum[j] or "").endswith("Toes") else 1.0)
        off[j] *= f
        ends[j] *= f
    return bvh_skeleton(
        joint_names=src.joint_names, parents=src.parents, offsets=off,
        rotation_orders=src.rotation_orders, end_sites=ends,
    )  # fmt: skip


def geometry(result: Any, legs: PlantTarget, floor_m: float) -> dict[str, Any]:
    """``feet_plant.foot_geometry``'s points of a written take, read back by BVH
    forward kinematics: world metres, the target's floor at z = 0 (the file's at
    ``floor_m``); the tip is the Toes joint's End Site, else the Foot's aim."""
    a = world_from_capture_mat("+Y")
    aq = rot.quat_from_mat(a)
    glob, pos = global_rotations(
        dataclasses.replace(result.skeleton, frames=result.frames)
    )
    p = CM * pos @ a.T
    p[..., 2] -= floor_m
    delta = rot.quat_mul(rot.quat_mul(aq, glob), rot.quat_conj(aq))
    heel_v, ball_v = foot_points(legs)
    n_frames = len(p)
    g: dict[str, Any] = {
        k: np.zeros((n_frames, 2, 3))
        for k in ("heel", "ball", "tip", "ankle", "under_mtp")
    }
    g["knee_deg"] = np.zeros((n_frames, 2))
    for s, side in enumerate(("Left", "Right")):
        ul, ll, ft = (legs.index(side + b) for b in ("UpperLeg", "LowerLeg", "Foot"))
        to = legs.index(side + "Toes") if side + "Toes" in legs.bone_names else ft
        up = np.array([0.0, 0.0, roll_radius(legs)[s]])
        g["ankle"][:, s] = p[:, ft]
        g["heel"][:, s] = p[:, ft] + rot.quat_rotate(delta[:, ft], heel_v[s])
        g["ball"][:, s] = p[:, ft] + rot.quat_rotate(delta[:, ft], ball_v[s])
        g["under_mtp"][:, s] = (
            p[:, ft] + rot.quat_rotate(delta[:, ft], ball_v[s] + up) - up
        )
        g["tip"][:, s] = p[:, to] + rot.quat_rotate(delta[:, to], legs.aim_offsets[to])
        u, v = p[:, ll] - p[:, ul], p[:, ft] - p[:, ll]
        cos = (
            np.sum(u * v, -1) / np.linalg.norm(u, axis=-1) / np.linalg.norm(v, axis=-1)
        )
        g["knee_deg"][:, s] = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return g


def raised(path: Path, up_cm: float) -> Path:
    """A copy of the BVH take with its root (and so its floor) ``up_cm`` higher."""
    src = read_bvh_hierarchy(path, read_motion=True)
    assert src.frames is not None and src.channels[0][1] == "Yposition"
    frames = np.array(src.frames)
    frames[:, 1] += up_cm
    out = path.with_name(f"{path.stem}_up{up_cm:g}.bvh")
    write_bvh(out, src, frames, src.frame_time_s)
    return out


def measure(
    path: Path, take: Any, k: float, toes: float = 1.0, truth_floor_m: float = 0.0
) -> dict[str, Any]:
    """Free and planted figures of the BVH take at ``path`` (the synthetic
    ``take``'s: its contact and supports) on legs ``k``x (toes ``toes`` more);
    ``truth_floor_m``: the true floor's height in the file, metres."""
    src = read_bvh_hierarchy(path, read_motion=True)
    tgt = scaled_target(src, k, toes)
    free = retarget_bvh(src, tgt)
    pl = plant_retarget(src, tgt, free, source_m_per_unit=CM, target_m_per_unit=CM)
    legs = PlantTarget.from_bvh(tgt, target_humanoid(src, tgt, free.mapping), CM)
    floor_t = pl.leg_ratio * pl.floor_m  # the target's floor: k times the source's
    gf, gp = geometry(free, legs, floor_t), geometry(pl.result, legs, floor_t)
    contact, truth = pl.contact, np.asarray(take.foot_contact)
    support = np.asarray(take.foot_support_m) - take.origin_world[2]
    # the truth's supports where the target stands them (its floor at k times the
    # one found): k (support + true floor - floor found)
    floor = (np.nan_to_num(support) + truth_floor_m - pl.floor_m) * pl.leg_ratio
    rate_hz = 1.0 / free.frame_time_s
    return {
        "planted": pl,
        "floor_off_mm": (pl.floor_m - truth_floor_m) * 1e3,
        "free": fp.skate_sink(gf, contact, floor, contact & truth),
        "plant": fp.skate_sink(gp, contact, floor, contact & truth),
        **fp.edges_and_swing(gp, gf, contact, rate_hz),
        "events": fp.event_errors(contact, truth),
        "knee_free": gf["knee_deg"],
        "knee_plant": gp["knee_deg"],
    }


HEADER = (
    "| source | legs | floor off, mm | skate free, mm (p95 frame / p95 contact) | "
    "skate plant, mm | sink free / plant, mm (max) | float free / plant, mm (p95) | "
    "knee at blend edges, deg: added (raw) | swing off path, mm | unreached frames | "
    "contact events off the truth, frames: median / max (events) |\n"
    "|---|---|---|---|---|---|---|---|---|---|---|"
)


def _row(label: str, k: float, m: dict[str, Any]) -> str:
    f, p, ev = m["free"], m["plant"], m["events"]
    cells = [
        label, f"{k:g}x", f"{m['floor_off_mm']:+.2f}",
        f"{f['skate_frame_p95_mm']:.2f} / {f['skate_run_p95_mm']:.1f}",
        f"{p['skate_frame_p95_mm']:.2f} / {p['skate_run_p95_mm']:.2f}",
        f"{f['sink_max_mm']:.2f} / {p['sink_max_mm']:.2f}",
        f"{f['float_p95_mm']:.2f} / {p['float_p95_mm']:.2f}",
        f"{m['knee_added_deg']:.2f} ({m['knee_edge_deg']:.1f})",
        f"{m['swing_max_mm']:.2f}", str(int(np.count_nonzero(m["planted"].flags))),
        f"{int(np.median(ev))} / {int(ev.max())} ({ev.size})" if ev.size else "-",
    ]  # fmt: skip
    return "| " + " | ".join(cells) + " |"


def main(argv: list[str] | None = None) -> int:
    """Measure and write the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, help="write the Markdown here")
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--rate", type=float, default=120.0)
    args = ap.parse_args(argv)
    started = time.perf_counter()
    lines = [HEADER]
    work = Path(tempfile.mkdtemp(prefix="feet_plant_bvh_"))
    for gait in fp.ACTIVITIES:
        take = pf.synthesize(
            seconds=args.seconds, rate_hz=args.rate, markerset=fp.SYNTH_RIG,
            motions=(gait,), seed=0,
        )  # fmt: skip
        path = work / f"{gait}.bvh"
        truth_bvh(take, path)
        for k in fp.LEG_SCALES:
            lines.append(_row(f"{gait} (truth)", k, measure(path, take, k)))
            print(lines[-1], flush=True)
    res, rig, cal, take = fp.synthetic("level_walk", args.seconds, args.rate)
    path = work / "level_walk_solve.bvh"
    write_solve_bvh(path, cal, res, args.rate)
    names = list(cal.bone_names)
    origins = np.asarray(cal.rest_bone_origin_pos)
    rest_low = min(  # the lowest rest foot point (ankle, foot aim) above the floor
        min(origins[f, 2], (origins[f] + rot.quat_rotate(
            cal.rest_world_from_bone_quat[f], np.array([0.0, cal.bone_lengths[f], 0])
        ))[2])
        for f in (names.index(rig.humanoid[s + "Foot"]) for s in ("Left", "Right"))
    )  # fmt: skip
    for k in fp.LEG_SCALES:
        m = measure(path, take, k, truth_floor_m=rest_low)
        lines.append(_row("level_walk (Plug-in Gait solve)", k, m))
        print(lines[-1], flush=True)
    took = time.perf_counter() - started
    lines += [
        "",
        f"(measured in {took:.0f} s: `python bench/feet_plant_bvh.py --out "
        f"docs/feet.md --seconds {args.seconds:g} --rate {args.rate:g}`)",
    ]
    if args.out is not None:
        fp.write_between(args.out, "\n".join(lines) + "\n", "feet_plant_bvh.py")
    return 0


if __name__ == "__main__":
    sys.exit(main())
