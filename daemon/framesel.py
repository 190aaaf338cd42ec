"""Frame selections ``a:b`` on the command line: 0-based, half-open row indices."""

from __future__ import annotations

from retargetd.daemon.cli import UsageError


def parse_frames(text: str | None, n_frames: int, *, option: str) -> slice:
    """Parse ``a:b`` (0-based, half-open rows of the take as loaded; either side may be
    omitted; negative counts from the end) into a slice of ``n_frames`` rows.

    Raises:
        UsageError: naming the option when the text is malformed or selects nothing.
    """
    if text is None:
        return slice(0, n_frames)
    parts = text.split(":")
    if len(parts) != 2:
        raise UsageError(f"{option}: expected a:b (0-based, half-open); got {text!r}")
    try:
        a = int(parts[0]) if parts[0].strip() else 0
        b = int(parts[1]) if parts[1].strip() else n_frames
    except ValueError:
        raise UsageError(f"{option}: expected integers a:b; got {text!r}") from None
    start, stop, _ = slice(a, b).indices(n_frames)
    if stop <= start:
        raise UsageError(
            f"{option}: {text!r} selects no frames of a take with {n_frames} frames"
        )
    return slice(start, stop)
