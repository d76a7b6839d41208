"""Liveliness between real Zenoh sessions: the base station sees an agent join and
leave, forgets a lost agent's state and releases its exploration goal."""

from __future__ import annotations

import time

import numpy as np
from conftest import free_port
from process_helpers import poll_until

from basestation.node import BaseStationNode
from common.bus import Bus
from common.config import Config, ZenohConfig


def test_lost_agent_releases_its_goal(cfg: Config, endpoint: str) -> None:
    cfg.exploration.enabled = True
    cfg.zenoh.listen = [endpoint]
    with Bus(cfg.zenoh, cfg.fleet) as bus:
        node = BaseStationNode(cfg, bus, None)
        node.start()
        assert node.explorer is not None
        node.explorer.restore_task("r0", np.array([[0.0, 0.0], [3.0, 1.0]]))
        node.explorer.restore_task("r1", np.array([[0.0, 0.0], [-3.0, 1.0]]))
        agent = Bus(ZenohConfig(connect=[endpoint]), cfg.fleet)
        agent.declare_alive("agent", "r0")
        assert poll_until(lambda: node.links.get("r0", {}).get("joins") == 1)
        node.step()
        assert "r0" in node.explorer.tasks  # alive: keeps its goal
        agent.close()
        assert poll_until(lambda: node.links["r0"]["losses"] == 1)
        node.step()
        assert "r0" not in node.explorer.tasks and "r1" in node.explorer.tasks
        assert node.stats()["links"]["r0"] == {"joins": 1, "losses": 1}
        node.drain(1.0)


def test_a_peer_without_listen_endpoints_gets_one_link_per_peer(cfg: Config) -> None:
    """An agent-like session (connect only) must not listen: gossip would tell the other
    peers where, they would connect back while it connects to them, and each pair would
    get two links (with Zenoh's default listener it did, every time; a base station
    restarted that way lost an agent's traffic in 1 of 8 recovery runs)."""
    base_ep, sim_ep = (f"tcp/127.0.0.1:{free_port()}" for _ in range(2))
    base = Bus(ZenohConfig(listen=[base_ep]), cfg.fleet)
    agent = Bus(ZenohConfig(connect=[base_ep]), cfg.fleet)  # gossip on, as by default
    sim = Bus(ZenohConfig(listen=[sim_ep], connect=[base_ep]), cfg.fleet)
    try:
        peers = {str(base.session.zid()), str(sim.session.zid())}
        # gossip brings the agent a link to the simulator as well (it connects out)
        assert poll_until(
            lambda: {str(link.zid) for link in agent.session.info.links()} == peers, 10.0
        )
        time.sleep(1.0)  # time for anyone to connect back to it
        zids = [str(link.zid) for link in agent.session.info.links()]
        assert sorted(zids) == sorted(peers), zids  # one link to each, no doubles
    finally:
        for bus in (agent, sim, base):
            bus.close()
