"""The agent process: one per drone.

Subscribes to its own drone's sensors, keeps the local pose (T_odom_base),
cuts keyframes and streams them through the outbox, applies the base
station's corrections (T_map_odom), flies its tour, and answers every laser
scan with a VehicleCommand (the simulator's lock-step handshake).

Threads: Zenoh callbacks only enqueue sensor messages or update the outbox /
correction under locks; all SLAM and control runs on the thread calling `run()`.

Every scan is a control tick: the agent publishes a ControlPose on
`robot/<id>/pose/control` whose `pose_map` blends each new correction in over
~7 s (`pose_smoother.py`, seed 000 §II). Path following keeps using the latest
raw correction to place map-frame paths in `odom` (seed 002 eq. 4).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from agent.control_log import ControlRecorder
from agent.downlink_gate import DownlinkGate
from agent.fresh_start import FreshStart, nearest_waypoint
from agent.keyframe_selector import KeyframeSelector
from agent.local_trajectory_builder import LocalSlamResult, LocalTrajectoryBuilder
from agent.odometry_tracker import OdometryTracker
from agent.outputs import frontend_stats, write_agent_outputs
from agent.path_follower import PathFollower
from agent.pose_smoother import IDENTITY7, PoseSmoother, pose7_compose
from agent.resume import STATE_FILE, ResumePoint, load, save
from agent.safety_guard import SafetyGuard, neighbours_in_body
from agent.sensor_sources import SensorSource
from agent.uplink import KeyframeUplink
from agent.vehicle import NullVehicle, ZenohVehicle
from common.bus import Bus
from common.config import Config
from common.geometry import map_to_odom, odom_to_map, pose4_to_pose7, pose7_to_pose4
from common.memory import HeapTrimmer
from common.metrics import percentiles
from common.row_spool import RowSpool
from common.stamps import MAX_EPOCH_JUMP, STAMP_SLACK_S, BackStepRepair, JumpGate, ScanRepeats, due
from protocol import (
    Altimeter,
    ClockSync,
    ControlPose,
    DownlinkMark,
    Imu,
    KeyframeAck,
    LaserScan,
    Neighbours,
    Odometry,
    PoseCorrection,
    RobotState,
    Scan2D,
)
from protocol import Path as PathMsg

log = logging.getLogger(__name__)

# The odometry's twist steers the guard's braking while it is at most this old (s).
TWIST_MAX_AGE_S = 0.25
# An altimeter reading older than this (s) gives no vertical speed, as none does: one that
# stopped during the take-off had the drone climb on at 0.5 m/s for good.
ALTITUDE_MAX_AGE_S = 0.5


class AgentNode:
    def __init__(
        self,
        cfg: Config,
        robot_id: str,
        bus: Bus,
        tour_map: np.ndarray,
        T_map_odom: np.ndarray | None = None,
        vehicle: ZenohVehicle | NullVehicle | None = None,
    ) -> None:
        """tour_map: (M, 2) waypoints in `map`; T_map_odom: [x, y, z, yaw] known at start;
        vehicle: where commands go (default: VehicleCommand over Zenoh)."""
        self.cfg = cfg
        self.robot_id = robot_id
        self.bus = bus
        self.keys = bus.keys
        self.vehicle = vehicle if vehicle is not None else ZenohVehicle(bus, robot_id)
        a = cfg.agent
        self.frontend: LocalTrajectoryBuilder | OdometryTracker = (
            LocalTrajectoryBuilder(a.local_slam, a.local_keyframe_period_s)
            if a.local_slam.enabled
            else OdometryTracker()
        )
        self.selector = KeyframeSelector(a)
        self.heap = HeapTrimmer()
        self.state_dir = Path(a.state_dir) if a.state_dir else None  # agent/resume.py
        self.resumed = resume = load(self.state_dir, a.resume_within_s) if self.state_dir else None
        self.uplink = KeyframeUplink(a, robot_id, bus, resume)
        if resume is not None and resume.T_map_odom is not None:
            T_map_odom = np.array(resume.T_map_odom)  # not the start pose: on the way
        self.outbox = self.uplink.outbox
        self.follower = PathFollower.from_config(a)
        self.guard = SafetyGuard.from_config(a, cfg.exploration.enabled)
        self.source_stats: Callable[[], dict[str, Any]] = dict  # the sensor source's counts
        # the base station's relays, the latest and the one before (see `_command`)
        self._neighbours: list[Neighbours] = []
        self.downlink = DownlinkGate(cfg.sim.sync_wait_s, resumed=resume is not None)
        self._twist: tuple[float, np.ndarray] | None = None  # odometry's (stamp, vx vy)
        self._altitude_stamp = -np.inf  # the altimeter's latest reading's
        self._on_map = T_map_odom is not None  # its map pose is known (start or correction)
        self._news_ages: deque[float] = deque(maxlen=20000)  # s, the relay's answer at use
        self.tour_map = np.asarray(tour_map, dtype=np.float64).reshape(-1, 2)
        self._corr_lock = threading.Lock()
        self.T_map_odom = np.zeros(4) if T_map_odom is None else np.asarray(T_map_odom, float)
        self.epoch = -1
        # an epoch far past the last is held until the next follows it (one of 2^63 had
        # every later correction ignored)
        self._epoch_jump = JumpGate(MAX_EPOCH_JUMP)
        # Control pose (main thread only); corrections reach it on the next scan.
        self.smoother = PoseSmoother(
            a.smoothing, None if T_map_odom is None else pose4_to_pose7(self.T_map_odom)
        )
        self._smoother_pending: np.ndarray | None = None  # pose7 not yet given to it
        self.control_log = ControlRecorder()
        self._new_correction = True
        self._new_path = False
        self.exploring = cfg.exploration.enabled
        self.mission_over = False
        self.clock = BackStepRepair()  # sensor stamps, across a step back of their clock
        self.last_scan_stamp: float | None = None
        self.repeats = ScanRepeats()  # a scan stamped like the last one used
        self.last_state_stamp = -np.inf
        self.scans = 0
        self.local_trajectory = RowSpool(5)  # every scan: stamp, T_odom_base [x y z yaw]
        self.base_links = {"joins": 0, "losses": 0}  # base-station liveliness events
        self._base_up = threading.Event()
        self._bases: set[str] = set()  # base-station tokens up (one, unless misconfigured)
        self.fresh = FreshStart.of(resume)  # where its odom frame begins
        if resume is not None:
            self._take_up(resume)

    def _take_up(self, r: ResumePoint) -> None:
        """Go on where an agent before this one was (agent/resume.py): local SLAM from
        its last pose by the odometry since, its next keyframe from its last one, the
        same sensor clock offset, correction epoch and path (at the same waypoint)."""
        if r.pose_odom is not None and r.stamp is not None:
            self.frontend.resume(r.stamp, np.array(r.pose_odom), r.odometry)
            self.clock.offset, self.clock.latest = r.clock_offset, r.stamp
        last = self.uplink.last_pose if self.uplink.last_pose is not None else r.keyframe_pose
        self.selector.last_pose = None if last is None else np.array(last, dtype=np.float64)
        self.epoch = r.epoch if self.uplink.chain == r.chain else -1  # (a new base station)
        if r.path is not None:
            self.tour_map = np.array(r.path, dtype=np.float64).reshape(-1, 2)
            self.follower.index = r.path_index

    def _hold_for_placement(self, stamp: float) -> bool:
        """A fresh agent found in flight (agent/fresh_start.py) hovers until the base
        station's first correction places it, `PLACEMENT_WAIT_S` at most (then its start pose
        composed with the odometry's), then flies on from its tour's nearest waypoint."""
        with self._corr_lock:  # (a placement come since this tick's control pose: the
            # next tick's takes it at once, then it flies on)
            if self._smoother_pending is not None or (
                self.epoch < 0 and not self.fresh.waited(stamp)
            ):
                return True
            if self.epoch < 0:  # no base station: its own guess
                self.T_map_odom = T = self.fresh.start_in_map(self.T_map_odom)
                self.smoother = PoseSmoother(self.cfg.agent.smoothing, pose4_to_pose7(T))
                self._new_correction = True  # the path again, in the new frame
            here = odom_to_map(self.T_map_odom, self.frontend.pose)[:2]
        self.follower.index, self.fresh.placed = nearest_waypoint(self.tour_map, here), True
        return False

    # --- wiring -------------------------------------------------------------------------
    def start(self, await_base: bool = False) -> None:
        """Declare subscriptions, then the liveliness token (so the token implies routes).
        The sensor source must be created before this (its subscriptions count too)."""
        rid, mine = self.robot_id, self.uplink.mine  # what is sent to this agent's session
        for topic, kind, on in (
            ("ack", KeyframeAck, self._on_ack), ("correction", PoseCorrection, self._on_correction),
            ("path", PathMsg, self._on_path), ("neighbours", Neighbours, self._on_neighbours),
            ("clock", DownlinkMark, self.downlink.on_mark),
        ):  # fmt: skip
            self.bus.subscribe(self.keys.robot(rid, topic), kind, mine(on))
        self.bus.watch_alive("basestation", self._on_base_alive)
        if await_base:  # a simulator's: its first messages count too (a live one: no
            self._await_base(self.cfg.sim.sync_wait_s)  # 10 s wait out of radio range)
        self.bus.declare_alive("agent", rid)

    def _await_base(self, timeout_s: float) -> None:
        """Wait (at most `timeout_s`) for the base station's token: it comes after the base
        station's subscriptions on the same link, so then a state or command sent reaches
        it (a lock-step simulator starts its clock when every agent's token is up)."""
        if not self._base_up.wait(timeout_s):
            log.warning("no base station after %.0f s: starting without it", timeout_s)

    def _on_base_alive(self, name: str, alive: bool) -> None:
        """Base-station liveliness (Zenoh thread). Gone: keep flying on local SLAM."""
        self.base_links["joins" if alive else "losses"] += 1
        (self._bases.add if alive else self._bases.discard)(name)
        (self._base_up.set if self._bases else self._base_up.clear)()
        if alive and len(self._bases) > 1:  # each would take keyframes the other misses
            log.error("%d base stations are up (%s): run one per fleet (a restarted one's "
                      "token lingers for Zenoh's lease, 10 s)", len(self._bases),
                      ", ".join(sorted(self._bases)))  # fmt: skip
        self.uplink.on_base_alive(name, alive, again=self.base_links["joins"] > 1)

    def _on_ack(self, msg: KeyframeAck, key: str) -> None:
        if msg.acked_seq >= 0 or len(self._bases) < 2:  # -1 from one of two: no new chain
            self.uplink.on_ack(msg)

    def _on_correction(self, msg: PoseCorrection, key: str) -> None:
        with self._corr_lock:
            if self._epoch_jump.holds(msg.epoch, max(self.epoch, 0)):
                log.error("correction epoch %d is far past the last %d: dropped unless the "
                          "next follows it", msg.epoch, self.epoch)  # fmt: skip
                return
            if msg.epoch > self.epoch:
                self.epoch = msg.epoch
                self.T_map_odom = pose7_to_pose4(msg.T_map_odom)
                self._on_map = True
                self._smoother_pending = np.array(msg.T_map_odom, dtype=np.float64)
                self._new_correction = True
        self.downlink.on_correction(msg.epoch)  # taken: a held tick may go on

    def _on_neighbours(self, msg: Neighbours, key: str) -> None:
        if msg.stamp > self.last_state_stamp + STAMP_SLACK_S:  # 1e9 s had frozen them
            log.error("neighbours answering a state of t=%.3f, not sent yet (last t=%.3f): "
                      "dropped", msg.stamp, self.last_state_stamp)  # fmt: skip
            return
        with self._corr_lock:
            if not self._neighbours or msg.stamp >= self._neighbours[-1].stamp:
                self._neighbours = [*self._neighbours[-1:], msg]
        self.downlink.on_neighbours(msg.stamp)

    def _on_path(self, msg: PathMsg, key: str) -> None:
        """A new path from the base station (exploration); empty: stop here."""
        with self._corr_lock:
            wp = np.asarray(msg.waypoints, dtype=np.float64).reshape(-1, 4)
            if msg.frame == "odom":  # keep it in map: corrections re-place it (eq. 4)
                wp = odom_to_map(self.T_map_odom, wp)
            self.tour_map = wp[:, :2]
            self._new_path = True
            self.guard.clear()
            self.mission_over = len(wp) == 0 and msg.path_id == 0
        self.downlink.on_path()

    # --- main loop ----------------------------------------------------------------------
    def run(
        self, source: SensorSource, stop: threading.Event, max_unacked: int | None = None
    ) -> None:
        """Process the source's messages until it ends or `stop` is set.

        `max_unacked`: flow control for sources that can run ahead of the base
        station (a log replay): wait while this many keyframes are unacknowledged.
        """
        self.source_stats = getattr(source, "stats", dict)
        for msg in source.messages(stop):
            if msg is not None:
                self.handle(msg)
            self._resend()
            self.heap.maybe_trim()
            while max_unacked is not None and len(self.outbox) > max_unacked and not stop.is_set():
                time.sleep(0.01)
                self._resend()

    def handle(self, msg: Any) -> None:
        if isinstance(msg, (Odometry, Imu, Altimeter, LaserScan)) and not (
            msg := self.clock.take(msg)
        ):
            return
        if isinstance(msg, Odometry):
            self.frontend.add_odometry(msg.stamp, pose7_to_pose4(msg.pose)[[0, 1, 3]])
            self._twist = (msg.stamp, np.asarray(msg.twist[:2], dtype=np.float64))
        elif isinstance(msg, Imu):
            self.frontend.add_imu(msg.stamp, msg.orientation)
        elif isinstance(msg, Altimeter):
            self.frontend.add_altitude(msg.stamp, msg.altitude)
            self._altitude_stamp = msg.stamp
        elif isinstance(msg, LaserScan):
            self.on_scan(msg)
        elif isinstance(msg, ClockSync):  # a lock-step simulator's, before its next tick
            self.downlink.on_clock(msg.stamp)

    def on_scan(self, scan: LaserScan) -> None:
        if repeat := self.repeats.check(scan.stamp, scan.ranges):  # answered again; or not
            self._command(scan.stamp, hover=repeat == "stale")  # used: from no new pose
            return
        self.downlink.wait()  # lock-step: the base station's paths and answers for it
        angles = scan.angle_min + scan.angle_increment * np.arange(len(scan.ranges))
        self.guard.update(angles, np.asarray(scan.ranges, dtype=np.float64), scan.range_min)
        result = self.frontend.add_scan(scan)
        if result is None:  # rejected (time going back, an odometry jump): logged there
            self._command(scan.stamp, hover=True)  # its pose was not updated: none stale
            return
        self.last_scan_stamp = scan.stamp
        self.repeats.used(scan.stamp, scan.ranges)
        self.scans += 1
        self.local_trajectory.append([scan.stamp, *result.pose])
        if not self.fresh.settled:  # a fresh agent's start (agent/fresh_start.py)
            odometry, altitude = self.frontend.odometry_at(scan.stamp), self.frontend.altitude
            self.fresh.take(scan.stamp, odometry, altitude, result.pose)
        self._publish_control_pose(scan.stamp, result.pose)
        if self.fresh.begun and self.selector.is_due(result.pose) and self.outbox.has_room():
            self._send_keyframe(scan, result)
        # the state before the command: in lock-step the command releases the clock, and
        # the base station's exploration step at this stamp must see where the drone is
        # now, not 0.5 s ago (0.5 m) (`due` has a rounding slack: lock-step stamps are
        # ticks x dt, and 0.4 - 0.2 < 0.2 had slipped the states off the base station's
        # sync stamps, to 0.825 s at the step of 1.0 s)
        if due(scan.stamp, self.last_state_stamp, self.cfg.agent.state_period_s):
            self.last_state_stamp = scan.stamp
            self._take_path()  # the state's status reflects a path that just came
            self.publish_state(scan.stamp)
            self.downlink.state_sent(scan.stamp)
            self._save_state(scan.stamp)  # hovering, it cuts no keyframes: still fresh
        self._command(scan.stamp)

    def _send_keyframe(self, scan: LaserScan, result: LocalSlamResult) -> None:
        pose, last = result.pose, self.selector.last_pose
        delta, cov = self.selector.cut(pose, result.covariance)
        scan2d = Scan2D.from_ranges(scan.angle_min, scan.angle_increment, scan.range_max,
                                    self.frontend.keyframe_ranges(scan),  # without the floor
                                    scan.range_min)  # fmt: skip
        sent = self.uplink.send(
            stamp=scan.stamp,
            pose_odom=pose4_to_pose7(pose),
            delta=pose4_to_pose7(delta),
            delta_cov=cov,
            scan2d=scan2d,
            odom_origin=self.fresh.now(self.frontend.odometry_at(scan.stamp), pose),
        )
        if not sent:  # refused (an altimeter's 1e9 m once): the next spans from the last sent
            self.selector.last_pose = last
        else:
            self._save_state(scan.stamp)

    def _save_state(self, stamp: float) -> None:
        """Where this agent is now, for one restarted on its state folder (resume.py)."""
        if self.state_dir is None or self.selector.last_pose is None:
            return
        if not self.outbox.history.max_keyframes:  # off (a disk error): nothing to resume
            return (self.state_dir / STATE_FILE).unlink(missing_ok=True)
        with self._corr_lock:
            epoch, T = self.epoch, self.T_map_odom.tolist() if self._on_map else None
            path, index = self.tour_map.tolist(), 0 if self._new_path else self.follower.index
        odom = self.frontend.odometry_at(stamp)
        up, kf = self.uplink, self.selector.last_pose.tolist()
        point = ResumePoint(up.chain, up.next_seq, up.outbox.acked_seq, epoch, T, stamp,
                            self.frontend.pose.tolist(), None if odom is None else odom.tolist(),
                            path, index, kf, self.clock.offset, up.session,
                            self.fresh.as_list())  # fmt: skip
        save(self.state_dir, point)

    def _publish_control_pose(self, stamp: float, pose_odom: np.ndarray) -> None:
        """One control tick at sensor time `stamp`: the smoothed and raw T_map_base."""
        with self._corr_lock:
            pending, self._smoother_pending = self._smoother_pending, None
            epoch = self.epoch
        if pending is not None and self.fresh.in_flight and not self.fresh.placed:
            self.smoother = PoseSmoother(self.cfg.agent.smoothing, pending)  # its placement
        elif pending is not None:  # (a start pose known wrong: nothing to blend from)
            self.smoother.on_correction(pending, stamp)
        T_odom_base = pose4_to_pose7(pose_odom)
        raw = self.smoother.target if self.smoother.target is not None else np.array(IDENTITY7)
        applied = self.smoother.applied(stamp)
        self.control_log.add(stamp, T_odom_base, raw, applied)
        self.bus.publish(
            self.keys.robot(self.robot_id, "pose/control"),
            ControlPose(
                robot_id=self.robot_id,
                stamp=stamp,
                epoch=epoch,
                alpha=self.smoother.alpha(stamp),
                pose_odom=T_odom_base,
                pose_map=pose7_compose(applied, T_odom_base),
                pose_map_raw=pose7_compose(raw, T_odom_base),
            ),
            reliable=False,  # a controller wants the newest pose, never a queue
        )

    def _take_path(self) -> None:
        """Hand the follower a new path, or its path re-placed by a new correction."""
        with self._corr_lock:
            if self._new_correction or self._new_path:
                pts = np.column_stack([self.tour_map, np.zeros((len(self.tour_map), 2))])
                tour_odom = map_to_odom(self.T_map_odom, pts) if len(pts) else pts
                # (a late path, or one a correction moved, caught up: not a scripted tour's
                # sparse waypoints, whose first may lie far from the start)
                here = self.frontend.pose[:2] if self._new_path or self.exploring else None
                self.follower.set_path(tour_odom[:, :2], not self._new_path, here)
                self._new_correction = self._new_path = False

    def _command(self, stamp: float, hover: bool = False) -> None:
        """The vehicle command for the scan at `stamp`; `hover`: no new pose (a scan not
        used): none from a stale one, the drone had flown on blind 16 m."""
        self._take_path()
        with self._corr_lock:
            # only answers to states before this tick: the answer to the state just sent
            # may be in by now or not (a race that made lock-step runs differ)
            earlier = [n for n in self._neighbours if n.stamp < stamp]
            nb = earlier[-1] if earlier and self._on_map else None
            T_map_odom = self.T_map_odom.copy()
        if nb is not None:
            a = self.cfg.agent
            self._news_ages.append(stamp - nb.stamp)
            here = odom_to_map(T_map_odom, self.frontend.pose)
            self.guard.set_neighbours(neighbours_in_body(
                nb.stamps, nb.xy, nb.velocity, stamp, here, a.neighbour_max_age_s,
                a.neighbour_extrapolation_s,
            ))  # fmt: skip
        z_known = abs(stamp - self._altitude_stamp) <= ALTITUDE_MAX_AGE_S  # (else it climbed)
        vx, vy, vz, yaw_rate = self.follower.command(self.frontend.pose, z_known)
        held = self.fresh.in_flight and not self.fresh.placed and self._hold_for_placement(stamp)
        if held or hover:  # where it is in map is not known yet, or no new pose: it hovers
            vx = vy = vz = yaw_rate = 0.0
        moving = self._twist  # the guard brakes along it (a turn lags the command)
        fresh = moving is not None and abs(stamp - moving[0]) <= TWIST_MAX_AGE_S
        vx, vy = self.guard.limit(stamp, vx, vy, velocity=moving[1] if fresh else None)
        sent = (self.uplink.next_seq, max(self.last_state_stamp, -1.0))  # lock-step base
        self.vehicle.command(stamp, vx, vy, vz, yaw_rate, *sent)

    def _resend(self) -> None:
        if self.uplink.resend():  # a new chain, for a base station with a new database
            with self._corr_lock:
                self.epoch = -1  # which numbers its corrections from 0 again
            if self.last_scan_stamp is not None:
                self._save_state(self.last_scan_stamp)

    def status(self) -> str:
        if self.scans == 0:
            return "starting"
        if not self.follower.done:
            return "blocked" if self.guard.blocked else "flying"
        if self.exploring and not self.mission_over:
            return "waiting"  # for its next path from the base station
        return "done"

    def publish_state(self, stamp: float, status: str | None = None) -> None:
        with self._corr_lock:
            T_map_odom, epoch = self.T_map_odom.copy(), self.epoch
        pose = self.frontend.pose
        self.bus.publish(
            self.keys.robot(self.robot_id, "state"),
            RobotState(
                robot_id=self.robot_id,
                stamp=stamp,
                status=status or self.status(),
                correction_epoch=epoch,
                keyframes_sent=self.uplink.next_seq,
                keyframes_acked=self.outbox.acked_seq + 1,
                chain=self.uplink.chain,
                session=self.uplink.session,
                outbox_len=len(self.outbox),
                pose_odom=pose4_to_pose7(pose),
                pose_map=pose4_to_pose7(odom_to_map(T_map_odom, pose)),
            ),
        )

    # --- shutdown -----------------------------------------------------------------------
    def drain(self, timeout_s: float) -> bool:
        """Resend until every keyframe is acknowledged or the timeout passes."""
        return self.uplink.drain(timeout_s)

    def forget_state(self) -> None:
        """Delete the state folder's state and keyframes: an agent stopped (not dead)
        with all acknowledged is not taken up by the next one (another mission's)."""
        if self.state_dir is not None:
            self.outbox.history.clear()
            (self.state_dir / STATE_FILE).unlink(missing_ok=True)

    def stats(self) -> dict[str, Any]:
        return {
            "robot_id": self.robot_id,
            **self.uplink.stats(),
            "base_station_links": dict(self.base_links),
            "lockstep_downlink_waits": self.downlink.waits,
            "lockstep_downlink_timeouts": self.downlink.timeouts,
            "scans": self.scans,
            **self.clock.stats(),
            "scans_stale_stamp": self.repeats.stale,
            **self.source_stats(),
            **frontend_stats(self.frontend),
            **self.guard.stats(),
            # sim time since the state the neighbours' relay answered (the latest ticks)
            **percentiles("neighbour_news_age_s", self._news_ages),
            "correction_epoch": self.epoch,
            "smoothing_restarts": self.smoother.restarts,
            "rejected_messages": dict(self.bus.rejected),
        }

    def write_outputs(self, out_dir: str | Path) -> None:
        write_agent_outputs(Path(out_dir), self.robot_id, self.stats(), self.local_trajectory,
                            self.control_log)  # fmt: skip
