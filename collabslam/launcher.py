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

import json
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from common.bus import endpoint
from common.config import Config, dump_config
from common.errors import ProcessError
from common.scenario import RobotScenario, Scenario, write_scenario
from simulation.tours import plan_tours, start_poses
from simulation.world import World, resolve_world

log = logging.getLogger(__name__)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class Child:
    name: str
    proc: subprocess.Popen[bytes]
    log_file: IO[bytes]


def make_scenario(cfg: Config, world_yaml: Path, n_robots: int) -> Scenario:
    world = World.load(str(world_yaml))
    starts = start_poses(world, n_robots, seed=cfg.sim.seed, spacing=cfg.sim.start_spacing_m)
    tours = plan_tours(world, starts, seed=cfg.sim.seed, length_m=cfg.sim.tour_length_m)
    robots = [RobotScenario(f"r{i}", starts[i], tours[i]) for i in range(n_robots)]
    return Scenario(str(world_yaml.resolve()), robots, cfg.sim.seed)


class Launcher:
    def __init__(
        self,
        cfg: Config,
        world: str,
        n_robots: int,
        out: Path,
        max_sim_time: float,
        log_level: str = "INFO",
    ) -> None:
        if n_robots < 1:
            raise ProcessError("--robots must be at least 1")
        self.cfg = cfg
        self.world_yaml = resolve_world(world)
        self.n_robots = n_robots
        self.out = out
        self.max_sim_time = max_sim_time
        self.log_level = log_level
        self.children: list[Child] = []
        self.stop = threading.Event()

    def _spawn(self, name: str, args: list[str]) -> Child:
        logs = self.out / "logs"
        logs.mkdir(parents=True, exist_ok=True)
        f = open(logs / f"{name}.log", "wb")  # noqa: SIM115 - closed in _close_logs
        cmd = [sys.executable, "-m", "collabslam.cli", "--log-level", self.log_level, *args]
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        proc = subprocess.Popen(
            cmd,
            stdout=f,
            stderr=subprocess.STDOUT,
            env=env,
            stdin=subprocess.DEVNULL,
            start_new_session=True,
        )
        child = Child(name, proc, f)
        self.children.append(child)
        log.info("started %s (pid %d)", name, proc.pid)
        return child

    def run(self) -> dict[str, Any]:
        t0 = time.monotonic()
        self.out.mkdir(parents=True, exist_ok=True)
        scenario = make_scenario(self.cfg, self.world_yaml, self.n_robots)
        write_scenario(self.out / "scenario.json", scenario)
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
        try:
            base = self._spawn("basestation", ["basestation", *common, "--listen", base_ep])
            sim = self._spawn(
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
                self._spawn(
                    r.robot_id,
                    [
                        "agent",
                        *common,
                        "--robot-id",
                        r.robot_id,
                        "--connect",
                        sim_ep,
                        "--connect",
                        base_ep,
                    ],
                )
                for r in scenario.robots
            ]
            self._supervise_until(sim, [base, *agents])
            for a in agents:
                a.proc.send_signal(signal.SIGINT)
            self._wait(agents, self.cfg.agent.drain_timeout_s + 30.0)
            base.proc.send_signal(signal.SIGINT)
            self._wait([base], 300.0)
        finally:
            self._terminate_all()
        from collabslam.summary import build_summary

        summary = build_summary(
            self.out, self.world_yaml, scenario.robot_ids, time.monotonic() - t0
        )
        (self.out / "summary.json").write_text(json.dumps(summary, indent=1))
        return summary

    def _supervise_until(self, sim: Child, others: list[Child]) -> None:
        """Wait for the simulator to finish; any other child exiting first is an error."""
        while True:
            if self.stop.is_set():
                log.info("interrupted: stopping the simulator")
                sim.proc.send_signal(signal.SIGINT)
                self._wait([sim], 30.0)
                return
            rc = sim.proc.poll()
            if rc is not None:
                if rc != 0:
                    raise ProcessError(self._died(sim, rc))
                return
            for c in others:
                rc = c.proc.poll()
                if rc is not None:
                    raise ProcessError(self._died(c, rc))
            time.sleep(0.2)

    def _died(self, c: Child, rc: int) -> str:
        return (
            f"{c.name} (pid {c.proc.pid}) exited with code {rc}; "
            f"see {self.out / 'logs' / (c.name + '.log')}"
        )

    def _wait(self, children: list[Child], timeout: float) -> None:
        deadline = time.monotonic() + timeout
        for c in children:
            try:
                rc = c.proc.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                raise ProcessError(f"{c.name} did not stop within {timeout:.0f} s") from None
            if rc != 0:
                raise ProcessError(self._died(c, rc))

    def _terminate_all(self) -> None:
        for c in self.children:
            if c.proc.poll() is None:
                log.warning("killing %s", c.name)
                c.proc.kill()
                c.proc.wait()
            c.log_file.close()
