"""Exploration decisions alone: `collabslam bench exploration --kinematic`.

The base station's own `ExplorationManager` decides every `exploration.period_s` of sim
time, as in a lock-step mission, but nothing else of the stack runs: no SLAM, agents,
Zenoh or processes. Each drone is where it is (perfect poses); the simulator's laser
(`LaserModel`, no noise) at those poses goes into one occupancy grid every
`SCAN_PERIOD_S` where the drone's agent would cut a keyframe (`map.*` thresholds:
`strict` as published, the exploration grid with
free at 0.49 as the base station's); each drone flies its path with the
agent's own `PathFollower` (cruise speed, slowing for the last waypoint, turning
first when it is far off the nose) on the simulator's own `Quadrotor` (its limits,
lag and wall contacts) behind the agent's `SafetyGuard` (walls from the last scan,
seen from where the drone is now, as the agent's guard gets a scan every 25 ms; the
vehicle's velocity; the other drones at their true positions). No SLAM error, no
keyframe or map lag.

So a run costs the exploration steps and the ray casting only: ~5-30 s of wall time
for a mission that takes 1-2 min in full, and the same seed gives the same run
(each in a fresh process, `run_kinematic`). It is for comparing exploration settings
and code (`--set exploration.*`) on many seeds; its times are not the benchmark's,
which fly the whole system. On rooms15 (12 seeds, 27th session) its lone drone took
39.3 s (missions: 41.5 s) but its teams of 3 were slower: 22.4 s (19.2 s). Small
changes to the decisions move single runs by seconds either way (a chaotic system),
so compare means over many seeds, and check a finding with full missions: without
own ground (`exploration.w_own=0`) it was 2.3 s faster on rooms15 where the missions
were 2.5 s slower. Rows have the
benchmark's fields (`collisions`: wall contacts of the `Quadrotor`s, plus one if two
drones came within two radii).
"""

from __future__ import annotations

import copy
import math
import multiprocessing
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from agent.keyframe_selector import KeyframeSelector
from agent.path_follower import PathFollower
from agent.safety_guard import SafetyGuard
from basestation.exploration_setup import make_explorer
from basestation.path_planner import densify
from collabslam.launcher import make_scenario
from common.config import Config
from common.errors import ConfigError
from common.logging_setup import set_sim_clock
from common.metrics import CoverageTarget, coverage_of, reachable_free
from common.occupancy_grid import OccupancyGrid
from simulation.quadrotor import Quadrotor
from simulation.sensors import LaserModel
from simulation.world import World

TICK_S = 0.05  # s of sim time per motion step
# s between scans: each drone's safety guard sees the latest; the map takes one only
# where the agent would cut a base-station keyframe (`KeyframeSelector`: 0.2 m or 0.1
# rad since the last), as the base station's map does: none while a drone hovers. With a
# scan every 0.2 s into the map (before the 56th session), a hovering drone's looks piled
# up: random:1's teams of 3 took 49.6 s (24 seeds), with keyframes 51.6 s, as missions'
# 52.2 s (x2.11 against the lone drone's 108.7 s here, x2.13 in missions; map.free_thresh
# 0.196)
SCAN_PERIOD_S = 0.2
PLANNING_TIME_S = 120.0  # s: a cap the check budget always reaches first


def run_kinematic(
    cfg: Config, world: str, n_robots: int, seed: int, strategy: str, max_sim_time: float
) -> dict[str, Any]:
    """One kinematic exploration mission (module docstring), its benchmark row, flown in
    a fresh process: OMPL's generator is seeded once per process, so only there does
    the same seed give the same run whatever ran before."""
    spawn = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=1, mp_context=spawn) as pool:
        args = (cfg, world, n_robots, seed, strategy, max_sim_time)
        return pool.submit(fly_kinematic, *args).result()


