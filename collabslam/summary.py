"""The run summary: what every process reported plus accuracy against ground truth."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from basestation.map_history import read_map_history
from basestation.robot_segments import robot_of
from common.errors import CollabSlamError
from common.map_io import read_map
from common.metrics import (
    ate_rmse,
    coverage_curve,
    map_accuracy,
    map_coverage,
    map_walls_found,
    min_separation,
    reachable_free,
    time_to_coverage,
)
from common.scenario import read_scenario
from common.trajectory_io import Trajectory, read_tum

log = logging.getLogger(__name__)


def _load(path: Path) -> dict[str, Any]:
    return json.loads(path.read_text()) if path.is_file() else {}


def build_summary(
    out: Path, world_yaml: Path, robot_ids: list[str], wall_time_s: float, contact_m: float = 0.5
) -> dict[str, Any]:
    """The run's `summary.json`. A robot's `collisions` are its contacts with walls;
    `robot_contact`: two robots came closer than `contact_m` (two drone radii). A
    robot's `ate_rmse_m` is horizontal (its height is the altimeter's, not SLAM's: it
    had been most of the figure), over its segments on the map (`on_map`: all were)."""
    sim = _load(out / "simulator.json")
    base = _load(out / "basestation.json")
    robots, agents = [], []
    for rid in robot_ids:
        agents.append(agent := _load(out / "agents" / f"{rid}.json"))
        segments = {s: r for s, r in base.get("robots", {}).items() if robot_of(s) == rid}
        in_graph = sum(r.get("keyframes_in_graph", 0) for r in segments.values())
        ate = None
        gt_path = out / "ground_truth" / f"{rid}.tum"
        try:  # (a file cut short: no ATE, the rest of the summary stands)
            # only segments on the map: a floating one's poses are in its own frame
            est = _segments_trajectory(out, rid, base)
            if est is not None and gt_path.is_file():
                ate = ate_rmse(est, read_tum(gt_path), with_z=False)
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
                "on_map": bool(segments)
                and all(r.get("anchored", True) for r in segments.values()),
                # joins to the map whole-map searches contradicted: undone (and made
                # again), or kept (final: its map and trajectory may be wrong)
                "joins_undone": sum(r.get("joins_undone", 0) for r in segments.values()),
                "join_contradicted": any(r.get("join_contradicted") for r in segments.values()),
            }
        )
    coverage = accuracy = walls = None
    if (out / "map.yaml").is_file():
        world, grid = read_map(world_yaml), read_map(out / "map.yaml")
        coverage, accuracy = map_coverage(grid, world), map_accuracy(grid, world)
        walls = map_walls_found(grid, world)
    gts = [read_tum(p) for r in robot_ids if (p := out / "ground_truth" / f"{r}.tum").is_file()]
    sep = min_separation(gts) if len(gts) == len(robot_ids) else None
    return {
        "robots": robots,
        "sim_time_s": sim.get("sim_time_s"),
        "sim_end_reason": sim.get("end_reason"),
        "wall_time_s": wall_time_s,
        "sim_realtime_factor": sim.get("realtime_factor"),
        "map_coverage": coverage,
        "map_accuracy": accuracy,
        "map_walls_found": walls,
        "isam2_update_ms_p95": base.get("isam2_update_ms_p95"),
        "min_robot_separation_m": sep,
        "robot_contact": sep is not None and sep < contact_m,
        **_coverage_over_time(out, world_yaml, sim.get("sim_time_s")),
        # robots not on the map, and why none of them can be (None: they can)
        "unjoined_robots": base.get("map_frame", {}).get("unjoined", []),
        "unjoinable_reason": base.get("map_frame", {}).get("unjoinable_reason"),
        "rejected_messages": base.get("rejected_messages", {}),
        "robot_runs_refused": base.get("robot_runs_refused", {}),  # not mapped: past the limit
        # waits of the lock-step clock given up (a base station's step over
        # `sim.basestation_timeout_s`, a cold numba cache): such a run may not repeat
        "lockstep_timeouts": sim.get("basestation_sync_timeouts", 0)
        + sim.get("late_states", 0)
        + base.get("clock_input_timeouts", 0)
        + sum(r.get("lockstep_downlink_timeouts", 0) for r in agents),
    }


_POSE_FIELDS = ("positions", "quats_xyzw")


def _segments_trajectory(out: Path, rid: str, base: dict[str, Any]) -> Trajectory | None:
    """The robot's trajectory in `map`: its segments' (one per run of its agent,
    basestation/robot_segments.py) in time order, those the base station had anchored;
    None if none was written."""
    paths = [out / "trajectories" / f"{rid}.tum", *(out / "trajectories").glob(f"{rid}~*.tum")]
    robots = base.get("robots", {})  # (a segment this run's base station did not map: none)
    paths = [p for p in paths if (p.stem == rid or p.stem in robots)
             and robots.get(p.stem, {}).get("anchored", True)]  # fmt: skip
    parts = [read_tum(p) for p in paths if p.is_file()]
    if not parts:
        return None
    stamps = np.concatenate([t.stamps for t in parts])
    order = np.argsort(stamps, kind="stable")
    cat = [np.concatenate([getattr(t, f) for t in parts])[order] for f in _POSE_FIELDS]
    return Trajectory(stamps[order], *cat)


def _coverage_over_time(out: Path, world_yaml: Path, sim_end_s: float | None) -> dict[str, Any]:
    """time_to_95_s and the coverage curve of the reachable free area (`map_coverage`:
    free, or wall surface within a cell or two of a real wall; `time_to_95_free_only_s`
    counts free cells only, as this metric did before), from the base
    station's map history (lock-step exploration runs only). The final map, which
    holds every keyframe taken before the simulation stopped, is the curve's last
    point at the end time: the snapshot before it lags the robots by the keyframes
    still on their way (a run that ended at 43.5 s scored 94.9 % at 43 s and 96.3 %
    in its final map)."""
    if not (out / "map_history.npz").is_file() or not (out / "scenario.json").is_file():
        return {}
    world = read_map(world_yaml)
    starts = [r.start_pose[:2] for r in read_scenario(out / "scenario.json").robots]
    history = read_map_history(out / "map_history.npz")
    if sim_end_s is not None and (out / "map.yaml").is_file():
        if not history or sim_end_s > history[-1][0]:
            history.append((float(sim_end_s), read_map(out / "map.yaml")))
    region = reachable_free(world, starts)
    t, c = coverage_curve(history, world, region)
    _, c_free = coverage_curve(history, world, region, wall_tolerance_m=0.0)
    return {
        "time_to_95_s": time_to_coverage(t, c, 0.95),
        "time_to_95_free_only_s": time_to_coverage(t, c_free, 0.95),
        "coverage_curve": [[float(a), round(float(b), 4)] for a, b in zip(t, c, strict=True)],
    }
