"""Frontier rule (seed 002 Fig. 4), grouping (Fig. 5) and incremental updates."""

from __future__ import annotations

import numpy as np
import pytest

from basestation.frontiers import FrontierDetector, frontier_mask
from common.map_io import GridMap

FREE, UNKNOWN, OCC = 0, -1, 100


def _grid(data: np.ndarray, res: float = 0.1) -> GridMap:
    return GridMap(np.asarray(data, dtype=np.int8), res, (0.0, 0.0, 0.0))


def _half_known(h: int = 21, w: int = 21) -> np.ndarray:
    """Left half free (walled on its other three sides), right half unknown: the edge
    between them is a frontier."""
    d = np.full((h, w), UNKNOWN, dtype=np.int8)
    d[:, : w // 2 + 1] = FREE
    d[0, : w // 2 + 1] = d[-1, : w // 2 + 1] = d[:, 0] = OCC
    return d


def test_fig4a_half_free_half_unknown_is_a_frontier() -> None:
    d = _half_known()
    m = frontier_mask(d, 3, 0.2)
    assert m[10, 10]  # on the edge
    assert not m[10, 3]  # deep in free space: nothing unknown around
    assert not m[10, 15]  # unknown cells are never frontiers


def test_fig4b_an_occupied_cell_in_the_circle_invalidates_it() -> None:
    d = _half_known()
    d[11, 9] = OCC
    m = frontier_mask(d, 3, 0.2)
    assert not m[10, 10]
    assert m[16, 10]  # the same edge far from the obstacle still is


def test_fig4c_too_few_unknown_cells_is_not_a_frontier() -> None:
    d = np.full((21, 21), FREE, dtype=np.int8)
    d[10, 11] = UNKNOWN  # a single unknown cell next to the point
    assert not frontier_mask(d, 3, 0.2)[10, 10]


def test_one_edge_becomes_one_goal_on_the_edge() -> None:
    det = FrontierDetector(radius_m=0.3, min_group_cells=3)
    frontiers = det.update(_grid(_half_known(41, 41)))
    assert len(frontiers) == 1
    f = frontiers[0]
    assert f.size >= 20
    ix, iy = ((f.goal - 0.05) / 0.1).round().astype(int)
    assert _half_known(41, 41)[iy, ix] == FREE and abs(ix - 20) <= 1 and abs(iy - 20) <= 3


def test_a_closed_room_has_no_frontier() -> None:
    d = np.full((30, 30), OCC, dtype=np.int8)
    d[1:-1, 1:-1] = FREE
    assert FrontierDetector().update(_grid(d)) == []


@pytest.mark.parametrize("boxes", [True, False])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_incremental_update_equals_a_full_recompute(seed: int, boxes: bool) -> None:
    """With the boxes the map changed in, or without (the detector compares grids)."""
    rng = np.random.default_rng(seed)
    d = np.full((120, 160), UNKNOWN, dtype=np.int8)
    d[20:100, 20:90] = FREE
    d[rng.integers(0, 120, 40), rng.integers(0, 160, 40)] = OCC
    det = FrontierDetector(radius_m=0.4, min_group_cells=1)
    det.update(_grid(d))
    before = det.cells_examined
    same = det.update(_grid(d.copy()), [] if boxes else None)
    assert det.cells_examined == before  # nothing changed: nothing examined
    assert [f.size for f in same] == [f.size for f in det.groups()]
    # the robot sees more: a box of cells becomes free, walls appear in it
    d2 = d.copy()
    d2[40:70, 90:120] = FREE
    d2[55, 95:118] = OCC
    touched = [((9.0, 4.0), (12.0, 7.0))]  # metres: columns 90-120, rows 40-70
    inc = det.update(_grid(d2), touched if boxes else None)
    assert 0 < det.cells_examined - before < d2.size / 2  # only around the change
    full = FrontierDetector(radius_m=0.4, min_group_cells=1).update(_grid(d2))
    assert [(f.size, tuple(f.goal)) for f in inc] == [(f.size, tuple(f.goal)) for f in full]
