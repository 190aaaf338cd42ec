"""Calibration: a base pose turns a rig into a calibrated skeleton, saved per performer.

``calibrate`` takes the base-pose frames of a take (a static trial, the first second
of a take, or frames captured live) and fixes everything the per-frame solve treats as
constant:

- the layout of every rigid segment's markers (to rebuild an occluded marker);
- the local offset of every ``rigid`` derived point: with a per-axis ``rule`` the point
  is placed in the base pose at the rule's height / width / depth (the body axes of the
  base pose: height = world +Z, width = the horizontal direction of ``rig.lateral``
  from right to left, depth = width x height, forward) and its offset in the three-point
  frame averaged over the frames; with ``offset_mm`` the offset is evaluated from the
  subject's measurements;
- bone lengths and rest orientations (world and parent-relative), averaged.

Measurements: a rig measurement takes an explicit override (``--measure``), else the
take's value (C3D ``PROCESSING``; a value <= 0 for a length whose default is > 0 counts
as "not measured", as Vicon writes 0 there), else the rig default; every
measurement used is saved with its source, and defaults used are reported, never fatal.

The calibrated skeleton is a JSON file (``retargetd calibrate --out performer.json``),
read back by :func:`load_calibration`.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from retargetd.daemon.body.calibrate_rom import RomPoints
from retargetd.daemon.body.rig import LinePoint, Rig
from retargetd.daemon.files import FileFormatError, loads_json, read_text, write_atomic
from retargetd.daemon.rotations import quat_conj, quat_from_mat, quat_mul
from retargetd.protocols.frames import F64Array

logger = logging.getLogger(__name__)

CALIBRATION_FORMAT = "retargetd-calibration"
CALIBRATION_VERSION = 1


class CalibrationError(ValueError):
    """A base pose that cannot calibrate the rig (one line, names the problem)."""


@dataclass(frozen=True, slots=True, kw_only=True)
class MeasurementUsed:
    """A measurement's value (mm) and where it came from."""

    value_mm: float
    source: str  # "take (PROCESSING)", "override", "default"


