"""A simulated flight for `bench gps`: ground truth, keyframes, odometry and loops.

The drone (the simulator's quadrotor model and the agent's path follower, on
ground truth) flies a scripted tour of a shipped world that revisits places. The
world's ``map`` frame is the ENU frame at the world's WGS84 origin. From the
ground truth:

- keyframes every ``agent.keyframe_distance_m`` / ``keyframe_angle_rad`` (seed 002);
- odometry between keyframes = the true relative motion plus Gaussian noise of
  ``MATCH_SIGMA_PER_M`` / ``MATCH_SIGMA_YAW_PER_M`` per metre (this benchmark's model
  of scan matching's error, not a setting of the agent) and a small systematic yaw
  drift (local SLAM without loop closing drifts);
- loop closures where the drone came back (within ``loop_radius_m``, at least
  ``basestation.constraints.loop_min_index_gap`` keyframes and ``loop_min_travel_m``
  of travel apart): the true relative pose plus small scan-matching noise.

Not the real local SLAM and scan verifier (too slow for a benchmark of the GPS
factor); they enter as the noise they produce.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from agent.path_follower import PathFollower
from common.config import Config
from common.geometry import se2_between, wrap_angle
from simulation.quadrotor import Quadrotor
from simulation.tours import plan_tours, start_poses
from simulation.world import World

FloatArray = NDArray[np.float64]
MATCH_SIGMA_PER_M = 0.005  # m of keyframe-delta std per metre flown
MATCH_SIGMA_YAW_PER_M = 0.002  # rad of keyframe-delta yaw std per metre


@dataclass
class Flight:
    stamps: FloatArray  # (N,) s, ground-truth samples (one per simulator tick)
    truth: FloatArray  # (N, 4) [east, north, up, yaw] in map = ENU
    kf_index: NDArray[np.int64]  # (K,) sample index of each keyframe
    deltas: list[FloatArray]  # K - 1 noisy T_prev_node [x, y, yaw]
    delta_covs: list[FloatArray]  # K - 1 3x3 covariances
    loops: list[tuple[int, int, FloatArray, FloatArray]]  # (i, j, T_i_j noisy, covariance)
    distance_m: float

    @property
    def kf_stamps(self) -> FloatArray:
        return self.stamps[self.kf_index]

    @property
    def kf_truth(self) -> FloatArray:
        return self.truth[self.kf_index]


def fly(cfg: Config, world_name: str, length_m: float, seed: int) -> tuple[FloatArray, FloatArray]:
    """Ground truth of one drone flying a tour: (N,) stamps, (N, 4) [x, y, z, yaw]."""
    world = World.load(world_name)
    q, a = cfg.sim.quadrotor, cfg.agent
    start = start_poses(world, 1, seed=seed)[0]
    tour = plan_tours(world, start[None, :], seed=seed, length_m=length_m)[0]
    vehicle = Quadrotor(
        np.array([start[0], start[1], q.altitude_m, start[2]]),
        max_speed=q.max_speed_mps,
        max_accel=q.max_accel_mps2,
        max_vertical_speed=q.max_vertical_speed_mps,
        max_yaw_rate=q.max_yaw_rate_rps,
        radius=q.radius_m,
    )
    follower = PathFollower.from_config(a)
    follower.set_path(tour)
    dt = 1.0 / cfg.sim.laser.rate_hz
    stamps, poses = [], []
    t = 0.0
    while t < 4 * length_m / a.cruise_speed_mps + 60.0 and not follower.done:
        stamps.append(t)
        poses.append(vehicle.pose.copy())
        vehicle.step(np.asarray(follower.command(vehicle.pose)), dt, world)
        t += dt
    return np.array(stamps), np.array(poses)


def _keyframes(truth: FloatArray, dist_m: float, angle_rad: float) -> NDArray[np.int64]:
    out = [0]
    for k in range(1, len(truth)):
        last = truth[out[-1]]
        moved = np.hypot(*(truth[k, :2] - last[:2]))
        if moved >= dist_m or abs(wrap_angle(truth[k, 3] - last[3])) >= angle_rad:
            out.append(k)
    return np.array(out, dtype=np.int64)


def make_flight(
    cfg: Config,
    world_name: str = "floor30x25",
    length_m: float = 300.0,
    seed: int = 0,
    yaw_drift_per_m: float = 0.002,  # rad per m of systematic local-SLAM heading drift
    loop_radius_m: float = 1.0,
    loop_sigmas: tuple[float, float, float] = (0.05, 0.05, 0.01),  # m, m, rad
    loop_stride: int = 5,  # keyframes between loop closures of one revisit
) -> Flight:
    stamps, truth = fly(cfg, world_name, length_m, seed)
    kf = _keyframes(truth, cfg.agent.keyframe_distance_m, cfg.agent.keyframe_angle_rad)
    rng = np.random.default_rng(seed + 1000)
    se2 = truth[kf][:, [0, 1, 3]]
    deltas, covs = [], []
    for k in range(1, len(kf)):
        d = se2_between(se2[k - 1], se2[k])
        dist = max(float(np.hypot(d[0], d[1])), 0.01)
        sig = np.array([MATCH_SIGMA_PER_M, MATCH_SIGMA_PER_M, MATCH_SIGMA_YAW_PER_M])
        sig = np.maximum(sig * dist, cfg.agent.odom_sigma_min)
        noisy = d + sig * rng.standard_normal(3)
        noisy[2] += yaw_drift_per_m * dist
        deltas.append(noisy)
        covs.append(np.diag(sig**2))
    travel = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(se2[:, :2], axis=0).T))])
    cc = cfg.basestation.constraints
    tree = cKDTree(se2[:, :2])
    loops, last_loop = [], -loop_stride
    ls_sig = np.asarray(loop_sigmas)
    for j in range(len(kf)):
        if j - last_loop < loop_stride:
            continue
        near = [
            i
            for i in tree.query_ball_point(se2[j, :2], loop_radius_m)
            if j - i >= cc.loop_min_index_gap and travel[j] - travel[i] >= cc.loop_min_travel_m
        ]
        if near:
            i = min(near, key=lambda n: np.hypot(*(se2[n, :2] - se2[j, :2])))
            rel = se2_between(se2[i], se2[j]) + ls_sig * rng.standard_normal(3)
            loops.append((i, j, rel, np.diag(ls_sig**2)))
            last_loop = j
    return Flight(stamps, truth, kf, deltas, covs, loops, float(travel[-1]))
