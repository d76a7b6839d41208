"""The base station's global SLAM: keyframes -> pose graph, constraints, estimates.

Owns the per-robot keyframe store, the iSAM2 pose graph, the constraint builder
(candidate search + verification worker) and the loop-closure manager (PCM + robust
factors). The node around it only moves messages.

Anchoring: a robot with a known start pose is tied to the map there. Without any known
start, ``basestation.map_frame_robot`` (or else the first robot to send a keyframe)
defines the map frame (its odom frame at its first keyframe). Every other robot's chain
(and a robot's later segments, basestation/robot_segments.py) floats in its own frame
until verified inter-robot constraints join it to the map; until then it gets no
correction and is left out of the map. basestation/map_frame.py warns if they cannot
be joined (the map's drone never flew).

GPS (``basestation.gps.enabled``): ``map`` is the ENU frame the fixes are converted to
(in simulation also the world frame). A robot with a known start uses its fixes as GPS
factors (``PoseGraph.add_gps_fix``). One with only a known *heading* (the autopilot's at
takeoff, ``start_headings``) starts on the virtual ENU-origin trajectory of seed 000
§III-C: its first node gets a loose prior at its latest fix with that heading, and the
fixes anchor it. Other robots ignore their fixes and float as without GPS.
"""

from __future__ import annotations

import functools
import logging
import time
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from basestation.constraint_builder import (
    ConstraintBuilder,
    Job,
    Verified,
    find_candidates,
    hypothesis_poses,
)
from basestation.false_matches import FalseMatches
from basestation.gps_fixes import gnss_start, node_stamp
from basestation.join_check import JoinCheck, apart, newly_joined
from basestation.keyframe_store import KeyframeScans, KeyframeStore
from basestation.loop_closure_manager import LoopClosureManager
from basestation.map_frame import MapFrame
from basestation.node_keys import NodeKeys
from basestation.persistence import Batch, Fix, Recovered, Start
from basestation.pose_graph import PoseGraph
from basestation.robot_segments import SEGMENT_START_SIGMAS, robot_of, segment_start
from basestation.scan_archive import ScanArchive, ScanReader
from basestation.slam_restore import restore
from basestation.slam_stats import slam_stats
from basestation.update_series import UpdateSeries
from basestation.whole_map_search import WholeMapSearch, tie
from common.config import Config
from common.errors import CollabSlamError
from common.geometry import pose7_to_pose4, quat_to_yaw, se2_between, se2_compose, se2_inverse
from common.metrics import TIMINGS_KEPT
from common.trajectory_io import Trajectory
from protocol import Keyframe
from protocol.messages import IN_FLIGHT_M, Scan2D

log = logging.getLogger(__name__)

NodeKey = tuple[str, int]
Query = Callable[[], tuple[list[np.ndarray], list[np.ndarray], int]]  # a node's, cached


