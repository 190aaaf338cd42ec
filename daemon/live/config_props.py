"""The ``[[prop]]`` tables of the daemon's configuration: props and virtual cameras
tracked as rigid bodies beside the performers (README "Props and a virtual camera";
the solve is ``retargetd.daemon.props``).

Each table names the prop, its markers (``markers``, or every label starting with
``prefix``, by default NAME + ":", the C3D / Vicon subject convention), its kind
("rigid" or "camera"), its calibration file and how it is streamed. The keys are
checked as ``[[performer]]``'s are (``config._build``), then across tables here.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

from retargetd.daemon.live.config_schema import (
    CALIBRATE_MAX_FRAMES,
    ConfigError,
    between,
    one_of,
    spec,
)

#: Props one daemon tracks: the pose stream's prop id is one byte.
MAX_PROPS = 255


@dataclass(frozen=True, slots=True, kw_only=True)
class PropConfig:
    """One prop (a ``[[prop]]`` table)."""

    # Unique; ``ctl calibrate --prop NAME``, status, the VMC tracker serial and the
    # pose stream name it.
    name: str = spec("", "performer_name")
    # Its marker labels as the stream names them; empty: every label starting with
    # ``prefix`` (the labels present when it is calibrated).
    markers: tuple[str, ...] = spec((), "names")
    # Left out with no ``markers``: NAME + ":".
    prefix: str = spec("", "prefix")
    # "camera": also streamed as /VMC/Ext/Cam with its field of view.
    kind: str = one_of("rigid", "rigid", "camera")
    # Its layout (``retargetd calibrate --prop``); "" = calibrate live first.
    calibration: str = spec("", "file")
    # Where a live calibration is saved ("" = over calibration, else NAME.prop.json).
    save_calibration: str = spec("", "out_path")
    # Frames averaged by a live calibration (at least 3: the stillness check's
    # thirds); default 30: a quarter to half a second at 60-120 Hz.
    calibrate_frames: int = between(30, 3, CALIBRATE_MAX_FRAMES)
    # The prop's origin from its markers' centroid, mm, in the world's axes at
    # calibration (a camera's sensor, a sword's grip): +-10 m covers a stage.
    pivot_x_mm: float = between(0.0, -10_000.0, 10_000.0)
    pivot_y_mm: float = between(0.0, -10_000.0, 10_000.0)
    pivot_z_mm: float = between(0.0, -10_000.0, 10_000.0)
    # The camera's vertical field of view, degrees (Unity's default camera: 60);
    # (0, 180) exclusive is every perspective lens.
    fov_deg: float = between(60.0, 1.0, 179.0)
    # An OSC address on the show-control port whose float argument sets fov_deg
    # live (a lens encoder, a fader); "" = fixed.
    fov_osc: str = spec("", "osc_address")
    # The fit's gate, mm (props/solve.py DEFAULT_GATE_M: reconstruction error, not
    # skin artefact); at most 100 mm, past any cluster's marker spacing.
    gate_mm: float = between(10.0, 1.0, 100.0)
    # One Euro smoothing (post/one_euro.py, Casiez et al. 2012): cutoff at rest, Hz
    # (0 = off) and its rise per unit speed (both rotation, Hz per rad/s, and
    # position, Hz per m/s).
    smooth_min_cutoff_hz: float = between(0.0, 0.0, 1000.0)
    smooth_beta: float = between(0.0, 0.0, 1000.0)
    # Its VMC destination "HOST:PORT"; "" = every performer's VMC destination.
    vmc: str = spec("", "host_port")


def check_props(
    props: tuple[PropConfig, ...], performer_names: tuple[str, ...], source: str
) -> None:
    """Across ``[[prop]]`` tables: at most MAX_PROPS, distinct names (from each
    other and from the performers': status and the pose stream name both), no
    marker claimed by two props, and 3 markers at least when listed."""
    if len(props) > MAX_PROPS:
        raise ConfigError(
            f"{source}: prop: at most {MAX_PROPS} props; got {len(props)}"
        )
    names: set[str] = set(performer_names)
    claimed: dict[str, str] = {}
    for i, p in enumerate(props):
        key = f"prop[{i}]"
        if p.name in names:
            raise ConfigError(
                f"{source}: {key}.name: {p.name!r} is taken (props and performers "
                "each need their own name)"
            )
        names.add(p.name)
        if p.markers and len(p.markers) < 3:
            raise ConfigError(
                f"{source}: {key}.markers: a rigid fit needs 3 markers at least; got "
                f"{len(p.markers)}"
            )
        for label in p.markers:
            if label in claimed:
                raise ConfigError(
                    f"{source}: {key}.markers: {label!r} is prop {claimed[label]!r}'s"
                )
            claimed[label] = p.name


def build_props(entries: Any, build: Any, source: str) -> tuple[PropConfig, ...]:
    """The ``[[prop]]`` tables, each read by ``build(PropConfig, table, prefix,
    source)`` (the config's own reader); ``prefix`` left out with no ``markers``
    is NAME + ":"."""
    if not isinstance(entries, list) or not entries:
        raise ConfigError(f"{source}: prop: expected [[prop]] tables; got {entries!r}")
    out = []
    for i, entry in enumerate(entries):
        key = f"prop[{i}]"
        if not isinstance(entry, dict):
            raise ConfigError(f"{source}: {key}: expected a table; got {entry!r}")
        prop = build(PropConfig, entry, f"{key}.", source)
        if "name" not in entry:
            raise ConfigError(f"{source}: {key}.name: every [[prop]] needs a name")
        if "prefix" not in entry and not prop.markers:
            prop = replace(prop, prefix=f"{prop.name}:")
        out.append(prop)
    return tuple(out)
