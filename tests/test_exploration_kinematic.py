"""The kinematic exploration model: the base station's decisions flown without the stack."""

from __future__ import annotations

import pytest

from benchmarks.exploration_kinematic import fly_kinematic, run_kinematic
from common.config import Config
from common.errors import ConfigError


@pytest.mark.e2e
def test_a_kinematic_team_explores_bshape_apart_and_repeatably() -> None:
    row = run_kinematic(Config(), "bshape", 3, 0, "coordinated", 60.0)
    assert row["end_reason"] == "95 %" and row["final_coverage"] >= 0.95
    assert row["time_to_95_s"] is not None and row["time_to_95_s"] < 30.0, row
    assert row["min_robot_separation_m"] >= 1.0, row  # (wall contacts: no guard here)
    assert all(d > 3.0 for d in row["distance_m"]), row  # every drone flew
    curve = [c for _, c in row["coverage_curve"]]
    assert curve == sorted(curve)  # the map only learns
    # the same seed flies the same mission (no clock races; OMPL seeded per process)
    again = run_kinematic(Config(), "bshape", 3, 0, "coordinated", 6.0)
    assert again["coverage_curve"] == row["coverage_curve"][: len(again["coverage_curve"])]
    assert again["end_reason"] == "max_sim_time"


def test_an_unknown_strategy_is_refused_not_flown_as_greedy() -> None:
    with pytest.raises(ConfigError, match="coordinated or greedy"):
        fly_kinematic(Config(), "bshape", 3, 0, "ours", 6.0)  # the bench's name, not the config's
