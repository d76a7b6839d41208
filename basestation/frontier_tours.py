"""Frontier tours shared out among the robots: who should look at which frontier.

One goal at a time (eq. 3) sends each robot to what is best for it now; the team's
time to explore is that of its robot with the most left to do. `minmax_tours` plans
an open tour through every frontier for each robot, from where it will be free (a
flying robot: its goal, after what is left of its way), so that the longest tour is
as short as it can be made: min-max multiple travelling salesmen, by min-max cheapest
insertion and then moving frontiers between and within tours (relocation, 2-opt)
while the longest tour, then the sum, shrinks. Exploration gives a robot goals from
its own tour only (`basestation/goal_costs.py`, `ExplorationManager._goals`).
A few tens of frontiers and up to ten robots take well under a millisecond (numba).
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray

FAR_M = 1e4  # m standing in for an unreachable pair (inf breaks the sums)


@njit(cache=True)
def _length(r, route, n, offset, S, C):  # noqa: ANN001, ANN202 (numba kernel)
    if n == 0:
        return offset[r]
    total = offset[r] + S[r, route[0]]
    for i in range(n - 1):
        total += C[route[i], route[i + 1]]
    return total


@njit(cache=True)
def _insert_delta(r, route, n, j, p, S, C):  # noqa: ANN001, ANN202
    """Length added to tour r (n frontiers) by frontier j at position p."""
    if n == 0:
        return S[r, j]
    if p == 0:
        return S[r, j] + C[j, route[0]] - S[r, route[0]]
    if p == n:
        return C[route[n - 1], j]
    return C[route[p - 1], j] + C[j, route[p]] - C[route[p - 1], route[p]]


@njit(cache=True)
def _better(a_max, a_sum, b_max, b_sum):  # noqa: ANN001, ANN202
    return a_max < b_max - 1e-9 or (abs(a_max - b_max) <= 1e-9 and a_sum < b_sum - 1e-9)


@njit(cache=True)
def _max_without(lengths, r):  # noqa: ANN001, ANN202
    m = 0.0
    for k in range(len(lengths)):
        if k != r and lengths[k] > m:
            m = lengths[k]
    return m


@njit(cache=True)
def _insert(routes, counts, lengths, r, p, j, offset, S, C):  # noqa: ANN001, ANN202
    """Frontier j into tour r at position p (tours, counts and lengths updated)."""
    n = counts[r]
    for q in range(n, p, -1):
        routes[r, q] = routes[r, q - 1]
    routes[r, p] = j
    counts[r] = n + 1
    lengths[r] = _length(r, routes[r], n + 1, offset, S, C)


@njit(cache=True)
def _solve(offset, S, C, rounds):  # noqa: ANN001, ANN202
    R, N = S.shape
    routes = np.full((R, N), -1, np.int64)
    counts = np.zeros(R, np.int64)
    lengths = offset.copy()
    placed = np.zeros(N, np.bool_)
    for _ in range(N):  # min-max cheapest insertion
        best_max, best_add, bj, br, bp = np.inf, np.inf, -1, -1, -1
        for j in range(N):
            if placed[j]:
                continue
            for r in range(R):
                rest = _max_without(lengths, r)
                for p in range(counts[r] + 1):
                    add = _insert_delta(r, routes[r], counts[r], j, p, S, C)
                    new_max = max(rest, lengths[r] + add)
                    if _better(new_max, add, best_max, best_add):
                        best_max, best_add, bj, br, bp = new_max, add, j, r, p
        _insert(routes, counts, lengths, br, bp, bj, offset, S, C)
        placed[bj] = True
    for _ in range(rounds):  # relocation and 2-opt while (max, sum) shrinks
        improved = False
        for a in range(R):
            i = 0
            while i < counts[a]:
                j = routes[a, i]
                # tour a without its i-th frontier
                tmp = np.empty(N, np.int64)
                m = 0
                for q in range(counts[a]):
                    if q != i:
                        tmp[m] = routes[a, q]
                        m += 1
                len_a = _length(a, tmp, m, offset, S, C)
                cur_max, cur_sum = lengths.max(), lengths.sum()
                best_max, best_sum, br, bp = cur_max, cur_sum, -1, -1
                for r in range(R):
                    base = len_a if r == a else lengths[r]
                    route = tmp if r == a else routes[r]
                    n = m if r == a else counts[r]
                    for p in range(n + 1):
                        if r == a and p == i:
                            continue
                        new_r = base + _insert_delta(r, route, n, j, p, S, C)
                        new_max, new_sum = 0.0, 0.0
                        for k in range(R):
                            v = new_r if k == r else (len_a if k == a else lengths[k])
                            new_max = max(new_max, v)
                            new_sum += v
                        if _better(new_max, new_sum, best_max, best_sum):
                            best_max, best_sum, br, bp = new_max, new_sum, r, p
                if br < 0:
                    i += 1
                    continue
                routes[a, :m] = tmp[:m]
                routes[a, m:] = -1
                counts[a] = m
                lengths[a] = len_a
                _insert(routes, counts, lengths, br, bp, j, offset, S, C)
                improved = True
        for r in range(R):  # 2-opt: reverse a stretch of one tour
            n = counts[r]
            for i in range(n - 1):
                for k in range(i + 1, n):
                    seg = routes[r, i : k + 1][::-1].copy()
                    trial = routes[r, :n].copy()
                    trial[i : k + 1] = seg
                    new_len = _length(r, trial, n, offset, S, C)
                    if new_len < lengths[r] - 1e-9:
                        routes[r, :n] = trial
                        lengths[r] = new_len
                        improved = True
        if not improved:
            break
    return routes, counts, lengths


def minmax_tours(
    offset: NDArray[np.float64],
    start: NDArray[np.float64],
    between: NDArray[np.float64],
    rounds: int = 20,
) -> tuple[list[list[int]], NDArray[np.float64]]:
    """Open tours through every frontier, one per robot, the longest as short as the
    heuristic makes it. `offset` (R,) m each robot still has to fly before it is free;
    `start` (R, N) m from each robot (where it will be free) to each frontier;
    `between` (N, N) m between frontiers (inf: unreachable). Returns each robot's tour
    (frontier indices in visiting order) and each tour's length (m, with the offset)."""
    S = np.nan_to_num(np.asarray(start, dtype=np.float64), posinf=FAR_M)
    C = np.nan_to_num(np.asarray(between, dtype=np.float64), posinf=FAR_M)
    off = np.asarray(offset, dtype=np.float64).copy()
    R, N = S.shape
    if R == 0 or N == 0:
        return [[] for _ in range(R)], off
    routes, counts, lengths = _solve(off, S, C, rounds)
    return [routes[r, : counts[r]].tolist() for r in range(R)], lengths
