"""Liveliness between real Zenoh sessions: the base station sees an agent join and
leave, forgets a lost agent's state and releases its exploration goal."""

from __future__ import annotations

import numpy as np
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
