"""Which markers are facial: the face config's list, or the layout's, never the body's.

A marker is facial when the face config lists it (``facial_markers``), or, when the
config lists none, when it is neither a head marker nor a marker the body rig names
(its aliases, prefixes and case, as ``body.calibration.match_markers`` matches them)
and it lies on the head's side of the neck in the neutral pose. Names a body rig uses
are never facial: a config that lists one is refused (:class:`FacialMarkerError`,
one line naming the marker).

The neck, in the neutral pose, is the horizontal plane :data:`NECK_BELOW_HEAD_M`
below the head markers' centroid (world +Z up, the internal world's axis: a neutral
face is held upright). Markers below it are body markers whatever their names.
The plane catches the torso and the limbs; the top of the thorax (C7, the
acromions) reaches above the chin's level, which is why the rig's names are checked
first and a rig is always given (the presets name ``plug-in-gait``).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np

from retargetd.daemon.body.calibration import match_markers
from retargetd.daemon.body.rig import Rig
from retargetd.protocols.frames import F64Array

logger = logging.getLogger(__name__)

#: The neck plane's depth below the head markers' centroid, metres. Measured on the
#: shared data: under the Plug-in Gait walk's own head band (LFHD RFHD LBHD RBHD) the
#: chins of the two real face meshes (ICT-FaceKit, MakeHuman) lie 0.147 and 0.149 m
#: below the centroid, that subject's CLAV (sternal notch) 0.218 m, STRN 0.362 m and
#: the shoulders 0.171-0.188 m. 0.2 m leaves 5 cm under the chin (a longer face, a
#: band worn higher) and puts the sternum and everything lower on the body's side.
NECK_BELOW_HEAD_M = 0.2


class FacialMarkerError(ValueError):
    """A body marker listed as facial, or no facial marker at all: one line."""


def rig_marker_labels(rigs: Sequence[Rig], labels: Sequence[str]) -> set[str]:
    """The labels the ``rigs`` name (matched as the body solve matches them)."""
    return {labels[c] for rig in rigs for c in match_markers(rig, labels) if c >= 0}


def check_listed(
    listed: Sequence[str], head_markers: Sequence[str], rigs: Sequence[Rig]
) -> None:
    """Refuse a listed facial marker that a body rig names (its name or an alias,
    after any ``Subject:`` prefix, in any case).

    Raises:
        FacialMarkerError: one line naming the first such marker and the rig.
    """
    head = {n.casefold() for n in head_markers}
    for rig in rigs:
        names = set(rig.markers) | {a for al in rig.markers.values() for a in al}
        folded = {n.casefold() for n in names} - head
        for n in listed:
            if n.rsplit(":", 1)[-1].casefold() in folded:
                raise FacialMarkerError(
                    f"facial_markers: {n} is a marker of the body rig {rig.name}, "
                    "not a facial marker"
                )


def on_head_side(head_world: F64Array, markers_world: F64Array) -> np.ndarray:
    """Which markers lie on the head's side of the neck in a neutral pose.

    Args:
        head_world: (H, 3) float64, metres, world: the head markers (NaN = unseen).
        markers_world: (N, 3) float64, metres, world (NaN = unseen: not facial).

    Returns:
        (N,) bool: above the plane :data:`NECK_BELOW_HEAD_M` below the head
        markers' centroid.
    """
    centre_z = float(np.nanmean(head_world[:, 2]))
    z = markers_world[:, 2]
    return np.isfinite(z) & (z > centre_z - NECK_BELOW_HEAD_M)


def select_facial(
    labels: Sequence[str],
    head_markers: Sequence[str],
    listed: Sequence[str],
    rigs: Sequence[Rig],
    neutral_world: F64Array | None,
) -> tuple[str, ...]:
    """The facial markers of a take or stream.

    Args:
        labels: (N,) the take's (stream's) marker labels.
        head_markers: the face config's head markers (never facial).
        listed: the face config's ``facial_markers`` (empty = choose).
        rigs: the body rigs; the labels they name are never facial.
        neutral_world: (N, 3) float64, metres, world: the mean neutral pose, columns
            as ``labels`` (None: the neck test is skipped, names only).

    Returns:
        The facial marker names, in ``listed`` order or else in label order.

    Raises:
        FacialMarkerError: a listed marker a rig names, or none left to choose.
    """
    if listed:
        check_listed(listed, head_markers, rigs)
        return tuple(listed)
    body = rig_marker_labels(rigs, labels)
    head = set(head_markers)
    keep = np.array([lb not in head and lb not in body for lb in labels], bool)
    if neutral_world is not None:
        cols = [labels.index(n) for n in head_markers if n in labels]
        if cols:
            keep &= on_head_side(neutral_world[cols], neutral_world)
    chosen = tuple(lb for lb, k in zip(labels, keep, strict=True) if k)
    if not chosen:
        raise FacialMarkerError(
            "facial markers: none (every label is a head marker, a marker of the "
            "body rig or below the neck); list them in facial_markers"
        )
    return chosen
