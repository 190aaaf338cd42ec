"""The sections of the daemon's configuration: one frozen dataclass per TOML table,
each field carrying its rule (:func:`spec`: a range, choices, an address, an
endpoint, a file...), the limits those rules cite and :class:`ConfigError`. The whole
file, its parsing and the rules across keys are :mod:`retargetd.daemon.live.config`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from retargetd.protocols.marker_input import (
    MAX_COORDINATE_M,
    MAX_MARKERS,
    MAX_MESSAGE_BYTES,
    MAX_RATE_HZ,
)

LOCALHOST = "127.0.0.1"

#: The most frames a live calibration may average: 5 s at 2000 Hz, the fastest
#: full-resolution optical capture rates (Vicon Vantage V16: up to 2000 Hz; Qualisys
#: Arqus: 300 Hz full frame, higher windowed). An average gains nothing past a few
#: seconds of stillness, and 10,000 frames of 200 markers are 48 MB at most (a count
#: of 2^31 grew the daemon's memory without bound: issue 12).
CALIBRATE_MAX_FRAMES = 10_000

#: The longest live range of motion (``ctl calibrate --rom --seconds S``), seconds:
#: bounded by the memory a request may make the daemon hold, 60 s at 2000 Hz (the
#: fastest full-resolution optical rate, as CALIBRATE_MAX_FRAMES) of 200 markers as
#: float64 is 576 MB; 60 s is still over twice the synthetic ``rom`` motion's two
#: cycles (24 s, each leg circling its hip twice), which place the hips to 4-6 mm.
CALIBRATE_ROM_MAX_S = 60.0

#: Ceiling for ``input.zmq.max_message_bytes``: the frame payload of the largest label
#: set allowed (100,000 markers x 12 bytes = 1.2 MB), rounded up to 2 MiB. The input
#: queue then holds at most RCVHWM (1,000) messages of 2 parts this size.
_ZMQ_MAX_MESSAGE_BYTES = 2 << 20


class ConfigError(ValueError):
    """A configuration problem, one line naming the key."""


def spec(default: Any, check: str = "", **limits: Any) -> Any:
    """A config field with its validation rule (read by ``_check_field`` and by the
    schema-generated test): ``check`` names the rule, ``limits`` its bounds."""
    return field(default=default, metadata={"check": check, **limits})


def between(default: Any, lo: float, hi: float, *, open_lo: bool = False) -> Any:
    return spec(default, "range", lo=lo, hi=hi, open_lo=open_lo)


def one_of(default: str, *choices: str) -> Any:
    return spec(default, "choices", choices=choices)


@dataclass(frozen=True, slots=True, kw_only=True)
class PerformerConfig:
    """Who is solved, with what."""

    rig: str = spec("menache", "rig")
    # false: a face and no body (its face streamed alone, nothing calibrated; the
    # face is [face]'s, or a [[performer]]'s face key): README "A face alone"
    body: bool = True
    # a calibration JSON; "" = calibrate live before streaming
    calibration: str = spec("", "file")
    # where a live calibration is saved ("" = next to it)
    save_calibration: str = spec("", "out_path")
    # Frames averaged by a live calibration. At least 3: the stillness check compares
    # the first and last thirds of the window. At most CALIBRATE_MAX_FRAMES.
    calibrate_frames: int = between(60, 3, CALIBRATE_MAX_FRAMES)
    # The fastest a marker may drift over the averaged frames (its net displacement
    # between the first and last thirds of the window over the time between them).
    # Quiet standing sways the centre of pressure at ~10 mm/s mean velocity (Prieto
    # et al. 1996, IEEE TBME 43(9):956, young adults eyes open: 8-15 mm/s), the body's
    # centre of mass slower still (Winter 1995, Gait & Posture 3:193); the slowest
    # walking is ~0.4 m/s and comfortable gait 1.3-1.5 m/s (Bohannon 1997, Age Ageing
    # 26:15). 50 mm/s is 3-5x quiet sway and an eighth of the slowest walk.
    calibrate_max_speed_m_s: float = between(0.05, 0.001, 1.0)
    # A pending calibration that collects no frame for this long expires (the
    # default is the marker input's restart gap: a source silent that long is a new
    # session, protocols/marker_input.py RESTART_GAP_NS).
    calibrate_timeout_s: float = between(1.0, 0.05, 60.0)


#: The inputs a ``[[performer]]`` may be tied to (``input``): any, or one of them.
PERFORMER_INPUTS = ("any", "osc", "zmq", "source")


@dataclass(frozen=True, slots=True, kw_only=True)
class NamedPerformerConfig(PerformerConfig):
    """One of several performers on one daemon (a ``[[performer]]`` table): the
    keys of ``[performer]`` plus who it is, which markers are its own and where its
    avatar goes (README "Several performers")."""

    # Unique; ``ctl calibrate --performer NAME``, status and the pose stream name it.
    name: str = spec("", "performer_name")
    # Its markers: the labels starting with this (stripped before the solve). Left
    # out, NAME + ":" (the C3D / Vicon subject convention "NAME:LASI"); "" = the
    # labels no other performer's prefix claims (e.g. a NatNet stream's first set).
    prefix: str = spec("", "prefix")
    # The input its frames come from ("any", "osc", "zmq" or "source").
    input: str = one_of("any", *PERFORMER_INPUTS)
    # Its VMC destination "HOST:PORT" (VMC is one avatar per port); "" = the
    # [output.vmc] host and port (one performer at most).
    vmc: str = spec("", "host_port")
    # Its face config (a preset or a face TOML) when [face] is on; "" = no face.
    face: str = spec("", "performer_face")
    # Its face training set (face.npz; live captures are saved over it).
    face_training: str = spec("", "training")


@dataclass(frozen=True, slots=True, kw_only=True)
class OscInputConfig:
    """OSC marker input (UDP)."""

    enabled: bool = True
    host: str = spec(LOCALHOST, "host")
    allow_remote: bool = False  # a host other than loopback needs this
    port: int = spec(39570, "port", lo=0, hi=65535)
    form: str = one_of("compact", "compact", "simple")
    # the simple form's marker names (compact: announced)
    labels: tuple[str, ...] = spec((), "names")
    units: str = spec("m", "units")
    up: str = spec("+Z", "up")
    # allowed source addresses, markers and show control (empty = any)
    allow: tuple[str, ...] = spec((), "hosts")
    # Input bounds (protocols/PROTOCOLS.md "Limits"): fastest plausible frame rate,
    # markers per label set, bytes per datagram (UDP cannot carry more than
    # MAX_MESSAGE_BYTES); zeros as occlusion.
    max_rate_hz: float = between(MAX_RATE_HZ, 1.0, 1e6)
    max_markers: int = between(MAX_MARKERS, 1, 100_000)
    max_message_bytes: int = between(MAX_MESSAGE_BYTES, 64, MAX_MESSAGE_BYTES)
    zero_is_occluded: bool = True
    # a marker with a world coordinate past this (metres) is occluded and counted
    max_coordinate_m: float = between(MAX_COORDINATE_M, 1.0, 1e6)
    # An HMAC key file (retargetd keys --hmac NAME): set, only datagrams signed with
    # it and newer than the last are taken (PROTOCOLS.md 13); "" = unsigned.
    key_file: str = spec("", "hmac_key")


@dataclass(frozen=True, slots=True, kw_only=True)
class ZmqInputConfig:
    """ZeroMQ marker input: PULL bound locally, or SUB connecting to a publisher."""

    enabled: bool = True
    mode: str = one_of("pull", "pull", "sub")
    endpoint: str = spec(f"tcp://{LOCALHOST}:39571", "endpoint")
    allow_remote: bool = False  # an endpoint other than loopback needs this
    units: str = spec("m", "units")
    up: str = spec("+Z", "up")
    max_rate_hz: float = between(MAX_RATE_HZ, 1.0, 1e6)
    max_markers: int = between(MAX_MARKERS, 1, 100_000)
    # per message part (ZMQ_MAXMSGSIZE), up to _ZMQ_MAX_MESSAGE_BYTES
    max_message_bytes: int = between(MAX_MESSAGE_BYTES, 64, _ZMQ_MAX_MESSAGE_BYTES)
    zero_is_occluded: bool = True
    max_coordinate_m: float = between(MAX_COORDINATE_M, 1.0, 1e6)
    # CURVE, as [control]: mode "pull", the daemon's .key_secret, and only the
    # client keys below may send; mode "sub", the daemon's .key_secret and the
    # publisher's public key (server_key): it connects as a CURVE client.
    secret_key: str = spec("", "secret_key")
    client_keys: tuple[str, ...] = spec((), "public_keys")
    server_key: str = spec("", "public_key")


@dataclass(frozen=True, slots=True, kw_only=True)
class VmcOutputConfig:
    """VMC output (OSC over UDP) to a marionette (Unity EVMC4U, VMC4UE, VMC4B...)."""

    enabled: bool = True
    host: str = spec(LOCALHOST, "host")
    port: int = spec(39539, "port", lo=1, hi=65535)
    allow_broadcast: bool = False  # a broadcast or multicast host needs this
    # The largest datagram, bytes; 0: 8192 to a loopback host, else 1472 (no IP
    # fragments on Ethernet). Else 548 (RFC 791's 576 minus headers) to the largest
    # UDP payload.
    max_datagram_bytes: int = between(0, 0, MAX_MESSAGE_BYTES)


@dataclass(frozen=True, slots=True, kw_only=True)
class PoseOutputConfig:
    """The ZeroMQ pose stream (PUB)."""

    enabled: bool = True
    endpoint: str = spec(f"tcp://{LOCALHOST}:39572", "endpoint")
    allow_remote: bool = False  # an endpoint other than loopback needs this
    sndhwm: int = between(4, 1, 1_000_000)
    # CURVE: the daemon's .key_secret; set, only the client keys below subscribe
    secret_key: str = spec("", "secret_key")
    client_keys: tuple[str, ...] = spec((), "public_keys")


@dataclass(frozen=True, slots=True, kw_only=True)
class ControlConfig:
    """The control socket (ZeroMQ REP) for ``retargetd ctl``."""

    endpoint: str = spec(f"tcp://{LOCALHOST}:39573", "endpoint")
    # Off loopback: allow_remote and CURVE (secret_key + client_keys) both needed.
    allow_remote: bool = False
    secret_key: str = spec("", "secret_key")
    client_keys: tuple[str, ...] = spec((), "public_keys")
    calibrate: bool = True  # `ctl calibrate` allowed
    reload: bool = True  # `ctl reload` allowed
    # The least time between two accepted reloads, and between two accepted
    # calibration requests, from any path (excess ones answered "rate limited").
    # A reload parses the rig and rebuilds the pipelines and the validator (tens of
    # ms, blocking the loop): once a second bounds that to a few per cent of the
    # loop's time; an operator reloads after editing a file, seconds apart.
    min_interval_s: float = between(1.0, 0.01, 3600.0)


@dataclass(frozen=True, slots=True, kw_only=True)
class ShowControlConfig:
    """OSC show-control input (VMC's performer port): calibrate, reload, status."""

    enabled: bool = True
    host: str = spec(LOCALHOST, "host")
    port: int = spec(39540, "port", lo=0, hi=65535)
    # Off loopback: allow_remote and a token both needed.
    allow_remote: bool = False
    # Set: every message's address starts with /TOKEN (PROTOCOLS.md).
    token: str = spec("", "token")
    calibrate: bool = True  # /VMC/Ext/Set/Calib/Exec and /rtd/calibrate allowed
    reload: bool = True  # /rtd/reload allowed


@dataclass(frozen=True, slots=True, kw_only=True)
class RecordConfig:
    """``ctl record start``: where recordings may be written."""

    # Every recording goes under this folder (relative: the daemon's working
    # directory); a path outside it or with ".." is refused.
    folder: str = spec("recordings", "folder")
    # The folder's recordings (*.mcap) may hold at most this many MB: record start
    # is refused at it and a recording stops there. Measured: the PiG walk at 120 Hz
    # with poses and the Foxglove channels writes 1.4 GB an hour, so 20 GB holds a
    # long show day of takes (~14 hours).
    max_total_mb: float = between(20_000.0, 1.0, 1e9)
    # The disk keeps at least this many MB free: record start is refused and a
    # recording stops below it (room for the MCAP footer, the OS and other files).
    min_free_mb: float = between(1024.0, 0.0, 1e9)
    # At most one record start per this many seconds (3,000 start/stop cycles in
    # 9.4 s wrote 3,000 files, issue 30); a refused start is counted rate_limited.
    min_interval_s: float = between(1.0, 0.0, 3600.0)


@dataclass(frozen=True, slots=True, kw_only=True)
class TargetConfig:
    """The engine skeleton rotations are re-expressed for."""

    skeleton: str = spec("humanoid", "skeleton")  # "humanoid" (T-pose) or a BVH
    bvh_units: str = spec("cm", "units")
    bvh_up: str = spec("+Y", "up")
    compensate_base_pose: bool = True
    # How the target's Spine, Chest and UpperChest are emitted: "mapped" (each from
    # the rig bone mapped to it, UpperChest slerp-filled) or "pivot" (the chapter's
    # shifting pivot: the Hips-to-thorax bend spread bottom-up, rx and rz doubled, at
    # most spine_pivot_limit_deg a joint; post/pivot.py SpinePivot; README).
    spine: str = one_of("mapped", "mapped", "pivot")
    spine_pivot_limit_deg: float = between(15.0, 0.0, 180.0, open_lo=True)
    # The feet: "free" (the rotations alone; the root scaled by the hips-height
    # ratio) or "plant" (the root scaled by the leg-length ratio and each stance foot
    # held where it landed by two-bone IK on the target's legs; post/plant.py
    # FootPlant; README "Feet that plant").
    feet: str = one_of("free", "free", "plant")


@dataclass(frozen=True, slots=True, kw_only=True)
class LoopConfig:
    """The solve loop."""

    solve_budget_ms: float = between(2.0, 0.0, 1000.0, open_lo=True)
    process_every_frame: bool = False  # offline replay: solve every frame, drop none
    stats_interval_s: float = between(5.0, 0.1, 3600.0)
    poll_timeout_ms: int = between(100, 1, 10_000)
    # Touch the fit this long before a steady stream's next frame (live/prewarm.py),
    # 0 = never: at least the touch's own cold cost (~0.1 ms) plus the poll's 1 ms
    # rounding; a stream faster than 2x this per frame, or whose spacing deviates by
    # half of this on average, is not touched.
    prewarm_ms: float = between(1.5, 0.0, 100.0)
    # Poll without sleeping from this long before a steady stream's next frame until
    # this long after it (live/spin.py), 0 = never (the default): for a machine with
    # a core to spare for the loop; on one whose cores are busy it delays the frame.
    spin_us: float = between(0.0, 0.0, 10_000.0)
    # With several [[performer]] tables: the threads their body solves run on, the
    # loop's included (live/solve_threads.py); 1 = all on the loop thread. The
    # solves are compiled nogil, so each thread can take a core of its own; at most
    # one thread per performer is started. 2: fewer drops than 1 in 7 of 9 paired
    # runs of 4 performers on the shared 2-core VM (README "Solves side by side").
    solve_threads: int = between(2, 1, 64)
    # A repeated log line (per reason) is printed once, then summarized with its
    # count at most once per this interval (a flood cannot grow the log).
    log_interval_s: float = between(10.0, 0.1, 3600.0)
    # Resample the output to the engine's rate (slerp between the two processed
    # poses around each tick, on the source's clock; README "Post stages"); 0 = send
    # every solved frame. Above the input's rate the loop's timer sends the ticks
    # between input frames, each one input period less one output period behind.
    output_rate_hz: float = between(0.0, 0.0, 10_000.0)


@dataclass(frozen=True, slots=True, kw_only=True)
class FaceSectionConfig:
    """The stabilized face, solved from the same marker stream as the body."""

    enabled: bool = False
    # a face preset (arkit52, vrm0, vrm1) or a face TOML
    config: str = spec("arkit52", "face_config")
    # face.npz (retargetd face-train); loaded when it exists
    training: str = spec("", "training")
    # where live captures are written ("" = over training)
    save_training: str = spec("", "out_path")
    # frames averaged by `ctl face-capture` (--count)
    capture_frames: int = between(60, 1, 100_000)
    # unitless weight damping: lambda = regularization * noise_rms^2, 1 = the MAP
    # ridge for a weight prior N(0, 1/3) (face/observability.py ridge; FACES.md)
    regularization: float = between(1.0, 0.0, 100.0)


@dataclass(frozen=True, slots=True, kw_only=True)
class ValidateSectionConfig:
    """The live validator: MuJoCo checks on their own thread, flags in the stream."""

    enabled: bool = False
    # frames waiting for the validator; more are dropped, counted
    queue: int = between(16, 1, 10_000)
    # 0 = 70 kg (the model's masses; no live check uses them); else [20, 300]
    body_mass_kg: float = spec(0.0, "mass")
    # the rate the source's frame numbers count at (speeds)
    rate_hz: float = between(240.0, 1.0, 10_000.0)


@dataclass(frozen=True, slots=True, kw_only=True)
class SolveConfig:
    """The body solve (README "Two ways to solve the body")."""

    method: str = one_of("fit", "construction", "fit")


@dataclass(frozen=True, slots=True, kw_only=True)
class ConsoleConfig:
    """The browser console (``retargetd run --console``): off unless asked."""

    enabled: bool = False
    host: str = spec(LOCALHOST, "host")
    port: int = spec(8080, "port", lo=0, hi=65535)
    allow_remote: bool = False  # a host other than loopback needs this
    # Snapshots published to the page per second (30: broadcast video's rate).
    publish_hz: float = between(30.0, 1.0, 120.0)


@dataclass(frozen=True, slots=True, kw_only=True)
class InputConfig:
    """Marker inputs."""

    # A capture system the daemon connects to itself, beside the OSC/ZeroMQ inputs:
    # "qtm://HOST[:PORT]" (Qualisys QTM, through qtm-rt) or "natnet://HOST[:PORT]
    # [?data_port=N&multicast=1&group=G&local=A&up=+Z&sets=A,B&subjects=1]" (Motive);
    # "" = none. README "Capture systems"; daemon/live/sources.py.
    source: str = spec("", "capture_source")
    osc: OscInputConfig = field(default_factory=OscInputConfig)
    zmq: ZmqInputConfig = field(default_factory=ZmqInputConfig)


@dataclass(frozen=True, slots=True, kw_only=True)
class OutputConfig:
    """Outputs."""

    vmc: VmcOutputConfig = field(default_factory=VmcOutputConfig)
    pose: PoseOutputConfig = field(default_factory=PoseOutputConfig)
