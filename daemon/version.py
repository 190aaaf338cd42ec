"""The installed distribution's version (``mocap-retargetd``), for ``--version`` and
the headers of files the daemon writes."""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version


def package_version() -> str:
    """The installed distribution's version, ``"unknown"`` when not installed."""
    try:
        return version("mocap-retargetd")
    except PackageNotFoundError:
        return "unknown"
