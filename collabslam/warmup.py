"""Compiles the numba kernels once, for `make venv` (`python -m collabslam.warmup`): else
the first exploring mission compiles them inside the base station (a slower start,
more memory). Called with each kernel's own signature, so that one that changes fails
here (tests/test_warmup.py) rather than leaving its warm-up silently undone."""

from __future__ import annotations

import numpy as np

from basestation import grid_search
from basestation.frontier_tours import minmax_tours


def main() -> None:
    minmax_tours(np.zeros(2), np.ones((2, 2)), np.ones((2, 2)))
    passable, xy, cells = np.ones((3, 3), bool), np.zeros((2, 2)), np.zeros(1, np.int64)
    grid_search.grid_distances(passable, 0.2, cells, cells, np.ones((3, 3)))
    grid_search.grid_astar(passable, 0.05, 0, 8, np.inf)
    grid_search.polyline_free(passable, 0.0, 0.0, 0.05, xy)
    grid_search.shortcut(passable, 0.0, 0.0, 0.05, xy)
    print("numba kernels compiled")


if __name__ == "__main__":
    main()