def fly_kinematic(
    cfg: Config, world: str, n_robots: int, seed: int, strategy: str, max_sim_time: float
) -> dict[str, Any]:
    """`run_kinematic` in this process. `strategy`: `exploration.strategy`'s values."""
    if strategy not in ("coordinated", "greedy"):  # set after the config's validation
        raise ConfigError(f"strategy: expected coordinated or greedy, got {strategy!r}")
    c = copy.deepcopy(cfg)
    c.exploration.enabled = True
    c.exploration.strategy = strategy
    c.sim.seed = seed
    # RRT* stops at its check budget only: its wall-time cap would make plans (and the
    # whole run) depend on how loaded the machine is
    c.exploration.planning_time_s = max(c.exploration.planning_time_s, PLANNING_TIME_S)
    t_wall = time.monotonic()
    w = World.load(world)
    starts = [r.start_pose for r in make_scenario(c, Path(world), n_robots).robots]
    ids = [f"r{i}" for i in range(n_robots)]
    q = c.sim.quadrotor
    vehicle = {
        r: Quadrotor(
            np.array([s[0], s[1], q.altitude_m, s[2]]), q.max_speed_mps, q.max_accel_mps2,
            q.max_vertical_speed_mps, q.max_yaw_rate_rps, radius=q.radius_m,
        )
        for r, s in zip(ids, starts, strict=True)
    }  # fmt: skip
    pose = {r: v.pose[[0, 1, 3]].copy() for r, v in vehicle.items()}
    target = CoverageTarget(w.grid, reachable_free(w.grid, [s[:2] for s in starts]))
    m, las = c.map, c.sim.laser
    x0, y0, x1, y1 = w.bounds
    grid = OccupancyGrid.from_bounds(
        (x0 - 1.0, y0 - 1.0), (x1 + 1.0, y1 + 1.0), m.resolution_m, p_hit=m.p_hit, p_miss=m.p_miss
    )
    laser = LaserModel(las.beams, math.radians(las.fov_deg), las.range_min_m, las.range_max_m, 0.0)
    rng = np.random.default_rng(seed)
    explorer = make_explorer(c, simulated=True)
    follower = {r: PathFollower.from_config(c.agent) for r in ids}
    a = c.agent
    guard = {
        r: SafetyGuard(
            a.vehicle_radius_m, a.safety_margin_m, a.max_accel_mps2, a.safety_reaction_s,
            a.blocked_after_s, neighbour_keep_m=a.neighbour_keep_m, velocity_lag_s=a.velocity_lag_s,
        )
        for r in ids
    }  # fmt: skip
    flying = {r: False for r in ids}
    seen = {r: np.zeros((0, 2)) for r in ids}  # each drone's last scan, world points
    keyframes = {r: KeyframeSelector(c.agent) for r in ids}
    idle = {r: 0.0 for r in ids}
    curve: list[list[float]] = []
    sep = math.inf
    scan_every = max(1, round(SCAN_PERIOD_S / TICK_S))
    step_every = max(1, round(c.exploration.period_s / TICK_S))
    end_reason, k = "max_sim_time", 0
    set_sim_clock(lambda: k * TICK_S)  # its DEBUG lines say the model's time
    while True:
        t = k * TICK_S
        if k % scan_every == 0:
            for r in ids:
                ranges = laser.measure(w, pose[r], rng)
                hit = ranges < laser.range_max
                bearing = pose[r][2] + laser.angles[hit]
                seen[r] = pose[r][:2] + ranges[hit, None] * np.column_stack(
                    [np.cos(bearing), np.sin(bearing)]
                )
                if not keyframes[r].is_due(vehicle[r].pose):
                    continue
                keyframes[r].cut(vehicle[r].pose)
                grid.insert_scan(
                    pose[r], ranges, laser.angles, laser.range_min, laser.range_max,
                    max_free_range=m.max_free_range_m,
                )  # fmt: skip
        if k % step_every == 0:
            strict = grid.to_gridmap(m.occupied_thresh, m.free_thresh)
            curve.append([round(t, 3), round(coverage_of(target, strict), 4)])
            if curve[-1][1] >= 0.95 or t >= max_sim_time:
                end_reason = "95 %" if curve[-1][1] >= 0.95 else end_reason
                break
            blocked = {r for r in ids if guard[r].blocked}
            explore = grid.to_gridmap(m.occupied_thresh, 0.49)
            paths = explorer.step(explore, pose, blocked=blocked, strict=strict)
            for r, p in paths.items():
                flying[r] = p is not None and len(p) > 0
                if flying[r]:
                    follower[r].set_path(densify(p, 0.25))
                    guard[r].clear()  # as the agent does with every new path
            if explorer.done:
                end_reason = "explored"
                break
        for r in ids:
            v = vehicle[r]
            cmd = (0.0, 0.0, 0.0, 0.0)
            if flying[r] and not follower[r].done:
                cmd = follower[r].command(v.pose)
            others = np.array([vehicle[o].pose[:2] for o in ids if o != r]).reshape(-1, 2)
            cy, sy = math.cos(v.pose[3]), math.sin(v.pose[3])
            d = others - v.pose[:2]
            guard[r].set_neighbours(
                np.column_stack([cy * d[:, 0] + sy * d[:, 1], -sy * d[:, 0] + cy * d[:, 1]])
            )
            d = seen[r] - v.pose[:2]  # the last scan's points, from here
            guard[r].update(np.arctan2(d[:, 1], d[:, 0]) - v.pose[3], np.hypot(d[:, 0], d[:, 1]))
            vx, vy = guard[r].limit(t, cmd[0], cmd[1], velocity=v.velocity_body[:2])
            v.step((vx, vy, cmd[2], cmd[3]), TICK_S, w)
            pose[r] = v.pose[[0, 1, 3]].copy()
            idle[r] += TICK_S if np.hypot(*v.velocity_world[:2]) < 0.2 else 0.0
        xy = np.array([pose[r][:2] for r in ids])
        for i in range(n_robots):
            for j in range(i + 1, n_robots):
                sep = min(sep, float(np.hypot(*(xy[i] - xy[j]))))
        k += 1
    hit = [t for t, v in curve if v >= 0.95]
    return {
        "robots": n_robots,
        "seed": seed,
        "model": "kinematic",
        "time_to_95_s": hit[0] if hit else None,
        "distance_m": [round(vehicle[r].distance_travelled, 2) for r in ids],
        "idle_s": [round(idle[r], 2) for r in ids],
        "collisions": sum(v.collisions for v in vehicle.values())
        + int(n_robots > 1 and sep < 2.0 * q.radius_m),
        "min_clearance_m": round(min(v.min_clearance for v in vehicle.values()), 3),
        "min_robot_separation_m": round(sep, 3) if n_robots > 1 else None,
        "sim_time_s": curve[-1][0],
        "end_reason": end_reason,
        "final_coverage": curve[-1][1],
        "wall_time_s": round(time.monotonic() - t_wall, 1),
        "coverage_curve": curve,
    }
