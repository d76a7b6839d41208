"""Pose graphs flown round a circle, for the reduction tests."""

from __future__ import annotations

import numpy as np

from basestation.pose_graph import PoseGraph
from common.geometry import se2_between

ODOM_COV = np.diag([1e-4, 1e-4, 1e-5])
LOOP_COV = np.diag([1e-3, 1e-3, 1e-4])
RADIUS, STEP = 5.0, 0.2
LAP = int(2 * np.pi * RADIUS / STEP)  # nodes per lap of the circle


def circle(i: int) -> np.ndarray:
    th = 2 * np.pi * i / LAP
    return np.array([RADIUS * np.sin(th), RADIUS - RADIUS * np.cos(th), th])


def fly_laps(graph: PoseGraph, laps: int, seed: int = 0, robot: str = "a") -> np.ndarray:
    """Laps of a circle with noisy odometry and a loop closure to lap 0 every 5 nodes
    (from lap 1 on), one update per node; returns the true poses."""
    rng = np.random.default_rng(seed)
    truth = [circle(i) for i in range(laps * LAP)]
    for i, p in enumerate(truth):
        if i == 0:
            graph.add_node(robot, 0, None, None)
        else:
            d = se2_between(truth[i - 1], p) + rng.normal(0, [0.01, 0.01, 0.001])
            graph.add_node(robot, i, d, ODOM_COV)
        if i >= LAP and i % 5 == 0:
            j = i % LAP
            T = se2_between(truth[j], p) + rng.normal(0, [0.01, 0.01, 0.001])
            graph.add_constraint((robot, j), (robot, i), T, LOOP_COV)
        graph.update()
    return np.array(truth)


def variables(graph: PoseGraph) -> int:
    return graph._isam.calculateEstimate().size()


def odometry_factors(graph: PoseGraph) -> int:
    return sum(r.kind == "odometry" for r in graph._factors.values())


def fly_with_window(graph: PoseGraph, laps: int, window: int | None, spread: int = 1) -> np.ndarray:
    """fly_laps, with each loop closure tied to the lap-0 node 2 m further on (so its two
    ends stay apart, on two variables; ``spread`` > 1: 2 m + 0.2 m x (0 .. spread - 1)
    in turn), and finalized ``window`` nodes after it was added (None: never), as
    LoopClosureManager finalizes the matches that leave PCM's window."""
    rng = np.random.default_rng(4)
    truth = [circle(i) for i in range(laps * LAP)]
    added: list[tuple[int, int]] = []  # (node, factor id)
    for i, p in enumerate(truth):
        d = None if i == 0 else se2_between(truth[i - 1], p) + rng.normal(0, [0.01, 0.01, 0.001])
        graph.add_node("a", i, d, None if i == 0 else ODOM_COV)
        if i >= LAP and i % 5 == 0:
            j = (i + 10 + (i // 5) % spread) % LAP
            T = se2_between(truth[j], p) + rng.normal(0, [0.01, 0.01, 0.001])
            added.append((i, graph.add_constraint(("a", j), ("a", i), T, LOOP_COV)))
        while window is not None and added and added[0][0] <= i - window:
            graph.finalize_constraint(added.pop(0)[1])
        graph.update()
    return np.array(truth)
