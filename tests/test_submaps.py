"""Probability grid insertion and Cartographer's two overlapping active submaps."""

from __future__ import annotations

import math

import numpy as np
import pytest

from agent.probability_grid import ProbabilityGrid
from agent.submaps import ActiveSubmaps
from common.errors import CollabSlamError, ConfigError
from common.geometry import se2_compose, se2_transform_points


def _cell(grid: ProbabilityGrid, x: float, y: float) -> tuple[int, int]:
    """(iy, ix) of the cell holding submap-frame point (x, y)."""
    ix = int(math.floor((x - grid.origin_xy[0]) / grid.resolution))
    iy = int(math.floor((y - grid.origin_xy[1]) / grid.resolution))
    return iy, ix


# ------------------------------------------------------------------ probability grid


def test_hits_raise_and_rays_lower_once_per_scan() -> None:
    grid = ProbabilityGrid(0.1, (-1.0, -1.0), (20, 20))
    # Two returns in the same cell, one 0.5 m further along the same ray.
    grid.insert([0.0, 0.0, 0.0], [[0.52, 0.05], [0.53, 0.05], [0.72, 0.05]])
    p = grid.data
    assert p[_cell(grid, 0.52, 0.05)] == pytest.approx(0.55)  # once, not twice
    # The far beam passes through the near hit cell: the hit wins in the same scan.
    assert p[_cell(grid, 0.72, 0.05)] == pytest.approx(0.55)
    for x in (0.05, 0.15, 0.25, 0.35, 0.45, 0.65):
        assert p[_cell(grid, x, 0.05)] == pytest.approx(0.49)
    assert np.isnan(grid.probability()[_cell(grid, 0.05, 0.55)])  # never observed
    assert grid.known_mask().sum() == 8
    # A second scan: odds multiply (0.55 -> 0.599, 0.49 -> 0.48).
    grid.insert([0.0, 0.0, 0.0], [[0.52, 0.05]])
    hit_odds = (0.55 / 0.45) ** 2
    assert p[_cell(grid, 0.52, 0.05)] == pytest.approx(hit_odds / (1 + hit_odds), rel=1e-6)
    miss_odds = (0.49 / 0.51) ** 2
    assert p[_cell(grid, 0.25, 0.05)] == pytest.approx(miss_odds / (1 + miss_odds), rel=1e-6)
    assert grid.num_scans == 2
    assert grid.to_occupied_mask().sum() == 2


def test_probabilities_stay_clamped() -> None:
    grid = ProbabilityGrid(0.1, (-1.0, -1.0), (20, 20))
    for _ in range(60):
        grid.insert([0.0, 0.0, 0.0], [[0.55, 0.05]], p_hit=0.9, p_miss=0.1)
    p = grid.data
    assert p[_cell(grid, 0.55, 0.05)] == pytest.approx(0.9)
    assert p[_cell(grid, 0.25, 0.05)] == pytest.approx(0.1)


def test_miss_points_clear_their_whole_ray() -> None:
    grid = ProbabilityGrid(0.1, (-1.0, -1.0), (20, 20))
    grid.insert([0.0, 0.0, 0.0], np.zeros((0, 2)), miss_points_sensor=[[0.0, 0.55]])
    p = grid.data
    for y in (0.05, 0.25, 0.55):  # end cell included
        assert p[_cell(grid, 0.05, y)] == pytest.approx(0.49)
    assert grid.to_occupied_mask().sum() == 0


def test_hits_only_and_nan_points_skipped() -> None:
    grid = ProbabilityGrid(0.1, (-1.0, -1.0), (20, 20))
    grid.insert([0.0, 0.0, 0.0], [[0.55, 0.05], [np.nan, 1.0], [np.inf, 0.0]], miss_rays=False)
    assert grid.known_mask().sum() == 1


def _crossed_cells(
    grid: ProbabilityGrid, a: np.ndarray, b: np.ndarray
) -> tuple[set[tuple[int, int]], set[tuple[int, int]]]:
    """Cells whose interior the segment a-b crosses over a length > 1e-9 m, and cells
    it touches at all (exact clipping against every cell of the bounding box)."""
    crossed, touched = set(), set()
    (iy0, ix0), (iy1, ix1) = _cell(grid, *np.minimum(a, b)), _cell(grid, *np.maximum(a, b))
    d = b - a
    for iy in range(iy0, iy1 + 1):
        for ix in range(ix0, ix1 + 1):
            lo = grid.origin_xy + np.array([ix, iy]) * grid.resolution
            hi = lo + grid.resolution
            t0, t1 = 0.0, 1.0
            for k in range(2):
                if d[k] == 0.0:
                    if not lo[k] <= a[k] <= hi[k]:
                        t0, t1 = 1.0, 0.0
                    continue
                ta, tb = sorted(((lo[k] - a[k]) / d[k], (hi[k] - a[k]) / d[k]))
                t0, t1 = max(t0, ta), min(t1, tb)
            if t1 >= t0:
                touched.add((iy, ix))
                if (t1 - t0) * np.linalg.norm(d) > 1e-9:
                    crossed.add((iy, ix))
    return crossed, touched


