"""Inter-robot search, with the real verifier on ray-cast scans of a shipped floor
plan: when two robots' maps are joined, the nodes one of them flew before the join
are searched against the other robot (GlobalSlam._backfill); robots with known starts
are searched against each other from the start."""

from __future__ import annotations

import numpy as np
from process_helpers import poll_until

from basestation.global_slam import GlobalSlam
from common.config import Config
from common.geometry import pose4_to_pose7, se2_between
from protocol import Keyframe, Scan2D
from simulation.raycast import cast_rays
from simulation.world import World

BEAMS = 360
RANGE_MAX = 30.0


def _keyframes(world: World, robot: str, truth: np.ndarray) -> list[Keyframe]:
    """Keyframes of a robot flying the true poses ``truth`` (N, 3), in its own odom
    frame (its first pose is the odom origin), with exact odometry."""
    angles = np.linspace(-np.pi, np.pi, BEAMS, endpoint=False)
    out = []
    for i, T in enumerate(truth):
        ranges = cast_rays(
            world.occupied, world.resolution, world.origin_xy, T, angles, RANGE_MAX,
            world.ray_blocks,
        )  # fmt: skip
        odom = se2_between(truth[0], T)
        delta = se2_between(truth[i - 1], T) if i else np.zeros(3)
        out.append(
            Keyframe(
                robot,
                i,
                0.5 * i,
                pose4_to_pose7([odom[0], odom[1], 1.0, odom[2]]),
                pose4_to_pose7([delta[0], delta[1], 0.0, delta[2]]),
                np.diag([1e-4, 1e-4, 1e-4, 1e-4, 1e-4, 1e-5]),
                Scan2D.from_ranges(angles[0], angles[1] - angles[0], RANGE_MAX, ranges),
                None,
            )
        )
    return out


def _settle(slam: GlobalSlam) -> None:
    """Verify everything queued, hand the matches over, optimize, search again."""
    for _ in range(5):
        assert poll_until(slam.idle, timeout=60.0)
        slam.integrate_constraints()
        slam.optimize()
        slam.search_constraints()
    assert poll_until(slam.idle, timeout=60.0)


def test_nodes_flown_before_a_join_are_matched_against_the_other_robot() -> None:
    world = World.load("floor30x25")
    n = 37  # 0.5 m apart along the corridor at y = 6 m
    xs = 1.5 + 0.5 * np.arange(n)
    truth_a = np.column_stack([xs, np.full(n, 6.0), np.zeros(n)])
    truth_b = truth_a + [0.0, 0.1, 0.02]
    cfg = Config()
    cfg.basestation.constraints.global_min_score = 1.0  # b cannot join by global search
    slam = GlobalSlam(cfg, known_starts={"a": truth_a[0]})
    try:
        for kf in _keyframes(world, "a", truth_a) + _keyframes(world, "b", truth_b):
            assert slam.admit(kf) == 1
        slam.optimize()
        slam.search_constraints()
        _settle(slam)
        assert not slam.graph.is_anchored("b")

        # three verified matches near b's end join the maps, as a real late join does
        cov = np.diag([1e-3, 1e-3, 1e-4])
        for j in (n - 1, n - 6, n - 11):
            slam.loops.add(("a", j), ("b", j), se2_between(truth_a[j], truth_b[j]), cov, "inter")
        slam.optimize()
        assert slam.graph.is_anchored("b")
        submitted = slam.builder.stats["submitted_inter"]
        slam.search_constraints()
        assert slam.builder.stats["submitted_inter"] - submitted >= 5  # b's earlier nodes
        _settle(slam)
    finally:
        slam.close()

    group = slam.loops.groups[("a", "b")]
    early = [
        m for i, m in group.measurements.items() if i in slam.loops.accepted and m.index_b < n - 11
    ]
    assert len(early) >= 5, f"only {len(early)} accepted matches on b's earlier nodes"
    for m in early:  # each agrees with the truth
        true = se2_between(truth_a[m.index_a], truth_b[m.index_b])
        assert np.hypot(*(m.T_a_b[:2] - true[:2])) < 0.1
    P = slam.graph.poses("b")
    assert np.abs(P[:, :2] - truth_b[:, :2]).max() < 0.1


def test_robots_with_known_starts_get_inter_robot_constraints() -> None:
    """Both starts known: the two chains are in `map` from their first node, though no
    constraint joins them yet, so a node is searched against the other robot too (it
    was searched against its own chain only, and such robots never got one)."""
    world = World.load("floor30x25")
    n = 37
    xs = 1.5 + 0.5 * np.arange(n)
    truth_a = np.column_stack([xs, np.full(n, 6.0), np.zeros(n)])
    truth_b = truth_a + [0.0, 0.1, 0.02]
    slam = GlobalSlam(Config(), known_starts={"a": truth_a[0], "b": truth_b[0]})
    try:
        for kf in _keyframes(world, "a", truth_a) + _keyframes(world, "b", truth_b):
            assert slam.admit(kf) == 1
        assert len(slam.graph.components()) == 2
        slam.optimize()
        slam.search_constraints()
        assert slam.builder.stats["submitted_inter"] >= 5
        _settle(slam)
    finally:
        slam.close()
    assert slam.loops.counts()["inter_robot_constraints"] >= 2
    assert len(slam.graph.components()) == 1  # one map now, by verified matches
    P = slam.graph.poses("b")
    assert np.abs(P[:, :2] - truth_b[:, :2]).max() < 0.1
