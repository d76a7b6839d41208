"""A robot of unknown start joined to the map in the wrong one of identical rooms: its
whole-map searches go on after the join, and once it has left the room they put it
elsewhere, so the join is undone and made again where they say
(basestation/join_check.py). Real verifier, ray-cast scans of a floor of four identical
rooms off one corridor."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from test_global_slam_backfill import _keyframes
from test_loop_closure_manager import LC_COV, _max_error, _setup, _true_T

from basestation.global_slam import GlobalSlam
from basestation.persistence import KeyframeDatabase
from common.config import Config, ConstraintConfig
from common.geometry import se2_between
from protocol import Keyframe, OdomOrigin
from simulation.floor_plan import Plan, rasterize, validate_world
from simulation.world import World

PITCH = 6.1  # m: a room 6 m wide and its partition
ROOMS = 4


def _rooms() -> World:
    """A 2 m corridor along y = 0-2 m, four identical 6 x 6 m rooms above it, each with
    its door 1.5 m from its left wall: alike from inside, apart from the corridor."""
    p = Plan(ROOMS * PITCH - 0.1, 8.1)
    p.free_rects.append((0.0, 0.0, ROOMS * PITCH - 0.1, 2.0))
    for i in range(ROOMS):
        p.room(i * PITCH, 2.1, i * PITCH + 6.0, 8.1)
        p.door_y(2.0, i * PITCH + 1.5)
    grid = rasterize(p, 0.05)
    validate_world(grid)
    return World(grid)


def _path(waypoints: list[np.ndarray], step: float = 0.2) -> np.ndarray:
    """(N, 3) poses every `step` m along the waypoints, heading along the way."""
    out = []
    for a, b in zip(waypoints[:-1], waypoints[1:], strict=True):
        n = max(1, int(np.ceil(np.hypot(*(b - a)) / step)))
        yaw = np.arctan2(b[1] - a[1], b[0] - a[0])
        out += [[*(a + t * (b - a)), yaw] for t in np.arange(n) / n]
    return np.array([*out, [*waypoints[-1], out[-1][2]]])


def _room(i: int, laps: float = 1.0) -> list[np.ndarray]:
    """A circle of 1.8 m radius about room i's centre, from its bottom."""
    th = -np.pi / 2 + np.linspace(0.0, 2 * np.pi * laps, int(40 * laps) + 1)
    return [np.array([i * PITCH + 3.0, 5.1]) + 1.8 * np.array([np.cos(t), np.sin(t)]) for t in th]


def _door(i: int, y: float) -> np.ndarray:
    return np.array([i * PITCH + 1.5, y])


def _feed(slam: GlobalSlam, keyframes: list[Keyframe]) -> None:
    """Admit keyframes as one batch, then optimize, search and verify (on this thread)
    until nothing is left, as live."""
    for kf in keyframes:
        assert slam.admit(kf) == 1
    slam.optimize()
    slam.search_constraints()
    while slam.verify_pending(1000.0):
        slam.integrate_constraints()
        slam.optimize()
        slam.search_constraints()


def _scenario(room: int) -> tuple[World, np.ndarray, np.ndarray]:
    """The truths of a (known start: the corridor and each room) and b (start unknown:
    two laps in room `room`, then out along the corridor)."""
    way_a = [np.array([1.0, 1.0])]
    for i in range(ROOMS):
        way_a += [_door(i, 1.0), _door(i, 3.5), *_room(i), _door(i, 3.5), _door(i, 1.0)]
    end = np.array([ROOMS * PITCH - 1.0, 1.0])
    truth_b = _path([*_room(room, 2.0), _door(room, 3.5), _door(room, 1.0), end, end - [8, 0]])
    return _rooms(), _path([*way_a, end]), truth_b


@pytest.mark.parametrize("undone", [True, False])
def test_a_restart_keeps_the_undo_and_the_check_of_a_join(tmp_path: Path, undone: bool) -> None:
    """A base station restarted from its database just after b's join was undone
    replays the undo (b had come back 6.1 m off, in the wrong room, for good); one
    restarted between the wrong join and its undo goes on checking it (b had stayed
    there, unchecked)."""
    world, truth_a, truth_b = _scenario(2)
    slam = GlobalSlam(Config(), known_starts={"a": truth_a[0]}, threaded=False)
    kf_a, kf_b = _keyframes(world, "a", truth_a), _keyframes(world, "b", truth_b)
    db = KeyframeDatabase(tmp_path / "base.db")
    k = 0
    try:
        for j in range(0, len(kf_a), 50):
            _feed(slam, kf_a[j : j + 50])
            db.commit(slam.take_journal())
        while not slam.join_check.undone["b"] and (undone or k < 100):  # joined wrongly at
            _feed(slam, kf_b[k : k + 5])  # 45, undone at 220
            db.commit(slam.take_journal())
            k += 5
    finally:
        slam.close()
        db.close()
    assert slam.join_check.undone["b"] == undone
    db = KeyframeDatabase(tmp_path / "base.db")
    again = GlobalSlam(Config(), known_starts={"a": truth_a[0]}, threaded=False)
    try:
        again.restore(db.load())
        assert again.loops.accepted == slam.loops.accepted
        for j in range(k, len(kf_b), 5):
            _feed(again, kf_b[j : j + 5])
    finally:
        again.close()
        db.close()
    err = np.hypot(*(again.graph.poses("b")[:, :2] - truth_b[:, :2]).T)
    assert err.max() < 0.1, f"restarted, b is up to {err.max():.2f} m off"
    assert again.stats()["robots"]["b"]["joins_undone"] == 1


