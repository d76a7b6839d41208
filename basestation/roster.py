"""The robots a base station serves: with a scenario, its robots only (others' messages
are dropped, with an error line); without one, any robot."""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterable

log = logging.getLogger(__name__)


class Roster:
    def __init__(self, robot_ids: Iterable[str] | None = None) -> None:
        self.ids: set[str] | None = None if robot_ids is None else set(robot_ids)
        self.drops = 0  # messages dropped from robots off the roster
        self._lock = threading.Lock()  # (Zenoh's threads and run()'s)

    def unknown(self, rid: str, what: str) -> bool:
        """Whether `rid` is off the roster: its `what` is dropped (logged: the first 20)."""
        if self.ids is None or rid in self.ids:
            return False
        with self._lock:
            self.drops = n = self.drops + 1
        if n <= 20 or n % 1000 == 0:
            log.error("%s from unknown robot %r dropped (%d so far); known: %s",
                      what, rid, n, sorted(self.ids))  # fmt: skip
        return True
