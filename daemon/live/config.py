"""The daemon's configuration: a TOML file parsed into frozen dataclasses.

``DaemonConfig.from_toml(path)`` validates everything before any socket opens; a wrong
key, type or value raises :class:`ConfigError` naming the key in one line (the CLI
exits 2). Without a file every value takes the default below. The commented example
is ``daemon/live/retargetd.example.toml`` (loaded by a test, so it cannot rot).

Endpoints (all on 127.0.0.1 by default; each configurable so several daemons, one per
performer, run side by side):

| endpoint | key | default |
|---|---|---|
| OSC marker input (UDP) | ``input.osc.port`` | 127.0.0.1:39570 |
| ZeroMQ marker input | ``input.zmq.endpoint`` | PULL bound at tcp://127.0.0.1:39571 |
| ZeroMQ pose output (PUB) | ``output.pose.endpoint`` | tcp://127.0.0.1:39572 |
| control socket (ZeroMQ REP) | ``control.endpoint`` | tcp://127.0.0.1:39573 |
| OSC show-control (UDP, VMC performer port) | ``show_control.port`` | 127.0.0.1:39540 |
| VMC output (UDP) | ``output.vmc.port`` | 127.0.0.1:39539 |

Each field carries its rule (``config_schema.spec``: a range, choices, an address,
an endpoint, a file...), applied as the key is read; ``_check`` adds the rules across
keys: off loopback needs ``allow_remote`` (and CURVE for control, a token for show
control), a broadcast VMC target needs ``allow_broadcast``. A test walks these
dataclasses and gives every key a wrong type, an out-of-range value and a misspelling.

``[[pipeline]]`` (``DaemonConfig.pipeline``) is the one array of tables: each entry's
kind and keys are checked as it is read (a misspelt key is named with the kind's
keys), and the stages are built once for the rig in ``_check`` (values, arm chains).
"""

from __future__ import annotations

import difflib
import ipaddress
import math
import re
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from retargetd.daemon.body.rig import RigError, load_rig
from retargetd.daemon.face.config import FaceConfigError, load_face_config
from retargetd.daemon.face.training import TrainingSet
from retargetd.daemon.files import FileFormatError, loads_toml, read_text
from retargetd.daemon.live.config_props import PropConfig, build_props, check_props
from retargetd.daemon.live.config_schema import (
    PERFORMER_INPUTS,
    ConfigError,
    ConsoleConfig,
    ControlConfig,
    FaceSectionConfig,
    InputConfig,
    LoopConfig,
    NamedPerformerConfig,
    OutputConfig,
    PerformerConfig,
    RecordConfig,
    ShowControlConfig,
    SolveConfig,
    TargetConfig,
    ValidateSectionConfig,
    spec,
)
from retargetd.daemon.live.surface import (
    check_token,
    endpoint_is_local,
    is_loopback_host,
    load_hmac_key,
    load_public_key,
    load_secret_key,
    parse_endpoint,
)
from retargetd.daemon.post.pipeline import KINDS, build_pipeline
from retargetd.protocols.conventions import normalize_units, normalize_up_axis
from retargetd.protocols.marker_input import MAX_MESSAGE_BYTES
from retargetd.protocols.natnet_client import parse_natnet_url
from retargetd.protocols.pose_stream import MAX_PERFORMERS
from retargetd.protocols.qtm import parse_qtm_url
from retargetd.protocols.vmc_out import MIN_DATAGRAM