@dataclass(frozen=True, slots=True, kw_only=True)
class Calibration:
    """A calibrated skeleton for one performer and one rig.

    Attributes:
        rig_name / rig_source / rig_sha256: which rig it was made for.
        marker_names: (Mr,) rig markers; ``markers_seen`` (Mr,) fraction of base-pose
            frames each was seen in.
        point_names: (P,) derived points in rig order; ``point_offsets`` (P, 3) metres,
            the local offset of each ``rigid`` point in its three-point frame (zeros for
            ``line`` points).
        segment_layouts: segment -> (marker names, (k, 3) metres base-pose positions).
        bone_names, bone_parents (-1 root), bone_lengths (B,) metres,
        rest_world_from_bone_quat (B, 4) and rest_parent_from_bone_quat (B, 4), w x y z.
        root_rest_pos: (3,) metres, the root bone's origin in the base pose.
        rest_bone_origin_pos: (B, 3) metres, world, each bone's origin in the base
            pose (the BVH export's offsets); None in files written before it existed.
        measurements: name -> value and source.
        base_pose: where the base pose came from (take, subject, frames a:b).
    """

    rig_name: str
    rig_source: str
    rig_sha256: str
    marker_names: tuple[str, ...]
    markers_seen: tuple[float, ...]
    point_names: tuple[str, ...]
    point_offsets: F64Array
    segment_layouts: dict[str, tuple[tuple[str, ...], F64Array]]
    bone_names: tuple[str, ...]
    bone_parents: tuple[int, ...]
    bone_lengths: F64Array
    rest_world_from_bone_quat: F64Array
    rest_parent_from_bone_quat: F64Array
    root_rest_pos: F64Array
    rest_bone_origin_pos: F64Array | None = None
    measurements: dict[str, MeasurementUsed] = field(default_factory=dict)
    base_pose: dict[str, Any] = field(default_factory=dict)
    #: (Mr, 3) metres, world: each rig marker's mean position over the base pose
    #: (NaN where never seen); the fit attaches the markers to their bones from it.
    base_marker_pos: F64Array | None = None
    #: The range of motion's functional joints (``calibrate --rom``;
    #: ``body.calibrate_rom``): ``{"source": {...}, "joints": {name: {...}}}``;
    #: empty without one.
    functional: dict[str, Any] = field(default_factory=dict)
    #: (Mr, 3) metres, world, base pose: where each marker sits on its bone in the
    #: take its layout was refined on (``--refine-layout``, ``body.refine``), carried
    #: into the base pose by its bone; None without a refinement. The fit attaches the
    #: markers from it (the joint model still comes from ``base_marker_pos``).
    layout_marker_pos: F64Array | None = None
    #: The refinement's record (``body.refine.refine_layout``): its source, rounds,
    #: residuals before and after, and per marker how far it moved; empty without.
    layout_refined: dict[str, Any] = field(default_factory=dict)

    @property
    def functional_axes(self) -> dict[str, F64Array]:
        """bone -> its functional hinge axis in the bone's rest axes (those used)."""
        joints = self.functional.get("joints", {})
        return {
            name: np.asarray(j["axis_bone"], dtype=np.float64)
            for name, j in joints.items()
            if j.get("kind") == "axis" and j.get("used") and "axis_bone" in j
        }

    def to_json(self) -> dict[str, Any]:
        """A JSON-ready dict (the file format of ``retargetd calibrate``)."""
        origins = (
            [None] * len(self.bone_names)
            if self.rest_bone_origin_pos is None
            else self.rest_bone_origin_pos
        )
        return {
            "format": CALIBRATION_FORMAT,
            "version": CALIBRATION_VERSION,
            "rig": {
                "name": self.rig_name,
                "source": self.rig_source,
                "sha256": self.rig_sha256,
            },
            "base_pose": self.base_pose,
            "measurements_mm": {
                k: {"value": v.value_mm, "source": v.source}
                for k, v in self.measurements.items()
            },
            "markers": {
                n: {"seen": s} | _position("base_m", pos) | _position("take_m", took)
                for n, s, pos, took in zip(
                    self.marker_names,
                    self.markers_seen,
                    _rows(self.base_marker_pos, len(self.marker_names)),
                    _rows(self.layout_marker_pos, len(self.marker_names)),
                    strict=False,
                )
            },
            "points": {
                n: {"offset_m": [float(x) for x in off]}
                for n, off in zip(self.point_names, self.point_offsets, strict=False)
            },
            "segments": {
                name: {
                    "markers": list(names),
                    "layout_m": np.asarray(layout).round(9).tolist(),  # as calibrate
                }
                for name, (names, layout) in self.segment_layouts.items()
            },
            "bones": {
                n: {
                    "parent": None if p < 0 else self.bone_names[p],
                    "length_m": float(length),
                    "rest_world_from_bone_quat": [float(x) for x in qw],
                    "rest_parent_from_bone_quat": [float(x) for x in qp],
                    **(
                        {}
                        if origin is None
                        else {"rest_origin_m": [float(x) for x in origin]}
                    ),
                }
                for n, p, length, qw, qp, origin in zip(
                    self.bone_names,
                    self.bone_parents,
                    self.bone_lengths,
                    self.rest_world_from_bone_quat,
                    self.rest_parent_from_bone_quat,
                    origins,
                    strict=False,
                )
            },
            "root_rest_pos_m": [float(x) for x in self.root_rest_pos],
            **({"functional": self.functional} if self.functional else {}),
            **({"layout_refined": self.layout_refined} if self.layout_refined else {}),
        }

    def save(self, path: str | Path) -> None:
        """Write the calibration as JSON, atomically (:func:`write_atomic`): a
        crash or a full disk leaves the file that was there whole.

        Raises:
            OSError: not written (one line naming the file); the old file is kept.
        """
        write_atomic(path, (json.dumps(self.to_json(), indent=1) + "\n").encode())


