"""Keyframe keys by the block: one robot id and an index array per robot.

The map is refreshed with every keyframe on it (every few seconds, 100,000 of them
after a long mission). A list of ``(robot_id, index)`` tuples costs a Python object
and a dict lookup per keyframe each time; `NodeKeys` holds one int64 array per
robot, so finding the map's rows of all keyframes is one numpy gather per robot.
It is still a sequence of ``(robot_id, index)`` tuples for code that wants them.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from typing import overload

import numpy as np

from basestation.scan_archive import NodeKey


class NodeKeys(Sequence[NodeKey]):
    def __init__(self, blocks: Iterable[tuple[str, np.ndarray]]) -> None:
        """`blocks`: (robot_id, indices) in order; the sequence is their concatenation."""
        self.blocks = [(rid, np.asarray(idx, dtype=np.int64).ravel()) for rid, idx in blocks]
        self._ends = np.cumsum([len(idx) for _, idx in self.blocks], dtype=np.int64)

    @classmethod
    def of(cls, keys: Sequence[NodeKey]) -> NodeKeys:
        """`keys` as blocks (runs of one robot; a NodeKeys is returned as it is)."""
        if isinstance(keys, NodeKeys):
            return keys
        blocks: list[tuple[str, list[int]]] = []
        for rid, i in keys:
            if not blocks or blocks[-1][0] != rid:
                blocks.append((rid, []))
            blocks[-1][1].append(i)
        return cls((rid, np.array(idx, dtype=np.int64)) for rid, idx in blocks)

    def spans(self) -> Iterator[tuple[str, np.ndarray, slice]]:
        """(robot_id, indices, positions in the sequence) of each block."""
        start = 0
        for (rid, idx), end in zip(self.blocks, self._ends.tolist(), strict=True):
            yield rid, idx, slice(start, end)
            start = end

    def __len__(self) -> int:
        return int(self._ends[-1]) if len(self._ends) else 0

    @overload
    def __getitem__(self, j: int) -> NodeKey: ...
    @overload
    def __getitem__(self, j: slice) -> list[NodeKey]: ...
    def __getitem__(self, j: int | slice) -> NodeKey | list[NodeKey]:
        if isinstance(j, slice):
            return [self[k] for k in range(*j.indices(len(self)))]
        if j < 0:
            j += len(self)
        if not 0 <= j < len(self):
            raise IndexError(j)
        b = int(np.searchsorted(self._ends, j, side="right"))
        rid, idx = self.blocks[b]
        return rid, int(idx[j - (int(self._ends[b - 1]) if b else 0)])
