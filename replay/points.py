"""Point handling shared by the take readers and writers (C3D, TRC).

A take file stores *points*: labelled 3-vectors per frame. Some are markers, some are
vendor model outputs (Plug-in Gait joint centres, segment points, angles, forces ...).
This module turns the raw points of any format into one
:class:`~retargetd.replay.take.Take`:

1. **Subjects.** A label ``"Name:LKNE"`` belongs to subject ``Name`` (Vicon, Motive
   prefixes; C3D ``SUBJECTS:LABEL_PREFIXES``/``NAMES`` are used when present). One
   subject is selected automatically, several need ``subject=``. Labels without a prefix
   in a file that has prefixed subjects belong to no subject: they are dropped when a
   subject is selected (they are typically unlabelled trajectories, and keeping them
   would mix a stray point into a subject's marker set) and listed in
   ``Take.unassigned_labels``. A file without prefixes but with exactly one C3D
   ``SUBJECTS:NAMES`` entry (Vicon single-subject files) holds that subject and all its
   labels.
2. **Kinds.** Each (prefix-stripped) label is a marker or a reference kind, see
   :func:`reference_kind`. References never enter ``Take.labels``/``positions``.
3. **Units and up axis.** An explicit override wins, then the file's value, then the
   format's default; the source of each is recorded for ``retargetd take info``.
4. **World.** Markers and position references go to world metres with
   ``retargetd.protocols.conventions.world_from_capture_pos``; the other references
   are kept as written.

Every problem with the input is a one-line :class:`~retargetd.replay.take.TakeError`
naming the file.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from retargetd.protocols import conventions as cv
from retargetd.protocols.frames import BoolArray, F64Array
from retargetd.replay.take import POSITION_KINDS, References, Take, TakeError

logger = logging.getLogger(__name__)

#: Plug-in Gait segment codes; a code plus O/A/L/P (origin, anterior, lateral,
#: proximal) names one of the segment's axis points (``LFEO`` is the knee centre).
PIG_SEGMENTS = (
    "PEL", "HED", "TRX", "LCL", "RCL", "LHU", "RHU", "LRA", "RRA", "LHN", "RHN",
    "LFE", "RFE", "LTI", "RTI", "LFO", "RFO", "LTO", "RTO",
)  # fmt: skip
_SEGMENT_POINT = re.compile(rf"(?:{'|'.join(PIG_SEGMENTS)})[OALP]")
_JOINT_CENTRE = re.compile(r"[LR]?[A-Z]{1,3}JC")
_MODEL_POINTS = frozenset({"CentreOfMass", "CentreOfMassFloor"})


@dataclass(frozen=True, slots=True)
class Resolved:
    """A value chosen from override, file or default, with where it came from."""

    value: str
    source: str


def reference_kind(label: str, declared: Mapping[str, str] | None = None) -> str | None:
    """Kind of vendor model output a label names, or None for a marker.

    Args:
        label: the point label, subject prefix already stripped.
        declared: label -> kind from the file itself (C3D ``POINT:ANGLES`` -> "angle"
            ...); checked first.

    Returns:
        One of ``retargetd.replay.take.REFERENCE_KINDS``, or None when it is a marker.
        By name: ``[LR]?[A-Z]{1,3}JC`` -> "joint_centre"; a Plug-in Gait segment code
        plus O/A/L/P -> "segment_point"; ``CentreOfMass(Floor)`` -> "model_point".
    """
    if declared and label in declared:
        return declared[label]
    if _JOINT_CENTRE.fullmatch(label):
        return "joint_centre"
    if _SEGMENT_POINT.fullmatch(label):
        return "segment_point"
    if label in _MODEL_POINTS:
        return "model_point"
    return None


def split_subjects(
    labels: Sequence[str],
    declared_prefixes: Sequence[str] = (),
    declared_names: Sequence[str] = (),
) -> tuple[tuple[str, ...], list[str | None], list[str]]:
    """Assign each label to a subject and strip its prefix.

    Args:
        labels: every point label as written.
        declared_prefixes: C3D ``SUBJECTS:LABEL_PREFIXES`` (``"Name:"``); may be
            empty.
        declared_names: C3D ``SUBJECTS:NAMES``, parallel to the prefixes when both
            exist.

    Returns:
        ``(subjects, owner, stripped)``: subject names in file order; per label the
        owning subject (None when it has no prefix); per label the name without it.
    """
    prefix_to_name: dict[str, str] = {}
    for i, prefix in enumerate(p.strip() for p in declared_prefixes):
        if prefix:
            name = declared_names[i].strip() if i < len(declared_names) else ""
            prefix_to_name[prefix] = name or prefix.rstrip(":")
    for label in labels:
        head, sep, _ = label.partition(":")
        if sep and head and not any(label.startswith(p) for p in prefix_to_name):
            prefix_to_name[head + ":"] = head
    # Longest prefix first, so "A:B:" wins over "A:".
    ordered = sorted(prefix_to_name, key=len, reverse=True)
    owner: list[str | None] = []
    stripped: list[str] = []
    for label in labels:
        match = next((p for p in ordered if label.startswith(p)), None)
        owner.append(prefix_to_name[match] if match else None)
        stripped.append(label[len(match) :] if match else label)
    subjects = tuple(dict.fromkeys(o for o in owner if o is not None))
    if not subjects:
        names = tuple(n.strip() for n in declared_names if n.strip())
        if len(names) == 1:
            # Vicon single-subject files: SUBJECTS:NAMES set, USES_PREFIXES = 0.
            return names, [names[0]] * len(labels), stripped
        if len(names) > 1:
            logger.warning(
                "file declares subjects %s but its labels carry no prefixes; "
                "loading all labels without a subject",
                ", ".join(names),
            )
    return subjects, owner, stripped


def select_subject(
    path: str, subjects: Sequence[str], subject: str | None
) -> str | None:
    """Choose the subject to load.

    Args:
        path: the take file, for messages.
        subjects: subjects found in the file.
        subject: the one asked for (``--subject``), or None.

    Returns:
        The selected subject, or None when the file has none.

    Raises:
        TakeError: several subjects and none asked for; asked for one not in the file.
    """
    listed = ", ".join(subjects)
    if subject is None:
        if len(subjects) > 1:
            raise TakeError(
                f"take {path} holds {len(subjects)} subjects ({listed}): "
                "pass --subject NAME"
            )
        return subjects[0] if subjects else None
    if subject in subjects:
        return subject
    if not subjects:
        raise TakeError(
            f"take {path} has no subjects (no 'Name:' label prefixes); "
            f"drop --subject {subject}"
        )
    raise TakeError(f"take {path} has no subject {subject!r}; it holds: {listed}")


def resolve_units(
    path: str, override: str | None, from_file: str | None, file_source: str,
    default: str, default_source: str,
) -> Resolved:  # fmt: skip
    """Pick the length unit: override, else the file's, else the default.

    Raises:
        TakeError: the override or the file's unit is not a known length unit.
    """
    if override is not None:
        try:
            return Resolved(cv.normalize_units(override), "override")
        except ValueError as exc:
            raise TakeError(f"take {path}: --take-units: {exc}") from None
    if from_file is not None and from_file.strip():
        try:
            return Resolved(cv.normalize_units(from_file), file_source)
        except ValueError as exc:
            raise TakeError(
                f"take {path}: {file_source}: {exc}; pass --take-units to override"
            ) from None
    return Resolved(default, default_source)


def resolve_up_axis(path: str, override: str | None) -> Resolved | None:
    """The up-axis override, normalised, or None when not given.

    Raises:
        TakeError: the override is not an axis.
    """
    if override is None:
        return None
    try:
        return Resolved(cv.normalize_up_axis(override), "override")
    except ValueError as exc:
        raise TakeError(f"take {path}: --take-up: {exc}") from None


def capture_from_world_pos(
    positions_world: F64Array, up_axis: str, units: str
) -> F64Array:
    """Inverse of ``world_from_capture_pos``: world metres to a capture frame and unit.

    Args:
        positions_world: (..., 3) float, metres, internal world; NaN allowed.
        up_axis: the capture frame's up axis (``"+Z"``, ``"+Y"`` ...).
        units: the capture frame's length unit (``"mm"``, ``"m"`` ...).

    Returns:
        (..., 3) float64 in ``units``, capture frame.
    """
    scale = cv.UNIT_TO_METRES[cv.normalize_units(units)]
    mat = cv.world_from_capture_mat(up_axis)
    # p_world = M p_capture * s, M orthonormal  =>  p_capture = M^T p_world / s.
    return np.matmul(np.asarray(positions_world, dtype=np.float64), mat) / scale


def check_positions(labels: Sequence[str], positions_world: F64Array) -> F64Array:
    """Validate a writer's input and return it as float64.

    Raises:
        ValueError: naming the shape mismatch.
    """
    pos = np.asarray(positions_world, dtype=np.float64)
    if pos.ndim != 3 or pos.shape[2] != 3 or pos.shape[1] != len(labels):
        raise ValueError(
            "positions_world must be (n_frames, n_labels, 3) with n_labels = "
            f"{len(labels)}; got shape {pos.shape}"
        )
    return pos


def assemble_take(
    *,
    path: str,
    fmt: str,
    labels: Sequence[str],
    points: F64Array,
    valid: BoolArray,
    subject: str | None,
    units: Resolved,
    up_axis: Resolved,
    rate_hz: float,
    first_frame: int,
    declared_prefixes: Sequence[str] = (),
    declared_names: Sequence[str] = (),
    declared_kinds: Mapping[str, str] | None = None,
    kind_units: Mapping[str, str] | None = None,
    measurements: Mapping[str, float] | None = None,
    manufacturer: str = "",
    reader: str = "",
    rate_source: str = "",
    repairs: Sequence[str] = (),
) -> Take:
    """Build a :class:`Take` from a file's raw points.

    Args:
        path: the file, for messages and ``Take.path``.
        fmt: ``"c3d"`` or ``"trc"``.
        labels: (N,) point labels as written (with prefixes).
        points: (T, N, 3) float64, file units, capture frame; anything where invalid.
        valid: (T, N) bool, True where the point was seen.
        subject: the subject asked for, or None.
        units: the resolved length unit of the file.
        up_axis: the resolved up axis of the file.
        rate_hz: frame rate, Hz.
        first_frame: the source's number of row 0.
        declared_prefixes: C3D ``SUBJECTS:LABEL_PREFIXES``.
        declared_names: C3D ``SUBJECTS:NAMES``.
        declared_kinds: label (as written or stripped) -> reference kind from the file.
        kind_units: reference kind -> unit of its values for non-position kinds.
        measurements: subject measurements, name -> value as written.
        manufacturer: the writing software.
        reader: the reader that read the file (``Take.reader``).
        rate_source: where ``rate_hz`` came from (``Take.rate_source``).
        repairs: what the reader worked around (``Take.repairs``).

    Returns:
        The take: markers of the selected subject in world metres, references apart.

    Raises:
        TakeError: ambiguous or unknown subject, bad rate, duplicate labels.
    """
    if not (np.isfinite(rate_hz) and rate_hz > 0):
        raise TakeError(f"take {path}: frame rate must be > 0 Hz; got {rate_hz}")
    subjects, owner, stripped = split_subjects(
        labels, declared_prefixes, declared_names
    )
    chosen = select_subject(path, subjects, subject)
    declared = dict(declared_kinds or {})
    kind_units = dict(kind_units or {})
    marker_cols: list[int] = []
    ref_cols: list[int] = []
    ref_kinds: list[str] = []
    unassigned: list[str] = []
    seen: set[str] = set()
    for col, (raw, name, who) in enumerate(zip(labels, stripped, owner, strict=True)):
        if who is None and chosen is not None:
            # Only possible when the subjects came from prefixes (see split_subjects).
            unassigned.append(raw)
            continue
        if who is not None and who != chosen:
            continue
        if name in seen:
            logger.warning("take %s: duplicate label %r: keeping the first", path, name)
            continue
        seen.add(name)
        kind = declared.get(raw) or reference_kind(name, declared)
        if kind is None:
            marker_cols.append(col)
        else:
            ref_cols.append(col)
            ref_kinds.append(kind)
    if unassigned:
        logger.info(
            "take %s: %d unprefixed labels belong to no subject and were dropped",
            path,
            len(unassigned),
        )
    points = np.where(valid[..., None], points, np.nan)
    positions = cv.world_from_capture_pos(
        points[:, marker_cols, :], up_axis.value, units.value
    )
    ref_values = points[:, ref_cols, :].copy()
    ref_units: list[str] = []
    for i, kind in enumerate(ref_kinds):
        if kind in POSITION_KINDS:
            ref_values[:, i, :] = cv.world_from_capture_pos(
                ref_values[:, i, :], up_axis.value, units.value
            )
            ref_units.append("m")
        else:
            ref_units.append(kind_units.get(kind, ""))
    references = References(
        labels=tuple(stripped[c] for c in ref_cols),
        kinds=tuple(ref_kinds),
        values=ref_values,
        units=tuple(ref_units),
    )
    return Take(
        path=path,
        format=fmt,
        subject=chosen,
        subjects=subjects,
        labels=tuple(stripped[c] for c in marker_cols),
        positions=positions,
        valid=np.ascontiguousarray(valid[:, marker_cols]),
        rate_hz=float(rate_hz),
        first_frame=int(first_frame),
        units=units.value,
        up_axis=up_axis.value,
        units_source=units.source,
        up_source=up_axis.source,
        world_from_capture=cv.world_from_capture_mat(up_axis.value),
        references=references,
        measurements=dict(measurements or {}),
        manufacturer=manufacturer,
        unassigned_labels=tuple(unassigned),
        reader=reader,
        rate_source=rate_source,
        repairs=tuple(repairs),
    )