def _rows(pos: F64Array | None, n: int) -> Sequence[F64Array | None]:
    """A (n, 3) array's rows, or n Nones without one."""
    return [None] * n if pos is None else list(pos)


def _position(key: str, pos: F64Array | None) -> dict[str, list[float]]:
    """``{key: [x, y, z]}`` (to the nanometre) for a finite position, else {}."""
    if pos is None or not np.isfinite(pos).all():
        return {}
    return {key: [round(float(x), 9) for x in pos]}


def rig_digest(rig: Rig) -> str:
    """A stable digest of a rig's content (its source text when it has one)."""
    return hashlib.sha256(repr(rig).encode()).hexdigest()


def load_calibration(path: str | Path) -> Calibration:
    """Read a calibration JSON file.

    Raises:
        CalibrationError: unreadable or not a calibration, naming the file.
    """
    try:
        doc = loads_json(read_text(path, "calibration"))
    except FileFormatError as exc:
        raise CalibrationError(f"{path}: {exc}") from None
    if not isinstance(doc, dict) or doc.get("format") != CALIBRATION_FORMAT:
        raise CalibrationError(f"{path}: not a retargetd calibration file")
    if doc.get("version") != CALIBRATION_VERSION:
        raise CalibrationError(
            f"{path}: calibration version {doc.get('version')!r}; this retargetd reads "
            f"version {CALIBRATION_VERSION}"
        )
    try:
        bones = doc["bones"]
        bone_names = tuple(bones)
        index = {n: i for i, n in enumerate(bone_names)}
        segs = {
            name: (tuple(s["markers"]), np.asarray(s["layout_m"], dtype=np.float64))
            for name, s in doc["segments"].items()
        }
        return Calibration(
            rig_name=doc["rig"]["name"],
            rig_source=doc["rig"]["source"],
            rig_sha256=doc["rig"]["sha256"],
            marker_names=tuple(doc["markers"]),
            markers_seen=tuple(float(m["seen"]) for m in doc["markers"].values()),
            point_names=tuple(doc["points"]),
            point_offsets=np.asarray(
                [p["offset_m"] for p in doc["points"].values()], dtype=np.float64
            ).reshape(-1, 3),
            segment_layouts=segs,
            bone_names=bone_names,
            bone_parents=tuple(
                -1 if b["parent"] is None else index[b["parent"]]
                for b in bones.values()
            ),
            bone_lengths=np.asarray([b["length_m"] for b in bones.values()]),
            rest_world_from_bone_quat=np.asarray(
                [b["rest_world_from_bone_quat"] for b in bones.values()]
            ).reshape(-1, 4),
            rest_parent_from_bone_quat=np.asarray(
                [b["rest_parent_from_bone_quat"] for b in bones.values()]
            ).reshape(-1, 4),
            root_rest_pos=np.asarray(doc["root_rest_pos_m"], dtype=np.float64),
            rest_bone_origin_pos=(
                np.asarray(
                    [b["rest_origin_m"] for b in bones.values()], dtype=np.float64
                ).reshape(-1, 3)
                if all("rest_origin_m" in b for b in bones.values())
                else None
            ),
            measurements={
                k: MeasurementUsed(value_mm=float(v["value"]), source=str(v["source"]))
                for k, v in doc["measurements_mm"].items()
            },
            base_pose=dict(doc.get("base_pose", {})),
            base_marker_pos=np.asarray(
                [m.get("base_m", [np.nan] * 3) for m in doc["markers"].values()],
                dtype=np.float64,
            ).reshape(-1, 3),
            functional=dict(doc.get("functional", {})),
            layout_marker_pos=(
                np.asarray(
                    [
                        m.get("take_m", m.get("base_m", [np.nan] * 3))
                        for m in doc["markers"].values()
                    ],
                    dtype=np.float64,
                ).reshape(-1, 3)
                if "layout_refined" in doc
                else None
            ),
            layout_refined=dict(doc.get("layout_refined", {})),
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise CalibrationError(f"{path}: malformed calibration ({exc!r})") from None


def check_calibration_fits(rig: Rig, calibration: Calibration) -> None:
    """Raise CalibrationError when a calibration was made for another rig."""
    if calibration.rig_name != rig.name or calibration.bone_names != rig.bone_names:
        raise CalibrationError(
            f"calibration is for rig {calibration.rig_name!r} "
            f"({len(calibration.bone_names)} bones), not {rig.name!r}"
        )
    if calibration.point_names != rig.point_names:
        raise CalibrationError(
            f"calibration for rig {rig.name!r} has other derived points than the rig "
            "file now has: recalibrate"
        )


def resolve_measurements(
    rig: Rig,
    from_take: Mapping[str, float],
    overrides: Mapping[str, float] | None = None,
) -> dict[str, MeasurementUsed]:
    """Choose each rig measurement's value: override, take, then default."""
    out: dict[str, MeasurementUsed] = {}
    for name, m in rig.measurements.items():
        if overrides and name in overrides:
            out[name] = MeasurementUsed(
                value_mm=float(overrides[name]), source="override"
            )
            continue
        value = from_take.get(name)
        if (
            value is not None
            and math.isfinite(value)
            and not (value <= 0.0 and m.default_mm > 0.0)
        ):
            out[name] = MeasurementUsed(value_mm=float(value), source="take")
        else:
            out[name] = MeasurementUsed(value_mm=m.default_mm, source="default")
    return out


def match_markers(rig: Rig, labels: Sequence[str]) -> tuple[int, ...]:
    """Column of each rig marker in ``labels`` (-1 when the take lacks it).

    Labels are matched after stripping any ``Name:`` prefix; a rig marker's aliases
    are tried in order; labels the rig does not name are ignored. A marker none of
    whose aliases is a label exactly then takes a label that equals one of its
    aliases but for case (``lasi`` for ``LASI``; aliases in order), when that
    alias has only one such spelling among the labels and no other marker took
    that label exactly: labs disagree on case, never on purpose within one take.
    A rig marker's own name is not a label unless it is listed as one (RIGS.md).
    """
    stripped: dict[str, int] = {}
    for i, label in enumerate(labels):
        stripped.setdefault(label.rsplit(":", 1)[-1], i)
    cols = [
        next((stripped[a] for a in aliases if a in stripped), -1)
        for aliases in rig.markers.values()
    ]
    if all(c >= 0 for c in cols):
        return tuple(cols)
    spellings: dict[str, list[str]] = {}
    for name in stripped:
        spellings.setdefault(name.casefold(), []).append(name)
    taken = {c for c in cols if c >= 0}
    for k, aliases in enumerate(rig.markers.values()):
        if cols[k] >= 0:
            continue
        for alias in aliases:
            found = spellings.get(alias.casefold(), [])
            if len(found) == 1 and stripped[found[0]] not in taken:
                cols[k] = stripped[found[0]]
                taken.add(cols[k])
                break
    return tuple(cols)


def _unit(v: F64Array) -> F64Array:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def three_point_frame(a: F64Array, b: F64Array, c: F64Array) -> F64Array:
    """(..., 3, 3) world_from_local of the frame of three points (columns x, y, z).

    Origin a, x = unit(b - a), z = unit(x x (c - a)), y = z x x.
    """
    x = _unit(b - a)
    z = _unit(np.cross(x, c - a))
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=-1)


