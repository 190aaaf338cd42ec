"""Rig files: how a marker set becomes the chapter's internal skeleton.

A rig is a TOML file (reference: ``daemon/body/rigs/RIGS.md``) declaring

- ``[rig]``: name, description, and ``lateral = [RIGHT, LEFT]``, the two points whose
  horizontal direction (right to left) gives the body's width axis in the base pose
  (height is world +Z, depth = width x height, i.e. forward); optional ``up_min_mm``
  (default :data:`UP_MIN_MM`): a bone whose up reference comes nearer its axis than
  this takes its roll from the previous frame;
- ``[measurements]``: named subject measurements in mm, each with a default;
- ``[markers]``: rig marker name -> take label, or a list of accepted labels;
- ``[segments.NAME]``: ``markers = [...]``, markers moving as one rigid body, used to
  rebuild an occluded marker from the others of its segment;
- ``[points.NAME]``: derived points built from the chapter's primitives:
  ``line = [A, B]`` with ``u`` (a point on the line A->B at parameter u, eq. 5.13-5.17),
  or ``rigid = [A, B, C]`` (a point held rigidly in the frame of three points,
  eq. 5.1-5.39) with either ``rule = {height = ..., width = ..., depth = ...}`` (the
  point's coordinates along the base-pose body axes, each an affine combination of
  points such as ``"SACRUM"`` or ``"0.5*L1 + 0.5*PELVIS"``) or ``offset_mm = [x, y, z]``
  (explicit offset in the three-point frame, each a number or a linear expression in
  measurements such as ``"LKneeWidth/2 + MarkerDiameter/2"``), and optional
  ``bend_min_deg`` (the frame's least bend in the base pose; calibrating under it
  warns: ``body.sanity.check_bends``);
- ``[bones.NAME]``: ``parent``, ``origin``, ``aim``, ``up`` (a point, or ``[A, B]`` for
  the direction A->B) and optional ``humanoid`` (standard humanoid bone name). Bone
  axes: +Y from origin to aim, +X towards the up reference (made orthogonal to Y),
  +Z = X x Y;
- ``[joints]``: named joint centres, name -> point;
- ``[fit]``: the rigid-skeleton fit's keys per marker and bone (``body.rig_fit``).

The three-point frame of ``rigid = [A, B, C]``: origin A, x = unit(B - A),
z = unit(x x (C - A)), y = z x x.

Parsing validates everything and raises :class:`RigError` with one line naming the
file, the key and the unknown or bad value (cycles included); every numeric key has a
range (:data:`RIG_RANGES`), and a value outside is named with the range allowed.
"""

from __future__ import annotations

import ast
import logging
import math
import re
from collections.abc import Mapping
from importlib import resources
from pathlib import Path
from typing import Any

from retargetd.daemon.body.rig_fit import parse_fit_table
from retargetd.daemon.body.rig_functional import parse_functional_table
from retargetd.daemon.body.rig_model import (
    HUMANOID_BONES,
    RIG_KEYS,
    RIG_RANGES,
    RULE_AXES,
    UP_MIN_MM,
    Bone,
    DerivedPoint,
    LinearExpr,
    LinePoint,
    Measurement,
    Rig,
    RigError,
    RigidPoint,
)
from retargetd.daemon.files import FileFormatError, loads_toml, read_text

logger = logging.getLogger(__name__)

_TOP_KEYS = (
    "rig", "measurements", "markers", "segments", "points", "bones", "joints", "fit",
    "functional",
)  # fmt: skip
#: Keys of a ``rigid`` point.
RIGID_KEYS = ("rigid", "rule", "offset_mm", "bend_min_deg", "description")


def shipped_rigs() -> tuple[str, ...]:
    """Names of the rigs shipped as package data."""
    folder = resources.files("retargetd.daemon.body.rigs")
    return tuple(
        sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml"))
    )


