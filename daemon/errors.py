"""Errors shared across the daemon's parts.

:class:`UsageError` is a problem the user fixes (a bad value, a missing file, an
ambiguous subject): the command line reports it in one line with exit code 2.
"""

from __future__ import annotations


class UsageError(Exception):
    """A user error the CLI reports in one line with exit code 2."""
