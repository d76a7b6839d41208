"""Which robot defines `map` when no start pose is known."""

from __future__ import annotations

import numpy as np
from process_helpers import synthetic_keyframe

from basestation.global_slam import GlobalSlam
from common.config import Config

ZERO = np.zeros(3)


def _first_keyframes(cfg: Config, order: list[str]) -> GlobalSlam:
    slam = GlobalSlam(cfg)
    for rid in order:
        assert slam.admit(synthetic_keyframe(rid, 0, ZERO, ZERO)) == 1
    slam.optimize()
    return slam


def test_the_first_robot_to_send_defines_map_by_default() -> None:
    cfg = Config()
    cfg.basestation.constraints.enabled = False
    slam = _first_keyframes(cfg, ["b", "a"])
    assert slam.graph.is_anchored("b") and not slam.graph.is_anchored("a")


def test_map_frame_robot_defines_map_even_when_it_sends_last() -> None:
    cfg = Config()
    cfg.basestation.constraints.enabled = False
    cfg.basestation.map_frame_robot = "a"
    slam = _first_keyframes(cfg, ["b", "c", "a"])
    assert slam.graph.is_anchored("a")
    assert not slam.graph.is_anchored("b") and not slam.graph.is_anchored("c")
    np.testing.assert_allclose(slam.T_map_odom("a"), 0.0, atol=1e-9)
