"""Robots that can never be joined to a map whose drone never flew are named, with the
reason, in a rate-limited warning, basestation.json and summary.json (bshape, 3 drones,
unknown starts, r0's tour empty: r0 sent 1 keyframe, r1 and r2 215 and 221, never
joined, and nothing said why)."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest
from process_helpers import synthetic_keyframe

from basestation.global_slam import GlobalSlam
from basestation.map_frame import MapFrame, spread_m
from collabslam.summary import build_summary
from common.config import Config
from simulation.world import resolve_world

ZERO = np.zeros(3)
STEP = np.array([0.5, 0.0, 0.0])


def _fly(slam: GlobalSlam, rid: str, n: int) -> None:
    """`n` keyframes 0.5 m apart along the robot's x axis."""
    for i in range(n):
        assert slam.admit(synthetic_keyframe(rid, i, i * STEP, STEP if i else ZERO)) == 1
    slam.optimize()


def _mission(cfg: Config, map_robot_keyframes: int, **kwargs) -> GlobalSlam:
    slam = GlobalSlam(cfg, threaded=False, **kwargs)
    if map_robot_keyframes:
        _fly(slam, "r0", map_robot_keyframes)
    _fly(slam, "r1", 10)  # 4.5 m: far enough to be joined
    _fly(slam, "r2", 10)
    return slam


def _warnings(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]


def test_robots_that_cannot_join_a_map_of_one_keyframe_are_named(
    caplog: pytest.LogCaptureFixture,
) -> None:
    slam = _mission(Config(), 1, known_starts={"r0": ZERO})  # the scenario's first robot
    try:
        caplog.set_level(logging.WARNING)
        slam.map_frame = frame = MapFrame(slam)  # its clock from 100 s on
        for now in (100.0, 110.0, 129.0):  # the first check starts the period
            frame.check(now)
        assert _warnings(caplog) == []
        frame.check(130.0)
        frame.check(140.0)  # rate-limited: not again before 160 s
        (line,) = _warnings(caplog)
        assert line.startswith("robots r1, r2 not joined to the map yet: the map (r0) has 1 "
                               "keyframe spread over 0.0 m; a join needs")  # fmt: skip
        frame.check(160.0)
        assert len(_warnings(caplog)) == 2

        st = slam.stats()["map_frame"]
        assert st["unjoined"] == ["r1", "r2"] and st["map_robots"] == ["r0"]
        assert st["map_keyframes"] == 1 and st["map_spread_m"] == 0.0
        assert "merge_min_spread_m" in st["unjoinable_reason"] and st["warnings"] == 2

        slam.converge()  # the mission's end: said once more, whenever the last was
        assert _warnings(caplog)[-1].startswith("robots r1, r2 not joined to the map at the end")
    finally:
        slam.close()


@pytest.mark.parametrize("two_on_map", [False, True])
def test_no_warning_while_the_map_can_take_them(
    two_on_map: bool, caplog: pytest.LogCaptureFixture
) -> None:
    """r0 flew 2.5 m; or r0 and r3 on the map, neither flew: matches with both that
    agree join a robot on its own spread (loop_closure_manager._agreeing_elsewhere)."""
    starts = {"r0": ZERO, "r3": np.array([9.0, 9.0, 0.0])} if two_on_map else {"r0": ZERO}
    slam = _mission(Config(), 1 if two_on_map else 6, known_starts=starts)
    try:
        if two_on_map:
            _fly(slam, "r3", 1)
        caplog.set_level(logging.WARNING)
        slam.converge()
        st = slam.stats()["map_frame"]
        assert st["unjoined"] == ["r1", "r2"] and st["unjoinable_reason"] is None
        assert _warnings(caplog) == [] and st["warnings"] == 0
    finally:
        slam.close()


