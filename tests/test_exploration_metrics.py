"""Exploration's yardsticks: map history over sim time, coverage-over-time curves, robot
separation and the reachable region, and `bench exploration`'s speed-ups from its rows."""

from __future__ import annotations

import numpy as np
import pytest
from grid_helpers import grid_with_wall

from basestation.map_history import MapHistory, read_map_history
from benchmarks.exploration import speedups
from common.errors import CollabSlamError
from common.map_io import GridMap
from common.metrics import coverage_curve, min_separation, reachable_free, time_to_coverage
from common.trajectory_io import Trajectory


def test_map_history_round_trip_and_coverage_over_time(tmp_path) -> None:
    world = grid_with_wall()
    region = reachable_free(world, [[1.0, 1.0]])
    assert region.sum() == (world.data == 0).sum()  # the wall leaves a way round
    h = MapHistory()
    for t, upto in ((1.0, 50), (2.0, 120), (3.0, 200)):
        data = np.full((200, 200), -1, np.int8)
        data[:upto] = world.data[:upto]
        h.add(t, GridMap(data, 0.05, (0.0, 0.0, 0.0)))
    h.write(tmp_path / "h.npz")
    back = read_map_history(tmp_path / "h.npz")
    assert [t for t, _ in back] == [1.0, 2.0, 3.0]
    np.testing.assert_array_equal(back[2][1].free_mask(), world.free_mask())
    t, c = coverage_curve(back, world, region)
    assert np.all(np.diff(c) > 0) and c[-1] == pytest.approx(1.0)
    assert time_to_coverage(t, c, 0.95) == 3.0
    assert time_to_coverage(t, c[:2], 0.95) is None
    with pytest.raises(CollabSlamError):
        read_map_history(tmp_path / "missing.npz")


def test_the_final_map_is_the_coverage_curves_last_point(tmp_path) -> None:
    """The last snapshot lags the robots by the keyframes still on their way: the map
    written at the end (every keyframe taken before the simulation stopped) counts at
    the end time."""
    from collabslam.summary import _coverage_over_time
    from common.map_io import write_map
    from common.scenario import RobotScenario, Scenario, write_scenario

    world = grid_with_wall()
    write_map(world, tmp_path / "world.yaml")
    start = np.array([1.0, 1.0, 0.0])
    write_scenario(tmp_path / "scenario.json", Scenario("world.yaml", [RobotScenario("r0", start)]))
    h = MapHistory()
    for t, upto in ((1.0, 50), (2.0, 150)):
        data = np.full((200, 200), -1, np.int8)
        data[:upto] = world.data[:upto]
        h.add(t, GridMap(data, 0.05, (0.0, 0.0, 0.0)))
    h.write(tmp_path / "map_history.npz")
    assert _coverage_over_time(tmp_path, tmp_path / "world.yaml", 2.4)["time_to_95_s"] is None
    write_map(world, tmp_path / "map.yaml")  # everything seen by the end
    cov = _coverage_over_time(tmp_path, tmp_path / "world.yaml", 2.4)
    assert cov["time_to_95_s"] == 2.4 and cov["coverage_curve"][-1] == [2.4, 1.0]


def test_min_separation_and_reachable_region_errors() -> None:
    t = np.arange(5.0)
    a = Trajectory.from_pose4(t, np.column_stack([t, 0 * t, 0 * t, 0 * t]))
    b = Trajectory.from_pose4(t, np.column_stack([4.0 - t, 0 * t + 1.0, 0 * t, 0 * t]))
    assert min_separation([a, b]) == pytest.approx(1.0)
    assert min_separation([a]) is None
    with pytest.raises(CollabSlamError):
        reachable_free(grid_with_wall(), [[5.0, 5.04]])  # inside the wall


def test_bench_speedups_from_rows() -> None:
    rows = {
        "ours": [{"robots": 1, "time_to_95_s": 60.0}, {"robots": 3, "time_to_95_s": 20.0}],
        "baseline": [{"robots": 1, "time_to_95_s": 60.0}, {"robots": 3, "time_to_95_s": None}],
    }
    s = speedups(rows, [1, 3], max_sim_time=100.0)
    assert s["ours_speedup_3"] == 3.0
    assert s["baseline_speedup_3"] == 0.6  # never reached: counted as the max sim time
    assert s["ours_faster_than_baseline_pct_3"] == 80.0
    rows["ours"] += [{"robots": 3, "time_to_95_s": 30.0}, {"robots": 3, "time_to_95_s": None}]
    rows["baseline"] += [{"robots": 3, "time_to_95_s": 40.0}, {"robots": 3, "time_to_95_s": 50.0}]
    s = speedups(rows, [1, 3], max_sim_time=100.0)
    assert s["ours_mean_time_to_95_s_3"] == 50.0 and s["ours_median_time_to_95_s_3"] == 30.0
    assert s["ours_median_speedup_3"] == 2.0 and s["baseline_median_time_to_95_s_3"] == 50.0
    assert s["ours_faster_than_baseline_median_pct_3"] == 40.0


def test_a_failed_mission_is_reported_and_the_batch_goes_on(tmp_path, monkeypatch) -> None:
    """One mission whose process died (a port taken by another program, say) is a row
    with its error, left out of the means, and the other missions still run."""
    import benchmarks.exploration as bench
    from common.config import load_config
    from common.errors import ProcessError

    def mission(cfg, world, n, seed, strategy, out, max_sim_time):
        if seed == 1:
            raise ProcessError(f"basestation (pid 1) exited with code 1; see {out}/logs")
        t = 10.0 * n if strategy == "greedy" else 5.0 * n
        return {"robots": n, "seed": seed, "time_to_95_s": t, "collisions": 0,
                "min_robot_separation_m": None, "coverage_curve": [[0, 0], [t, 1]]}  # fmt: skip

    monkeypatch.setattr(bench, "run_mission", mission)
    report = bench.run(load_config(), tmp_path / "b", tmp_path, ["bshape"], [1], 3, 100.0)
    assert [r["seed"] for r in report["ours"]] == [0, 1, 2]
    failed = report["ours"][1]
    assert failed["time_to_95_s"] is None and "exited with code 1" in failed["error"]
    assert report["failed_runs"] == 2  # ours and the baseline's seed 1
    assert report["summary"]["ours_mean_time_to_95_s_1"] == 5.0  # not 100 s for the failed
    assert report["summary"]["ours_faster_than_baseline_pct_1"] == 50.0
