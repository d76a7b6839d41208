"""Quadrotor kinematics: limits, body frame, attitude, wall contacts."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from common.errors import ConfigError
from common.map_io import GridMap
from simulation.quadrotor import Quadrotor
from simulation.world import World

DT = 0.02


@pytest.fixture(scope="module")
def hall() -> World:
    """20 x 10 m room, walls one cell thick at origin (0, 0): inner faces at x = 0.05,
    x = 19.95, y = 0.05, y = 9.95; a 1 x 1 m pillar at x 14..15, y 4..5."""
    data = np.full((200, 400), 100, dtype=np.int8)
    data[1:-1, 1:-1] = 0
    data[80:100, 280:300] = 100
    return World(GridMap(data=data, resolution=0.05, origin=(0.0, 0.0, 0.0)))


def fly(q: Quadrotor, world: World, cmd: list[float], seconds: float) -> list[np.ndarray]:
    vel = []
    for _ in range(round(seconds / DT)):
        q.step(cmd, DT, world)
        vel.append(q.velocity_world.copy())
    return vel


def test_reaches_commanded_velocity_within_accel_limit(hall: World) -> None:
    q = Quadrotor([3.0, 5.0, 1.0, 0.0], max_accel=1.0)
    vel = np.array([np.zeros(3), *fly(q, hall, [0.8, 0.0, 0.0, 0.0], 3.0)])
    np.testing.assert_allclose(q.velocity_body, [0.8, 0.0, 0.0], atol=1e-3)
    accel = np.linalg.norm(np.diff(vel[:, :2], axis=0), axis=1) / DT
    assert accel.max() <= 1.0 + 1e-9
    assert accel.max() > 0.9  # the limit is actually reached at the start
    assert q.collisions == 0 and q.min_clearance > 1.0


def test_speed_limits_clip_commands(hall: World) -> None:
    q = Quadrotor([3.0, 5.0, 1.0, 0.0], max_speed=1.0, max_vertical_speed=0.5, max_yaw_rate=1.0)
    fly(q, hall, [3.0, 3.0, 2.0, 0.0], 3.0)
    assert np.linalg.norm(q.velocity_world[:2]) == pytest.approx(1.0, abs=1e-3)
    np.testing.assert_allclose(
        q.velocity_world[:2] / np.linalg.norm(q.velocity_world[:2]), [math.sqrt(0.5)] * 2
    )  # direction kept
    assert q.velocity_world[2] == pytest.approx(0.5, abs=1e-3)
    fly(q, hall, [0.0, 0.0, 0.0, -5.0], 2.0)
    assert q.yaw_rate == pytest.approx(-1.0)


def test_yaw_acceleration_limited(hall: World) -> None:
    q = Quadrotor([3.0, 5.0, 1.0, 0.0], max_yaw_rate=1.0, max_yaw_accel=2.0)
    q.step([0.0, 0.0, 0.0, 1.0], 0.1, hall)
    assert q.yaw_rate == pytest.approx(0.2)
    assert q.pose[3] == pytest.approx(0.01)  # trapezoid: 0.5 * 0.2 * 0.1


def test_body_frame_command(hall: World) -> None:
    q = Quadrotor([5.0, 3.0, 1.0, math.pi / 2], time_constant=0.0, max_accel=100.0)
    q.step([1.0, 0.0, 0.0, 0.0], 0.1, hall)  # forward = +y in the map
    np.testing.assert_allclose(q.velocity_world, [0.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(q.velocity_body, [1.0, 0.0, 0.0], atol=1e-12)
    q.step([0.0, 1.0, 0.0, 0.0], 0.1, hall)  # left = -x in the map
    np.testing.assert_allclose(q.velocity_world, [-1.0, 0.0, 0.0], atol=1e-12)


def test_tilt_follows_acceleration(hall: World) -> None:
    q = Quadrotor([5.0, 5.0, 1.0, 0.0])
    q.step([1.0, 0.0, 0.0, 0.0], DT, hall)  # accelerate forward: nose down
    assert q.pitch == pytest.approx(math.atan2(1.0, 9.80665), rel=1e-6)
    assert q.roll == pytest.approx(0.0, abs=1e-12)
    assert q.accel_body[0] > 0.9 and abs(q.accel_body[2]) < 0.2
    q2 = Quadrotor([5.0, 5.0, 1.0, 0.0])
    q2.step([0.0, 1.0, 0.0, 0.0], DT, hall)  # accelerate left: right side up, roll < 0
    assert q2.roll < -0.09 and q2.angular_velocity_body[0] < 0.0


def test_flying_into_a_wall_stops_at_contact(hall: World) -> None:
    q = Quadrotor([17.0, 5.0, 1.0, 0.0], radius=0.25)
    xs, collided = [], []
    for _ in range(round(6.0 / DT)):
        info = q.step([1.0, 0.0, 0.0, 0.0], DT, hall)
        xs.append(q.pose[0])
        collided.append(info.collided)
        assert info.clearance >= -1e-9
    # The right wall's face is at x = 19.95: the disc edge never passes it.
    assert max(xs) <= 19.95 - 0.25 + 1e-9
    assert max(xs) == pytest.approx(19.7, abs=1e-3)
    assert q.collisions == 1 and q.collision_steps == sum(collided) > 10
    assert 0.0 <= q.min_clearance < 1e-3
    # Back off, then hit again: a second contact event.
    fly(q, hall, [-1.0, 0.0, 0.0, 0.0], 2.0)
    assert q.pose[0] < 19.0
    fly(q, hall, [1.0, 0.0, 0.0, 0.0], 5.0)
    assert q.collisions == 2


def test_never_enters_obstacles_at_any_angle(hall: World) -> None:
    """Fly at the pillar and the corners from many headings; the disc never overlaps an
    occupied cell."""
    occ_iy, occ_ix = np.nonzero(hall.occupied)
    lo = np.stack([occ_ix, occ_iy], axis=1) * 0.05  # lower-left corners of occupied cells
    tree = cKDTree(lo + 0.025)
    dt = 0.05
    for heading in np.linspace(-math.pi, math.pi, 10, endpoint=False):
        q = Quadrotor([12.0, 4.5, 1.0, heading])
        for _ in range(round(16.0 / dt)):
            q.step([1.0, 0.3, 0.0, 0.0], dt, hall)
            # Exact distance from the centre to the nearest occupied cell squares.
            _, idx = tree.query(q.pose[:2], k=12)
            d = np.maximum(np.maximum(lo[idx] - q.pose[:2], q.pose[:2] - lo[idx] - 0.05), 0.0)
            assert np.hypot(d[:, 0], d[:, 1]).min() >= 0.25 - 1e-9
        assert q.collisions >= 1


def test_escapes_when_starting_too_close(hall: World) -> None:
    q = Quadrotor([0.2, 5.0, 1.0, 0.0])  # 0.15 m from the left wall, radius 0.25
    fly(q, hall, [0.5, 0.0, 0.0, 0.0], 2.0)
    assert q.pose[0] > 0.5 and q.collisions == 0
    q = Quadrotor([0.2, 5.0, 1.0, math.pi])  # pushing into it instead
    fly(q, hall, [0.5, 0.0, 0.0, 0.0], 1.0)
    assert q.pose[0] == pytest.approx(0.2) and q.collisions == 1


def test_rejects_bad_inputs(hall: World) -> None:
    with pytest.raises(ConfigError):
        Quadrotor([0.0, 0.0, 0.0])
    with pytest.raises(ConfigError):
        Quadrotor([1.0, 1.0, 1.0, 0.0], max_speed=0.0)
    with pytest.raises(ConfigError):
        Quadrotor([1.0, 1.0, 1.0, 0.0]).step([1.0, 0.0, 0.0], DT, hall)
    with pytest.raises(ConfigError):
        Quadrotor([1.0, 1.0, 1.0, 0.0]).step([1.0, 0.0, 0.0, 0.0], 0.0, hall)
