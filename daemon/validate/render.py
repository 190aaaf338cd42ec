"""Pictures for a ``validate`` report: snapshots of the worst frames and a plot.

* **Snapshots** (``snapshot_FFFFFF.png``, 640x480): the model posed at the worst
  frames (the union of the worst frames of the failing checks, or of every check when
  none fails, taken round-robin by check and capped at :data:`MAX_SNAPSHOTS`),
  rendered headless by MuJoCo. The bones a check blames at that frame (limits: the
  bones beyond their limit; self-penetration: the deepest pair; floor penetration: the
  segments below the floor) are drawn red, the others grey-blue. A free camera looks
  at the root from the performer's front, 35 deg to the side (the calibration pose's
  forward turned with the root), 15 deg from above, far enough for the whole
  calibrated skeleton to fit.
* **Plot** (``checks.png``): each check's per-frame value divided by its threshold
  over time (log scale, threshold line at 1; a check whose threshold is 0, the
  anatomical limits, plots ``1 + value / 10 deg`` where beyond, else at the bottom),
  the snapshot frames marked.

Rendering runs in a subprocess (``python -m retargetd.daemon.validate.render JOB``)
with ``MUJOCO_GL`` set before mujoco is imported and its working directory in a
temporary directory (MuJoCo writes ``MUJOCO_LOG.TXT`` there): EGL first, then OSMesa
(Debian: ``libegl1 libegl-mesa0 libgl1-mesa-dri libopengl0``, ``libosmesa6``). A GL
failure or crash never fails the report: when no backend works, snapshots are skipped
and the reason is returned. The plot needs no GL (matplotlib's Agg).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.solve import BodySolve
from retargetd.daemon.validate.checks import FrameChecker, TakeReport
from retargetd.daemon.validate.limits import limit_violation_deg
from retargetd.daemon.validate.model import ValidationModel

MAX_SNAPSHOTS = 6
WIDTH, HEIGHT = 640, 480
BACKENDS = ("egl", "osmesa")
RENDER_TIMEOUT_S = 120.0
PLOT_NAME = "checks.png"
#: ``render.skipped`` when the caller turned the snapshots off (``--no-snapshots``).
SNAPSHOTS_OFF = "snapshots off (--no-snapshots)"

BONE_RGBA = (0.55, 0.62, 0.75, 1.0)
BLAMED_RGBA = (0.9, 0.1, 0.1, 1.0)
FLOOR_RGBA = (0.3, 0.3, 0.3, 1.0)
LIMIT_PLOT_SCALE_DEG = 10.0
CAMERA_AZIMUTH_OFFSET_DEG = 35.0  # from straight in front, towards the left
CAMERA_ELEVATION_DEG = -15.0
CAMERA_FOVY_DEG = 45.0  # MuJoCo's default free-camera field of view
CAMERA_MARGIN = 1.25  # frame height / skeleton size


def worst_frames(rep: TakeReport, cap: int = MAX_SNAPSHOTS) -> list[int]:
    """Frames to snapshot: failing checks' worst frames (every check's if none
    fails), round-robin by check, deduplicated, at most ``cap``, sorted."""
    names = rep.failed() or list(rep.checks)
    per_check = []
    for name in names:
        c = rep.checks[name]
        v = np.where(np.isfinite(c.values), c.values, -np.inf)
        order = np.argsort(-v, kind="stable")
        if name in rep.failed():
            order = order[c.flagged[order]]
        per_check.append([int(t) for t in order[:cap]])
    chosen: list[int] = []
    for rank in range(cap):
        for frames in per_check:
            if rank < len(frames) and frames[rank] not in chosen and len(chosen) < cap:
                chosen.append(frames[rank])
    return sorted(chosen)


def _blamed_bones(
    vm: ValidationModel, solve: BodySolve, rep: TakeReport, t: int, checker: Any
) -> tuple[set[int], list[str]]:
    """Bones to draw red at frame ``t`` and the checks flagging that frame."""
    flagged = [n for n, c in rep.checks.items() if c.flagged[t]]
    blamed: set[int] = set()
    if "limits" in flagged:
        viol, _ = limit_violation_deg(vm.skeleton, solve.rest_from_bone_quat[t : t + 1])
        blamed |= {
            int(b) for b in np.flatnonzero(viol[0] > rep.checks["limits"].threshold)
        }
    d = checker.data
    if "self_penetration" in flagged and checker.out.self_pair[0] >= 0:
        blamed |= set(checker.out.self_pair)
    if "floor_penetration" in flagged and d.ncon:
        depth_m = 1e-3 * rep.checks["floor_penetration"].threshold
        for c in range(d.ncon):
            g0, g1 = (int(g) for g in d.contact.geom[c])
            if vm.floor_geom in (g0, g1) and -float(d.contact.dist[c]) > depth_m:
                blamed.add(int(vm.geom_bone[g1 if g0 == vm.floor_geom else g0]))
    blamed.discard(-1)
    return blamed, flagged


def _camera(vm: ValidationModel, solve: BodySolve, t: int) -> dict[str, Any]:
    """A free camera at frame ``t``: lookat the root, front-left, sized to fit."""
    skel = vm.skeleton
    root = next(b for b, p in enumerate(skel.bone_parents) if p < 0)
    up = np.array([0.0, 0.0, 1.0])
    forward_rest = np.cross(skel.left_world, up)
    turn = rot.quat_mul(
        solve.world_from_bone_quat[t, root],
        rot.quat_conj(skel.rest_world_from_bone_quat[root]),
    )
    forward = rot.quat_rotate(turn, forward_rest)
    forward[2] = 0.0
    if np.linalg.norm(forward) < 1e-6:  # root pitched 90 deg: keep the rest view
        forward = forward_rest.copy()
    # MuJoCo's free camera looks along (cos az cos el, sin az cos el, sin el): from
    # the performer's front, it looks along -forward.
    azimuth = np.degrees(np.arctan2(-forward[1], -forward[0]))
    azimuth += CAMERA_AZIMUTH_OFFSET_DEG
    rest = np.concatenate([skel.rest_origin_world, skel.rest_origin_world[:1]])
    size = float(np.ptp(rest, axis=0).max()) + float(skel.bone_lengths.max())
    size = max(size, 0.5)
    distance = CAMERA_MARGIN * size / (2.0 * np.tan(np.radians(CAMERA_FOVY_DEG / 2)))
    return {
        "lookat": [float(x) for x in solve.root_pos[t]],
        "distance": float(distance),
        "azimuth": float(azimuth),
        "elevation": CAMERA_ELEVATION_DEG,
    }


def snapshot_jobs(
    vm: ValidationModel, solve: BodySolve, rep: TakeReport, frames: list[int]
) -> list[dict[str, Any]]:
    """Per frame: qpos, geom colours, camera, flagged checks, blamed bones."""
    checker = FrameChecker(vm)
    root = next(b for b, p in enumerate(vm.skeleton.bone_parents) if p < 0)
    jobs = []
    for t in frames:
        checker.check(
            solve.root_pos[t],
            solve.world_from_bone_quat[t, root],
            solve.rest_from_bone_quat[t],
        )
        blamed, flagged = _blamed_bones(vm, solve, rep, t, checker)
        rgba = np.tile(BONE_RGBA, (vm.model.ngeom, 1))
        rgba[vm.floor_geom] = FLOOR_RGBA
        for g, b in enumerate(vm.geom_bone):
            if b in blamed:
                rgba[g] = BLAMED_RGBA
        jobs.append(
            {
                "frame": int(t),
                "file": f"snapshot_{t:06d}.png",
                "checks": flagged,
                "blamed_bones": [vm.skeleton.bone_names[b] for b in sorted(blamed)],
                "qpos": [float(x) for x in checker.data.qpos],
                "rgba": rgba.tolist(),
                "camera": _camera(vm, solve, t),
            }
        )
    return jobs


def render_snapshots(
    xml: str,
    jobs: list[dict[str, Any]],
    out_dir: Path,
    *,
    backends: tuple[str, ...] | None = None,
    width: int = WIDTH,
    height: int = HEIGHT,
) -> dict[str, Any]:
    """Render ``jobs`` into ``out_dir`` in a subprocess, trying each GL backend.

    Returns:
        ``{"backend": name or None, "skipped": reason or None, "seconds_start": s,
        "seconds_per_snapshot": s, "tried": {backend: error}}``.
    """
    if backends is None:
        env_gl = os.environ.get("MUJOCO_GL")
        backends = tuple(dict.fromkeys(([env_gl] if env_gl else []) + list(BACKENDS)))
    tried: dict[str, str] = {}
    with tempfile.TemporaryDirectory(prefix="retargetd-render-") as tmp:
        job_path = Path(tmp) / "job.json"
        (Path(tmp) / "model.xml").write_text(xml)
        job_path.write_text(
            json.dumps(
                {
                    "xml": str(Path(tmp) / "model.xml"),
                    "out_dir": str(Path(out_dir).resolve()),
                    "width": width,
                    "height": height,
                    "frames": jobs,
                }
            )
        )
        for backend in backends:
            env = {**os.environ, "MUJOCO_GL": backend}
            if backend == "osmesa":
                env.setdefault("PYOPENGL_PLATFORM", "osmesa")
            elif backend == "egl":
                env.setdefault("PYOPENGL_PLATFORM", "egl")
            try:
                proc = subprocess.run(
                    [
                        sys.executable,
                        "-m",
                        "retargetd.daemon.validate.render",
                        str(job_path),
                    ],
                    cwd=tmp,
                    env=env,
                    capture_output=True,
                    text=True,
                    timeout=RENDER_TIMEOUT_S,
                    check=False,
                )
            except subprocess.TimeoutExpired:
                tried[backend] = f"timed out after {RENDER_TIMEOUT_S:g} s"
                continue
            if proc.returncode == 0:
                result = json.loads(proc.stdout.strip().splitlines()[-1])
                return {**result, "skipped": None, "tried": tried}
            lines = (proc.stderr or proc.stdout or "").strip().splitlines()
            tried[backend] = lines[-1] if lines else f"exit code {proc.returncode}"
    reason = "no headless GL backend works: " + "; ".join(
        f"{b}: {e}" for b, e in tried.items()
    )
    return {
        "backend": None,
        "skipped": reason,
        "seconds_start": None,
        "seconds_per_snapshot": None,
        "tried": tried,
    }


def plot_checks(
    rep: TakeReport, rate_hz: float, path: Path, marks: list[int] | None = None
) -> None:
    """One PNG: every check's values / threshold over time, threshold line at 1."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 5), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    t = np.arange(rep.n_frames) / rate_hz
    floor = 1e-3
    for name, c in rep.checks.items():
        v = np.asarray(c.values, dtype=np.float64)
        if c.threshold > 0:
            norm, label = v / c.threshold, name
        else:
            # Threshold 0 (degrees beyond the table): 0 is "inside", drawn at the
            # bottom; beyond draws above the threshold line.
            norm = np.where(v > 0.0, 1.0 + v / LIMIT_PLOT_SCALE_DEG, 0.0)
            label = f"{name} (1 + deg/{LIMIT_PLOT_SCALE_DEG:g})"
        style = "-" if c.n_flagged else ":"
        ax.plot(t, np.clip(norm, floor, None), style, lw=1.0, label=label)
    ax.axhline(1.0, color="k", lw=1.5, label="threshold")
    for f in marks or []:
        ax.axvline(f / rate_hz, color="r", lw=0.6, alpha=0.5)
    ax.set_yscale("log")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("value / threshold")
    title = "PASS" if rep.passed else "FAIL: " + ", ".join(rep.failed())
    ax.set_title(f"validate: {title} (red lines: snapshot frames; dotted: passing)")
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    fig.tight_layout()
    fig.savefig(path)


