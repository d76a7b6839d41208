"""Point thinning for scan matching: finite-point checks, a voxel filter keeping one
point per voxel (chosen at random, reproducibly), and Cartographer's adaptive voxel
filter (the largest voxel that still leaves `min_num_points`)."""

from __future__ import annotations

import logging
import math

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from common.errors import CollabSlamError, ConfigError

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]


def finite_points(points: ArrayLike, name: str = "points") -> FloatArray:
    p = np.asarray(points, dtype=np.float64)
    if p.size == 0:
        return np.zeros((0, 2))
    if p.ndim != 2 or p.shape[1] != 2:
        raise CollabSlamError(f"{name} must have shape (N, 2), got {p.shape}")
    finite = np.isfinite(p[:, 0] + p[:, 1])  # NaN and +-inf propagate through the sum
    return p if finite.all() else p[finite]


def check_probability(p: float, name: str = "unknown_probability") -> float:
    if not 0.0 < p < 1.0:
        raise ConfigError(f"{name} must be in (0, 1), got {p}")
    return float(p)


# ----------------------------------------------------------------------------- filters


@njit(cache=True, inline="always")
def _rank(i):  # noqa: ANN001, ANN202 (numba kernel)
    """A fixed pseudo-random 63-bit rank of index i (splitmix64's finalizer)."""
    z = np.uint64(i) + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return np.int64((z ^ (z >> np.uint64(31))) >> np.uint64(1))


@njit(cache=True)
def _one_per_voxel(points, inv_size):
    """Mask of one point of each occupied voxel, chosen at random (a fixed
    pseudo-random rank per index, so the same input gives the same points): an
    open-addressing hash set of the packed voxel keys. Not the first point in input
    order: a scan's points come in beam order, so the first of a voxel sits at its
    clockwise end, and matching such points against submaps built from them turned
    the local SLAM's heading by +0.2-1 deg a minute in the simulator (Cartographer
    also moved to a randomized voxel filter)."""
    n = points.shape[0]
    cap = 16
    while cap < 2 * n:
        cap *= 2
    keys = np.empty(cap, np.int64)
    used = np.zeros(cap, np.bool_)
    best = np.empty(cap, np.int64)  # index of the point kept in the slot's voxel
    best_rank = np.empty(cap, np.int64)
    for i in range(n):
        kx = np.int64(math.floor(points[i, 0] * inv_size))
        ky = np.int64(math.floor(points[i, 1] * inv_size))
        key = (kx << 32) ^ (ky & 0xFFFFFFFF)
        h = ((key * 0x9E3779B97F4A7C15) >> 17) & (cap - 1)
        while used[h] and keys[h] != key:
            h = (h + 1) & (cap - 1)
        r = _rank(i)
        if not used[h]:
            used[h] = True
            keys[h] = key
            best[h] = i
            best_rank[h] = r
        elif r < best_rank[h]:
            best[h] = i
            best_rank[h] = r
    keep = np.zeros(n, np.bool_)
    for h in range(cap):
        if used[h]:
            keep[best[h]] = True
    return keep


def voxel_filter(points: ArrayLike, voxel_size: float) -> FloatArray:
    """Keep one point (`_one_per_voxel`: at random, the same for the same input) of
    every occupied square voxel (m), in input order; non-finite points are dropped."""
    p = finite_points(points)
    return p[voxel_mask(p, voxel_size)] if len(p) else p


def voxel_mask(points: FloatArray, voxel_size: float) -> NDArray[np.bool_]:
    """The mask `voxel_filter` keeps of (N, 2) finite points (m)."""
    return _one_per_voxel(points, 1.0 / voxel_size)


def adaptive_voxel_filter(
    points: ArrayLike,
    max_length: float = 0.5,
    min_num_points: int = 200,
    max_range: float = 50.0,
) -> FloatArray:
    """Cartographer's `AdaptiveVoxelFilter` on (N, 2) sensor-frame points (m).

    Drops non-finite points and points beyond `max_range`. Then it uses the largest
    voxel size <= `max_length` that keeps at least `min_num_points`: it halves the
    size, then binary-searches to within 10 %. If even max_length / 100 keeps too
    few, all points are returned.
    """
    p = finite_points(points)
    p = p[np.einsum("ij,ij->i", p, p) <= max_range * max_range]
    return p[adaptive_voxel_mask(p, max_length, min_num_points)]


def adaptive_voxel_mask(
    points: FloatArray, max_length: float, min_num_points: int
) -> NDArray[np.bool_]:
    """The mask `adaptive_voxel_filter` keeps of (N, 2) finite points (m)."""
    if len(points) <= min_num_points:
        return np.ones(len(points), np.bool_)
    return _adaptive_voxel_mask(points, max_length, min_num_points)


@njit(cache=True)
def _adaptive_voxel_mask(p, max_length, min_num_points):
    """Cartographer's search, as one loop so that _one_per_voxel has one call site
    (every inlined copy adds compile time): halve the voxel size until enough points
    remain, then bisect between the dense (low) and sparse (high) sizes to 10 %."""
    size = high = max_length
    low = 0.0  # largest size known to keep enough points (0: none yet)
    best = np.ones(p.shape[0], np.bool_)  # if no size is dense enough: every point
    while True:
        keep = _one_per_voxel(p, 1.0 / size)
        if keep.sum() >= min_num_points:
            if size == max_length:
                return keep
            low, best = size, keep
        else:
            high = size
        if low == 0.0:
            if high <= 1e-2 * max_length:
                return best
            size = 0.5 * high
        elif high / low <= 1.1:
            return best
        else:
            size = 0.5 * (low + high)


# ------------------------------------------------------------ correlative (numba kernels)
