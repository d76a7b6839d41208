"""Tests for common.metrics (ATE, map coverage and accuracy)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from common.errors import CollabSlamError
from common.geometry import se2_transform_points
from common.map_io import GridMap
from common.metrics import (
    associate,
    ate_rmse,
    map_accuracy,
    map_accuracy_per_label,
    map_coverage,
    map_walls_found,
)
from common.occupancy_grid import OccupancyGrid
from common.trajectory_io import Trajectory

RES = 0.05


def _world() -> GridMap:
    """A 10 x 8 m building: free inside [0, 10] x [0, 8], walls 2 cells thick around it,
    an inner wall at x = 5 with a door, unknown outside (1 m margin)."""
    h, w = int(10 / RES), int(12 / RES)
    data = np.full((h, w), -1, dtype=np.int8)
    m = int(1 / RES)  # margin cells
    data[m - 2 : h - m + 2, m - 2 : w - m + 2] = 100
    data[m : h - m, m : w - m] = 0
    wall = m + int(5 / RES)
    data[m : h - m, wall : wall + 2] = 100
    data[m + int(3 / RES) : m + int(4 / RES), wall : wall + 2] = 0  # door
    return GridMap(data=data, resolution=RES, origin=(-1.0, -1.0, 0.0))


def _gt(n: int = 100) -> Trajectory:
    t = np.linspace(0.0, 9.9, n)
    poses = np.column_stack([t, np.sin(t), 0.1 * t, 0.3 * t])
    return Trajectory.from_pose4(t, poses)


def test_ate_identical_offset_and_alignment() -> None:
    gt = _gt()
    assert ate_rmse(gt, gt) == pytest.approx(0.0, abs=1e-12)

    p = gt.positions + np.array([0.3, 0.4, 0.0])
    shifted = Trajectory(gt.stamps, p, gt.quats_xyzw)
    assert ate_rmse(shifted, gt) == pytest.approx(0.5)
    assert ate_rmse(shifted, gt, align=True) == pytest.approx(0.0, abs=1e-9)

    xy = se2_transform_points([2.0, -1.0, 0.7], gt.positions[:, :2])
    moved = Trajectory(gt.stamps, np.column_stack([xy, gt.positions[:, 2] + 0.2]), gt.quats_xyzw)
    assert ate_rmse(moved, gt) > 1.0
    assert ate_rmse(moved, gt, align=True) == pytest.approx(0.0, abs=1e-9)

    noisy = Trajectory(gt.stamps, gt.positions + [[0.1, 0, 0], [-0.1, 0, 0]] * 50, gt.quats_xyzw)
    assert ate_rmse(noisy, gt, align=True) == pytest.approx(0.1, abs=1e-3)  # noise stays


def test_ate_needs_two_associated_poses() -> None:
    gt = _gt()
    late = Trajectory.from_pose4([20.0, 21.0, 22.0], np.zeros((3, 4)))
    with pytest.raises(CollabSlamError, match="at least 2 associated poses"):
        ate_rmse(late, gt)
    single = Trajectory.from_pose4([1.0], np.zeros((1, 4)))
    with pytest.raises(CollabSlamError):
        ate_rmse(single, gt)


def test_associate_interpolates_inside_span_only() -> None:
    t_gt = np.array([0.0, 0.1, 0.2, 0.3, 1.0, 1.1])
    yaw = np.array([3.0, 3.1, -3.1, -3.0, 0.0, 0.0])  # crosses +-pi between 0.1 and 0.2
    gt = Trajectory.from_pose4(t_gt, np.column_stack([10 * t_gt, -t_gt, t_gt, yaw]))
    t_est = np.array([-0.05, 0.05, 0.15, 0.6, 1.05, 1.2])
    est = Trajectory.from_pose4(t_est, np.zeros((6, 4)))
    e, g = associate(est, gt, max_dt=0.1)
    assert e.shape == g.shape == (3, 3)  # -0.05 and 1.2 outside span; 0.6 is 0.3 s from gt
    np.testing.assert_allclose(g[:, 0], [0.5, 1.5, 10.5])
    np.testing.assert_allclose(g[:, 1], [-0.05, -0.15, -1.05])
    assert abs(abs(g[1, 2]) - math.pi) < 1e-9  # halfway between 3.1 and -3.1 is pi, not 0
    e4, g4 = associate(est, gt, max_dt=0.1, with_z=True)
    assert g4.shape == (3, 4)
    np.testing.assert_allclose(g4[:, 2], [0.05, 0.15, 1.05])


def test_coverage() -> None:
    world = _world()
    empty = GridMap(np.full((20, 20), -1, np.int8), 0.5, (-1.0, -1.0, 0.0))
    assert map_coverage(empty, world) == 0.0
    assert map_coverage(world, world) == 1.0

    half = world.data.copy()
    half[:, : half.shape[1] // 2] = -1  # only x >= 5 known
    cov = map_coverage(GridMap(half, RES, world.origin), world)
    assert 0.4 < cov < 0.6

    coarse = GridMap(world.data[::2, ::2].copy(), 0.1, (-1.0, -1.0, 0.0))
    assert map_coverage(coarse, world) > 0.97  # other resolution: nearest-cell sampling

    with pytest.raises(CollabSlamError, match="no free cell"):
        map_coverage(world, empty)


def test_coverage_counts_the_wall_surface_but_not_a_wall_where_there_is_none() -> None:
    world = _world()
    m, wall = int(1 / RES), int(6 / RES)  # margin cells; the inner wall's first column
    n_free = np.count_nonzero(world.free_mask())
    thick = world.data.copy()
    thick[m : m + int(3 / RES), wall - 2 : wall] = 100  # 2 cells of surface, up to the door
    drawn = GridMap(thick, RES, world.origin)
    lost = np.count_nonzero(world.free_mask() & ~drawn.free_mask())
    assert lost > 0
    assert map_coverage(drawn, world) == 1.0  # seen, and right within the tolerance
    assert map_coverage(drawn, world, wall_tolerance_m=0.0) == pytest.approx(1 - lost / n_free)

    ghost = world.data.copy()
    ghost[m + 20 : m + 40, m + 20 : m + 40] = 100  # a wall in the middle of a room
    cov = map_coverage(GridMap(ghost, RES, world.origin), world)
    assert cov == pytest.approx(1 - 400 / n_free)
    with pytest.raises(CollabSlamError, match="wall_tolerance_m"):
        map_coverage(world, world, wall_tolerance_m=-0.1)


def test_accuracy_perfect_shifted_and_resampled() -> None:
    world = _world()
    assert map_accuracy(world, world) == 1.0

    assert map_accuracy_per_label(world, world) == (1.0, 1.0)

    shifted = GridMap(world.data, RES, (-0.5, -1.0, 0.0))  # every wall 0.5 m off in x
    assert map_accuracy(shifted, world) < 0.95
    free_acc, occ_acc = map_accuracy_per_label(shifted, world)
    assert occ_acc < 0.7 and free_acc < 0.97  # x-walls wrong, free space outside

    moved = world.data.copy()
    wall = moved[world.height // 2] == 100
    inner = np.flatnonzero(wall)[2:-2]  # the inner wall's columns (outer walls excluded)
    moved[:, inner] = world.data[:, inner - 10]  # inner wall drawn 0.5 m further in +x
    moved[:, inner + 10] = world.data[:, inner]
    free_acc, occ_acc = map_accuracy_per_label(GridMap(moved, RES, world.origin), world)
    assert occ_acc < 0.85 and free_acc == 1.0

    coarse = GridMap(world.data[1::2, 1::2].copy(), 0.1, (-0.95, -0.95, 0.0))
    assert map_accuracy(coarse, world) > 0.99

    empty = GridMap(np.full((5, 5), -1, np.int8), RES, (0.0, 0.0, 0.0))
    with pytest.raises(CollabSlamError, match="no known cell"):
        map_accuracy(empty, world)


def test_accuracy_outside_the_building() -> None:
    world = _world()
    ghost_wall = world.data.copy()
    ghost_wall[:, :10] = 100  # occupied over world-unknown: not counted
    assert map_accuracy(GridMap(ghost_wall, RES, world.origin), world) == 1.0
    seen_through = world.data.copy()
    seen_through[:, :10] = 0  # free over world-unknown: the laser cannot see there
    assert map_accuracy(GridMap(seen_through, RES, world.origin), world) < 0.99


def test_accuracy_of_a_laser_map_with_thin_walls() -> None:
    """Hits land on the wall surface, partly in the free cells next to the drawn walls."""
    world = _world()
    grid = OccupancyGrid.from_bounds((-1.0, -1.0), (11.0, 9.0), RES)
    angles = np.linspace(-math.pi, math.pi, 1440, endpoint=False).astype(np.float32)
    for x in np.linspace(0.7, 4.3, 10):
        for y in (1.0, 4.0, 7.0):
            pose = np.array([x, y, 0.3])
            a = pose[2] + angles.astype(np.float64)
            d = np.column_stack([np.cos(a), np.sin(a)])
            with np.errstate(divide="ignore"):
                hi = np.where(d > 0, ([5.0, 8.0] - pose[:2]) / d, np.inf)
                lo = np.where(d < 0, ([0.0, 0.0] - pose[:2]) / d, np.inf)
            ranges = np.minimum(hi, lo).min(axis=1)  # left room [0, 5] x [0, 8], door ignored
            grid.insert_scan(pose, ranges.astype(np.float32), angles, 0.1, 20.0)
    laser_map = grid.to_gridmap()
    assert laser_map.occupied_mask().sum() > 300
    assert map_accuracy(laser_map, world) > 0.99
    assert map_accuracy(laser_map, world, tolerance_m=0.0) < map_accuracy(laser_map, world)
    assert 0.3 < map_coverage(laser_map, world) < 0.6  # one of the two rooms


def test_the_horizontal_ate_leaves_the_altimeters_noise_out() -> None:
    """The graph is 2-D: a keyframe's height is the altimeter's reading. Its 2 cm noise
    had been most of `summary.json`'s ATE (0.0234 m against 0.0115 m horizontal)."""
    gt = _gt()
    p = gt.positions.copy()
    p[:, 2] += np.random.default_rng(0).normal(0.0, 0.02, len(p))
    est = Trajectory(gt.stamps, p, gt.quats_xyzw)
    assert ate_rmse(est, gt) == pytest.approx(0.02, abs=0.005)
    assert ate_rmse(est, gt, with_z=False) == pytest.approx(0.0, abs=1e-9)


