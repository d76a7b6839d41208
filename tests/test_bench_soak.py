"""`collabslam bench soak`: latency rows over time, memory helpers, a tiny real mission."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from agent.local_trajectory_builder import LocalTrajectoryBuilder
from basestation.update_series import UpdateSeries
from benchmarks.soak import rss_mb, run, slope_per_min, soak_config
from collabslam.cli import build_parser
from common.config import Config
from common.errors import ConfigError

KEYS = {"robots", "sim_minutes", "wall_s", "rss_mb", "rss_peak_mb"}
KEYS |= {"rss_growth_mb_per_min_second_half", "outbox_high_water", "outbox_series"}
KEYS |= {"update_ms", "keyframes_sent", "keyframes_in_graph", "map_accuracy"}


def test_update_series_rows_per_period() -> None:
    s = UpdateSeries(period_s=10.0)
    t0 = s.t0
    for k, ms in enumerate([1.0, 2.0, 3.0, 4.0]):  # period [0, 10)
        s.add(ms, now=t0 + 1.0 + k)
    s.add(50.0, now=t0 + 35.0)  # periods [10, 30) idle: no rows for them
    s.add(10.0, now=t0 + 36.0)
    s.add(7.0, now=t0 + 41.0)  # closes [30, 40)
    assert len(s.rows) == 2
    t, n, p50, p95, mx = s.rows[0]
    assert (t, n, p50, mx) == (10.0, 4.0, 2.5, 4.0) and 3.0 < p95 <= 4.0
    assert s.rows[1][:2] == [40.0, 2.0] and s.rows[1][4] == 50.0
    out = s.to_json()
    assert out["columns"][0] == "t_s" and out["period_s"] == 10.0
    assert len(out["rows"]) == 3 and out["rows"][2][1:] == [1.0, 7.0, 7.0, 7.0]
    assert len(s.rows) == 2  # to_json does not close the open period
    json.dumps(out)


def test_memory_helpers() -> None:
    now, peak, anon = rss_mb(os.getpid()) or (0.0, 0.0, 0.0)
    assert 0.0 < anon < now <= peak
    assert rss_mb(2**22 + 12345) is None  # beyond pid_max: no such process
    line = [[t, 100.0 + 0.5 * t] for t in np.arange(0.0, 120.0, 5.0)]
    assert slope_per_min(line, 60.0, 120.0) == pytest.approx(30.0)
    assert slope_per_min(line, 200.0, 300.0) is None


def test_soak_config_flies_long_tours(cfg: Config) -> None:
    assert cfg.exploration.enabled  # the default mission explores, the soak must not
    c = soak_config(cfg, 30.0)
    assert not c.exploration.enabled and cfg.exploration.enabled
    assert c.sim.tour_length_m >= 30.0 * 60.0 * c.agent.cruise_speed_mps
    args = build_parser().parse_args(
        ["bench", "soak", "--json", "o.json", "--robots", "3", "--sim-minutes", "2.5"]
    )
    kwargs = args.bench_kwargs(args)
    assert kwargs == {"robots": 3, "sim_minutes": 2.5, "world": "floor30x25", "sample_s": 5.0}
    with pytest.raises(ConfigError, match="sim-minutes"):
        run(cfg, Path("unused"), Path("unused"), sim_minutes=0.0)


def test_agents_drop_finished_submaps(cfg: Config) -> None:
    """Local SLAM matches only against active submaps: finished ones are not kept
    (they grew an agent without bound over a long flight)."""
    builder = LocalTrajectoryBuilder(cfg.agent.local_slam)
    assert builder.submaps.max_finished_submaps == cfg.agent.local_slam.max_finished_submaps == 0


@pytest.mark.e2e
def test_bench_runs_a_tiny_soak(cfg: Config, tmp_path: Path) -> None:
    # Real-time clock: a lock-step mission this short can be over (18 s of sim time in
    # about a second) before the bench's Zenoh session sees the first robot state.
    cfg.sim.clock, cfg.sim.rate = "realtime", 1.5
    res = run(cfg, tmp_path / "bench", tmp_path, robots=2, sim_minutes=0.3, sample_s=0.5)
    assert KEYS <= set(res)
    assert res["robots"] == 2 and res["sim_time_s"] == pytest.approx(18.0, abs=0.5)
    assert len(res["rss_mb"]) >= 10 and all(mb > 10.0 for _, mb in res["rss_mb"][-5:])
    assert res["rss_peak_mb"] >= max(mb for _, mb in res["rss_mb"])
    assert res["basestation_cpu"] and all(cores >= 0.0 for _, cores, _ in res["basestation_cpu"])
    box = res["outbox_series"]
    assert set(box) == {"t_s", "r0", "r1"} and len(box["r0"]) == len(box["t_s"]) > 5
    assert set(res["outbox_high_water"]) == {"r0", "r1"}
    assert res["state_messages"] > 20 and max(sim for _, sim in res["sim_s"]) > 15.0
    assert res["update_ms"] and all(p50 <= p95 <= mx for _, p50, p95, mx in res["update_ms"])
    assert res["keyframes_in_graph"] == res["keyframes_sent"] > 20
    assert res["map_accuracy"] > 0.9
    mem = res["basestation_memory"]  # the base station's own samples, after its heap trims
    rows = [dict(zip(mem["columns"], r, strict=True)) for r in mem["rows"]]
    assert rows and all(r["rss_mb"] > 10.0 and r["py_blocks_k"] > 10.0 for r in rows)
    # keyframes admitted when sampled: the last trim may come before the last keyframes
    counts = [r["count"] for r in rows]
    assert counts == sorted(counts) and 0 < counts[-1] <= res["keyframes_in_graph"]
    arrays = [r["arrays_mb"] for r in rows]  # per-keyframe arrays: they only grow
    assert arrays == sorted(arrays) and 0.0 < arrays[-1] < rows[-1]["heap_in_use_mb"]
    assert Path(res["plot"]).stat().st_size > 10_000
    json.dumps(res)
