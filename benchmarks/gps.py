"""`collabslam bench gps`: georeferencing a flight with GPS factors (seed 000 §III).

One simulated flight with loops (`benchmarks.gps_flight`), GNSS fixes from
`simulation.gnss` (sigma 1.5 m, 1 Hz, bias, outages; 10 % multipath outliers in
the outlier runs, the same fixes otherwise), and the base station's `PoseGraph`
fed keyframe by keyframe (one iSAM2 update per keyframe, GPS fixes in the
configured batches), for each setting:

- ``none``: no GPS factor; the start is the first fix with the autopilot's heading
  (the virtual ENU-origin trajectory of §III-C), the only georeference;
- ``inverse`` (eq. 5), ``isotropic`` (eq. 6), and inverse with two (a, b) (eq. 7);
  each with and without Huber, with 0 and 10 % outliers.

``ate_rmse_m``: horizontal RMSE (m) of the keyframe positions in ENU against the
ground truth, without any alignment (the graph is 2-D; altitude comes from the
altimeter and is not scored). Also the iSAM2 update p95 (thread CPU time per
``PoseGraph.update``, so that other processes on the machine do not count) with
and without GPS factors, and a picture like seed 000 Fig. 8.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from basestation.gps_factor import GpsWeighting
from basestation.pose_graph import PoseGraph
from benchmarks.gps_flight import Flight, make_flight
from common.config import Config
from common.geodesy import GeoOrigin
from common.trajectory_io import Trajectory, write_tum
from simulation.gnss import GnssFix, simulate_fixes, world_origin
from simulation.world import World

log = logging.getLogger(__name__)

ROBOT = "uav"
HEADING_SIGMA_RAD = 0.05  # compass error of the autopilot heading used at the start


@dataclass(frozen=True)
class RunSpec:
    weighting: str  # none | inverse | isotropic
    a: float = 1.0
    b: float = 0.0
    huber: bool = False
    outlier_fraction: float = 0.0

    @property
    def label(self) -> str:
        name = self.weighting
        if (self.a, self.b) != (1.0, 0.0):  # eq. 7
            name += f" a={self.a:g} b={self.b:g}"
        if self.huber:
            name += " +Huber"
        if self.outlier_fraction:
            name += f" {self.outlier_fraction:.0%} outl."
        return name


def default_specs(outlier_fraction: float = 0.1) -> list[RunSpec]:
    """No GPS; eq. 5, 6 and 7 (two (a, b)); Huber on/off under 0 and 10 % outliers for
    eq. 5 and eq. 6."""
    specs = [RunSpec("none")]
    specs += [
        RunSpec("inverse"),
        RunSpec("isotropic"),
        RunSpec("inverse", 1.0, 0.5),
        RunSpec("inverse", 0.5, 0.0),
    ]
    for weighting in ("inverse", "isotropic"):
        specs += [
            RunSpec(weighting, huber=True),
            RunSpec(weighting, outlier_fraction=outlier_fraction),
            RunSpec(weighting, huber=True, outlier_fraction=outlier_fraction),
        ]
    return specs


def solve(
    cfg: Config, flight: Flight, fixes: list[GnssFix], origin: GeoOrigin, spec: RunSpec, seed: int
) -> tuple[np.ndarray, list[float], dict[str, int]]:
    """Feed the flight (and fixes unless ``none``) keyframe by keyframe into a PoseGraph;
    returns (K, 3) final ENU poses, iSAM2 update times (ms) and GPS statistics."""
    g = cfg.basestation.gps
    weighting = GpsWeighting(
        "inverse" if spec.weighting == "none" else spec.weighting,
        spec.a,
        spec.b,
        g.huber_k if spec.huber else None,
        g.sigma_min_m,
        (g.antenna_x_m, g.antenna_y_m),
    )
    bs = cfg.basestation
    graph = PoseGraph(
        bs.relinearize_threshold,
        bs.relinearize_skip,
        (bs.prior_sigma_xy_m, bs.prior_sigma_xy_m, bs.prior_sigma_yaw_rad),
        track_changes=False,
        gps_weighting=weighting,
        max_pending_gps_fixes=g.max_pending_fixes,
        gps_batch_period_s=g.batch_period_s,
        factorization="QR",  # the loose georeferenced start needs it (see PoseGraph)
    )
    enu = [f.enu(origin)[:2] for f in fixes]
    heading = flight.kf_truth[0, 3] + HEADING_SIGMA_RAD * np.random.default_rng(seed).normal()
    start = np.array([*enu[0], heading])  # virtual ENU-origin trajectory (§III-C)
    graph.add_robot(ROBOT, start, (g.start_sigma_xy_m, g.start_sigma_xy_m, g.start_sigma_yaw_rad))
    loops_at: dict[int, list[Any]] = {}
    for loop in flight.loops:
        loops_at.setdefault(loop[1], []).append(loop)
    cc = bs.constraints
    robust = None if cc.robust_kernel == "none" else cc.robust_kernel
    times: list[float] = []
    next_fix = 0
    for k, t in enumerate(flight.kf_stamps):
        if k == 0:
            graph.add_node(ROBOT, 0, None, None, initial_guess=start, stamp=float(t))
        else:
            graph.add_node(ROBOT, k, flight.deltas[k - 1], flight.delta_covs[k - 1], stamp=float(t))
        while next_fix < len(fixes) and fixes[next_fix].stamp <= t:
            if spec.weighting != "none":
                f = fixes[next_fix]
                graph.add_gps_fix(ROBOT, f.stamp, enu[next_fix], f.sigmas_enu)
            next_fix += 1
        for i, j, rel, cov in loops_at.get(k, []):
            graph.add_constraint((ROBOT, i), (ROBOT, j), rel, cov, robust, cc.robust_k)
        t0 = time.thread_time()  # CPU time: the machine is shared, wall time is noisy
        graph.update()
        times.append((time.thread_time() - t0) * 1e3)
    graph.flush_gps()
    graph.update(extra_iterations=10)
    return graph.poses(ROBOT), times, graph.gps_stats()


def _ate(est: np.ndarray, flight: Flight) -> float:
    d = est[:, :2] - flight.kf_truth[:, :2]
    return float(np.sqrt(np.mean(np.sum(d**2, axis=1))))


def _plot(
    path: Path, flight: Flight, fixes_enu: np.ndarray, results: dict[str, np.ndarray]
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t, gt = flight.kf_stamps, flight.kf_truth
    fig, axes = plt.subplots(2, 2, figsize=(13, 9))
    ax = axes[0, 0]
    ax.scatter(fixes_enu[:, 1], fixes_enu[:, 2], s=4, c="0.6", label="GPS fixes")
    ax.plot(gt[:, 0], gt[:, 1], "k-", lw=2, label="ground truth")
    for label, est in results.items():
        ax.plot(est[:, 0], est[:, 1], lw=1, label=label)
    ax.set(xlabel="east (m)", ylabel="north (m)", title="trajectories in ENU", aspect="equal")
    ax.legend(fontsize=7)
    for ax, col, name in ((axes[0, 1], 0, "east"), (axes[1, 0], 1, "north")):
        ax.scatter(fixes_enu[:, 0], fixes_enu[:, 1 + col], s=4, c="0.6", label="GPS")
        ax.plot(t, gt[:, col], "k-", lw=2, label="ground truth")
        for label, est in results.items():
            ax.plot(t, est[:, col], lw=1, label=label)
        ax.set(xlabel="time (s)", ylabel=f"{name} (m)", title=f"{name} coordinate over time")
    ax = axes[1, 1]
    for label, est in results.items():
        ax.plot(t, np.hypot(*(est[:, :2] - gt[:, :2]).T), lw=1, label=label)
    ax.set(xlabel="time (s)", ylabel="horizontal error (m)", title="error of the final estimate")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run(
    cfg: Config,
    out_dir: Path,
    data_dir: Path,
    world: str = "floor30x25",
    length_m: float = 300.0,
    gnss_seeds: int = 6,
    specs: list[RunSpec] | None = None,
) -> dict[str, Any]:
    """Every spec on one flight with ``gnss_seeds`` independent GNSS noise draws;
    ``ate_rmse_m`` is the mean over the draws (one draw is one random number)."""
    del data_dir  # simulated only
    out_dir.mkdir(parents=True, exist_ok=True)
    seed = cfg.sim.seed
    flight = make_flight(cfg, world, length_m, seed)
    origin = world_origin(World.load(world).geo_origin, cfg.sim.gnss)
    log.info(
        "flight: %.0f m, %.0f s, %d keyframes, %d loop closures",
        flight.distance_m,
        flight.stamps[-1],
        len(flight.kf_index),
        len(flight.loops),
    )
    fixes: dict[tuple[float, int], list[GnssFix]] = {}
    runs, estimates, update_ms = [], {}, {}
    for spec in specs or default_specs():
        ates, times, stats = [], [], {}
        for k in range(gnss_seeds):
            key = (spec.outlier_fraction, seed + k)
            if key not in fixes:  # same draws across outlier fractions but for the jumps
                gnss = dataclasses.replace(cfg.sim.gnss, outlier_fraction=key[0])
                fixes[key] = simulate_fixes(
                    gnss, origin, flight.stamps, flight.truth[:, :3], key[1]
                )
            est, t_ms, stats = solve(cfg, flight, fixes[key], origin, spec, key[1])
            ates.append(_ate(est, flight))
            times += t_ms
            if k == 0:
                estimates[spec] = est
        row = {**dataclasses.asdict(spec), "ate_rmse_m": float(np.mean(ates))}
        row["ate_rmse_m_per_seed"] = ates
        row.update(stats, update_ms_p95=float(np.percentile(times, 95)))
        log.info("%s: ATE %.3f m (%s)", spec.label, row["ate_rmse_m"], np.round(ates, 3))
        runs.append(row)
        update_ms[spec] = times
        est = estimates[spec]
        z = flight.kf_truth[:, 2]
        traj = Trajectory.from_pose4(flight.kf_stamps, np.column_stack([est[:, :2], z, est[:, 2]]))
        name = spec.label.replace(" ", "_").replace("%", "pct").replace("=", "")
        write_tum(out_dir / f"{name}.tum", traj, wgs84_origin=origin)
    write_tum(
        out_dir / "ground_truth.tum",
        Trajectory.from_pose4(flight.kf_stamps, flight.kf_truth),
        wgs84_origin=origin,
    )
    fixes0 = fixes[min(fixes)]
    fixes_enu = np.array([[fx.stamp, *fx.enu(origin)] for fx in fixes0])
    shown = [s for s in estimates if not s.huber and s.outlier_fraction == 0.0]
    shown += [s for s in estimates if s.weighting == "inverse" and s.outlier_fraction > 0.0]
    _plot(out_dir / "gps_fig8.png", flight, fixes_enu, {s.label: estimates[s] for s in shown})
    result = {"runs": runs, **_summary(runs, update_ms)}
    result["flight"] = {**_flight_info(flight, fixes0), "gnss_seeds": gnss_seeds}
    return result


def _flight_info(flight: Flight, fixes: list[GnssFix]) -> dict[str, Any]:
    return {
        "distance_m": flight.distance_m,
        "duration_s": float(flight.stamps[-1]),
        "keyframes": len(flight.kf_index),
        "loop_closures": len(flight.loops),
        "gps_fixes": len(fixes),
        "gps_sigma_median_m": float(np.median([f.sigmas_enu[:2] for f in fixes])),
    }


def _summary(runs: list[dict[str, Any]], update_ms: dict[RunSpec, list[float]]) -> dict[str, Any]:
    def ate(weighting: str, huber: bool, outliers: bool) -> float | None:
        for r in runs:  # (eq. 5 / 6 alone: a = 1, b = 0)
            if (r["weighting"], r["huber"], r["outlier_fraction"] > 0, r["a"], r["b"]) == (
                weighting,
                huber,
                outliers,
                1.0,
                0.0,
            ):
                return float(r["ate_rmse_m"])
        return None

    gps_clean = [
        r["ate_rmse_m"] for r in runs if r["weighting"] != "none" and not r["outlier_fraction"]
    ]
    out: dict[str, Any] = {"ate_no_gps_m": ate("none", False, False)}
    if gps_clean:
        out["ate_gps_worst_without_outliers_m"] = max(gps_clean)
    change: dict[str, dict[str, float]] = {}
    for weighting in ("inverse", "isotropic"):
        for huber in (False, True):
            clean, dirty = ate(weighting, huber, False), ate(weighting, huber, True)
            if clean and dirty:
                key = "huber" if huber else "no_huber"
                change.setdefault(key, {})[weighting] = 100.0 * (dirty / clean - 1.0)
    out["outlier_change_pct"] = change  # ATE change from 10 % multipath outliers
    no_gps = [t for s, t in update_ms.items() if s.weighting == "none"]
    with_gps = [t for s, t in update_ms.items() if s.weighting != "none"]
    if no_gps and with_gps:
        p_without = float(np.percentile(np.concatenate(no_gps), 95))
        p_with = float(np.percentile(np.concatenate(with_gps), 95))
        out["isam2_update_ms_p95_without_gps"] = p_without
        out["isam2_update_ms_p95_with_gps"] = p_with
        out["isam2_update_p95_ratio"] = p_with / p_without
        out["isam2_update_ms_mean_without_gps"] = float(np.mean(np.concatenate(no_gps)))
        out["isam2_update_ms_mean_with_gps"] = float(np.mean(np.concatenate(with_gps)))
    return out
