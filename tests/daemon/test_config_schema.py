"""Every key of the daemon config, generated from the schema (the dataclasses of
``daemon/live/config_schema.py`` and each field's rule), given a wrong type, an
out-of-range value and a misspelling: ``retargetd run --config`` exits 2 with one
line on stderr naming the key, before any socket opens. Undecodable bytes too, in
the daemon config, a rig file and a face config (issue 12: a non-UTF-8 byte gave a
traceback).
"""

from __future__ import annotations

import dataclasses
import json
import tomllib
from collections.abc import Iterator
from importlib import resources
from pathlib import Path
from typing import Any

import pytest

from retargetd.daemon.cli.main import main
from retargetd.daemon.live.config import (
    ConfigError,
    DaemonConfig,
    NamedPerformerConfig,
)
from retargetd.daemon.live.config_props import PropConfig


def _leaves(kind: Any, prefix: str = "") -> Iterator[tuple[str, dataclasses.Field]]:
    """(dotted key, field) of every leaf of the schema, walking nested sections."""
    instance = kind()
    for f in dataclasses.fields(kind):
        value = getattr(instance, f.name)
        if dataclasses.is_dataclass(value):
            yield from _leaves(type(value), f"{prefix}{f.name}.")
        else:
            yield f"{prefix}{f.name}", f


def _sections(kind: Any, prefix: str = "") -> Iterator[str]:
    instance = kind()
    for f in dataclasses.fields(kind):
        value = getattr(instance, f.name)
        if dataclasses.is_dataclass(value):
            yield f"{prefix}{f.name}"
            yield from _sections(type(value), f"{prefix}{f.name}.")


# ``performers`` is read from [[performer]] tables (PERFORMER_LEAVES below), ``props``
# from [[prop]] tables (PROP_LEAVES).
LEAVES = {k: f for k, f in _leaves(DaemonConfig) if k not in ("performers", "props")}
PERFORMER_LEAVES = {f.name: f for f in dataclasses.fields(NamedPerformerConfig)}
PROP_LEAVES = {f.name: f for f in dataclasses.fields(PropConfig)}
SECTIONS = list(_sections(DaemonConfig))


def _wrong_type(default: Any) -> Any:
    """A TOML value of another type than the key's."""
    if isinstance(default, bool):
        return "yes"
    if isinstance(default, int | float):
        return "1"
    if isinstance(default, str):
        return 5
    if isinstance(default, tuple):
        return "a"
    raise AssertionError(f"no wrong type for {default!r}")


def _out_of_range(f: dataclasses.Field, tmp: Path) -> Any:
    """A value of the right type that the key's rule refuses (None for a bool:
    true and false are its whole range)."""
    meta = f.metadata
    check = meta.get("check", "")
    missing = str(tmp / "missing" / "file")
    values: dict[str, Any] = {
        "port": meta.get("hi", 0) + 1,
        "host": "localhost",  # a name, not an address
        "hosts": ["127.0.0.1", "nope"],
        "endpoint": "tcp://127.0.0.1:99999",
        "units": "furlong",
        "up": "north",
        "names": ["A", "A"],
        "rig": missing,
        "file": missing,
        "out_path": missing,
        "folder": "/dev/null",
        "skeleton": missing,
        "face_config": missing,
        "training": str(tmp),  # exists, but is no training set
        "mass": 10.0,
        "capture_source": "vicon://10.0.0.1",
        "token": "short",
        "secret_key": missing,
        "public_keys": [missing],
        "public_key": missing,
        "hmac_key": missing,
        "pipeline": [{"kind": "nope"}],
        "performer_name": "a b",
        "prefix": "x" * 65,
        "host_port": "127.0.0.1:0",
        "performer_face": missing,
        "osc_address": "lens fov",
    }
    if check == "range":
        hi = meta["hi"]
        return type(f.default)(hi * 2 + 1)
    if check == "choices":
        return "zzz"
    if check in values:
        return values[check]
    assert check == "" and isinstance(f.default, bool), (
        f"{f.name}: every key but a bool needs a rule (config_schema.spec)"
    )
    return None


def _misspelled(key: str) -> str:
    """The last part of the key with two letters swapped (never another key)."""
    *head, last = key.split(".")
    i = 1 if len(last) > 2 else 0
    wrong = last[:i] + last[i + 1] + last[i] + last[i + 2 :]
    if wrong == last:
        wrong = last + "s"
    return ".".join([*head, wrong])


def _toml(key: str, value: Any) -> str:
    """A one-key TOML document (JSON scalars and arrays are TOML too; a list of
    tables is written as ``[[key]]`` tables)."""
    *section, name = key.split(".")
    if isinstance(value, list) and value and isinstance(value[0], dict):
        return "".join(
            f"[[{key}]]\n" + "".join(f"{k} = {json.dumps(v)}\n" for k, v in t.items())
            for t in value
        )
    head = f"[{'.'.join(section)}]\n" if section else ""
    return f"{head}{name} = {json.dumps(value)}\n"


CASES = [
    pytest.param(key, kind, id=f"{key}-{kind}")
    for key in LEAVES
    for kind in ("wrong_type", "out_of_range", "misspelled")
] + [pytest.param(s, "misspelled", id=f"[{s}]-misspelled") for s in SECTIONS]


def test_the_schema_is_walked() -> None:
    # Sanity: the walk reaches nested sections and every kind of key.
    assert "input.osc.port" in LEAVES and "output.pose.client_keys" in LEAVES
    assert "performer.calibrate_max_speed_m_s" in LEAVES
    assert {"input", "input.osc", "output.vmc", "record"} <= set(SECTIONS)
    assert len(LEAVES) >= 60


