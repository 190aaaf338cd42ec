"""Golden solve outputs: the cases, how each is computed, stored and compared.

Used by ``tests/daemon/test_golden.py`` (loaded by path: tests are not a package) and
by ``tests/golden/regenerate.py`` (the one-command regeneration). See
``tests/golden/README.md`` for the file format, the tolerances and why.
"""

from __future__ import annotations

import json
import math
import platform
import subprocess
import sys
from dataclasses import dataclass, field
from importlib.metadata import version
from pathlib import Path
from typing import Any

import numpy as np
from paths import DATASETS

GOLDEN_DIR = Path(__file__).resolve().parent
REPO_ROOT = GOLDEN_DIR.parent.parent
#: Same place as ``tests/conftest.py``'s DATASETS (tests can't import conftest).

FORMAT = "retargetd-golden"
FORMAT_VERSION = 1

#: Tolerances (see README.md "Tolerances"): rotation angle of conj(q_gold) * q_now,
#: sign-insensitive, in radians; joint centres and root position in millimetres;
#: flags exact.
TOL_ANGLE_RAD = 1e-4
TOL_MM = 0.05
#: Decimals stored: quaternion components, millimetres. The rounding error they leave
#: (< 2e-6 rad, < 5e-4 mm) is well inside the tolerances.
QUAT_DECIMALS = 6
MM_DECIMALS = 3

FLAG_BITS = {1: "held", 2: "rebuilt", 4: "partial", 8: "never"}


@dataclass(frozen=True)
class Case:
    """One golden case. ``take`` is relative to the datasets folder (None: synthetic);
    ``rig`` a shipped rig name or a path relative to the repository."""

    name: str
    rig: str
    step: int
    take: str | None = None
    calibration: dict[str, Any] = field(default_factory=dict)
    synth: dict[str, Any] | None = None

    @property
    def needs_datasets(self) -> bool:
        return self.take is not None or self.calibration.get("take") is not None

    @property
    def label(self) -> str:
        """How failures name the case: the case and its take."""
        what = self.take if self.take is not None else f"synthesize({self.synth})"
        return f"{self.name} [{what}]"

    def definition(self) -> dict[str, Any]:
        out: dict[str, Any] = {"name": self.name, "rig": self.rig}
        if self.take is not None:
            out["take"] = self.take
        if self.synth is not None:
            out["synth"] = dict(self.synth)
        out["calibration"] = dict(self.calibration)
        out["step"] = self.step
        return out


CASES: tuple[Case, ...] = (
    Case(
        name="pig-walk",
        rig="plug-in-gait",
        take="btkdata/PiG_Motion-FlatFoot-Full.c3d",
        calibration={
            "take": "btkdata/PiG_Calibration-FlatFoot-Full.c3d",
            "frames": "all",
            "measurements": "take",
        },
        step=27,
    ),
    Case(
        name="motek-ballet",
        rig="cmu41",
        take="btkdata/MOTEK_ballet_reduced.trc",
        calibration={
            "take": "btkdata/MOTEK_T.trc",
            "frames": "all",
            "measurements": "take",
        },
        step=9,
    ),
    Case(
        name="tennis-serve",
        rig="cmu41",
        take="kineticstoolkit/kinematics_tennis_serve.c3d",
        calibration={"take": "self", "frames": [0, 50], "measurements": "take"},
        step=91,
    ),
    Case(
        # tests/daemon/test_occlusion.py: the stillest 10 all-seen frames, pelvis
        # width and depth measured on them.
        name="walking2-occlusion",
        rig="tests/data/walking2-rig.toml",
        take="opensim-core/walking2.c3d",
        calibration={
            "take": "self",
            "frames": [534, 544],
            "measurements": "pelvis width and depth from LASI RASI LPSI RPSI",
        },
        step=104,
    ),
    Case(
        # No noise, no dropout: no random stream is drawn, so the take depends only on
        # the performer's arithmetic (stable across numpy versions to a few ulp).
        name="synthetic-menache",
        rig="menache",
        synth={
            "seconds": 3.0,
            "rate_hz": 60.0,
            "markerset": "menache",
            "seed": 0,
            "noise_mm": 0.0,
            "dropout": 0.0,
        },
        calibration={"frames": "base_pose", "measurements": "rig defaults"},
        step=18,
    ),
)
CASE_BY_NAME = {c.name: c for c in CASES}


def golden_path(case: Case) -> Path:
    return GOLDEN_DIR / f"{case.name}.json"


