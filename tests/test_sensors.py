"""Sensor noise models: laser, odometry, IMU, altimeter."""

from __future__ import annotations

import math

import numpy as np
import pytest

from agent.scan_preprocessor import ScanPreprocessor
from common.config import LocalSlamConfig
from common.errors import ConfigError
from common.geometry import quat_to_rpy
from common.map_io import GridMap
from simulation.raycast import cast_rays
from simulation.sensors import GRAVITY, AltimeterModel, ImuModel, LaserModel, OdometryModel
from simulation.world import World


@pytest.fixture(scope="module")
def room() -> World:
    """8 x 6 m room (one-cell walls) whose right wall has a 1 m gap to the outside."""
    data = np.full((120, 160), 100, dtype=np.int8)
    data[1:-1, 1:-1] = 0
    data[50:70, -1] = 0
    return World(GridMap(data=data, resolution=0.05, origin=(0.0, 0.0, 0.0)))


# ----------------------------------------------------------------------------- laser


def test_laser_angles_hokuyo_defaults() -> None:
    laser = LaserModel()
    assert laser.angles.shape == (1081,)
    assert laser.angles[0] == pytest.approx(-math.radians(135))
    assert laser.angles[-1] == pytest.approx(math.radians(135))
    assert laser.angle_increment == pytest.approx(math.radians(0.25))
    full = LaserModel(beams=360, fov_rad=2 * math.pi)
    assert full.angle_increment == pytest.approx(math.radians(1.0))
    assert full.angles[-1] < math.pi - 1e-6  # no duplicated beam


def test_laser_noise_statistics(room: World) -> None:
    laser = LaserModel(range_noise_std=0.01)
    pose = np.array([3.0, 3.0, 0.3])
    true = cast_rays(room.occupied, 0.05, room.origin_xy, pose, laser.angles, laser.range_max)
    rng = np.random.default_rng(1)
    scans = np.stack([laser.measure(room, pose, rng) for _ in range(50)])
    assert scans.dtype == np.float32
    hit = np.isfinite(true)
    err = scans[:, hit] - true[hit]
    assert abs(float(err.mean())) < 1e-3
    assert float(err.std()) == pytest.approx(0.01, rel=0.1)


def test_laser_no_return_reads_range_max(room: World) -> None:
    laser = LaserModel(beams=721, fov_rad=2 * math.pi, range_max=30.0)
    # Looking through the gap in the right wall (y 2.5..3.5 m) to the outside.
    ranges = laser.measure(room, [6.0, 3.0, 0.0], np.random.default_rng(0))
    # The gap spans +-14 deg from there.
    assert np.all(ranges[np.abs(laser.angles) < math.radians(13)] == np.float32(30.0))
    assert np.all(ranges[np.abs(laser.angles) > math.radians(15)] < 10.0)
    short = LaserModel(range_max=2.0).measure(room, [4.0, 3.0, 0.0], np.random.default_rng(0))
    assert np.all(short == np.float32(2.0))  # every wall is > 2 m away
    assert np.all((short >= 0.1) & (short <= 2.0))


