"""Whole-map searches both ways, with the real verifier on ray-cast scans of a shipped
floor plan: a robot whose start is unknown searches its newest scans against the map,
and a robot on the map searches its scans against the floating robot's map, so a place
the floating robot flew before the map reached it still joins the two."""

from __future__ import annotations

import numpy as np
from test_global_slam_backfill import _feed, _keyframes

from basestation.global_slam import GlobalSlam
from basestation.whole_map_search import WholeMapSearch
from common.config import Config, ConstraintConfig
from simulation.world import World


def test_a_robot_joins_where_the_map_reaches_only_after_it_has_flown_there() -> None:
    world = World.load("floor30x25")
    n = 37  # 0.5 m apart along the corridor at y = 6 m
    xs = 1.5 + 0.5 * np.arange(n)
    room = np.column_stack([11.5 + 0.5 * np.arange(5), np.full(5, 20.0), np.zeros(5)])
    corridor = np.column_stack([xs, np.full(n, 6.0), np.zeros(n)])
    truth_a = np.vstack([room, corridor])  # a room that sees nothing of the corridor first
    truth_b = np.column_stack([xs, np.full(n, 6.1), np.full(n, 0.02)])
    kf_a = _keyframes(world, "a", truth_a)
    cfg = Config()
    cfg.basestation.constraints.merge_stretch_keyframes = 10  # 5 m: keyframes 0.5 m apart
    slam = GlobalSlam(cfg, known_starts={"a": truth_a[0]})
    try:
        _feed(slam, kf_a[:5] + _keyframes(world, "b", truth_b))
        # b's own searches met only a's room: b's start stays unknown, and b flies no more
        assert not slam.graph.is_anchored("b")
        assert slam.builder.stats["submitted_global"] >= n // 5

        for k in range(5, len(kf_a), 5):  # a flies the corridor b flew
            _feed(slam, kf_a[k : k + 5])
    finally:
        slam.close()

    assert slam.graph.is_anchored("b")
    P = slam.graph.poses("b")
    err = np.hypot(*(P[:, :2] - truth_b[:, :2]).T)
    assert err.max() < 0.1, f"b placed up to {err.max():.2f} m off"


def test_the_whole_map_target_follows_a_growing_map() -> None:
    """Rebuilt once the map grew by a quarter (at least global_query_keyframes, at most
    global_map_rebuild_nodes nodes): a target built from the map's first nodes must not
    stay until it has 200 (ACES: a lagging first segment's 30-node map was searched for
    minutes)."""
    cc = ConstraintConfig()  # 20 and 200
    search = WholeMapSearch(cc, lambda r, i: np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]]))

    def query(key, nodes, poses):
        return [np.zeros((3, 2))], [np.zeros(3)], 3

    def built_from(n_map: int) -> int:
        poses = {"a": np.zeros((n_map, 3)), "b": np.zeros((5, 3))}
        job = search.job(("b", 4), poses, ["a", "b"], query)
        assert job is not None and job.target_nodes is not None
        return len(job.target_nodes)

    assert [built_from(n) for n in (10, 29, 30, 49, 50, 400, 499, 500, 1000, 1199, 1200)] == [
        10, 10, 30, 30, 50, 400, 400, 500, 1000, 1000, 1200,
    ]  # fmt: skip