@dataclass(frozen=True)
class Computed:
    """The whole solve of a case, in stored units (quaternions w x y z, millimetres)."""

    bone_names: tuple[str, ...]
    joint_names: tuple[str, ...]
    first_frame: int
    rows: np.ndarray  # (N,) sampled rows
    world_from_bone_quat: np.ndarray  # (T, B, 4)
    rest_from_bone_quat: np.ndarray  # (T, B, 4)
    joint_centres_mm: np.ndarray  # (T, J, 3)
    root_mm: np.ndarray  # (T, 3)
    bone_flags: np.ndarray  # (T, B) uint8
    calibration_inputs: dict[str, Any]


def _calibration_measurements(take: Any, window: slice) -> dict[str, float]:
    pos = take.positions[window]

    def mean(label: str) -> np.ndarray:
        return pos[:, take.labels.index(label)].mean(axis=0)

    width = 1000 * np.linalg.norm(mean("LASI") - mean("RASI"))
    depth = 1000 * np.linalg.norm(
        (mean("LASI") + mean("RASI")) / 2 - (mean("LPSI") + mean("RPSI")) / 2
    )
    return {"InterAsisDistance": float(width), "PelvisDepth": float(depth)}


def compute(case: Case, datasets: Path = DATASETS) -> Computed:
    """Calibrate and solve a case from its definition."""
    from retargetd.daemon.body.calibration import calibrate
    from retargetd.daemon.body.rig import load_rig
    from retargetd.daemon.body.solve import BodySolver
    from retargetd.daemon.synth.performer import synthesize
    from retargetd.replay.takes import load_take

    rig_ref = case.rig
    rig = load_rig(REPO_ROOT / rig_ref if rig_ref.endswith(".toml") else rig_ref)
    spec = case.calibration
    overrides: dict[str, float] | None = None
    if case.synth is not None:
        synth = synthesize(**case.synth)
        labels, positions, first_frame = synth.labels, synth.markers_world, 0
        assert spec["frames"] == "base_pose"
        cal_labels, cal_pos, measurements = (
            labels,
            positions[synth.base_pose_frames],
            None,
        )
    else:
        assert case.take is not None
        take = load_take(datasets / case.take)
        labels, positions, first_frame = take.labels, take.positions, take.first_frame
        static = take if spec["take"] == "self" else load_take(datasets / spec["take"])
        frames = spec["frames"]
        window = slice(None) if frames == "all" else slice(frames[0], frames[1])
        cal_labels, cal_pos = static.labels, static.positions[window]
        measurements = static.measurements
        if spec["measurements"].startswith("pelvis"):
            measurements = None
            overrides = _calibration_measurements(static, window)
    cal = calibrate(
        rig, cal_pos, cal_labels, take_measurements=measurements, overrides=overrides
    )
    res = BodySolver(rig, cal, labels).solve_take(positions)
    n = res.world_from_bone_quat.shape[0]
    return Computed(
        bone_names=tuple(res.bone_names),
        joint_names=tuple(res.joint_names),
        first_frame=int(first_frame),
        rows=np.arange(0, n, case.step),
        world_from_bone_quat=res.world_from_bone_quat,
        rest_from_bone_quat=res.rest_from_bone_quat,
        joint_centres_mm=1000.0 * res.joint_centres,
        root_mm=1000.0 * res.root_pos,
        bone_flags=res.bone_flags,
        calibration_inputs={
            "frames_used": int(cal_pos.shape[0]),
            "overrides_mm": {
                k: round(v, MM_DECIMALS) for k, v in (overrides or {}).items()
            },
        },
    )


def produced_by() -> dict[str, str]:
    """The software that produced a golden: package version, git commit, stack."""
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=REPO_ROOT, capture_output=True,
            text=True, timeout=10, check=True,
        ).stdout.strip()  # fmt: skip
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"], cwd=REPO_ROOT,
            capture_output=True, text=True, timeout=10, check=True,
        ).stdout.strip()  # fmt: skip
        if dirty:
            commit += "+dirty"
    except (OSError, subprocess.SubprocessError):
        commit = "unknown"
    import numba
    import scipy

    return {
        "retargetd": version("mocap-retargetd"),
        "commit": commit,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "numba": numba.__version__,
        "platform": f"{sys.platform}-{platform.machine()}",
    }


def _rounded(a: np.ndarray, decimals: int) -> list[Any]:
    """Nested lists of rounded floats; None for NaN."""
    out = np.round(np.asarray(a, dtype=np.float64), decimals) + 0.0  # no -0.0
    return [
        _rounded(x, decimals) if x.ndim else (None if math.isnan(x) else float(x))
        for x in out
    ]


