"""Hand-made occupancy grids shared by the exploration tests."""

from __future__ import annotations

import numpy as np

from common.map_io import GridMap


def grid_with_wall() -> GridMap:
    """10 x 10 m free, a wall at y = 5 m from x = 0 to 8 m."""
    data = np.zeros((200, 200), np.int8)
    data[100:102, :160] = 100
    return GridMap(data, 0.05, (0.0, 0.0, 0.0))
