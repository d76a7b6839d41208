"""The base-station daemon.

Receives every robot's keyframes, hands them to global SLAM (in order per robot,
one iSAM2 graph, loop closures and inter-robot constraints), acknowledges them
once they are in the graph (and, with `basestation.db_path`, on disk: see
basestation/persistence.py; a restart with the same database resumes), publishes
each robot's T_map_odom after every optimization, and keeps the global occupancy
grid up to date. At shutdown it writes the map, the trajectories and its statistics.

Threads: Zenoh callbacks only enqueue (a robot's state is answered there, with where the
others are); the constraint builder verifies matches on its worker, and live, exploration
steps plan on theirs (exploration_worker.py); the rest is `run()`'s.
In a lock-step simulation with exploration everything happens when its clock asks, on
`run()`'s thread, verification included (basestation/lockstep.py): runs repeat exactly.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import queue
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np

from basestation.correction_epochs import CorrectionEpochs
from basestation.exploration_setup import (
    explorer_stats,
    keep_unheard_clear,
    make_explorer,
    planar_pose,
)
from basestation.exploration_worker import ExplorationWorker, StepInputs, StepResult
from basestation.global_slam import GlobalSlam
from basestation.gnss_intake import GnssIntake, map_georeference
from basestation.gps_fixes import local_pose
from basestation.inbox import KeyframeInbox
from basestation.lockstep import LockstepClock
from basestation.map_builder import MapBuilder
from basestation.map_history import MapHistory
from basestation.map_outputs import write_map_outputs
from basestation.neighbour_relay import NeighbourRelay
from basestation.persistence import Batch, open_database
from basestation.robot_segments import RobotSegments, robot_of
from basestation.roster import Roster, scenario_starts
from common.bus import Bus
from common.config import Config
from common.geometry import pose4_to_pose7
from common.logging_setup import set_sim_clock
from common.map_io import EXPLORATION_FREE_THRESH
from common.memory import HeapTrimmer
from common.metrics import TIMINGS_KEPT
from common.scenario import Scenario
from protocol import (
    ClockSync,
    GnssFix,
    Keyframe,
    PoseCorrection,
    RobotState,
    VehicleCommand,
    encode,
)

log = logging.getLogger(__name__)

# s of tile redraws between heap trims writing the outputs (else freed temporaries stay)
OUTPUT_REDRAW_CHUNK_S = 1.0


class BaseStationNode:
    def __init__(
        self, cfg: Config, bus: Bus, scenario: Scenario | None, lockstep: bool = False
    ) -> None:  # lockstep: a lock-step simulator with exploration drives it (lockstep.py)
        self.cfg = cfg
        self.bus = bus
        self.keys = bus.keys
        # With a scenario the roster is closed (other ids dropped), and it says where
        # robots start (roster.scenario_starts)
        self.roster = Roster(None if scenario is None else scenario.robot_ids)
        starts, headings = scenario_starts(cfg, scenario)
        self.db = open_database(cfg.basestation.db_path)
        # a lock-step simulator's clock paces everything (basestation/lockstep.py)
        lockstep = lockstep and cfg.base_sync_period_s() > 0.0
        self.clock = LockstepClock(lockstep, cfg.sim.basestation_timeout_s)
        if lockstep:  # DEBUG lines say the sim time of the step they are about
            set_sim_clock(lambda: self.clock.requested if self.clock.requested >= 0 else None)
        self.slam = GlobalSlam(cfg, starts, headings, self.db.scan_reader(), threaded=not lockstep)
        # With a scenario, map is the world frame: ENU at its WGS84 origin (gnss_intake.py)
        origin, not_enu = map_georeference(scenario, bool(headings))
        self.gnss = GnssIntake(origin, 2.0 * cfg.map.max_radius_m, not_enu)  # fixes -> map
        self.map = MapBuilder(cfg.map, self.slam.store.scans)
        self.explorer = make_explorer(cfg, lockstep) if cfg.exploration.enabled else None
        self.steps = ExplorationWorker(self.explorer) if self.explorer else None  # live: a thread
        self._last_explore, self._path_id = 0.0, 0
        self._explore_ms: deque[float] = deque(maxlen=TIMINGS_KEPT)  # wall time of the steps
        self.inbox = KeyframeInbox()  # bounded (see basestation/inbox.py)
        self.gnss_inbox: queue.Queue[GnssFix] = queue.Queue()  # basestation.gps.enabled
        self.states: dict[str, RobotState] = {}  # by segment (robot_segments.py)
        self.slam.odom_now = lambda r: local_pose(self.states.get(r))  # (GNSS starts)
        self.segments = RobotSegments()  # each run of a robot's agent: a robot of the graph
        self.neighbours = NeighbourRelay(strictly_earlier=lockstep)
        self.epochs = CorrectionEpochs(self.db)
        self.intake_pauses = self.syncs = 0
        self._last_map, self._map_dirty = 0.0, False
        self._lock = threading.Lock()
        self.map_history = MapHistory(max_snapshots=cfg.basestation.map_history_max_snapshots)
        self.links: dict[str, dict[str, int]] = {}  # agent -> {"joins": n, "losses": n}
        self._alive: set[str] = set()  # agents whose liveliness token is up
        self._lost: list[tuple[str, Any, bool]] = []  # (segment, pose, stopped): run()'s thread
        self.recovered: dict[str, Any] = {}
        slam = self.slam  # per-keyframe arrays: keyframe store, pose graph, map builder
        arrays = [slam.store.arrays_nbytes, slam.graph.arrays_nbytes, self.map.arrays_nbytes]
        self.heap = HeapTrimmer(slam.store.total_keyframes, arrays, slam.graph.factor_slots)

    # --- persistence --------------------------------------------------------------------
    def recover(self) -> None:
        """Resume from the database (if any): rebuild graph, map and exploration state,
        and continue epochs and path ids above every one sent before."""
        t0 = time.monotonic()
        rec = self.db.load()
        self.epochs.resume(rec.epoch)
        self._path_id = max(self._path_id, rec.path_id)
        self.gnss.restore(rec.gnss_origin)  # (before its fixes are replayed)
        off = "" if self.cfg.basestation.gps.enabled else "basestation.gps.enabled is off"
        if (why := self.gnss.not_enu or off) and rec.fixes:  # (not ENU: an earlier version's)
            log.warning("%d stored GNSS fixes not replayed: %s", len(rec.fixes), why)
            rec.fixes = []
        if rec.empty:
            return
        self.slam.restore(rec)
        self.segments.restore({rid: r.session for rid, r in self.slam.store.robots.items()})
        if self.steps:
            self.steps.restore(rec.paths)
        self._map_dirty = True  # rebuilt by run(), after the acks have gone out
        self.recovered = {
            "keyframes": len(rec.keyframes),
            "matches": len(rec.constraints),
            "in_graph": {r: self.slam.graph.num_nodes(r) for r in self.slam.graph.robots()},
            "seconds": time.monotonic() - t0,
        }
        log.info("recovered from %s (start %d): %d keyframes, %d matches in %.1f s; epoch %d",
                 self.db.path, rec.starts, len(rec.keyframes), len(rec.constraints),
                 self.recovered["seconds"], self.epochs.current)  # fmt: skip

    def _persist(self, batch: Batch | None = None) -> None:
        """Write what changed (one transaction) before anything is acked or published."""
        if batch is None:
            batch = self.slam.take_journal()
        batch.origin = self.gnss.new_origin()  # (once set: the map's WGS84 origin)
        self.db.commit(batch)
        self.slam.saved(batch)  # its scans may leave memory now

    # --- wiring -------------------------------------------------------------------------
    def start(self) -> None:
        self.recover()
        self.bus.subscribe(self.keys.all_robots("keyframe"), Keyframe, self._on_keyframe)
        self.bus.subscribe(self.keys.all_robots("state"), RobotState, self._on_state)
        if self.clock.active:
            self.bus.subscribe(self.keys.clock("sim"), ClockSync, self.clock.on_request)
            cmds = self.keys.all_robots("cmd")
            self.bus.subscribe(cmds, VehicleCommand, self.clock.on_command)
            self.bus.watch_alive("sim", self.clock.on_sim_alive)
        self.bus.watch_alive("agent", self._on_agent_alive)
        if self.cfg.basestation.gps.enabled:
            self.bus.subscribe(self.keys.all_robots("sensor/gnss"), GnssFix, self._on_fix)
            self.clock.takes_fixes = True
        self.bus.declare_alive("basestation", "base", unique=True)
        if self.recovered:  # tell agents what is safe, and where their maps are now
            for rid in self.slam.store.robots:
                self._ack(rid)
            self.publish_corrections()

    def _on_fix(self, msg: GnssFix, key: str) -> None:
        self.gnss_inbox.put(msg)
        self.clock.on_fix()

    def _on_keyframe(self, msg: Keyframe, key: str) -> None:
        if not self.roster.unknown(msg.robot_id, "keyframe") and (msg := self._to_segment(msg)):
            self.inbox.put(msg)

    def _on_state(self, msg: RobotState, key: str) -> None:
        """(Zenoh thread) keep it; answer with where the others are (neighbour guard)."""
        if self.roster.unknown(msg.robot_id, "state") or not (msg := self._to_segment(msg)):
            return
        with self._lock:  # (a run before the robot's newest: relayed, not explored for;
            late = msg.status == "stopped" and robot_of(msg.robot_id) not in self._alive
            if msg.robot_id == self.segments.current(robot_of(msg.robot_id)) and not late:
                self.states[msg.robot_id] = msg  # nor a stop that came after its token went)
            answer = self.neighbours.on_state(msg)
        self._send("neighbours", answer)
        store, rid = self.slam.store, msg.robot_id
        if msg.keyframes_acked > 0 and (none := store.none_of(rid, msg.chain, msg.keyframes_acked)):
            self._send("ack", none)  # a new chain
        elif store.acknowledges(rid, msg.chain) and not self.bus.rivals_up:  # (else: theirs)
            self.epochs.seen(msg.correction_epoch)  # another base station's, if above ours

    def _to_segment(self, msg: Any) -> Any:
        """`msg` of an agent as its run's segment's (robot_segments.py; None: no room); a
        new run makes the segment before it past: state forgotten, goal released."""
        segment, past = self.segments.segment(msg.robot_id, msg.session)
        if segment is None:
            return None
        if past is not None:
            self._forget(past)
        return msg if segment == msg.robot_id else dataclasses.replace(msg, robot_id=segment)

    def _forget(self, segment: str, silent: bool = False) -> bool:
        """A segment's state forgotten, its goal released on run()'s thread; `silent`: its token
        went away, the drone may fly on, or hovers if its last state said it stopped (returned)."""
        with self._lock:
            state = self.states.pop(segment, None)
            self.neighbours.forget(segment)
            stopped = state is not None and state.status == "stopped"
            self._lost.append((segment, planar_pose(state) if silent and state else None, stopped))
        return stopped

    def _send(self, topic: str, msg: Any) -> None:
        """Publish `msg` of a segment (its robot_id) to that run of its robot's agent."""
        msg = self.segments.address(msg)
        self.bus.publish(self.keys.robot(msg.robot_id, topic), msg)

    def _on_agent_alive(self, name: str, alive: bool) -> None:
        """Liveliness (Zenoh thread): a lost agent's state is forgotten and its goal
        released on run()'s thread; it gets a new one when it is back."""
        with self._lock:
            ev = self.links.setdefault(name, {"joins": 0, "losses": 0})
            ev["joins" if alive else "losses"] += 1
            (self._alive.add if alive else self._alive.discard)(name)
        if alive:
            log.info("agent %s joined", name)
        elif self._forget(self.segments.current(name), silent=True):  # (a clean stop)
            log.info("agent %s stopped: its goal is released, where it hovers kept clear", name)
        else:
            log.warning("agent %s lost (liveliness token gone): its goal is released, its "
                        "way kept clear", name)  # fmt: skip

    # --- processing ---------------------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        while not stop.is_set():
            self.step(timeout=0.05)

    def step(self, timeout: float = 0.0) -> int:
        """Process one batch of keyframes and verified constraints; returns #admitted.
        In a lock-step simulation: answer the clock's request, if one comes."""
        if self.clock.paced_by_sim():
            stamp = self.clock.wait_request(timeout)
            admitted = 0 if stamp is None else self.sync(stamp)
            self._release_lost()
            self.heap.maybe_trim()
            return admitted
        if self.clock.verify_on_worker(time.monotonic()):
            self.slam.start_verifier()
        limit = self.cfg.basestation.pause_intake_backlog
        if limit and self.slam.backlog() > limit:
            self.intake_pauses += 1
            time.sleep(min(timeout, 0.01))
            admitted = 0
        else:
            self._take_fixes()  # first: a robot's first keyframe may start at its latest fix
            admitted = self._take_batch(timeout)
        if self.slam.integrate_constraints():
            self._optimized()
        self._release_lost()
        now = time.monotonic()
        redraw = self._map_dirty or self.map.pending  # tiles left from a correction
        if redraw and now - self._last_map >= self.cfg.basestation.map_update_period_s:
            self.refresh_map()
            self._last_map = now
        if self.steps and self.clock.wall_paced(now):
            if result := self.steps.done():  # a period after a step's end, the next
                self._send_paths(result)
                self._last_explore = time.monotonic()
            elif not self.steps.busy and now - self._last_explore >= self.cfg.exploration.period_s:
                if inputs := self._step_inputs():
                    self.steps.start(inputs)
        self.heap.maybe_trim()
        return admitted

    def sync(self, stamp: float) -> int:
        """Answer the simulator's clock at sim time `stamp` (basestation/lockstep.py): take
        everything the robots sent up to it, verify, optimize, map and explore, then mark
        each robot's downlink and release the clock; returns #keyframes admitted."""
        with self._lock:
            robots = set(self._alive) if self.roster.ids is None else set(self.roster.ids)
        missing = self.clock.wait_inputs(stamp, robots, self._received, self.cfg.sim.sync_wait_s)
        if missing:
            log.warning("t=%.3f: not all in yet from %s; going on", stamp, ", ".join(missing))
        self._take_fixes()
        batch = self.inbox.take(len(self.inbox) + 1)
        admitted = self.process(sorted(batch, key=lambda kf: (kf.robot_id, kf.seq)))
        budget = self.cfg.basestation.constraints.max_candidates_per_s
        self.slam.verify_pending(budget * self.cfg.base_sync_period_s())
        if self.slam.integrate_constraints():
            self._optimized()
        if self._map_dirty:  # all of it: a wall-time budget would make it depend on the load
            self.map.update(*self.slam.map_keyframes(), budget_s=None)
            self._map_dirty = False
        elif self.map.pending:
            self.map.work(None)
        grid = self.map.gridmap()
        if grid is not None:
            self.map_history.add(stamp, grid)
        self.clock.answered = stamp
        if self.explorer is not None:
            self.explore()
        self.syncs += 1
        for rid in sorted(robots):  # what each robot's current run gets by this answer
            self._send("clock", self.clock.mark(self.segments.current(rid), stamp))
        self.bus.publish(self.keys.clock("basestation"), ClockSync("basestation", stamp))
        return admitted

    def _received(self, rid: str) -> tuple[int, float]:
        """(keyframes of `rid` received, its latest state's stamp), for the clock."""
        rid = self.segments.current(rid)
        r = self.slam.store.robots.get(rid)
        seq = max(self.inbox.highest_seq(rid), -1 if r is None else r.next_seq - 1)
        state = self.states.get(rid)  # one dict read: atomic
        return seq + 1, -1.0 if state is None else state.stamp

    def _release_lost(self, lost: list[tuple[str, Any]] | None = None) -> None:
        """Goals of agents whose liveliness token went away go back to the queue, their
        ways kept clear (`lost`: taken from `_lost` under the lock already)."""
        if lost is None:
            if self.steps and self.steps.busy:
                return  # the explorer is the worker's: released before the next step
            with self._lock:
                lost, self._lost = self._lost, []
        for name, pose, stopped in lost:
            if self.steps:
                self.steps.explorer.release(name, pose, stopped)

    def explore(self) -> None:
        """One exploration step, at once: new paths (map frame) for the robots that need
        one (a step in flight on the worker is finished first)."""
        if self.steps:
            if result := self.steps.done(wait=True):
                self._send_paths(result)
            if inputs := self._step_inputs():
                self._send_paths(self.steps.now(inputs))

    def _step_inputs(self) -> StepInputs | None:
        """(run()'s thread, no step in flight) losses released, unheard starts kept
        clear, and what a step plans from (None: no map yet)."""
        grid = self.map.gridmap(free_thresh=EXPLORATION_FREE_THRESH)
        if grid is None or self.steps is None:
            return None
        with self._lock:  # one lost by now is released first (the step had given its goal away)
            states, alive = dict(self.states), set(map(self.segments.current, self._alive))
            lost, self._lost = self._lost, []
        self._release_lost(lost)
        graph, silent = self.slam.graph, self.steps.explorer.silent
        poses: dict[str, np.ndarray] = {}
        for rid in graph.robots():
            if not graph.is_anchored(rid):
                continue
            if rid in states:
                poses[rid] = planar_pose(states[rid])
            elif rid in alive and rid not in silent:  # no state yet: its newest keyframe
                poses[rid] = graph.pose(rid, graph.latest_index(rid))
        keep_unheard_clear(self.steps.explorer, self.slam.known_starts, {*graph.robots(), *states})
        blocked = {rid for rid, st in states.items() if st.status == "blocked"}
        stamps = {rid: st.stamp for rid, st in states.items()}  # (its state's: real time too)
        return StepInputs(grid, self.map.gridmap(), poses, blocked, stamps, self.epochs.current)

    def _send_paths(self, result: StepResult) -> None:
        """A step's paths: logged, stored, then sent."""
        self._explore_ms.append(result.wall_ms)
        msgs = self.steps.path_messages(result, self._path_id, self.cfg.agent.cruise_altitude_m)
        out = [(rid, pid, encode(self.segments.address(msg))) for rid, pid, msg in msgs]
        self._path_id += len(out)
        self._persist(Batch(paths=out))
        for rid, _, payload in out:
            self.bus.put_raw(self.keys.robot(robot_of(rid), "path"), payload)
            self.clock.sent_path(rid)

    def _take_fixes(self) -> None:
        """GNSS fixes -> ENU at the map's WGS84 origin (`GnssIntake`) -> graph."""
        while True:
            try:
                fix = self.gnss_inbox.get_nowait()
            except queue.Empty:
                return
            if self.roster.unknown(fix.robot_id, "GNSS fix"):
                continue
            fix = dataclasses.replace(fix, robot_id=self.segments.current(fix.robot_id))
            for f, xy in self.gnss.take(fix):
                self.slam.add_gps_fix(f.robot_id, f.stamp, xy, f.sigmas_enu)

    def _take_batch(self, timeout: float) -> int:
        batch = self.inbox.take(self.cfg.basestation.batch_max, timeout)
        return self.process(batch) if batch else 0

    def process(self, batch: list[Keyframe]) -> int:
        touched: set[str] = set()
        admitted = 0
        for kf in batch:  # of known robots (`_on_keyframe`)
            touched.add(kf.robot_id)
            admitted += self.slam.admit(kf)
        if admitted:
            self._optimized()  # persists the batch before any ack below
        for rid in touched:  # ack admitted and duplicate keyframes alike
            self._ack(rid)
        return admitted

    def _ack(self, rid: str) -> None:
        if (ack := self.slam.store.ack(rid)) is not None:
            self._send("ack", ack)

    def _optimized(self) -> None:
        self._persist()
        self.slam.optimize()
        self._map_dirty = True
        self.publish_corrections()
        self.slam.search_constraints()  # new nodes, and nodes of maps just joined

    def publish_corrections(self) -> None:
        epoch = self.epochs.next()
        stamp = time.time()
        for rid in self.slam.graph.robots():
            T = self.slam.T_map_odom(rid)
            if T is None or self.slam.store.robot(rid).foreign or not self.segments.served(rid):
                continue  # (not on the map; another agent's frame; a run gone quiet)
            T7 = pose4_to_pose7([T[0], T[1], 0.0, T[2]])
            self._send("correction", PoseCorrection(rid, epoch, stamp, T7))
            self.clock.sent_correction(rid, epoch)

    def refresh_map(self) -> None:
        """New keyframes into the grid, and up to `map.rerender_budget_s` of redrawing
        the tiles a correction moved (the rest at the next refreshes)."""
        if self._map_dirty:
            self.map.update(*self.slam.map_keyframes())
        else:
            self.map.work(self.cfg.map.rerender_budget_s)
        self._map_dirty = False

    def drain(self, timeout_s: float | None = None) -> None:
        """Process everything already received, and pending verifications."""
        self.clock.sim_gone = True  # the mission is over: what is left is taken as it comes
        timeout_s = self.cfg.basestation.drain_timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            busy = self.step(timeout=0.0) or not self.inbox.empty() or not self.slam.idle()
            if not busy:
                if not self.slam.integrate_constraints():
                    break
                self._optimized()
            time.sleep(0.01)
        if self.slam.graph.flush_gps():  # the last GPS batch, due or not
            self._optimized()
        if self.steps and (result := self.steps.close()):
            self._send_paths(result)
        self.slam.converge()  # the final map and trajectories: the optimum, not a step to it
        self.publish_corrections()
        self.slam.close()
        self._persist()
        self.db.close()

    # --- outputs ------------------------------------------------------------------------
    def stats(self) -> dict[str, Any]:
        return {
            **self.slam.stats(),
            "gnss_fixes_not_enu": self.gnss.ignored,  # the map frame is not ENU: none taken
            "unknown_robot_drops": self.roster.drops,
            "intake_pauses": self.intake_pauses,
            "inbox_drops": self.inbox.drops,  # full inbox: sent again by the agents
            "heap_trims": self.heap.trims,
            "memory_series": self.heap.series_json(),  # after each trim: where the RSS is
            "rejected_messages": dict(self.bus.rejected),
            "other_base_stations": sorted(self.bus.rivals),
            "correction_epoch": self.epochs.current,
            "links": {k: dict(v) for k, v in self.links.items()},
            "persistence": self.db.stats() and {**self.db.stats(), "recovered": self.recovered},
            "exploration": explorer_stats(self.explorer, self._path_id, self._explore_ms),
            "robot_segments": self.segments.stats(),  # robots with more than one
            "robot_runs_refused": self.segments.refused_runs(),  # past the segment limit
            "clock_syncs": self.syncs,
            "clock_input_timeouts": self.clock.input_timeouts,
            **self.map.rerender_stats(),
        }

    def write_outputs(self, out_dir: str | Path) -> None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        self._map_dirty = True
        self.refresh_map()
        while self.map.pending:  # the written map is drawn at the final poses everywhere
            self.map.work(OUTPUT_REDRAW_CHUNK_S)
            self.heap.trim()  # the redraws' freed temporaries, back to the system
        self.heap.trim()  # and a last memory sample, however short the mission was
        trajs, grid = self.slam.trajectories(), self.map.gridmap()
        write_map_outputs(out, trajs, grid, self.slam.graph.is_anchored, self.gnss.origin)
        if len(self.map_history):
            self.map_history.write(out / "map_history.npz")
        (out / "basestation.json").write_text(json.dumps(self.stats(), indent=1))
        log.info("outputs written to %s", out)
