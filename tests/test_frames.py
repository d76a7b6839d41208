"""map <-> odom transforms of goals and paths (seed 002 eq. 4)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from common.geometry import map_to_odom, odom_to_map, wrap_angle

coord = st.floats(-100, 100)
angle = st.floats(-10, 10)


@settings(max_examples=300, deadline=None)
@given(coord, coord, st.floats(-2, 2), angle, st.integers(0, 10_000))
def test_map_odom_round_trip(x: float, y: float, z: float, yaw: float, seed: int) -> None:
    T = np.array([x, y, z, yaw])
    rng = np.random.default_rng(seed)
    path = np.column_stack([rng.uniform(-50, 50, (20, 3)), rng.uniform(-4, 4, 20)])
    back = odom_to_map(T, map_to_odom(T, path))
    np.testing.assert_allclose(back[:, :3], path[:, :3], atol=1e-9)
    np.testing.assert_allclose(wrap_angle(back[:, 3] - path[:, 3]), 0.0, atol=1e-9)


def test_a_goal_ahead_in_map_is_ahead_in_odom() -> None:
    # the robot's odom frame sits at (10, 0) in map, turned by +90 deg
    T_map_odom = np.array([10.0, 0.0, 0.0, np.pi / 2])
    goal_map = np.array([10.0, 5.0, 1.0, np.pi / 2])  # 5 m "north" of the odom origin
    np.testing.assert_allclose(map_to_odom(T_map_odom, goal_map), [5.0, 0.0, 1.0, 0.0], atol=1e-12)
