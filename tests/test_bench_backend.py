"""Tests for benchmarks.backend (`collabslam bench backend`) on small graphs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from benchmarks.backend import ROBOTS, run, simulate_team, split_g2o
from common.config import Config
from common.g2o_io import read_g2o

SIZE_KEYS = {
    "nodes",
    "source",
    "isam2_update_ms_p50",
    "isam2_update_ms_p95",
    "isam2_update_ms_max",
    "batch_ms",
    "ratio_batch_over_isam2",
}


def test_split_uses_every_edge_once_in_time_order(shared_data: Path) -> None:
    data = read_g2o(shared_data / "g2o" / "M3500.g2o")
    n = 200
    feed = split_g2o(data, n)
    assert set(feed.starts) == set(ROBOTS) and len(feed.nodes) == n
    sizes = {r: sum(node.robot_id == r for node in feed.nodes) for r in ROBOTS}
    assert max(sizes.values()) - min(sizes.values()) <= 1  # 3 near-equal segments
    seen: dict[str, int] = {r: 0 for r in ROBOTS}
    step = -1
    for node in feed.nodes:  # each chain in index order; steps interleave robots
        assert node.index == seen[node.robot_id]
        assert node.index >= step
        step = node.index
        seen[node.robot_id] += 1
        assert (node.delta is None) == (node.index == 0)
        for c in node.constraints:  # both ends exist once the node arrives
            for robot, index in (c.key_a, c.key_b):
                assert index < seen[robot]
    edges = sum(max(e.i, e.j) < n for e in data.edges_se2)
    odometry = sum(node.index > 0 for node in feed.nodes)
    assert odometry + sum(len(node.constraints) for node in feed.nodes) == edges


def test_simulated_team_has_inter_robot_loops_and_truthful_starts() -> None:
    feed, truth = simulate_team(nodes_per_robot=80, seed=3)
    assert len(feed.nodes) == 3 * 80
    constraints = [c for node in feed.nodes for c in node.constraints]
    assert any(c.key_a[0] != c.key_b[0] for c in constraints)
    for robot, start in feed.starts.items():
        np.testing.assert_allclose(start, truth[robot][0])


def test_run_small(cfg: Config, shared_data: Path, tmp_path: Path) -> None:
    result = run(
        cfg, tmp_path, shared_data, sizes=(200,), chi2_max_nodes=300, sim_nodes_per_robot=60
    )
    assert set(result) == {"sizes", "chi2", "sim", "reduced"}
    (entry,) = result["sizes"]
    assert SIZE_KEYS <= set(entry)
    assert entry["nodes"] == 200 and entry["source"] == "M3500.g2o[:200]"
    for key in ("isam2_update_ms_p50", "isam2_update_ms_p95", "isam2_update_ms_max"):
        assert entry[key] > 0
    assert entry["isam2_update_ms_p50"] <= entry["isam2_update_ms_p95"]
    assert entry["isam2_update_ms_p95"] <= entry["isam2_update_ms_max"]
    assert entry["batch_ms"] > 0 and entry["ratio_batch_over_isam2"] > 0
    assert entry["chi2_isam2"] == pytest.approx(entry["chi2_batch"], rel=0.01)
    assert set(result["chi2"]) == {"M3500", "intel"}
    for chi2 in result["chi2"].values():
        assert chi2["isam2"] == pytest.approx(chi2["batch"], rel=0.01)
    sim = result["sim"]
    assert sim["nodes"] == 180 and sim["isam2_update_ms_p50"] > 0
    assert sim["chi2_isam2"] == pytest.approx(sim["chi2_batch"], rel=0.01)
    ate = sim["ate_rms_m"]
    assert ate["isam2"] < ate["odometry"]  # loop closures help
    assert (tmp_path / "M3500_200_update_ms.txt").is_file()
    near, *_, far, default = result["reduced"]  # 0.5 ... 2.0 m from the first node, default
    assert near["reduce_distance_m"] < far["reduce_distance_m"]
    assert near["reduce_after_nodes"] == far["reduce_after_nodes"] == 0
    assert default["reduce_after_nodes"] == Config().basestation.reduce_after_nodes > 200
    assert default["variables"] == default["nodes"]  # 200 nodes: the default does not reduce
    assert far["variables"] < near["variables"] < near["nodes"] == 200
    for reduced in (near, far):  # frozen offsets cost little against the whole graph's optimum
        assert 0 < reduced["offset_from_batch_optimum_m_mean"] < 0.1
        assert reduced["isam2_update_ms_p50"] > 0
