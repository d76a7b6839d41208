"""Finds loop-closure and inter-robot candidates and verifies them by scan matching.

Candidates (seed 002 §1.1, eq. 2): for a new node, nodes within `search_radius_m`
and `search_angle_rad` in the same map frame (the same graph component). The
nearest node of every other robot gives an inter-robot candidate; the nearest
node of the same robot at least `loop_min_index_gap` keyframes back gives a
loop-closure candidate. A robot whose chain is not connected to the map yet
gets a global search of its latest scan against the whole map every
`global_search_every` keyframes (its start pose is unknown).

Verification runs on one worker thread (in a lock-step simulation on the caller's,
`run_pending`, at the clock's requests): the main thread packs each job with
everything it needs (the scans, where each was taken, the guess), so the worker
never touches the graph. A job may carry each node's points in that node's own
frame (`in_node_frames`: read-only arrays shared with the keyframe store and other
jobs, so a full queue costs little memory); the worker places them. The worker
keeps to `max_candidates_per_s` and takes jobs by priority: global searches
first (robots in turn, oldest first; each robot keeps its newest
`global_pending_per_robot`: live, only the newest scan is worth the search), then
inter-robot candidates, then loop closures; each of the last two queues holds at
most `max_queue` jobs (when full, new ones are not built) and serves the newest
first. Under load (10 robots on 2 cores) the worker verifies fewer candidates than
the robots bring: served oldest first, every match came ~800 keyframes after its
node (minutes), after the robot had long flown on and the reduced pose graph had
already passed the node; served newest first, what is verified is where the robots
are now, and the older candidates wait until the worker catches up.
"""

from __future__ import annotations

import collections
import logging
import math
import threading
import time
from dataclasses import dataclass

import numpy as np

from basestation.pcm import LoopMeasurement
from basestation.scan_verifier import ScanVerifier, VerifiedMatch
from common.config import ConstraintConfig
from common.errors import TooFewPoints
from common.geometry import (
    se2_between,
    se2_compose,
    se2_inverse,
    se2_transform_points,
    wrap_angle,
)

log = logging.getLogger(__name__)

NodeKey = tuple[str, int]
GLOBAL_SEARCH_COST = 10
GLOBAL_TARGETS_CACHED = 4  # whole-map search targets kept built (the map and floating maps)


@dataclass(frozen=True)
class Job:
    kind: str  # "loop" | "inter" | "global"
    a: NodeKey  # target node (its frame is the target frame; for "global": b)
    b: NodeKey  # query node
    T_a_b_guess: np.ndarray  # for "global": unused
    # points in frame a (for "global": the scans of target_nodes in the map's frame)
    target_scans: list[np.ndarray]
    query_points: np.ndarray | list[np.ndarray]  # points in frame b (see in_node_frames)
    target_origins: list[np.ndarray] | None = None  # sensor pose of each target scan
    n_sensor: int | None = None  # the first n query points are node b's own scan
    target_key: object = None  # cache key of the target (global map version)
    # With in_node_frames: query_points is a list of per-node points placed in frame b by
    # query_origins (node b's own scan first, n_sensor points) and, but for "global" jobs
    # (their target is the map, already in the map frame), target_scans[i] is in its own
    # node's frame, placed in frame a by target_origins[i] (T_a_i).
    in_node_frames: bool = False
    query_origins: list[np.ndarray] | None = None
    target_nodes: list[NodeKey] | None = None  # "global": the node of each target scan
    # "global", a join's check (basestation/join_check.py): where the map has node b now
    check_at: np.ndarray | None = None

    def queue_name(self) -> str:
        """A global search's queue: its query robot's, and the target map's first robot."""
        first = self.target_nodes[0][0] if self.target_nodes else ""
        return f"{self.b[0]}>{first}"

    def placed_targets(self) -> list[np.ndarray]:
        """The target scans in frame a."""
        if not self.in_node_frames or self.kind == "global":
            return self.target_scans
        assert self.target_origins is not None
        return [
            se2_transform_points(T, p)
            for T, p in zip(self.target_origins, self.target_scans, strict=True)
        ]

    def placed_query(self) -> np.ndarray:
        """The query points in frame b (node b's own first)."""
        if not self.in_node_frames:
            return np.asarray(self.query_points)
        assert self.query_origins is not None
        parts = [
            se2_transform_points(T, p)
            for T, p in zip(self.query_origins, self.query_points, strict=True)
        ]
        return np.vstack(parts) if parts else np.zeros((0, 2))

    def placed_query_sensors(self) -> np.ndarray | None:
        """Where each point of `placed_query` was seen from (frame b); None: b's origin."""
        if not self.in_node_frames:
            return None
        assert self.query_origins is not None
        parts = [
            np.broadcast_to(np.asarray(T, dtype=np.float64)[:2], (len(p), 2))
            for T, p in zip(self.query_origins, self.query_points, strict=True)
        ]
        return np.vstack(parts) if parts else np.zeros((0, 2))


