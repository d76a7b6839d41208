"""The base station's global grid: incremental insertion and partial re-rendering."""

from __future__ import annotations

import json
import tracemalloc
from pathlib import Path

import numpy as np
from test_basestation_memory import _tour  # 1081-beam scans along a line

from basestation.map_builder import BATCH, VIEW_KEEP, MapBuilder
from basestation.node import BaseStationNode
from common.bus import Bus
from common.config import Config, MapConfig
from protocol.messages import Scan2D


def _scan(rng: np.random.Generator) -> Scan2D:
    n = 181
    r = rng.uniform(1.0, 4.0, n)
    r[rng.random(n) < 0.1] = np.nan  # some no-returns
    return Scan2D.from_ranges(-np.pi / 2, np.pi / (n - 1), 8.0, r)


def _full_render(mb: MapBuilder, scans, poses) -> np.ndarray:
    """Log-odds of every keyframe drawn at `poses` (in insertion order) into one empty
    grid on mb's lattice: what a complete re-render must give."""
    assert mb.grid is not None
    h, w = mb.grid.shape
    ref = mb.grid.empty_like_region(slice(0, h), slice(0, w))
    for scan, pose in zip(scans, poses, strict=True):
        r = scan.ranges()
        r[np.isnan(r)] = scan.range_max
        ref.insert_scan(pose, r, scan.angles(), 0.0, scan.range_max, max_free_range=10.0)
    return np.asarray(ref.log_odds)


def _line(rng: np.random.Generator, n: int) -> np.ndarray:
    """Keyframes along x, 1 m apart, off the cell lattice (no float ties)."""
    return np.column_stack(
        [np.arange(n) + rng.uniform(0, 0.05, n), rng.uniform(-0.02, 0.02, n),
         rng.uniform(-0.01, 0.01, n)]
    )  # fmt: skip


def test_moved_keyframes_rerender_only_their_region_and_match_a_full_render() -> None:
    cfg = MapConfig()
    rng = np.random.default_rng(1)
    n = 40
    keys = [("a", i) for i in range(n)]
    scans = [_scan(rng) for _ in range(n)]
    poses = _line(rng, n)
    mb = MapBuilder(cfg)
    assert mb.update(keys[:30], scans[:30], poses[:30]) is False
    assert mb.update(keys, scans, poses) is False  # only new keyframes: incremental
    # a loop closure moves the last five keyframes
    moved = poses.copy()
    moved[35:, 1] += 0.5
    assert mb.update(keys, scans, moved, budget_s=None) is True
    tiles = mb.rerenders
    assert tiles >= 1 and mb.pending == 0
    total = mb.grid.shape[0] * mb.grid.shape[1]
    assert 0 < mb.rerendered_cells < 0.6 * total
    ref = _full_render(mb, scans, moved)
    assert ref.shape == mb.grid.shape
    diff = np.abs(mb.grid.log_odds - ref) > 1e-5
    # identical but for a few cells of near-diagonal rays: a ray clipped at a tile's
    # edge may walk by rows where the whole ray walks by columns
    assert diff.sum() <= 30, diff.sum()
    # the move changed the map (the comparison above could fail)
    assert (np.abs(_full_render(mb, scans, poses) - ref) > 1e-5).sum() > 1000
    # nothing moved: nothing re-rendered
    assert mb.update(keys, scans, moved) is False and mb.rerenders == tiles


