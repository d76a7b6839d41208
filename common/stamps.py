"""Comparing sensor stamps: sim stamps are `ticks * dt` in floating point, so a
period of 10 ticks measures 0.25 s, or 0.2499999999999999 s, or 0.2500000000000001 s."""

from __future__ import annotations

from dataclasses import dataclass

# s: stamps this close count as equal
STAMP_SLACK_S = 1e-6
# s: a stamp this far past the previous one is taken only once the next one follows it
MAX_STAMP_JUMP_S = 60.0
# correction epochs: a base station restarted on its database skips at most one reserved
# block (basestation.persistence.EPOCH_BLOCK, 1000)
MAX_EPOCH_JUMP = 100_000


def due(stamp: float, since: float, period_s: float) -> bool:
    """Whether `period_s` has passed from `since` to `stamp` (to `STAMP_SLACK_S`)."""
    return stamp - since >= period_s - STAMP_SLACK_S


@dataclass
class JumpGate:
    """Holds back a stamp far past the stream's last (`MAX_STAMP_JUMP_S`): taken as the
    newest, one such stamp (a driver's glitch: 1e9 s once) had every later message
    refused as going back in time, for good. It is taken when the next one follows it
    (the stream did jump: a sensor off for a while). `max_jump` in the stream's unit
    (s, or correction epochs)."""

    max_jump: float = MAX_STAMP_JUMP_S
    pending: float | None = None

    def holds(self, stamp: float, last: float | None) -> bool:
        """Whether the message stamped `stamp` (the stream's last taken: `last`) is held
        back (dropped by the caller, with a log line)."""
        p = self.pending
        follows = p is not None and p < stamp <= p + self.max_jump
        if last is None or stamp <= last + self.max_jump or follows:
            self.pending = None
            return False
        self.pending = stamp
        return True