def to_golden(case: Case, c: Computed) -> dict[str, Any]:
    """The golden document of a computed case (rounded, sampled)."""
    frames = []
    for r in c.rows:
        frames.append(
            {
                "row": int(r),
                "frame": c.first_frame + int(r),
                "root_mm": _rounded(c.root_mm[r], MM_DECIMALS),
                "bone_flags": [int(f) for f in c.bone_flags[r]],
                "world_from_bone_quat": _rounded(
                    c.world_from_bone_quat[r], QUAT_DECIMALS
                ),
                "rest_from_bone_quat": _rounded(
                    c.rest_from_bone_quat[r], QUAT_DECIMALS
                ),
                "joint_centres_mm": _rounded(c.joint_centres_mm[r], MM_DECIMALS),
            }
        )
    return {
        "format": FORMAT,
        "version": FORMAT_VERSION,
        "case": case.definition(),
        "produced_by": produced_by(),
        "tolerances": {"angle_rad": TOL_ANGLE_RAD, "mm": TOL_MM, "flags": "exact"},
        "calibration_inputs": c.calibration_inputs,
        "n_frames": int(c.bone_flags.shape[0]),
        "first_frame": c.first_frame,
        "bone_names": list(c.bone_names),
        "joint_names": list(c.joint_names),
        "flag_counts": flag_counts(c.bone_names, c.bone_flags),
        "frames": frames,
    }


def flag_counts(bone_names: tuple[str, ...], flags: np.ndarray) -> dict[str, Any]:
    """Over the whole take: per bone with any flag, frames with each flag bit."""
    out: dict[str, Any] = {}
    for b, name in enumerate(bone_names):
        counts = {
            label: int(((flags[:, b] & bit) != 0).sum())
            for bit, label in FLAG_BITS.items()
        }
        counts = {k: v for k, v in counts.items() if v}
        if counts:
            out[name] = counts
    return out


def dumps(doc: dict[str, Any]) -> str:
    """Compact, diff-friendly JSON: a line per header field (per bone for the flag
    counts) and per frame field."""

    def one(v: Any, sep: tuple[str, str] = (", ", ": ")) -> str:
        return json.dumps(v, separators=sep)

    lines = []
    for key, value in doc.items():
        if key == "frames":
            rows = []
            for fr in value:
                fields = [f"  {one(k)}: {one(v, (',', ':'))}" for k, v in fr.items()]
                rows.append(" {\n" + ",\n".join(fields) + "\n }")
            lines.append(' "frames": [\n' + ",\n".join(rows) + "\n ]")
        elif key == "flag_counts" and value:
            inner = ",\n".join(f"  {one(k)}: {one(v)}" for k, v in value.items())
            lines.append(f" {one(key)}: {{\n{inner}\n }}")
        else:
            lines.append(f" {one(key)}: {one(value)}")
    return "{\n" + ",\n".join(lines) + "\n}\n"


def load_golden(case: Case) -> dict[str, Any]:
    doc = json.loads(golden_path(case).read_text())
    if doc.get("format") != FORMAT or doc.get("version") != FORMAT_VERSION:
        raise ValueError(f"{golden_path(case)}: not a {FORMAT} v{FORMAT_VERSION} file")
    return doc


@dataclass(frozen=True)
class Offence:
    """One value beyond tolerance (or a structural difference when ``row`` < 0)."""

    row: int
    frame: int
    field: str
    name: str
    excess: float  # value / tolerance; inf for structure and flags
    detail: str

    def describe(self) -> str:
        where = f"row {self.row} (frame {self.frame})" if self.row >= 0 else "take"
        return f"{where} {self.field} {self.name}: {self.detail}"


def _angles(gold: np.ndarray, now: np.ndarray) -> np.ndarray:
    """Angle (rad) of conj(gold) * now, sign-insensitive; gold renormalised."""
    g = gold / np.linalg.norm(gold, axis=-1, keepdims=True)
    n = now / np.linalg.norm(now, axis=-1, keepdims=True)
    dot = np.abs(np.sum(g * n, axis=-1))
    # |vector part| of conj(g) * n, for precision at small angles.
    w = (
        g[..., :1] * n[..., 1:]
        - n[..., :1] * g[..., 1:]
        - np.cross(g[..., 1:], n[..., 1:])
    )
    return 2.0 * np.arctan2(np.linalg.norm(w, axis=-1), dot)


@dataclass(frozen=True)
class Comparison:
    """Every difference of a computed case from its golden."""

    offences: list[Offence]
    max_angle_rad: dict[str, float]
    max_mm: dict[str, float]
    flag_changes: int

    @property
    def ok(self) -> bool:
        return not self.offences


