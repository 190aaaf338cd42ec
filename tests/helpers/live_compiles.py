"""Which compiled kernels a live daemon compiles (or loads from numba's cache) after
its warm-up, while frames stream through every path of the loop (issue 35; issue 30
item 6: no pose gap the source did not cause).

A kernel first called with a type signature the warm-up (``Daemon.open``) did not
call compiles on the loop's frame: on a fresh cache the stance detector's (issue 34)
took 1.0-2.3 s of the loop's CPU on the soak's first solved frame (a 1039 ms and a
2352 ms ``markers`` stall, measured); from a warm cache it is still a load of tens
of milliseconds. Either adds an overload to the kernel's dispatcher, which is what
this counts: every numba dispatcher of every imported ``retargetd`` module, before
the first frame and after the last, whatever thread called it (a compile holds the
GIL, so one off the loop stalls it too).

Run as a script, in a fresh interpreter: a kernel that an earlier test of the same
process had called would hide a lazy one. ``python live_compiles.py CALIBRATION
[OVERRIDES_JSON]`` prints one JSON object: ``new`` (dispatcher -> overloads added
while streaming) and ``stats`` (what the stream exercised).
"""

from __future__ import annotations

import json
import socket
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from live_harness import (
    RATE_HZ,
    OscSource,
    _deep_merge,
    _ephemeral_doc,
    _take,
    _unused_udp_port,
    _wait_until,
)
from numba.core.dispatcher import Dispatcher

from retargetd.daemon.cli.ctl import request
from retargetd.daemon.live.config import DaemonConfig
from retargetd.daemon.live.loop import Daemon


def overloads() -> dict[str, int]:
    """Compiled signatures per numba dispatcher of the imported ``retargetd``
    modules (by module and name; a dispatcher imported into several, once)."""
    seen: dict[int, str] = {}
    found: dict[str, int] = {}
    for name, module in sorted(sys.modules.items()):
        if not name.startswith("retargetd.") or module is None:
            continue
        for attr, value in vars(module).items():
            if isinstance(value, Dispatcher) and id(value) not in seen:
                seen[id(value)] = key = f"{name}.{attr}"
                found[key] = len(value.overloads)
    return found


def _rows(n: int, start: int = 0) -> list[np.ndarray]:
    """``n`` frames of the take, from row ``start``, forward then backward (no
    jump from its end to its start)."""
    markers = _take().markers_world
    period = 2 * (markers.shape[0] - 1)
    out = []
    for k in range(start, start + n):
        j = k % period
        out.append(markers[j if j < markers.shape[0] else period - j].copy())
    return out


def stream(d: Daemon, src: OscSource, folder: Path) -> None:
    """Every path a live frame can take, paced at the take's rate: a new label set
    (its pipeline built), the stream, one marker hidden, every marker hidden
    (unseen), bursts of bad frames (every marker on one point, at 1e30, at zero,
    labels reversed: unexplained, implausible, reseeded after), a pause, a source
    restart (frame numbers from 0, labels announced again), a recording, status."""
    ctl = d.endpoints["control"].split()[0]

    def ask(req: dict[str, Any]) -> dict[str, Any]:
        reply = request(ctl, req, 30_000)
        assert reply is not None and reply.get("ok"), (req, reply)
        return reply

    src.announce()
    _wait_until(
        lambda: (
            d.osc_stream.label_set == src.label_set and d.performers.ready(d.osc_stream)
        ),
        "the label set's pipeline",
    )
    src.send_paced(_rows(150), RATE_HZ)
    hidden = _rows(20, 150)
    for r in hidden:
        r[0] = np.nan
    src.send_paced(hidden, RATE_HZ)
    src.send_paced([np.full_like(r, np.nan) for r in _rows(10, 170)], RATE_HZ)
    src.send_paced(_rows(30, 180), RATE_HZ)
    good = _rows(15, 210)
    bursts = [np.broadcast_to(r.mean(axis=0), r.shape).copy() for r in good[:5]]
    bursts += [np.full_like(r, 1e30) for r in good[5:8]]
    bursts += [np.zeros_like(r) for r in good[8:10]]
    bursts += [r[::-1].copy() for r in good[10:]]
    src.send_paced(bursts, RATE_HZ)
    src.send_paced(_rows(60, 225), RATE_HZ)
    time.sleep(0.3)  # the source paused
    src.send_paced(_rows(30, 285), RATE_HZ)
    src.next_id = 0  # the source restarted: frame numbers from 0, labels again
    src.announce(wait=False)
    src.send_paced(_rows(60, 315), RATE_HZ)
    ask({"cmd": "status"})
    ask({"cmd": "record", "action": "start", "path": str(folder / "take.mcap")})
    src.send_paced(_rows(60, 375), RATE_HZ)
    ask({"cmd": "record", "action": "stop"})
    src.send_paced(_rows(20, 435), RATE_HZ)
    _wait_until(
        lambda: not ask({"cmd": "status"})["status"]["record"]["finishing"],
        "the recording to finish",
    )


def main(argv: list[str]) -> int:
    calibration = argv[0]
    extra = json.loads(argv[1]) if len(argv) > 1 else {}
    with tempfile.TemporaryDirectory(prefix="compiles-") as tmp:
        doc = _deep_merge(
            _ephemeral_doc(_unused_udp_port()),
            {
                "performer": {"calibration": calibration},
                "solve": {"method": "fit"},  # the default, which the soak runs
                "validate": {"enabled": True},
                "record": {"folder": tmp},
            },
        )
        d = Daemon(
            DaemonConfig.from_dict(_deep_merge(doc, extra), source="compiles"),
            out=lambda _l: None,
        )
        new = _streamed(d, Path(tmp))
    s = d.stats
    print(
        json.dumps(
            {
                "new": new,
                "stats": {k: getattr(s, k) for k in (
                    "frames_solved", "unseen", "unexplained", "reseeded",
                    "restarts", "post_restarts",
                )},
            }
        )
    )  # fmt: skip
    return 0


def _streamed(d: Daemon, folder: Path) -> dict[str, int]:
    """Open ``d``, run its loop in a thread through :func:`stream`, close it; the
    overloads added after the warm-up, per dispatcher."""
    errors: list[BaseException] = []
    stop = threading.Event()

    def run() -> None:
        try:
            d.run(stop.is_set)
        except BaseException as exc:  # re-raised below
            errors.append(exc)

    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        d.open()
        before = overloads()
        thread = threading.Thread(target=run, name="live-daemon", daemon=True)
        thread.start()
        host, port = d.endpoints["osc markers"].split()[0][6:].rsplit(":", 1)
        try:
            stream(d, OscSource(sock, (host, int(port))), folder)
            time.sleep(0.2)  # the last frames through the loop and the validator
        finally:
            stop.set()
            thread.join(30.0)
        after = overloads()
    finally:
        sock.close()
        d.close()
    if errors:
        raise errors[0]
    return {k: n - before.get(k, 0) for k, n in after.items() if n > before.get(k, 0)}


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
