"""The real rigid cluster, solved and shown: pyomeca's 8-marker box (``boite:`` in
``markers_analogs.c3d``), calibrated on its first 20 frames and solved on every
frame; writes a figure of its path, its turn and its rigidity residual.

Run from the repository root::

    python bench/props_box.py [--out docs/props-box.png]

Prints the residual's median, p95 and max, the frames held and the markers gated.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from scipy.spatial.transform import Rotation

from retargetd.daemon.cli.prop_io import load_prop_take
from retargetd.daemon.props import kernel as pk
from retargetd.daemon.props.layout import calibrate_prop
from retargetd.daemon.props.solve import solve_take

TAKE = (
    Path(__file__).resolve().parent.parent.parent
    / "shared" / "datasets" / "pyomeca" / "markers_analogs.c3d"
)  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="docs/props-box.png")
    args = parser.parse_args()
    take, labels, cols = load_prop_take(str(TAKE), (), "boite:")
    names = [labels[c] for c in cols]
    layout = calibrate_prop(
        take.positions[:20][:, cols], names, name="boite", rate_hz=take.rate_hz
    )
    track = solve_take(layout, labels, take.positions, take.valid)
    rms_mm = track.rms_m * 1e3
    seen = take.valid[:, cols].sum(axis=1)
    held = int(np.count_nonzero(track.flags & pk.FLAG_HELD))
    gated = int((seen - track.used).sum())
    print(
        f"box: {len(names)} markers, {take.n_frames} frames at {take.rate_hz:g} Hz; "
        f"residual RMS median {np.nanmedian(rms_mm):.2f} mm, p95 "
        f"{np.nanpercentile(rms_mm, 95):.2f} mm, max {np.nanmax(rms_mm):.2f} mm; "
        f"held {held} frames; seen markers left out {gated}"
    )
    t = np.arange(take.n_frames) / take.rate_hz
    rot = Rotation.from_quat(track.world_from_prop_quat, scalar_first=True)
    turned = np.degrees((rot * rot[0].inv()).magnitude())
    fig, ax = plt.subplots(3, 1, figsize=(7, 7), sharex=True)
    for k, axis in enumerate("xyz"):
        ax[0].plot(t, track.prop_pos_world[:, k], label=axis)
    ax[0].set_ylabel("origin (m, world)")
    ax[0].legend(loc="upper right", ncols=3)
    ax[1].plot(t, turned, color="k")
    ax[1].set_ylabel("turned from frame 0 (deg)")
    ax[2].plot(t, rms_mm, color="C3", lw=0.8)
    ax[2].axhline(10.0, color="grey", ls="--", lw=0.8)
    ax[2].text(t[-1], 9.0, "gate 10 mm", ha="right", va="top", fontsize=8)
    ax[2].set_ylabel("residual RMS (mm)")
    ax[2].set_yscale("log")
    ax[2].set_xlabel("time (s)")
    fig.suptitle("pyomeca box (boite:), 8 markers: the rigid fit per frame")
    fig.tight_layout()
    fig.savefig(args.out, dpi=80)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
