"""Frontiers exploration gives up on, so that a mission ends instead of retrying forever.

A frontier goal the map itself kept a robot from reaching `max_failures` times is given
up (`failed`), as is one still there when a robot looked at it from where it stands
(the exploration manager's cleanup). And when the whole team is stuck, `stall_steps`
exploration steps in a row in which no robot flies or got a path, every frontier left is
given up (`note_progress`): robots that hold one another, each keeping the margin from
where the others hover, would otherwise hover until the mission's end (random:1 seed 3:
98 % of the area known at 70 s, then 230 s of hovering). Nothing changes while all
hover (the same map and poses get the same answers), so waiting longer is no use;
unless a robot has gone silent (its link lost): it may be flying on, its scans held in
its outbox until the link is back, so the team waits `silent_stall_steps` for it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

log = logging.getLogger(__name__)


@dataclass
class FrontierGiveUp:
    max_failures: int = 8  # failed plans before a frontier is given up
    radius_m: float = 0.6  # m: goals this close count as the same frontier
    stall_steps: int = 5  # steps in a row with no robot moving: what is left is given up
    silent_stall_steps: int = 60  # ... while a robot is silent (1 min at 1 step/s)
    failures: list[tuple[NDArray[np.float64], int]] = field(default_factory=list)
    stalled: int = 0  # steps in a row so far
    started: bool = False  # a robot has moved (before that, the first map is still coming)

    def given_up(self, goal: ArrayLike) -> bool:
        g0 = np.asarray(goal, dtype=np.float64)
        return any(
            n >= self.max_failures and np.hypot(*(g0 - g)) < self.radius_m for g, n in self.failures
        )

    def failed(self, goal: ArrayLike, count: int = 1) -> None:
        """One more failure (`count`; `max_failures`: give it up now) at `goal`."""
        g0 = np.asarray(goal, dtype=np.float64)
        for k, (g, n) in enumerate(self.failures):
            if np.hypot(*(g0 - g)) < self.radius_m:
                self.failures[k] = (g, n + count)
                return
        self.failures.append((g0.copy(), count))

    def note_progress(
        self, moving: bool, goals: list[NDArray[np.float64]], silent: bool = False
    ) -> None:
        """After an exploration step: `moving`, whether any robot flies or got a path;
        `goals`, the frontiers left (all given up once the team stalled); `silent`,
        whether a robot is silent (module doc)."""
        self.started |= moving
        self.stalled = 0 if moving or not goals or not self.started else self.stalled + 1
        if self.stalled >= (self.silent_stall_steps if silent else self.stall_steps):
            log.warning("no robot could move for %d steps: %d frontiers given up",
                        self.stalled, len(goals))  # fmt: skip
            for g in goals:
                self.failed(g, self.max_failures)
            self.stalled = 0
