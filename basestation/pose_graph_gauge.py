"""Which robots share a frame, and the gauge prior that holds each floating frame.

Gauge (how disjoint chains stay well-posed): the graph is split into connected
components of robots (linked by inter-robot constraints). A component containing a
robot with a known start is held by those start priors alone. A floating component
gets exactly one *gauge prior* (``prior_sigmas``) on the first node of its
earliest-registered robot, at that node's current estimate: it fixes the
component's own frame and carries no information. When a constraint joins
components, surplus gauge priors are removed in the same update (so the merge is
not biased) and extra iterations let the moved chain settle; if removing a
constraint splits a component again, a gauge prior is re-added. Before a join, the
caller may first move the floating component rigidly to where the joining
constraints put it (``move_floating``): Gauss-Newton from a frame half a turn off
settled a 600-node ACES segment into a bent minimum.

Package-internal: a mixin of ``basestation.pose_graph.PoseGraph``.
"""

from __future__ import annotations

import logging
from collections import Counter
from typing import TYPE_CHECKING

import gtsam
import numpy as np

from basestation.pose_graph_state import FloatArray, PoseGraphState, pose2
from common.geometry import se2_compose, se2_inverse

logger = logging.getLogger(__name__)


class GaugeMixin(PoseGraphState):
    """Robot components (cached per topology version) and their gauge priors."""

    if TYPE_CHECKING:  # provided by PoseGraph

        def pose(self, robot_id: str, index: int) -> FloatArray: ...

        def update(self, extra_iterations: int = 0) -> object: ...

    def _init_gauges(self) -> None:
        self._pair_count: Counter[tuple[str, str]] = Counter()  # inter-robot constraints
        # robot pairs tied for good: a node of one is an alias of the other's variable
        self._alias_ties: set[tuple[str, str]] = set()
        self._topology_dirty = False
        self._topology_version = 0  # bumped on every change of the robots' grouping
        self._components_cache: tuple[int, list[list[str]]] = (-1, [])
        self._component_of: dict[str, int] = {}  # robot -> component label at last update

    def components(self) -> list[list[str]]:
        """Robots grouped by inter-robot constraints (including pending ones); within a
        group, poses share one frame. Robots with no node yet are not listed."""
        return [list(c) for c in self._components()]

    def is_anchored(self, robot_id: str) -> bool:
        """True if the robot's group contains a robot with a known start (the map frame)."""
        for comp in self._components():
            if robot_id in comp:
                return any(self._chains[r].T_map_first is not None for r in comp)
        return False

    def _topology_changed(self) -> None:
        """The robots' grouping may have changed: regroup, and reconcile at the next update."""
        self._topology_dirty = True
        self._topology_version += 1

    def _components(self) -> list[list[str]]:
        """Cached until the grouping changes (queried per robot after every update);
        callers must not modify the lists."""
        version, cached = self._components_cache
        if version != self._topology_version:
            cached = self._compute_components()
            self._components_cache = (self._topology_version, cached)
        return cached

    def _compute_components(self) -> list[list[str]]:
        parent = {rid: rid for rid, c in self._chains.items() if c.size > 0}

        def find(r: str) -> str:
            while parent[r] != r:
                parent[r] = parent[parent[r]]
                r = parent[r]
            return r

        for (a, b), count in self._pair_count.items():
            if count > 0:
                parent[find(a)] = find(b)
        for a, b in self._alias_ties:  # even if PCM removed every constraint between them
            parent[find(a)] = find(b)
        groups: dict[str, list[str]] = {}
        for rid in parent:  # registration order inside each group
            groups.setdefault(find(rid), []).append(rid)
        return list(groups.values())

    def _reconcile_gauges(self) -> bool:
        """Give each floating component exactly one gauge prior; True if components merged."""
        components = self._components()
        merged = any(
            len({self._component_of.get(r, -1 - i) for i, r in enumerate(component)}) > 1
            for component in components
        )
        self._component_of = {r: n for n, comp in enumerate(components) for r in comp}
        for component in components:
            anchored = any(self._chains[r].T_map_first is not None for r in component)
            holders = [r for r in component if self._chains[r].gauge_factor is not None]
            keep = None if anchored else (holders[0] if holders else component[0])
            for rid in holders:
                chain = self._chains[rid]
                if rid != keep and chain.gauge_factor is not None:
                    self._drop_factor(chain.gauge_factor)
                    chain.gauge_factor = None
                    logger.debug("robot %r merged into another frame: gauge removed", rid)
            if keep is not None and self._chains[keep].gauge_factor is None:
                chain = self._chains[keep]
                prior = gtsam.PriorFactorPose2(
                    gtsam.symbol(chain.char, 0), pose2(self.pose(keep, 0)), self._prior_noise
                )
                chain.gauge_factor = self._add_factor(prior, "gauge")
        self._topology_dirty = False
        return merged

    def move_floating(self, robot_id: str, T_new_old: FloatArray, iterations: int = 30) -> bool:
        """Move the floating component of ``robot_id`` rigidly by ``T_new_old`` (its new
        frame from its current one): its gauge prior is put at the moved pose and the
        component relinearized there (at most ``iterations`` steps; none of its own
        factors change, so it only turns and shifts). False if it is not floating."""
        comp = next((c for c in self._components() if robot_id in c), [robot_id])
        holder = next((r for r in comp if self._chains[r].gauge_factor is not None), None)
        if holder is None or any(self._chains[r].T_map_first is not None for r in comp):
            return False
        chain = self._chains[holder]
        assert chain.gauge_factor is not None
        self._drop_factor(chain.gauge_factor)
        target = se2_compose(T_new_old, self.pose(holder, 0))
        prior = gtsam.PriorFactorPose2(
            gtsam.symbol(chain.char, 0), pose2(target), self._prior_noise
        )
        chain.gauge_factor = self._add_factor(prior, "gauge")
        self.update(extra_iterations=iterations)
        return True

    def georeference(
        self, robot_id: str, start: FloatArray, start_sigmas: FloatArray, iterations: int = 30
    ) -> bool:
        """Give a floating chain the loose start prior it would have had (GNSS: a robot's
        first fix came after its first keyframe): its component is first moved rigidly
        so that the robot's first node is at `start` ([x, y, yaw]); the chain then counts
        as anchored and the gauge prior goes. False if it is not floating."""
        chain = self._chains[robot_id]
        if not chain.size or self.is_anchored(robot_id):
            return False
        self.move_floating(robot_id, se2_compose(start, se2_inverse(self.pose(robot_id, 0))),
                           iterations)  # fmt: skip
        chain.T_map_first = np.array(start, dtype=np.float64)
        chain.start_sigmas = np.array(start_sigmas, dtype=np.float64)
        noise = gtsam.noiseModel.Diagonal.Sigmas(chain.start_sigmas)
        prior = gtsam.PriorFactorPose2(gtsam.symbol(chain.char, 0), pose2(start), noise)
        self._add_factor(prior, "start")
        self._topology_changed()  # anchored now: the gauge prior goes at the next update
        return True
