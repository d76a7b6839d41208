"""MapHistory: snapshots of the free cells over sim time, bounded for long missions."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from basestation.map_history import MapHistory, read_map_history
from common.map_io import GridMap


def _grid(k: int) -> GridMap:
    """A 6 x 10 grid whose first k cells (row-major) are free, the rest unknown."""
    data = np.full(60, -1, dtype=np.int8)
    data[:k] = 0
    return GridMap(data.reshape(6, 10), 0.05, (1.0, 2.0, 0.0))


def test_unbounded_keeps_every_snapshot(tmp_path: Path) -> None:
    h = MapHistory()
    for k in range(30):
        h.add(float(k), _grid(k))
    assert len(h) == 30 and h.stride == 1
    h.write(tmp_path / "h.npz")
    back = read_map_history(tmp_path / "h.npz")
    assert [t for t, _ in back] == [float(k) for k in range(30)]
    assert int((back[17][1].data == 0).sum()) == 17


def test_bounded_history_thins_to_an_even_stride(tmp_path: Path) -> None:
    """One snapshot per sync at 1 s: past max_snapshots every other one goes and the
    stride doubles, so the kept stamps stay evenly spaced over the whole mission."""
    h = MapHistory(max_snapshots=8)
    for k in range(100):
        h.add(float(k), _grid(k % 60))
        assert len(h) <= 8
    assert h.stride == 16
    assert h.stamps == [float(16 * i) for i in range(len(h))] and h.stamps[-1] == 96.0
    h.write(tmp_path / "h.npz")
    back = read_map_history(tmp_path / "h.npz")
    assert [t for t, _ in back] == h.stamps
    assert [int((g.data == 0).sum()) for _, g in back] == [int(t) % 60 for t in h.stamps]