def test_a_builder_reading_scans_back_by_key_draws_what_one_holding_them_draws() -> None:
    cfg = MapConfig()
    rng = np.random.default_rng(5)
    n = 40
    keys = [("b", i // 2) if i % 2 else ("a", i // 2) for i in range(n)]  # two robots
    by_key = {k: _scan(rng) for k in keys}
    scans = [by_key[k] for k in keys]
    poses = _line(rng, n)
    asked: list[tuple[str, int]] = []

    def source(wanted: list[tuple[str, int]]) -> list[Scan2D]:
        asked.extend(wanted)
        return [by_key[k] for k in wanted]

    held, read = MapBuilder(cfg), MapBuilder(cfg, scan_source=source)
    moved = poses.copy()
    moved[25:, 1] += 0.4  # a correction: tiles are redrawn from scans read back
    for mb in (held, read):
        mb.update(keys, scans, poses)
        assert mb.update(keys, scans, moved, budget_s=None) is True
    assert asked and set(asked) <= set(keys) and {"a", "b"} <= {k[0] for k in asked}
    np.testing.assert_array_equal(read.grid.log_odds, held.grid.log_odds)


def test_budgeted_rerender_finishes_to_the_same_grid_as_an_unbudgeted_one() -> None:
    cfg = MapConfig()
    rng = np.random.default_rng(2)
    n = 60
    keys = [("a", i) for i in range(n)]
    scans = [_scan(rng) for _ in range(n)]
    steps = [(30, _line(rng, n))]
    p = steps[0][1].copy()
    p[20:30, 1] += 0.3  # a correction
    steps.append((45, p.copy()))  # ... and new keyframes arrive while tiles are redrawn
    p[:10, 2] += 0.02  # a rotation of the start
    steps.append((60, p.copy()))
    full, slow = MapBuilder(cfg), MapBuilder(cfg)
    spread = 0
    for k, poses in steps:
        assert full.update(keys[:k], scans[:k], poses[:k], budget_s=None) == (k > 30)
        slow.update(keys[:k], scans[:k], poses[:k], budget_s=0.0)  # one batch per call
        assert full.pending == 0
        spread = max(spread, slow.pending)
    assert spread >= 2  # redraws were left for later calls
    draws = slow.rerender_draws
    slow.update(keys, scans, steps[-1][1], budget_s=0.0)  # nothing moved: work goes on
    assert draws < slow.rerender_draws <= draws + BATCH
    slow.finish()
    assert type(slow.rerendered_cells) is int and type(slow.rerender_draws) is int
    assert slow.pending == 0 and slow.rerenders >= 1  # tiles dirtied twice drawn once
    np.testing.assert_array_equal(slow.grid.log_odds, full.grid.log_odds)
    np.testing.assert_array_equal(slow.grid.observed, full.grid.observed)
    diff = np.abs(slow.grid.log_odds - _full_render(slow, scans, steps[-1][1])) > 1e-5
    assert diff.sum() <= 30, diff.sum()


def test_most_moved_tile_is_redrawn_first() -> None:
    cfg = MapConfig()
    rng = np.random.default_rng(3)
    n = 40
    keys = [("a", i) for i in range(n)]
    scans = [_scan(rng) for _ in range(n)]
    poses = _line(rng, n)
    mb = MapBuilder(cfg)
    mb.update(keys, scans, poses)
    moved = poses.copy()
    moved[:3, 1] += 0.05  # the start moves a little, the end a lot
    moved[-3:, 1] += 0.4
    mb.update(keys, scans, moved, budget_s=0.0)
    assert mb.pending >= 2
    far_end = (moved[-1, 0] - mb._anchor[0]) // cfg.rerender_tile_m
    assert mb._job is not None and mb._job.tile[0] >= far_end - 1


def test_map_memory_per_keyframe_is_small() -> None:
    """Bookkeeping per keyframe (the scans belong to the caller): < 200 bytes."""
    cfg = MapConfig()
    rng = np.random.default_rng(4)
    scans = [_scan(rng) for _ in range(50)]
    n = 3000
    keys = [("a", i) for i in range(n)]
    poses = np.column_stack([rng.uniform(0, 2, n), rng.uniform(0, 2, n), rng.uniform(-3, 3, n)])
    every = [scans[i % 50] for i in range(n)]
    mb = MapBuilder(cfg)
    mb.update(keys[:100], every[:100], poses[:100])  # the grid covers them all already
    tracemalloc.start()
    before = tracemalloc.get_traced_memory()[0]
    for k in range(200, n + 1, 100):
        mb.update(keys[:k], every[:k], poses[:k])
    grown = tracemalloc.get_traced_memory()[0] - before
    tracemalloc.stop()
    per_kf = grown / (n - 100)
    assert 0 < per_kf < 200, per_kf


def test_written_map_finishes_pending_tiles_at_the_final_poses(
    tmp_path: Path, cfg: Config, endpoint: str
) -> None:
    cfg.zenoh.listen = [endpoint]
    cfg.exploration.enabled = False
    cfg.map.rerender_budget_s = 0.0
    kfs = _tour("r0", 160)
    with Bus(cfg.zenoh, cfg.fleet) as bus:
        node = BaseStationNode(cfg, bus, None)
        node.process(kfs)
        node.refresh_map()
        keys, scans, poses = node.slam.map_keyframes()
        shifted = poses + np.array([0.0, 0.3, 0.0])  # a stale correction: tiles pending
        node.map.update(keys, scans, shifted, budget_s=0.0)
        assert node.map.pending > 1
        node.write_outputs(tmp_path)
        assert node.map.pending == 0 and (tmp_path / "map.pgm").is_file()
        assert json.loads((tmp_path / "basestation.json").read_text())["map_rerender_pending"] == 0
        # every tile was redrawn from the newest VIEW_KEEP keyframes of each view (the
        # tour goes back and forth over 4 m 8 times: 160 keyframes, ~16 x 2 views)
        assert node.map.rerender_skipped > 0
        newest = node.map._newest_per_view(np.arange(len(keys)))
        assert len(newest) < 0.7 * len(keys)
        ref = _full_render(node.map, [scans[k] for k in newest], poses[newest])
        diff = np.abs(node.map.grid.log_odds - ref) > 1e-5
        assert diff.sum() <= 30, diff.sum()
        node.drain(1.0)


def test_redraw_keeps_the_newest_keyframes_of_each_view() -> None:
    mb = MapBuilder(MapConfig())
    # 10 keyframes at one view, 2 at another, 1 at a third (interleaved in time)
    poses = np.array([[0.1, 0.1, 0.0]] * 10 + [[2.1, 0.1, 0.0]] * 2 + [[0.1, 0.1, np.pi]])
    order = np.array([0, 10, 1, 2, 3, 11, 4, 5, 6, 12, 7, 8, 9])
    mb._pose = poses[order]
    kept = mb._newest_per_view(np.arange(len(order)))
    assert list(order[kept]) == [10, 11, 12, 7, 8, 9]  # the last VIEW_KEEP (3) of view 1
    assert VIEW_KEEP == 3


def test_map_from_scans_read_back_from_the_database_is_the_same(
    tmp_path: Path, cfg: Config, endpoint: str
) -> None:
    """A base station with a database keeps only a few scans in memory (scan_cache) and
    reads old ones back for tile redraws; its map equals one without a database, after
    a correction too, and the map written after drain() (database closed) as well."""
    cfg.zenoh.listen = [endpoint]
    cfg.exploration.enabled = False
    cfg.basestation.constraints.enabled = False
    kfs = _tour("r0", 200)
    with Bus(cfg.zenoh, cfg.fleet) as bus:
        plain = BaseStationNode(cfg, bus, None)
        cfg.basestation.db_path = str(tmp_path / "base.db")
        cfg.basestation.scan_cache = 20
        stored = BaseStationNode(cfg, bus, None)
        for node in (plain, stored):
            for k in range(0, len(kfs), 25):
                node.process(kfs[k : k + 25])
                node.refresh_map()
            keys, scans, poses = node.slam.map_keyframes()
            bent = poses + np.column_stack([np.zeros(len(poses)), 0.002 * np.arange(len(poses)),
                                            np.zeros(len(poses))])  # fmt: skip
            node.map.update(keys, scans, bent, budget_s=None)  # every tile redrawn
        archive = stored.slam.store.scan_archive
        assert archive.in_memory == 20 and archive.reads > 100
        assert plain.slam.store.scan_archive.in_memory == 200
        assert stored.map.rerenders == plain.map.rerenders > 0
        np.testing.assert_array_equal(stored.map.grid.log_odds, plain.map.grid.log_odds)
        stored.drain(1.0)
        stored.write_outputs(tmp_path / "out")  # redraws read scans after the db closed
        plain.drain(1.0)
        plain.write_outputs(tmp_path / "plain")
    assert (tmp_path / "out" / "map.pgm").read_bytes() == (
        tmp_path / "plain" / "map.pgm"
    ).read_bytes()


def _after_looks(cfg: MapConfig, k: int) -> tuple[int, int]:
    """(published, exploration) value of a cell 1.5 m ahead of k keyframes that all saw
    3 m past it."""
    n = 181
    scan = Scan2D.from_ranges(-np.pi / 2, np.pi / (n - 1), 8.0, np.full(n, 3.0))
    mb = MapBuilder(cfg)
    keys = [("a", i) for i in range(k)]
    mb.update(keys, [scan] * k, np.tile([0.01, 0.01, 0.0], (k, 1)), budget_s=None)
    probe = np.array([[1.5, 0.0]])
    return int(mb.gridmap().sample(probe)[0]), int(mb.gridmap(free_thresh=0.49).sample(probe)[0])


def test_a_scan_that_saw_nothing_clears_nothing() -> None:
    """A laser dropout's keyframes (all beams "no return": the agent goes on with its
    odometry and still cuts them) had cleared every wall 10 m around as free space."""
    n = 181
    wall = Scan2D.from_ranges(-np.pi / 2, np.pi / (n - 1), 8.0, np.full(n, 3.0))
    blind = Scan2D.from_ranges(-np.pi / 2, np.pi / (n - 1), 8.0, np.full(n, np.nan))
    few = Scan2D.from_ranges(
        -np.pi / 2, np.pi / (n - 1), 8.0, np.r_[np.full(10, 3.0), np.full(n - 10, np.nan)]
    )
    mb = MapBuilder(MapConfig())
    pose = np.array([[0.01, 0.01, 0.0]])
    mb.update([("a", 0)], [wall], pose, budget_s=None)
    before = mb.gridmap().occupied_mask().sum()
    keys = [("a", i) for i in range(1, 11)]
    mb.update([("a", 0), *keys], [wall] + [blind] * 5 + [few] * 5, np.tile(pose, (11, 1)),
              budget_s=None)  # fmt: skip
    assert before > 50 and mb.gridmap().occupied_mask().sum() == before


def test_published_map_calls_a_cell_free_after_two_looks_exploration_after_one() -> None:
    """`map.free_thresh` 0.35: two keyframes that saw through a cell make it free in the
    published map; exploration reads it free after one (docs/architecture.md, "Two views
    of one map"). map_server's 0.196 would take four."""
    assert _after_looks(MapConfig(), 1) == (-1, 0)  # free to exploration, unknown published
    assert _after_looks(MapConfig(), 2) == (0, 0)
    assert _after_looks(MapConfig(free_thresh=0.196), 3) == (-1, 0)
    assert _after_looks(MapConfig(free_thresh=0.196), 4) == (0, 0)


def test_keyframes_beyond_max_radius_are_not_drawn_and_the_map_stays_bounded() -> None:
    """One far GNSS fix pulled a robot 465 km away and the grid tried to allocate 133 TiB,
    and a second robot started 1e8 m off allocated 3.2 TiB: the map stops
    `max_radius_m` from the first keyframe."""
    cfg = MapConfig(max_radius_m=50.0)
    rng = np.random.default_rng(3)
    n = 20
    keys = [("a", i) for i in range(n)] + [("b", 0), ("b", 1)]
    scans = [_scan(rng) for _ in keys]
    poses = np.vstack([_line(rng, n), [[1e8, 0.0, 0.0], [1e8 + 1.0, 0.0, 0.0]]])
    mb = MapBuilder(cfg)
    mb.update(keys, scans, poses, budget_s=None)
    assert mb.beyond_radius == 2 and mb.grid is not None
    assert mb.grid.shape[1] * cfg.resolution_m < 2 * cfg.max_radius_m + 5.0
    moved = poses.copy()
    moved[10:n, 0] += 465e3  # half of robot a's keyframes pulled 465 km east
    mb.update(keys, scans, moved, budget_s=None)
    h, w = mb.grid.shape
    assert w * cfg.resolution_m < 2 * cfg.max_radius_m + 5.0 and mb.pending == 0
    ref = _full_render(mb, scans[:10], moved[:10])  # what is left in reach is drawn
    assert (np.abs(mb.grid.log_odds - ref) > 1e-5).sum() <= 30


def test_readings_below_the_lasers_range_min_are_neither_walls_nor_free_space() -> None:
    """A drone whose laser sees its own frame (0.15 m, under the driver's range_min of
    0.3 m): those readings had gone into keyframes as returns, and the map had occupied
    cells along the flight line. They are no readings now: not drawn, nor taken as no
    return (which clears free space 10 m along the beam, through the walls behind)."""
    n = 181
    r = np.full(n, 3.0)
    r[:20] = 0.15  # -90..-71 degrees: a frame arm
    scan = Scan2D.from_ranges(-np.pi / 2, np.pi / (n - 1), 8.0, r, range_min=0.3)
    assert np.all(np.isnan(scan.ranges()[:20])) and np.allclose(scan.ranges()[20:], 3.0)
    no_return = Scan2D.from_ranges(-np.pi / 2, np.pi / (n - 1), 8.0, np.where(r < 0.3, np.nan, r))
    probe = np.array([[0.0, -1.5], [0.0, -0.15]])  # 1.5 m along the arm, and the arm
    values = []
    for s in (scan, no_return):
        mb = MapBuilder(MapConfig())
        mb.update([("a", i) for i in range(5)], [s] * 5, np.tile([0.01, 0.01, 0.0], (5, 1)),
                  budget_s=None)  # fmt: skip
        values.append(mb.gridmap().sample(probe).tolist())
    assert values[0] == [-1, -1]  # unknown
    assert values[1][0] == 0  # (no return: free)
