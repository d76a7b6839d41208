"""The base station's global grid: incremental insertion and partial re-rendering."""

from __future__ import annotations

import numpy as np

from basestation.map_builder import MapBuilder
from common.config import MapConfig
from protocol.messages import Scan2D


def _scan(rng: np.random.Generator) -> Scan2D:
    n = 181
    r = rng.uniform(1.0, 4.0, n)
    r[rng.random(n) < 0.1] = np.nan  # some no-returns
    return Scan2D.from_ranges(-np.pi / 2, np.pi / (n - 1), 8.0, r)


def _from_scratch(cfg: MapConfig, keys, scans, poses) -> MapBuilder:
    fresh = MapBuilder(cfg)
    fresh.update(keys, scans, poses)
    assert fresh.grid is not None
    return fresh


def test_moved_keyframes_rerender_only_their_region_and_match_a_full_render() -> None:
    cfg = MapConfig()
    rng = np.random.default_rng(1)
    n = 40
    keys = [("a", i) for i in range(n)]
    scans = [_scan(rng) for _ in range(n)]
    poses = np.column_stack([np.arange(n) * 1.0, np.zeros(n), np.zeros(n)])
    mb = MapBuilder(cfg)
    assert mb.update(keys[:30], scans[:30], poses[:30]) is False
    assert mb.update(keys, scans, poses) is False  # only new keyframes: incremental
    # a loop closure moves the last five keyframes
    moved = poses.copy()
    moved[35:, 1] += 0.5
    assert mb.update(keys, scans, moved) is True
    assert mb.rerenders == 1
    total = mb.grid.shape[0] * mb.grid.shape[1]
    assert 0 < mb.rerendered_cells < 0.6 * total
    ref = _from_scratch(cfg, keys, scans, moved)
    # same lattice: compare where both grids exist (outside, both are unknown)
    res = cfg.resolution_m
    lo = np.maximum(mb.grid.origin_xy, ref.grid.origin_xy)
    hi = np.minimum(
        np.array(mb.grid.origin_xy) + res * np.array(mb.grid.shape[::-1]),
        np.array(ref.grid.origin_xy) + res * np.array(ref.grid.shape[::-1]),
    )
    ra, ca = mb.grid.region(lo + res / 2, hi - res / 2)
    rb, cb = ref.grid.region(lo + res / 2, hi - res / 2)
    assert ra.stop - ra.start > 300 and cb.stop - cb.start > 1000
    diff = np.abs(mb.grid.log_odds[ra, ca] - ref.grid.log_odds[rb, cb]) > 1e-5
    # identical but for rays running exactly along cell boundaries (float ties)
    assert diff.sum() <= 20, diff.sum()
    # nothing moved: nothing re-rendered
    assert mb.update(keys, scans, moved) is False and mb.rerenders == 1
