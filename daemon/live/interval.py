"""Seconds between two solved frames, for the fit's prediction (the live loop's
``BodyPath`` and the replays that reproduce it, ``bench/soak.py``)."""

from __future__ import annotations

from typing import Any


def frame_interval_s(
    last: tuple[float, int, int], frame: Any, received_ns: int, rate_hz: float
) -> tuple[float, tuple[float, int, int]]:
    """Seconds between a solved frame and the one solved before it, for the fit's
    prediction: the source's clock when it sends one, else its frame numbers at
    ``rate_hz`` (``[validate] rate_hz``), else the receive clock; 0 for the first
    frame (the solver's own rate then). Shared by the loop and the replays that
    reproduce it (``bench/soak.py``).

    Args:
        last: the previous solved frame's (source time s, frame number, receive ns);
            (NaN, -1, 0) before any.
        frame: this frame (``source_time_s``, ``frame_id``).
        received_ns: its receive time.
        rate_hz: the source's frame-number rate.

    Returns:
        (seconds, this frame's (source time, frame number, receive ns)).
    """
    last_t, last_id, last_ns = last
    t, fid = frame.source_time_s, frame.frame_id
    now = (t, fid, received_ns)
    if last_ns == 0:
        return 0.0, now
    if t == t and last_t == last_t and t > last_t:  # (NaN: no source clock)
        return float(t - last_t), now
    if fid > last_id >= 0:
        return (fid - last_id) / rate_hz, now
    return max(received_ns - last_ns, 0) * 1e-9, now
