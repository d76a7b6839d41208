"""Shortest paths on a grid of passable cells, 8-connected (numba kernels).

A cell is a node; it is joined to each of its 8 neighbours that is passable too, by
`cell_m` straight and `cell_m` x sqrt(2) diagonally (a diagonal step between two
passable cells is allowed whatever the two cells beside it are, as a grid path's
corners are cut by its shortcutting anyway). Cells are numbered row by row
(`iy * w + ix`).

`grid_distances` is Dijkstra from each source, stopped once every target is settled;
`grid_astar` is A* with the octile distance (consistent on this grid, so the path is
a shortest one) from one cell to another. Both keep an indexed binary heap keyed by
(cost, cell), so equal costs are taken in cell order: the same question always gets
the same answer. Written out here rather than run through scipy's csgraph, which
needs the graph built as a sparse matrix first: an exploration step asks for paths
and distances hundreds of times, and building the graph cost more than the search.
Both searches share one kernel (`_search`), the neighbour loop written out in it:
moved into helper functions, numba ran it at half the speed.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

SQRT2 = math.sqrt(2.0)
_DY = np.array([0, 0, 1, -1, 1, 1, -1, -1], dtype=np.int64)
_DX = np.array([1, -1, 0, 0, 1, -1, 1, -1], dtype=np.int64)
_DIAGONAL = np.array([False, False, False, False, True, True, True, True])


@njit(cache=True)
def _before(key: NDArray[np.float64], a: int, b: int) -> bool:
    return key[a] < key[b] or (key[a] == key[b] and a < b)


@njit(cache=True, inline="always")
def _put(heap, pos, i, node):  # noqa: ANN001, ANN202 (numba kernel)
    """Cell `node` at heap slot `i`."""
    heap[i] = node
    pos[node] = i


@njit(cache=True)
def _sift_up(heap, pos, key, i):  # noqa: ANN001, ANN202 (numba kernel)
    node = heap[i]
    while i > 0:
        parent = (i - 1) >> 1
        if not _before(key, node, heap[parent]):
            break
        _put(heap, pos, i, heap[parent])
        i = parent
    _put(heap, pos, i, node)


@njit(cache=True)
def _pop(heap, pos, key, size):  # noqa: ANN001, ANN202 (numba kernel)
    """Remove and return the first cell of the heap of `size` cells."""
    top = heap[0]
    pos[top] = -1
    size -= 1
    if size == 0:
        return top
    node = heap[size]
    i = 0
    while True:
        child = 2 * i + 1
        if child >= size:
            break
        if child + 1 < size and _before(key, heap[child + 1], heap[child]):
            child += 1
        if not _before(key, heap[child], node):
            break
        _put(heap, pos, i, heap[child])
        i = child
    _put(heap, pos, i, node)
    return top


@njit(cache=True)
def _search(flat, wt, h, w, cell_m, src, wanted, left, goal, limit_m, g, f, pred, done, heap, pos):  # noqa: ANN001, ANN202, E501 (numba kernel)
    """Settle cells from `src` (g: cost so far, `pred`: the cell before) until the
    `left` cells marked `wanted` are settled or no cell is left within `limit_m`;
    returns how many wanted cells were not reached. `goal` >= 0: A*, the heap keyed
    by g plus the octile distance to `goal`; -1: Dijkstra, keyed by g. `g` and `f` are
    inf, `done` False and `pos` -1 everywhere on entry; `pos` is -1 again on return.
    One loop for both searches: moved into helper functions, numba ran it at half
    the speed."""
    gy, gx = (goal // w, goal % w) if goal >= 0 else (0, 0)
    g[src] = 0.0
    f[src] = 0.0
    heap[0] = src
    pos[src] = 0
    size = 1
    while size > 0 and left > 0:
        u = _pop(heap, pos, f, size)
        size -= 1
        done[u] = True
        if wanted[u]:
            left -= 1
        if not flat[u]:
            continue
        uy, ux = u // w, u % w
        for d in range(8):
            vy, vx = uy + _DY[d], ux + _DX[d]
            if vy < 0 or vy >= h or vx < 0 or vx >= w:
                continue
            v = vy * w + vx
            if done[v] or not flat[v]:
                continue
            ng = g[u] + (cell_m * SQRT2 if _DIAGONAL[d] else cell_m) * 0.5 * (wt[u] + wt[v])
            if ng < g[v] and ng <= limit_m:
                g[v] = ng
                pred[v] = u
                if goal >= 0:  # + the octile distance (summed in this order: same keys)
                    ay, ax = abs(vy - gy), abs(vx - gx)
                    f[v] = ng + cell_m * (max(ay, ax) - min(ay, ax)) + cell_m * SQRT2 * min(ay, ax)
                else:
                    f[v] = ng
                if pos[v] < 0:
                    heap[size] = v
                    size += 1
                    _sift_up(heap, pos, f, size - 1)
                else:
                    _sift_up(heap, pos, f, pos[v])
    while size > 0:  # stopped early: empty the heap
        size -= 1
        pos[heap[size]] = -1
    return left


@njit(cache=True)
def grid_distances(
    passable: NDArray[np.bool_],
    cell_m: float,
    sources: NDArray[np.int64],
    targets: NDArray[np.int64],
    weight: NDArray[np.float64],
) -> NDArray[np.float64]:
    """(len(sources), len(targets)) shortest distances (m) between cells (`inf`:
    not connected), a step between two cells costing its length times the mean of
    their `weight`s (>= 1, the shape of `passable`); a source or target on a cell that
    is not passable reaches only itself."""
    h, w = passable.shape
    n = h * w
    flat = passable.ravel()
    wt = weight.ravel()
    out = np.full((len(sources), len(targets)), np.inf)
    g, f = np.empty(n), np.empty(n)
    pred = np.empty(n, dtype=np.int64)
    done = np.empty(n, dtype=np.bool_)
    heap = np.empty(n, dtype=np.int64)
    pos = np.full(n, -1, dtype=np.int64)
    wanted = np.zeros(n, dtype=np.bool_)
    left = 0
    for t in targets:
        if not wanted[t]:
            wanted[t] = True
            left += 1
    for k in range(len(sources)):
        g[:] = np.inf
        f[:] = np.inf
        done[:] = False
        _search(
            flat,
            wt,
            h,
            w,
            cell_m,
            sources[k],
            wanted,
            left,
            -1,
            np.inf,
            g,
            f,
            pred,
            done,
            heap,
            pos,
        )
        for j in range(len(targets)):
            out[k, j] = g[targets[j]]
    return out


@njit(cache=True)
def grid_astar(
    passable: NDArray[np.bool_], cell_m: float, src: int, dst: int, limit_m: float
) -> NDArray[np.int64]:
    """The cells of a shortest path from cell `src` to cell `dst` (both ends
    included), over passable cells only and at most `limit_m` long; empty if there
    is none."""
    h, w = passable.shape
    n = h * w
    flat = passable.ravel()
    if not (flat[src] and flat[dst]):
        return np.empty(0, dtype=np.int64)
    g, f = np.full(n, np.inf), np.full(n, np.inf)
    pred = np.full(n, -1, dtype=np.int64)
    done = np.zeros(n, dtype=np.bool_)
    heap = np.empty(n, dtype=np.int64)
    pos = np.full(n, -1, dtype=np.int64)
    wanted = np.zeros(n, dtype=np.bool_)
    wanted[dst] = True
    wt = np.ones(n)
    if _search(flat, wt, h, w, cell_m, src, wanted, 1, dst, limit_m, g, f, pred, done, heap, pos):
        return np.empty(0, dtype=np.int64)
    count = 1
    v = dst
    while v != src:
        v = pred[v]
        count += 1
    path = np.empty(count, dtype=np.int64)
    v = dst
    for i in range(count - 1, -1, -1):
        path[i] = v
        if i > 0:
            v = pred[v]
    return path


@njit(cache=True)
def _segment_free(blocked, ox, oy, resolution, ax, ay, bx, by):  # noqa: ANN001, ANN202
    h, w = blocked.shape
    n = max(2, int(math.ceil(math.hypot(bx - ax, by - ay) / (0.25 * resolution))) + 1)
    step = 1.0 / (n - 1)
    dx, dy = bx - ax, by - ay
    for i in range(n):
        t = 1.0 if i == n - 1 else i * step
        ix = int(math.floor(((ax + t * dx) - ox) / resolution))
        iy = int(math.floor(((ay + t * dy) - oy) / resolution))
        if ix < 0 or ix >= w or iy < 0 or iy >= h or blocked[iy, ix]:
            return False
    return True


@njit(cache=True)
def polyline_free(
    blocked: NDArray[np.bool_], ox: float, oy: float, resolution: float, path: NDArray[np.float64]
) -> bool:
    """Whether every point along the polyline `path` ((N, 2), m), sampled every quarter
    cell or closer (each segment from its start to its end, both included), lies
    inside the grid on a cell that is not `blocked` (cell (0, 0) with its corner at
    (`ox`, `oy`))."""
    if len(path) == 1:
        return _segment_free(
            blocked, ox, oy, resolution, path[0, 0], path[0, 1], path[0, 0], path[0, 1]
        )
    for k in range(len(path) - 1):
        a, b = path[k], path[k + 1]
        if not _segment_free(blocked, ox, oy, resolution, a[0], a[1], b[0], b[1]):
            return False
    return True


@njit(cache=True)
def shortcut(
    blocked: NDArray[np.bool_], ox: float, oy: float, resolution: float, path: NDArray[np.float64]
) -> NDArray[np.int64]:
    """Indices of the points of `path` kept by greedy shortcutting: from each kept
    point, the farthest later point still in free sight of it (`polyline_free`)."""
    keep = np.empty(len(path), dtype=np.int64)
    keep[0] = 0
    count, i = 1, 0
    while i < len(path) - 1:
        j = i + 1
        while j + 1 < len(path) and _segment_free(
            blocked, ox, oy, resolution, path[i, 0], path[i, 1], path[j + 1, 0], path[j + 1, 1]
        ):
            j += 1
        keep[count] = j
        count += 1
        i = j
    return keep[:count]
