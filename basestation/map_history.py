"""What the global map knew over sim time (for coverage-over-time metrics).

The base station adds one snapshot per lock-step clock sync; each keeps the free
and the occupied cells of the grid as two bit masks with its origin, so the file
stays small (tens of kB per snapshot for a 30 x 25 m floor at 5 cm). With
`max_snapshots` set, memory is bounded for long missions: when one more would
exceed it, every other snapshot is dropped and from then on only every other sync
is kept (the time resolution halves, the span stays the whole mission).
`read_map_history` gives back
`GridMap`s in which free cells are 0, occupied ones 100 and the rest unknown (-1)
(files written before the occupied mask was kept: free and unknown only).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from common.errors import CollabSlamError
from common.map_io import OCCUPIED, UNKNOWN, GridMap


@dataclass
class MapHistory:
    stamps: list[float] = field(default_factory=list)  # sim time, s
    _masks: list[np.ndarray] = field(default_factory=list)  # packed free, then occupied bits
    _shapes: list[tuple[int, int]] = field(default_factory=list)
    _origins: list[tuple[float, float]] = field(default_factory=list)
    resolution: float = 0.0
    max_snapshots: int = 0  # 0: keep every snapshot
    stride: int = 1  # keep every stride-th add()
    _adds: int = 0

    def __len__(self) -> int:
        return len(self.stamps)

    def add(self, stamp: float, grid: GridMap) -> None:
        if self.resolution and grid.resolution != self.resolution:
            raise CollabSlamError("MapHistory: the grid resolution changed")
        self._adds += 1
        if (self._adds - 1) % self.stride:
            return
        self.resolution = grid.resolution
        free = grid.free_mask()
        self.stamps.append(float(stamp))
        self._masks.append(
            np.packbits(np.concatenate([free.ravel(), grid.occupied_mask().ravel()]))
        )
        self._shapes.append(free.shape)
        self._origins.append((grid.origin[0], grid.origin[1]))
        if self.max_snapshots and len(self.stamps) > self.max_snapshots:
            # kept adds are multiples of stride; keep multiples of 2 * stride
            for series in (self.stamps, self._masks, self._shapes, self._origins):
                del series[1::2]
            self.stride *= 2

    def write(self, path: str | Path) -> None:
        lengths = np.array([len(m) for m in self._masks], dtype=np.int64)
        np.savez_compressed(
            path,
            stamps=np.array(self.stamps),
            shapes=np.array(self._shapes, dtype=np.int64).reshape(-1, 2),
            origins=np.array(self._origins).reshape(-1, 2),
            lengths=lengths,
            bits=np.concatenate(self._masks) if self._masks else np.zeros(0, np.uint8),
            resolution=np.array(self.resolution),
            planes=np.array(2),  # free and occupied
        )


def read_map_history(path: str | Path) -> list[tuple[float, GridMap]]:
    """(sim time, GridMap of its free and occupied cells) per snapshot, in time order."""
    try:
        z = np.load(path)
        stamps, shapes, origins = z["stamps"], z["shapes"], z["origins"]
        lengths, bits, res = z["lengths"], z["bits"], float(z["resolution"])
        planes = int(z["planes"]) if "planes" in z else 1
    except (OSError, KeyError, ValueError) as exc:
        raise CollabSlamError(f"{path}: not a map history file ({exc})") from None
    out = []
    ends = np.cumsum(lengths)
    for k, (t, (h, w), (ox, oy)) in enumerate(zip(stamps, shapes, origins, strict=True)):
        cells = np.unpackbits(bits[ends[k] - lengths[k] : ends[k]])
        data = np.full(h * w, UNKNOWN, dtype=np.int8)
        data[cells[: h * w].astype(bool)] = 0
        if planes == 2:
            data[cells[h * w : 2 * h * w].astype(bool)] = OCCUPIED
        data = data.reshape(h, w)
        out.append((float(t), GridMap(data, res, (float(ox), float(oy), 0.0))))
    return out
