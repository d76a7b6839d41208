"""`collabslam bench smoothing`: the step metrics, and a tiny real flight."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from agent.control_log import ControlLog
from agent.pose_smoother import PoseSmoother, blend_alpha, pose7_compose
from benchmarks.smoothing import run, score_log
from collabslam.cli import build_parser
from common.config import Config
from common.errors import ConfigError
from common.geometry import pose4_to_pose7

KEYS = {"max_step_raw_m", "max_step_filtered_m", "max_rot_step_raw_deg"}
KEYS |= {"max_rot_step_filtered_deg", "ratio_filtered_over_raw", "target_met"}


def test_steps_exclude_the_robots_own_motion(cfg: Config) -> None:
    """A robot flying a 5 m radius circle; at t = 2 s the correction moves 0.5 m
    and turns 5 deg. Only the correction shows as a step."""
    stamps = np.arange(0.0, 12.0, 0.025)
    odom = np.array([pose4_to_pose7([5 * np.cos(t), 5 * np.sin(t), 1.0, t]) for t in stamps])
    before, after = pose4_to_pose7([0, 0, 0, 0]), pose4_to_pose7([0.3, 0.4, 0, np.deg2rad(5)])
    sm = PoseSmoother(cfg.agent.smoothing, before)
    raw, applied = [], []
    for i, t in enumerate(stamps):
        if i == 80:
            sm.on_correction(after, t)
        raw.append(sm.target)
        applied.append(sm.applied(t))
    s = score_log(ControlLog(stamps, odom, np.array(raw), np.array(applied)))
    assert s["corrections_changed"] == 1
    assert s["max_rot_step_raw_deg"] == pytest.approx(5.0)
    assert s["max_rot_step_filtered_deg"] == pytest.approx(5.0 * (1 - blend_alpha(0.0)))
    # The raw step is the full displacement of the robot's map position by the new
    # correction (rotation on the ~5 m lever arm included), not the flown arc.
    jump = pose7_compose(after, odom[80])[:3] - pose7_compose(before, odom[80])[:3]
    assert s["max_step_raw_m"] == pytest.approx(float(np.linalg.norm(jump)))
    assert s["max_step_filtered_m"] <= 0.1 * s["max_step_raw_m"]
    assert s["steps_over_5cm_raw"] == 1 and s["steps_over_5cm_filtered"] == 0


@pytest.mark.e2e
def test_bench_runs_a_tiny_flight(cfg: Config, tmp_path: Path) -> None:
    res = run(
        cfg,
        tmp_path / "bench",
        tmp_path,
        robots=1,
        length_m=15.0,
        max_sim_time=15.0,
        scenarios=("odometry_drift",),
    )
    assert KEYS <= set(res) and KEYS <= set(res["scenarios"]["odometry_drift"])
    r0 = res["scenarios"]["odometry_drift"]["robots"]["r0"]
    assert r0["ticks"] > 0.9 * 15.0 * cfg.sim.laser.rate_hz
    assert r0["max_step_filtered_m"] <= r0["max_step_raw_m"] + 1e-9
    assert Path(res["plot"]).is_file() and Path(res["plot"]).stat().st_size > 10_000
    assert (tmp_path / "bench" / "odometry_drift" / "control_poses" / "r0.csv").is_file()
    json.dumps(res)  # JSON-ready


def test_cli_arguments_and_unknown_scenario(cfg: Config, tmp_path: Path) -> None:
    args = build_parser().parse_args(
        ["bench", "smoothing", "--json", "o.json", "--robots", "1", "--scenarios", "local_slam"]
    )
    kwargs = args.bench_kwargs(args)
    assert kwargs["robots"] == 1 and kwargs["scenarios"] == ("local_slam",)
    with pytest.raises(ConfigError, match="unknown scenario"):
        run(cfg, tmp_path / "b", tmp_path, scenarios=("nope",))
    assert not (tmp_path / "b").exists()
