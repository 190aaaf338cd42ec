"""Errors raised at the protocol boundary.

Decoders raise only :class:`DecodeError`; receive loops count its ``reason`` slug.
"""

from __future__ import annotations


class DecodeError(ValueError):
    """A packet or file record that does not match its documented layout.

    Args:
        reason: short slug counted by receive loops (``"bad_length"`` ...).
        detail: human-readable detail for the first occurrence's log line.
    """

    def __init__(self, reason: str, detail: str = "") -> None:
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason
        self.detail = detail
