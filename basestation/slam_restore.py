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

from basestation.persistence import Batch, Fix, Recovered, StoredConstraint
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
    the graph optimized before and after, as when they were first added; and the joins
    to the map undone between them (kind "unlink")."""
    slam.optimize()
    for c in stored:
        m = c.measurement
        if c.kind == "unlink":  # a join undone there (basestation/join_check.py)
            slam.join_check.replay_undo(m.robot_a, m.id)
            continue
        try:
            slam.loops.add(
                (m.robot_a, m.index_a), (m.robot_b, m.index_b), m.T_a_b,
                m.covariance, c.kind, measurement_id=m.id,
            )  # fmt: skip
        except CollabSlamError as e:
            log.error("stored match %d not restored: %s", m.id, e)
    slam._constraints_added = bool(stored)  # the forced relinearization, as when live
    slam.optimize()


def restore(slam: GlobalSlam, rec: Recovered) -> None:
    """Rebuild `slam`'s graph from the database: GNSS fixes, keyframes and stored matches
    are replayed through the same paths (admission, loop-closure manager and PCM) in the
    order they were first taken (`replay_order`); the graph is optimized before each
    batch of matches, as it was then. Stored matches are not verified again."""
    slam._stored_starts = dict(rec.chain_starts)
    for kind, items in replay_order(rec):
        if kind == "fixes":
            for fix in items:
                slam.add_gps_fix(*fix)
        elif kind == "matches":
            replay_matches(slam, items)
        else:
            for kf in items:
                if slam.admit(kf, replay=True) == 0:
                    log.error("stored keyframe %s/%d not admitted", kf.robot_id, kf.seq)
            slam.saved(Batch(items))  # on disk already: the scans may leave memory, and
            slam._unsaved.clear()  # the journal need not keep the keyframes till the end
        slam.join_check.watch()  # joins to the map made as live: checked from there on
    slam.optimize()
    slam._new_nodes.clear()  # their candidates were searched before the crash
    slam.backfilled = set(rec.backfilled)
    slam._together = together_after_restore(slam, rec.backfilled)
    slam.take_journal()  # all of it is on disk already
    accepted = slam.loops.accepted
    differ = sum(
        c.in_graph != (c.measurement.id in accepted) for c in rec.constraints if c.kind != "unlink"
    )
    if differ:
        log.warning("%d restored matches changed in/out of the graph on replay", differ)


def together_after_restore(
    slam: GlobalSlam, backfilled: set[tuple[str, str]]
) -> dict[str, frozenset[str]]:
    """Each robot with the robots it shares a map with and is done with: started known
    on the map together, or joined with its backfill verified (`persistence`,
    `backfilled`). The first search joins the others again and queues their backfill:
    the jobs of a join were lost with a crash before they were verified (the chain
    flown before it hung on its odometry), and a done one had been queued again at
    every restart (up to `backfill_max_candidates` jobs a pair)."""
    known = {r for r in slam.graph.robots() if r in slam.known_starts}
    out = {}
    for frame in slam._frames(slam.graph.components()):
        for r in frame:
            out[r] = frozenset(
                o for o in frame
                if o == r or (r in known and o in known) or (min(r, o), max(r, o)) in backfilled
            )  # fmt: skip
    return out
