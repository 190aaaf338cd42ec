"""Plug-in Gait's legs against the synthetic performer's truth, calibrated on the base
pose alone and with a range of motion (``calibrate --rom``, issue 29 item 1).

Run from the repository root::

    python bench/truth_rom.py          # 3 s on 2 cores (compiled kernels cached)

The performer wears ``plug-in-gait`` (1 mm noise). The range of motion is its own
``rom`` take (25 s at 120 Hz, seed 3, after the T-pose hold); each motion set (the
default motions and three activities, 10 s at 120 Hz, seed 0) is calibrated on its
first 120 frames (the T-pose), once without and once with that range of motion, and
solved with each method (``body.method.make_body_solver``, the validator's joint
limits). Printed per case: the p95 angle error of each leg bone against its truth
segment (``synth.truth.compare_with_truth``), the p95 joint-centre error of the hips,
knees and ankles, and how many of all the compared bones are past p95 5 deg.
"""

from __future__ import annotations

import numpy as np

from retargetd.daemon.body.calibration import calibrate
from retargetd.daemon.body.method import make_body_solver
from retargetd.daemon.body.rig import load_rig
from retargetd.daemon.synth import performer as pf
from retargetd.daemon.synth.truth import compare_with_truth
from retargetd.daemon.validate.limits import JOINT_LIMITS_DEG
from retargetd.daemon.validate.model import SEGMENT_KIND

RATE_HZ = 120.0
MOTION_SETS = {
    "default": pf.DEFAULT_MOTIONS,
    "deep_squat": ("deep_squat",),
    "kick": ("kick",),
    "run": ("run",),
}
LEGS = ("lupperleg", "rupperleg", "llowerleg", "rlowerleg")
JOINTS = ("LHJC", "RHJC", "LKJC", "RKJC", "LAJC", "RAJC")


def main() -> None:
    rig = load_rig("plug-in-gait")
    rom_take = pf.synthesize(
        seconds=25.0, rate_hz=RATE_HZ, markerset="plug-in-gait", motions=("rom",),
        noise_mm=1.0, seed=3,
    )  # fmt: skip
    rom = (
        rom_take.markers_world[rom_take.base_pose_frames.stop :],
        rom_take.labels,
        {"take": "synthetic rom, seed 3"},
    )
    print(f"p95 deg: {' '.join(LEGS)} | p95 mm: {' '.join(JOINTS)} | bones > 5 deg")
    for name, motions in MOTION_SETS.items():
        take = pf.synthesize(
            seconds=10.0, rate_hz=RATE_HZ, markerset="plug-in-gait",
            motions=motions, noise_mm=1.0, seed=0,
        )  # fmt: skip
        base = take.markers_world[:120]
        cals = {
            "base pose": calibrate(rig, base, take.labels),
            "with rom": calibrate(rig, base, take.labels, rom=rom),
        }
        for method in ("fit", "construction"):
            for label, cal in cals.items():
                solver = make_body_solver(
                    method, rig, cal, take.labels, joint_limits=JOINT_LIMITS_DEG,
                    segment_kind=SEGMENT_KIND, rate_hz=RATE_HZ,
                )  # fmt: skip
                solve = solver.solve_take(take.markers_world)
                cmp = compare_with_truth(solve, take, rig)
                deg = dict(zip(cmp.bone_names, cmp.p95_deg, strict=True))
                mm = dict(zip(cmp.joint_names, cmp.joint_p95_mm, strict=True))
                past = int(np.sum(np.asarray(cmp.p95_deg) > 5.0))
                print(
                    f"{name:10s} {method:12s} {label:9s} "
                    + " ".join(f"{deg[b]:5.1f}" for b in LEGS)
                    + " | "
                    + " ".join(f"{mm[j]:5.1f}" for j in JOINTS)
                    + f" | {past}"
                )


if __name__ == "__main__":
    main()