def body_axes(rig: Rig, pts: Mapping[str, F64Array]) -> F64Array:
    """(F, 3, 3) base-pose body axes per frame, columns height, width, depth."""
    right, left = rig.lateral
    lat = pts[left] - pts[right]
    lat = lat.copy()
    lat[..., 2] = 0.0
    width = _unit(lat)
    height = np.broadcast_to(np.array([0.0, 0.0, 1.0]), width.shape)
    depth = np.cross(width, height)
    return np.stack([height, width, depth], axis=-1)


def _finite_mean(x: F64Array, axis: int = 0) -> F64Array:
    """Mean over ``axis`` of the finite entries (NaN where there are none), quietly."""
    ok = np.isfinite(x)
    count = ok.sum(axis=axis)
    total = np.where(ok, x, 0.0).sum(axis=axis)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def _mean_quat(q: F64Array) -> F64Array:
    """Average of (F, 4) quaternions near each other (sign-aligned chordal mean)."""
    ok = np.isfinite(q).all(axis=-1)
    q = q[ok]
    if q.shape[0] == 0:
        return np.array([1.0, 0.0, 0.0, 0.0])
    signs = np.where(q @ q[0] < 0.0, -1.0, 1.0)
    mean = (q * signs[:, None]).sum(axis=0)
    return mean / np.linalg.norm(mean)


