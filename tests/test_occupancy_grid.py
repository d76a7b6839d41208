"""Tests for common.occupancy_grid (log-odds grid, ray insertion)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from common.errors import CollabSlamError, ConfigError
from common.occupancy_grid import OccupancyGrid, logodds

RES = 0.1
L_HIT, L_MISS = logodds(0.7), logodds(0.4)
L_MIN, L_MAX = logodds(0.12), logodds(0.97)


def _grid() -> OccupancyGrid:
    return OccupancyGrid.from_bounds((0.0, 0.0), (5.0, 4.0), RES)  # 50 x 40 cells


def _one_beam(grid: OccupancyGrid, pose: list[float], rng: float, **kw: float) -> None:
    grid.insert_scan(
        pose,
        np.array([rng], np.float32),
        np.array([0.0], np.float32),
        kw.get("range_min", 0.05),
        kw.get("range_max", 10.0),
        kw.get("max_free_range"),
    )


def _room_ranges(pose: np.ndarray, angles: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Ranges from `pose` inside the square room [lo, hi]^2 to its walls."""
    a = pose[2] + angles
    d = np.stack([np.cos(a), np.sin(a)], axis=1)
    with np.errstate(divide="ignore"):
        t = np.where(d > 0, (hi - pose[:2]) / d, np.where(d < 0, (lo - pose[:2]) / d, np.inf))
    return t.min(axis=1).astype(np.float32)


def test_single_beam_hit_and_free_cells() -> None:
    grid = _grid()
    _one_beam(grid, [0.25, 0.25, 0.0], 2.0)  # from cell (2, 2) to the hit in cell (22, 2)
    lo = grid.log_odds
    assert lo[2, 22] == pytest.approx(L_HIT)  # the hit cell is not also "free"
    np.testing.assert_allclose(lo[2, 2:22], L_MISS, rtol=1e-6)
    assert np.count_nonzero(lo) == 21  # nothing else touched, nothing beyond the hit
    assert grid.observed.sum() == 21

    for _ in range(3):  # four scans to cross free_thresh 0.196 with p_miss 0.4
        _one_beam(grid, [0.25, 0.25, 0.0], 2.0)
    gm = grid.to_gridmap()
    assert gm.data[2, 22] == 100
    assert np.all(gm.data[2, 2:22] == 0)
    assert np.all(gm.data[2, 23:] == -1) and np.all(gm.data[3] == -1)


def test_each_cell_updated_once_per_scan_and_hits_win() -> None:
    grid = _grid()
    angles = np.linspace(-0.3, 0.3, 200).astype(np.float32)  # many beams share cells
    ranges = np.full(200, 1.5, np.float32)
    ranges[100] = 0.5  # this beam's hit cell lies on the other beams' rays
    grid.insert_scan([1.05, 2.05, 0.0], ranges, angles, 0.05, 10.0)
    lo = grid.log_odds
    values = lo[lo != 0]
    assert np.all(np.isclose(values, L_MISS) | np.isclose(values, L_HIT))
    assert lo[20, 10] == pytest.approx(L_MISS)  # sensor cell: one miss, not 200
    hit_ix = math.floor((1.05 + 0.5 * math.cos(float(angles[100]))) / RES)
    hit_iy = math.floor((2.05 + 0.5 * math.sin(float(angles[100]))) / RES)
    assert lo[hit_iy, hit_ix] == pytest.approx(L_HIT)


def test_traced_cells_follow_the_beam() -> None:
    rng = np.random.default_rng(1)
    for _ in range(50):
        grid = OccupancyGrid.from_bounds((0.0, 0.0), (4.0, 4.0), RES)
        start = rng.uniform(1.5, 2.5, 2)
        yaw = rng.uniform(-math.pi, math.pi)
        r = rng.uniform(0.1, 1.4)
        _one_beam(grid, [start[0], start[1], yaw], r)
        end = start + r * np.array([math.cos(yaw), math.sin(yaw)])
        iy, ix = np.nonzero(grid.observed)
        n_expected = (
            max(
                abs(math.floor(end[0] / RES) - math.floor(start[0] / RES)),
                abs(math.floor(end[1] / RES) - math.floor(start[1] / RES)),
            )
            + 1
        )
        assert len(ix) == n_expected  # one cell per column (or row), none twice
        centres = (np.column_stack([ix, iy]) + 0.5) * RES
        d = end - start
        t = np.clip(((centres - start) @ d) / (d @ d), 0.0, 1.0)
        dist = np.linalg.norm(centres - (start + t[:, None] * d), axis=1)
        assert dist.max() <= RES * math.sqrt(0.5) + 1e-9  # every cell touches the beam
        hit = np.floor(end / RES).astype(int)
        assert grid.log_odds[hit[1], hit[0]] == pytest.approx(L_HIT)


