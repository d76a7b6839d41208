"""OMPL RRT* paths on the global grid: never through blocked cells."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from basestation.path_planner import PathPlanner, PlanningMap, unknown_length
from common.map_io import GridMap

RES = 0.1


def _grid(data: np.ndarray) -> GridMap:
    return GridMap(np.asarray(data, dtype=np.int8), RES, (0.0, 0.0, 0.0))


def _room_with_wall() -> np.ndarray:
    d = np.zeros((100, 100), dtype=np.int8)  # 10 x 10 m, all free
    d[:, 0] = d[:, -1] = d[0, :] = d[-1, :] = 100
    d[:80, 48:52] = 100  # a wall from the bottom, a gap at the top
    return d


def test_path_goes_around_a_wall_and_keeps_its_distance() -> None:
    grid = _grid(_room_with_wall())
    planner = PathPlanner(inflation_m=0.4, time_budget_s=0.5, seed=1)
    path = planner.plan(grid, [2.0, 2.0], [8.0, 2.0])
    assert path is not None
    np.testing.assert_allclose(path[0], [2.0, 2.0])
    np.testing.assert_allclose(path[-1], [8.0, 2.0])
    assert path[:, 1].max() > 8.0  # over the top of the wall
    assert PlanningMap(grid, 0.4).segment_free(path)


def test_unknown_space_counts_as_free() -> None:
    d = np.full((60, 60), -1, dtype=np.int8)
    d[:, :20] = 0
    path = PathPlanner(seed=2).plan(_grid(d), [1.0, 3.0], [5.0, 3.0])
    assert path is not None and len(path) == 2  # straight through the unknown


def test_another_robot_blocks_a_corridor() -> None:
    d = np.full((40, 100), 100, dtype=np.int8)
    d[15:25, 1:99] = 0  # a 1 m wide corridor, 10 m long
    grid = _grid(d)
    planner = PathPlanner(inflation_m=0.1, robot_clearance_m=1.0, time_budget_s=0.2, seed=3)
    assert planner.plan(grid, [1.0, 2.0], [9.0, 2.0]) is not None
    assert planner.plan(grid, [1.0, 2.0], [9.0, 2.0], others=[[[5.0, 2.0]]]) is None


def test_another_robots_path_is_blocked_along_its_segments() -> None:
    grid = _grid(np.zeros((100, 100), dtype=np.int8))  # 10 x 10 m, all free
    route = np.array([[1.0, 5.0], [9.0, 5.0]])  # two vertices 8 m apart
    pm = PlanningMap(grid, 0.0, [route], robot_clearance_m=1.0)
    xs = np.linspace(1.0, 9.0, 33)
    assert not pm.is_free(np.column_stack([xs, np.full_like(xs, 5.0)])).any()
    assert not pm.is_free(np.column_stack([xs, np.full_like(xs, 5.95)])).any()
    assert pm.is_free(np.column_stack([xs, np.full_like(xs, 6.1)])).all()
    # the route walls off the lower half: no way from below it to above it
    planner = PathPlanner(inflation_m=0.1, robot_clearance_m=1.0, time_budget_s=0.2, seed=4)
    wall = np.array([[-1.0, 5.0], [11.0, 5.0]])
    assert planner.plan(grid, [5.0, 2.0], [5.0, 8.0], others=[wall]) is None


def test_blocked_goal_gives_no_path() -> None:
    grid = _grid(_room_with_wall())
    assert PathPlanner().plan(grid, [2.0, 2.0], [5.0, 3.0]) is None  # inside the wall


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000))
def test_a_path_never_crosses_occupied_or_inflated_cells(seed: int) -> None:
    rng = np.random.default_rng(seed)
    d = np.where(rng.random((60, 60)) < 0.5, 0, -1).astype(np.int8)
    for _ in range(rng.integers(3, 12)):  # random rectangular obstacles
        y, x = rng.integers(0, 55, 2)
        d[y : y + rng.integers(1, 15), x : x + rng.integers(1, 15)] = 100
    grid = _grid(d)
    start, goal = rng.uniform(0.2, 5.8, 2), rng.uniform(0.2, 5.8, 2)
    planner = PathPlanner(inflation_m=0.2, time_budget_s=0.1, seed=seed)
    path = planner.plan(grid, start, goal)
    if path is None:
        return
    pm = PlanningMap(grid, 0.2)
    # outside the start's escape disc nothing may be inflated
    t = np.linspace(0, 1, 50)[:, None]
    dense = np.vstack([a + t * (b - a) for a, b in zip(path[:-1], path[1:], strict=True)])
    iy, ix = pm.cells(dense)
    # nothing occupied outside the robot's own footprint at the start (map noise under a
    # robot is cleared: it is there)
    off_start = np.hypot(*(dense - start).T) > planner.robot_radius_m + 2 * RES
    assert not pm.occupied[iy[off_start], ix[off_start]].any()
    far = np.hypot(*(dense - start).T) > planner.start_escape_m + 2 * RES  # cell rounding
    assert not pm.blocked[iy[far], ix[far]].any()


def _quarter_cell_samples(path: np.ndarray) -> np.ndarray:
    """Points along a path a quarter cell apart (as the planner checks its paths)."""
    pts = []
    for a, b in zip(path[:-1], path[1:], strict=True):
        n = max(2, int(np.ceil(np.hypot(*(b - a)) / (0.25 * RES))) + 1)
        pts.append(a + np.linspace(0.0, 1.0, n)[:, None] * (b - a))
    return np.vstack(pts)


def test_a_robot_beside_a_door_jamb_is_not_sent_past_it_closer() -> None:
    # rooms15: a drone in a door, 0.33 m from the jamb's corner, was sent on past the
    # corner closer than that; its safety guard held it there. Now it first leaves the
    # jamb's zone straight away from it, and is not sent back into the zone after
    d = np.zeros((60, 60), dtype=np.int8)  # 6 x 6 m at 0.1 m
    d[29:31, 35:] = 100  # a wall along y = 3 from x = 3.5 east: its corner at (3.5, 3.1)
    d[29:31, :20] = 100  # the door's other side, 1.5 m away
    grid = _grid(d)
    pm = PlanningMap(grid, 0.35)
    for start, goal in (([3.28, 3.22], [5.5, 5.0]), ([3.28, 3.22], [4.0, 2.4])):
        s = np.array(start)
        (sy,), (sx,) = pm.cells(s[None])
        assert pm.wall_distance[sy, sx] < 0.35 + 2 * RES  # in the zone RRT* plans around
        path = PathPlanner(inflation_m=0.35, time_budget_s=0.5, seed=1).plan(grid, s, goal)
        assert path is not None
        iy, ix = pm.cells(_quarter_cell_samples(path))
        assert pm.wall_distance[iy, ix].min() >= pm.wall_distance[sy, sx] - 1e-9


def _serpentine() -> np.ndarray:
    """10 x 10 m with four walls, gaps alternating right and left: a long detour."""
    d = np.zeros((100, 100), dtype=np.int8)
    d[:, 0] = d[:, -1] = d[0, :] = d[-1, :] = 100
    for k, y in enumerate((20, 40, 60, 80)):
        d[y : y + 2, :85] = 100 if k % 2 == 0 else 0
        if k % 2:
            d[y : y + 2, 15:] = 100
    return d


def test_grid_path_when_rrt_star_runs_out_of_time() -> None:
    grid = _grid(_serpentine())
    planner = PathPlanner(inflation_m=0.3, time_budget_s=1e-4, attempts=1, seed=4)
    path = planner.plan(grid, [1.0, 1.0], [1.0, 9.0])
    assert path is not None and planner.fallbacks == 1
    np.testing.assert_allclose(path[[0, -1]], [[1.0, 1.0], [1.0, 9.0]])
    assert PlanningMap(grid, 0.3).segment_free(path)
    length = np.sum(np.hypot(*np.diff(path, axis=0).T))
    assert 30.0 < length < 45.0  # through every gap, shortcut (not a staircase of cells)


class _CountingRrtStar(PathPlanner):
    rrt_runs = 0

    def _rrt_star(self, *args):  # type: ignore[no-untyped-def]
        self.rrt_runs += 1
        return super()._rrt_star(*args)


def test_no_path_into_a_sealed_room_even_with_the_fallback() -> None:
    d = _serpentine()
    d[80:82, :] = 100  # the top row of rooms is sealed off
    planner = _CountingRrtStar(inflation_m=0.3, time_budget_s=1e-3, attempts=1, seed=5)
    assert planner.plan(_grid(d), [1.0, 1.0], [1.0, 9.0]) is None
    assert planner.fallbacks == 0
    assert planner.rrt_runs == 0  # no cell path: RRT* is not run (its budget is saved)
    assert planner.plan(_grid(_serpentine()), [1.0, 1.0], [1.0, 9.0]) is not None
    assert planner.rrt_runs == 1


class _LongWayRound(PathPlanner):
    """RRT* as on a loaded CPU: its first solution, the long way round a wall."""

    def _rrt_star(self, pm, check, s, g, good_enough_m, have_fallback):  # type: ignore[no-untyped-def]
        path = np.array([s, [s[0], 2.0], [9.0, 2.0], [9.0, 5.0], g])
        return path if check.segment_free(path) else None


def test_a_long_way_round_from_rrt_star_is_replaced_by_the_shorter_grid_path() -> None:
    d = np.zeros((100, 100), dtype=np.int8)
    d[:, 0] = d[:, -1] = d[0, :] = d[-1, :] = 100
    d[40:42, :80] = 100  # a wall at y = 4 m up to x = 8 m ...
    d[40:42, 10:22] = 0  # ... with a door at x = 1-2.2 m
    planner = _LongWayRound(inflation_m=0.3, time_budget_s=0.05, seed=6)
    path = planner.plan(_grid(d), [1.6, 1.0], [3.0, 7.0])
    assert path is not None and planner.detours_shortened == 1 and planner.fallbacks == 1
    assert path[:, 0].max() < 4.0 and np.sum(np.hypot(*np.diff(path, axis=0).T)) < 8.0
    assert PlanningMap(_grid(d), 0.3).segment_free(path)
    d[40:42, 10:22] = 100  # no door: the long way is the way
    path = planner.plan(_grid(d), [1.6, 1.0], [3.0, 7.0])
    assert (
        path is not None
        and path[:, 0].max() > 8.0
        and PlanningMap(_grid(d), 0.3).segment_free(path)
    )


_PLAN_SCRIPT = """
import sys, threading, time, json
import numpy as np
from basestation.path_planner import PathPlanner
from common.map_io import GridMap
d = np.zeros((100, 100), dtype=np.int8)
d[:, 0] = d[:, -1] = d[0, :] = d[-1, :] = 100
d[:80, 48:52] = 100
d[20:, 25:27] = 100  # a second wall
grid = GridMap(d, 0.1, (0.0, 0.0, 0.0))
stop, rounds = [], [0]
def hog():  # holds the GIL in turns with the planner's validity checks
    while not stop:
        sum(range(2000))
        rounds[0] += 1
