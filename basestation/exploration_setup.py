"""An `ExplorationManager` set up from the config's `[exploration]` section."""

from __future__ import annotations

from basestation.exploration import ExplorationManager
from basestation.frontiers import FrontierDetector
from basestation.goal_assigner import AssignmentWeights, GoalAssigner
from basestation.path_planner import PathPlanner
from common.config import Config

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
