"""Face config: which markers stabilize, which are facial, what is solved, what is sent.

A face config is a TOML file (or a shipped preset by name: ``arkit52``, ``vrm0``,
``vrm1``, in ``daemon/face/faces/``)::

    name = "my-face"                       # optional, defaults to the file stem
    head_markers = ["LFHD", "RFHD", "LBHD", "RBHD"]   # >= 3, rigid on the head
    head_weights = [1.0, 1.0, 1.0, 1.0]    # optional: weight of each in the rigid fit
                                           # (equal is best for equal noise; else
                                           # 1 / variance of each marker)
    facial_markers = ["BRL1", "BRR1", ...]  # [] = chosen (``face.markers``): not a
                                           # head marker, not the body rig's, above
                                           # the neck in the neutral pose
    body_rig = "plug-in-gait"              # optional: its markers are never facial
    expressions = ["browDownLeft", ...]     # the solved shapes (training poses)

    [output]                               # optional; absent = identity map
    # name sent to the engine = an expression, or a linear mix of expressions
    Blink_L = "eyeBlinkLeft"
    Joy = { mouthSmileLeft = 0.5, mouthSmileRight = 0.5 }

Output values are ``clip(M w, 0, 1)`` with ``M`` (n_out x K) from :meth:`output_matrix`
(one small mat-vec per frame); an expression missing from the training set
contributes nothing. The presets solve ARKit 52 and send ARKit names (``arkit52``),
VRM 0.x preset blend shapes (``vrm0``: A I U E O, Blink, Blink_L/R, Joy, Angry,
Sorrow, Fun, LookUp/Down/Left/Right) or VRM 1.0 expressions (``vrm1``: aa ih ou ee
oh, blinkLeft/Right, happy, angry, sad, relaxed, surprised, lookUp/Down/Left/Right).
The VRM mixes are a starting point meant to be tuned per avatar: copy the preset.
Reference: ``daemon/face/faces/FACES.md``.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from retargetd.daemon.body.rig import shipped_rigs
from retargetd.daemon.files import FileFormatError, loads_toml, read_text

logger = logging.getLogger(__name__)

F64Array = npt.NDArray[np.float64]


#: Every key a face config may hold (``output`` is the table).
FACE_KEYS = (
    "name", "head_markers", "head_weights", "facial_markers", "body_rig",
    "expressions", "output",
)  # fmt: skip


class FaceConfigError(ValueError):
    """A bad face config: one line naming the file, the key and the value."""


@dataclass(frozen=True, slots=True, kw_only=True)
class FaceConfig:
    """A parsed face config (see the module docstring for the file format).

    Attributes:
        name: config name.
        head_markers: (H,) stabilization marker names, H >= 3.
        head_weights: (H,) rigid-fit weights, >= 0.
        facial_markers: facial marker names; empty = chosen (``face.markers``).
        body_rig: the body rig (shipped name or file) whose markers are never
            facial; "" = none named here (the daemon's rig still applies).
        expressions: (K,) solved expression names.
        outputs: output names, in send order.
        mix: per output, ((expression, gain), ...).
    """

    name: str
    head_markers: tuple[str, ...]
    head_weights: tuple[float, ...]
    facial_markers: tuple[str, ...]
    body_rig: str
    expressions: tuple[str, ...]
    outputs: tuple[str, ...]
    mix: tuple[tuple[tuple[str, float], ...], ...]

    def output_matrix(self, expression_names: Sequence[str]) -> F64Array:
        """M: (n_outputs, K) float64 mapping weights in ``expression_names`` order to
        the outputs (expressions absent from ``expression_names`` are dropped)."""
        col = {n: i for i, n in enumerate(expression_names)}
        m = np.zeros((len(self.outputs), len(expression_names)))
        for o, terms in enumerate(self.mix):
            for expr, gain in terms:
                if expr in col:
                    m[o, col[expr]] += gain
        return m


def shipped_faces() -> tuple[str, ...]:
    """Names of the face configs shipped as package data."""
    folder = resources.files("retargetd.daemon.face.faces")
    return tuple(
        sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml"))
    )


def _names(
    src: str, doc: dict[str, Any], key: str, *, required: bool
) -> tuple[str, ...]:
    if key not in doc:
        if required:
            raise FaceConfigError(f"{src}: missing key {key!r}")
        return ()
    val = doc[key]
    if not isinstance(val, list) or not all(isinstance(v, str) and v for v in val):
        raise FaceConfigError(f"{src}: {key}: expected a list of names, got {val!r}")
    dup = sorted({v for v in val if val.count(v) > 1})
    if dup:
        raise FaceConfigError(f"{src}: {key}: duplicate names {dup}")
    return tuple(val)


def parse_face_config(doc: dict[str, Any], src: str, default_name: str) -> FaceConfig:
    """Validate a parsed TOML document into a :class:`FaceConfig`.

    Raises:
        FaceConfigError: naming ``src``, the key and the bad value.
    """
    unknown = sorted(set(doc) - set(FACE_KEYS))
    if unknown:
        raise FaceConfigError(f"{src}: unknown keys {unknown}")
    head = _names(src, doc, "head_markers", required=True)
    if len(head) < 3:
        raise FaceConfigError(f"{src}: head_markers: need >= 3, got {list(head)}")
    weights = doc.get("head_weights", [1.0] * len(head))
    if (
        not isinstance(weights, list)
        or len(weights) != len(head)
        or not all(isinstance(w, int | float) and w >= 0 for w in weights)
    ):
        raise FaceConfigError(
            f"{src}: head_weights: expected {len(head)} numbers >= 0, got {weights!r}"
        )
    facial = _names(src, doc, "facial_markers", required=False)
    both = sorted(set(head) & set(facial))
    if both:
        raise FaceConfigError(
            f"{src}: facial_markers: markers also in head_markers: {both}"
        )
    body_rig = doc.get("body_rig", "")
    if not isinstance(body_rig, str):
        raise FaceConfigError(f"{src}: body_rig: expected a rig name, got {body_rig!r}")
    if body_rig and not _rig_named(body_rig):
        raise FaceConfigError(
            f"{src}: body_rig: no shipped rig named {body_rig!r} (shipped: "
            f"{', '.join(shipped_rigs())}; or a path to a rig .toml file)"
        )
    exprs = _names(src, doc, "expressions", required=True)
    if not exprs:
        raise FaceConfigError(f"{src}: expressions: empty")
    table = doc.get("output")
    outputs: list[str] = []
    mix: list[tuple[tuple[str, float], ...]] = []
    if table is None:
        outputs = list(exprs)
        mix = [((e, 1.0),) for e in exprs]
    elif not isinstance(table, dict):
        raise FaceConfigError(f"{src}: output: expected a table, got {table!r}")
    else:
        for out, spec in table.items():
            terms = {spec: 1.0} if isinstance(spec, str) else spec
            if not isinstance(terms, dict) or not all(
                isinstance(g, int | float) for g in terms.values()
            ):
                raise FaceConfigError(
                    f"{src}: output.{out}: expected an expression name or "
                    f"{{ expression = gain, ... }}, got {spec!r}"
                )
            bad = sorted(set(terms) - set(exprs))
            if bad:
                raise FaceConfigError(f"{src}: output.{out}: unknown expressions {bad}")
            outputs.append(out)
            mix.append(tuple((e, float(g)) for e, g in terms.items()))
    name = doc.get("name", default_name)
    if not isinstance(name, str) or not name:
        raise FaceConfigError(f"{src}: name: expected a string, got {name!r}")
    return FaceConfig(
        name=name,
        head_markers=head,
        head_weights=tuple(float(w) for w in weights),
        facial_markers=facial,
        body_rig=body_rig,
        expressions=exprs,
        outputs=tuple(outputs),
        mix=tuple(mix),
    )


def load_face_config(name_or_path: str | Path) -> FaceConfig:
    """Load a shipped face config by name (``"arkit52"``) or a TOML file by path.

    Raises:
        FaceConfigError: unknown preset, unreadable file or bad content (one line).
    """
    text_name = str(name_or_path)
    path = Path(text_name)
    if path.suffix == "" and text_name in shipped_faces():
        res = resources.files("retargetd.daemon.face.faces").joinpath(
            f"{text_name}.toml"
        )
        text, src, stem = (
            res.read_text(encoding="utf-8"),
            f"face preset {text_name}",
            text_name,
        )
    elif path.is_file():
        try:
            text = read_text(path, "face config")
        except FileFormatError as exc:
            raise FaceConfigError(f"{path}: {exc}") from None
        src, stem = str(path), path.stem
    else:
        raise FaceConfigError(
            f"face config {text_name!r}: no such file or preset "
            f"(presets: {', '.join(shipped_faces())})"
        )
    try:
        doc = loads_toml(text)
    except FileFormatError as exc:
        raise FaceConfigError(f"{src}: {exc}") from None
    return parse_face_config(doc, src, stem)


def _rig_named(name: str) -> bool:
    """Whether ``name`` can name a rig: a shipped one, or a path to a ``.toml`` (that
    one is read where the rig is used, which names a missing file in one line)."""
    return name in shipped_rigs() or name.lower().endswith(".toml") or "/" in name
