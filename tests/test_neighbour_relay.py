"""The base station's answer to each robot's state: where the other robots are."""

from __future__ import annotations

import numpy as np

from agent.node import AgentNode
from agent.vehicle import NullVehicle
from basestation.neighbour_relay import NeighbourRelay
from common.bus import Bus
from common.config import Config, ZenohConfig
from common.geometry import pose4_to_pose7
from protocol import Neighbours, RobotState, decode, encode


def _state(
    rid: str, stamp: float, x: float, y: float, epoch: int = 3, odom: tuple | None = None
) -> RobotState:
    """At (x, y) in map; in odom at `odom` ([x, y, yaw]; default: the same pose)."""
    p = pose4_to_pose7([x, y, 1.0, 0.0])
    o = p if odom is None else pose4_to_pose7([odom[0], odom[1], 1.0, odom[2]])
    return RobotState(rid, stamp, "flying", epoch, 10, 10, 0, o, p)


def test_each_robot_hears_the_others_with_their_velocities() -> None:
    relay = NeighbourRelay()
    first = relay.on_state(_state("r0", 1.0, 0.0, 0.0))
    assert first.robot_id == "r0" and len(first.xy) == 0  # alone so far
    relay.on_state(_state("r1", 1.0, 5.0, 0.0))
    relay.on_state(_state("r1", 1.5, 5.0, 0.5))  # r1 flies +y at 1 m/s
    ans = decode(encode(relay.on_state(_state("r0", 1.6, 0.2, 0.0))))  # what goes out
    np.testing.assert_allclose(ans.xy, [[5.0, 0.5]])
    np.testing.assert_allclose(ans.velocity, [[0.0, 1.0]])
    np.testing.assert_allclose(ans.stamps, [1.5])
    assert ans.robot_id == "r0" and ans.stamp == 1.6
    back = relay.on_state(_state("r1", 1.7, 5.0, 0.7))
    np.testing.assert_allclose(back.xy, [[0.2, 0.0]])
    np.testing.assert_allclose(back.velocity, [[0.2 / 0.6, 0.0]])


def test_velocity_from_odometry_and_old_or_unplaced_robots_left_out() -> None:
    relay = NeighbourRelay(max_age_s=2.0)
    # odom turned 90 deg from map: 0.2 m along odom x in 0.2 s is 1 m/s along map y; the
    # 0.5 m jump in map is a new correction, not motion
    relay.on_state(_state("r1", 1.0, 5.0, 0.0, epoch=3, odom=(0.0, 0.0, -np.pi / 2)))
    relay.on_state(_state("r1", 1.2, 5.5, 0.2, epoch=4, odom=(0.2, 0.0, -np.pi / 2)))
    ans = relay.on_state(_state("r0", 1.2, 0, 0))
    np.testing.assert_allclose(ans.velocity, [[0.0, 1.0]], atol=1e-9)
    np.testing.assert_allclose(ans.xy, [[5.5, 0.2]])
    relay.on_state(_state("r2", 1.2, 9.0, 9.0, epoch=-1))  # not on the map yet
    assert len(relay.on_state(_state("r0", 1.3, 0, 0)).xy) == 1
    assert len(relay.on_state(_state("r0", 3.5, 0, 0)).xy) == 0  # r1's news is 2.3 s old
    relay.on_state(_state("r1", 3.6, 5.0, 0.0, epoch=4))
    relay.on_state(_state("r1", 3.0, 0.0, 0.0, epoch=4))  # late: changes nothing
    np.testing.assert_allclose(relay.on_state(_state("r0", 3.7, 0, 0)).xy, [[5.0, 0.0]])
    relay.forget("r1")  # its liveliness token went away
    assert len(relay.on_state(_state("r0", 3.8, 0, 0)).xy) == 0


def test_two_states_a_hair_apart_give_no_velocity() -> None:
    """1e-12 s apart: 1e18 m/s (an infinite velocity, from poses far out, had every
    answer that held it refused by the agents: they lost every neighbour)."""
    relay = NeighbourRelay()
    relay.on_state(_state("r1", 1.0, 5.0, 0.0))
    relay.on_state(_state("r1", 1.0 + 1e-12, -1e6, 0.0))
    ans = decode(encode(relay.on_state(_state("r0", 1.1, 0.0, 0.0))))
    np.testing.assert_array_equal(ans.velocity, [[0.0, 0.0]])


def test_lockstep_answers_do_not_depend_on_which_state_came_first() -> None:
    """In lock-step every robot reports at the same stamps; the answer to a state of stamp
    t holds the others' latest states before t, whichever of two states of stamp t came
    first, and lists them by robot id."""
    answers = []
    for order in (("r0", "r1", "r2"), ("r2", "r1", "r0")):
        relay = NeighbourRelay(strictly_earlier=True)
        for rid, x in (("r1", 5.0), ("r2", 9.0), ("r0", 0.0)):
            relay.on_state(_state(rid, 1.0, x, 0.0))
        got = {}
        for rid in order:  # the states of t = 1.2, in this order of arrival
            x = {"r0": 0.1, "r1": 5.1, "r2": 9.1}[rid]
            got[rid] = relay.on_state(_state(rid, 1.2, x, 0.0))
        answers.append(got)
    for rid in ("r0", "r1", "r2"):
        a, b = answers[0][rid], answers[1][rid]
        np.testing.assert_array_equal(a.xy, b.xy)
        np.testing.assert_array_equal(a.stamps, [1.0, 1.0])
    np.testing.assert_array_equal(answers[0]["r0"].xy, [[5.0, 0.0], [9.0, 0.0]])
    np.testing.assert_array_equal(answers[1]["r2"].xy, [[0.0, 0.0], [5.0, 0.0]])


def test_a_tick_uses_only_answers_to_states_sent_before_it(cfg: Config, endpoint: str) -> None:
    """The answer to the state a tick has just sent may be in by its command or not (a
    race: lock-step runs of one seed differed): a tick uses answers to earlier states."""
    with Bus(ZenohConfig(listen=[endpoint]), cfg.fleet) as bus:
        node = AgentNode(cfg, "r0", bus, np.zeros((0, 2)), np.zeros(4), NullVehicle())

        def answer(stamp: float, x: float) -> None:
            node._on_neighbours(
                Neighbours("r0", stamp, np.array([stamp - 0.2]), np.array([[x, 0.0]]),
                           np.zeros((1, 2))),
                "",
            )  # fmt: skip

        node.last_state_stamp = 1.0  # the states of t = 0.8 and 1.0 went out
        answer(0.8, 2.0)
        answer(1.0, 3.0)  # the answer to the state of t = 1.0, in before its command
        node._command(1.0)
        np.testing.assert_allclose(node.guard.neighbours, [[2.0, 0.0]], atol=1e-9)
        node._command(1.05)  # the next tick
        np.testing.assert_allclose(node.guard.neighbours, [[3.0, 0.0]], atol=1e-9)


def test_a_state_stamped_far_ahead_once_leaves_no_ghost() -> None:
    """A state stamped 1e9 s (a broken clock) had frozen its robot's track: every later
    state counted as late, and the others were told of it where it once was."""
    relay = NeighbourRelay()
    relay.on_state(_state("r1", 1.0, 5.0, 0.0))
    relay.on_state(_state("r1", 1e9, 9.0, 9.0))  # held back
    relay.on_state(_state("r1", 1.5, 5.0, 0.5))
    ans = relay.on_state(_state("r0", 1.6, 0.0, 0.0))
    np.testing.assert_allclose(ans.xy, [[5.0, 0.5]])
    np.testing.assert_allclose(ans.stamps, [1.5])
