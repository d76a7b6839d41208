"""The agent's safety guard: never fly into what the live scan shows."""

from __future__ import annotations

import numpy as np

from agent.safety_guard import SafetyGuard

ANGLES = np.linspace(-np.radians(135.0), np.radians(135.0), 1081)


def _guard() -> SafetyGuard:
    return SafetyGuard(
        radius_m=0.25, margin_m=0.05, max_accel=1.0, reaction_s=0.1, blocked_after_s=2.0
    )


def _wall_ranges(x_wall: float) -> np.ndarray:
    """A wall across the way at x = x_wall (body frame), nothing else in range."""
    with np.errstate(divide="ignore"):
        r = x_wall / np.cos(ANGLES)
    return np.where((np.cos(ANGLES) > 0.05) & (r < 30.0), r, np.inf)


def test_far_wall_does_not_slow_the_drone() -> None:
    g = _guard()
    g.update(ANGLES, _wall_ranges(20.0))
    assert g.limit(0.0, 1.0, 0.0) == (1.0, 0.0)


def test_speed_toward_a_wall_allows_stopping_before_it() -> None:
    g = _guard()
    for x_wall in (0.5, 0.8, 1.2, 2.0):
        g.update(ANGLES, _wall_ranges(x_wall))
        vx, vy = g.limit(0.0, 1.0, 0.0)
        room = x_wall - 0.30 - 0.05  # disc edge at corridor half-width, stop margin
        # flying at vx for the reaction time, then braking at 1 m/s^2, stays within room
        assert vx * 0.1 + vx**2 / 2.0 <= max(room, 0.0) + 1e-6, (x_wall, vx)
        assert abs(vy) < 1e-9
    g.update(ANGLES, _wall_ranges(3.0))
    assert g.limit(0.0, 1.0, 0.0)[0] == 1.0  # far enough: full speed


def test_wall_alongside_does_not_stop_motion_parallel_to_it() -> None:
    # a wall 0.4 m to the left, parallel to x: beyond the 0.30 m corridor
    g = _guard()
    with np.errstate(divide="ignore"):
        r = 0.4 / np.sin(ANGLES)
    g.update(ANGLES, np.where((np.sin(ANGLES) > 0.05) & (r < 30.0), r, np.inf))
    vx, vy = g.limit(0.0, 1.0, 0.0)
    assert vx == 1.0 and vy == 0.0


def test_no_motion_toward_a_point_already_too_close() -> None:
    g = _guard()
    ranges = np.full(len(ANGLES), np.inf)
    ranges[np.argmin(np.abs(ANGLES - np.pi / 2))] = 0.2  # a point 0.2 m to the left
    g.update(ANGLES, ranges)
    vx, vy = g.limit(0.0, 0.0, 0.5)  # asked to move left, into it
    assert abs(vy) < 1e-9 and abs(vx) < 1e-9
    vx, vy = g.limit(0.0, 0.0, -0.5)  # moving away is fine
    assert vy == -0.5


def test_held_still_long_enough_is_blocked_and_a_new_path_clears_it() -> None:
    g = _guard()
    g.update(ANGLES, _wall_ranges(0.3))
    for t in np.arange(0.0, 1.9, 0.1):
        g.limit(float(t), 1.0, 0.0)
        assert not g.blocked
    g.limit(2.05, 1.0, 0.0)
    assert g.blocked
    g.clear()
    assert not g.blocked
    g.update(ANGLES, _wall_ranges(10.0))
    g.limit(2.1, 1.0, 0.0)
    assert not g.blocked
