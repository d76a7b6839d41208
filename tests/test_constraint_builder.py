"""Candidate search (seed 002 eq. 2) and the verification worker's queueing."""

from __future__ import annotations

import time

import numpy as np

from basestation.constraint_builder import (
    GLOBAL_SEARCH_COST,
    ConstraintBuilder,
    Job,
    find_candidates,
)
from common.config import ConstraintConfig


def _line(x: np.ndarray, yaw: np.ndarray | float = 0.0, y: float = 0.0) -> np.ndarray:
    return np.column_stack([x, np.full_like(x, y), np.broadcast_to(yaw, x.shape)])


def test_driving_on_along_a_corridor_is_not_a_loop() -> None:
    cc = ConstraintConfig()
    P = _line(np.arange(100) * 0.2)
    assert find_candidates(cc, ("a", 99), {"a": P}, ["a"]) == []


def test_coming_back_is_a_loop_with_the_nearest_old_node() -> None:
    cc = ConstraintConfig()
    out_and_back = np.concatenate([np.arange(60) * 0.2, 12.0 - np.arange(1, 60) * 0.2])
    P = _line(out_and_back)
    assert find_candidates(cc, ("a", len(P) - 1), {"a": P}, ["a"]) == [("loop", ("a", 1))]
    # facing the other way (|dyaw| > r_theta): no candidate
    P[-1, 2] = np.pi
    assert find_candidates(cc, ("a", len(P) - 1), {"a": P}, ["a"]) == []


def test_nearest_node_of_each_other_robot_in_the_component() -> None:
    cc = ConstraintConfig()
    poses = {
        "a": _line(np.arange(10) * 0.5),
        "b": _line(np.arange(10) * 0.5, y=1.0),
        "c": _line(np.arange(10) * 0.5 + 100.0),  # too far
    }
    got = find_candidates(cc, ("a", 4), poses, ["a", "b", "c"])
    assert got == [("inter", ("b", 4))]
    assert find_candidates(cc, ("a", 4), poses, ["a"]) == []  # b not in a's component


def test_worker_verifies_in_priority_order_and_reports_failures() -> None:
    cc = ConstraintConfig(max_candidates_per_s=1000.0)
    builder = ConstraintBuilder(cc)
    try:
        rng = np.random.default_rng(0)
        # an L-shaped wall seen from the origin; the query sees it from 0.3 m further on
        wall = np.vstack(
            [
                _line(np.linspace(-3, 3, 200), y=2.0)[:, :2],
                np.column_stack([np.full(200, 3.0), np.linspace(-2, 2, 200)]),
            ]
        )
        query = wall - np.array([0.3, 0.0]) + rng.normal(0, 0.005, wall.shape)
        good = Job(
            "loop", ("a", 0), ("a", 50), np.array([0.25, 0.05, 0.0]), [wall], query, [np.zeros(3)]
        )
        junk = Job(
            "inter",
            ("b", 0),
            ("a", 50),
            np.zeros(3),
            [wall],
            rng.uniform(-20, 20, (300, 2)),
            [np.zeros(3)],
        )
        builder.submit(good)
        builder.submit(junk)
        deadline = time.monotonic() + 60
        while not builder.idle() and time.monotonic() < deadline:
            time.sleep(0.05)
        results = builder.results()
        assert [r.job.kind for r in results] == ["loop"]
        np.testing.assert_allclose(results[0].match.T_a_b, [0.3, 0.0, 0.0], atol=0.02)
        assert builder.stats["failed_inter"] == 1 and builder.stats["verified_loop"] == 1
    finally:
        builder.close()


def test_inter_robot_and_loop_queues_take_turns() -> None:
    builder = ConstraintBuilder(ConstraintConfig())
    builder.close()  # no worker: the queues are read here
    pts, origin = [np.zeros((1, 2))], [np.zeros(3)]
    for k in range(3):
        for kind in ("inter", "loop"):
            builder._queues[kind].append(
                Job(kind, ("a", k), ("b", k), np.zeros(3), pts, pts[0], origin)
            )
    order = [builder._next_job().kind for _ in range(6)]
    assert order == ["inter", "loop"] * 3 and builder._next_job() is None


def test_the_newest_candidates_are_verified_first() -> None:
    builder = ConstraintBuilder(ConstraintConfig(max_queue=5))
    builder.close()  # no worker: the queue is read here
    pts, origin = [np.zeros((1, 2))], [np.zeros(3)]
    for k in range(3):
        builder.submit(Job("loop", ("a", 100 + k), ("a", k), np.zeros(3), pts, pts[0], origin))
    assert [builder._next_job().a[1] for _ in range(3)] == [102, 101, 100]


