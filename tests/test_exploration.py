"""Exploration logic end to end in one process: robots on ideal odometry fly the
manager's RRT* paths through a shipped world, their (noise-free) scans build the
grid, and exploration must end with the world's reachable free space known."""

from __future__ import annotations

import math

import numpy as np

from basestation.exploration import ExplorationManager, _Task
from basestation.frontiers import FrontierDetector
from basestation.path_planner import PathPlanner
from common.map_io import GridMap
from common.occupancy_grid import OccupancyGrid
from simulation.sensors import LaserModel
from simulation.tours import start_poses
from simulation.world import World

SPEED, DT, RADIUS = 1.0, 0.25, 0.2  # m/s, s per tick, robot radius (m)


def _advance(pose: np.ndarray, path: np.ndarray, world: World) -> tuple[np.ndarray, np.ndarray]:
    """Move SPEED * DT along the path (dropping reached waypoints); stop at a wall the
    map did not show yet (the manager replans once the scan shows it)."""
    step = SPEED * DT
    while len(path) and step > 0:
        d = path[0] - pose[:2]
        n = float(np.hypot(*d))
        move = min(n, step)
        nxt = pose[:2] + (d / n * move if n > 1e-9 else 0.0)
        if not world.is_free(nxt[None], RADIUS)[0]:
            return pose, np.zeros((0, 2))
        yaw = math.atan2(d[1], d[0]) if n > 1e-9 else pose[2]
        pose = np.array([nxt[0], nxt[1], yaw])
        step -= move
        if move >= n:
            path = path[1:]
    return pose, path


def _explore(world_name: str, n_robots: int, max_ticks: int = 2400):
    world = World.load(world_name)
    laser = LaserModel(360, math.radians(270.0), 0.1, 10.0, 0.0)
    lo, hi = np.array(world.bounds[:2]), np.array(world.bounds[2:])
    grid = OccupancyGrid.from_bounds(lo - 1.0, hi + 1.0, 0.1)
    rng = np.random.default_rng(0)
    poses = {f"r{k}": p for k, p in enumerate(start_poses(world, n_robots, seed=1))}
    paths = {r: np.zeros((0, 2)) for r in poses}
    mgr = ExplorationManager(
        detector=FrontierDetector(radius_m=0.3, min_group_cells=8),
        planner=PathPlanner(inflation_m=0.25, robot_clearance_m=0.8, time_budget_s=0.1),
    )
    min_sep = np.inf
    for tick in range(max_ticks):
        for p in poses.values():
            grid.insert_scan(p, laser.measure(world, p, rng), laser.angles, 0.1, 10.0)
        if tick >= 8 and tick % 4 == 0:  # a few scans first: free needs several misses
            for r, path in mgr.step(grid.to_gridmap(), poses).items():
                paths[r] = np.zeros((0, 2)) if path is None else path[1:]
            if mgr.done:
                break
        for r in poses:
            poses[r], paths[r] = _advance(poses[r], paths[r], world)
        ps = np.array([p[:2] for p in poses.values()])
        if len(ps) > 1:
            d = np.hypot(*(ps[:, None] - ps[None]).transpose(2, 0, 1))
            min_sep = min(min_sep, d[np.triu_indices(len(ps), 1)].min())
    return world, grid, mgr, tick, min_sep


def _known_free_fraction(world: World, grid: OccupancyGrid) -> float:
    g = grid.to_gridmap()
    free_world = world.is_free(_cell_centres(world), 0.0)
    xy = _cell_centres(world)[free_world]
    ij = np.floor((xy - np.array(g.origin[:2])) / g.resolution).astype(int)
    return float(np.mean(g.data[ij[:, 1], ij[:, 0]] == 0))


def _cell_centres(world: World) -> np.ndarray:
    x0, y0, x1, y1 = world.bounds
    xs = np.arange(x0 + 0.05, x1, 0.1)
    ys = np.arange(y0 + 0.05, y1, 0.1)
    X, Y = np.meshgrid(xs, ys)
    return np.column_stack([X.ravel(), Y.ravel()])


def test_two_robots_explore_the_room_set_until_no_frontier_is_left() -> None:
    world, grid, mgr, ticks, min_sep = _explore("rooms15", 2)
    assert mgr.done, f"still {len(mgr.frontiers)} frontiers after {ticks} ticks"
    known = _known_free_fraction(world, grid)
    assert known > 0.9, known
    assert min_sep > 0.5


def test_a_support_leg_stops_when_exploration_is_over() -> None:
    """A robot with no frontier of its own moving up behind the others (a support leg)
    had flown its whole leg after the last frontier went: with 8 drones on bshape, idle
    legs of 22-26 m held the mission's end from 21 s to 44 s."""
    res = 0.05
    data = np.zeros((int(4 / res), int(24 / res)), dtype=np.int8)  # a room, walled in
    data[:3, :] = data[-3:, :] = data[:, :3] = data[:, -3:] = 100
    grid = GridMap(data, res, (0.0, 0.0, 0.0))
    m = ExplorationManager()
    path = np.array([[2.0, 2.0], [22.0, 2.0]])  # 20 m, nothing in the way
    m.tasks["r0"] = _Task(path[-1].copy(), path, support=True)
    assert m.step(grid, {"r0": np.array([2.0, 2.0, 0.0])}, strict=grid) == {"r0": None}
    assert m.done and not m.frontiers