def test_a_run_restarted_in_flight_while_its_join_is_checked_is_placed_anew() -> None:
    """b is joined to the wrong room; 10 keyframes on, its agent restarts in flight (run
    b~2, in the odometry source's frame of b's run). b~2 floats and is joined, checked
    and undone in turn: before, it started where b's wrong join put it and stayed there,
    6.1 m off, unchecked."""
    world, truth_a, truth_b = _scenario(2)
    slam = GlobalSlam(Config(), known_starts={"a": truth_a[0]}, threaded=False)
    kf_a = _keyframes(world, "a", truth_a)
    kf_b = [
        dataclasses.replace(k, odom_origin=OdomOrigin(0.0, 0.0, 0.0))
        for k in _keyframes(world, "b", truth_b)
    ]
    try:
        for k in range(0, len(kf_a), 50):
            _feed(slam, kf_a[k : k + 50])
        k = 0
        while not slam.graph.is_anchored("b"):
            _feed(slam, kf_b[k : k + 5])
            k += 5
        _feed(slam, kf_b[k : k + 10])
        s, o = k + 10, OdomOrigin(*se2_between(truth_b[0], truth_b[k + 10]))
        kf_2 = [
            dataclasses.replace(kf, stamp=0.5 * (s + i), session=2, odom_origin=o)
            for i, kf in enumerate(_keyframes(world, "b~2", truth_b[s:]))
        ]
        for j in range(0, len(kf_2), 5):
            _feed(slam, kf_2[j : j + 5])
    finally:
        slam.close()
    assert slam.graph.is_anchored("b~2")
    err = np.hypot(*(slam.graph.poses("b~2")[:, :2] - truth_b[s:, :2]).T)
    assert err.max() < 0.1, f"b~2 is up to {err.max():.2f} m off"


@pytest.mark.parametrize("room", [2, 0])
def test_a_join_to_the_wrong_one_of_identical_rooms_is_undone_and_made_again(room: int) -> None:
    """Starting in the third room, b is joined to the fourth; in the first, rightly (its
    checks agree, or find it alike elsewhere: the join stays)."""
    world, truth_a, truth_b = _scenario(room)
    slam = GlobalSlam(Config(), known_starts={"a": truth_a[0]}, threaded=False)
    kf_a, kf_b = _keyframes(world, "a", truth_a), _keyframes(world, "b", truth_b)
    first_join = None
    try:
        for k in range(0, len(kf_a), 50):
            _feed(slam, kf_a[k : k + 50])
        for k in range(0, len(kf_b), 5):
            _feed(slam, kf_b[k : k + 5])
            if first_join is None and slam.graph.is_anchored("b"):
                first_join = slam.graph.poses("b")[-1, :2] - truth_b[k + 4, :2]
    finally:
        slam.close()

    assert first_join is not None  # while in its room: in the next one, or its own
    off = PITCH if room == 2 else 0.0
    assert abs(first_join[0] - off) < 0.2 and abs(first_join[1]) < 0.2, first_join
    assert slam.graph.is_anchored("b")
    err = np.hypot(*(slam.graph.poses("b")[:, :2] - truth_b[:, :2]).T)
    assert err.max() < 0.1, f"b is up to {err.max():.2f} m off"
    assert slam.stats()["robots"]["b"]["joins_undone"] == (room == 2)
    assert not slam.stats()["robots"]["b"]["join_contradicted"]


def test_unlink_puts_a_joined_robot_off_the_map_unless_a_match_of_it_is_final() -> None:
    """`LoopClosureManager.unlink`: the robot's inter-robot matches leave the graph and
    are forgotten, so it floats again and new matches join it afresh; with one of them
    out of PCM's window (final), nothing changes."""
    for window, undone in ((100, True), (3, False)):
        cfg = ConstraintConfig()
        cfg.pcm_window = window
        graph, manager, truth = _setup(np.random.default_rng(0), cfg)
        pairs = [(2, 2), (8, 8), (14, 14), (17, 17)]
        for i, j in pairs:
            manager.add(("a", i), ("b", j), _true_T(truth, ("a", i), ("b", j)), LC_COV, "inter")
        graph.update()
        assert graph.is_anchored("b")
        n = manager.unlink("b")
        assert (n == len(pairs)) if undone else n is None
        graph.update()
        assert graph.is_anchored("b") is not undone
        if undone:
            assert not manager.links and not manager.groups
            for i, j in pairs[:3]:
                T = _true_T(truth, ("a", i), ("b", j))
                manager.add(("a", i), ("b", j), T, LC_COV, "inter")
            graph.update()
            assert graph.is_anchored("b") and _max_error(graph, truth) < 0.3
