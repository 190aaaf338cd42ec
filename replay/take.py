"""The in-memory take: labelled markers over time, in the internal world.

Every take format (C3D, TRC, and later MCAP recordings) loads into one :class:`Take`.
Positions are converted once, at load, from the file's units and up axis to world
metres (see ``retargetd.protocols.conventions``). Vendor model outputs stored beside
the markers (Plug-in Gait joint centres, segment points, angles, forces ...) are kept
apart in :class:`References` and never enter the marker stream.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from retargetd.protocols.frames import BoolArray, F64Array

#: Kinds of vendor model output a take may carry (``References.kinds``).
REFERENCE_KINDS = (
    "joint_centre",  # e.g. LHJC, LKJC (computed joint centres)
    "segment_point",  # Plug-in Gait segment origin/anterior/lateral/proximal (LFEO ...)
    "model_point",  # other computed points (CentreOfMass ...)
    "angle",  # degrees, as written by the vendor
    "force",
    "moment",
    "power",
    "other",
)

#: Reference kinds that are positions, converted to world metres like the markers.
POSITION_KINDS = ("joint_centre", "segment_point", "model_point")


class TakeError(ValueError):
    """A take that cannot be loaded as asked (missing file, unknown format, ambiguous
    subject ...). The message is one line, meant for the user."""


@dataclass(frozen=True, slots=True, kw_only=True)
class References:
    """Vendor model outputs stored beside the markers.

    Attributes:
        labels: (R,) names with any subject prefix stripped.
        kinds: (R,) one of :data:`REFERENCE_KINDS` per label.
        values: (T, R, 3) float64. Position kinds are in metres, internal world; the
            others are as written by the vendor (``units`` gives them), never rotated.
        units: (R,) unit of each label's values (``"m"`` for positions, ``"deg"`` ...).
    """

    labels: tuple[str, ...]
    kinds: tuple[str, ...]
    values: F64Array
    units: tuple[str, ...]

    def index(self, label: str) -> int:
        """Column of ``label`` in ``values``. Raises KeyError naming the label."""
        try:
            return self.labels.index(label)
        except ValueError:
            raise KeyError(f"no reference named {label!r}") from None

    def get(self, label: str) -> F64Array:
        """(T, 3) values of one reference."""
        return self.values[:, self.index(label), :]


def _no_references() -> References:
    return References(labels=(), kinds=(), values=np.zeros((0, 0, 3)), units=())


@dataclass(frozen=True, slots=True, kw_only=True)
class Take:
    """A loaded take.

    Attributes:
        path: the file it came from.
        format: ``"c3d"``, ``"trc"`` or ``"mcap"`` (a recording).
        subject: the subject this take holds (prefix stripped from labels), or None.
        subjects: every subject found in the file: label prefixes (``Name:``), or the
            single C3D ``SUBJECTS:NAMES`` entry of an unprefixed file; else empty.
        labels: (M,) marker labels, subject prefix stripped.
        positions: (T, M, 3) float64, metres, internal world; NaN rows = occluded.
        valid: (T, M) bool, True where the marker was seen.
        rate_hz: frame rate.
        first_frame: the source's number of row 0 (C3D header first frame, TRC Frame#).
        units: the file's length unit before conversion (``"mm"``, ``"m"`` ...).
        up_axis: the file's up axis before conversion (``"+Z"``, ``"+Y"`` ...).
        units_source / up_source: where each came from (``"file"``, ``"default"``,
            ``"override"``), with the parameter when from the file.
        world_from_capture: (3, 3) float64 rotation applied at load.
        references: vendor model outputs (joint centres, angles ...), kept apart.
        measurements: subject measurements (C3D ``PROCESSING`` group), name -> value as
            written by the vendor (lengths in mm for Vicon, body mass in kg).
        manufacturer: the writing software as found in the file, or "".
        unassigned_labels: labels as written that carry no subject prefix in a file
            whose other labels do; they belong to no subject and were left out.
        reader: the reader that read the file (``"ezc3d 1.7.2"``, ``"c3d 0.6.0
            (fallback)"``, ``"retargetd TRC reader"`` ...), or "".
        rate_source: where ``rate_hz`` came from (``"file (POINT:RATE)"``,
            ``"override (--take-rate)"`` ...), or "".
        repairs: what the reader had to work around to read the file, one line each
            (empty for a file read as written).
    """

    path: str
    format: str
    subject: str | None
    subjects: tuple[str, ...]
    labels: tuple[str, ...]
    positions: F64Array
    valid: BoolArray
    rate_hz: float
    first_frame: int
    units: str
    up_axis: str
    units_source: str
    up_source: str
    world_from_capture: F64Array
    references: References = field(default_factory=_no_references)
    measurements: dict[str, float] = field(default_factory=dict)
    manufacturer: str = ""
    unassigned_labels: tuple[str, ...] = ()
    reader: str = ""
    rate_source: str = ""
    repairs: tuple[str, ...] = ()

    @property
    def n_frames(self) -> int:
        """Number of frames (rows)."""
        return int(self.positions.shape[0])

    @property
    def n_markers(self) -> int:
        """Number of markers (columns)."""
        return int(self.positions.shape[1])

    @property
    def duration_s(self) -> float:
        """Duration from the first to one past the last frame, seconds."""
        return self.n_frames / self.rate_hz

    @property
    def gap_fraction(self) -> float:
        """Fraction of (frame, marker) samples that are occluded."""
        if self.valid.size == 0:
            return 0.0
        return float(1.0 - self.valid.mean())

    def select_rows(self, rows: slice) -> Take:
        """The take cut to ``rows`` (a step-1 slice of row indices, as
        ``daemon.cli.args.parse_frames`` gives): markers, validity and references
        cut alike, ``first_frame`` moved on by ``rows.start`` so that row 0 of the
        result keeps its source frame number."""
        start, stop, step = rows.indices(self.n_frames)
        if step != 1 or stop <= start:
            raise ValueError(f"rows must select frames in order; got {rows}")
        refs = self.references
        if refs.values.shape[0] == self.n_frames:
            refs = replace(refs, values=refs.values[start:stop])
        return replace(
            self,
            positions=self.positions[start:stop],
            valid=self.valid[start:stop],
            references=refs,
            first_frame=self.first_frame + start,
        )

    def marker_index(self, label: str) -> int:
        """Column of a marker label. Raises KeyError naming the label."""
        try:
            return self.labels.index(label)
        except ValueError:
            raise KeyError(f"take {self.path} has no marker {label!r}") from None
