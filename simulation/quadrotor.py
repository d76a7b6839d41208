"""Quadrotor kinematics for the 2.5-D simulator.

The drone tracks a velocity command given in its yaw-aligned body frame
(vx forward, vy left, vz up, yaw_rate) like a velocity-controlled multirotor:
the velocity follows the command through a first-order lag (`time_constant`)
with the acceleration, speed, vertical-speed, yaw-rate and yaw-acceleration
limits applied. Roll and pitch are the tilts that produce the horizontal
acceleration, for the IMU model. The airframe is a disc of `radius` in the
plane: it never overlaps an occupied cell. When a step would hit a wall the
drone stops at the contact point (horizontal velocity zeroed) and the step is
reported as a collision; motions that move away from an obstacle are always
allowed, so a drone that starts too close can escape.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from common.errors import ConfigError
from common.geometry import wrap_angle
from simulation.sensors import GRAVITY
from simulation.world import World

logger = logging.getLogger(__name__)

__all__ = ["Quadrotor", "StepInfo"]

_BISECT_ROUNDS = 2  # contact located to 1/(BISECT_POINTS + 1)^2 of a sample step
_BISECT_POINTS = 30


@dataclass(frozen=True)
class StepInfo:
    """What happened during one `Quadrotor.step`."""

    collided: bool  # the step was cut short by a wall contact
    clearance: float  # m between the disc's edge and the nearest occupied cell, after the step
    distance: float  # m travelled horizontally during the step


def _clip_norm(v: NDArray[np.float64], limit: float) -> NDArray[np.float64]:
    n = float(np.linalg.norm(v))
    return v * (limit / n) if n > limit else v


class Quadrotor:
    """A velocity-controlled quadrotor; see the module docstring.

    State: `pose` [x, y, z, yaw] (map frame, m / rad), `velocity_world` (3,) m/s,
    `yaw_rate` rad/s. Counters: `collisions` (contact events: steps that collide after a
    step that did not), `collision_steps`, `min_clearance` (m, disc edge to wall, over the
    whole flight), `distance_travelled` (m, horizontal).
    """

    def __init__(
        self,
        pose: ArrayLike,
        max_speed: float = 1.0,
        max_accel: float = 1.0,
        max_vertical_speed: float = 0.5,
        max_yaw_rate: float = 1.0,
        max_yaw_accel: float = 2.0,
        radius: float = 0.25,
        time_constant: float = 0.2,
    ) -> None:
        p = np.asarray(pose, dtype=np.float64).reshape(-1)
        if p.shape != (4,) or not np.all(np.isfinite(p)):
            raise ConfigError(f"quadrotor pose must be 4 finite numbers [x, y, z, yaw], got {p}")
        for name, v in (
            ("max_speed", max_speed),
            ("max_accel", max_accel),
            ("max_vertical_speed", max_vertical_speed),
            ("max_yaw_rate", max_yaw_rate),
            ("max_yaw_accel", max_yaw_accel),
            ("radius", radius),
        ):
            if not (math.isfinite(v) and v > 0.0):
                raise ConfigError(f"quadrotor {name} must be > 0, got {v}")
        if not (math.isfinite(time_constant) and time_constant >= 0.0):
            raise ConfigError(f"quadrotor time_constant must be >= 0, got {time_constant}")
        self.max_speed = float(max_speed)
        self.max_accel = float(max_accel)
        self.max_vertical_speed = float(max_vertical_speed)
        self.max_yaw_rate = float(max_yaw_rate)
        self.max_yaw_accel = float(max_yaw_accel)
        self.radius = float(radius)
        self.time_constant = float(time_constant)

        self.pose = p.copy()
        self.pose[3] = float(wrap_angle(p[3]))
        self.velocity_world = np.zeros(3)
        self.yaw_rate = 0.0
        self.accel_world = np.zeros(3)  # m/s^2 during the last step
        self.roll = 0.0
        self.pitch = 0.0
        self.roll_rate = 0.0
        self.pitch_rate = 0.0
        self.collisions = 0
        self.collision_steps = 0
        self.distance_travelled = 0.0
        self.min_clearance = math.inf
        self._in_contact = False

    # ------------------------------------------------------------------ derived truth

    def _heading_rotation(self) -> NDArray[np.float64]:
        c, s = math.cos(self.pose[3]), math.sin(self.pose[3])
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    @property
    def velocity_body(self) -> NDArray[np.float64]:
        """(3,) true velocity (m/s) in the yaw-aligned body frame (what odometry measures)."""
        return self._heading_rotation().T @ self.velocity_world

    @property
    def accel_body(self) -> NDArray[np.float64]:
        """(3,) true linear acceleration (m/s^2, gravity excluded) in the full body frame
        (roll and pitch included) during the last step: the input of `ImuModel.measure`.
        The velocity lost in a wall contact is not included (no impact spike)."""
        return self._body_rotation().T @ self.accel_world

    @property
    def angular_velocity_body(self) -> NDArray[np.float64]:
        """(3,) true body rates (rad/s); small-angle approximation (roll, pitch, yaw rates)."""
        return np.array([self.roll_rate, self.pitch_rate, self.yaw_rate])

    def _body_rotation(self) -> NDArray[np.float64]:
        cr, sr = math.cos(self.roll), math.sin(self.roll)
        cp, sp = math.cos(self.pitch), math.sin(self.pitch)
        rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
        ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
        return self._heading_rotation() @ ry @ rx

    # ------------------------------------------------------------------ dynamics

    def _limited(
        self, current: NDArray[np.float64], target: NDArray[np.float64], dt: float
    ) -> NDArray[np.float64]:
        """New velocity: first-order lag towards target, acceleration-limited."""
        tau = max(self.time_constant, dt)
        accel = _clip_norm((target - current) / tau, self.max_accel)
        return current + accel * dt

    def step(self, cmd_body: ArrayLike, dt: float, world: World) -> StepInfo:
        """Advance dt seconds following cmd_body = (vx, vy, vz, yaw_rate) (m/s, rad/s,
        yaw-aligned body frame). Commands beyond the limits are clipped."""
        cmd = np.asarray(cmd_body, dtype=np.float64).reshape(-1)
        if cmd.shape != (4,) or not np.all(np.isfinite(cmd)):
            raise ConfigError(
                f"cmd_body must be 4 finite numbers (vx, vy, vz, yaw_rate), got {cmd}"
            )
        if not (dt > 0.0 and math.isfinite(dt)):
            raise ConfigError(f"dt must be > 0, got {dt}")

        # Yaw: rate- and acceleration-limited.
        yaw_cmd = float(np.clip(cmd[3], -self.max_yaw_rate, self.max_yaw_rate))
        dw = float(
            np.clip(yaw_cmd - self.yaw_rate, -self.max_yaw_accel * dt, self.max_yaw_accel * dt)
        )
        new_yaw_rate = self.yaw_rate + dw

        # Velocity target in the world frame, speed limits applied.
        target = self._heading_rotation() @ cmd[:3]
        target[:2] = _clip_norm(target[:2], self.max_speed)
        target[2] = float(np.clip(target[2], -self.max_vertical_speed, self.max_vertical_speed))
        v0 = self.velocity_world
        v1 = v0.copy()
        v1[:2] = self._limited(v0[:2], target[:2], dt)
        v1[2:] = self._limited(v0[2:], target[2:], dt)

        p0 = self.pose[:2].copy()
        p1 = p0 + 0.5 * (v0[:2] + v1[:2]) * dt
        p_end, collided = self._sweep(p0, p1, world)
        v_cmd = v1.copy()
        if collided:
            v1[:2] = 0.0
        z1 = max(self.pose[2] + 0.5 * (v0[2] + v1[2]) * dt, 0.0)
        if z1 == 0.0 and v1[2] < 0.0:
            v1[2] = 0.0

        # The commanded (limit-respecting) acceleration drives the attitude and the IMU; the
        # velocity lost in a wall contact is an impact the model does not resolve.
        self.accel_world = (v_cmd - v0) / dt
        self.velocity_world = v1
        self.pose[:2] = p_end
        self.pose[2] = z1
        self.pose[3] = float(wrap_angle(self.pose[3] + 0.5 * (self.yaw_rate + new_yaw_rate) * dt))
        self.yaw_rate = new_yaw_rate
        self._update_attitude(dt)

        moved = float(np.linalg.norm(p_end - p0))
        self.distance_travelled += moved
        clearance = float(world.clearance(p_end[None])[0]) - self.radius
        self.min_clearance = min(self.min_clearance, clearance)
        if collided:
            self.collision_steps += 1
            if not self._in_contact:
                self.collisions += 1
                logger.debug("contact at (%.2f, %.2f)", p_end[0], p_end[1])
        self._in_contact = collided
        return StepInfo(collided=collided, clearance=clearance, distance=moved)

    def _sweep(
        self, p0: NDArray[np.float64], p1: NDArray[np.float64], world: World
    ) -> tuple[NDArray[np.float64], bool]:
        """Furthest point along p0 -> p1 where the disc stays clear; (point, collided)."""
        length = float(np.linalg.norm(p1 - p0))
        if length == 0.0:
            return p1, False
        n = int(math.ceil(length / (0.25 * world.resolution))) + 1
        t = np.linspace(0.0, 1.0, n + 1)
        pts = p0 + t[:, None] * (p1 - p0)
        clear = world.clearance(pts)
        # A sample is blocked when it is closer than the radius AND closer than where the
        # step started (so a drone already too close may still move away).
        need = min(self.radius, float(clear[0]))
        blocked = np.flatnonzero(clear[1:] < need) + 1
        if blocked.size == 0:
            return p1, False
        lo, hi = float(t[blocked[0] - 1]), float(t[blocked[0]])
        # Bisection on the contact, all candidate points evaluated at once per round.
        for _ in range(_BISECT_ROUNDS):
            ts = np.linspace(lo, hi, _BISECT_POINTS + 2)
            clear = world.clearance(p0 + ts[:, None] * (p1 - p0))
            blocked_ts = np.flatnonzero(clear < need)
            first = int(blocked_ts[0]) if blocked_ts.size else len(ts) - 1
            if first == 0:  # lo itself reads blocked: stay there
                break
            lo, hi = float(ts[first - 1]), float(ts[first])
        return p0 + lo * (p1 - p0), True

    def _update_attitude(self, dt: float) -> None:
        """Roll/pitch that tilt the thrust to produce the horizontal acceleration."""
        a_heading = self._heading_rotation().T @ self.accel_world
        thrust_z = GRAVITY + a_heading[2]
        pitch = math.atan2(a_heading[0], thrust_z)
        roll = math.atan2(-a_heading[1], math.hypot(a_heading[0], thrust_z))
        self.roll_rate = (roll - self.roll) / dt
        self.pitch_rate = (pitch - self.pitch) / dt
        self.roll, self.pitch = roll, pitch