def test_ray_traversal_visits_every_crossed_cell() -> None:
    random_ends = np.random.default_rng(0).uniform(-2.5, 2.5, size=(40, 2))
    for sensor in (np.array([0.013, -0.021]), np.array([0.0, 0.0])):  # inside / on a corner
        axis_parallel = sensor + np.array([[0.0, 1.5], [1.5, 0.0], [-2.0, 0.0], [0.0, -0.7]])
        for end in np.vstack([random_ends, axis_parallel]):
            _check_ray(sensor, end)


def _check_ray(sensor: np.ndarray, end: np.ndarray) -> None:
    grid = ProbabilityGrid(0.05, (-3.0, -3.0), (120, 120))
    grid.insert([*sensor, 0.0], [end - sensor])
    free = {(int(iy), int(ix)) for iy, ix in np.argwhere(grid.data == np.float32(0.49))}
    crossed, touched = _crossed_cells(grid, sensor, end)
    crossed.discard(_cell(grid, *end))
    touched.discard(_cell(grid, *end))
    # the cells the segment crosses, end cell excepted (corner grazes may go either way)
    assert crossed <= free <= touched, (sensor, end)


def test_grid_grows_and_keeps_cells_in_place() -> None:
    grid = ProbabilityGrid(0.05, (-1.0, -1.0), (40, 40), grow_margin_m=1.0)
    grid.insert([0.0, 0.0, 0.0], [[0.52, 0.33]])
    before = grid.data[_cell(grid, 0.52, 0.33)]
    grid.insert([0.0, 0.0, 0.0], [[-7.3, 4.1]])  # far outside: grows
    assert grid.shape[0] > 40 and grid.shape[1] > 40
    assert grid.data[_cell(grid, 0.52, 0.33)] == before  # same world cell, same value
    assert grid.data[_cell(grid, -7.3, 4.1)] == pytest.approx(0.55)
    # The lattice did not shift: the origin moved by whole cells.
    assert np.allclose(np.mod(grid.origin_xy + 1.0 + 1e-9, 0.05), 1e-9, atol=1e-7)


def test_frozen_grid_is_cropped_and_read_only() -> None:
    grid = ProbabilityGrid(0.05, (-5.0, -5.0), (200, 200))
    grid.insert([0.0, 0.0, 0.0], [[1.02, 0.51], [1.02, -0.49]])
    occupied = grid.to_occupied_mask().sum()
    grid.freeze()
    assert grid.frozen
    assert grid.shape[0] < 200 and grid.shape[1] < 200
    assert grid.to_occupied_mask().sum() == occupied
    assert grid.data[_cell(grid, 1.02, 0.51)] == pytest.approx(0.55)
    with pytest.raises(CollabSlamError):
        grid.insert([0.0, 0.0, 0.0], [[1.0, 0.0]])


def test_grid_rejects_bad_arguments() -> None:
    with pytest.raises(ConfigError):
        ProbabilityGrid(0.0, (0.0, 0.0), (10, 10))
    with pytest.raises(ConfigError):
        ProbabilityGrid(0.05, (0.0, 0.0), (0, 10))
    grid = ProbabilityGrid(0.05, (0.0, 0.0), (10, 10))
    with pytest.raises(ConfigError):
        grid.insert([0.0, 0.0, 0.0], [[1.0, 1.0]], p_hit=0.4)
    with pytest.raises(CollabSlamError):
        grid.insert([0.0, 0.0, 0.0], [[1.0, 1.0, 1.0]])
    with pytest.raises(CollabSlamError):
        grid.insert([np.nan, 0.0, 0.0], [[1.0, 1.0]])


# ------------------------------------------------------------------- active submaps


def _scan() -> np.ndarray:
    """A few returns on a 3 m circle (sensor frame)."""
    a = np.linspace(-2.0, 2.0, 41)
    return 3.0 * np.stack([np.cos(a), np.sin(a)], axis=1)


def _pose(k: int) -> np.ndarray:
    return np.array([0.1 * k, 0.02 * k, 0.01 * k])


