"""Liveliness between real Zenoh sessions: the base station sees an agent join and
leave, forgets a lost agent's state and releases its exploration goal."""

from __future__ import annotations

import logging
import time

import numpy as np
import pytest
from process_helpers import poll_until

from basestation.node import BaseStationNode
from collabslam.cli import SIGN_OFF_WAIT_S
from collabslam.supervisor import free_port
from common.bus import Bus
from common.config import Config, ZenohConfig
from protocol import RobotState


def _exploring_with_r0(
    cfg: Config, bus: Bus, endpoint: str, **other_tasks: list[list[float]]
) -> tuple[BaseStationNode, Bus]:
    """An exploring base station on `bus` whose r0 (alive, on its own bus: returned) has
    a path, as have `other_tasks`' robots."""
    node = BaseStationNode(cfg, bus, None)
    node.start()
    assert node.explorer is not None
    node.explorer.restore_task("r0", np.array([[0.0, 0.0], [1.0, 0.0], [3.0, 1.0]]))
    for rid, path in other_tasks.items():
        node.explorer.restore_task(rid, np.array(path))
    agent = Bus(ZenohConfig(connect=[endpoint]), cfg.fleet)
    agent.declare_alive("agent", "r0")
    assert poll_until(lambda: node.links.get("r0", {}).get("joins") == 1)
    return node, agent