def test_laser_is_deterministic_per_seed(room: World) -> None:
    laser = LaserModel()
    a = laser.measure(room, [2.0, 2.0, 1.0], np.random.default_rng(7))
    b = laser.measure(room, [2.0, 2.0, 1.0], np.random.default_rng(7))
    c = laser.measure(room, [2.0, 2.0, 1.0], np.random.default_rng(8))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_a_tilted_laser_sees_walls_farther_and_the_floor_and_the_agent_levels_it(
    room: World,
) -> None:
    """The laser is fixed to the body: pitched 0.1 rad (a 1 m/s^2 acceleration) its beam
    ahead meets the wall 4.95 m away at 4.95 / cos(0.1), and from 0.3 m up the floor at
    0.3 / sin(0.1); the agent's levelling with the IMU's roll and pitch gives back the
    level scan's points and drops the floor's (the laser had stayed level while the IMU
    reported the tilt, so the agent's levelling shortened level walls' points)."""
    laser = LaserModel(beams=1081, range_noise_std=0.0)
    ahead = np.argmin(np.abs(laser.angles))
    pose, rng = np.array([3.0, 1.5, 0.0]), np.random.default_rng(0)
    level = laser.measure(room, pose, rng)
    tilted = laser.measure(room, pose, rng, roll=0.05, pitch=0.1, height=1.0)
    assert tilted[ahead] == pytest.approx(4.95 / math.cos(0.1), abs=1e-4)
    low = laser.measure(room, pose, rng, pitch=0.1, height=0.3)
    assert low[ahead] == pytest.approx(0.3 / math.sin(0.1), abs=1e-4)

    prep = ScanPreprocessor(LocalSlamConfig())
    inc = laser.angle_increment
    want = prep.prepare(laser.angles[0], inc, laser.range_max, level).points
    got = prep.prepare(laser.angles[0], inc, laser.range_max, tilted, 0.05, 0.1, 1.0).points
    assert len(got) > 0.95 * len(want)
    # every levelled point lies on a wall of the level scan (within its beam spacing)
    dist = np.linalg.norm(got[:, None, :] - want[None, :, :], axis=2).min(axis=1)
    assert np.quantile(dist, 0.99) < 0.03
    # ... and so do the keyframes (they had carried floor hits to the map as walls)
    kf = prep.level_ranges(laser.angles[0], inc, laser.range_max, tilted, 0.05, 0.1, 1.0)
    assert kf[ahead] == tilted[ahead]  # a wall: as read
    kf = prep.level_ranges(laser.angles[0], inc, laser.range_max, low, 0.0, 0.1, 0.3)
    assert kf[ahead] == -np.inf and np.isfinite(kf[np.abs(laser.angles) > 2.0]).all()
    floor = prep.prepare(laser.angles[0], inc, laser.range_max, low, 0.0, 0.1, 0.3).points
    assert not np.any(np.hypot(*floor.T)[np.abs(np.arctan2(floor[:, 1], floor[:, 0])) < 0.5]
                      > 2.9)  # fmt: skip


def test_laser_rejects_bad_config() -> None:
    with pytest.raises(ConfigError):
        LaserModel(range_min=5.0, range_max=1.0)
    with pytest.raises(ConfigError):
        LaserModel(beams=0)


# ----------------------------------------------------------------------------- odometry


def test_odometry_noiseless_integrates_a_circle() -> None:
    odom = OdometryModel(speed_noise_frac=0.0, yaw_rate_noise_std=0.0, yaw_rate_bias=0.0)
    rng = np.random.default_rng(0)
    np.testing.assert_array_equal(odom.pose, np.zeros(4))
    w = 2 * math.pi / 20.0  # one full turn in 20 s at 1 m/s: radius 20 / (2 pi)
    for _ in range(2000):
        odom.step([1.0, 0.0, 0.05], w, 0.01, rng)
    np.testing.assert_allclose(odom.pose[[0, 1, 3]], [0.0, 0.0, 0.0], atol=1e-6)
    assert odom.pose[2] == pytest.approx(1.0)
    assert odom.distance == pytest.approx(20.0)
    # Quarter turn: at (r, r).
    odom.reset()
    for _ in range(500):
        odom.step([1.0, 0.0, 0.0], w, 0.01, rng)
    r = 20.0 / (2 * math.pi)
    np.testing.assert_allclose(odom.pose[:2], [r, r], atol=1e-6)


def test_odometry_drifts_with_yaw_bias() -> None:
    odom = OdometryModel(speed_noise_frac=0.0, yaw_rate_noise_std=0.0, yaw_rate_bias=0.01)
    rng = np.random.default_rng(0)
    for _ in range(1000):
        odom.step([1.0, 0.0, 0.0], 0.0, 0.01, rng)  # truly straight for 10 m
    assert odom.pose[3] == pytest.approx(0.1)
    assert odom.pose[1] == pytest.approx(0.5 * 0.01 * 10.0**2, rel=0.02)  # ~ b t^2 / 2
    assert odom.twist[3] == pytest.approx(0.01)


