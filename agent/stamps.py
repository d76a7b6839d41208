"""Comparing sensor stamps: sim stamps are `ticks * dt` in floating point, so a
period of 10 ticks measures 0.25 s, or 0.2499999999999999 s, or 0.2500000000000001 s."""

from __future__ import annotations

# s: stamps this close count as equal
STAMP_SLACK_S = 1e-6


def due(stamp: float, since: float, period_s: float) -> bool:
    """Whether `period_s` has passed from `since` to `stamp` (to `STAMP_SLACK_S`)."""
    return stamp - since >= period_s - STAMP_SLACK_S