def write_visuals(
    report_dir: Path,
    vm: ValidationModel,
    solve: BodySolve,
    rep: TakeReport,
    rate_hz: float,
    *,
    max_snapshots: int = MAX_SNAPSHOTS,
    backends: tuple[str, ...] | None = None,
    snapshots: bool = True,
) -> dict[str, Any]:
    """Snapshots and the plot into ``report_dir``; a JSON-ready summary for the
    report (``plot``, ``snapshots`` with frame/file/checks/blamed bones, ``render``:
    backend, timings, or why the snapshots were skipped).

    With ``snapshots=False`` nothing is rendered (no GL subprocess: at library scale
    its start-up and frames dominate a take's validate); the plot still marks the
    worst frames and ``render.skipped`` is :data:`SNAPSHOTS_OFF`."""
    report_dir = Path(report_dir)
    frames = worst_frames(rep, max_snapshots)
    plot_checks(rep, rate_hz, report_dir / PLOT_NAME, frames)
    jobs = snapshot_jobs(vm, solve, rep, frames) if snapshots else []
    t0 = time.perf_counter()
    if snapshots:
        render = render_snapshots(vm.xml, jobs, report_dir, backends=backends)
    else:
        render = {
            "backend": None,
            "skipped": SNAPSHOTS_OFF,
            "seconds_start": None,
            "seconds_per_snapshot": None,
            "tried": {},
        }
    render["seconds_total"] = time.perf_counter() - t0
    snaps = [
        {k: j[k] for k in ("frame", "file", "checks", "blamed_bones")}
        for j in jobs
        if render["skipped"] is None
    ]
    return {"plot": PLOT_NAME, "snapshots": snaps, "render": render}


