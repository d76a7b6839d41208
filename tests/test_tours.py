"""Start poses and scripted tours on shipped and never-seen worlds."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from common.errors import CollabSlamError
from common.map_io import GridMap
from simulation.tours import plan_tours, start_poses
from simulation.world import SHIPPED_WORLDS, World
from simulation.world_generator import random_floor

CLEARANCE = 0.5
LENGTH = 60.0

_CACHE: dict[str, World] = {}


def get_world(name: str) -> World:
    if name not in _CACHE:
        if name.startswith("random"):
            seed, w, h = (int(v) for v in name.split("_")[1:])
            _CACHE[name] = World(random_floor(seed, float(w), float(h)))
        else:
            _CACHE[name] = World.load(name)
    return _CACHE[name]


WORLDS = [*SHIPPED_WORLDS, "random_401_22_16", "random_402_30_20", "random_403_14_18"]


def room(width_m: float, height_m: float) -> GridMap:
    data = np.full((round(height_m / 0.05), round(width_m / 0.05)), 100, dtype=np.int8)
    data[1:-1, 1:-1] = 0
    return GridMap(data=data, resolution=0.05, origin=(0.0, 0.0, 0.0))


def sample_segments(tour: np.ndarray, step: float = 0.01) -> np.ndarray:
    pts = [tour[:1]]
    for a, b in itertools.pairwise(tour):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / step)))
        t = np.linspace(0.0, 1.0, n + 1)[1:, None]
        pts.append(a + t * (b - a))
    return np.vstack(pts)


def at_arclength(tour: np.ndarray, s: np.ndarray) -> np.ndarray:
    cum = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(tour, axis=0), axis=1))]
    return np.stack([np.interp(s, cum, tour[:, 0]), np.interp(s, cum, tour[:, 1])], axis=1)


def polyline_length(tour: np.ndarray) -> float:
    return float(np.sum(np.linalg.norm(np.diff(tour, axis=0), axis=1)))


@pytest.mark.parametrize("name", WORLDS)
def test_starts_and_tours(name: str) -> None:
    world = get_world(name)
    n = 3
    starts = start_poses(world, n, seed=1, spacing=1.5, clearance=0.6)
    assert starts.shape == (n, 3)
    # Valid: in free space, >= 0.6 m from walls and unknown, spread >= 1.5 m, but close.
    assert world.in_free_cell(starts[:, :2]).all()
    assert (world.free_clearance(starts[:, :2]) >= 0.6 - 1e-9).all()
    gaps = np.linalg.norm(starts[:, None, :2] - starts[None, :, :2], axis=2)[np.triu_indices(n, 1)]
    assert gaps.min() >= 1.5 - 1e-9
    assert gaps.max() <= 1.5 * n + 1.0
    assert np.all(starts[:, 2] == starts[0, 2])  # all face the same way

    tours = plan_tours(world, starts, seed=1, length_m=LENGTH, clearance=CLEARANCE)
    assert len(tours) == n
    for start, tour in zip(starts, tours, strict=True):
        assert tour.ndim == 2 and tour.shape[1] == 2 and len(tour) >= 3
        np.testing.assert_array_equal(tour[0], start[:2])
        assert polyline_length(tour) == pytest.approx(LENGTH, abs=1e-6)
        # Every straight segment keeps the clearance from walls and from unknown space.
        pts = sample_segments(tour)
        assert world.clearance(pts).min() >= CLEARANCE - 1e-6
        assert world.free_clearance(pts).min() >= CLEARANCE - 1e-3
    # Robots head for different regions: flying their tours at the same speed, any two
    # are more than 2 m apart most of the time.
    s = np.linspace(0.0, LENGTH, 241)
    where = [at_arclength(t, s) for t in tours]
    for a, b in itertools.combinations(where, 2):
        assert np.mean(np.linalg.norm(a - b, axis=1) > 2.0) > 0.5


def test_tours_deterministic_per_seed() -> None:
    world = get_world("rooms15")
    starts = start_poses(world, 2, seed=3)
    np.testing.assert_array_equal(starts, start_poses(world, 2, seed=3))
    a = plan_tours(world, starts, seed=3, length_m=30.0)
    b = plan_tours(world, starts, seed=3, length_m=30.0)
    c = plan_tours(world, starts, seed=4, length_m=30.0)
    for ta, tb in zip(a, b, strict=True):
        np.testing.assert_array_equal(ta, tb)
    assert any(len(ta) != len(tc) or not np.allclose(ta, tc) for ta, tc in zip(a, c, strict=True))
    assert not np.array_equal(starts, start_poses(world, 2, seed=5))


def test_many_robots_fit_and_short_tours() -> None:
    world = get_world("floor30x25")
    starts = start_poses(world, 10, seed=0)
    gaps = np.linalg.norm(starts[:, None, :2] - starts[None, :, :2], axis=2)
    assert gaps[np.triu_indices(10, 1)].min() >= 1.5 - 1e-9
    tours = plan_tours(world, starts, seed=0, length_m=5.0)
    assert all(polyline_length(t) == pytest.approx(5.0, abs=1e-6) for t in tours)
    assert all(len(t) >= 2 for t in tours)


def test_small_room_still_gives_a_tour() -> None:
    world = World(room(3.0, 3.0))
    starts = start_poses(world, 1, seed=0, spacing=1.0, clearance=0.6)
    (tour,) = plan_tours(world, starts, seed=0, length_m=20.0, clearance=0.5)
    assert len(tour) >= 2
    assert 0.0 < polyline_length(tour) <= 20.0 + 1e-6
    assert world.clearance(sample_segments(tour)).min() >= 0.5 - 1e-6


def test_disconnected_rooms_each_robot_stays_reachable() -> None:
    g = room(10.0, 4.0)
    g.data[:, 100] = 100  # two closed rooms side by side
    world = World(g)
    starts = np.array([[2.5, 2.0, 0.0], [7.5, 2.0, 0.0]])
    tours = plan_tours(world, starts, seed=0, length_m=15.0)
    assert (tours[0][:, 0] < 5.0).all() and (tours[1][:, 0] > 5.0).all()
    assert all(polyline_length(t) > 5.0 for t in tours)


def test_too_narrow_world_gives_start_only_tours() -> None:
    world = World(room(10.0, 0.9))  # 0.8 m corridor: nowhere 0.5 m from both walls
    starts = np.array([[2.0, 0.45, 0.0]])
    (tour,) = plan_tours(world, starts, seed=0, length_m=10.0, clearance=0.5)
    np.testing.assert_array_equal(tour, starts[:, :2])
    with pytest.raises(CollabSlamError, match="clearance|cannot place"):
        start_poses(world, 1, seed=0, clearance=0.6)


def test_errors_on_empty_world_and_overcrowding() -> None:
    solid = World(GridMap(data=np.full((40, 40), 100, np.int8), resolution=0.05, origin=(0, 0, 0)))
    with pytest.raises(CollabSlamError, match="no free space"):
        plan_tours(solid, np.array([[1.0, 1.0, 0.0]]), seed=0, length_m=10.0)
    with pytest.raises(CollabSlamError):
        start_poses(solid, 1, seed=0)
    with pytest.raises(CollabSlamError, match="cannot place 20 robots"):
        start_poses(World(room(4.0, 4.0)), 20, seed=0)
