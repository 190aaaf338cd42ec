"""Rig files and face configs, every key of the shipped ones mutated (generated from
the documents, not listed by hand): a value of the wrong type, a misspelt key and an
out-of-range value (for a rig: every numeric leaf, each side of its range in
``RIG_RANGES``, NaN and infinity), each give ``retargetd run --config`` (the file
named in ``performer.rig`` / ``face.config``) exit 2 and one line naming the key.

The rig format's free names (a marker, measurement, segment, point, bone or joint
name: the key right under those tables) are the user's and cannot be misspelt;
every other key is the format's own.
"""

from __future__ import annotations

import copy
import json
import math
import tomllib
from collections.abc import Iterator
from importlib import resources
from pathlib import Path
from typing import Any

import pytest

from retargetd.daemon.body.rig import RigError, load_rig, shipped_rigs
from retargetd.daemon.body.rig_model import RIG_RANGES, NumberRange
from retargetd.daemon.cli import run as run_module
from retargetd.daemon.cli.main import main
from retargetd.daemon.face.config import (
    FACE_KEYS,
    FaceConfigError,
    load_face_config,
    shipped_faces,
)

#: Tables whose keys are names chosen by the rig's author (RIGS.md).
NAME_TABLES = ("markers", "measurements", "segments", "points", "bones", "joints")


def _leaves(doc: dict[str, Any], path: tuple[str, ...] = ()) -> Iterator[Any]:
    for key, value in doc.items():
        if isinstance(value, dict) and value:
            yield from _leaves(value, (*path, key))
        else:
            yield (*path, key), value


def _dump(doc: dict[str, Any]) -> str:
    """TOML text of a document as dotted keys (scalars and arrays of scalars)."""
    lines = []
    for path, value in _leaves(doc):
        key = ".".join(json.dumps(k) for k in path)
        if isinstance(value, dict):
            text = "{}"
        elif isinstance(value, float) and math.isnan(value):
            text = "nan"
        elif isinstance(value, float) and math.isinf(value):
            text = "inf" if value > 0 else "-inf"
        elif isinstance(value, list):
            text = "[" + ", ".join(_dump_scalar(v) for v in value) + "]"
        else:
            text = json.dumps(value)
        lines.append(f"{key} = {text}\n")
    return "".join(lines)


def _dump_scalar(value: Any) -> str:
    if isinstance(value, float) and math.isnan(value):
        return "nan"
    if isinstance(value, float) and math.isinf(value):
        return "inf" if value > 0 else "-inf"
    return json.dumps(value)


def _with(doc: dict[str, Any], path: tuple[str, ...], value: Any) -> dict[str, Any]:
    out = copy.deepcopy(doc)
    table = out
    for key in path[:-1]:
        table = table[key]
    table[path[-1]] = value
    return out


def _renamed(doc: dict[str, Any], path: tuple[str, ...], new: str) -> dict[str, Any]:
    out = copy.deepcopy(doc)
    table = out
    for key in path[:-1]:
        table = table[key]
    table[new] = table.pop(path[-1])
    return out


def _wrong_type(value: Any) -> Any:
    if isinstance(value, str | list | dict):
        return True
    return "x"  # a number or a bool


def _misspelt(name: str) -> str:
    if len(name) < 2:
        return name + "s"
    i = 1 if len(name) > 2 else 0
    wrong = name[:i] + name[i + 1] + name[i] + name[i + 2 :]
    return wrong if wrong != name else name + "s"


def _loads(section: str, path: Path) -> bool:
    """True when the file loads (then ``run`` would start a daemon: not run)."""
    try:
        if section == "performer":
            load_rig(path)
        else:
            load_face_config(path)
    except (RigError, FaceConfigError):
        return False
    return True


class _WouldStart(Exception):
    """``run`` accepted its config and was about to open a daemon."""


@pytest.fixture(autouse=True)
def _no_daemon(monkeypatch: pytest.MonkeyPatch) -> None:
    """``retargetd run`` stops where it would open the daemon: a file it accepts is
    told by :class:`_WouldStart`, not a daemon left running. (One load per mutated
    file, in ``run`` itself: a load beforehand, to keep a daemon from starting,
    parsed each file twice, the slowest part of these tests.)"""

    def would_start(*args: Any, **kwargs: Any) -> Any:
        raise _WouldStart

    monkeypatch.setattr(run_module, "make_daemon", would_start)


