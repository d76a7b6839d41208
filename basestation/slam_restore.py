"""The order a restart replays the database in (`GlobalSlam.restore`): batch by batch as
first written, and within a batch as the base station took them then: its GNSS fixes
(the node takes them before the keyframes: a robot's first keyframe may start at its
latest fix), its keyframes, then its matches. Keyframes are read as it goes
(`persistence.StoredKeyframes`), never all held at once."""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Iterator
from itertools import groupby
from operator import itemgetter
from typing import TYPE_CHECKING, Any

from basestation.persistence import Fix, Recovered, StoredConstraint
from common.errors import CollabSlamError

if TYPE_CHECKING:
    from basestation.global_slam import GlobalSlam

log = logging.getLogger(__name__)


def replay_order(rec: Recovered) -> Iterator[tuple[str, list[Any]]]:
    """("fixes", [Fix]), ("keyframes", [Keyframe]) and ("matches", [StoredConstraint]), in
    the order they were first taken."""
    matches: dict[int, list[StoredConstraint]] = {}
    for c in rec.constraints:
        matches.setdefault(c.batch, []).append(c)
    fixes: dict[int, list[Fix]] = {}
    for b, f in rec.fixes:
        fixes.setdefault(b, []).append(f)
    rest = deque(sorted(set(matches) | set(fixes)))  # batches with fixes or matches

    def batch(b: int, keyframes: list[Any] | None = None) -> Iterator[tuple[str, list[Any]]]:
        while rest and rest[0] <= b:
            rest.popleft()
        if b in fixes:
            yield "fixes", fixes.pop(b)
        if keyframes is not None:
            yield "keyframes", keyframes
        if b in matches:
            yield "matches", matches.pop(b)

    for b, group in groupby(rec.keyframes, key=itemgetter(0)):
        while rest and rest[0] < b:  # batches without keyframes
            yield from batch(rest[0])
        yield from batch(b, [kf for _, kf in group])
    while rest:
        yield from batch(rest[0])


def replay_matches(slam: GlobalSlam, stored: list[StoredConstraint]) -> None:
    """One batch's stored matches through the loop-closure manager (not verified again),
    the graph optimized before and after, as when they were first added."""
    slam.optimize()
    for c in stored:
        m = c.measurement
        try:
            slam.loops.add(
                (m.robot_a, m.index_a), (m.robot_b, m.index_b), m.T_a_b,
                m.covariance, c.kind, measurement_id=m.id,
            )  # fmt: skip
        except CollabSlamError as e:
            log.error("stored match %d not restored: %s", m.id, e)
    slam._constraints_added = bool(stored)  # the forced relinearization, as when live
    slam.optimize()
