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
"""

from __future__ import annotations

import ipaddress
import math
import tomllib
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from retargetd.daemon.face.config import FaceConfigError, load_face_config
from retargetd.daemon.face.training import TrainingSet
from retargetd.protocols.conventions import normalize_units, normalize_up_axis
from retargetd.protocols.marker_input import MAX_MARKERS, MAX_MESSAGE_BYTES, MAX_RATE_HZ
from retargetd.protocols.natnet import parse_natnet_url
from retargetd.protocols.qtm import parse_qtm_url

LOCALHOST = "127.0.0.1"


class ConfigError(ValueError):
    """A configuration problem, one line naming the key."""


@dataclass(frozen=True, slots=True, kw_only=True)
class PerformerConfig:
    """Who is solved, with what."""

    rig: str = "menache"
    calibration: str = ""  # a calibration JSON; "" = calibrate live before streaming
    save_calibration: str = ""  # where a live calibration is saved ("" = next to it)
    calibrate_frames: int = 60  # frames averaged by a live calibration


@dataclass(frozen=True, slots=True, kw_only=True)
class OscInputConfig:
    """OSC marker input (UDP)."""

    enabled: bool = True
    host: str = LOCALHOST
    port: int = 39570
    form: str = "compact"  # "compact" or "simple"
    labels: tuple[str, ...] = ()  # the simple form's marker names (compact: announced)
    units: str = "m"
    up: str = "+Z"
    allow: tuple[str, ...] = ()  # allowed source addresses, markers and show control
    # (empty = any)
    # Input bounds (protocols/PROTOCOLS.md "Limits"): fastest plausible frame rate,
    # markers per label set, bytes per datagram; zeros as occlusion.
    max_rate_hz: float = MAX_RATE_HZ
    max_markers: int = MAX_MARKERS
    max_message_bytes: int = MAX_MESSAGE_BYTES
    zero_is_occluded: bool = True


@dataclass(frozen=True, slots=True, kw_only=True)
class ZmqInputConfig:
    """ZeroMQ marker input: PULL bound locally, or SUB connecting to a publisher."""

    enabled: bool = True
    mode: str = "pull"  # "pull" (bind) or "sub" (connect)
    endpoint: str = f"tcp://{LOCALHOST}:39571"
    units: str = "m"
    up: str = "+Z"
    max_rate_hz: float = MAX_RATE_HZ
    max_markers: int = MAX_MARKERS
    max_message_bytes: int = MAX_MESSAGE_BYTES  # per message part (ZMQ_MAXMSGSIZE)
    zero_is_occluded: bool = True


@dataclass(frozen=True, slots=True, kw_only=True)
class VmcOutputConfig:
    """VMC output (OSC over UDP) to a marionette (Unity EVMC4U, VMC4UE, VMC4B...)."""

    enabled: bool = True
    host: str = LOCALHOST
    port: int = 39539


@dataclass(frozen=True, slots=True, kw_only=True)
class PoseOutputConfig:
    """The ZeroMQ pose stream (PUB)."""

    enabled: bool = True
    endpoint: str = f"tcp://{LOCALHOST}:39572"
    sndhwm: int = 4


@dataclass(frozen=True, slots=True, kw_only=True)
class ControlConfig:
    """The control socket (ZeroMQ REP, local only) for ``retargetd ctl``."""

    endpoint: str = f"tcp://{LOCALHOST}:39573"


@dataclass(frozen=True, slots=True, kw_only=True)
class ShowControlConfig:
    """OSC show-control input (VMC's performer port): calibrate, reload, status."""

    enabled: bool = True
    host: str = LOCALHOST
    port: int = 39540


@dataclass(frozen=True, slots=True, kw_only=True)
class TargetConfig:
    """The engine skeleton rotations are re-expressed for."""

    skeleton: str = "humanoid"  # "humanoid" (T-pose) or a BVH file
    bvh_units: str = "cm"
    bvh_up: str = "+Y"
    compensate_base_pose: bool = True


@dataclass(frozen=True, slots=True, kw_only=True)
class LoopConfig:
    """The solve loop."""

    solve_budget_ms: float = 2.0
    process_every_frame: bool = False  # offline replay: solve every frame, drop none
    stats_interval_s: float = 5.0
    poll_timeout_ms: int = 100


@dataclass(frozen=True, slots=True, kw_only=True)
class FaceSectionConfig:
    """The stabilized face, solved from the same marker stream as the body."""

    enabled: bool = False
    config: str = "arkit52"  # a face preset (arkit52, vrm0, vrm1) or a face TOML
    training: str = ""  # face.npz (retargetd face-train); loaded when it exists
    save_training: str = ""  # where live captures are written ("" = over training)
    capture_frames: int = 60  # frames averaged by `ctl face-capture` (--count)
    regularization: float = 1e-3  # unitless weight damping (solve_face)


@dataclass(frozen=True, slots=True, kw_only=True)
class ValidateSectionConfig:
    """The live validator: MuJoCo checks on their own thread, flags in the stream."""

    enabled: bool = False
    queue: int = 16  # frames waiting for the validator; more are dropped, counted
    body_mass_kg: float = 0.0  # 0 = 70 kg (the model's masses; no live check uses them)
    rate_hz: float = 240.0  # the rate the source's frame numbers count at (speeds)


@dataclass(frozen=True, slots=True, kw_only=True)
class InputConfig:
    """Marker inputs."""

    # A capture system the daemon connects to itself, beside the OSC/ZeroMQ inputs:
    # "qtm://HOST[:PORT]" (Qualisys QTM, through qtm-rt) or "natnet://HOST[:PORT]
    # [?data_port=N&multicast=1&group=G&local=A&up=+Z&sets=A,B]" (OptiTrack Motive);
    # "" = none. README "Capture systems"; daemon/live/sources.py.
    source: str = ""
    osc: OscInputConfig = field(default_factory=OscInputConfig)
    zmq: ZmqInputConfig = field(default_factory=ZmqInputConfig)


@dataclass(frozen=True, slots=True, kw_only=True)
class OutputConfig:
    """Outputs."""

    vmc: VmcOutputConfig = field(default_factory=VmcOutputConfig)
    pose: PoseOutputConfig = field(default_factory=PoseOutputConfig)


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

    @classmethod
    def from_toml(cls, path: str | Path) -> DaemonConfig:
        """Read and validate a TOML config. Raises ConfigError naming the key."""
        try:
            text = Path(path).read_text()
        except OSError as exc:
            raise ConfigError(f"{path}: cannot read config: {exc.strerror}") from None
        try:
            doc = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{path}: not valid TOML: {exc}") from None
        return cls.from_dict(doc, source=str(path))

    @classmethod
    def from_dict(cls, doc: dict[str, Any], *, source: str = "config") -> DaemonConfig:
        """Build from a parsed document. Raises ConfigError naming the key."""
        config = _build(cls, doc, "", source)
        _check(config, source)
        return config


def _build(kind: Any, doc: Any, prefix: str, source: str) -> Any:
    if not isinstance(doc, dict):
        raise ConfigError(
            f"{source}: {prefix.rstrip('.') or '(top)'}: expected a table"
        )
    known = {f.name: f for f in fields(kind)}
    kwargs: dict[str, Any] = {}
    for key, value in doc.items():
        name = f"{prefix}{key}"
        if key not in known:
            raise ConfigError(
                f"{source}: {name}: unknown key (expected one of: {', '.join(known)})"
            )
        default = getattr(kind(), key)
        if hasattr(default, "__dataclass_fields__"):
            kwargs[key] = _build(type(default), value, f"{name}.", source)
        else:
            kwargs[key] = _coerce(value, default, name, source)
    return kind(**kwargs)


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


def _check_host(host: str, name: str, source: str) -> None:
    try:
        ipaddress.ip_address(host)
    except ValueError:
        raise ConfigError(
            f"{source}: {name}: expected an IP address (e.g. 127.0.0.1); got {host!r}"
        ) from None


def _check_port(port: int, name: str, source: str) -> None:
    if not 0 <= port <= 65535:
        raise ConfigError(f"{source}: {name}: expected a port 0-65535; got {port}")


def _check_endpoint(endpoint: str, name: str, source: str) -> None:
    if not endpoint.startswith(("tcp://", "ipc://", "inproc://")):
        raise ConfigError(
            f"{source}: {name}: expected tcp://HOST:PORT or ipc://PATH; "
            f"got {endpoint!r}"
        )


def _check(c: DaemonConfig, source: str) -> None:
    osc, zin = c.input.osc, c.input.zmq
    if osc.form not in ("compact", "simple"):
        raise ConfigError(
            f"{source}: input.osc.form: expected 'compact' or 'simple'; "
            f"got {osc.form!r}"
        )
    if osc.form == "simple" and osc.enabled and not osc.labels:
        raise ConfigError(
            f"{source}: input.osc.labels: the simple form needs the marker names"
        )
    if zin.mode not in ("pull", "sub"):
        raise ConfigError(
            f"{source}: input.zmq.mode: expected 'pull' or 'sub'; got {zin.mode!r}"
        )
    for units_key, units, up_key, up in (
        ("input.osc.units", osc.units, "input.osc.up", osc.up),
        ("input.zmq.units", zin.units, "input.zmq.up", zin.up),
        ("target.bvh_units", c.target.bvh_units, "target.bvh_up", c.target.bvh_up),
    ):
        try:
            normalize_units(units)
        except ValueError as exc:
            raise ConfigError(f"{source}: {units_key}: {exc}") from None
        try:
            normalize_up_axis(up)
        except ValueError as exc:
            raise ConfigError(f"{source}: {up_key}: {exc}") from None
    for name, host in (
        ("input.osc.host", osc.host),
        ("output.vmc.host", c.output.vmc.host),
        ("show_control.host", c.show_control.host),
        *((f"input.osc.allow[{i}]", a) for i, a in enumerate(osc.allow)),
    ):
        _check_host(host, name, source)
    for name, port in (
        ("input.osc.port", osc.port),
        ("output.vmc.port", c.output.vmc.port),
        ("show_control.port", c.show_control.port),
    ):
        _check_port(port, name, source)
    for name, ep in (
        ("input.zmq.endpoint", zin.endpoint),
        ("output.pose.endpoint", c.output.pose.endpoint),
        ("control.endpoint", c.control.endpoint),
    ):
        _check_endpoint(ep, name, source)
    _check_input_limits(c.input, source)
    _check_capture_source(c.input.source, source)
    ctl = c.control.endpoint
    if ctl.startswith("tcp://") and not ctl.startswith(
        ("tcp://127.", "tcp://localhost")
    ):
        raise ConfigError(
            f"{source}: control.endpoint: the control socket is local only "
            f"(tcp://127.0.0.1:PORT or ipc://); got {ctl!r}"
        )
    loop = c.loop
    if not 0.0 < loop.solve_budget_ms <= 1000.0:
        raise ConfigError(
            f"{source}: loop.solve_budget_ms: expected (0, 1000]; "
            f"got {loop.solve_budget_ms}"
        )
    if not 0.1 <= loop.stats_interval_s <= 3600.0:
        raise ConfigError(
            f"{source}: loop.stats_interval_s: expected [0.1, 3600]; "
            f"got {loop.stats_interval_s}"
        )
    if not 1 <= loop.poll_timeout_ms <= 10_000:
        raise ConfigError(
            f"{source}: loop.poll_timeout_ms: expected [1, 10000]; "
            f"got {loop.poll_timeout_ms}"
        )
    if not 1 <= c.performer.calibrate_frames <= 100_000:
        raise ConfigError(
            f"{source}: performer.calibrate_frames: expected [1, 100000]; "
            f"got {c.performer.calibrate_frames}"
        )
    if not 1 <= c.output.pose.sndhwm <= 1_000_000:
        raise ConfigError(
            f"{source}: output.pose.sndhwm: expected >= 1; got {c.output.pose.sndhwm}"
        )
    _check_face(c.face, source)
    v = c.validate
    if not 1 <= v.queue <= 10_000:
        raise ConfigError(
            f"{source}: validate.queue: expected [1, 10000]; got {v.queue}"
        )
    if not (v.body_mass_kg == 0.0 or 20.0 <= v.body_mass_kg <= 300.0):
        raise ConfigError(
            f"{source}: validate.body_mass_kg: expected 0 (70 kg) or "
            f"[20, 300]; got {v.body_mass_kg}"
        )
    if not 1.0 <= v.rate_hz <= 10_000.0:
        raise ConfigError(
            f"{source}: validate.rate_hz: expected [1, 10000]; got {v.rate_hz}"
        )


#: Ceiling for ``input.zmq.max_message_bytes``: the frame payload of the largest label
#: set allowed (100,000 markers x 12 bytes = 1.2 MB), rounded up to 2 MiB. The input
#: queue then holds at most RCVHWM (1,000) messages of 2 parts this size.
_ZMQ_MAX_MESSAGE_BYTES = 2 << 20


def _check_input_limits(inputs: InputConfig, source: str) -> None:
    for name, section, most_bytes in (
        ("input.osc", inputs.osc, MAX_MESSAGE_BYTES),  # UDP cannot carry more
        ("input.zmq", inputs.zmq, _ZMQ_MAX_MESSAGE_BYTES),
    ):
        if not 1.0 <= section.max_rate_hz <= 1e6:
            raise ConfigError(
                f"{source}: {name}.max_rate_hz: expected [1, 1000000]; "
                f"got {section.max_rate_hz}"
            )
        if not 1 <= section.max_markers <= 100_000:
            raise ConfigError(
                f"{source}: {name}.max_markers: expected [1, 100000]; "
                f"got {section.max_markers}"
            )
        if not 64 <= section.max_message_bytes <= most_bytes:
            raise ConfigError(
                f"{source}: {name}.max_message_bytes: expected [64, {most_bytes}]; "
                f"got {section.max_message_bytes}"
            )


def _check_capture_source(url: str, source: str) -> None:
    """``input.source``: empty, or a URL the capture inputs parse."""
    try:
        if url.startswith("natnet://"):
            parse_natnet_url(url)
        elif url.startswith("qtm://"):
            parse_qtm_url(url)
        elif url:
            raise ValueError(
                f"expected qtm://HOST[:PORT] or natnet://HOST[:PORT][?...]; got {url!r}"
            )
    except ValueError as exc:
        raise ConfigError(f"{source}: input.source: {exc}") from None


def _check_face(f: FaceSectionConfig, source: str) -> None:
    if not 1 <= f.capture_frames <= 100_000:
        raise ConfigError(
            f"{source}: face.capture_frames: expected [1, 100000]; "
            f"got {f.capture_frames}"
        )
    if not 0.0 <= f.regularization <= 1.0:
        raise ConfigError(
            f"{source}: face.regularization: expected [0, 1]; got {f.regularization}"
        )
    if not f.enabled:
        return

    try:
        load_face_config(f.config)
    except FaceConfigError as exc:
        raise ConfigError(f"{source}: face.config: {exc}") from None
    if f.training and Path(f.training).exists():
        try:
            TrainingSet.load(f.training)
        except (OSError, ValueError) as exc:
            raise ConfigError(f"{source}: face.training: {exc}") from None
