"""The range of motion's part of a calibration (``calibrate --rom``): the rig's
``[functional]`` joints (``body.rig_functional``) estimated from the moving take
(``body.functional``) while :func:`~retargetd.daemon.body.calibration.calibrate`
places the rig's points in order.

:class:`RomPoints` follows the calibration's loop over the derived points: for each
point it is told the base pose's offset, and it returns the offset to keep: the
functional centre where the rig names the point one and the motion determined it,
else the base pose's. A point named as an axis' ``centre`` is moved onto that axis
(nearest point, at the base pose). Every estimate is recorded, determined or not
(:attr:`RomPoints.record`: the calibration file's ``functional`` table), and a joint
the motion did not determine is named in one line (:attr:`RomPoints.notes`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from retargetd.daemon import rotations as rot
from retargetd.daemon.body.functional import (
    MAX_AXIS_SE_RAD,
    MAX_SE_M,
    MIN_ARC_RAD,
    Estimate,
    hinge_axis,
    sphere_centre,
)
from retargetd.daemon.body.rig_fit import hinge_axes_in_bone
from retargetd.daemon.body.rig_functional import FunctionalAxis
from retargetd.daemon.body.rig_model import LinePoint, Rig
from retargetd.protocols.frames import F64Array

Frame = Callable[[F64Array, F64Array, F64Array], F64Array]


def _local(frame: F64Array, origin: F64Array, world: F64Array) -> F64Array:
    """(F, K, 3) world points in the (F, 3, 3) frames at (F, 3) origins."""
    return np.einsum("fji,fkj->fki", frame, world - origin[:, None, :])


def _mean_finite(x: F64Array) -> F64Array:
    ok = np.isfinite(x).all(axis=-1)
    return x[ok].mean(axis=0) if ok.any() else np.full(x.shape[-1], np.nan)


class RomPoints:
    """The functional joints of ``rig`` from a range of motion (module docstring).

    Args:
        rig: the rig (its ``[functional]`` table).
        marker_pos: (F, Mr, 3) the range of motion's rig markers, metres, world; NaN
            where occluded.
        frame_of: the calibration's three-point frame function.
        source: where the range of motion came from (recorded).
    """

    def __init__(
        self,
        rig: Rig,
        marker_pos: F64Array,
        frame_of: Frame,
        source: Mapping[str, Any],
    ) -> None:
        self.rig = rig
        self.frame_of = frame_of
        self.pts: dict[str, F64Array] = {
            m: marker_pos[:, i] for i, m in enumerate(rig.markers)
        }
        self.centres = {c.point: c for c in rig.functional.points}
        self.axes_at = {a.centre: a for a in rig.functional.axes if a.centre}
        self.axes: dict[str, tuple[FunctionalAxis, Estimate]] = {}
        self.record: dict[str, dict[str, Any]] = {}
        self.notes: list[str] = []
        self.source = dict(source)

    def _markers(self, names: Sequence[str]) -> F64Array:
        return np.stack([self.pts[m] for m in names], axis=1)

    def offset(
        self,
        point: Any,
        base_offset: F64Array,
        base_pts: Mapping[str, F64Array],
    ) -> F64Array:
        """The offset to keep for ``point`` (the calibration's loop, in order)."""
        if isinstance(point, LinePoint):
            self.pts[point.name] = self.pts[point.a] + point.u * (
                self.pts[point.b] - self.pts[point.a]
            )
            return base_offset
        off = np.asarray(base_offset, dtype=np.float64)
        frame = self.frame_of(*(self.pts[n] for n in point.frame))
        origin = self.pts[point.frame[0]]
        spec = self.centres.get(point.name)
        if spec is not None:
            est = sphere_centre(_local(frame, origin, self._markers(spec.markers)))
            shift = float(np.linalg.norm(est.value - off))
            self.record[point.name] = _centre_record(est, off, spec.markers)
            if est.determined:
                off = est.value
            else:
                self.notes.append(_not_determined(point.name, est, "centre"))
            self.record[point.name]["moved_mm"] = round(1e3 * shift, 2)
        axis_spec = self.axes_at.get(point.name)
        if axis_spec is not None:
            est = self._axis(axis_spec)
            if est.determined:  # onto the axis, nearest point, at the base pose
                off = _onto_axis(self.frame_of, base_pts, axis_spec, est, point, off)
        self.pts[point.name] = origin + frame @ off
        return off

    def _axis(self, spec: FunctionalAxis) -> Estimate:
        if spec.bone in self.axes:
            return self.axes[spec.bone][1]
        frame = self.frame_of(*(self.pts[n] for n in spec.frame))
        origin = self.pts[spec.frame[0]]
        est = hinge_axis(_local(frame, origin, self._markers(spec.markers)))
        self.axes[spec.bone] = (spec, est)
        if not est.determined:
            self.notes.append(_not_determined(spec.bone, est, "axis"))
        return est

    def finish(
        self,
        base_pts: Mapping[str, F64Array],
        rest_wfb: F64Array,
        rest_pfb: F64Array,
    ) -> dict[str, Any]:
        """Every axis (those without a ``centre`` too) in its bone's rest axes, and
        the record: the calibration file's ``functional`` table (``notes``: a line
        for each joint the motion did not determine)."""
        bones = self.rig.bone_names
        rig_axis_in_bone = hinge_axes_in_bone(self.rig.fit.bones, bones, rest_pfb)
        for spec in self.rig.functional.axes:
            est = self._axis(spec)
            rec = _axis_record(est, spec.markers)
            if est.determined:
                frame = self.frame_of(*(base_pts[n] for n in spec.frame))
                world = _mean_finite(np.einsum("fij,j->fi", frame, est.value))
                b = bones.index(spec.bone)
                axis = rot.quat_rotate(rot.quat_conj(rest_wfb[b]), world)
                axis = axis / np.linalg.norm(axis)
                ref = rig_axis_in_bone.get(spec.bone)
                if ref is not None:
                    if float(axis @ ref) < 0.0:  # the rig's sense of flexion
                        axis = -axis
                    rec["angle_from_rig_deg"] = round(
                        math.degrees(math.acos(min(1.0, abs(float(axis @ ref))))), 2
                    )
                rec["axis_bone"] = [round(float(v), 9) for v in axis]
            self.record[spec.bone] = rec
        return {"source": self.source, "joints": self.record, "notes": self.notes}


def _onto_axis(
    frame_of: Frame,
    base_pts: Mapping[str, F64Array],
    spec: FunctionalAxis,
    est: Estimate,
    point: Any,
    off: F64Array,
) -> F64Array:
    """``point``'s offset moved, at the base pose, to the nearest point of the axis."""
    af = frame_of(*(base_pts[n] for n in spec.frame))
    a0 = base_pts[spec.frame[0]] + np.einsum("fij,j->fi", af, est.point)
    n = np.einsum("fij,j->fi", af, est.value)
    pf = frame_of(*(base_pts[n_] for n_ in point.frame))
    p0 = base_pts[point.frame[0]]
    at = p0 + np.einsum("fij,j->fi", pf, off)
    on = a0 + n * np.sum((at - a0) * n, axis=-1, keepdims=True)
    new = _mean_finite(np.einsum("fji,fj->fi", pf, on - p0))
    return new if np.isfinite(new).all() else off


def _centre_record(
    est: Estimate, base_offset: F64Array, markers: Sequence[str]
) -> dict[str, Any]:
    return {
        "kind": "centre",
        "markers": list(markers),
        "offset_m": [round(float(v), 9) for v in est.value],
        "base_pose_offset_m": [round(float(v), 9) for v in base_offset],
        "rms_mm": round(1e3 * est.rms_m, 3),
        "se_mm": round(1e3 * est.se, 3) if est.se < _HARDLY_MOVED_M else None,
        "frames": est.frames,
        "determined": est.determined,
        "used": est.determined,
    }


def _axis_record(est: Estimate, markers: Sequence[str]) -> dict[str, Any]:
    return {
        "kind": "axis",
        "markers": list(markers),
        "axis_frame": [round(float(v), 9) for v in est.value],
        "rms_mm": round(1e3 * est.rms_m, 3),
        "se_deg": round(math.degrees(est.se), 3) if est.se < 1.0 else None,
        "arc_deg": round(math.degrees(est.arc_rad), 1),
        "frames": est.frames,
        "determined": est.determined,
        "used": est.determined,
    }


#: A predicted error past this (metres; for an axis, radians) says the joint hardly
#: moved: the number itself means nothing then.
_HARDLY_MOVED_M = 1.0


def _not_determined(name: str, est: Estimate, kind: str) -> str:
    if est.frames == 0:
        why = "its markers were not seen in it"
    elif est.se >= _HARDLY_MOVED_M:
        why = "the joint hardly moved"
    elif kind == "centre":
        why = f"predicted error {1e3 * est.se:.1f} mm > {1e3 * MAX_SE_M:.0f} mm"
    else:
        why = (
            f"it turned {math.degrees(est.arc_rad):.0f} deg (>= "
            f"{math.degrees(MIN_ARC_RAD):.0f} wanted), predicted error "
            f"{math.degrees(est.se):.1f} deg (<= {math.degrees(MAX_AXIS_SE_RAD):.1f})"
        )
    keep = "keeps its base-pose offset" if kind == "centre" else "keeps the rig's axis"
    return f"range of motion does not determine {name}'s {kind}: {why}; it {keep}"