class GlobalSlam:
    def __init__(
        self,
        cfg: Config,
        known_starts: dict[str, np.ndarray] | None = None,
        start_headings: dict[str, float] | None = None,  # rad in ENU, GPS only
        scan_reader: ScanReader | None = None,  # old scans from the database; None: in RAM
        threaded: bool = True,  # verify candidates on a worker thread (else verify_pending)
    ) -> None:
        self.cfg = cfg
        b = cfg.basestation
        self.gps_enabled = b.gps.enabled
        self.gps_fixes_ignored = 0  # fixes of robots not (yet) anchored by a known start
        self.graph = PoseGraph.from_config(b)
        scans = ScanArchive(scan_reader, b.scan_cache)
        self.store = KeyframeStore(b.reorder_window, b.scan_points_cache, scans)
        self.known_starts = dict(known_starts or {})
        # robots started at a given map pose (not the first robot defining map): GPS-able
        self._georeferenced = set(self.known_starts)
        self.start_headings = dict(start_headings or {}) if b.gps.enabled else {}
        self._last_fix: dict[str, np.ndarray] = {}  # robot -> latest fix [east, north]
        self._floating_starts: dict[str, np.ndarray] = {}  # heading robot -> odom of node 0
        self._early_fixes: dict[str, list[tuple[float, np.ndarray, np.ndarray]]] = {}
        self._node_stamps: dict[str, float] = {}  # robot -> stamp of its latest node
        self.odom_now: Callable[[str], np.ndarray | None] = lambda r: None  # latest local pose
        self.cc = b.constraints
        self.builder = ConstraintBuilder(self.cc, threaded=threaded) if self.cc.enabled else None
        self.loops = LoopClosureManager(self.graph, self.cc, self._chain_covariance)
        self.updates = 0  # iSAM2 updates; the latest TIMINGS_KEPT of their latencies:
        self.update_ms: deque[float] = deque(maxlen=TIMINGS_KEPT)
        self.update_series = UpdateSeries(b.update_series_period_s)  # latencies over time
        self._new_nodes: list[NodeKey] = []
        self._constraints_added = False  # verified matches handed over since the last update
        self.false_matches = FalseMatches(self.cc, self.graph, self.loops)  # evaluation only
        self.whole_map = WholeMapSearch(self.cc, self.store.points)
        self.join_check = JoinCheck(
            self.cc, self.graph, self.loops, self._georeferenced, self.builder
        )
        self._last_candidate: dict[tuple[str, str], int] = {}  # (robot, target robot) -> index
        self._together: dict[str, frozenset[str]] = {}  # robot -> its map's robots, last search
        self.backfill_open: set[tuple[str, str]] = set()  # joins whose backfill runs (sorted)
        self.backfilled: set[tuple[str, str]] = set()  # ... and whose backfill is done
        self._unsaved: list[Keyframe] = []  # admitted since the last take_journal()
        self._unsaved_fixes: list[Fix] = []  # GNSS fixes given since then
        self._unsaved_starts: dict[str, Start] = {}  # chains started since then
        self._stored_starts: dict[str, Start] = {}  # restore: as they started then
        self.map_frame = MapFrame(self)  # who defines map; warns if robots cannot join it

    # --- keyframes ----------------------------------------------------------------------
    def admit(self, kf: Keyframe, replay: bool = False) -> int:
        """Offer a keyframe (`replay`: the database's); returns how many entered the graph."""
        for k in (ready := self.store.admit(kf, replay)):
            self._add_node(k)
        self._unsaved.extend(ready)
        return len(ready)

    def add_gps_fix(
        self, robot_id: str, stamp: float, enu_xy: np.ndarray, sigmas_enu: np.ndarray
    ) -> None:
        """A fix in ``map`` = ENU; used once the robot's chain exists from a known start
        or heading."""
        self._last_fix[robot_id] = xy = np.asarray(enu_xy, dtype=np.float64)[:2]
        self._unsaved_fixes.append((robot_id, float(stamp), xy, np.asarray(sigmas_enu, float)))
        expected = robot_id in self.known_starts or robot_id in self.start_headings
        if robot_id not in self.graph.robots() and expected:  # wait for its first keyframe
            early = self._early_fixes.setdefault(robot_id, [])
            early.append((stamp, enu_xy, sigmas_enu))
            del early[: -self.cfg.basestation.gps.max_pending_fixes]
            return
        if robot_id not in self._georeferenced and not (
            self._late_start(robot_id, xy) or self._joined_georeferenced(robot_id)
        ):
            self.gps_fixes_ignored += 1
            return
        self.graph.add_gps_fix(robot_id, stamp, enu_xy, sigmas_enu)

    def take_journal(self) -> Batch:
        """What changed since the last call (admitted keyframes, new matches, matches
        entering or leaving the graph, GNSS fixes given), for the database."""
        constraints, changes = self.loops.take_journal()
        batch = Batch(self._unsaved, constraints, changes, fixes=self._unsaved_fixes,
                      chain_starts=self._unsaved_starts)  # fmt: skip
        self._unsaved, self._unsaved_fixes, self._unsaved_starts = [], [], {}
        if self.backfill_open and (self.builder is None or self.builder.drained()):
            batch.backfilled = sorted(self.backfill_open)  # (verified, results in this batch)
            self.backfilled |= self.backfill_open
            self.backfill_open = set()
        return batch

    def saved(self, batch: Batch) -> None:
        """`batch` (from take_journal) is committed: its scans may leave memory."""
        self.store.saved([(k.robot_id, k.seq) for k in batch.keyframes])

    def restore(self, rec: Recovered) -> None:
        """Rebuild the graph from the database (`slam_restore.restore`)."""
        restore(self, rec)

    def _add_node(self, kf: Keyframe) -> None:
        rid = kf.robot_id
        stamp = node_stamp(self._node_stamps, kf) if self.gps_enabled else None
        if kf.seq == 0:  # a known start is T_map_odom: a chain can start on the way
            odom, start = pose7_to_pose4(kf.pose_odom)[[0, 1, 3]], self.known_starts.get(rid)
            start_sigmas = None
            o = kf.odom_origin  # a run that began in flight: its odom frame is not the start's
            if start is not None and o is not None and np.hypot(o.x, o.y) > IN_FLIGHT_M:
                log.warning("robot %s: its first keyframe here began in flight, %.1f m along "
                            "its odometry: started there (loosely), not at its start pose",
                            rid, np.hypot(o.x, o.y))  # fmt: skip
                start, start_sigmas = se2_compose(start, [o.x, o.y, o.yaw]), SEGMENT_START_SIGMAS
            start = None if start is None else se2_compose(start, odom)
            T_map_odom = self.join_check.settled(self.T_map_odom)  # (not a join checked)
            T = segment_start(rid, self.graph.robots(), T_map_odom, self.store.robot)
            if start is None and T is not None:  # a later run (GNSS fixes as its first's)
                start, start_sigmas = se2_compose(T, odom), SEGMENT_START_SIGMAS
                if robot_of(rid) in self._georeferenced:
                    self._georeferenced.add(rid)
            elif start is None and rid in self.start_headings and rid in self._last_fix:
                g = self.cfg.basestation.gps  # virtual ENU-origin trajectory (seed 000 §III-C)
                fix, heading = self._last_fix[rid], self.start_headings[rid]
                start = gnss_start(fix, heading, odom, self.odom_now(rid))
                start_sigmas = (g.start_sigma_xy_m, g.start_sigma_xy_m, g.start_sigma_yaw_rad)
                self._georeferenced.add(rid)
                log.info("robot %s starts georeferenced at its latest GNSS fix", rid)
            elif start is None and rid in self.start_headings:
                self._floating_starts[rid] = odom  # georeferenced at its first fix
                log.warning("robot %s: no GNSS fix before its first keyframe", rid)
            elif start is None and self.map_frame.defines_map(rid):
                self.known_starts[rid] = np.zeros(3)
                start = odom
                log.info("robot %s defines the map frame", rid)
            if rid in self._stored_starts:  # (restore: a GNSS start used the state then)
                start, start_sigmas = self._stored_starts.pop(rid)
                if start is not None and rid in self._floating_starts:  # (`_late_start`)
                    del self._floating_starts[rid]
                    self._georeferenced.add(rid)
            self._unsaved_starts[rid] = (start, start_sigmas)
            self.graph.add_robot(rid, start, start_sigmas)
            self.graph.add_node(rid, 0, None, None, initial_guess=start, stamp=stamp)
            for fix in self._early_fixes.pop(rid, []):  # fixes older than the node drop
                if rid in self._georeferenced:
                    self.graph.add_gps_fix(rid, *fix)
                else:
                    self.gps_fixes_ignored += 1
        else:
            d = kf.delta
            delta = np.array([d[0], d[1], float(quat_to_yaw(d[3:7]))])
            cov = kf.delta_cov[np.ix_([0, 1, 5], [0, 1, 5])]
            self.graph.add_node(rid, kf.seq, delta, cov, stamp=stamp)
        self._new_nodes.append((rid, kf.seq))

    def _late_start(self, rid: str, fix: np.ndarray) -> bool:
        """A robot with a start heading whose first keyframe came before its first GNSS
        fix (fixes are held until the map's WGS84 origin is set): at its first fix, its
        chain is put where that fix and the heading say (`gnss_start`); if matches have
        put it on the map meanwhile (ENU: every start here is), its fixes count as they
        are (they had all been ignored). Whether it is georeferenced now."""
        if (odom := self._floating_starts.pop(rid, None)) is None:
            return False
        self._georeferenced.add(rid)
        if not self.graph.is_anchored(rid):
            g = self.cfg.basestation.gps
            start = gnss_start(fix, self.start_headings[rid], odom, self.odom_now(rid))
            sigmas = np.array([g.start_sigma_xy_m, g.start_sigma_xy_m, g.start_sigma_yaw_rad])
            self.graph.georeference(rid, start, sigmas)
            self._unsaved_starts[rid] = (start, sigmas)  # (a restart starts it there)
            log.info("robot %s georeferenced at its first GNSS fix", rid)
        return True

    def _joined_georeferenced(self, rid: str) -> bool:
        """A robot without a start of its own (a later run of a drone: a second flight, a
        battery swap) that matches have put on the map of georeferenced robots (ENU):
        its fixes count from now on (all 80 of a second flight's had been ignored)."""
        if not (self._georeferenced and self.graph.is_anchored(rid)):
            return False
        self._georeferenced.add(rid)
        log.info("robot %s is on the georeferenced map: its GNSS fixes count", rid)
        return True

    def optimize(self) -> None:
        """One iSAM2 update. After new constraints one forced relinearization step
        follows at once (loop closures move nodes far; between them iSAM2 checks for
        relinearization only every `relinearize_skip` updates)."""
        t0 = time.perf_counter()
        self.graph.update(extra_iterations=1 if self._constraints_added else 0)
        self._constraints_added = False
        ms = (time.perf_counter() - t0) * 1e3
        self.updates += 1
        self.update_ms.append(ms)
        self.update_series.add(ms)
        self.map_frame.check(time.monotonic())

    def converge(self, max_iterations: int = 20) -> None:
        """Relinearize until nothing moves (up to `max_iterations` forced iSAM2 steps):
        between updates iSAM2 relinearizes only every `relinearize_skip` updates and
        variables whose step exceeds the threshold, so the estimate after the last match
        added or removed need not be the optimum yet. Run once the inputs have stopped."""
        if self.graph.num_nodes():
            self.graph.update(extra_iterations=max_iterations)
            self.map_frame.check(time.monotonic(), final=True)

    # --- constraints --------------------------------------------------------------------
    def _chain_covariance(self, robot: str, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        return self.store.robot(robot).chain_covariance(i, j)

    def _points_in(
        self, frame: NodeKey, nodes: list[NodeKey], poses: dict[str, np.ndarray]
    ) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """The nodes' scan points, each in its own node's frame (the store's read-only
        arrays, shared, not copied: jobs wait in queues), and their poses in the frame
        of node `frame` (T_frame_node)."""
        T_w_f = poses[frame[0]][frame[1]]
        points = [self.store.points(rid, i) for rid, i in nodes]
        return points, [se2_between(T_w_f, poses[rid][i]) for rid, i in nodes]

    def _query(
        self, key: NodeKey, nodes: list[NodeKey], poses: dict[str, np.ndarray]
    ) -> tuple[list[np.ndarray], list[np.ndarray], int]:
        """The nodes' points and poses in key's frame (as `_points_in`), key's own scan
        first; and its length."""
        ordered = [key, *(n for n in nodes if n != key)]
        points, origins = self._points_in(key, ordered, poses)
        return points, origins, len(points[0])

    def _neighbours(self, key: NodeKey, k: int) -> list[NodeKey]:
        rid, i = key
        n = self.store.robot(rid).next_seq
        return [(rid, j) for j in range(max(0, i - k), min(n, i + k + 1))]

    def search_constraints(self) -> None:
        """Queue verification jobs for the nodes added since the last call, and for the
        earlier nodes of robots whose maps have just been joined (see `_backfill`)."""
        new, self._new_nodes = self._new_nodes, []
        if self.builder is None:
            return
        components = self.graph.components()
        frames = self._frames(components)
        self.builder.cancel_global(frames)  # searches queued before two maps were joined
        self.join_check.watch()  # robots joined since: checked (basestation/join_check.py)
        joined = newly_joined(self.graph.num_nodes, self._together, frames)
        self._together = {r: frozenset(f) for f in frames for r in f}
        if not new and not joined:
            return
        comp_of = {r: c for c in components for r in c}
        frame_of = {r: f for f in frames for r in f}
        poses = {r: self.graph.poses(r) for r in self.graph.robots() if r in comp_of}
        links = self.loops.pending_links()
        for key in new:
            frame = frame_of.get(key[0])
            if frame is None:
                continue
            query = functools.cache(lambda k=key: self._query(k, self._neighbours(k, 1), poses))
            self._submit_candidates(key, poses, frame, query)
            for m in links:  # a match with a separate map: look for more where it says
                if key[0] in (m.robot_a, m.robot_b):
                    hyp = hypothesis_poses(m, key[0], poses)
                    other = m.robot_a if m.robot_b == key[0] else m.robot_b
                    self._submit_candidates(key, hyp, [*comp_of[other], key[0]], query, "inter")
            if not self.graph.is_anchored(key[0]):
                on_map = self.graph.is_anchored(frames[0][0])
                if key[1] % self.cc.global_search_every == 0 and on_map:
                    self._submit_global(key, poses, frames[0])
            elif len(frames) > 1 and self.whole_map.floating_due():
                for floating in frames[1:]:  # where a robot not on the map flew before
                    self._submit_global(key, poses, floating)
            if self.join_check.due(key):  # a robot joined lately: is it where the join says?
                self._submit_global(key, poses, frames[0], check=True)
        for a, b in joined:
            self._backfill(a, b, poses)

    def _frames(self, components: list[list[str]]) -> list[list[str]]:
        """Robots searched against each other: all maps anchored in `map` as one."""
        anchored = [r for c in components if self.graph.is_anchored(c[0]) for r in c]
        floating = [c for c in components if not self.graph.is_anchored(c[0])]
        return [anchored, *floating] if anchored else floating

    def _backfill(self, robot: str, other: str, poses: dict[str, np.ndarray]) -> None:
        """Inter-robot candidates for the nodes ``robot`` added before its map and
        ``other``'s were joined. New nodes are searched against the robots of their own
        map only, so without this the part of a chain flown before the join (a robot
        with an unknown start: everything before its first verified match) would never
        be tied to the places the other robot saw too, and would hang on its odometry
        alone. Every `candidate_stride`-th node with a candidate, thinned evenly to at
        most `backfill_max_candidates`."""
        found = []
        for i in range(0, len(poses[robot]), self.cc.candidate_stride):
            key = (robot, i)
            found += [(key, t) for _, t in find_candidates(self.cc, key, poses, [other])]
        n = self.cc.backfill_max_candidates
        keep = np.unique(np.linspace(0, len(found) - 1, n).astype(int)) if found else []
        chosen = [found[k] for k in keep]
        self.backfill_open.add((min(robot, other), max(robot, other)))
        for key, target in chosen:
            query = self._query(key, self._neighbours(key, 1), poses)
            self._submit_match("inter", key, target, poses, query)
        log.info(
            "maps of %s and %s joined: %d earlier nodes of %s queued against %s",
            robot, other, len(chosen), robot, other,
        )  # fmt: skip

    def _submit_candidates(
        self, key: NodeKey, poses: dict[str, np.ndarray], robots: list[str], query: Query,
        only: str | None = None,
    ) -> None:  # fmt: skip
        """Robots not searched: too soon after the last candidate with them, or their kind's
        queue is full (the verifier is behind: a job is not worth building). Inter-robot
        candidates between stretches the two robots are tied at already are not verified."""
        rid, idx = key
        searched = [
            o for o in robots
            if (kind := "loop" if o == rid else "inter") == (only or kind)
            and idx - self._last_candidate.get((rid, o), -(10**9)) >= self.cc.candidate_stride
            and self.builder.has_room(kind)
        ]  # fmt: skip
        for kind, target in find_candidates(self.cc, key, poses, searched):
            if not self.builder.has_room(kind):
                continue
            self._last_candidate[(rid, target[0])] = idx
            if kind == "inter" and self.loops.covered(key, target):
                self.builder.count("redundant_inter")  # the two places are tied already
            else:
                self._submit_match(kind, key, target, poses, query())

    def _submit_match(
        self, kind: str, key: NodeKey, target: NodeKey, poses: dict[str, np.ndarray],
        query: tuple[list[np.ndarray], list[np.ndarray], int],
    ) -> None:  # fmt: skip
        """Queue the verification of node ``key`` (``query``: its scan and neighbours, as
        `_query` gives them) against ``target`` and its `target_neighbours`."""
        k = self.cc.target_neighbours
        scans, origins = self._points_in(target, self._neighbours(target, k), poses)
        guess = se2_between(poses[target[0]][target[1]], poses[key[0]][key[1]])
        q_points, q_origins, n_own = query
        self.builder.submit(
            Job(kind, target, key, guess, scans, q_points, origins, n_own,
                in_node_frames=True, query_origins=q_origins)
        )  # fmt: skip

    def _submit_global(
        self, key: NodeKey, poses: dict[str, np.ndarray], frame: list[str], check: bool = False
    ) -> None:
        """Queue a search of robot key[0]'s recent scans against the whole map of the robots
        in ``frame`` (basestation/whole_map_search.py; `check`: of its join)."""
        job = self.whole_map.job(key, poses, frame, self._query, check)
        if job is not None:
            self.builder.submit(job)

    def verify_pending(self, budget: float) -> int:
        """Verify up to `budget` waiting candidates here (`ConstraintBuilder.run_pending`)."""
        return 0 if self.builder is None else self.builder.run_pending(budget)

    def start_verifier(self) -> None:
        if self.builder is not None:  # verify on the worker thread from now on
            self.builder.start()

    def integrate_constraints(self) -> int:
        """Hand verified matches to the loop-closure manager; returns how many arrived."""
        if self.builder is None:
            return 0
        results = self.builder.results()
        self._constraints_added |= bool(results)
        for v in results:
            try:
                self._integrate(v)
                self.false_matches.after(v)
            except CollabSlamError as e:  # a stale or degenerate match: drop it, keep going
                log.error("verified %s match %s -> %s dropped: %s", v.job.kind, v.job.a, v.job.b, e)
        return len(results)

    def _integrate(self, v: Verified) -> None:
        job, m = v.job, v.match
        if self.join_check.takes(job):  # a joined robot's check (basestation/join_check.py)
            if (r := self.join_check.result(v)) is not None:  # undone: placed anew
                self._together = apart(self._together, r)  # (its backfill runs again)
        elif job.kind == "global":  # tie b to the target map's nearest node, as it was then
            a, T_a_b = tie(job, m)
            self.loops.add(a, job.b, T_a_b, m.covariance, "inter")
        elif job.kind == "inter" and self.loops.covered(job.a, job.b):
            self.builder.count("redundant_inter")  # tied while it waited in the queue
        else:
            self.loops.add(job.a, job.b, m.T_a_b, m.covariance, job.kind)

    def backlog(self) -> int:
        """Candidates waiting for verification."""
        return 0 if self.builder is None else self.builder.backlog()

    def idle(self) -> bool:
        return self.builder is None or self.builder.idle()

    def close(self) -> None:
        if self.builder is not None:
            self.builder.close()

    # --- estimates ----------------------------------------------------------------------
    def T_map_odom(self, rid: str) -> np.ndarray | None:
        """[x, y, yaw] at the robot's latest keyframe, None while it is not on the map."""
        idx = self.graph.latest_index(rid)
        if idx is None or not self.graph.is_anchored(rid):
            return None
        T_odom_base = self.store.robot(rid).poses_odom[idx][[0, 1, 3]]
        return se2_compose(self.graph.pose(rid, idx), se2_inverse(T_odom_base))

    def map_keyframes(self) -> tuple[NodeKeys, Sequence[Scan2D], np.ndarray]:
        """Keyframes of robots on the map that have a scan, their scans (fetched when
        indexed: memory or database) and optimized poses."""
        blocks, poses = [], []
        for rid, r in self.store.robots.items():
            n = self.graph.num_nodes(rid) if rid in self.graph.robots() else 0
            if n == 0 or not self.graph.is_anchored(rid):
                continue
            idx = np.flatnonzero(np.frombuffer(r.has_scan, dtype=np.uint8)[:n])
            blocks.append((rid, idx))
            poses.append(self.graph.poses(rid)[idx])
        P = np.concatenate(poses) if poses else np.zeros((0, 3))
        keys = NodeKeys(blocks)
        return keys, KeyframeScans(self.store, keys), P

    def trajectories(self) -> dict[str, Trajectory]:
        out = {}
        for rid, r in self.store.robots.items():
            if rid not in self.graph.robots() or self.graph.num_nodes(rid) == 0:
                continue
            est = self.graph.poses(rid)
            poses4 = np.column_stack([est[:, :2], r.poses_odom.view()[: len(est), 2], est[:, 2]])
            out[rid] = Trajectory.in_time_order(r.stamps.view()[: len(est), 0].copy(), poses4, rid)
        return out

    def stats(self) -> dict[str, Any]:
        """Counts and latencies for basestation.json (`slam_stats`)."""
        return slam_stats(self)