def test_walls_found_sees_a_map_without_walls() -> None:
    """A map that draws every known cell free scores 0.96-0.99 `map_accuracy` (free
    cells over thin walls lie within its tolerance); it finds none of the walls."""
    world = _world()
    assert map_walls_found(world, world) == 1.0
    no_walls = GridMap(np.where(world.data == 100, 0, world.data).astype(np.int8), RES,
                       world.origin)  # fmt: skip
    assert map_accuracy(no_walls, world) > 0.9 and map_walls_found(no_walls, world) == 0.0
    field = GridMap(np.zeros((40, 40), np.int8), RES, (0.0, 0.0, 0.0))  # an open field
    assert map_walls_found(field, field) is None  # (the summary had raised after the mission)


def test_speedups_are_over_the_seeds_both_sides_measured() -> None:
    """One crashed 3-drone run (seed 1, a slow world) had left the 3-drone mean over the
    two fast seeds against the lone drone's over all three: x3.6 for a x3.0 team, and
    30.6 % over a baseline that is 16.7 % slower on every seed."""
    from pathlib import Path

    from benchmarks.exploration import failed_row, speedups
    from common.errors import ProcessError

    def row(n: int, seed: int, t: float) -> dict:
        return {"robots": n, "seed": seed, "time_to_95_s": t}

    lone = [row(1, 0, 30.0), row(1, 1, 120.0), row(1, 2, 120.0)]
    crashed = failed_row(3, 1, ProcessError("agent r2 died"), Path("x"))
    ours = [*lone, row(3, 0, 10.0), crashed, row(3, 2, 40.0)]
    base = [*lone, row(3, 0, 12.0), row(3, 1, 48.0), row(3, 2, 48.0)]
    s = speedups({"ours": ours, "baseline": base}, [1, 3], 400.0)
    assert s["ours_speedup_3"] == pytest.approx(3.0, abs=0.01)
    assert s["ours_faster_than_baseline_pct_3"] == pytest.approx(16.7, abs=0.1)
    assert s["failed_runs"] == 1