def test_two_overlapping_submaps_and_finishing() -> None:
    n = 3
    submaps = ActiveSubmaps(resolution=0.05, scans_per_submap=n)
    assert submaps.matching_submap() is None
    into = submaps.insert(_pose(0), _scan())
    assert [s.index for s in into] == [0]
    first = submaps.matching_submap()
    assert first is not None and first.index == 0
    np.testing.assert_allclose(first.T_local_submap, _pose(0))
    for k in range(1, n):
        submaps.insert(_pose(k), _scan())
    assert len(submaps.active) == 1 and first.num_scans == n
    # Scan n starts the second submap; it goes into both.
    into = submaps.insert(_pose(n), _scan())
    assert [s.index for s in into] == [0, 1]
    second = submaps.active[1]
    np.testing.assert_allclose(second.T_local_submap, _pose(n))
    assert (first.num_scans, second.num_scans) == (n + 1, 1)
    assert submaps.matching_submap() is first  # the older one
    for k in range(n + 1, 2 * n):
        submaps.insert(_pose(k), _scan())
    # The older one is full (2n scans): finished, still matched until replaced.
    assert first.finished and first.grid.frozen and first.num_scans == 2 * n
    assert submaps.matching_submap() is first
    into = submaps.insert(_pose(2 * n), _scan())
    assert [s.index for s in into] == [1, 2]
    assert submaps.finished == [first]
    assert submaps.matching_submap() is second


def test_submap_invariants_over_a_long_run() -> None:
    n = 4
    submaps = ActiveSubmaps(resolution=0.1, scans_per_submap=n)
    memberships: dict[int, list[int]] = {}
    for k in range(37):
        for s in submaps.insert(_pose(k), _scan()):
            memberships.setdefault(k, []).append(s.index)
        assert len(submaps.active) <= 2
    for k, idx in memberships.items():
        assert len(idx) == (1 if k < n else 2), (k, idx)
    for s in submaps.finished:
        assert s.finished and s.num_scans == 2 * n
        np.testing.assert_allclose(s.T_local_submap, _pose(n * s.index))
    assert [s.index for s in submaps.finished] == list(range(len(submaps.finished)))


def test_finished_submaps_can_be_bounded() -> None:
    submaps = ActiveSubmaps(resolution=0.1, scans_per_submap=1, max_finished_submaps=2)
    for k in range(10):
        submaps.insert(_pose(k), _scan())
    assert [s.index for s in submaps.finished] == [6, 7]


def test_a_scan_lands_at_the_same_local_place_in_both_submaps() -> None:
    submaps = ActiveSubmaps(resolution=0.05, scans_per_submap=1)
    submaps.insert([0.3, -0.2, 0.4], _scan())
    T_local_sensor = np.array([1.1, 0.7, -0.8])
    scan = _scan()
    older, newer = submaps.insert(T_local_sensor, scan)
    expected = se2_transform_points(T_local_sensor, scan)
    for submap in (older, newer):
        np.testing.assert_allclose(
            submap.to_local(submap.to_submap(T_local_sensor)), T_local_sensor, atol=1e-12
        )
        hit = submap.grid.data > 0.5
        xs, ys = submap.grid.cell_centers()
        iy, ix = np.nonzero(hit)
        centres_local = se2_transform_points(
            submap.T_local_submap, np.stack([xs[ix], ys[iy]], axis=1)
        )
        # every return lies within a cell diagonal of an occupied cell centre
        d = np.linalg.norm(expected[:, None, :] - centres_local[None, :, :], axis=2).min(axis=1)
        assert d.max() < 0.05 * math.sqrt(0.5) + 1e-9


def test_inserting_into_a_finished_submap_raises() -> None:
    submaps = ActiveSubmaps(resolution=0.1, scans_per_submap=1)
    submaps.insert(_pose(0), _scan())
    submaps.insert(_pose(1), _scan())
    finished = submaps.active[0]
    assert finished.finished
    with pytest.raises(CollabSlamError):
        finished.insert(_pose(2), _scan())


def test_bad_configuration_raises() -> None:
    with pytest.raises(ConfigError):
        ActiveSubmaps(scans_per_submap=0)
    with pytest.raises(ConfigError):
        ActiveSubmaps(max_finished_submaps=-1)


def test_to_submap_is_the_inverse_of_to_local() -> None:
    submaps = ActiveSubmaps()
    submaps.insert([2.0, -1.0, 2.5], _scan())
    submap = submaps.matching_submap()
    assert submap is not None
    T = np.array([3.3, 0.4, -2.9])
    np.testing.assert_allclose(submap.to_local(submap.to_submap(T)), T, atol=1e-12)
    np.testing.assert_allclose(submap.to_submap([2.0, -1.0, 2.5]), [0.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(se2_compose(submap.T_local_submap, [0, 0, 0]), [2.0, -1.0, 2.5])
