"""A new path starts where the drone is, not where its last state said it was.

The base station plans from the drone's last `RobotState`; with a real-time clock the
path arrives 0.2-0.6 s later, when a drone at 1 m/s has flown 0.3-0.8 m past the path's
first waypoint. The follower started at that waypoint: the drone braked, flew back for
it and turned round again (bshape, 3 drones, real time: 13-24 of 44-48 new paths;
mission 46-77 s against 38-39 s with this). The drone is flown by the agent's
`PathFollower` on the simulator's `Quadrotor` in the shipped bshape world."""

from __future__ import annotations

import numpy as np
import pytest

from agent.path_follower import PathFollower
from basestation.path_planner import densify
from common.config import load_config
from simulation.quadrotor import Quadrotor
from simulation.world import World

DT = 1 / 40


@pytest.mark.parametrize("lag_s", [0.0, 0.4, 0.6])
def test_a_path_planned_from_an_old_state_is_taken_up_where_the_drone_is(lag_s: float) -> None:
    cfg, world = load_config(), World.load("bshape")
    f = PathFollower.from_config(cfg.agent)
    q = Quadrotor(np.array([2.0, 10.5, 1.0, 0.0]))
    f.set_path(densify(np.array([[2.0, 10.5], [9.0, 10.5]]), 0.25))
    seen = []
    for _ in range(80):  # 2 s: up to cruise speed, eastwards
        q.step(np.array(f.command(q.pose)), DT, world)
        seen.append(q.pose.copy())
    then = seen[-1 - int(round(lag_s / DT))][:2]  # where its state said it was
    goal = np.array([7.0, 10.5])
    f.set_path(densify(np.array([then, goal]), 0.25), here=q.pose[:2])
    t, back = 0.0, 0.0
    while np.hypot(*(q.pose[:2] - goal)) > 0.2 and t < 20.0:
        x0 = q.pose[0]
        q.step(np.array(f.command(q.pose)), DT, world)
        back, t = back + max(0.0, x0 - q.pose[0]), t + DT
    assert back < 0.01 and t < 4.0  # on at cruise speed (9.2-9.5 s, 1.1-1.3 m back before)
    assert q.collisions == 0


@pytest.mark.parametrize("shift_m", [-2.0, -1.0, 1.0])
def test_a_correction_moving_the_path_along_its_way_does_not_turn_the_drone_back(
    shift_m: float,
) -> None:
    """A correction re-places the path in odom: moved 1-2 m back along its way, the
    waypoint the drone flew to was suddenly behind it, and it stopped, turned 160-174
    degrees and flew back 0.7-1.7 m (losing ~6 m in 6 s). It goes on from the waypoint
    nearest it ahead; moved forward, it keeps the one it had."""
    path = densify(np.array([[0.0, 0.0], [20.0, 0.0]]), 0.25)
    f = PathFollower.from_config(load_config().agent)
    f.set_path(path)
    f.index = 20  # flying to x = 5.0, at x = 4.9
    here = np.array([4.9, 0.0])
    f.set_path(path + [shift_m, 0.0], keep_progress=True, here=here)
    ahead = f.waypoints[f.index][0] - here[0]
    assert f.index >= 20 and -0.25 <= ahead <= 0.25 + max(shift_m, 0.0)


def test_a_path_planned_seconds_ago_is_caught_up_on_all_the_way_to_the_drone() -> None:
    """A live exploration step of 2-5 s (4 drones on a loaded laptop): the path starts
    where the drone was then, 2-5 m behind it; a catch-up of 1.5 m had the drone fly
    back 1.2-3.8 m for it."""
    f = PathFollower.from_config(load_config().agent)
    f.set_path(densify(np.array([[0.0, 0.0], [20.0, 0.0]]), 0.25), here=np.array([4.0, 0.1]))
    assert f.waypoints[f.index][0] == pytest.approx(4.0)