@dataclass(frozen=True, slots=True, kw_only=True)
class DaemonConfig:
    """The whole configuration (see the module docstring for the endpoint table)."""

    performer: PerformerConfig = field(default_factory=PerformerConfig)
    input: InputConfig = field(default_factory=InputConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    control: ControlConfig = field(default_factory=ControlConfig)
    show_control: ShowControlConfig = field(default_factory=ShowControlConfig)
    target: TargetConfig = field(default_factory=TargetConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)
    face: FaceSectionConfig = field(default_factory=FaceSectionConfig)
    validate: ValidateSectionConfig = field(default_factory=ValidateSectionConfig)
    record: RecordConfig = field(default_factory=RecordConfig)
    console: ConsoleConfig = field(default_factory=ConsoleConfig)
    solve: SolveConfig = field(default_factory=SolveConfig)
    # [[pipeline]] post stages between the body solve and the target mapping, in the
    # order listed (README "Post stages"): tables with ``kind`` and its keys.
    pipeline: tuple[dict[str, Any], ...] = spec((), "pipeline")
    # The [[performer]] tables (empty: one performer, [performer]). Read from the
    # TOML key ``performer`` when it is an array of tables; ``performer`` is then
    # the first of them.
    performers: tuple[NamedPerformerConfig, ...] = spec((), "performer_list")
    # The [[prop]] tables (config_props.py): rigid props and virtual cameras.
    props: tuple[PropConfig, ...] = spec((), "prop_list")

    @classmethod
    def from_toml(cls, path: str | Path) -> DaemonConfig:
        """Read and validate a TOML config. Raises ConfigError naming the key."""
        try:
            doc = loads_toml(read_text(path, "config"))
        except FileFormatError as exc:
            raise ConfigError(f"{path}: {exc}") from None
        return cls.from_dict(doc, source=str(path))

    @classmethod
    def from_dict(cls, doc: dict[str, Any], *, source: str = "config") -> DaemonConfig:
        """Build from a parsed document. Raises ConfigError naming the key."""
        if "props" in doc:
            raise ConfigError(
                f"{source}: props: unknown key (props are [[prop]] tables)"
            )
        props = build_props(doc["prop"], _build, source) if "prop" in doc else ()
        doc = {k: v for k, v in doc.items() if k != "prop"}
        if "performers" in doc:
            raise ConfigError(
                f"{source}: performers: unknown key (several performers are "
                "[[performer]] tables)"
            )
        entries = doc.get("performer")
        performers: tuple[NamedPerformerConfig, ...] = ()
        if isinstance(entries, list):
            performers = _build_performers(entries, source)
            doc = {k: v for k, v in doc.items() if k != "performer"}
        config = _build(cls, doc, "", source)
        if performers:
            config = replace(config, performer=performers[0], performers=performers)
        _check(config, source)
        _check_performers(config, source)
        if props:
            names = tuple(p.name for p in config.performers)
            check_props(props, names, source)
            config = replace(config, props=props)
        return config


def _build(kind: Any, doc: Any, prefix: str, source: str) -> Any:
    if not isinstance(doc, dict):
        raise ConfigError(
            f"{source}: {prefix.rstrip('.') or '(top)'}: expected a table; got {doc!r}"
        )
    known = {f.name: f for f in fields(kind)}
    kwargs: dict[str, Any] = {}
    for key, value in doc.items():
        name = f"{prefix}{key}"
        if key not in known:
            near = difflib.get_close_matches(key, known, n=1)
            hint = f"did you mean {near[0]!r}? " if near else ""
            raise ConfigError(
                f"{source}: {name}: unknown key ({hint}expected one of: "
                f"{', '.join(known)})"
            )
        default = getattr(kind(), key)
        if known[key].metadata.get("check") == "pipeline":
            kwargs[key] = _pipeline_tables(value, name, source)
        elif hasattr(default, "__dataclass_fields__"):
            kwargs[key] = _build(type(default), value, f"{name}.", source)
        else:
            kwargs[key] = _coerce(value, default, name, source)
            _check_field(kwargs[key], known[key].metadata, name, source)
    return kind(**kwargs)


def parse_target(table: Any, source: str = "config") -> TargetConfig:
    """A ``[target]`` table alone (``solve --pipeline FILE.toml``), every key checked.

    Raises:
        ConfigError: naming the key.
    """
    config: TargetConfig = _build(TargetConfig, table, "target.", source)
    return config


def _coerce(value: Any, default: Any, name: str, source: str) -> Any:
    def bad(expected: str) -> ConfigError:
        return ConfigError(f"{source}: {name}: expected {expected}; got {value!r}")

    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise bad("true or false")
        return value
    if isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise bad("an integer")
        return value
    if isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise bad("a number")
        if not math.isfinite(value):
            raise bad("a finite number")
        return float(value)
    if isinstance(default, str):
        if not isinstance(value, str):
            raise bad("a string")
        return value
    if isinstance(default, tuple):
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise bad("a list of strings")
        return tuple(value)
    raise bad(type(default).__name__)  # pragma: no cover


def _pipeline_tables(value: Any, name: str, source: str) -> tuple[dict[str, Any], ...]:
    """``[[pipeline]]``: an array of tables, each with a known ``kind`` and only that
    kind's keys (values are checked when the stages are built for the rig)."""
    if not isinstance(value, list) or not all(isinstance(v, dict) for v in value):
        raise ConfigError(
            f"{source}: {name}: expected [[{name}]] tables (kind = "
            f"{' | '.join(repr(k) for k in sorted(KINDS))}, ...); got {value!r}"
        )
    for n, entry in enumerate(value):
        kind = entry.get("kind")
        if kind not in KINDS:
            raise ConfigError(
                f"{source}: {name}[{n}].kind: expected one of {sorted(KINDS)}; "
                f"got {kind!r}"
            )
        allowed = KINDS[kind][0]
        unknown = sorted(set(entry) - allowed - {"kind"})
        if unknown:
            near = difflib.get_close_matches(unknown[0], allowed, n=1)
            hint = f"did you mean {near[0]!r}? " if near else ""
            raise ConfigError(
                f"{source}: {name}[{n}].{unknown[0]}: unknown key for kind {kind!r} "
                f"({hint}expected one of: {', '.join(sorted(allowed))})"
            )
    return tuple(dict(v) for v in value)


def check_pipeline(
    entries: tuple[dict[str, Any], ...], rig: Any, source: str = "config"
) -> None:
    """Build the ``[[pipeline]]`` stages once for ``rig``'s bones: every value
    checked (a fraction, a cutoff) and the rig able to carry each stage (a twist
    needs arm chains). Raises ConfigError naming the entry."""
    if not entries:
        return
    try:
        build_pipeline(
            entries,
            bone_names=rig.bone_names,
            bone_parents=rig.bone_parent_indices(),
        )
    except ValueError as exc:
        raise ConfigError(f"{source}: {exc} (rig {rig.name})") from None


def _check_field(value: Any, meta: Any, name: str, source: str) -> None:
    """Apply a field's rule (its ``spec`` metadata) to a value given in the file."""
    check = meta.get("check", "")
    try:
        _apply_rule(check, meta, value)
    except _ItemError as exc:  # one item of a list: input.osc.allow[0]: ...
        raise ConfigError(f"{source}: {name}[{exc.index}]: {exc}") from None
    except ValueError as exc:
        raise ConfigError(f"{source}: {name}: {exc}") from None


class _ItemError(ValueError):
    """A rule failed on item ``index`` of a list value."""

    def __init__(self, index: int, message: str) -> None:
        super().__init__(message)
        self.index = index


def _apply_rule(check: str, meta: Any, value: Any) -> None:
    if check == "range":
        lo, hi = meta["lo"], meta["hi"]
        if not ((lo < value) if meta["open_lo"] else (lo <= value)) or value > hi:
            brackets = "(" if meta["open_lo"] else "["
            raise ValueError(
                f"expected {brackets}{_number(lo)}, {_number(hi)}]; got {value}"
            )
    elif check == "port":
        if not meta["lo"] <= value <= meta["hi"]:
            raise ValueError(f"expected a port {meta['lo']}-{meta['hi']}; got {value}")
    elif check == "choices":
        if value not in meta["choices"]:
            options = " or ".join(repr(c) for c in meta["choices"])
            raise ValueError(f"expected {options}; got {value!r}")
    elif check == "host":
        _check_host(value)
    elif check == "hosts":
        for i, host in enumerate(value):
            try:
                _check_host(host)
            except ValueError as exc:
                raise _ItemError(i, str(exc)) from None
    elif check == "endpoint":
        parse_endpoint(value)
    elif check == "units":
        normalize_units(value)
    elif check == "up":
        normalize_up_axis(value)
    elif check == "names":
        if any(not v for v in value) or len(set(value)) != len(value):
            raise ValueError(f"expected distinct non-empty names; got {list(value)}")
    elif check == "rig":
        try:
            load_rig(value)
        except RigError as exc:
            raise ValueError(str(exc)) from None
    elif check == "file":
        if value and not Path(value).is_file():
            raise ValueError(f"no such file: {value!r}")
    elif check == "out_path":
        if value and not Path(value).resolve().parent.is_dir():
            raise ValueError(f"the folder of {value!r} does not exist")
    elif check == "folder":
        if not value or (Path(value).exists() and not Path(value).is_dir()):
            raise ValueError(f"expected a folder; got {value!r}")
    elif check == "skeleton":
        if value != "humanoid" and not Path(value).is_file():
            raise ValueError(f"expected 'humanoid' or a BVH file; got {value!r}")
    elif check == "face_config":
        try:
            load_face_config(value)
        except FaceConfigError as exc:
            raise ValueError(str(exc)) from None
    elif check == "training":
        if value and Path(value).exists():
            try:
                TrainingSet.load(value)
            except (OSError, ValueError) as exc:
                raise ValueError(str(exc)) from None
    elif check == "capture_source":
        _check_capture_source(value)
    elif check == "mass":
        if not (value == 0.0 or 20.0 <= value <= 300.0):
            raise ValueError(f"expected 0 (70 kg) or [20, 300]; got {value}")
    elif check == "token":
        if value:
            check_token(value)
    elif check == "secret_key":
        if value:
            load_secret_key(value)
    elif check == "public_keys":
        for path in value:
            load_public_key(path)
    elif check == "public_key":
        if value:
            load_public_key(value)
    elif check == "hmac_key":
        if value:
            load_hmac_key(value)
    elif check == "performer_name":
        if not _NAME_RE.fullmatch(value):
            raise ValueError(
                "expected a name of letters, digits, '_', '-' or '.' (1-64); "
                f"got {value!r}"
            )
    elif check == "prefix":
        if any(c in value for c in "\0\n") or len(value) > 64:
            raise ValueError(
                f"expected a label prefix of <= 64 characters; got {value!r}"
            )
    elif check == "osc_address":
        if value and (
            not value.startswith("/") or any(c in value for c in " #*,?[]{}")
        ):
            raise ValueError(
                f"expected an OSC address such as /lens/fov; got {value!r}"
            )
    elif check == "host_port":
        if value:
            parse_host_port(value)
    elif check == "performer_face":
        if value:
            try:
                load_face_config(value)
            except FaceConfigError as exc:
                raise ValueError(str(exc)) from None
    elif check:  # pragma: no cover
        raise AssertionError(f"unknown config rule {check!r}")


_NAME_RE = re.compile(r"[A-Za-z0-9_.-]{1,64}")


def parse_host_port(value: str) -> tuple[str, int]:
    """``"HOST:PORT"`` (an IP address and a port 1-65535) as ``(host, port)``.

    Raises:
        ValueError: anything else (the message shows the value).
    """
    host, sep, port = value.rpartition(":")
    if not sep or not port.isdigit() or not 1 <= int(port) <= 65535:
        raise ValueError(f"expected HOST:PORT (port 1-65535); got {value!r}")
    _check_host(host)
    return host, int(port)


def _build_performers(
    entries: list[Any], source: str
) -> tuple[NamedPerformerConfig, ...]:
    """The ``[[performer]]`` tables, each checked like ``[performer]``; ``prefix``
    left out is NAME + ":"."""
    if not entries:
        raise ConfigError(f"{source}: performer: expected at least one [[performer]]")
    out = []
    for i, entry in enumerate(entries):
        key = f"performer[{i}]"
        if not isinstance(entry, dict):
            raise ConfigError(f"{source}: {key}: expected a table; got {entry!r}")
        perf = _build(NamedPerformerConfig, entry, f"{key}.", source)
        if "name" not in entry:
            raise ConfigError(f"{source}: {key}.name: every [[performer]] needs a name")
        if "prefix" not in entry:
            perf = replace(perf, prefix=f"{perf.name}:")
        out.append(perf)
    return tuple(out)


def _check_performers(c: DaemonConfig, source: str) -> None:
    """Across ``[[performer]]`` tables: distinct names, prefixes (per input) and VMC
    destinations."""
    if len(c.performers) > MAX_PERFORMERS:
        raise ConfigError(
            f"{source}: performer: at most {MAX_PERFORMERS} performers (the pose "
            f"stream's performer id is one byte); got {len(c.performers)}"
        )
    names: set[str] = set()
    claims: set[tuple[str, str]] = set()
    destinations: dict[tuple[str, int], str] = {}
    default_vmc = (c.output.vmc.host, c.output.vmc.port)
    for i, p in enumerate(c.performers):
        key = f"performer[{i}]"
        if p.name in names:
            raise ConfigError(f"{source}: {key}.name: {p.name!r} is taken")
        names.add(p.name)
        enabled = {
            "osc": c.input.osc.enabled,
            "zmq": c.input.zmq.enabled,
            "source": bool(c.input.source),
        }
        if p.input != "any" and not enabled[p.input]:
            where = "input.source" if p.input == "source" else f"input.{p.input}"
            raise ConfigError(
                f"{source}: {key}.input: {p.input!r} is off ({where}): this "
                "performer would never get a frame"
            )
        inputs = PERFORMER_INPUTS[1:] if p.input == "any" else (p.input,)
        for inp in inputs:
            if (inp, p.prefix) in claims:
                raise ConfigError(
                    f"{source}: {key}.prefix: {p.prefix!r} on input {inp} is "
                    "another performer's (each performer's markers are its own)"
                )
            claims.add((inp, p.prefix))
        if c.output.vmc.enabled:
            dest = parse_host_port(p.vmc) if p.vmc else default_vmc
            if dest in destinations:
                raise ConfigError(
                    f"{source}: {key}.vmc: {dest[0]}:{dest[1]} is performer "
                    f"{destinations[dest]!r}'s too: VMC is one avatar per port, give "
                    'each performer its own vmc = "HOST:PORT"'
                )
            destinations[dest] = p.name
            target = ipaddress.ip_address(dest[0])
            if p.vmc and target.is_unspecified:
                raise ConfigError(
                    f"{source}: {key}.vmc: expected a receiver's address; got {p.vmc}"
                )
            broadcast = target.is_multicast or dest[0] == "255.255.255.255"
            if broadcast and not c.output.vmc.allow_broadcast:
                raise ConfigError(
                    f"{source}: {key}.vmc: {dest[0]} is a broadcast/multicast "
                    "address: VMC goes to one receiver unless output.vmc."
                    "allow_broadcast = true"
                )


def _number(x: float) -> str:
    """A bound as written: 1000000, 0.05 (never 1e+06)."""
    return str(int(x)) if float(x).is_integer() else f"{x:g}"


def _check_capture_source(url: str) -> None:
    """``input.source``: empty, or a URL the capture inputs parse."""
    if url.startswith("natnet://"):
        parse_natnet_url(url)
    elif url.startswith("qtm://"):
        parse_qtm_url(url)
    elif url:
        raise ValueError(
            f"expected qtm://HOST[:PORT] or natnet://HOST[:PORT][?...]; got {url!r}"
        )


def _check_host(host: str) -> None:
    try:
        ipaddress.ip_address(host)
    except ValueError:
        raise ValueError(
            f"expected an IP address (e.g. 127.0.0.1); got {host!r}"
        ) from None


def _check(c: DaemonConfig, source: str) -> None:
    """Checks across keys (each key's own rule ran when it was read)."""

    def fail(key: str, message: str) -> ConfigError:
        return ConfigError(f"{source}: {key}: {message}")

    check_pipeline(c.pipeline, load_rig(c.performer.rig), source)
    osc = c.input.osc
    if osc.form == "simple" and osc.enabled and not osc.labels:
        raise fail("input.osc.labels", "the simple form needs the marker names")
    remote = "binding off loopback needs allow_remote = true on this endpoint"
    for key, host, allowed in (
        ("input.osc.host", osc.host, osc.allow_remote),
        ("show_control.host", c.show_control.host, c.show_control.allow_remote),
        ("console.host", c.console.host, c.console.allow_remote),
    ):
        if not is_loopback_host(host) and not allowed:
            raise fail(key, f"{remote}; got {host!r}")
    for key, ep, allowed in (
        ("input.zmq.endpoint", c.input.zmq.endpoint, c.input.zmq.allow_remote),
        ("output.pose.endpoint", c.output.pose.endpoint, c.output.pose.allow_remote),
        ("control.endpoint", c.control.endpoint, c.control.allow_remote),
    ):
        if not endpoint_is_local(ep) and not allowed:
            raise fail(key, f"{remote}; got {ep!r}")
    zin = c.input.zmq
    servers: list[tuple[str, Any]] = [("control", c.control)]
    servers.append(("output.pose", c.output.pose))
    if zin.mode == "pull":
        servers.append(("input.zmq", zin))
        if zin.server_key:
            raise fail(
                "input.zmq.server_key", 'is for mode = "sub" (a publisher\'s key)'
            )
    else:
        if zin.client_keys:
            raise fail(
                "input.zmq.client_keys",
                'are for mode = "pull"; a SUB takes the publisher\'s server_key',
            )
        if bool(zin.secret_key) != bool(zin.server_key):
            key = "server_key" if zin.secret_key else "secret_key"
            raise fail(
                f"input.zmq.{key}",
                "CURVE on a SUB needs the daemon's secret_key and the publisher's "
                "server_key",
            )
    for section, cfg in servers:
        if cfg.secret_key and not cfg.client_keys:
            raise fail(
                f"{section}.client_keys",
                "CURVE (secret_key set) needs the public keys of the allowed clients",
            )
        if cfg.client_keys and not cfg.secret_key:
            raise fail(f"{section}.secret_key", "client_keys need the daemon's key")
    if not endpoint_is_local(c.control.endpoint) and not c.control.secret_key:
        raise fail(
            "control.secret_key",
            "the control socket off loopback needs CURVE: secret_key and "
            "client_keys (retargetd keys)",
        )
    show = c.show_control
    if show.enabled and not is_loopback_host(show.host) and not show.token:
        raise fail(
            "show_control.token",
            "show control off loopback needs a shared token (PROTOCOLS.md)",
        )
    vmc = c.output.vmc
    target = ipaddress.ip_address(vmc.host)
    broadcast = target.is_multicast or str(target) in ("255.255.255.255",)
    if target.is_unspecified:
        raise fail("output.vmc.host", f"expected a receiver's address; got {vmc.host}")
    if 0 < vmc.max_datagram_bytes < MIN_DATAGRAM:
        raise fail(
            "output.vmc.max_datagram_bytes",
            f"expected 0 (automatic) or {MIN_DATAGRAM}-{MAX_MESSAGE_BYTES} (RFC 791: "
            "every IPv4 "
            f"host accepts 576 bytes, 548 after the headers); got "
            f"{vmc.max_datagram_bytes}",
        )
    if broadcast and not vmc.allow_broadcast:
        raise fail(
            "output.vmc.host",
            f"{vmc.host} is a broadcast/multicast address: VMC goes to one receiver "
            "unless allow_broadcast = true",
        )
