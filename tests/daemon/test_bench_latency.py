"""Issue 35 item 1: ``bench/bench_latency.py`` measures a floor per input -> output
pair the daemon offers. The pair relays (ZeroMQ PULL -> UDP, UDP -> PUB, PULL -> PUB)
really relay through those socket kinds (every timed frame arrives, once, with its
number), and each daemon case is judged against its own pair's relay. No timing is
asserted here (STYLE.md section 10): the bench prints the figures."""

from __future__ import annotations

import argparse
import multiprocessing as mp
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from bench_scripts import bench_module


@pytest.mark.timeout(120)
@pytest.mark.parametrize("relay", ["relay-zmq", "relay-pub", "relay-zmq-pub"])
def test_pair_relay_forwards_every_frame(relay: str, tmp_path: Path) -> None:
    bl = bench_module("bench_latency")
    rng = np.random.default_rng(0)
    take = SimpleNamespace(
        labels=tuple(f"M{k}" for k in range(12)), positions=rng.normal(size=(50, 12, 3))
    )
    args = argparse.Namespace(seconds=0.5, warmup=0.2)
    result = bl.run_case(mp.get_context("spawn"), relay, 240.0, args, take, None,
                         tmp_path)  # fmt: skip
    n = len(result.sent_ns)
    assert n == 120
    got = np.sort(result.recv["raw_frame"])
    timed = got[(got >= result.frame0) & (got < result.frame0 + n)]
    # every timed frame through the relay's socket kinds, once each
    assert np.array_equal(timed, np.arange(result.frame0, result.frame0 + n))
    summary = bl.summarize(result)
    assert summary.raw_recv == n and np.isfinite(summary.raw[1])


def _summary(bl, name: str, **kw) -> object:
    s = bl.Summary(name, 240.0, 100, 240.0, 0)
    for k, v in kw.items():
        setattr(s, k, v)
    return s


def test_each_case_is_judged_against_its_pair_relay() -> None:
    bl = bench_module("bench_latency")
    summaries = [
        _summary(bl, "raw 240 Hz", raw=(50.0, 100.0)),
        _summary(bl, "relay 240 Hz", raw=(80.0, 200.0)),  # +100
        _summary(bl, "relay-pub 240 Hz", raw=(90.0, 400.0)),  # +300
        _summary(bl, "relay-zmq 240 Hz", raw=(90.0, 300.0)),  # +200
        _summary(bl, "relay-zmq-pub 240 Hz", raw=(90.0, 500.0)),  # +400
        _summary(bl, "osc 240 Hz", vmc=(100.0, 220.0), pose=(200.0, 700.0)),
        _summary(bl, "zmq 240 Hz fit", vmc=(100.0, 350.0), pose=(200.0, 400.0)),
        _summary(bl, "natnet 240 Hz", vmc=(100.0, 350.0), pose=(200.0, 400.0)),
    ]
    lines = {ln.split(" added")[0].strip(): ln for ln in bl.pair_floor_lines(summaries)}
    # osc -> VMC: 120 over raw against the UDP relay's 100
    assert "relay    100 µs; ratio  1.20" in lines["osc 240 Hz -> VMC T"]
    # osc -> pose: 600 against relay-pub's 300
    assert "relay-pub    300 µs; ratio  2.00" in lines["osc 240 Hz -> pose"]
    # zmq -> VMC: 250 against relay-zmq's 200; zmq -> pose: 300 against 400
    assert "relay-zmq    200 µs; ratio  1.25" in lines["zmq 240 Hz fit -> VMC T"]
    assert "relay-zmq-pub    400 µs; ratio  0.75" in lines["zmq 240 Hz fit -> pose"]
    # a capture input has no pair relay here, and says so
    assert lines["natnet 240 Hz -> VMC T"].endswith("no pair relay")
    # only the relays a run needs
    assert bl._baselines(["osc"]) == ["raw", "relay", "relay+", "relay-pub"]
    assert "relay-zmq-pub" in bl._baselines(["osc", "zmq"])


def test_the_spin_variant_turns_spin_us_on_and_body_leaves_it_off(
    tmp_path: Path,
) -> None:
    """``+spin`` puts ``[loop] spin_us`` in the daemon's config (a config the daemon
    reads), ``body`` leaves the default (off)."""
    import tomllib

    from retargetd.daemon.live.config import DaemonConfig

    bl = bench_module("bench_latency")
    assert bl._valid_variant("body+spin") and bl._valid_variant("fit+plant+spin")
    assert not bl._valid_variant("spin")
    got = {}
    for variant in ("body", "body+spin"):
        text = bl._config_toml(tmp_path / "c.json", "osc", 9, variant, tmp_path / "f")
        loop = tomllib.loads(text)["loop"]  # its [loop], as the daemon reads it
        got[variant] = DaemonConfig.from_dict({"loop": loop}).loop.spin_us
    assert got == {"body": 0.0, "body+spin": bl.SPIN_US} and bl.SPIN_US > 0
