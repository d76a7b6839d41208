"""An `ExplorationManager` set up from the config's `[exploration]` section."""

from __future__ import annotations

import time
from collections.abc import Iterable
from typing import Any

import numpy as np

from basestation.exploration import ExplorationManager
from basestation.frontiers import FrontierDetector
from basestation.goal_assigner import AssignmentWeights, GoalAssigner
from basestation.path_planner import PathPlanner, densify
from common.config import Config
from common.geometry import pose7_to_pose4
from common.metrics import percentiles
from protocol import Path as PathMsg

# s: the wall-time cap of one plan in a simulation, where plans stop at their check budget
# only (a cap that cut a mission's first plans, while its kernels loaded on a loaded
# machine, made two runs of one mission differ)
SIMULATION_PLANNING_CAP_S = 60.0


def make_explorer(cfg: Config, simulated: bool = False) -> ExplorationManager:
    """An `ExplorationManager` set up from `cfg.exploration`; `simulated`: for a lock-step
    (or kinematic) simulation, whose runs must not depend on the machine's load."""
    e = cfg.exploration
    time_cap = SIMULATION_PLANNING_CAP_S if simulated else e.planning_time_s
    return ExplorationManager(
        detector=FrontierDetector(e.frontier_radius_m, min_group_cells=e.min_frontier_cells),
        strict_detector=FrontierDetector(e.frontier_radius_m, min_group_cells=e.min_frontier_cells),
        assigner=GoalAssigner(AssignmentWeights(e.w_distance, e.w_heading, e.w_previous)),
        planner=PathPlanner(
            e.inflation_m, e.robot_clearance_m, time_cap, check_budget=e.planning_checks
        ),
        coordinated=e.strategy == "coordinated",
        speed_mps=cfg.agent.cruise_speed_mps,
        # the agents' follower flies at full speed up to this far off the nose and not at
        # all beyond that: a robot facing away is taken to set off once halfway between
        turn_free_deg=0.5 * (cfg.agent.full_speed_off_nose_deg + cfg.agent.max_off_nose_deg),
        **{k: getattr(e, k) for k in COST_FIELDS},
    )


# exploration config fields that are ExplorationManager fields of the same name
COST_FIELDS = (
    "w_spread", "spread_radius_m", "seen_range_m", "seen_fov_deg", "seen_cost_m", "w_own",
    "own_cap_m", "tours", "w_gain", "gain_full_m2", "gain_near_m", "gain_radius_m", "handover_m",
    "lag_s", "handover_unknown",
)  # fmt: skip


def explorer_stats(
    explorer: ExplorationManager | None, paths_sent: int, step_ms: Iterable[float]
) -> dict[str, Any] | None:
    """The base station's `exploration` statistics (None: it does not explore)."""
    if explorer is None:
        return None
    return {
        "done": explorer.done,
        "frontiers": len(explorer.frontiers),
        "paths_sent": paths_sent,
        "unreachable": explorer.unreachable,
        "planner_searches": explorer.planner.plans,
        "planner_grid_fallbacks": explorer.planner.fallbacks,
        "planner_detours_shortened": explorer.planner.detours_shortened,
        "detours_refused": explorer.detours_refused,
        **percentiles("step_ms", step_ms),
    }


def keep_unheard_clear(
    explorer: ExplorationManager, known_starts: dict[str, np.ndarray], heard: set[str]
) -> None:
    """A drone of the scenario not heard of yet (its link up late) hovers at its known
    start: kept clear there, as a silent robot's way is, until it is heard (another had
    been planned 0.04 m from it, and flown 0.41 m from it in a real-time mission)."""
    for rid, start in known_starts.items():
        if rid not in heard and rid not in explorer.silent:
            explorer.silent[rid] = np.asarray(start, dtype=np.float64)[None, :2]


def planar_pose(state: Any) -> np.ndarray:
    """[x, y, yaw] in `map` of a robot's `RobotState`, as exploration plans from."""
    return pose7_to_pose4(state.pose_map)[[0, 1, 3]]


def path_message(
    robot_id: str, path_id: int, path: np.ndarray | None, z: float, epoch: int
) -> PathMsg:
    """The Path of an exploration step's `path` (map [x, y] points, every 0.25 m at
    altitude `z`; None: hold where it is)."""
    p = np.zeros((0, 2)) if path is None else densify(path, 0.25)
    wp = np.column_stack([p, np.full(len(p), z), np.zeros(len(p))]).astype(np.float32)
    return PathMsg(robot_id, path_id, time.time(), "map", epoch, wp)
