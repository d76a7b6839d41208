"""`collabslam bench smoothing`: the pose steps a flight controller sees when loops
close, with and without the smoothing filter (seed 000 §II, Fig. 1).

Each flight is a real `collabslam run` (simulator, base station and agents as
separate processes over loopback Zenoh, the code path users run). Every agent
records each control tick (`control_poses/<id>.csv`): T_odom_base, the latest
raw correction and the correction its PoseSmoother applied. From those:

- step at tick k (m) = |T_map_odom(k)·T_odom_base(k) − T_map_odom(k−1)·T_odom_base(k)|,
    the change of the control pose between consecutive ticks beyond the robot's
  own (local SLAM) motion, i.e. the jump the correction introduced;
- rotation step (deg) = angle of T_map_odom(k−1)⁻¹·T_map_odom(k);
- the price: `max_offset_filtered_vs_raw_m` (how far the smoothed position
  trails the latest estimate) and `time_offset_over_5cm_s`.

"raw" applies every correction at once (what the controller saw without the
filter, same flight); "filtered" is the smoothed pose the agent published.

Flights (`scenarios`):
- `odometry_drift`: the agent tracks odometry only (`agent.local_slam.enabled =
  false`) with 3 % speed noise and a 0.003 rad/s gyro bias, so the odometry
  drifts by decimetres between loop closures and the corrections jump visibly;
- `local_slam`: the configuration as given (full local SLAM; small corrections).
"""

from __future__ import annotations

import copy
import logging
from pathlib import Path
from typing import Any

import numpy as np

from agent.control_log import (
    ControlLog,
    control_positions,
    correction_steps,
    read_control_log,
)
from benchmarks.smoothing_plot import plot_smoothing
from collabslam.launcher import Launcher
from common.config import Config
from common.config_validation import validate
from common.errors import ConfigError

log = logging.getLogger(__name__)

TARGET_RATIO = 0.1  # max_step_filtered_m <= max_step_raw_m / 10 (issue 6)
SCENARIOS = ("odometry_drift", "local_slam")
DRIFT_OVERRIDES = {  # scenario odometry_drift, on top of the given config
    "agent.local_slam.enabled": False,
    "sim.odometry.speed_noise_frac": 0.03,  # 1-sigma fraction of speed
    "sim.odometry.yaw_rate_bias": 0.003,  # rad/s
}


def score_log(ctl: ControlLog) -> dict[str, Any]:
    """The step metrics of one robot's control log (raw and filtered)."""
    if len(ctl) < 2:
        return {"ticks": len(ctl)}
    raw_t, raw_r = correction_steps(ctl.T_map_odom_raw, ctl.T_odom_base)
    fil_t, fil_r = correction_steps(ctl.T_map_odom_applied, ctl.T_odom_base)
    changes = np.any(np.abs(np.diff(ctl.T_map_odom_raw, axis=0)) > 0.0, axis=1)
    # The price of smoothing: how far the smoothed position trails the latest estimate.
    offset = np.linalg.norm(
        control_positions(ctl.T_map_odom_applied, ctl.T_odom_base)
        - control_positions(ctl.T_map_odom_raw, ctl.T_odom_base),
        axis=1,
    )
    dt = np.diff(ctl.stamps, prepend=ctl.stamps[0])
    return {
        "ticks": len(ctl),
        "duration_s": float(ctl.stamps[-1] - ctl.stamps[0]),
        "corrections_changed": int(changes.sum()),
        "max_step_raw_m": float(raw_t.max()),
        "max_step_filtered_m": float(fil_t.max()),
        "max_rot_step_raw_deg": float(raw_r.max()),
        "max_rot_step_filtered_deg": float(fil_r.max()),
        "steps_over_5cm_raw": int((raw_t > 0.05).sum()),
        "steps_over_5cm_filtered": int((fil_t > 0.05).sum()),
        "max_offset_filtered_vs_raw_m": float(offset.max()),
        "time_offset_over_5cm_s": float(dt[offset > 0.05].sum()),
    }


