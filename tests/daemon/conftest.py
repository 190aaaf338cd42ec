"""Fixtures for live-daemon tests: loopback sockets that are always closed.

Every socket binds 127.0.0.1 (port 0 or ``tcp://127.0.0.1:*``), so tests run in
parallel and never collide with the daemon's default ports.
"""

from __future__ import annotations

import socket
from collections.abc import Callable, Iterator
from typing import Any

import pytest
import zmq


@pytest.fixture
def udp_socket() -> Iterator[Callable[..., socket.socket]]:
    """A factory of UDP sockets, bound to 127.0.0.1 (port 0) when ``bind=True``;
    every one is closed at teardown."""
    made: list[socket.socket] = []

    def make(*, bind: bool = False, timeout_s: float = 0.05) -> socket.socket:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        made.append(sock)
        if bind:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 21)
            sock.bind(("127.0.0.1", 0))
        sock.settimeout(timeout_s)
        return sock

    yield make
    for sock in made:
        sock.close()


@pytest.fixture
def zmq_socket() -> Iterator[Callable[[int], Any]]:
    """A factory of ZeroMQ sockets (``linger = 0``), all closed at teardown."""
    ctx = zmq.Context.instance()
    made: list[Any] = []

    def make(kind: int) -> Any:
        sock = ctx.socket(kind)
        sock.setsockopt(zmq.LINGER, 0)
        made.append(sock)
        return sock

    yield make
    for sock in made:
        sock.close()
