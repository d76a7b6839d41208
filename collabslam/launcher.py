"""`collabslam run`: the simulator, the base station and N agents as separate OS
processes on loopback Zenoh, supervised.

Order: base station (listens), simulator (listens, connects to the base),
agents (connect to both). The simulator ends the mission (max sim time or all
tours done); then agents get SIGINT and drain their outboxes, then the base
station gets SIGINT and writes the map and trajectories. A child that dies
early is named and the run stops with a ProcessError. Ctrl-C stops everything
gracefully (a second Ctrl-C kills).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import signal
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from collabslam.supervisor import (
    Child,
    ProcessGroup,
    clear_run_outputs,
    delete_database,
    free_port,
)
from common.bus import endpoint
from common.config import Config, dump_config
from common.errors import ConfigError, ProcessError
from common.scenario import RobotScenario, Scenario, write_scenario
from simulation.gnss import world_origin
from simulation.tours import plan_tours, spread_start_poses, start_poses
from simulation.world import World, resolve_world

log = logging.getLogger(__name__)


def agent_command(
    common: list[str], robot_id: str, *connect: str, await_base: bool = False
) -> list[str]:
    """`collabslam agent` arguments for one robot (`common`: --config/--out/... options)
    connecting to each of the `connect` endpoints; `await_base`: an exploring simulator's
    (it waits for the base station before starting)."""
    return [
        "agent",
        *common,
        "--robot-id",
        robot_id,
        *(a for ep in connect for a in ("--connect", ep)),
        *(["--await-base"] if await_base else []),
    ]


def make_scenario(cfg: Config, world_yaml: Path, n_robots: int) -> Scenario:
    world = World.load(str(world_yaml))
    if cfg.sim.start_apart:
        starts = spread_start_poses(world, n_robots, seed=cfg.sim.seed)
    else:
        starts = start_poses(world, n_robots, seed=cfg.sim.seed, spacing=cfg.sim.start_spacing_m)
    if cfg.exploration.enabled:  # the base station sends the paths
        tours = [np.zeros((0, 2)) for _ in range(n_robots)]
    else:
        tours = plan_tours(world, starts, seed=cfg.sim.seed, length_m=cfg.sim.tour_length_m)
    robots = [RobotScenario(f"r{i}", starts[i], tours[i]) for i in range(n_robots)]
    return Scenario(str(world_yaml.resolve()), robots, cfg.sim.seed)


def with_gnss_origin(cfg: Config, scenario: Scenario) -> Scenario:
    """`scenario` with the WGS84 origin its simulator makes GNSS fixes at (the world's,
    else `sim.gnss.origin_*`): the base station then puts `map` there too. It had taken
    the median of the first fixes, ~13 m off, for a world without one (ATE 0.023 ->
    0.063 m)."""
    if scenario.wgs84_origin is not None or not cfg.sim.gnss.enabled:
        return scenario
    world = World.load(scenario.world)
    return dataclasses.replace(scenario, wgs84_origin=world_origin(world.geo_origin, cfg.sim.gnss))


class Launcher:
    def __init__(
        self,
        cfg: Config,
        world: str,
        n_robots: int,
        out: Path,
        max_sim_time: float,
        log_level: str = "INFO",
        scenario: Scenario | None = None,
    ) -> None:
        """`scenario`: starts and tours to fly instead of the world's defaults for
        `n_robots` (its robots are the team)."""
        if n_robots < 1:
            raise ProcessError("--robots must be at least 1")
        z = cfg.zenoh  # (each process would listen there: the second had died, "in use")
        if z.listen or z.connect or z.config_file:
            raise ConfigError("zenoh.listen / connect / config_file: `collabslam run` gives "
                              "each process its own loopback endpoints; leave them "
                              "unset")  # fmt: skip
        self.cfg = cfg
        self.world_yaml = resolve_world(world)
        self.n_robots = n_robots
        self.out = out
        self.max_sim_time = max_sim_time
        self.scenario = scenario
        self.group = ProcessGroup(out, log_level)
        self.stop = threading.Event()

    def run(self) -> dict[str, Any]:
        t0 = time.monotonic()
        self.out.mkdir(parents=True, exist_ok=True)
        clear_run_outputs(self.out)
        scenario = self.scenario or make_scenario(self.cfg, self.world_yaml, self.n_robots)
        scenario = with_gnss_origin(self.cfg, scenario)
        write_scenario(self.out / "scenario.json", scenario)
        # The base station's crash record (2 ms per batch); a new mission never resumes
        # an old one, so any database left there is deleted first.
        db = self.cfg.basestation.db_path or str(self.out / "basestation.db")
        delete_database(db)
        dump_config(self.cfg, self.out / "config.toml")
        common = [
            "--config",
            str(self.out / "config.toml"),
            "--scenario",
            str(self.out / "scenario.json"),
            "--out",
            str(self.out),
        ]
        base_ep, sim_ep = endpoint(free_port()), endpoint(free_port())
        g = self.group
        try:
            paced = ["--lockstep"] if self.cfg.base_sync_period_s() > 0.0 else []
            base = g.spawn(
                "basestation", ["basestation", *common, "--listen", base_ep, "--db", db, *paced]
            )
            sim = g.spawn(
                "sim",
                [
                    "sim",
                    *common,
                    "--listen",
                    sim_ep,
                    "--connect",
                    base_ep,
                    "--max-sim-time",
                    str(self.max_sim_time),
                ],
            )
            agents = [
                g.spawn(
                    r.robot_id,
                    agent_command(
                        common, r.robot_id, sim_ep, base_ep, await_base=self.cfg.exploration.enabled
                    ),
                )  # fmt: skip
                for r in scenario.robots
            ]
            try:
                self._supervise_until(sim, [base, *agents])
            except ProcessError:  # one child died: the others still write their outputs
                self._wind_down([sim, *agents], base)
                with contextlib.suppress(Exception):  # (what the survivors wrote)
                    self._summary(scenario.robot_ids, t0)
                raise
            for a in agents:
                a.proc.send_signal(signal.SIGINT)
            g.wait(agents, self.cfg.agent.drain_timeout_s + 30.0)
            base.proc.send_signal(signal.SIGINT)
            g.wait([base], 300.0)
        finally:
            g.terminate_all()
        summary = self._summary(scenario.robot_ids, t0)
        if summary["lockstep_timeouts"] and self.cfg.sim.clock == "lockstep":
            log.warning("%d lock-step waits were given up (a process slower than its "
                        "timeout: sim.basestation_timeout_s, sim.sync_wait_s): this run "
                        "may not repeat", summary["lockstep_timeouts"])  # fmt: skip
        return summary

    def _summary(self, robot_ids: list[str], t0: float) -> dict[str, Any]:
        """summary.json, from the outputs the processes wrote."""
        from collabslam.summary import build_summary

        wall, contact = time.monotonic() - t0, 2.0 * self.cfg.sim.quadrotor.radius_m
        summary = build_summary(self.out, self.world_yaml, robot_ids, wall, contact)
        (self.out / "summary.json").write_text(json.dumps(summary, indent=1))
        return summary

    def _wind_down(self, others: list[Child], base: Child) -> None:
        """Stop the children still running as a mission's end does (SIGINT: the agents
        drain, the simulator writes its ground truth, then the base station its map): one
        agent's crash had had the others killed and every output of the mission lost."""
        for c in others:
            if c.proc.poll() is None:
                c.proc.send_signal(signal.SIGINT)
        deadline = time.monotonic() + self.cfg.agent.drain_timeout_s + 30.0
        for c in [*others, base]:
            if c is base and base.proc.poll() is None:
                base.proc.send_signal(signal.SIGINT)
                deadline = time.monotonic() + 300.0
            try:
                c.proc.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                pass  # (terminate_all kills it)

    def _supervise_until(self, sim: Child, others: list[Child]) -> None:
        """Wait for the simulator to finish; any other child exiting first is an error."""
        while True:
            if self.stop.is_set():
                log.info("interrupted: stopping the simulator")
                sim.proc.send_signal(signal.SIGINT)
                self.group.wait([sim], 30.0)
                return
            rc = sim.proc.poll()
            if rc is not None:
                if rc != 0:
                    raise ProcessError(self.group.died(sim, rc))
                return
            self.group.check(others)
            time.sleep(0.2)