def visuals_text(vis: dict[str, Any]) -> list[str]:
    """report.txt lines for :func:`write_visuals`' summary."""
    lines = [f"Plot: {vis['plot']}"]
    r = vis["render"]
    if r["skipped"] is not None:
        lines.append(f"Snapshots skipped: {r['skipped']}")
        return lines
    lines.append(
        f"Snapshots ({r['backend']}, {r['seconds_per_snapshot']:.3f} s each after "
        f"{r['seconds_start']:.2f} s start; red: blamed bones):"
    )
    for s in vis["snapshots"]:
        blamed = ", ".join(s["blamed_bones"]) or "-"
        checks = ", ".join(s["checks"]) or "none flagged"
        lines.append(f"    {s['file']}  frame {s['frame']}: {checks}; red: {blamed}")
    return lines


def _render_main(job_path: str) -> int:
    """Subprocess entry: MUJOCO_GL is already set; render every frame of the job."""
    t0 = time.perf_counter()
    import mujoco
    from matplotlib.image import imsave

    job = json.loads(Path(job_path).read_text())
    model = mujoco.MjModel.from_xml_path(job["xml"])
    data = mujoco.MjData(model)
    out_dir = Path(job["out_dir"])
    renderer = mujoco.Renderer(model, job["height"], job["width"])
    try:
        cam = mujoco.MjvCamera()
        cam.type = mujoco.mjtCamera.mjCAMERA_FREE
        start = time.perf_counter() - t0
        t1 = time.perf_counter()
        for f in job["frames"]:
            data.qpos[:] = f["qpos"]
            mujoco.mj_kinematics(model, data)
            model.geom_rgba[:] = np.asarray(f["rgba"])
            c = f["camera"]
            cam.lookat[:] = c["lookat"]
            cam.distance = c["distance"]
            cam.azimuth = c["azimuth"]
            cam.elevation = c["elevation"]
            renderer.update_scene(data, camera=cam)
            imsave(out_dir / f["file"], renderer.render())
        per = (time.perf_counter() - t1) / max(len(job["frames"]), 1)
    finally:
        renderer.close()
    sys.stdout.write(
        json.dumps(
            {
                "backend": os.environ.get("MUJOCO_GL"),
                "seconds_start": start,
                "seconds_per_snapshot": per,
            }
        )
        + "\n"
    )
    return 0


if __name__ == "__main__":
    sys.exit(_render_main(sys.argv[1]))
