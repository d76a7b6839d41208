"""`collabslam bench local-slam`: speed and accuracy of the agent's local SLAM.

- sim: one drone flies a >= 200 m tour of a shipped world; its recorded
  1081-beam UTM-30LX scans (40 Hz) go through the whole local SLAM
  (`LocalTrajectoryBuilder`, exactly what the agent runs) on one core.
  `sim.drift_pct` = final position error / distance flown (no loop closing).
- corridor: 40 m straight along a plain 3 m corridor (88 m long, walls only), where the
  scans say nothing about the way flown: `corridor.distance_err_pct` is local SLAM's
  distance flown against the truth's (the odometry's beside it). Misses along grazing
  rays had eroded the walls ahead, and local SLAM came up 20 % short.
- intel / aces: the whole Intel Research Lab and ACES logs through the same local SLAM,
  scored with the Kuemmerle et al. relations (`intel.*`, `aces.*`).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from agent.local_trajectory_builder import LocalTrajectoryBuilder
from agent.sensor_sources import CarmenReplay
from benchmarks.sensor_recording import record_tour
from common.config import Config
from common.drift_metrics import drift_percent
from common.geometry import pose7_to_pose4
from common.map_io import write_map
from common.relations import read_relations, score_relations
from common.trajectory_io import Trajectory, write_tum
from protocol import Altimeter, Imu, LaserScan, Odometry
from simulation.world_generator import generate_world

log = logging.getLogger(__name__)


def run_local_slam(cfg: Config, messages: Any) -> tuple[Trajectory, int, float]:
    """Feed sensor messages to a fresh LocalTrajectoryBuilder; (trajectory, scans, seconds)."""
    b = LocalTrajectoryBuilder(cfg.agent.local_slam, cfg.agent.local_keyframe_period_s)
    stamps, poses = [], []
    t0 = time.perf_counter()
    for m in messages:
        if isinstance(m, LaserScan):
            r = b.add_scan(m)
            if r is not None:
                stamps.append(r.stamp)
                poses.append(r.pose)
        elif isinstance(m, Odometry):
            b.add_odometry(m.stamp, pose7_to_pose4(m.pose)[[0, 1, 3]])
        elif isinstance(m, Imu):
            b.add_imu(m.stamp, m.orientation)
        elif isinstance(m, Altimeter):
            b.add_altitude(m.stamp, m.altitude)
    wall = time.perf_counter() - t0
    return Trajectory.from_pose4(np.array(stamps), np.array(poses)), b.scans, wall


def _warm_up(cfg: Config) -> None:
    """Compile the numba kernels before timing (their cache makes this quick)."""
    rec = record_tour(cfg, "rooms15", length_m=3.0, seed=1)
    run_local_slam(cfg, rec.messages)


def bench_sim(cfg: Config, out_dir: Path, world: str, length_m: float) -> dict[str, Any]:
    rec = record_tour(cfg, world, length_m=length_m, seed=cfg.sim.seed)
    traj, scans, wall = run_local_slam(cfg, rec.messages)
    write_tum(out_dir / "sim_local_slam.tum", traj)
    write_tum(out_dir / "sim_ground_truth.tum", rec.ground_truth)
    rate = scans / wall
    return {
        "world": world,
        "scans": scans,
        "distance_m": rec.distance_m,
        "scans_per_s": rate,
        "sensor_hz": cfg.sim.laser.rate_hz,
        "realtime_factor": rate / cfg.sim.laser.rate_hz,
        "drift_pct": drift_percent(traj, rec.ground_truth, align_first=True),
        "wall_s": wall,
    }


CORRIDOR_START = (4.0, 1.5, 0.0)  # m, rad: 4 m into the corridor, on its axis, facing along


def corridor_flight(cfg: Config, out_dir: Path, length_m: float = 40.0) -> dict[str, Any]:
    """Local SLAM and odometry along a plain corridor (module doc): the distance each
    says was flown against the truth's (%), and its cross-track RMS (m), each track's
    first pose put on the truth's."""
    yaml = out_dir / "corridor.yaml"
    write_map(generate_world("corridor"), yaml)
    x0, y0, _ = CORRIDOR_START
    tour = np.array([[x0, y0], [x0 + length_m, y0]])
    rec = record_tour(cfg, str(yaml), length_m, start=CORRIDOR_START, tour=tour)
    traj, scans, wall = run_local_slam(cfg, rec.messages)
    odo = [(m.stamp, pose7_to_pose4(m.pose)) for m in rec.messages if isinstance(m, Odometry)]
    odometry = Trajectory.from_pose4(np.array([t for t, _ in odo]), np.array([p for _, p in odo]))
    out: dict[str, Any] = {"length_m": length_m, "scans": scans, "wall_s": wall}
    for name, track in (("", traj), ("odometry_", odometry)):
        err, across = _along_corridor(track, rec.ground_truth)
        out[f"{name}distance_err_pct"] = err
        out[f"{name}cross_track_rms_m"] = across
    return out


def _along_corridor(track: Trajectory, truth: Trajectory) -> tuple[float, float]:
    """(distance along x against the truth's, %; RMS of y off the truth's, m) of `track`
    with its first pose put on the truth's at that stamp."""
    t = track.stamps
    true = np.column_stack([np.interp(t, truth.stamps, truth.positions[:, k]) for k in (0, 1)])
    first, true_yaw = track.poses_se2()[0], np.interp(t[0], truth.stamps, truth.poses_se2()[:, 2])
    d = true_yaw - first[2]
    rot = np.array([[np.cos(d), np.sin(d)], [-np.sin(d), np.cos(d)]])
    xy = (track.positions[:, :2] - first[:2]) @ rot + true[0]
    flown, true_flown = xy[-1, 0] - xy[0, 0], true[-1, 0] - true[0, 0]
    return 100.0 * (flown - true_flown) / true_flown, float(
        np.sqrt(np.mean((xy[:, 1] - true[:, 1]) ** 2))
    )


def bench_carmen(
    cfg: Config, out_dir: Path, log_path: Path, rel_path: Path, name: str
) -> dict[str, Any]:
    import threading

    messages = list(CarmenReplay(log_path, "bench").messages(threading.Event()))
    traj, scans, wall = run_local_slam(cfg, messages)
    write_tum(out_dir / f"{name}_local_slam.tum", traj)
    err = score_relations(traj, read_relations(rel_path))
    return {
        "scans": scans,
        "scans_per_s": scans / wall,
        "wall_s": wall,
        **err.as_dict(),
    }


def run(
    cfg: Config, out_dir: Path, data_dir: Path, world: str = "floor30x25", length_m: float = 220.0
) -> dict[str, Any]:
    out_dir.mkdir(parents=True, exist_ok=True)
    _warm_up(cfg)
    result: dict[str, Any] = {"sim": bench_sim(cfg, out_dir, world, length_m)}
    log.info("sim: %s", result["sim"])
    result["corridor"] = corridor_flight(cfg, out_dir)
    log.info("corridor: %s", result["corridor"])
    for name in ("intel", "aces"):
        log_path = data_dir / "carmen" / f"{name}.clf.bz2"
        rel_path = data_dir / "carmen" / f"{name}.relations"
        if log_path.is_file() and rel_path.is_file():
            result[name] = bench_carmen(cfg, out_dir, log_path, rel_path, name)
            log.info("%s: %s", name, result[name])
        else:
            log.warning("%s not found: skipped", log_path)
    return result