def _check(
    capsys: pytest.CaptureFixture[str],
    tmp_path: Path,
    section: str,
    key: str,
    text: str,
    named: str,
    also: str = "",
) -> str | None:
    """None when the run exits 2 with one line naming ``named`` (and holding
    ``also``), the error the file's own (``SECTION.KEY: FILE: ...``); else what is
    wrong."""
    target = tmp_path / "file.toml"
    target.write_text(text)
    config = tmp_path / "daemon.toml"
    config.write_text(f"[{section}]\n{key} = {json.dumps(str(target))}\n")
    try:
        rc = main(["run", "--config", str(config)])
    except _WouldStart:
        return f"{named}: accepted"
    err = capsys.readouterr().err
    if f"{section}.{key}: {target}: " not in err:
        return f"{named}: not the file's error: {err!r}"
    if rc != 2 or err.count("\n") != 1 or named not in err:
        return f"{named}: rc {rc}, stderr {err!r}"
    if also not in err:
        return f"{named}: no {also} in {err!r}"
    return None


def _shipped_rig(name: str) -> dict[str, Any]:
    folder = resources.files("retargetd.daemon.body.rigs")
    return tomllib.loads((folder / f"{name}.toml").read_text())


def _shipped_face(name: str) -> dict[str, Any]:
    folder = resources.files("retargetd.daemon.face.faces")
    return tomllib.loads((folder / f"{name}.toml").read_text())


