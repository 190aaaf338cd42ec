"""NatNet frame decode: our decoder against the PyPI ``natnet`` package.

Run from the repository root::

    python bench/bench_natnet.py [--calls N]

Frames are written by the test emulator (``tests/protocols/natnet_emulator.py``,
NatNet 4.1 and 3.1 layouts): the real walk ``PiG_Motion-FlatFoot-Full.c3d`` (35
markers, from ``../shared/datasets/btkdata``; a synthetic 35-marker frame without the
datasets, said in the output) and a 200-marker frame (the walk's markers tiled).

Timed, one frame per call, ``time.perf_counter_ns`` around each call after a
warm-up, median / p99 in microseconds:

- ``ours``: ``MarkerStream.feed(NatNetDecoder...)``: the whole hot path (checks,
  marker-set positions, labelled-marker flags, suffix, conversion to world metres into
  the preallocated packet, sequencing);
- ``natnet``: ``natnet.DataFrame.read_from_buffer``, the package's decode into its
  frozen dataclasses, nothing converted (the baseline, same run, same bytes);
- the ratio of medians ``natnet / ours``.

Speed is printed, never asserted (STYLE.md section 10).
"""

from __future__ import annotations

import argparse
import gc
import importlib.util
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from retargetd.protocols import natnet
from retargetd.protocols.marker_input import MarkerStream

ROOT = Path(__file__).resolve().parent.parent
PIG = ROOT.parent / "shared" / "datasets" / "btkdata" / "PiG_Motion-FlatFoot-Full.c3d"


def _emulator() -> Any:
    spec = importlib.util.spec_from_file_location(
        "natnet_emulator", ROOT / "tests" / "protocols" / "natnet_emulator.py"
    )
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["natnet_emulator"] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def _time(fn: Callable[[int], object], calls: int) -> tuple[float, float]:
    for i in range(200):
        fn(i)
    samples = np.empty(calls)
    gc.disable()
    try:
        for i in range(calls):
            t0 = time.perf_counter_ns()
            fn(i)
            samples[i] = time.perf_counter_ns() - t0
    finally:
        gc.enable()
    return float(np.median(samples)) / 1e3, float(np.percentile(samples, 99)) / 1e3


def _ours(
    stream: MarkerStream, dec: natnet.NatNetDecoder, packets: list[bytes]
) -> Callable[[int], object]:
    n = len(packets)
    clock = iter(range(1, 1 << 62))  # receive times that only increase

    def call(i: int) -> object:
        return stream.feed(dec, packets[i % n], t_ns=next(clock))

    return call


def _theirs(
    pkg: Any, buffer: Any, version: tuple[int, int], packets: list[bytes]
) -> Callable[[int], object]:
    v = pkg.Version(*version)
    bodies = [p[4:] for p in packets]
    n = len(bodies)

    def call(i: int) -> object:
        return pkg.DataFrame.read_from_buffer(buffer(bodies[i % n]), v)

    return call


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", type=int, default=20000)
    args = parser.parse_args()
    em = _emulator()
    if PIG.is_file():
        from retargetd.replay.takes import load_take

        take = load_take(PIG)
        positions, labels = take.positions, list(take.labels)
        source = f"{PIG.name} ({positions.shape[1]} markers)"
    else:
        rng = np.random.default_rng(0)
        positions = rng.normal(size=(100, 35, 3))
        labels = [f"M{i}" for i in range(35)]
        source = "synthetic 35 markers (datasets absent)"
    print(f"load: {os.getloadavg()[0]:.2f} (1-min average), {args.calls} calls each")
    try:
        import natnet as natnet_pkg
        from natnet.packet_buffer import PacketBuffer
    except ImportError:
        natnet_pkg = None
        print("natnet package not installed: baseline skipped")
    tiled = np.concatenate([positions] * 6, axis=1)[:, :200]
    cases = [(source, positions, labels)]
    cases.append(("200 markers (walk tiled)", tiled, [f"M{i}" for i in range(200)]))
    print(
        f"{'frame':42s} {'ver':>4s} {'ours med':>9s} {'p99':>7s} "
        f"{'natnet med':>10s} {'p99':>7s} {'ratio':>6s}"
    )
    for name, pos_world, names in cases:
        pos = pos_world @ em.MOTIVE_FROM_WORLD.T
        t_count = pos.shape[0]
        for version in ((4, 1), (3, 1)):
            packets = [
                em.frame_of_data(version, k, pos[k], k / 100.0) for k in range(t_count)
            ]
            models = natnet.decode_model_defs(
                em.model_defs(version, names), natnet.Version(*version)
            )
            ls = natnet.label_set_from_models(models, 1)
            dec = natnet.NatNetDecoder(models, ls)
            stream = MarkerStream(ls, "+Y", "m")
            # Frame numbers in the packets repeat every T calls; with a zero restart
            # gap the sequencer accepts each repeat (as a restart), never drops it.
            stream.sequencer.restart_gap_ns = 0
            med, p99 = _time(_ours(stream, dec, packets), args.calls)
            assert stream.counters.dropped() == 0
            line = f"{name:42s} {version[0]}.{version[1]:<2d} {med:9.1f} {p99:7.1f}"
            if natnet_pkg is not None:
                theirs = _theirs(natnet_pkg, PacketBuffer, version, packets)
                b_med, b_p99 = _time(theirs, args.calls)
                line += f" {b_med:10.1f} {b_p99:7.1f} {b_med / med:6.1f}"
            print(line)


if __name__ == "__main__":
    main()