@pytest.mark.parametrize(("key", "kind"), CASES)
def test_every_key_bad_gives_exit_2_and_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], key: str, kind: str
) -> None:
    if kind == "misspelled":
        wrong = _misspelled(key)
        if key in SECTIONS:
            *parent, last = wrong.split(".")
            text = f"[{'.'.join([*parent, last])}]\nx = 1\n"
        else:
            text = _toml(wrong, 1)
        named = wrong
    else:
        f = LEAVES[key]
        value = _wrong_type(f.default) if kind == "wrong_type" else None
        if kind == "out_of_range":
            value = _out_of_range(f, tmp_path)
            if value is None:
                assert isinstance(f.default, bool)
                return  # a bool has no out-of-range value (its wrong type is tested)
        text = _toml(key, value)
        named = key
    path = tmp_path / "bad.toml"
    path.write_text(text)
    # In process first: a document that were accepted would start a daemon below.
    with pytest.raises(ConfigError) as info:
        DaemonConfig.from_toml(path)
    assert f": {named}" in str(info.value), (text, str(info.value))
    assert main(["run", "--config", str(path)]) == 2
    out, err = capsys.readouterr()
    assert err.count("\n") == 1 and err.endswith("\n"), err
    assert err.startswith("retargetd run: error: ") and named in err, err
    assert "listening on" not in out


#: The array-of-tables whose keys are checked one by one: table, its leaves, and the
#: value its `name` key gets when another key is the one under test.
TABLE_LEAVES = {"performer": (PERFORMER_LEAVES, "A"), "prop": (PROP_LEAVES, "cam")}


@pytest.mark.parametrize(
    ("table", "key", "kind"),
    [
        pytest.param(table, key, kind, id=f"{table}[0].{key}-{kind}")
        for table, (leaves, _) in TABLE_LEAVES.items()
        for key in leaves
        for kind in ("wrong_type", "out_of_range", "misspelled")
    ],
)
def test_every_table_array_key_bad_gives_exit_2_and_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], table: str, key: str,
    kind: str,
) -> None:  # fmt: skip
    # The keys of a [[performer]] or [[prop]] table, named TABLE[i].KEY in the error.
    leaves, name = TABLE_LEAVES[table]
    f = leaves[key]
    head = f"[[{table}]]\n" + ("" if key == "name" else f'name = "{name}"\n')
    if kind == "misspelled":
        wrong = _misspelled(key)
        text = f"{head}{wrong} = 1\n"
        named = f"{table}[0].{wrong}"
    else:
        value = (
            _wrong_type(f.default)
            if kind == "wrong_type"
            else _out_of_range(f, tmp_path)
        )
        if value is None:
            return  # a bool has no out-of-range value (its wrong type is tested)
        text = f"{head}{key} = {json.dumps(value)}\n"
        named = f"{table}[0].{key}"
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        DaemonConfig.from_toml(path)
    assert f": {named}" in str(info.value), (text, str(info.value))
    assert main(["run", "--config", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and named in err, err


def test_props_across_tables(tmp_path: Path) -> None:
    path = tmp_path / "p.toml"
    path.write_text('[[prop]]\nname = "cam"\nkind = "camera"\n')
    (cam,) = DaemonConfig.from_toml(path).props
    assert cam.prefix == "cam:" and cam.kind == "camera" and cam.fov_deg == 60.0
    for text, said in (
        ('[[prop]]\nname = "a"\n[[prop]]\nname = "a"\n', "prop[1].name"),
        ('[[prop]]\nname = "a"\nmarkers = ["x", "y"]\n', "prop[0].markers"),
        (
            '[[prop]]\nname = "a"\nmarkers = ["x", "y", "z"]\n'
            '[[prop]]\nname = "b"\nmarkers = ["z", "u", "v"]\n',
            "prop[1].markers",
        ),
        ('[[performer]]\nname = "a"\n[[prop]]\nname = "a"\n', "prop[0].name"),
        ('[[prop]]\nkind = "rigid"\n', "prop[0].name"),
    ):
        path.write_text(text)
        with pytest.raises(ConfigError, match=said.replace("[", r"\[")):
            DaemonConfig.from_toml(path)


def test_non_utf8_config_rig_and_face_config_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = b'[performer]\nrig = "caf\xe9"\n'
    config = tmp_path / "bad.toml"
    config.write_bytes(bad)
    rig = tmp_path / "rig.toml"
    rig.write_bytes(b"[rig]\nname = '\xff\xfe'\n")
    face = tmp_path / "face.toml"
    face.write_bytes(b"name = '\xc3'\n")
    for text, where in (
        (None, config),
        (f"[performer]\nrig = {json.dumps(str(rig))}\n", rig),
        (f"[face]\nconfig = {json.dumps(str(face))}\n", face),
    ):
        path = config
        if text is not None:
            path = tmp_path / "ok.toml"
            path.write_text(text)
        assert main(["run", "--config", str(path)]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "Traceback" not in err, err
        assert f"{where}: not UTF-8 text" in err, err


def test_the_example_config_names_every_key() -> None:
    example = resources.files("retargetd.daemon.live") / "retargetd.example.toml"
    doc = tomllib.loads(example.read_text())

    def flat(d: dict[str, Any], prefix: str = "") -> Iterator[str]:
        for k, v in d.items():
            if isinstance(v, dict):
                yield from flat(v, f"{prefix}{k}.")
            else:
                yield f"{prefix}{k}"

    assert set(flat(doc)) == set(LEAVES)