def compare(case: Case, doc: dict[str, Any], c: Computed) -> Comparison:
    """Compare a computed case with its golden document."""
    off: list[Offence] = []
    structure = {
        "case": (doc["case"], case.definition()),
        "bone_names": (doc["bone_names"], list(c.bone_names)),
        "joint_names": (doc["joint_names"], list(c.joint_names)),
        "n_frames": (doc["n_frames"], int(c.bone_flags.shape[0])),
        "first_frame": (doc["first_frame"], c.first_frame),
    }
    for key, (gold, now) in structure.items():
        if gold != now:
            off.append(Offence(-1, -1, key, "", math.inf, f"{gold} -> {now}"))
    if off:
        return Comparison(off, {}, {}, 0)
    counts = flag_counts(c.bone_names, c.bone_flags)
    for bone in sorted(set(doc["flag_counts"]) | set(counts)):
        gold, now = doc["flag_counts"].get(bone, {}), counts.get(bone, {})
        if gold != now:
            off.append(
                Offence(-1, -1, "flag_counts", bone, math.inf, f"{gold} -> {now}")
            )
    max_angle = {"world_from_bone_quat": 0.0, "rest_from_bone_quat": 0.0}
    max_mm = {"joint_centres_mm": 0.0, "root_mm": 0.0}
    flag_changes = 0
    for fr in doc["frames"]:
        r, frame = fr["row"], fr["frame"]
        for key in max_angle:
            ang = _angles(np.asarray(fr[key], dtype=np.float64), getattr(c, key)[r])
            max_angle[key] = max(max_angle[key], float(ang.max()))
            for b in np.flatnonzero(~(ang <= TOL_ANGLE_RAD)):
                off.append(Offence(
                    r, frame, key, f"bone {c.bone_names[b]}",
                    float(ang[b]) / TOL_ANGLE_RAD,
                    f"{ang[b]:.3g} rad ({math.degrees(ang[b]):.3g} deg) "
                    f"> {TOL_ANGLE_RAD:g} rad",
                ))  # fmt: skip
        gold_j = np.array(fr["joint_centres_mm"], dtype=np.float64)
        gold_r = np.array(fr["root_mm"], dtype=np.float64)[None]
        for key, gold, now, names in (
            ("joint_centres_mm", gold_j, c.joint_centres_mm[r], c.joint_names),
            ("root_mm", gold_r, c.root_mm[r][None], ("root",)),
        ):
            nan_gold, nan_now = np.isnan(gold).any(-1), np.isnan(now).any(-1)
            d = np.linalg.norm(now - gold, axis=-1)
            d = np.where(nan_gold & nan_now, 0.0, d)
            d = np.where(nan_gold ^ nan_now, math.inf, d)
            max_mm[key] = max(max_mm[key], float(d.max()))
            for j in np.flatnonzero(~(d <= TOL_MM)):
                detail = (
                    f"{d[j]:.3g} mm > {TOL_MM:g} mm"
                    if np.isfinite(d[j])
                    else f"NaN changed: {gold[j].tolist()} -> {now[j].tolist()}"
                )
                off.append(
                    Offence(r, frame, key, names[j], float(d[j]) / TOL_MM, detail)
                )
        gold_f = np.asarray(fr["bone_flags"])
        for b in np.flatnonzero(gold_f != c.bone_flags[r]):
            flag_changes += 1
            was, now_f = _flag_text(int(gold_f[b])), _flag_text(int(c.bone_flags[r, b]))
            bone = f"bone {c.bone_names[b]}"
            off.append(
                Offence(r, frame, "bone_flags", bone, math.inf, f"{was} -> {now_f}")
            )
    return Comparison(off, max_angle, max_mm, flag_changes)


def _flag_text(flags: int) -> str:
    names = [label for bit, label in FLAG_BITS.items() if flags & bit]
    return f"{flags} ({'|'.join(names) or 'none'})"


def failure_message(case: Case, cmp: Comparison, limit: int = 10) -> str:
    """The worst ``limit`` offences (relative to their tolerance), naming the case
    (take), the row and source frame, and the bone or joint."""
    worst = sorted(cmp.offences, key=lambda o: (-o.excess, o.row, o.field, o.name))[
        :limit
    ]
    lines = [
        f"golden {case.label}: {len(cmp.offences)} value(s) beyond tolerance "
        f"(rotations {TOL_ANGLE_RAD:g} rad, positions {TOL_MM:g} mm, flags exact); "
        f"worst {len(worst)}:"
    ]
    lines += [f"  {o.describe()}" for o in worst]
    lines.append(
        "If the change is intended: python tests/golden/regenerate.py "
        f"{case.name}  (see tests/golden/README.md)"
    )
    return "\n".join(lines)
