"""Descriptor exhaustion (issue 30 item 3): while a daemon had no file descriptor
left, its control socket went unanswered with nothing logged. A ``retargetd run``
process's limit is lowered from outside (``prlimit``) to what it holds plus a few,
connections to its control port use them up, and the episode is logged once at its
start and once at its end, counted in status (read over a connection made before)."""

from __future__ import annotations

import json
import os
import resource
import socket
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import zmq
from live_harness import EXACT_RIG, WAIT_S

#: Descriptors left to the daemon, and connections opened to use them up.
SPARE_FDS = 4
CONNECTIONS = 16


@pytest.fixture
def held() -> Iterator[list[socket.socket]]:
    socks: list[socket.socket] = []
    yield socks
    for sock in socks:
        sock.close()


def _wait_line(proc: Any, text: str) -> str:
    deadline = time.monotonic() + WAIT_S
    while True:
        for line in proc.lines:
            if text in line:
                return str(line)
        proc._next_line(deadline)


def test_descriptor_exhaustion_is_logged_once_per_episode_and_counted(
    run_daemon: Callable[..., Any],
    exact_calibration: Path,
    zmq_socket: Callable[[int], Any],
    held: list[socket.socket],
) -> None:
    proc = run_daemon(exact_calibration, rig=str(EXACT_RIG))
    ep = proc.endpoints["control"]
    port = int(ep.rsplit(":", 1)[1])
    # A connection made before: it needs no new descriptor in the daemon.
    req = zmq_socket(zmq.REQ)
    req.setsockopt(zmq.RCVTIMEO, int(WAIT_S * 1000))
    req.connect(ep)

    def status() -> dict[str, Any]:
        req.send(b'{"cmd": "status"}')
        reply = json.loads(req.recv())
        assert reply["ok"], reply
        return dict(reply["status"])

    assert status()["fd_exhausted"] is False
    pid = proc.p.pid
    soft, hard = resource.prlimit(pid, resource.RLIMIT_NOFILE)
    in_use = len(os.listdir(f"/proc/{pid}/fd"))
    resource.prlimit(pid, resource.RLIMIT_NOFILE, (in_use + SPARE_FDS, hard))
    try:
        for _ in range(CONNECTIONS):  # the kernel completes them (its backlog)
            held.append(socket.create_connection(("127.0.0.1", port), timeout=5.0))
        start = _wait_line(proc, "cannot accept a connection")
        assert start.startswith("control: cannot accept a connection: Too many open")
        during = status()
        assert during["fd_exhausted"] is True
        assert during["counters"]["fd_episodes"] == 1
        assert during["counters"]["fd_accept_failures"] >= 1
    finally:
        for sock in held:
            sock.close()
        held.clear()
        resource.prlimit(pid, resource.RLIMIT_NOFILE, (soft, hard))
    end = _wait_line(proc, "file descriptors available again")
    assert "failed accepts seen in the episode" in end
    after = status()
    assert after["fd_exhausted"] is False
    assert after["counters"]["fd_episodes"] == 1
    # one line at the start, one at the end, however many accepts failed
    assert sum("cannot accept a connection" in ln for ln in proc.lines) == 1
    assert sum("available again" in ln for ln in proc.lines) == 1
    assert proc.ctl({"cmd": "status"}) is not None  # new connections are taken
    rc, err = proc.stop()
    assert rc == 0, err
    print(f"episode: {start!r} ... {end!r}; {after['counters']['fd_accept_failures']}")
