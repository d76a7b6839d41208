"""Evaluation only: wrong matches injected among the verified ones, so that outlier
rejection (PCM, the lone-match check, robust kernels) can be measured
(`basestation.constraints.false_match_fraction`, `eval carmen`)."""

from __future__ import annotations

import numpy as np

from basestation.constraint_builder import Verified
from basestation.loop_closure_manager import LoopClosureManager
from basestation.pose_graph import PoseGraph
from common.config import ConstraintConfig


class FalseMatches:
    def __init__(self, cc: ConstraintConfig, graph: PoseGraph, loops: LoopClosureManager) -> None:
        self.cc = cc
        self.graph = graph
        self.loops = loops
        self.rng = np.random.default_rng(cc.false_match_seed)

    def after(self, v: Verified) -> None:
        """After each verified match, a wrong one with probability f / (1 - f), so that a
        fraction f of all matches is false (f = 0: never)."""
        f = self.cc.false_match_fraction
        if f > 0 and self.rng.random() < f / (1.0 - f):
            self.inject(v)

    def inject(self, v: Verified) -> None:
        """A wrong match like perceptual aliasing produces. The query node is said to be
        within a metre of a random other node of the same kind (same robot for a loop,
        another anchored robot otherwise), with the real match's covariance."""
        rng = self.rng
        b = v.job.b
        if v.job.kind == "loop":
            n = max(0, b[1] - self.cc.loop_min_index_gap)
            robot = b[0]
        else:
            others = [r for r in self.graph.robots() if r != b[0] and self.graph.is_anchored(r)]
            robot = others[int(rng.integers(len(others)))] if others else b[0]
            n = self.graph.num_nodes(robot) if robot != b[0] else 0
        if n < 1:
            return
        a = (robot, int(rng.integers(n)))
        T = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(-np.pi / 4, np.pi / 4)])
        self.loops.add(a, b, T, v.match.covariance, "false")