@dataclass(frozen=True)
class Verified:
    job: Job
    match: VerifiedMatch  # T_a_b (for "global": node b in the frame of the target's origins)
    here: VerifiedMatch | None = None  # a join's check: b matched about `check_at`, if it is


def find_candidates(
    cfg: ConstraintConfig, new: NodeKey, poses: dict[str, np.ndarray], component: list[str]
) -> list[tuple[str, NodeKey]]:
    """(kind, target node) pairs for `new`, searching robots of its component only.

    poses: robot -> (N, 3) current estimates (same frame within the component).
    """
    rid, idx = new
    p = poses[rid][idx]
    out: list[tuple[str, NodeKey]] = []
    for other in component:
        P = poses[other]
        if other == rid:
            P = P[: max(0, idx - cfg.loop_min_index_gap)]
        if len(P) == 0:
            continue
        d = np.hypot(P[:, 0] - p[0], P[:, 1] - p[1])
        near = np.flatnonzero(d < cfg.search_radius_m)  # angles and travel: of these only
        near = near[np.abs(wrap_angle(P[near, 2] - p[2])) < cfg.search_angle_rad]
        if other == rid and len(near):  # a loop: the robot went away and came back
            steps = np.hypot(*np.diff(poses[rid][near[0] : idx + 1, :2], axis=0).T)
            travel = np.cumsum(steps[::-1])[::-1][near - near[0]]  # from node j to idx
            near = near[(travel >= cfg.loop_min_travel_m) & (travel >= 2.0 * d[near])]
        if not len(near):
            continue
        j = int(near[np.argmin(d[near])])
        out.append(("loop" if other == rid else "inter", (other, j)))
    return out


def hypothesis_poses(
    m: LoopMeasurement, robot: str, poses: dict[str, np.ndarray]
) -> dict[str, np.ndarray]:
    """`poses` with `robot`'s chain moved into the other robot's map frame as the
    match `m` (between two separate maps) puts it."""
    if m.robot_b == robot:
        na, nb, T_a_b = (m.robot_a, m.index_a), (robot, m.index_b), m.T_a_b
    else:
        na, nb, T_a_b = (m.robot_b, m.index_b), (robot, m.index_a), se2_inverse(m.T_a_b)
    T = se2_compose(se2_compose(poses[na[0]][na[1]], T_a_b), se2_inverse(poses[robot][nb[1]]))
    return {**poses, robot: se2_compose(T, poses[robot])}