@pytest.mark.parametrize("said_where", [False, True])
def test_a_lost_agents_goal_is_released_and_its_way_kept_clear(
    cfg: Config, endpoint: str, said_where: bool, caplog: pytest.LogCaptureFixture
) -> None:
    """A lost agent's goal goes back to the queue. One that said where it was flies on
    along its path: the rest of that path, from where its last state put it, stays out
    of the others' plans (`ExplorationManager.silent`). The loss is a warning."""
    caplog.set_level(logging.INFO)
    cfg.exploration.enabled = True
    cfg.zenoh.listen = [endpoint]
    with Bus(cfg.zenoh, cfg.fleet) as bus:
        node, agent = _exploring_with_r0(cfg, bus, endpoint, r1=[[0.0, 0.0], [-3.0, 1.0]])
        node.step()
        assert "r0" in node.explorer.tasks  # alive: keeps its goal
        if said_where:
            pose = np.array([0.5, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
            node._on_state(RobotState("r0", 1.0, "flying", -1, 0, 0, 0, pose, pose), "")
        agent.close()
        assert poll_until(lambda: node.links["r0"]["losses"] == 1)
        node.step()
        assert "r0" not in node.explorer.tasks and "r1" in node.explorer.tasks
        assert "r0" not in node.states
        if said_where:
            way = [[0.5, 0.0], [1.0, 0.0], [3.0, 1.0]]
            assert np.allclose(node.explorer.silent["r0"], way)
        else:  # never said where it was: nothing held
            assert "r0" not in node.explorer.silent
        assert node.stats()["links"]["r0"] == {"joins": 1, "losses": 1}
        node.drain(1.0)
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any(m.startswith("agent r0 lost (liveliness token gone)") for m in warned), warned


def test_an_agent_that_says_it_stops_is_not_logged_as_lost(
    cfg: Config, endpoint: str, caplog: pytest.LogCaptureFixture
) -> None:
    """An agent stopped cleanly (a mission's end) sends a last state, `stopped`, before
    its token goes: the base station logs a stop at INFO, not a loss (it had warned of
    every drone at the end of every mission), releases its goal and keeps only where it
    hovers clear (it flies no further)."""
    caplog.set_level(logging.INFO)
    cfg.exploration.enabled = True
    cfg.zenoh.listen = [endpoint]
    with Bus(cfg.zenoh, cfg.fleet) as bus:
        node, agent = _exploring_with_r0(cfg, bus, endpoint)
        pose = np.array([0.5, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
        agent.publish(agent.keys.robot("r0", "state"),
                      RobotState("r0", 1.0, "stopped", -1, 0, 0, 0, pose, pose))  # fmt: skip
        time.sleep(SIGN_OFF_WAIT_S)  # then its token goes, as `collabslam agent` does
        agent.close()
        assert poll_until(lambda: node.links["r0"]["losses"] == 1)
        node.step()
        assert "r0" not in node.explorer.tasks and "r0" not in node.states
        node._on_state(RobotState("r0", 1.0, "stopped", -1, 0, 0, 0, pose, pose), "")
        assert "r0" not in node.states  # a stop come after the token went: not taken back
        assert np.allclose(node.explorer.silent["r0"], [[0.5, 0.0]])  # where it hovers
        node.drain(1.0)
    messages = [r.getMessage() for r in caplog.records]
    assert "agent r0 stopped: its goal is released, where it hovers kept clear" in messages
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING], messages


@pytest.mark.e2e
def test_one_link_per_pair_of_processes_after_a_base_station_restart(cfg: Config) -> None:
    """Simulator and agent up, then a (restarted) base station: each pair of processes
    must end with one link. With Zenoh's defaults, gossip told the base station where
    the others listened and it connected to them while they reconnected to it: two
    links per pair (nearly every time for the agent, which listened on every interface),
    and a base station restarted that way lost an agent's traffic in 1 of 8 recovery
    runs. Now only processes that listen accept, and only the others connect."""
    base_ep, sim_ep = (f"tcp/127.0.0.1:{free_port()}" for _ in range(2))
    sim = Bus(ZenohConfig(listen=[sim_ep], connect=[base_ep]), cfg.fleet)
    agent = Bus(ZenohConfig(connect=[sim_ep, base_ep]), cfg.fleet)  # gossip on: default
    buses = [agent, sim]
    try:
        time.sleep(1.0)  # both are retrying the base station's endpoint
        base = Bus(ZenohConfig(listen=[base_ep]), cfg.fleet)
        buses.append(base)
        zid = {bus: str(bus.session.zid()) for bus in buses}

        def peers(bus: Bus) -> list[str]:
            return sorted(str(link.zid) for link in bus.session.info.links())

        def others(bus: Bus) -> list[str]:
            return sorted(z for b, z in zid.items() if b is not bus)

        assert poll_until(lambda: all(set(peers(b)) == set(others(b)) for b in buses), 15.0)
        time.sleep(2.0)  # time for anyone to connect a second time
        for bus in buses:
            assert peers(bus) == others(bus)  # one link to each, no doubles
    finally:
        for bus in buses:
            bus.close()


def test_two_base_stations_on_one_fleet_are_named(
    cfg: Config, endpoint: str, caplog: pytest.LogCaptureFixture
) -> None:
    """Two base stations on one fleet split the agents' keyframes between them; both
    had declared one token, so nobody could tell. Now each base station's token is its
    own, and each one, and every agent, names the other in an error line."""
    from agent.node import AgentNode
    from agent.vehicle import NullVehicle

    other = f"tcp/127.0.0.1:{free_port()}"  # peers do not route: the agent links to both
    with (
        Bus(ZenohConfig(listen=[endpoint]), cfg.fleet) as first,
        Bus(ZenohConfig(listen=[other], connect=[endpoint]), cfg.fleet) as second,
        Bus(ZenohConfig(connect=[endpoint, other]), cfg.fleet) as agent_bus,
    ):
        first.declare_alive("basestation", "base", unique=True)
        agent = AgentNode(cfg, "r0", agent_bus, np.zeros((0, 2)), np.zeros(4), NullVehicle())
        agent.start()  # (lock-step: waits for a base station's token)
        assert poll_until(lambda: len(agent._bases) == 1)
        assert not first.rivals and "base stations are up" not in caplog.text
        second.declare_alive("basestation", "base", unique=True)
        assert poll_until(lambda: len(first.rivals) == len(second.rivals) == 1)
        assert first.rivals.isdisjoint(second.rivals) and first.rivals_up == first.rivals
        assert poll_until(lambda: len(agent._bases) == 2)
        assert "another basestation is up on fleet" in caplog.text
        assert "2 base stations are up" in caplog.text