def _scenario_cfg(cfg: Config, name: str, length_m: float) -> Config:
    c = copy.deepcopy(cfg)
    c.exploration.enabled = False  # scripted tours with loops: the corrections to smooth
    c.sim.tour_length_m = length_m
    if name == "odometry_drift":
        for dotted, value in DRIFT_OVERRIDES.items():
            *parents, leaf = dotted.split(".")
            node: Any = c
            for part in parents:
                node = getattr(node, part)
            setattr(node, leaf, value)
    validate(c)
    return c


def fly(
    cfg: Config, out: Path, world: str, robots: int, max_sim_time: float
) -> dict[str, ControlLog]:
    """One `collabslam run`; the control logs of its robots."""
    Launcher(cfg, world, robots, out, max_sim_time, "WARNING").run()
    return {p.stem: read_control_log(p) for p in sorted((out / "control_poses").glob("*.csv"))}


def _combine(per_robot: dict[str, dict[str, Any]]) -> dict[str, Any]:
    keys = ("max_step_raw_m", "max_step_filtered_m", "max_rot_step_raw_deg")
    keys += ("max_rot_step_filtered_deg",)
    scored = [s for s in per_robot.values() if "max_step_raw_m" in s]
    out: dict[str, Any] = {k: max((s[k] for s in scored), default=None) for k in keys}
    raw, fil = out["max_step_raw_m"], out["max_step_filtered_m"]
    out["ratio_filtered_over_raw"] = fil / raw if raw else None
    # None: no correction ever moved the control pose, nothing to smooth.
    out["target_met"] = bool(fil <= raw * TARGET_RATIO) if raw else None
    return out


def run(
    cfg: Config,
    out_dir: Path,
    data_dir: Path,
    world: str = "bshape",
    robots: int = 2,
    length_m: float = 120.0,
    max_sim_time: float = 150.0,
    scenarios: tuple[str, ...] = SCENARIOS,
) -> dict[str, Any]:
    """Fly each scenario and score every robot's control-pose stream (data_dir unused)."""
    unknown = sorted(set(scenarios) - set(SCENARIOS))
    if unknown:
        raise ConfigError(f"unknown scenario {unknown[0]!r}: expected one of {SCENARIOS}")
    out_dir.mkdir(parents=True, exist_ok=True)
    result: dict[str, Any] = {
        "world": world,
        "robots": robots,
        "tour_length_m": length_m,
        "control_rate_hz": cfg.sim.laser.rate_hz,
        "smoothing": {
            "enabled": cfg.agent.smoothing.enabled,
            "s": cfg.agent.smoothing.s,
            "t_x_s": cfg.agent.smoothing.t_x_s,
            "duration_s": cfg.agent.smoothing.duration_s,
        },
        "target": f"max_step_filtered_m <= max_step_raw_m * {TARGET_RATIO}",
        "scenarios": {},
    }
    logs: dict[str, ControlLog] = {}
    for name in scenarios:
        c = _scenario_cfg(cfg, name, length_m)
        flown = fly(c, out_dir / name, world, robots, max_sim_time)
        per_robot = {rid: score_log(ctl) for rid, ctl in flown.items()}
        overrides = DRIFT_OVERRIDES if name == "odometry_drift" else {}
        result["scenarios"][name] = {
            "overrides": overrides,
            **_combine(per_robot),
            "robots": per_robot,
        }
        logs.update({f"{name}/{rid}": ctl for rid, ctl in flown.items()})
        log.info("%s: %s", name, _combine(per_robot))
    combined = {k: v for k, v in result["scenarios"].items()}
    all_robots = {f"{n}/{rid}": s for n, sc in combined.items() for rid, s in sc["robots"].items()}
    result.update(_combine(all_robots))
    worst = max(
        (k for k, s in all_robots.items() if "max_step_raw_m" in s),
        key=lambda k: all_robots[k]["max_step_raw_m"],
        default=None,
    )
    if worst is not None:
        png = out_dir / "smoothing.png"
        plot_smoothing(logs[worst], png, title=f"{world}, {worst}")
        result["plot"] = str(png)
        result["plot_robot"] = worst
    return result
