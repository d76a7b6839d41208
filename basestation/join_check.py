"""Checks a robot's join to the map over its first keyframes after it.

A robot whose start is unknown is joined to the map by `min_consistent_to_merge`
agreeing matches (basestation/loop_closure_manager.py). In a floor of identical rooms
all of them can put it in the wrong room, and once it was on the map its whole-map
search stopped: it stayed there for good, silently (a drone starting in the third of
four identical rooms, joined to the first: 12.8 m off, map accuracy 0.995). So for
`join_check_keyframes` keyframes after a join, every `global_search_every`-th keyframe
of the robot is still searched against the whole map of the others
(basestation/whole_map_search.py), and matched where the join put it too. A match
that puts the robot's node within `merge_agree_m` and `merge_agree_rad` of its
estimate agrees with the join; one farther contradicts it if it scores `SCORE_MARGIN`
above the match where the join put it, or that one fails (else both places fit: places
alike, no evidence either way). When the robot's latest results are contradicting
matches, with no agreeing one among them, that put it in one place (its newest node
within `merge_agree_m` / `merge_agree_rad`) from `min_consistent_to_merge` stretches
of `merge_stretch_keyframes` keyframes (the rule that joins maps), the join is undone:
an error line names the robot, its inter-robot matches leave the graph and are
forgotten (`LoopClosureManager.unlink`; it floats again), and the contradicting matches
are offered as new ones, which join it where they put it (the merge rule decides; the
new join is checked in turn). A join that cannot be undone (one of its matches left
PCM's window: final) is logged as an error and stays; basestation.json and
summary.json count both per robot (`joins_undone`, `join_contradicted`).

An undo is stored with the matches (`LoopClosureManager.unlink`: kind "unlink"): a
restarted base station replays the matches and the undo in the order they came
(`replay_undo`), so the robot is where the live one had it, and watches the joins it
replays as they are made (a check still running goes on; its evidence starts afresh).
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable, Container
from dataclasses import dataclass, field

import numpy as np

from basestation.constraint_builder import ConstraintBuilder, Job, Verified
from basestation.loop_closure_manager import LoopClosureManager
from basestation.pose_graph import PoseGraph
from basestation.whole_map_search import tie
from common.config import ConstraintConfig
from common.geometry import se2_compose, se2_inverse, wrap_angle

log = logging.getLogger(__name__)

NodeKey = tuple[str, int]
# A match elsewhere contradicts a join only if it scores this much above the robot's
# scans matched where the join put it (or those fail verification there): in identical
# rooms both scored 0.97-1.0 inside a room, and 0.98-1.0 against 0.77-0.84 or failing
# once it was out in the corridor.
SCORE_MARGIN = 0.05


@dataclass
class _Contradiction:
    node: int  # the robot's node searched
    shift: np.ndarray  # the map frame's move the match asks for (T_new_old)
    match: tuple[NodeKey, NodeKey, np.ndarray, np.ndarray]  # (map node, node, T, cov)


@dataclass
class _Watch:
    until: int  # the robot's last keyframe checked
    # contradictions since the last agreeing match
    against: list[_Contradiction] = field(default_factory=list)
    agreed: int = 0


class JoinCheck:
    def __init__(
        self,
        cc: ConstraintConfig,
        graph: PoseGraph,
        loops: LoopClosureManager,
        own_start: Container[str],
        builder: ConstraintBuilder | None,
    ) -> None:
        """`own_start`: robots placed by a start of their own (known, or GNSS), not
        joined by matches (a live set: read at each `watch`)."""
        self.cc, self.graph, self.loops, self.own_start = cc, graph, loops, own_start
        self.builder = builder
        self._floating: set[str] = set()  # robots seen off the map
        self.watched: dict[str, _Watch] = {}
        self.undone: Counter[str] = Counter()  # joins undone, per robot
        self.kept: set[str] = set()  # robots whose contradicted join could not be undone

    def watch(self) -> None:
        """Note the robots joined to the map since the last call: watched from now on."""
        for r in self.graph.robots():
            if not self.graph.num_nodes(r):
                continue
            if not self.graph.is_anchored(r):
                self._floating.add(r)
                self.watched.pop(r, None)
            elif r in self._floating:
                self._floating.discard(r)
                n = self.cc.join_check_keyframes
                if n > 0 and r not in self.own_start:
                    self.watched[r] = _Watch(self.graph.num_nodes(r) - 1 + n)

    def due(self, key: NodeKey) -> bool:
        """Whether the new node `key` of a robot on the map is searched against the map."""
        w = self.watched.get(key[0])
        if w is None:
            return False
        if key[1] > w.until:
            del self.watched[key[0]]
            log.debug(
                "robot %s: its join held for %d keyframes", key[0], self.cc.join_check_keyframes
            )
            return False
        return key[1] % self.cc.global_search_every == 0

    def takes(self, job: Job) -> bool:
        """Whether a verified whole-map search is one of these checks (queued as one, of a
        robot on the map: one floating again since is searched for as such)."""
        return job.check_at is not None and self.graph.is_anchored(job.b[0])

    def result(self, v: Verified) -> str | None:
        """Weigh a check's match; the robot if its join was undone now."""
        job, m = v.job, v.match
        rid = job.b[0]
        if (w := self.watched.get(rid)) is None:
            return None  # (its watch is over)
        a, T_a_b = tie(job, m)
        put = se2_compose(self.graph.pose(*a), T_a_b)
        est = self.graph.pose(*job.b)
        if self._close(put, est):
            w.against, w.agreed = [], w.agreed + 1
            return None
        log.debug("robot %s: node %d matched %.1f m from where its join put it (score %.3f; "
                  "%s where the join put it)", rid, job.b[1], float(np.hypot(*(put[:2] - est[:2]))),
                  m.score, "none" if v.here is None else f"{v.here.score:.3f}")  # fmt: skip
        if v.here is not None and v.here.score >= m.score - SCORE_MARGIN:
            return None  # it fits about as well where the join put it: places alike
        shift = se2_compose(put, se2_inverse(est))
        w.against.append(_Contradiction(job.b[1], shift, (a, job.b, T_a_b, m.covariance)))
        newest = self.graph.poses(rid)[-1]
        there = se2_compose(shift, newest)
        same = [c for c in w.against if self._close(se2_compose(c.shift, newest), there)]
        if self._stretches([c.node for c in same]) < self.cc.min_consistent_to_merge:
            return None
        del self.watched[rid]
        return rid if self._undo(rid, w, same, newest, there) else None

    def _undo(
        self, rid: str, w: _Watch, same: list[_Contradiction], newest: np.ndarray,
        there: np.ndarray,
    ) -> bool:  # fmt: skip
        moved = float(np.hypot(*(there[:2] - newest[:2])))
        n = self.loops.unlink(rid)
        if n is None or self.graph.is_anchored(rid):
            self.kept.add(rid)
            log.error("robot %s: %d whole-map matches put it %.1f m from where its join to "
                      "the map did, but the join is final: it stays (its map and "
                      "trajectory may be wrong)", rid, len(same), moved)  # fmt: skip
            return False
        self.undone[rid] += 1
        self._floating.add(rid)
        log.error("robot %s: %d whole-map matches put it %.1f m from where its join to the "
                  "map did (%d agreed since the join): the join is undone (%d matches "
                  "taken out), it is placed again", rid, len(same), moved, w.agreed, n)  # fmt: skip
        if self.builder is not None:  # (candidates searched where it is not)
            self.builder.cancel_inter(rid)
        self.graph.update()  # it floats: its own gauge prior, before the matches move it
        for a, b, T_a_b, cov in (c.match for c in same):
            self.loops.add(a, b, T_a_b, cov, "inter")
        return True

    def settled(
        self, T_map_odom: Callable[[str], np.ndarray | None]
    ) -> Callable[[str], np.ndarray | None]:
        """`T_map_odom` for the segments whose join is no longer checked: a later run of a
        robot starts where its run before it is on the map (basestation/robot_segments.py)
        only once that one's join has held, else it floats and is joined (and checked)
        as one of unknown start: started from a wrong join, it had stayed there for good,
        unchecked (identical rooms: 6.1 m off)."""
        return lambda s: None if s in self.watched else T_map_odom(s)

    def replay_undo(self, rid: str, measurement_id: int) -> None:
        """A stored undo, replayed by a restart (basestation/slam_restore.py)."""
        if self.loops.unlink(rid, measurement_id) is not None:
            self.undone[rid] += 1
            self.graph.update()  # it floats, as live before the matches that moved it

    def _close(self, p: np.ndarray, q: np.ndarray) -> bool:
        return bool(
            np.hypot(*(p[:2] - q[:2])) <= self.cc.merge_agree_m
            and abs(wrap_angle(p[2] - q[2])) <= self.cc.merge_agree_rad
        )

    def _stretches(self, nodes: list[int]) -> int:
        """How many of the nodes are `merge_stretch_keyframes` apart along the chain."""
        count, last = 0, None
        for i in sorted(nodes):
            if last is None or i - last >= self.cc.merge_stretch_keyframes:
                count, last = count + 1, i
        return count

    def stats(self, rid: str) -> dict[str, int | bool]:
        return {"joins_undone": self.undone[rid], "join_contradicted": rid in self.kept}


def newly_joined(
    num_nodes: Callable[[str], int], before: dict[str, frozenset[str]], frames: list[list[str]]
) -> list[tuple[str, str]]:
    """Pairs of robots that had nodes at the last search (`before`: each robot's frame
    then), each in a different frame then and in one of `frames` now (the pair's robot
    with fewer nodes first)."""
    pairs = []
    for comp in frames:
        for i, a in enumerate(comp):
            for b in comp[i + 1 :]:
                if a in before and b in before and b not in before[a]:
                    pairs.append((a, b) if num_nodes(a) <= num_nodes(b) else (b, a))
    return pairs


def apart(together: dict[str, frozenset[str]], robot: str) -> dict[str, frozenset[str]]:
    """`together` (each robot's frame at the last search) with `robot` alone: its join
    was undone, so joining it again is a new join (`newly_joined`: its backfill runs)."""
    return {r: f - {robot} for r, f in together.items()} | {robot: frozenset({robot})}
