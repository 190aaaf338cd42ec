"""The operator's browser console (issue 18): live 3D, plots and buttons on ``viser``.

:mod:`~retargetd.daemon.console.snapshot` is what the loop touches (a latest-snapshot
slot and a command queue, neither of which ever blocks it);
:mod:`~retargetd.daemon.console.app` is the console thread and its page;
:mod:`~retargetd.daemon.console.offline` plays solved takes on the same page with a
timeline (``serve_offline``). ``viser`` is imported only by ``app`` and ``offline``.
"""

from retargetd.daemon.console.snapshot import (
    COMMAND_KINDS,
    DEFAULT_PUBLISH_HZ,
    Command,
    CommandQueue,
    ConsoleLayout,
    SkeletonProgram,
    Snapshot,
    SnapshotSlot,
    bone_endpoints,
)

__all__ = [
    "COMMAND_KINDS",
    "DEFAULT_PUBLISH_HZ",
    "Command",
    "CommandQueue",
    "ConsoleLayout",
    "SkeletonProgram",
    "Snapshot",
    "SnapshotSlot",
    "bone_endpoints",
]
