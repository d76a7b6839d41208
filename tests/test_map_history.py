"""MapHistory: snapshots of the free and occupied cells over sim time, bounded for long
missions."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from basestation.map_history import MapHistory, read_map_history
from common.map_io import GridMap


def _grid(k: int) -> GridMap:
    """A 6 x 10 grid whose first k cells (row-major) are free, the last one occupied
    (uncertain, 70, from k = 5 on), the rest unknown."""
    data = np.full(60, -1, dtype=np.int8)
    data[:k] = 0
    if k >= 5:
        data[-1] = 70
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
    assert back[17][1].occupied_mask().sum() == 1 and back[17][1].data[-1, -1] == 100
    assert not back[4][1].occupied_mask().any()
    assert np.array_equal(back[17][1].known_mask(), _grid(17).known_mask())


def test_a_file_of_free_cells_only_still_reads(tmp_path: Path) -> None:
    """Files written before the occupied cells were kept: free and unknown."""
    bits = np.packbits(np.r_[np.ones(3, bool), np.zeros(57, bool)])
    np.savez_compressed(
        tmp_path / "old.npz",
        stamps=np.array([2.0]),
        shapes=np.array([[6, 10]]),
        origins=np.array([[1.0, 2.0]]),
        lengths=np.array([len(bits)]),
        bits=bits,
        resolution=np.array(0.05),
    )
    ((t, g),) = read_map_history(tmp_path / "old.npz")
    assert t == 2.0 and int((g.data == 0).sum()) == 3 and int((g.data == -1).sum()) == 57


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
