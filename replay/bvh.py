"""BVH (Biovision Hierarchy) reading: the skeleton, and optionally the motion.

The file, as read here (``shared/reference/engines.md`` "BVH")::

    HIERARCHY
    ROOT Hips
    {
        OFFSET 0.0 95.0 0.0
        CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
        JOINT Spine
        {
            OFFSET 0.0 10.0 0.0
            CHANNELS 3 Zrotation Xrotation Yrotation
            ...
            End Site
            {
                OFFSET 0.0 15.0 0.0
            }
        }
    }
    MOTION
    Frames: 2
    Frame Time: 0.0333333
    <one line of sum(channels) numbers per frame>

- ``OFFSET``: the joint's origin in its parent's frame, in the file's length unit and
  axes (usually +Y up, centimetres; the file does not say: the caller declares it).
  There is no rest rotation: the rest pose is every joint at identity, i.e. every joint
  frame parallel to the file's axes.
- ``CHANNELS``: per joint, in the order the motion lines hold them. Rotation channels
  compose in the listed order, ``R = R1 R2 R3`` (``Zrotation Xrotation Yrotation`` is
  ``Rz Rx Ry``, the intrinsic sequence ``"ZXY"`` in scipy's spelling); angles in
  degrees.
- ``End Site``: a leaf's tip offset (no channels, no name).
- Names run to the end of the line (so ``mixamorig:Hips`` and names with spaces
  survive); a ``{`` on the same line is accepted.

One ``ROOT`` per file. Every problem raises ``ValueError`` naming the file and line.

Writing (:func:`write_bvh`) takes plain arrays (a :class:`BvhSkeleton` built with
:func:`bvh_skeleton`, and the motion as one row of channel values per frame, made with
:func:`bvh_motion`) and emits the same layout: two-space indents, ``{`` on its own
line, joints depth first (children in the order given), End Sites on leaves, numbers
with a fixed count of decimals. What the numbers mean (unit, axes, rest pose) is the
caller's; the file cannot say.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from retargetd.protocols.frames import F64Array

logger = logging.getLogger(__name__)

#: Channel names, canonical spelling (matched case-insensitively).
CHANNEL_NAMES = (
    "Xposition",
    "Yposition",
    "Zposition",
    "Xrotation",
    "Yrotation",
    "Zrotation",
)
_CHANNEL_BY_LOWER = {c.lower(): c for c in CHANNEL_NAMES}


@dataclass(frozen=True, slots=True, kw_only=True)
class BvhSkeleton:
    """A BVH hierarchy (and its motion, when read).

    Attributes:
        source: where it was read from (a path, or ``"<text>"``).
        joint_names: (J,) joint names as written, parents before children.
        parents: (J,) parent index, -1 for the root.
        offsets: (J, 3) float64, the file's length unit and axes: each joint's origin
            in its parent's frame (the root's: from the file origin).
        channels: (J,) tuple of channel names per joint (canonical spelling).
        rotation_orders: (J,) the rotation channels' axes in order, e.g. ``"ZXY"``
            (compose ``R = R_Z R_X R_Y``; intrinsic, scipy's upper case); ``""`` for a
            joint without rotation channels.
        end_sites: (J, 3) float64, the file's unit: the End Site offset of each joint
            that has one, NaN rows elsewhere.
        frame_time_s: seconds per frame from the MOTION header (NaN without one).
        n_frames: frames declared in the MOTION header (0 without one).
        frames: (n_frames, n_channels) float64 motion values (degrees for rotations,
            the file's unit for positions) when read with ``read_motion=True``, else
            None.
    """

    source: str
    joint_names: tuple[str, ...]
    parents: tuple[int, ...]
    offsets: F64Array
    channels: tuple[tuple[str, ...], ...]
    rotation_orders: tuple[str, ...]
    end_sites: F64Array
    frame_time_s: float = float("nan")
    n_frames: int = 0
    frames: F64Array | None = None

    @property
    def n_channels(self) -> int:
        """Total number of channels (numbers per motion line)."""
        return sum(len(c) for c in self.channels)

    def channel_offsets(self) -> tuple[int, ...]:
        """Index of each joint's first channel within a motion line."""
        out, at = [], 0
        for c in self.channels:
            out.append(at)
            at += len(c)
        return tuple(out)

    def rest_positions(self) -> F64Array:
        """(J, 3) float64 joint positions in the rest pose, the file's unit and axes.

        The rest pose has every joint at identity, so positions are sums of offsets.
        """
        pos = np.zeros((len(self.joint_names), 3))
        for j, p in enumerate(self.parents):
            pos[j] = self.offsets[j] + (pos[p] if p >= 0 else 0.0)
        return pos


class _Lines:
    """Token cursor over the file, one line at a time (names run to the line's end)."""

    def __init__(self, text: str, source: str) -> None:
        self.source = source
        self.lines = [(n, line.split()) for n, line in enumerate(text.splitlines(), 1)]
        self.lines = [(n, toks) for n, toks in self.lines if toks]
        self.i = 0

    def error(self, message: str, line: int | None = None) -> ValueError:
        if line is None:
            line = self.lines[self.i][0] if self.i < len(self.lines) else self.last
        return ValueError(f"{self.source}:{line}: {message}")

    @property
    def last(self) -> int:
        return self.lines[-1][0] if self.lines else 1

    def peek(self) -> tuple[int, list[str]] | None:
        return self.lines[self.i] if self.i < len(self.lines) else None

    def take(self, what: str) -> tuple[int, list[str]]:
        if self.i >= len(self.lines):
            raise self.error(f"unexpected end of file, expected {what}", self.last)
        item = self.lines[self.i]
        self.i += 1
        return item

    def expect_open(self) -> None:
        n, toks = self.take("'{'")
        if toks != ["{"]:
            raise self.error(f"expected '{{', got {' '.join(toks)!r}", n)


def _floats(cur: _Lines, n: int, toks: list[str], count: int, what: str) -> list[float]:
    if len(toks) != count:
        raise cur.error(f"{what} needs {count} numbers, got {len(toks)}", n)
    try:
        values = [float(t) for t in toks]
    except ValueError:
        raise cur.error(f"{what}: not a number in {' '.join(toks)!r}", n) from None
    if not all(np.isfinite(values)):
        raise cur.error(f"{what}: non-finite value in {' '.join(toks)!r}", n)
    return values


def parse_bvh(
    text: str, *, source: str = "<text>", read_motion: bool = False
) -> BvhSkeleton:
    """Parse BVH text (see the module docstring).

    Args:
        text: the whole file.
        source: name used in error messages.
        read_motion: also read the MOTION lines into ``frames`` (the header is
            always checked when present).

    Returns:
        The skeleton (with its motion when asked).

    Raises:
        ValueError: ``"<source>:<line>: <problem>"``.
    """
    cur = _Lines(text, source)
    n, toks = cur.take("HIERARCHY")
    if toks != ["HIERARCHY"]:
        raise cur.error(f"expected HIERARCHY, got {' '.join(toks)!r}", n)
    names: list[str] = []
    parents: list[int] = []
    offsets: list[list[float]] = []
    channels: list[tuple[str, ...]] = []
    orders: list[str] = []
    ends: list[list[float]] = []

    def joint(parent: int, n_decl: int, decl: list[str]) -> None:
        # decl = ["ROOT" | "JOINT", name..., maybe "{"]
        words = decl[1:]
        brace = bool(words) and words[-1] == "{"
        if brace:
            words = words[:-1]
        if not words:
            raise cur.error(f"{decl[0]} without a name", n_decl)
        name = " ".join(words)
        if name in names:
            raise cur.error(f"duplicate joint name {name!r}", n_decl)
        if not brace:
            cur.expect_open()
        index = len(names)
        names.append(name)
        parents.append(parent)
        offsets.append([np.nan] * 3)
        channels.append(())
        orders.append("")
        ends.append([np.nan] * 3)
        seen_offset = False
        while True:
            n, toks = cur.take(f"'}}' closing joint {name!r}")
            key = toks[0]
            if key == "}":
                if len(toks) != 1:
                    raise cur.error(f"unexpected {' '.join(toks[1:])!r} after '}}'", n)
                break
            if key == "OFFSET":
                if seen_offset:
                    raise cur.error(f"joint {name!r}: second OFFSET", n)
                offsets[index] = _floats(cur, n, toks[1:], 3, "OFFSET")
                seen_offset = True
            elif key == "CHANNELS":
                if channels[index]:
                    raise cur.error(f"joint {name!r}: second CHANNELS", n)
                channels[index], orders[index] = _channels(cur, n, toks)
            elif key == "JOINT":
                joint(index, n, toks)
            elif key == "End" and len(toks) >= 2 and toks[1] == "Site":
                if toks[2:] not in ([], ["{"]):
                    raise cur.error(f"unexpected {' '.join(toks[2:])!r}", n)
                if toks[2:] == []:
                    cur.expect_open()
                n2, toks2 = cur.take("OFFSET of the End Site")
                if toks2[0] != "OFFSET":
                    raise cur.error(f"End Site needs an OFFSET, got {toks2[0]!r}", n2)
                ends[index] = _floats(cur, n2, toks2[1:], 3, "OFFSET")
                n3, toks3 = cur.take("'}' closing the End Site")
                if toks3 != ["}"]:
                    raise cur.error(f"expected '}}', got {' '.join(toks3)!r}", n3)
            else:
                raise cur.error(f"joint {name!r}: unexpected {key!r}", n)
        if not seen_offset:
            raise cur.error(f"joint {name!r} has no OFFSET", n)

    n, toks = cur.take("ROOT")
    if toks[0] != "ROOT":
        raise cur.error(f"expected ROOT, got {toks[0]!r}", n)
    joint(-1, n, toks)
    frame_time = float("nan")
    n_frames = 0
    frames: F64Array | None = None
    nxt = cur.peek()
    if nxt is not None and nxt[1][0] == "ROOT":
        raise cur.error("a second ROOT: only one skeleton per file is supported")
    if nxt is not None:
        n, toks = cur.take("MOTION")
        if toks != ["MOTION"]:
            raise cur.error(f"expected MOTION, got {' '.join(toks)!r}", n)
        n, toks = cur.take("Frames:")
        if len(toks) != 2 or toks[0] != "Frames:" or not toks[1].isdigit():
            raise cur.error(f"expected 'Frames: <count>', got {' '.join(toks)!r}", n)
        n_frames = int(toks[1])
        n, toks = cur.take("Frame Time:")
        if toks[:2] != ["Frame", "Time:"]:
            raise cur.error(f"expected 'Frame Time: <s>', got {' '.join(toks)!r}", n)
        (frame_time,) = _floats(cur, n, toks[2:], 1, "Frame Time")
        if frame_time <= 0.0:
            raise cur.error(f"Frame Time must be > 0, got {frame_time}", n)
        if read_motion:
            n_ch = sum(len(c) for c in channels)
            rows = []
            for k in range(n_frames):
                n, toks = cur.take(f"motion line {k + 1} of {n_frames}")
                rows.append(_floats(cur, n, toks, n_ch, f"motion line {k + 1}"))
            frames = np.asarray(rows, dtype=np.float64).reshape(n_frames, n_ch)
            rest = cur.peek()
            if rest is not None:
                raise cur.error(f"more motion lines than 'Frames: {n_frames}'")
    arr_off = np.asarray(offsets, dtype=np.float64)
    arr_end = np.asarray(ends, dtype=np.float64)
    for a in (arr_off, arr_end) + (() if frames is None else (frames,)):
        a.flags.writeable = False
    return BvhSkeleton(
        source=source,
        joint_names=tuple(names),
        parents=tuple(parents),
        offsets=arr_off,
        channels=tuple(channels),
        rotation_orders=tuple(orders),
        end_sites=arr_end,
        frame_time_s=frame_time,
        n_frames=n_frames,
        frames=frames,
    )


def _channels(cur: _Lines, n: int, toks: list[str]) -> tuple[tuple[str, ...], str]:
    if len(toks) < 2 or not toks[1].isdigit():
        raise cur.error("CHANNELS needs a count", n)
    count = int(toks[1])
    given = toks[2:]
    if len(given) != count:
        raise cur.error(f"CHANNELS {count} lists {len(given)} channels", n)
    out = []
    for c in given:
        canon = _CHANNEL_BY_LOWER.get(c.lower())
        if canon is None:
            raise cur.error(
                f"unknown channel {c!r} (expected one of {', '.join(CHANNEL_NAMES)})", n
            )
        if canon in out:
            raise cur.error(f"channel {canon} listed twice", n)
        out.append(canon)
    order = "".join(c[0] for c in out if c.endswith("rotation"))
    if len(order) not in (0, 3):
        raise cur.error(f"a joint needs 0 or 3 rotation channels, got {len(order)}", n)
    return tuple(out), order


def read_bvh_hierarchy(path: str | Path, *, read_motion: bool = False) -> BvhSkeleton:
    """Read a BVH file's hierarchy (and its motion, when asked).

    Args:
        path: the ``.bvh`` file.
        read_motion: also read the MOTION lines (default: header only).

    Returns:
        The skeleton: offsets in the file's own unit and axes.

    Raises:
        ValueError: an unreadable file, or ``"<path>:<line>: <problem>"``.
    """
    try:
        text = Path(path).read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: cannot read BVH: {exc}") from None
    return parse_bvh(text, source=str(path), read_motion=read_motion)


#: The six rotation orders a joint's three rotation channels can take (Tait-Bryan:
#: each axis once), spelt as the channels are listed: ``"ZXY"`` is ``Zrotation
#: Xrotation Yrotation``, ``R = R_Z R_X R_Y``.
ROTATION_ORDERS = ("XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX")
_POSITION_CHANNELS = ("Xposition", "Yposition", "Zposition")


def normalize_rotation_order(order: str) -> str:
    """Canonical spelling (``"ZXY"``) of a rotation order (``"zxy"``, ``"Z X Y"`` ...).

    Raises:
        ValueError: naming the value unless it is one of :data:`ROTATION_ORDERS`.
    """
    text = "".join(str(order).split()).upper()
    if text not in ROTATION_ORDERS:
        raise ValueError(
            f"rotation order must be one of {', '.join(ROTATION_ORDERS)}; got {order!r}"
        )
    return text


def _check_name(name: str) -> None:
    if (
        not isinstance(name, str)
        or not name.strip()
        or name != name.strip()
        or any(c in name for c in "{}\r\n\t")
    ):
        raise ValueError(
            "joint names must be non-empty, without surrounding spaces, braces, tabs "
            f"or line breaks; got {name!r}"
        )


def bvh_skeleton(
    *,
    joint_names: Sequence[str],
    parents: Sequence[int],
    offsets: F64Array,
    rotation_orders: Sequence[str],
    end_sites: F64Array | None = None,
    root_position: bool = True,
) -> BvhSkeleton:
    """A skeleton to write: channels built from each joint's rotation order.

    Args:
        joint_names: (J,) unique names.
        parents: (J,) parent index, -1 for the one root; parents before children.
        offsets: (J, 3) float, the file's length unit and axes: each joint's origin in
            its parent's frame (the root's: from the file origin).
        rotation_orders: (J,) one of :data:`ROTATION_ORDERS` per joint.
        end_sites: optional (J, 3) float, the file's unit: End Site offsets of leaf
            joints, NaN rows where there is none.
        root_position: give the root ``Xposition Yposition Zposition`` channels
            before its rotation channels.

    Returns:
        The skeleton (``source="<built>"``, no motion).

    Raises:
        ValueError: naming the argument and what was received.
    """
    names = tuple(joint_names)
    n = len(names)
    par = tuple(int(p) for p in parents)
    if n == 0 or len(par) != n:
        raise ValueError(
            f"joint_names and parents must be non-empty and match: {n} names, "
            f"{len(par)} parents"
        )
    for name in names:
        _check_name(name)
    if len(set(names)) != n:
        raise ValueError(f"joint_names must be unique; got {names!r}")
    if par[0] != -1 or any(not 0 <= p < j for j, p in enumerate(par) if j > 0):
        raise ValueError(
            f"parents must be -1 for joint 0 (the one root) and name an earlier joint "
            f"for every other; got {par!r}"
        )
    off = np.array(offsets, dtype=np.float64)
    if off.shape != (n, 3) or not np.isfinite(off).all():
        raise ValueError(f"offsets must be finite ({n}, 3); got shape {off.shape}")
    ends = (
        np.full((n, 3), np.nan)
        if end_sites is None
        else np.array(end_sites, dtype=np.float64)
    )
    has_end = np.isfinite(ends).all(axis=-1)
    if ends.shape != (n, 3) or not (has_end | np.isnan(ends).all(axis=-1)).all():
        raise ValueError(
            f"end_sites must be ({n}, 3), rows finite or all NaN; got {ends.shape}"
        )
    parent_set = set(par)
    with_children = [names[j] for j in range(n) if has_end[j] and j in parent_set]
    if with_children:
        raise ValueError(f"End Sites only go on leaf joints; not on {with_children}")
    if len(rotation_orders) != n:
        raise ValueError(f"rotation_orders must have {n} entries")
    orders = tuple(normalize_rotation_order(o) for o in rotation_orders)
    channels = tuple(
        (_POSITION_CHANNELS if j == 0 and root_position else ())
        + tuple(f"{axis}rotation" for axis in orders[j])
        for j in range(n)
    )
    for a in (off, ends):
        a.flags.writeable = False
    return BvhSkeleton(
        source="<built>",
        joint_names=names,
        parents=par,
        offsets=off,
        channels=channels,
        rotation_orders=orders,
        end_sites=ends,
    )


def bvh_motion(
    skeleton: BvhSkeleton, angles_deg: F64Array, positions: F64Array | None = None
) -> F64Array:
    """Channel values per frame from per-joint angles and positions.

    Args:
        skeleton: the hierarchy (its ``channels`` say what goes where).
        angles_deg: (T, J, 3) float, degrees: each joint's angles in the order of its
            ``rotation_orders`` entry (``"ZXY"``: Z, X, Y).
        positions: (T, J, 3) float, the file's unit and axes, x y z; read only for
            joints with position channels (other rows may be NaN). Required when any
            joint has position channels.

    Returns:
        (T, n_channels) float64, one motion line per frame, in the skeleton's joint
        order.

    Raises:
        ValueError: on a shape mismatch or missing positions.
    """
    ang = np.asarray(angles_deg, dtype=np.float64)
    n = len(skeleton.joint_names)
    if ang.ndim != 3 or ang.shape[1:] != (n, 3):
        raise ValueError(f"angles_deg must be (frames, {n}, 3); got {ang.shape}")
    out = np.zeros((ang.shape[0], skeleton.n_channels))
    at = skeleton.channel_offsets()
    for j, chans in enumerate(skeleton.channels):
        order = skeleton.rotation_orders[j]
        for k, chan in enumerate(chans):
            axis = "XYZ".index(chan[0])
            if chan.endswith("rotation"):
                out[:, at[j] + k] = ang[:, j, order.index(chan[0])]
                continue
            if positions is None:
                raise ValueError(
                    f"joint {skeleton.joint_names[j]!r} has position channels: "
                    "give positions"
                )
            pos = np.asarray(positions, dtype=np.float64)
            if pos.shape != ang.shape:
                raise ValueError(f"positions must be {ang.shape}; got {pos.shape}")
            out[:, at[j] + k] = pos[:, j, axis]
    return out


def split_bvh_motion(
    skeleton: BvhSkeleton, frames: F64Array
) -> tuple[F64Array, F64Array]:
    """The inverse of :func:`bvh_motion`.

    Args:
        skeleton: the hierarchy.
        frames: (T, n_channels) float, motion lines.

    Returns:
        ``(angles_deg, positions)``: (T, J, 3) float64 each; angles in each joint's
        rotation order (zeros for a joint without rotation channels), positions in
        the file's unit and axes (NaN for a joint without position channels; a
        missing axis reads 0).
    """
    fr = np.asarray(frames, dtype=np.float64)
    if fr.ndim != 2 or fr.shape[1] != skeleton.n_channels:
        raise ValueError(
            f"frames must be (frames, {skeleton.n_channels}); got {fr.shape}"
        )
    n = len(skeleton.joint_names)
    ang = np.zeros((fr.shape[0], n, 3))
    pos = np.full((fr.shape[0], n, 3), np.nan)
    at = skeleton.channel_offsets()
    for j, chans in enumerate(skeleton.channels):
        if any(c.endswith("position") for c in chans):
            pos[:, j] = 0.0
        for k, chan in enumerate(chans):
            if chan.endswith("rotation"):
                ang[:, j, skeleton.rotation_orders[j].index(chan[0])] = fr[:, at[j] + k]
            else:
                pos[:, j, "XYZ".index(chan[0])] = fr[:, at[j] + k]
    return ang, pos


def _preorder(parents: tuple[int, ...]) -> list[int]:
    children: list[list[int]] = [[] for _ in parents]
    for j, p in enumerate(parents):
        if p >= 0:
            children[p].append(j)
    order: list[int] = []
    stack = [0]
    while stack:
        j = stack.pop()
        order.append(j)
        stack.extend(reversed(children[j]))
    return order


def format_bvh(
    skeleton: BvhSkeleton,
    frames: F64Array,
    frame_time_s: float,
    *,
    decimals: int = 6,
) -> str:
    """BVH text for a skeleton and its motion (see :func:`write_bvh`)."""
    n = len(skeleton.joint_names)
    fr = np.asarray(frames, dtype=np.float64)
    if fr.ndim != 2 or fr.shape[1] != skeleton.n_channels:
        raise ValueError(
            f"frames must be (frames, {skeleton.n_channels}) channel values; got "
            f"{fr.shape}"
        )
    if not np.isfinite(fr).all():
        raise ValueError("frames must be finite (BVH has no missing values)")
    if not (math.isfinite(frame_time_s) and frame_time_s > 0.0):
        raise ValueError(f"frame_time_s must be > 0; got {frame_time_s}")
    if not 0 <= decimals <= 17:
        raise ValueError(f"decimals must be in 0..17; got {decimals}")
    order = _preorder(skeleton.parents)
    if sorted(order) != list(range(n)):
        raise ValueError("parents do not form one tree rooted at joint 0")
    num = f"{{:.{decimals}f}}".format
    depth = [0] * n
    lines = ["HIERARCHY"]
    open_stack: list[int] = []
    for j in order:
        p = skeleton.parents[j]
        while open_stack and open_stack[-1] != p:
            closed = open_stack.pop()
            lines.append("  " * depth[closed] + "}")
        depth[j] = 0 if p < 0 else depth[p] + 1
        pad = "  " * depth[j]
        lines.append(f"{pad}{'ROOT' if p < 0 else 'JOINT'} {skeleton.joint_names[j]}")
        lines.append(pad + "{")
        lines.append(f"{pad}  OFFSET " + " ".join(num(v) for v in skeleton.offsets[j]))
        chans = skeleton.channels[j]
        lines.append(f"{pad}  CHANNELS {len(chans)}" + "".join(f" {c}" for c in chans))
        end = skeleton.end_sites[j]
        if np.isfinite(end).all():
            lines += [f"{pad}  End Site", f"{pad}  {{"]
            lines.append(f"{pad}    OFFSET " + " ".join(num(v) for v in end))
            lines.append(f"{pad}  }}")
        open_stack.append(j)
    while open_stack:
        lines.append("  " * depth[open_stack.pop()] + "}")
    at = skeleton.channel_offsets()
    cols = np.concatenate(
        [np.arange(at[j], at[j] + len(skeleton.channels[j])) for j in order]
    ).astype(np.int64)
    lines += ["MOTION", f"Frames: {fr.shape[0]}", f"Frame Time: {frame_time_s:.9g}"]
    lines.extend(" ".join(num(v) for v in row) for row in fr[:, cols].tolist())
    return "\n".join(lines) + "\n"


def write_bvh(
    path: str | Path,
    skeleton: BvhSkeleton,
    frames: F64Array,
    frame_time_s: float,
    *,
    decimals: int = 6,
) -> None:
    """Write a BVH file: the hierarchy, then the motion.

    Joints are written depth first (children in the order given), so a joint order
    that is not depth first comes back from :func:`read_bvh_hierarchy` in file order;
    each motion line is permuted to match.

    Args:
        path: the ``.bvh`` file to create (overwritten).
        skeleton: the hierarchy, e.g. from :func:`bvh_skeleton`.
        frames: (T, n_channels) float, channel values per frame in the skeleton's
            joint order (see :func:`bvh_motion`): degrees for rotations, the file's
            unit for positions.
        frame_time_s: seconds per frame (``1 / rate``).
        decimals: digits after the point for every number.

    Raises:
        ValueError: a bad shape, non-finite values, a bad frame time.
    """
    text = format_bvh(skeleton, frames, frame_time_s, decimals=decimals)
    target = Path(path)
    tmp = target.with_name(f".{target.name}.tmp")
    try:
        tmp.write_text(text, encoding="utf-8")
        tmp.replace(target)
    finally:
        tmp.unlink(missing_ok=True)
    logger.debug(
        "wrote %s: %d joints, %d frames",
        path,
        len(skeleton.joint_names),
        np.shape(frames)[0],
    )
