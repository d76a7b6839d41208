"""The robots a base station serves: with a scenario, its robots only (others' messages
are dropped, with an error line); without one, any robot. And where they start."""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterable

import numpy as np

from common.config import Config
from common.scenario import Scenario

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


def scenario_starts(
    cfg: Config, scenario: Scenario | None
) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """(known start poses, start headings) the graph takes from the scenario: every
    robot's start pose if `basestation.known_start_poses`; else the first robot's (the
    map frame) and the others by matching; with GPS, none, each robot at its first fix
    with the scenario's heading (seed 000)."""
    if scenario is None:
        return {}, {}
    starts = {r.robot_id: r.start_pose for r in scenario.robots}
    if not cfg.basestation.known_start_poses and cfg.basestation.gps.enabled:
        return {}, {rid: float(p[2]) for rid, p in starts.items()}
    if not cfg.basestation.known_start_poses:
        return dict(list(starts.items())[:1]), {}
    return starts, {}
