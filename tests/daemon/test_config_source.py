"""``[input] source``: a capture-system URL, checked before any socket opens."""

from __future__ import annotations

import pytest

from retargetd.daemon.live.config import ConfigError, DaemonConfig
from retargetd.daemon.live.sources import parse_source


def test_default_is_no_capture_system() -> None:
    assert DaemonConfig().input.source == ""


@pytest.mark.parametrize(
    ("url", "system", "where"),
    [
        ("qtm://10.0.0.5", "qtm", ("10.0.0.5", 22223)),
        ("qtm://10.0.0.5:22224", "qtm", ("10.0.0.5", 22224)),
        ("natnet://10.0.0.7", "natnet", ("10.0.0.7", 1510, 1511, False, "+Y")),
        (
            "natnet://10.0.0.7:1600?data_port=1601&multicast=1&up=+Z",
            "natnet",
            ("10.0.0.7", 1600, 1601, True, "+Z"),
        ),
    ],
)
def test_source_urls_parse(url: str, system: str, where: tuple[object, ...]) -> None:
    config = DaemonConfig.from_dict({"input": {"source": url}})
    assert config.input.source == url
    got_system, opts = parse_source(url)
    assert got_system == system
    if system == "qtm":
        assert opts == where
    else:
        got = (opts.host, opts.command_port, opts.data_port, opts.multicast)
        assert (*got, opts.up_axis) == where


@pytest.mark.parametrize(
    ("url", "said"),
    [
        ("vicon://10.0.0.1", "expected qtm://HOST[:PORT] or natnet://"),
        ("qtm://", "expected qtm://HOST[:PORT]"),
        ("natnet://10.0.0.7?speed=2", "unknown natnet:// option"),
        ("natnet://10.0.0.7?up=sideways", "up"),
    ],
)
def test_bad_source_is_one_line_naming_the_key(url: str, said: str) -> None:
    with pytest.raises(ConfigError) as exc:
        DaemonConfig.from_dict({"input": {"source": url}})
    text = str(exc.value)
    assert "input.source" in text and said in text and "\n" not in text
