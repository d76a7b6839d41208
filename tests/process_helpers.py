"""Helpers for the base-station tests: synthetic keyframes, and real base-station
processes with a SQLite record."""

from __future__ import annotations

import signal
import sqlite3
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from collabslam.supervisor import Child, ProcessGroup
from common.geometry import pose4_to_pose7
from protocol import Keyframe, Scan2D


def synthetic_keyframe(
    robot: str, seq: int, pose: np.ndarray, delta: np.ndarray, beams: int = 91,
    fov: float = np.pi, base_range: float = 2.0, ripple: float = 0.1, phase: float = 1.0,
) -> Keyframe:  # fmt: skip
    """A keyframe at `pose` [x, y, yaw] (odom, 1 m up) after `delta`, 0.5 s per seq,
    whose scan (`beams` over `fov` rad) is base_range + ripple * sin(3 a + phase * seq)."""
    angles = np.linspace(-0.5 * fov, 0.5 * fov, beams)
    ranges = base_range + ripple * np.sin(3 * angles + phase * seq)
    return Keyframe(
        robot,
        seq,
        0.5 * seq,
        pose4_to_pose7([pose[0], pose[1], 1.0, pose[2]]),
        pose4_to_pose7([delta[0], delta[1], 0.0, delta[2]]),
        np.diag([4e-4, 4e-4, 1e-4, 1e-4, 1e-4, 1e-4]),
        Scan2D.from_ranges(angles[0], angles[1] - angles[0], 30.0, ranges),
        None,
    )


def stored_keyframes(db: Path, robot_id: str | None = None) -> int:
    """Keyframes in a base station's database, all or one robot's (read-only; 0 while
    it does not exist)."""
    query, args = "SELECT count(*) FROM keyframes", ()
    if robot_id is not None:
        query, args = query + " WHERE robot_id = ?", (robot_id,)
    try:
        with sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=5) as con:
            return int(con.execute(query, args).fetchone()[0])
    except sqlite3.Error:
        return 0


def poll_until(pred: Callable[[], bool], timeout: float = 20.0) -> bool:
    """Poll `pred` every 50 ms; whether it became true within `timeout` s."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.05)
    return False


def wait_for(
    pred: Callable[[], bool], timeout: float, what: str, group: ProcessGroup, running: list[Child]
) -> None:
    """Poll `pred` until true; fail on timeout or if a running child died."""
    deadline = time.monotonic() + timeout
    while not pred():
        group.check(running)
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.1)


@dataclass
class TourMission:
    """A mission's files written (`tour_mission`), for tests that run its processes."""

    out: Path
    world: Path
    robots: list[str]
    common: list[str]  # --config / --scenario / --out
    base_ep: str
    sim_ep: str

    def agent(self, robot_id: str, *extra: str, state: bool = False) -> list[str]:
        """An agent's command; `state`: with a state folder (`agent.state_dir`, as the
        systemd unit gives it: a restarted agent takes up where it was)."""
        from collabslam.launcher import agent_command

        folder = ["--set", f'agent.state_dir="{self.out / "state" / robot_id}"'] if state else []
        return [*agent_command(self.common, robot_id, self.sim_ep, self.base_ep), *folder, *extra]

    def base(self, db: Path) -> list[str]:
        return ["basestation", *self.common, "--listen", self.base_ep, "--db", str(db)]

    def sim(self) -> list[str]:
        return ["sim", *self.common, "--listen", self.sim_ep, "--connect", self.base_ep]


def tour_mission(
    tmp_path: Path, n_robots: int = 2, world_name: str = "bshape", explore: bool = False
) -> TourMission:
    """Scripted tours (no exploration: the drones fly on while a base station is down),
    or with `explore` an exploring team (lock-step: the base station needs
    `--lockstep`)."""
    from collabslam.launcher import make_scenario
    from collabslam.supervisor import free_port
    from common.bus import endpoint
    from common.config import dump_config, load_config
    from common.scenario import write_scenario
    from simulation.world import resolve_world

    out = tmp_path / "run"
    tours = {"sim.tour_length_m": 400.0, "exploration.enabled": False}
    cfg = load_config(
        overrides={
            "basestation.map_update_period_s": 0.5,
            "basestation.drain_timeout_s": 5.0,  # pending verifications: not needed here
            **({} if explore else tours),
        }
    )
    world = resolve_world(world_name)
    scenario = make_scenario(cfg, world, n_robots)
    write_scenario(out / "scenario.json", scenario)
    dump_config(cfg, out / "config.toml")
    common = ["--config", str(out / "config.toml"), "--scenario", str(out / "scenario.json")]
    common += ["--out", str(out)]
    eps = endpoint(free_port()), endpoint(free_port())
    return TourMission(out, world, scenario.robot_ids, common, *eps)


def end_mission(g: ProcessGroup, sim: Child, agents: list[Child], base: Child) -> None:
    """The simulator stops, then the agents (they drain), then the base station."""
    sim.proc.send_signal(signal.SIGINT)
    g.wait([sim], 30)
    for a in agents:
        a.proc.send_signal(signal.SIGINT)
    g.wait(agents, 60)
    base.proc.send_signal(signal.SIGINT)
    g.wait([base], 120)