def test_odometry_speed_noise_is_relative() -> None:
    odom = OdometryModel(speed_noise_frac=0.05, yaw_rate_noise_std=0.0, yaw_rate_bias=0.0)
    rng = np.random.default_rng(3)
    vx = []
    for _ in range(2000):
        odom.step([2.0, 0.0, 0.0], 0.0, 0.01, rng)
        vx.append(odom.twist[0])
    assert np.std(vx) == pytest.approx(2.0 * 0.05, rel=0.1)
    assert np.mean(vx) == pytest.approx(2.0, abs=0.01)
    odom.step([0.0, 0.0, 0.0], 0.0, 0.01, rng)
    assert odom.twist[0] == 0.0  # no motion, no speed noise


# ----------------------------------------------------------------------------- IMU


def test_imu_at_rest_reads_gravity() -> None:
    imu = ImuModel(
        gyro_noise_std=0.0,
        gyro_bias=[0.01, 0.0, -0.02],
        accel_noise_std=0.0,
        accel_bias=0.0,
        attitude_noise_std=0.0,
    )
    gyro, acc, quat = imu.measure(np.zeros(3), np.zeros(3), 0.0, 0.0, 1.0, np.random.default_rng(0))
    np.testing.assert_allclose(gyro, [0.01, 0.0, -0.02])
    np.testing.assert_allclose(acc, [0.0, 0.0, GRAVITY], atol=1e-12)
    np.testing.assert_allclose(quat_to_rpy(quat), [0.0, 0.0, 1.0], atol=1e-12)


def test_imu_tilted_gravity_and_attitude_noise() -> None:
    imu = ImuModel(accel_noise_std=0.0, accel_bias=0.0, attitude_noise_std=0.01)
    rng = np.random.default_rng(2)
    pitch = 0.2  # nose down
    rolls, accs = [], []
    for _ in range(400):
        _, acc, quat = imu.measure(np.zeros(3), np.zeros(3), 0.0, pitch, 0.5, rng)
        r, p, y = quat_to_rpy(quat)
        rolls.append(r)
        accs.append(acc)
        assert y == pytest.approx(0.5, abs=1e-9)
        assert p == pytest.approx(pitch, abs=0.06)
    assert np.std(rolls) == pytest.approx(0.01, rel=0.15)
    np.testing.assert_allclose(
        np.mean(accs, axis=0), GRAVITY * np.array([-math.sin(pitch), 0.0, math.cos(pitch)])
    )


def test_imu_gyro_noise_and_accel_passthrough() -> None:
    imu = ImuModel(gyro_noise_std=0.05, gyro_bias=0.0, accel_noise_std=0.0, accel_bias=0.1)
    rng = np.random.default_rng(4)
    gyros = np.array(
        [imu.measure([0.0, 0.0, 0.3], [1.0, 0.0, 0.0], 0, 0, 0, rng)[0] for _ in range(500)]
    )
    assert gyros[:, 2].mean() == pytest.approx(0.3, abs=0.01)
    assert gyros.std(axis=0) == pytest.approx([0.05] * 3, rel=0.15)
    _, acc, _ = imu.measure(np.zeros(3), [1.0, 0.0, 0.0], 0, 0, 0, rng)
    np.testing.assert_allclose(acc, [1.1, 0.1, GRAVITY + 0.1])


# ----------------------------------------------------------------------------- altimeter


def test_altimeter_bias_and_noise() -> None:
    alt = AltimeterModel(noise_std=0.02, bias=0.1)
    rng = np.random.default_rng(5)
    z = np.array([alt.measure(1.5, rng) for _ in range(2000)])
    assert z.mean() == pytest.approx(1.6, abs=0.003)
    assert z.std() == pytest.approx(0.02, rel=0.1)
    with pytest.raises(ConfigError):
        AltimeterModel(noise_std=-1.0)
