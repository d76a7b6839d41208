"""Per-robot keyframe sequences: in-order admission, duplicates and gaps.

Agents deliver at least once and may resend, so the store admits each robot's
keyframes strictly in `seq` order: a seq already admitted is a harmless
duplicate (counted, re-acknowledged, never added twice); a seq beyond a gap is
held (up to `reorder_window` per robot) until the gap fills.

Seqs count within the agent's keyframe chain (`Keyframe.chain`). An agent whose
state says keyframes were acknowledged while none of its robot's is admitted here
(they went with another base station's database: a new laptop, a database lost) is
told so, an ack of -1 (`none_of`); it then starts a new chain, what it kept renumbered
from seq 0, and the store follows it. Keyframes of an older chain are dropped (sent
before the switch); a newer chain once keyframes are admitted is refused with an
error (a second base station told the agent it had none).
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from agent.voxel_filter import voxel_mask
from basestation.scan_archive import NodeKey, ScanArchive
from common.geometry import pose7_to_pose4
from common.growable import Rows
from protocol.messages import Keyframe, KeyframeAck, Scan2D

log = logging.getLogger(__name__)

GAP_WARN = 200  # keyframes held behind one missing seq: an error line (and at 10x)


@dataclass
class RobotKeyframes:
    """One robot's admitted keyframes. Per keyframe only what the base station uses
    later is kept (~75 bytes): stamp, odometry pose and running variances in growable
    arrays, and whether it has a scan. The scans (the protocol's uint16 millimetres:
    the map and the scan points for matching are made from them) are in the store's
    `ScanArchive`, the whole keyframe in the database (basestation/persistence.py)."""

    robot_id: str
    stamps: Rows = field(default_factory=lambda: Rows(1))
    poses_odom: Rows = field(default_factory=lambda: Rows(4))  # T_odom_base [x, y, z, yaw]
    has_scan: bytearray = field(default_factory=bytearray)  # 1: the keyframe has a scan
    var_cumsum: Rows = field(default_factory=lambda: Rows(2))  # running [var_xy, var_yaw]
    held: dict[int, Keyframe] = field(default_factory=dict)
    duplicates: int = 0
    id_conflicts: int = 0  # refused as another source's (see `foreign`)
    foreign: bool = False  # another agent sends as this robot: nothing more is admitted
    chain: int = 0  # the agent's keyframe chain admitted (Keyframe.chain)
    stale_chain: int = 0  # keyframes of an older chain, dropped
    chain_conflicts: int = 0  # a newer chain not renumbered from the first admitted
    unchecked_chain: int = 0  # keyframes of a newer chain beyond those admitted: dropped
    session: int = 0  # the agent run its keyframes are from (basestation/robot_segments.py)
    odom_origin: np.ndarray | None = None  # at its first keyframe: on the odometry's [x y yaw]
    odom_origin_latest: np.ndarray | None = None  # at its latest keyframe with one

    def chain_covariance(self, i: ArrayLike, j: ArrayLike) -> np.ndarray:
        """Approximate (n, 3, 3) covariances of nodes j relative to nodes i (index arrays)
        along the chain: summed per-keyframe variances, plus the heading uncertainty
        swept over the (odometry) distance between them. Zero where i == j."""
        i, j = np.atleast_1d(i), np.atleast_1d(j)
        lo, hi = np.minimum(i, j), np.maximum(i, j)
        cum = self.var_cumsum.view()
        v = cum[hi] - cum[lo]
        P = self.poses_odom.view()
        d2 = np.sum((P[hi, :2] - P[lo, :2]) ** 2, axis=1)
        same = lo == hi
        var_xy = np.where(same, 0.0, v[:, 0] + 0.5 * v[:, 1] * d2 + 1e-6)
        var_yaw = np.where(same, 0.0, v[:, 1] + 1e-8)
        out = np.zeros((len(i), 3, 3))
        out[:, 0, 0] = out[:, 1, 1] = var_xy
        out[:, 2, 2] = var_yaw
        return out

    @property
    def next_seq(self) -> int:
        return len(self.stamps)


def scan_points(scan: Scan2D | None, voxel_m: float = 0.05) -> np.ndarray:
    """A scan's returns as (N, 2) float32 points in its body frame (m), one per voxel
    (`agent.voxel_filter`: at random, not the first in beam order)."""
    if scan is None:
        return np.zeros((0, 2), dtype=np.float32)
    r = scan.ranges()
    a = scan.angles()
    ok = np.isfinite(r)
    pts = np.column_stack([r[ok] * np.cos(a[ok]), r[ok] * np.sin(a[ok])]).astype(np.float64)
    if len(pts) == 0:
        return pts
    return pts[voxel_mask(pts, voxel_m)].astype(np.float32)


class KeyframeStore:
    def __init__(
        self, reorder_window: int = 1000, points_cache: int = 3000,
        scans: ScanArchive | None = None,
    ) -> None:  # fmt: skip
        """`points_cache`: keyframes whose scan points are kept (least recently used
        dropped first); the others are made again from their scans when asked for.
        `scans`: where the scans are kept (None: an archive holding all in memory)."""
        self.reorder_window = reorder_window
        self.points_cache = points_cache
        self.scan_archive = ScanArchive() if scans is None else scans
        self.robots: dict[str, RobotKeyframes] = {}
        self._points: OrderedDict[tuple[str, int], np.ndarray] = OrderedDict()
        self.points_made = 0  # scan_points() calls (cache misses)
        self._clouds_from: set[str] = set()  # robots warned of for sending 3-D clouds

    def points(self, robot_id: str, i: int) -> np.ndarray:
        """Keyframe i's scan points, (N, 2) float32 in its body frame (m); read only."""
        key = (robot_id, i)
        pts = self._points.get(key)
        if pts is not None:
            self._points.move_to_end(key)
            return pts
        pts = scan_points(self.scan(robot_id, i))
        pts.flags.writeable = False  # shared with verification jobs
        self.points_made += 1
        self._points[key] = pts
        while len(self._points) > self.points_cache:
            self._points.popitem(last=False)
        return pts

    def scan(self, robot_id: str, i: int) -> Scan2D | None:
        """Keyframe i's scan (None: it has none)."""
        return self.scans([(robot_id, i)])[0]

    def scans(self, keys: list[NodeKey]) -> list[Scan2D | None]:
        """The scans of admitted keyframes `keys` (memory or database)."""
        return self.scan_archive.get(keys)

    def saved(self, keys: list[NodeKey]) -> None:
        """These keyframes are committed to the database (their scans may leave memory)."""
        self.scan_archive.saved(keys)

    def total_keyframes(self) -> int:
        """Keyframes admitted, all robots."""
        return sum(len(r.stamps) for r in list(self.robots.values()))

    def arrays_nbytes(self) -> int:
        """Bytes of the per-keyframe arrays (all robots, capacity)."""
        return sum(
            r.stamps.nbytes + r.poses_odom.nbytes + r.var_cumsum.nbytes + len(r.has_scan)
            for r in list(self.robots.values())
        )

    def robot(self, robot_id: str) -> RobotKeyframes:
        if robot_id not in self.robots:
            self.robots[robot_id] = RobotKeyframes(robot_id)
        return self.robots[robot_id]

    def admit(self, kf: Keyframe, replay: bool = False) -> list[Keyframe]:
        """Offer one keyframe (`replay`: from the database, where only admitted ones are);
        returns the keyframes now admitted, in order (maybe none)."""
        r = self.robot(kf.robot_id)
        if r.foreign:
            r.id_conflicts += 1
            return []
        if not self._in_chain(r, kf, replay):
            return []
        if kf.seq < r.next_seq or kf.seq in r.held:
            r.duplicates += 1
            kept = r.held[kf.seq].stamp if kf.seq in r.held else float(r.stamps[kf.seq, 0])
            if kf.stamp != kept:  # a resent keyframe is the same bytes: another source
                self._foreign(r, f"keyframe seq {kf.seq} came again stamped {kf.stamp:.3f} "
                                 f"(kept: {kept:.3f})")  # fmt: skip
            return []
        if kf.seq > r.next_seq:
            if kf.seq > r.next_seq + self.reorder_window:  # no agent is that far ahead
                log.error("robot %s: keyframe seq %d is beyond the reorder window (waiting "
                          "for seq %d): dropped", kf.robot_id, kf.seq, r.next_seq)  # fmt: skip
                return []
            if len(r.held) >= self.reorder_window:
                log.error(
                    "robot %s: reorder window full (%d held, waiting for seq %d); "
                    "dropped seq %d (it will be resent)",
                    kf.robot_id,
                    len(r.held),
                    r.next_seq,
                    kf.seq,
                )
                return []
            r.held[kf.seq] = kf
            if len(r.held) in (GAP_WARN, 10 * GAP_WARN):  # not a reordering: a lost start
                log.error("robot %s: still waiting for keyframe seq %d of chain %d with %d "
                          "later ones held (lost with another base station's database, and "
                          "its agent did not start a new chain on the ack -1: an old one?)",
                          kf.robot_id, r.next_seq, r.chain, len(r.held))  # fmt: skip
            return []
        ready = [kf]
        while r.next_seq + len(ready) in r.held:
            ready.append(r.held.pop(r.next_seq + len(ready)))
        for k in ready:
            if len(r.stamps) and k.stamp < r.stamps[-1, 0]:
                log.warning(
                    "robot %s: keyframe %d stamp %.3f is before the previous one (kept in the "
                    "graph, left out of the written trajectory)",
                    k.robot_id,
                    k.seq,
                    k.stamp,
                )
            o = None if k.odom_origin is None else np.array([k.odom_origin.x, k.odom_origin.y,
                                                             k.odom_origin.yaw])  # fmt: skip
            if not len(r.stamps):
                r.session, r.odom_origin = k.session, o
            r.odom_origin_latest = o if o is not None else r.odom_origin_latest
            r.stamps.append([k.stamp])
            r.poses_odom.append(pose7_to_pose4(k.pose_odom))
            c = k.delta_cov
            prev = r.var_cumsum[-1] if len(r.var_cumsum) else np.zeros(2)
            r.var_cumsum.append(
                prev
                + (np.zeros(2) if k.seq == 0 else np.array([0.5 * (c[0, 0] + c[1, 1]), c[5, 5]]))
            )
            r.has_scan.append(k.scan2d is not None)
            if k.cloud3d is not None and k.robot_id not in self._clouds_from:
                self._clouds_from.add(k.robot_id)
                log.warning("robot %s sends 3-D clouds: the base station maps 2-D "
                            "scans only; its keyframes join the pose graph, its clouds "
                            "are neither matched nor drawn", k.robot_id)  # fmt: skip
            self.scan_archive.add((k.robot_id, k.seq), k.scan2d)
        return ready

    @staticmethod
    def _in_chain(r: RobotKeyframes, kf: Keyframe, replay: bool) -> bool:
        """Whether `kf` is of the robot's chain. A newer chain is taken up while nothing
        of the robot's is admitted (what is held of the old one is dropped), or once one
        of its keyframes is one admitted here (the same stamp at the same seq: the agent
        sent everything again renumbered from its first, for another base station, and
        this one, on its older database, follows on). Keyframes of a newer chain that
        cannot be checked yet are dropped: the agent's state brings an ack -1 of its
        chain (`none_of`), and it sends everything from its first keyframe again."""
        if kf.chain == r.chain:
            return True
        if kf.chain < r.chain:  # sent before its agent started the new chain
            r.stale_chain += 1
            return False
        if r.next_seq == 0 or replay:  # (the database holds only admitted ones)
            if not replay:
                log.warning("robot %s: its agent starts keyframe chain %d (it had keyframes "
                            "acknowledged by a base station without this one's database: "
                            "what it kept comes renumbered from seq 0); %d held keyframes "
                            "of chain %d dropped", kf.robot_id, kf.chain, len(r.held),
                            r.chain)  # fmt: skip
            r.chain, r.held = kf.chain, {}
            return True
        if kf.seq >= r.next_seq:
            r.unchecked_chain += 1
            return False
        if kf.stamp == r.stamps[kf.seq, 0]:
            log.warning("robot %s: its agent sends keyframe chain %d (renumbered for another "
                        "base station from its first keyframe, as admitted here): followed "
                        "on from chain %d at seq %d", kf.robot_id, kf.chain, r.chain,
                        r.next_seq)  # fmt: skip
            r.chain, r.held = kf.chain, {}
            return True
        r.chain_conflicts += 1
        KeyframeStore._foreign(r, f"keyframe {kf.seq} of chain {kf.chain} is not keyframe "
                               f"{kf.seq} of chain {r.chain} admitted here (its agent kept "
                               f"too few keyframes to send them all again, or another agent "
                               f"sends as it)")  # fmt: skip
        return False

    @staticmethod
    def _foreign(r: RobotKeyframes, what: str) -> None:
        """Another source sends as this robot in its session (an agent that does not
        tell its session restarted, or one whose state folder was copied; an agent gone
        over to another base station): no more of its keyframes are admitted,
        acknowledged or answered with corrections. Mixing them had joined two odometry
        frames in one trajectory. (A run of the agent in another session is another
        segment of the robot: basestation/robot_segments.py.)"""
        r.id_conflicts += 1
        r.foreign, r.held = True, {}
        log.error("robot %s: %s: another agent sends as %s (restarted, or two with this "
                  "id); no more of its keyframes are mapped, acknowledged or corrected (two "
                  "agents' frames cannot be joined): restart the mission, or give the new "
                  "one another robot id", r.robot_id, what, r.robot_id)  # fmt: skip

    def acked_seq(self, robot_id: str) -> int:
        """Highest seq such that every keyframe up to it is admitted (-1 if none)."""
        return self.robot(robot_id).next_seq - 1

    def ack(self, robot_id: str) -> KeyframeAck | None:
        """The acknowledgement for `robot_id`: up to where all of its chain's keyframes
        are admitted (None: none is)."""
        r = self.robot(robot_id)
        ok = r.next_seq and not r.foreign
        return KeyframeAck(robot_id, r.next_seq - 1, r.chain) if ok else None

    def none_of(self, robot_id: str, chain: int, acked: int) -> KeyframeAck | None:
        """Ack -1 of `chain` for an agent that says `acked` (> 0) keyframes of it were
        acknowledged, if this store lacks some of them: none of the robot's is admitted
        (they are in another base station's database), only an older chain's are (this
        one is on an older database: the agent's next chain, everything again from its
        first keyframe, lets it follow on), or fewer than `acked` of this chain (another
        base station acknowledged the rest; this one acknowledges only what it has). None:
        a state from before a chain this store has taken up too, or a robot refused as
        another source's. Safe from any thread (it only reads)."""
        r = self.robots.get(robot_id)
        if r is not None and (
            r.foreign or chain < r.chain or chain == r.chain and r.next_seq >= acked
        ):
            return None
        return KeyframeAck(robot_id, -1, chain)

    def acknowledges(self, robot_id: str, chain: int) -> bool:
        """Whether this store acknowledges `robot_id`'s keyframes of `chain` (some are
        admitted, and no other source's)."""
        r = self.robots.get(robot_id)
        return r is not None and not r.foreign and r.chain == chain and r.next_seq > 0


class KeyframeScans(Sequence[Scan2D]):
    """The scans of `keys`, read from the keyframe store when indexed (not held here)."""

    def __init__(self, store: KeyframeStore, keys: Sequence[NodeKey]) -> None:
        self._store = store
        self._keys = keys

    def __len__(self) -> int:
        return len(self._keys)

    def __getitem__(self, i):  # noqa: ANN001, ANN204 (int or slice)
        if isinstance(i, slice):
            return self._store.scans(self._keys[i])
        scan = self._store.scan(*self._keys[i])
        assert scan is not None  # map_keyframes lists keyframes with a scan only
        return scan