def load_rig(name_or_path: str | Path) -> Rig:
    """Load a shipped rig by name (``"menache"``) or a rig file by path.

    Raises:
        RigError: one line naming the file, the key and the bad value.
    """
    text_name = str(name_or_path)
    path = Path(text_name)
    if path.suffix.lower() != ".toml" and "/" not in text_name and not path.exists():
        resource = resources.files("retargetd.daemon.body.rigs") / f"{text_name}.toml"
        if not resource.is_file():
            raise RigError(
                f"no shipped rig named {text_name!r} (shipped: "
                f"{', '.join(shipped_rigs())}; or give a path to a .toml file)"
            )
        return parse_rig(resource.read_text(), source=f"{text_name} (shipped)")
    try:
        text = read_text(path, "rig file")
    except FileFormatError as exc:
        raise RigError(f"{path}: {exc}") from None
    return parse_rig(text, source=str(path))


def _did_you_mean(name: str, known: set[str]) -> str:
    """``" (did you mean 'X'?)"`` for the closest known name, else ``""``."""
    import difflib

    close = difflib.get_close_matches(name, sorted(known), n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""


def parse_linear(text: str | float | int, *, where: str) -> LinearExpr:
    """Parse a linear expression such as ``"LKneeWidth/2 + 7"`` or ``"0.5*A + 0.5*B"``.

    Raises:
        RigError: naming ``where`` when the text is not a linear expression.
    """
    if isinstance(text, bool):
        raise RigError(f"{where}: expected a number or an expression, got {text!r}")
    if isinstance(text, int | float):
        if not math.isfinite(text):
            raise RigError(f"{where}: {text!r} is not finite")
        return LinearExpr(float(text), (), str(text))
    if not isinstance(text, str):
        raise RigError(f"{where}: expected a number or an expression, got {text!r}")
    try:
        tree = ast.parse(text, mode="eval").body
    except SyntaxError:
        raise RigError(f"{where}: cannot parse expression {text!r}") from None
    constant, terms = _linear(tree, where=where, text=text)
    merged: dict[str, float] = {}
    for name, coef in terms:
        merged[name] = merged.get(name, 0.0) + coef
    return LinearExpr(constant, tuple(merged.items()), text)


def _linear(
    node: ast.expr, *, where: str, text: str
) -> tuple[float, list[tuple[str, float]]]:
    hint = ""
    if isinstance(node, ast.Attribute) or any(
        isinstance(n, ast.Attribute) for n in ast.walk(node)
    ):
        hint = (
            "; names in an expression are letters, digits and _ only: give a dotted "
            'label a plain rig name in [markers] (REIAS = "R.EIAS") and use that'
        )
    bad = RigError(
        f"{where}: {text!r} is not a linear expression of names and numbers{hint}"
    )
    if isinstance(node, ast.Constant) and isinstance(node.value, int | float):
        if isinstance(node.value, bool):
            raise bad
        return float(node.value), []
    if isinstance(node, ast.Name):
        return 0.0, [(node.id, 1.0)]
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub | ast.UAdd):
        c, t = _linear(node.operand, where=where, text=text)
        sign = -1.0 if isinstance(node.op, ast.USub) else 1.0
        return sign * c, [(n, sign * k) for n, k in t]
    if isinstance(node, ast.BinOp):
        lc, lt = _linear(node.left, where=where, text=text)
        rc, rt = _linear(node.right, where=where, text=text)
        if isinstance(node.op, ast.Add):
            return lc + rc, lt + rt
        if isinstance(node.op, ast.Sub):
            return lc - rc, lt + [(n, -k) for n, k in rt]
        if isinstance(node.op, ast.Mult):
            if lt and rt:
                raise bad
            if lt:
                return lc * rc, [(n, k * rc) for n, k in lt]
            return lc * rc, [(n, k * lc) for n, k in rt]
        if isinstance(node.op, ast.Div):
            if rt or rc == 0.0:
                raise bad
            return lc / rc, [(n, k / rc) for n, k in lt]
    raise bad


