"""The kinematic exploration model: the base station's decisions flown without the stack."""

from __future__ import annotations

from pathlib import Path

import pytest

from benchmarks.exploration import run
from benchmarks.exploration_kinematic import fly_kinematic, run_kinematic
from collabslam.cli import build_parser
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


def test_a_bench_batch_may_start_at_any_seed(tmp_path: Path) -> None:
    """`bench exploration --first-seed K --seeds N`: seeds K..K+N-1, so that batches of one
    setting split over cores or machines add up to the seeds of one run."""
    report = run(
        Config(), tmp_path, tmp_path, ["bshape"], [3], 2, 3.0, ["ours"], kinematic=True,
        first_seed=5,
    )  # fmt: skip
    assert [r["seed"] for r in report["ours"]] == [5, 6]
    one = run_kinematic(Config(), "bshape", 3, 6, "coordinated", 3.0)
    assert one["coverage_curve"] == report["ours"][1]["coverage_curve"]  # seed 6 is seed 6
    args = build_parser().parse_args(
        ["bench", "exploration", "--json", "o.json", "--seeds", "24", "--first-seed", "24"]
    )
    kwargs = args.bench_kwargs(args)
    assert kwargs["first_seed"] == 24 and kwargs["seeds"] == 24
    with pytest.raises(ConfigError, match="first-seed"):
        run(Config(), tmp_path, tmp_path, ["bshape"], [3], 1, 3.0, ["ours"], first_seed=-1)


@pytest.mark.parametrize(
    ("robots", "strategies", "world", "match"),
    [
        ([3, 0], ["ours"], "bshape", "team sizes must be >= 1"),
        ([3], ["ours", "foo"], "bshape", "--strategies"),
        ([3], ["ours"], "random:abc", "random:SEED"),
    ],
)
def test_bad_bench_arguments_are_refused_before_any_run(
    tmp_path: Path, robots: list[int], strategies: list[str], world: str, match: str
) -> None:
    with pytest.raises(ConfigError, match=match):
        run(Config(), tmp_path, tmp_path, [world], robots, 1, 3.0, strategies, kinematic=True)
    assert not (tmp_path / "runs").exists()  # nothing flown
    with pytest.raises(SystemExit):  # argparse: a usage line and exit 2
        build_parser().parse_args(["bench", "exploration", "--json", "o.json", "--robots", "3,x"])