def compute_points(
    rig: Rig,
    marker_pos: F64Array,
    point_offsets: F64Array,
) -> dict[str, F64Array]:
    """All rig points (markers and derived) over frames, with the given offsets.

    Args:
        rig: the rig.
        marker_pos: (F, Mr, 3) metres, world; NaN = occluded.
        point_offsets: (P, 3) metres, local offsets of rigid points (rig order).

    Returns:
        name -> (F, 3) metres, world.
    """
    pts = {m: marker_pos[:, i] for i, m in enumerate(rig.markers)}
    for p, off in zip(rig.points, point_offsets, strict=False):
        if isinstance(p, LinePoint):
            pts[p.name] = pts[p.a] + p.u * (pts[p.b] - pts[p.a])
        else:
            frame = three_point_frame(*(pts[n] for n in p.frame))
            pts[p.name] = pts[p.frame[0]] + frame @ off
    return pts


def calibrate(
    rig: Rig,
    positions: F64Array,
    labels: Sequence[str],
    *,
    take_measurements: Mapping[str, float] | None = None,
    overrides: Mapping[str, float] | None = None,
    base_pose: Mapping[str, Any] | None = None,
    rom: tuple[F64Array, Sequence[str], Mapping[str, Any]] | None = None,
) -> Calibration:
    """Calibrate a rig on base-pose frames.

    Args:
        rig: the rig.
        positions: (F, M, 3) float64, metres, world; NaN rows = occluded. The
            performer holds the base pose over these frames.
        labels: (M,) the take's marker labels.
        take_measurements: the take's subject measurements (mm), if any.
        overrides: measurement overrides (mm).
        base_pose: provenance saved with the calibration (take, frames ...).
        rom: a range of motion for the rig's ``[functional]`` joints: (F, M, 3)
            positions as ``positions``, its labels, and its provenance
            (``body.calibrate_rom``); a joint it does not determine keeps the base
            pose's estimate, said in a line of ``functional["notes"]``.

    Returns:
        The calibrated skeleton.

    Raises:
        CalibrationError: no frames, or a bone whose points were never seen.
    """
    positions = np.asarray(positions, dtype=np.float64)
    if positions.ndim != 3 or positions.shape[0] == 0:
        raise CalibrationError(
            f"calibration needs (frames, markers, 3) positions; got {positions.shape}"
        )
    cols = np.asarray(match_markers(rig, labels))
    n_frames = positions.shape[0]
    marker_pos = np.full((n_frames, len(cols), 3), np.nan)
    have = cols >= 0
    marker_pos[:, have] = positions[:, cols[have]]
    seen = np.isfinite(marker_pos).all(axis=-1)
    seen_frac = seen.mean(axis=0)
    missing = [m for m, f in zip(rig.markers, seen_frac, strict=False) if f == 0.0]
    if missing:
        logger.warning("calibration: markers never seen: %s", ", ".join(missing))
    meas = resolve_measurements(rig, take_measurements or {}, overrides)
    values = {k: v.value_mm for k, v in meas.items()}
    defaults = [k for k, v in meas.items() if v.source == "default"]
    if defaults:
        logger.info(
            "calibration: measurements at rig defaults: %s", ", ".join(defaults)
        )

    # Rigid segments: the base-pose layout of the markers that were seen.
    layouts: dict[str, tuple[tuple[str, ...], F64Array]] = {}
    index = {m: i for i, m in enumerate(rig.markers)}
    mean_pos = _finite_mean(np.where(seen[..., None], marker_pos, np.nan))
    for seg, names in rig.segments.items():
        kept = tuple(n for n in names if seen_frac[index[n]] > 0.0)
        if len(kept) < 3:
            logger.warning("calibration: segment %s has < 3 markers seen: unused", seg)
            continue
        layouts[seg] = (kept, mean_pos[[index[n] for n in kept]].round(9))

    # Derived points in order; a rule point's offset is fixed from the base pose,
    # a functional one from the range of motion.
    romp = None
    if rom is not None and rig.functional:
        rom_pos = np.asarray(rom[0], dtype=np.float64)
        rom_cols = np.asarray(match_markers(rig, rom[1]), dtype=np.int64)
        rom_markers = np.full((rom_pos.shape[0], len(rom_cols), 3), np.nan)
        rom_markers[:, rom_cols >= 0] = rom_pos[:, rom_cols[rom_cols >= 0]]
        romp = RomPoints(rig, rom_markers, three_point_frame, rom[2])
    offsets = np.zeros((len(rig.points), 3))
    pts = {m: marker_pos[:, i] for i, m in enumerate(rig.markers)}
    for k, p in enumerate(rig.points):
        if isinstance(p, LinePoint):
            pts[p.name] = pts[p.a] + p.u * (pts[p.b] - pts[p.a])
            if romp is not None:
                romp.offset(p, offsets[k], pts)
            continue
        frame = three_point_frame(*(pts[n] for n in p.frame))  # (F, 3, 3)
        origin = pts[p.frame[0]]
        if p.offset_mm is not None:
            offsets[k] = [e.evaluate(values) * 1e-3 for e in p.offset_mm]
        else:
            assert p.rule is not None
            for name in rig.lateral:
                if name not in pts:
                    raise CalibrationError(
                        f"rig {rig.name}: rig.lateral point {name!r} must be a marker "
                        f"or a point defined before {p.name!r}"
                    )
            axes = body_axes(rig, pts)  # (F, 3, 3) columns height, width, depth
            target = np.zeros_like(origin)
            for col, axis in enumerate(("height", "width", "depth")):
                combo = sum(coef * pts[n] for n, coef in p.rule[axis].terms)
                vec = axes[..., col]
                target = target + vec * np.sum(vec * combo, axis=-1, keepdims=True)
            local = np.einsum("fji,fj->fi", frame, target - origin)
            ok = np.isfinite(local).all(axis=-1)
            if not ok.any():
                raise CalibrationError(
                    f"rig {rig.name}: point {p.name}: its markers were never all seen "
                    "in the base pose"
                )
            offsets[k] = local[ok].mean(axis=0)
        if romp is not None:
            offsets[k] = romp.offset(p, offsets[k], pts)
        pts[p.name] = origin + frame @ offsets[k]

    # Bones: rest orientation per frame with the kernel's construction, averaged.
    wfb = bone_world_quats(rig, pts)  # (F, B, 4), NaN where undetermined
    rest_wfb = np.zeros((len(rig.bones), 4))
    lengths = np.zeros(len(rig.bones))
    origins = np.zeros((len(rig.bones), 3))
    for b, bone in enumerate(rig.bones):
        if not np.isfinite(wfb[:, b]).all(axis=-1).any():
            raise CalibrationError(
                f"rig {rig.name}: bone {bone.name}: its points were never all seen in "
                "the base pose (markers: "
                + ", ".join(_bone_markers(rig, bone.name))
                + ")"
            )
        rest_wfb[b] = _mean_quat(wfb[:, b])
        lengths[b] = np.nanmean(
            np.linalg.norm(pts[bone.aim] - pts[bone.origin], axis=-1)
        )
        origins[b] = _finite_mean(pts[bone.origin])
    parents = rig.bone_parent_indices()
    rest_pfb = np.zeros_like(rest_wfb)
    for b, par in enumerate(parents):
        rest_pfb[b] = (
            rest_wfb[b] if par < 0 else quat_mul(quat_conj(rest_wfb[par]), rest_wfb[b])
        )
    root = rig.bones[0].origin
    functional: dict[str, Any] = {}
    if romp is not None:
        functional = romp.finish(pts, rest_wfb, rest_pfb)
    return Calibration(
        rig_name=rig.name,
        rig_source=rig.source,
        rig_sha256=rig_digest(rig),
        marker_names=rig.marker_names,
        markers_seen=tuple(float(f) for f in seen_frac),
        point_names=rig.point_names,
        point_offsets=offsets,
        segment_layouts=layouts,
        bone_names=rig.bone_names,
        bone_parents=parents,
        bone_lengths=lengths,
        rest_world_from_bone_quat=rest_wfb,
        rest_parent_from_bone_quat=rest_pfb,
        root_rest_pos=_finite_mean(pts[root]),
        rest_bone_origin_pos=origins,
        measurements=meas,
        base_pose=dict(base_pose or {}, frames_used=int(n_frames)),
        base_marker_pos=_stored_m(_nan_mean_rows(marker_pos)),
        functional=functional,
    )