class ConstraintBuilder:
    def __init__(
        self, cfg: ConstraintConfig, verifier: ScanVerifier | None = None, threaded: bool = True
    ) -> None:
        self.cfg = cfg
        self.verifier = verifier or ScanVerifier(
            linear_window=cfg.linear_window_m,
            angular_window=math.radians(cfg.angular_window_deg),
            min_score=cfg.min_score,
            min_overlap=cfg.min_overlap,
            max_corr_dist=cfg.max_corr_dist_m,
        )
        self._global: dict[str, collections.deque[Job]] = {}  # robot -> its global searches
        self._last_kind = "loop"  # queue served last (see _next_job)
        self._queues: dict[str, collections.deque[Job]] = {
            kind: collections.deque(maxlen=cfg.max_queue) for kind in ("inter", "loop")
        }
        self._results: list[Verified] = []
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        # whole-map search targets by target_key, newest last (the map, floating maps)
        self._global_targets: collections.OrderedDict[object, object] = collections.OrderedDict()
        self.stats = collections.Counter()
        self._busy = False
        self._busy_kind: str | None = None
        self._thread: threading.Thread | None = None
        if threaded:
            self.start()

    def start(self) -> None:
        """Start the worker thread (once); without it, `run_pending` verifies on the caller's."""
        if self._thread is None:
            self._thread = threading.Thread(
                target=self._work, name="constraint-builder", daemon=True
            )
            self._thread.start()

    def submit(self, job: Job) -> None:
        with self._lock:
            self.stats[f"submitted_{job.kind}"] += 1
            if job.kind == "global":
                n = self.cfg.global_pending_per_robot
                q = self._global.setdefault(job.queue_name(), collections.deque(maxlen=n))
                if len(q) == n:
                    self.stats["superseded_global"] += 1
                q.append(job)
            else:
                q = self._queues[job.kind]
                if len(q) == q.maxlen:
                    self.stats[f"dropped_{job.kind}"] += 1
                q.append(job)
        self._wake.set()

    def count(self, name: str) -> None:
        """Count a candidate the caller left out (``name``: why) in ``stats``."""
        with self._lock:
            self.stats[name] += 1

    def cancel_global(self, frames: list[list[str]]) -> None:
        """Drop the waiting global searches whose query robot is now in one of ``frames``
        (robots mapped in one frame) with the target map's robots: joined since (but not
        the checks of a join, `Job.check_at`)."""
        with self._lock:
            for name in list(self._global):
                query, target = name.split(">")
                if any(query in f and target in f for f in frames):
                    q = self._global.pop(name)
                    checks = [j for j in q if j.check_at is not None]
                    self.stats["cancelled_global"] += len(q) - len(checks)
                    if checks:
                        self._global[name] = collections.deque(checks, maxlen=q.maxlen)

    def cancel_inter(self, robot: str) -> None:
        """Drop the waiting inter-robot candidates of `robot`, and their results not taken
        yet: its join to the map was undone (basestation/join_check.py), and they were
        searched where the join had put it."""
        with self._lock:
            q = self._queues["inter"]
            keep = [j for j in q if robot not in (j.a[0], j.b[0])]
            self.stats["cancelled_inter"] += len(q) - len(keep)
            q.clear()
            q.extend(keep)
            self._results = [
                v
                for v in self._results
                if v.job.kind != "inter" or robot not in (v.job.a[0], v.job.b[0])
            ]

    def has_room(self, kind: str) -> bool:
        """False while the queue of ``kind`` is full: a job submitted now would only push
        out an older one, so the caller need not build it (skipped, counted)."""
        with self._lock:
            q = self._queues[kind]
            if len(q) < (q.maxlen or 0):
                return True
            self.stats[f"skipped_{kind}"] += 1
            return False

    def _next_job(self) -> Job | None:
        """Global searches first, then the inter-robot and loop queues in turn (neither
        starves the other when both are longer than the budget)."""
        if self._global:
            robot = next(iter(self._global))
            q = self._global.pop(robot)
            job = q.popleft()
            if q:
                self._global[robot] = q  # to the back: the next robot's turn
            return job
        kinds = sorted(self._queues, key=lambda k: k == self._last_kind)  # the other first
        for kind in kinds:
            if self._queues[kind]:
                self._last_kind = kind
                return self._queues[kind].pop()  # the newest first
        return None

    def backlog(self) -> int:
        """Pending work in candidate units: a global search counts as
        `GLOBAL_SEARCH_COST` candidates (it costs about that much more)."""
        with self._lock:
            n_global = sum(map(len, self._global.values())) + (self._busy_kind == "global")
            return GLOBAL_SEARCH_COST * n_global + sum(len(q) for q in self._queues.values())

    def results(self) -> list[Verified]:
        with self._lock:
            out, self._results = self._results, []
        return out

    def idle(self) -> bool:
        with self._lock:
            return not self._busy and not self._global and not any(self._queues.values())

    def drained(self) -> bool:
        """Idle, and every result taken: each job queued so far has its answer in."""
        with self._lock:
            idle = not self._busy and not self._global and not any(self._queues.values())
            return idle and not self._results

    def close(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=10)

    def run_pending(self, budget: float) -> int:
        """Without the worker thread (a lock-step simulation): verify queued jobs on this
        thread, in the worker's order, until `budget` candidates' worth is spent (a global
        search costs `GLOBAL_SEARCH_COST`) or none is left; returns how many ran. The same
        queues in give the same results out, however loaded the machine is."""
        if self._thread is not None:
            return 0
        ran, spent = 0, 0.0
        while spent < budget:
            with self._lock:
                job = self._next_job()
            if job is None:
                break
            self._finish(job, self._try_verify(job))
            spent += GLOBAL_SEARCH_COST if job.kind == "global" else 1
            ran += 1
        return ran

    def _try_verify(self, job: Job) -> Verified | None:
        try:
            return self._verify(job)
        except TooFewPoints as e:  # (a 3-D robot's scans: a traceback per candidate)
            log.debug("verification of %s: %s", job.kind, e)
            return None
        except Exception:
            log.exception("verification of %s failed", job.kind)
            return None

    def _finish(self, job: Job, verified: Verified | None) -> None:
        with self._lock:
            self.stats[f"verified_{job.kind}" if verified else f"failed_{job.kind}"] += 1
            if verified is not None:
                self._results.append(verified)
            self._busy = False
            self._busy_kind = None

    def _work(self) -> None:
        period = 1.0 / self.cfg.max_candidates_per_s
        while not self._stop.is_set():
            with self._lock:
                job = self._next_job()
                self._busy = job is not None
                self._busy_kind = job.kind if job is not None else None
            if job is None:
                self._wake.wait(0.1)
                self._wake.clear()
                continue
            t0 = time.monotonic()
            self._finish(job, self._try_verify(job))
            rest = period - (time.monotonic() - t0)
            if rest > 0:
                self._stop.wait(rest)

    def _verify(self, job: Job) -> Verified | None:
        v = self.verifier
        if job.kind == "global":
            target = self._global_targets.pop(job.target_key, None)
            if target is None:
                target = v.build_target(job.target_scans, job.target_origins)
            self._global_targets[job.target_key] = target
            while len(self._global_targets) > GLOBAL_TARGETS_CACHED:
                self._global_targets.popitem(last=False)
            query = job.placed_query()
            match = v.global_search(
                target,
                query,
                self.cfg.global_min_score,
                query[: job.n_sensor],
                self.cfg.global_candidates,
                job.placed_query_sensors(),
            )
            log.debug(
                "whole-map search of %s:%d against %s: %s", *job.b, job.target_key,
                "none" if match is None else f"{np.round(match.T_a_b, 2)} score {match.score:.2f}",
            )  # fmt: skip
            if match is None or job.check_at is None:
                return None if match is None else Verified(job, match)
            here = v.verify(target, query, job.check_at, sensor_points=query[: job.n_sensor],
                            query_sensors_b=job.placed_query_sensors())  # fmt: skip
            return Verified(job, match, here)
        query = job.placed_query()
        target = v.build_target(job.placed_targets(), job.target_origins)
        match = v.verify(
            target,
            query,
            job.T_a_b_guess,
            sensor_points=query[: job.n_sensor],
            query_sensors_b=job.placed_query_sensors(),
        )
        return None if match is None else Verified(job, match)


def relative_guess(poses: dict[str, np.ndarray], a: NodeKey, b: NodeKey) -> np.ndarray:
    return se2_between(poses[a[0]][a[1]], poses[b[0]][b[1]])
