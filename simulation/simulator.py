"""The simulator process: flies every drone of a scenario and publishes its sensors.

Per tick (one laser period, 1/40 s for the UTM-30LX) each quadrotor follows the
last VehicleCommand, and the simulator publishes odometry, IMU, altimeter and
then the laser scan of each drone over Zenoh, exactly as a real drone driver
would. The sim clock runs either
- lock-step: the next tick starts only when every agent has answered this
  tick's scan with a VehicleCommand of the same stamp, and with exploration every
  `exploration.period_s` only when the base station has answered the clock
  (basestation/lockstep.py): results do not depend on how loaded the machine is; or
- real time x `rate`: ticks are paced against the wall clock.
Ground truth is recorded per robot and written as TUM at the end.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from common.bus import Bus
from common.config import Config
from common.errors import ProcessError
from common.geometry import pose4_to_pose7
from common.row_spool import RowSpool
from common.scenario import Scenario
from common.stamps import JumpGate
from common.trajectory_io import Trajectory, write_tum
from protocol import (
    Altimeter,
    ClockSync,
    GnssFix,
    Imu,
    LaserScan,
    Odometry,
    RobotState,
    VehicleCommand,
    encode,
)
from simulation.gnss import GnssModel, world_origin
from simulation.quadrotor import Quadrotor
from simulation.sensors import AltimeterModel, ImuModel, LaserModel, OdometryModel
from simulation.world import World

log = logging.getLogger(__name__)

BASE = "the base station"  # in the set of processes alive (no valid robot id)


# s of sim time: a drone whose agent has answered no tick for this long (or for a tick,
# with a laser slower than 4 Hz) hovers, as a driver must (an agent killed in flight
# had its drone fly on its last command into a wall 5.8 s later, before its restart)
COMMAND_TIMEOUT_S = 0.25


@dataclass
class SimRobot:
    robot_id: str
    vehicle: Quadrotor
    odometry: OdometryModel
    imu: ImuModel
    altimeter: AltimeterModel
    rng: np.random.Generator
    gnss: GnssModel | None = None  # sim.gnss.enabled
    command: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    answered: float = -1.0  # stamp of the last tick this robot's agent answered
    # a command stamped far past the last (one at 1e9 s had every later one dropped as an
    # old answer, and lock-step stopped waiting for the robot)
    command_jump: JumpGate = field(default_factory=JumpGate)
    status: str = "starting"
    state_stamp: float = -1.0  # of the RobotState `status` is from
    state_due: float = -1.0  # of the latest RobotState its agent sent (its command says)
    gt: RowSpool = field(default_factory=lambda: RowSpool(5))  # [t, x, y, z, yaw]
    tick: list[tuple[str, bytes]] = field(default_factory=list)  # the last tick's messages


class Simulator:
    def __init__(
        self, cfg: Config, bus: Bus, scenario: Scenario, world: World, max_sim_time: float
    ) -> None:
        self.cfg = cfg
        self.bus = bus
        self.keys = bus.keys
        self.world = world
        self.max_sim_time = max_sim_time
        s = cfg.sim
        self.laser = LaserModel(
            beams=s.laser.beams,
            fov_rad=np.radians(s.laser.fov_deg),
            range_min=s.laser.range_min_m,
            range_max=s.laser.range_max_m,
            range_noise_std=s.laser.range_noise_std_m,
        )
        self.dt = 1.0 / s.laser.rate_hz
        q = s.quadrotor
        self.robots: dict[str, SimRobot] = {}
        origin = scenario.wgs84_origin or world_origin(world.geo_origin, s.gnss)
        # where the world frame is ENU: the fixes' origin (the ground truth had named the
        # world's while the fixes were made at the scenario's); None: nowhere known
        self.geo_origin = (
            origin if scenario.wgs84_origin or world.geo_origin or s.gnss.enabled else None
        )
        for i, r in enumerate(scenario.robots):
            x, y, yaw = (float(v) for v in r.start_pose)
            self.robots[r.robot_id] = SimRobot(
                robot_id=r.robot_id,
                vehicle=Quadrotor(
                    np.array([x, y, q.altitude_m, yaw]),
                    max_speed=q.max_speed_mps,
                    max_accel=q.max_accel_mps2,
                    max_vertical_speed=q.max_vertical_speed_mps,
                    max_yaw_rate=q.max_yaw_rate_rps,
                    radius=q.radius_m,
                ),
                odometry=OdometryModel(
                    speed_noise_frac=s.odometry.speed_noise_frac,
                    yaw_rate_noise_std=s.odometry.yaw_rate_noise_std,
                    yaw_rate_bias=s.odometry.yaw_rate_bias,
                ),
                imu=ImuModel(
                    gyro_noise_std=s.imu.gyro_noise_std,
                    gyro_bias=s.imu.gyro_bias,
                    accel_noise_std=s.imu.accel_noise_std,
                    accel_bias=s.imu.accel_bias,
                ),
                altimeter=AltimeterModel(
                    noise_std=s.altimeter.noise_std_m, bias=s.altimeter.bias_m
                ),
                rng=np.random.default_rng([s.seed, i]),
                gnss=GnssModel(s.gnss, origin, 1000 * s.seed + i) if s.gnss.enabled else None,
            )
        self.t = 0.0
        self.ticks = 0
        self.republished = 0
        self.wall_s = 0.0
        self.end_reason = ""
        self._cond = threading.Condition()
        self._alive: set[str] = set()
        # lock-step handshake with the base station (exploration decisions in sim time)
        self.sync_period = cfg.base_sync_period_s()
        self._base_clock = -1.0
        self._base_jump = JumpGate()  # an answer far past the clock (1e9 s) is held
        self.base_syncs = 0
        self.gnss_fixes = 0  # published (told to the base station with each clock request)
        self.base_sync_timeouts = 0
        self.late_states = 0  # agents' states taken as lost (lock-step went on without)

    # --- wiring -------------------------------------------------------------------------
    def start(self) -> None:
        for rid in self.robots:
            self.bus.subscribe(self.keys.robot(rid, "cmd"), VehicleCommand, self._on_command)
            self.bus.subscribe(self.keys.robot(rid, "state"), RobotState, self._on_state)
        if self.sync_period:
            self.bus.subscribe(self.keys.clock("basestation"), ClockSync, self._on_base_clock)
        if self.cfg.exploration.enabled:  # real time too: no clock before the base station
            self.bus.watch_alive("basestation", self._on_base_alive)
        self.bus.watch_alive("agent", self._on_alive)
        self.bus.declare_alive("sim", "sim")

    def _on_base_clock(self, msg: ClockSync, key: str) -> None:
        with self._cond:
            if self._base_jump.holds(msg.stamp, max(self._base_clock, 0.0)):
                log.error("base station's clock answer t=%.3f is far past t=%.3f: dropped",
                          msg.stamp, self._base_clock)  # fmt: skip
                return
            self._base_clock = max(self._base_clock, msg.stamp)
            self._cond.notify_all()

    def _on_base_alive(self, name: str, alive: bool) -> None:
        self._on_alive(BASE, alive)

    def _on_alive(self, name: str, alive: bool) -> None:
        with self._cond:
            (self._alive.add if alive else self._alive.discard)(name)
            self._cond.notify_all()

    def _on_command(self, msg: VehicleCommand, key: str) -> None:
        with self._cond:
            r = self.robots[msg.robot_id]
            if msg.stamp < r.answered:
                return  # an old answer to a re-published tick
            if r.command_jump.holds(msg.stamp, max(r.answered, self.t)):
                log.error("robot %s: command stamped %.6g, far past the clock: dropped "
                          "unless the next follows it", msg.robot_id, msg.stamp)  # fmt: skip
                return
            r.command = (msg.vx, msg.vy, msg.vz, msg.yaw_rate)
            r.answered = msg.stamp
            r.state_due = msg.state_stamp
            self._cond.notify_all()

    def _on_state(self, msg: RobotState, key: str) -> None:
        with self._cond:
            r = self.robots[msg.robot_id]
            if msg.stamp >= r.state_stamp and msg.status != "stopped":  # (its agent's last
                r.status, r.state_stamp = msg.status, msg.stamp  # word: `done` stays done)
            self._cond.notify_all()

    def wait_for_agents(self, stop: threading.Event) -> None:
        deadline = time.monotonic() + self.cfg.sim.start_timeout_s
        # with exploration, the base station too: then it has our link and subscriptions,
        # and no sensor message (a GNSS fix it would wait for) goes nowhere
        # (real time too: its clock had started 2.5-14.5 s before the base station heard
        # of the drones, which hovered, and one planned through another's hover point)
        expected = set(self.robots) | ({BASE} if self.cfg.exploration.enabled else set())
        with self._cond:
            while not expected <= self._alive:
                if stop.is_set():
                    return
                if time.monotonic() > deadline:
                    missing = sorted(expected - self._alive)
                    raise ProcessError(f"never came alive: {', '.join(missing)}")
                self._cond.wait(0.1)
        log.info("all %d agents alive: starting the %s clock", len(self.robots), self.cfg.sim.clock)

    # --- the clock ----------------------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        self.wait_for_agents(stop)
        lockstep = self.cfg.sim.clock == "lockstep"
        t_wall0 = time.monotonic()
        gt_period = 1.0 / self.cfg.sim.ground_truth_rate_hz
        next_gt = 0.0
        next_sync = 0.0  # the first handshake at t = 0: every robot's first path then
        self._publish_tick(0.0)
        for r in self.robots.values():
            self._record(r, 0.0)
        while not stop.is_set():
            if lockstep:
                self._wait_answers(stop)
                if self.sync_period and self.t >= next_sync - 1e-9:
                    next_sync += self.sync_period
                    if self._wait_basestation(stop):
                        self._tell_agents(self.t)
            else:
                delay = t_wall0 + self.t / self.cfg.sim.rate - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            if self.t >= self.max_sim_time - 1e-9:
                self.end_reason = "max_sim_time"
                break
            if all(r.status == "done" for r in self.robots.values()):
                self.end_reason = "robots_done"  # tours flown, or exploration over
                break
            self.ticks += 1
            self.t = self.ticks * self.dt
            self._step_physics()
            if self.t >= next_gt - 1e-9:
                next_gt += gt_period
                for r in self.robots.values():
                    self._record(r, self.t)
            self._publish_tick(self.t)
        if stop.is_set():
            self.end_reason = self.end_reason or "interrupted"
        self.wall_s = time.monotonic() - t_wall0
        log.info(
            "simulation ended at t=%.1f s (%s) after %.1f s wall (%.1fx real time)",
            self.t,
            self.end_reason,
            self.wall_s,
            self.t / max(self.wall_s, 1e-9),
        )

    def _wait_answers(self, stop: threading.Event) -> None:
        timeout = self.cfg.sim.lockstep_timeout_s
        with self._cond:
            while not stop.is_set():
                # the state a command says came before it too (another key: no order)
                late = [
                    r
                    for r in self.robots.values()
                    if r.answered < self.t or r.state_stamp < r.state_due
                ]
                if not late:
                    return
                if not self._cond.wait(timeout):
                    self._late(late)

    def _late(self, late: list[SimRobot]) -> None:
        """Re-publish the tick to agents that have not answered it; a state that has not
        come in time is taken as lost (an agent sends it once)."""
        silent = [r.robot_id for r in late if r.answered < self.t]
        if silent:  # one line for all (a cold start's compiling had made 3 a wait)
            log.warning("t=%.3f: no command yet from %s; re-publishing the tick", self.t,
                        ", ".join(silent))  # fmt: skip
        for r in late:
            if r.answered >= self.t:
                log.warning(
                    "t=%.3f: %s's state of t=%.3f never came", self.t, r.robot_id, r.state_due
                )
                r.state_stamp = r.state_due
                self.late_states += 1
                continue
            self.republished += 1
            gnss = self.keys.sensor(r.robot_id, "gnss")  # (the base station has it: sent
            for key, payload in r.tick:  # again, it had counted 4 times in the graph)
                if key != gnss:  # the same messages: measuring again would draw noise
                    self.bus.put_raw(key, payload)

    def _wait_basestation(self, stop: threading.Event) -> bool:
        """Hold the clock at `self.t` until the base station has answered it (True)."""
        self.base_syncs += 1
        deadline = time.monotonic() + self.cfg.sim.basestation_timeout_s
        request = ClockSync("sim", self.t, self.gnss_fixes)
        with self._cond:
            while not stop.is_set() and self._base_clock < self.t - 1e-9:
                if time.monotonic() > deadline:
                    self.base_sync_timeouts += 1
                    log.warning("t=%.3f: no answer from the base station; going on (a base "
                                "station started by hand needs --lockstep, or run the sim "
                                "with --set sim.clock=realtime)", self.t)  # fmt: skip
                    return False
                self.bus.publish(self.keys.clock("sim"), request)  # again if it was missed
                self._cond.wait(self.cfg.sim.lockstep_timeout_s)
        return not stop.is_set()

    def _tell_agents(self, t: float) -> None:
        """Before the next tick (on a sensor key: one subscriber keeps them in order): the
        base station answered `t`, so each agent waits for what it sent by then."""
        msg = ClockSync("sim", t)
        for rid in self.robots:
            self.bus.publish(self.keys.sensor(rid, "clock"), msg)

    def _step_physics(self) -> None:
        for r in self.robots.values():
            with self._cond:  # no answer for COMMAND_TIMEOUT_S (its agent dead): hover
                late = self.t - r.answered > max(COMMAND_TIMEOUT_S, self.dt) + 1e-9
                cmd = (0.0, 0.0, 0.0, 0.0) if late else r.command
            r.vehicle.step(np.asarray(cmd), self.dt, self.world)
            r.odometry.step(r.vehicle.velocity_body, r.vehicle.yaw_rate, self.dt, r.rng)

    def _record(self, r: SimRobot, t: float) -> None:
        r.gt.append([t, *r.vehicle.pose])

    def _publish_tick(self, t: float) -> None:
        for r in self.robots.values():
            self._publish_sensors(r, t)

    def _publish_sensors(self, r: SimRobot, t: float) -> None:
        v, rid, keys = r.vehicle, r.robot_id, self.keys
        odo = r.odometry
        msgs: list[tuple[str, Any]] = [
            (
                keys.sensor(rid, "odom"),
                Odometry(rid, t, pose4_to_pose7(odo.pose), np.asarray(odo.twist)),
            )
        ]
        w, a, q = r.imu.measure(
            v.angular_velocity_body, v.accel_body, v.roll, v.pitch, float(v.pose[3]), r.rng
        )
        msgs.append((keys.sensor(rid, "imu"), Imu(rid, t, w, a, q)))
        alt = float(r.altimeter.measure(float(v.pose[2]), r.rng))
        msgs.append((keys.sensor(rid, "altimeter"), Altimeter(rid, t, alt)))
        fix = r.gnss.measure(t, v.pose[:3]) if r.gnss is not None else None
        if fix is not None:  # world frame = ENU at the world's origin; antenna at the body
            self.gnss_fixes += 1
            msgs.append((keys.sensor(rid, "gnss"), GnssFix(rid, t, fix.lla, fix.sigmas_enu)))
        pose = v.pose
        ranges = self.laser.measure(
            self.world, np.array([pose[0], pose[1], pose[3]]), r.rng, v.roll, v.pitch, pose[2]
        )
        angles = self.laser.angles
        scan = LaserScan(
            rid,
            t,
            float(angles[0]),
            float(angles[1] - angles[0]),
            self.laser.range_min,
            self.laser.range_max,
            ranges,
        )
        msgs.append((keys.sensor(rid, "scan"), scan))
        r.tick = [(key, encode(msg)) for key, msg in msgs]
        for key, payload in r.tick:
            self.bus.put_raw(key, payload)

    # --- outputs ------------------------------------------------------------------------
    def stats(self) -> dict[str, Any]:
        return {
            "sim_time_s": self.t,
            "wall_time_s": self.wall_s,
            "realtime_factor": self.t / max(self.wall_s, 1e-9),
            "ticks": self.ticks,
            "republished_ticks": self.republished,
            "basestation_syncs": self.base_syncs,
            "basestation_sync_timeouts": self.base_sync_timeouts,
            "late_states": self.late_states,
            "end_reason": self.end_reason,
            "robots": {
                rid: {
                    "distance_m": r.vehicle.distance_travelled,
                    "collisions": r.vehicle.collisions,
                    "min_clearance_m": r.vehicle.min_clearance,
                    "status": r.status,
                }
                for rid, r in self.robots.items()
            },
        }

    def write_outputs(self, out_dir: str | Path) -> None:
        out = Path(out_dir)
        for rid, r in self.robots.items():
            gt = r.gt.rows()
            write_tum(
                out / "ground_truth" / f"{rid}.tum",
                Trajectory.from_pose4(gt[:, 0], gt[:, 1:5]),
                wgs84_origin=self.geo_origin,  # the world frame is ENU there
            )
        (out / "simulator.json").write_text(json.dumps(self.stats(), indent=1))


__all__ = ["Simulator"]
