"""Fly one simulated drone along a tour and record its sensor messages.

Used by benchmarks so that only the code under test is timed: the drone flies
its tour with a perfect controller (on ground truth) through the same world,
quadrotor and sensor models as the simulator process, and every tick's
messages are kept in memory in publication order.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from agent.path_follower import PathFollower
from common.config import Config
from common.geometry import pose4_to_pose7
from common.trajectory_io import Trajectory
from protocol import Altimeter, Imu, LaserScan, Odometry
from simulation.quadrotor import Quadrotor
from simulation.sensors import AltimeterModel, ImuModel, LaserModel, OdometryModel
from simulation.tours import plan_tours, start_poses
from simulation.world import World


@dataclass
class Recording:
    messages: list[Any] = field(default_factory=list)
    ground_truth: Trajectory | None = None
    distance_m: float = 0.0
    scans: int = 0


def record_tour(
    cfg: Config,
    world_name: str,
    length_m: float,
    seed: int = 0,
    max_time_s: float = 3600.0,
    *,
    start: ArrayLike | None = None,
    tour: ArrayLike | None = None,
) -> Recording:
    """`start` [x, y, yaw] and `tour` (N, 2) waypoints: flown as given (else drawn for the
    world by `seed`, `length_m` long)."""
    world = World.load(world_name)
    s, q = cfg.sim, cfg.sim.quadrotor
    if start is None:
        start = start_poses(world, 1, seed=seed)[0]
    start = np.asarray(start, dtype=np.float64).reshape(3)
    if tour is None:
        tour = plan_tours(world, start[None, :], seed=seed, length_m=length_m)[0]
    tour = np.asarray(tour, dtype=np.float64)
    rng = np.random.default_rng(seed)
    laser = LaserModel(
        s.laser.beams,
        np.radians(s.laser.fov_deg),
        s.laser.range_min_m,
        s.laser.range_max_m,
        s.laser.range_noise_std_m,
    )
    odo = OdometryModel(
        s.odometry.speed_noise_frac, s.odometry.yaw_rate_noise_std, s.odometry.yaw_rate_bias
    )
    imu = ImuModel(s.imu.gyro_noise_std, s.imu.gyro_bias, s.imu.accel_noise_std, s.imu.accel_bias)
    alt = AltimeterModel(s.altimeter.noise_std_m, s.altimeter.bias_m)
    vehicle = Quadrotor(
        np.array([start[0], start[1], q.altitude_m, start[2]]),
        max_speed=q.max_speed_mps,
        max_accel=q.max_accel_mps2,
        max_vertical_speed=q.max_vertical_speed_mps,
        max_yaw_rate=q.max_yaw_rate_rps,
        radius=q.radius_m,
    )
    a = cfg.agent
    follower = PathFollower.from_config(a)
    follower.set_path(tour)
    dt = 1.0 / s.laser.rate_hz
    rec = Recording()
    gt: list[list[float]] = []
    t = 0.0
    while t < max_time_s and not follower.done:
        v = vehicle
        w, acc, quat = imu.measure(
            v.angular_velocity_body, v.accel_body, v.roll, v.pitch, float(v.pose[3]), rng
        )
        rec.messages += [
            Odometry("bench", t, pose4_to_pose7(odo.pose), np.asarray(odo.twist)),
            Imu("bench", t, w, acc, quat),
            Altimeter("bench", t, alt.measure(float(v.pose[2]), rng)),
            LaserScan(
                "bench",
                t,
                float(laser.angles[0]),
                laser.angle_increment,
                laser.range_min,
                laser.range_max,
                laser.measure(world, v.pose[[0, 1, 3]], rng, v.roll, v.pitch, v.pose[2]),
            ),
        ]
        gt.append([t, *v.pose])
        rec.scans += 1
        cmd = follower.command(v.pose)
        vehicle.step(np.asarray(cmd), dt, world)
        odo.step(vehicle.velocity_body, vehicle.yaw_rate, dt, rng)
        t += dt
    g = np.array(gt)
    rec.ground_truth = Trajectory.from_pose4(g[:, 0], g[:, 1:5])
    rec.distance_m = vehicle.distance_travelled
    return rec
