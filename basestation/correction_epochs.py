"""The base station's correction epochs: one count over all robots, one step per
published set of corrections (`PoseCorrection.epoch`; an agent takes a correction only
if its epoch is above the last it took).

Epochs are never reused after a restart on the same database: they are reserved in
blocks there (`persistence.EPOCH_BLOCK`, one write per block). They also move past any
epoch an agent says it took (`RobotState.correction_epoch`): that one came from
another base station (one with a new database served the fleet meanwhile, and this one
is back on its older database), whose count its corrections would otherwise stay below
for as long as that one ran.
"""

from __future__ import annotations

from basestation.persistence import EPOCH_BLOCK, KeyframeDatabase, NullDatabase
from common.stamps import MAX_EPOCH_JUMP


class CorrectionEpochs:
    def __init__(self, db: KeyframeDatabase | NullDatabase) -> None:
        self.db = db
        self.current = 0  # the latest epoch published
        self._reserved = 0  # on the database: epochs up to it may have been used
        self._seen = 0  # the highest epoch an agent reported (another base station's)

    def resume(self, epoch: int) -> None:
        """Go on above `epoch` (every epoch used before on this database is below it)."""
        self.current = self._reserved = max(self.current, epoch)

    def seen(self, epoch: int) -> None:
        """(Zenoh thread) An agent took corrections up to `epoch`; one far ahead (not
        from a base station: a count that never wraps) is not followed."""
        if self.current < epoch < self.current + MAX_EPOCH_JUMP:
            self._seen = max(self._seen, epoch)

    def next(self) -> int:
        """The epoch of the corrections about to be published."""
        self.current = max(self.current, self._seen) + 1
        if self.current > self._reserved:  # never reuse an epoch after a restart
            self._reserved = self.current + EPOCH_BLOCK
            self.db.reserve_epochs(self._reserved)
        return self.current