def test_invalid_and_no_return_beams() -> None:
    grid = _grid()
    ranges = np.array([np.nan, np.inf, -np.inf, 0.01], np.float32)
    grid.insert_scan([2.0, 2.0, 0.0], ranges, np.zeros(4, np.float32), 0.05, 3.0)
    assert not grid.observed.any()

    _one_beam(grid, [0.25, 0.25, 0.0], 3.0, range_max=3.0, max_free_range=1.0)  # no return
    lo = grid.log_odds
    assert not np.any(lo > 0)  # no hit anywhere
    np.testing.assert_allclose(lo[2, 2:13], L_MISS, rtol=1e-6)  # cleared up to 1.0 m (x=1.25)
    assert np.count_nonzero(lo) == 11

    grid.clear()
    _one_beam(grid, [0.25, 0.25, 0.0], 7.0, range_max=3.0)  # clears up to range_max
    assert np.count_nonzero(grid.log_odds) == 31 and not np.any(grid.log_odds > 0)

    grid.clear()
    _one_beam(grid, [0.25, 0.25, 0.0], 1.0, range_max=math.inf)  # every finite range hits
    assert grid.log_odds[2, 12] == pytest.approx(L_HIT)


def test_a_beam_angle_not_finite_is_refused() -> None:
    """A NaN angle had marked cell (0, 0) observed and free, with no error."""
    grid = _grid()
    with pytest.raises(CollabSlamError, match="finite"):
        grid.insert_scan([2.5, 2.5, 0.0], np.ones(2, np.float32), np.array([np.nan, 0.0]), 0, 10)
    with pytest.raises(CollabSlamError, match="finite"):
        grid.insert_scans([[2.5, 2.5, 0.0]], np.ones((1, 2)), np.array([0.0, np.inf]), 0, 10)
    assert not grid.observed.any()


def test_rays_leaving_the_grid_are_clipped_without_wraparound() -> None:
    grid = _grid()
    angles = np.linspace(-math.pi, math.pi, 720, endpoint=False).astype(np.float32)
    ranges = np.full(720, 20.0, np.float32)  # every endpoint outside the 5 x 4 m grid
    grid.insert_scan([0.55, 0.35, 0.3], ranges, angles, 0.05, 30.0)
    lo = grid.log_odds
    assert not np.any(lo > 0)  # endpoints outside: no hits
    assert grid.observed[0, :].all() and grid.observed[:, 0].all()
    assert grid.observed[-1, :].all() and grid.observed[:, -1].all()

    outside = OccupancyGrid.from_bounds((0.0, 0.0), (5.0, 4.0), RES)
    # Sensor 3 m left of the grid, looking along +x at y = 2.05 m: enters at x = 0.
    _one_beam(outside, [-3.0, 2.05, 0.0], 4.0)
    np.testing.assert_allclose(outside.log_odds[20, :10], L_MISS, rtol=1e-6)
    assert outside.log_odds[20, 10] == pytest.approx(L_HIT)
    assert np.count_nonzero(outside.log_odds) == 11
    _one_beam(outside, [-3.0, 5.0, 0.0], 10.0)  # passes above the grid entirely
    assert np.count_nonzero(outside.log_odds) == 11


def test_clamping() -> None:
    grid = _grid()
    for _ in range(30):
        _one_beam(grid, [0.25, 0.25, 0.0], 1.0)
    assert grid.log_odds[2, 12] == pytest.approx(L_MAX, rel=1e-6)
    assert grid.log_odds[2, 5] == pytest.approx(L_MIN, rel=1e-6)
    p = grid.probability()
    assert p.dtype == np.float32
    assert p[2, 12] == pytest.approx(0.97, abs=1e-5) and p[2, 5] == pytest.approx(0.12, abs=1e-5)
    assert p[30, 30] == 0.5


def test_square_room_map() -> None:
    grid = OccupancyGrid.from_bounds((-1.0, -1.0), (5.0, 5.0), 0.05)
    angles = np.linspace(-math.pi, math.pi, 1081, endpoint=False).astype(np.float32)
    for x, y, yaw in [
        (1.0, 1.0, 0.0),
        (3.0, 1.2, 1.0),
        (3.0, 3.0, 2.0),
        (1.1, 3.0, -2.0),
        (2.0, 2.0, 0.5),
    ]:
        pose = np.array([x, y, yaw])
        grid.insert_scan(pose, _room_ranges(pose, angles, 0.0, 4.0), angles, 0.1, 10.0)
    gm = grid.to_gridmap()
    occ = gm.cell_to_world(np.argwhere(gm.occupied_mask())[:, ::-1])
    wall_dist = np.minimum(np.abs(occ), np.abs(occ - 4.0)).min(axis=1)
    assert len(occ) > 200 and wall_dist.max() <= 0.05 + 1e-9  # every hit on a wall
    free = gm.cell_to_world(np.argwhere(gm.free_mask())[:, ::-1])
    assert len(free) > 0.8 * (4.0 / 0.05) ** 2  # the room is mapped
    assert np.all((free > -0.05) & (free < 4.05))  # nothing free behind the walls
    outside = gm.sample([[-0.5, -0.5], [4.5, 2.0], [2.0, 4.6]])
    np.testing.assert_array_equal(outside, [-1, -1, -1])


