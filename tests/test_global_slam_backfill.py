"""Inter-robot search, with the real verifier on ray-cast scans of a shipped floor
plan: when two robots' maps are joined, the nodes one of them flew before the join
are searched against the other robot (GlobalSlam._backfill); robots with known starts
are searched against each other from the start."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from process_helpers import poll_until

from basestation.global_slam import GlobalSlam
from basestation.persistence import KeyframeDatabase
from common.config import Config
from common.geometry import pose4_to_pose7, se2_between
from protocol import Keyframe, Scan2D
from simulation.raycast import cast_rays
from simulation.world import World

BEAMS = 360
RANGE_MAX = 30.0


def _keyframes(world: World, robot: str, truth: np.ndarray) -> list[Keyframe]:
    """Keyframes of a robot flying the true poses ``truth`` (N, 3), in its own odom
    frame (its first pose is the odom origin), with exact odometry."""
    angles = np.linspace(-np.pi, np.pi, BEAMS, endpoint=False)
    out = []
    for i, T in enumerate(truth):
        ranges = cast_rays(
            world.occupied, world.resolution, world.origin_xy, T, angles, RANGE_MAX,
            world.ray_blocks,
        )  # fmt: skip
        odom = se2_between(truth[0], T)
        delta = se2_between(truth[i - 1], T) if i else np.zeros(3)
        out.append(
            Keyframe(
                robot,
                i,
                0.5 * i,
                pose4_to_pose7([odom[0], odom[1], 1.0, odom[2]]),
                pose4_to_pose7([delta[0], delta[1], 0.0, delta[2]]),
                np.diag([1e-4, 1e-4, 1e-4, 1e-4, 1e-4, 1e-5]),
                Scan2D.from_ranges(angles[0], angles[1] - angles[0], RANGE_MAX, ranges),
                None,
            )
        )
    return out


def _feed(slam: GlobalSlam, keyframes: list[Keyframe]) -> None:
    """Admit keyframes as one batch, then optimize, search and settle, as live."""
    for kf in keyframes:
        assert slam.admit(kf) == 1
    slam.optimize()
    slam.search_constraints()
    _settle(slam)


def _settle(slam: GlobalSlam) -> None:
    """Verify everything queued, hand the matches over, optimize, search again."""
    for _ in range(5):
        assert poll_until(slam.idle, timeout=60.0)
        slam.integrate_constraints()
        slam.optimize()
        slam.search_constraints()
    assert poll_until(slam.idle, timeout=60.0)


def _corridor(n: int = 37) -> tuple[World, np.ndarray, np.ndarray]:
    """floor30x25 and two robots' truths side by side along its corridor, 0.1 m apart."""
    xs = 1.5 + 0.5 * np.arange(n)
    truth_a = np.column_stack([xs, np.full(n, 6.0), np.zeros(n)])
    return World.load("floor30x25"), truth_a, truth_a + [0.0, 0.1, 0.02]


def _b_floating(cfg: Config) -> tuple[GlobalSlam, np.ndarray, np.ndarray]:
    """a from its known start and b floating along the corridor (b cannot join by global
    search; three stretches of 5 m join maps), both fed, searched and settled."""
    world, truth_a, truth_b = _corridor()
    cfg.basestation.constraints.global_min_score = 1.0
    cfg.basestation.constraints.merge_stretch_keyframes = 10  # 5 m: keyframes 0.5 m apart
    slam = GlobalSlam(cfg, known_starts={"a": truth_a[0]})
    for kf in _keyframes(world, "a", truth_a) + _keyframes(world, "b", truth_b):
        assert slam.admit(kf) == 1
    slam.optimize()
    slam.search_constraints()
    _settle(slam)
    return slam, truth_a, truth_b


