"""Sensor noise models: 2-D laser, odometry, IMU, altimeter.

Each model holds only its parameters (and, for odometry, its integrated state);
randomness always comes from the `np.random.Generator` passed to each call, so
a simulation seeded once is reproducible.

Frames: "body" is the drone's FLU frame. Velocities handed to the odometry are
in the yaw-aligned body frame (x forward, y left, z up; roll and pitch ignored,
the 2.5-D convention of `common.geometry`); the IMU takes the full body frame, and so
does the laser: it is fixed to the body and tilts with it (the agent levels its
points with the IMU's roll and pitch).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from common.errors import ConfigError
from common.geometry import rpy_to_quat, wrap_angle
from simulation.raycast import cast_rays
from simulation.world import World

__all__ = ["GRAVITY", "AltimeterModel", "ImuModel", "LaserModel", "OdometryModel"]

GRAVITY = 9.80665  # m/s^2


def _check_nonneg(**values: float) -> None:
    for name, v in values.items():
        if not (math.isfinite(v) and v >= 0.0):
            raise ConfigError(f"{name} must be a finite number >= 0, got {v}")


def _vec3(value: ArrayLike, name: str) -> NDArray[np.float64]:
    v = np.broadcast_to(np.asarray(value, dtype=np.float64), (3,)).copy()
    if not np.all(np.isfinite(v)):
        raise ConfigError(f"{name} must be finite, got {value}")
    return v


class LaserModel:
    """A planar scanning laser (defaults: Hokuyo UTM-30LX, as in seed 002).

    Beam i points at `angles[i]` (rad, counter-clockwise from the sensor's +x), evenly
    spread over `fov_rad` centred on +x. `measure` returns float32 ranges (m) with
    Gaussian noise; beams with no valid return (nothing within range_max, or a noisy
    range outside [range_min, range_max)) read exactly `range_max`.
    """

    def __init__(
        self,
        beams: int = 1081,
        fov_rad: float = math.radians(270.0),
        range_min: float = 0.1,
        range_max: float = 30.0,
        range_noise_std: float = 0.01,
    ) -> None:
        if beams < 1:
            raise ConfigError(f"laser beams must be >= 1, got {beams}")
        if not 0.0 < fov_rad <= 2.0 * math.pi:
            raise ConfigError(f"laser fov_rad must be in (0, 2 pi], got {fov_rad}")
        if not 0.0 <= range_min < range_max:
            raise ConfigError(
                f"laser needs 0 <= range_min < range_max, got {range_min}, {range_max}"
            )
        _check_nonneg(range_noise_std=range_noise_std)
        self.beams = int(beams)
        self.fov_rad = float(fov_rad)
        self.range_min = float(range_min)
        self.range_max = float(range_max)
        self.range_noise_std = float(range_noise_std)
        if beams == 1:
            self.angles = np.zeros(1)
        elif fov_rad >= 2.0 * math.pi - 1e-9:  # full circle: do not repeat the first beam
            self.angles = -math.pi + np.arange(beams) * (2.0 * math.pi / beams)
        else:
            self.angles = np.linspace(-fov_rad / 2, fov_rad / 2, beams)

    @property
    def angle_increment(self) -> float:
        """rad between consecutive beams."""
        return float(self.angles[1] - self.angles[0]) if self.beams > 1 else 0.0

    def measure(
        self,
        world: World,
        T_world_sensor: ArrayLike,
        rng: np.random.Generator,
        roll: float = 0.0,
        pitch: float = 0.0,
        height: float = math.inf,
    ) -> NDArray[np.float32]:
        """(beams,) noisy ranges (m) from a sensor at [x, y, yaw] in the map frame, tilted
        by roll and pitch (rad, the body's: the laser is fixed to it) at ``height`` m
        above the floor: walls stand from the floor up without end, so a tilted beam
        meets a wall farther than level, and a beam pointing down may meet the floor
        (at 1 m, 5.8 degrees of pitch meets it ~10 m ahead, as on a real drone)."""
        angles, horizontal = self.angles, 1.0
        down = np.zeros(0)
        if roll or pitch:  # beam (cos a, sin a, 0) turned by Ry(pitch) Rx(roll)
            ca, sa = np.cos(self.angles), np.sin(self.angles)
            cr, sr, cp, sp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
            x, y = cp * ca + sp * sr * sa, cr * sa
            down = sp * ca - cp * sr * sa  # -z: the beam's fall per metre along it
            angles, horizontal = np.arctan2(y, x), np.hypot(x, y)
        true = cast_rays(
            world.occupied,
            world.resolution,
            world.origin_xy,
            T_world_sensor,
            angles,
            self.range_max,
            blocks=world.ray_blocks,
        )
        if len(down):
            with np.errstate(divide="ignore"):
                floor = np.where(down > 0.0, max(height, 0.0) / down, np.inf)
            true = np.minimum(true / horizontal, floor).astype(np.float32)
        noisy = true + rng.normal(0.0, self.range_noise_std, true.shape).astype(np.float32)
        invalid = ~np.isfinite(true) | (noisy < self.range_min) | (noisy >= self.range_max)
        noisy[invalid] = self.range_max
        return noisy.astype(np.float32)


class OdometryModel:
    """Dead reckoning from noisy body velocities and a biased yaw rate.

    Each `step` corrupts the TRUE yaw-aligned body velocity (vx, vy, vz) with a relative
    Gaussian error (`speed_noise_frac` per axis, plus an optional constant scale error
    `speed_scale_bias`) and the true yaw rate with white noise (`yaw_rate_noise_std`,
    rad/s per sample) and a constant bias (`yaw_rate_bias`, rad/s), then integrates
    them (midpoint yaw) into `pose` = [x, y, z, yaw] in the odometry's own frame, which
    starts at identity. `twist` is the last noisy (vx, vy, vz, yaw_rate).
    """

    def __init__(
        self,
        speed_noise_frac: float = 0.01,
        yaw_rate_noise_std: float = 0.002,
        yaw_rate_bias: float = 0.0005,
        speed_scale_bias: float = 0.0,
        vertical_noise_std: float = 0.0,
    ) -> None:
        _check_nonneg(
            speed_noise_frac=speed_noise_frac,
            yaw_rate_noise_std=yaw_rate_noise_std,
            vertical_noise_std=vertical_noise_std,
        )
        if not (math.isfinite(yaw_rate_bias) and math.isfinite(speed_scale_bias)):
            raise ConfigError("odometry biases must be finite")
        self.speed_noise_frac = float(speed_noise_frac)
        self.yaw_rate_noise_std = float(yaw_rate_noise_std)
        self.yaw_rate_bias = float(yaw_rate_bias)
        self.speed_scale_bias = float(speed_scale_bias)
        self.vertical_noise_std = float(vertical_noise_std)
        self.pose = np.zeros(4)  # [x, y, z, yaw], odometry frame
        self.twist = np.zeros(4)  # noisy [vx, vy, vz, yaw_rate], body frame
        self.distance = 0.0  # m of noisy horizontal path integrated so far

    def reset(self) -> None:
        """Back to the identity pose (a new odometry frame)."""
        self.pose = np.zeros(4)
        self.twist = np.zeros(4)
        self.distance = 0.0

    def step(
        self,
        true_body_vel: ArrayLike,
        true_yaw_rate: float,
        dt: float,
        rng: np.random.Generator,
    ) -> NDArray[np.float64]:
        """Integrate one interval of dt seconds; returns the new pose (a copy)."""
        if not (dt >= 0.0 and math.isfinite(dt)):
            raise ConfigError(f"dt must be a finite number >= 0, got {dt}")
        v = np.asarray(true_body_vel, dtype=np.float64).reshape(3)
        rel = rng.normal(0.0, self.speed_noise_frac, 3)
        v_meas = v * (1.0 + self.speed_scale_bias + rel)
        v_meas[2] += rng.normal(0.0, self.vertical_noise_std) if self.vertical_noise_std else 0.0
        w_meas = float(true_yaw_rate) + self.yaw_rate_bias
        w_meas += float(rng.normal(0.0, self.yaw_rate_noise_std))
        yaw_mid = self.pose[3] + 0.5 * w_meas * dt
        c, s = math.cos(yaw_mid), math.sin(yaw_mid)
        self.pose[0] += (c * v_meas[0] - s * v_meas[1]) * dt
        self.pose[1] += (s * v_meas[0] + c * v_meas[1]) * dt
        self.pose[2] += v_meas[2] * dt
        self.pose[3] = float(wrap_angle(self.pose[3] + w_meas * dt))
        self.twist = np.array([v_meas[0], v_meas[1], v_meas[2], w_meas])
        self.distance += math.hypot(v_meas[0], v_meas[1]) * dt
        return self.pose.copy()


class ImuModel:
    """A 6-axis IMU with an attitude filter output.

    Gyro: true body angular velocity + bias + white noise (rad/s). Accelerometer:
    specific force in the body frame, i.e. the true body-frame linear acceleration plus
    gravity reaction (+9.81 m/s^2 on body z when level and at rest), + bias + white noise.
    Orientation: quaternion [qx, qy, qz, qw] of (roll, pitch, yaw) with small Gaussian
    errors on roll and pitch (and optionally yaw), as an onboard attitude estimate gives.
    Biases may be scalars (same on each axis) or 3-vectors.
    """

    def __init__(
        self,
        gyro_noise_std: float = 0.002,
        gyro_bias: ArrayLike = 0.0005,
        accel_noise_std: float = 0.05,
        accel_bias: ArrayLike = 0.02,
        attitude_noise_std: float = 0.005,
        yaw_noise_std: float = 0.0,
    ) -> None:
        _check_nonneg(
            gyro_noise_std=gyro_noise_std,
            accel_noise_std=accel_noise_std,
            attitude_noise_std=attitude_noise_std,
            yaw_noise_std=yaw_noise_std,
        )
        self.gyro_noise_std = float(gyro_noise_std)
        self.gyro_bias = _vec3(gyro_bias, "gyro_bias")
        self.accel_noise_std = float(accel_noise_std)
        self.accel_bias = _vec3(accel_bias, "accel_bias")
        self.attitude_noise_std = float(attitude_noise_std)
        self.yaw_noise_std = float(yaw_noise_std)

    def measure(
        self,
        true_angular_velocity: ArrayLike,
        true_linear_accel_body: ArrayLike,
        roll: float,
        pitch: float,
        yaw: float,
        rng: np.random.Generator,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """(angular_velocity (3,) rad/s, linear_acceleration (3,) m/s^2 incl. gravity,
        orientation (4,) [qx, qy, qz, qw]); all in the body frame of attitude
        (roll, pitch, yaw) rad."""
        omega = np.asarray(true_angular_velocity, dtype=np.float64).reshape(3)
        acc = np.asarray(true_linear_accel_body, dtype=np.float64).reshape(3)
        cr, sr = math.cos(roll), math.sin(roll)
        cp, sp = math.cos(pitch), math.sin(pitch)
        gravity_body = GRAVITY * np.array([-sp, sr * cp, cr * cp])  # R^T [0, 0, g]
        gyro = omega + self.gyro_bias + rng.normal(0.0, self.gyro_noise_std, 3)
        accel = acc + gravity_body + self.accel_bias + rng.normal(0.0, self.accel_noise_std, 3)
        att = rng.normal(0.0, self.attitude_noise_std, 2)
        yaw_err = float(rng.normal(0.0, self.yaw_noise_std)) if self.yaw_noise_std else 0.0
        quat = rpy_to_quat(roll + att[0], pitch + att[1], yaw + yaw_err)
        return gyro, accel, quat


class AltimeterModel:
    """Height above ground (m) with a constant bias and Gaussian noise."""

    def __init__(self, noise_std: float = 0.02, bias: float = 0.0) -> None:
        _check_nonneg(noise_std=noise_std)
        if not math.isfinite(bias):
            raise ConfigError(f"altimeter bias must be finite, got {bias}")
        self.noise_std = float(noise_std)
        self.bias = float(bias)

    def measure(self, true_height_above_ground: float, rng: np.random.Generator) -> float:
        """One reading (m)."""
        return float(true_height_above_ground + self.bias + rng.normal(0.0, self.noise_std))
