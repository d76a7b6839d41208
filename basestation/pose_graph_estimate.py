"""The pose graph's whole estimate as arrays: every committed node's pose (aliases of the
reduced pose graph resolved), cached until the next update, and which robots moved.

Package-internal: a mixin of ``basestation.pose_graph.PoseGraph``; conventions as there.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import gtsam
import numpy as np

from basestation.pose_graph_reduction import CHAR_SHIFT
from basestation.pose_graph_state import FloatArray, PoseGraphState
from common.errors import CollabSlamError
from common.geometry import se2_compose, wrap_angle
from common.growable import grown, on_disk


class EstimateMixin(PoseGraphState):
    """All committed poses, chain after chain in index order (rows of ``_estimate``)."""

    if TYPE_CHECKING:  # provided by PoseGraph
        _isam: gtsam.ISAM2
        _estimate: FloatArray
        _estimate_buffers: list[FloatArray]
        _estimate_valid: bool
        _change_epsilon: float

        @property
        def reducing(self) -> bool: ...

    def _offset(self, robot_id: str) -> int:
        offset = 0
        for rid, chain in self._chains.items():
            if rid == robot_id:
                return offset
            offset += chain.num_committed
        raise CollabSlamError(f"unknown robot {robot_id!r}")

    def arrays_nbytes(self) -> int:
        """Bytes of the per-node arrays: the estimate, aliases and stamps (capacity)."""
        chains = list(self._chains.values())
        per_chain = sum(
            c.alias_key.nbytes + c.alias_offset.nbytes
            + (0 if c.stamps is None else c.stamps.nbytes)
            for c in chains
        )  # fmt: skip
        return self._estimate.nbytes + per_chain

    def _full_estimate(self) -> FloatArray:
        """All committed poses (one O(n) calculateEstimate, cached until the next update)."""
        if not self._estimate_valid:
            self._estimate = self._extract(self._isam.calculateEstimate())
            self._estimate_valid = True
        return self._estimate

    def _estimate_rows(self, n: int) -> FloatArray:
        """Room for the next estimate's n rows. Kept on disk like the other per-node
        arrays (the base station: common.growable), in two buffers taken in turn (the
        last estimate stays valid while the next is made); else a new array."""
        bufs = self._estimate_buffers
        if not on_disk(bufs[0]):
            return np.empty((n, 3))
        bufs.reverse()
        bufs[0] = grown(bufs[0], n)
        return bufs[0][:n]

    def _extract(self, values: gtsam.Values) -> FloatArray:
        """Every committed node's pose, chain after chain in index order."""
        # Keys sort by (character, index): rows come chain after chain in index order
        rows = np.asarray(gtsam.utilities.extractPose2(values), dtype=np.float64).reshape(-1, 3)
        expected = sum(c.num_committed for c in self._chains.values())
        out = self._estimate_rows(expected)
        if not self.reducing:
            if rows.shape[0] != expected:
                raise CollabSlamError(f"estimate has {rows.shape[0]} poses, expected {expected}")
            chains, start, at = list(self._chains.values()), 0, {}
            for c in sorted(chains, key=lambda c: c.char):  # rows by key character: 'A' < 'a'
                at[c.char], start = start, start + c.num_committed
            done = 0
            for c in chains:  # (a 27th chain's rows had been taken for the first chain's)
                out[done : done + c.num_committed] = rows[at[c.char] :][: c.num_committed]
                done += c.num_committed
            return out
        done = 0
        keys = np.fromiter(values.keys(), dtype=np.int64, count=values.size())
        for chain in self._chains.values():
            n = chain.num_committed
            chain.grow_aliases(n)
            aliases = chain.alias_key[:n]
            own = (ord(chain.char) << CHAR_SHIFT) + np.arange(n, dtype=np.int64)
            src = np.where(aliases >= 0, aliases, own)
            at = np.minimum(np.searchsorted(keys, src), max(len(keys) - 1, 0))
            if n and (len(keys) == 0 or np.any(keys[at] != src)):
                raise CollabSlamError(f"estimate misses nodes of chain {chain.char!r}")
            poses = rows[at] if n else np.zeros((0, 3))
            mask = aliases >= 0
            poses[mask] = se2_compose(poses[mask], chain.alias_offset[:n][mask])
            out[done : done + n] = poses
            done += n
        return out

    def _changed_robots(
        self, old: FloatArray, new: FloatArray, old_counts: list[int]
    ) -> frozenset[str]:
        changed, old_off, new_off = set(), 0, 0
        for (robot_id, chain), n_old in zip(self._chains.items(), old_counts, strict=True):
            if n_old:
                diff = new[new_off : new_off + n_old] - old[old_off : old_off + n_old]
                diff[:, 2] = wrap_angle(diff[:, 2])
                if np.abs(diff).max() > self._change_epsilon:
                    changed.add(robot_id)
            old_off += n_old
            new_off += chain.num_committed
        return frozenset(changed)