def test_nodes_flown_before_a_join_are_matched_against_the_other_robot() -> None:
    n, cfg = 37, Config()  # 0.5 m apart along the corridor at y = 6 m
    slam, truth_a, truth_b = _b_floating(cfg)
    try:
        assert not slam.graph.is_anchored("b")

        # three verified matches on b's last 20 nodes (three stretches: see
        # merge_stretch_keyframes) join the maps, as a real late join does
        cov = np.diag([1e-3, 1e-3, 1e-4])
        for j in (n - 1, n - 11, n - 21):
            slam.loops.add(("a", j), ("b", j), se2_between(truth_a[j], truth_b[j]), cov, "inter")
        slam.optimize()
        assert slam.graph.is_anchored("b")
        submitted = slam.builder.stats["submitted_inter"]
        slam.search_constraints()
        assert slam.builder.stats["submitted_inter"] - submitted >= 5  # b's earlier nodes
        _settle(slam)
    finally:
        slam.close()

    group = slam.loops.groups[("a", "b")]
    early = [
        m for i, m in group.measurements.items() if i in slam.loops.accepted and m.index_b < n - 21
    ]
    # one tie per stretch of `inter_redundant_keyframes` (the rest is redundant): the
    # join's match at n - 21 covers b's nodes from n - 31 on, so one or two before that
    k = cfg.basestation.constraints.inter_redundant_keyframes
    tied = np.array(sorted(m.index_b for m in early))
    assert len(tied) >= 1 and tied.min() < n - 21 - k, f"b's earlier nodes tied at {tied}"
    gaps = np.diff([0, *tied, n - 21])
    assert gaps.max() <= 2 * k + 1, f"b's earlier nodes tied at {tied} only"
    for m in early:  # each agrees with the truth
        true = se2_between(truth_a[m.index_a], truth_b[m.index_b])
        assert np.hypot(*(m.T_a_b[:2] - true[:2])) < 0.1
    P = slam.graph.poses("b")
    assert np.abs(P[:, :2] - truth_b[:, :2]).max() < 0.1


def test_robots_with_known_starts_get_inter_robot_constraints() -> None:
    """Both starts known: the two chains are in `map` from their first node, though no
    constraint joins them yet, so a node is searched against the other robot too (it
    was searched against its own chain only, and such robots never got one)."""
    world = World.load("floor30x25")
    n = 37
    xs = 1.5 + 0.5 * np.arange(n)
    truth_a = np.column_stack([xs, np.full(n, 6.0), np.zeros(n)])
    truth_b = truth_a + [0.0, 0.1, 0.02]
    slam = GlobalSlam(Config(), known_starts={"a": truth_a[0], "b": truth_b[0]})
    try:
        for kf in _keyframes(world, "a", truth_a) + _keyframes(world, "b", truth_b):
            assert slam.admit(kf) == 1
        assert len(slam.graph.components()) == 2
        slam.optimize()
        slam.search_constraints()
        assert slam.builder.stats["submitted_inter"] >= 5
        _settle(slam)
    finally:
        slam.close()
    assert slam.loops.counts()["inter_robot_constraints"] >= 2
    assert len(slam.graph.components()) == 1  # one map now, by verified matches
    P = slam.graph.poses("b")
    assert np.abs(P[:, :2] - truth_b[:, :2]).max() < 0.1


def _side_by_side(redundant_keyframes: int) -> tuple[list[tuple[int, int]], dict, float]:
    """Two robots with known starts fly a corridor side by side, a few keyframes at a
    time: the accepted ties (a, b), the builder's counts, b's largest position error."""
    (world, truth_a, truth_b), n = _corridor(), 37
    cfg = Config()
    cfg.basestation.constraints.inter_redundant_keyframes = redundant_keyframes
    slam = GlobalSlam(cfg, known_starts={"a": truth_a[0], "b": truth_b[0]})
    try:
        kfs = {r: _keyframes(world, r, t) for r, t in (("a", truth_a), ("b", truth_b))}
        for first in range(0, n, 4):
            _feed(slam, kfs["a"][first : first + 4] + kfs["b"][first : first + 4])
    finally:
        slam.close()
    ties = sorted(map(tuple, slam.loops.links[("a", "b")].view()[:, 1:].tolist()))
    error = float(np.abs(slam.graph.poses("b")[:, :2] - truth_b[:, :2]).max())
    return ties, dict(slam.builder.stats), error


