"""The floor under time_to_95_s (benchmarks/exploration_bound.py) on hand-made worlds."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from benchmarks.exploration import _bound
from benchmarks.exploration_bound import first_seen_m, time_to_fraction_bound_s, travel_time_s
from common.config import Config
from common.map_io import GridMap, write_map
from common.scenario import RobotScenario, Scenario, write_scenario


def _world(free: list[tuple[float, float, float, float]], size_m: float = 14.0) -> GridMap:
    """Walls everywhere but the given free boxes (x0, y0, x1, y1) in m; 0.1 m cells."""
    n = int(size_m / 0.1)
    data = np.full((n, n), 100, dtype=np.int8)
    for x0, y0, x1, y1 in free:
        data[int(y0 / 0.1) : int(y1 / 0.1), int(x0 / 0.1) : int(x1 / 0.1)] = 0
    return GridMap(data, 0.1, (0.0, 0.0, 0.0))


def test_travel_time_from_rest() -> None:
    assert travel_time_s(0.0, 1.0, 1.0) == 0.0
    assert travel_time_s(0.5, 1.0, 1.0) == pytest.approx(1.0)  # the ramp: 1 s to 1 m/s
    assert travel_time_s(10.5, 1.0, 1.0) == pytest.approx(11.0)
    assert travel_time_s(0.125, 1.0, 1.0) == pytest.approx(0.5)  # still accelerating


def test_open_room_is_seen_from_the_start() -> None:
    room = _world([(1.0, 1.0, 9.0, 9.0)], 10.0)
    assert time_to_fraction_bound_s(room, [[5.0, 5.0]], viewpoint_m=0.4) == pytest.approx(0.0)


def test_around_a_corner_takes_the_way_to_the_corner() -> None:
    """An L: a 12 m leg east from the start, then 12 m north. Half the free area is
    in the north leg, seen only once a drone is near the corner (~11 m away)."""
    ell = _world([(1.0, 1.0, 13.0, 2.0), (12.0, 1.0, 13.0, 13.0)])
    start = [[1.5, 1.5]]
    t95 = time_to_fraction_bound_s(ell, start, viewpoint_m=0.4)
    assert t95 is not None and 9.0 < t95 < 12.0
    t50 = time_to_fraction_bound_s(ell, start, fraction=0.5, viewpoint_m=0.4)
    assert t50 is not None and t50 < 1.0 < t95  # the east leg: in sight from the start
    d = first_seen_m(ell, start, viewpoint_m=0.4)
    assert np.isfinite(d).all() and d.min() == 0.0
    # a second drone already at the corner sees the north leg at once
    assert time_to_fraction_bound_s(ell, [[1.5, 1.5], [12.5, 1.5]], viewpoint_m=0.4) < 1.0


def test_walled_off_area_is_not_part_of_the_region() -> None:
    two = _world([(1.0, 1.0, 5.0, 5.0), (8.0, 8.0, 12.0, 12.0)])
    d = first_seen_m(two, [[3.0, 3.0]], viewpoint_m=0.4)
    assert len(d) == 40 * 40  # only the room the start is in


def test_bench_rows_get_the_bound_of_their_starts(tmp_path: Path) -> None:
    """`bench exploration --bound`: the bound of a mission's own starts, once per start."""
    world = tmp_path / "ell.yaml"
    write_map(_world([(1.0, 1.0, 13.0, 2.0), (12.0, 1.0, 13.0, 13.0)]), world)
    out = tmp_path / "run"
    out.mkdir()
    start = np.array([1.5, 1.5, 0.0])
    write_scenario(out / "scenario.json", Scenario(str(world), [RobotScenario("r0", start)]))
    cache: dict = {}
    t = _bound(Config(), str(world), out, cache)
    assert t is not None and 9.0 < t < 12.0
    assert _bound(Config(), str(world), out, cache) == t and len(cache) == 1