def test_grow_to_include_keeps_content_and_lattice() -> None:
    grid = _grid()
    _one_beam(grid, [0.25, 0.25, 0.0], 2.0)
    before = grid.to_gridmap()
    grid.grow_to_include((1.0, 1.0), (4.0, 3.0), margin=1.0)  # already inside: no-op
    assert grid.shape == (40, 50)
    grid.grow_to_include((-0.33, 0.5), (6.01, 3.0), margin=1.0)
    assert grid.shape == (40, 50 + 14 + 21)
    ox, oy = grid.origin_xy
    assert ox == pytest.approx(-1.4) and oy == 0.0
    after = grid.to_gridmap()
    pts = before.cell_to_world(np.argwhere(before.known_mask())[:, ::-1])
    np.testing.assert_array_equal(after.sample(pts), before.sample(pts))
    assert after.known_mask().sum() == before.known_mask().sum()
    _one_beam(grid, [-1.0, 3.05, 0.0], 7.45)  # new area is usable: hit at x = 6.45
    assert grid.log_odds[30, 78] == pytest.approx(L_HIT)
    assert grid.log_odds[30, 4] == pytest.approx(L_MISS)


def test_clear_and_to_gridmap_unknown() -> None:
    grid = _grid()
    _one_beam(grid, [0.25, 0.25, 0.0], 2.0)
    gm = grid.to_gridmap(occupied_thresh=0.6, free_thresh=0.45)
    assert gm.data[2, 22] == 100 and gm.data[2, 10] == 0
    assert gm.data[10, 10] == -1  # never touched: unknown even if 0.5 were "known"
    assert gm.origin == (0.0, 0.0, 0.0) and gm.resolution == RES
    grid.clear()
    assert not grid.observed.any() and not grid.log_odds.any()
    assert np.all(grid.to_gridmap().data == -1)


def test_validation() -> None:
    with pytest.raises(ConfigError):
        OccupancyGrid(0.1, (0.0, 0.0), (10, 10), p_hit=0.4)
    with pytest.raises(ConfigError):
        OccupancyGrid(0.0, (0.0, 0.0), (10, 10))
    with pytest.raises(ConfigError):
        OccupancyGrid.from_bounds((1.0, 0.0), (0.0, 1.0), 0.1)
    grid = _grid()
    with pytest.raises(CollabSlamError, match="one length"):
        grid.insert_scan([0, 0, 0], np.ones(3), np.ones(4), 0.1, 5.0)
    with pytest.raises(CollabSlamError, match="range_min"):
        grid.insert_scan([0, 0, 0], np.ones(3), np.ones(3), 5.0, 1.0)
    assert OccupancyGrid.from_bounds((0.0, 0.0), (1.0, 0.55), 0.1).shape == (6, 10)


def test_insert_scans_equals_scans_inserted_one_by_one() -> None:
    rng = np.random.default_rng(5)
    k, n = 6, 181
    poses = np.column_stack([rng.uniform(1, 4, k), rng.uniform(1, 4, k), rng.uniform(-3, 3, k)])
    ranges = rng.uniform(0.5, 6.0, (k, n)).astype(np.float32)
    ranges[rng.random((k, n)) < 0.1] = 8.0  # no return: clears up to max_free_range
    angles = np.linspace(-np.pi, np.pi, n, endpoint=False, dtype=np.float32)
    one, many = _grid(), _grid()
    for p, r in zip(poses, ranges, strict=True):
        one.insert_scan(p, r, angles, 0.1, 8.0, max_free_range=5.0)
    many.insert_scans(poses, ranges, angles, 0.1, 8.0, max_free_range=5.0)
    assert one.observed.sum() > 1000
    np.testing.assert_array_equal(many.log_odds, one.log_odds)
    np.testing.assert_array_equal(many.observed, one.observed)
    with pytest.raises(CollabSlamError):
        many.insert_scans(poses[:2], ranges, angles, 0.1, 8.0)