def _stored_m(pos: F64Array) -> F64Array:
    """Positions rounded as the calibration file stores them (nm), so a calibration
    used at once solves exactly as the same one saved and loaded (the fit is
    iterative, with a gate: a difference in the last digits can tip a frame's
    decision)."""
    return np.array([[round(float(x), 9) for x in row] for row in pos]).reshape(
        pos.shape
    )


def _nan_mean_rows(pos: F64Array) -> F64Array:
    """(F, M, 3) -> (M, 3): the mean over frames of each marker's seen rows (NaN for a
    marker never seen), without numpy's empty-slice warning."""
    ok = np.asarray(np.isfinite(pos).all(axis=-1))
    n: np.ndarray = ok.sum(axis=0)
    total = np.where(ok[..., None], pos, 0.0).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = total / n[:, None]
    mean[n == 0] = np.nan
    return mean


def _bone_markers(rig: Rig, bone_name: str) -> list[str]:
    bone = next(b for b in rig.bones if b.name == bone_name)
    out: list[str] = []
    for p in bone.inputs:
        out.extend(m for m in rig.markers_of(p, base_pose=True) if m not in out)
    return out


def bone_world_quats(rig: Rig, pts: Mapping[str, F64Array]) -> F64Array:
    """World rotation of every bone from its points, numpy (calibration, test oracle).

    Args:
        rig: the rig.
        pts: point name -> (F, 3) metres, world.

    Returns:
        (F, B, 4) world_from_bone, w x y z; NaN where the bone is undetermined.
    """
    out = []
    for bone in rig.bones:
        y = pts[bone.aim] - pts[bone.origin]
        y = y / np.linalg.norm(y, axis=-1, keepdims=True)
        up = (
            pts[bone.up[1]] - pts[bone.up[0]]
            if len(bone.up) == 2
            else pts[bone.up[0]] - pts[bone.origin]
        )
        x = up - np.sum(up * y, axis=-1, keepdims=True) * y
        nx = np.linalg.norm(x, axis=-1, keepdims=True)
        bad = ~(nx[..., 0] > 1e-2 * np.linalg.norm(up, axis=-1))
        x = x / nx
        z = np.cross(x, y)
        mat = np.stack([x, y, z], axis=-1)
        q = np.full((*mat.shape[:-2], 4), np.nan)
        ok = np.isfinite(mat).all(axis=(-1, -2)) & ~bad
        if ok.any():
            q[ok] = quat_from_mat(mat[ok])
        out.append(q)
    return np.stack(out, axis=-2)