@pytest.mark.parametrize("rig", shipped_rigs())
def test_rig_every_key_wrong_type_and_misspelt(
    rig: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    doc = _shipped_rig(rig)
    (tmp_path / "ok.toml").write_text(_dump(doc))
    assert _loads("performer", tmp_path / "ok.toml")  # the dump itself is valid
    # and run takes it as far as opening the daemon
    assert _check(capsys, tmp_path, "performer", "rig", _dump(doc), "ok") == (
        "ok: accepted"
    )
    problems = []
    n = 0
    renamed_keys: set[tuple[str, ...]] = set()
    for path, value in _leaves(doc):
        n += 1
        bad = _with(doc, path, _wrong_type(value))
        problems.append(
            _check(capsys, tmp_path, "performer", "rig", _dump(bad), ".".join(path))
        )
        for i, part in enumerate(path):
            if i == 1 and path[0] in NAME_TABLES:
                continue  # a name of the author's
            if path[: i + 1] in renamed_keys:
                continue  # the same file as a leaf before this one wrote
            renamed_keys.add(path[: i + 1])
            wrong = _misspelt(part)
            renamed = _renamed(doc, path[: i + 1], wrong)
            named = ".".join((*path[:i], wrong))
            problems.append(
                _check(capsys, tmp_path, "performer", "rig", _dump(renamed), named)
            )
    problems = [p for p in problems if p is not None]
    assert n > 100 and not problems, problems[:5]


def _face_out_of_range(key: str, value: Any) -> Any:
    """A value of the right type the face config refuses."""
    if key == "name":
        return ""
    if key == "head_weights":
        return [-1.0, 1.0, 1.0, 1.0]
    if key == "output":
        return {"x": "noSuchExpression"}
    if key == "expressions":
        return []
    if key == "head_markers":
        return ["A", "B"]  # fewer than 3
    if key == "facial_markers":
        return ["LFHD"]  # a head marker too
    if key == "body_rig":
        return "noSuchRig"  # neither a shipped rig nor a rig file
    raise AssertionError(f"no out-of-range value for face key {key!r}")


@pytest.mark.parametrize("face", shipped_faces())
def test_face_config_every_key_wrong_type_out_of_range_misspelt(
    face: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    doc = _shipped_face(face)
    doc.setdefault("head_weights", [1.0] * len(doc["head_markers"]))
    doc.setdefault("output", {e: e for e in doc["expressions"]})
    assert set(doc) == set(FACE_KEYS)  # every key of the schema is exercised
    section, key = "face", "config"
    (tmp_path / "ok.toml").write_text(_dump(doc))
    assert _loads(section, tmp_path / "ok.toml")  # the dump itself is valid
    # and run takes it as far as opening the daemon
    assert _check(capsys, tmp_path, section, key, _dump(doc), "ok") == "ok: accepted"
    problems = []
    for name in FACE_KEYS:
        value = doc[name]
        for bad in (
            _with(doc, (name,), _wrong_type(value)),
            _with(doc, (name,), _face_out_of_range(name, value)),
        ):
            text = _dump(bad)
            if name == "output" and not bad["output"]:
                text = text.replace('"output" = {}', "output = {}")
            problems.append(_check(capsys, tmp_path, section, key, text, name))
        wrong = _misspelt(name)
        problems.append(
            _check(
                capsys,
                tmp_path,
                section,
                key,
                _dump(_renamed(doc, (name,), wrong)),
                wrong,
            )
        )
    problems = [p for p in problems if p is not None]
    assert not problems, problems[:5]


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _numeric_leaves(
    doc: dict[str, Any],
) -> Iterator[tuple[tuple[str, ...], int | None, float]]:
    """(key path, index in a list or None, value) of every number in a rig."""
    for path, value in _leaves(doc):
        if _is_number(value):
            yield path, None, value
        elif isinstance(value, list):
            for i, item in enumerate(value):
                if _is_number(item):
                    yield path, i, item


def _schema_key(path: tuple[str, ...]) -> str:
    """``RIG_RANGES`` key of a leaf: the author's name replaced by ``*``."""
    parts = list(path)
    if parts[0] in NAME_TABLES and len(parts) > 1:
        parts[1] = "*"
    if parts[0] == "fit" and len(parts) > 2:  # [fit.bones.NAME], [fit.markers.NAME]
        parts[2] = "*"
    if parts == ["measurements", "*"]:  # the short form NAME = default
        parts.append("default")
    return ".".join(parts)


def _outside(rng: NumberRange) -> list[float]:
    """Values just outside each end of the range, farther out, and non-finite."""
    below = rng.low if rng.low_open else math.nextafter(rng.low, -math.inf)
    above = math.nextafter(rng.high, math.inf)
    span = rng.high - rng.low
    return [below, rng.low - span, above, rng.high + span, math.nan, math.inf]


def _inside(rng: NumberRange) -> list[float]:
    """The range's ends that belong to it."""
    low = math.nextafter(rng.low, math.inf) if rng.low_open else rng.low
    return [low, rng.high]


def _set_number(
    doc: dict[str, Any], path: tuple[str, ...], index: int | None, value: float
) -> dict[str, Any]:
    if index is None:
        return _with(doc, path, value)
    table: Any = doc
    for key in path:
        table = table[key]
    items = list(table)
    items[index] = value
    return _with(doc, path, items)


def test_rig_ranges_cover_the_shipped_rigs_numbers() -> None:
    """Every numeric key of the shipped rigs has a range, and every range is used."""
    keys = {
        _schema_key(path)
        for rig in shipped_rigs()
        for path, _, _ in _numeric_leaves(_shipped_rig(rig))
    }
    assert keys == set(RIG_RANGES)


@pytest.mark.parametrize("rig", shipped_rigs())
def test_rig_every_number_out_of_range(
    rig: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    doc = _shipped_rig(rig)
    problems: list[str | None] = []
    n = 0
    for path, index, _ in _numeric_leaves(doc):
        n += 1
        rng = RIG_RANGES[_schema_key(path)]
        named = ".".join(path) + ("" if index is None else f"[{index}]")
        for value in _inside(rng):  # the ends themselves pass this key's check
            (tmp_path / "in.toml").write_text(
                _dump(_set_number(doc, path, index, value))
            )
            try:  # (a measurement at its end may put an offset past its own)
                load_rig(tmp_path / "in.toml")
            except RigError as exc:
                if f": {named}:" in str(exc):
                    problems.append(f"{named} = {value!r}: refused: {exc}")
        for value in _outside(rng):
            text = _dump(_set_number(doc, path, index, value))
            # a finite value's error names the range
            also = str(rng) if math.isfinite(value) else ""
            problems.append(
                _check(capsys, tmp_path, "performer", "rig", text, named, also)
            )
    problems = [p for p in problems if p is not None]
    assert n > 0 and not problems, problems[:5]
