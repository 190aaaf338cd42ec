"""Daemon config: defaults, the shipped example, one-line errors naming the key."""

from __future__ import annotations

import re
from importlib import resources
from pathlib import Path

import pytest

from retargetd.daemon.cli.main import main
from retargetd.daemon.live.config import ConfigError, DaemonConfig


def test_example_config_documents_the_defaults() -> None:
    example = resources.files("retargetd.daemon.live") / "retargetd.example.toml"
    assert DaemonConfig.from_toml(str(example)) == DaemonConfig()


def test_the_fit_is_the_default_body_solve() -> None:
    """Issue 14 item 4: once its tests pass (they do), the fit is the default, in the
    daemon's config and on the command line; the construction stays a choice."""
    from retargetd.daemon.body.method import METHODS
    from retargetd.daemon.cli.main import build_parser

    assert DaemonConfig().solve.method == "fit" and METHODS[0] == "fit"
    chosen = DaemonConfig.from_dict({"solve": {"method": "construction"}})
    assert chosen.solve.method == "construction"
    parser = build_parser()
    need = ["take.c3d", "--rig", "menache", "--calibration", "c.json"]
    for cmd in (
        ["solve", *need, "--out", "o.npz"],
        ["validate", *need, "--report", "r.html"],
    ):
        assert parser.parse_args(cmd).method == "fit", cmd
        args = parser.parse_args([*cmd, "--method", "construction"])
        assert args.method == "construction", cmd


def test_defaults_bind_loopback_only() -> None:
    c = DaemonConfig()
    assert c.input.osc.host == "127.0.0.1" and c.show_control.host == "127.0.0.1"
    assert c.output.vmc.port == 39539 and c.show_control.port == 39540
    for ep in (c.input.zmq.endpoint, c.output.pose.endpoint, c.control.endpoint):
        assert ep.startswith("tcp://127.0.0.1:")


@pytest.mark.parametrize(
    ("toml", "message"),
    [
        ("[input.osc]\nprot = 1", "input.osc.prot: unknown key"),
        ("[inputs]\nx = 1", "inputs: unknown key"),
        ("[loop]\nsolve_budget_ms = 'fast'", "loop.solve_budget_ms: expected a number"),
        ("[loop]\nsolve_budget_ms = 0", "loop.solve_budget_ms: expected (0, 1000]"),
        ("[input.osc]\nport = 70000", "input.osc.port: expected a port"),
        ("[input.osc]\nhost = 'localhost'", "input.osc.host: expected an IP address"),
        ("[input.osc]\nform = 'fancy'", "input.osc.form"),
        ("[input.osc]\nform = 'simple'", "input.osc.labels: the simple form needs"),
        ("[input.zmq]\nup = 'north'", "input.zmq.up: up axis must be one of"),
        ("[input.zmq]\nunits = 'furlong'", "input.zmq.units: length units"),
        ("[input.zmq]\nmode = 'push'", "input.zmq.mode"),
        ("[output.vmc]\nenabled = 'yes'", "output.vmc.enabled: expected true or false"),
        (
            "[output.vmc]\nmax_datagram_bytes = 500",
            "output.vmc.max_datagram_bytes: expected 0 (automatic) or 548-65507",
        ),
        (
            "[control]\nendpoint = 'tcp://0.0.0.0:1'",
            "control.endpoint: binding off loopback needs allow_remote = true",
        ),
        ("[input.osc]\nallow = ['nope']", "input.osc.allow[0]: expected an IP address"),
        ("[loop\n", "not valid TOML"),
    ],
)
def test_bad_config_is_one_line_naming_the_key(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], toml: str, message: str
) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(toml)
    with pytest.raises(ConfigError, match=None) as info:
        DaemonConfig.from_toml(path)
    assert message in str(info.value) and "\n" not in str(info.value)
    # Through the CLI: exit 2, one line, before any socket opens.
    assert main(["run", "--config", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0] and str(path) in err[0]


@pytest.mark.parametrize(
    ("toml", "message"),
    [
        (
            "[input.osc]\nmax_rate_hz = 0",
            "input.osc.max_rate_hz: expected [1, 1000000]",
        ),
        (
            "[input.zmq]\nmax_rate_hz = 'fast'",
            "input.zmq.max_rate_hz: expected a number",
        ),
        ("[input.osc]\nmax_markers = 0", "input.osc.max_markers: expected [1, 100000]"),
        (
            "[input.zmq]\nmax_markers = 2.5",
            "input.zmq.max_markers: expected an integer",
        ),
        # UDP cannot carry more than 65,507 bytes; ZeroMQ may go to 2 MiB.
        ("[input.osc]\nmax_message_bytes = 65508", "input.osc.max_message_bytes"),
        ("[input.zmq]\nmax_message_bytes = 3000000", "input.zmq.max_message_bytes"),
        ("[input.osc]\nzero_is_occluded = 1", "input.osc.zero_is_occluded: expected"),
    ],
)
def test_input_limits_are_validated(tmp_path: Path, toml: str, message: str) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(toml)
    with pytest.raises(ConfigError, match=re.escape(message)):
        DaemonConfig.from_toml(path)


def test_input_limits_within_range_are_taken() -> None:
    c = DaemonConfig.from_dict(
        {"input": {"zmq": {"max_message_bytes": 2 << 20, "max_rate_hz": 240}}}
    )
    assert c.input.zmq.max_message_bytes == 2 << 20
    assert c.input.zmq.max_rate_hz == 240.0
    assert c.input.osc.zero_is_occluded and c.input.osc.max_markers == 5454
