"""Datagrams the kernel dropped on a UDP socket because its receive buffer was full.

Read from ``/proc/net/udp`` (``udp6``), the ``drops`` column of the line whose inode is
the socket's, when the status or the stats line is built: nothing on the hot path.
The alternative, ``SO_RXQ_OVFL``, delivers the count as ancillary data on every
datagram, so each receive would become a ``recvmsg`` that allocates its ancillary list
(no ``recvfrom_into`` without allocation). Linux only: elsewhere the count is None.
"""

from __future__ import annotations

import os
import socket
from pathlib import Path

_TABLES = {
    socket.AF_INET: Path("/proc/net/udp"),
    socket.AF_INET6: Path("/proc/net/udp6"),
}
_INODE, _DROPS = 9, 12  # columns of a /proc/net/udp line (after `sl`)


def udp_kernel_drops(sock: socket.socket | None) -> int | None:
    """Datagrams the kernel dropped for ``sock`` since it opened (None: unknown)."""
    if sock is None or sock.fileno() < 0:
        return None
    table = _TABLES.get(sock.family)
    if table is None:
        return None
    inode = str(os.fstat(sock.fileno()).st_ino)
    try:
        lines = table.read_text().splitlines()[1:]
    except OSError:
        return None
    for line in lines:
        cols = line.split()
        if len(cols) > _DROPS and cols[_INODE] == inode:
            return int(cols[_DROPS])
    return None