def test_stretches_two_robots_are_tied_at_get_no_more_inter_robot_matches() -> None:
    """Once a match ties two stretches of two robots' chains, the candidates between
    those stretches (within `inter_redundant_keyframes` at both ends) are not verified,
    or not used if they were queued before the tie: iSAM2 gets about one tie per
    stretch, not one per `candidate_stride`, and the estimate stays as good."""
    ties, stats, error = _side_by_side(Config().basestation.constraints.inter_redundant_keyframes)
    all_ties, all_stats, all_error = _side_by_side(0)
    assert all_stats.get("redundant_inter", 0) == 0 and len(all_ties) >= 12, all_ties
    assert stats["redundant_inter"] >= 10, stats
    assert stats["submitted_inter"] < all_stats["submitted_inter"], (stats, all_stats)
    assert 2 <= len(ties) <= len(all_ties) / 2, (ties, all_ties)
    assert error < 0.1 and all_error < 0.1


def _early_ties(slam: GlobalSlam, n: int) -> int:
    group = slam.loops.groups[("a", "b")]
    return sum(
        1 for i, m in group.measurements.items() if i in slam.loops.accepted and m.index_b < n - 21
    )


def test_a_joins_backfill_is_queued_again_after_a_restart(tmp_path: Path) -> None:
    """A base station killed after two maps were joined (and stored) but before the
    join's backfill jobs were verified: restored, it had taken the maps as joined for
    good, never queued them again, and b's chain before the join hung on its odometry."""
    n, cfg = 37, Config()
    db = KeyframeDatabase(tmp_path / "base.db")
    slam, truth_a, truth_b = _b_floating(cfg)
    starts = {"a": truth_a[0]}
    try:
        db.commit(slam.take_journal())
        cov = np.diag([1e-3, 1e-3, 1e-4])
        for j in (n - 1, n - 11, n - 21):  # the join, as the node stores it
            slam.loops.add(("a", j), ("b", j), se2_between(truth_a[j], truth_b[j]), cov, "inter")
        slam.optimize()
        db.commit(slam.take_journal())  # node._persist: on disk before acks
        before = slam.builder.stats["submitted_inter"]
        slam.search_constraints()
        live_backfill = slam.builder.stats["submitted_inter"] - before
        _settle(slam)
        live_early = _early_ties(slam, n)
    finally:
        slam.close()
    # ---- SIGKILL here: the backfill jobs were queued, not verified; restart on the db
    db.close()
    db2 = KeyframeDatabase(tmp_path / "base.db")
    slam2 = GlobalSlam(cfg, known_starts=dict(starts))
    try:
        slam2.restore(db2.load())
        assert slam2.graph.is_anchored("b")
        before = slam2.builder.stats.get("submitted_inter", 0)
        slam2.search_constraints()
        restored_backfill = slam2.builder.stats.get("submitted_inter", 0) - before
        _settle(slam2)
        restored_early = _early_ties(slam2, n)
    finally:
        slam2.close()
    assert live_backfill >= 5 and live_early >= 1
    assert restored_backfill >= 5, "the join's backfill is never queued after the restart"
    assert restored_early >= 1, "b's pre-join nodes stay untied after the restart"
    # ... and stored once done (verified, its matches in): not queued at the next restart
    # (a done backfill had been queued again at every restart)
    slam2.integrate_constraints()
    batch = slam2.take_journal()
    assert batch.backfilled == [("a", "b")]
    db2.commit(batch)
    db2.close()
    slam3 = GlobalSlam(cfg, known_starts=dict(starts))
    try:
        slam3.restore(KeyframeDatabase(tmp_path / "base.db").load())
        assert slam3.backfilled == {("a", "b")}
        slam3.search_constraints()
        assert slam3.builder.stats.get("submitted_inter", 0) == 0
    finally:
        slam3.close()