def parse_rig(text: str, *, source: str) -> Rig:
    """Parse and validate rig TOML text. ``source`` names the file in errors."""
    try:
        doc = loads_toml(text)
    except FileFormatError as exc:
        hint = ""
        dotted = re.search(r"^\s*([A-Za-z0-9_-]+)\.([A-Za-z0-9_.-]+)\s*=", text, re.M)
        if dotted:
            a, b = dotted.groups()
            hint = (
                f" (a bare key with a dot, {a}.{b}, is a TOML table: quote it, "
                f'"{a}.{b}" = ..., or name the rig marker without dots, '
                f'{a}{b.replace(".", "")} = "{a}.{b}")'
            )
        raise RigError(f"{source}: {exc}{hint}") from None
    return _Parser(doc, source).parse()


class _Parser:
    def __init__(self, doc: dict[str, Any], source: str) -> None:
        self.doc = doc
        self.src = source

    def fail(self, key: str, message: str) -> RigError:
        return RigError(f"{self.src}: {key}: {message}")

    def table(self, key: str, value: Any) -> dict[str, Any]:
        if not isinstance(value, dict):
            raise self.fail(key, f"expected a table, got {type(value).__name__}")
        return value

    def string(self, key: str, value: Any) -> str:
        if not isinstance(value, str) or not value:
            raise self.fail(key, f"expected a non-empty string, got {value!r}")
        return value

    def text(self, key: str, value: Any) -> str:
        """A free-text string (may be empty), e.g. a description."""
        if not isinstance(value, str):
            raise self.fail(key, f"expected a string, got {value!r}")
        return value

    def strings(self, key: str, value: Any, n: int | None = None) -> tuple[str, ...]:
        if isinstance(value, str):
            value = [value]
        if not isinstance(value, list) or not all(
            isinstance(v, str) and v for v in value
        ):
            raise self.fail(key, f"expected a list of names, got {value!r}")
        if n is not None and len(value) != n:
            raise self.fail(key, f"expected {n} names, got {len(value)}: {value!r}")
        return tuple(value)

    def in_range(self, key: str, schema: str, value: float, shown: str = "") -> None:
        """Raise naming ``key`` when ``value`` is outside ``RIG_RANGES[schema]``."""
        rng = RIG_RANGES[schema]
        if value not in rng:
            raise self.fail(
                key,
                f"{shown or repr(value)} is out of range: allowed {rng} ({rng.why})",
            )

    def number(self, key: str, value: Any, schema: str) -> float:
        """``value`` as a float, named at ``key`` unless a number in its range."""
        if not isinstance(value, int | float) or isinstance(value, bool):
            raise self.fail(key, f"expected a number, got {value!r}")
        self.in_range(key, schema, value)
        return float(value)

    def unknown_keys(
        self, key: str, table: dict[str, Any], allowed: tuple[str, ...]
    ) -> None:
        for k in table:
            if k not in allowed:
                raise self.fail(
                    f"{key}.{k}" if key else k,
                    f"unknown key (expected one of: {', '.join(allowed)})",
                )

    def parse(self) -> Rig:
        doc = self.doc
        self.unknown_keys("", doc, _TOP_KEYS)
        head = self.table("rig", doc.get("rig", {}))
        self.unknown_keys("rig", head, RIG_KEYS)
        name = self.string("rig.name", head.get("name"))
        up_min = head.get("up_min_mm", UP_MIN_MM)
        if not isinstance(up_min, int | float) or isinstance(up_min, bool):
            raise self.fail("rig.up_min_mm", f"expected a number, got {up_min!r}")
        self.in_range("rig.up_min_mm", "rig.up_min_mm", up_min)
        description = self.text("rig.description", head.get("description", ""))
        measurements = self.parse_measurements()
        markers = self.parse_markers()
        points = self.parse_points(markers, measurements)
        known = set(markers) | {p.name for p in points}
        if "lateral" not in head:
            raise self.fail("rig.lateral", "missing: give [RIGHT, LEFT] point names")
        lateral = self.strings("rig.lateral", head["lateral"], n=2)
        for item in lateral:
            self.known_point("rig.lateral", item, known)
        segments = self.parse_segments(markers)
        bones = self.parse_bones(known)
        joints = self.parse_joints(known)
        humanoid: dict[str, str] = {}
        for bone in bones:
            if bone.humanoid is not None:
                if bone.humanoid in humanoid:
                    raise self.fail(
                        f"bones.{bone.name}.humanoid",
                        f"{bone.humanoid!r} is already mapped to bone "
                        f"{humanoid[bone.humanoid]!r}",
                    )
                humanoid[bone.humanoid] = bone.name
        fit = parse_fit_table(
            doc.get("fit", {}),
            markers=markers,
            points={p.name for p in points},
            bones={b.name for b in bones},
            roots={b.name for b in bones if b.parent is None},
            fail=self.fail,
        )
        functional = parse_functional_table(
            doc.get("functional", {}), markers, points, bones, self.fail
        )
        return Rig(
            name=name,
            source=self.src,
            description=description,
            lateral=(lateral[0], lateral[1]),
            measurements=measurements,
            markers=markers,
            segments=segments,
            points=points,
            bones=bones,
            joints=joints,
            humanoid=humanoid,
            up_min_mm=float(up_min),
            fit=fit,
            functional=functional,
        )

    def known_point(self, key: str, name: str, known: set[str]) -> None:
        if name not in known:
            raise self.fail(
                key, f"unknown point or marker {name!r}{_did_you_mean(name, known)}"
            )

    def parse_measurements(self) -> dict[str, Measurement]:
        out: dict[str, Measurement] = {}
        table = self.table("measurements", self.doc.get("measurements", {}))
        for mname, spec in table.items():
            key = f"measurements.{mname}"
            if isinstance(spec, int | float) and not isinstance(spec, bool):
                spec = {"default": spec}
            spec = self.table(key, spec)
            self.unknown_keys(key, spec, ("default", "description"))
            default = spec.get("default")
            if (
                not isinstance(default, int | float)
                or isinstance(default, bool)
                or not math.isfinite(default)
            ):
                raise self.fail(f"{key}.default", f"expected a number, got {default!r}")
            self.in_range(f"{key}.default", "measurements.*.default", default)
            out[mname] = Measurement(
                name=mname,
                default_mm=float(default),
                description=self.text(
                    f"{key}.description", spec.get("description", "")
                ),
            )
        return out

    def parse_markers(self) -> dict[str, tuple[str, ...]]:
        table = self.table("markers", self.doc.get("markers", {}))
        if not table:
            raise self.fail("markers", "a rig needs at least one marker")
        for m, v in table.items():
            if isinstance(v, dict):
                first = next(iter(v), "X")
                raise self.fail(
                    f"markers.{m}",
                    f"TOML read the dotted key {m}.{first} as a table: name the rig "
                    f"marker without dots and give the label as the value ({m}{first} "
                    f'= "{m}.{first}"), or quote the key ("{m}.{first}" = ...)',
                )
        return {m: self.strings(f"markers.{m}", v) for m, v in table.items()}

    def parse_segments(
        self, markers: dict[str, tuple[str, ...]]
    ) -> dict[str, tuple[str, ...]]:
        out: dict[str, tuple[str, ...]] = {}
        table = self.table("segments", self.doc.get("segments", {}))
        owner: dict[str, str] = {}
        for sname, spec in table.items():
            key = f"segments.{sname}"
            spec = self.table(key, spec)
            self.unknown_keys(key, spec, ("markers",))
            names = self.strings(f"{key}.markers", spec.get("markers"))
            for m in names:
                if m not in markers:
                    raise self.fail(
                        f"{key}.markers",
                        f"unknown marker {m!r}{_did_you_mean(m, set(markers))}",
                    )
                if m in owner:
                    raise self.fail(
                        f"{key}.markers", f"marker {m!r} is already in {owner[m]!r}"
                    )
                owner[m] = sname
            if len(names) < 3:
                raise self.fail(
                    f"{key}.markers", "a rigid segment needs at least 3 markers"
                )
            out[sname] = names
        return out

    def parse_points(
        self, markers: dict[str, tuple[str, ...]], measurements: dict[str, Measurement]
    ) -> tuple[DerivedPoint, ...]:
        table = self.table("points", self.doc.get("points", {}))
        parsed: dict[str, DerivedPoint] = {}
        for pname, spec in table.items():
            key = f"points.{pname}"
            if pname in markers:
                raise self.fail(key, "a derived point cannot reuse a marker's name")
            spec = self.table(key, spec)
            if "line" in spec:
                self.unknown_keys(key, spec, ("line", "u", "description"))
                a, b = self.strings(f"{key}.line", spec["line"], n=2)
                u = self.number(f"{key}.u", spec.get("u", 0.5), "points.*.u")
                parsed[pname] = LinePoint(name=pname, a=a, b=b, u=u)
            elif "rigid" in spec:
                self.unknown_keys(key, spec, RIGID_KEYS)
                a, b, c = self.strings(f"{key}.rigid", spec["rigid"], n=3)
                bend = self.number(
                    f"{key}.bend_min_deg",
                    spec.get("bend_min_deg", 0.0),
                    "points.*.bend_min_deg",
                )
                if len({a, b, c}) != 3:
                    raise self.fail(f"{key}.rigid", "needs three different points")
                has_rule, has_off = "rule" in spec, "offset_mm" in spec
                if has_rule == has_off:
                    raise self.fail(key, "give exactly one of 'rule' and 'offset_mm'")
                if has_rule:
                    rule_t = self.table(f"{key}.rule", spec["rule"])
                    self.unknown_keys(f"{key}.rule", rule_t, RULE_AXES)
                    rule = {}
                    for axis in RULE_AXES:
                        if axis not in rule_t:
                            raise self.fail(f"{key}.rule", f"missing axis {axis!r}")
                        expr = parse_linear(
                            rule_t[axis], where=f"{self.src}: {key}.rule.{axis}"
                        )
                        if abs(sum(k for _, k in expr.terms) - 1.0) > 1e-9 or (
                            expr.constant != 0.0
                        ):
                            raise self.fail(
                                f"{key}.rule.{axis}",
                                f"{expr.text!r} must be an affine combination of "
                                "points (coefficients summing to 1, no constant)",
                            )
                        rule[axis] = expr
                    parsed[pname] = RigidPoint(
                        name=pname, frame=(a, b, c), rule=rule, bend_min_deg=bend
                    )
                else:
                    off = spec["offset_mm"]
                    if not isinstance(off, list) or len(off) != 3:
                        raise self.fail(
                            f"{key}.offset_mm", f"expected [x, y, z], got {off!r}"
                        )
                    exprs = tuple(
                        parse_linear(v, where=f"{self.src}: {key}.offset_mm[{i}]")
                        for i, v in enumerate(off)
                    )
                    for i, expr in enumerate(exprs):
                        for n in expr.names:
                            if n not in measurements:
                                raise self.fail(
                                    f"{key}.offset_mm[{i}]",
                                    f"unknown measurement {n!r}",
                                )
                        defaults = {n: measurements[n].default_mm for n in expr.names}
                        value = expr.evaluate(defaults)
                        shown = (
                            f"{expr.text!r} = {value:g} at the measurements' defaults"
                            if expr.names
                            else ""
                        )
                        self.in_range(
                            f"{key}.offset_mm[{i}]",
                            "points.*.offset_mm",
                            value,
                            shown or repr(value),
                        )
                    parsed[pname] = RigidPoint(
                        name=pname,
                        frame=(a, b, c),
                        offset_mm=(exprs[0], exprs[1], exprs[2]),
                        bend_min_deg=bend,
                    )
            else:
                # A misspelt 'line' or 'rigid' is named as the unknown key it is.
                self.unknown_keys(key, spec, ("line", "u", *RIGID_KEYS))
                raise self.fail(key, "a point needs 'line' or 'rigid'")
        known = set(markers) | set(parsed)
        for p in parsed.values():
            for item in p.inputs:
                self.known_point(f"points.{p.name}", item, known)
        deps = {n: p.inputs for n, p in parsed.items()}
        return tuple(parsed[n] for n in self.order(deps, "points.%s"))

    def order(self, deps: Mapping[str, tuple[str, ...]], key: str) -> list[str]:
        """Topological order of ``deps`` (name -> the names it needs; a name not in
        ``deps`` is a leaf); a cycle is reported by its path at ``key % name``."""
        done: list[str] = []
        state: dict[str, int] = {}

        def visit(name: str, path: list[str]) -> None:
            if name not in deps or state.get(name) == 2:
                return
            if state.get(name) == 1:
                cycle = [*path[path.index(name) :], name]
                raise self.fail(key % name, "cycle " + " -> ".join(cycle))
            state[name] = 1
            for item in deps[name]:
                visit(item, [*path, name])
            state[name] = 2
            done.append(name)

        for name in deps:
            visit(name, [])
        return done

    def parse_bones(self, known: set[str]) -> tuple[Bone, ...]:
        table = self.table("bones", self.doc.get("bones", {}))
        if not table:
            raise self.fail("bones", "a rig needs at least one bone")
        bones: dict[str, Bone] = {}
        for bname, spec in table.items():
            key = f"bones.{bname}"
            spec = self.table(key, spec)
            self.unknown_keys(
                key, spec, ("parent", "origin", "aim", "up", "humanoid", "description")
            )
            for req in ("origin", "aim", "up"):
                if req not in spec:
                    raise self.fail(f"{key}.{req}", "missing")
            parent = spec.get("parent", "")
            if not isinstance(parent, str):
                raise self.fail(
                    f"{key}.parent", f"expected a bone name, got {parent!r}"
                )
            origin = self.string(f"{key}.origin", spec["origin"])
            aim = self.string(f"{key}.aim", spec["aim"])
            up = self.strings(f"{key}.up", spec["up"])
            if len(up) not in (1, 2):
                raise self.fail(f"{key}.up", "give a point or [FROM, TO]")
            for sub, item in (("origin", origin), ("aim", aim)):
                self.known_point(f"{key}.{sub}", item, known)
            for item in up:
                self.known_point(f"{key}.up", item, known)
            if origin == aim:
                raise self.fail(f"{key}.aim", "aim must differ from origin")
            humanoid = spec.get("humanoid")
            if humanoid is not None and humanoid not in HUMANOID_BONES:
                raise self.fail(
                    f"{key}.humanoid",
                    f"unknown humanoid bone {humanoid!r} "
                    f"(one of {', '.join(HUMANOID_BONES)})",
                )
            bones[bname] = Bone(
                name=bname,
                parent=parent or None,
                origin=origin,
                aim=aim,
                up=up,
                humanoid=humanoid,
            )
        for b in bones.values():
            if b.parent is not None and b.parent not in bones:
                raise self.fail(f"bones.{b.name}.parent", f"unknown bone {b.parent!r}")
        deps = {n: (b.parent,) if b.parent else () for n, b in bones.items()}
        ordered = self.order(deps, "bones.%s.parent")
        return tuple(bones[n] for n in ordered)

    def parse_joints(self, known: set[str]) -> dict[str, str]:
        table = self.table("joints", self.doc.get("joints", {}))
        out = {}
        for jname, point in table.items():
            key = f"joints.{jname}"
            point = self.string(key, point)
            self.known_point(key, point, known)
            out[jname] = point
        return out
