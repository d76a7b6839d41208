"""The base-station daemon.

Receives every robot's keyframes, admits them in order per robot, adds them
to one iSAM2 pose graph (one chain per robot), acknowledges them once they are
in the graph, publishes each robot's T_map_odom after every optimization, and
keeps the global occupancy grid up to date. At shutdown it writes the map,
the trajectories and its statistics.

Threads: Zenoh callbacks only enqueue; everything else runs on `run()`'s thread.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from basestation.keyframe_store import KeyframeStore
from basestation.map_builder import MapBuilder
from basestation.pose_graph import PoseGraph
from common.bus import Bus
from common.config import Config
from common.geometry import pose4_to_pose7, quat_to_yaw, se2_compose, se2_inverse
from common.map_io import write_map
from common.picture import render_map_picture
from common.scenario import Scenario
from common.trajectory_io import Trajectory, write_tum
from protocol import Keyframe, KeyframeAck, PoseCorrection, RobotState

log = logging.getLogger(__name__)


class BaseStationNode:
    def __init__(self, cfg: Config, bus: Bus, scenario: Scenario | None) -> None:
        self.cfg = cfg
        self.bus = bus
        self.keys = bus.keys
        b = cfg.basestation
        self.graph = PoseGraph(
            relinearize_threshold=b.relinearize_threshold,
            relinearize_skip=b.relinearize_skip,
            prior_sigmas=(b.prior_sigma_xy_m, b.prior_sigma_xy_m, b.prior_sigma_yaw_rad),
        )
        self.store = KeyframeStore(b.reorder_window)
        self.map = MapBuilder(cfg.map)
        self.inbox: queue.Queue[Keyframe] = queue.Queue()
        self.states: dict[str, RobotState] = {}
        # With a scenario the roster is closed (other robot ids are dropped) and start
        # poses are known; without one, any robot may join with a floating chain.
        self.known_starts: dict[str, np.ndarray] = {}
        self.roster: set[str] | None = None
        if scenario is not None:
            self.known_starts = {r.robot_id: r.start_pose for r in scenario.robots}
            self.roster = set(self.known_starts)
        self.epoch = 0
        self.unknown_robot_drops = 0
        self.update_ms: list[float] = []
        self._last_map = 0.0
        self._map_dirty = False
        self._lock = threading.Lock()

    # --- wiring -------------------------------------------------------------------------
    def start(self) -> None:
        self.bus.subscribe(
            self.keys.all_robots("keyframe"), Keyframe, lambda m, k: self.inbox.put(m)
        )
        self.bus.subscribe(self.keys.all_robots("state"), RobotState, self._on_state)
        self.bus.watch_alive("agent", self._on_agent_alive)
        self.bus.declare_alive("basestation", "base")

    def _on_state(self, msg: RobotState, key: str) -> None:
        with self._lock:
            self.states[msg.robot_id] = msg

    def _on_agent_alive(self, name: str, alive: bool) -> None:
        log.info("agent %s %s", name, "joined" if alive else "left")

    # --- processing ---------------------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        while not stop.is_set():
            self.step(timeout=0.05)

    def step(self, timeout: float = 0.0) -> int:
        """Process one batch of received keyframes; returns how many were admitted."""
        batch: list[Keyframe] = []
        try:
            batch.append(
                self.inbox.get(timeout=timeout) if timeout > 0 else self.inbox.get_nowait()
            )
            while len(batch) < self.cfg.basestation.batch_max:
                batch.append(self.inbox.get_nowait())
        except queue.Empty:
            pass
        admitted = self.process(batch) if batch else 0
        now = time.monotonic()
        if self._map_dirty and now - self._last_map >= self.cfg.basestation.map_update_period_s:
            self.refresh_map()
            self._last_map = now
        return admitted

    def process(self, batch: list[Keyframe]) -> int:
        touched: set[str] = set()
        admitted = 0
        for kf in batch:
            rid = kf.robot_id
            if self.roster is not None and rid not in self.roster:
                self.unknown_robot_drops += 1
                if self.unknown_robot_drops <= 20 or self.unknown_robot_drops % 1000 == 0:
                    log.error(
                        "keyframe from unknown robot %r dropped (%d so far); known: %s",
                        rid,
                        self.unknown_robot_drops,
                        sorted(self.roster),
                    )
                continue
            touched.add(rid)
            for k in self.store.admit(kf):
                self._add_to_graph(k)
                admitted += 1
        if admitted:
            t0 = time.perf_counter()
            self.graph.update()
            self.update_ms.append((time.perf_counter() - t0) * 1e3)
            self._map_dirty = True
        for rid in touched:  # ack admitted and duplicate keyframes alike
            acked = self.store.acked_seq(rid)
            if acked >= 0:
                self.bus.publish(self.keys.robot(rid, "ack"), KeyframeAck(rid, acked))
        if admitted:
            self.publish_corrections()
        return admitted

    def _add_to_graph(self, kf: Keyframe) -> None:
        rid = kf.robot_id
        if kf.seq == 0:
            start = self.known_starts.get(rid)  # None: unknown start, floating chain
            self.graph.add_robot(rid, start)
            self.graph.add_node(rid, 0, None, None, initial_guess=start)
            return
        d = kf.delta
        delta = np.array([d[0], d[1], float(quat_to_yaw(d[3:7]))])
        cov = kf.delta_cov[np.ix_([0, 1, 5], [0, 1, 5])]
        self.graph.add_node(rid, kf.seq, delta, cov)

    def publish_corrections(self) -> None:
        self.epoch += 1
        stamp = time.time()
        for rid, r in self.store.robots.items():
            if not r.keyframes or self.graph.latest_index(rid) is None:
                continue
            idx = self.graph.latest_index(rid)
            T_map_base = self.graph.pose(rid, idx)
            T_odom_base = r.poses_odom[idx][[0, 1, 3]]
            T_map_odom = se2_compose(T_map_base, se2_inverse(T_odom_base))
            self.bus.publish(
                self.keys.robot(rid, "correction"),
                PoseCorrection(
                    rid,
                    self.epoch,
                    stamp,
                    pose4_to_pose7([T_map_odom[0], T_map_odom[1], 0.0, T_map_odom[2]]),
                ),
            )

    def _all_keyframes(self) -> tuple[list[tuple[str, int]], list[Any], np.ndarray]:
        keys, scans, poses = [], [], []
        for rid, r in self.store.robots.items():
            n = self.graph.num_nodes(rid) if rid in self.graph.robots() else 0
            if n == 0:
                continue
            est = self.graph.poses(rid)
            for i in range(n):
                if r.keyframes[i].scan2d is not None:
                    keys.append((rid, i))
                    scans.append(r.keyframes[i].scan2d)
                    poses.append(est[i])
        return keys, scans, np.array(poses).reshape(-1, 3)

    def refresh_map(self) -> None:
        keys, scans, poses = self._all_keyframes()
        self.map.update(keys, scans, poses)
        self._map_dirty = False

    def drain(self) -> None:
        """Process everything already received."""
        while self.step(timeout=0.0) or not self.inbox.empty():
            pass

    # --- outputs ------------------------------------------------------------------------
    def trajectories(self) -> dict[str, Trajectory]:
        out = {}
        for rid, r in self.store.robots.items():
            if rid not in self.graph.robots() or self.graph.num_nodes(rid) == 0:
                continue
            est = self.graph.poses(rid)
            z = np.array([p[2] for p in r.poses_odom[: len(est)]])
            poses4 = np.column_stack([est[:, 0], est[:, 1], z, est[:, 2]])
            out[rid] = Trajectory.from_pose4(np.array(r.stamps[: len(est)]), poses4)
        return out

    def stats(self) -> dict[str, Any]:
        upd = np.array(self.update_ms) if self.update_ms else np.zeros(1)
        return {
            "robots": {
                rid: {
                    "keyframes_in_graph": self.graph.num_nodes(rid)
                    if rid in self.graph.robots()
                    else 0,
                    "duplicates": r.duplicates,
                    "held_out_of_order": len(r.held),
                }
                for rid, r in self.store.robots.items()
            },
            "unknown_robot_drops": self.unknown_robot_drops,
            "rejected_messages": dict(self.bus.rejected),
            "correction_epoch": self.epoch,
            "isam2_updates": len(self.update_ms),
            "isam2_update_ms_p50": float(np.percentile(upd, 50)),
            "isam2_update_ms_p95": float(np.percentile(upd, 95)),
            "map_full_renders": self.map.full_renders,
        }

    def write_outputs(self, out_dir: str | Path) -> None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        self.refresh_map()
        trajs = self.trajectories()
        for rid, traj in trajs.items():
            write_tum(out / "trajectories" / f"{rid}.tum", traj)
        grid = self.map.gridmap()
        if grid is not None:
            write_map(grid, out / "map.yaml", "map.pgm")
            render_map_picture(
                out / "map.png",
                grid,
                trajectories={rid: t.positions[:, :2] for rid, t in trajs.items()},
                robots={rid: t.poses_se2()[-1] for rid, t in trajs.items() if len(t)},
                title=f"collabslam map: {len(trajs)} robots",
            )
        (out / "basestation.json").write_text(json.dumps(self.stats(), indent=1))
        log.info("outputs written to %s", out)