def test_a_full_queue_has_no_room_and_counts_the_skip() -> None:
    builder = ConstraintBuilder(ConstraintConfig(max_queue=2))
    builder.close()
    pts, origin = [np.zeros((1, 2))], [np.zeros(3)]
    assert builder.has_room("inter")
    for k in range(2):
        builder.submit(Job("inter", ("a", k), ("b", k), np.zeros(3), pts, pts[0], origin))
    assert not builder.has_room("inter") and builder.has_room("loop")
    assert builder.stats["skipped_inter"] == 1


def test_global_searches_wait_per_target_map_take_turns_and_are_dropped_once_joined() -> None:
    builder = ConstraintBuilder(ConstraintConfig(global_pending_per_robot=2))
    builder.close()  # no worker: the queues are read here
    pts, origin = [np.zeros((1, 2))], [np.zeros(3)]

    def search(query: str, k: int, target: str) -> Job:
        return Job("global", (query, k), (query, k), np.zeros(3), pts, pts[0], origin,
                   target_nodes=[(target, 0)])  # fmt: skip

    for k in range(3):  # u searches the map (of a); a searches u's floating map
        builder.submit(search("u", k, "a"))
        builder.submit(search("a", k, "u"))
    builder.submit(search("v", 0, "a"))
    assert builder.stats["superseded_global"] == 2  # each pair keeps its newest 2
    assert builder.backlog() == 5 * GLOBAL_SEARCH_COST
    first = [builder._next_job().b for _ in range(3)]  # the maps in turn, oldest first
    assert first == [("u", 1), ("a", 1), ("v", 0)]
    builder.cancel_global([["a", "u"], ["v"]])  # u has joined a's map
    assert builder.stats["cancelled_global"] == 2
    assert builder._next_job() is None and builder.idle()


def test_without_the_worker_the_caller_verifies_within_its_budget() -> None:
    """Lock-step simulation: queued jobs are verified on the caller's thread, in the
    worker's order, up to a budget in candidates (a global search costs ten)."""
    builder = ConstraintBuilder(ConstraintConfig(), threaded=False)
    wall = _line(np.linspace(-3, 3, 200), y=2.0)[:, :2]
    for k in range(5):
        builder.submit(
            Job("loop", ("a", k), ("a", 50 + k), np.zeros(3), [wall], wall, [np.zeros(3)])
        )
    time.sleep(0.2)
    assert builder.backlog() == 5  # no thread took any
    assert builder.run_pending(2.0) == 2 and builder.backlog() == 3
    done = builder.results()
    assert [r.job.a for r in done] == [("a", 4), ("a", 3)]  # the newest first, as the worker
    assert builder.run_pending(100.0) == 3 and builder.idle()
    assert [r.job.a for r in builder.results()] == [("a", 2), ("a", 1), ("a", 0)]
    builder.start()  # from now on the worker verifies; the caller no longer does
    builder.submit(Job("loop", ("a", 9), ("a", 59), np.zeros(3), [wall], wall, [np.zeros(3)]))
    assert builder.run_pending(100.0) == 0
    deadline = time.monotonic() + 30
    while not builder.idle() and time.monotonic() < deadline:
        time.sleep(0.02)
    assert [r.job.a for r in builder.results()] == [("a", 9)]
    builder.close()


def test_each_query_point_knows_the_keyframe_it_was_seen_from() -> None:
    """The verifier's facing test needs where each query point was seen from (frame b)."""
    own, neighbour = np.array([[1.0, 0.0], [2.0, 0.0]]), np.array([[0.5, 0.5]])
    origins = [np.zeros(3), np.array([0.4, -0.2, np.pi / 2])]
    job = Job("loop", ("a", 0), ("a", 9), np.zeros(3), [own], [own, neighbour], [np.zeros(3)],
              in_node_frames=True, query_origins=origins)  # fmt: skip
    points, sensors = job.placed_query(), job.placed_query_sensors()
    assert sensors is not None and sensors.shape == points.shape == (3, 2)
    np.testing.assert_allclose(sensors, [[0, 0], [0, 0], [0.4, -0.2]])
    np.testing.assert_allclose(points[2], [0.4 - 0.5, -0.2 + 0.5])  # rotated by 90 deg
    flat = Job("loop", ("a", 0), ("a", 9), np.zeros(3), [own], own, [np.zeros(3)])
    assert flat.placed_query_sensors() is None  # all seen from b's origin
