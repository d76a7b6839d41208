"""Branch and bound over max-pooled score pyramids (Cartographer's
`FastCorrelativeScanMatcher2D`, Olson 2009), as numba kernels for
`agent.correlative_matcher`: the k best lattice poses (angle index, cell offsets) of
a discretized scan in a window, exactly as an exhaustive search would rank them.

`levels[k]` is the pyramid level whose cell holds the max over a 2^k x 2^k block of
full-resolution cells (uint8, 255 = probability 1); `flat[a, i]` the index of scan
point i at angle a in a level (row width `w`); a node (a, dx, dy, k) covers offsets
[dx, dx + 2^k) x [dy, dy + 2^k) at angle a. With k > 1 best poses, a leaf within
`sep` cells and `sep_a` angle steps of a kept one counts as that one (non-maximum
suppression), so the k are distinct places, not one peak's neighbours.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def _node_score(level, flat, a, off, n):
    acc = 0
    for i in range(n):
        acc += level[flat[a, i] + off]
    return acc / (255.0 * n)


@njit(cache=True)
def _bound(levels, flat, a, dx, dy, k, w, win, ang_cost, lin_coef):
    """Upper bound of the penalized score over the node: angle a, offsets
    [dx, dx + 2^k) x [dy, dy + 2^k) clipped to the window (exact when k == 0)."""
    near = 0.0
    for d in (dx, dy):
        hi = min(d + (1 << k) - 1, win)
        if not d <= 0 <= hi:
            m = min(abs(d), abs(hi))
            near += m * m
    f = ang_cost[a] + lin_coef * math.sqrt(near)
    return math.exp(-f * f) * _node_score(levels[k], flat, a, dy * w + dx, flat.shape[1])


@njit(cache=True)
def _argsort(x):
    """Indices sorting x ascending (Shell sort: np.argsort costs seconds of compile)."""
    n = x.shape[0]
    idx = np.arange(n)
    gap = n // 2
    while gap > 0:
        for i in range(gap, n):
            j, k = i, idx[i]
            while j >= gap and x[idx[j - gap]] > x[k]:
                idx[j] = idx[j - gap]
                j -= gap
            idx[j] = k
        gap //= 2
    return idx


@njit(cache=True)
def _keep(best, best_s, n, a, dx, dy, s, sep, sep_a, n_ang):
    """Offer leaf (a, dx, dy) with score s to the k best (descending, n kept; all
    leaves closer than sep cells and sep_a angle steps to a kept one count as that
    one, non-maximum suppression). Returns the new count."""
    k = best_s.shape[0]
    for i in range(n):
        da = abs(a - best[i, 0])
        da = min(da, n_ang - da)  # a full circle of headings wraps
        if da <= sep_a and abs(dx - best[i, 1]) <= sep and abs(dy - best[i, 2]) <= sep:
            if s <= best_s[i]:
                return n
            n -= 1  # the better leaf takes its neighbour's place
            for j in range(i, n):
                best[j, :], best_s[j] = best[j + 1, :], best_s[j + 1]
            break
    j = min(n, k - 1)
    while j > 0 and best_s[j - 1] < s:
        best[j, :], best_s[j] = best[j - 1, :], best_s[j - 1]
        j -= 1
    best[j, 0], best[j, 1], best[j, 2], best_s[j] = a, dx, dy, s
    return min(n + 1, k)


@njit(cache=True)
def branch_and_bound(levels, flat, w, win, depth, ang_cost, lin_coef, min_score, k, sep, sep_a):
    """The k best (angle index, dx, dy) and scores > min_score, at least sep cells or
    sep_a angle steps apart (count first, then arrays in descending score order).
    Depth-first, best child first, pruning nodes whose bound <= the k-th best leaf."""
    n_ang = flat.shape[0]
    step = 1 << depth
    per_axis = (2 * win) // step + 1
    n_root = n_ang * per_axis * per_axis
    root = np.empty((n_root, 3), np.int64)
    root_s = np.empty(n_root)
    r = 0
    for a in range(n_ang):
        for ix in range(per_axis):
            for iy in range(per_axis):
                dx, dy = -win + ix * step, -win + iy * step
                root[r, 0], root[r, 1], root[r, 2] = a, dx, dy
                root_s[r] = _bound(levels, flat, a, dx, dy, depth, w, win, ang_cost, lin_coef)
                r += 1
    cap = n_root + 4 * (depth + 1)
    st = np.empty((cap, 4), np.int64)  # angle, dx, dy, depth
    st_s = np.empty(cap)
    order = _argsort(root_s)  # ascending: the best root is popped first
    for j in range(n_root):
        q = order[j]
        st[j, 0], st[j, 1], st[j, 2], st[j, 3] = root[q, 0], root[q, 1], root[q, 2], depth
        st_s[j] = root_s[q]
    sp = n_root
    best = np.zeros((k, 3), np.int64)
    best_s = np.full(k, min_score)
    n = 0
    floor = min_score  # the k-th best score once k are kept
    ch = np.empty((4, 2), np.int64)
    ch_s = np.empty(4)
    while sp > 0:
        sp -= 1
        a, dx, dy, d = st[sp, 0], st[sp, 1], st[sp, 2], st[sp, 3]
        if st_s[sp] <= floor:
            continue
        if d == 0:
            n = _keep(best, best_s, n, a, dx, dy, st_s[sp], sep, sep_a, n_ang)
            floor = best_s[k - 1] if n == k else min_score
            continue
        half = 1 << (d - 1)
        m = 0
        for cx in (dx, dx + half):
            for cy in (dy, dy + half):
                if cx > win or cy > win:
                    continue
                s = _bound(levels, flat, a, cx, cy, d - 1, w, win, ang_cost, lin_coef)
                j = m  # insertion sort, ascending
                while j > 0 and ch_s[j - 1] > s:
                    ch[j, 0], ch[j, 1], ch_s[j] = ch[j - 1, 0], ch[j - 1, 1], ch_s[j - 1]
                    j -= 1
                ch[j, 0], ch[j, 1], ch_s[j] = cx, cy, s
                m += 1
        for j in range(m):
            if ch_s[j] > floor:
                st[sp, 0], st[sp, 1], st[sp, 2], st[sp, 3] = a, ch[j, 0], ch[j, 1], d - 1
                st_s[sp] = ch_s[j]
                sp += 1
    return n, best, best_s
