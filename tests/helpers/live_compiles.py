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
[OVERRIDES_JSON [DATASETS]]`` (with the datasets folder, the ICT face on too) prints
one JSON object: ``new`` (dispatcher -> overloads added while streaming) and
``stats`` (what the stream exercised).
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
from face_harness import _face, _stream
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
from retargetd.daemon.synth import face as fs
from retargetd.protocols.marker_input import LabelSet


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


class Frames:
    """The take's frames, forward then backward (no jump from its end to its start);
    with ``face`` ((training set, head rotations, head positions):
    ``face_harness._face``), each with the ICT face's markers after the body's."""

    def __init__(self, face: tuple[Any, Any, Any] | None = None) -> None:
        take = _take()
        self.face = face
        self.labels = take.labels if face is None else _stream(*face, *_idx(1))[0]

    def rows(self, n: int, start: int = 0) -> list[np.ndarray]:
        """``n`` frames from the ``start``-th (float64 copies)."""
        idx, weights = _idx(n, start)
        if self.face is None:
            return [_take().markers_world[i].copy() for i in idx]
        return list(_stream(*self.face, idx, weights)[1])


def _idx(n: int, start: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The take's rows for frames ``start`` .. ``start + n`` (forward, then
    backward) and seeded ARKit weights for them."""
    rows = _take().markers_world.shape[0]
    period = 2 * (rows - 1)
    j = np.arange(start, start + n) % period
    weights = fs.synth_weights(np.random.default_rng(start), n, RATE_HZ)
    return np.where(j < rows, j, period - j), weights


def stream(d: Daemon, src: OscSource, frames: Frames, folder: Path) -> None:
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
    src.send_paced(frames.rows(150), RATE_HZ)
    hidden = frames.rows(20, 150)
    for r in hidden:
        r[0] = np.nan
    src.send_paced(hidden, RATE_HZ)
    src.send_paced([np.full_like(r, np.nan) for r in frames.rows(10, 170)], RATE_HZ)
    src.send_paced(frames.rows(30, 180), RATE_HZ)
    good = frames.rows(15, 210)
    bursts = [np.broadcast_to(r.mean(axis=0), r.shape).copy() for r in good[:5]]
    bursts += [np.full_like(r, 1e30) for r in good[5:8]]
    bursts += [np.zeros_like(r) for r in good[8:10]]
    bursts += [r[::-1].copy() for r in good[10:]]
    src.send_paced(bursts, RATE_HZ)
    src.send_paced(frames.rows(60, 225), RATE_HZ)
    time.sleep(0.3)  # the source paused
    src.send_paced(frames.rows(30, 285), RATE_HZ)
    src.next_id = 0  # the source restarted: frame numbers from 0, labels again
    src.announce(wait=False)
    src.send_paced(frames.rows(60, 315), RATE_HZ)
    ask({"cmd": "status"})
    ask({"cmd": "record", "action": "start", "path": str(folder / "take.mcap")})
    src.send_paced(frames.rows(60, 375), RATE_HZ)
    ask({"cmd": "record", "action": "stop"})
    src.send_paced(frames.rows(20, 435), RATE_HZ)
    _wait_until(
        lambda: not ask({"cmd": "status"})["status"]["record"]["finishing"],
        "the recording to finish",
    )


def main(argv: list[str]) -> int:
    calibration = argv[0]
    extra = json.loads(argv[1]) if len(argv) > 1 else {}
    face = _face(Path(argv[2])) if len(argv) > 2 else None
    with tempfile.TemporaryDirectory(prefix="compiles-") as tmp:
        if face is not None:  # the ICT face on the performer's head
            face[0].save(Path(tmp) / "face.npz")
            extra = _deep_merge(extra, {"face": {
                "enabled": True, "config": "arkit52",
                "training": str(Path(tmp) / "face.npz"),
            }})  # fmt: skip
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
        new = _streamed(d, Frames(face), Path(tmp))
    s = d.stats
    print(
        json.dumps(
            {
                "new": new,
                "stats": {k: getattr(s, k) for k in (
                    "frames_solved", "unseen", "unexplained", "reseeded",
                    "restarts", "post_restarts", "face_solved",
                )},
            }
        )
    )  # fmt: skip
    return 0


def _streamed(d: Daemon, frames: Frames, folder: Path) -> dict[str, int]:
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
            src = OscSource(sock, (host, int(port)))
            src.label_set = LabelSet(1, frames.labels)
            stream(d, src, frames, folder)
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
