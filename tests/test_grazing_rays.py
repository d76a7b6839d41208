"""Grazing rays do not erode the walls they run along (agent/probability_grid.py)."""

from __future__ import annotations

import math

import numpy as np

from agent.probability_grid import GRAZING_TAIL_MAX_M, ProbabilityGrid, grazing_tails
from agent.scan_matcher import ScanMatcher

HALF_WIDTH = 1.525  # m, a ~3 m corridor along +x, its walls mid-cell


def corridor_scan(x: float, max_range: float = 30.0) -> np.ndarray:
    """Sensor-frame hits (beam order, 0.25 degree beams over 270 degrees) of a sensor at
    (x, 0) facing +x in an endless corridor."""
    a = np.radians(np.arange(-135.0, 135.0, 0.25))
    s = np.sin(a)
    with np.errstate(divide="ignore"):
        r = np.where(np.abs(s) > 1e-9, HALF_WIDTH / np.abs(s), np.inf)
    keep = r < max_range
    return np.column_stack([np.cos(a[keep]), s[keep]]) * r[keep, None]


def test_tails_follow_the_incidence_and_stop_at_depth_edges() -> None:
    res = 0.05
    wall = np.column_stack([np.linspace(2.0, 20.0, 61), np.full(61, HALF_WIDTH)])
    tails = grazing_tails(wall, res, 2.0)
    rng = np.hypot(wall[:, 0], wall[:, 1])
    sin_a = HALF_WIDTH / rng
    want = np.minimum(2.0 * res / sin_a, GRAZING_TAIL_MAX_M) / rng
    assert tails[0] == 0.0 and tails[-1] == 0.0  # no neighbour on one side
    np.testing.assert_allclose(tails[1:-1], want[1:-1], rtol=1e-9)
    assert tails[-2] > 0.05  # a far grazing hit keeps ~1.3 m of its 20 m ray
    facing = np.column_stack([np.full(21, 3.0), np.linspace(-1.0, 1.0, 21)])
    assert np.all(grazing_tails(facing, res, 2.0)[1:-1] < 0.04)  # ~0.1 m of 3 m
    edge = wall.copy()
    edge[1::2, 1] += 0.3  # every other hit on another surface: no line, all cleared
    assert np.all(grazing_tails(edge, res, 2.0) == 0.0)
    assert np.all(grazing_tails(wall, res, 0.0) == 0.0)


def _corridor_grid(keep_cells: float, n_scans: int = 60, step: float = 0.05) -> ProbabilityGrid:
    grid = ProbabilityGrid(0.05, (-2.0, -2.0), (80, 80))
    for i in range(n_scans):
        grid.insert([i * step, 0.0, 0.0], corridor_scan(i * step), grazing_keep_cells=keep_cells)
    return grid


def _wall_probability(grid: ProbabilityGrid, x0: float, x1: float) -> float:
    """Mean over the wall's cells between x0 and x1 of its surest row (the hits fall on
    either side of the wall's line with rounding)."""
    xs, ys = grid.cell_centers()
    rows = np.abs(ys - HALF_WIDTH) < 0.05
    cols = (xs > x0) & (xs < x1)
    p = grid.probability(unknown=0.0)[np.ix_(rows, cols)]
    return float(p.max(axis=0).mean())


def test_walls_ahead_keep_their_hits_and_the_match_stays_on_odometry() -> None:
    """Cartographer's insertion (0) clears the corridor's walls ahead with the tails of
    grazing rays. The match then looks constrained along the corridor (its sigma under
    the remapping limit) and moves off the true pose; with the tails kept, the walls
    ahead stay walls, the corridor reads as unconstrained and the prediction is kept."""
    x_last = 59 * 0.05
    truth = np.array([x_last + 0.05, 0.0, 0.0])
    out = {}
    for keep in (0.0, 2.0):
        grid = _corridor_grid(keep)
        matcher = ScanMatcher()
        m = matcher.match(grid, corridor_scan(truth[0]), truth)
        sigma_along = math.sqrt(m.covariance[0, 0])
        out[keep] = (_wall_probability(grid, x_last + 6.0, x_last + 12.0), sigma_along, m.pose)
    limit = ScanMatcher().unconstrained_sigma_xy
    wall0, sigma0, pose0 = out[0.0]
    wall2, sigma2, pose2 = out[2.0]
    assert wall2 > 0.8 and wall0 < 0.7  # the wall 6-12 m ahead: a wall, or eroded
    assert sigma2 > limit > sigma0
    np.testing.assert_allclose(pose2, truth, atol=1e-4)
    assert pose0[0] - truth[0] < -0.02  # slid back towards the surer walls