@pytest.mark.parametrize("known", [False, True])
def test_a_map_robot_that_never_sends_is_named(
    known: bool, caplog: pytest.LogCaptureFixture
) -> None:
    """Its agent never started: `map_frame_robot`, or the scenario's first robot."""
    cfg = Config()
    cfg.basestation.map_frame_robot = "r0"
    slam = _mission(cfg, 0, known_starts={"r0": ZERO} if known else None)
    try:
        caplog.set_level(logging.WARNING)
        slam.converge()
        reason = slam.stats()["map_frame"]["unjoinable_reason"]
        assert reason == "no robot is on the map: r0 sent no keyframe"
        assert _warnings(caplog) == [f"robots r1, r2 not joined to the map at the end: {reason}"]
    finally:
        slam.close()


def test_spread_of_keyframes() -> None:
    rng = np.random.default_rng(0)
    hover = rng.normal(0.0, 0.05, (5000, 2))  # hours of a drone drifting on one spot
    hover[:2] = [[-0.5, 0.0], [0.5, 0.0]]
    assert spread_m(hover) == pytest.approx(1.0, abs=0.08)
    line = np.column_stack([np.linspace(0.0, 3.0, 7), np.linspace(0.0, 4.0, 7)])
    assert spread_m(line) == pytest.approx(5.0, abs=0.08)
    assert spread_m(line, enough=2.0) >= 2.0
    assert spread_m(np.zeros((1, 2))) == 0.0


def test_summary_names_the_unjoined_robots(tmp_path: Path) -> None:
    reason = "the map (r0) has 1 keyframe spread over 0.0 m"
    base = {"map_frame": {"unjoined": ["r1", "r2"], "unjoinable_reason": reason}}
    (tmp_path / "basestation.json").write_text(json.dumps(base))
    summary = build_summary(tmp_path, resolve_world("bshape"), ["r0", "r1", "r2"], 1.0)
    assert summary["unjoined_robots"] == ["r1", "r2"]
    assert summary["unjoinable_reason"] == reason


def test_robots_waiting_for_gnss_are_named(caplog: pytest.LogCaptureFixture) -> None:
    """GPS on, starts from GNSS: indoors no fix came, so no robot is on the map."""
    cfg = Config()
    cfg.basestation.gps.enabled = True
    slam = GlobalSlam(cfg, start_headings={"r1": 0.0, "r2": 0.0}, threaded=False)
    try:
        _fly(slam, "r1", 10)
        _fly(slam, "r2", 10)
        caplog.set_level(logging.WARNING)
        slam.converge()
        reason = slam.stats()["map_frame"]["unjoinable_reason"]
        assert reason == "no robot is on the map: r1, r2 had no GNSS fix yet"
    finally:
        slam.close()


def test_a_robot_waiting_for_gnss_is_named_beside_a_map_that_never_flew(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """GPS on: r0 had a fix and is the map (it hovers), r1 flew indoors with none yet. r1
    joins at its first fix (`GlobalSlam._late_start`): the reason says it has none, not
    only that the map's drone never flew."""
    cfg = Config()
    cfg.basestation.gps.enabled = True
    slam = GlobalSlam(cfg, start_headings={"r0": 0.0, "r1": 0.0}, threaded=False)
    try:
        slam.add_gps_fix("r0", 0.0, np.zeros(2), np.array([0.5, 0.5, 1.0]))
        _fly(slam, "r0", 1)
        _fly(slam, "r1", 10)
        caplog.set_level(logging.WARNING)
        slam.converge()
        reason = slam.stats()["map_frame"]["unjoinable_reason"]
        assert reason.startswith("the map (r0) has 1 keyframe spread over 0.0 m")
        assert reason.endswith("its drone has not flown; r1 had no GNSS fix yet")
        slam.add_gps_fix("r1", 9.0, np.array([4.5, 0.0]), np.array([0.5, 0.5, 1.0]))
        slam.optimize()
        assert slam.stats()["map_frame"]["unjoined"] == []  # its fix joined it
    finally:
        slam.close()
