"""The grid search kernels against scipy's csgraph Dijkstra and a numpy line check."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from basestation.grid_search import grid_astar, grid_distances, polyline_free, shortcut


def _csgraph(passable: np.ndarray, cell_m: float, weight: np.ndarray | None = None) -> coo_matrix:
    """The same grid as a sparse graph (each pair of passable 8-neighbours once; a step
    costs its length times the mean `weight` of its two cells)."""
    h, w = passable.shape
    wt = np.ones(passable.shape) if weight is None else weight
    idx = np.arange(h * w).reshape(h, w)
    rows, cols, vals = [], [], []
    for dy, dx, length in (
        (0, 1, 1.0),
        (1, 0, 1.0),
        (1, 1, math.sqrt(2.0)),
        (1, -1, math.sqrt(2.0)),
    ):
        x0, x1 = max(0, -dx), w - max(0, dx)
        both = passable[: h - dy, x0:x1] & passable[dy:, x0 + dx : x1 + dx]
        rows.append(idx[: h - dy, x0:x1][both])
        cols.append(idx[dy:, x0 + dx : x1 + dx][both])
        mean = 0.5 * (wt[: h - dy, x0:x1] + wt[dy:, x0 + dx : x1 + dx])[both]
        vals.append(length * cell_m * mean)
    r, c, v = np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
    return coo_matrix((v, (r, c)), shape=(h * w, h * w))


def _grids(count: int, seed: int):  # noqa: ANN202
    rng = np.random.default_rng(seed)
    for _ in range(count):
        h, w = (int(v) for v in rng.integers(1, 30, 2))
        yield rng, rng.random((h, w)) > rng.uniform(0.0, 0.45)


def test_distances_match_csgraph_dijkstra() -> None:
    for rng, passable in _grids(200, 1):
        n = passable.size
        src = rng.integers(0, n, int(rng.integers(1, 4)))
        dst = rng.integers(0, n, int(rng.integers(1, 6)))
        weight = np.where(rng.random(passable.shape) < 0.3, 3.0, 1.0)  # unknown cells x3
        graph = _csgraph(passable, 0.2, weight).tocsr()
        ref = dijkstra(graph, directed=False, indices=src)[:, dst]
        got = grid_distances(passable, 0.2, src.astype(np.int64), dst.astype(np.int64), weight)
        assert got.shape == ref.shape
        assert np.array_equal(np.isinf(got), np.isinf(ref))
        assert np.allclose(got[np.isfinite(got)], ref[np.isfinite(ref)], rtol=0, atol=1e-9)


def test_astar_path_is_a_shortest_one() -> None:
    found = 0
    for rng, passable in _grids(200, 2):
        h, w = passable.shape
        s, d = (int(v) for v in rng.integers(0, passable.size, 2))
        path = grid_astar(passable, 0.05, s, d, np.inf)
        ref = dijkstra(_csgraph(passable, 0.05).tocsr(), directed=False, indices=s)[d]
        if not (passable.flat[s] and passable.flat[d]) or np.isinf(ref):
            assert len(path) == 0
            continue
        found += 1
        assert path[0] == s and path[-1] == d
        iy, ix = np.divmod(path, w)
        step = np.maximum(np.abs(np.diff(iy)), np.abs(np.diff(ix)))
        assert np.all(step == 1) and passable.flat[path].all()
        diagonal = (np.abs(np.diff(iy)) + np.abs(np.diff(ix))) == 2
        assert np.sum(np.where(diagonal, math.sqrt(2.0), 1.0)) * 0.05 == pytest.approx(
            ref, abs=1e-9
        )
    assert found > 50


def test_astar_respects_the_limit() -> None:
    passable = np.ones((1, 30), dtype=bool)
    assert len(grid_astar(passable, 0.1, 0, 20, 2.05)) == 21
    assert len(grid_astar(passable, 0.1, 0, 20, 1.95)) == 0


def _reference_free(blocked: np.ndarray, origin: np.ndarray, res: float, path: np.ndarray) -> bool:
    """PlanningMap.segment_free as it was written in numpy (quarter-cell samples)."""
    pts = [path] if len(path) == 1 else []
    for a, b in zip(path[:-1], path[1:], strict=True):
        n = max(2, int(math.ceil(np.hypot(*(b - a)) / (0.25 * res))) + 1)
        pts.append(a + np.linspace(0.0, 1.0, n)[:, None] * (b - a))
    ij = np.floor((np.vstack(pts) - origin) / res).astype(np.int64)
    h, w = blocked.shape
    inside = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
    return bool(inside.all() and not blocked[ij[:, 1], ij[:, 0]].any())


def test_polyline_free_matches_the_sampled_check() -> None:
    rng = np.random.default_rng(3)
    blocked_seen = 0
    for _ in range(2000):
        h, w = (int(v) for v in rng.integers(5, 40, 2))
        res = float(rng.choice([0.05, 0.1, 0.2]))
        blocked = rng.random((h, w)) < rng.uniform(0.0, 0.03)
        origin = rng.uniform(-3.0, 3.0, 2).round(int(rng.integers(0, 4)))
        k = int(rng.integers(1, 5))  # points on cell corners, centres and just inside
        cells = rng.integers(-1, max(h, w) + 1, (k, 2)) + rng.choice([0.0, 0.5, 0.25, 1e-9], (k, 2))
        path = origin + cells * res
        want = _reference_free(blocked, origin, res, path)
        blocked_seen += not want
        assert polyline_free(blocked, origin[0], origin[1], res, path) == want
    assert blocked_seen > 200


def test_shortcut_keeps_the_farthest_cell_in_sight() -> None:
    blocked = np.zeros((20, 20), dtype=bool)
    blocked[5:15, 10] = True  # a wall in the middle
    cells = np.array(
        [[x + 0.5, 2.5] for x in range(2, 12)] + [[11.5, y + 0.5] for y in range(3, 18)]
    )
    cells = cells * 0.1
    keep = shortcut(blocked, 0.0, 0.0, 0.1, cells)
    assert keep[0] == 0 and keep[-1] == len(cells) - 1
    for a, b in zip(keep[:-1], keep[1:], strict=True):
        assert polyline_free(blocked, 0.0, 0.0, 0.1, cells[[a, b]])
        if b + 1 < len(cells):  # greedy: the next cell is out of sight
            assert not polyline_free(blocked, 0.0, 0.0, 0.1, cells[[a, b + 1]])
    assert len(keep) < len(cells) // 2
