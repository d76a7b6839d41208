"""Whole-map search targets and jobs (Cartographer's global localization, both ways).

A robot whose start is unknown has its recent scans searched against the whole map;
a robot on the map has its recent scans searched against each floating map (a robot,
or robots joined to each other, not on the map yet), since the floating robot's own
searches only ever try its newest scans. `WholeMapSearch` keeps one target per map
(the robots' scans placed in their frame), rebuilt when robots join it or it has
grown by a quarter (at least `global_query_keyframes`, at most
`global_map_rebuild_nodes` nodes), builds the jobs, and turns a verified match into a
tie to the target's nearest node as it stood when the search was queued (a join or
correction in between does not bend it).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from basestation.constraint_builder import Job
from basestation.scan_verifier import VerifiedMatch
from common.config import ConstraintConfig
from common.geometry import se2_between, se2_transform_points

NodeKey = tuple[str, int]
# (key, nodes, poses) -> the nodes' points and poses in key's frame, and key's own length
QueryFn = Callable[
    [NodeKey, list[NodeKey], dict[str, np.ndarray]], tuple[list[np.ndarray], list[np.ndarray], int]
]


@dataclass(frozen=True)
class _MapTarget:
    key: tuple[tuple[str, ...], int]  # (robots, their nodes when it was built)
    nodes: list[NodeKey]
    scans: list[np.ndarray]  # (n_i, 2) float32, frame of the map
    origins: list[np.ndarray]  # each node's pose then


class WholeMapSearch:
    def __init__(self, cc: ConstraintConfig, points: Callable[[str, int], np.ndarray]) -> None:
        self.cc = cc
        self._points = points  # a node's scan points in its own frame
        self._targets: dict[tuple[str, ...], _MapTarget] = {}  # by the map's robots
        self._map_nodes_unsearched = 0  # map nodes since the last search of floating maps

    def _rebuild_step(self, n_built: int) -> int:
        """New map nodes before a target built from `n_built` nodes is rebuilt: a quarter
        of its size, at least `global_query_keyframes`, at most
        `global_map_rebuild_nodes`. A fixed step of 200 kept a target built from the
        map's first few nodes until it had 200 (ACES replays where the first segment
        lagged: the middle one searched a map of a few dozen nodes for minutes, found
        nothing, and never joined)."""
        cc = self.cc
        return min(cc.global_map_rebuild_nodes, max(cc.global_query_keyframes, n_built // 4))

    def floating_due(self) -> bool:
        """Count a node added to the map; True once per `global_query_keyframes` of them
        (of all its robots together: the load does not grow with the team)."""
        self._map_nodes_unsearched += 1
        if self._map_nodes_unsearched < self.cc.global_query_keyframes:
            return False
        self._map_nodes_unsearched = 0
        return True

    def job(
        self, key: NodeKey, poses: dict[str, np.ndarray], frame: list[str], query: QueryFn,
        check: bool = False,
    ) -> Job | None:  # fmt: skip
        """A search of robot key[0]'s recent scans against the whole map of the robots in
        ``frame`` (None if it has none); `check`: of a robot on that map, whose join is
        checked (basestation/join_check.py: it is matched where the map has it, too)."""
        robots = tuple(sorted(r for r in frame if r != key[0] and len(poses.get(r, ()))))
        if not robots:
            return None
        n = sum(len(poses[r]) for r in robots)
        target = self._targets.get(robots)
        if target is None or n >= target.key[1] + self._rebuild_step(target.key[1]):
            map_key = (robots, n)
            nodes = [(r, i) for r in robots for i in range(len(poses[r]))]
            scans = [
                se2_transform_points(poses[r][i], self._points(r, i)).astype(np.float32)
                for r, i in nodes
            ]
            target = _MapTarget(map_key, nodes, scans, [poses[r][i] for r, i in nodes])
            for k in [k for k in self._targets if set(k) & set(robots)]:  # older versions
                del self._targets[k]
            self._targets[robots] = target
        first = max(0, key[1] - self.cc.global_query_keyframes + 1)
        recent = [(key[0], j) for j in range(first, key[1] + 1)]
        q_points, q_origins, n_own = query(key, recent, poses)
        at = np.array(poses[key[0]][key[1]]) if check else None
        return Job("global", key, key, np.zeros(3), target.scans, q_points, target.origins,
                   n_own, target_key=target.key, in_node_frames=True, query_origins=q_origins,
                   target_nodes=target.nodes, check_at=at)  # fmt: skip


def tie(job: Job, m: VerifiedMatch) -> tuple[NodeKey, np.ndarray]:
    """A verified whole-map match as (target node, T_node_b): the target's node nearest
    to where the match puts b, as it stood when the search was queued."""
    assert job.target_nodes is not None and job.target_origins is not None
    origins = np.asarray(job.target_origins)
    i = int(np.argmin(np.hypot(*(origins[:, :2] - m.T_a_b[:2]).T)))
    return job.target_nodes[i], se2_between(origins[i], m.T_a_b)