if sys.argv[1] == "loaded":
    for _ in range(3):
        threading.Thread(target=hog, daemon=True).start()
planner = PathPlanner(inflation_m=0.3, time_budget_s=60.0, seed=7, check_budget=4000,
                      rrt_good_enough=0.0)  # RRT* never stops early: the budget decides
# the cell path reported as the straight line (through the walls): it fails the final
# check, so RRT* gets its whole budget on every question
planner._grid_path = lambda grid, pm, s, g: np.array([s, g])
t0 = time.perf_counter()
rounds[0] = 0  # from here on: while it plans
paths = []
for s, g in [([1.0, 1.0], [9.0, 1.0]), ([1.5, 8.5], [8.5, 2.0]), ([3.5, 2.0], [9.0, 5.0])]:
    p = planner.plan(grid, s, g)
    paths.append(None if p is None else np.round(p, 9).tolist())
stop.append(1)
print(json.dumps({"paths": paths, "checks": planner.validity_checks,
                  "wall_s": time.perf_counter() - t0, "hog_rounds": rounds[0]}))
"""


def test_plans_are_the_same_however_loaded_the_machine_is(tmp_path) -> None:
    """With a validity-check budget, two fresh processes asked the same questions get
    the same RRT* paths, one of them slowed down by threads competing for the CPU."""
    root = Path(__file__).resolve().parents[1]
    script = tmp_path / "plan.py"
    script.write_text(_PLAN_SCRIPT)
    out = {}
    for mode in ("idle", "loaded"):
        done = subprocess.run(
            [sys.executable, str(script), mode],
            capture_output=True, text=True, cwd=root, timeout=120, check=True,
            env={**os.environ, "PYTHONPATH": str(root)},
        )  # fmt: skip
        out[mode] = json.loads(done.stdout.strip().splitlines()[-1])
    assert out["idle"]["checks"] >= 3 * 4000 * 0.25  # RRT* ran on every question
    assert all(p is not None for p in out["idle"]["paths"])
    assert out["loaded"]["paths"] == out["idle"]["paths"]
    assert out["loaded"]["checks"] == out["idle"]["checks"]
    # the planner shared the interpreter with the hogs while it planned (its wall time
    # against the idle run's is no proof: on a busy machine both are slow)
    assert out["loaded"]["hog_rounds"] > 100 and out["idle"]["hog_rounds"] == 0


def test_a_robot_outside_every_wall_zone_is_given_no_way_into_one() -> None:
    d = np.zeros((60, 60), dtype=np.int8)  # the door of the test above
    d[29:31, 35:] = 100
    d[29:31, :20] = 100
    grid = _grid(d)
    pm = PlanningMap(grid, 0.35)
    start = np.array([3.78, 3.47])  # 0.4 m above the wall, 0.45 m from its corner
    (sy,), (sx,) = pm.cells(start[None])
    assert 0.35 < pm.wall_distance[sy, sx] < 0.35 + 2 * RES
    for goal in ([3.0, 2.3], [2.6, 1.5]):  # round the corner, through the door
        path = PathPlanner(inflation_m=0.35, time_budget_s=0.5, seed=1).plan(grid, start, goal)
        assert path is not None
        iy, ix = pm.cells(_quarter_cell_samples(path))
        assert pm.wall_distance[iy, ix].min() > 0.35


def _known_l_shape() -> np.ndarray:
    """10 x 10 m: known free along the bottom (y < 2 m) and the right (x > 8 m), the
    rest unknown."""
    d = np.full((100, 100), -1, dtype=np.int8)
    d[:20, :] = 0
    d[:, 80:] = 0
    return d


def test_unknown_length_of_a_path() -> None:
    grid = _grid(_known_l_shape())
    assert unknown_length(grid, np.array([[0.5, 1.0], [9.5, 1.0]])) == 0.0
    assert abs(unknown_length(grid, np.array([[1.0, 0.5], [1.0, 6.5]])) - 4.5) < 0.05


def test_a_map_with_no_wall_has_no_wall_zone() -> None:
    """An open field (nothing occupied): scipy's distance transform measured every cell
    from a point beside cell (0, 0), so a phantom wall zone blocked the map's corner and
    a goal there was unreachable."""
    data = np.zeros((100, 100), np.int8)
    data[:, 80:] = -1
    grid = GridMap(data, 0.05, (0.0, 0.0, 0.0))
    pm = PlanningMap(grid, 0.4)
    assert not pm.blocked.any() and not pm.in_wall_zone(np.array([0.1, 0.1]))
    assert PathPlanner(check_budget=2000).plan(grid, [2.0, 2.0], [0.1, 0.1]) is not None
