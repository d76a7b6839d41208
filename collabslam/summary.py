"""The run summary: what every process reported plus accuracy against ground truth."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

from common.errors import CollabSlamError
from common.map_io import read_map
from common.metrics import ate_rmse, map_accuracy, map_coverage
from common.trajectory_io import read_tum

log = logging.getLogger(__name__)


def _load(path: Path) -> dict[str, Any]:
    return json.loads(path.read_text()) if path.is_file() else {}


def build_summary(
    out: Path, world_yaml: Path, robot_ids: list[str], wall_time_s: float
) -> dict[str, Any]:
    sim = _load(out / "simulator.json")
    base = _load(out / "basestation.json")
    robots = []
    for rid in robot_ids:
        agent = _load(out / "agents" / f"{rid}.json")
        in_graph = base.get("robots", {}).get(rid, {}).get("keyframes_in_graph", 0)
        ate = None
        est_path, gt_path = out / "trajectories" / f"{rid}.tum", out / "ground_truth" / f"{rid}.tum"
        if est_path.is_file() and gt_path.is_file():
            try:
                ate = ate_rmse(read_tum(est_path), read_tum(gt_path))
            except CollabSlamError as exc:
                log.warning("no ATE for %s: %s", rid, exc)
        sim_r = sim.get("robots", {}).get(rid, {})
        robots.append(
            {
                "id": rid,
                "keyframes_sent": agent.get("keyframes_sent", 0),
                "keyframes_acked": agent.get("keyframes_acked", 0),
                "keyframes_in_graph": in_graph,
                "keyframes_resent": agent.get("keyframes_resent", 0),
                "distance_m": sim_r.get("distance_m", 0.0),
                "collisions": sim_r.get("collisions", 0),
                "min_clearance_m": sim_r.get("min_clearance_m"),
                "ate_rmse_m": ate,
            }
        )
    coverage = accuracy = None
    if (out / "map.yaml").is_file():
        world, grid = read_map(world_yaml), read_map(out / "map.yaml")
        coverage, accuracy = map_coverage(grid, world), map_accuracy(grid, world)
    return {
        "robots": robots,
        "sim_time_s": sim.get("sim_time_s"),
        "sim_end_reason": sim.get("end_reason"),
        "wall_time_s": wall_time_s,
        "sim_realtime_factor": sim.get("realtime_factor"),
        "map_coverage": coverage,
        "map_accuracy": accuracy,
        "isam2_update_ms_p95": base.get("isam2_update_ms_p95"),
        "rejected_messages": base.get("rejected_messages", {}),
    }
