"""The local keyframe motion filter (agent/motion_filter.py)."""

from __future__ import annotations

import numpy as np

from agent.motion_filter import MotionFilter


def test_a_moving_drone_gets_a_keyframe_every_period_to_the_tick() -> None:
    """Stamps are ticks x 25 ms in floating point: 10 ticks measure 0.25 s give or take
    1e-16 s, which must still count as the 0.25 s period (it slipped a tick in ~0.3 %
    of pairs when compared exactly)."""
    f = MotionFilter(period_s=0.25, min_distance_m=0.01, min_angle_rad=0.01, max_time_s=5.0)
    dt = 0.025
    ticks = [k for k in range(33, 4000) if f.accept(k * dt, np.array([0.04 * k, 0.0, 0.0]))]
    assert np.all(np.diff(ticks) == 10)
    assert (43 * dt - 33 * dt) < 0.25  # the case is there


def test_a_hovering_drone_gets_one_after_max_time_only() -> None:
    f = MotionFilter(period_s=0.25, min_distance_m=0.1, min_angle_rad=0.05, max_time_s=1.0)
    still = np.zeros(3)
    accepted = [k for k in range(200) if f.accept(k * 0.025, still)]
    assert accepted == list(range(0, 200, 40))
    assert f.rejected == 200 - len(accepted)
